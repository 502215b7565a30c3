"""The options of ``cogexplore up`` and ``cogexplore bench system`` (light: no torch, MuJoCo or Zenoh)."""

from __future__ import annotations

import argparse

from services.options import (
    MAX_TORCH_THREADS,
    add_runs_dir_argument,
    add_tensorboard_argument,
    count_argument,
    port_argument,
    positive_number_argument,
    seconds_argument,
    whole_number_argument,
)
from shared.config import DEFAULT_PRESET


def add_up_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--actors", type=count_argument, default=2, help="actor processes (default: 2)")
    parser.add_argument("--preset", default=None,
                        help=f"preset name or TOML path (default: the run's config.toml if it exists, else "
                             f"{DEFAULT_PRESET}, the shipped model's recipe)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override one config field (repeatable)")
    limit = parser.add_mutually_exclusive_group()
    limit.add_argument("--updates", type=count_argument, default=None,
                       help="stop after this many learner updates")
    limit.add_argument("--minutes", type=positive_number_argument, default=None, help="stop after this many minutes")
    parser.add_argument("--run", default=None, help="run name (default: run-<date>-<time>)")
    again = parser.add_mutually_exclusive_group()
    again.add_argument("--resume", action="store_true",
                       help="continue the existing run --run names: a finished one (its learner reached the total "
                            "updates) redoes its final evaluation and report, or trains on with a higher --updates; "
                            "without either flag an unfinished run resumes and a finished one is refused")
    again.add_argument("--fresh", action="store_true",
                       help="start the run over: its existing folder is kept, renamed to <run>.old-<date>-<time>")
    again.add_argument("--report-only", action="store_true",
                       help="no training: the final evaluation and report of the existing run --run names, as far as "
                            "its learner got (a run that services started without up, e.g. docker compose's, once its "
                            "learner has stopped); starts no router or service")
    add_runs_dir_argument(parser)
    parser.add_argument("--device", default=None, help="learner device: auto, cpu, cuda")
    add_tensorboard_argument(parser)  # passed on to the learner, actors and evaluator
    parser.add_argument("--port", type=port_argument, default=None,
                        help="router port on loopback (default: a free port)")
    parser.add_argument("--listen", action="append", default=None, metavar="ENDPOINT",
                        help="where the router listens instead: tls/0.0.0.0:7447 with --tls so that actors on "
                             "other machines can join (beyond loopback TLS only), tcp/127.0.0.1:PORT for actors "
                             "started by hand on this one (refused once the run has TLS: its access control admits "
                             "every role over TLS only, and its loopback router listens with TLS); repeatable")
    parser.add_argument("--tls", action="store_true",
                        help="a new run's security folder gets TLS certificates (the router's for localhost, this "
                             "machine's hostname and each --host): needed to listen beyond loopback")
    parser.add_argument("--host", action="append", default=[], metavar="NAME",
                        help="with --tls: another name or address other machines reach this one by (repeatable)")
    parser.add_argument("--eval-every", type=count_argument, default=1000,
                        help="evaluator: updates between evaluations (default 1000)")
    parser.add_argument("--no-evaluator", action="store_true", help="do not start the evaluator service")
    parser.add_argument("--final-episodes", type=count_argument, default=10,
                        help="episodes per start in the final evaluation (default 10, the paper's)")
    parser.add_argument("--final-average", type=count_argument, default=4, metavar="K",
                        help="the final evaluation and report play the mean of the last K checkpoints' weights, "
                             "exported as RUN/<run>-meanK.safetensors (default 4: a DQN's greedy policy swings "
                             "from one checkpoint to the next; 1: the last checkpoint alone); the run keeps at "
                             "least K checkpoints")
    parser.add_argument("--no-report", action="store_true", help="skip the final evaluation and report")
    parser.add_argument("--rerun-connect", default=None, metavar="URL",
                        help="stream evaluations and every 20th actor episode live to a Rerun viewer, "
                             "e.g. rerun+http://127.0.0.1:9876/proxy (start one with `rerun`)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def add_bench_system_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--actors", type=count_argument, default=None,
                        help="actor processes (default: 1; with --compare-single-process 2, as `up`)")
    # Options of one mode default to None so that one given to the other mode is refused, not dropped.
    parser.add_argument("--seconds", type=positive_number_argument, default=None,
                        help="measurement window (default: 60; not with --compare-single-process)")
    parser.add_argument("--warmup-s", type=seconds_argument, default=None,
                        help="seconds to wait once the system is in its steady state (default: 5; not with "
                             "--compare-single-process)")
    parser.add_argument("--preset", default=None,
                        help=f"preset name or TOML path (default: fast; with --compare-single-process {DEFAULT_PRESET}, "
                             "the shipped recipe)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                        help="override one config field, e.g. --set train.replay_ratio=0.02 to lift the "
                             "learner's flow control and measure raw actor throughput (repeatable)")
    compare = parser.add_argument_group("against the single-process trainer")
    compare.add_argument("--compare-single-process", action="store_true",
                         help="run `cogexplore up` (with --actors) and then `cogexplore train`, each for --minutes, and "
                              "print both runs' updates/s, env steps/s and scores under both protocols, and their "
                              "ratios (services/up/compare.py)")
    compare.add_argument("--minutes", type=positive_number_argument, default=None,
                         help="with --compare-single-process: wall time of each run (default 5)")
    compare.add_argument("--episodes-per-start", type=count_argument, default=None,
                         help="with --compare-single-process: test episodes per start for each score (default 2)")
    parser.add_argument("--device", default=None,
                        help="learner device: auto, cpu, cuda (not with --compare-single-process, whose runs "
                             "take the preset's)")
    parser.add_argument("--learner-threads", type=whole_number_argument(1, MAX_TORCH_THREADS), default=None,
                        help="OMP_NUM_THREADS for the started processes (default: inherited; not with "
                             "--compare-single-process)")
    parser.add_argument("--startup-timeout-s", type=positive_number_argument, default=None,
                        help="give up if the system is not in its steady state in this time (default: 600; not "
                             "with --compare-single-process)")
    parser.add_argument("--runs-dir", default=None,
                        help="keep the run folder (logs, stats) here; default: a temporary folder, removed")
    parser.add_argument("--json", action="store_true", help="print JSON")


def add_bench_fuzz_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--payloads", type=int, default=10_000, help="payloads to send in all (default 10000)")
    parser.add_argument("--max-bytes", type=int, default=64 * 1024,
                        help="random payloads and padding up to this size (default 65536)")
    parser.add_argument("--big-bytes", type=int, default=0,
                        help="also one zero-filled payload this large per key and round (memory; e.g. 50000000)")
    parser.add_argument("--preset", default="smoke", help="the fuzzed run's preset (default smoke)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the payloads (default 0)")
    parser.add_argument("--runs-dir", default=None, help="keep the run folder here (default: a temporary one, "
                                                         "removed unless a service crashed)")
    parser.add_argument("--json", action="store_true", help="print JSON (always)")
