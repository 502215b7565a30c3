"""The map expert as a teacher: its command (explore.expert_label_prob) and its safe-set marks, the
commands that still have a way out (explore.safe_label_prob). Both travel from the actor's batcher
over the wire into replay and survive a save; the large-margin loss teaches the labelled command,
and the safe-set margin loss a marked one, mirrored with the image, whatever command the network
itself took."""

import csv
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from services.actor.batcher import TransitionBatcher
from services.runs import RunPaths
from services.tools.train import train_single_process
from shared.config import (
    ALL_COMMANDS_MASK,
    ConfigError,
    DQNConfig,
    EnvConfig,
    ExploreConfig,
    ModelConfig,
    ReplayConfig,
    SensorConfig,
    commands_mask,
    load_preset,
    mask_commands,
    mirror_action,
)
from shared.expert.expert import CommandExpert, ExpertGuide, SupervisedError
from shared.learning.dqn import DQNAgent, large_margin_loss, set_margin_loss
from shared.learning.learner import LearnerCore
from shared.learning.replay import ReplayError, ReplayMemory
from shared.sim.env import ExploreEnv
from shared.wire.messages import NO_EXPERT_LABEL, MessageError, TransitionBatch

TINY = SensorConfig(width=40, height=30)
SMALL = ModelConfig(fc1=32, fc2=16, dropout=0.0, previous_action=True)


def _stripe(column: int, depth_mm: int = 700) -> np.ndarray:
    """A 30 x 40 image: a near stripe six pixels wide at ``column`` in front of a far wall."""
    frame = np.full((30, 40), 3000, np.uint16)
    frame[:, column:column + 6] = depth_mm
    return frame


def test_labels_travel_from_the_batcher_over_the_wire_into_replay_and_survive_a_save(one_torch_thread):
    cfg = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30,
                                               "train.warmup_transitions": 4})
    batcher = TransitionBatcher("a0", batch_steps=4)
    batcher.begin_episode(_stripe(0) / 1000.0, start_index=0)
    labels = [3, None, 0, 4, None, None]
    batches = []
    for t, label in enumerate(labels):
        batch = batcher.add(2, cfg.env.reward_move, _stripe(t + 1) / 1000.0, False, t == len(labels) - 1, 0,
                            (0.0, 0.0, 0.0), label)
        if batch is not None:
            batches.append(TransitionBatch.decode(batch.encode()))
    assert [b.steps for b in batches] == [4, 2]
    assert batches[0].expert_action.tolist() == [3, NO_EXPERT_LABEL, 0, 4]
    assert batches[1].expert_action is None  # no label in it: nothing extra on the wire
    assert batches[0].expert_labels().tolist() == [3, -1, 0, 4] and batches[1].expert_labels().tolist() == [-1, -1]

    core = LearnerCore(cfg, device="cpu")
    for b in batches:
        core.ingest(b)
    sample = core.replay.sample(64, 1)
    stored = {int(tid): int(lab) for tid, lab in zip(sample.indices, sample.expert_action)}
    assert stored == {t: (-1 if lab is None else lab) for t, lab in enumerate(labels) if t in stored}
    assert len(stored) == len(labels)  # 64 draws with replacement reach all six

    arrays, meta = core.replay.state_dict()
    restored = ReplayMemory(cfg.replay, (30, 40))
    restored.load_state_dict(arrays, meta)
    again = restored.sample(64, 1)
    assert {int(t): int(lab) for t, lab in zip(again.indices, again.expert_action)} == stored
    # a memory saved before labels existed reads "no label" everywhere
    older = ReplayMemory(cfg.replay, (30, 40))
    older.load_state_dict({k: v for k, v in arrays.items() if k != "expert_action"}, meta)
    assert (older.sample(32, 1).expert_action == -1).all()
    # a damaged file's label, used as an index, would crash an update: refused on loading
    damaged = dict(arrays, expert_action=np.where(arrays["expert_action"] == 3, 9, arrays["expert_action"]).astype(np.int8))
    with pytest.raises(ReplayError, match="expert label outside"):
        ReplayMemory(cfg.replay, (30, 40)).load_state_dict(damaged, meta)

    with pytest.raises(ReplayError, match="expert_action"):
        core.replay.add("b", _stripe(1), 2, 1.0, _stripe(2), False, expert_action=5)


