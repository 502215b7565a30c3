"""The authors' supervised obstacle-avoidance model (Tai et al., IROS 2016), rebuilt in simulation.

Three parts, all used by ``cogexplore pretrain`` and ``cogexplore experiment``:

**Expert labels.** The paper's labels came from a human driver; ours from :class:`CommandExpert`,
which may use privileged map information. For a pose it rolls out, on the world's clearance map
(distance to the nearest obstacle), every plan "command ``a`` for one step, then command ``b``
for 1 to ``turn_steps`` steps, then straight" with the environment's exact unicycle kinematics (the
speed table and control period of the env) for ``horizon_steps`` steps. A step is safe when the
robot disc keeps ``robot_radius + contact_margin`` from every obstacle during it and, at its end,
nothing lies in the camera's horizontal view wedge nearer than ``collision_distance +
depth_margin`` (the task's depth collision rule). A plan scores its safe steps (until the first
unsafe one) over the horizon, plus ``space_weight`` times its mean clearance (capped at
``space_cap_m``, over its safe step ends: free space), and command ``a`` the best score of its
plans, plus ``view_weight`` times the free distance straight ahead after its step (over the
sensor's range: toward open space), plus a small preference for straight, then the half turns.
The label is the best command.

**Data.** :func:`generate_dataset` drives the robot through the worlds with the expert mixed with
noise (single random commands and bursts of one repeated random command), so that the data also
covers recoveries from poses the expert would not drive into; every frame the robot acts on is
labelled with the expert's command. Episodes start at a world start pose or at a random free pose
and end at a collision or after ``episode_steps``. On disk (never pickled)::

    <dir>/manifest.json    what was generated, with which settings, and the test split
    <dir>/depth_mm.npy     (N, H, W) uint16 millimetres, 0 = no return
    <dir>/labels.npy       (N,) uint8 expert command (shared.config.ACTION_NAMES)
    <dir>/episodes.npy     (N,) int32 episode id (the split is by episode, never by frame)
    <dir>/worlds.npy       (N,) uint8 index into manifest["worlds"]
    <dir>/poses.npy        (N, 3) float64 robot x, y, yaw (the expert labels exactly these)

**Model.** :func:`train_supervised` trains ``shared.model.SupervisedNet`` (the Q-network's conv
stack + one fc layer to 5 classes, softmax cross-entropy) with Adam, mirrored images as
augmentation (a mirrored image's label is the mirrored command); :func:`save_supervised` writes
it as safetensors in the checkpoint module's style (format ``cogexplore-supervised``, digest,
JSON metadata with the model card) plus a ``.card.json`` sidecar. :func:`init_agent_conv`
copies its conv layers into a DQN agent (the paper's transfer).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F

from shared.config import (
    ACTION_NAMES,
    DEPTH_ENCODINGS,
    NUM_ACTIONS,
    SPEED_TABLES,
    ConfigError,
    EnvConfig,
    SensorConfig,
    mirror_action,
)
from shared.model import (
    ModelError,
    SupervisedNet,
    architecture_fingerprint,
    copy_conv_weights,
    load_tensors,
    mirror_images,
    preprocess_depth,
    reduce_allocator_page_faults,
    resolve_device,
    weights_to_tensors,
)

if TYPE_CHECKING:
    from shared.dqn import DQNAgent
    from shared.world import World

DATA_FORMAT = "cogexplore-sl-data"
MODEL_FORMAT = "cogexplore-supervised"
VERSION = 1
MANIFEST = "manifest.json"
_ARRAYS = ("depth_mm", "labels", "episodes", "worlds", "poses")
MIN_EPISODES = 8
"""Episodes are capped at frames / MIN_EPISODES steps, so that a split by episode has some."""


class SupervisedError(ValueError):
    """Bad settings, a dataset or model file that is missing, partial or does not fit."""


# ---------------------------------------------------------------------------------------------
# The expert
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ExpertConfig:
    """How the expert looks ahead and scores (see the module docstring)."""

    horizon_steps: int = 24
    """Control steps each plan is rolled out for (24 x 12.5 cm = 3 m at the test speeds)."""
    turn_steps: int = 4
    """Longest follow-up: plans hold the second command for 1..turn_steps steps, then go straight
    (0: plans are one command, then straight)."""
    substeps: int = 4
    """Contact samples per step."""
    contact_margin_m: float = 0.05
    """Clearance beyond the robot radius the path must keep."""
    depth_margin_m: float = 0.05
    """Extra distance beyond the collision distance the view wedge must be clear to."""
    wedge_spacing_m: float = 0.04
    """Spacing of the sample points along the edges of the view wedge checked at each step end."""
    space_cap_m: float = 1.0
    """Clearance counted as free space is capped here (an open hall is not preferred to a room)."""
    space_weight: float = 0.1
    """Weight of the mean capped clearance (in units of the whole horizon's safe steps)."""
    view_weight: float = 0.05
    """Weight of the free distance straight ahead after the command's step (over view_range_m):
    of two equally safe commands, the one facing more open space wins."""
    view_range_m: float = 4.0
    """Free distance ahead is measured up to this (the sensor's range)."""
    preference: tuple[float, ...] = (0.0, 0.01, 0.02, 0.01, 0.0)
    """Bonus per command: ties go to straight, then to the half turns."""
    resolution_m: float = 0.05
    """Occupancy-grid cell size the clearance map is built on."""

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, allowed: str) -> None:
            if not ok:
                raise SupervisedError(f"expert {name} = {getattr(self, name)!r} is invalid: {allowed}")

        need(isinstance(self.horizon_steps, int) and 1 <= self.horizon_steps <= 200, "horizon_steps",
             "an integer in [1, 200]")
        need(isinstance(self.turn_steps, int) and 0 <= self.turn_steps < self.horizon_steps, "turn_steps",
             "an integer in [0, horizon_steps)")
        need(isinstance(self.substeps, int) and 1 <= self.substeps <= 50, "substeps", "an integer in [1, 50]")
        for name in ("contact_margin_m", "depth_margin_m", "space_weight", "view_weight"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and math.isfinite(v) and 0 <= v <= 10, name, "a number in [0, 10]")
        need(isinstance(self.space_cap_m, (int, float)) and 0 < self.space_cap_m <= 10, "space_cap_m",
             "metres in (0, 10]")
        need(isinstance(self.view_range_m, (int, float)) and 0 < self.view_range_m <= 50, "view_range_m",
             "metres in (0, 50]")
        need(isinstance(self.wedge_spacing_m, (int, float)) and 0.005 <= self.wedge_spacing_m <= 0.2,
             "wedge_spacing_m", "metres in [0.005, 0.2]")
        need(len(self.preference) == NUM_ACTIONS and all(math.isfinite(float(p)) for p in self.preference),
             "preference", f"{NUM_ACTIONS} finite numbers")
        need(isinstance(self.resolution_m, (int, float)) and 0.01 <= self.resolution_m <= 0.2, "resolution_m",
             "metres in [0.01, 0.2]")


