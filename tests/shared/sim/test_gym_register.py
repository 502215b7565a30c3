"""The Gymnasium ids: found from a fresh interpreter, the paper's step cap on both, and the
TimeLimit and the env's own cap ending an episode once, as a truncation."""

import json
import subprocess
import sys

import gymnasium as gym
import pytest

from shared.config import EnvConfig
from shared.errors import CogexploreError
from shared.evaluation import PAPER_MAX_STEPS
from shared.sim.gym_register import ENV_ID, IMAGE_ENV_ID, register_envs
from shared.sim.world import SceneBuilder, StartPose


def test_a_fresh_interpreter_makes_both_ids_from_the_module_named_in_the_id():
    code = """
import json, sys
import gymnasium as gym
assert not [m for m in sys.modules if m.split(".")[0] == "shared"]
out = {}
for env_id in ("cogexplore/Explore-v0", "cogexplore/ExploreImage-v0"):
    env = gym.make("shared.sim.gym_register:" + env_id, world="box-room")
    obs, _ = env.reset(seed=0)
    out[env_id] = [env.spec.id, env.spec.max_episode_steps, list(obs.shape), str(obs.dtype)]
    env.close()
print(json.dumps(out))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out == {ENV_ID: [ENV_ID, PAPER_MAX_STEPS, [120, 160], "float32"],
                   IMAGE_ENV_ID: [IMAGE_ENV_ID, PAPER_MAX_STEPS, [1, 120, 160], "uint8"]}


def test_registering_loads_neither_mujoco_nor_torch():
    code = ("import sys, shared.sim.gym_register, gymnasium as gym; "
            "print(sorted(m for m in ('mujoco', 'torch') if m in sys.modules), "
            "all(i in gym.registry for i in ('cogexplore/Explore-v0', 'cogexplore/ExploreImage-v0')))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[]", "True"]


def test_specs_carry_the_papers_step_cap_and_registering_again_changes_nothing():
    before = {i: gym.spec(i) for i in (ENV_ID, IMAGE_ENV_ID)}
    register_envs()
    for env_id, spec in before.items():
        assert gym.spec(env_id) is spec
        assert spec.max_episode_steps == PAPER_MAX_STEPS == 200


def _open_floor():
    """One far wall: circling at the hard-left command (radius ~0.23 m) never collides."""
    b = SceneBuilder("open", (-3.0, -3.0, 8.0, 3.0))
    b.wall(6.0, -1.0, 6.0, 1.0, height=2.0)
    return b.build("open", [StartPose(0.0, 0.0, 0.0)])


def _episode(env) -> list[tuple[bool, bool, int]]:
    env.reset(seed=0)
    flags = []
    while True:
        _, _, terminated, truncated, info = env.step(0)
        flags.append((terminated, truncated, info["step"]))
        if terminated or truncated:
            return flags


@pytest.mark.parametrize("make_kwargs, env_cap, length", [
    ({}, None, PAPER_MAX_STEPS),  # the TimeLimit, before the env's own cap of 500
    ({"max_episode_steps": 30}, 30, 30),  # both at once: still one end
    ({}, 40, 40),  # the env's own cap, before the TimeLimit
])
def test_one_truncation_ends_the_episode(make_kwargs, env_cap, length):
    config = EnvConfig(max_episode_steps=env_cap) if env_cap else EnvConfig()
    env = gym.make(ENV_ID, config=config, world=_open_floor(), start_index=0, **make_kwargs)
    flags = _episode(env)
    assert len(flags) == length
    assert flags[-1] == (False, True, length)
    assert not any(t or tr for t, tr, _ in flags[:-1])
    env.close()


@pytest.mark.parametrize("kwargs, match", [
    ({"sensor": {"widht": 40}}, r"unknown field\(s\) \['widht'\]"),
    ({"speed": "test"}, r"unknown field\(s\) \['speed'\]"),
    ({"sensor": [1, 2]}, "sensor must be a SensorConfig"),
    ({"config": {"world": "box-room"}}, "config must be an EnvConfig"),
    ({"sensor": {"width": "40"}}, "width"),
])
def test_a_typo_in_makes_keywords_is_a_clear_error(kwargs, match):
    for env_id in (ENV_ID, IMAGE_ENV_ID):
        with pytest.raises(CogexploreError, match=match):
            gym.make(env_id, world="box-room", **kwargs)
