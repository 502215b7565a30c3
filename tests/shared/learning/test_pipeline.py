"""TargetPipeline: each update's TD targets from the weights before the previous update, on a second
thread, with every random draw on the training thread."""

import copy

import numpy as np
import pytest
import torch

from shared.config import DQNConfig, ModelConfig, SensorConfig, load_preset
from shared.learning.dqn import Augmentation, DQNAgent
from shared.learning.learner import LearnerCore
from shared.learning.pipeline import TargetPipeline
from tests.shared.learning.test_dqn import make_batch

TINY = SensorConfig(width=40, height=30)
SMALL = ModelConfig(fc1=32, fc2=16, dropout=0.0)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _agent() -> DQNAgent:
    cfg = DQNConfig(optimizer="adam", lr=1e-3, double_dqn=True, mirror_augment=True,
                    shift_augment_px=2, target_sync_every=2)
    return DQNAgent(SMALL, TINY, cfg, device="cpu", seed=0)


def _submit(pipeline: TargetPipeline, batch, twin: DQNAgent) -> Augmentation | None:
    """Submit ``batch``; the augmentation it drew, drawn again by ``twin`` from the same generator state."""
    state = torch.get_rng_state()
    pipeline.submit(batch)
    after = torch.get_rng_state()
    torch.set_rng_state(state)
    aug = twin.draw_augmentation(batch)
    torch.set_rng_state(after)
    return aug


def test_targets_come_from_the_weights_before_the_previous_update_and_the_first_ones_are_exact():
    agent = _agent()
    b1, b2, b3 = make_batch(seed=1), make_batch(seed=2), make_batch(seed=3)
    pipeline = TargetPipeline(agent)
    try:
        theta0 = copy.deepcopy(agent)
        aug1 = _submit(pipeline, b1, theta0)
        assert aug1 is not None and aug1.flip.any() and not aug1.flip.all() and aug1.obs_shift.any()
        _, p1 = pipeline.take()
        assert torch.equal(p1.y, theta0.prepare(b1, aug1).y)  # nothing to lag behind yet

        snapshot = copy.deepcopy(agent)  # theta_0 still: batch 2's targets are made beside update 1
        aug2 = _submit(pipeline, b2, snapshot)
        agent.apply(p1)  # theta_1
        _, p2 = pipeline.take()
        assert torch.equal(p2.y, snapshot.prepare(b2, aug2).y)
        lagged = dict(pipeline._online.named_parameters())
        assert all(torch.equal(lagged[n], p) for n, p in snapshot.online.named_parameters())
        assert any(not torch.equal(lagged[n], p) for n, p in agent.online.named_parameters())  # theta_1 moved on

        snapshot = copy.deepcopy(agent)  # theta_1, before update 2 syncs theta^-
        aug3 = _submit(pipeline, b3, snapshot)
        assert agent.apply(p2)["synced_target"]  # theta^- written while the worker computes
        _, p3 = pipeline.take()
        assert torch.equal(p3.y, snapshot.prepare(b3, aug3).y)
    finally:
        pipeline.close()


def test_the_workers_theta_minus_follows_each_sync_and_each_loaded_state():
    agent = _agent()  # target_sync_every=2
    pipeline = TargetPipeline(agent)
    try:
        version = agent.target_version
        for update in (1, 2, 3):
            _submit(pipeline, make_batch(seed=update), agent)
            _, prepared = pipeline.take()
            assert agent.apply(prepared)["synced_target"] == (update == 2)
        assert agent.target_version == version + 1  # written once, by update 2's sync
        # the next targets use the synced theta^- (and theta as it is now: nothing trains beside them)
        snapshot = copy.deepcopy(agent)
        aug = _submit(pipeline, make_batch(seed=4), snapshot)
        _, prepared = pipeline.take()
        assert torch.equal(prepared.y, snapshot.prepare(make_batch(seed=4), aug).y)

        other = _agent()  # another run's state, its theta^- synced at other updates
        for seed in (5, 6, 7, 8, 9):
            other.update(make_batch(seed=seed))
        other.sync_target()
        agent.load_state_tensors(*other.state_tensors())
        assert agent.target_version > version + 1
        aug = _submit(pipeline, make_batch(seed=10), other)
        _, prepared = pipeline.take()
        assert torch.equal(prepared.y, other.prepare(make_batch(seed=10), aug).y)
        assert all(torch.equal(mine, theirs) for mine, theirs in
                   zip(pipeline._target.parameters(), other.target.parameters()))
    finally:
        pipeline.close()


def test_the_worker_reads_its_own_copies_never_the_trained_parameters():
    agent = _agent()
    pipeline = TargetPipeline(agent)
    try:
        trained = {p.data_ptr() for net in (agent.online, agent.target) for p in net.parameters()}
        read = {p.data_ptr() for net in (pipeline._online, pipeline._target) for p in net.parameters()}
        assert not trained & read
        assert not any(p.requires_grad for p in pipeline._online.parameters())
    finally:
        pipeline.close()


def test_submit_and_take_must_alternate():
    pipeline = TargetPipeline(_agent())
    try:
        with pytest.raises(RuntimeError, match="nothing was submitted"):
            pipeline.take()
        pipeline.submit(make_batch())
        with pytest.raises(RuntimeError, match="not taken"):
            pipeline.submit(make_batch())
    finally:
        pipeline.close()


def _trained_core(pipeline: bool, updates: int = 12) -> LearnerCore:
    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": 16, "dqn.batch_size": 8,
                                               "replay.capacity": 256, "dqn.mirror_augment": True})
    core = LearnerCore(cfg, device="cpu", pipeline=pipeline)
    rng = np.random.default_rng(0)
    for i in range(64):
        core.add_transition("s", rng.uniform(0.3, 4.0, (30, 40)).astype(np.float32), int(rng.integers(5)),
                            -100.0 if i % 9 == 8 else 1.0, None if i % 9 == 8 else
                            rng.uniform(0.3, 4.0, (30, 40)).astype(np.float32), i % 9 == 8, False)
    for _ in range(updates):
        assert core.train_step() is not None
    return core


def test_a_pipelined_learner_repeats_exactly_and_learns_like_the_plain_one():
    first, second, plain = _trained_core(True), _trained_core(True), _trained_core(False)
    try:
        weights = [dict(c.agent.online.state_dict()) for c in (first, second, plain)]
        assert all(torch.equal(weights[0][n], weights[1][n]) for n in weights[0])  # thread timing changes nothing
        assert any(not torch.equal(weights[0][n], weights[2][n]) for n in weights[0])  # one update's lag shows
        assert first.updates == plain.updates == 12
        loss_pipe, _ = first.recent()
        loss_plain, _ = plain.recent()
        assert np.isfinite(loss_pipe) and loss_pipe < 3 * loss_plain + 1.0
    finally:
        for core in (first, second):
            core.close()


def test_a_closed_core_trains_on_unpipelined():
    core = _trained_core(True, updates=2)
    core.close()
    assert core.train_step() is not None and core.updates == 3
