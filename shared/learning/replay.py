"""Replay memory: a ring of transitions over a ring of depth frames, each frame stored once.

Frames are uint16 millimetres (0 = no return; the wire format too), 38.4 KB for a 160x120 image.
Consecutive transitions of an episode share a frame (the next_obs of one is the obs of the
next), so a transition costs about one frame plus ~40 bytes of indices; a collision ends an
episode without a next frame, a truncation keeps one (it bootstraps). See ``bytes_per_transition``.

Transitions arrive as streams: ``add(stream_id, ...)`` takes an id per actor/episode source, so
interleaved streams from several actors keep their own episode chains. A stream's next
transition reuses the previous next_obs frame when its obs is that same image (checked, so a lost
transition never links the wrong frames) and, where the caller numbers its steps (``step``), when
it is the step right after (a repeated image, an all-zero one beyond the sensor's range, could
otherwise join two transitions across a lost one). The per-stream chain (``next`` links) is what n-step
returns are computed from at sampling time, for any n. It also gives each transition its
previous command (the action of its predecessor in the chain, -1 at an episode's start or after
a broken link), and the ``MAX_ACTION_HISTORY`` commands before that (its predecessor's history,
shifted), for networks that read them (``model.previous_action``, ``model.action_history``), and
the images before each one (its ancestors' obs frames) for networks that read several
(``model.frame_stack``: ``sample(..., frames=K)``).

Frames and transitions are both FIFO rings. The frame ring has some slack over the transition
capacity (one extra frame per truncated episode); when a frame is overwritten, every transition
that referenced it is invalidated at once, so sampling never returns a transition whose frames
were overwritten, and n-step chains stop at the first invalid link (a shorter return with its
own bootstrap, which is still a correct target).

Optional proportional prioritised replay (Schaul et al. 2016) keeps p_i^alpha in a sum tree;
new transitions get the largest priority seen so far; importance weights are normalised by the
batch maximum.

Not thread-safe: a learner that ingests on one thread and samples on another holds a lock.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Hashable

import numpy as np

from shared.config import ALL_COMMANDS_MASK, MAX_ACTION_HISTORY, MAX_FRAME_STACK, NUM_ACTIONS, ReplayConfig
from shared.depth import depth_to_mm
from shared.errors import CogexploreError

PRIORITY_EPS = 1e-3
MAX_OPEN_STREAMS = 1024
"""Episodes whose chain stays open for their next transition; beyond, the longest silent one's chain
ends (an actor that died mid-episode, or ids nobody will continue, must not grow the memory)."""
"""Added to |TD error| so that no valid transition's probability falls to 0."""


class ReplayError(CogexploreError):
    """Bad transition, bad sample request or incompatible replay state."""


@dataclass(frozen=True)
class Batch:
    """A sampled batch; n-step data is kept raw so the update owns gamma.

    ``rewards[i, k]`` is the reward of step k of sample i's chain for k < n_steps[i] (0 after);
    ``terminated[i]`` says the chain ended in a collision (no bootstrap); otherwise the target
    bootstraps from ``next_obs[i]`` with gamma ** n_steps[i]. Frames are uint16 millimetres.
    """

    obs: np.ndarray  # (B, H, W) uint16 mm; (B, K, H, W) sampled with frames=K > 1, most recent first
    action: np.ndarray  # (B,) int64
    rewards: np.ndarray  # (B, n) float32
    n_steps: np.ndarray  # (B,) int64, 1..n
    terminated: np.ndarray  # (B,) bool
    next_obs: np.ndarray  # (B, H, W) or (B, K, H, W) uint16 mm, as obs; zeros where terminated
    previous_action: np.ndarray  # (B, MAX_ACTION_HISTORY) int64 commands before obs, most recent first (-1: none)
    next_previous_action: np.ndarray  # (B, MAX_ACTION_HISTORY) int64 commands before next_obs (the chain's last first)
    weights: np.ndarray  # (B,) float32 importance-sampling weights (ones when uniform)
    indices: np.ndarray  # (B,) int64 transition ids, for update_priorities
    demo: np.ndarray | None = None  # (B,) bool: from a demonstration (shared.learning.demos); None: none are
    expert_action: np.ndarray | None = None  # (B,) int64 labelled command (large-margin loss), -1: none; None: none
    safe_commands: np.ndarray | None = None  # (B,) uint8 safe-set bitmask (safe-set margin loss), 0: none; None: none

    def __len__(self) -> int:
        return int(self.action.shape[0])


