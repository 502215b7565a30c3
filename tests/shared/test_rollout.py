"""The one episode loop: it adds nothing to the env, tells observers in order, and ends episodes right."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from shared.config import EnvConfig, SensorConfig
from shared.learning.policy import ActionChoice
from shared.rollout import Rollout
from shared.sim.env import ExploreEnv

SENSOR = SensorConfig(width=32, height=24)


def make_env(**overrides) -> ExploreEnv:
    return ExploreEnv(EnvConfig(world="box-room", speed_table="test", **overrides), SENSOR)


class Journal:
    """An observer that writes down every hook it hears, tagged with its name."""

    def __init__(self, name: str, log: list):
        self.name, self.log = name, log

    def begin_episode(self, episode):
        self.log.append((self.name, "begin", episode.index))

    def on_step(self, step):
        self.log.append((self.name, "step", step.index))

    def end_episode(self, episode):
        self.log.append((self.name, "end", episode.steps))


def test_a_rollout_episode_is_exactly_the_envs_own_loop():
    """Same seed, same commands: the loop's observations, rewards and infos are the env's."""
    actions = [2, 2, 1, 0, 2, 3, 4, 2] * 10
    env = make_env()
    steps = []
    loop = Rollout(env, lambda _obs, _info, n: actions[n], [SimpleNamespace(on_step=steps.append)])
    episode = loop.run_episode(seed=3, options={"start_index": 1})
    env.close()

    twin = make_env()
    obs, info = twin.reset(seed=3, options={"start_index": 1})
    np.testing.assert_array_equal(episode.first_obs, obs)
    for k, step in enumerate(steps):
        np.testing.assert_array_equal(step.obs, obs)
        assert step.info["pose"] == info["pose"] and step.action == actions[k]
        obs, reward, terminated, truncated, info = twin.step(actions[k])
        np.testing.assert_array_equal(step.next_obs, obs)
        assert (step.reward, step.terminated, step.truncated) == (reward, terminated, truncated)
    twin.close()
    assert episode.done and episode.steps == len(steps) and episode.episode_return == sum(s.reward for s in steps)
    assert steps[-1].last and not any(s.last for s in steps[:-1])


def test_observers_hear_every_step_before_any_episode_end_and_the_policy_is_reset():
    log: list = []
    resets = []

    class Policy:
        def reset(self):
            resets.append(len(log))

        def __call__(self, _obs, _info, _n):
            return ActionChoice(2, np.zeros(5, np.float32), 0.0, False)  # straight ahead into the wall

    env = make_env()
    loop = Rollout(env, Policy(), [Journal("a", log), Journal("b", log)])
    first = loop.run_episode(seed=0, options={"start_index": 0})
    assert resets == [0] and log[:2] == [("a", "begin", 0), ("b", "begin", 0)]
    body = log[2:-2]
    assert body == [(name, "step", k) for k in range(first.steps) for name in ("a", "b")]
    assert log[-2:] == [("a", "end", first.steps), ("b", "end", first.steps)]
    assert first.terminated and not first.truncated  # a collision ends it, never the cap
    assert loop.episode is None
    with pytest.raises(RuntimeError, match="begin_episode"):
        loop.step()
    second = loop.run_episode(seed=0, options={"start_index": 0})
    assert second.index == 1 and resets == [0, len(log) - 2 * (second.steps + 2)]
    env.close()


def test_max_steps_truncates_and_env_steps_count_on_from_where_they_start():
    seen = []
    env = make_env()
    # half turns in the open: no collision within five steps
    loop = Rollout(env, lambda _obs, _info, n: seen.append(n) or (1, None), max_steps=5, env_steps=100)
    episode = loop.run_episode(seed=0, options={"start_index": 0})
    env.close()
    assert episode.truncated and not episode.terminated and episode.steps == 5
    assert seen == [100, 101, 102, 103, 104] and loop.env_steps == 105


def test_choices_in_every_form_and_a_checked_action():
    env = make_env()
    for choice, q in ((1, None), ((1, [0.0] * 5), [0.0] * 5), (ActionChoice(1, np.ones(5), 0.1, True), "ones")):
        loop = Rollout(env, lambda _o, _i, _n, c=choice: c, max_steps=1)
        loop.begin_episode(seed=0, options={"start_index": 0})
        step = loop.step()
        assert step.action == 1
        if q == "ones":
            np.testing.assert_array_equal(step.q_values, np.ones(5))
        else:
            assert step.q_values == q

    def check(action):
        if action not in range(5):
            raise ValueError(f"bad command {action!r}")
        return int(action)

    loop = Rollout(env, lambda _o, _i, _n: 7, check_action=check)
    loop.begin_episode(seed=0)
    with pytest.raises(ValueError, match="bad command 7"):
        loop.step()
    env.close()


def test_a_caller_placed_start_is_used_as_given():
    env = make_env()
    obs, info = env.reset(seed=0, options={"start_index": 0})
    loop = Rollout(env, lambda _o, _i, _n: 1, max_steps=2)
    episode = loop.begin_episode(obs=obs)
    assert episode.first_obs is obs and episode.first_info == {} and episode.obs is obs
    loop.step()
    assert episode.info["step"] == 1
    env.close()
