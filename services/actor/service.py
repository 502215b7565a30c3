"""The actor process: one environment, an epsilon-greedy policy on the newest weights it has,
transitions out in small reliable batches, weights in without ever blocking the env loop.

    cogexplore actor --run NAME --connect tcp/<router-host>:7447

Flow per step: take the newest weights the subscriber has parked (if any) -> pick an
action -> step the env -> batch the transition -> publish a batch when full or when the
episode ends. While no learner is alive (liveliness), the loop pauses instead of
publishing into the void, and resumes by itself when one is back.

With ``--rerun-connect URL`` (env ``COGEXPLORE_RERUN_URL``) every ``--rerun-every-episodes``-th
episode (env ``COGEXPLORE_RERUN_EVERY_EPISODES``, default 20) also goes live to that Rerun
viewer (``EpisodeStream``: depth every ``--rerun-image-every``-th step, pose, trajectory,
Q-values and the command taken), as one recording named after the actor. The env loop only
queues copies; a worker thread does the rest, and a viewer that is down is skipped.
"""

from __future__ import annotations

import argparse
import collections
import hashlib
import logging
import os
import threading
import time

import torch

from services.actor.batcher import TransitionBatcher
from services.common import (
    add_service_arguments, default_process_id, resolve_config, run_paths, setup_logging,
    stop_event_on_signals, zenoh_settings,
)
from shared.config import ConfigError, RunConfig
from shared.env import ExploreEnv
from shared.keys import RunKeys
from shared.messages import EpisodeStats, FlowControl, MessageError, RejectCounter, WeightsMessage
from shared.model import QNetwork, architecture_fingerprint, resolve_device
from shared.policy import EpsilonGreedyPolicy, EpsilonSchedule
from shared.supervised import ExpertGuide
from shared.transport import (
    LivelinessWatch, declare_alive, declare_reliable_publisher, open_session, query_latest,
    subscribe_messages,
)
from shared.weights import load_message

log = logging.getLogger("cogexplore.actor")

ENV_RERUN_URL = "COGEXPLORE_RERUN_URL"
ENV_RERUN_EVERY_EPISODES = "COGEXPLORE_RERUN_EVERY_EPISODES"
DEFAULT_RERUN_EVERY_EPISODES = 20
DEFAULT_RERUN_IMAGE_EVERY = 5


class WeightSlot:
    """The newest weights seen, parked by Zenoh threads and taken by the env loop.

    Holding only the newest means a slow actor skips versions instead of queueing them.
    """

    def __init__(self, fingerprint: str):
        self.fingerprint = fingerprint
        self._lock = threading.Lock()
        self._newest: WeightsMessage | None = None
        self.refused = 0

    def offer(self, message: WeightsMessage, _key: str = "") -> None:
        try:
            message.check_fingerprint(self.fingerprint)
        except MessageError as exc:
            if self.refused == 0:
                log.error("refusing weights: %s (is the learner running another model config?)", exc)
            self.refused += 1
            return
        with self._lock:
            if self._newest is None or message.policy_version > self._newest.policy_version:
                self._newest = message

    def take_newer_than(self, version: int) -> WeightsMessage | None:
        with self._lock:
            message = self._newest
        return message if message is not None and message.policy_version > version else None


