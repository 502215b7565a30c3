"""The options of ``cogexplore sim-robot`` (light: no Zenoh, no MuJoCo)."""

from __future__ import annotations

import argparse

from services.bus.options import DEFAULT_ODOM_TOPIC, add_ros2_arguments
from services.options import positive_number_argument, whole_number_argument


def add_sim_robot_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", default="paper-indoor", help="world name, file or procedural:N (default paper-indoor)")
    p.add_argument("--start", type=int, default=1, metavar="N",
                   help="start pose, 1-based as in the tables and `worlds demo --start` (default 1)")
    p.add_argument("--preset", default=None,
                   help="preset whose camera and robot it simulates (default: the shipped recipe's)")
    p.add_argument("--encoding", choices=("32FC1", "16UC1"), default="32FC1",
                   help="depth image encoding: 32FC1 metres (lossless) or 16UC1 millimetres (what most depth "
                        "drivers publish); default 32FC1")
    p.add_argument("--lockstep", action="store_true",
                   help="one control period per cmd_vel, as fast as commands come (a zero twist advances nothing "
                        "and repeats the image); default: real time, holding the last command")
    p.add_argument("--cmd-timeout", type=positive_number_argument, default=0.5, metavar="SECONDS",
                   help="real time: stop when no cmd_vel has come for this long, as a TurtleBot base does (default 0.5)")
    p.add_argument("--odom-topic", default=DEFAULT_ODOM_TOPIC, metavar="TOPIC",
                   help=f"nav_msgs/msg/Odometry topic (default {DEFAULT_ODOM_TOPIC})")
    p.add_argument("--max-periods", type=whole_number_argument(1), default=None, metavar="N",
                   help="exit after N control periods (a collided robot's periods count too)")
    add_ros2_arguments(p)
