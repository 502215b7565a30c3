"""The options of ``cogexplore router`` and ``python -m services.router``."""

from __future__ import annotations

import argparse

from services.bus import DEFAULT_ROUTER_LISTEN
from services.options import add_log_level_argument

READY_LINE = "cogexplore router ready"
"""Printed (flushed) on stdout once the router listens, for scripts that wait for it."""


def add_arguments(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the router's options to ``parser`` (used by ``cogexplore router`` too)."""
    parser.add_argument("--listen", action="append", metavar="ENDPOINT",
                        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447; repeat or separate "
                             f"with commas for several (default: {','.join(DEFAULT_ROUTER_LISTEN)})")
    parser.add_argument("--config", metavar="FILE", default=None,
                        help="a Zenoh JSON5 config file (TLS, credentials, access control); "
                             "--listen overrides its listen endpoints")
    add_log_level_argument(parser)
    return parser
