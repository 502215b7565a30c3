"""Jittered named starts in training (``EnvConfig.start_jitter_m`` / ``start_jitter_deg``): a jitter
of zero changes nothing, a jitter moves named starts within bounds and never against an obstacle,
callers that fix a start or a jitter win, and the test protocol never inherits a training jitter
(real env, real MuJoCo, tiny images and step caps)."""

from __future__ import annotations

import logging
import math

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.seeding import np_random
from sim_checks import robot_gap_m

from shared.config import ConfigError, EnvConfig, SensorConfig
from shared.evaluation import PROTOCOLS
from shared.evaluation.protocol import evaluate_policy, run_protocol
from shared.sim.env import (
    ENV_ID,
    START_DEPTH_MARGIN_M,
    EnvError,
    ExploreEnv,
    min_valid_depth,
)
from shared.sim.sensor import floor_depths_m

SENSOR = SensorConfig(width=40, height=30)
JITTER = {"start_jitter_m": 0.3, "start_jitter_deg": 45.0}  # wide: box-room's start 4 is 0.26 m from a wall


def yaw_offset_deg(yaw: float, named_yaw: float) -> float:
    return abs(math.degrees(math.atan2(math.sin(yaw - named_yaw), math.cos(yaw - named_yaw))))


def is_named_exactly(env: ExploreEnv, info: dict) -> bool:
    named = env.world.starts[info["start_index"]]
    return info["pose"] == pytest.approx((named.x, named.y, named.yaw), abs=1e-9)


def test_zero_jitter_resets_are_todays_and_draw_nothing() -> None:
    env = ExploreEnv(EnvConfig(world="paper-indoor", start_jitter_m=0.0, start_jitter_deg=0.0), SENSOR)
    exact = ExploreEnv(EnvConfig(world="paper-indoor"), SENSOR)
    for seed in range(4):
        obs, info = env.reset(seed=seed)
        # Today's reset, drawn by hand: the noise seed, then the start; nothing more.
        rng = np_random(seed)[0]
        rng.integers(2**63)
        index = int(rng.integers(len(env.world.starts)))
        assert info["start_index"] == index and is_named_exactly(env, info)
        assert env.np_random.bit_generator.state == rng.bit_generator.state
        named = exact.world.starts[index]
        exact.robot.set_pose(named.x, named.y, named.yaw)
        np.testing.assert_array_equal(obs, exact.camera.capture(exact.data))
    env.close()
    exact.close()


def test_a_config_jitter_moves_named_starts_within_bounds_and_clear_of_obstacles() -> None:
    env = ExploreEnv(EnvConfig(world="box-room", speed_table="test", **JITTER), SENSOR)
    cfg = env.env_config
    poses = set()
    for seed in range(40):
        obs, info = env.reset(seed=seed)
        named = env.world.starts[info["start_index"]]
        x, y, yaw = info["pose"]
        assert max(abs(x - named.x), abs(y - named.y)) <= 0.3 and yaw_offset_deg(yaw, named.yaw) <= 45.0 + 1e-9
        assert not info["random_start"] and robot_gap_m(env) > 0 and not env.robot.touching_obstacle()
        assert min_valid_depth(obs) >= cfg.collision_distance_m + START_DEPTH_MARGIN_M
        assert info["distance_from_start_m"] == 0.0 and env.step(2)[4]["step"] == 1
        poses.add((round(x, 6), round(y, 6)))
    assert len(poses) == 40
    assert len({env.reset(seed=s)[1]["start_index"] for s in range(40)}) == 4  # every start was drawn
    # The draw is the seed's; a start fixed in the config (a training run from one pose) is jittered too.
    assert env.reset(seed=7)[1]["pose"] == env.reset(seed=7)[1]["pose"]
    one = ExploreEnv(EnvConfig(world="box-room", start_index=3, **JITTER), SENSOR)
    _, info = one.reset(seed=0)
    assert info["start_index"] == 3 and not is_named_exactly(one, info)
    env.close()
    one.close()


def test_callers_that_fix_the_start_or_the_jitter_win_over_the_config() -> None:
    env = ExploreEnv(EnvConfig(world="box-room", **JITTER), SENSOR)
    # The exact pose, asked for explicitly (even with no start given) or by fixing the start.
    for options in ({"start_jitter": None}, {"start_index": 2}, {"start_index": 2, "start_jitter": None},
                    {"start_jitter": (0.0, 0.0)}):
        _, info = env.reset(seed=1, options=options)
        assert is_named_exactly(env, info), options
    # A jitter of the caller's own, even with a start fixed, replaces the config's.
    for seed in range(10):
        _, info = env.reset(seed=seed, options={"start_index": 1, "start_jitter": (0.02, 1.0)})
        named = env.world.starts[1]
        assert max(abs(info["pose"][0] - named.x), abs(info["pose"][1] - named.y)) <= 0.02
        assert 0 < yaw_offset_deg(info["pose"][2], named.yaw) <= 1.0 + 1e-9
    env.close()
    # Gymnasium's id takes the fields as any other keyword.
    made = gym.make(ENV_ID, world="box-room", sensor=SENSOR, start_jitter_m=0.1, start_jitter_deg=6.0)
    _, info = made.reset(seed=0)
    named = made.unwrapped.world.starts[info["start_index"]]
    assert 0 < max(abs(info["pose"][0] - named.x), abs(info["pose"][1] - named.y)) <= 0.1
    made.close()


