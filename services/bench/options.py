"""The options of ``cogexplore bench env|learner|transport|drive`` (``bench system``: services.up.options).

Every benchmark prints its figures as JSON on stdout, indented with ``--json`` and on one line
without it (a line a script can append to a log)."""

from __future__ import annotations

import argparse

from services.bus.options import ROS2_FORMATS
from services.options import MAX_TORCH_THREADS, count_argument, positive_number_argument, whole_number_argument
from shared.wire.messages import MAX_BATCH_STEPS, MAX_FRAME_PIXELS

JSON_HELP = "print the JSON indented (default: on one line)"
MIN_IMAGES = 10
MAX_IMAGES = 1_000_000
"""The most images ``bench drive --images`` may ask for: 3,300 times the default 300 (a p99 is steady
after a few thousand), over five hours at the 20 ms target, for a soak as long as anyone would run,
and its bookkeeping stays near 100 MB. 10**10 grew a list of 80 GB before the first image was sent."""


def add_env_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--world", default="paper-indoor", help="the world stepped (default paper-indoor)")
    p.add_argument("--steps", type=count_argument, default=2000, help="env steps timed (default 2000)")
    p.add_argument("--backend", choices=["raycast", "gl"], default="raycast",
                   help="the depth renderer: MuJoCo ray casts or OpenGL (default raycast)")
    p.add_argument("--per-pixel", action="store_true",
                   help="cast every pixel's ray (disable the exact column fast path; raycast only: the gl "
                        "backend renders every pixel anyway)")
    p.add_argument("--no-pin", action="store_true", help="do not pin the process to CPU 0")
    p.add_argument("--expert-labels", action="store_true",
                   help="also time the map expert's label at every step (explore.expert_label_prob's cost; "
                        "steps_per_s then includes it)")
    p.add_argument("--json", action="store_true", help=JSON_HELP)


def add_learner_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="auto", help="torch device: auto, cpu, cuda, cuda:N (default auto)")
    p.add_argument("--repeats", type=count_argument, default=8, help="timed updates per variant (default 8)")
    p.add_argument("--threads", type=whole_number_argument(1, MAX_TORCH_THREADS), default=None,
                   help=f"torch threads (default: torch's; at most {MAX_TORCH_THREADS})")
    p.add_argument("--baseline", action="store_true",
                   help="also time a plain PyTorch update (the paper network only: not with --preset or --set)")
    p.add_argument("--preset", default=None,
                   help="time this preset's update (name or TOML path; e.g. robust-40x30, the shipped recipe) "
                        "instead of the paper network's in float32")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override one config field of --preset (default preset: the shipped recipe's), repeatable")
    p.add_argument("--json", action="store_true", help=JSON_HELP)


def add_transport_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seconds", type=positive_number_argument, default=5.0,
                   help="duration of each measurement (default 5)")
    p.add_argument("--batch-steps", type=count_argument, default=16,
                   help=f"transitions per batch (default 16; at most {MAX_BATCH_STEPS}, the wire's limit)")
    p.add_argument("--height", type=count_argument, default=120,
                   help=f"image height (default 120; height x width at most {MAX_FRAME_PIXELS} pixels, the "
                        "wire's limit)")
    p.add_argument("--width", type=count_argument, default=160, help="image width (default 160)")
    p.add_argument("--threads", action="store_true",
                   help="publisher and subscriber as threads of this process, not spawned processes")
    p.add_argument("--json", action="store_true", help=JSON_HELP)


def add_drive_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--checkpoint", default="pretrained", help="the policy drive runs (default pretrained)")
    p.add_argument("--onnx", default=None, metavar="FILE", help="time `drive --onnx FILE` instead")
    p.add_argument("--images", type=whole_number_argument(MIN_IMAGES, MAX_IMAGES), default=300, help="images timed (default 300)")
    p.add_argument("--width", type=count_argument, default=None,
                   help="image width sent (default: the network's, 40 for the shipped model; a Kinect sends 640; "
                        "width x height at most 1920 x 1080 pixels)")
    p.add_argument("--height", type=count_argument, default=None, help="image height sent (default: the network's)")
    p.add_argument("--encoding", choices=("32FC1", "16UC1"), default="16UC1",
                   help="image encoding sent (default 16UC1, what depth drivers publish)")
    p.add_argument("--ros2-format", choices=ROS2_FORMATS, default="rmw_zenoh", help="wire format")
    p.add_argument("--json", action="store_true", help=JSON_HELP)
