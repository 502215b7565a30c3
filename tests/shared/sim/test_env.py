"""The Gymnasium environment: motion, reward, episode end, determinism."""

import dataclasses
import math
import re

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import shared.sim.env  # noqa: F401  (registers cogexplore/Explore-v0)
from shared.config import SPEED_TABLES, EnvConfig, SensorConfig
from shared.errors import PolicyError
from shared.evaluation.policies import RandomPolicy
from shared.sim.env import ENV_ID, EnvError, ExploreEnv
from shared.sim.robot import MAX_TWIST_MPS, MAX_TWIST_RPS
from shared.sim.world import SceneBuilder, StartPose, WorldError


def _corridor_world(face_distances: list[float]):
    """Starts at the origin-ish facing +x towards a wall; one start per requested distance
    from the camera to the wall's face."""
    b = SceneBuilder("probe", (-2.0, -2.0, 8.0, 2.0 + 3 * len(face_distances)))
    starts = []
    for i, dist in enumerate(face_distances):
        y = 3.0 * i
        b.wall(dist + 0.05, y - 1.0, dist + 0.05, y + 1.0, height=2.0)
        starts.append(StartPose(0.0, y, 0.0, f"wall-{dist}"))
    return b.build("probe", starts)


def test_check_env_passes():
    env = ExploreEnv(world="box-room")
    check_env(env, skip_render_check=True)
    env.close()


def test_registered_with_gymnasium():
    env = gym.make(ENV_ID, world="box-room", speed_table="test")
    obs, info = env.reset(seed=0)
    assert obs.shape == (120, 160) and obs.dtype == np.float32
    assert set(info) >= {"pose", "start_index", "collision_cause", "distance_from_start_m",
                         "path_length_m", "min_depth_m", "step"}
    env.close()


@pytest.mark.parametrize("table", ["train", "test"])
def test_straight_and_turn_speeds(table):
    omegas, v = SPEED_TABLES[table]
    env = ExploreEnv(world=_corridor_world([6.0]), speed_table=table, start_index=0)
    period = env.env_config.control_period_s
    env.reset(seed=0)
    _, reward, term, _, info = env.step(2)  # straight
    assert reward == 1.0 and not term
    assert abs(info["pose"][0] - v * period) < 0.01 and abs(info["pose"][1]) < 1e-6
    env.reset(seed=0)
    _, _, _, _, info = env.step(0)  # left: arc of radius v/omega
    omega = omegas[0]
    assert abs(info["pose"][2] - omega * period) < 0.01
    radius = v / omega
    assert abs(info["pose"][0] - radius * math.sin(omega * period)) < 0.01
    assert abs(info["pose"][1] - radius * (1 - math.cos(omega * period))) < 0.01


def test_collision_rule_fires_below_055_m():
    # train speed moves 0.16 m per step: from 0.70 m the next image reads 0.54 m (collision),
    # from 0.75 m it reads 0.59 m (no collision).
    env = ExploreEnv(world=_corridor_world([0.70, 0.75]), speed_table="train")
    obs, info = env.reset(options={"start_index": 0})
    assert info["min_depth_m"] == pytest.approx(0.70, abs=0.01)
    _, reward, term, trunc, info = env.step(2)
    assert term and not trunc and reward == -100.0
    assert info["collision_cause"] == "depth" and info["min_depth_m"] < 0.55
    env.reset(options={"start_index": 1})
    _, reward, term, _, info = env.step(2)
    assert not term and reward == 1.0 and info["collision_cause"] is None
    assert 0.55 < info["min_depth_m"] < 0.6


def test_body_contact_is_a_collision_even_when_unseen():
    # A wall beside the robot is outside the 57 degree field of view; turning into it
    # while moving makes the body touch it.
    b = SceneBuilder("side", (-2.0, -1.0, 6.0, 1.0))
    b.wall(-2.0, -0.2, 6.0, -0.2, height=2.0)  # face at y = -0.15, robot radius 0.18
    world = b.build("side", [StartPose(0.0, 0.06, 0.0)])
    env = ExploreEnv(world=world, collision_distance_m=0.01)
    env.reset(seed=0)
    causes = []
    for _ in range(3):
        _, _, term, _, info = env.step(4)  # right turn, towards the wall
        causes.append(info["collision_cause"])
        if term:
            break
    # the touch ends the episode as a collision, by contact: the depth image never came within 0.01 m
    assert term and causes[-1] == "contact", causes
    assert info["min_depth_m"] > 0.01, info


