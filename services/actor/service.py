"""The actor process: one environment, an epsilon-greedy policy on the newest weights it has,
transitions out in small reliable batches, weights in without ever blocking the env loop.

    cogexplore actor --run NAME --connect tcp/<router-host>:7447

Flow per step: take the newest weights the subscriber has parked (if any) -> pick an
action -> step the env -> batch the transition -> publish a batch when full or when the
episode ends (and the last steps when the actor stops). Epsilon runs over the fleet's env steps:
this actor's own times ``--num-actors``, but never behind the learner's count of the run's (a
restarted actor, or a resumed run, goes on where the run is). While no learner is alive
(liveliness), the loop pauses instead of publishing into the void, and resumes by itself when
one is back.

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
import json
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from services.actor.batcher import TransitionBatcher
from services.actor.options import (
    DEFAULT_RERUN_EVERY_EPISODES,
    DEFAULT_RERUN_IMAGE_EVERY,
)
from services.bus.follower import WeightFollower
from services.bus.run_config import join_run_config
from services.bus.session import (
    LivelinessWatch,
    declare_alive,
    declare_reliable_publisher,
    open_service_session,
    zenoh_settings,
)
from services.process import default_process_id, lower_priority, setup_logging, stop_event_on_signals
from services.runs import run_paths
from shared.config import ConfigError, RunConfig
from shared.expert.expert import ExpertGuide
from shared.learning.model import (
    QNetwork,
    architecture_fingerprint,
    named_shapes,
    resolve_device,
)
from shared.learning.policy import EpsilonGreedyPolicy, EpsilonSchedule
from shared.learning.stats import TensorBoardLog, episode_row
from shared.rollout import Episode, Rollout, Step
from shared.sim.env import ExploreEnv
from shared.wire.keys import RunKeys
from shared.wire.messages import (
    EpisodeStats,
    FlowControl,
    LearnerEpochs,
    RejectCounter,
    TransitionBatch,
    future_epoch_error,
    new_epoch,
)

log = logging.getLogger("cogexplore.actor")

FLOW_QUIET_S = 2.0
"""How long the followed learner must have sent no flow control (it speaks every 0.1 s) before
another learner process's is taken."""


