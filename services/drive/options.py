"""The options of ``cogexplore drive`` and ``cogexplore sim-robot`` (light: no Zenoh, no torch)."""

from __future__ import annotations

import argparse

from services.bus.options import add_ros2_arguments
from services.options import positive_number_argument, whole_number_argument


def add_drive_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", default="pretrained",
                   help="the policy: pretrained (the shipped model), a checkpoint, run folder or weights export "
                        "(what `evaluate --checkpoint` takes); default pretrained")
    p.add_argument("--onnx", default=None, metavar="FILE",
                   help="run an ONNX export instead (`cogexplore model export --onnx`): onnxruntime, no torch")
    p.add_argument("--device", default="auto", help="torch device for --checkpoint: auto, cpu, cuda (default auto)")
    p.add_argument("--speed-table", choices=("test", "train"), default="test",
                   help="the commands' speeds: the paper's test table (the protocol's) or its train table (default test)")
    p.add_argument("--watchdog", type=positive_number_argument, default=0.5, metavar="SECONDS",
                   help="stop (zero twist) when no valid image has come for this long (default 0.5)")
    p.add_argument("--max-image-age", type=positive_number_argument, default=None, metavar="SECONDS",
                   help="stop on an image whose header stamp is further than this from this machine's clock, "
                        "past or future (default: stamps unused; needs the robot's clock in step with this one)")
    p.add_argument("--collision-distance", type=positive_number_argument, default=None, metavar="METRES",
                   help="stop when the nearest valid depth is below this (default: the task's, 0.55)")
    p.add_argument("--control-period", type=positive_number_argument, default=None, metavar="SECONDS",
                   help="at most one command per period (default: the policy's, 0.5)")
    p.add_argument("--lockstep", action="store_true",
                   help="one command per image, however fast they come (with `sim-robot --lockstep`)")
    p.add_argument("--rerun-connect", default=None, metavar="URL",
                   help="also stream depth, commands, Q-values, nearest depth and latency to the Rerun viewer at URL "
                        "(e.g. rerun+http://127.0.0.1:9876/proxy)")
    p.add_argument("--rrd", default=None, metavar="FILE", help="also record them to a Rerun file")
    p.add_argument("--max-decisions", type=whole_number_argument(1), default=None, metavar="N",
                   help="exit after N decisions (tests, demos)")
    add_ros2_arguments(p)
