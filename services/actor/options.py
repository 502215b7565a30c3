"""The options of ``cogexplore actor`` (light: importable without torch, MuJoCo or Zenoh)."""

from __future__ import annotations

import argparse
import os

from services.options import add_service_arguments, count_argument, whole_number_argument
from services.viz import ENV_RERUN_URL
from shared.wire.messages import MAX_BATCH_STEPS

ENV_RERUN_EVERY_EPISODES = "COGEXPLORE_RERUN_EVERY_EPISODES"
DEFAULT_RERUN_EVERY_EPISODES = 20
DEFAULT_RERUN_IMAGE_EVERY = 5
DEFAULT_NICENESS = 10
"""An actor's CPU niceness: the learner, the usual limit where they share cores, goes first."""


def add_actor_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_arguments(parser, from_learner=True)
    parser.add_argument("--actor-id", default=None, help="unique id (default: actor-<hostname>-<pid>)")
    parser.add_argument("--actor-index", type=int, default=None,
                        help="index i of this actor among --num-actors: its epsilon in a per-actor (Ape-X) "
                             "schedule, part of its seed (with its id and process), and which of the extra worlds "
                             "it builds; default: a hash of the actor id modulo --num-actors, so replicas that "
                             "cannot be numbered (compose's "
                             "--scale) may share an index (their seeds still differ), and each then builds every "
                             "extra world (a shared index would leave another's worlds unplayed)")
    # A string default goes through the type: a bad env value is an option error, not a traceback.
    parser.add_argument("--num-actors", type=count_argument, default=os.environ.get("COGEXPLORE_NUM_ACTORS") or "1",
                        help="number of actors N in the run: the epsilon schedule runs over the fleet's steps, "
                             "a per-actor schedule spreads over N, and with --actor-index each actor builds 1/N of "
                             "the extra worlds (env COGEXPLORE_NUM_ACTORS, which docker-compose.yml passes on: set "
                             "it to the --scale of actor; default 1)")
    parser.add_argument("--batch-steps", type=whole_number_argument(1, MAX_BATCH_STEPS), default=16,
                        help=f"transitions per published batch, at most {MAX_BATCH_STEPS} (the wire's limit; default 16)")
    parser.add_argument("--max-steps", type=count_argument, default=None, help="stop after this many env steps")
    parser.add_argument("--nice", type=int, default=DEFAULT_NICENESS, metavar="N",
                        help=f"lower this process's CPU priority by N, 0-19 (default {DEFAULT_NICENESS}): where it "
                             "shares cores with the learner (`up` on one machine) the learner goes first, which "
                             "made 7%% more updates/s on 2 cores; an actor mostly waits for flow-control credit anyway")
    live = parser.add_argument_group("Rerun live", "watch a sample of this actor's episodes")
    live.add_argument("--rerun-connect", metavar="URL", default=os.environ.get(ENV_RERUN_URL) or None,
                      help=f"stream every N-th episode to the Rerun viewer at URL, e.g. "
                           f"rerun+http://127.0.0.1:9876/proxy (env {ENV_RERUN_URL}; default: none); a viewer "
                           "that does not answer is skipped")
    live.add_argument("--rerun-every-episodes", type=int, metavar="N",
                      default=os.environ.get(ENV_RERUN_EVERY_EPISODES) or str(DEFAULT_RERUN_EVERY_EPISODES),
                      help=f"stream every N-th episode (env {ENV_RERUN_EVERY_EPISODES}; default "
                           f"{DEFAULT_RERUN_EVERY_EPISODES})")
    live.add_argument("--rerun-image-every", type=int, default=DEFAULT_RERUN_IMAGE_EVERY, metavar="K",
                      help=f"depth image of every K-th step of a streamed episode (default {DEFAULT_RERUN_IMAGE_EVERY})")
