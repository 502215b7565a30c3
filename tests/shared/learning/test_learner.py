"""LearnerCore without Zenoh: the replay-ratio rule and what it ingests."""

import numpy as np
import pytest
import torch

from shared.config import load_preset
from shared.learning.learner import Diverged, LearnerCore
from shared.learning.replay import ReplayError
from shared.wire.messages import MessageError, TransitionBatch


def _frame(value: float) -> np.ndarray:
    return np.full((30, 40), value, dtype=np.float32)


def test_replay_ratio_rule_and_wanted_transitions():
    cfg = load_preset("smoke").with_overrides({"train.replay_ratio": 0.5, "train.warmup_transitions": 10,
                                               "train.total_updates": 6, "dqn.batch_size": 4})
    core = LearnerCore(cfg, device="cpu")
    assert core.updates_due() == 0
    for i in range(10):
        core.add_transition("s", _frame(1.0), 1, 1.0, _frame(1.0), False, False)
    assert core.updates_due() == 1  # warm-up reached: the first update
    core.train_step()
    assert core.updates_due() == 0
    for i in range(4):
        core.add_transition("s", None, 1, 1.0, _frame(1.0), False, False)
    assert core.updates_due() == 2  # 0.5 updates per transition
    assert core.transitions_wanted(slack=3) == 10 + 2 + 3
    assert core.transitions_wanted(slack=1000) == 10 + 12  # never beyond what total_updates needs


@pytest.mark.parametrize("warmup, ratio, total", [(0, 1.0, 5), (3, 1.0, 2), (0, 4.0, 12)])
def test_credit_reaches_every_update_when_the_warmup_is_under_a_batch(warmup, ratio, total):
    # The actors send what the credit allows and no more (services.actor.service.FlowGate): credit that
    # stopped short of the first batch held them while the learner waited for that batch, for ever.
    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": warmup, "train.replay_ratio": ratio,
                                               "train.total_updates": total, "dqn.batch_size": 8})
    core = LearnerCore(cfg, device="cpu")
    for _ in range(10 * total):
        while core.received < core.transitions_wanted(slack=256):
            core.add_transition("s", _frame(1.0), 1, 1.0, _frame(1.0), False, False)
        for _ in range(core.updates_due()):
            core.train_step()
    assert core.done and core.updates == total
    assert core.transitions_needed >= 8


def test_ingest_rejects_frames_of_another_sensor_and_stores_nothing():
    core = LearnerCore(load_preset("smoke"), device="cpu")
    batch = TransitionBatch.from_steps(actor_id="a", episode=0, first_step=0, start_index=0,
                                       depth=[_frame(1.0)[:20]], next_depth=_frame(1.0)[:20], action=[0],
                                       reward=[1.0], policy_version=[0], pose=[(0, 0, 0)])
    with pytest.raises(MessageError):
        core.ingest(batch)
    assert core.received == 0 and len(core.replay) == 0


def _batch(actor_id: str = "a", reward: float = 1.0, depth_m: float = 1.0, actor_epoch: int = 0, episode: int = 0,
           terminated: bool = False) -> TransitionBatch:
    return TransitionBatch.from_steps(actor_id=actor_id, episode=episode, first_step=0, start_index=0,
                                      depth=[_frame(depth_m)], next_depth=None if terminated else _frame(depth_m),
                                      action=[0], reward=[reward], policy_version=[0], pose=[(0, 0, 0)],
                                      terminated=terminated, actor_epoch=actor_epoch)


@pytest.mark.parametrize("batch,why", [
    (_batch(reward=3.4e38), "reward"),                        # finite, passes the schema, poisons every target
    (_batch(reward=-100.0), "reward"),                        # a collision's reward on a move that did not end
    (_batch(reward=1.0, terminated=True), "reward"),          # a collision paid like a move
    (_batch(depth_m=9.0), "beyond the sensor's range"),       # the smoke sensor sees 4 m
])
def test_ingest_refuses_what_the_task_cannot_produce_and_stores_nothing(batch: TransitionBatch, why: str):
    core = LearnerCore(load_preset("smoke"), device="cpu")
    with pytest.raises(MessageError, match=why) as info:
        core.ingest(TransitionBatch.decode(batch.encode()))
    assert info.value.cause == "range" and core.received == 0 and len(core.replay) == 0 and not core.actors
    core.ingest(_batch(reward=-100.0, terminated=True))  # what the task does pay is stored
    assert core.received == 1


