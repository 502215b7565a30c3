"""The robust test protocol: jittered starts that never touch an obstacle, Kinect-like depth noise,
every draw seeded by (seed, start, episode) so that two policies meet the same ones, and a jitter
and noise of zero that is the paper's protocol exactly (real env, real MuJoCo, tiny step caps)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from rrd_checks import recorded_protocol
from sim_checks import robot_gap_m

from services.cli import main
from shared.config import ConfigError, SensorConfig
from shared.depth import range_gate
from shared.evaluation import PROTOCOLS, ProtocolConfig
from shared.evaluation.policies import ReactivePolicy
from shared.evaluation.protocol import episode_seed, evaluate_policy
from shared.evaluation.results import load_results
from shared.sim.env import START_DEPTH_MARGIN_M, EnvError, ExploreEnv, min_valid_depth
from shared.sim.sensor import DepthCamera

SENSOR = SensorConfig(width=40, height=30)
ROBUST = PROTOCOLS["robust"]


class Recorder:
    """A policy that records the first image and pose of every episode and otherwise acts as
    ``inner``. It reads the pose (``reads_pose``), so the protocol hands it each step's info."""

    reads_pose = True

    def __init__(self, inner):
        self.inner = inner
        self.firsts: list[np.ndarray] = []
        self.first_poses: list[tuple[float, float, float]] = []
        self._new = True

    def reset(self) -> None:
        self._new = True

    def __call__(self, depth_m: np.ndarray, info):
        if self._new:
            self.firsts.append(depth_m.copy())
            self.first_poses.append(tuple(info["pose"]))
            self._new = False
        return self.inner(depth_m)


def test_the_named_sets_and_their_overrides() -> None:
    paper = PROTOCOLS["paper"]
    assert not paper.jittered and paper.sensor(SensorConfig(noise_std_m=0.03)) == SensorConfig()
    assert (ROBUST.start_jitter_m, ROBUST.start_jitter_deg) == (0.05, 3.0) and ROBUST.jittered
    noisy = ROBUST.sensor(SENSOR)
    assert (noisy.noise_std_m, noisy.noise_quadratic_per_m, noisy.width) == (0.0012, 0.0019, 40)
    assert ROBUST.overridden() == ROBUST and ROBUST.overridden(start_jitter_m=0.05).name == "robust"
    custom = ROBUST.overridden(start_jitter_m=0.1, sensor_noise_std_m=0.01)
    assert custom.name == "custom" and custom.start_jitter_m == 0.1 and custom.start_jitter_deg == 3.0
    assert (custom.sensor_noise_std_m, custom.sensor_noise_quadratic_per_m) == (0.01, 0.0)  # constant noise
    assert ProtocolConfig.from_dict(custom.to_dict()) == custom
    with pytest.raises(ConfigError, match="start_jitter_deg = 400"):
        ProtocolConfig("x", start_jitter_deg=400)


