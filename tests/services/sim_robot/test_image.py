"""The sim-robot's depth image as a ROS depth driver sends it."""

from __future__ import annotations

import numpy as np

from services.sim_robot.service import ros_depth
from shared.ros2.messages import decode_depth_image, encode_depth_image
from shared.sim.env import ExploreEnv


def test_a_pixel_without_a_return_is_nan_in_32fc1_and_zero_in_16uc1():
    # REP 117: it was 0.0 m in 32FC1, an obstacle at the lens to a consumer that follows the REP.
    env = ExploreEnv(world="paper-indoor", start_index=0, render_mode="depth_array")
    try:
        env.reset(seed=0)
        depth = env.render()
    finally:
        env.close()
    blind = depth == 0
    assert blind.any() and (~blind).any()  # beyond the 4 m range somewhere, a return elsewhere
    as_float = decode_depth_image(encode_depth_image(ros_depth(depth, "32FC1"), encoding="32FC1", stamp_ns=1)).depth_m
    assert np.isnan(as_float[blind]).all() and np.array_equal(as_float[~blind], depth[~blind])
    as_mm = decode_depth_image(encode_depth_image(ros_depth(depth, "16UC1"), encoding="16UC1", stamp_ns=1)).depth_m
    assert (as_mm[blind] == 0).all() and np.allclose(as_mm[~blind], depth[~blind], atol=1e-3)