def test_step_cap_truncates_not_terminates():
    env = ExploreEnv(world=_corridor_world([6.0]), max_episode_steps=3, start_index=0)
    env.reset(seed=0)
    flags = [env.step(0)[2:4] for _ in range(3)]  # turning in place never collides here
    assert flags[:2] == [(False, False), (False, False)]
    assert flags[2] == (False, True)


def test_same_seed_same_episode():
    def rollout(seed):
        env = ExploreEnv(world="box-room", max_episode_steps=30)
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(seed)
        frames, poses = [obs], []
        for _ in range(30):
            obs, _, term, trunc, info = env.step(int(rng.integers(5)))
            frames.append(obs)
            poses.append(info["pose"])
            if term or trunc:
                break
        return np.stack(frames), poses

    a, pa = rollout(7)
    b, pb = rollout(7)
    np.testing.assert_array_equal(a, b)
    assert pa == pb


def test_bad_action_and_start_are_clear_errors():
    env = ExploreEnv(world="box-room")
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(7)
    with pytest.raises(ValueError, match="start_index"):
        env.reset(options={"start_index": 99})
    with pytest.raises(ValueError, match="start_index"):
        ExploreEnv(world="box-room", start_index=99)


def test_a_twist_beyond_the_robots_limits_or_not_a_number_is_a_clear_error():
    env = ExploreEnv(world=_corridor_world([6.0]), start_index=0)
    env.reset(seed=0)
    for linear, angular in ((80.0, 0.0), (1e12, 0.0), (-MAX_TWIST_MPS - 0.01, 0.0), (0.0, MAX_TWIST_RPS + 0.01),
                            (float("nan"), 0.0), (0.0, float("inf")), ("0.2", 0.0), (0.2, None), (True, 0.0)):
        with pytest.raises(EnvError, match="twist"):
            env.step_twist(linear, angular)
    assert env.robot.pose() == pytest.approx((0.0, 0.0, 0.0))  # nothing was driven
    *_, terminated, _, info = env.step_twist(MAX_TWIST_MPS, -MAX_TWIST_RPS)
    assert not terminated and info["path_length_m"] > 0.5
    env.close()


def test_a_robot_too_large_for_the_worlds_starts_is_refused_at_construction():
    with pytest.raises(WorldError) as err:
        ExploreEnv(world="box-room", robot_radius_m=0.8)
    msg = str(err.value)
    assert "world 'box-room'" in msg and "robot_radius_m 0.8" in msg and "1 'sw'" in msg and "\n" not in msg
    assert "every command's first step ends in a collision at 3 of its 4 starts" in msg and "centre" not in msg
    assert "1 'sw' (touching geom" in msg
    ExploreEnv(world="box-room", robot_radius_m=0.25).close()  # a little larger still fits


def test_a_camera_that_sees_a_wall_as_a_collision_from_a_start_is_refused_at_construction():
    # box-room's starts were checked with the default camera; at 120 degrees the 'nw' start's first
    # image holds the cylinder beside it at 0.15 m and no command's first step ends clear of it, so every
    # episode from there was a collision at once
    with pytest.raises(WorldError) as err:
        ExploreEnv(world="box-room", sensor=SensorConfig(hfov_deg=120.0, width=64, height=48))
    msg = str(err.value)
    assert re.search(r"hfov_deg 120, vfov_deg 43\), every command's first step ends in a collision at 1 of its 4 "
                     r"starts: 4 'nw' \(its first image reads 0\.1\d m\)$", msg), msg
    assert "\n" not in msg
    # at 90 degrees it sees the cylinder at 0.26 m too, but going straight ends clear: taken
    ExploreEnv(world="box-room", sensor=SensorConfig(hfov_deg=90.0, width=64, height=48)).close()


@pytest.mark.parametrize("sensor", [SensorConfig(vfov_deg=80.0), SensorConfig(mount_height_m=0.15),
                                    SensorConfig(width=40, height=30, vfov_deg=80.0)])
def test_a_camera_that_sees_the_floor_as_a_collision_is_refused_at_construction(sensor):
    with pytest.raises(EnvError) as err:
        ExploreEnv(world="box-room", sensor=sensor)
    assert "the bare floor reads" in str(err.value) and "collision_distance_m 0.55" in str(err.value)
    # Gated out by min_range_m, the near floor is no return, and no collision.
    gated = dataclasses.replace(sensor, min_range_m=0.6)
    env = ExploreEnv(world="box-room", sensor=gated, start_index=2)
    env.reset(seed=0)
    assert not env.step(2)[2]
    env.close()