def test_a_start_with_no_clear_draw_is_played_exact_in_training_and_an_error_for_the_caller(caplog) -> None:
    # A collision distance just short of the floor's nearest reading, so that the env takes it, but
    # within START_DEPTH_MARGIN_M of it: no drawn pose can be clear.
    collision_m = float(floor_depths_m(SENSOR).min()) - START_DEPTH_MARGIN_M / 2
    env = ExploreEnv(EnvConfig(world="box-room", collision_distance_m=collision_m, **JITTER), SENSOR)
    with caplog.at_level(logging.WARNING, logger="cogexplore.env"):
        infos = [env.reset(seed=seed)[1] for seed in range(6)]
    assert all(is_named_exactly(env, info) for info in infos)
    warned = [r.getMessage() for r in caplog.records if "env.start_jitter" in r.getMessage()]
    assert len(warned) == len({info["start_index"] for info in infos})  # once per start
    assert "of world 'box-room': none of 100 poses drawn within ±0.3 m" in warned[0]
    with pytest.raises(EnvError, match="none of 100 poses"):
        env.reset(seed=0, options={"start_jitter": (0.3, 45.0)})
    env.close()


def test_random_free_pose_starts_are_not_jittered() -> None:
    plain = ExploreEnv(EnvConfig(world="paper-indoor", random_start_prob=1.0), SENSOR)
    jittered = ExploreEnv(EnvConfig(world="paper-indoor", random_start_prob=1.0, start_jitter_m=0.1,
                                    start_jitter_deg=6.0), SENSOR)
    for seed in range(4):
        a, b = plain.reset(seed=seed), jittered.reset(seed=seed)
        assert b[1]["random_start"] and b[1]["pose"] == a[1]["pose"]
        np.testing.assert_array_equal(a[0], b[0])
    plain.close()
    jittered.close()


def test_the_protocol_never_inherits_a_training_jitter() -> None:
    trained = EnvConfig(world="box-room", start_jitter_m=0.1, start_jitter_deg=6.0)
    kwargs = {"world": "box-room", "sensor_cfg": SENSOR, "starts": [0, 3], "episodes_per_start": 2, "max_steps": 2,
              "seed": 4, "progress": False}
    paper = evaluate_policy(lambda d: (2, None), env_cfg=trained, protocol=PROTOCOLS["paper"], **kwargs)
    starts = ExploreEnv(world="box-room", sensor=SENSOR).world.starts
    assert all(e.trajectory_xy[0] == (starts[e.start_index].x, starts[e.start_index].y) for e in paper.episodes)
    assert (paper.meta["env"]["start_jitter_m"], paper.meta["env"]["start_jitter_deg"]) == (0.0, 0.0)
    # The robust protocol's draws are its own: the same as for a model trained from exact starts.
    robust = evaluate_policy(lambda d: (2, None), env_cfg=trained, protocol=PROTOCOLS["robust"], **kwargs)
    assert robust.episodes == evaluate_policy(lambda d: (2, None), protocol=PROTOCOLS["robust"], **kwargs).episodes
    assert {e.trajectory_xy[0] for e in robust.episodes}.isdisjoint((s.x, s.y) for s in starts)
    # An env a caller built with a training jitter still gets exact starts from the paper's protocol.
    direct = run_protocol(lambda d: (2, None), lambda: ExploreEnv(trained, SENSOR, speed_table="test"),
                          starts=[0, 3], episodes_per_start=2, max_steps=2, seed=4, progress=False)
    assert [e.trajectory_xy for e in direct.episodes] == [e.trajectory_xy for e in paper.episodes]


@pytest.mark.parametrize("field,value", [
    ("start_jitter_m", -0.01), ("start_jitter_m", 1.5), ("start_jitter_m", float("nan")), ("start_jitter_m", True),
    ("start_jitter_deg", -1.0), ("start_jitter_deg", 46.0), ("start_jitter_deg", float("inf")),
    ("start_jitter_deg", "6"),
])
def test_bad_jitter_values_are_config_errors_naming_the_field(field, value) -> None:
    with pytest.raises(ConfigError, match=rf"\[env\] {field} = "):
        EnvConfig(**{field: value})
    EnvConfig(start_jitter_m=1.0, start_jitter_deg=45.0)  # the bounds themselves are allowed


@pytest.mark.parametrize("jitter", [(1e300, 0.0), (1.7e308, 1e308), (0.0, 1e300), (10.01, 0.0), (0.1, 180.5)])
def test_a_reset_jitter_beyond_any_world_is_an_env_error_not_an_overflow(jitter) -> None:
    # numpy's uniform overflowed (a traceback) past ~9e307 m, and a 1e300 m draw became a cell index
    # by an invalid cast; degrees past 180 draw no other heading.
    env = ExploreEnv(EnvConfig(world="box-room"), SENSOR)
    with pytest.raises(EnvError, match=r"start_jitter .*metres in \[0, 10\] and degrees in \[0, 180\]"):
        env.reset(seed=0, options={"start_index": 0, "start_jitter": jitter})
    try:  # the bounds themselves are taken (a 4 m room may have no clear draw within ±10 m)
        env.reset(seed=0, options={"start_index": 0, "start_jitter": (10.0, 180.0)})
    except EnvError as exc:
        assert "none of 100 poses" in str(exc)
    env.close()
