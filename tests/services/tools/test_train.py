"""Learning is real: the single-process trainer beats the random policy on a small world, and its
Q-values have learned what a collision costs.

The `tiny` preset (box-room, small fc layers, 3000 updates) at 20x15 depth pixels trains in
about a minute on 2 cores; the trained greedy policy is then put through the test
protocol next to the random policy, with the same seeds, and its Q-values are read on steps a
random driver took, next to an untrained network's.
"""

import csv
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from services.runs import RunPaths
from services.tools.train import train_single_process
from shared.config import NUM_ACTIONS, load_preset
from shared.evaluation.policies import GreedyPolicy, make_policy
from shared.evaluation.protocol import evaluate_policy
from shared.learning.checkpoints import CheckpointManager, average_models, load_model
from shared.learning.model import QNetwork
from shared.learning.stats import EpisodeRow, LearnerRow
from shared.rollout import Rollout
from shared.sim.env import ExploreEnv


def random_driver_steps(cfg, episodes: int, seed: int) -> list[tuple[np.ndarray, int, bool]]:
    """(depth image, command, whether that command collided) for every step of a uniformly random
    driver's episodes in the config's world."""
    env = ExploreEnv(cfg.env, cfg.sensor)
    rng = np.random.default_rng(seed)
    steps = []
    keep = SimpleNamespace(on_step=lambda step: steps.append((step.obs, step.action, step.terminated)))
    loop = Rollout(env, lambda *_: int(rng.integers(NUM_ACTIONS)), observers=[keep])
    try:
        for episode in range(episodes):
            loop.run_episode(seed=seed + episode)
    finally:
        env.close()
    return steps


def collision_ranking(net, steps) -> float:
    """How often the network values a command that collided below one that did not, over every
    such pair of steps (the area under the ROC curve of -Q as a collision predictor; ties count
    half): 0.5 is chance."""
    policy = GreedyPolicy(net)
    q_taken = np.array([policy(depth_m)[1][action] for depth_m, action, _ in steps])
    collided = np.array([c for *_, c in steps])
    crash, safe = q_taken[collided][:, None], q_taken[~collided][None, :]
    return float((crash < safe).mean() + 0.5 * (crash == safe).mean())


@pytest.mark.timeout(900)
def test_tiny_training_beats_random_and_learns_what_a_collision_costs(tmp_path: Path):
    torch.manual_seed(0)
    # A quarter of tiny's pixels (20 x 15, the same network): an update takes about 40% as long.
    cfg = load_preset("tiny").with_overrides({"train.checkpoint_every": 500, "train.keep_checkpoints": 5,
                                              "sensor.width": 20, "sensor.height": 15})
    paths = RunPaths(tmp_path / "tiny")
    # A 3000-update run ends where float summation order takes it, so the thread count is pinned:
    # the run then repeats on one machine, though not across CPUs.
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        result = train_single_process(cfg, paths, progress=False)
    finally:
        torch.set_num_threads(threads)
    assert result["updates"] == cfg.train.total_updates
    manager = CheckpointManager(paths.checkpoints)
    kept = manager.checkpoints()
    assert [p.name for p in kept] == [manager.path_for(u).name for u in range(1000, 3001, 500)]
    # The model a run ships: the mean of its last four checkpoints' weights (`up --final-average 4`).
    # The last checkpoint alone swings: over seeds 0-3 and 1-2 threads it scored 15.0-53.3 (twice
    # no better than random), the mean of the last four 34.0-98.3.
    model = average_models([load_model(p) for p in kept[-4:]])
    assert model.policy_version == 3000

    protocol = dict(world=cfg.env.world, sensor_cfg=cfg.sensor, episodes_per_start=5, max_steps=100,
                    seed=123, progress=False)
    trained = evaluate_policy(make_policy("greedy", net=model.net), **protocol).summary["overall"]["mean_steps"]
    random = evaluate_policy(make_policy("random", seed=123), **protocol).summary["overall"]["mean_steps"]
    print(f"mean moving steps over 4 starts x 5 episodes (cap 100): trained {trained:.1f}, random {random:.1f}")
    assert trained >= 1.5 * random and trained >= random + 5

    # The greedy score alone does not tell learning from none: an untrained tiny network's constant
    # command drives 28 steps on this protocol. Its Q-values do: a collision's -100 must be in them.
    # On a random driver's steps (40 episodes, about 470 steps, 40 collisions) the trained models
    # ranked the colliding commands below the safe ones 0.87-0.89 of the time, an untrained twin 0.45.
    steps = random_driver_steps(cfg, episodes=40, seed=1000)
    assert 20 <= sum(c for *_, c in steps) < len(steps) / 2
    torch.manual_seed(0)
    untrained = QNetwork(cfg.model, cfg.sensor).eval()
    learned, chance = collision_ranking(model.net, steps), collision_ranking(untrained, steps)
    print(f"colliding commands ranked below safe ones: trained {learned:.3f}, untrained {chance:.3f}")
    assert learned >= 0.75 and chance <= 0.65


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



