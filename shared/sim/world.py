"""Indoor worlds: static scenes of walls, cylinders and clutter, with start poses.

A :class:`World` is the static scene as MJCF text (no robot; ``shared.sim.robot`` adds it)
plus its start poses and floor extent. ``load_world`` resolves a name:

- built-in names (``paper-indoor``, ``corridor``, ``box-room``; see ``BUILTIN_WORLDS``),
- ``procedural:<seed>``: rooms off a corridor plus clutter, deterministic in the seed,
- a path to a user MJCF file whose start poses are sites named ``start_*``.

Every static geom except the floor plane (named ``floor``) is an obstacle. Every start of
every world passes :func:`validate_starts` (one implementation for all kinds).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from shared.config import (PROCEDURAL_PREFIX, ROBOT_FIELDS, SPEED_TABLES, EnvConfig, SensorConfig, is_finite_number,
                           is_procedural_seed)
from shared.errors import CogexploreError
from shared.sim import maps
from shared.sim.robot import (FLOOR_GEOM, ROBOT_BODY, ROBOT_CONTACT_BITS, ROBOT_GEOM_GROUP, ROBOT_HEIGHT_M, Robot,
                              build_model)
from shared.sim.sensor import DepthCamera
from shared.sim.world_cache import cached_world

log = logging.getLogger(__name__)


def _log_mujoco_warning(text: str) -> None:
    # MuJoCo's own handler prints the warning and appends it to MUJOCO_LOG.TXT in whatever folder the
    # process was started from (a user's home, a checkout): the process's log is where it belongs.
    log.warning("MuJoCo: %s", text)


mujoco.set_mju_user_warning(_log_mujoco_warning)

# 2 m: taller than any ray of the 0.35 m high camera climbs within its 4 m range, so every
# obstacle fills its image columns from the floor up (the depth camera's fast path relies on it).
WALL_HEIGHT_M = 2.0
OBSTACLE_RGBA = (0.75, 0.72, 0.65, 1.0)

MIN_START_CLEARANCE_M = 0.1
"""A start's robot disc must be at least this far from every obstacle."""
MIN_FREE_AHEAD_M = 1.0
"""Free depth straight ahead of a start, across the robot's width."""
START_VIEW_MARGIN_M = 0.1
"""The start's depth image must read at least collision_distance_m plus this everywhere."""
NUM_STARTS = 12  # the paper's 12 start points


class WorldError(CogexploreError):
    """A world cannot be built or loaded; the message names the world and the problem."""


@dataclass(frozen=True)
class StartPose:
    """A start position (m) and initial heading (rad, counter-clockwise from +x)."""

    x: float
    y: float
    yaw: float
    name: str = ""


@dataclass(frozen=True)
class World:
    name: str
    """Name as given to ``load_world``."""
    mjcf: str
    """The static scene as MJCF text: a floor plane named 'floor' and obstacle geoms."""
    starts: tuple[StartPose, ...]
    """Start poses (the paper has 12)."""
    extent: tuple[float, float, float, float]
    """(xmin, ymin, xmax, ymax) of the area the robot can be in, in metres."""
    kind: str = "builtin"
    """'builtin', 'procedural' or 'file'."""
    asset_sha256: tuple[tuple[str, str, str], ...] = ()
    """(kind, file as the MJCF names it, SHA-256 hex of its content) of every file MuJoCo reads beside
    the MJCF text (:func:`_asset_files`), sorted; empty for built-in and procedural worlds."""

    @property
    def size_m(self) -> tuple[float, float]:
        xmin, ymin, xmax, ymax = self.extent
        return xmax - xmin, ymax - ymin

    @property
    def label(self) -> str:
        """How error messages name this world (a file world by its path)."""
        return f"MJCF file '{self.name}'" if self.kind == "file" else f"world '{self.name}'"


class SceneBuilder:
    """Builds a static scene with MjSpec from 2D primitives (all obstacles are vertical)."""

    def __init__(self, name: str, extent: tuple[float, float, float, float]):
        self.spec = mujoco.MjSpec()
        self.spec.modelname = name
        self.extent = extent
        xmin, ymin, xmax, ymax = extent
        cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
        # size 0: an infinite plane, so rays never fall off the floor's edge
        self.spec.worldbody.add_geom(
            name=FLOOR_GEOM, type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[cx, cy, 0.0], size=[0.0, 0.0, 0.25],
            rgba=[0.35, 0.35, 0.38, 1.0],
        )
        self._count = 0

    def _name(self, kind: str) -> str:
        self._count += 1
        return f"{kind}_{self._count}"

    def box(self, cx: float, cy: float, half_x: float, half_y: float, yaw: float = 0.0,
            height: float = WALL_HEIGHT_M) -> None:
        """An axis-aligned (or yawed) box standing on the floor."""
        self.spec.worldbody.add_geom(
            name=self._name("box"), type=mujoco.mjtGeom.mjGEOM_BOX,
            pos=[cx, cy, height / 2], size=[half_x, half_y, height / 2],
            quat=[math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)], rgba=list(OBSTACLE_RGBA),
        )

    def wall(self, x0: float, y0: float, x1: float, y1: float, thickness: float = 0.1,
             height: float = WALL_HEIGHT_M) -> None:
        """A straight wall segment from (x0, y0) to (x1, y1), extended by half its thickness
        at both ends so that walls meeting at a corner close it."""
        length = math.hypot(x1 - x0, y1 - y0)
        self.box((x0 + x1) / 2, (y0 + y1) / 2, length / 2 + thickness / 2, thickness / 2,
                 yaw=math.atan2(y1 - y0, x1 - x0), height=height)

    def rect(self, x0: float, y0: float, x1: float, y1: float, height: float = WALL_HEIGHT_M) -> None:
        """A solid axis-aligned block covering exactly [x0, x1] x [y0, y1]."""
        self.box((x0 + x1) / 2, (y0 + y1) / 2, abs(x1 - x0) / 2, abs(y1 - y0) / 2, height=height)

    def cylinder(self, cx: float, cy: float, radius: float, height: float = WALL_HEIGHT_M) -> None:
        self.spec.worldbody.add_geom(
            name=self._name("cyl"), type=mujoco.mjtGeom.mjGEOM_CYLINDER,
            pos=[cx, cy, height / 2], size=[radius, height / 2, 0.0], rgba=list(OBSTACLE_RGBA),
        )

    def boundary(self) -> None:
        """Four walls around the extent."""
        xmin, ymin, xmax, ymax = self.extent
        self.wall(xmin, ymin, xmax, ymin)
        self.wall(xmax, ymin, xmax, ymax)
        self.wall(xmax, ymax, xmin, ymax)
        self.wall(xmin, ymax, xmin, ymin)

    def build(self, name: str, starts: list[StartPose], kind: str = "builtin") -> World:
        return World(name=name, mjcf=self.spec.to_xml(), starts=tuple(starts), extent=self.extent, kind=kind)


# ---------------------------------------------------------------------------
# Start validation (shared by every kind of world)
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class StartCheck:
    """What :class:`StartChecker` measured at one pose; ``problems`` empty means valid."""

    clearance_m: float
    """Distance from the robot disc to the nearest obstacle (negative: overlapping)."""
    nearest_geom: str
    free_ahead_m: float
    """Free distance straight ahead, the least over rays spread across the robot's width."""
    min_view_depth_m: float
    """Nearest valid depth in the start's depth image (inf if none)."""
    problems: tuple[str, ...]
    touching: bool = False
    """The robot is inside or touching an obstacle (or the pose is not finite); ``problems[0]`` says so."""

    @property
    def ok(self) -> bool:
        return not self.problems


