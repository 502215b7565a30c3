"""The options every service process takes (``learner``, ``actor``, ``evaluator``), with the
environment variables containers set instead (docker-compose.yml)."""

from __future__ import annotations

import argparse
import os

from services.runs import CONFIG_FILE

ENV_RUN = "COGEXPLORE_RUN"
ENV_PRESET = "COGEXPLORE_PRESET"
ENV_RUNS_DIR = "COGEXPLORE_RUNS_DIR"
ENV_DEVICE = "COGEXPLORE_DEVICE"


def add_service_arguments(parser: argparse.ArgumentParser, *, preset: bool = True) -> None:
    """--run, --preset, --set, --runs-dir, --device and the Zenoh endpoint options."""
    env = os.environ
    parser.add_argument("--run", default=env.get(ENV_RUN, "default"),
                        help=f"run name: Zenoh namespace and runs/<run>/ folder (env {ENV_RUN}; default: default)")
    if preset:
        parser.add_argument("--preset", default=env.get(ENV_PRESET),
                            help=f"preset name or TOML path (env {ENV_PRESET}); default: the run's "
                                 f"{CONFIG_FILE} if it exists, else 'paper'")
        parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                            help="override one config field, e.g. --set dqn.lr=3e-4 (repeatable)")
    parser.add_argument("--runs-dir", default=env.get(ENV_RUNS_DIR, "runs"),
                        help=f"where run folders live (env {ENV_RUNS_DIR}; default: runs)")
    parser.add_argument("--device", default=env.get(ENV_DEVICE),
                        help=f"torch device: auto, cpu, cuda, cuda:N (env {ENV_DEVICE}; default: the config's)")
    z = parser.add_argument_group("Zenoh", "endpoints (env COGEXPLORE_ZENOH_CONNECT/LISTEN/MODE/CONFIG)")
    z.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="router endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable; default "
                        "tcp/127.0.0.1:7447)")
    z.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    z.add_argument("--zenoh-mode", choices=["client", "peer"], default=None, help="Zenoh session mode")
    z.add_argument("--zenoh-config", default=None, metavar="JSON5",
                   help="a Zenoh JSON5 config file (the options above override it)")


