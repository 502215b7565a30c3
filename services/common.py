"""What every service process shares: its command-line options (with environment-variable
equivalents for containers), the run folder, the resolved config, logging and signals."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import socket
import threading
from dataclasses import dataclass
from pathlib import Path

from shared.config import RunConfig, load_preset, parse_override, to_toml
from shared.keys import validate_name
from shared.transport import ZenohSettings, parse_endpoints

ENV_RUN = "COGEXPLORE_RUN"
ENV_PRESET = "COGEXPLORE_PRESET"
ENV_RUNS_DIR = "COGEXPLORE_RUNS_DIR"
ENV_DEVICE = "COGEXPLORE_DEVICE"
CONFIG_FILE = "config.toml"


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


def zenoh_settings(args: argparse.Namespace) -> ZenohSettings:
    """Environment variables first, command-line options over them."""
    overrides: dict[str, object] = {}
    if args.connect:
        overrides["connect"] = parse_endpoints(args.connect)
    if args.listen:
        overrides["listen"] = parse_endpoints(args.listen)
    if args.zenoh_mode:
        overrides["mode"] = args.zenoh_mode
    if args.zenoh_config:
        overrides["config_file"] = args.zenoh_config
    return ZenohSettings.from_env(**overrides)


@dataclass(frozen=True)
class RunPaths:
    """The layout of runs/<run>/."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / CONFIG_FILE

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    @property
    def stats(self) -> Path:
        return self.root / "stats"

    @property
    def recordings(self) -> Path:
        return self.root / "recordings"

    @property
    def report(self) -> Path:
        return self.root / "report"

    def make(self) -> "RunPaths":
        for d in (self.root, self.checkpoints, self.logs, self.stats, self.recordings, self.report):
            d.mkdir(parents=True, exist_ok=True)
        return self


def run_paths(args: argparse.Namespace) -> RunPaths:
    validate_name(args.run, "run name")
    return RunPaths(Path(args.runs_dir) / args.run)


def resolve_config(args: argparse.Namespace, paths: RunPaths | None = None) -> RunConfig:
    """--preset if given, else the run's saved config, else 'paper'; then --set and --device."""
    source = args.preset
    if source is None:
        source = str(paths.config) if paths is not None and paths.config.exists() else "paper"
    cfg = load_preset(source)
    overrides = dict(parse_override(o) for o in getattr(args, "overrides", []) or [])
    if getattr(args, "device", None):
        overrides["train.device"] = args.device
    return cfg.with_overrides(overrides) if overrides else cfg


def save_config(cfg: RunConfig, paths: RunPaths) -> None:
    """Write the run's config atomically (services started later read it back)."""
    paths.root.mkdir(parents=True, exist_ok=True)
    tmp = paths.config.with_suffix(".tmp")
    tmp.write_text(to_toml(cfg))
    os.replace(tmp, paths.config)


def default_process_id(role: str) -> str:
    """hostname-pid: distinct for scaled containers and for processes on one machine."""
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:40] or "host"
    return f"{role}-{host}-{os.getpid()}"


def setup_logging(level: str = "INFO", logfile: Path | None = None) -> None:
    handlers: list[logging.Handler] = [logging.StreamHandler()]
    if logfile is not None:
        logfile.parent.mkdir(parents=True, exist_ok=True)
        handlers.append(logging.FileHandler(logfile))
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), handlers=handlers, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def stop_event_on_signals() -> threading.Event:
    """An Event set by SIGINT or SIGTERM, so loops can finish their step and clean up."""
    stop = threading.Event()

    def handler(signum: int, _frame: object) -> None:
        logging.getLogger(__name__).info("signal %s: stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    return stop