def test_expert_labels_teach_their_command_mirrored_with_the_image_not_the_command_taken(one_torch_thread):
    """The network chose at random; the expert names "turn away from the near stripe" (right when it
    is on the left, left when on the right). With mirror augmentation a flipped sample must carry
    the flipped label: else the stripe on the right would be taught both turns."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    replay = ReplayMemory(ReplayConfig(capacity=400), (30, 40), seed=0)
    columns = [c for c in range(0, 35) if abs(c + 3 - 20) >= 4]  # no stripe near the centre
    for episode in range(6):
        for t, column in enumerate(rng.permutation(columns)[:20]):
            label = 4 if column + 3 < 20 else 0
            replay.add(episode, _stripe(int(column)), int(rng.integers(0, 5)), 0.1, _stripe(int(column), 900),
                       False, t == 19, expert_action=label)
    agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=3e-3, n_step=1, mirror_augment=True), device="cpu",
                     seed=0)
    first = agent.update(replay.sample(32, 1))
    assert "label_agreement" in first and "label_margin_loss" in first
    for _ in range(400):
        metrics = agent.update(replay.sample(32, 1))
    assert metrics["label_agreement"] == 1.0
    images = np.stack([_stripe(c) for c in columns])
    wanted = np.array([4 if c + 3 < 20 else 0 for c in columns])
    q = agent.q_values(images, np.full(len(columns), -1))
    assert (q.argmax(axis=1) == wanted).all()
    q_mirrored = agent.q_values(images[:, :, ::-1].copy(), np.full(len(columns), -1))
    assert (q_mirrored.argmax(axis=1) == mirror_action(wanted)).all()


def test_a_commands_mask_round_trips_and_names_bit_a_for_command_a():
    flags = np.array([True, False, False, True, True])
    assert commands_mask(flags) == 0b11001 == 25
    assert mask_commands(25).tolist() == flags.tolist()
    assert mask_commands(np.array([0, ALL_COMMANDS_MASK])).tolist() == [[False] * 5, [True] * 5]


def test_the_set_margin_loss_is_dqfds_with_one_command_and_zero_once_the_best_allowed_leads():
    torch.manual_seed(0)
    q = torch.randn(64, 5)
    label = torch.randint(0, 5, (64,))
    # DQfD's own formula, written out: max_a [Q(a) + margin (a != a_E)] - Q(a_E)
    penalty = torch.full_like(q, 0.8).scatter_(1, label[:, None], 0.0)
    dqfd = ((q + penalty).max(dim=1).values - q.gather(1, label[:, None]).squeeze(1)).mean()
    loss, agreement = large_margin_loss(q, label, 0.8)
    assert torch.allclose(loss, dqfd)
    assert agreement == pytest.approx(float((q.argmax(1) == label).float().mean()))

    q = torch.tensor([[5.0, 4.5, 1.0, 0.0, 0.0], [5.0, 2.0, 9.0, 0.0, 0.0]])
    allowed = torch.tensor([[False, True, True, False, False], [True, False, True, False, False]])
    loss, agreement = set_margin_loss(q, allowed, 1.0)
    # row 0: the best allowed (4.5) trails the best other (5.0): 5.0 + 1 - 4.5 = 1.5; row 1: 9 leads by 4: 0
    assert loss.item() == pytest.approx(0.75) and agreement == 0.5


def test_the_expert_marks_the_commands_with_a_way_out_for_the_drawn_share_of_steps():
    env_cfg = EnvConfig(speed_table="train", reward_trap_penalty=50.0)
    env = ExploreEnv(env_cfg, TINY, world="box-room", max_episode_steps=40)
    env.reset(seed=0)
    expert = CommandExpert(env.world, env.env_config, env.sensor_config)
    always = ExpertGuide(env, 0.0, seed=0, safe_prob=1.0)
    assert ExpertGuide(env, 0.0, seed=0).safe_label((0.0, 0.0, 0.0)) == 0  # marking off
    rng = np.random.default_rng(0)
    xmin, ymin, xmax, ymax = env.world.extent
    lo, hi = np.array([xmin, ymin]) + 0.3, np.array([xmax, ymax]) - 0.3
    poses = [(*rng.uniform(lo, hi), rng.uniform(-np.pi, np.pi)) for _ in range(300)]
    mixed = 0
    for pose in poses:
        safe = expert.safe_commands(*pose, env_cfg.trap_horizon_steps)
        steps, _ = expert.plan_scores(*pose)
        assert safe.tolist() == (steps.max(axis=1) >= env_cfg.trap_horizon_steps).tolist()
        mark = always.safe_label(pose)
        if safe.any() and not safe.all():
            assert mark == commands_mask(safe)
            mixed += 1
        else:
            assert mark == 0  # nothing to tell apart: no mark
    assert mixed >= 10  # poses near the walls tell commands apart
    # the guide asks the env's own expert, whose plans at the pose the trap charge already has
    pose = poses[0]
    first = env.map_expert().plan_scores(*pose)
    assert env.map_expert().plan_scores(*pose) is first and not first[0].flags.writeable
    some = ExpertGuide(env, 0.0, seed=0, safe_prob=0.4)
    asked = [some.safe_label(p) != 0 for p in poses for _ in range(4)]
    share = np.mean(asked) / (mixed / len(poses))
    assert 0.3 < share < 0.5
    with pytest.raises(SupervisedError, match="safe-set label probability"):
        ExpertGuide(env, 0.0, safe_prob=2.0)
    with pytest.raises(ConfigError, match="safe_label_prob"):
        ExploreConfig(safe_label_prob=-0.1)
    with pytest.raises(ConfigError, match="safe_margin"):
        DQNConfig(safe_margin=float("nan"))


def test_marks_travel_from_the_batcher_over_the_wire_into_replay_and_survive_a_save(one_torch_thread):
    cfg = load_preset("smoke").with_overrides({"sensor.width": 40, "sensor.height": 30,
                                               "train.warmup_transitions": 4})
    batcher = TransitionBatcher("a0", batch_steps=4)
    batcher.begin_episode(_stripe(0) / 1000.0, start_index=0)
    marks = [0b11100, 0, 0b00111, 0b00100, 0, 0]
    batches = []
    for t, mark in enumerate(marks):
        batch = batcher.add(2, cfg.env.reward_move, _stripe(t + 1) / 1000.0, False, t == len(marks) - 1, 0,
                            (0.0, 0.0, 0.0), None, mark)
        if batch is not None:
            batches.append(TransitionBatch.decode(batch.encode()))
    assert [b.steps for b in batches] == [4, 2]
    assert batches[0].safe_commands.tolist() == marks[:4]
    assert batches[1].safe_commands is None and batches[0].expert_action is None  # nothing extra on the wire

    core = LearnerCore(cfg, device="cpu")
    for b in batches:
        core.ingest(b)
    sample = core.replay.sample(64, 1)
    stored = {int(tid): int(m) for tid, m in zip(sample.indices, sample.safe_commands)}
    assert stored == dict(enumerate(marks))  # 64 draws with replacement reach all six
    arrays, meta = core.replay.state_dict()
    restored = ReplayMemory(cfg.replay, (30, 40))
    restored.load_state_dict(arrays, meta)
    again = restored.sample(64, 1)
    assert {int(t): int(m) for t, m in zip(again.indices, again.safe_commands)} == stored
    older = ReplayMemory(cfg.replay, (30, 40))  # saved before marks existed: none anywhere
    older.load_state_dict({k: v for k, v in arrays.items() if k != "safe_commands"}, meta)
    assert (older.sample(32, 1).safe_commands == 0).all()
    damaged = dict(arrays, safe_commands=arrays["safe_commands"].astype(np.int64) * 8)
    with pytest.raises(ReplayError, match="safe-set mark outside"):
        ReplayMemory(cfg.replay, (30, 40)).load_state_dict(damaged, meta)

    with pytest.raises(ReplayError, match="safe_commands"):
        core.replay.add("b", _stripe(1), 2, 1.0, _stripe(2), False, safe_commands=32)
    good = batches[0]
    with pytest.raises(MessageError, match="safe_commands"):
        dataclasses.replace(good, safe_commands=np.array([1, 2, 40, 0], np.uint8))
    with pytest.raises(MessageError, match="safe_commands"):
        batcher.begin_episode(_stripe(0) / 1000.0, start_index=0)
        batcher.add(2, 1.0, _stripe(1) / 1000.0, False, True, 0, (0.0, 0.0, 0.0), None, -1)


def test_marks_teach_a_command_with_a_way_out_mirrored_with_the_image(one_torch_thread):
    """The network took commands at random and every one paid the same, so the TD loss alone
    leaves them tied; the marks say "turn away from the near stripe" (only the two turns away have
    a way out). With mirror augmentation a flipped sample must carry the flipped mark, or the stripe
    on the right would be taught both sides."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    replay = ReplayMemory(ReplayConfig(capacity=400), (30, 40), seed=0)
    columns = [c for c in range(0, 35) if abs(c + 3 - 20) >= 4]  # no stripe near the centre
    away_from = {"left": 0b11000, "right": 0b00011}  # stripe on the left: either right turn
    for episode in range(6):
        for t, column in enumerate(rng.permutation(columns)[:20]):
            mark = away_from["left" if column + 3 < 20 else "right"]
            replay.add(episode, _stripe(int(column)), int(rng.integers(0, 5)), 0.1, _stripe(int(column), 900),
                       False, t == 19, safe_commands=mark)
    agent = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", lr=3e-3, n_step=1, mirror_augment=True), device="cpu",
                     seed=0)
    first = agent.update(replay.sample(32, 1))
    assert "safe_agreement" in first and "label_agreement" not in first
    for _ in range(300):
        metrics = agent.update(replay.sample(32, 1))
    assert metrics["safe_agreement"] == 1.0 and metrics["safe_margin_loss"] < first["safe_margin_loss"]
    images = np.stack([_stripe(c) for c in columns])
    on_left = np.array([c + 3 < 20 for c in columns])
    greedy = agent.q_values(images, np.full(len(columns), -1)).argmax(axis=1)
    assert np.where(on_left, greedy >= 3, greedy <= 1).all()
    mirrored = agent.q_values(images[:, :, ::-1].copy(), np.full(len(columns), -1)).argmax(axis=1)
    assert np.where(on_left, mirrored <= 1, mirrored >= 3).all()
    off = DQNAgent(SMALL, TINY, DQNConfig(optimizer="adam", n_step=1, safe_weight=0.0), device="cpu", seed=0)
    assert "safe_agreement" not in off.update(replay.sample(32, 1))  # weight 0: the marks are ignored


