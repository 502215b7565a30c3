"""``cogexplore evaluate`` and its parts: the protocol through ``evaluate_policy``, the results
JSON, checkpoints of every kind, the baselines and the recorded .rrd (real env, real files)."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader
from rrd_checks import recorded_protocol

from services.cli import main
from services.viz.rerun import evaluate_recorded
from shared.config import SensorConfig, load_preset
from shared.evaluation import PROTOCOLS
from shared.evaluation.policies import (
    PolicyError,
    RandomPolicy,
    ReactivePolicy,
    make_policy,
)
from shared.evaluation.protocol import EvaluationCancelled, evaluate_policy, file_world_sha256, world_sha256
from shared.evaluation.results import SCHEMA_ID, validate_results_json
from shared.learning.checkpoints import CheckpointError, load_model, weights_sha256
from shared.sim.sensor import intrinsics
from shared.sim.world import load_world
from tests.shared.evaluation.test_eval_log import write_room
from tests.shared.sim.test_world import write_asset_world, write_stl

RERUN_CLI = Path(sys.executable).with_name("rerun")
SMALL = {"sensor.width": 64, "sensor.height": 48, "model.fc1": 32, "model.fc2": 16, "env.world": "box-room"}


def small_config():
    return load_preset("paper").with_overrides(SMALL)


def make_run(root: Path, policy_version: int = 1000, seed: int = 0) -> Path:
    """A run folder with one checkpoint of a fresh network and a weights export next to it."""
    from shared.learning.checkpoints import CheckpointManager, export_weights
    from shared.learning.dqn import DQNAgent

    cfg = small_config()
    agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=seed)
    agent.update_count = agent.policy_version = policy_version
    CheckpointManager(root / "checkpoints").save(agent, config=cfg.to_dict())
    export_weights(root / "weights.safetensors", agent.online, policy_version)
    return root


def evaluate(argv: list[str]) -> int:
    """``cogexplore evaluate ARGV``: the exit status."""
    return main(["evaluate", *argv])


def verify_rrd(path: Path) -> None:
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    proc = subprocess.run([str(RERUN_CLI), "rrd", "verify", str(path)], capture_output=True, text=True,
                          env=env, timeout=60)
    assert proc.returncode == 0, proc.stderr + proc.stdout


def entities(path: Path) -> dict[str, int]:
    """Temporal rows per entity path of a recording."""
    counts: dict[str, int] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        if not chunk.is_static:
            name = chunk.entity_path.lstrip("/")
            counts[name] = counts.get(name, 0) + chunk.to_record_batch().num_rows
    return counts


# -- the world's digest -------------------------------------------------------------------------


def test_a_worlds_digest_is_what_it_had_before_files_counted_when_it_names_none(tmp_path: Path) -> None:
    # eval.jsonl rows, model-select caches and report results keyed by these digests still stand
    assert world_sha256(load_world("paper-indoor")) == \
        "549d060f9f9624f70e20a61012a9aee90544cb542cc4238851cd06e16c6859b1"
    room = load_world(str(write_room(tmp_path / "room.xml")))
    before = {"mjcf": room.mjcf, "starts": [dataclasses.asdict(s) for s in room.starts], "extent": list(room.extent)}
    assert room.asset_sha256 == () and world_sha256(room) == hashlib.sha256(
        json.dumps(before, sort_keys=True).encode()).hexdigest()


def test_a_world_files_digest_changes_with_the_mesh_it_names(tmp_path: Path) -> None:
    # A replaced mesh beside an unchanged MJCF file was scored with the old mesh's results.
    path = write_asset_world(tmp_path / "a")
    first, played = file_world_sha256(str(path)), load_world(str(path))
    write_stl(tmp_path / "a" / "meshes" / "obstacle.stl", 0.5)
    edited = load_world(str(path))
    assert edited.mjcf == played.mjcf and file_world_sha256(str(path)) == world_sha256(edited) != first
    write_stl(tmp_path / "a" / "meshes" / "obstacle.stl", 0.3)
    assert file_world_sha256(str(path)) == first


def test_the_same_world_in_another_folder_differs_only_by_its_mjcf_text(tmp_path: Path) -> None:
    # The files count by content under the name the MJCF gives them; the played MJCF text holds the
    # absolute meshdir and texturedir (a scene compiled from text finds its files by them), so a copy
    # elsewhere has another digest, and the same one once that text is the same.
    a, b = (load_world(str(write_asset_world(tmp_path / d))) for d in ("a", "b"))
    assert a.asset_sha256 == b.asset_sha256 and a.mjcf != b.mjcf
    assert a.mjcf.replace(str(tmp_path / "a"), str(tmp_path / "b")) == b.mjcf
    assert world_sha256(a) != world_sha256(b) == world_sha256(dataclasses.replace(a, name=b.name, mjcf=b.mjcf))


# -- the protocol -----------------------------------------------------------------------------


def test_protocol_runs_every_start_times_episodes_within_the_cap() -> None:
    sensor = SensorConfig(width=64, height=48)
    results = evaluate_policy(ReactivePolicy(sensor), world="box-room", sensor_cfg=sensor, episodes_per_start=2,
                              max_steps=5, progress=False)
    assert [(e.start_index, e.episode) for e in results.episodes] == [(s, k) for s in range(4) for k in range(2)]
    assert all(1 <= e.steps <= 5 for e in results.episodes)
    assert all(e.truncated == (e.steps == 5 and not e.terminated) for e in results.episodes)
    assert results.meta["speed_table"] == "test" and results.meta["env"]["speed_table"] == "test"
    assert results.meta["env"]["max_episode_steps"] == 5 and results.meta["sensor"]["width"] == 64
    # Turning on the spot never collides in box-room's open middle: every episode hits the cap.
    circling = evaluate_policy(lambda d: (0, None), world="box-room", sensor_cfg=sensor, starts=[2],
                               episodes_per_start=3, max_steps=5, progress=False)
    assert [e.steps for e in circling.episodes] == [5, 5, 5]
    assert all(e.truncated and not e.terminated for e in circling.episodes)


def test_the_conditions_played_win_over_a_callers_meta() -> None:
    # a caller's meta overwrote them: results that said another world, protocol or sensor than
    # they were played under, and that report and selection would reuse as such
    sensor = SensorConfig(width=40, height=30)
    claimed = {"world": "paper-indoor", "world_sha256": "0" * 64, "protocol": {"name": "robust"},
               "sensor": {"width": 80}, "env": {}, "max_steps": 200, "seed": 7, "model": "mine"}
    results = evaluate_policy(lambda d: (0, None), world="box-room", sensor_cfg=sensor, starts=[2], max_steps=3,
                              episodes_per_start=1, progress=False, meta=claimed)
    plain = evaluate_policy(lambda d: (0, None), world="box-room", sensor_cfg=sensor, starts=[2], max_steps=3,
                            episodes_per_start=1, progress=False)
    assert results.meta["model"] == "mine"  # what the caller alone knows is kept
    assert {k: results.meta[k] for k in claimed if k != "model"} == {k: plain.meta[k] for k in claimed if k != "model"}
    assert results.meta["world"] == "box-room" and results.meta["protocol"]["name"] == "paper"


def test_training_worlds_the_protocol_never_plays_are_not_loaded(tmp_path: Path) -> None:
    # A run trained beside a world file that was moved since could not be tested any more: the
    # protocol's env loaded every extra world at construction, though it plays --world alone.
    from shared.config import EnvConfig

    moved = tmp_path / "lab.xml"  # trained beside, gone since
    trained = EnvConfig(extra_worlds=str(moved), extra_world_prob=0.5, random_start_prob=0.5)
    sensor = SensorConfig(width=40, height=30)
    results = evaluate_policy(lambda d: (0, None), world="box-room", sensor_cfg=sensor, env_cfg=trained, starts=[2],
                              max_steps=3, episodes_per_start=1, progress=False)
    assert [e.steps for e in results.episodes] == [3]
    assert results.meta["env"]["extra_worlds"] == "" and results.meta["env"]["random_start_prob"] == 0.0


def test_a_greedy_policy_with_previous_commands_starts_each_episode_without_one() -> None:
    import torch

    from shared.config import ModelConfig
    from shared.evaluation.policies import GreedyPolicy
    from shared.learning.model import QNetwork

    sensor = SensorConfig(width=40, height=30)
    torch.manual_seed(0)
    policy = GreedyPolicy(QNetwork(ModelConfig(fc1=16, fc2=8, previous_action=True, action_history=3),
                                        sensor))
    seen: list[int | None] = []  # the previous command of each call
    chosen: list[int] = []
    runner = policy.policy._runner
    q_values = runner.q_values

    def spy(depth, previous_action=None):
        seen.append(previous_action)
        q = q_values(depth, previous_action)
        chosen.append(int(np.argmax(q)))
        return q

    runner.q_values = spy
    # through the cancellable wrapper that evaluate_policy puts around a policy with a stop event
    results = evaluate_policy(policy, world="box-room", sensor_cfg=sensor, starts=[1, 2], episodes_per_start=2,
                              max_steps=4, progress=False, stop=threading.Event())
    firsts = set(np.cumsum([0] + [e.steps for e in results.episodes])[:-1].tolist())
    assert len(firsts) == 4 and all(seen[i] is None for i in firsts)
    # the commands this episode chose, most recent first
    for i in range(len(seen)):
        if i not in firsts:
            start = max(f for f in firsts if f < i)
            assert seen[i].tolist() == [chosen[start:i][::-1]]


def test_random_policy_repeats_under_a_seed() -> None:
    sensor = SensorConfig(width=64, height=48)

    def run(seed: int):
        return evaluate_policy(RandomPolicy(seed), world="box-room", sensor_cfg=sensor, episodes_per_start=2,
                               max_steps=8, seed=seed, progress=False).episodes

    first = run(3)
    assert run(3) == first
    assert run(4) != first


def test_a_random_episode_is_the_same_whatever_ran_before_it() -> None:
    # Its draws once ran on from the episodes before: --starts 2 alone, or the paper protocol after
    # the robust one on the same policy object (cogexplore report), played other episodes.
    sensor = SensorConfig(width=40, height=30)
    kw = {"world": "box-room", "sensor_cfg": sensor, "episodes_per_start": 2, "max_steps": 30, "progress": False}
    full = evaluate_policy(RandomPolicy(0), **kw).episodes
    alone = evaluate_policy(RandomPolicy(0), starts=[2], **kw).episodes
    assert alone == tuple(e for e in full if e.start_index == 2)
    reused = RandomPolicy(0)
    evaluate_policy(reused, protocol=PROTOCOLS["robust"], **kw)
    assert evaluate_policy(reused, **kw).episodes == full


def test_stop_cancels_within_a_step_and_drops_the_partial_recording(tmp_path: Path) -> None:
    sensor = SensorConfig(width=64, height=48)
    stop = threading.Event()
    calls = []

    def policy(depth):
        calls.append(1)
        if len(calls) == 3:
            stop.set()
        return 0, None

    rrd = tmp_path / "partial.rrd"
    with pytest.raises(EvaluationCancelled):
        evaluate_recorded(policy, world="box-room", sensor_cfg=sensor, max_steps=50, rrd=rrd, progress=False,
                          stop=stop)
    assert len(calls) == 3 and not rrd.exists() and list(tmp_path.iterdir()) == []

    # An evaluation of a version already recorded (a restarted learner's first weights) writes
    # beside the earlier file, which stays whole if this one is cancelled and is replaced if it ends.
    earlier = tmp_path / "eval-001000.rrd"
    evaluate_recorded(lambda depth: (0, None), world="box-room", sensor_cfg=sensor, max_steps=5, rrd=earlier,
                      starts=[0], episodes_per_start=1, progress=False)
    whole = earlier.read_bytes()
    calls.clear()
    stop.clear()
    with pytest.raises(EvaluationCancelled):
        evaluate_recorded(policy, world="box-room", sensor_cfg=sensor, max_steps=50, rrd=earlier, progress=False,
                          stop=stop)
    assert earlier.read_bytes() == whole and [f.name for f in tmp_path.iterdir()] == [earlier.name]
    evaluate_recorded(lambda depth: (1, None), world="box-room", sensor_cfg=sensor, max_steps=5, rrd=earlier,
                      starts=[1], episodes_per_start=1, progress=False)
    assert earlier.read_bytes() != whole and [f.name for f in tmp_path.iterdir()] == [earlier.name]


# -- the reactive baseline -----------------------------------------------------------------------


def floor_image(sensor: SensorConfig) -> np.ndarray:
    """What the camera sees on an empty floor: rows below the horizon at h / tan(angle), 0 above."""
    _, fy, _, cy = intrinsics(sensor)
    up = (cy - (np.arange(sensor.height) + 0.5)) / fy
    with np.errstate(divide="ignore"):
        rows = np.where(up < 0, sensor.mount_height_m / -up, 0.0)
    rows = np.where(rows > sensor.max_range_m, 0.0, rows)
    return np.repeat(rows[:, None], sensor.width, axis=1).astype(np.float32)


def test_reactive_policy_reads_free_space_not_the_floor() -> None:
    sensor = SensorConfig()
    policy = ReactivePolicy(sensor)
    floor = floor_image(sensor)
    # An empty floor is all free: straight ahead.
    assert np.isinf(policy.column_depth(floor)).all()
    assert policy(floor)[0] == 2
    # A wall 0.8 m ahead across the left two thirds: turn right.
    blocked_left = floor.copy()
    blocked_left[:, : 2 * sensor.width // 3] = 0.8
    action, scores = policy(blocked_left)
    assert action in (3, 4) and scores.shape == (5,)
    # The mirror image turns left.
    assert policy(blocked_left[:, ::-1].copy())[0] in (0, 1)
    # A post straight ahead blocks the straight command, with free floor on both sides.
    post = floor.copy()
    post[:, 70:90] = 1.0
    assert policy(post)[0] != 2
    # Deterministic: the same image, the same command and scores.
    assert policy(post)[0] == policy(post)[0]
    np.testing.assert_array_equal(policy.scores(post), policy.scores(post))


def test_policy_errors_are_clear() -> None:
    with pytest.raises(PolicyError, match="needs a network"):
        make_policy("greedy")
    with pytest.raises(PolicyError, match="unknown policy"):
        make_policy("sl-model")
    with pytest.raises(PolicyError, match="sensor gives"):
        ReactivePolicy(SensorConfig())(np.zeros((10, 10), np.float32))
    with pytest.raises(PolicyError, match="corridor_m"):
        ReactivePolicy(corridor_m=-1.0)


# -- checkpoints --------------------------------------------------------------------------------


def test_every_kind_of_checkpoint_loads_the_same_network(tmp_path: Path) -> None:
    from shared.learning.checkpoints import CheckpointManager

    run = make_run(tmp_path / "run")
    ckpt_file = CheckpointManager(run / "checkpoints").latest()
    loaded = {src: load_model(src) for src in (run, run / "checkpoints", ckpt_file, run / "weights.safetensors")}
    digests = {m.weights_sha256 for m in loaded.values()}
    assert len(digests) == 1
    for m in loaded.values():
        assert m.policy_version == 1000 and not m.net.training
        assert (m.net.sensor_cfg.width, m.net.sensor_cfg.height) == (64, 48)
    assert loaded[run].kind == "checkpoint" and loaded[run].path == ckpt_file
    assert loaded[run].run_config is not None and loaded[run].run_config.env.world == "box-room"
    assert loaded[run / "weights.safetensors"].kind == "weights"
    assert loaded[run].label == "run@1000"
    # Another network's weights have another digest.
    other = make_run(tmp_path / "other", seed=1)
    assert load_model(other).weights_sha256 != digests.pop()


def test_bad_checkpoints_are_named_in_the_error(tmp_path: Path) -> None:
    with pytest.raises(CheckpointError, match="does not exist"):
        load_model(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(CheckpointError, match="holds no checkpoint"):
        load_model(tmp_path / "empty")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a safetensors file")
    with pytest.raises(CheckpointError, match=r"junk.safetensors is not a readable safetensors file \(partial"):
        load_model(junk)  # said once, not once as "neither" kind of file and again for each kind


# -- the command ----------------------------------------------------------------------------------


def test_evaluate_writes_results_json_and_a_verified_recording(tmp_path: Path, capsys) -> None:
    run = make_run(tmp_path / "run")
    out_json, out_rrd = tmp_path / "out" / "results.json", tmp_path / "out" / "eval.rrd"
    status = evaluate((["--checkpoint", str(run), "--episodes-per-start", "1", "--max-steps", "5",
                                 "--json", str(out_json), "--rrd", str(out_rrd), "--device", "cpu", "--quiet"]))
    assert status == 0
    printed = capsys.readouterr().out
    assert "| Count | run@1000 |" in printed

    doc = json.loads(out_json.read_text())
    assert set(doc) == {"schema", "meta", "episodes", "summary"} and doc["schema"] == SCHEMA_ID
    results = validate_results_json(doc)
    assert len(results.episodes) == 4  # box-room (the checkpoint's world): 4 starts x 1
    meta = doc["meta"]
    assert meta["policy"] == "greedy" and meta["policy_version"] == 1000 and meta["world"] == "box-room"
    assert meta["weights_sha256"] == load_model(run).weights_sha256
    assert meta["episodes_per_start"] == 1 and meta["max_steps"] == 5 and meta["speed_table"] == "test"
    assert meta["protocol"] == PROTOCOLS["robust"].to_dict()  # the default of `cogexplore evaluate`
    assert set(doc["summary"]) == {"overall", "per_start"} and len(doc["summary"]["per_start"]) == 4
    overall = doc["summary"]["overall"]
    for key in ("mean_steps", "mean_distance_m", "mean_path_length_m", "mean_coverage_m2", "mean_coverage_pct",
                "collisions", "reached_cap"):
        assert key in overall
    for e in doc["episodes"]:
        assert len(e["trajectory_xy"]) == e["steps"] + 1 and e["steps"] <= 5

    verify_rrd(out_rrd)
    rows = entities(out_rrd)
    total_steps = sum(e.steps for e in results.episodes)
    assert rows["camera/depth"] == total_steps
    assert rows["policy/q/straight"] == total_steps and rows["policy/action"] == total_steps
    assert rows["world/trajectory/start_1/episode_0"] == results.episodes[0].steps + 1
    assert rows["eval/mean_steps"] == 1  # the summary at the policy version
    assert recorded_protocol(out_rrd) == pytest.approx(PROTOCOLS["robust"].to_dict())


def test_evaluate_baseline_out_of_the_box(tmp_path: Path) -> None:
    out = tmp_path / "random.json"
    status = evaluate((["--policy", "reactive", "--world", "box-room", "--episodes-per-start", "2",
                                 "--max-steps", "5", "--json", str(out), "--set", "sensor.width=64",
                                 "--set", "sensor.height=48", "--quiet"]))
    assert status == 0
    results = validate_results_json(out.read_text())
    assert len(results.episodes) == 8 and results.meta["policy"] == "reactive"
    assert results.meta["sensor"]["width"] == 64


def test_evaluate_starts_are_numbered_from_one_as_in_the_tables(tmp_path: Path) -> None:
    out = tmp_path / "two.json"
    assert evaluate(["--policy", "reactive", "--world", "box-room", "--starts", "2", "4", "--episodes-per-start",
                     "1", "--max-steps", "3", "--json", str(out), "--set", "sensor.width=64",
                     "--set", "sensor.height=48", "--quiet"]) == 0
    results = validate_results_json(out.read_text())
    assert [e.start_index for e in results.episodes] == [1, 3]  # the JSON's start_index is 0-based


def test_evaluate_several_worlds_one_after_the_other(tmp_path: Path, capsys, monkeypatch) -> None:
    run = make_run(tmp_path / "run")
    status = evaluate((["--checkpoint", str(run), "--world", "box-room,corridor", "--episodes-per-start",
                                 "1", "--max-steps", "5", "--json", str(tmp_path / "r.json"), "--device", "cpu",
                                 "--quiet"]))
    assert status == 0
    printed = capsys.readouterr().out
    assert "## box-room" in printed and "## corridor" in printed
    per_world = {}
    for world, starts in (("box-room", 4), ("corridor", len(load_world("corridor").starts))):
        results = validate_results_json((tmp_path / f"r-{world}.json").read_text())
        assert results.meta["world"] == world and len(results.episodes) == starts
        assert results.meta["policy_version"] == 1000  # the same network in every world
        per_world[world] = results.summary["overall"]["mean_steps"]
    last = json.loads(printed.strip().splitlines()[-1])
    assert last["per_world_mean_steps"] == pytest.approx(per_world)
    assert last["mean_steps_over_worlds"] == pytest.approx(sum(per_world.values()) / 2)
    assert not (tmp_path / "r.json").exists()

    # A world that fails while it runs (here Ctrl-C) leaves the results of the worlds before it.
    for f in tmp_path.glob("r-*.json"):
        f.unlink()
    calls = []

    def interrupt_in_corridor(*args, **kwargs):
        calls.append(kwargs["world"])
        if kwargs["world"] == "corridor":
            raise KeyboardInterrupt
        return evaluate_recorded(*args, **kwargs)

    monkeypatch.setattr("services.tools.evaluate.evaluate_recorded", interrupt_in_corridor)
    assert evaluate(["--checkpoint", str(run), "--world", "box-room,corridor", "--episodes-per-start", "1",
                     "--max-steps", "5", "--json", str(tmp_path / "r.json"), "--device", "cpu", "--quiet"]) == 130
    assert calls == ["box-room", "corridor"]
    assert validate_results_json((tmp_path / "r-box-room.json").read_text()).meta["world"] == "box-room"
    assert not (tmp_path / "r-corridor.json").exists()


@pytest.mark.parametrize("argv,message", [
    ([], "give --checkpoint"),
    (["--policy", "random", "--world", "box-room,corridor", "--rrd", "x.rrd"], "--rrd take one world"),
    (["--policy", "random", "--world", "procedural:3-x"], "--world: "),
    (["--policy", "random", "--world", " , "], "names no world"),
    (["--policy", "greedy"], "needs --checkpoint"),
    (["--policy", "random", "--world", "nowhere"], "unknown world"),
    (["--policy", "random", "--set", "dqn.lr=1"], "only takes sensor"),
    (["--policy", "random", "--episodes-per-start", "0", "--world", "box-room"], "episodes_per_start"),
    (["--policy", "random", "--world", "box-room", "--starts", "0"], "--starts 0: world 'box-room' has starts 1-4"),
    (["--policy", "random", "--world", "box-room", "--starts", "1", "5"], "--starts 5: world 'box-room' has"),
    (["--policy", "random", "--world", "box-room", "--starts", "2", "1", "2"], "names start 2 more than once"),
    (["--policy", "random", "--world", "box-room", "--starts", "9", "--rrd", "x.rrd"], "--starts 9: world"),
    (["--policy", "random", "--world", "box-room,nowhere.xml"], "MJCF file 'nowhere.xml' does not exist"),
])
def test_evaluate_refuses_bad_options_clearly(argv: list[str], message: str, capsys, tmp_path: Path,
                                              monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert evaluate(argv + ["--json", "r.json", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert message in err
    assert list(tmp_path.iterdir()) == []  # refused before any file: a recording, a world's results


@pytest.mark.parametrize("worlds", ["box-room", "box-room,corridor"])
def test_evaluate_refuses_a_json_path_that_is_a_folder_before_it_runs(worlds: str, capsys, tmp_path: Path) -> None:
    # The results were written once every episode had run: a folder there failed the run at its end.
    folder = tmp_path / ("r" if worlds == "box-room" else "r-corridor.json")
    folder.mkdir()
    assert evaluate(["--policy", "reactive", "--world", worlds, "--episodes-per-start", "1", "--max-steps", "2",
                     "--json", str(tmp_path / "r"), "--set", "sensor.width=64", "--set", "sensor.height=48",
                     "--quiet"]) == 2
    captured = capsys.readouterr()
    assert f"error: --json: {folder} is a folder" in captured.err and "protocol" not in captured.out
    assert sorted(tmp_path.iterdir()) == [folder]


def test_greedy_policy_takes_the_best_q_value(tmp_path: Path) -> None:
    model = load_model(make_run(tmp_path / "run"))
    policy = make_policy("greedy", net=model.net)
    depth = np.full((48, 64), 2.0, np.float32)
    action, q = policy(depth)
    assert q.shape == (5,) and action == int(np.argmax(q)) and all(math.isfinite(v) for v in q)
    assert weights_sha256(model.net) == model.weights_sha256


def test_an_ensemble_plays_the_mean_of_its_networks_q_values(tmp_path: Path) -> None:
    import torch

    from shared.config import ModelConfig
    from shared.learning.model import InferenceRunner, ModelError, QEnsemble, QNetwork

    sensor = SensorConfig(width=40, height=30)
    torch.manual_seed(0)
    nets = [QNetwork(ModelConfig(fc1=16, fc2=8, previous_action=True), sensor).eval() for _ in range(2)]
    alone, pair = make_policy("greedy", net=nets[0]), make_policy("greedy", net=QEnsemble(nets))
    runners = [InferenceRunner(n) for n in nets]
    rng = np.random.default_rng(0)
    previous = None
    differ = 0
    for _ in range(12):
        depth = rng.uniform(0.3, 4.0, (30, 40)).astype(np.float32)
        action, q = pair(depth)
        # each network reads the command the ensemble chose last, not the one it would have chosen
        mean = np.mean([r.q_values(depth, previous) for r in runners], axis=0)
        assert np.allclose(q, mean, atol=1e-6) and action == int(np.argmax(mean))
        differ += not np.allclose(q, runners[0].q_values(depth, previous))
        previous = action
    assert differ == 12  # two different networks: the mean is neither's
    pair.reset()
    alone.reset()
    depth = np.full((30, 40), 2.0, np.float32)
    assert np.allclose(pair(depth)[1], np.mean([r.q_values(depth, None) for r in runners], axis=0), atol=1e-6)
    # an ensemble of a network with itself is that network
    twin = make_policy("greedy", net=QEnsemble([nets[0], nets[0]]))
    assert np.allclose(twin(depth)[1], alone(depth)[1], atol=1e-6)
    # an ensemble joins with its networks; features stack every member's pool3 (receptive-field maps)
    trio = QEnsemble([QEnsemble(nets), nets[0]])
    assert len(trio.members) == 3 and len(QEnsemble([trio]).members) == 3  # counted once flattened
    assert tuple(trio.features(torch.ones(1, 1, 30, 40)).shape) == (1, 3 * 64, 3, 5)
    with pytest.raises(ModelError, match="same camera"):
        QEnsemble([nets[0], QNetwork(ModelConfig(fc1=16, fc2=8), SensorConfig(width=64, height=48))])
    with pytest.raises(ModelError, match="2 to 16"):
        QEnsemble(nets[:1])
    with pytest.raises(ModelError, match="2 to 16 networks, got 18"):
        QEnsemble([QEnsemble(nets * 5), QEnsemble(nets * 4)])


def test_evaluate_an_ensemble_records_its_members(tmp_path: Path, capsys) -> None:
    first, second = make_run(tmp_path / "a", seed=0), make_run(tmp_path / "b", policy_version=2000, seed=1)
    argv = ["--checkpoint", str(first), "--world", "box-room", "--episodes-per-start", "1", "--max-steps", "5",
            "--device", "cpu", "--quiet"]
    assert evaluate(argv + ["--ensemble", str(second / "weights.safetensors"), "--json", str(tmp_path / "e.json")]) == 0
    results = validate_results_json((tmp_path / "e.json").read_text())
    assert results.meta["model"] == "a@1000+weights@2000"
    assert [m["policy_version"] for m in results.meta["ensemble"]] == [1000, 2000]
    assert [m["weights_sha256"] for m in results.meta["ensemble"]] == [load_model(first).weights_sha256,
                                                                      load_model(second).weights_sha256]
    # with itself as its only member, an ensemble plays exactly the checkpoint alone
    assert evaluate(argv + ["--ensemble", str(first), "--json", str(tmp_path / "twin.json")]) == 0
    assert evaluate(argv + ["--json", str(tmp_path / "alone.json")]) == 0
    twin, alone = (validate_results_json((tmp_path / f"{n}.json").read_text()) for n in ("twin", "alone"))
    assert [e.steps for e in twin.episodes] == [e.steps for e in alone.episodes]
    assert [e.trajectory_xy for e in twin.episodes] == [e.trajectory_xy for e in alone.episodes]
    # the same ensemble as one file (`model export --ensemble`) plays the same episodes
    joined = tmp_path / "joined.safetensors"
    assert main(["model", "export", str(first), str(second / "weights.safetensors"), "--ensemble",
                 "--out", str(joined)]) == 0
    assert evaluate(argv[:1] + [str(joined)] + argv[2:] + ["--json", str(tmp_path / "file.json")]) == 0
    from_file = validate_results_json((tmp_path / "file.json").read_text())
    assert [e.trajectory_xy for e in from_file.episodes] == [e.trajectory_xy for e in results.episodes]
    assert from_file.meta["model"] == "joined@1000"
    assert [m["weights_sha256"] for m in from_file.meta["ensemble"]] == [
        m["weights_sha256"] for m in results.meta["ensemble"]]
    capsys.readouterr()
    other = tmp_path / "other"  # trained for another robot: refused, not scored on moves it never made
    from shared.learning.checkpoints import CheckpointManager
    from shared.learning.dqn import DQNAgent

    cfg = small_config().with_overrides({"env.control_period_s": 0.25})
    CheckpointManager(other / "checkpoints").save(DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=2),
                                                  config=cfg.to_dict())
    assert evaluate(argv + ["--ensemble", str(other)]) == 2
    assert "env.control_period_s" in capsys.readouterr().err
    assert evaluate(["--policy", "random", "--world", "box-room", "--ensemble", str(first), "--quiet"]) == 2
    assert "ensemble plays the greedy policy" in capsys.readouterr().err


def test_evaluate_refuses_worlds_whose_results_would_share_one_json_file(tmp_path: Path, capsys,
                                                                         monkeypatch) -> None:
    # 'w/a.xml' and 'w-a.xml' both slug to 'w-a.xml': the second world's results overwrote the
    # first's, and both were printed as saved to the one file
    monkeypatch.chdir(tmp_path)
    xml = (Path(__file__).resolve().parents[3] / "shared" / "sim" / "worlds" / "two_rooms.xml").read_text()
    (tmp_path / "w").mkdir()
    (tmp_path / "w" / "a.xml").write_text(xml)
    (tmp_path / "w-a.xml").write_text(xml)
    assert evaluate(["--policy", "random", "--world", "w/a.xml,w-a.xml", "--max-steps", "1", "--json", "r.json",
                     "--quiet"]) == 2
    assert "would both write r-w-a.xml.json" in capsys.readouterr().err
    assert not list(tmp_path.glob("r*.json"))
