"""Planner demonstrations: escapes a privileged planner finds in the simulator, kept as transitions.

Some starts need a manoeuvre that epsilon-greedy exploration practically never finds. Start 6 of
``paper-indoor`` faces a 1.4 m wide dead end: at the protocol's test speeds the robot survives only
if it turns about some 2.8 m before the end wall, on a path that clears the 0.55 m depth rule by
about a centimetre (at the faster training speeds no escape exists at all, ``cogexplore worlds starts
paper-indoor --speed train``). No training run learned it (MODEL_CARD.md, Limits).

**The planner** (:func:`plan_commands`) searches the environment itself, not a map: from a start
pose it tries every command from every kept pose (:meth:`ExploreEnv.snapshot` / ``restore``), so
it applies the env's exact collision rule, image by image. It is a beam search over command
sequences; poses are merged per (``cell_m``, ``heading_deg``) cell, and per cell (and in the
beam) the sequence with the fewest command switches wins, then the one with the most depth
margin: the plans it keeps are smooth (start 6: a half-right, six straights, a half-left, five
lefts, straight out), which a network can imitate. Of the sequences that survive longest, the one ending farthest from
the start is the demonstration.

**The demonstration** (:func:`record_demonstration`) replays the commands in the env from the
start and keeps every image (uint16 mm), command and reward: a chain of transitions. The learner
keeps them in a separate replay memory that is never overwritten and adds ``dqn.demo_batch`` of
them to every batch, with the large-margin loss of DQfD (Hester et al., 2018) on top of the TD
loss, so that the demonstrated command's Q-value beats every other by ``dqn.demo_margin`` in those
images (shared.learning.dqn). The TD targets of a test-speed demonstration bootstrap like any transition's;
only its images and rewards come from the planner.

**On disk** (never pickled): an ``.npz`` of plain arrays (``allow_pickle=False``), ``meta`` a JSON
document in a uint8 array, and per demonstration ``i``: ``depth_mm.i`` (T+1, H, W) uint16 (the
image before each step and after the last), ``actions.i`` (T,) int64, ``rewards.i`` (T,) float32.
"""

from __future__ import annotations

import json
import math
import zipfile
import zlib
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.config import NUM_ACTIONS, ReplayConfig
from shared.depth import depth_to_mm
from shared.errors import CogexploreError
from shared.files import write_atomically
from shared.jsontext import parse_json
from shared.rollout import Rollout, Step

if TYPE_CHECKING:
    from shared.learning.replay import ReplayMemory
    from shared.sim.env import ExploreEnv

DEMO_FORMAT = "cogexplore-demos"
VERSION = 1
SHIPPED_DEMOS = Path(__file__).resolve().parents[1] / "pretrained" / "paper-indoor-demos.npz"
"""``pretrained:demos``: the shipped demonstrations (``paper-indoor``, fast-40x30's sensor; see
shared/pretrained/MODEL_CARD.md)."""
MAX_DEMO_FILE_BYTES = 4 * 2**30
"""The most a demonstration file may unpack to (some 100 000 images of 160x120): a damaged or
hostile archive must not take the learner's memory."""


class DemoError(CogexploreError):
    """A demonstration file that is missing, damaged or does not fit; bad planner settings."""


@dataclass(frozen=True)
class StartDraw:
    """A start drawn around a named pose as a jittered protocol draws its episodes' starts
    (``ExploreEnv.reset``'s ``start_jitter``; ``shared.evaluation.protocol.episode_seed``), so a
    plan can begin where a robust test episode, or a training episode, begins."""

    seed: int
    """The env's reset seed (for a test episode's draw: ``episode_seed(seed, start, episode)``)."""
    jitter_m: float
    """Up to this many metres in x and y."""
    jitter_deg: float
    """Up to this many degrees of heading."""


@dataclass(frozen=True)
class Plan:
    """The planner's command sequence from one start and what it achieves in the env."""

    world: str
    start_index: int
    speed_table: str
    actions: tuple[int, ...]
    survived_steps: int
    """Steps the sequence survives (``len(actions)``); below the horizon when every sequence the
    beam kept collided sooner."""
    horizon: int
    switches: int
    """Command changes along the sequence."""
    min_margin_m: float
    """Smallest (minimum image depth - collision distance) along the sequence."""
    distance_m: float
    """Distance from the start at the end."""
    start_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The pose it started from (x m, y m, yaw rad): the start's own, or a draw around it."""
    draw: StartDraw | None = None
    """The draw around the start it began from (None: the exact start pose)."""