def test_a_novelty_paying_task_accepts_a_moves_bonus_up_to_its_cap_and_nothing_beyond():
    from shared.config import NEW_AREA_CAP_M2

    core = LearnerCore(load_preset("smoke").with_overrides({"env.reward_new_area_per_m2": 2.5}), device="cpu")
    top = 1.0 + 2.5 * NEW_AREA_CAP_M2
    for reward in (1.0, 1.37, top):
        core.ingest(TransitionBatch.decode(_batch(reward=reward).encode()))
    for reward in (top + 0.01, 0.5):
        with pytest.raises(MessageError, match="pays 1 to 11 per move"):
            core.ingest(_batch(reward=reward))
    with pytest.raises(MessageError, match="reward"):  # a collision is still r_ter alone
        core.ingest(_batch(reward=1.37, terminated=True))
    assert core.received == 3


def test_a_trap_charging_task_accepts_the_charged_move_over_the_wire_and_nothing_below_it():
    core = LearnerCore(load_preset("smoke").with_overrides({"env.reward_trap_penalty": 50.0}), device="cpu")
    for reward in (1.0, -49.0):
        core.ingest(TransitionBatch.decode(_batch(reward=reward).encode()))
    for reward in (-49.5, 1.5):
        with pytest.raises(MessageError, match="pays -49 to 1 per move"):
            core.ingest(_batch(reward=reward))
    assert core.received == 2


def test_per_actor_state_stays_bounded_whatever_ids_arrive():
    from shared.learning.learner import MAX_TRACKED_ACTORS
    from shared.learning.replay import MAX_OPEN_STREAMS
    from shared.wire.messages import FlowControl

    core = LearnerCore(load_preset("smoke").with_overrides({"replay.capacity": 10_000}), device="cpu")
    for i in range(4097):  # invented ids, each leaving an episode open
        core.ingest(_batch(actor_id=f"fake-{i}"))
    core.ingest(_batch(actor_id="real"))
    assert len(core.actors) == MAX_TRACKED_ACTORS and "real" in core.actors and "fake-0" not in core.actors
    assert len(core.replay._streams) <= MAX_OPEN_STREAMS
    flow = FlowControl(learner_id="learner", updates=0, transitions_received=core.received, transitions_wanted=0,
                       received_from=core.received_by_actor, actor_epochs=core.actor_epochs())
    assert FlowControl.decode(flow.encode()).received_from["real"] == 1  # the learner's own message still fits


def test_a_restarted_actor_process_starts_a_fresh_count():
    core = LearnerCore(load_preset("smoke"), device="cpu")
    for _ in range(3):
        core.ingest(_batch(actor_epoch=1))
    core.ingest(_batch(actor_epoch=2))
    assert core.received_by_actor == {"a": 1} and core.actor_epochs() == {"a": 2} and core.received == 4


def test_ingest_links_a_batch_to_its_episode_only_as_the_direct_continuation():
    def steps(first_step: int, actions: list[int], episode: int = 0) -> TransitionBatch:
        # every image all zeros: open space beyond the sensor's range, the same at every step
        n = len(actions)
        return TransitionBatch.from_steps(actor_id="a", episode=episode, first_step=first_step, start_index=0,
                                          depth=[_frame(0.0)] * n, next_depth=_frame(0.0), action=actions,
                                          reward=[1.0] * n, policy_version=[0] * n, pose=[(0, 0, 0)] * n,
                                          actor_epoch=7)

    core = LearnerCore(load_preset("smoke"), device="cpu")
    replay = core.replay
    core.ingest(steps(0, [1, 2]))
    core.ingest(steps(2, [3, 4]))  # the batch after: one chain, its first obs the frame already stored
    core.ingest(steps(6, [0, 1]))  # steps 4-5 lost in transit: a new chain, though the images match
    core.ingest(steps(0, [2], episode=1))  # the next episode starts its own
    assert replay._frames_written == 3 + 2 + 3 + 2  # the linked batch alone reuses a frame
    batch = replay._gather(np.arange(7), 3, np.ones(7, np.float32))
    np.testing.assert_array_equal(batch.n_steps, [3, 3, 2, 1, 2, 1, 1])
    np.testing.assert_array_equal(batch.previous_action[:, 0], [-1, 1, 2, 3, -1, 0, -1])

