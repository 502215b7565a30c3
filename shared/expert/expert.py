"""The privileged map expert: the labels of the supervised data, and the guide of expert episodes.

The paper's labels came from a human driver; ours from :class:`CommandExpert`, which may use
privileged map information. For a pose it rolls out, on the world's clearance map (distance to
the nearest obstacle), every plan "command ``a`` for one step, then command ``b`` for 1 to
``turn_steps`` steps, then straight" with the environment's exact unicycle kinematics (the speed
table and control period of the env) for ``horizon_steps`` steps. A step is safe when the robot
disc keeps ``robot_radius + contact_margin`` from every obstacle during it and, at its end,
nothing lies in the camera's horizontal view wedge nearer than ``collision_distance +
depth_margin`` (the task's depth collision rule). A plan scores its safe steps (until the first
unsafe one) over the horizon, plus ``space_weight`` times its mean clearance (capped at
``space_cap_m``, over its safe step ends: free space), and command ``a`` the best score of its
plans, plus ``view_weight`` times the free distance straight ahead after its step (over the
sensor's range: toward open space), plus a small preference for straight, then the half turns.
The label is the best command.

:class:`ExpertGuide` lets the expert drive a share of training episodes
(``explore.expert_episode_prob``); it is a rollout observer (``shared.rollout``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from shared.config import NUM_ACTIONS, SPEED_TABLES, EnvConfig, SensorConfig, commands_mask
from shared.errors import CogexploreError

if TYPE_CHECKING:
    from shared.sim.world import World


CLEARANCE_CAP_M = 8.0
"""The expert's clearance map is exact below at least this (m), and reads at least it beyond:
above any clearance in the shipped worlds (procedural rooms are at most about 10 m across), so
capping the beam's openness here changes nothing there, and above the largest random-start
clearance (``DriveConfig.min_start_clearance_m``, below 5 m)."""


class SupervisedError(CogexploreError):
    """Bad settings, a dataset or model file that is missing, partial or does not fit."""


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
        from shared.sim.maps import clearance_map, occupancy_grid
        from shared.sim.sensor import column_angles

        self.world = world
        self.env_cfg = env_cfg or EnvConfig()
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self.cfg = cfg or ExpertConfig()
        self.grid = occupancy_grid(world, self.cfg.resolution_m)
        # Exact below every clearance the expert compares or scores (contact, view wedge, space_cap_m,
        # openness, random starts): the map's row pass costs one sweep per cell of the largest
        # distance it resolves, hours for a world with an obstacle kilometres from the rest.
        self.clearance_cap_m = max(CLEARANCE_CAP_M, self.cfg.space_cap_m,
                                   self.env_cfg.robot_radius_m + self.cfg.contact_margin_m)
        self.clearance = clearance_map(self.grid.occupied, self.grid.resolution_m, self.clearance_cap_m)
        angular, linear = SPEED_TABLES[self.env_cfg.speed_table]
        self.angular_rps = np.asarray(angular, dtype=np.float64)
        self.linear_mps = float(linear)
        self._last_plans: tuple[tuple[float, float, float], tuple[np.ndarray, np.ndarray]] | None = None
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
        """Clearance (m) of world points; 0 outside the map. Exact below ``clearance_cap_m``;
        a point at least that far from every obstacle reads ``clearance_cap_m`` or more (not its
        distance)."""
        ix, iy = self.grid.world_to_cell(x, y)
        inside = self.grid.contains(ix, iy)
        ny, nx = self.grid.shape
        vals = self.clearance[np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]
        return np.where(inside, vals, 0.0)

    def plan_scores(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
        """(safe steps (A, P) int, plan score (A, P)) of every plan from pose (x, y, yaw), grouped
        by first command A. The last pose's are kept (read-only): the trap charge asks at the pose a
        step reaches, and the next step's safe-set mark asks at the same pose."""
        key = (float(x), float(y), float(yaw))
        if self._last_plans is not None and self._last_plans[0] == key:
            return self._last_plans[1]
        plans = self._plan_scores(*key)
        for array in plans:
            array.flags.writeable = False
        self._last_plans = (key, plans)
        return plans

    def _plan_scores(self, x: float, y: float, yaw: float) -> tuple[np.ndarray, np.ndarray]:
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

    def safe_commands(self, x: float, y: float, yaw: float, steps: int) -> np.ndarray:
        """(5,) bool: whether some plan starting with each command stays safe for ``steps`` steps
        from pose (x, y, yaw), the command's own step included (the plans' shapes only: a lower
        bound, so in a tight place every command can read False)."""
        safe, _ = self.plan_scores(x, y, yaw)
        return safe.max(axis=1) >= steps

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

    def _successors(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every command from every pose (N, 3): (the safe next poses, their command, their parent's
        index), with the plans' step checks (contact samples and the view wedge at the step's end)."""
        c, e = self.cfg, self.env_cfg
        frac = (np.arange(1, c.substeps + 1) / c.substeps) * e.control_period_s
        need = e.robot_radius_m + c.contact_margin_m
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

    @staticmethod
    def _pose_cells(poses: np.ndarray, cell_m: float, heading_bins: int) -> np.ndarray:
        """(N, 3) int64 (x cell, y cell, heading bin) of each pose: poses in one cell are merged."""
        return np.stack([np.floor(poses[:, 0] / cell_m), np.floor(poses[:, 1] / cell_m),
                         np.floor(poses[:, 2] / (2 * math.pi) * heading_bins) % heading_bins], axis=1).astype(np.int64)

    def survival_steps(self, x: float, y: float, yaw: float, horizon: int = 60, beam: int = 300,
                       cell_m: float = 0.05, heading_deg: float = 10.0) -> np.ndarray:
        """(5,) the most steps the robot survives from pose (x, y, yaw) after each first command,
        whatever it commands next (up to ``horizon``; 0: the first step already fails), by a beam
        search over command sequences on the clearance map with the same step checks as the
        plans. Poses are merged per (cell_m, heading_deg) cell; at most ``beam`` per first command
        are kept at each depth (a seeded random sample), so it is a lower bound: the beam may miss a
        sequence. Finds trap starts, such as a dead end too narrow to turn around in."""
        heading_bins = max(1, round(360.0 / heading_deg))
        rng = np.random.default_rng(0)
        survived = np.zeros(NUM_ACTIONS, dtype=int)
        poses, first, _ = self._successors(np.array([[x, y, yaw]], dtype=np.float64))
        survived[first] = 1
        for depth in range(2, horizon + 1):
            poses, _, parent = self._successors(poses)
            first = first[parent]
            if len(poses) == 0:
                break
            cell = np.concatenate([self._pose_cells(poses, cell_m, heading_bins), first[:, None]], axis=1)
            _, unique = np.unique(cell, axis=0, return_index=True)
            keep = []
            for a in np.unique(first[unique]):
                idx = unique[first[unique] == a]
                keep.append(idx if len(idx) <= beam else rng.choice(idx, beam, replace=False))
            keep_idx = np.concatenate(keep)
            poses, first = poses[keep_idx], first[keep_idx]
            survived[np.unique(first)] = depth
        return survived

    def has_way_out(self, x: float, y: float, yaw: float, steps: int, beam: int = 48,
                    cell_m: float = 0.05, heading_deg: float = 10.0) -> bool:
        """Whether some command sequence from pose (x, y, yaw) stays safe for ``steps`` steps (the
        plans' step checks). First the plans (one command, a turn, straight: enough in open space),
        then, where none is safe that long, a beam search that keeps the ``beam`` most open poses
        (clearance at the pose and 0.5 m ahead, each capped at ``clearance_cap_m``) at each depth:
        deterministic, and a lower bound (the beam may miss a sequence), so a tight place can count
        as one with no way out."""
        safe, _ = self.plan_scores(x, y, yaw)
        if safe.max() >= steps:
            return True
        heading_bins = max(1, round(360.0 / heading_deg))
        poses = np.array([[x, y, yaw]], dtype=np.float64)
        for _ in range(steps):
            poses, _, _ = self._successors(poses)
            if len(poses) == 0:
                return False
            if len(poses) > beam:
                _, unique = np.unique(self._pose_cells(poses, cell_m, heading_bins), axis=0, return_index=True)
                poses = poses[unique]
            if len(poses) > beam:
                ahead = poses[:, :2] + 0.5 * np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])], axis=1)
                # capped: beyond the cap the map is not exact (more open than that is open enough)
                cap = self.clearance_cap_m
                openness = (np.minimum(self._lookup(poses[:, :2], 0.0, 0.0, 0.0), cap)
                            + np.minimum(self._lookup(ahead, 0.0, 0.0, 0.0), cap))
                poses = poses[np.argsort(-openness, kind="stable")[:beam]]
        return True

    def best_safe_steps(self, x: float, y: float, yaw: float) -> int:
        """Safe steps of the best plan from this pose (0: every plan fails at once)."""
        safe, _ = self.plan_scores(x, y, yaw)
        return int(safe.max())


class ExpertGuide:
    """Chooses which training episodes the expert drives (``explore.expert_episode_prob``) and
    gives the expert's command in them; None in the others. Also draws which steps the expert
    labels as a teacher (``explore.expert_label_prob``, :meth:`teacher_label`). One per environment."""

    def __init__(self, env: Any, prob: float, seed: int | None = None, *, label_prob: float = 0.0,
                 safe_prob: float = 0.0):
        for name, p in (("expert episode probability", prob), ("expert label probability", label_prob),
                        ("safe-set label probability", safe_prob)):
            if not (isinstance(p, (int, float)) and 0.0 <= p <= 1.0):
                raise SupervisedError(f"{name} must be in [0, 1], got {p!r}")
        self.prob = float(prob)
        self.label_prob = float(label_prob)
        self.env = env
        self.rng = np.random.default_rng(seed)
        # its own stream: labelling on or off leaves the episodes' draws as they were
        self.label_rng = np.random.default_rng(None if seed is None else seed + 1)
        self.safe_prob = float(safe_prob)
        self.safe_rng = np.random.default_rng(None if seed is None else seed + 2)
        self.active = False

    def begin_episode(self, episode: Any = None) -> bool:
        """Draw whether the episode now starting is expert-driven (a rollout observer's hook)."""
        self.active = self.prob > 0 and self.rng.random() < self.prob
        return self.active

    def action(self, pose: Sequence[float]) -> int | None:
        """The expert's command at ``pose`` (x, y, yaw) in an expert-driven episode, else None."""
        return self._command(pose) if self.active else None

    def teacher_label(self, pose: Sequence[float]) -> int | None:
        """The expert's command at ``pose``, the pose a decision was taken at, for a ``label_prob``
        share of the calls (None for the others)."""
        if self.label_prob <= 0 or self.label_rng.random() >= self.label_prob:
            return None
        return self._command(pose)

    def safe_label(self, pose: Sequence[float]) -> int:
        """For a ``safe_prob`` share of the calls, the bitmask (bit a: command a) of the commands with
        a way out from ``pose``, the pose a decision was taken at (``CommandExpert.safe_commands``
        over ``env.trap_horizon_steps``); 0 for the other calls and where every command or none has
        one (nothing to tell apart)."""
        if self.safe_prob <= 0 or self.safe_rng.random() >= self.safe_prob:
            return 0
        x, y, yaw = pose
        safe = self.env.map_expert().safe_commands(float(x), float(y), float(yaw),
                                                    self.env.env_config.trap_horizon_steps)
        if safe.all() or not safe.any():
            return 0
        return commands_mask(safe)

    def _command(self, pose: Sequence[float]) -> int:
        x, y, yaw = pose  # the expert of the world now playing (env.extra_worlds), one per world
        return self.env.map_expert().label(float(x), float(y), float(yaw))