@dataclass(frozen=True)
class Demonstration:
    """One recorded demonstration: images, commands and rewards along a planner's sequence."""

    world: str
    start_index: int
    speed_table: str
    depth_mm: np.ndarray  # (T+1, H, W) uint16
    actions: np.ndarray  # (T,) int64
    rewards: np.ndarray  # (T,) float32
    terminated: bool
    """The last step collided (a planner's demonstration normally survives: then the chain's last
    transition is a truncation, and its target bootstraps)."""

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    def meta(self) -> dict[str, Any]:
        return {"world": self.world, "start_index": self.start_index, "speed_table": self.speed_table,
                "steps": len(self), "terminated": self.terminated,
                "frame_shape": list(self.depth_mm.shape[1:])}


def _reset_kwargs(start_index: int, draw: StartDraw | None) -> dict[str, Any]:
    """``env.reset``'s arguments for start ``start_index``, exact or at ``draw`` (the jitter is
    always explicit: an env built with a training jitter must not move an exact start)."""
    if draw is None:
        return {"options": {"start_index": start_index, "start_jitter": None}}
    return {"seed": draw.seed, "options": {"start_index": start_index,
                                           "start_jitter": (draw.jitter_m, draw.jitter_deg)}}


def plan_commands(env: ExploreEnv, start_index: int, *, horizon: int = 80, beam: int = 2000,
                  cell_m: float = 0.05, heading_deg: float = 10.0, draw: StartDraw | None = None,
                  progress: Callable[[int, int], None] | None = None) -> Plan:
    """Beam search in ``env`` (its world, speed table and sensor) for the demonstration from
    start ``start_index`` (0-based), or from ``draw`` around it: see the module docstring.
    ``progress(depth, kept)`` is called after each depth. The env is left at the end of some
    explored sequence: reset it before use."""
    if not (isinstance(horizon, int) and 1 <= horizon <= 1000):
        raise DemoError(f"horizon must be an integer in [1, 1000], got {horizon!r}")
    if horizon > env.env_config.max_episode_steps:  # the search would step on from nodes the cap ended
        raise DemoError(f"horizon {horizon} exceeds the env's step cap ({env.env_config.max_episode_steps}): "
                        "build the env with env.max_episode_steps at least the horizon")
    if not (isinstance(beam, int) and 1 <= beam <= 100_000):
        raise DemoError(f"beam must be an integer in [1, 100000], got {beam!r}")
    if not (0 < cell_m <= 1.0 and 0 < heading_deg <= 180):
        raise DemoError(f"cell_m must be in (0, 1] and heading_deg in (0, 180], got {cell_m}, {heading_deg}")
    if not (isinstance(start_index, int) and 0 <= start_index < len(env.main_world.starts)):
        raise DemoError(f"start index {start_index!r} out of range: {env.main_world.name!r} has "
                        f"{len(env.main_world.starts)} starts")
    threshold = env.env_config.collision_distance_m
    heading_bins = max(1, round(360.0 / heading_deg))
    _, first_info = env.reset(**_reset_kwargs(start_index, draw))
    start_pose = tuple(float(v) for v in first_info["pose"])
    # node: (snapshot, actions, switches, min margin, distance from start)
    frontier: list[tuple[Any, list[int], int, float, float]] = [(env.snapshot(), [], 0, math.inf, 0.0)]
    for depth in range(1, horizon + 1):
        cells: dict[tuple[int, int, int], tuple[Any, list[int], int, float, float]] = {}
        for snap, actions, switches, margin, _ in frontier:
            for a in range(NUM_ACTIONS):
                env.restore(snap)
                _, _, terminated, _, info = env.step(a)
                if terminated:
                    continue
                x, y, yaw = info["pose"]
                child = (env.snapshot(), actions + [a], switches + int(bool(actions) and actions[-1] != a),
                         min(margin, info["min_depth_m"] - threshold), info["distance_from_start_m"])
                key = (math.floor(x / cell_m), math.floor(y / cell_m),
                       math.floor((yaw / (2 * math.pi)) * heading_bins) % heading_bins)
                held = cells.get(key)
                if held is None or (child[2], -child[3]) < (held[2], -held[3]):
                    cells[key] = child
        if not cells:
            break
        frontier = sorted(cells.values(), key=lambda n: (n[2], -n[3]))[:beam]
        if progress is not None:
            progress(depth, len(frontier))
    # The deepest survivors: farthest from the start (in half-metre bands), then the smoothest.
    best = min(frontier, key=lambda n: (-math.floor(n[4] / 0.5), n[2], -n[3]))
    _, actions, switches, margin, distance = best
    return Plan(env.main_world.name, start_index, env.env_config.speed_table, tuple(actions), len(actions),
                horizon, switches, float(margin) if actions else 0.0, float(distance), start_pose, draw)


