"""The learner process: transitions in, DQN updates at the replay ratio, weights out.

    cogexplore learner --run NAME --preset fast

Zenoh callbacks only decode, validate and queue; one loop owns the replay memory and the
agent: drain the queue into replay -> run the updates that are due -> publish weights every
``--weights-every`` updates (from a sender thread that keeps only the newest, on a Zenoh
session of its own, so that neither a slow link nor a receiver that stops reading stalls
training or the flow control) -> publish flow control and statistics -> checkpoint. On start
with an existing run it resumes from the run's latest checkpoint; on SIGTERM/SIGINT or at
``total_updates`` it writes a final checkpoint and exits 0. Weights that have diverged (NaN or
infinite) are neither published nor saved: the learner stops with one error line naming the run's last
good checkpoint (a non-zero exit, which ``up`` reports as the run's failure); its next start resumes
there at half the learning rate (``shared.learning.divergence``).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import logging
import threading
import time
from pathlib import Path

import numpy as np
import torch

from services.bus.session import (
    LivelinessWatch,
    declare_alive,
    declare_reliable_publisher,
    open_service_session,
    serve_latest,
    subscribe_messages,
    zenoh_settings,
)
from services.process import setup_logging, stop_event_on_signals
from services.runs import RunLock, RunPaths, resolve_config, run_paths, save_config
from shared.config import RunConfig
from shared.learning.checkpoints import CheckpointError, CheckpointManager, NonFiniteWeights
from shared.learning.divergence import RunDivergences, sets_lr
from shared.learning.learner import Diverged, LearnerCore, RateMeter, diverged_error, resume_from
from shared.learning.model import resolve_device
from shared.learning.stats import CsvLog, LearnerRow, TensorBoardLog, rewind
from shared.learning.weights import to_message
from shared.wire.keys import KeyExprError, RunKeys, parse_key
from shared.wire.messages import (
    MAX_BATCH_STEPS,
    NON_FINITE,
    FlowControl,
    LearnerStats,
    MessageError,
    RejectCounter,
    RunConfigMessage,
    TransitionBatch,
    new_epoch,
)

log = logging.getLogger("cogexplore.learner")

INBOX_BYTES = 256 * 2**20
"""Received transition batches waiting for the learner's loop, at most (their arrays' bytes)."""
INBOX_BATCHES = 4096
INGEST_BUDGET_S = 0.05
"""Time one pass of the learner's loop spends taking batches in before its update and flow control."""


class BatchInbox:
    """Transition batches from the Zenoh threads to the learner's loop, bounded by their bytes
    (``max_bytes``) and count: 4096 batches of 160 x 120 frames held 10 GB. Flow control keeps a
    few hundred transitions per actor in flight; beyond that it is a flood, refused (the caller
    counts it)."""

    def __init__(self, max_bytes: int = INBOX_BYTES, max_batches: int = INBOX_BATCHES):
        self.max_bytes, self.max_batches = max_bytes, max_batches
        self._batches: collections.deque[tuple[TransitionBatch, int]] = collections.deque()
        self._bytes = 0
        self._lock = threading.Lock()

    def put(self, batch: TransitionBatch) -> bool:
        """Queue ``batch``; False (nothing queued) when the inbox is full."""
        size = sum(v.nbytes for v in vars(batch).values() if isinstance(v, np.ndarray))
        with self._lock:
            if len(self._batches) >= self.max_batches or self._bytes + size > self.max_bytes:
                return False
            self._batches.append((batch, size))
            self._bytes += size
            return True

    def get(self) -> TransitionBatch | None:
        """The oldest queued batch, or None."""
        with self._lock:
            if not self._batches:
                return None
            batch, size = self._batches.popleft()
            self._bytes -= size
            return batch


class LatestSender:
    """Publishes the newest weights on its own thread; older unsent versions are skipped."""

    def __init__(self, publisher, name: str = "weights-sender"):
        self._publisher = publisher
        self._cond = threading.Condition()
        self._pending: bytes | None = None
        self._closed = False
        self.latest: bytes | None = None  # also served to queries
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def offer(self, payload: bytes) -> None:
        with self._cond:
            self._pending = payload
            self.latest = payload
            self._cond.notify()

    def _run(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: self._pending is not None or self._closed)
                if self._pending is None:  # closed, and all offered was published
                    return
                payload, self._pending = self._pending, None
            try:
                self._publisher.put(payload)
            except Exception:
                log.exception("publishing weights failed")

    def close(self) -> None:
        """Publish the newest offer if it is still pending (the learner's final weights), then stop
        the thread; waits 5 s at most for a put in progress."""
        with self._cond:
            self._closed = True
            self._cond.notify()
        self._thread.join(timeout=5.0)


