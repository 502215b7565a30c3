"""The Zenoh router process: ``cogexplore router`` or ``python -m services.router --listen tcp/0.0.0.0:7447``.

Every process of a run connects to it (``COGEXPLORE_ZENOH_CONNECT``).
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path
from typing import Sequence

from services.bus import DEFAULT_ROUTER_LISTEN
from services.bus.session import TransportError, parse_endpoints, run_router
from services.cli import error_line
from services.router.options import READY_LINE, add_arguments


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="python -m services.router",
        description="Run the Zenoh router all cogexplore processes meet at, until SIGINT/SIGTERM.")
    return add_arguments(parser)


def _refuse(message: BaseException | str) -> int:
    # one line: `up` shows the last line of the router's log as the reason it stopped
    print(error_line("router", message), file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    """Run the router from parsed arguments; returns the process exit status (2: a bad option or
    config file, said in one line)."""
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        listen = parse_endpoints(",".join(args.listen), "--listen") if args.listen else ()
    except ValueError as exc:
        return _refuse(exc)
    if args.config is not None and Path(args.config).exists() and not Path(args.config).is_file():
        return _refuse(f"--config {args.config} is not a file")
    if not listen and args.config is None:
        listen = DEFAULT_ROUTER_LISTEN

    def ready(_session: object) -> None:
        print(f"{READY_LINE} on {', '.join(listen) or 'the config file endpoints'}", flush=True)

    try:
        return run_router(listen, config_file=args.config, on_ready=ready)
    except (TransportError, ValueError) as exc:
        return _refuse(exc)


def main(argv: Sequence[str] | None = None) -> int:
    return run(build_parser().parse_args(argv))