class FlowGate:
    """The learner's replay-ratio credit (FlowControl) as seen by one actor: it may step
    while the learner still wants more transitions than this actor has in flight (sent,
    but not yet counted by the learner in ``received_from``).

    A transition not counted within ``horizon_s`` is taken as lost (e.g. sent just before
    the learner subscribed), so a lost batch can never hold the actor for good.
    """

    def __init__(self, actor_id: str, horizon_s: float = 10.0) -> None:
        self.actor_id = actor_id
        self.horizon_s = horizon_s
        self._lock = threading.Lock()
        self._credit: int | None = None  # None: no word from the learner yet
        self._received_from_me = 0
        self._sent = 0
        self._sends: collections.deque = collections.deque()  # (time, total sent after it)
        self._settled = 0  # total sent as of horizon_s ago: arrived or lost by now
        self.changed = threading.Event()

    def on_flow(self, message: FlowControl, _key: str = "") -> None:
        with self._lock:
            received = message.received_from.get(self.actor_id, 0)
            if received < self._received_from_me:  # the count went back: a restarted learner
                self._sent = self._settled = received
                self._sends.clear()
            self._credit = message.credit
            self._received_from_me = received
        self.changed.set()

    def reset(self) -> None:
        """Forget the accounting (a learner came back: it counts afresh)."""
        with self._lock:
            self._credit, self._received_from_me, self._sent, self._settled = None, 0, 0, 0
            self._sends.clear()

    def sent(self, transitions: int, now: float | None = None) -> None:
        with self._lock:
            self._sent += transitions
            self._sends.append((time.monotonic() if now is None else now, self._sent))

    def open(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        with self._lock:
            while self._sends and now - self._sends[0][0] > self.horizon_s:
                self._settled = self._sends.popleft()[1]
            if self._credit is None:
                return True
            in_flight = max(0, self._sent - max(self._received_from_me, self._settled))
            return self._credit - in_flight > 0


def run_actor(cfg: RunConfig, run: str, actor_id: str, settings, stop: threading.Event, *,
              actor_index: int = 0, num_actors: int = 1, batch_steps: int = 16,
              max_steps: int | None = None, seed: int | None = None, rerun_url: str | None = None,
              rerun_every_episodes: int = DEFAULT_RERUN_EVERY_EPISODES,
              rerun_image_every: int = DEFAULT_RERUN_IMAGE_EVERY) -> dict:
    """The actor loop; returns counters when ``stop`` is set (or after ``max_steps`` env steps).
    ``rerun_url``: stream every ``rerun_every_episodes``-th episode live to that Rerun viewer."""
    keys = RunKeys(run)
    device = resolve_device(cfg.train.device if cfg.train.device != "auto" else "cpu")
    torch.set_num_threads(1)  # several actors share the machine's cores with the learner
    seed = cfg.train.seed * 1000 + actor_index + 1 if seed is None else seed
    env = ExploreEnv(cfg.env, cfg.sensor)
    net = QNetwork(cfg.model, cfg.sensor).to(device)
    # The schedule runs on this actor's steps times the fleet size: an estimate of the global
    # env-step count that needs no message from anyone.
    policy = EpsilonGreedyPolicy(net, EpsilonSchedule(cfg.explore, actor_index, num_actors), seed=seed)
    guide = ExpertGuide(env, cfg.explore.expert_episode_prob, seed=seed + 7_919)
    batcher = TransitionBatcher(actor_id, batch_steps)
    slot = WeightSlot(architecture_fingerprint(net))
    rejects = RejectCounter("weights message", log)
    gate = FlowGate(actor_id)
    counters = {"env_steps": 0, "episodes": 0, "batches": 0, "paused_s": 0.0, "throttled_s": 0.0,
                "weights_loaded": 0}
    policy_version = 0
    stream = None
    if rerun_url:
        from services.evaluator.rerun_log import EpisodeStream

        stream = EpisodeStream(rerun_url, env.world, cfg.sensor, recording_name=f"actor {actor_id} ({run})",
                               every_episodes=rerun_every_episodes, image_every=rerun_image_every,
                               robot_radius_m=cfg.env.robot_radius_m)
        log.info("streaming every %d-th episode to the Rerun viewer at %s", rerun_every_episodes, rerun_url)

    with open_session(settings, wait_s=30.0) as session:
        token = declare_alive(session, keys.alive("actor", actor_id))  # noqa: F841  (kept alive)
        learners = LivelinessWatch(session, keys.all_alive("learner"))
        weights_sub = subscribe_messages(session, keys.weights, WeightsMessage, slot.offer, rejects)  # noqa: F841
        flow_sub = subscribe_messages(session, keys.flow, FlowControl, gate.on_flow, rejects)  # noqa: F841
        publisher = declare_reliable_publisher(session, keys.transitions(actor_id))
        stats_publisher = session.declare_publisher(keys.episode_stats(actor_id))

        def fetch_latest() -> None:  # on its own thread: the env loop never waits on a query
            payload = query_latest(session, keys.weights_latest, timeout_s=5.0)
            if payload is not None:
                message = rejects.decode(payload, WeightsMessage, source=keys.weights_latest)
                if message is not None:
                    slot.offer(message)

        threading.Thread(target=fetch_latest, name="weights-query", daemon=True).start()

        obs, info = env.reset(seed=seed)
        guide.begin_episode()
        policy.reset()
        batcher.begin_episode(obs, info["start_index"])
        if stream is not None:
            stream.begin_episode(batcher.episode, info["start_index"], env.world)
        episode_return, episode_start = 0.0, time.monotonic()
        paused_since: float | None = None
        while not stop.is_set() and (max_steps is None or counters["env_steps"] < max_steps):
            if not learners.alive:
                if paused_since is None:
                    paused_since = time.monotonic()
                    log.info("no learner alive on run %r: pausing", run)
                learners.wait(bool, timeout_s=0.5)
                continue
            if paused_since is not None:
                counters["paused_s"] += time.monotonic() - paused_since
                paused_since = None
                log.info("learner is back: resuming")
                gate.reset()
                threading.Thread(target=fetch_latest, name="weights-query", daemon=True).start()

            if not gate.open():
                # The learner is behind the replay ratio: wait for its next credit rather than
                # take CPU from it (both usually share a machine).
                held = time.monotonic()
                gate.changed.clear()
                gate.changed.wait(0.5)
                counters["throttled_s"] += time.monotonic() - held
                continue

            message = slot.take_newer_than(policy_version)
            if message is not None:
                load_message(net, message)
                policy_version = message.policy_version
                counters["weights_loaded"] += 1

            choice = policy.act(obs, step=counters["env_steps"] * num_actors, guide_action=guide.action(info["pose"]))
            action, epsilon = choice.action, choice.epsilon
            if stream is not None:  # info is still obs's: the pose the decision was taken at
                stream.log_step(info["step"], info["pose"], obs, choice.q_values, action)
            next_obs, reward, terminated, truncated, info = env.step(action)
            counters["env_steps"] += 1
            episode_return += reward
            batch = batcher.add(action, reward, next_obs, terminated, truncated, policy_version, info["pose"])
            if batch is not None:
                publisher.put(batch.encode())
                gate.sent(batch.steps)
                counters["batches"] += 1
            obs = next_obs
            if terminated or truncated:
                stats = EpisodeStats(
                    actor_id=actor_id, episode=batcher.episode, start_index=info["start_index"],
                    steps=info["step"], episode_return=episode_return, terminated=terminated,
                    truncated=truncated, collision_cause=info["collision_cause"],
                    path_length_m=info["path_length_m"], distance_from_start_m=info["distance_from_start_m"],
                    epsilon=epsilon, policy_version=policy_version,
                    duration_s=time.monotonic() - episode_start,
                    extra={"expert_guided": float(guide.active),
                           "extra_world": float(info["world"] != env.main_world.name)})
                stats_publisher.put(stats.encode())
                counters["episodes"] += 1
                if stream is not None:
                    stream.end_episode({"steps": info["step"], "truncated": truncated,
                                        "collision_cause": info["collision_cause"],
                                        "distance_m": info["distance_from_start_m"],
                                        "path_length_m": info["path_length_m"]}, final_pose=info["pose"])
                obs, info = env.reset()
                guide.begin_episode()
                policy.reset()
                batcher.begin_episode(obs, info["start_index"])
                if stream is not None:
                    stream.begin_episode(batcher.episode, info["start_index"], env.world)
                episode_return, episode_start = 0.0, time.monotonic()
        learners.close()
    env.close()
    counters["policy_version"] = policy_version
    counters["rejected_weights"] = rejects.total + slot.refused
    if stream is not None:
        stream.close()
        counters.update(rerun_episodes_streamed=stream.episodes_streamed, rerun_steps_streamed=stream.steps_logged,
                        rerun_episodes_skipped=stream.episodes_skipped, rerun_dropped=stream.dropped)
    return counters


def add_actor_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_arguments(parser)
    parser.add_argument("--actor-id", default=None, help="unique id (default: actor-<hostname>-<pid>)")
    parser.add_argument("--actor-index", type=int, default=None,
                        help="index i of this actor among --num-actors (per-actor epsilon, seed); default: "
                             "derived from the actor id, so scaled replicas differ")
    parser.add_argument("--num-actors", type=int, default=int(os.environ.get("COGEXPLORE_NUM_ACTORS", "1")),
                        help="number of actors N, for per-actor epsilon (env COGEXPLORE_NUM_ACTORS; default 1)")
    parser.add_argument("--batch-steps", type=int, default=16, help="transitions per published batch")
    parser.add_argument("--max-steps", type=int, default=None, help="stop after this many env steps")
    live = parser.add_argument_group("Rerun live", "watch a sample of this actor's episodes")
    live.add_argument("--rerun-connect", metavar="URL", default=os.environ.get(ENV_RERUN_URL) or None,
                      help=f"stream every N-th episode to the Rerun viewer at URL, e.g. "
                           f"rerun+http://127.0.0.1:9876/proxy (env {ENV_RERUN_URL}; default: none); a viewer "
                           "that does not answer is skipped")
    live.add_argument("--rerun-every-episodes", type=int, metavar="N",
                      # A string default goes through type=int: a bad env value is an option error.
                      default=os.environ.get(ENV_RERUN_EVERY_EPISODES) or str(DEFAULT_RERUN_EVERY_EPISODES),
                      help=f"stream every N-th episode (env {ENV_RERUN_EVERY_EPISODES}; default "
                           f"{DEFAULT_RERUN_EVERY_EPISODES})")
    live.add_argument("--rerun-image-every", type=int, default=DEFAULT_RERUN_IMAGE_EVERY, metavar="K",
                      help=f"depth image of every K-th step of a streamed episode (default {DEFAULT_RERUN_IMAGE_EVERY})")
    parser.add_argument("--log-level", default="INFO")


def run_actor_command(args: argparse.Namespace) -> int:
    paths = run_paths(args)
    actor_id = args.actor_id or default_process_id("actor")
    setup_logging(args.log_level)
    cfg = resolve_config(args, paths)
    stop = stop_event_on_signals()
    settings = zenoh_settings(args)
    log.info("actor %s joining run %r via %s", actor_id, args.run, settings.describe())
    if args.num_actors < 1:
        raise ConfigError(f"--num-actors must be >= 1, got {args.num_actors}")
    for option, value in (("--rerun-every-episodes", args.rerun_every_episodes),
                          ("--rerun-image-every", args.rerun_image_every)):
        if value < 1:
            raise ConfigError(f"{option} must be >= 1, got {value}")
    if args.rerun_connect:
        from services.evaluator.rerun_log import parse_viewer_url

        parse_viewer_url(args.rerun_connect)  # a malformed URL fails here, before the session opens
    # A stable hash (not Python's salted hash()) so that a restarted actor keeps its slot.
    digest = int(hashlib.sha256(actor_id.encode()).hexdigest()[:12], 16)
    index = args.actor_index if args.actor_index is not None else digest % args.num_actors
    if not 0 <= index < args.num_actors:
        raise ConfigError(f"--actor-index must be in [0, {args.num_actors}), got {index}")
    seed = cfg.train.seed * 1000 + (index if args.actor_index is not None else digest % 100_000) + 1
    counters = run_actor(cfg, args.run, actor_id, settings, stop, actor_index=index,
                         num_actors=args.num_actors, batch_steps=args.batch_steps, max_steps=args.max_steps,
                         seed=seed, rerun_url=args.rerun_connect, rerun_every_episodes=args.rerun_every_episodes,
                         rerun_image_every=args.rerun_image_every)
    log.info("actor %s done: %s", actor_id, counters)
    return 0
