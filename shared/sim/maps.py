"""Top-down maps of a world: occupancy grid, connectivity, visit heatmaps, coverage, PNG.

The occupancy grid is rasterised from the *compiled* MuJoCo model, so it works for any
world, user MJCF included. A cell is occupied when some obstacle geom comes within half a
cell of the cell's centre at any height in :data:`OCCUPANCY_BAND_M` (the band the robot's
body and camera occupy). Measuring "within half a cell" rather than "centre inside" keeps
walls thinner than a cell from slipping between cell centres, which would let the flood
fill leak through them; it costs a fringe of at most half a cell around each obstacle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Protocol, Sequence

import mujoco
import numpy as np

from shared.config import SensorConfig
from shared.errors import CogexploreError
from shared.files import save_png
from shared.sim.robot import FLOOR_GEOM
from shared.sim.sensor import intrinsics


class Mappable(Protocol):
    """What a map is made of: a ``shared.sim.world.World`` (which builds its own maps with this
    module, so this module names the fields it reads instead of importing it)."""

    name: str
    mjcf: str
    starts: Sequence[Any]
    extent: tuple[float, float, float, float]

OCCUPANCY_BAND_M = (0.02, 0.40)
"""Heights (m) at which obstacles count: the robot body spans 0.01-0.31 m and the camera
sits at 0.35 m, so anything here either blocks the body or fills the camera's horizon."""
_BAND_STEP_M = 0.05


