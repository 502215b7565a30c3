"""How far ahead of its collisions a policy goes wrong (``cogexplore evaluate --foresight``).

:class:`ForesightProbe` wraps any policy under the test protocol and, at every decision, asks the
privileged map expert (``shared.expert.expert.CommandExpert``, at the protocol's speeds) whether some
command still has a plan that stays safe for ``horizon`` steps from the robot's true pose. For each
episode that ends in a collision, the number of decisions between the last such state and the
collision is how far ahead the policy would have had to see: a collision with a safe plan among its
last few decisions is a mistake the image in front of the robot could show; one whose last safe
state lies many decisions back needed foresight. It only observes: the wrapped policy chooses
every command. The expert's plans are one command, a turn of a few steps, then straight: a lower
bound on what can be survived, so "no safe plan" can be pessimistic in tight places.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from shared.config import EnvConfig, SensorConfig
from shared.evaluation.policies import ExpertsByWorld


class ForesightProbe:
    """``policy_fn`` under the protocol, with the expert's safe-plan check at every decision
    (``reads_pose``: the protocol passes it the robot's pose and world). ``horizon``: the safe steps
    a plan needs (the expert's own horizon at most)."""

    reads_pose = True

    def __init__(self, policy_fn: Any, sensor_cfg: SensorConfig, env_cfg: EnvConfig, horizon: int | None = None):
        from shared.expert.expert import ExpertConfig

        self.policy_fn = policy_fn
        self.reset = getattr(policy_fn, "reset", None)
        self.seed_episode = getattr(policy_fn, "seed_episode", None)  # the protocol seeds what it wraps
        self.name = getattr(policy_fn, "name", "policy")
        self.experts = ExpertsByWorld(sensor_cfg, env_cfg)
        most = ExpertConfig().horizon_steps
        self.horizon = most if horizon is None else horizon
        if not (isinstance(self.horizon, int) and 1 <= self.horizon <= most):
            raise ValueError(f"horizon must be an integer in [1, {most}] (the expert's plans), got {horizon!r}")
        self.episodes: list[list[bool]] = []
        """Per episode, per decision: some command still had a ``horizon``-step safe plan."""

    def __call__(self, depth_m: np.ndarray, info: Mapping[str, Any] | None = None) -> Any:
        expert, pose = self.experts(info, "the foresight probe")
        if info.get("step", 0) == 0 or not self.episodes:
            self.episodes.append([])
        safe, _ = expert.plan_scores(*pose)
        self.episodes[-1].append(bool(safe.max() >= self.horizon))
        inner = self.policy_fn
        return inner(depth_m, info) if getattr(inner, "reads_pose", False) else inner(depth_m)

    def summary(self, collided: Sequence[bool]) -> dict[str, Any]:
        """:func:`foresight_summary` of the episodes observed (``collided``: each one's, in the order played)."""
        return foresight_summary(self.episodes, collided, self.horizon)


def foresight_summary(episodes: Sequence[Sequence[bool]], collided: Sequence[bool], horizon: int) -> dict[str, Any]:
    """Per collision, the decisions from the last state with a safe plan (``episodes``: per episode,
    per decision, whether one existed) to the collision; summarised."""
    if len(collided) != len(episodes):
        raise ValueError(f"{len(collided)} episodes given, {len(episodes)} observed")
    back = [len(flags) - int(np.flatnonzero(flags)[-1]) for flags, hit in zip(episodes, collided)
            if hit and any(flags)]
    hopeless = sum(1 for flags, hit in zip(episodes, collided) if hit and not any(flags))
    quartiles = np.percentile(back, [25, 50, 75]).tolist() if back else [None] * 3
    return {"horizon_steps": horizon, "collisions": int(sum(collided)),
            "without_a_safe_plan_at_any_decision": hopeless,
            "decisions_from_the_last_safe_state": dict(zip(("p25", "median", "p75"), quartiles)),
            "within_3_decisions": sum(1 for b in back if b <= 3),
            "more_than_10_decisions": sum(1 for b in back if b > 10)}