def _unicycle(v: float, w: np.ndarray, t: np.ndarray, x0: np.ndarray, y0: np.ndarray, th0: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Exact arc motion from (x0, y0, th0) after time t at speed v and turn rate w (broadcast)."""
    th = th0 + w * t
    straight = np.abs(w) < 1e-9
    w_safe = np.where(straight, 1.0, w)
    x = np.where(straight, x0 + v * t * np.cos(th0), x0 + v / w_safe * (np.sin(th) - np.sin(th0)))
    y = np.where(straight, y0 + v * t * np.sin(th0), y0 - v / w_safe * (np.cos(th) - np.cos(th0)))
    return x, y, th


class CommandExpert:
    """Labels a robot pose in a world with the command that leads toward the most free space
    the robot can pass (privileged: it reads the map, not the image)."""

    def __init__(self, world: World, env_cfg: EnvConfig | None = None, sensor_cfg: SensorConfig | None = None,
                 cfg: ExpertConfig | None = None):
        from shared.maps import clearance_map, occupancy_grid
        from shared.sensor import column_angles

        self.world = world
        self.env_cfg = env_cfg or EnvConfig()
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self.cfg = cfg or ExpertConfig()
        self.grid = occupancy_grid(world, self.cfg.resolution_m)
        self.clearance = clearance_map(self.grid.occupied, self.grid.resolution_m)
        angular, linear = SPEED_TABLES[self.env_cfg.speed_table]
        self.angular_rps = np.asarray(angular, dtype=np.float64)
        self.linear_mps = float(linear)
        self._plans_relative()
        # Half the horizontal field of view: the outermost column's angle.
        self.half_fov_rad = float(np.abs(column_angles(self.sensor_cfg)).max())
        self._wedge_relative()
        self._prepare_lookup()

    # -- precomputed geometry, relative to a robot at the origin heading +x ------------------
    def _plans_relative(self) -> None:
        c, e = self.cfg, self.env_cfg
        n, s, period = c.horizon_steps, c.substeps, e.control_period_s
        kmax = max(1, c.turn_steps)
        # Plans of first command a: a at step 0, then b for 1..turn_steps steps, then straight
        # (turns, turning around), or b for k steps and its mirror for k steps, then straight
        # (a lateral shift: lining up with a gap).
        follow: list[np.ndarray] = []
        for b in range(NUM_ACTIONS):
            for k in range(1, kmax + 1) if c.turn_steps else [0]:
                r = np.zeros(n)
                r[1:1 + k] = self.angular_rps[b]
                follow.append(r)
                if c.turn_steps and b != NUM_ACTIONS // 2 and 1 + 2 * k <= n:
                    r = r.copy()
                    r[1 + k:1 + 2 * k] = self.angular_rps[NUM_ACTIONS - 1 - b]
                    follow.append(r)
        rates = np.repeat(np.stack(follow)[None], NUM_ACTIONS, axis=0)  # (A, P, N)
        rates[..., 0] = self.angular_rps[:, None]
        shape = rates.shape[:-1]
        x, y, th = np.zeros(shape), np.zeros(shape), np.zeros(shape)
        samples = np.zeros(shape + (n, s, 2))
        ends = np.zeros(shape + (n, 3))
        frac = (np.arange(1, s + 1) / s) * period
        for k in range(n):
            w = rates[..., k]
            sx, sy, _ = _unicycle(self.linear_mps, w[..., None], frac, x[..., None], y[..., None], th[..., None])
            samples[..., k, :, 0], samples[..., k, :, 1] = sx, sy
            x, y, th = _unicycle(self.linear_mps, w, np.float64(period), x, y, th)
            ends[..., k, :] = np.stack([x, y, th], axis=-1)
        self._samples_rel = samples.astype(np.float32)  # (A, P, N, S, 2) contact samples during each step
        self._ends_rel = ends        # (A, P, N, 3) pose at each step's end

    def _wedge_relative(self) -> None:
        c, e, s = self.cfg, self.env_cfg, self.sensor_cfg
        reach = e.collision_distance_m + c.depth_margin_m
        tan = math.tan(self.half_fov_rad)
        spacing = c.wedge_spacing_m
        # The wedge's edges finely (an obstacle enters the view through them as the robot moves)
        # and its inside coarsely (anything wider than the coarse spacing sitting inside).
        n_side = max(2, math.ceil(reach / math.cos(self.half_fov_rad) / spacing) + 1)
        t = np.linspace(0.1, reach, n_side)
        n_far = max(2, math.ceil(2 * reach * tan / spacing) + 1)
        far_lat = np.linspace(-reach * tan, reach * tan, n_far)
        ax_in, lat_in = np.meshgrid(np.arange(0.15, reach, 0.15), np.linspace(-0.66, 0.66, 3), indexing="ij")
        pts = np.concatenate([
            np.stack([t, t * tan], axis=1), np.stack([t, -t * tan], axis=1),
            np.stack([np.full(n_far, reach), far_lat], axis=1),
            np.stack([ax_in.ravel(), (lat_in * ax_in * tan).ravel()], axis=1)])
        pts[:, 0] += s.mount_forward_m  # the camera sits this far ahead of the robot's centre
        self._wedge_pts = pts
        self._wedge_tolerance = 0.5 * spacing + 0.5 * self.grid.resolution_m

    # -- lookups ---------------------------------------------------------------------------
    def _prepare_lookup(self) -> None:
        # The clearance map with a border of zeros: points off the map read 0 without a mask.
        ny, nx = self.grid.shape
        padded = np.zeros((ny + 2, nx + 2), np.float32)
        padded[1:-1, 1:-1] = self.clearance
        self._flat = padded.ravel()
        self._nx, self._ny = nx, ny
        self._inv_res = 1.0 / self.grid.resolution_m
        # View-wedge points at every plan step end, relative to the start pose
        ends, wpts = self._ends_rel, self._wedge_pts
        c, s = np.cos(ends[..., 2])[..., None], np.sin(ends[..., 2])[..., None]
        wx = ends[..., 0, None] + c * wpts[:, 0] - s * wpts[:, 1]
        wy = ends[..., 1, None] + s * wpts[:, 0] + c * wpts[:, 1]
        self._wedge_rel = np.stack([wx, wy], axis=-1).astype(np.float32)  # (A, P, N, W, 2)
        # A ray along each command's heading after its step: (A, R, 2)
        step = 0.5 * self.grid.resolution_m
        self._ray_t = np.arange(step, self.cfg.view_range_m + 1e-9, step)
        first = ends[:, 0, 0]  # (A, 3): every plan of a command shares its first step
        self._ray_rel = np.stack([first[:, 0, None] + np.cos(first[:, 2])[:, None] * self._ray_t,
                                  first[:, 1, None] + np.sin(first[:, 2])[:, None] * self._ray_t],
                                 axis=-1).astype(np.float32)

    def _lookup(self, rel: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
        """Clearance at points given relative to the pose (x, y, yaw) (array (..., 2))."""
        ox, oy = self.grid.origin_xy
        cos, sin = math.cos(yaw), math.sin(yaw)
        k = self._inv_res
        # cell coordinates + 1 (the border), clipped so that anything off the map hits the border
        fx = (rel[..., 0] * (cos * k) - rel[..., 1] * (sin * k)) + ((x - ox) * k + 1.0)
        fy = (rel[..., 0] * (sin * k) + rel[..., 1] * (cos * k)) + ((y - oy) * k + 1.0)
        ix = np.clip(fx, 0, self._nx + 1).astype(np.intp)
        iy = np.clip(fy, 0, self._ny + 1).astype(np.intp)
        return self._flat[iy * (self._nx + 2) + ix]

    def clearance_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Clearance (m) of world points; 0 outside the map."""
        ix, iy = self.grid.world_to_cell(x, y)
        inside = self.grid.contains(ix, iy)
        ny, nx = self.grid.shape
        vals = self.clearance[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]
        return np.where(inside, vals, 0.0)

    def plan_scores(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """(safe steps (A, P) int, plan score (A, P)) of every plan from pose (x, y, yaw), grouped
        by first command A."""
        c, e = self.cfg, self.env_cfg
        contact_ok = (self._lookup(self._samples_rel, x, y, yaw)
                      >= e.robot_radius_m + c.contact_margin_m).all(axis=-1)  # (A, P, N)
        view_ok = (self._lookup(self._wedge_rel, x, y, yaw) > self._wedge_tolerance).all(axis=-1)
        ok = contact_ok & view_ok
        # safe steps: the leading run of safe steps along the horizon
        safe = np.where(ok.all(axis=-1), ok.shape[-1], np.argmin(ok, axis=-1))
        end_clear = np.minimum(self._lookup(self._ends_rel[..., :2], x, y, yaw), c.space_cap_m) / c.space_cap_m
        counted = np.arange(ok.shape[-1]) < safe[..., None]
        space = np.where(safe > 0, (end_clear * counted).sum(-1) / np.maximum(safe, 1), 0.0)
        score = safe / c.horizon_steps + c.space_weight * space
        return safe, score

    def free_ahead(self, x: float, y: float, yaw: float) -> np.ndarray:
        """(5,) free distance (m, up to view_range_m) straight ahead after each command's step,
        for a corridor as wide as the robot plus the contact margin."""
        blocked = self._lookup(self._ray_rel, x, y, yaw) < self.env_cfg.robot_radius_m + self.cfg.contact_margin_m
        first = np.where(blocked.any(axis=1), np.argmax(blocked, axis=1), len(self._ray_t))
        return np.concatenate([[0.0], self._ray_t])[first]

    def scores(self, x: float, y: float, yaw: float) -> np.ndarray:
        """(5,) command scores: the best plan score starting with that command, plus the free
        distance ahead after it (weighted) and the preference."""
        c = self.cfg
        _, plan = self.plan_scores(x, y, yaw)
        view = self.free_ahead(x, y, yaw) / c.view_range_m
        return plan.max(axis=1) + c.view_weight * view + np.asarray(c.preference)

    def label(self, x: float, y: float, yaw: float) -> int:
        """The expert's command (index into ACTION_NAMES) at pose (x, y, yaw)."""
        return int(np.argmax(self.scores(x, y, yaw)))

    def survival_steps(self, x: float, y: float, yaw: float, horizon: int = 60, beam: int = 300,
                       cell_m: float = 0.05, heading_deg: float = 10.0) -> np.ndarray:
        """(5,) the most steps the robot survives from pose (x, y, yaw) after each first command,
        whatever it commands next (up to ``horizon``; 0: the first step already fails), by a beam
        search over command sequences on the clearance map with the same step checks as the
        plans. Poses are merged per (cell_m, heading_deg) cell; at most ``beam`` per first command
        are kept at each depth (a seeded random sample), so it is a lower bound: the beam may miss a
        sequence. Finds trap starts, such as a dead end too narrow to turn around in."""
        c, e = self.cfg, self.env_cfg
        frac = (np.arange(1, c.substeps + 1) / c.substeps) * e.control_period_s
        need = e.robot_radius_m + c.contact_margin_m
        heading_bins = max(1, round(360.0 / heading_deg))
        rng = np.random.default_rng(0)

        def successors(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            """Every command from every pose: (safe next poses, their command, their parent's index)."""
            n = len(poses)
            w = np.tile(self.angular_rps, n)
            x0, y0, t0 = (np.repeat(poses[:, i], NUM_ACTIONS)[:, None] for i in range(3))
            sx, sy, _ = _unicycle(self.linear_mps, w[:, None], frac[None], x0, y0, t0)
            world = np.stack([sx, sy], axis=-1)
            ok = (self._lookup(world, 0.0, 0.0, 0.0) >= need).all(axis=1)  # world points: the identity pose
            x1, y1, t1 = sx[:, -1], sy[:, -1], t0[:, 0] + w * e.control_period_s
            cos, sin = np.cos(t1)[:, None], np.sin(t1)[:, None]
            wx = x1[:, None] + cos * self._wedge_pts[:, 0] - sin * self._wedge_pts[:, 1]
            wy = y1[:, None] + sin * self._wedge_pts[:, 0] + cos * self._wedge_pts[:, 1]
            ok &= (self._lookup(np.stack([wx, wy], axis=-1), 0.0, 0.0, 0.0) > self._wedge_tolerance).all(axis=1)
            command = np.tile(np.arange(NUM_ACTIONS), n)
            parent = np.repeat(np.arange(n), NUM_ACTIONS)
            return np.stack([x1, y1, t1], axis=1)[ok], command[ok], parent[ok]

        survived = np.zeros(NUM_ACTIONS, dtype=int)
        poses, first, _ = successors(np.array([[x, y, yaw]], dtype=np.float64))
        survived[first] = 1
        for depth in range(2, horizon + 1):
            poses, _, parent = successors(poses)
            first = first[parent]
            if len(poses) == 0:
                break
            cell = np.stack([np.floor(poses[:, 0] / cell_m), np.floor(poses[:, 1] / cell_m),
                             np.floor(poses[:, 2] / (2 * math.pi) * heading_bins) % heading_bins,
                             first], axis=1).astype(np.int64)
            _, unique = np.unique(cell, axis=0, return_index=True)
            keep = []
            for a in np.unique(first[unique]):
                idx = unique[first[unique] == a]
                keep.append(idx if len(idx) <= beam else rng.choice(idx, beam, replace=False))
            keep_idx = np.concatenate(keep)
            poses, first = poses[keep_idx], first[keep_idx]
            survived[np.unique(first)] = depth
        return survived

    def best_safe_steps(self, x: float, y: float, yaw: float) -> int:
        """Safe steps of the best plan from this pose (0: every plan fails at once)."""
        safe, _ = self.plan_scores(x, y, yaw)
        return int(safe.max())


class ExpertGuide:
    """Chooses which training episodes the expert drives (``explore.expert_episode_prob``) and
    gives the expert's command in them; None in the others. One per environment."""

    def __init__(self, env: Any, prob: float, seed: int | None = None):
        if not (isinstance(prob, (int, float)) and 0.0 <= prob <= 1.0):
            raise SupervisedError(f"expert episode probability must be in [0, 1], got {prob!r}")
        self.prob = float(prob)
        self.env = env
        self._experts: dict[str, CommandExpert] = {}  # per world, built when first needed
        self.rng = np.random.default_rng(seed)
        self.active = False

    def begin_episode(self) -> bool:
        """Draw whether the episode now starting is expert-driven."""
        self.active = self.prob > 0 and self.rng.random() < self.prob
        return self.active

    def action(self, pose: Sequence[float]) -> int | None:
        """The expert's command at ``pose`` (x, y, yaw) in an expert-driven episode, else None."""
        if not self.active:
            return None
        world = self.env.world  # the world of the episode now playing (env.extra_worlds)
        expert = self._experts.get(world.name)
        if expert is None:
            expert = self._experts[world.name] = CommandExpert(world, self.env.env_config, self.env.sensor_config)
        x, y, yaw = pose
        return expert.label(float(x), float(y), float(yaw))


# ---------------------------------------------------------------------------------------------
# The dataset
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DriveConfig:
    """How the data-collection driver mixes the expert with noise and starts its episodes."""

    episode_steps: int = 150
    """Episode cap (an episode also ends at a collision); at most frames / MIN_EPISODES."""
    noise_prob: float = 0.15
    """Probability that a step takes a uniformly random command instead of the expert's."""
    burst_prob: float = 0.04
    """Probability per step of starting a burst: one random command held for a few steps."""
    burst_steps: tuple[int, int] = (2, 5)
    """Burst length range (inclusive)."""
    random_start_prob: float = 0.75
    """Probability that an episode starts at a random free pose instead of a world start."""
    min_start_clearance_m: float = 0.45
    """A random start keeps this far from every obstacle (and must not read a collision)."""

    def __post_init__(self) -> None:
        def need(ok: bool, name: str, allowed: str) -> None:
            if not ok:
                raise SupervisedError(f"drive {name} = {getattr(self, name)!r} is invalid: {allowed}")

        need(isinstance(self.episode_steps, int) and self.episode_steps >= 1, "episode_steps", "an integer >= 1")
        for name in ("noise_prob", "burst_prob", "random_start_prob"):
            v = getattr(self, name)
            need(isinstance(v, (int, float)) and 0 <= v <= 1, name, "a probability in [0, 1]")
        lo, hi = self.burst_steps
        need(isinstance(lo, int) and isinstance(hi, int) and 1 <= lo <= hi, "burst_steps",
             "two integers 1 <= low <= high")
        need(isinstance(self.min_start_clearance_m, (int, float)) and 0 < self.min_start_clearance_m < 5,
             "min_start_clearance_m", "metres in (0, 5)")


def _jsonable(obj: Any) -> Any:
    return json.loads(json.dumps(obj))


@dataclass
class SupervisedDataset:
    """A generated dataset folder, opened read-only (arrays memory-mapped)."""

    root: Path
    manifest: dict[str, Any]
    depth_mm: np.ndarray
    labels: np.ndarray
    episodes: np.ndarray
    worlds: np.ndarray
    poses: np.ndarray

    @classmethod
    def open(cls, root: str | Path) -> SupervisedDataset:
        """Open and check a dataset folder; SupervisedError if missing, partial or inconsistent."""
        root = Path(root)
        path = root / MANIFEST
        if not path.is_file():
            raise SupervisedError(f"{root} is not a complete dataset: {MANIFEST} is missing")
        try:
            manifest = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise SupervisedError(f"{path} is not valid JSON: {exc}") from None
        if manifest.get("format") != DATA_FORMAT or manifest.get("version") != VERSION:
            raise SupervisedError(f"{path}: not a {DATA_FORMAT} v{VERSION} manifest")
        arrays = {}
        for name in _ARRAYS:
            f = root / f"{name}.npy"
            want = manifest["files"][name]
            try:
                a = np.load(f, mmap_mode="r", allow_pickle=False)
            except (OSError, ValueError) as exc:
                raise SupervisedError(f"{f} cannot be read: {exc}") from None
            if list(a.shape) != want["shape"] or str(a.dtype) != want["dtype"]:
                raise SupervisedError(f"{f} is {a.dtype} {list(a.shape)}, the manifest says "
                                      f"{want['dtype']} {want['shape']}")
            arrays[name] = a
        labels = np.asarray(arrays["labels"])
        if labels.size and int(labels.max()) >= NUM_ACTIONS:
            raise SupervisedError(f"{root}: labels must be in 0..{NUM_ACTIONS - 1}, found {int(labels.max())}")
        return cls(root, manifest, **arrays)

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @property
    def sensor_cfg(self) -> SensorConfig:
        return SensorConfig(**self.manifest["sensor"])

    def split(self) -> tuple[np.ndarray, np.ndarray]:
        """(train, test) frame indices; whole episodes go to one side."""
        test = np.isin(self.episodes, np.asarray(self.manifest["test_episodes"], dtype=self.episodes.dtype))
        return np.flatnonzero(~test), np.flatnonzero(test)

    def label_counts(self, indices: np.ndarray | None = None) -> dict[str, int]:
        labels = self.labels if indices is None else self.labels[indices]
        counts = np.bincount(np.asarray(labels), minlength=NUM_ACTIONS)
        return {name: int(c) for name, c in zip(ACTION_NAMES, counts)}


def dataset_request(worlds: Sequence[str], frames: int, sensor_cfg: SensorConfig, env_cfg: EnvConfig,
                    expert_cfg: ExpertConfig, drive_cfg: DriveConfig, seed: int,
                    test_fraction: float) -> dict[str, Any]:
    """Everything that determines a dataset's content: a reused dataset must match it."""
    return _jsonable({"worlds": list(worlds), "frames": int(frames), "sensor": asdict(sensor_cfg),
                      "env": asdict(env_cfg), "expert": asdict(expert_cfg), "drive": asdict(drive_cfg),
                      "seed": int(seed), "test_fraction": float(test_fraction)})


def _random_free_pose(expert: CommandExpert, rng: np.random.Generator, min_clear: float) -> tuple[float, float, float]:
    cells = np.argwhere(expert.clearance >= min_clear)
    if cells.size == 0:
        raise SupervisedError(f"world {expert.world.name!r} has no point {min_clear} m from every obstacle")
    iy, ix = cells[rng.integers(len(cells))]
    x, y = expert.grid.cell_to_world(ix, iy)
    r = expert.grid.resolution_m
    return float(x + rng.uniform(-r / 2, r / 2)), float(y + rng.uniform(-r / 2, r / 2)), float(rng.uniform(-math.pi, math.pi))


def _start_episode(env: Any, expert: CommandExpert, drive: DriveConfig, rng: np.random.Generator,
                   reset_seed: int) -> np.ndarray:
    """Reset the env at a world start or a random free pose; returns the first image."""
    from shared.env import min_valid_depth

    obs, _ = env.reset(seed=reset_seed, options={"start_index": int(rng.integers(len(env.world.starts)))})
    if rng.random() >= drive.random_start_prob:
        return obs
    for _ in range(100):
        x, y, yaw = _random_free_pose(expert, rng, drive.min_start_clearance_m)
        env.robot.set_pose(x, y, yaw)
        obs = env.camera.capture(env.data)
        if (min_valid_depth(obs) >= env.env_config.collision_distance_m + 0.1
                and expert.best_safe_steps(x, y, yaw) >= 2):
            return obs
    obs, _ = env.reset(seed=reset_seed)  # a crowded world: fall back to a (validated) start pose
    return obs


def generate_dataset(out_dir: str | Path, *, worlds: Sequence[str], frames: int,
                     sensor_cfg: SensorConfig | None = None, env_cfg: EnvConfig | None = None,
                     expert_cfg: ExpertConfig | None = None, drive_cfg: DriveConfig | None = None,
                     seed: int = 0, test_fraction: float = 0.2, progress: bool = True) -> SupervisedDataset:
    """Drive through ``worlds`` (frames split evenly) and write a labelled dataset to ``out_dir``.

    The env's robot and task come from ``env_cfg`` (its ``world`` is replaced per world; the
    speed table is the one the data is collected at). A folder left by an interrupted run is
    replaced; the manifest is written last, so a folder with a manifest is complete.
    """
    from tqdm import tqdm

    from shared.env import ExploreEnv
    from shared.world import load_world

    sensor_cfg = sensor_cfg or SensorConfig()
    env_cfg = env_cfg or EnvConfig(speed_table="test")
    expert_cfg = expert_cfg or ExpertConfig()
    drive_cfg = drive_cfg or DriveConfig()
    worlds = list(worlds)
    if not worlds:
        raise SupervisedError("give at least one world to collect data in")
    if not (isinstance(frames, int) and frames >= 2 * len(worlds)):
        raise SupervisedError(f"frames must be an integer >= {2 * len(worlds)} (two per world), got {frames!r}")
    if not (isinstance(test_fraction, (int, float)) and 0 < test_fraction < 1):
        raise SupervisedError(f"test_fraction must be in (0, 1), got {test_fraction!r}")
    world_objs = [load_world(w) for w in worlds]  # fail early on an unknown world
    out = Path(out_dir)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    h, w = sensor_cfg.height, sensor_cfg.width
    depth = np.lib.format.open_memmap(out / "depth_mm.npy", mode="w+", dtype=np.uint16, shape=(frames, h, w))
    labels = np.zeros(frames, np.uint8)
    episodes = np.zeros(frames, np.int32)
    world_idx = np.zeros(frames, np.uint8)
    poses = np.zeros((frames, 3), np.float64)
    rng = np.random.default_rng(seed)
    started = time.monotonic()
    quota = [frames // len(worlds) + (1 if i < frames % len(worlds) else 0) for i in range(len(worlds))]
    # A split by episode needs several episodes: small datasets get shorter episodes.
    episode_cap = max(1, min(drive_cfg.episode_steps, frames // MIN_EPISODES))
    n = 0
    episode = 0
    episode_worlds: list[int] = []
    episode_lengths: list[int] = []
    taken = np.zeros(NUM_ACTIONS, np.int64)
    with tqdm(total=frames, desc="collect", unit="frame", disable=not progress) as bar:
        for wi, (world, want) in enumerate(zip(world_objs, quota)):
            env = ExploreEnv(env_cfg, sensor_cfg, world=world, max_episode_steps=episode_cap,
                             start_index=None)
            expert = CommandExpert(world, env.env_config, sensor_cfg, expert_cfg)
            end = n + want
            try:
                while n < end:
                    obs = _start_episode(env, expert, drive_cfg, rng, int(rng.integers(2**31)))
                    burst_left, burst_action, length = 0, 0, 0
                    while n < end:
                        x, y, yaw = env.robot.pose()
                        label = expert.label(x, y, yaw)
                        if burst_left > 0:
                            action, burst_left = burst_action, burst_left - 1
                        elif rng.random() < drive_cfg.burst_prob:
                            burst_action = int(rng.integers(NUM_ACTIONS))
                            burst_left = int(rng.integers(drive_cfg.burst_steps[0], drive_cfg.burst_steps[1] + 1)) - 1
                            action = burst_action
                        elif rng.random() < drive_cfg.noise_prob:
                            action = int(rng.integers(NUM_ACTIONS))
                        else:
                            action = label
                        depth[n] = np.rint(np.clip(obs, 0.0, 65.535) * 1000.0).astype(np.uint16)
                        labels[n], episodes[n], world_idx[n] = label, episode, wi
                        poses[n] = (x, y, yaw)
                        taken[action] += 1
                        n += 1
                        length += 1
                        bar.update(1)
                        obs, _, terminated, truncated, _ = env.step(action)
                        if terminated or truncated:
                            break
                    episode_worlds.append(wi)
                    episode_lengths.append(length)
                    episode += 1
            finally:
                env.close()
    depth.flush()
    del depth
    if episode < 2:
        shutil.rmtree(out)
        raise SupervisedError(f"only {episode} episode(s) were collected: a split by episode needs two; "
                              "collect more frames or lower the episode cap")
    # The test split: whole episodes, shuffled, until test_fraction of the frames is covered.
    order = rng.permutation(episode)
    lengths = np.asarray(episode_lengths)
    target = test_fraction * frames
    test_eps: list[int] = []
    covered = 0
    for e in order[:-1]:  # at least one episode stays for training
        if covered >= target:
            break
        test_eps.append(int(e))
        covered += int(lengths[e])
    for name, arr in (("labels", labels), ("episodes", episodes), ("worlds", world_idx), ("poses", poses)):
        np.save(out / f"{name}.npy", arr, allow_pickle=False)
    counts = np.bincount(labels, minlength=NUM_ACTIONS)
    manifest = {
        "format": DATA_FORMAT, "version": VERSION, "created_unix": time.time(),
        "request": dataset_request(worlds, frames, sensor_cfg, env_cfg, expert_cfg, drive_cfg, seed, test_fraction),
        "frames": frames, "episodes": episode, "worlds": worlds, "sensor": asdict(sensor_cfg),
        "speed_table": env_cfg.speed_table,
        "frames_per_world": {wname: int(q) for wname, q in zip(worlds, quota)},
        "episodes_per_world": {wname: int(sum(1 for x in episode_worlds if x == i)) for i, wname in enumerate(worlds)},
        "episode_cap": episode_cap,
        "mean_episode_steps": float(lengths.mean()),
        "label_counts": {name: int(c) for name, c in zip(ACTION_NAMES, counts)},
        "action_counts": {name: int(c) for name, c in zip(ACTION_NAMES, taken)},
        "test_episodes": sorted(test_eps),
        "test_frames": int(covered),
        "seconds": round(time.monotonic() - started, 3),
        "files": {"depth_mm": {"dtype": "uint16", "shape": [frames, h, w]},
                  "labels": {"dtype": "uint8", "shape": [frames]},
                  "episodes": {"dtype": "int32", "shape": [frames]},
                  "worlds": {"dtype": "uint8", "shape": [frames]},
                  "poses": {"dtype": "float64", "shape": [frames, 3]}},
    }
    tmp = out / f".{MANIFEST}.tmp"
    tmp.write_text(json.dumps(manifest, indent=1))
    os.replace(tmp, out / MANIFEST)
    return SupervisedDataset.open(out)


def open_or_generate(out_dir: str | Path, request: Mapping[str, Any], progress: bool = True
                     ) -> tuple[SupervisedDataset, bool]:
    """The dataset in ``out_dir`` if its request matches ``request`` (from :func:`dataset_request`),
    else a freshly generated one. Returns (dataset, reused)."""
    out = Path(out_dir)
    if (out / MANIFEST).is_file():
        try:
            ds = SupervisedDataset.open(out)
            if ds.manifest.get("request") == _jsonable(dict(request)):
                return ds, True
        except SupervisedError:
            pass  # partial or foreign: regenerate below
    r = request
    ds = generate_dataset(out, worlds=r["worlds"], frames=r["frames"], sensor_cfg=SensorConfig(**r["sensor"]),
                          env_cfg=EnvConfig(**r["env"]),
                          expert_cfg=ExpertConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                     for k, v in r["expert"].items()}),
                          drive_cfg=DriveConfig(**{k: tuple(v) if isinstance(v, list) else v
                                                   for k, v in r["drive"].items()}),
                          seed=r["seed"], test_fraction=r["test_fraction"], progress=progress)
    return ds, False


# ---------------------------------------------------------------------------------------------
# Training and evaluation
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TrainSettings:
    """Supervised training hyperparameters."""

    epochs: int = 3
    batch_size: int = 64
    lr: float = 1e-3
    """Adam learning rate."""
    weight_decay: float = 1e-4
    mirror: bool = True
    """Mirror each batch's images with probability 1/2 (labels mirrored too)."""
    class_balance: float = 0.5
    """Cross-entropy class weights (1 / class frequency) ** class_balance: 0 is the plain loss
    (which, with most labels 'straight', can settle on always answering straight), 1 weighs
    every class equally; in between trades overall accuracy for the turns' accuracy."""
    seed: int = 0
    device: str = "auto"
    depth_encoding: str = "metric"
    """The network's depth input encoding (``ModelConfig.depth_encoding``); a DRL run that copies
    these conv layers must use the same one."""

    def __post_init__(self) -> None:
        if self.depth_encoding not in DEPTH_ENCODINGS:
            raise SupervisedError(f"depth_encoding must be one of {', '.join(DEPTH_ENCODINGS)}, "
                                  f"got {self.depth_encoding!r}")
        if not (isinstance(self.epochs, int) and self.epochs >= 1):
            raise SupervisedError(f"epochs must be an integer >= 1, got {self.epochs!r}")
        if not (isinstance(self.batch_size, int) and 1 <= self.batch_size <= 4096):
            raise SupervisedError(f"batch_size must be an integer in [1, 4096], got {self.batch_size!r}")
        if not (isinstance(self.lr, (int, float)) and 0 < self.lr <= 1):
            raise SupervisedError(f"lr must be in (0, 1], got {self.lr!r}")
        if not (isinstance(self.weight_decay, (int, float)) and 0 <= self.weight_decay < 1):
            raise SupervisedError(f"weight_decay must be in [0, 1), got {self.weight_decay!r}")
        if not (isinstance(self.class_balance, (int, float)) and 0 <= self.class_balance <= 1):
            raise SupervisedError(f"class_balance must be in [0, 1], got {self.class_balance!r}")


def confusion_matrix(true: np.ndarray, pred: np.ndarray) -> np.ndarray:
    """(5, 5) counts: row = expert label, column = predicted command."""
    m = np.zeros((NUM_ACTIONS, NUM_ACTIONS), np.int64)
    np.add.at(m, (np.asarray(true, np.int64), np.asarray(pred, np.int64)), 1)
    return m


def classification_metrics(true: np.ndarray, pred: np.ndarray) -> dict[str, Any]:
    """Accuracy, per-class accuracy (recall; None for a class with no example), balanced accuracy
    (mean over the classes present: chance is 1/5 whatever the label distribution) and the
    confusion matrix."""
    cm = confusion_matrix(true, pred)
    support = cm.sum(axis=1)
    per_class = {name: (float(cm[i, i] / support[i]) if support[i] else None) for i, name in enumerate(ACTION_NAMES)}
    present = [v for v in per_class.values() if v is not None]
    total = int(support.sum())
    return {"accuracy": float(np.trace(cm) / total) if total else 0.0,
            "balanced_accuracy": float(np.mean(present)) if present else 0.0,
            "per_class_accuracy": per_class, "support": {n: int(s) for n, s in zip(ACTION_NAMES, support)},
            "confusion_matrix": cm.tolist(), "frames": total}


def predict(net: SupervisedNet, depth_mm: np.ndarray, indices: np.ndarray | None = None,
            batch_size: int = 256) -> np.ndarray:
    """Predicted commands (argmax of the logits, eval mode) for frames of (N, H, W) depth."""
    device = next(net.parameters()).device
    idx = np.arange(len(depth_mm)) if indices is None else np.asarray(indices)
    out = np.empty(len(idx), np.int64)
    was_training = net.training
    net.eval()
    try:
        with torch.inference_mode():
            for i in range(0, len(idx), batch_size):
                chunk = np.sort(idx[i:i + batch_size])  # sorted: sequential reads from the memmap
                order = np.argsort(np.argsort(idx[i:i + batch_size]))
                logits = net(preprocess_depth(np.asarray(depth_mm[chunk]), device))
                out[i:i + len(chunk)] = logits.argmax(dim=1).cpu().numpy()[order]
    finally:
        net.train(was_training)
    return out


def train_supervised(dataset: SupervisedDataset, settings: TrainSettings | None = None, *,
                     progress: bool = True) -> tuple[SupervisedNet, dict[str, Any]]:
    """Train a SupervisedNet on the dataset's train split; returns it (eval mode) and its model
    card (data size, label distribution, test accuracy, per-class accuracy, confusion matrix)."""
    from tqdm import tqdm

    s = settings or TrainSettings()
    reduce_allocator_page_faults()
    device = resolve_device(s.device)
    train_idx, test_idx = dataset.split()
    if len(train_idx) == 0 or len(test_idx) == 0:
        raise SupervisedError(f"{dataset.root}: the split has {len(train_idx)} train and {len(test_idx)} test frames")
    torch.manual_seed(s.seed)
    rng = np.random.default_rng(s.seed)
    net = SupervisedNet(dataset.sensor_cfg, s.depth_encoding).to(device)
    opt = torch.optim.Adam(net.parameters(), lr=s.lr, weight_decay=s.weight_decay)
    labels_all = np.asarray(dataset.labels)
    freq = np.bincount(labels_all[train_idx], minlength=NUM_ACTIONS).astype(np.float64)
    if s.mirror:
        freq = (freq + freq[::-1]) / 2  # what the mirrored batches see on average
    freq = np.maximum(freq, 1.0) / freq.sum()
    weights = (1.0 / (NUM_ACTIONS * freq)) ** s.class_balance
    class_weights = torch.tensor(weights / (weights * freq).sum(), dtype=torch.float32, device=device)
    steps_per_epoch = math.ceil(len(train_idx) / s.batch_size)
    started = time.monotonic()
    history: list[dict[str, float]] = []
    net.train()
    with tqdm(total=s.epochs * steps_per_epoch, desc="train SL", unit="batch", disable=not progress) as bar:
        for epoch in range(s.epochs):
            perm = rng.permutation(train_idx)
            loss_sum, correct, seen = 0.0, 0, 0
            for b in range(steps_per_epoch):
                idx = np.sort(perm[b * s.batch_size:(b + 1) * s.batch_size])
                x = preprocess_depth(np.asarray(dataset.depth_mm[idx]), device)
                y = torch.from_numpy(labels_all[idx].astype(np.int64)).to(device)
                if s.mirror:
                    flip = torch.from_numpy(rng.random(len(idx)) < 0.5).to(device)
                    x = mirror_images(x, flip)
                    y = torch.where(flip, mirror_action(y), y)
                logits = net(x)
                loss = F.cross_entropy(logits, y, weight=class_weights)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                opt.step()
                loss_sum += float(loss.detach()) * len(idx)
                correct += int((logits.detach().argmax(1) == y).sum())
                seen += len(idx)
                bar.update(1)
                bar.set_postfix(epoch=epoch + 1, loss=f"{loss_sum / seen:.3f}", acc=f"{correct / seen:.3f}")
            test = classification_metrics(labels_all[test_idx], predict(net, dataset.depth_mm, test_idx))
            history.append({"epoch": epoch + 1, "train_loss": loss_sum / seen, "train_accuracy": correct / seen,
                            "test_accuracy": test["accuracy"], "test_balanced_accuracy": test["balanced_accuracy"]})
    seconds = time.monotonic() - started
    net.eval()
    test = classification_metrics(labels_all[test_idx], predict(net, dataset.depth_mm, test_idx))
    counts = dataset.label_counts()
    majority = max(counts.values()) / max(1, len(dataset))
    card = {
        "model": "SupervisedNet (ConvTrunk + fc to 5 classes, softmax)",
        "data": {"root": str(dataset.root), "frames": len(dataset), "train_frames": len(train_idx),
                 "test_frames": len(test_idx), "episodes": int(dataset.manifest["episodes"]),
                 "test_episodes": len(dataset.manifest["test_episodes"]), "worlds": dataset.manifest["worlds"],
                 "speed_table": dataset.manifest.get("speed_table"),
                 "label_counts": counts, "majority_class_rate": majority},
        "training": {**asdict(s), "seconds": round(seconds, 2), "class_weights": weights.tolist(),
                     "history": history},
        "test": test,
        "accuracy": test["accuracy"],
        "balanced_accuracy": test["balanced_accuracy"],
        "per_class_accuracy": test["per_class_accuracy"],
        "confusion_matrix": test["confusion_matrix"],
        "classes": list(ACTION_NAMES),
    }
    return net, _jsonable(card)


# ---------------------------------------------------------------------------------------------
# Model files and transfer
# ---------------------------------------------------------------------------------------------


def card_path(model_path: str | Path) -> Path:
    """Where the JSON model card of a model file lives: ``<stem>.card.json`` next to it."""
    p = Path(model_path)
    return p.with_name(p.name.removesuffix(".safetensors") + ".card.json")


def save_supervised(path: str | Path, net: SupervisedNet, card: Mapping[str, Any] | None = None) -> Path:
    """Write the model as safetensors (weights, sensor config, fingerprint, card in the metadata,
    atomically, with a digest) and its card as ``<stem>.card.json``."""
    from shared.checkpoint import save_tensors_file, atomic_write_text

    path = Path(path)
    if path.suffix != ".safetensors":
        raise SupervisedError(f"a supervised model file must end in .safetensors, got {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {"format": MODEL_FORMAT, "version": VERSION, "fingerprint": architecture_fingerprint(net),
            "sensor": asdict(net.sensor_cfg), "depth_encoding": net.trunk.depth_encoding,
            "card": _jsonable(dict(card or {}))}
    save_tensors_file(path, weights_to_tensors(net), meta)
    atomic_write_text(card_path(path), json.dumps(meta["card"], indent=2) + "\n")
    return path


def load_supervised(path: str | Path, device: str | torch.device = "cpu") -> tuple[SupervisedNet, dict[str, Any]]:
    """Rebuild the SupervisedNet of a :func:`save_supervised` file (eval mode) and its metadata."""
    from shared.checkpoint import CheckpointError, load_tensors_file

    path = Path(path)
    try:
        tensors, meta = load_tensors_file(path, MODEL_FORMAT)
    except CheckpointError as exc:
        raise SupervisedError(f"not a supervised model (write one with `cogexplore pretrain`): {exc}") from None
    try:
        net = SupervisedNet(SensorConfig(**meta["sensor"]), meta.get("depth_encoding", "metric"))
    except (ConfigError, ModelError, TypeError, KeyError) as exc:
        raise SupervisedError(f"{path}: sensor or depth-encoding metadata is invalid: {exc}") from None
    if architecture_fingerprint(net) != meta.get("fingerprint"):
        raise SupervisedError(f"{path}: fingerprint {meta.get('fingerprint')} does not match its architecture")
    try:
        load_tensors(net, tensors)
    except ModelError as exc:
        raise SupervisedError(f"{path}: {exc}") from None
    return net.to(resolve_device(device)).eval(), meta


def copy_conv_from_supervised(dst: torch.nn.Module, path: str | Path) -> dict[str, Any]:
    """Copy the conv layers of the supervised model file into ``dst`` (a QNetwork); nothing else
    changes. The conv weights do not depend on the image size, so any sensor size fits."""
    src, meta = load_supervised(path)
    device = next(dst.parameters()).device
    try:
        copy_conv_weights(src.to(device), dst)
    except ModelError as exc:
        raise SupervisedError(f"{path}: cannot copy its conv layers: {exc}") from None
    return meta


def init_agent_conv(agent: DQNAgent, path: str | Path) -> dict[str, Any]:
    """The paper's transfer: the agent's online conv layers from the supervised model, and the
    target network synchronised to the online one. ``pretrained:sl`` names the shipped supervised
    model. Returns the model file's metadata."""
    from shared.checkpoint import CheckpointError, pretrained_path

    try:
        path = pretrained_path(path) or path
    except CheckpointError as exc:
        raise SupervisedError(f"train.init_conv_from: {exc}") from None
    if not Path(path).is_file():
        raise SupervisedError(f"train.init_conv_from = {str(path)!r}: no such file (write one with "
                              "`cogexplore pretrain --out PATH`)")
    meta = copy_conv_from_supervised(agent.online, path)
    agent.sync_target()
    return meta


@dataclass
class PretrainResult:
    """What :func:`pretrain` produced."""

    model_path: Path
    card: dict[str, Any]
    dataset: SupervisedDataset
    data_reused: bool
    seconds: dict[str, float] = field(default_factory=dict)


def pretrain(out: str | Path, *, worlds: Sequence[str], frames: int, sensor_cfg: SensorConfig,
             env_cfg: EnvConfig, data_dir: str | Path | None = None, settings: TrainSettings | None = None,
             expert_cfg: ExpertConfig | None = None, drive_cfg: DriveConfig | None = None, seed: int = 0,
             test_fraction: float = 0.2, progress: bool = True) -> PretrainResult:
    """Generate (or reuse) the data, train, and write the model and its card to ``out``."""
    out = Path(out)
    data_dir = Path(data_dir) if data_dir is not None else out.with_name(out.name.removesuffix(".safetensors") + "-data")
    request = dataset_request(worlds, frames, sensor_cfg, env_cfg, expert_cfg or ExpertConfig(),
                              drive_cfg or DriveConfig(), seed, test_fraction)
    t0 = time.monotonic()
    dataset, reused = open_or_generate(data_dir, request, progress=progress)
    t1 = time.monotonic()
    net, card = train_supervised(dataset, settings or TrainSettings(seed=seed), progress=progress)
    t2 = time.monotonic()
    card["data"]["generated_seconds"] = dataset.manifest.get("seconds")
    card["data"]["reused"] = reused
    card["data"]["request"] = request
    save_supervised(out, net, card)
    return PretrainResult(out, card, dataset, reused, {"data": t1 - t0, "train": t2 - t1})
