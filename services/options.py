"""The options every service process takes (``learner``, ``actor``, ``evaluator``), with the
environment variables containers set instead (docker-compose.yml), and the test-protocol options of
every command that runs the protocol (``evaluate``, the evaluator, ``experiment``, ``model select``)."""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable

from services.bus import DEFAULT_ROUTER_WAIT_S, ENV_ROUTER_WAIT
from services.runs import CONFIG_FILE
from shared.config import DEFAULT_PRESET, ConfigError, parse_number
from shared.evaluation import (
    DEFAULT_PROTOCOL,
    PROTOCOLS,
    ProtocolConfig,
    protocol_named,
)

ENV_RUN = "COGEXPLORE_RUN"
ENV_PRESET = "COGEXPLORE_PRESET"
ENV_RUNS_DIR = "COGEXPLORE_RUNS_DIR"
ENV_DEVICE = "COGEXPLORE_DEVICE"
DEFAULT_CONFIG_WAIT_S = 120.0
"""How long an actor or evaluator without --preset waits for its learner's configuration."""


def _number_argument(*, strict: bool, unit: str = "") -> Callable[[str], float]:
    """argparse ``type`` of a finite number >= 0 (> 0 with ``strict``): :func:`shared.config.parse_number`."""
    def parse(text: str) -> float:
        try:
            return parse_number(text, "", strict=strict, unit=unit)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None

    return parse


seconds_argument = _number_argument(strict=False, unit="of seconds")
"""argparse ``type`` of a time to wait: finite seconds, 0 or more (NaN would wait forever)."""
positive_number_argument = _number_argument(strict=True)
"""argparse ``type`` of a duration that must pass: a finite number > 0 (minutes, a window, a period)."""


def whole_number_argument(minimum: int, maximum: int | None = None) -> Callable[[str], int]:
    """argparse ``type`` of a whole number >= ``minimum`` (and <= ``maximum`` where given)."""
    span = f">= {minimum}" if maximum is None else f"in {minimum}..{maximum}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = minimum - 1
        if value < minimum or (maximum is not None and value > maximum):
            raise argparse.ArgumentTypeError(f"must be a whole number {span}, got {text!r}")
        return value

    parse.__name__ = f"whole number {span}"
    return parse


count_argument = whole_number_argument(1)
"""argparse ``type`` of a count of at least one (episodes, updates between evaluations, steps)."""
port_argument = whole_number_argument(1, 65535)
"""argparse ``type`` of a TCP port."""


def add_router_wait_argument(group: argparse._ArgumentGroup | argparse.ArgumentParser) -> None:
    """--router-wait: how long a process that joins a router retries while none answers."""
    group.add_argument("--router-wait", type=seconds_argument, default=None, metavar="SECONDS",
                       help=f"keep retrying this long while no router answers, as when it starts beside this "
                            f"process (env {ENV_ROUTER_WAIT}; default {DEFAULT_ROUTER_WAIT_S:.0f}; 0: fail at once)")


def add_log_level_argument(parser: argparse.ArgumentParser) -> None:
    """--log-level of a long-running service."""
    parser.add_argument("--log-level", default="INFO", type=str.upper, choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                        help="log verbosity (default INFO)")


def add_runs_dir_argument(parser: argparse.ArgumentParser) -> None:
    """--runs-dir: the folder that holds runs/<run>/, for every command that writes or reads a run."""
    parser.add_argument("--runs-dir", default=os.environ.get(ENV_RUNS_DIR) or "runs", metavar="DIR",
                        help=f"the folder holding the run folders, runs/<run>/ (env {ENV_RUNS_DIR}; "
                             "default: runs)")


def add_tensorboard_argument(parser: argparse.ArgumentParser) -> None:
    """--tensorboard / --no-tensorboard, for every command that trains, acts or evaluates."""
    parser.add_argument("--tensorboard", action=argparse.BooleanOptionalAction, default=True,
                        help="also write the statistics as TensorBoard event files in runs/<run>/tb/<process>/ "
                             "(view: tensorboard --logdir runs/; default: on)")