@pytest.mark.parametrize("pipeline", [False, True])
def test_transitions_with_a_non_finite_loss_leave_replay_and_the_learner_goes_on(pipeline: bool):
    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": 8, "dqn.batch_size": 8, "dqn.n_step": 1,
                                               "dqn.loss": "mse", "replay.capacity": 64})
    core = LearnerCore(cfg, device="cpu", pipeline=pipeline)
    with pytest.raises(ReplayError, match="not one this task pays"):
        core.add_transition("s", _frame(1.0), 0, 3.4e38, _frame(1.1), False, False)
    for i in range(32):  # a replay memory saved before the bounds existed: every other reward poisoned
        core.replay.add(("s", i), _frame(1.0 + 0.01 * i), i % 5, 3.4e38 if i % 2 else 1.0, _frame(1.1), False)
        core.received += 1
    before = {name: t.clone() for name, t in core.agent.online.state_dict().items()}
    skipped = sum(core.train_step() is None for _ in range(40))
    assert skipped > 0 and core.dropped_nonfinite > 0 and core.updates == 40 - skipped
    _, rewards = core.replay.stored_rewards()
    assert core.purge_out_of_bounds() == int((rewards > 1e30).sum()) and len(core.replay) == 16
    assert core.train_step() is not None
    assert all(bool(t.isfinite().all()) for t in core.agent.online.state_dict().values())
    assert any(not torch.equal(before[n], t) for n, t in core.agent.online.state_dict().items())
    core.close()


@pytest.mark.parametrize("pipeline", [False, True])
def test_an_update_skipped_for_a_non_finite_loss_is_skipped_once(pipeline: bool):
    # Pipelined, the next batch was drawn before the offending transition left the replay memory: its
    # update was skipped over the same transition again, removing nothing.
    cfg = load_preset("smoke").with_overrides({"dqn.batch_size": 8, "dqn.n_step": 1, "dqn.loss": "mse"})
    core = LearnerCore(cfg, device="cpu", pipeline=pipeline)
    for i in range(3):  # one poisoned of three: nearly every batch of 8 draws it
        core.replay.add(("s", i), _frame(1.0 + 0.1 * i), i, 3.4e38 if i == 1 else 1.0, _frame(1.2), False)
    skipped = sum(core.train_step() is None for _ in range(10))
    assert (skipped, core.dropped_nonfinite, core.updates) == (1, 1, 9)
    core.close()
    # Batches of 2 from one good and one poisoned: the batch drawn before the removal could hold the
    # removed transition alone, and the learner stopped, calling its network diverged (DQNError).
    cfg = cfg.with_overrides({"dqn.batch_size": 2, "replay.prioritized": False, "train.seed": 1})
    core = LearnerCore(cfg, device="cpu", pipeline=pipeline)
    for i in range(2):
        core.replay.add(("s", i), _frame(1.0 + 0.1 * i), i, 3.4e38 if i == 1 else 1.0, _frame(1.2), False)
    assert core.train_step() is None and core.train_step() is not None
    core.close()


def diverge_at(monkeypatch: pytest.MonkeyPatch, update: int) -> None:
    """From update ``update`` on, the first command's output bias is infinite, as an update whose arithmetic
    overflowed leaves it (NaN Q-values for a dueling network); the updates themselves are real."""
    from shared.learning.dqn import DQNAgent

    real_apply = DQNAgent.apply

    def apply(agent: DQNAgent, prepared):
        metrics = real_apply(agent, prepared)
        if agent.update_count == update:
            with torch.no_grad():
                list(agent.online.parameters())[-1][0] = float("inf")
        return metrics

    monkeypatch.setattr(DQNAgent, "apply", apply)