def test_the_same_seed_gives_two_policies_the_same_starts_and_noise() -> None:
    runs = {}
    for name, inner in (("circling", lambda d: (0, None)), ("reactive", ReactivePolicy(SENSOR))):
        policy = Recorder(inner)
        results = evaluate_policy(policy, world="box-room", sensor_cfg=SENSOR, starts=[0, 3], episodes_per_start=3,
                                  max_steps=6, seed=5, progress=False, protocol=ROBUST)
        runs[name] = (results, policy)
    (circling, recorder_a), (reactive, recorder_b) = runs["circling"], runs["reactive"]
    assert [e.steps for e in circling.episodes] != [e.steps for e in reactive.episodes]  # two policies indeed
    starts_a = [e.trajectory_xy[0] for e in circling.episodes]
    assert starts_a == [e.trajectory_xy[0] for e in reactive.episodes]
    # The whole start pose, heading included, and the first image, noise included: the same, bit for bit.
    assert len(recorder_a.first_poses) == 6 and recorder_a.first_poses == recorder_b.first_poses
    assert all(np.array_equal(a, b) for a, b in zip(recorder_a.firsts, recorder_b.firsts, strict=True))
    # Each start's episodes are different draws within the jitter, around the named pose.
    env = ExploreEnv(world="box-room", sensor=SENSOR)
    turns_deg = []
    for e, (x, y, yaw) in zip(circling.episodes, recorder_a.first_poses, strict=True):
        named = env.world.starts[e.start_index]
        assert (x, y) == e.trajectory_xy[0]
        assert max(abs(x - named.x), abs(y - named.y)) <= ROBUST.start_jitter_m
        turns_deg.append(math.degrees(math.remainder(yaw - named.yaw, math.tau)))
    assert max(abs(t) for t in turns_deg) <= ROBUST.start_jitter_deg + 1e-9 and len(set(turns_deg)) == 6
    assert len(set(starts_a[:3])) == 3 and len(set(starts_a[3:])) == 3
    # The noise reached the camera: each first image differs from a noise-free capture at its pose by
    # the Kinect's sigma at that depth (z-scores of spread 1), not by nothing.
    kinect = DepthCamera(env.model, ROBUST.sensor(SENSOR), seed=0)
    z_scores = []
    for first, pose in zip(recorder_a.firsts, recorder_a.first_poses, strict=True):
        env.robot.set_pose(*pose)
        clean = env.camera.capture(env.data)
        keep = (clean > 0.5) & (clean < 3.8)  # away from the range gate, where noise can drop a return
        z_scores.append((first[keep] - clean[keep]) / kinect.noise_std_m(clean[keep]))
    z = np.concatenate(z_scores)
    assert z.size > 500 and abs(z.mean()) < 0.1 and z.std() == pytest.approx(1.0, abs=0.1)
    env.close()
    # The same seed repeats the run exactly; another seed draws other starts.
    again = evaluate_policy(lambda d: (0, None), world="box-room", sensor_cfg=SENSOR, starts=[0, 3],
                            episodes_per_start=3, max_steps=6, seed=5, progress=False, protocol=ROBUST)
    assert again.episodes == circling.episodes
    other = evaluate_policy(lambda d: (0, None), world="box-room", sensor_cfg=SENSOR, starts=[0, 3],
                            episodes_per_start=3, max_steps=6, seed=6, progress=False, protocol=ROBUST)
    assert [e.trajectory_xy[0] for e in other.episodes] != starts_a
    assert circling.meta["protocol"] == ROBUST.to_dict()
    assert circling.meta["sensor"]["noise_quadratic_per_m"] == 0.0019


def test_zero_jitter_and_noise_is_the_paper_protocol_exactly() -> None:
    policy = ReactivePolicy(SENSOR)
    starts, max_steps = [0, 5, 6], 60
    zero = ROBUST.overridden(start_jitter_m=0.0, start_jitter_deg=0.0, sensor_noise_std_m=0.0)
    assert zero.name == "custom" and not zero.jittered
    kwargs = {"world": "paper-indoor", "sensor_cfg": SENSOR, "starts": starts, "episodes_per_start": 2,
              "max_steps": max_steps, "seed": 0, "progress": False}
    paper = evaluate_policy(policy, protocol=PROTOCOLS["paper"], **kwargs)
    assert evaluate_policy(policy, protocol=zero, **kwargs).episodes == paper.episodes
    # The paper's protocol as it always ran: each episode reset at the exact start with its seed,
    # the policy driven until a collision or the cap.
    env = ExploreEnv(world="paper-indoor", speed_table="test", sensor=SENSOR, max_episode_steps=max_steps)
    for e in paper.episodes:
        obs, info = env.reset(seed=episode_seed(0, e.start_index, e.episode), options={"start_index": e.start_index})
        named = env.world.starts[e.start_index]
        assert info["pose"][:2] == pytest.approx((named.x, named.y), abs=1e-12)
        steps, done = 0, False
        while not done:
            obs, _, terminated, truncated, info = env.step(policy(obs)[0])
            steps, done = steps + 1, terminated or truncated
        assert (steps, info["pose"][:2]) == (e.steps, pytest.approx(e.trajectory_xy[-1], abs=1e-12))
    env.close()
    assert len({e.steps for e in paper.episodes}) > 1  # the starts differ, so the check compares something


def test_a_jittered_start_never_touches_or_faces_an_obstacle_too_near() -> None:
    # A wide draw (±0.8 m, any heading) in the small box room: many draws land in or against walls.
    jitter = (0.8, 180.0)
    env = ExploreEnv(world="box-room", speed_table="test", sensor=SENSOR)
    cfg = env.env_config
    rng = np.random.default_rng(0)
    rejected = 0
    for _ in range(200):
        named = env.world.starts[3]  # the tightest start: 0.26 m from a wall
        env.robot.set_pose(named.x + rng.uniform(-0.8, 0.8), named.y + rng.uniform(-0.8, 0.8), rng.uniform(-3, 3))
        rejected += robot_gap_m(env) <= 0 or min_valid_depth(env.camera.capture(env.data)) < cfg.collision_distance_m
    assert rejected > 20  # the rule has something to reject
    poses = set()
    for start in range(len(env.world.starts)):
        named = env.world.starts[start]
        for seed in range(30):
            obs, info = env.reset(seed=seed, options={"start_index": start, "start_jitter": jitter})
            x, y, _ = info["pose"]
            poses.add((round(x, 6), round(y, 6)))
            assert max(abs(x - named.x), abs(y - named.y)) <= 0.8
            assert robot_gap_m(env) > 0 and not env.robot.touching_obstacle()
            assert min_valid_depth(obs) >= cfg.collision_distance_m + START_DEPTH_MARGIN_M
            assert info["start_index"] == start
            # Each draw began a new episode: its first step counts from 1, whatever the last episode took.
            assert env.step(2)[4]["step"] == 1
    assert len(poses) == 4 * 30
    # The draw is the seed's: the same seed, the same pose.
    first = env.reset(seed=7, options={"start_index": 3, "start_jitter": jitter})[1]["pose"]
    assert env.reset(seed=7, options={"start_index": 3, "start_jitter": jitter})[1]["pose"] == first
    env.close()