def add_service_arguments(parser: argparse.ArgumentParser, *, preset: bool = True, from_learner: bool = False) -> None:
    """--run, --preset, --set, --runs-dir, --tensorboard, --device and the Zenoh endpoint options;
    ``from_learner`` (actors, the evaluator): the config defaults to the learner's, and --config-wait."""
    env = os.environ
    parser.add_argument("--run", default=env.get(ENV_RUN) or "default",
                        help=f"run name: Zenoh namespace and runs/<run>/ folder (env {ENV_RUN}; default: default)")
    if preset:
        default = ("the run's configuration, asked of its learner; a preset named is checked against it and "
                   "refused where the run's data would differ" if from_learner else
                   f"the run's {CONFIG_FILE} if it exists, else {DEFAULT_PRESET}")
        parser.add_argument("--preset", default=env.get(ENV_PRESET) or None,
                            help=f"preset name or TOML path (env {ENV_PRESET}); default: {default}")
        parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                            help="override one config field, e.g. --set dqn.lr=3e-4 (repeatable)")
    if preset and from_learner:
        parser.add_argument("--config-wait", type=seconds_argument, default=DEFAULT_CONFIG_WAIT_S, metavar="SECONDS",
                            help=f"without --preset: how long to wait for the learner to answer with the run's "
                                 f"configuration (default {DEFAULT_CONFIG_WAIT_S:.0f})")
    add_runs_dir_argument(parser)
    add_tensorboard_argument(parser)
    add_log_level_argument(parser)
    device_default = "the CPU, whatever the run's learner uses" if from_learner else "the config's"
    parser.add_argument("--device", default=env.get(ENV_DEVICE) or None,
                        help=f"torch device: auto, cpu, cuda, cuda:N (env {ENV_DEVICE}; default: {device_default})")
    z = parser.add_argument_group("Zenoh", "endpoints (env COGEXPLORE_ZENOH_CONNECT/LISTEN/MODE/CONFIG; an option "
                                           "given here wins over its variable)")
    z.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="router endpoint to connect to, e.g. tcp/10.0.0.5:7447 (repeatable; default "
                        "tcp/127.0.0.1:7447)")
    z.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    z.add_argument("--zenoh-mode", choices=["client", "peer"], default=None, help="Zenoh session mode")
    z.add_argument("--zenoh-config", default=None, metavar="JSON5",
                   help="a Zenoh JSON5 config file (the options above override it); default: the run's "
                        "credentials, runs/<run>/secure/<role>.json5, where they exist")
    add_router_wait_argument(z)


def add_protocol_arguments(parser: argparse.ArgumentParser, default: str = DEFAULT_PROTOCOL) -> None:
    """``--protocol`` and the options that override its set (``protocol_from_args`` reads them)."""
    group = parser.add_argument_group("test protocol", "; ".join(p.describe() for p in PROTOCOLS.values()))
    group.add_argument("--protocol", choices=tuple(PROTOCOLS), default=default,
                       help=f"the named test conditions (default {default}); the options below override them, "
                            "and the results then name the protocol `custom`")
    group.add_argument("--start-jitter-m", type=float, default=None, metavar="M",
                       help="each episode starts within ±M m in x and y of the named start pose")
    group.add_argument("--start-jitter-deg", type=float, default=None, metavar="D",
                       help="and within ±D degrees of its heading")
    group.add_argument("--sensor-noise-m", type=float, default=None, metavar="S",
                       help="Gaussian depth noise of S m at every distance, instead of the set's (0: none)")


MAX_TORCH_THREADS = 1024
"""The most torch CPU threads a command takes: far beyond any machine's cores; OpenMP crashes the
process (no error) when asked for 100000000."""


def add_cpu_threads_argument(parser: argparse.ArgumentParser) -> None:
    """``--threads`` of a command that plays policies one image at a time (``evaluate``, ``report``,
    ``model select``)."""
    parser.add_argument("--threads", type=whole_number_argument(0, MAX_TORCH_THREADS), default=1, metavar="N",
                        help="torch CPU threads (default 1, as the services' actors and evaluator: a policy "
                             "steps one image at a time, and processes that each take every core wait on one "
                             "another, so two evaluations side by side, or one beside `cogexplore up`'s learner, "
                             "run several times slower; 0: torch's default, every core, a fifth faster on an "
                             "otherwise idle machine)")


def apply_cpu_threads(threads: int) -> None:
    """Give torch ``threads`` CPU threads for this process (0: leave torch's default)."""
    if threads:
        import torch

        torch.set_num_threads(threads)


def protocol_from_args(args: argparse.Namespace) -> ProtocolConfig:
    """The protocol of ``add_protocol_arguments``' options."""
    return protocol_named(args.protocol).overridden(
        start_jitter_m=args.start_jitter_m, start_jitter_deg=args.start_jitter_deg,
        sensor_noise_std_m=args.sensor_noise_m)
