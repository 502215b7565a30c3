"""The Kinect-like depth camera.

Depth is metric distance along the optical axis (what a Kinect reports), not ray length;
pixels with no return within ``[min_range_m, max_range_m]`` read 0, as in the paper's
images. Image row 0 is the top, column 0 the left.

Two backends produce the same image:

- ``raycast`` (default): ``mujoco.mj_multiRay`` from the camera centre through every
  pixel centre. No OpenGL, deterministic, exact. Casting all H x W rays costs ~0.3 us per
  ray and geom (18 ms a frame in a 66-geom room), so when the world allows it the camera
  casts one horizontal ray per *column* instead and composes the image exactly: if every
  obstacle is an upright prism (a box turned only about z, or an upright cylinder) standing
  on the floor and taller than the highest ray can climb within range, then every pixel of
  a column meets the same obstacle at the same axial depth, or the floor first, whose depth
  per row is known in closed form. Worlds that break the condition (spheres, tables, low
  boxes, tilted geoms) get the per-pixel cast; ``DepthCamera.mode`` says which is used.
- ``gl``: MuJoCo's renderer with the depth buffer (needs ``MUJOCO_GL=egl`` or ``osmesa``
  set before mujoco is imported). It samples the same pinhole model through the camera's
  intrinsics; away from depth discontinuities it agrees with ``raycast`` to within
  ``GL_TOLERANCE_M`` (depth-buffer quantisation), at edges a pixel may take either side.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from shared.config import SensorConfig
from shared.depth import range_gate
from shared.errors import CogexploreError
from shared.sim.robot import CAMERA_NAME, FLOOR_GEOM, ROBOT_BODY, ROBOT_GEOM_GROUP

GL_TOLERANCE_M = 0.02
GL_NEAR_M = 0.01
"""The GL camera's near clip plane (m), or min_range_m where that is nearer: nothing the camera
should see is clipped."""
KINECT_NOISE_OFFSET_M = 0.4
"""Distance (m) below which the depth noise no longer shrinks (``SensorConfig.noise_quadratic_per_m``):
the z0 of Nguyen et al. 2012's fit sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m, valid from ~0.5 m."""


class SensorError(CogexploreError):
    """The depth camera cannot work here (the 'gl' backend without an OpenGL context)."""


def intrinsics(cfg: SensorConfig) -> tuple[float, float, float, float]:
    """Pinhole intrinsics (fx, fy, cx, cy) in pixels, from the fields of view."""
    fx = (cfg.width / 2) / math.tan(math.radians(cfg.hfov_deg) / 2)
    fy = (cfg.height / 2) / math.tan(math.radians(cfg.vfov_deg) / 2)
    return fx, fy, cfg.width / 2, cfg.height / 2


def column_angles(cfg: SensorConfig) -> np.ndarray:
    """Horizontal angle (rad) of each image column's centre, positive to the left."""
    fx, _, cx, _ = intrinsics(cfg)
    return np.arctan((cx - (np.arange(cfg.width) + 0.5)) / fx)