@pytest.mark.parametrize("pipeline", [False, True])
def test_weights_gone_infinite_stop_the_learner_and_leave_its_replay_memory_alone(pipeline: bool):
    # One command's Q-value infinite (its bias overflowed): the samples that took it gave an infinite loss,
    # were blamed and removed from the replay memory, update after update, and the rest trained on.
    cfg = load_preset("smoke").with_overrides({"model.dueling": False, "dqn.batch_size": 8, "dqn.n_step": 1,
                                               "train.warmup_transitions": 8, "replay.capacity": 64})
    core = LearnerCore(cfg, device="cpu", pipeline=pipeline)
    for i in range(32):
        core.replay.add(("s", i), _frame(1.0 + 0.01 * i), i % 2, 1.0, _frame(1.1), False)
        core.received += 1
    assert core.train_step() is not None
    core.check_finite()  # finite: nothing to say
    with torch.no_grad():
        core.agent.online.fc3.bias[0] = float("inf")
    said = r"^update 1: weight online.fc3.bias holds NaN or infinite values, the network has diverged"
    with pytest.raises(Diverged, match=said):
        core.check_finite()
    for _ in range(5):
        with pytest.raises(Diverged, match=said):
            core.train_step()
    assert (len(core.replay), core.dropped_nonfinite, core.updates) == (32, 0, 1)
    core.close()


def test_a_resumed_replay_memory_keeps_nothing_the_task_cannot_produce(tmp_path):
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.learner import resume_from

    cfg = load_preset("smoke")
    core = LearnerCore(cfg, device="cpu")
    for i in range(10):
        core.replay.add(("s", i), _frame(1.0), 0, 3.4e38 if i < 3 else 1.0, _frame(1.1), False)
    manager = CheckpointManager(tmp_path)
    manager.save(core.agent, replay=core.replay, config=cfg.to_dict())
    resumed = LearnerCore(cfg, device="cpu")
    assert resume_from(CheckpointManager(tmp_path), resumed)
    _, rewards = resumed.replay.stored_rewards()
    assert len(resumed.replay) == 7 and set(rewards.tolist()) == {1.0}


def test_a_resume_whose_replay_memory_was_lost_warms_up_again(tmp_path):
    """A checkpoint without its replay memory (an older one, or a learner run with save_replay off)
    resumes with an empty memory: the next update must wait for a fresh warm-up, not sample its
    whole batch from the first transition in, and the actors must get the credit to fill it."""
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.learner import resume_from

    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": 8, "dqn.batch_size": 4,
                                               "train.replay_ratio": 0.5})
    core = LearnerCore(cfg, device="cpu")
    for i in range(20):
        core.add_transition("s", _frame(1.0 + 0.01 * i), 1, 1.0, _frame(1.01 + 0.01 * i), False, False)
        for _ in range(core.updates_due()):
            core.train_step()
    assert core.updates == 7 and core.updates_due() == 0
    CheckpointManager(tmp_path).save(core.agent, config=cfg.to_dict(), extra=core.checkpoint_extra())
    resumed = LearnerCore(cfg, device="cpu")
    assert resume_from(CheckpointManager(tmp_path), resumed)
    assert resumed.updates == 7 and len(resumed.replay) == 0
    assert resumed.received == 20  # still the run's count (stats, epsilon): the ratio no longer counts 6 of them
    assert resumed.transitions_wanted(slack=0) - resumed.received >= 8  # credit for the warm-up
    due = []
    for i in range(10):
        resumed.add_transition("t", _frame(2.0 + 0.01 * i), 1, 1.0, _frame(2.01 + 0.01 * i), False, False)
        due.append(resumed.updates_due())
    assert due == [0] * 7 + [1, 1, 2]  # the warm-up's 8 transitions, then 0.5 updates per transition again
    assert len(set(resumed._sample().indices.tolist())) > 1
    # a later resume, its memory kept this time, keeps pacing as before it
    for _ in range(resumed.updates_due()):
        resumed.train_step()
    later = tmp_path / "later"
    CheckpointManager(later).save(resumed.agent, config=cfg.to_dict(), extra=resumed.checkpoint_extra(),
                                  replay=resumed.replay)
    again = LearnerCore(cfg, device="cpu")
    assert resume_from(CheckpointManager(later), again)
    assert (again.received, again.unpaced, again.updates_due()) == (30, resumed.unpaced, 0)


