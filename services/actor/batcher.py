"""Turning an actor's environment steps into TransitionBatch messages (no Zenoh here)."""

from __future__ import annotations

import numpy as np

from shared.depth import depth_to_mm
from shared.wire.messages import MAX_BATCH_STEPS, TransitionBatch


class TransitionBatcher:
    """Collects the steps of one episode and cuts them into batches of at most
    ``batch_steps`` transitions; a batch never spans two episodes (see shared.wire.messages).

    Call ``begin_episode`` after each reset with the first observation, then ``add`` after
    every step; ``add`` returns a batch when one is complete, else None.
    """

    def __init__(self, actor_id: str, batch_steps: int = 16, actor_epoch: int = 0):
        if not 1 <= batch_steps <= MAX_BATCH_STEPS:
            raise ValueError(f"batch_steps must be in [1, {MAX_BATCH_STEPS}], got {batch_steps}")
        self.actor_id = actor_id
        self.actor_epoch = actor_epoch
        self.batch_steps = batch_steps
        self.episode = -1
        self._start_index = 0
        self._obs_mm: np.ndarray | None = None
        self._first_step = 0
        self._steps_in_episode = 0
        self._frames: list[np.ndarray] = []
        self._actions: list[int] = []
        self._rewards: list[float] = []
        self._versions: list[int] = []
        self._poses: list[tuple[float, float, float]] = []
        self._labels: list[int | None] = []
        self._safe: list[int] = []

    def begin_episode(self, first_obs_m: np.ndarray, start_index: int) -> None:
        """Start a new episode (any unsent steps of the previous one are dropped)."""
        self.episode += 1
        self._start_index = int(start_index)
        self._obs_mm = depth_to_mm(first_obs_m)
        self._first_step = 0
        self._steps_in_episode = 0
        self._clear()

    def add(self, action: int, reward: float, next_obs_m: np.ndarray, terminated: bool,
            truncated: bool, policy_version: int, pose: tuple[float, float, float],
            expert_action: int | None = None, safe_commands: int = 0) -> TransitionBatch | None:
        """``expert_action``: the expert's command in the obs this step acted in (None: no label);
        ``safe_commands``: its safe-set bitmask there (0: no mark)."""
        if self._obs_mm is None:
            raise RuntimeError("begin_episode() must be called before add()")
        self._frames.append(self._obs_mm)
        self._actions.append(int(action))
        self._rewards.append(float(reward))
        self._versions.append(int(policy_version))
        self._poses.append(pose)
        self._labels.append(expert_action)
        self._safe.append(int(safe_commands))
        self._steps_in_episode += 1
        next_mm = depth_to_mm(next_obs_m)
        self._obs_mm = next_mm
        if terminated or truncated or len(self._frames) >= self.batch_steps:
            return self._cut(next_mm, terminated, truncated)
        return None

    @property
    def pending(self) -> int:
        """Transitions held but not yet sent."""
        return len(self._frames)

    def flush(self) -> TransitionBatch | None:
        """The transitions held, as a batch cut mid-episode (the last one's next image included), or
        None when none is: what an actor that stops still owes the learner."""
        return self._cut(self._obs_mm, False, False) if self._frames else None

    def _cut(self, next_mm: np.ndarray, terminated: bool, truncated: bool) -> TransitionBatch:
        batch = TransitionBatch.from_steps(
            actor_id=self.actor_id, episode=self.episode, first_step=self._first_step,
            start_index=self._start_index, actor_epoch=self.actor_epoch, depth=np.stack(self._frames),
            next_depth=None if terminated else next_mm, action=self._actions,
            reward=self._rewards, policy_version=self._versions, pose=self._poses,
            terminated=terminated, truncated=truncated and not terminated, expert_action=self._labels,
            safe_commands=self._safe)
        self._first_step = self._steps_in_episode
        self._clear()
        return batch

    def _clear(self) -> None:
        self._frames, self._actions, self._rewards, self._versions, self._poses = [], [], [], [], []
        self._labels, self._safe = [], []