def ray_directions_body(cfg: SensorConfig) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions in the robot frame (x forward, y left, z up), row-major
    (H*W, 3), and for each ray the factor turning ray length into axial depth."""
    fx, fy, cx, cy = intrinsics(cfg)
    cols = (cx - (np.arange(cfg.width) + 0.5)) / fx
    rows = (cy - (np.arange(cfg.height) + 0.5)) / fy
    left, up = np.meshgrid(cols, rows)  # (H, W) each
    dirs = np.stack([np.ones_like(left), left, up], axis=-1).reshape(-1, 3)
    norm = np.linalg.norm(dirs, axis=1)
    return dirs / norm[:, None], 1.0 / norm


def floor_depths_m(cfg: SensorConfig) -> np.ndarray:
    """Axial depth (m) at which each image row's rays meet a bare floor, top row first; inf at and
    above the horizon."""
    _, fy, _, cy = intrinsics(cfg)
    up = (cy - (np.arange(cfg.height) + 0.5)) / fy
    with np.errstate(divide="ignore"):
        return np.where(up < 0, cfg.mount_height_m / -up, np.inf)


def _columns_exact(model: mujoco.MjModel, cfg: SensorConfig, robot_body: int) -> bool:
    """True if every non-robot geom is the floor plane at z = 0 or an upright prism from the
    floor up past the highest point a ray reaches within range (see module docstring)."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    reach = cfg.mount_height_m + cfg.max_range_m * math.tan(math.radians(cfg.vfov_deg) / 2) + 0.01
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == robot_body:
            continue
        gtype = int(model.geom_type[g])  # numpy ints do not compare equal to mjtGeom members
        pos, zaxis = data.geom_xpos[g], data.geom_xmat[g].reshape(3, 3)[:, 2]
        if gtype == int(mujoco.mjtGeom.mjGEOM_PLANE):
            infinite = model.geom_size[g][0] == 0 or model.geom_size[g][1] == 0
            if abs(pos[2]) > 1e-9 or zaxis[2] < 1 - 1e-9 or not infinite:
                return False
            continue
        if gtype not in (int(mujoco.mjtGeom.mjGEOM_BOX), int(mujoco.mjtGeom.mjGEOM_CYLINDER)):
            return False
        if abs(zaxis[2]) < 1 - 1e-9:  # tilted
            return False
        half_height = model.geom_size[g][2] if gtype == int(mujoco.mjtGeom.mjGEOM_BOX) else model.geom_size[g][1]
        if pos[2] - half_height > 1e-6 or pos[2] + half_height < reach:
            return False
    return True


