"""The sim-robot's depth image as a ROS depth driver sends it."""

from __future__ import annotations

import numpy as np

from services.sim_robot.service import ros_depth
from shared.ros2.messages import decode_depth_image, encode_depth_image
from shared.sim.env import ExploreEnv


def _start_depth() -> np.ndarray:
    env = ExploreEnv(world="paper-indoor", start_index=0, render_mode="depth_array")
    try:
        env.reset(seed=0)
        return env.render()
    finally:
        env.close()


def test_a_pixel_without_a_return_is_plus_inf_in_32fc1_and_zero_in_16uc1():
    # REP 117: nothing within range is +Inf (NaN is an erroneous measurement, which a costmap
    # clears nothing with; 0.0 m is an obstacle at the lens); REP 118: 0 in millimetres.
    depth = _start_depth()
    blind = depth == 0
    assert blind.any() and (~blind).any()  # beyond the 4 m range somewhere, a return elsewhere
    as_float = decode_depth_image(encode_depth_image(ros_depth(depth, "32FC1"), encoding="32FC1", stamp_ns=1)).depth_m
    assert np.isposinf(as_float[blind]).all() and np.array_equal(as_float[~blind], depth[~blind])
    as_mm = decode_depth_image(encode_depth_image(ros_depth(depth, "16UC1"), encoding="16UC1", stamp_ns=1)).depth_m
    assert (as_mm[blind] == 0).all() and np.allclose(as_mm[~blind], depth[~blind], atol=1e-3)


def test_a_camera_with_a_minimum_range_sends_nan_where_too_near_and_too_far_look_alike():
    # Its 0 is also what lies nearer than min_range_m (REP 117's -Inf): +Inf would tell a consumer
    # that an obstacle at the lens is free space.
    depth = _start_depth()
    sent = ros_depth(depth, "32FC1", min_range_m=0.6)
    assert np.isnan(sent[depth == 0]).all() and np.array_equal(sent[depth > 0], depth[depth > 0])
