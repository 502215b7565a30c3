"""The one agent-environment loop of cogexplore, with observers for what differs.

Every place that plays episodes (the actor, the single-process trainer, the test protocol, the
supervised data collection) drives a :class:`Rollout`, in the spirit of Acme's
``EnvironmentLoop``::

    loop = Rollout(env, policy, observers=[batcher, stats])
    loop.begin_episode(seed=0)
    while running:
        step = loop.step()          # choose, env.step, tell the observers
        if step.last:               # the episode ended (its end_episode hooks have run)
            loop.begin_episode()

or, for one whole episode, ``loop.run_episode(seed=..., options=...)``.

``policy(obs, info, env_steps)`` chooses each command from the observation, the env's ``info``
of that observation and the number of env steps this loop has taken; it returns an action index,
an ``(action, q_values)`` pair, or an object with ``.action`` (and optionally ``.q_values``), e.g.
``shared.learning.policy.ActionChoice``. A policy with a ``reset()`` method (one that remembers its
last command) is reset as each episode begins.

An observer has any of ``begin_episode(episode)``, ``on_step(step)`` and ``end_episode(episode)``;
they run in the order given, ``on_step`` of every observer before ``end_episode`` of any, so an
observer that stores a transition has stored it before one that reports the episode. What the
actor, trainer, protocol and data collection do differently (batching transitions for the wire,
streaming to Rerun, coverage, episode statistics, the expert guide) are observers; the loop itself
knows nothing of any of them.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Episode:
    """One episode as it is played: where it began and what has happened so far."""

    index: int
    """Episodes this loop began before this one."""
    first_obs: np.ndarray
    """The observation the episode began with."""
    first_info: Mapping[str, Any]
    """``env.reset``'s info (pose, start index, world, ...); empty when the caller reset the env."""
    steps: int = 0
    """Env steps taken in the episode."""
    episode_return: float = 0.0
    """Sum of its rewards."""
    terminated: bool = False
    """It ended in a collision (set when it ends)."""
    truncated: bool = False
    """It reached the env's step cap or the loop's ``max_steps`` (set when it ends)."""
    last_step: "Step | None" = None
    """Its most recent step."""
    started_s: float = field(default_factory=time.monotonic)
    """``time.monotonic()`` when it began."""

    @property
    def obs(self) -> np.ndarray:
        """The observation the next command is chosen on."""
        return self.first_obs if self.last_step is None else self.last_step.next_obs

    @property
    def info(self) -> Mapping[str, Any]:
        """The env's info of :attr:`obs`."""
        return self.first_info if self.last_step is None else self.last_step.next_info

    @property
    def done(self) -> bool:
        return self.terminated or self.truncated


@dataclass(frozen=True)
class Step:
    """One env step: what the command was chosen on, the command, and what came of it."""

    episode: Episode
    index: int
    """Steps of the episode before this one (0 for its first)."""
    obs: np.ndarray
    info: Mapping[str, Any]
    """The observation the command was chosen on, and its info (e.g. the pose it was taken at)."""
    choice: Any
    """What the policy returned."""
    action: int
    q_values: Any
    """The policy's Q-values or scores for the five commands, or None."""
    reward: float
    next_obs: np.ndarray
    next_info: Mapping[str, Any]
    terminated: bool
    truncated: bool

    @property
    def last(self) -> bool:
        """The episode ended with this step."""
        return self.terminated or self.truncated


def _unpack(choice: Any) -> tuple[int, Any]:
    if isinstance(choice, (tuple, list)):
        return choice[0], choice[1] if len(choice) > 1 else None
    if hasattr(choice, "action"):
        return choice.action, getattr(choice, "q_values", None)
    return choice, None


class Rollout:
    """One environment, one policy, episodes step by step; observers hear of every step.

    ``max_steps`` (None: only the env's own cap) truncates an episode after that many steps.
    ``check_action`` (optional) validates each command before the env sees it and returns it as
    an ``int``; it raises on a bad one. ``env_steps`` is the count the policy sees first (a
    resumed training run goes on from its checkpoint's).
    """

    def __init__(self, env: Any, policy: Callable[[np.ndarray, Mapping[str, Any], int], Any],
                 observers: Iterable[Any] = (), *, max_steps: int | None = None,
                 check_action: Callable[[Any], int] | None = None, env_steps: int = 0):
        self.env = env
        self.policy = policy
        self.observers = tuple(observers)
        self.max_steps = max_steps
        self.check_action = check_action
        self.env_steps = env_steps
        """Env steps taken (from ``env_steps`` on); a caller may move it on (an actor to its run's count)."""
        self.episodes = 0
        """Episodes begun."""
        self.episode: Episode | None = None
        """The episode now playing (None before the first and once one has ended)."""
        self._reset_policy = getattr(policy, "reset", None)
        self._hooks = {name: [getattr(o, name) for o in self.observers if hasattr(o, name)]
                       for name in ("begin_episode", "on_step", "end_episode")}

    def begin_episode(self, *, seed: int | None = None, options: Mapping[str, Any] | None = None,
                      obs: np.ndarray | None = None, info: Mapping[str, Any] | None = None) -> Episode:
        """Start an episode: ``env.reset(seed=..., options=...)``, or, when the caller has reset
        (or placed) the robot itself, the ``obs`` (and ``info``) it got. The policy is reset and
        every observer's ``begin_episode`` runs."""
        if obs is None:
            obs, info = self.env.reset(seed=seed, options=dict(options) if options is not None else None)
        self.episode = Episode(self.episodes, obs, info if info is not None else {})
        self.episodes += 1
        if self._reset_policy is not None:
            self._reset_policy()
        for hook in self._hooks["begin_episode"]:
            hook(self.episode)
        return self.episode

    def step(self) -> Step:
        """Choose a command on the current observation, step the env, tell the observers; when
        the episode ends (collision, the env's cap or ``max_steps``), the ``end_episode`` hooks
        run and :attr:`episode` becomes None."""
        episode = self.episode
        if episode is None:
            raise RuntimeError("begin_episode() must come before step()")
        obs, info = episode.obs, episode.info
        choice = self.policy(obs, info, self.env_steps)
        action, q_values = _unpack(choice)
        if self.check_action is not None:
            action = self.check_action(action)
        next_obs, reward, terminated, truncated, next_info = self.env.step(action)
        self.env_steps += 1
        episode.steps += 1
        episode.episode_return += reward
        terminated = bool(terminated)
        truncated = not terminated and (bool(truncated) or (self.max_steps is not None
                                                            and episode.steps >= self.max_steps))
        step = Step(episode, episode.steps - 1, obs, info, choice, action, q_values, reward, next_obs, next_info,
                    terminated, truncated)
        episode.last_step = step
        for hook in self._hooks["on_step"]:
            hook(step)
        if step.last:
            episode.terminated, episode.truncated = terminated, truncated
            self.episode = None
            for hook in self._hooks["end_episode"]:
                hook(episode)
        return step

    def run_episode(self, **begin: Any) -> Episode:
        """One whole episode (``begin`` as for :meth:`begin_episode`); returns it, ended."""
        episode = self.begin_episode(**begin)
        while not episode.done:
            self.step()
        return episode