class DepthCamera:
    """Captures depth images from the camera mounted on the robot of a compiled model."""

    def __init__(self, model: mujoco.MjModel, cfg: SensorConfig, seed: int | None = None,
                 allow_columns: bool = True):
        self.model = model
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self.body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, ROBOT_BODY)
        self.camera_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, CAMERA_NAME)
        self._floor_geom = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_GEOM)
        self._renderer: mujoco.Renderer | None = None
        self.mode = "gl" if cfg.backend == "gl" else (
            "columns" if allow_columns and _columns_exact(model, cfg, self.body_id) else "pixels")
        # Each mode keeps only its own buffers: an env keeps a camera for every world it has played
        # (a hundred on an actor), and the per-pixel ones are (H*W, 3) float64.
        if self.mode == "pixels":
            self._dirs_body, self._axial = ray_directions_body(cfg)
            n = cfg.height * cfg.width
            self._vec = np.empty((n, 3), dtype=np.float64)
            self._dist = np.empty(n, dtype=np.float64)
            self._geomid = np.empty(n, dtype=np.int32)
        elif self.mode == "columns":
            fx, _, cx, _ = intrinsics(cfg)
            left = (cx - (np.arange(cfg.width) + 0.5)) / fx
            self._col_dirs_body = np.stack([np.ones_like(left), left, np.zeros_like(left)], axis=1)
            self._col_axial = 1.0 / np.linalg.norm(self._col_dirs_body, axis=1)
            self._col_dirs_body *= self._col_axial[:, None]
            self._col_vec = np.empty((cfg.width, 3))
            self._col_dist = np.empty(cfg.width)
            self._col_geomid = np.empty(cfg.width, dtype=np.int32)
            self._floor_depth = floor_depths_m(cfg)[:, None]

    def reseed(self, seed: int | None) -> None:
        """Restart the noise generator (the env calls this on reset with a seed)."""
        self.rng = np.random.default_rng(seed)

    def capture(self, data: mujoco.MjData) -> np.ndarray:
        """A float32 (H, W) depth image in metres; 0 where there is no return."""
        if self.mode == "gl":
            depth = self._render_gl(data)
        elif self.mode == "columns":
            depth = self._raycast_columns(data)
        else:
            depth = self._raycast(data)
        cfg = self.cfg
        if cfg.noise_std_m > 0 or cfg.noise_quadratic_per_m > 0:
            depth = depth + (self.rng.standard_normal(depth.shape) * self.noise_std_m(depth)).astype(np.float32) \
                * (depth > 0)
        if cfg.dropout_prob > 0:
            depth = np.where(self.rng.random(depth.shape) < cfg.dropout_prob, 0.0, depth)
        return range_gate(depth, cfg.min_range_m, cfg.max_range_m)

    def noise_std_m(self, depth_m: np.ndarray) -> np.ndarray | float:
        """The depth noise's standard deviation (m) at each depth (``SensorConfig.noise_std_m``
        and ``noise_quadratic_per_m``)."""
        cfg = self.cfg
        if cfg.noise_quadratic_per_m == 0:
            return cfg.noise_std_m
        beyond = np.maximum(depth_m.astype(np.float64) - KINECT_NOISE_OFFSET_M, 0.0)
        return cfg.noise_std_m + cfg.noise_quadratic_per_m * beyond ** 2

    def _raycast(self, data: mujoco.MjData) -> np.ndarray:
        cfg = self.cfg
        origin = data.cam_xpos[self.camera_id].copy()
        rot = data.xmat[self.body_id].reshape(3, 3)
        np.matmul(self._dirs_body, rot.T, out=self._vec)
        n = self._dist.shape[0]
        # cutoff: geoms whose bounding sphere is beyond the range cannot produce a valid pixel
        cutoff = cfg.max_range_m / float(self._axial.min()) + 1e-3
        mujoco.mj_multiRay(self.model, data, origin, self._vec.reshape(-1), None, 1, self.body_id,
                           self._geomid, self._dist, None, n, cutoff)
        depth = np.where(self._dist < 0, 0.0, self._dist * self._axial)
        return depth.reshape(cfg.height, cfg.width).astype(np.float32)

    def _raycast_columns(self, data: mujoco.MjData) -> np.ndarray:
        cfg = self.cfg
        origin = data.cam_xpos[self.camera_id].copy()
        rot = data.xmat[self.body_id].reshape(3, 3)
        np.matmul(self._col_dirs_body, rot.T, out=self._col_vec)
        # The floor is composed analytically: exclude it by casting only at obstacles.
        mujoco.mj_multiRay(self.model, data, origin, self._col_vec.reshape(-1), None, 1, self.body_id,
                           self._col_geomid, self._col_dist, None, cfg.width, 1e9)
        wall = np.where((self._col_dist < 0) | (self._col_geomid == self._floor_geom), np.inf,
                        self._col_dist * self._col_axial)
        depth = np.minimum(self._floor_depth, wall[None, :])
        return np.where(np.isinf(depth), 0.0, depth).astype(np.float32)

    def _render_gl(self, data: mujoco.MjData) -> np.ndarray:
        cfg = self.cfg
        if self._renderer is None:
            try:
                self._renderer = mujoco.Renderer(self.model, height=cfg.height, width=cfg.width)
            except Exception as exc:  # no GL context: say how to get one
                raise SensorError(
                    "the 'gl' depth backend needs an OpenGL context: set MUJOCO_GL=egl (or osmesa) "
                    f"before importing mujoco, or use backend='raycast' ({' '.join(str(exc).split())})") from None
            self._renderer.enable_depth_rendering()
            # Every world geom group in view (MuJoCo shows only 0-2 by default), the robot's own body
            # hidden: the raycast backend sees the same.
            self._scene_option = mujoco.MjvOption()
            self._scene_option.geomgroup[:] = 1
            self._scene_option.geomgroup[ROBOT_GEOM_GROUP] = 0
            # MuJoCo scales its clip planes by the model's extent (near = 1% of it: 2 m in a 100 m
            # world, hiding every nearer obstacle); the camera's own range sets them instead.
            near = min(cfg.min_range_m, GL_NEAR_M) if cfg.min_range_m > 0 else GL_NEAR_M
            extent = self.model.stat.extent
            self.model.vis.map.znear = near / extent
            self.model.vis.map.zfar = 1.01 * cfg.max_range_m / extent
        self._renderer.update_scene(data, camera=self.camera_id, scene_option=self._scene_option)
        # The depth buffer holds distance along the optical axis already.
        depth = self._renderer.render().astype(np.float32)
        depth[depth >= self.model.vis.map.zfar * self.model.stat.extent * 0.999] = 0.0
        return depth

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