def test_a_random_policy_with_a_negative_seed_is_a_clear_error():
    # The seed reaches numpy's generator, whose own refusal is a traceback (evaluate --seed -1).
    for seed in (-1, 1.5, "3"):
        with pytest.raises(PolicyError, match="seed"):
            RandomPolicy(seed)
    assert RandomPolicy(3)(np.zeros((30, 40), np.float32))[0] in range(5)


def test_info_tracks_distance_and_path_length():
    env = ExploreEnv(world=_corridor_world([6.0]), start_index=0, speed_table="test")
    env.reset(seed=0)
    for _ in range(4):
        _, _, _, _, info = env.step(2)
    assert info["distance_from_start_m"] == pytest.approx(0.5, abs=0.03)
    assert info["path_length_m"] == pytest.approx(info["distance_from_start_m"], abs=1e-6)
    assert EnvConfig().control_period_s == 0.5


def test_random_starts_are_clear_varied_and_never_used_by_the_test_protocol():
    from shared.config import SensorConfig
    from shared.sim.maps import occupancy_grid

    env = ExploreEnv(EnvConfig(world="paper-indoor", random_start_prob=1.0, random_start_clearance_m=0.6),
                     sensor=SensorConfig(width=40, height=30))
    grid = occupancy_grid(env.world, 0.05)
    occupied_xy = np.stack(grid.cell_to_world(*np.argwhere(grid.occupied)[:, ::-1].T), axis=1)
    named = {(s.x, s.y) for s in env.world.starts}
    poses = []
    for seed in range(8):
        obs, info = env.reset(seed=seed)
        assert info["random_start"] is True
        x, y, _ = info["pose"]
        assert (x, y) not in named
        # 0.6 m from every occupied cell (less half a cell of jitter), and not a collision at once
        assert np.hypot(occupied_xy[:, 0] - x, occupied_xy[:, 1] - y).min() > 0.6 - 0.05
        assert shared.sim.env.min_valid_depth(obs) >= 0.55 + 0.1
        assert info["distance_from_start_m"] == 0.0
        poses.append((round(x, 2), round(y, 2)))
    assert len(set(poses)) == 8
    # an explicit start index (what evaluation passes) always starts at that world start
    _, info = env.reset(seed=0, options={"start_index": 3})
    s = env.world.starts[3]
    assert info["random_start"] is False and info["pose"][:2] == pytest.approx((s.x, s.y), abs=1e-9)
    # the same seed draws the same random start
    a = env.reset(seed=5)[1]["pose"]
    b = env.reset(seed=5)[1]["pose"]
    assert a == b


@pytest.mark.timeout(60)
def test_a_world_with_an_obstacle_kilometres_away_draws_its_starts_at_once(tmp_path):
    # A 4 m room and a pillar 2 km east: the map spans 2 km, and the clearance map's row pass swept
    # once per cell of its largest distance (40,000 sweeps, minutes) before the first jittered start.
    path = tmp_path / "far.xml"
    walls = "".join(f'<geom type="box" pos="{x} {y} 1" size="{hx} {hy} 1"/>'
                    for x, y, hx, hy in ((2, 0, 0.05, 2), (-2, 0, 0.05, 2), (0, 2, 2, 0.05), (0, -2, 2, 0.05)))
    path.write_text(f'<mujoco><worldbody><geom name="floor" type="plane" size="0 0 1"/>{walls}'
                    '<geom type="cylinder" pos="2000 0 1" size="0.2 1"/>'
                    '<site name="start_a" pos="-1 0 0"/></worldbody></mujoco>')
    env = ExploreEnv(EnvConfig(world=str(path), random_start_prob=1.0), sensor=SensorConfig(width=40, height=30))
    obs, info = env.reset(seed=0, options={"start_index": 0, "start_jitter": (0.05, 3.0)})
    assert info["pose"][0] == pytest.approx(-1.0, abs=0.05) and shared.sim.env.min_valid_depth(obs) >= 0.65
    obs, info = env.reset(seed=1)  # a random start, on the same map
    assert info["random_start"] and shared.sim.env.min_valid_depth(obs) >= 0.65
    env.close()