@pytest.mark.parametrize("updates_before", [0, 10])
def test_a_resume_without_its_memory_never_draws_a_batch_from_fewer_transitions_than_a_batch(tmp_path,
                                                                                       updates_before):
    """At update 0 (a checkpoint saved during the warm-up) and with a warm-up shorter than a batch,
    the first update after such a resume waited for neither."""
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.learner import resume_from

    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": 2 if updates_before else 8,
                                               "dqn.batch_size": 8 if updates_before else 4,
                                               "train.replay_ratio": 0.5})
    core = LearnerCore(cfg, device="cpu")
    for i in range(20 if updates_before else 7):
        core.add_transition("s", _frame(1.0 + 0.01 * i), 1, 1.0, _frame(1.01 + 0.01 * i), False, False)
        for _ in range(core.updates_due()):
            core.train_step()
    assert core.updates == updates_before
    CheckpointManager(tmp_path).save(core.agent, config=cfg.to_dict(), extra=core.checkpoint_extra())
    resumed = LearnerCore(cfg, device="cpu")
    assert resume_from(CheckpointManager(tmp_path), resumed)
    for i in range(12):
        resumed.add_transition("t", _frame(2.0 + 0.01 * i), 1, 1.0, _frame(2.01 + 0.01 * i), False, False)
        if resumed.updates_due():
            assert len(resumed.replay) >= max(cfg.dqn.batch_size, cfg.train.warmup_transitions), i
            break
    else:
        pytest.fail("no update after twelve new transitions")


def test_a_frame_stack_learner_trains_on_stacks_from_the_replay_chain():
    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": 8, "dqn.batch_size": 8,
                                               "model.frame_stack": 2, "replay.capacity": 64})
    core = LearnerCore(cfg, device="cpu")
    for step in range(12):
        core.add_transition("s", _frame(1.0 + 0.1 * step), step % 5, 1.0, _frame(1.1 + 0.1 * step), False, False)
    batch = core._sample()
    h, w = cfg.sensor.height, cfg.sensor.width
    assert batch.obs.shape == (8, 2, h, w)
    # each stack is this image and the one before it in the episode (the first image repeated at its start)
    before = np.maximum(batch.obs[:, 0, 0, 0].astype(int) - 100, 1000)
    np.testing.assert_array_equal(batch.obs[:, 1, 0, 0], before)
    before_weights = core.agent.online.trunk.conv1.weight.detach().clone()
    assert core.train_step() is not None
    assert not torch.equal(before_weights, core.agent.online.trunk.conv1.weight)
    core.close()


def test_a_run_whose_every_checkpoint_is_damaged_is_not_started_over(tmp_path):
    # resume_from said "nothing to resume" and the learner trained a new network into the folder,
    # pruning the damaged (or diverged, now refused) checkpoints away with its own
    from shared.learning.checkpoints import CheckpointError, CheckpointManager
    from shared.learning.learner import resume_from

    cfg = load_preset("smoke")
    core = LearnerCore(cfg, device="cpu")
    assert not resume_from(CheckpointManager(tmp_path), core)  # an empty folder: a new run
    saved = CheckpointManager(tmp_path).save(core.agent, config=cfg.to_dict(), extra=core.checkpoint_extra())
    saved.write_bytes(saved.read_bytes()[:-64])
    with pytest.raises(CheckpointError, match=r"none of the 1 checkpoint\(s\) .* loads .*move that folder away"):
        resume_from(CheckpointManager(tmp_path), LearnerCore(cfg, device="cpu"))
    assert saved.exists()