def test_train_on_an_existing_run_keeps_its_recipe_unless_told_another(tmp_path: Path, capsys):
    """`cogexplore train --run R` on a run that exists trains on with R's config.toml (it used to take
    the paper preset and overwrite R's recipe); a new run's default stays the paper's."""
    from services.cli import build_parser, main
    from services.runs import RunPaths
    from services.tools.train import train_config
    from shared.config import load_preset

    common = ["--runs-dir", str(tmp_path), "--quiet"]
    assert main(["train", "--preset", "tiny", "--updates", "20", "--run", "r", "--set", "train.warmup_transitions=64",
                 *common]) == 0
    run = RunPaths(tmp_path / "r")
    recipe = load_preset(run.config)
    assert main(["train", "--run", "r", "--updates", "30", *common]) == 0
    assert "'updates': 30" in capsys.readouterr().out  # on from update 20, with the run's tiny network
    assert load_preset(run.config) == recipe.with_overrides({"train.total_updates": 30})
    parser = build_parser()
    assert train_config(parser.parse_args(["train", "--run", "new", *common]), RunPaths(tmp_path / "new")) \
        == load_preset("paper")
    told = parser.parse_args(["train", "--run", "r", "--preset", "smoke", *common])
    assert train_config(told, run) == load_preset("smoke")
    # A preset whose network cannot resume the run is refused, and the run's recipe stays: it was
    # written before the resume was tried, so the run could then not resume at all.
    saved = run.config.read_bytes()
    assert main(["train", "--run", "r", "--preset", "smoke", "--updates", "40", *common]) == 2
    assert "cannot resume" in capsys.readouterr().err and run.config.read_bytes() == saved
    assert main(["train", "--run", "r", "--updates", "40", *common]) == 0


def test_a_trainer_restarted_without_a_checkpoint_does_not_log_its_updates_going_back(tmp_path: Path):
    # Killed before its first checkpoint, a run starts again at update 0: its rows were trimmed only
    # after a resume from a checkpoint, so learner.csv and episodes.csv went back to 0 mid-file.
    import shutil

    from services.cli import main
    from services.runs import RunPaths
    from shared.learning.stats import EpisodeRow, LearnerRow, read_csv_records

    common = ["--runs-dir", str(tmp_path), "--quiet", "--run", "r", "--preset", "tiny",
              "--set", "train.warmup_transitions=64", "--set", "train.log_every=5"]
    assert main(["train", "--updates", "30", *common]) == 0
    run = RunPaths(tmp_path / "r")
    assert max(int(r["update"]) for r in read_csv_records(run.stats / LearnerRow.FILE)) > 10
    shutil.rmtree(run.checkpoints)  # as if it had died before writing one
    assert main(["train", "--updates", "10", *common]) == 0
    for row_type in (LearnerRow, EpisodeRow):
        updates = [int(r["update"]) for r in read_csv_records(run.stats / row_type.FILE)]
        assert updates == sorted(updates) and max(updates) <= 10, (row_type.FILE, updates)


def test_the_last_update_s_checkpoint_is_written_once(tmp_path: Path, checkpoint_saves: list[int]):
    # At total_updates the periodic checkpoint and then the final one wrote the same file twice.
    saved = checkpoint_saves
    cfg = load_preset("smoke").with_overrides({"train.total_updates": 10, "train.checkpoint_every": 5})
    paths = RunPaths(tmp_path / "r")
    assert train_single_process(cfg, paths, progress=False, tensorboard=False)["updates"] == 10
    assert saved == [5, 10]
    # an end off the period, and a resume that has nothing left to do, still write their final checkpoint
    for _ in range(2):
        train_single_process(cfg.with_overrides({"train.total_updates": 13}), paths, progress=False, tensorboard=False)
    assert saved == [5, 10, 13, 13]
    assert [p.name for p in CheckpointManager(paths.checkpoints).checkpoints()] == [
        f"ckpt-{u:09d}.safetensors" for u in (5, 10, 13)]  # keep_checkpoints: the newest 3