def test_random_start_config_is_validated():
    from shared.config import ConfigError

    with pytest.raises(ConfigError, match="random_start_prob"):
        EnvConfig(random_start_prob=1.5)
    with pytest.raises(ConfigError, match="random_start_clearance_m"):
        EnvConfig(random_start_clearance_m=float("nan"))


def test_extra_worlds_share_the_episodes_and_fixed_starts_stay_in_the_main_world(tmp_path, caplog):
    import logging

    from shared.config import SensorConfig
    from shared.sim.world import WorldError

    env = ExploreEnv(EnvConfig(world="box-room", extra_worlds="corridor, procedural:7-8", extra_world_prob=0.6,
                               max_episode_steps=3), sensor=SensorConfig(width=40, height=30))
    worlds = []
    for episode in range(60):
        obs, info = env.reset(seed=0 if episode == 0 else None)
        start = env.world.starts[info["start_index"]]
        assert info["pose"][:2] == pytest.approx((start.x, start.y), abs=1e-9)  # a start of the world drawn
        _, _, _, _, info = env.step(2)
        worlds.append(info["world"])
    counts = {name: worlds.count(name) for name in set(worlds)}
    assert set(counts) == {"box-room", "corridor", "procedural:7", "procedural:8"}, counts
    assert 0.45 < 1 - counts["box-room"] / 60 < 0.75
    # what evaluation passes, an explicit start, always plays the main world
    assert all(env.reset(options={"start_index": 0})[1]["world"] == "box-room" for _ in range(10))
    # the same seed draws the same worlds, starts and depth noise, on a used env and a fresh one
    def episodes(env: ExploreEnv) -> list:
        seen = []
        for k in range(8):
            _, info = env.reset(seed=3) if k == 0 else env.reset()
            seen.append((info["world"], info["start_index"], env.step(2)[0].tobytes()))
        assert len({world for world, _, _ in seen}) > 1
        return seen

    noisy = SensorConfig(width=40, height=30, noise_std_m=0.01)
    used = ExploreEnv(env.env_config, sensor=noisy)
    for _ in range(20):
        used.reset()
    fresh = ExploreEnv(env.env_config, sensor=noisy)
    assert episodes(used) == episodes(fresh)
    for e in (env, used, fresh):
        e.close()
    # a world name that does not resolve fails when the env is made, not episodes into a run
    broken = tmp_path / "broken.xml"
    broken.write_text("<mujoco><worldbody><geom type='box'")
    for name in ("no-such-world", str(broken)):
        with pytest.raises(WorldError):
            ExploreEnv(EnvConfig(world="box-room", extra_worlds=name, extra_world_prob=0.5))
    # one that breaks later is dropped with a warning when drawn, and its episodes play the main world
    later = tmp_path / "later.xml"
    later.write_text('<mujoco><worldbody><geom name="floor" type="plane" size="0 0 1"/>'
                     '<geom type="box" pos="0 3 1" size="3 0.1 1"/><geom type="box" pos="0 -3 1" size="3 0.1 1"/>'
                     '<geom type="box" pos="3 0 1" size="0.1 3 1"/><geom type="box" pos="-3 0 1" size="0.1 3 1"/>'
                     '<site name="start_a" pos="0 0 0"/></worldbody></mujoco>')
    env = ExploreEnv(EnvConfig(world="box-room", extra_worlds=f"{later}, corridor", extra_world_prob=1.0))
    later.write_text("<mujoco><worldbody><geom type='box'")
    with caplog.at_level(logging.WARNING, logger="cogexplore.env"):
        played = [env.reset(seed=k)[1]["world"] for k in range(12)]
    assert set(played) == {"box-room", "corridor"} and played.count("box-room") == 1, played
    assert sum("dropping" in r.getMessage() for r in caplog.records) == 1
    env.close()


def test_a_fleet_of_actors_shares_the_extra_worlds_between_them():
    from shared.config import SensorConfig
    from shared.sim.env import EnvError

    cfg = EnvConfig(world="box-room", extra_worlds="corridor, procedural:7-8", extra_world_prob=1.0,
                    max_episode_steps=2)
    played: list[set[str]] = []
    for index in range(2):
        env = ExploreEnv(cfg, sensor=SensorConfig(width=40, height=30))
        env.share_extra_worlds(index, 2)
        played.append({env.reset(seed=k)[1]["world"] for k in range(12)})
        env.close()
    assert played == [{"corridor", "procedural:8"}, {"procedural:7"}]  # every 2nd from the actor's index
    few = ExploreEnv(cfg, sensor=SensorConfig(width=40, height=30))
    few.share_extra_worlds(4, 5)  # more actors than worlds: each plays them all
    assert {few.reset(seed=k)[1]["world"] for k in range(20)} == {"corridor", "procedural:7", "procedural:8"}
    with pytest.raises(EnvError, match="index 2 of count 2"):
        few.share_extra_worlds(2, 2)
    few.close()


