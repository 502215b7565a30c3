"""The depth camera against known geometry, with real MuJoCo."""

import math

import mujoco
import numpy as np
import pytest

from shared.config import EnvConfig, SensorConfig
from shared.sim.robot import Robot, build_model
from shared.sim.sensor import GL_TOLERANCE_M, DepthCamera, column_angles, intrinsics
from shared.sim.world import SceneBuilder, StartPose

TALL = 2.0  # obstacles taller than any in-range ray: the camera may use its column fast path


def _room(wall_x: float, height: float = TALL, extra_cylinder: bool = False):
    """A wall across +x at ``wall_x`` (its near face at wall_x - 0.05)."""
    b = SceneBuilder("probe", (-1.0, -3.0, wall_x + 1.0, 3.0))
    b.wall(wall_x, -3.0, wall_x, 3.0, height=height)
    if extra_cylinder:
        b.cylinder(wall_x - 1.0, 0.8, 0.2, height=height)
    world = b.build("probe", [StartPose(0.0, 0.0, 0.0)])
    sensor = SensorConfig()
    model = build_model(world.mjcf, EnvConfig(), sensor)
    data = mujoco.MjData(model)
    robot = Robot(model, data)
    robot.set_pose(0.0, 0.0, 0.0)
    return model, data, robot, sensor


@pytest.mark.parametrize("allow_columns", [True, False])
def test_wall_depth_at_image_centre_within_1cm(allow_columns):
    model, data, _, sensor = _room(wall_x=2.0)
    camera = DepthCamera(model, sensor, allow_columns=allow_columns)
    assert camera.mode == ("columns" if allow_columns else "pixels")
    depth = camera.capture(data)
    assert depth.shape == (120, 160) and depth.dtype == np.float32
    centre = depth[58:62, 78:82]
    assert np.all(np.abs(centre - 1.95) < 0.01)
    # axial depth, not ray length: the whole wall reads the same depth across a row
    assert np.allclose(depth[60, 10:150], 1.95, atol=1e-3)


def test_out_of_range_pixels_are_zero_and_floor_is_seen():
    model, data, _, sensor = _room(wall_x=6.0)
    depth = DepthCamera(model, sensor).capture(data)
    assert np.all(depth[:60] == 0.0), "nothing within 4 m above the horizon"
    assert np.all(depth <= sensor.max_range_m)
    floor = depth[-1, 80]
    fy = intrinsics(sensor)[1]
    expected = sensor.mount_height_m / ((119.5 - 60) / fy)
    assert abs(floor - expected) < 1e-3
    assert floor > EnvConfig().collision_distance_m, "the floor must never trigger the collision rule"


def test_column_fast_path_matches_per_pixel_cast():
    model, data, robot, sensor = _room(wall_x=3.0, extra_cylinder=True)
    fast, exact = DepthCamera(model, sensor), DepthCamera(model, sensor, allow_columns=False)
    assert fast.mode == "columns"
    rng = np.random.default_rng(0)
    for _ in range(10):
        robot.set_pose(rng.uniform(-0.5, 1.5), rng.uniform(-2, 2), rng.uniform(-math.pi, math.pi))
        np.testing.assert_allclose(fast.capture(data), exact.capture(data), atol=1e-4)


def test_low_obstacles_fall_back_to_per_pixel():
    model, data, _, sensor = _room(wall_x=2.0, height=0.5)
    camera = DepthCamera(model, sensor)
    assert camera.mode == "pixels"
    depth = camera.capture(data)
    # the camera (0.35 m high) sees over the 0.5 m wall in the upper rows only beyond range
    assert depth[110, 80] > 0 and depth[0, 80] == 0


def test_column_angles_span_the_field_of_view():
    sensor = SensorConfig()
    angles = column_angles(sensor)
    assert angles[0] > 0 > angles[-1]
    assert math.isclose(angles[0] - angles[-1], math.radians(57.0), rel_tol=0.02)


def test_noise_and_dropout_are_seeded():
    model, data, _, _ = _room(wall_x=2.0)
    noisy = SensorConfig(noise_std_m=0.01, dropout_prob=0.1)
    a = DepthCamera(model, noisy, seed=3).capture(data)
    b = DepthCamera(model, noisy, seed=3).capture(data)
    c = DepthCamera(model, noisy, seed=4).capture(data)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert 0.05 < (a == 0).mean() < 0.15


def test_gl_backend_agrees_with_raycast():
    model, data, robot, _ = _room(wall_x=3.0, extra_cylinder=True)
    robot.set_pose(0.3, 0.2, 0.25)
    try:
        gl = DepthCamera(model, SensorConfig(backend="gl")).capture(data)
    except RuntimeError as exc:
        pytest.skip(f"no OpenGL context here: {exc}")
    ray = DepthCamera(model, SensorConfig()).capture(data)
    both = (gl > 0) & (ray > 0)
    assert ((gl > 0) != (ray > 0)).mean() < 0.01, "valid-pixel masks differ only at edges"
    assert np.percentile(np.abs(gl[both] - ray[both]), 99) < GL_TOLERANCE_M