class StartChecker:
    """Checks candidate start poses in one compiled world (robot added).

    A valid start has the robot disc clear of every obstacle by MIN_START_CLEARANCE_M,
    MIN_FREE_AHEAD_M of free space straight ahead across the robot's width, and a first
    depth image that reads at least collision_distance_m + START_VIEW_MARGIN_M everywhere,
    so that no episode begins with a collision."""

    _AHEAD_HEIGHTS_M = (0.05, 0.17, 0.29)  # within the robot body's 0.01-0.31 m

    def __init__(self, world: World, env_cfg: EnvConfig | None = None, sensor_cfg: SensorConfig | None = None):
        self.world = world
        self.env_cfg = env_cfg or EnvConfig()
        self.sensor_cfg = checked_sensor(sensor_cfg or SensorConfig())
        try:
            self.model = build_model(world.mjcf, self.env_cfg, self.sensor_cfg)
        except ValueError as exc:
            raise WorldError(f"{world.label}: MuJoCo cannot compile it with the robot added: {exc}") from None
        self.data = mujoco.MjData(self.model)
        self.robot = Robot(self.model, self.data)
        m = self.model
        self.obstacles = [g for g in range(m.ngeom)
                          if m.geom_bodyid[g] != self.robot.body_id and g != self.robot.floor_id]
        self.camera = DepthCamera(m, self.sensor_cfg)
        self._geomid = np.zeros(1, dtype=np.int32)

    def _geom_name(self, g: int) -> str:
        return self.model.geom(g).name or f"geom #{g}"

    def check(self, x: float, y: float, yaw: float) -> StartCheck:
        if not all(math.isfinite(v) for v in (x, y, yaw)):  # MuJoCo would go on with NaN physics
            return StartCheck(clearance_m=math.nan, nearest_geom="", free_ahead_m=math.nan, min_view_depth_m=math.nan,
                              problems=(f"at a pose that is not finite ({x}, {y}, {yaw})",), touching=True)
        m, d, r = self.model, self.data, self.env_cfg.robot_radius_m
        self.robot.set_pose(x, y, yaw)
        clearance, nearest = math.inf, ""
        for g in self.obstacles:
            dist = mujoco.mj_geomDistance(m, d, self.robot.geom_id, g, 10.0, None)
            if dist < clearance:
                clearance, nearest = dist, self._geom_name(g)
        touching = self.robot.touching_obstacle() or clearance <= 0.0
        c, s = math.cos(yaw), math.sin(yaw)
        heading = np.array([c, s, 0.0])
        free_ahead = math.inf
        for lateral in (-r, -r / 2, 0.0, r / 2, r):
            for z in self._AHEAD_HEIGHTS_M:
                pnt = np.array([x - s * lateral, y + c * lateral, z])
                hit = mujoco.mj_ray(m, d, pnt, heading, None, 1, self.robot.body_id, self._geomid)
                if hit >= 0:
                    free_ahead = min(free_ahead, hit)
        depth = self.camera.capture(d)
        valid = depth[depth > 0]
        min_view = float(valid.min()) if valid.size else math.inf
        need_view = self.env_cfg.collision_distance_m + START_VIEW_MARGIN_M
        problems: list[str] = []
        if touching:
            problems.append(f"inside or touching an obstacle (geom '{nearest}', distance {clearance:.3f} m)")
        elif clearance < MIN_START_CLEARANCE_M:
            problems.append(f"only {clearance:.3f} m from geom '{nearest}' (needs >= {MIN_START_CLEARANCE_M} m)")
        if free_ahead < MIN_FREE_AHEAD_M:
            problems.append(f"only {free_ahead:.2f} m of free depth straight ahead (needs >= {MIN_FREE_AHEAD_M} m)")
        if min_view < need_view:
            problems.append(f"nearest depth in view {min_view:.2f} m (needs >= {need_view:.2f} m, or the "
                            "first step may end in a depth collision)")
        return StartCheck(clearance_m=float(clearance), nearest_geom=nearest, free_ahead_m=float(free_ahead),
                          min_view_depth_m=min_view, problems=tuple(problems), touching=touching)

    def unsafe_first_actions(self, x: float, y: float, yaw: float,
                             speed_tables: tuple[str, ...] = tuple(SPEED_TABLES)) -> list[tuple[str, int]]:
        """(speed table, action) pairs whose first step from this pose ends in a collision,
        judged as the env judges it (contact, or depth below collision_distance_m).

        Not part of a start's validity (user worlds may have tighter starts); procedural
        worlds use it to pick starts from which every first move is safe."""
        bad = []
        for table in speed_tables:
            angular, linear = SPEED_TABLES[table]
            for action, turn in enumerate(angular):
                self.robot.set_pose(x, y, yaw)
                touched = self.robot.drive(linear, turn, self.env_cfg.substeps)
                depth = self.camera.capture(self.data)
                valid = depth[depth > 0]
                if touched or (valid.size and float(valid.min()) < self.env_cfg.collision_distance_m):
                    bad.append((table, action))
        return bad


def validate_starts(world: World, env_cfg: EnvConfig | None = None,
                    sensor_cfg: SensorConfig | None = None) -> tuple[StartCheck, ...]:
    """Check every start of ``world`` (see :class:`StartChecker`); raise WorldError naming
    each invalid start, else return the per-start measurements."""
    if not world.starts:
        raise WorldError(f"{world.label} has no start poses")
    checker = StartChecker(world, env_cfg, sensor_cfg)
    checks = tuple(checker.check(s.x, s.y, s.yaw) for s in world.starts)
    bad = [f"start {i} '{s.name}' at ({s.x:.2f}, {s.y:.2f}): {'; '.join(c.problems)}"
           for i, (s, c) in enumerate(zip(world.starts, checks), start=1) if c.problems]
    if bad:
        raise WorldError(f"{world.label}: invalid start(s): " + " | ".join(bad))
    return checks


def checked_sensor(sensor_cfg: SensorConfig) -> SensorConfig:
    """The camera a start is checked with: ``sensor_cfg`` without noise (a check must not depend
    on a draw) and ray-cast (no OpenGL needed)."""
    return dataclasses.replace(sensor_cfg.noise_free(), backend="raycast")


def check_starts_fit(world: World, env_cfg: EnvConfig, sensor_cfg: SensorConfig) -> None:
    """WorldError unless every start of ``world`` has a first step some command survives, for this
    robot and camera: the robot not inside or touching an obstacle (at its radius), and, where its
    first image (without noise) already reads nearer than ``collision_distance_m``, at least one
    command of its speed table whose step ends clear. Otherwise every episode from that start ends
    at its first step. A world's starts are checked (:func:`validate_starts`) for the default robot
    and camera when it is made; a larger robot can stand in a wall, a wider or lower camera see one
    at the lens. Checked once per world, robot and camera."""
    robot = dataclasses.replace(EnvConfig(), **{f: getattr(env_cfg, f) for f in _ROBOT_ENV_FIELDS})
    # as a cache key: a World built with lists (dataclasses.replace(w, starts=[...])) is not hashable
    bad = _starts_ending_at_once(dataclasses.replace(world, starts=tuple(world.starts), extent=tuple(world.extent)),
                                 robot, checked_sensor(sensor_cfg))
    if bad:
        raise WorldError(f"{world.label}: with robot_radius_m {robot.robot_radius_m:g}, collision_distance_m "
                         f"{robot.collision_distance_m:g} and this camera (hfov_deg {sensor_cfg.hfov_deg:g}, vfov_deg "
                         f"{sensor_cfg.vfov_deg:g}), every command's first step ends in a collision at {len(bad)} of "
                         f"its {len(world.starts)} starts: {_listed(bad)}")