def test_extra_world_lists_parse_and_bad_ones_are_config_errors():
    from shared.config import ConfigError, parse_world_list

    assert parse_world_list(" corridor,procedural:3-5, procedural:4 ,,procedural:9") == (
        "corridor", "procedural:3", "procedural:4", "procedural:5", "procedural:9")
    assert EnvConfig(extra_worlds="procedural:1000-1199").extra_world_names[-1] == "procedural:1199"
    for text, match in (("procedural:x", "seed"), ("procedural:5-3", "below"), ("procedural:1-3-4", "seed"),
                        ("procedural:0-20000", "more than")):
        with pytest.raises(ConfigError, match=match):
            EnvConfig(extra_worlds=text)
    with pytest.raises(ConfigError, match="extra_world_prob"):
        EnvConfig(extra_world_prob=0.5)  # no extra worlds to play
    with pytest.raises(ConfigError, match="extra_world_prob"):
        EnvConfig(extra_worlds="corridor", extra_world_prob=float("nan"))


def test_the_novelty_reward_pays_each_steps_newly_seen_floor_and_a_snapshot_rewinds_it():
    from shared.config import NEW_AREA_CAP_M2
    from shared.sim.maps import CoverageTracker, occupancy_grid

    per_m2 = 2.5
    env = ExploreEnv(world="paper-indoor", reward_new_area_per_m2=per_m2, max_episode_steps=60)
    plain = ExploreEnv(world="paper-indoor", max_episode_steps=60)
    # An independent tracker fed the same poses and images: the first view is not paid.
    tracker = CoverageTracker(occupancy_grid(env.world), env.sensor_config)
    # Start 5 of paper-indoor, circling half-right: the first lap opens new floor, the next
    # ones see it again and pay little more than r_move (the sensor's edge cells).
    depth, info = env.reset(seed=3, options={"start_index": 4})
    plain.reset(seed=3, options={"start_index": 4})
    tracker.observe(*info["pose"], depth)
    paid, snap = [], None
    for k, action in enumerate([3] * 30):
        if k == 4:
            snap = env.snapshot()
        depth, reward, terminated, truncated, info = env.step(action)
        _, plain_reward, plain_terminated, *_ = plain.step(action)
        assert terminated == plain_terminated  # the term pays; it never moves the robot
        if terminated:
            assert reward == plain_reward == -100.0  # a collision pays r_ter alone
            break
        new_area = tracker.observe(*info["pose"], depth)
        assert plain_reward == 1.0
        assert reward == pytest.approx(1.0 + per_m2 * min(new_area, NEW_AREA_CAP_M2))
        paid.append(reward)
    assert len(paid) == 30 and max(paid) > 1.5 and min(paid) >= 1.0 and paid[-1] < 1.25
    # Rewound to step 4 and replayed, step 5 pays again what it paid: the seen floor is rewound too.
    env.restore(snap)
    assert paid[4] > 1.0 and env.step(3)[1] == pytest.approx(paid[4])


def test_the_novelty_reward_is_validated_and_bounds_what_a_learner_accepts():
    from shared.config import NEW_AREA_CAP_M2, ConfigError

    with pytest.raises(ConfigError, match="reward_new_area_per_m2"):
        EnvConfig(reward_new_area_per_m2=-1.0)
    with pytest.raises(ConfigError, match="reward_new_area_per_m2"):
        EnvConfig(reward_new_area_per_m2=math.nan)
    paper, novelty = EnvConfig(), EnvConfig(reward_new_area_per_m2=2.5)
    top = 1.0 + 2.5 * NEW_AREA_CAP_M2
    rewards = np.array([1.0, 1.7, top, top + 0.01, 0.99, -100.0, 3.4e38])
    assert paper.pays(rewards).tolist() == [True, False, False, False, False, True, False]
    assert novelty.pays(rewards).tolist() == [True, True, True, False, False, True, False]
    assert not novelty.pays_for_a_move(-100.0)
    assert "1 to 11 per move" in novelty.describe_rewards()


