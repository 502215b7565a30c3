"""Learning is real: the single-process trainer beats the random policy on a small world.

The `tiny` preset (box-room, 40x30 depth image, small fc layers, 3000 updates) trains in a
couple of minutes on 2 cores; the trained greedy policy is then put through the test
protocol next to the random policy, with the same seeds.
"""

import csv
from pathlib import Path

import pytest
import torch

from services.runs import RunPaths
from services.tools.train import train_single_process
from shared.config import load_preset
from shared.evaluation.policies import make_policy
from shared.evaluation.protocol import evaluate_policy
from shared.learning.checkpoints import CheckpointManager, load_model
from shared.learning.stats import EpisodeRow, LearnerRow


@pytest.mark.timeout(900)
def test_tiny_training_beats_random_by_a_clear_margin(tmp_path: Path):
    torch.manual_seed(0)
    cfg = load_preset("tiny").with_overrides({"train.checkpoint_every": 500, "train.keep_checkpoints": 5})
    paths = RunPaths(tmp_path / "tiny")
    # A 3000-update run ends where float summation order takes it: the same seed scored 41.0 on 2
    # threads and 21.8 on 1 (OMP_NUM_THREADS=1), and 22.75 on 2 threads of a CPU without
    # AVX512-BF16 (random 13.25 there). Pinning the count makes the run repeat on one machine, not
    # across CPUs, so the margin below is one every measured machine clears.
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        result = train_single_process(cfg, paths, progress=False)
    finally:
        torch.set_num_threads(threads)
    assert result["updates"] == cfg.train.total_updates
    kept = [p.name for p in CheckpointManager(paths.checkpoints).checkpoints()]
    assert kept == [CheckpointManager(paths.checkpoints).path_for(u).name for u in range(1000, 3001, 500)]

    protocol = dict(world=cfg.env.world, sensor_cfg=cfg.sensor, episodes_per_start=5, max_steps=100,
                    seed=123, progress=False)
    model = load_model(paths.root)
    trained = evaluate_policy(make_policy("greedy", net=model.net), **protocol).summary["overall"]["mean_steps"]
    random = evaluate_policy(make_policy("random", seed=123), **protocol).summary["overall"]["mean_steps"]
    print(f"mean moving steps over 4 starts x 5 episodes (cap 100): trained {trained:.1f}, random {random:.1f}")
    assert trained >= 1.5 * random and trained >= random + 5


def test_trainer_lets_the_expert_drive_the_drawn_episodes(tmp_path: Path):
    """explore.expert_episode_prob: with epsilon 0 the expert's episodes run to the step cap
    collision-free, the untrained network's do not, and episodes.csv says which were which. With
    extra worlds the expert guides in each episode's own world, and episodes.csv names it."""
    torch.manual_seed(0)
    cfg = load_preset("tiny").with_overrides({
        "explore.expert_episode_prob": 0.5, "explore.eps_start": 0.0, "explore.eps_end": 0.0,
        "env.extra_worlds": "corridor", "env.extra_world_prob": 0.5,
        "env.max_episode_steps": 40, "train.total_updates": 20, "train.warmup_transitions": 500,
        "train.checkpoint_every": 1000})
    train_single_process(cfg, RunPaths(tmp_path / "guided"), progress=False)
    with open(tmp_path / "guided" / "stats" / "episodes.csv") as f:
        episodes = list(csv.DictReader(f))
    guided = [e for e in episodes if e["expert_guided"] == "1"]
    plain = [e for e in episodes if e["expert_guided"] == "0"]
    assert guided and plain and len(guided) + len(plain) == len(episodes)
    assert {e["world"] for e in guided} == {"box-room", "corridor"}
    assert all(e["collision_cause"] == "" and e["steps"] == "40" for e in guided)
    assert sum(int(e["steps"]) for e in plain) / len(plain) < 30


def test_train_writes_its_rows_as_tensorboard_scalars_too(tmp_path: Path, tensorboard_scalars):
    """`cogexplore train`: learner.csv and episodes.csv, number for number, in tb/train (TensorBoard's
    reader); --no-tensorboard writes no tb folder."""
    from services.cli import main

    common = ["train", "--preset", "tiny", "--updates", "30", "--runs-dir", str(tmp_path), "--quiet",
              "--set", "train.warmup_transitions=64", "--set", "train.log_every=10"]
    assert main([*common, "--run", "tb"]) == 0
    run = tmp_path / "tb"
    board = tensorboard_scalars(run / "tb" / "train")
    board.assert_steps_increase()
    assert [s for s, _ in board.tags["learner/loss"]] == [10, 20, 30]
    assert board.assert_match_csv(run / "stats" / "learner.csv", LearnerRow) == 3
    assert board.assert_match_csv(run / "stats" / "episodes.csv", EpisodeRow) >= 3
    assert {"episodes/steps", "episodes/return", "episodes/epsilon", "episodes/update"} <= set(board.tags)

    assert main([*common, "--updates", "10", "--run", "off", "--no-tensorboard"]) == 0
    assert (tmp_path / "off" / "stats" / "learner.csv").is_file() and not (tmp_path / "off" / "tb").exists()
