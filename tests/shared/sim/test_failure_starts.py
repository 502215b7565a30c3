"""Failure starts in training (``EnvConfig.failure_start_prob``): episodes that begin where an earlier
episode of the env went wrong, a few steps before its collision, in its world, jittered and clear;
never for a start the caller fixes, and nothing drawn when off (real env, real MuJoCo, tiny images)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from shared.config import ConfigError, EnvConfig, SensorConfig
from shared.sim.env import START_DEPTH_MARGIN_M, ExploreEnv, min_valid_depth

SENSOR = SensorConfig(width=40, height=30)
STRAIGHT = 2


def drive_straight_into_a_wall(env: ExploreEnv) -> tuple[str, list[tuple[float, float, float]]]:
    """Play one episode straight on from the env's current start; its world and poses, the collision's last."""
    poses = [env.robot.pose()]
    for _ in range(env.env_config.max_episode_steps):
        _, _, terminated, truncated, info = env.step(STRAIGHT)
        poses.append(info["pose"])
        if terminated or truncated:
            break
    assert terminated, "the probe drives straight until it hits something"
    return info["world"], poses


def near(pose: tuple[float, float, float], base: tuple[float, float, float], jitter_m: float,
         jitter_deg: float) -> bool:
    turn = math.degrees(abs(math.atan2(math.sin(pose[2] - base[2]), math.cos(pose[2] - base[2]))))
    return abs(pose[0] - base[0]) <= jitter_m + 1e-9 and abs(pose[1] - base[1]) <= jitter_m + 1e-9 and \
        turn <= jitter_deg + 1e-6


def test_an_episode_starts_a_few_steps_before_an_earlier_collision_in_its_world_clear_and_jittered() -> None:
    # box-room is the main world; every usual episode plays procedural:1000.
    cfg = EnvConfig(world="box-room", extra_worlds="procedural:1000", extra_world_prob=1.0,
                    failure_start_prob=1.0, failure_start_back_steps=6,
                    start_jitter_m=0.05, start_jitter_deg=3.0, max_episode_steps=400)

    for seed in range(20):  # the first seed whose start has more than six steps of floor straight ahead
        env = ExploreEnv(cfg, SENSOR)
        _, info = env.reset(seed=seed)
        world, poses = drive_straight_into_a_wall(env)
        if len(poses) > 8:
            break
        env.close()
    assert info["failure_start"] is False  # nothing remembered yet: a usual start
    assert world == "procedural:1000"
    before = poses[-7:-1]  # the six steps back the config allows, not the collision's own pose
    starts = []
    for seed in range(1, 9):
        obs, info = env.reset(seed=seed)
        assert info["failure_start"] is True and info["random_start"] is False
        assert info["world"] == world  # where it went wrong, though box-room is the main world
        assert any(near(info["pose"], b, 0.05, 3.0) for b in before), info["pose"]
        assert not any(near(info["pose"], b, 0.05, 3.0) for b in poses[:-7] if b not in before)
        assert min_valid_depth(obs) >= cfg.collision_distance_m + START_DEPTH_MARGIN_M
        assert not env.robot.touching_obstacle()
        starts.append(info["pose"])
    assert len({(round(x, 3), round(y, 3)) for x, y, _ in starts}) == len(starts)  # never the same twice
    # A start the caller fixes (what evaluation does) is the named one, in the main world.
    _, info = env.reset(seed=0, options={"start_index": 1})
    named = env.world.starts[1]
    assert info["failure_start"] is False and info["world"] == "box-room"
    assert info["pose"] == pytest.approx((named.x, named.y, named.yaw), abs=1e-9)
    env.close()


def test_a_procedural_world_written_with_leading_zeros_is_one_world() -> None:
    # 'procedural:007' is the World 'procedural:7': its collisions must be found under that name.
    cfg = EnvConfig(world="box-room", extra_worlds="procedural:007", extra_world_prob=1.0, failure_start_prob=1.0,
                    max_episode_steps=400)
    env = ExploreEnv(cfg, SENSOR)
    env.reset(seed=0)
    world, _ = drive_straight_into_a_wall(env)
    assert world == "procedural:7" and set(env._scenes) == {"box-room", "procedural:7"}
    _, info = env.reset(seed=1)
    assert info["failure_start"] is True and info["world"] == "procedural:7"
    env.close()
    both = ExploreEnv(dataclasses.replace(cfg, extra_worlds="procedural:007, procedural:7"), SENSOR)
    assert both._extra_world_names == ("procedural:7",)  # one world, drawn as often as any other
    both.close()


def test_off_it_draws_nothing_and_remembers_nothing() -> None:
    """failure_start_prob = 0: after the same collisions the same seeds give the same episodes as a
    config without the field set at all, so every earlier run replays as it did."""
    plain = ExploreEnv(EnvConfig(world="box-room", random_start_prob=0.5, max_episode_steps=400), SENSOR)
    off = ExploreEnv(EnvConfig(world="box-room", random_start_prob=0.5, max_episode_steps=400,
                               failure_start_prob=0.0, failure_start_back_steps=50), SENSOR)
    for seed in range(4):
        a_obs, a = plain.reset(seed=seed)
        b_obs, b = off.reset(seed=seed)
        assert a["pose"] == b["pose"] and b["failure_start"] is False
        np.testing.assert_array_equal(a_obs, b_obs)
        assert drive_straight_into_a_wall(plain) == drive_straight_into_a_wall(off)
    assert len(off._failures) == 0
    plain.close()
    off.close()


def test_failure_start_config_is_validated() -> None:
    for value in (-0.1, 1.5, float("nan"), "0.5"):
        with pytest.raises(ConfigError, match="failure_start_prob"):
            EnvConfig(failure_start_prob=value)
    for value in (0, 101, 2.0, True):
        with pytest.raises(ConfigError, match="failure_start_back_steps"):
            EnvConfig(failure_start_back_steps=value)