def test_the_trap_reward_charges_once_the_step_that_enters_a_place_with_no_way_out():
    penalty = 50.0
    env = ExploreEnv(world="paper-indoor", reward_trap_penalty=penalty, max_episode_steps=60)
    plain = ExploreEnv(world="paper-indoor", max_episode_steps=60)
    expert = env.map_expert()
    # Start 6 (index 5) faces the dead end: straight ahead at the training speed it is entered
    # steps before the wall, and the charge falls on the step whose pose has no way out left.
    env.reset(seed=1, options={"start_index": 5})
    plain.reset(seed=1, options={"start_index": 5})
    way_out, rewards, snap = [True], [], None
    for _ in range(60):
        if not way_out[-1] and snap is None:
            snap = env.snapshot()
        _, reward, terminated, truncated, info = env.step(2)
        _, plain_reward, plain_terminated, *_ = plain.step(2)
        assert terminated == plain_terminated  # the term pays; it never moves the robot
        rewards.append(reward)
        if terminated:
            assert reward == plain_reward == -100.0  # a collision pays r_ter alone
            break
        way_out.append(expert.has_way_out(*info["pose"], env.env_config.trap_horizon_steps))
    entered = [k for k in range(1, len(way_out)) if way_out[k - 1] and not way_out[k]]
    assert len(entered) == 1 and 1 < entered[0] < len(rewards) - 2  # well before the wall
    charged = [k for k, r in enumerate(rewards[:-1]) if r != 1.0]
    assert charged == [entered[0] - 1] and rewards[charged[0]] == 1.0 - penalty
    # A snapshot inside the trap keeps it: replayed from there, no step is charged again.
    env.restore(snap)
    assert env.step(2)[1] == 1.0
    # A longer horizon asks more of a way out, so the same drive is charged earlier (at 24 steps
    # the start itself has none, and starting in a trap is never charged).
    far = ExploreEnv(world="paper-indoor", reward_trap_penalty=penalty, trap_horizon_steps=20,
                     max_episode_steps=60)
    far.reset(seed=1, options={"start_index": 5})
    far_rewards = [far.step(2)[1] for _ in range(charged[0] + 1)]
    assert far_rewards.count(1.0 - penalty) == 1 and far_rewards.index(1.0 - penalty) < charged[0]


def test_the_trap_reward_is_validated_bounds_what_a_learner_accepts_and_stays_out_of_the_test():
    from shared.config import ConfigError
    from shared.evaluation.protocol import protocol_env_config

    for bad in (-1.0, math.nan, 1001.0):
        with pytest.raises(ConfigError, match="reward_trap_penalty"):
            EnvConfig(reward_trap_penalty=bad)
    for bad in (0, 101, 16.0, True):
        with pytest.raises(ConfigError, match="trap_horizon_steps"):
            EnvConfig(reward_trap_penalty=50.0, trap_horizon_steps=bad)
    trap = EnvConfig(reward_trap_penalty=50.0)
    rewards = np.array([1.0, -49.0, -20.0, -49.01, 1.01, -100.0])
    assert trap.pays(rewards).tolist() == [True, True, True, False, False, True]
    assert EnvConfig().pays(rewards).tolist() == [True, False, False, False, False, True]
    assert "-49 to 1 per move" in trap.describe_rewards()
    # The protocol counts steps: it never pays for the trap's map checks.
    assert protocol_env_config(trap, "paper-indoor", 200).reward_trap_penalty == 0.0


@pytest.mark.parametrize("options", [{"start_idx": 2}, {"start_index": 2, "jitter": (0.1, 5)}, [("start_index", 2)]])
def test_a_reset_option_the_env_does_not_take_is_refused_not_ignored(options):
    # A misspelt start_index would otherwise play random starts under an evaluation that fixed one.
    env = ExploreEnv(world="box-room")
    try:
        with pytest.raises(EnvError, match="reset options") as err:
            env.reset(seed=0, options=options)
        assert "\n" not in str(err.value)
        env.reset(seed=0, options={"start_index": 2, "start_jitter": None})
        assert env.robot.pose()[:2] == pytest.approx((env.world.starts[2].x, env.world.starts[2].y))
    finally:
        env.close()


