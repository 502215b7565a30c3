"""The env's rgb_array frames (shared.sim.render): shape, colours, the robot and its path.

RecordVideo itself needs moviepy (with imageio-ffmpeg, ~170 MB), which the project does not
carry; these tests check what RecordVideo takes from the env instead: the frame's type and size,
an even size for the encoder, an honest render_fps and the env checker's render checks."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from shared.sim.env import ENV_ID, ExploreEnv
from shared.sim.maps import MAP_FREE_RGB, MAP_OBSTACLE_RGB
from shared.sim.render import (DEPTH_LUT, FRAME_HEIGHT_PX, HEADING_RGB, PATH_RGB, ROBOT_RGB, MapCanvas,
                               depth_colours)
from shared.sim.world import SceneBuilder, StartPose


def _room():
    """A 6 x 4 m room with its walls, a pillar, and a start facing +x down the middle."""
    b = SceneBuilder("room", (-3.0, -2.0, 3.0, 2.0))
    b.boundary()
    b.cylinder(1.5, 1.2, 0.3)
    return b.build("room", [StartPose(-2.0, 0.0, 0.0)])


def _pixels(frame: np.ndarray, rgb) -> np.ndarray:
    """(N, 2) (row, column) of the pixels of exactly ``rgb``."""
    return np.argwhere((frame == np.array(rgb, np.uint8)).all(axis=2))


def test_rgb_array_passes_the_env_checker_and_has_an_honest_fps():
    env = gym.make(ENV_ID, world="box-room", render_mode="rgb_array", control_period_s=0.25).unwrapped
    check_env(env)  # with a spec, it also makes and renders each other render mode
    assert env.metadata["render_fps"] == 4.0 and ExploreEnv.metadata["render_fps"] == 2
    assert "rgb_array" in ExploreEnv.metadata["render_modes"]
    env.close()


def test_a_frame_is_the_depth_beside_the_map():
    env = ExploreEnv(world=_room(), render_mode="rgb_array", start_index=0)
    depth, _ = env.reset(seed=0)
    frame = env.render()
    depth_w = FRAME_HEIGHT_PX * 160 // 120
    map_w = FRAME_HEIGHT_PX * 6 // 4  # the map keeps the room's 6 x 4 m aspect
    assert frame.dtype == np.uint8 and frame.shape == (FRAME_HEIGHT_PX, depth_w + 4 + map_w, 3)
    assert frame.shape[0] % 2 == 0 and frame.shape[1] % 2 == 0
    depth_panel, map_panel = frame[:, :depth_w], frame[:, depth_w + 4:]
    # the depth panel: the image at 2x through the colour table
    np.testing.assert_array_equal(depth_panel[::2, ::2], depth_colours(depth, 4.0))
    # the map: the boundary walls dark, the middle of the room free
    assert (map_panel[0] == MAP_OBSTACLE_RGB).all() and (map_panel[-1] == MAP_OBSTACLE_RGB).all()
    assert (map_panel[FRAME_HEIGHT_PX // 2, map_w // 2] == MAP_FREE_RGB).all()
    # the robot's disc at its start, (-2, 0): a sixth of the way across, half way down
    rows, cols = _pixels(map_panel, ROBOT_RGB).T
    assert rows.mean() == pytest.approx(FRAME_HEIGHT_PX / 2, abs=1.0)
    assert cols.mean() == pytest.approx(map_w / 6, abs=1.0)
    # its heading tick points +x (to the right of the disc)
    assert _pixels(map_panel, HEADING_RGB)[:, 1].mean() > cols.mean() + 2
    env.close()


def test_the_robot_moves_on_the_map_and_leaves_its_path():
    env = ExploreEnv(world=_room(), render_mode="rgb_array", start_index=0, speed_table="test")
    env.reset(seed=0)
    first = env.render()
    for _ in range(8):
        _, _, terminated, _, _ = env.step(2)  # straight along +x, 1 m in all
        assert not terminated
    last = env.render()
    start_col = _pixels(first, ROBOT_RGB)[:, 1].mean()
    end_col = _pixels(last, ROBOT_RGB)[:, 1].mean()
    px_per_m = FRAME_HEIGHT_PX / 4
    assert end_col - start_col == pytest.approx(1.0 * px_per_m, abs=2.0)
    path = _pixels(last, PATH_RGB)
    assert len(path) and path[:, 1].min() < start_col and path[:, 1].max() > start_col + px_per_m / 2
    # a new episode starts a new path
    env.reset(seed=0)
    np.testing.assert_array_equal(env.render(), first)
    env.close()


def test_restore_puts_the_path_back():
    env = ExploreEnv(world=_room(), render_mode="rgb_array", start_index=0)
    env.reset(seed=0)
    env.step(2)
    snap = env.snapshot()
    before = env.render()
    for _ in range(4):
        env.step(0)
    assert not np.array_equal(env.render(), before)
    env.restore(snap)
    np.testing.assert_array_equal(env.render(), before)


def test_near_is_warm_and_bright_far_and_no_return_dark():
    colours = depth_colours(np.array([[0.3, 2.0, 3.9, 0.0]]), 4.0)[0].astype(int)
    near, mid, far, none = colours
    assert near[0] > 240 and near.sum() > mid.sum() > far.sum()  # red high: warm
    np.testing.assert_array_equal(none, DEPTH_LUT[0])
    assert DEPTH_LUT.shape == (256, 3) and DEPTH_LUT.dtype == np.uint8


def test_the_map_canvas_flips_y_and_clips_what_is_off_the_map():
    from shared.sim.maps import empty_grid

    canvas = MapCanvas(empty_grid((0.0, 0.0, 2.0, 1.0), 0.05), height_px=100)
    assert canvas.shape == (100, 200)
    np.testing.assert_allclose(canvas.to_pixels(np.array([[0.0, 1.0], [2.0, 0.0]])), [[0, 0], [200, 100]])
    image = canvas.draw([(-5.0, -5.0), (5.0, 5.0)], (1.0, 0.25, 0.0), radius_m=0.1)  # no error off the map
    rows, _ = _pixels(image, ROBOT_RGB).T
    assert rows.mean() == pytest.approx(75, abs=1.0)  # y = 0.25 m is near the bottom


def test_gym_make_renders_rgb_array():
    env = gym.make(ENV_ID, world="box-room", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.ndim == 3 and frame.shape[2] == 3 and frame.dtype == np.uint8
    env.close()
    with pytest.raises(ValueError, match="render_mode"):
        ExploreEnv(world="box-room", render_mode="human")