def concat_batches(batch: Batch, demo_batch: Batch) -> Batch:
    """``batch`` followed by ``demo_batch``, the latter's samples marked as demonstrations and labelled
    with their own command (the update adds the large-margin loss on them). Both must have the same
    n-step width."""
    if batch.rewards.shape[1] != demo_batch.rewards.shape[1]:
        raise ReplayError(f"n-step widths differ: {batch.rewards.shape[1]} and {demo_batch.rewards.shape[1]}")
    joined = {name: np.concatenate([getattr(batch, name), getattr(demo_batch, name)])
              for name in ("obs", "action", "rewards", "n_steps", "terminated", "next_obs", "previous_action",
                           "next_previous_action", "weights", "indices")}
    demo = np.concatenate([np.zeros(len(batch), bool) if batch.demo is None else batch.demo,
                           np.ones(len(demo_batch), bool)])
    label = np.concatenate([np.full(len(batch), -1, np.int64) if batch.expert_action is None else batch.expert_action,
                            demo_batch.action])
    marks = None if batch.safe_commands is None else \
        np.concatenate([batch.safe_commands, np.zeros(len(demo_batch), np.uint8)])
    return Batch(**joined, demo=demo, expert_action=label, safe_commands=marks)


class SumTree:
    """Binary sum tree over ``size`` leaves (float64), with vectorised batch operations."""

    def __init__(self, size: int):
        self.size = size
        self.leaf0 = 1 << max(0, (size - 1).bit_length())
        self.tree = np.zeros(2 * self.leaf0, dtype=np.float64)

    @property
    def total(self) -> float:
        return float(self.tree[1])

    def get(self, idx: np.ndarray | int) -> np.ndarray:
        return self.tree[self.leaf0 + np.asarray(idx)]

    def set(self, idx: np.ndarray | int, value: np.ndarray | float) -> None:
        pos = np.atleast_1d(np.asarray(idx, dtype=np.int64)) + self.leaf0
        self.tree[pos] = value
        # recompute parents from children (no running deltas, so no float drift)
        pos = np.unique(pos // 2)
        while pos.size and pos[0] >= 1:
            self.tree[pos] = self.tree[2 * pos] + self.tree[2 * pos + 1]
            if pos[0] == 1:
                break
            pos = np.unique(pos // 2)

    def find(self, mass: np.ndarray) -> np.ndarray:
        """Leaf index i in [0, size) with prefix(i) <= mass < prefix(i+1), for each mass in [0, total).
        A mass within rounding of the total may land on a zero leaf (the caller checks priorities)."""
        pos = np.ones(mass.shape, dtype=np.int64)
        mass = mass.astype(np.float64, copy=True)
        while pos[0] < self.leaf0:
            left = 2 * pos
            lv = self.tree[left]
            go_right = mass >= lv
            mass = np.where(go_right, mass - lv, mass)
            pos = np.where(go_right, left + 1, left)
        # The subtractions round: a mass just under the total can walk past the last leaf into the
        # zero padding up to the next power of two, an index no caller's arrays have.
        return np.minimum(pos - self.leaf0, self.size - 1)


class ReplayMemory:
    """Transition ring over a frame ring; see the module docstring."""

    def __init__(self, cfg: ReplayConfig, frame_shape: tuple[int, int], *,
                 frame_capacity: int | None = None, seed: int | None = None):
        if not isinstance(cfg, ReplayConfig):
            raise ReplayError(f"cfg must be a ReplayConfig, got {type(cfg).__name__}")
        if len(frame_shape) != 2 or min(frame_shape) < 1:
            raise ReplayError(f"frame_shape must be (H, W), got {frame_shape}")
        self.cfg = cfg
        self.capacity = cfg.capacity
        self.frame_shape = (int(frame_shape[0]), int(frame_shape[1]))
        # one frame per transition, plus one per truncated episode (or broken stream): 1/8 slack
        self.frame_capacity = int(frame_capacity or self.capacity + self.capacity // 8 + 2)
        if self.frame_capacity < 4:
            raise ReplayError(f"frame_capacity must be >= 4, got {self.frame_capacity}")
        n, f = self.capacity, self.frame_capacity
        try:
            # np.zeros maps untouched pages lazily: a large memory costs RAM only as it fills
            self._frames = np.zeros((f, *self.frame_shape), dtype=np.uint16)
            self._frame_id = np.full(f, -1, dtype=np.int64)  # global id of the frame in each slot
            self._frame_refs = np.full((f, 2), -1, dtype=np.int64)  # transition ids using the frame
            self._tid = np.full(n, -1, dtype=np.int64)
            self._obs_fid = np.full(n, -1, dtype=np.int64)
            self._next_fid = np.full(n, -1, dtype=np.int64)
            self._next_tid = np.full(n, -1, dtype=np.int64)
            self._prev_tid = np.full(n, -1, dtype=np.int64)  # the chain's predecessor (-1: episode start)
            self._reward = np.zeros(n, dtype=np.float32)
            self._action = np.zeros(n, dtype=np.uint8)
            self._expert_action = np.full(n, -1, dtype=np.int8)  # the expert's command in obs, -1: none
            self._safe_commands = np.zeros(n, dtype=np.uint8)  # its safe-set bitmask in obs, 0: none
            self._previous_action = np.full((n, MAX_ACTION_HISTORY), -1, dtype=np.int8)  # most recent first
            self._terminated = np.zeros(n, dtype=bool)
            self._truncated = np.zeros(n, dtype=bool)
            self._valid = np.zeros(n, dtype=bool)
        except MemoryError as exc:  # more than the machine will map: name the setting, not the array
            raise ReplayError(f"replay.capacity = {n} of {self.frame_shape[1]}x{self.frame_shape[0]} images "
                              f"needs more memory than this machine has ({exc})") from None
        self._frames_written = 0
        self._transitions_added = 0
        self._num_valid = 0
        # id -> (last tid, its next frame id, the step that continues it; -1: not numbered)
        self._streams: dict[Hashable, tuple[int, int, int]] = {}
        self._rng = np.random.default_rng(seed)
        self._tree = SumTree(n) if cfg.prioritized else None
        self._max_priority = 1.0

    # ------------------------------------------------------------------ sizes
    def __len__(self) -> int:
        """Transitions that can be sampled now."""
        return self._num_valid

    @property
    def transitions_added(self) -> int:
        return self._transitions_added

    @property
    def nbytes(self) -> int:
        arrays = (self._frames, self._frame_id, self._frame_refs, self._tid, self._obs_fid,
                  self._next_fid, self._next_tid, self._prev_tid, self._reward, self._action, self._expert_action,
                  self._safe_commands,
                  self._previous_action,
                  self._terminated, self._truncated, self._valid)
        tree = self._tree.tree.nbytes if self._tree is not None else 0
        return sum(a.nbytes for a in arrays) + tree

    @property
    def bytes_per_transition(self) -> float:
        """Allocated bytes per transition of capacity (frames, slack and indices included)."""
        return self.nbytes / self.capacity

    # ------------------------------------------------------------------ frames
    def _frame_present(self, fid: int, writes: int = 0) -> bool:
        """Frame ``fid`` is stored now and survives ``writes`` more frame writes."""
        return (fid >= 0 and self._frame_id[fid % self.frame_capacity] == fid
                and fid >= self._frames_written + writes - self.frame_capacity)

    def _write_frame(self, frame_mm: np.ndarray) -> int:
        fid = self._frames_written
        slot = fid % self.frame_capacity
        for tid in self._frame_refs[slot]:
            if tid >= 0:
                self._invalidate(int(tid))
        self._frame_refs[slot] = -1
        self._frames[slot] = frame_mm
        self._frame_id[slot] = fid
        self._frames_written += 1
        return fid

    def _add_ref(self, fid: int, tid: int) -> None:
        refs = self._frame_refs[fid % self.frame_capacity]
        # a frame is used by at most two transitions: as next_obs of one and obs of its successor
        free = np.flatnonzero(refs < 0)
        assert free.size, "a frame gained a third reference"
        refs[free[0]] = tid

    def _invalidate(self, tid: int) -> None:
        slot = tid % self.capacity
        if self._tid[slot] == tid and self._valid[slot]:
            self._valid[slot] = False
            self._num_valid -= 1
            if self._tree is not None:
                self._tree.set(slot, 0.0)

    # ------------------------------------------------------------------ adding
    def add(self, stream_id: Hashable, obs: np.ndarray | None, action: int, reward: float,
            next_obs: np.ndarray | None, terminated: bool, truncated: bool = False, *,
            expert_action: int | None = None, safe_commands: int = 0, step: int | None = None) -> int:
        """Store one transition of stream ``stream_id``; returns its transition id.

        ``obs``/``next_obs`` are (H, W) float metres or uint16 millimetres. ``obs=None`` means
        "the previous next_obs of this stream" (compact streams). A collision (``terminated``)
        has no next frame: pass ``next_obs=None`` (a given one is ignored). A truncated
        transition needs its next_obs; after either, the stream's episode ends. ``expert_action``:
        the expert's command in ``obs`` (a label for the large-margin loss), None: none. ``step``:
        the transition's index in its episode; given, it continues the stream's chain only from the
        transition of ``step - 1`` (None: from the stream's last, its image permitting).
        """
        if not (isinstance(action, (int, np.integer)) and 0 <= int(action) < NUM_ACTIONS):
            raise ReplayError(f"action must be an integer in [0, {NUM_ACTIONS}), got {action!r}")
        if expert_action is not None and not (isinstance(expert_action, (int, np.integer))
                                              and 0 <= int(expert_action) < NUM_ACTIONS):
            raise ReplayError(f"expert_action must be None or an integer in [0, {NUM_ACTIONS}), got {expert_action!r}")
        if not (isinstance(safe_commands, (int, np.integer)) and 0 <= int(safe_commands) <= ALL_COMMANDS_MASK):
            raise ReplayError(f"safe_commands must be a bitmask in [0, {ALL_COMMANDS_MASK}], got {safe_commands!r}")
        if step is not None and not (isinstance(step, (int, np.integer)) and step >= 0):
            raise ReplayError(f"step must be None or an integer >= 0, got {step!r}")
        if not np.isfinite(reward):
            raise ReplayError(f"reward must be finite, got {reward!r}")
        if terminated and truncated:
            raise ReplayError("a transition cannot be both terminated (collision) and truncated")
        if not terminated and next_obs is None:
            raise ReplayError("a non-terminal transition needs next_obs (it bootstraps)")
        next_mm = None if terminated else self._check_frame(next_obs, "next_obs")
        writes = 0 if next_mm is None else 1
        state = self._streams.get(stream_id)
        if state is not None and step is not None and state[2] != step:
            state = None  # not the step after the stream's last: something between them was lost
        obs_fid = -1
        prev_tid = -1
        # reuse the stream's last frame only if it outlives this transition's own frame write
        if obs is None:
            if state is None or not self._frame_present(state[1], writes):
                raise ReplayError(f"stream {stream_id!r}: obs=None needs an open episode whose last "
                                  "frame is still stored (and, with a step, ends at the one before)")
            prev_tid, obs_fid = state[:2]
        else:
            obs_mm = self._check_frame(obs, "obs")
            if state is not None and self._frame_present(state[1], writes) and np.array_equal(
                    self._frames[state[1] % self.frame_capacity], obs_mm):
                prev_tid, obs_fid = state[:2]

        tid = self._transitions_added
        slot = tid % self.capacity
        if self._tid[slot] >= 0:
            self._invalidate(int(self._tid[slot]))  # the ring overwrites the oldest transition
        if obs_fid < 0:
            obs_fid = self._write_frame(obs_mm)
        next_fid = -1 if next_mm is None else self._write_frame(next_mm)
        if not self._frame_present(obs_fid):  # pragma: no cover - frame ring >= 4 slots
            raise ReplayError("frame ring too small for one transition")
        self._tid[slot] = tid
        self._obs_fid[slot] = obs_fid
        self._next_fid[slot] = next_fid
        self._next_tid[slot] = -1
        self._reward[slot] = reward
        self._action[slot] = int(action)
        self._expert_action[slot] = -1 if expert_action is None else int(expert_action)
        self._safe_commands[slot] = int(safe_commands)
        prev_slot = prev_tid % self.capacity
        if prev_tid >= 0 and self._tid[prev_slot] == prev_tid:
            self._previous_action[slot] = self._history_after(prev_slot)
            self._prev_tid[slot] = prev_tid
        else:
            self._previous_action[slot] = -1
            self._prev_tid[slot] = -1
        self._terminated[slot] = bool(terminated)
        self._truncated[slot] = bool(truncated)
        self._valid[slot] = True
        self._num_valid += 1
        self._add_ref(obs_fid, tid)
        if next_fid >= 0:
            self._add_ref(next_fid, tid)
        if prev_tid >= 0 and self._tid[prev_tid % self.capacity] == prev_tid:
            self._next_tid[prev_tid % self.capacity] = tid
        if self._tree is not None:
            self._tree.set(slot, self._max_priority ** self.cfg.priority_alpha)
        self._transitions_added += 1
        self._streams.pop(stream_id, None)
        if not (terminated or truncated):
            # last: the dict runs from the longest silent
            self._streams[stream_id] = (tid, next_fid, -1 if step is None else int(step) + 1)
            while len(self._streams) > MAX_OPEN_STREAMS:
                del self._streams[next(iter(self._streams))]  # an episode silent that long: its chain ends
        return tid

    def remove(self, ids: np.ndarray | Sequence[int]) -> int:
        """Take transitions out of sampling (ids of ``Batch.indices``; ids already overwritten are
        skipped); their chains end there. Returns how many were still stored."""
        before = self._num_valid
        for tid in np.unique(np.asarray(ids, dtype=np.int64)):
            self._invalidate(int(tid))
        return before - self._num_valid

    def stored_rewards(self) -> tuple[np.ndarray, np.ndarray]:
        """(ids, rewards) of every transition that can be sampled now."""
        slots = np.flatnonzero(self._valid)
        return self._tid[slots].copy(), self._reward[slots].copy()

    def end_stream(self, stream_id: Hashable) -> None:
        """Forget a stream's open episode (e.g. its actor left); the next add starts a new chain."""
        self._streams.pop(stream_id, None)

    def _check_frame(self, frame: np.ndarray, name: str) -> np.ndarray:
        try:
            frame_mm = depth_to_mm(frame)
        except ValueError as exc:
            raise ReplayError(f"{name}: {exc}") from None
        if frame_mm.shape != self.frame_shape:
            raise ReplayError(f"{name} has shape {frame_mm.shape}, replay stores {self.frame_shape}")
        return frame_mm

    # ------------------------------------------------------------------ sampling
    def sample(self, batch_size: int, n_step: int = 1, frames: int = 1) -> Batch:
        """Draw ``batch_size`` transitions (with replacement) and their n-step chains. ``frames`` > 1:
        obs and next_obs are stacks of that many images, each followed by the ones before it in its
        episode (the oldest one known repeated where the episode, or its stored chain, began later)."""
        if not (isinstance(batch_size, int) and batch_size >= 1):
            raise ReplayError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        if not (isinstance(n_step, int) and n_step >= 1):
            raise ReplayError(f"n_step must be an integer >= 1, got {n_step!r}")
        _check_frames(frames)
        if self._num_valid == 0:
            raise ReplayError("cannot sample from an empty replay memory")
        if self._tree is not None:
            slots = self._sample_prioritized(batch_size)
            probs = self._tree.get(slots) / self._tree.total
            weights = (self._num_valid * probs) ** (-self.cfg.priority_beta)
            weights = (weights / weights.max()).astype(np.float32)
        else:
            slots = self._sample_uniform(batch_size)
            weights = np.ones(batch_size, dtype=np.float32)
        return self._gather(slots, n_step, weights, frames)

    def labelled(self, frames: int = 1, *, safe_marks: bool = False) -> Batch:
        """Every stored transition the expert labelled (``explore.expert_label_prob``; with ``safe_marks``,
        every one it marked with its safe set, ``explore.safe_label_prob``), oldest first, as a one-step
        Batch whose ``expert_action`` (``safe_commands``) holds them: the states a run's actors visited,
        for measuring how far a network (or anything) agrees with the expert there."""
        _check_frames(frames)
        slots = np.flatnonzero(self._valid & ((self._safe_commands > 0) if safe_marks else (self._expert_action >= 0)))
        if slots.size == 0:
            raise ReplayError("no stored transition carries " + (
                "a safe-set mark (the run trained with explore.safe_label_prob = 0?)" if safe_marks else
                "an expert label (the run trained with explore.expert_label_prob = 0?)"))
        slots = slots[np.argsort(self._tid[slots])]
        return self._gather(slots, 1, np.ones(slots.size, np.float32), frames)

    def _sample_uniform(self, batch_size: int) -> np.ndarray:
        filled = min(self._transitions_added, self.capacity)
        slots = self._rng.integers(0, filled, size=batch_size)
        for _ in range(8):  # invalid slots are rare: redraw them a few times
            bad = ~self._valid[slots]
            if not bad.any():
                return slots
            slots[bad] = self._rng.integers(0, filled, size=int(bad.sum()))
        valid = np.flatnonzero(self._valid[:filled])
        bad = ~self._valid[slots]
        slots[bad] = self._rng.choice(valid, size=int(bad.sum()))
        return slots

    def _sample_prioritized(self, batch_size: int) -> np.ndarray:
        tree = self._tree
        assert tree is not None
        total = tree.total
        # stratified: one draw per equal slice of the total mass
        mass = (np.arange(batch_size) + self._rng.random(batch_size)) * (total / batch_size)
        slots = tree.find(np.minimum(mass, np.nextafter(total, 0)))
        bad = ~self._valid[slots] | (tree.get(slots) <= 0)
        if bad.any():  # float edge cases only: fall back to valid slots by priority
            valid = np.flatnonzero(self._valid)
            p = tree.get(valid)
            slots[bad] = self._rng.choice(valid, size=int(bad.sum()), p=p / p.sum())
        return slots

    def _gather(self, slots: np.ndarray, n_step: int, weights: np.ndarray, frames: int = 1) -> Batch:
        b = slots.shape[0]
        rewards = np.zeros((b, n_step), dtype=np.float32)
        rewards[:, 0] = self._reward[slots]
        n_steps = np.ones(b, dtype=np.int64)
        last = slots.copy()  # slot of each chain's last transition
        alive = ~(self._terminated[slots] | self._truncated[slots])
        for k in range(1, n_step):
            nxt_tid = self._next_tid[last]
            nxt_slot = nxt_tid % self.capacity
            ok = alive & (nxt_tid >= 0) & (self._tid[nxt_slot] == nxt_tid) & self._valid[nxt_slot]
            if not ok.any():
                break
            last = np.where(ok, nxt_slot, last)
            rewards[ok, k] = self._reward[nxt_slot[ok]]
            n_steps[ok] += 1
            alive = ok & ~(self._terminated[nxt_slot] | self._truncated[nxt_slot])
        terminated = self._terminated[last].copy()
        next_fid = self._next_fid[last]
        next_fid = np.where(next_fid >= 0, next_fid, 0)
        if frames == 1:
            obs = self._frames[self._obs_fid[slots] % self.frame_capacity]
            next_obs = self._frames[next_fid % self.frame_capacity]
        else:  # the images before next_obs are the chain's last obs and the ones before it
            obs = self._frames[self._obs_stack(slots, frames) % self.frame_capacity]
            next_obs = self._frames[np.concatenate([next_fid[:, None], self._obs_stack(last, frames - 1)], axis=1)
                                    % self.frame_capacity]
        next_obs[terminated] = 0
        return Batch(obs=obs, action=self._action[slots].astype(np.int64), rewards=rewards,
                     n_steps=n_steps, terminated=terminated, next_obs=next_obs,
                     previous_action=self._previous_action[slots].astype(np.int64),
                     next_previous_action=self._history_after(last),
                     weights=weights,
                     indices=self._tid[slots].copy(),
                     expert_action=self._expert_action[slots].astype(np.int64),
                     safe_commands=self._safe_commands[slots].copy())

    def _obs_stack(self, slots: np.ndarray, frames: int) -> np.ndarray:
        """(B, frames) frame ids: each slot's obs, then its predecessors' obs, most recent first; where
        the chain stops (episode start, an overwritten transition or frame) the oldest id found repeats."""
        fids = np.empty((slots.shape[0], frames), dtype=np.int64)
        fids[:, 0] = self._obs_fid[slots]
        cur = slots
        ok = np.ones(slots.shape[0], dtype=bool)
        for j in range(1, frames):
            prev = self._prev_tid[cur]
            prev_slot = prev % self.capacity
            fid = self._obs_fid[prev_slot]
            ok &= (prev >= 0) & (self._tid[prev_slot] == prev) & (fid >= 0)
            ok &= self._frame_id[fid % self.frame_capacity] == fid
            fids[:, j] = np.where(ok, fid, fids[:, j - 1])
            cur = np.where(ok, prev_slot, cur)
        return fids

    def _history_after(self, slots: np.ndarray | int) -> np.ndarray:
        """The command history (int64, most recent first) of whatever follows ``slots`` in their
        chains: each slot's own command, then its history less the oldest."""
        return np.concatenate([np.asarray(self._action[slots], dtype=np.int64)[..., None],
                               self._previous_action[slots, :-1]], axis=-1)

    def update_priorities(self, indices: np.ndarray, td_errors: np.ndarray) -> None:
        """Set priorities |td| + eps of sampled transitions (ids that were overwritten are skipped)."""
        if self._tree is None:
            return
        indices = np.asarray(indices, dtype=np.int64)
        td = np.abs(np.asarray(td_errors, dtype=np.float64))
        if indices.shape != td.shape:
            raise ReplayError(f"indices {indices.shape} and td_errors {td.shape} differ in shape")
        if not np.all(np.isfinite(td)):
            raise ReplayError("td_errors contain NaN or infinity")
        slots = indices % self.capacity
        live = (self._tid[slots] == indices) & self._valid[slots]
        if not live.any():
            return
        prio = td[live] + PRIORITY_EPS
        self._max_priority = max(self._max_priority, float(prio.max()))
        # duplicates in a batch: the last write wins, as in a sequential update
        self._tree.set(slots[live], prio ** self.cfg.priority_alpha)

    def priorities(self) -> np.ndarray:
        """p_i^alpha per slot (0 for empty/invalid); prioritised replay only."""
        if self._tree is None:
            raise ReplayError("replay is not prioritised")
        return self._tree.get(np.arange(self.capacity)).copy()

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """(arrays, JSON-able metadata) that restore this memory exactly, RNG included."""
        filled_f = min(self._frames_written, self.frame_capacity)
        arrays = {
            "frames": self._frames[:filled_f], "frame_id": self._frame_id,
            "frame_refs": self._frame_refs, "tid": self._tid, "obs_fid": self._obs_fid,
            "next_fid": self._next_fid, "next_tid": self._next_tid, "prev_tid": self._prev_tid,
            "reward": self._reward,
            "action": self._action, "expert_action": self._expert_action,
            "safe_commands": self._safe_commands, "previous_action": self._previous_action,
            "terminated": self._terminated, "truncated": self._truncated,
            "valid": self._valid,
        }
        if self._tree is not None:
            arrays["tree"] = self._tree.tree
        meta = {
            "capacity": self.capacity, "frame_capacity": self.frame_capacity,
            "frame_shape": list(self.frame_shape), "prioritized": self.cfg.prioritized,
            "frames_written": self._frames_written, "transitions_added": self._transitions_added,
            "num_valid": self._num_valid, "max_priority": self._max_priority,
            "streams": [[_stream_key(k), *map(int, v)] for k, v in self._streams.items()],
            "rng": self._rng.bit_generator.state,
        }
        return arrays, meta

    def state_mismatch(self, meta: Any) -> str | None:
        """Why a saved state (``state_dict``'s meta) cannot load into this memory (another shape
        or options), or None when it can."""
        want = {"capacity": self.capacity, "frame_capacity": self.frame_capacity,
                "frame_shape": list(self.frame_shape), "prioritized": self.cfg.prioritized}
        got = {k: meta.get(k) for k in want} if isinstance(meta, dict) else meta
        return None if got == want else f"saved {got}, memory {want}"

    def load_state_dict(self, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
        """Restore from ``state_dict`` output; the memory must have the same shape and options."""
        mismatch = self.state_mismatch(meta)
        if mismatch is not None:
            raise ReplayError(f"replay state does not fit this memory: {mismatch}")
        try:
            frames = arrays["frames"]
            self._frames[: frames.shape[0]] = frames
            for name in ("frame_id", "frame_refs", "tid", "obs_fid", "next_fid", "next_tid",
                         "reward", "action", "terminated", "truncated", "valid"):
                getattr(self, f"_{name}")[...] = arrays[name]
            # replays saved before previous commands were kept read "none"; before their history, the
            # last command only
            previous = np.asarray(arrays.get("previous_action", -1))
            self._previous_action[...] = -1
            if previous.ndim == 1:
                self._previous_action[:, 0] = previous
            else:
                self._previous_action[...] = previous
            # ...and before their predecessors were kept, every image stack starts at its own obs
            self._prev_tid[...] = arrays.get("prev_tid", -1)
            self._expert_action[...] = arrays.get("expert_action", -1)  # before labels: none
            if ((self._expert_action < -1) | (self._expert_action >= NUM_ACTIONS)).any():
                raise ValueError(f"an expert label outside -1..{NUM_ACTIONS - 1}")
            marks = np.asarray(arrays.get("safe_commands", 0))  # before marks: none
            if ((marks < 0) | (marks > ALL_COMMANDS_MASK)).any():
                raise ValueError(f"a safe-set mark outside 0..{ALL_COMMANDS_MASK}")
            self._safe_commands[...] = marks
            if self._tree is not None:
                self._tree.tree[...] = arrays["tree"]
        except (KeyError, ValueError) as exc:
            raise ReplayError(f"replay state is incomplete or malformed: {exc}") from None
        self._frames_written = int(meta["frames_written"])
        self._transitions_added = int(meta["transitions_added"])
        self._num_valid = int(meta["num_valid"])
        self._max_priority = float(meta["max_priority"])
        # saved before steps were kept: a numbered stream's next transition starts a new chain
        self._streams = {_stream_from_key(k): (int(t), int(f), int(s[0]) if s else -1)
                         for k, t, f, *s in meta["streams"]}
        self._rng.bit_generator.state = meta["rng"]


def _check_frames(frames: Any) -> None:
    if not (isinstance(frames, int) and not isinstance(frames, bool) and 1 <= frames <= MAX_FRAME_STACK):
        raise ReplayError(f"frames must be an integer in [1, {MAX_FRAME_STACK}], got {frames!r}")


def _stream_key(k: Hashable) -> Any:
    if isinstance(k, (str, int)) and not isinstance(k, bool):
        return k
    if isinstance(k, tuple) and all(isinstance(x, (str, int)) for x in k):
        return {"tuple": list(k)}
    raise ReplayError(f"stream ids must be str, int or tuples of them to be saved, got {k!r}")


def _stream_from_key(k: Any) -> Hashable:
    return tuple(k["tuple"]) if isinstance(k, dict) else k
