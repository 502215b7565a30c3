"""Action selection: greedy and epsilon-greedy over the Q-network, with epsilon schedules.

Schedules: a linear decay from ``eps_start`` to ``eps_end`` over ``eps_decay_steps`` environment
steps (the paper's epsilon-greedy), or Ape-X per-actor constants eps_i = base^(1 + alpha*i/(N-1))
(Horgan et al. 2018), so that a fleet of actors spans greedy to very exploratory behaviour.
Every choice returns the action and all five Q-values (the evaluator logs them).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from shared.config import MAX_ACTION_HISTORY, NUM_ACTIONS, ExploreConfig
from shared.depth import image_stack
from shared.errors import PolicyError  # defined torch-free, for the ONNX runner too
from shared.learning.model import InferenceRunner, QNetwork


def linear_epsilon(step: int, cfg: ExploreConfig) -> float:
    """eps_start -> eps_end linearly over eps_decay_steps environment steps, then eps_end."""
    if step < 0:
        raise PolicyError(f"step must be >= 0, got {step}")
    if cfg.eps_decay_steps == 0 or step >= cfg.eps_decay_steps:
        return float(cfg.eps_end)
    frac = step / cfg.eps_decay_steps
    return float(cfg.eps_start + frac * (cfg.eps_end - cfg.eps_start))


def apex_epsilon(actor_index: int, num_actors: int, base: float = 0.4, alpha: float = 7.0) -> float:
    """Ape-X: eps_i = base ** (1 + alpha * i / (N - 1)); a single actor gets ``base``."""
    if not (isinstance(num_actors, int) and num_actors >= 1):
        raise PolicyError(f"num_actors must be an integer >= 1, got {num_actors!r}")
    if not (isinstance(actor_index, int) and 0 <= actor_index < num_actors):
        raise PolicyError(f"actor_index must be in [0, {num_actors}), got {actor_index!r}")
    if num_actors == 1:
        return float(base)
    return float(base ** (1.0 + alpha * actor_index / (num_actors - 1)))


class EpsilonSchedule:
    """epsilon as a function of the environment step, for one actor."""

    def __init__(self, cfg: ExploreConfig | None = None, actor_index: int = 0, num_actors: int = 1):
        self.cfg = cfg or ExploreConfig()
        self.actor_index = actor_index
        self.num_actors = num_actors
        # validate now, so a bad fleet size fails at start-up, not at the first step
        self._apex = (apex_epsilon(actor_index, num_actors, self.cfg.apex_base, self.cfg.apex_alpha)
                      if self.cfg.per_actor else None)

    def __call__(self, step: int) -> float:
        return self._apex if self._apex is not None else linear_epsilon(step, self.cfg)


@dataclass(frozen=True)
class ActionChoice:
    action: int
    q_values: np.ndarray  # (5,) float32, online network, dropout off
    epsilon: float
    explored: bool  # True when the action was drawn at random


class NonFiniteQValues(PolicyError):
    """A network gave Q-values that are not finite: weights that load (each one finite) but so large
    that the arithmetic overflows. argmax reads NaN as command 0, a full turn: a test must not score
    such a network as if it had chosen it, nor a policy remember it as its last command."""

    def __init__(self, q_values: np.ndarray):
        self.q_values = np.asarray(q_values)
        super().__init__(f"the network gave Q-values that are not finite ({self.q_values.tolist()}): its weights "
                         "are broken (each finite, but large enough to overflow)")


def greedy_action(q_values: np.ndarray) -> int:
    """argmax of (5,) Q-values; ties go to the lowest index (deterministic)."""
    q = np.asarray(q_values)
    if q.shape != (NUM_ACTIONS,):
        raise PolicyError(f"q_values must have shape ({NUM_ACTIONS},), got {q.shape}")
    return int(np.argmax(q))


class EpsilonGreedyPolicy:
    """epsilon-greedy over a QNetwork. With ``schedule=None`` it is purely greedy.

    The network is shared, not copied: load new weights into ``net`` and the next ``act`` uses
    them. Random draws come from the policy's own generator (seeded), never the global ones.
    The policy remembers the commands it chose last (``previous_actions``, most recent first, up to
    ``MAX_ACTION_HISTORY``: what a ``model.previous_action`` network reads) and, for a network that reads
    several images (``model.frame_stack``), the images it acted on before; call ``reset()`` when an
    episode starts.

    As a rollout policy (``shared.rollout``), ``policy(obs, info, env_steps)`` acts at step
    ``env_steps * step_scale`` (an actor of a fleet of N estimates the fleet's step count as its own
    times N, needing no message from anyone) with the command of ``guide`` (an
    ``shared.expert.expert.ExpertGuide``, or anything whose ``action(pose)`` is a command or None)
    in place of the greedy one.
    """

    def __init__(self, net: QNetwork, schedule: EpsilonSchedule | None = None,
                 seed: int | None = None, *, guide: Any = None, step_scale: int = 1):
        self.net = net
        self.schedule = schedule
        self.rng = np.random.default_rng(seed)
        self._runner = InferenceRunner(net)
        self.previous_actions: tuple[int, ...] = ()
        self.frame_stack = int(getattr(net.model_cfg, "frame_stack", 1))
        self.previous_frames: tuple[np.ndarray, ...] = ()  # most recent first, at most frame_stack - 1
        self.guide = guide
        self.step_scale = step_scale

    def __call__(self, depth_m: np.ndarray, info: Mapping[str, Any], env_steps: int) -> ActionChoice:
        guide_action = self.guide.action(info["pose"]) if self.guide is not None else None
        return self.act(depth_m, step=env_steps * self.step_scale, guide_action=guide_action)

    def reset(self) -> None:
        """A new episode: no previous command, no earlier images."""
        self.previous_actions = ()
        self.previous_frames = ()

    @property
    def previous_action(self) -> int | None:
        """The last command chosen this episode (None before the first)."""
        return self.previous_actions[0] if self.previous_actions else None

    def _chose(self, choice: ActionChoice) -> ActionChoice:
        self.previous_actions = (choice.action, *self.previous_actions[:MAX_ACTION_HISTORY - 1])
        return choice

    def q_values(self, depth_m: np.ndarray) -> np.ndarray:
        """(5,) Q-values for this image after this episode's commands (and images); changes nothing."""
        history = np.array([self.previous_actions], dtype=np.int64) if self.previous_actions else None
        if self.frame_stack == 1:
            return self._runner.q_values(depth_m, history)
        return self._runner.q_values(image_stack(depth_m, self.previous_frames, self.frame_stack)[None], history)[0]

    def _q_values(self, depth_m: np.ndarray) -> np.ndarray:
        q = self.q_values(depth_m)
        if self.frame_stack > 1:  # the image acted on joins the memory
            self.previous_frames = (np.array(depth_m), *self.previous_frames)[:self.frame_stack - 1]
        return q

    def epsilon(self, step: int) -> float:
        return 0.0 if self.schedule is None else self.schedule(step)

    def act(self, depth_m: np.ndarray, step: int = 0, guide_action: int | None = None) -> ActionChoice:
        """Choose an action for one (H, W) depth image at environment step ``step``.
        ``guide_action`` (an expert's command) replaces the greedy one, not the random one."""
        q = self._q_values(depth_m)
        eps = self.epsilon(step)
        # draw both numbers every step so the random stream does not depend on the Q-values
        u, rand_action = self.rng.random(), int(self.rng.integers(NUM_ACTIONS))
        if u < eps:
            return self._chose(ActionChoice(rand_action, q, eps, True))
        if guide_action is not None:
            if not (isinstance(guide_action, (int, np.integer)) and 0 <= guide_action < NUM_ACTIONS):
                raise PolicyError(f"guide_action must be an action index in [0, {NUM_ACTIONS}), got {guide_action!r}")
            return self._chose(ActionChoice(int(guide_action), q, eps, False))
        return self._chose(ActionChoice(greedy_action(q), q, eps, False))

    def greedy(self, depth_m: np.ndarray) -> ActionChoice:
        """The greedy action (test protocol); NonFiniteQValues, nothing chosen, when the Q-values are not finite."""
        q = self._q_values(depth_m)
        if not np.isfinite(q).all():
            raise NonFiniteQValues(q)
        return self._chose(ActionChoice(greedy_action(q), q, 0.0, False))