def test_a_resumed_trainer_marks_each_session_and_the_summary_adds_their_times(tmp_path: Path):
    # A reviewer's three sessions (to updates 25, 30 and 40): the second's one row (0.051 s) came
    # before the third's (0.094 s), the clock did not go back, and the second session's time was lost.
    from shared.learning.stats import read_csv_records, summarize_learner_log

    paths = RunPaths(tmp_path / "r")
    for updates in (10, 12, 16):
        cfg = load_preset("smoke").with_overrides({"train.total_updates": updates, "train.log_every": 5,
                                                   "train.checkpoint_every": 10, "train.warmup_transitions": 8})
        train_single_process(cfg, paths, progress=False, tensorboard=False)
    rows = list(read_csv_records(paths.stats / LearnerRow.FILE))
    session_s = {r["session"]: float(r["time_s"]) for r in rows}  # each session's time at its last row
    assert [int(r["update"]) for r in rows] == [5, 10, 12, 15, 16] and len(session_s) == 3
    assert summarize_learner_log(paths.stats / LearnerRow.FILE).learner_s == pytest.approx(sum(session_s.values()))


def test_a_resumed_trainer_s_episode_log_goes_on_from_its_checkpoint(tmp_path: Path):
    # episodes.csv was cut back by update only: a session's episodes logged after its last checkpoint at
    # that same update (the warm-up's, all at update 0, or at a replay ratio under 1) stayed, and the
    # next session, going on from the checkpoint's env step, logged env_step going back; its episode
    # numbers started at 0 again.
    import shutil

    from shared.learning.stats import read_csv_records

    paths = RunPaths(tmp_path / "r")
    cfg = load_preset("smoke").with_overrides({"train.warmup_transitions": 64, "train.replay_ratio": 0.25,
                                               "train.checkpoint_every": 5, "train.log_every": 5})

    def train(updates: int) -> list[dict]:
        train_single_process(cfg.with_overrides({"train.total_updates": updates}), paths, progress=False,
                             tensorboard=False)
        return list(read_csv_records(paths.stats / EpisodeRow.FILE))

    first = train(6)
    rows = train(12)
    assert len(rows) > len(first)
    for column in ("env_step", "episode"):
        values = [int(r[column]) for r in rows]
        assert values == sorted(values), (column, values)
    assert len({r["episode"] for r in rows}) == len(rows)
    shutil.rmtree(paths.checkpoints)  # as if the run had died before its first checkpoint
    rows = train(3)
    steps = [int(r["env_step"]) for r in rows]
    assert steps == sorted(steps) and [int(r["episode"]) for r in rows] == list(range(len(rows)))


def test_train_s_progress_bar_on_a_non_terminal_is_not_redrawn_every_tenth_of_a_second(tmp_path: Path, capsys):
    # stderr to a file or a pipe (nohup, a CI log): tqdm drew its bar every 0.1 s there, a paper run's
    # log a single line of megabytes of carriage returns.
    from services.cli import main

    assert main(["train", "--preset", "smoke", "--updates", "60", "--runs-dir", str(tmp_path), "--run", "r",
                 "--set", "train.warmup_transitions=32"]) == 0
    err = capsys.readouterr().err
    assert "train: 100%" in err and err.count("\r") <= 3, err.count("\r")