def record_demonstration(env: ExploreEnv, start_index: int, actions: Sequence[int],
                         draw: StartDraw | None = None) -> Demonstration:
    """Play ``actions`` in ``env`` from start ``start_index`` (or from ``draw`` around it) and keep
    its images, commands and rewards (it stops at a collision)."""
    if len(actions) == 0:
        raise DemoError("a demonstration needs at least one command")
    if not all(isinstance(a, (int, np.integer)) and 0 <= int(a) < NUM_ACTIONS for a in actions):
        raise DemoError(f"commands must be integers in [0, {NUM_ACTIONS}), got {list(actions)!r}")
    steps: list[Step] = []
    loop = Rollout(env, lambda _obs, _info, n: int(actions[n]), [SimpleNamespace(on_step=steps.append)],
                   max_steps=len(actions))
    episode = loop.run_episode(**_reset_kwargs(start_index, draw))
    frames = [depth_to_mm(episode.first_obs)] + [depth_to_mm(s.next_obs) for s in steps]
    return Demonstration(env.main_world.name, int(start_index), env.env_config.speed_table,
                         np.stack(frames), np.asarray([s.action for s in steps], np.int64),
                         np.asarray([s.reward for s in steps], np.float32), bool(episode.terminated))


# ---------------------------------------------------------------------------------------------
# Files
# ---------------------------------------------------------------------------------------------


def save_demonstrations(path: str | Path, demos: Sequence[Demonstration], extra: dict[str, Any] | None = None
                        ) -> Path:
    """Write demonstrations to ``path`` (.npz), atomically. ``extra``: more JSON metadata (the plans)."""
    if not demos:
        raise DemoError("nothing to save")
    path = Path(path)
    if path.suffix != ".npz":
        raise DemoError(f"demonstration files end in .npz, got {path}")
    meta = {"format": DEMO_FORMAT, "version": VERSION, "demos": [d.meta() for d in demos], **(extra or {})}
    arrays: dict[str, np.ndarray] = {"meta": np.frombuffer(json.dumps(meta).encode(), np.uint8)}
    for i, d in enumerate(demos):
        arrays[f"depth_mm.{i}"], arrays[f"actions.{i}"], arrays[f"rewards.{i}"] = d.depth_mm, d.actions, d.rewards
    path.parent.mkdir(parents=True, exist_ok=True)
    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:  # a file object: savez would add ".npz" to a name
            np.savez_compressed(fh, **arrays)

    return write_atomically(path, write)