def test_a_step_before_reset_or_after_a_failed_reset_is_refused():
    # Before a reset the robot stands wherever MuJoCo put it (the origin: in paper-indoor's hall, a
    # pose no start has), and a failed reset may have switched worlds under the episode.
    env = ExploreEnv(world="paper-indoor")
    try:
        for step in (lambda: env.step(2), lambda: env.step_twist(0.2, 0.0)):
            with pytest.raises(EnvError, match="before reset"):
                step()
        env.reset(seed=0)
        env.step(2)
        with pytest.raises(EnvError):
            env.reset(seed=0, options={"start_index": 99})
        with pytest.raises(EnvError, match="before reset"):
            env.step(2)
        env.reset(seed=0)
        assert env.step(2)[4]["step"] == 1
    finally:
        env.close()


def test_a_world_keeps_its_start_maps_as_a_bool_map_and_int32_cells():
    # An actor keeps a hundred worlds: the float64 clearance map and the int64 (iy, ix) start cells
    # it kept with each were ~0.7 MB of a procedural world's ~1.6 MB. Only two thresholds of the map
    # are ever read, so it keeps those, with the same cells.
    from shared.sim.maps import clearance_map, occupancy_grid

    cfg = EnvConfig(world="procedural:1000", random_start_prob=1.0, start_jitter_m=0.1, start_jitter_deg=6.0)
    env = ExploreEnv(cfg, sensor=SensorConfig(width=40, height=30))
    env.reset(seed=0)  # a random start
    env.reset(seed=1, options={"start_index": 2, "start_jitter": (0.1, 6.0)})  # a jittered one
    scene = env._scene
    grid, fits, cells = scene.free_space()
    clearance = clearance_map(grid.occupied, grid.resolution_m)
    assert grid is occupancy_grid(env.world, shared.sim.env.MAP_RESOLUTION_M)
    assert fits.dtype == np.bool_ and np.array_equal(fits, clearance >= cfg.robot_radius_m)
    assert cells.dtype == np.int32
    assert np.array_equal(cells, np.flatnonzero(clearance >= cfg.random_start_clearance_m))
    held = [v for v in vars(scene).values() if isinstance(v, tuple)]
    assert not [a for t in held for a in t if isinstance(a, np.ndarray) and a.dtype == np.float64]
    assert fits.nbytes + cells.nbytes < grid.occupied.size * 3
    env.close()


def test_a_step_after_the_episode_ended_is_refused_until_reset():
    # Stepping on after a collision drove the robot on from inside it and reported the collision
    # again (-100 each time, no error): a loop that missed `terminated` trained on the same crash.
    env = ExploreEnv(world=_corridor_world([0.70, 6.0]), speed_table="train", max_episode_steps=2)
    try:
        env.reset(options={"start_index": 0})
        assert env.step(2)[2]  # into the wall
        for step in (lambda: env.step(2), lambda: env.step_twist(0.0, 0.0)):
            with pytest.raises(EnvError, match=r"after the episode ended \(a collision\): call env.reset\(\)") as err:
                step()
            assert "\n" not in str(err.value)
        env.reset(options={"start_index": 1})
        assert env.step(0)[2:4] == (False, False)
        assert env.step(0)[2:4] == (False, True)  # the env's own step cap, as Gymnasium's Env.step asks: reset
        with pytest.raises(EnvError, match=r"after the episode ended \(truncated at its 2-step cap\)"):
            env.step(0)
        assert env.reset(options={"start_index": 1})[1]["step"] == 0 and env.step(0)[4]["step"] == 1
    finally:
        env.close()


def test_a_snapshot_restores_whether_its_episode_had_ended():
    # The planner (shared.learning.demos) steps into a collision and restores the pose before it to try
    # another command: a snapshot taken before the end plays on, one taken at the end is ended still.
    env = ExploreEnv(world=_corridor_world([0.70]), speed_table="train", start_index=0)
    try:
        env.reset(seed=0)
        before = env.snapshot()
        assert env.step(2)[2]
        ended = env.snapshot()
        env.restore(before)
        assert env.step(0)[4]["step"] == 1  # the episode plays on from the pose before the collision
        env.restore(ended)
        with pytest.raises(EnvError, match="after the episode ended"):
            env.step(0)
        # one of another world is refused before it changes anything: the env plays on as it was
        env.reset(seed=0)
        other = ("another world's scene", *ended[1:])
        with pytest.raises(EnvError, match="own world"):
            env.restore(other)
        assert env.step(0)[4]["step"] == 1
    finally:
        env.close()