def test_an_update_skipped_for_a_non_finite_loss_is_not_logged_saved_or_counted(tmp_path: Path,
                                                                                checkpoint_saves: list[int]):
    # A skipped update (LearnerCore.train_step None) left the update count where it was, but the trainer
    # went on as if it had run: the bar moved, and the update before it was logged and checkpointed again
    # (update 0 too, before any update had run).
    import io

    from tqdm import tqdm

    from services.tools.train import _Training
    from shared.expert.expert import ExpertGuide
    from shared.learning.divergence import RunDivergences
    from shared.learning.learner import LearnerCore
    from shared.learning.policy import EpsilonGreedyPolicy, EpsilonSchedule
    from shared.learning.stats import CsvLog, TensorBoardLog, read_csv_records

    cfg = load_preset("smoke").with_overrides({
        "train.warmup_transitions": 8, "dqn.batch_size": 8, "dqn.n_step": 1, "dqn.loss": "mse",
        "train.log_every": 1, "train.checkpoint_every": 1, "train.total_updates": 12})
    core = LearnerCore(cfg, device="cpu")
    frame = np.ones((cfg.sensor.height, cfg.sensor.width), np.float32)
    for i in range(16):  # a replay memory saved before the reward bounds existed: every other one poisoned
        core.replay.add(("old", i), frame + 0.01 * i, i % 5, 3.4e38 if i % 2 else 1.0, frame * 1.1, False)
        core.received += 1
    paths = RunPaths(tmp_path / "r")
    paths.make()
    env = ExploreEnv(cfg.env, cfg.sensor)
    guide = ExpertGuide(env, 0.0, seed=0)
    policy = EpsilonGreedyPolicy(core.agent.online, EpsilonSchedule(cfg.explore), seed=1, guide=guide)
    with CsvLog(paths.stats, LearnerRow) as learner_log, CsvLog(paths.stats, EpisodeRow) as episode_log, \
            TensorBoardLog(None) as board, tqdm(total=12, file=io.StringIO()) as bar:
        training = _Training(cfg, core, CheckpointManager(paths.checkpoints, keep=20), RunDivergences(paths.root),
                             guide, learner_log, episode_log, bar, board)
        loop = Rollout(env, policy, [guide, training], env_steps=core.received)
        loop.begin_episode(seed=0)
        while not core.done:
            if loop.step().last:
                loop.begin_episode()
        assert bar.n == core.updates == 12
    env.close()
    assert core.dropped_nonfinite > 0
    assert [int(r["update"]) for r in read_csv_records(paths.stats / LearnerRow.FILE)] == list(range(1, 13))
    assert checkpoint_saves == list(range(1, 12))  # the last one is the final save's


def test_train_refuses_a_device_or_start_file_it_cannot_use_before_it_makes_the_run_folder(tmp_path: Path, capsys):
    # The run folder (stats/, checkpoints/, logs/...) was made first, then LearnerCore refused: a run
    # with no config and nothing in it was left behind.
    from services.cli import main

    common = ["train", "--preset", "smoke", "--updates", "5", "--runs-dir", str(tmp_path), "--run", "r", "--quiet"]
    for bad, said in ((["--device", "cuda:99"], "cuda:99"),
                      (["--set", f"train.init_from={tmp_path / 'none.safetensors'}"], "no such file"),
                      (["--set", f"train.demos={tmp_path / 'none.npz'}", "--set", "dqn.demo_batch=4"], "none.npz")):
        assert main([*common, *bad]) == 2
        err = capsys.readouterr().err
        assert said in err and len(err.strip().splitlines()) == 1, err
        assert not (tmp_path / "r").exists()


def test_a_run_resumes_after_its_transfer_file_has_gone(tmp_path: Path, capsys):
    # Its checkpoint replaces the transferred weights, yet the trainer (and the distributed learner, and
    # up's start check) read train.init_from again at every start: a moved or deleted file stopped the run.
    from services.cli import main
    from shared.learning.checkpoints import export_weights
    from shared.learning.learner import LearnerCore

    source = export_weights(tmp_path / "w.safetensors", LearnerCore(load_preset("smoke"), device="cpu").agent.online)
    common = ["train", "--preset", "smoke", "--runs-dir", str(tmp_path), "--run", "r", "--quiet",
              "--set", "train.warmup_transitions=32"]
    assert main([*common, "--set", f"train.init_from={source}", "--updates", "5"]) == 0
    source.unlink()
    # the run's own config, as it was saved: no --preset or --set of the transfer
    assert main(["train", "--runs-dir", str(tmp_path), "--run", "r", "--quiet", "--updates", "8"]) == 0, \
        capsys.readouterr().err
    assert CheckpointManager(tmp_path / "r" / "checkpoints").latest().name == "ckpt-000000008.safetensors"
    # a transfer file given anew is checked, on a resumed run as on a new one, before anything is written
    for run in ("r", "r2"):
        assert main(["train", "--runs-dir", str(tmp_path), "--run", run, "--quiet", "--updates", "9", "--preset",
                     "smoke", "--set", f"train.init_from={tmp_path / 'other.safetensors'}"]) == 2
        assert "other.safetensors" in capsys.readouterr().err
    assert not (tmp_path / "r2").exists()
    assert CheckpointManager(tmp_path / "r" / "checkpoints").latest().name == "ckpt-000000008.safetensors"