_ROBOT_ENV_FIELDS = tuple(f.partition(".")[2] for f in ROBOT_FIELDS)
"""What a start's first step depends on besides the world and the camera (shared.config.ROBOT_FIELDS)."""


@functools.lru_cache(maxsize=256)
def _starts_ending_at_once(world: World, robot: EnvConfig, sensor_cfg: SensorConfig) -> tuple[str, ...]:
    checker = StartChecker(world, robot, sensor_cfg)
    bad = []
    for i, start in enumerate(world.starts, start=1):
        check = checker.check(start.x, start.y, start.yaw)
        if check.touching:
            bad.append(f"{i} '{start.name}' (touching geom '{check.nearest_geom}')" if check.nearest_geom
                       else f"{i} '{start.name}' (touching)")
        elif check.min_view_depth_m < robot.collision_distance_m and len(checker.unsafe_first_actions(
                start.x, start.y, start.yaw, (robot.speed_table,))) == len(SPEED_TABLES[robot.speed_table][0]):
            bad.append(f"{i} '{start.name}' (its first image reads {check.min_view_depth_m:.2f} m)")
    return tuple(bad)


def _listed(items: list[str] | tuple[str, ...], most: int = 4) -> str:
    """The first ``most`` items, comma-separated, and how many more: one line however many."""
    more = f" and {len(items) - most} more" if len(items) > most else ""
    return ", ".join(items[:most]) + more


# ---------------------------------------------------------------------------
# Built-in worlds
# ---------------------------------------------------------------------------


def box_room(name: str = "box-room") -> World:
    """A 4 x 4 m room with one box and one cylinder; small and fast, for tests."""
    b = SceneBuilder(name, (-2.0, -2.0, 2.0, 2.0))
    b.boundary()
    b.box(1.0, 1.0, 0.3, 0.3)
    b.cylinder(-1.0, 0.8, 0.25)
    starts = [StartPose(-1.2, -1.2, math.pi / 4, "sw"), StartPose(1.2, -1.2, 3 * math.pi / 4, "se"),
              StartPose(0.0, 0.0, -math.pi / 2, "centre"), StartPose(-1.2, 1.3, 0.0, "nw")]
    return b.build(name, starts)


def paper_indoor(name: str = "paper-indoor") -> World:
    """The reference world, 12 x 12 m, after the paper's Gazebo world (Fig. 2, sec. III-A).

    Corridors run along the west, north and south walls; a central hall holds cylinders of
    several radii at staggered depths, free-standing pillars and a pair of boxes with a gap
    too narrow for the robot; the east side has sharp corners (a diamond pillar, an L-shaped
    wall and a wedge), a room with more cylinders, and a second narrow gap; the south has a
    dead-end corridor. Everything is one connected space; 12 starts cover the kinds of scene.
    """
    b = SceneBuilder(name, (-6.0, -6.0, 6.0, 6.0))
    b.boundary()
    # Walls dividing the corridors, the hall, the east side and the dead end.
    b.wall(-4.6, -3.0, -4.6, 4.5)      # west corridor | hall
    b.wall(-3.4, 4.5, 2.2, 4.5)        # north corridor | hall (door at its west end)
    b.wall(2.2, 1.0, 2.2, 4.5)         # hall | north-east room
    b.wall(3.6, 1.0, 6.0, 1.0)         # north-east room | east side (door at its west end)
    b.wall(2.2, -3.0, 2.2, -0.5)       # hall | east side (door between y -0.5 and 1.0)
    b.wall(-3.4, -3.0, 2.2, -3.0)      # hall | south (door at its west end)
    b.wall(-3.4, -4.5, 1.0, -4.5)      # dead-end corridor | south corridor
    b.wall(1.0, -4.5, 1.0, -3.0)       # the dead end
    # West corridor: a pillar jutting from the outer wall narrows it to 0.8 m.
    b.box(-5.7, 0.5, 0.25, 0.3)
    # North corridor: a cylinder leaves a 0.2 m slit on one side, 0.8 m on the other.
    b.cylinder(0.0, 5.55, 0.2)
    # Hall: cylinders of several radii at different depths from the west door.
    b.cylinder(-2.4, 0.9, 0.2)
    b.cylinder(-1.1, -0.2, 0.3)
    b.cylinder(0.4, 1.4, 0.5)
    b.cylinder(-2.9, 2.3, 0.15)
    b.cylinder(1.2, -1.0, 0.25)
    b.cylinder(0.5, 3.1, 0.35)
    # Hall: pillars, one turned to show a sharp edge.
    b.box(-3.0, -1.9, 0.35, 0.35, yaw=0.5)
    b.box(-0.4, -2.2, 0.6, 0.2)
    # Hall: two boxes 0.3 m apart (too narrow for the 0.36 m robot).
    b.rect(-2.7, 3.05, -1.7, 3.55)
    b.rect(-1.4, 3.05, -0.6, 3.55)
    # East side: a diamond pillar, an L-shaped wall and a wedge: sharp corners.
    b.box(4.4, -0.5, 0.45, 0.45, yaw=math.pi / 4)
    b.wall(3.4, -2.2, 5.0, -2.2)
    b.wall(5.0, -2.2, 5.0, -3.5)
    b.box(3.0, -1.5, 0.6, 0.08, yaw=-0.6)
    # South-east: two cylinders 0.3 m apart.
    b.cylinder(3.0, -4.0, 0.25)
    b.cylinder(3.8, -4.0, 0.25)
    # North-east room: cylinders of several radii and a block in a corner.
    b.cylinder(4.5, 3.6, 0.4)
    b.cylinder(3.4, 2.6, 0.2)
    b.cylinder(5.1, 2.0, 0.25)
    b.rect(5.2, 5.2, 5.95, 5.95)
    # South-west: a small cluster at different depths.
    b.cylinder(-5.0, -3.8, 0.15)
    b.cylinder(-4.1, -5.3, 0.3)
    starts = [
        StartPose(-5.3, -2.0, math.pi / 2, "corridor-west"),
        StartPose(-2.0, 5.25, 0.0, "corridor-north"),
        StartPose(-1.0, -5.25, 0.0, "corridor-south"),
        StartPose(-3.9, 0.5, 0.0, "hall-cylinders"),
        StartPose(-1.55, 1.8, math.pi / 2, "narrow-gap"),
        StartPose(-2.8, -3.75, 0.0, "dead-end"),
        StartPose(2.6, -0.5, 0.0, "sharp-corners"),
        StartPose(3.0, 4.2, -math.pi / 4, "room-north-east"),
        StartPose(0.8, 0.1, 0.0, "hall-east-door"),
        StartPose(1.6, -3.75, 0.0, "cylinder-pair"),
        StartPose(1.6, -2.2, math.pi, "hall-pillars"),
        StartPose(-4.0, 5.25, -math.pi / 2, "junction-north-west"),
    ]
    return b.build(name, starts)


