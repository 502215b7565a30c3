"""The options of ``cogexplore evaluator`` and ``python -m services.evaluator``."""

from __future__ import annotations

import argparse
import os

from services.options import (
    add_protocol_arguments,
    add_service_arguments,
    count_argument,
    positive_number_argument,
    seconds_argument,
)
from services.viz import ENV_RERUN_URL
from shared.evaluation import PAPER_EPISODES_PER_START, PAPER_MAX_STEPS, TEST_SEED

DEFAULT_EVERY_UPDATES = 1000
CHEAP_EPISODES_PER_START = 1
DEFAULT_IMAGE_EVERY = 10


def add_evaluator_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``cogexplore evaluator`` (and ``python -m services.evaluator``)."""
    add_service_arguments(parser, from_learner=True)
    parser.add_argument("--id", default=None, help="evaluator id (default: evaluator-<host>-<pid>)")
    parser.add_argument("--every-updates", type=count_argument, default=DEFAULT_EVERY_UPDATES, metavar="K",
                        help=f"evaluate when the policy version enters a new multiple of K (default "
                             f"{DEFAULT_EVERY_UPDATES})")
    parser.add_argument("--full", action="store_true",
                        help=f"the paper's full protocol: {PAPER_EPISODES_PER_START} episodes per start "
                             f"(default {CHEAP_EPISODES_PER_START})")
    parser.add_argument("--episodes-per-start", type=count_argument, default=None, metavar="N",
                        help="episodes per start (overrides --full)")
    parser.add_argument("--max-steps", type=count_argument, default=PAPER_MAX_STEPS, metavar="N",
                        help=f"moving steps per episode at most (default {PAPER_MAX_STEPS})")
    parser.add_argument("--world", default=None, help="world to evaluate in (default: the run config's)")
    parser.add_argument("--image-every", type=count_argument, default=DEFAULT_IMAGE_EVERY, metavar="N",
                        help=f"record every N-th depth image (default {DEFAULT_IMAGE_EVERY})")
    parser.add_argument("--no-record", action="store_true", help="no .rrd recordings (live streaming stays)")
    parser.add_argument("--rerun-connect", metavar="URL", default=os.environ.get(ENV_RERUN_URL) or None,
                        help=f"also stream every evaluation live to the Rerun viewer at URL, e.g. "
                             f"rerun+http://rerun:9876/proxy (env {ENV_RERUN_URL}; default: none). A viewer "
                             "that does not answer is skipped with a warning; the service goes on")
    parser.add_argument("--seed", type=int, default=TEST_SEED,
                        help=f"seed of the evaluation episodes (default {TEST_SEED})")
    parser.add_argument("--once", action="store_true", help="evaluate the latest weights once and exit")
    parser.add_argument("--wait-weights", type=seconds_argument, default=60.0, metavar="SECONDS",
                        help="with --once: how long to wait for weights (default 60)")
    parser.add_argument("--query-timeout", type=positive_number_argument, default=2.0, metavar="SECONDS",
                        help="timeout of the start-up query for the latest weights (default 2)")
    add_protocol_arguments(parser)
