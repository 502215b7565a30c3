"""The depth camera against known geometry, with real MuJoCo."""

import json
import math
import os
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from shared.config import EnvConfig, SensorConfig
from shared.sim.robot import Robot, build_model
from shared.sim.sensor import GL_TOLERANCE_M, DepthCamera, SensorError, column_angles, floor_depths_m, intrinsics
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
    except SensorError as exc:
        pytest.skip(f"no OpenGL context here: {exc}")
    ray = DepthCamera(model, SensorConfig()).capture(data)
    both = (gl > 0) & (ray > 0)
    assert ((gl > 0) != (ray > 0)).mean() < 0.01, "valid-pixel masks differ only at edges"
    assert np.percentile(np.abs(gl[both] - ray[both]), 99) < GL_TOLERANCE_M


def test_the_gl_backend_without_opengl_is_a_one_line_error():
    # GLFW with no display to open a window on: no OpenGL context (a fresh interpreter, as MUJOCO_GL
    # is read when mujoco is imported).
    code = _GL_PROBE.replace("print(json.dumps({\"skip\": str(exc)}))",
                             "print(json.dumps({\"error\": type(exc).__name__, \"message\": str(exc)}))")
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                          env={**env, "MUJOCO_GL": "glfw"})
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    if "gl" in out:
        pytest.skip("GLFW opened a context here")
    # A CogexploreError: the command line prints it in one line, with no traceback.
    assert out["error"] == "SensorError" and "MUJOCO_GL=egl" in out["message"] and "\n" not in out["message"]


_GL_PROBE = """
import json
import mujoco
from shared.config import EnvConfig, SensorConfig
from shared.sim.robot import Robot, build_model
from shared.sim.sensor import DepthCamera, SensorError
# A far marker makes the model's extent 400 m (MuJoCo's default near plane: 4 m); the wall 1 m
# ahead covers the right of the view, a pillar in group 3 the left.
xml = ('<mujoco><worldbody><geom name="floor" type="plane" size="0 0 1"/>'
       '<geom name="marker" type="box" pos="200 0 1" size="0.1 0.1 1"/>'
       '<geom name="wall" type="box" pos="1.05 -1 1" size="0.05 1 1"/>'
       '<geom name="pillar" type="box" pos="1.55 1 1" size="0.05 1 1" group="3"/></worldbody></mujoco>')
sensor = SensorConfig(width=40, height=30)
model = build_model(xml, EnvConfig(), sensor)
data = mujoco.MjData(model)
Robot(model, data).set_pose(0.0, 0.0, 0.0)
try:
    gl = DepthCamera(model, SensorConfig(width=40, height=30, backend="gl")).capture(data)
except SensorError as exc:
    print(json.dumps({"skip": str(exc)}))
else:
    ray = DepthCamera(model, sensor).capture(data)
    print(json.dumps({"gl": gl.tolist(), "ray": ray.tolist()}))
"""


def test_the_gl_backend_sees_what_the_raycast_sees_near_and_in_any_world_group():
    # MUJOCO_GL must be set before mujoco is imported: a fresh interpreter.
    done = subprocess.run([sys.executable, "-c", _GL_PROBE], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MUJOCO_GL": "egl"})
    assert done.returncode == 0, done.stderr[-2000:]
    images = json.loads(done.stdout.strip().splitlines()[-1])
    if "skip" in images:
        pytest.skip(f"no EGL context here: {images['skip']}")
    gl, ray = np.array(images["gl"]), np.array(images["ray"])
    assert ray[15, 35] == pytest.approx(1.0, abs=0.01) and ray[15, 5] == pytest.approx(1.5, abs=0.01)
    both = (gl > 0) & (ray > 0)
    assert ((gl > 0) != (ray > 0)).mean() < 0.02, "valid-pixel masks differ only at edges"
    assert np.percentile(np.abs(gl[both] - ray[both]), 99) < GL_TOLERANCE_M


def test_floor_depths_are_where_each_rows_ray_meets_the_floor():
    sensor = SensorConfig(width=40, height=30)
    floor = floor_depths_m(sensor)
    _, fy, _, cy = intrinsics(sensor)
    assert np.all(np.isinf(floor[:15])) and np.all(np.diff(floor[15:]) < 0)
    assert floor[-1] == pytest.approx(sensor.mount_height_m * fy / (29.5 - cy))
    model, data, _, _ = _room(wall_x=50.0)  # nothing in range but the floor
    depth = DepthCamera(model, sensor).capture(data)
    np.testing.assert_allclose(depth[-1], floor[-1], rtol=1e-5)


_SMALL_BUFFER = '<mujoco><visual><global offwidth="10" offheight="10"/></visual><worldbody/></mujoco>'


@pytest.mark.parametrize("mjcf, width, height", [(_SMALL_BUFFER, 160, 120), ("<mujoco/>", 1024, 600)])
def test_the_offscreen_buffer_holds_the_cameras_image(mjcf, width, height):
    # The GL backend renders into it: smaller (a world's <visual>, or MuJoCo's 640 x 480 default for
    # a wide sensor) and the camera fails as if there were no OpenGL at all.
    model = build_model(mjcf, EnvConfig(), SensorConfig(width=width, height=height))
    assert model.vis.global_.offwidth >= width and model.vis.global_.offheight >= height


_GL_WIDE_PROBE = """
import json
import mujoco
from shared.config import EnvConfig, SensorConfig
from shared.sim.robot import Robot, build_model
from shared.sim.sensor import DepthCamera, SensorError
xml = ('<mujoco><visual><global offwidth="10" offheight="10"/></visual><worldbody>'
       '<geom name="floor" type="plane" size="0 0 1"/><geom type="box" pos="1.05 0 1" size="0.05 2 1"/>'
       '</worldbody></mujoco>')
sensor = SensorConfig(width=800, height=48, backend="gl")
model = build_model(xml, EnvConfig(), sensor)
data = mujoco.MjData(model)
Robot(model, data).set_pose(0.0, 0.0, 0.0)
try:
    gl = DepthCamera(model, sensor).capture(data)
except SensorError as exc:
    print(json.dumps({"error": str(exc)}))
else:
    print(json.dumps({"centre": float(gl[24, 400])}))
"""


def test_the_gl_backend_renders_an_image_wider_than_mujocos_default_buffer():
    done = subprocess.run([sys.executable, "-c", _GL_WIDE_PROBE], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MUJOCO_GL": "egl"})
    assert done.returncode == 0, done.stderr[-2000:]
    out = json.loads(done.stdout.strip().splitlines()[-1])
    if "error" in out and "framebuffer" not in out["error"]:
        pytest.skip(f"no EGL context here: {out['error']}")
    assert out.get("centre") == pytest.approx(1.0, abs=GL_TOLERANCE_M), out


def test_a_camera_keeps_only_its_own_modes_buffers():
    # An env keeps a camera for every world it has played (an actor 100): a column camera held the
    # per-pixel ray buffers too, (H*W, 3) float64 it never used.
    model, data, _, sensor = _room(wall_x=2.0)
    held = {}
    for allow_columns in (True, False):
        camera = DepthCamera(model, sensor, allow_columns=allow_columns)
        held[camera.mode] = sum(v.nbytes for v in vars(camera).values() if isinstance(v, np.ndarray))
        assert camera.capture(data)[sensor.height // 2, sensor.width // 2] == pytest.approx(1.95, abs=0.01)
    pixels = sensor.height * sensor.width
    assert held["columns"] < pixels * 8  # a few float64s per column and image row, none per pixel
    assert held["pixels"] >= pixels * 3 * 8