class FlowGate:
    """The learner's replay-ratio credit (FlowControl) as seen by one actor process: it may step
    while the learner still wants more transitions than this actor has in flight (sent, but not
    yet counted by the learner in ``received_from``).

    It holds until the learner's first word, so nothing is sent beyond the learner's want at the
    start or after a learner came back. It follows one learner process
    (:class:`shared.wire.messages.LearnerEpochs`): flow control of another learner epoch is ignored
    while the followed learner speaks, and starts the accounting afresh once it has been quiet for
    ``quiet_s`` (a restarted learner; a forged credit of 0 would otherwise hold the actor for good);
    one from the future is refused. The learner counts per actor process
    (``actor_epoch``): a count of a predecessor under the same id is not this process's.

    A transition not counted within ``horizon_s`` is taken as lost (e.g. sent just before
    the learner subscribed), so a lost batch can never hold the actor for good; for the same
    reason, a learner that says nothing for ``horizon_s`` after the gate began to wait no longer
    holds it (a learner speaks every 0.1 s).
    """

    def __init__(self, actor_id: str, horizon_s: float = 10.0, actor_epoch: int = 0,
                 rejects: RejectCounter | None = None, quiet_s: float = FLOW_QUIET_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.actor_id = actor_id
        self.rejects = rejects
        self.actor_epoch = actor_epoch
        self.horizon_s = horizon_s
        self._waiting_since: float | None = None  # when open() first found no credit
        self._lock = threading.Lock()
        self._epochs = LearnerEpochs(quiet_s, clock)  # the learner process whose word counts
        self._credit: int | None = None  # None: no word from the learner yet: hold
        self._received_from_me = 0
        self._sent = 0
        self._sends: collections.deque = collections.deque()  # (time, total sent after it)
        self._lost = 0  # sent, and never to be counted by the learner (not counted within horizon_s)
        self.ignored = 0
        """Flow-control messages of another learner process than the one followed, or from the future."""
        self.run_steps = 0
        """Transitions the followed learner has received in all: the run's env steps (a resumed run's too)."""
        self.changed = threading.Event()

    def on_flow(self, message: FlowControl, _key: str = "") -> None:
        with self._lock:
            first = self._epochs.followed is None
            verdict = self._epochs.admit(message.learner_epoch)
            if verdict == LearnerEpochs.FUTURE:
                if self.rejects is not None:  # not a late word of a dead learner: an impossible one
                    self.rejects.reject(future_epoch_error("flow control"), _key)
                self.ignored += 1
                return
            if verdict == LearnerEpochs.OTHER:
                self.ignored += 1
                return
            if verdict == LearnerEpochs.NEW and not first:  # another learner process counts afresh
                self._sent = self._lost = 0
                self._sends.clear()
                self._received_from_me = 0
            mine = message.actor_epochs.get(self.actor_id) == self.actor_epoch
            received = message.received_from.get(self.actor_id, 0) if mine else 0
            if received < self._received_from_me:  # the count went back: the learner lost track
                self._sent, self._lost = received, 0
                self._sends.clear()
            self._credit = message.credit
            self._received_from_me = received
            self.run_steps = message.transitions_received
        self.changed.set()

    def reset(self) -> None:
        """Forget the credit (a learner came back: wait for its word), and take what was sent before as
        arrived or lost. Only that: the same learner process (back after a router restart)
        goes on with its count of this actor's transitions, so what is sent from now on counts as in
        flight against it; another learner's first word starts the accounting afresh (``on_flow``)."""
        with self._lock:
            self._credit, self._waiting_since = None, None
            self._sends.clear()
            self._sends.append((float("-inf"), self._sent))  # settled at the next open()

    def sent(self, transitions: int, now: float | None = None) -> None:
        with self._lock:
            self._sent += transitions
            self._sends.append((time.monotonic() if now is None else now, self._sent))

    def open(self, now: float | None = None) -> bool:
        now = time.monotonic() if now is None else now
        with self._lock:
            while self._sends and now - self._sends[0][0] > self.horizon_s:
                # all sent up to then has arrived (in order) or never will: the learner's shortfall is lost.
                # (Its count compared with a total of horizon_s ago instead held that loss against the
                # actor for as long as it sent more than the loss in horizon_s.)
                self._lost = max(self._lost, self._sends.popleft()[1] - self._received_from_me)
            # nor can more be lost than the learner has not counted (one it counted late, after a stall, was not)
            self._lost = min(self._lost, max(0, self._sent - self._received_from_me))
            if self._credit is None:
                self._waiting_since = now if self._waiting_since is None else self._waiting_since
                return now - self._waiting_since > self.horizon_s
            self._waiting_since = None
            in_flight = max(0, self._sent - self._received_from_me - self._lost)
            return self._credit - in_flight > 0


class Outbox:
    """Rollout observer: what an actor publishes. Each step goes into the episode's current batch
    (``TransitionBatcher``), sent when full or when the episode ends; each finished episode goes
    out as ``EpisodeStats``. ``policy_version`` is the version of the weights acting now."""

    def __init__(self, actor_id: str, batcher: TransitionBatcher, publisher: Any, stats_publisher: Any,
                 gate: FlowGate, guide: ExpertGuide, main_world: str, rejects: RejectCounter):
        self.actor_id = actor_id
        self.rejects = rejects
        self.batcher = batcher
        self.publisher = publisher
        self.stats_publisher = stats_publisher
        self.gate = gate
        self.guide = guide
        self.main_world = main_world
        self.policy_version = 0
        self.batches = 0
        self.held_s = 0.0
        """Seconds of the current episode spent held by flow control."""

    def begin_episode(self, episode: Episode) -> None:
        self.batcher.begin_episode(episode.first_obs, episode.first_info["start_index"])

    def on_step(self, step: Step) -> None:
        batch = self.batcher.add(step.action, step.reward, step.next_obs, step.terminated, step.truncated,
                                 self.policy_version, step.next_info["pose"],
                                 self.guide.teacher_label(step.info["pose"]),
                                 self.guide.safe_label(step.info["pose"]))
        if batch is not None:
            self._send(batch)

    def flush(self) -> None:
        """Send the steps of the episode still playing (the actor stops): each is a whole transition
        (its next image included), stored by the learner as any batch cut mid-episode is."""
        batch = self.batcher.flush()
        if batch is not None:
            self._send(batch)

    def _send(self, batch: TransitionBatch) -> None:
        self.publisher.put(batch.encode())
        self.gate.sent(batch.steps)
        self.batches += 1

    def end_episode(self, episode: Episode) -> None:
        info = episode.info
        stats = EpisodeStats(
            actor_id=self.actor_id, episode=episode.index, start_index=info["start_index"],
            steps=info["step"], episode_return=episode.episode_return, terminated=episode.terminated,
            truncated=episode.truncated, collision_cause=info["collision_cause"],
            path_length_m=info["path_length_m"], distance_from_start_m=info["distance_from_start_m"],
            epsilon=episode.last_step.choice.epsilon, policy_version=self.policy_version,
            duration_s=time.monotonic() - episode.started_s,
            extra={"expert_guided": float(self.guide.active), "extra_world": float(info["world"] != self.main_world),
                   "failure_start": float(info["failure_start"]),
                   EpisodeStats.HELD_S: self.held_s, EpisodeStats.REJECTED: float(self.rejects.total)})
        self.held_s = 0.0
        self.stats_publisher.put(stats.encode())


class EpisodeScalars:
    """Rollout observer: each finished episode as an ``EpisodeRow`` to TensorBoard, at this actor's
    env step; its ``update`` is the policy version acting when the episode ended."""

    def __init__(self, board: TensorBoardLog, outbox: Outbox, guide: ExpertGuide):
        self.board, self.outbox, self.guide = board, outbox, guide
        self.env_steps = 0
        self.started = time.monotonic()

    def on_step(self, step: Step) -> None:
        self.env_steps += 1

    def end_episode(self, episode: Episode) -> None:
        self.board.write_row(episode_row(episode, env_step=self.env_steps, update=self.outbox.policy_version,
                                         time_s=time.monotonic() - self.started, expert_guided=self.guide.active))


class LiveEpisodes:
    """Rollout observer: a sample of the episodes to a live Rerun viewer (``EpisodeStream``)."""

    def __init__(self, stream: Any, env: ExploreEnv):
        self.stream = stream
        self.env = env

    def begin_episode(self, episode: Episode) -> None:
        self.stream.begin_episode(episode.index, episode.first_info["start_index"], self.env.world)

    def on_step(self, step: Step) -> None:  # the pose the decision was taken at
        self.stream.log_step(step.info["step"], step.info["pose"], step.obs, step.q_values, step.action)

    def end_episode(self, episode: Episode) -> None:
        info = episode.info
        self.stream.end_episode({"steps": info["step"], "truncated": episode.truncated,
                                 "collision_cause": info["collision_cause"],
                                 "distance_m": info["distance_from_start_m"],
                                 "path_length_m": info["path_length_m"]}, final_pose=info["pose"])


def process_seed(run_seed: int, actor_index: int, actor_id: str, actor_epoch: int) -> int:
    """The seed of an actor process's episodes (starts, exploration noise, the expert's draws): the
    run's ``train.seed``, the actor's index and id, and the process's epoch, so that a restarted actor
    (same id, same index) plays new episodes, not its predecessor's again into the same replay."""
    key = f"{run_seed}/{actor_index}/{actor_id}/{actor_epoch}".encode()
    return int.from_bytes(hashlib.sha256(key).digest()[:8], "big")


def run_actor(cfg: RunConfig, run: str, actor_id: str, settings, stop: threading.Event, *,
              actor_index: int = 0, num_actors: int = 1, share_worlds: bool = True, batch_steps: int = 16,
              max_steps: int | None = None, seed: int | None = None, rerun_url: str | None = None,
              rerun_every_episodes: int = DEFAULT_RERUN_EVERY_EPISODES,
              rerun_image_every: int = DEFAULT_RERUN_IMAGE_EVERY, tensorboard: Path | None = None) -> dict:
    """The actor loop; returns counters when ``stop`` is set (or after ``max_steps`` env steps).
    ``share_worlds``: build only this actor's 1/``num_actors`` of the extra worlds (its index is its
    own: a hashed index may be another actor's too, and the worlds of an index no one has would
    never be played). ``rerun_url``: stream every ``rerun_every_episodes``-th episode live to that Rerun viewer.
    ``tensorboard``: a folder for its episodes as TensorBoard events. ``seed``: of its episodes, fixed
    (the same episodes every time); by default :func:`process_seed`, new for each process."""
    keys = RunKeys(run)
    device = resolve_device(cfg.train.device if cfg.train.device != "auto" else "cpu")
    torch.set_num_threads(1)  # several actors share the machine's cores with the learner
    actor_epoch = new_epoch()  # this process: the learner's allowance for it starts from nothing
    seed = process_seed(cfg.train.seed, actor_index, actor_id, actor_epoch) if seed is None else seed
    env = ExploreEnv(cfg.env, cfg.sensor)
    if share_worlds:
        env.share_extra_worlds(actor_index % num_actors, num_actors)  # a world costs ~0.2 s of CPU to build
    net = QNetwork(cfg.model, cfg.sensor).to(device).eval()  # it only acts: no dropout, no mode switch per step
    guide = ExpertGuide(env, cfg.explore.expert_episode_prob, seed=seed + 7_919,
                        label_prob=cfg.explore.expert_label_prob, safe_prob=cfg.explore.safe_label_prob)
    policy = EpsilonGreedyPolicy(net, EpsilonSchedule(cfg.explore, actor_index, num_actors), seed=seed,
                                 guide=guide, step_scale=num_actors)
    rejects = RejectCounter("weights or flow message", log)
    follower = WeightFollower(architecture_fingerprint(net), rejects, shapes=named_shapes(net))
    gate = FlowGate(actor_id, actor_epoch=actor_epoch)  # a bad flow message is counted once, by the follower
    counters = {"env_steps": 0, "episodes": 0, "batches": 0, "paused_s": 0.0, "throttled_s": 0.0,
                "weights_loaded": 0}
    stream = None
    if rerun_url:
        from services.viz.rerun import EpisodeStream

        stream = EpisodeStream(rerun_url, env.world, cfg.sensor, recording_name=f"actor {actor_id} ({run})",
                               every_episodes=rerun_every_episodes, image_every=rerun_image_every,
                               robot_radius_m=cfg.env.robot_radius_m)
        log.info("streaming every %d-th episode to the Rerun viewer at %s", rerun_every_episodes, rerun_url)

    with open_service_session(settings, stop) as session, TensorBoardLog(tensorboard) as board, \
            follower.following(session, keys, on_flow=gate.on_flow):
        token = declare_alive(session, keys.alive("actor", actor_id))  # noqa: F841  (kept alive)
        learners = LivelinessWatch(session, keys.all_alive("learner"))
        outbox = Outbox(actor_id, TransitionBatcher(actor_id, batch_steps, actor_epoch),
                        declare_reliable_publisher(session, keys.transitions(actor_id)),
                        session.declare_publisher(keys.episode_stats(actor_id)), gate, guide, env.main_world.name,
                        rejects)
        loop = Rollout(env, policy, [guide, outbox] + ([EpisodeScalars(board, outbox, guide)] if board.enabled else [])
                       + ([LiveEpisodes(stream, env)] if stream is not None else []))
        loop.begin_episode(seed=seed)
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
                follower.fetch_latest(session, keys, background=True)

            if not gate.open():
                # The learner is behind the replay ratio: wait for its next credit rather than
                # take CPU from it (both usually share a machine).
                held = time.monotonic()
                gate.changed.clear()
                gate.changed.wait(0.5)
                held = time.monotonic() - held
                counters["throttled_s"] += held
                outbox.held_s += held
                continue

            message = follower.take()
            if message is not None and follower.load(net, message):
                outbox.policy_version = message.policy_version
                counters["weights_loaded"] += 1

            # epsilon's step: this process's own count times the fleet's size, but no less than the run's
            # (a restarted actor, or any of a resumed run, started again at eps_start)
            loop.env_steps = max(loop.env_steps, -(-gate.run_steps // num_actors))
            step = loop.step()
            counters["env_steps"] += 1
            if step.last:
                counters["episodes"] += 1
                loop.begin_episode()
        if paused_since is not None:  # stopped while paused: that wait counts too
            counters["paused_s"] += time.monotonic() - paused_since
        outbox.flush()
        learners.close()
    env.close()
    counters.update(batches=outbox.batches, policy_version=outbox.policy_version, rejected_weights=rejects.total)
    if stream is not None:
        stream.close()
        counters.update(rerun_episodes_streamed=stream.episodes_streamed, rerun_steps_streamed=stream.steps_logged,
                        rerun_episodes_skipped=stream.episodes_skipped, rerun_dropped=stream.dropped)
    return counters


def run_actor_command(args: argparse.Namespace) -> int:
    paths = run_paths(args)
    actor_id = args.actor_id or default_process_id("actor")
    setup_logging(args.log_level)
    settings = zenoh_settings(args, "actor")
    log.info("actor %s joining run %r via %s", actor_id, args.run, settings.describe())
    for option, value in (("--rerun-every-episodes", args.rerun_every_episodes),
                          ("--rerun-image-every", args.rerun_image_every)):
        if value < 1:
            raise ConfigError(f"{option} must be >= 1, got {value}")
    if args.rerun_connect:
        from services.viz.rerun import parse_viewer_url

        parse_viewer_url(args.rerun_connect)  # a malformed URL fails here, before the session opens
    # A stable hash (not Python's salted hash()) so that a restarted actor keeps its slot.
    digest = int(hashlib.sha256(actor_id.encode()).hexdigest()[:12], 16)
    index = args.actor_index if args.actor_index is not None else digest % args.num_actors
    if not 0 <= index < args.num_actors:
        raise ConfigError(f"--actor-index must be in [0, {args.num_actors}), got {index}")
    lower_priority(args.nice)  # before the first session: its Zenoh threads, and torch's, take it too
    cfg, check = join_run_config(args, paths, settings, "this actor")  # before the handlers: Ctrl-C ends a wait
    stop = stop_event_on_signals()
    if check is not None:
        check.start(settings, stop)  # a preset the run's data cannot use stops the actor
    counters = run_actor(cfg, args.run, actor_id, settings, stop, actor_index=index,
                         num_actors=args.num_actors, share_worlds=args.actor_index is not None, batch_steps=args.batch_steps, max_steps=args.max_steps,
                         rerun_url=args.rerun_connect, rerun_every_episodes=args.rerun_every_episodes,
                         rerun_image_every=args.rerun_image_every,
                         tensorboard=paths.tensorboard_folder(actor_id) if args.tensorboard else None)
    log.info("actor %s done: %s", actor_id, json.dumps(counters))  # one JSON line: scripts read it
    refused = check.finish() if check is not None else None
    if refused is not None:
        raise refused
    return 0
