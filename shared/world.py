"""Indoor worlds: static scenes of walls, cylinders and clutter, with start poses.

A :class:`World` is the static scene as MJCF text (no robot; ``shared.robot`` adds it)
plus its start poses and floor extent. ``load_world`` resolves a name:

- built-in names (``box-room``, ``paper-indoor``, ``corridor``),
- ``procedural:<seed>``,
- a path to a user MJCF file whose start poses are sites named ``start_*``.

Every static geom except the floor plane (named ``floor``) is an obstacle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco

from shared.robot import FLOOR_GEOM

# 2 m: taller than any ray of the 0.35 m high camera climbs within its 4 m range, so every
# obstacle fills its image columns from the floor up (the depth camera's fast path relies on it).
WALL_HEIGHT_M = 2.0
OBSTACLE_RGBA = (0.75, 0.72, 0.65, 1.0)


class WorldError(ValueError):
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

    @property
    def size_m(self) -> tuple[float, float]:
        xmin, ymin, xmax, ymax = self.extent
        return xmax - xmin, ymax - ymin


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
        """A straight wall segment from (x0, y0) to (x1, y1)."""
        length = math.hypot(x1 - x0, y1 - y0)
        self.box((x0 + x1) / 2, (y0 + y1) / 2, length / 2 + thickness / 2, thickness / 2,
                 yaw=math.atan2(y1 - y0, x1 - x0), height=height)

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

    def build(self, name: str, starts: list[StartPose]) -> World:
        return World(name=name, mjcf=self.spec.to_xml(), starts=tuple(starts), extent=self.extent)


def box_room(name: str = "box-room") -> World:
    """A 4 x 4 m room with one box and one cylinder; small and fast, for tests."""
    b = SceneBuilder(name, (-2.0, -2.0, 2.0, 2.0))
    b.boundary()
    b.box(1.0, 1.0, 0.3, 0.3)
    b.cylinder(-1.0, 0.8, 0.25)
    starts = [StartPose(-1.2, -1.2, math.pi / 4, "sw"), StartPose(1.2, -1.2, 3 * math.pi / 4, "se"),
              StartPose(0.0, 0.0, -math.pi / 2, "centre"), StartPose(-1.2, 1.3, 0.0, "nw")]
    return b.build(name, starts)


BUILTIN_WORLDS = {
    "box-room": box_room,
}


def load_world(name: str) -> World:
    """Resolve a built-in name, ``procedural:<seed>`` or an MJCF path to a World."""
    if name in BUILTIN_WORLDS:
        return BUILTIN_WORLDS[name]()
    raise WorldError(f"unknown world {name!r}; built-in worlds: {sorted(BUILTIN_WORLDS)}")