def test_a_start_with_no_clear_draw_is_named_in_the_error(tmp_path: Path, capsys) -> None:
    # A collision distance the bare floor passes (0.89 m at its nearest) but no drawn view keeps
    # (a start needs it plus a margin: 0.95 m, nearer than the floor): no drawn pose can be clear.
    env = ExploreEnv(world="box-room", sensor=SENSOR, collision_distance_m=0.85)
    with pytest.raises(EnvError, match=r"start 2 of world 'box-room': none of 100 poses drawn within ±0.05 m and "
                                       r"±3° of it keeps 0.18 m from obstacles"):
        env.reset(seed=1, options={"start_index": 1, "start_jitter": (0.05, 3.0)})
    for bad in ((0.05,), (-1.0, 3.0), (float("nan"), 0.0)):
        with pytest.raises(EnvError, match="start_jitter"):
            env.reset(seed=1, options={"start_index": 1, "start_jitter": bad})
    env.close()
    assert main(["evaluate", "--policy", "reactive", "--world", "box-room", "--set", "env.collision_distance_m=0.85",
                 "--episodes-per-start", "1", "--max-steps", "3", "--quiet"]) == 2
    assert "start 1 of world 'box-room'" in capsys.readouterr().err


def test_depth_noise_grows_with_distance_as_a_kinects() -> None:
    env = ExploreEnv(world="box-room", sensor=SENSOR)
    named = env.world.starts[2]
    env.robot.set_pose(named.x, named.y, named.yaw)
    clean = env.camera.capture(env.data)
    kinect = ROBUST.sensor(SENSOR)
    camera = DepthCamera(env.model, kinect, seed=0)
    sigma = camera.noise_std_m(np.array([1.0, 2.0, 4.0]))
    np.testing.assert_allclose(sigma, 0.0012 + 0.0019 * np.array([0.36, 2.56, 12.96]))
    assert camera.noise_std_m(np.array([0.3]))[0] == pytest.approx(0.0012)  # no shrinking below 0.4 m
    frames = np.stack([camera.capture(env.data) for _ in range(300)])
    keep = (clean > 0.5) & (clean < 3.8)  # away from the range gate, where noise can drop a return
    assert keep.sum() > 100 and np.unique(np.round(clean[keep], 1)).size > 5  # several distances
    z = (frames[:, keep] - clean[keep]) / camera.noise_std_m(clean[keep])
    assert abs(z.mean()) < 0.05 and z.std() == pytest.approx(1.0, abs=0.05)
    # A constant sigma is the noise the sensor always had: the same draws as before.
    constant = SensorConfig(width=40, height=30, noise_std_m=0.01)
    a = DepthCamera(env.model, constant, seed=3).capture(env.data)
    rng = np.random.default_rng(3)
    b = clean + rng.normal(0.0, 0.01, clean.shape).astype(np.float32) * (clean > 0)
    np.testing.assert_array_equal(a, range_gate(b, 0.0, 4.0))
    env.close()


