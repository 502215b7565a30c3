"""The map expert as a teacher (explore.expert_label_prob): its labels travel from the actor's
batcher over the wire into replay, survive a save, and the large-margin loss teaches the labelled
command, mirrored with the image, in transitions where the network itself chose another."""

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from services.actor.batcher import TransitionBatcher
from services.runs import RunPaths
from services.tools.train import train_single_process
from shared.config import DQNConfig, ModelConfig, ReplayConfig, SensorConfig, load_preset, mirror_action
from shared.learning.dqn import DQNAgent
from shared.learning.learner import LearnerCore
from shared.learning.replay import ReplayError, ReplayMemory
from shared.wire.messages import NO_EXPERT_LABEL, TransitionBatch

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


def test_the_trainer_labels_its_steps_with_the_experts_commands(tmp_path: Path, capsys):
    """explore.expert_label_prob = 1 in the single-process trainer: every stored transition carries the
    expert's command, stats/learner.csv reports how often the network already agrees, and `cogexplore
    model agreement` measures models against the labels its saved replay memory keeps."""
    from services.cli import main

    torch.manual_seed(0)
    cfg = load_preset("tiny").with_overrides({
        "explore.expert_label_prob": 1.0, "train.total_updates": 60, "train.warmup_transitions": 100,
        "train.log_every": 20, "train.checkpoint_every": 1000})
    paths = RunPaths(tmp_path / "taught")
    train_single_process(cfg, paths, progress=False)
    with open(paths.stats / "learner.csv") as f:
        rows = list(csv.DictReader(f))
    agreement = [float(r["label_agreement"]) for r in rows if r["label_agreement"]]
    assert len(agreement) == 3 and all(0.0 <= a <= 1.0 for a in agreement)
    capsys.readouterr()
    assert main(["model", "agreement", str(paths.root), "--model", str(paths.root)]) == 0
    report = json.loads(capsys.readouterr().out)
    replay_size = int(rows[-1]["replay_size"])
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
    assert "no stored transition carries an expert label" in capsys.readouterr().err