@pytest.mark.parametrize("option, column", [("explore.expert_label_prob", "label_agreement"),
                                            ("explore.safe_label_prob", "safe_agreement")])
def test_the_trainer_labels_its_steps_and_model_agreement_measures_models_on_them(tmp_path: Path, capsys, option,
                                                                                   column):
    """The expert's commands (explore.expert_label_prob = 1) or its safe-set marks
    (explore.safe_label_prob = 1) in the single-process trainer: stats/learner.csv reports how often
    the network already agrees (its command is the label; it keeps a way out), and `cogexplore model
    agreement` measures models against what its saved replay memory keeps."""
    from services.cli import main

    torch.manual_seed(0)
    cfg = load_preset("tiny").with_overrides({
        option: 1.0, "train.total_updates": 60, "train.warmup_transitions": 100,
        "train.log_every": 20, "train.checkpoint_every": 1000})
    paths = RunPaths(tmp_path / "taught")
    train_single_process(cfg, paths, progress=False)
    with open(paths.stats / "learner.csv") as f:
        rows = list(csv.DictReader(f))
    agreement = [float(r[column]) for r in rows if r[column]]
    assert len(agreement) == 3 and all(0.0 <= a <= 1.0 for a in agreement)
    other = ({"label_agreement", "safe_agreement"} - {column}).pop()
    assert all(r[other] == "" for r in rows)
    capsys.readouterr()
    assert main(["model", "agreement", str(paths.root), "--model", str(paths.root)]) == 0
    report = json.loads(capsys.readouterr().out)
    replay_size = int(rows[-1]["replay_size"])
    if column == "safe_agreement":
        marks = report["safe_marks"]
        assert "labelled_states" not in report  # no expert labels in this run: only the marks' part
        assert 0 < marks["marked_states"] < replay_size  # open places carry no mark
        assert all(0.0 < v < 1.0 for v in marks["safe_share"].values())
        assert marks["baselines"]["always straight"] == marks["safe_share"]["straight"]
        assert 0.0 <= marks["models"][str(paths.root)] <= 1.0
        return
    assert "safe_marks" not in report
    assert report["labelled_states"] == replay_size > 100  # every stored transition is labelled
    assert sum(report["label_share"].values()) == pytest.approx(1.0)
    always = [v for k, v in report["baselines"].items() if k.startswith("always ")]
    assert always == [pytest.approx(max(report["label_share"].values()))]  # the majority command's share
    model = report["models"][str(paths.root)]
    assert model["frames"] == replay_size and 0.0 <= model["accuracy"] <= 1.0
    assert sum(map(sum, model["confusion_matrix"])) == replay_size
    off = load_preset("tiny").with_overrides({"train.total_updates": 20, "train.warmup_transitions": 100,
                                             "train.log_every": 20, "train.checkpoint_every": 1000})
    train_single_process(off, RunPaths(tmp_path / "plain"), progress=False)
    with open(tmp_path / "plain" / "stats" / "learner.csv") as f:
        assert all(r["label_agreement"] == "" for r in csv.DictReader(f))
    assert main(["model", "agreement", str(tmp_path / "plain")]) == 2
    assert "no stored transition carries an expert label or a safe-set mark" in capsys.readouterr().err