def corridor(name: str = "corridor") -> World:
    """A structured corridor loop (an '8': outer ring plus a middle corridor, 1.35-1.55 m
    wide), like the corridors of the paper's supervised data."""
    b = SceneBuilder(name, (-5.0, -4.0, 5.0, 4.0))
    b.boundary()
    b.rect(-3.6, -2.6, -0.7, 2.4)
    b.rect(0.7, -2.6, 3.4, 2.4)
    west, east, south, north = -4.28, 4.17, -3.28, 3.17  # corridor centre lines
    starts = [
        StartPose(west, -1.5, math.pi / 2, "west-northbound"),
        StartPose(west, 1.5, -math.pi / 2, "west-southbound"),
        StartPose(east, -1.0, math.pi / 2, "east-northbound"),
        StartPose(east, 1.5, -math.pi / 2, "east-southbound"),
        StartPose(-2.5, south, 0.0, "south-eastbound"),
        StartPose(2.0, south, math.pi, "south-westbound"),
        StartPose(-2.0, north, 0.0, "north-eastbound"),
        StartPose(2.5, north, math.pi, "north-westbound"),
        StartPose(0.0, -1.5, math.pi / 2, "middle-northbound"),
        StartPose(0.0, 1.0, -math.pi / 2, "middle-southbound"),
        StartPose(west, south, 0.0, "corner-south-west"),
        StartPose(0.0, north, 0.0, "junction-north"),
    ]
    return b.build(name, starts)


BUILTIN_WORLDS = {
    "paper-indoor": paper_indoor,
    "corridor": corridor,
    "box-room": box_room,
}


# ---------------------------------------------------------------------------
# Procedural worlds
# ---------------------------------------------------------------------------

_DOOR_KEEPOUT_M = 0.8  # clutter stays this far from door centres


@dataclass(frozen=True)
class _Shape:
    """A 2D primitive of a procedural world: a box (cx, cy, hx, hy, yaw) or a cylinder (cx, cy, r)."""

    kind: str
    cx: float
    cy: float
    a: float
    b: float = 0.0
    yaw: float = 0.0

    def transposed(self) -> "_Shape":
        # Reflecting through y = x maps a box at yaw t with halves (a, b) to one at -t with (b, a).
        if self.kind == "box":
            return _Shape("box", self.cy, self.cx, self.b, self.a, -self.yaw)
        return _Shape(self.kind, self.cy, self.cx, self.a)

    def emit(self, b: SceneBuilder) -> None:
        if self.kind == "box":
            b.box(self.cx, self.cy, self.a, self.b, yaw=self.yaw)
        else:
            b.cylinder(self.cx, self.cy, self.a)

    def rasterise(self, occupied: np.ndarray, grid: maps.OccupancyGrid) -> None:
        """Mark the cells the shape reaches, exactly as maps.occupancy_grid would."""
        h = WALL_HEIGHT_M / 2
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        mat = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        pos = np.array([self.cx, self.cy, h])
        if self.kind == "box":
            gtype, size = mujoco.mjtGeom.mjGEOM_BOX, np.array([self.a, self.b, h])
            aabb = np.array([0.0, 0.0, 0.0, self.a, self.b, h])
        else:
            gtype, size = mujoco.mjtGeom.mjGEOM_CYLINDER, np.array([self.a, h, 0.0])
            aabb = np.array([0.0, 0.0, 0.0, self.a, self.a, h])
        maps.rasterise_geom(occupied, grid, int(gtype), size, pos, mat, aabb)


def _segment_with_doors(x0: float, x1: float, y: float, doors: list[tuple[float, float]],
                        thickness: float = 0.1) -> list[_Shape]:
    """Boxes along y = const from x0 to x1, leaving gaps (centre, width)."""
    shapes, cursor = [], x0
    for centre, width in sorted(doors):
        a, b = centre - width / 2, centre + width / 2
        if a - cursor > 0.05:
            shapes.append(_Shape("box", (cursor + a) / 2, y, (a - cursor) / 2, thickness / 2))
        cursor = b
    if x1 - cursor > 0.05:
        shapes.append(_Shape("box", (cursor + x1) / 2, y, (x1 - cursor) / 2, thickness / 2))
    return shapes


def _vertical_segment_with_doors(y0: float, y1: float, x: float, doors: list[tuple[float, float]],
                                 thickness: float = 0.1) -> list[_Shape]:
    return [s.transposed() for s in _segment_with_doors(y0, y1, x, doors, thickness)]