def run_learner(cfg: RunConfig, run: str, paths: RunPaths, settings, stop: threading.Event, *,
                learner_id: str = "learner", weights_every: int = 25, stats_every_s: float = 1.0,
                flow_slack: int | None = None, device: str | None = None, save_replay: bool = True,
                tensorboard: Path | None = None, pipeline: bool = False, lr_given: bool = False) -> dict:
    """The learner loop; saves ``cfg`` as the run's config once it has resumed. Returns final counters.
    ``tensorboard``: a folder for its rows as TensorBoard events; ``pipeline``: TD targets one update
    ahead on a second thread (LearnerCore); ``lr_given``: ``cfg``'s ``dqn.lr`` is the user's choice for this
    start, kept after a divergence (``shared.learning.divergence``). Diverged (after closing down) when the
    agent's weights have diverged: they are then neither published nor saved, and the run's checkpoints
    stay as they were."""
    with RunLock(paths, "learner"):  # one learner writes a run
        return _learn_locked(cfg, run, paths, settings, stop, learner_id=learner_id, weights_every=weights_every,
                             stats_every_s=stats_every_s, flow_slack=flow_slack, device=device,
                             save_replay=save_replay, tensorboard=tensorboard, pipeline=pipeline, lr_given=lr_given)


def _learn_locked(cfg: RunConfig, run: str, paths: RunPaths, settings, stop: threading.Event, *, learner_id: str,
                  weights_every: int, stats_every_s: float, flow_slack: int | None, device: str | None,
                  save_replay: bool, tensorboard: Path | None, pipeline: bool, lr_given: bool) -> dict:
    keys = RunKeys(run)
    paths.make()
    epoch = new_epoch()  # this process: its word replaces a quiet earlier learner's, whatever their update
    checkpoints = CheckpointManager(paths.checkpoints, keep=cfg.train.keep_checkpoints)
    divergences = RunDivergences(paths.root)
    cfg = divergences.resume_config(cfg, lr_given=lr_given)  # after a divergence: at half the rate it diverged at
    core = LearnerCore(cfg, device=device or cfg.train.device, pipeline=pipeline,
                       transfer=not checkpoints.checkpoints())
    resume_from(checkpoints, core)
    # The run's config is what trains it (a resume's --set dqn.lr included, which a later start without it
    # keeps), saved only now: a transfer or demonstration file it cannot read, or a checkpoint it does not
    # fit, refused the run, and its config stays as it was.
    save_config(cfg, paths)
    # its updates after the checkpoint come again; with none (a learner killed before its first), all do
    rewind(paths.stats, LearnerRow, core.updates)
    config_dict = cfg.to_dict()

    def save_checkpoint(final: bool = False) -> None:
        """A periodic checkpoint whose write fails is said and training goes on; a final one raises."""
        if core.checkpoint(checkpoints, config_dict, final=final, with_replay=save_replay) is not None:
            divergences.saved(core.updates, cfg.dqn.lr)

    def weights_message() -> bytes:
        try:  # the message checks its tensors are finite: a second pass over the weights would cost a publish
            return to_message(core.agent.online, core.agent.policy_version, learner_epoch=epoch).encode()
        except MessageError as exc:
            if exc.cause == NON_FINITE:
                core.check_finite()  # said as the network's divergence, naming the weight
            raise
    # a batch of this sensor's frames at most: anything longer is refused before it is copied
    batch_bytes = (MAX_BATCH_STEPS + 1) * cfg.sensor.height * cfg.sensor.width * 2 + 2**16
    inbox = BatchInbox()
    rejects = RejectCounter("transition batch", log)
    flow_slack = flow_slack if flow_slack is not None else max(256, 4 * cfg.dqn.batch_size)
    update_rate, transition_rate = RateMeter(), RateMeter()
    started = time.monotonic()

    def on_batch(batch: TransitionBatch, key: str) -> None:
        try:
            source = parse_key(key).source
        except KeyExprError as exc:  # a chunk the wildcard takes but no actor id can be ("a0~x")
            rejects.reject(MessageError("range", str(exc)), key)
            return
        if source != batch.actor_id:
            rejects.reject(MessageError("inconsistent", f"actor id {batch.actor_id!r} sent on {key}"), key)
            return
        if not inbox.put(batch):
            rejects.reject(MessageError("oversize", "learner inbox full"), key)

    # The weights go out on a session (a link to the router) of their own. The router forwards a message on
    # the task that reads the link it came on: a BLOCK message for a receiver that stopped reading (a laptop
    # asleep, a process stopped) holds that link for up to Zenoh's wait_before_close (5 s), and the sender's
    # own queue waits behind it. On one link with the weights, the flow control and statistics (DROP) waited
    # too: the learner's loop stood still and every actor ran out of credit, 5 s per such receiver. A learner
    # in peer or router mode keeps one session (second_link says why).
    weights_link = settings.second_link()
    with open_service_session(settings, stop) as session, \
            (open_service_session(weights_link, stop) if weights_link else contextlib.nullcontext(session)) \
            as weights_session, CsvLog(paths.stats, LearnerRow) as stats_log, TensorBoardLog(tensorboard) as board:
        actors = LivelinessWatch(session, keys.all_alive("actor"))
        sender = LatestSender(declare_reliable_publisher(weights_session, keys.weights))
        # A querier that stops reading holds a reply, and the link it goes out on, the same way: its replies
        # are given up (a follower without an answer takes the weights' stream, an unanswered config query
        # is asked again), and the newest weights (megabytes each) are answered on the weights' link.
        queryable = serve_latest(weights_session, keys.weights_latest, lambda: sender.latest, drop=True)  # noqa: F841
        run_config = RunConfigMessage(learner_id=learner_id, config=cfg).encode()  # what actors without a preset take
        config_queryable = serve_latest(session, keys.config, lambda: run_config, drop=True)  # noqa: F841
        sub = subscribe_messages(session, keys.all_transitions, TransitionBatch, on_batch, rejects,  # noqa: F841
                                 max_bytes=batch_bytes)
        flow_pub = session.declare_publisher(keys.flow)
        stats_pub = session.declare_publisher(keys.learner_stats(learner_id))
        sender.offer(weights_message())
        # Announce the learner only now that it can receive: actors start sending on this token.
        token = declare_alive(session, keys.alive("learner", learner_id))  # noqa: F841

        last_stats = last_flow = 0.0
        last_published = core.updates
        waiting_s = waiting_reported_s = 0.0  # time in passes with no update due: the learner waited for data

        def publish_stats(now: float) -> None:
            """One LearnerStats message and one learner.csv row (also TensorBoard's)."""
            nonlocal last_stats, waiting_reported_s
            waiting_share = min(1.0, (waiting_s - waiting_reported_s) / max(1e-9, now - max(last_stats, started)))
            waiting_reported_s = waiting_s
            loss, mean_q = core.recent()
            agreement, safe_agreement = core.recent_label_agreement(), core.recent_safe_agreement()
            lag = core.weight_lag()
            live = len(actors.alive)
            stats = LearnerStats(
                learner_id=learner_id, updates=core.updates, policy_version=core.agent.policy_version,
                replay_size=len(core.replay), transitions_received=core.received,
                transitions_rejected=rejects.total, loss=loss, mean_q=mean_q,
                updates_per_s=update_rate.rate(now), transitions_per_s=transition_rate.rate(now),
                uptime_s=now - started, rejects=rejects.counts,
                extra={"actors_alive": live, "dropped_nonfinite": core.dropped_nonfinite,
                       LearnerStats.WAITING_SHARE: waiting_share,
                       **({} if agreement is None else {"label_agreement": agreement}),
                       **({} if safe_agreement is None else {"safe_agreement": safe_agreement}),
                       "mean_weight_lag": (sum(lag.values()) / len(lag)) if lag else 0.0,
                       **{f"weight_lag.{a}": float(v) for a, v in list(lag.items())[-24:]},  # the 24 heard last
                       **{f"received.{a}": float(n) for a, n in list(core.received_by_actor.items())[-24:]}})
            stats_pub.put(stats.encode())
            row = LearnerRow(
                time_s=now - started, update=core.updates, policy_version=core.agent.policy_version, loss=loss,
                mean_q=mean_q, updates_per_s=stats.updates_per_s, transitions=core.received,
                transitions_per_s=stats.transitions_per_s, replay_size=len(core.replay),
                rejected=rejects.total, actors_alive=live, mean_weight_lag=stats.extra["mean_weight_lag"],
                label_agreement=agreement, safe_agreement=safe_agreement, lr=core.agent.lr if core.updates else None,
                session=epoch)
            stats_log.write(row)
            board.write_row(row)
            last_stats = now

        diverged: Diverged | NonFiniteWeights | None = None
        unsaved: CheckpointError | None = None
        try:
            while not stop.is_set() and not core.done:
                pass_started = time.monotonic()
                # 1. data in, for INGEST_BUDGET_S at most: a flood must not hold the updates, flow
                # control and a stop request off (the loop ingested until the inbox was empty)
                drained = 0
                while not stop.is_set() and time.monotonic() - pass_started < INGEST_BUDGET_S:
                    batch = inbox.get()
                    if batch is None:
                        break
                    try:
                        drained += core.ingest(batch)
                    except (MessageError, ValueError) as exc:
                        rejects.reject(exc if isinstance(exc, MessageError)
                                       else MessageError("inconsistent", str(exc)), batch.actor_id)
                if drained:
                    transition_rate.add(drained)
                # 2. one due update per pass (an update can take a second on a CPU: data, credit
                # and statistics keep flowing between updates)
                due = min(core.updates_due(), 1)
                # a step skipped for a non-finite loss (None) is no update: its checkpoint was written again
                trained = 0
                for _ in range(due):
                    if core.train_step() is not None:
                        trained += 1
                        update_rate.add(1)
                if core.updates - last_published >= weights_every:
                    sender.offer(weights_message())
                    last_published = core.updates
                # the last update's checkpoint is the final one below: written here too, it was written twice
                if core.updates and core.updates % cfg.train.checkpoint_every == 0 and trained and not core.done:
                    save_checkpoint()
                # 3. control and statistics
                now = time.monotonic()
                if now - last_flow >= 0.1 or due:
                    flow_pub.put(FlowControl(learner_id=learner_id, updates=core.updates,
                                             transitions_received=core.received,
                                             transitions_wanted=core.transitions_wanted(flow_slack),
                                             received_from=core.received_by_actor,
                                             actor_epochs=core.actor_epochs(), learner_epoch=epoch).encode())
                    last_flow = now
                if now - last_stats >= stats_every_s:
                    publish_stats(now)
                if not drained and not due:
                    time.sleep(0.005)  # idle: wait for data without spinning a core
                if not due:
                    waiting_s += time.monotonic() - pass_started

            # Final: the log's last row at the last update, weights out (actors and evaluator see the
            # last version), checkpoint.
            publish_stats(time.monotonic())
            sender.offer(weights_message())
            save_checkpoint(final=True)
        except (Diverged, NonFiniteWeights) as exc:  # it can no longer learn: its last good weights stay out
            diverged = exc
        except CheckpointError as exc:  # the final checkpoint's write failed: said once all is closed
            unsaved = exc
        sender.close()  # after it has put the final weights, even behind a slow put of earlier ones
        actors.close()
        core.close()
    if diverged is not None:
        raise diverged_error(diverged, checkpoints, core, divergences)
    if unsaved is not None:
        raise unsaved
    return {"updates": core.updates, "transitions": core.received, "rejected": rejects.total,
            "rejects": rejects.counts, "replay_size": len(core.replay)}


def run_learner_command(args: argparse.Namespace) -> int:
    paths = run_paths(args).make()
    setup_logging(args.log_level, paths.logs / "learner-service.log")
    cfg = resolve_config(args, paths)
    if args.updates is not None:
        cfg = cfg.with_overrides({"train.total_updates": args.updates})
    pipeline = args.pipeline == "on" or (args.pipeline == "auto"
                                         and resolve_device(cfg.train.device).type == "cpu")
    # pipelined, the two stages run side by side: each takes half the cores torch would use
    torch.set_num_threads(max(1, torch.get_num_threads() // (2 if pipeline else 1)))
    stop = stop_event_on_signals()
    settings = zenoh_settings(args, "learner")
    log.info("learner %s for run %r via %s", args.learner_id, args.run, settings.describe())
    result = run_learner(cfg, args.run, paths, settings, stop, learner_id=args.learner_id,
                         weights_every=args.weights_every, pipeline=pipeline, lr_given=sets_lr(args.overrides),
                         tensorboard=paths.tensorboard_folder(args.learner_id) if args.tensorboard else None)
    log.info("learner done: %s", json.dumps(result))  # one JSON line: scripts read it
    return 0
