"""The options of ``cogexplore learner``."""

from __future__ import annotations

import argparse

from services.options import add_service_arguments, count_argument


def add_learner_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_arguments(parser)
    parser.add_argument("--learner-id", default="learner", help="learner id (default: learner)")
    parser.add_argument("--updates", type=count_argument, default=None, help="override train.total_updates")
    parser.add_argument("--weights-every", type=int, default=25, help="updates between weight publications")
    parser.add_argument("--pipeline", choices=("auto", "on", "off"), default="auto",
                        help="compute each update's TD targets on a second thread during the update before it "
                             "(shared/learning/pipeline.py): auto = on a CPU (default), off on a GPU")