def load_demonstrations(path: str | Path, frame_shape: tuple[int, int] | None = None) -> list[Demonstration]:
    """Read and check a demonstration file (or ``pretrained:demos``); ``frame_shape`` (H, W): the
    images must have it."""
    path = SHIPPED_DEMOS if str(path) == "pretrained:demos" else Path(path)
    try:
        # mmap: a lone .npy array (no archive) is mapped, not read whatever its size
        npz = np.load(path, mmap_mode="r", allow_pickle=False)
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise ValueError("one array, not an .npz archive")
        with npz:
            unpacked = sum(info.file_size for info in npz.zip.infolist())
            if unpacked > MAX_DEMO_FILE_BYTES:
                raise ValueError(f"it unpacks to {unpacked} bytes, more than {MAX_DEMO_FILE_BYTES}")
            arrays = {k: npz[k] for k in npz.files}
        plain = [k for k, v in arrays.items() if not isinstance(v, np.ndarray)]
        if plain:  # np.load gives a member that is no .npy array as its bytes
            raise ValueError(f"{plain[0]!r} is not an array")
    except FileNotFoundError:
        raise DemoError(f"{path}: no such demonstration file") from None
    # not an npz, damaged (zip or deflate data), object arrays, or an array header claiming more than it holds
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, MemoryError) as exc:
        raise DemoError(f"{path} is not a readable demonstration file: {exc}") from None
    if "meta" not in arrays:
        raise DemoError(f"{path}: no metadata: not a demonstration file")
    meta = parse_json(arrays["meta"].tobytes(), f"{path}: its metadata", DemoError)
    entries = meta.get("demos") if isinstance(meta, dict) else None
    if not (isinstance(entries, list) and all(isinstance(e, dict) for e in entries)):
        raise DemoError(f"{path}: damaged metadata: no list of demonstrations")
    if meta.get("format") != DEMO_FORMAT or meta.get("version") != VERSION:
        raise DemoError(f"{path}: format {meta.get('format')!r} version {meta.get('version')!r}, "
                        f"expected {DEMO_FORMAT!r} version {VERSION}")
    demos = []
    for i, entry in enumerate(entries):
        try:
            depth_mm, actions, rewards = arrays[f"depth_mm.{i}"], arrays[f"actions.{i}"], arrays[f"rewards.{i}"]
            terminated = entry["terminated"]
            world, start, speed = str(entry["world"]), int(entry["start_index"]), str(entry["speed_table"])
        except (KeyError, TypeError, ValueError, OverflowError) as exc:  # overflow: a start_index of 1e999
            raise DemoError(f"{path}: demonstration {i} is incomplete ({exc})") from None
        problem = None
        if depth_mm.dtype != np.uint16 or depth_mm.ndim != 3:
            problem = f"depth_mm is {depth_mm.dtype} {depth_mm.shape}, expected uint16 (T+1, H, W)"
        elif actions.dtype != np.int64 or actions.ndim != 1 or len(actions) < 1 or len(depth_mm) != len(actions) + 1:
            problem = f"actions are {actions.dtype} {actions.shape} for {len(depth_mm)} images, expected int64 (T,)"
        elif ((actions < 0) | (actions >= NUM_ACTIONS)).any():
            problem = f"a command is outside [0, {NUM_ACTIONS})"
        elif rewards.dtype != np.float32 or rewards.shape != actions.shape or not np.isfinite(rewards).all():
            problem = f"rewards are {rewards.dtype} {rewards.shape}, expected finite float32 {actions.shape}"
        elif frame_shape is not None and tuple(depth_mm.shape[1:]) != tuple(frame_shape):
            problem = f"images are {tuple(depth_mm.shape[1:])}, the run's sensor gives {tuple(frame_shape)}"
        elif not isinstance(terminated, bool):
            problem = f"terminated is {terminated!r}, expected true or false"
        if problem:
            raise DemoError(f"{path}: demonstration {i}: {problem}")
        demos.append(Demonstration(world, start, speed, depth_mm, actions, rewards, terminated))
    if not demos:
        raise DemoError(f"{path} holds no demonstration")
    return demos


def demo_replay(demos: Sequence[Demonstration], frame_shape: tuple[int, int], seed: int = 0) -> ReplayMemory:
    """A replay memory holding exactly these demonstrations' transitions (one chain each), for
    the learner's demonstration share of every batch."""
    from shared.learning.replay import ReplayMemory

    total = sum(len(d) for d in demos)
    # every frame of every chain stays: one per transition and one after each chain's last
    memory = ReplayMemory(ReplayConfig(capacity=max(2, total)), frame_shape, frame_capacity=total + len(demos) + 4,
                          seed=seed)
    for i, d in enumerate(demos):
        last = len(d) - 1
        for t in range(len(d)):
            end = t == last
            memory.add(("demo", i), d.depth_mm[t], int(d.actions[t]), float(d.rewards[t]),
                       None if (end and d.terminated) else d.depth_mm[t + 1],
                       terminated=end and d.terminated, truncated=end and not d.terminated)
    return memory


def plan_summary(plan: Plan) -> dict[str, Any]:
    """A plan as JSON-able data."""
    out = asdict(plan)
    out["actions"] = list(plan.actions)
    return out