@pytest.mark.parametrize("diverged_at", [4, 3], ids=["at-a-checkpoint", "between-checkpoints"])
def test_diverged_weights_stop_the_trainer_in_one_line_and_its_good_checkpoint_stays(tmp_path: Path, monkeypatch,
                                                                                     capsys, diverged_at: int):
    # Weights gone NaN at a checkpoint's update were saved like any other, and with one checkpoint kept the
    # run's good one pruned: nothing of it loaded, and the trainer stopped at the next update on a DQNError
    # that named no checkpoint to resume from.
    from services.cli import main
    from tests.shared.learning.test_learner import diverge_at

    diverge_at(monkeypatch, diverged_at)
    code = main(["train", "--preset", "smoke", "--updates", "10", "--runs-dir", str(tmp_path), "--run", "r", "--quiet",
                 "--set", "train.warmup_transitions=32", "--set", "train.checkpoint_every=2",
                 "--set", "train.keep_checkpoints=1"])
    err = capsys.readouterr().err
    checkpoints = CheckpointManager(tmp_path / "r" / "checkpoints")
    good = checkpoints.path_for(2)
    # at a checkpoint the weights are checked at its save; between, at the next update (a loss that is NaN)
    said = [line for line in err.splitlines() if "diverged" in line]
    assert code == 2 and "Traceback" not in err and said == [
        f"cogexplore train: error: update {diverged_at}: weight online.advantage.bias holds NaN or infinite values, "
        "the network has diverged (the learning rate is probably too high); stopped without saving its weights: "
        f"the run resumes from its last good checkpoint {good} (update 2); its next start resumes at "
        f"dqn.lr={load_preset('smoke').dqn.lr / 2:g} (diverged.json)"], err
    assert checkpoints.checkpoints() == [good] and checkpoints.load_latest().update_count == 2


def test_a_run_that_diverges_resumes_at_half_the_rate_and_a_streak_of_them_stops(tmp_path: Path, monkeypatch, capsys):
    # A run restarted on failure (compose's restart: on-failure) resumed from its last good checkpoint at the
    # rate it had diverged at, and would diverge there again, for ever. The preset named at every start
    # (compose's COGEXPLORE_PRESET, `train --preset`) must not bring its own rate back.
    from services.cli import main
    from services.runs import saved_config
    from tests.shared.learning.test_learner import diverge_at

    paths = RunPaths(tmp_path / "r")
    args = ["train", "--runs-dir", str(tmp_path), "--run", "r", "--quiet", "--updates", "6", "--preset", "smoke",
            "--set", "train.warmup_transitions=32", "--set", "train.checkpoint_every=2"]
    rate = load_preset("smoke").dqn.lr
    for n in range(1, 5):  # diverges at update 3 from its checkpoint at 2, four times
        with monkeypatch.context() as patch:
            diverge_at(patch, 3)
            assert main(args) == 2
        err = capsys.readouterr().err
        if n > 1:
            assert f"divergence {n - 1} in a row" in err and saved_config(paths).dqn.lr == pytest.approx(rate)
        rate /= 2
        said = err.strip().splitlines()[-1]
        assert (f"its next start resumes at dqn.lr={rate:g}" in said) == (n < 4), said
    assert "diverged 4 times in a row, it is not resumed again without --set dqn.lr=<rate>" in said
    assert main(args) == 2 and "not resumed again" in capsys.readouterr().err
    assert CheckpointManager(paths.checkpoints).load_latest().update_count == 2
    # the user's rate resumes it, even the one it last diverged at; past update 3 the streak is over
    assert main(args + ["--set", f"dqn.lr={rate * 2!r}"]) == 0
    assert f"at the rate given, dqn.lr={rate * 2:g}" in capsys.readouterr().err
    assert not (paths.root / "diverged.json").exists() and saved_config(paths).dqn.lr == rate * 2
    assert CheckpointManager(paths.checkpoints).load_latest().update_count == 6