def test_evaluate_records_the_protocol_and_refuses_its_noise_as_an_override(tmp_path: Path, capsys) -> None:
    common = ["--policy", "reactive", "--world", "box-room", "--starts", "1", "--episodes-per-start", "2",
              "--max-steps", "3", "--quiet"]
    for argv, want in (([], ROBUST), (["--protocol", "paper"], PROTOCOLS["paper"]),
                       (["--protocol", "paper", "--start-jitter-m", "0.1", "--start-jitter-deg", "5",
                         "--sensor-noise-m", "0.02"],
                        ProtocolConfig("custom", start_jitter_m=0.1, start_jitter_deg=5.0, sensor_noise_std_m=0.02))):
        out, rrd = tmp_path / f"{want.name}.json", tmp_path / f"{want.name}.rrd"
        assert main(["evaluate", *common, *argv, "--json", str(out), "--rrd", str(rrd)]) == 0
        printed = capsys.readouterr().out
        doc = json.loads(out.read_text())
        assert doc["meta"]["protocol"] == want.to_dict() and load_results(out).protocol == want
        assert recorded_protocol(rrd) == pytest.approx(want.to_dict())  # the recording says it too
        assert doc["meta"]["sensor"]["noise_std_m"] == want.sensor_noise_std_m
        assert f"protocol {want.describe()}" in printed
        summary_line = next(line for line in printed.splitlines() if line.startswith("{"))
        assert json.loads(summary_line)["protocol"] == want.name
    assert main(["evaluate", *common, "--set", "sensor.noise_std_m=0.02"]) == 2
    assert "the test protocol sets the sensor's noise" in capsys.readouterr().err
    assert main(["evaluate", *common, "--set", "env.start_jitter_m=0.1"]) == 2  # training's jitter, not the test's
    assert "the test protocol sets the start jitter" in capsys.readouterr().err
    # The protocol's own env fields: the override did nothing (env.world=corridor played box-room).
    for field, flag in (("env.world=corridor", "--world"), ("env.speed_table=train", "test speeds"),
                        ("env.max_episode_steps=50", "--max-steps"), ("env.start_index=2", "--starts"),
                        ("env.reward_trap_penalty=5", "counts steps")):
        assert main(["evaluate", *common, "--set", field]) == 2
        err = capsys.readouterr().err
        assert f"error: {field.split('=')[0]}: " in err and flag in err
    assert main(["evaluate", *common, "--start-jitter-m", "-1"]) == 2
    assert "start_jitter_m = -1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["evaluate", *common, "--protocol", "exact"])
    assert "invalid choice: 'exact' (choose from 'paper', 'robust')" in capsys.readouterr().err


def test_the_map_expert_drives_from_the_true_pose_and_outlasts_the_reactive_baseline(tmp_path: Path) -> None:
    runs = {}
    for policy in ("expert", "reactive"):
        out = tmp_path / f"{policy}.json"
        assert main(["evaluate", "--policy", policy, "--world", "procedural:301", "--starts", "1", "2", "3",
                     "--episodes-per-start", "1", "--max-steps", "60", "--json", str(out), "--quiet"]) == 0
        runs[policy] = load_results(out)
    assert runs["expert"].meta["policy"] == "expert" and runs["expert"].meta["env"]["speed_table"] == "test"
    expert_steps = [e.steps for e in runs["expert"].episodes]
    reactive_steps = [e.steps for e in runs["reactive"].episodes]
    assert sum(expert_steps) > sum(reactive_steps) and min(expert_steps) == 60
    # without the rollout's pose it refuses, rather than guessing from the image
    from shared.evaluation.policies import ExpertPolicy
    from shared.learning.policy import PolicyError

    with pytest.raises(PolicyError, match="pose and world"):
        ExpertPolicy(SENSOR)(np.ones((30, 40), np.float32))


def test_the_fields_evaluate_refuses_are_those_the_protocol_sets() -> None:
    # PROTOCOL_ENV_FIELDS is what evaluate refuses as --set and what experiment keeps from its tests:
    # a field protocol_env_config sets but the table missed was an override that silently did nothing
    import dataclasses

    from shared.config import EnvConfig
    from shared.evaluation.protocol import PROTOCOL_ENV_FIELDS, protocol_env_config

    base = EnvConfig(extra_worlds="procedural:5")
    changed = {"world": "corridor", "speed_table": "train", "max_episode_steps": 50, "start_index": 2,
               "start_jitter_m": 0.1, "start_jitter_deg": 5.0, "reward_trap_penalty": 5.0,
               "extra_worlds": "procedural:6", "extra_world_prob": 0.5, "random_start_prob": 0.5,
               "failure_start_prob": 0.5}
    assert set(changed) == set(PROTOCOL_ENV_FIELDS)
    ignored = {name for name, value in changed.items()
               if protocol_env_config(dataclasses.replace(base, **{name: value}), "box-room", 200)
               == protocol_env_config(base, "box-room", 200)}
    assert ignored == set(PROTOCOL_ENV_FIELDS)
    # and every other field reaches the protocol's env
    for f in dataclasses.fields(EnvConfig):
        if f.name not in PROTOCOL_ENV_FIELDS:
            assert getattr(protocol_env_config(base, "box-room", 200), f.name) == getattr(base, f.name), f.name