def _split(rng: np.random.Generator, length: float, min_part: float, max_parts: int) -> list[float]:
    """Cut [0, length] into 1..max_parts parts of at least min_part; returns the cut points."""
    k = int(rng.integers(1, max(1, min(max_parts, int(length // min_part))) + 1))
    spare = length - k * min_part
    weights = rng.uniform(0.5, 1.5, size=k)
    parts = min_part + spare * weights / weights.sum()
    return [float(v) for v in np.cumsum(parts)[:-1]]


def _procedural_layout(rng: np.random.Generator) -> tuple[float, float, list[_Shape],
                                                                     list[tuple[str, tuple[float, float, float, float]]],
                                                                     list[tuple[float, float]], list[_Shape]]:
    """Walls, rooms, doors and candidate clutter in a frame whose x is the long side."""
    W = round(float(rng.uniform(8.0, 14.0)), 1)
    H = round(float(rng.uniform(8.0, 14.0)), 1)
    L, S = max(W, H), min(W, H)
    xmin, ymin, xmax, ymax = -L / 2, -S / 2, L / 2, S / 2
    cw = round(float(rng.uniform(1.2, 1.6)), 2)  # corridor width between wall faces
    low_h = float(rng.uniform(2.6, S - cw - 2.6))
    y_lo = round(ymin + low_h, 2)          # corridor's south wall face
    y_hi = round(y_lo + cw, 2)             # corridor's north wall face
    t = 0.1
    walls: list[_Shape] = []
    rooms: list[tuple[str, tuple[float, float, float, float]]] = []
    doors: list[tuple[float, float]] = []
    corridor_doors: dict[str, list[tuple[float, float]]] = {"south": [], "north": []}
    for side, (r0, r1) in (("south", (ymin, y_lo - t)), ("north", (y_hi + t, ymax))):
        cuts = [xmin] + [round(xmin + c, 2) for c in _split(rng, L, 2.8, 3)] + [xmax]
        for i in range(len(cuts) - 1):
            a, b = cuts[i], cuts[i + 1]
            rooms.append((f"room-{side}-{i + 1}", (a + (t / 2 if i else 0), r0, b - (t / 2 if i < len(cuts) - 2 else 0), r1)))
            dw = round(float(rng.uniform(0.9, 1.3)), 2)
            if rng.random() < 0.2:
                dw = round(min(2.0, (b - a) - 0.8), 2)  # an open-plan room
            dc = round(float(rng.uniform(a + 0.4 + dw / 2, b - 0.4 - dw / 2)), 2)
            corridor_doors[side].append((dc, dw))
            doors.append((dc, y_lo - t / 2 if side == "south" else y_hi + t / 2))
            if i > 0:
                # A divider between rooms i-1 and i, sometimes with a door of its own.
                divider_doors = []
                if rng.random() < 0.5:
                    ddw = round(float(rng.uniform(0.9, 1.2)), 2)
                    ddc = round(float(rng.uniform(r0 + 0.3 + ddw / 2, r1 - 0.3 - ddw / 2)), 2)
                    divider_doors.append((ddc, ddw))
                    doors.append((a, ddc))
                walls += _vertical_segment_with_doors(r0, r1, a, divider_doors, t)
    walls += _segment_with_doors(xmin, xmax, y_lo - t / 2, corridor_doors["south"], t)
    walls += _segment_with_doors(xmin, xmax, y_hi + t / 2, corridor_doors["north"], t)
    rooms.append(("corridor", (xmin, y_lo, xmax, y_hi)))
    # Candidate clutter, most of it in rooms, a little in the corridor.
    clutter: list[_Shape] = []
    for rname, (a, r0, b, r1) in rooms:
        area = (b - a) * (r1 - r0)
        n = int(rng.integers(0, 3)) if rname == "corridor" else int(rng.integers(2, 3 + min(6, int(area / 4))))
        for _ in range(n):
            if rname == "corridor" or rng.random() < 0.45:
                r = round(float(rng.uniform(0.1, 0.2 if rname == "corridor" else 0.45)), 2)
                bound = r
                shape = _Shape("cyl", 0.0, 0.0, r)
            else:
                hx = round(float(rng.uniform(0.15, 0.6)), 2)
                hy = round(float(rng.uniform(0.15, 0.6)), 2)
                yaw = 0.0 if rng.random() < 0.5 else round(float(rng.uniform(0.0, math.pi)), 3)
                bound = math.hypot(hx, hy) if yaw else max(hx, hy)
                shape = _Shape("box", 0.0, 0.0, hx, hy, yaw)
            lo_x, hi_x = a + bound + 0.05, b - bound - 0.05
            lo_y, hi_y = r0 + bound + 0.05, r1 - bound - 0.05
            if lo_x >= hi_x or lo_y >= hi_y:
                continue
            cx = round(float(rng.uniform(lo_x, hi_x)), 2)
            cy = round(float(rng.uniform(lo_y, hi_y)), 2)
            if rname == "corridor":  # against one of the corridor walls
                cy = round(y_lo + bound + 0.02 if rng.random() < 0.5 else y_hi - bound - 0.02, 2)
            clutter.append(_Shape(shape.kind, cx, cy, shape.a, shape.b, shape.yaw))
    return L, S, walls, rooms, doors, clutter


def procedural_world(seed: int) -> World:
    """Rooms off a corridor, doors, and clutter; deterministic in ``seed``.

    Clutter that would cut the traversable space (free space shrunk by the robot radius on
    a 5 cm grid) into more than one piece is dropped, so the world is always connected;
    12 starts are spread over the rooms and the corridor and checked like every start."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise WorldError(f"procedural seed must be an integer >= 0, got {seed!r}")
    name = f"{PROCEDURAL_PREFIX}{seed}"
    rng = np.random.default_rng(int(seed))
    env_cfg = EnvConfig()
    radius = env_cfg.robot_radius_m
    for _attempt in range(6):
        L, S, walls, rooms, doors, clutter = _procedural_layout(rng)
        transpose = bool(rng.random() < 0.5)
        extent = (-L / 2, -S / 2, L / 2, S / 2)
        grid = maps.empty_grid(extent, 0.05)
        occupied = np.zeros(grid.shape, dtype=bool)
        boundary = [_Shape("box", 0.0, -S / 2, L / 2 + 0.05, 0.05), _Shape("box", 0.0, S / 2, L / 2 + 0.05, 0.05),
                    _Shape("box", -L / 2, 0.0, 0.05, S / 2 + 0.05), _Shape("box", L / 2, 0.0, 0.05, S / 2 + 0.05)]
        for shape in boundary + walls:
            shape.rasterise(occupied, grid)
        if maps.label_components(maps.traversable(maps.OccupancyGrid(grid.origin_xy, 0.05, occupied), radius))[1] != 1:
            continue  # the walls alone must leave one connected space; draw another layout
        kept: list[_Shape] = []
        for shape in clutter:
            if any(math.hypot(shape.cx - dx, shape.cy - dy) < _DOOR_KEEPOUT_M for dx, dy in doors):
                continue
            trial = occupied.copy()
            shape.rasterise(trial, grid)
            if maps.label_components(maps.traversable(maps.OccupancyGrid(grid.origin_xy, 0.05, trial), radius))[1] == 1:
                occupied, kept = trial, kept + [shape]
        shapes = boundary + walls + kept
        if transpose:
            shapes = [s.transposed() for s in shapes]
            extent = (-S / 2, -L / 2, S / 2, L / 2)
            rooms = [(n, (r0, a, r1, b)) for n, (a, r0, b, r1) in rooms]
        builder = SceneBuilder(name, extent)
        for shape in shapes:
            shape.emit(builder)
        scene = builder.build(name, [], kind="procedural")
        starts = _pick_starts(scene, rooms, rng, env_cfg)
        if starts is None:
            continue
        world = World(name=name, mjcf=scene.mjcf, starts=tuple(starts), extent=extent, kind="procedural")
        if not maps.is_connected(maps.occupancy_grid(world), radius):
            continue  # rounding in the MJCF text moved a cell; try another draw
        return world
    raise WorldError(f"world '{name}': no valid layout with {NUM_STARTS} starts after 6 attempts")


def _pick_starts(scene: World, regions: list[tuple[str, tuple[float, float, float, float]]],
                 rng: np.random.Generator, env_cfg: EnvConfig) -> list[StartPose] | None:
    """NUM_STARTS valid starts spread over the regions (round robin, >= 1.2 m apart)."""
    checker = StartChecker(scene, env_cfg)
    grid = maps.occupancy_grid(scene)
    margin = env_cfg.robot_radius_m + MIN_START_CLEARANCE_M + grid.resolution_m
    roomy = ~maps.inflate(grid.occupied, margin / grid.resolution_m)
    iy, ix = np.nonzero(roomy)
    cx, cy = grid.cell_to_world(ix, iy)
    order = list(range(len(regions)))
    rng.shuffle(order)
    starts: list[StartPose] = []
    per_region = {i: 0 for i in order}
    headings = np.arange(16) * (math.pi / 8)
    for _round in range(6):
        for ri in order:
            if len(starts) == NUM_STARTS:
                return starts
            rname, (x0, y0, x1, y1) = regions[ri]
            inside = np.nonzero((cx > x0) & (cx < x1) & (cy > y0) & (cy < y1))[0]
            if inside.size == 0:
                continue
            for k in rng.permutation(inside)[:12]:
                x, y = round(float(cx[k]), 2), round(float(cy[k]), 2)
                if any(math.hypot(x - s.x, y - s.y) < 1.2 for s in starts):
                    continue
                found = None
                for yaw in rng.permutation(headings):
                    yaw = round(float(math.atan2(math.sin(yaw), math.cos(yaw))), 4)
                    if checker.check(x, y, yaw).ok and not checker.unsafe_first_actions(x, y, yaw):
                        found = yaw
                        break
                if found is not None:
                    per_region[ri] += 1
                    starts.append(StartPose(x, y, found, f"{rname}-{per_region[ri]}"))
                    break
    return starts if len(starts) == NUM_STARTS else None


# ---------------------------------------------------------------------------
# User MJCF worlds
# ---------------------------------------------------------------------------


def load_world_file(path: str | Path, name: str | None = None) -> World:
    """A world from an MJCF file: static geoms, starts from sites named ``start_*`` (x, y
    from the site position, heading from the site's x axis). A floor plane named 'floor'
    is added unless the file has one (an upward plane at z = 0 with another name is renamed).

    Refused, besides what MuJoCo refuses: moving bodies, physics options that would reach the robot
    (:func:`_check_options`), geoms the robot or its camera would treat unlike an obstacle
    (:func:`_check_geoms`), a non-finite start, a start whose heading is vertical, a start off the floor
    or outside the walls that enclose the other starts, a 'floor' that is no floor and text that is not UTF-8."""
    try:
        return _load_world_file(Path(path), f"MJCF file '{path}'", name or str(path))
    except UnicodeDecodeError as exc:  # MuJoCo reads any bytes; its names and MJCF text come back as str
        raise WorldError(f"MJCF file '{path}' holds text that is not UTF-8 (byte "
                         f"{exc.object[exc.start:exc.start + 1]!r} in a name or comment): save it as UTF-8") from None


def _load_world_file(p: Path, label: str, name: str) -> World:
    if not p.is_file():
        raise WorldError(f"{label} {'is not a file' if p.exists() else 'does not exist'}")
    try:
        spec = mujoco.MjSpec.from_file(str(p))
    except ValueError as exc:
        raise WorldError(f"{label}: MuJoCo cannot parse it: {exc}".rstrip()) from None
    if any(body.name == ROBOT_BODY for body in spec.bodies):
        raise WorldError(f"{label} already has a body named '{ROBOT_BODY}'; the robot is added by "
                         "cogexplore, remove or rename that body")
    # Asset paths must survive the trip through MJCF text compiled from a string.
    base = p.resolve().parent
    spec.meshdir = str((base / spec.meshdir).resolve()) if spec.meshdir else str(base)
    spec.texturedir = str((base / spec.texturedir).resolve()) if spec.texturedir else str(base)
    try:
        model = spec.compile()
    except ValueError as exc:
        raise WorldError(f"{label}: MuJoCo cannot compile it: {exc}".rstrip()) from None
    _check_text_reads_same_files(spec, model, label)
    assets = _asset_digests(spec, label)  # now: the files MuJoCo has just read, not those of a later edit
    if model.njnt > 0:
        moving = sorted({model.body(int(model.jnt_bodyid[j])).name or f"body #{int(model.jnt_bodyid[j])}"
                         for j in range(model.njnt)})
        raise WorldError(f"{label}: bodies with joints are not static: {moving}; a world may hold only "
                         "static geoms (no joints, no free bodies)")
    _check_options(model, label)
    try:
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
    except mujoco.FatalError as exc:  # e.g. a <size memory> too small for the scene
        raise WorldError(f"{label}: MuJoCo cannot simulate it: {' '.join(str(exc).split())}") from None
    starts = []
    for i in range(model.nsite):
        site = model.site(i).name
        if site.startswith("start_"):
            x, y = (float(v) for v in data.site_xpos[i][:2])
            xmat = data.site_xmat[i]
            start = StartPose(x, y, float(math.atan2(xmat[3], xmat[0])), site)
            if not all(math.isfinite(v) for v in (start.x, start.y, start.yaw)):
                raise WorldError(f"{label}: start site '{site}' has no finite position and heading "
                                 f"(x {start.x}, y {start.y}, yaw {start.yaw})")
            if math.hypot(xmat[0], xmat[3]) < _MIN_HEADING_XY:  # the heading would be rounding noise
                raise WorldError(f"{label}: start site '{site}' has its x axis (the start's heading) pointing "
                                 "straight up or down; turn it about z only (euler=\"0 0 <degrees>\")")
            z = float(data.site_xpos[i][2])
            if not -FLOOR_TOLERANCE_M <= z <= MAX_START_HEIGHT_M:  # the robot starts on the floor whatever z says
                raise WorldError(f"{label}: start site '{site}' is at z = {z:g}, off the floor the robot starts on: "
                                 f"put it at z = 0 (at most {MAX_START_HEIGHT_M:g} m, the robot's top)")
            starts.append(start)
    if not starts:
        raise WorldError(f"{label} has no start sites: add sites named start_<something> "
                         "(position = start, site x axis = initial heading)")
    # The floor: keep one named 'floor', else rename the first upward plane at z = 0, else add one.
    floor_ids = [g for g in range(model.ngeom) if model.geom(g).name == FLOOR_GEOM]
    if floor_ids and _top_z(model, data, floor_ids[0]) > FLOOR_TOLERANCE_M:
        raise WorldError(f"{label}: geom '{FLOOR_GEOM}' rises above z = 0 (an upward plane or a slab whose top is "
                         f"within {FLOOR_TOLERANCE_M * 100:g} cm of it is a floor); the robot would pass through it "
                         "as through the floor: rename it (an obstacle) or lower it")
    if not floor_ids:
        for g in range(model.ngeom):
            if _is_floor_plane(model, data, g):
                next(sg for sg in spec.geoms if sg.id == g).name = FLOOR_GEOM
                floor_ids = [g]
                break
    _check_geoms(model, data, label, set(floor_ids))
    extent = _geom_extent(model, data, set(floor_ids), starts)
    if not floor_ids:
        xmin, ymin, xmax, ymax = extent
        spec.worldbody.add_geom(name=FLOOR_GEOM, type=mujoco.mjtGeom.mjGEOM_PLANE,
                                pos=[(xmin + xmax) / 2, (ymin + ymax) / 2, 0.0], size=[0.0, 0.0, 0.25],
                                rgba=[0.35, 0.35, 0.38, 1.0])
    world = World(name=name, mjcf=spec.to_xml(), starts=tuple(starts), extent=extent, kind="file",
                  asset_sha256=assets)
    if floor_ids:  # the file's own floor; the one added is an infinite plane
        _check_floor_covers(world, model, data, floor_ids[0])
    validate_starts(world)
    _check_starts_walled_in(world)
    return world


def _check_floor_covers(world: World, model: mujoco.MjModel, data: mujoco.MjData, floor: int) -> None:
    """WorldError when the file's floor (a plane with a size, or a slab) ends before the open space
    around the starts does: the camera would see no floor there, a hole no training image shows."""
    plane = int(model.geom_type[floor]) == int(mujoco.mjtGeom.mjGEOM_PLANE)
    if plane and (model.geom_size[floor][:2] <= 0).all():
        return  # infinite
    grid = maps.occupancy_grid(world)
    labels, _ = maps.label_components(~grid.occupied)
    ix, iy = grid.world_to_cell(np.array([s.x for s in world.starts]), np.array([s.y for s in world.starts]))
    inside = (ix >= 0) & (iy >= 0) & (ix < grid.shape[1]) & (iy < grid.shape[0])
    around = np.isin(labels, labels[iy[inside], ix[inside]]) & (labels >= 0)
    cy, cx = np.nonzero(around)
    x, y = grid.cell_to_world(cx, cy)
    if plane:
        centre, half = np.zeros(2), model.geom_size[floor][:2].astype(np.float64)
        half[half <= 0] = np.inf  # a plane of size 0 along an axis is infinite along it
    else:
        centre, half = model.geom_aabb[floor][:2], model.geom_aabb[floor][3:5]
    rot = data.geom_xmat[floor].reshape(3, 3)[:2, :2]  # an upward floor: its x-y plane is the world's
    local = (np.stack([x, y], axis=1) - data.geom_xpos[floor][:2]) @ rot - centre
    outside = np.any(np.abs(local) > half + grid.resolution_m, axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        raise WorldError(f"{world.label}: its geom '{FLOOR_GEOM}' ends before the open space around the starts does "
                         f"(nothing under ({x[k]:.2f}, {y[k]:.2f}) m): the camera would see no floor there; make it "
                         "a plane of size 0 (infinite), or larger")


def _asset_files(spec: mujoco.MjSpec) -> list[tuple[str, str, Path]]:
    """(kind, file as the MJCF names it, path) of every file MuJoCo reads at compile beside the MJCF
    text (``<include>`` is inlined at parse): meshes, height fields and skins under the meshdir,
    textures (one file or a cube's six) under the texturedir; a name taken whole when absolute and by its
    last part under ``strippath``, as MuJoCo takes it. Directories relative to the model file must have
    been resolved (``_load_world_file`` does)."""
    named: list[tuple[str, str, str]] = [(kind, spec.meshdir, e.file) for kind, elements in
                                         (("mesh", spec.meshes), ("hfield", spec.hfields), ("skin", spec.skins))
                                         for e in elements]
    named += [("texture", spec.texturedir, f) for t in spec.textures for f in (t.file, *t.cubefiles)]
    files = []
    for kind, folder, file in named:
        if not file:  # an asset made from data in the MJCF, or a cube face left out
            continue
        stripped = file.replace("\\", "/").rsplit("/", 1)[-1] if spec.strippath else file
        files.append((kind, file, Path(folder) / stripped))  # an absolute name replaces the folder
    return files


_ASSET_DATA_FIELDS = ("mesh_vert", "mesh_face", "hfield_data", "tex_data", "skin_vert", "skin_face")
"""The compiled model's arrays that hold what MuJoCo read from a world's asset files."""


def _check_text_reads_same_files(spec: mujoco.MjSpec, model: mujoco.MjModel, label: str) -> None:
    """WorldError unless the MJCF text a World keeps (``spec.to_xml()``, its files found from the world
    file's meshdir and texturedir) compiles to the asset data MuJoCo just read from the file. A
    ``<model>`` asset's files are found from its own folder or meshdir, which the text does not carry:
    it would name other files (or none), and the digest with them."""
    if not _asset_files(spec):  # nothing read from files, nothing to differ
        return
    text = spec.to_xml()  # outside the try: text that is not UTF-8 is load_world_file's to name
    try:
        again = mujoco.MjSpec.from_string(text).compile()
    except ValueError as exc:  # a file the text names is not where the <model> found it
        why = f" (its text does not compile: {' '.join(str(exc).split())})"
    else:
        if all(np.array_equal(getattr(model, f), getattr(again, f)) for f in _ASSET_DATA_FIELDS):
            return
        why = ""
    raise WorldError(f"{label}: a <model> asset names mesh, height field, skin or texture files found from its "
                     "own folder or meshdir, which cogexplore cannot carry (it would read other files): name "
                     f"them by absolute paths, or move them under the world's meshdir or texturedir{why}")


def _asset_digests(spec: mujoco.MjSpec, label: str) -> tuple[tuple[str, str, str], ...]:
    """:attr:`World.asset_sha256` of a spec MuJoCo compiled (so every file it names exists)."""
    digests = set()
    for kind, file, path in _asset_files(spec):
        try:
            digests.add((kind, file, hashlib.sha256(path.read_bytes()).hexdigest()))
        except OSError as exc:  # removed since the compile, or unreadable
            raise WorldError(f"{label}: cannot read its {kind} file '{file}' ({path}): "
                             f"{exc.strerror or exc}") from None
    return tuple(sorted(digests))


_MIN_HEADING_XY = 1e-6
"""Least horizontal part of a start site's x axis from which its heading is read."""
MAX_START_HEIGHT_M = ROBOT_HEIGHT_M + 0.01
"""Highest z of a start site: the top of the robot standing on the floor (a site at its centre or
top still marks where it stands; one above it is a misplaced site)."""


def _check_starts_walled_in(world: World) -> None:
    """WorldError naming the starts outside the walls that enclose the world's other starts: from
    those the robot can drive off the map, from the others it cannot (the map spans the obstacles
    and the starts, so a start beyond the walls stretches it to the start). A world whose starts
    all reach the map's edge is an open floor, and none of its starts is refused."""
    try:
        grid = maps.occupancy_grid(world)
    except maps.MapError:  # a world too wide for a map: the env names that itself when it needs one
        return
    labels, _ = maps.free_components(grid, EnvConfig().robot_radius_m)
    edge = {int(v) for side in (labels[0], labels[-1], labels[:, 0], labels[:, -1]) for v in side} - {-1}
    ix, iy = grid.world_to_cell([s.x for s in world.starts], [s.y for s in world.starts])
    inside = grid.contains(ix, iy)  # a start on the map's own border may round onto the cell past it
    reach_edge = [not inside[k] or int(labels[iy[k], ix[k]]) in edge for k in range(len(world.starts))]
    if any(reach_edge) and not all(reach_edge):
        outside = [f"'{s.name}' at ({s.x:g}, {s.y:g})" for s, out in zip(world.starts, reach_edge) if out]
        raise WorldError(f"{world.label}: start site(s) {_listed(outside)} outside the walls that enclose its "
                         "other starts (the robot could drive off the map from there): move them inside")


# The <option> flags that would change whether the robot collides or moves (contacts, constraints,
# actuation, overridden contact parameters); the solver's own (warmstart, energy, sleep, ...) cannot.
_FLAG_BITS = [(mujoco.mjtDisableBit.mjDSBL_CONTACT, "disable"), (mujoco.mjtDisableBit.mjDSBL_CONSTRAINT, "disable"),
              (mujoco.mjtDisableBit.mjDSBL_ACTUATION, "disable"), (mujoco.mjtEnableBit.mjENBL_OVERRIDE, "enable")]


def _check_options(model: mujoco.MjModel, label: str) -> None:
    """WorldError naming the ``<option>`` settings a world's author would expect to change how the
    robot collides or moves (contact="disable", disabled actuator groups, a medium). The robot never
    takes any of the world's options (``shared.sim.robot.build_model`` compiles under MuJoCo's
    built-in ones), so a world that relies on these would not be the world its author meant; the
    others are ignored."""
    opt = model.opt
    settings = [f'<flag {bit.name.split("_", 1)[1].lower()}="{value}">' for bit, value in _FLAG_BITS
                if (opt.disableflags if value == "disable" else opt.enableflags) & int(bit)]
    if opt.disableactuator:
        settings.append(f"actuatorgroupdisable (mask {opt.disableactuator})")
    settings += [name for name in ("wind", "density", "viscosity") if np.any(np.asarray(getattr(opt, name)) != 0)]
    if settings:
        raise WorldError(f"{label}: <option> sets {', '.join(settings)}, which cogexplore's robot never takes; "
                         "remove it (a world holds static geoms and start sites; the robot's physics is cogexplore's)")


FLOOR_TOLERANCE_M = 0.01
"""How far from z = 0 a floor's top may lie (the robot's disc clears z = 0 by 1 cm)."""


def _top_z(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> float:
    """The highest point of geom ``g`` (inf for a plane that does not face up: a wall or a ceiling)."""
    if int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE):
        return float(data.geom_xpos[g][2]) if data.geom_xmat[g][8] > 1 - 1e-6 else math.inf
    center, half = model.geom_aabb[g][:3], model.geom_aabb[g][3:]
    corners = center + half * np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)])
    return float((data.geom_xpos[g] + corners @ data.geom_xmat[g].reshape(3, 3).T)[:, 2].max())


def _is_floor_plane(model: mujoco.MjModel, data: mujoco.MjData, g: int) -> bool:
    """Whether geom ``g`` is an upward plane at z = 0 (what an unnamed floor is recognised by)."""
    return int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE) and abs(_top_z(model, data, g)) <= FLOOR_TOLERANCE_M


def _check_geoms(model: mujoco.MjModel, data: mujoco.MjData, label: str, floor: set[int]) -> None:
    """WorldError naming the geoms the robot and its depth camera would treat unlike the obstacles
    the map marks: one placed or sized by a NaN or an infinity (MuJoCo only warns of a NaN in the
    MJCF, and such a geom is everywhere and nowhere to the map and the start checks), one fully
    transparent (ray casts pass through alpha 0), one in the robot's own geom group (which the GL
    camera hides), an obstacle whose contype and conaffinity never meet the robot's (it would drive
    through it), one with a contact margin (it would stop the robot short of its surface, where no
    contact is reported)."""
    invisible, hidden, intangible, cushioned, unplaced = [], [], [], [], []
    for g in range(model.ngeom):
        name = f"'{model.geom(g).name}'" if model.geom(g).name else f"#{g}"
        if not all(np.isfinite(a).all() for a in (data.geom_xpos[g], data.geom_xmat[g], model.geom_size[g])):
            unplaced.append(name)
        matid = int(model.geom_matid[g])
        if (model.mat_rgba[matid][3] if matid >= 0 else model.geom_rgba[g][3]) == 0:
            invisible.append(name)
        if int(model.geom_group[g]) == ROBOT_GEOM_GROUP:
            hidden.append(name)
        contype, conaffinity = int(model.geom_contype[g]), int(model.geom_conaffinity[g])
        if g not in floor and not (contype & ROBOT_CONTACT_BITS or conaffinity & ROBOT_CONTACT_BITS):
            intangible.append(f"{name} (contype {contype}, conaffinity {conaffinity})")
        if model.geom_margin[g] != 0:  # < 0: no contact until the robot is that deep inside
            cushioned.append(f"{name} ({model.geom_margin[g]:g} m)")
    problems = []
    if unplaced:
        problems.append(f"geom(s) {_listed(unplaced)} whose position, orientation or size is not finite (a NaN "
                        "or inf in the MJCF, or in a body above them)")
    if invisible:
        problems.append(f"geom(s) {_listed(invisible)} fully transparent (rgba alpha 0): the depth camera "
                        "cannot see them; give them a visible colour")
    if hidden:
        problems.append(f"geom(s) {_listed(hidden)} in group {ROBOT_GEOM_GROUP}, the robot's own, which the GL "
                        "depth camera hides; use another group")
    if intangible:
        problems.append(f"geom(s) {_listed(intangible)} that never collide with the robot (its contype and "
                        f"conaffinity are {ROBOT_CONTACT_BITS}): it would drive through them; give them contype "
                        f"or conaffinity {ROBOT_CONTACT_BITS}, or, for visual-only geoms, add <compiler "
                        "discardvisual=\"true\"/> (the camera would see them as obstacles)")
    if cushioned:
        problems.append(f"geom(s) {_listed(cushioned)} with a contact margin, which would stop the robot short "
                        "of them with no contact to end the episode (or, below 0, let it into them); remove it")
    if problems:
        raise WorldError(f"{label} has " + "; and ".join(problems))


def _geom_extent(model: mujoco.MjModel, data: mujoco.MjData, skip: set[int],
                 starts: list[StartPose]) -> tuple[float, float, float, float]:
    """Union of the obstacle geoms' world bounding boxes (x, y) and the start positions."""
    lo = np.array([min(s.x for s in starts), min(s.y for s in starts)])
    hi = np.array([max(s.x for s in starts), max(s.y for s in starts)])
    found = False
    for g in range(model.ngeom):
        if g in skip or int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE):
            continue
        mat = data.geom_xmat[g].reshape(3, 3)
        centre = data.geom_xpos[g] + mat @ model.geom_aabb[g][:3]
        half = np.abs(mat) @ model.geom_aabb[g][3:]
        lo = np.minimum(lo, centre[:2] - half[:2])
        hi = np.maximum(hi, centre[:2] + half[:2])
        found = True
    if not found:
        lo, hi = lo - 2.0, hi + 2.0
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


# ---------------------------------------------------------------------------
# Resolution and summaries
# ---------------------------------------------------------------------------


def _finite(value: Any) -> float:
    if not is_finite_number(value):  # an integer beyond a float's range is not one either
        raise ValueError(f"{value!r} is not a finite number")
    return float(value)


def _world_fields(world: World) -> dict[str, Any]:
    """A procedural world as JSON fields (:mod:`shared.sim.world_cache`)."""
    return {"name": world.name, "kind": world.kind, "mjcf": world.mjcf, "extent": list(world.extent),
            "starts": [[s.x, s.y, s.yaw, s.name] for s in world.starts]}


def _world_from_fields(fields: dict[str, Any]) -> World:
    """The procedural world in :func:`_world_fields`'s fields; ValueError naming what is wrong."""
    if fields.get("kind") != "procedural" or not isinstance(fields.get("mjcf"), str):
        raise ValueError("it does not hold a procedural world")
    extent, starts = fields.get("extent"), fields.get("starts")
    if not isinstance(extent, list) or len(extent) != 4 or not isinstance(starts, list):
        raise ValueError("its extent or starts are malformed")
    poses = []
    for start in starts:
        if not isinstance(start, list) or len(start) != 4 or not isinstance(start[3], str):
            raise ValueError("a start pose is malformed")
        poses.append(StartPose(_finite(start[0]), _finite(start[1]), _finite(start[2]), start[3]))
    return World(name=str(fields["name"]), mjcf=fields["mjcf"], starts=tuple(poses),
                 extent=tuple(_finite(v) for v in extent), kind="procedural")


@functools.lru_cache(maxsize=32)
def _cached_world(name: str) -> World:
    if name in BUILTIN_WORLDS:
        return BUILTIN_WORLDS[name]()
    seed_text = name[len(PROCEDURAL_PREFIX):]
    if not is_procedural_seed(seed_text):
        raise WorldError(f"world {name[:40]!r}: the seed after '{PROCEDURAL_PREFIX}' must be an integer >= 0 "
                         "of at most 18 digits")
    return cached_world(name, lambda: procedural_world(int(seed_text)), _world_fields, _world_from_fields)


def canonical_world_name(name: str) -> str:
    """The name ``load_world(name)``'s World carries: ``procedural:007`` is ``procedural:7``; every
    other name as written."""
    seed_text = name[len(PROCEDURAL_PREFIX):]
    if name.startswith(PROCEDURAL_PREFIX) and is_procedural_seed(seed_text):
        return f"{PROCEDURAL_PREFIX}{int(seed_text)}"
    return name


def load_world(name: str) -> World:
    """Resolve a built-in name, ``procedural:<seed>`` or an MJCF path to a World.

    Built-in and procedural worlds are cached (they are immutable), procedural ones also on disk
    (:mod:`shared.sim.world_cache`); files are read anew."""
    if not isinstance(name, str) or not name:
        raise WorldError(f"a world name must be a non-empty string, got {name!r}")
    if name in BUILTIN_WORLDS or name.startswith(PROCEDURAL_PREFIX):
        return _cached_world(canonical_world_name(name))
    if name.lower().endswith(".xml") or Path(name).is_file():
        return load_world_file(name)
    raise WorldError(f"unknown world {name!r}: use a built-in world {sorted(BUILTIN_WORLDS)}, "
                     f"'{PROCEDURAL_PREFIX}<seed>', or the path of an MJCF file")


def obstacle_geom_count(world: World) -> int:
    """Geoms in the static scene other than the floor."""
    model = mujoco.MjSpec.from_string(world.mjcf).compile()
    floor = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_GEOM)
    return int(model.ngeom - (1 if floor >= 0 else 0))


def world_summary(name: str) -> dict[str, Any]:
    """Plain-data facts about a world (for the ``worlds`` CLI and reports)."""
    world = load_world(name)
    grid = maps.occupancy_grid(world)
    w, h = world.size_m
    return {
        "name": world.name,
        "kind": world.kind,
        "size_m": [round(w, 3), round(h, 3)],
        "extent": [round(v, 3) for v in world.extent],
        "num_starts": len(world.starts),
        "num_obstacle_geoms": obstacle_geom_count(world),
        "free_area_m2": round(maps.free_area_m2(grid), 2),
        "connected": maps.is_connected(grid, EnvConfig().robot_radius_m),
    }