class MapError(CogexploreError):
    """Bad input to a map function (shape, resolution, coordinates)."""


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """A top-down boolean grid: ``occupied[iy, ix]`` is the cell whose lower-left corner is
    ``origin_xy + (ix, iy) * resolution_m``."""

    origin_xy: tuple[float, float]
    """World (x, y) of the grid's lower-left corner, metres."""
    resolution_m: float
    """Cell side, metres."""
    occupied: np.ndarray = field(repr=False)
    """(ny, nx) bool; read-only so that cached grids cannot be changed by a caller."""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise MapError(f"resolution_m must be a positive number, got {self.resolution_m!r}")
        occ = np.asarray(self.occupied)
        if occ.ndim != 2 or occ.dtype != np.bool_:
            raise MapError(f"occupied must be a 2-D bool array, got {occ.dtype} {occ.shape}")
        occ = occ.copy() if occ.flags.writeable else occ
        occ.flags.writeable = False
        object.__setattr__(self, "occupied", occ)
        object.__setattr__(self, "origin_xy", (float(self.origin_xy[0]), float(self.origin_xy[1])))

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx)."""
        return self.occupied.shape  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, ymin, xmax, ymax) of the grid in metres."""
        ny, nx = self.shape
        x0, y0 = self.origin_xy
        return x0, y0, x0 + nx * self.resolution_m, y0 + ny * self.resolution_m

    @property
    def cell_area_m2(self) -> float:
        return self.resolution_m ** 2

    @property
    def free_area_m2(self) -> float:
        return free_area_m2(self)

    def world_to_cell(self, x: np.ndarray | float, y: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices (ix, iy) containing world points; may lie outside the grid (see contains)."""
        ix = np.floor((np.asarray(x, dtype=np.float64) - self.origin_xy[0]) / self.resolution_m).astype(np.int64)
        iy = np.floor((np.asarray(y, dtype=np.float64) - self.origin_xy[1]) / self.resolution_m).astype(np.int64)
        return ix, iy

    def cell_to_world(self, ix: np.ndarray | int, iy: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """World (x, y) of cell centres."""
        x = self.origin_xy[0] + (np.asarray(ix, dtype=np.float64) + 0.5) * self.resolution_m
        y = self.origin_xy[1] + (np.asarray(iy, dtype=np.float64) + 0.5) * self.resolution_m
        return x, y

    def contains(self, ix: np.ndarray | int, iy: np.ndarray | int) -> np.ndarray:
        ny, nx = self.shape
        ix, iy = np.asarray(ix), np.asarray(iy)
        return (ix >= 0) & (ix < nx) & (iy >= 0) & (iy < ny)

    def is_free(self, x: float, y: float) -> bool:
        """True if the world point lies in a free cell of the grid."""
        ix, iy = self.world_to_cell(x, y)
        return bool(self.contains(ix, iy)) and not bool(self.occupied[iy, ix])


def free_area_m2(grid: OccupancyGrid) -> float:
    """Area of the grid's free cells, m^2."""
    return float(np.count_nonzero(~grid.occupied)) * grid.cell_area_m2


# ---------------------------------------------------------------------------
# Rasterisation
# ---------------------------------------------------------------------------


def empty_grid(extent: tuple[float, float, float, float], resolution_m: float) -> OccupancyGrid:
    """An all-free grid covering ``extent`` = (xmin, ymin, xmax, ymax)."""
    xmin, ymin, xmax, ymax = extent
    if not (math.isfinite(resolution_m) and resolution_m > 0):
        raise MapError(f"resolution_m must be a positive number, got {resolution_m!r}")
    if not (xmax > xmin and ymax > ymin):
        raise MapError(f"extent {extent} is empty")
    nx = max(1, int(math.ceil((xmax - xmin) / resolution_m - 1e-9)))
    ny = max(1, int(math.ceil((ymax - ymin) / resolution_m - 1e-9)))
    if nx * ny > 25_000_000:
        raise MapError(f"grid of {nx} x {ny} cells over {extent} at {resolution_m} m is too large")
    return OccupancyGrid((xmin, ymin), resolution_m, np.zeros((ny, nx), dtype=bool))


def _outside_distance(local: np.ndarray, gtype: int, size: np.ndarray) -> np.ndarray:
    """Distance from points (N, 3) in a geom's frame to the geom (0 inside); conservative
    (never more than the true distance) where not exact."""
    G = mujoco.mjtGeom
    if gtype == G.mjGEOM_BOX:
        q = np.maximum(np.abs(local) - size[:3], 0.0)
        return np.linalg.norm(q, axis=1)
    if gtype == G.mjGEOM_SPHERE:
        return np.maximum(np.linalg.norm(local, axis=1) - size[0], 0.0)
    if gtype == G.mjGEOM_CYLINDER:
        radial = np.maximum(np.hypot(local[:, 0], local[:, 1]) - size[0], 0.0)
        axial = np.maximum(np.abs(local[:, 2]) - size[1], 0.0)
        return np.hypot(radial, axial)
    if gtype == G.mjGEOM_CAPSULE:
        z = np.clip(local[:, 2], -size[1], size[1])
        return np.maximum(np.linalg.norm(local - np.stack([0 * z, 0 * z, z], axis=1), axis=1) - size[0], 0.0)
    if gtype == G.mjGEOM_ELLIPSOID:
        # The k-scaled ellipsoid lies at least (k - 1) * min(size) outside the geom.
        k = np.linalg.norm(local / size[:3], axis=1)
        return np.maximum(k - 1.0, 0.0) * float(np.min(size[:3]))
    if gtype == G.mjGEOM_PLANE:
        return np.maximum(local[:, 2], 0.0)
    raise MapError(f"no distance test for geom type {gtype}")


def _cell_window(grid: OccupancyGrid, lo: np.ndarray, hi: np.ndarray) -> tuple[slice, slice] | None:
    """Index window of cells whose centres may lie within [lo, hi] (x, y)."""
    ny, nx = grid.shape
    x0, y0 = grid.origin_xy
    r = grid.resolution_m
    ix0 = max(0, int(math.floor((lo[0] - x0) / r - 0.5)))
    ix1 = min(nx, int(math.ceil((hi[0] - x0) / r + 0.5)))
    iy0 = max(0, int(math.floor((lo[1] - y0) / r - 0.5)))
    iy1 = min(ny, int(math.ceil((hi[1] - y0) / r + 0.5)))
    if ix0 >= ix1 or iy0 >= iy1:
        return None
    return slice(iy0, iy1), slice(ix0, ix1)


def _convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of 2-D points (Andrew's monotone chain)."""
    pts = np.unique(points, axis=0)
    if len(pts) < 3:
        return pts

    def cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    lower: list[np.ndarray] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[np.ndarray] = []
    for p in pts[::-1]:
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return np.array(lower[:-1] + upper[:-1])


def _polygon_distance_ok(xy: np.ndarray, hull: np.ndarray, tol: float) -> np.ndarray:
    """Points within ``tol`` of a convex CCW polygon (edge half-planes pushed out by tol:
    slightly generous at vertices, which is the conservative side)."""
    inside = np.ones(len(xy), dtype=bool)
    n = len(hull)
    for i in range(n):
        a, b = hull[i], hull[(i + 1) % n]
        edge = b - a
        length = float(np.hypot(*edge)) or 1.0
        # Signed distance to the left of the edge (inside for a CCW polygon).
        side = (edge[0] * (xy[:, 1] - a[1]) - edge[1] * (xy[:, 0] - a[0])) / length
        inside &= side >= -tol
    return inside


def rasterise_geom(occupied: np.ndarray, grid: OccupancyGrid, gtype: int, size: np.ndarray,
                   pos: np.ndarray, mat: np.ndarray, aabb: np.ndarray,
                   mesh_vertices: np.ndarray | None = None) -> None:
    """Mark (in place, into ``occupied`` shaped like ``grid``) the cells one geom reaches.

    ``mat`` is the geom's 3x3 world rotation, ``aabb`` its local box (centre xyz, half xyz)
    as in ``MjModel.geom_aabb``, ``mesh_vertices`` (V, 3) in the geom frame for meshes.
    """
    G = mujoco.mjtGeom
    size = np.asarray(size, dtype=np.float64)
    pos = np.asarray(pos, dtype=np.float64)
    mat = np.asarray(mat, dtype=np.float64).reshape(3, 3)
    tol = grid.resolution_m / 2
    z_lo, z_hi = OCCUPANCY_BAND_M
    if gtype == G.mjGEOM_PLANE:
        if abs(mat[2, 2]) > 0.999:
            return  # horizontal planes are floors or ceilings, never walls
        lo, hi = np.array(grid.extent[:2]), np.array(grid.extent[2:])
    else:
        centre = pos + mat @ aabb[:3]
        half = np.abs(mat) @ aabb[3:]
        if centre[2] + half[2] < z_lo - tol or centre[2] - half[2] > z_hi + tol:
            return  # entirely above or below the band
        lo, hi = centre[:2] - half[:2] - tol, centre[:2] + half[:2] + tol
    window = _cell_window(grid, lo, hi)
    if window is None:
        return
    sy, sx = window
    ix, iy = np.meshgrid(np.arange(sx.start, sx.stop), np.arange(sy.start, sy.stop))
    cx, cy = grid.cell_to_world(ix.ravel(), iy.ravel())
    if gtype == G.mjGEOM_MESH and mesh_vertices is not None and len(mesh_vertices) >= 3:
        world_v = mesh_vertices @ mat.T + pos
        hull = _convex_hull(world_v[:, :2])
        if len(hull) >= 3:
            hit = _polygon_distance_ok(np.stack([cx, cy], axis=1), hull, tol)
        else:
            hit = np.ones(cx.shape, dtype=bool)
    elif gtype in (G.mjGEOM_BOX, G.mjGEOM_SPHERE, G.mjGEOM_CYLINDER, G.mjGEOM_CAPSULE,
                   G.mjGEOM_ELLIPSOID, G.mjGEOM_PLANE):
        zs = np.arange(z_lo, z_hi + 1e-9, _BAND_STEP_M)
        pts = np.empty((cx.size, zs.size, 3))
        pts[:, :, 0] = cx[:, None]
        pts[:, :, 1] = cy[:, None]
        pts[:, :, 2] = zs[None, :]
        local = (pts.reshape(-1, 3) - pos) @ mat  # row form of mat.T @ (p - pos)
        dist = _outside_distance(local, gtype, size).reshape(cx.size, zs.size)
        hit = (dist <= tol).any(axis=1)
    else:
        # Height fields, SDFs and unknown types: their bounding box is the safe footprint.
        hit = np.ones(cx.size, dtype=bool)
    sub = occupied[sy, sx]
    sub |= hit.reshape(sub.shape)
    occupied[sy, sx] = sub


_GRID_CACHE: dict[tuple[str, str, float], OccupancyGrid] = {}


def occupancy_grid(world: Mappable, resolution_m: float = 0.05) -> OccupancyGrid:
    """Occupancy of ``world.extent`` rasterised from the compiled static scene (cached per
    world name, scene text and resolution)."""
    key = (world.name, world.mjcf, float(resolution_m))
    cached = _GRID_CACHE.get(key)
    if cached is not None:
        return cached
    try:
        grid = empty_grid(world.extent, resolution_m)
    except MapError as exc:  # the world's, not a caller's: name it (an obstacle placed kilometres away?)
        raise MapError(f"world {world.name!r}: {exc}: its obstacles and starts span more than a map of "
                       "rooms holds (one placed far from the rest?)") from None
    model = mujoco.MjSpec.from_string(world.mjcf).compile()
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    occupied = np.zeros(grid.shape, dtype=bool)
    floor_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_GEOM)
    for g in range(model.ngeom):
        if g == floor_id:
            continue
        vertices = None
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_dataid[g] >= 0:
            mid = model.geom_dataid[g]
            adr, num = model.mesh_vertadr[mid], model.mesh_vertnum[mid]
            vertices = np.asarray(model.mesh_vert[adr:adr + num], dtype=np.float64)
        rasterise_geom(occupied, grid, int(model.geom_type[g]), model.geom_size[g], data.geom_xpos[g],
                       data.geom_xmat[g], model.geom_aabb[g], vertices)
    grid = OccupancyGrid(grid.origin_xy, grid.resolution_m, occupied)
    if len(_GRID_CACHE) > 64:
        _GRID_CACHE.clear()
    _GRID_CACHE[key] = grid
    return grid


# ---------------------------------------------------------------------------
# Connectivity
# ---------------------------------------------------------------------------


def clearance_map(occupied: np.ndarray, resolution_m: float, max_m: float | None = None) -> np.ndarray:
    """Exact Euclidean distance (m) from each cell centre to the nearest occupied cell centre
    (0 on occupied cells); separable two-pass transform, no scipy needed. With ``max_m``, only
    distances below it are exact and the others read ``max_m`` or more: the row pass costs one
    sweep per cell of the largest distance it resolves, so a world with an obstacle kilometres
    from the rest would otherwise take hours."""
    occ = np.asarray(occupied, dtype=bool)
    if occ.ndim != 2:
        raise MapError(f"occupied must be a 2-D array, got shape {occ.shape}")
    ny, nx = occ.shape
    if not occ.any():
        return np.full((ny, nx), np.inf)
    big = float(nx + ny + 1)
    g = np.empty((ny, nx))
    d = np.full(nx, big)
    for iy in range(ny):  # cells to the nearest occupied cell in the same column: down, then up
        d = np.where(occ[iy], 0.0, d + 1.0)
        g[iy] = d
    d = np.full(nx, big)
    for iy in range(ny - 1, -1, -1):
        d = np.where(occ[iy], 0.0, d + 1.0)
        g[iy] = np.minimum(g[iy], d)
    # Row pass: out(x) = min over x' of (x - x')^2 + g(x')^2, offset by offset. An offset dx can
    # only lower cells whose value is above dx^2, so the loop ends once none is: a room's walls
    # keep that to a few metres of cells, not the grid's width (7 ms instead of 230 for all pairs
    # on a procedural world: an actor builds a hundred of them).
    out = g ** 2
    g2 = out.copy()
    # A cell whose distance is below max_m has its nearest occupied cell fewer than max_m away.
    stop = math.inf if max_m is None else (max_m / resolution_m) ** 2
    for dx in range(1, nx):
        shift = dx * dx
        if shift >= min(out.max(), stop):
            break
        np.minimum(out[:, dx:], g2[:, :-dx] + shift, out=out[:, dx:])
        np.minimum(out[:, :-dx], g2[:, dx:] + shift, out=out[:, :-dx])
    return np.sqrt(out) * resolution_m


def inflate(occupied: np.ndarray, radius_cells: float) -> np.ndarray:
    """Cells within ``radius_cells`` (centre to centre) of an occupied cell.

    Outside the grid counts as free, so a world without boundary walls is not closed in."""
    occupied = np.asarray(occupied, dtype=bool)
    out = occupied.copy()
    r = int(math.floor(radius_cells))
    ny, nx = occupied.shape
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if (dx or dy) and dx * dx + dy * dy <= radius_cells * radius_cells + 1e-9:
                src = occupied[max(0, -dy):ny - max(0, dy), max(0, -dx):nx - max(0, dx)]
                out[max(0, dy):ny - max(0, -dy), max(0, dx):nx - max(0, -dx)] |= src
    return out


def label_components(mask: np.ndarray) -> tuple[np.ndarray, int]:
    """4-connected components of a bool mask: (labels (ny, nx) int32, -1 off the mask; count).

    Labels are numbered in row-major order of each component's first cell. Works on runs
    of cells per row (union-find over runs), which is fast without scipy."""
    mask = np.asarray(mask, dtype=bool)
    ny, nx = mask.shape
    padded = np.zeros((ny, nx + 2), dtype=np.int8)
    padded[:, 1:-1] = mask
    d = np.diff(padded, axis=1)
    starts = np.argwhere(d == 1)
    ends = np.argwhere(d == -1)
    rows, s, e = starts[:, 0], starts[:, 1], ends[:, 1]  # run covers columns [s, e)
    n_runs = len(rows)
    parent = list(range(n_runs))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    row_first = np.searchsorted(rows, np.arange(ny + 1))
    for r in range(ny - 1):
        i, i_end = int(row_first[r]), int(row_first[r + 1])
        j, j_end = i_end, int(row_first[r + 2])
        while i < i_end and j < j_end:
            if s[i] < e[j] and s[j] < e[i]:  # column intervals overlap: 4-connected
                a, b = find(i), find(j)
                if a != b:
                    parent[max(a, b)] = min(a, b)
            if e[i] < e[j]:
                i += 1
            else:
                j += 1
    labels = np.full((ny, nx), -1, dtype=np.int32)
    compact: dict[int, int] = {}
    for k in range(n_runs):
        root = find(k)
        lab = compact.setdefault(root, len(compact))
        labels[rows[k], s[k]:e[k]] = lab
    return labels, len(compact)


def traversable(grid: OccupancyGrid, robot_radius_m: float) -> np.ndarray:
    """Cells where the robot's centre can be without its disc overlapping an occupied cell."""
    return ~inflate(grid.occupied, robot_radius_m / grid.resolution_m)


def free_components(grid: OccupancyGrid, robot_radius_m: float = 0.18) -> tuple[np.ndarray, int]:
    """Connected components of the traversable space (the robot's configuration space)."""
    return label_components(traversable(grid, robot_radius_m))


def is_connected(grid: OccupancyGrid, robot_radius_m: float = 0.18) -> bool:
    """True if the traversable space is one piece (no pocket the robot could not reach)."""
    return free_components(grid, robot_radius_m)[1] == 1


# ---------------------------------------------------------------------------
# Visits, heatmaps, coverage
# ---------------------------------------------------------------------------


def visit_counts(grid: OccupancyGrid, xy: np.ndarray | Sequence[Sequence[float]]) -> np.ndarray:
    """(ny, nx) int64 count of points per cell; points outside the grid are not counted."""
    pts = np.asarray(xy, dtype=np.float64)
    if pts.size == 0:
        return np.zeros(grid.shape, dtype=np.int64)
    if pts.ndim != 2 or pts.shape[1] < 2:
        raise MapError(f"xy must be (N, 2) points, got shape {pts.shape}")
    ix, iy = grid.world_to_cell(pts[:, 0], pts[:, 1])
    keep = grid.contains(ix, iy) & np.isfinite(pts[:, 0]) & np.isfinite(pts[:, 1])
    counts = np.zeros(grid.shape, dtype=np.int64)
    np.add.at(counts, (iy[keep], ix[keep]), 1)
    return counts


def normalize_heatmap(counts: np.ndarray) -> np.ndarray:
    """Counts scaled to [0, 1] by the largest count (the paper's heatmaps); all zeros stay 0."""
    c = np.asarray(counts, dtype=np.float64)
    if np.any(c < 0) or not np.all(np.isfinite(c)):
        raise MapError("counts must be finite and non-negative")
    peak = c.max(initial=0.0)
    return c / peak if peak > 0 else np.zeros_like(c)


class CoverageTracker:
    """Free cells the depth camera has seen along its horizon row over an episode."""

    def __init__(self, grid: OccupancyGrid, sensor_cfg: SensorConfig | None = None):
        self.grid = grid
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self._seen = np.zeros(grid.shape, dtype=bool)
        self._free = ~grid.occupied
        self._free_area = free_area_m2(grid)

    def reset(self) -> None:
        self._seen[:] = False

    def restore(self, seen: np.ndarray) -> None:
        """Set the seen cells to a copy of an earlier :attr:`seen` (a snapshot's)."""
        if np.shape(seen) != self._seen.shape:
            raise MapError(f"seen has shape {np.shape(seen)}, this grid is {self._seen.shape}")
        self._seen[:] = seen

    @property
    def seen(self) -> np.ndarray:
        """(ny, nx) bool: free cells seen so far (a copy)."""
        return self._seen.copy()

    @property
    def seen_area_m2(self) -> float:
        return float(np.count_nonzero(self._seen)) * self.grid.cell_area_m2

    @property
    def seen_fraction(self) -> float:
        """Seen area over the grid's free area (0 for a grid with no free cell)."""
        return self.seen_area_m2 / self._free_area if self._free_area > 0 else 0.0

    def observe(self, x: float, y: float, yaw: float, depth_m: np.ndarray,
                sensor_cfg: SensorConfig | None = None) -> float:
        """Mark the free cells seen from pose (x, y, yaw) in a depth image; returns the
        newly seen area in m^2.

        A cell is seen when its centre projects into an image column (the camera's pinhole
        model) and lies nearer along the optical axis than that column's depth on the horizon
        row, or than the sensor's maximum range where the pixel is 0 (no return; with a
        ``min_range_m``, only where the column sees the floor). Testing cell
        centres against the pixel that covers them, rather than marching one ray per column,
        counts the whole field of view at any image width: 40 rays leave most cells beyond
        ~2 m between them, and a ray grazing a cell's corner would count the whole cell."""
        cfg = sensor_cfg or self.sensor_cfg
        depth = np.asarray(depth_m, dtype=np.float64)
        if depth.shape != (cfg.height, cfg.width):
            raise MapError(f"depth_m has shape {depth.shape}, expected ({cfg.height}, {cfg.width}) "
                           "from the sensor config")
        h = cfg.height
        # The optical axis is horizontal, so the horizon lies on the centre row(s).
        rows = depth[[h // 2 - 1, h // 2]] if h % 2 == 0 else depth[[h // 2]]
        rows = np.where(rows > 0, rows, np.inf)
        horizon = rows.min(axis=0)
        # Depth is along the optical axis, and so is the range gate: a 0 pixel means "beyond
        # max range" on that axis, or, with a min_range_m, an obstacle nearer than that, which
        # hides the floor below it too: only a column with some return below the horizon is open.
        beyond = np.full(cfg.width, True) if cfg.min_range_m <= 0 else (depth[(h + 1) // 2:] > 0).any(axis=0)
        reach = np.where(np.isfinite(horizon), np.minimum(horizon, cfg.max_range_m),
                         np.where(beyond, cfg.max_range_m, 0.0))
        fx, _, cx_px, _ = intrinsics(cfg)
        ox = x + cfg.mount_forward_m * math.cos(yaw)
        oy = y + cfg.mount_forward_m * math.sin(yaw)
        fwd, left = np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])
        # The view is the triangle from the camera to the two far corners of the image at max range.
        half = cfg.max_range_m * math.tan(math.radians(cfg.hfov_deg) / 2)
        far = np.array([ox, oy]) + cfg.max_range_m * fwd
        corners = np.stack([[ox, oy], far + half * left, far - half * left])
        window = _cell_window(self.grid, corners.min(axis=0), corners.max(axis=0))
        if window is None:
            return 0.0
        sy, sx = window
        ix, iy = np.meshgrid(np.arange(sx.start, sx.stop), np.arange(sy.start, sy.stop))
        px, py = self.grid.cell_to_world(ix, iy)
        axial = (px - ox) * fwd[0] + (py - oy) * fwd[1]
        lateral = (px - ox) * left[0] + (py - oy) * left[1]
        ahead = axial > 0
        # Column whose pixel the centre projects into (column 0 is the left edge: +lateral).
        u = np.where(ahead, cx_px - fx * lateral / np.where(ahead, axial, 1.0), -1.0)
        col = np.floor(np.clip(u, -1.0, cfg.width)).astype(np.int64)  # centres a hair ahead: no overflow
        in_view = ahead & (col >= 0) & (col < cfg.width)
        seen = in_view & (axial < reach[np.clip(col, 0, cfg.width - 1)]) & self._free[sy, sx]
        before = np.count_nonzero(self._seen)
        self._seen[sy, sx] |= seen
        return float(np.count_nonzero(self._seen) - before) * self.grid.cell_area_m2


# ---------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------


HEATMAP_CMAP = "YlOrRd"
"""Pale yellow (rare) to dark red (busiest): never as dark as an obstacle."""
MAP_FREE_RGB = (244, 242, 236)
"""Free cells on every top-down map (these figures and the env's ``rgb_array`` frames)."""
MAP_OBSTACLE_RGB = (43, 43, 43)
"""Occupied cells on every top-down map."""


def plain_text(text: str) -> str:
    """``text`` for a matplotlib title or label, shown as written: a model, run or world file named
    ``a$x$b`` would otherwise be typeset as mathtext, and one named ``a$\\x$`` fail to draw."""
    return text.replace("$", r"\$")


def draw_map(ax: Any, world: Mappable, grid: OccupancyGrid, heatmap: np.ndarray | None = None,
             trajectories: Iterable[np.ndarray] | None = None, title: str | None = None,
             small: bool = False) -> Any:
    """Draw the top-down map on a matplotlib axis: obstacles dark, starts as numbered arrows
    along their headings, optional heatmap (2-D cells over the grid's extent, 0 = not drawn) and
    trajectories (each (N, 2+) xy). ``title`` (default the world's name) is plain text. Returns
    the heatmap's image (for a colorbar) or None."""
    from matplotlib.colors import ListedColormap

    xmin, ymin, xmax, ymax = grid.extent
    cmap = ListedColormap([np.divide(MAP_FREE_RGB, 255), np.divide(MAP_OBSTACLE_RGB, 255)])
    ax.imshow(grid.occupied.astype(np.uint8), origin="lower", extent=(xmin, xmax, ymin, ymax),
              cmap=cmap, vmin=0, vmax=1, interpolation="nearest")
    im = None
    if heatmap is not None:
        hm = np.asarray(heatmap, dtype=np.float64)
        if hm.ndim != 2:
            raise MapError(f"heatmap must be 2-D (cells over the grid's extent), got shape {hm.shape}")
        im = ax.imshow(np.ma.masked_where(hm <= 0, hm), origin="lower", extent=(xmin, xmax, ymin, ymax),
                       cmap=HEATMAP_CMAP, alpha=0.9, vmin=0.0, vmax=max(1.0, float(hm.max())),
                       interpolation="nearest")
    for k, traj in enumerate(trajectories or ()):
        t = np.asarray(traj, dtype=np.float64)
        if t.ndim != 2 or t.shape[1] < 2:
            raise MapError(f"trajectory {k} must be (N, 2) points, got shape {t.shape}")
        ax.plot(t[:, 0], t[:, 1], lw=1.0, alpha=0.8)
    arrow = 0.06 * max(xmax - xmin, ymax - ymin)
    for i, s in enumerate(world.starts):
        ax.annotate("", xy=(s.x + arrow * math.cos(s.yaw), s.y + arrow * math.sin(s.yaw)), xytext=(s.x, s.y),
                    arrowprops=dict(arrowstyle="-|>", color="#d62728", lw=1.2 if small else 1.6))
        ax.text(s.x - 0.35 * arrow * math.cos(s.yaw), s.y - 0.35 * arrow * math.sin(s.yaw), str(i + 1),
                color="#1f3fbf", fontsize=7 if small else 8, ha="center", va="center", fontweight="bold")
    ax.set_xlim(xmin, xmax)
    ax.set_ylim(ymin, ymax)
    ax.set_aspect("equal")
    ax.set_title(plain_text(title if title is not None else world.name), fontsize=10 if small else None)
    if small:
        ax.tick_params(labelsize=7)
    else:
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
    return im


MAX_FIGURE_ASPECT = 2.0
"""A map figure's width over height at most (its inverse at least), whatever the world's shape: a
corridor 100 times longer than wide would make a figure 100,000 pixels wide; the map keeps its shape
inside."""


def drawable_aspect(width_over_height: float) -> float:
    """``width_over_height`` bounded to [1 / MAX_FIGURE_ASPECT, MAX_FIGURE_ASPECT]."""
    return min(MAX_FIGURE_ASPECT, max(1 / MAX_FIGURE_ASPECT, width_over_height))


def render_map_png(world: Mappable, grid: OccupancyGrid, out_path: str | Path,
                   trajectories: Iterable[np.ndarray] | None = None, heatmap: np.ndarray | None = None,
                   title: str | None = None, dpi: int = 120) -> Path:
    """The map of :func:`draw_map` as a PNG (with a colorbar for a heatmap). Returns the path."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    xmin, ymin, xmax, ymax = grid.extent
    w, h = xmax - xmin, ymax - ymin
    fig = Figure(figsize=(6.5 * drawable_aspect(w / h) + (1.2 if heatmap is not None else 0.0), 6.5))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    im = draw_map(ax, world, grid, heatmap=heatmap, trajectories=trajectories, title=title)
    if im is not None:
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="normalised visits")
    fig.tight_layout()
    return save_png(fig, out_path, dpi)
