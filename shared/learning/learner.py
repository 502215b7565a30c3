"""The learner's algorithm side, without Zenoh: replay memory + DQN agent + the replay-ratio
rule, and resuming them from a run's checkpoints. Both the learner service
(``services/learner/service.py``) and the single-process trainer (``services/tools/train.py``)
drive one of these.

Replay ratio r = updates per inserted transition (the paper's Algorithm 1: one update per
environment step, r = 1). After ``warmup_transitions`` have arrived, update k is due once
``r * (received - warmup) >= k``; the learner asks actors for data only up to the point
where the ratio would fall behind (``transitions_wanted``), see shared.wire.messages.FlowControl.
A resume whose replay memory is empty (not kept) warms up again: the transitions received before it
stop counting for the ratio (``LearnerCore.unpaced``, :func:`resume_from`).

What comes in is checked against the task itself (``TransitionBatch.require_physical``: rewards the
task pays, depth within the sensor's range), and what the learner keeps per actor is bounded
(:data:`MAX_TRACKED_ACTORS`, the least recently heard forgotten first), so no message, and no number
of invented actor ids, can poison the replay memory or outgrow the learner. An update whose loss is
not finite is not applied: the transitions that made it so leave the replay memory, counted.
"""

from __future__ import annotations

import collections
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Hashable

import numpy as np

from shared.config import RunConfig, is_whole
from shared.learning.checkpoints import (
    CheckpointError,
    CheckpointManager,
    NonFiniteWeights,
    init_agent_conv,
    init_agent_weights,
    non_finite_tensor,
)
from shared.learning.demos import DemoError, Demonstration, demo_replay, load_demonstrations
from shared.learning.divergence import RunDivergences
from shared.learning.dqn import DQNAgent, DQNError, NonFiniteLoss
from shared.learning.pipeline import TargetPipeline
from shared.learning.replay import Batch, ReplayError, ReplayMemory, concat_batches
from shared.wire.messages import MAX_BATCH_STEPS, TransitionBatch

log = logging.getLogger("cogexplore.learner")

MAX_TRACKED_ACTORS = 256
"""Actor processes the learner keeps a record of (counts, weights version); beyond, the one heard
from least recently is forgotten (a real fleet is far smaller; invented ids cannot grow it)."""


class Diverged(DQNError):
    """The agent can no longer learn: a weight is NaN or infinite, or every sample's loss is. Its
    weights must reach neither an actor nor a checkpoint (:func:`diverged_error`)."""


def diverged_error(cause: Exception, checkpoints: CheckpointManager, core: "LearnerCore | None" = None,
                   divergences: RunDivergences | None = None) -> Diverged:
    """The one-line error a learner stops with when its agent has diverged (``cause``): what diverged,
    and the run's newest checkpoint that loads, which a resume starts from. With ``core`` and
    ``divergences`` (the run's record) the divergence is recorded, and the line says the rate the next
    start resumes at."""
    good = checkpoints.load_latest()
    where = (f"the run resumes from its last good checkpoint {good.path} (update {good.update_count})"
             if good is not None else f"no checkpoint in {checkpoints.directory} loads")
    if core is not None and divergences is not None:
        where += "; " + divergences.diverged(update=core.updates, resumed_from=good.update_count if good else 0,
                                             lr=core.cfg.dqn.lr, cause=str(cause))
    return Diverged(f"{cause}; stopped without saving its weights: {where}")


@dataclass
class ActorRecord:
    """What the learner knows of one actor process."""

    epoch: int
    """The process's ``actor_epoch``: a restart under the same id is a new record."""
    received: int = 0
    """Transitions received from this process."""
    version: int = 0
    """The weights version its newest transitions were chosen with."""
    seen_s: float = field(default_factory=time.monotonic)


def transfer_weights(agent: DQNAgent, cfg: RunConfig) -> None:
    """The run's transfer into a new agent: ``train.init_from`` (the whole network) or else
    ``train.init_conv_from`` (the supervised conv layers); CheckpointError when a file is missing
    or does not fit."""
    if cfg.train.init_from:  # fine-tuning: the whole network, conv layers included
        init_agent_weights(agent, cfg.train.init_from)
    elif cfg.train.init_conv_from:
        init_agent_conv(agent, cfg.train.init_conv_from)


def run_demonstrations(cfg: RunConfig) -> list[Demonstration]:
    """The run's planner demonstrations (``train.demos``), read and checked (DemoError), their rewards
    against the task's too: what an actor's transitions must pass, a demonstration must."""
    frame_shape = (cfg.sensor.height, cfg.sensor.width)
    demos = []
    for path in cfg.train.demo_paths:
        for i, d in enumerate(load_demonstrations(path, frame_shape)):
            # Every step a move the task pays, but a collision's last, r_ter: a file recorded under
            # another reward (or a finite but huge one) would bend every TD target it reaches.
            paid = cfg.env.pays_for_a_move(d.rewards)
            if d.terminated:
                paid[-1] = d.rewards[-1] == np.float32(cfg.env.reward_collision)
            if not paid.all():
                bad = int(np.flatnonzero(~paid)[0])
                raise DemoError(f"{path}: demonstration {i}: reward[{bad}] = {float(d.rewards[bad])!r}, this "
                                f"task pays {cfg.env.describe_rewards()} (recorded under another env reward?)")
            demos.append(d)
    return demos


def check_start_sources(cfg: RunConfig, *, resumed_from: RunConfig | None = None) -> None:
    """Load what a learner of ``cfg`` reads from files at its start besides its checkpoint, so that a
    launcher refuses a missing or unfit one before it saves the config, not in the learner after: the
    demonstrations, and the transfer's weights unless the run resumes from a checkpoint
    (``resumed_from``: the config it was saved with) with the same transfer files (the checkpoint
    replaces those weights, and the files may have gone since; one given anew is checked all the same).
    Raises CheckpointError or DemoError."""
    same_transfer = resumed_from is not None and all(
        getattr(cfg.train, name) == getattr(resumed_from.train, name) for name in ("init_from", "init_conv_from"))
    if not same_transfer:
        transfer_weights(DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu"), cfg)
    run_demonstrations(cfg)


class LearnerCore:
    """Replay memory, agent and the replay-ratio rule. ``pipeline``: compute each update's TD targets
    on a second thread during the update before it (:class:`shared.learning.pipeline.TargetPipeline`;
    call :meth:`close` at the end). ``transfer``: start from the run's transfer files (``train.init_from``,
    ``init_conv_from``); not for a run that resumes from a checkpoint, which replaces those weights (the
    files may have gone since)."""

    def __init__(self, cfg: RunConfig, device: str = "auto", *, pipeline: bool = False, transfer: bool = True):
        self.cfg = cfg
        self.agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device=device, seed=cfg.train.seed)
        # its copies of the nets are refreshed at every batch, so a later resume or transfer reaches them
        self._pipeline = TargetPipeline(self.agent) if pipeline else None
        if transfer:  # before any resume, which overwrites these weights
            transfer_weights(self.agent, cfg)
        frame_shape = (cfg.sensor.height, cfg.sensor.width)
        self.replay = ReplayMemory(cfg.replay, frame_shape, seed=cfg.train.seed)
        # Planner demonstrations (train.demos) live apart and are never overwritten; they are
        # read from their files at every start, so checkpoints do not carry them.
        self.demo_replay: ReplayMemory | None = None
        demos = run_demonstrations(cfg)
        if demos:
            self.demo_replay = demo_replay(demos, frame_shape, seed=cfg.train.seed + 3)
        self.received = 0
        """Transitions received in all (the run's env steps; stats, epsilon, the actors' credit)."""
        self.unpaced = 0
        """Of ``received``, those the replay ratio no longer counts: a resume that found no replay memory
        sets it (:func:`resume_from`), so a new warm-up fills the memory before the next update."""
        self.actors: collections.OrderedDict[str, ActorRecord] = collections.OrderedDict()
        """Actor id -> its current process's record, least recently heard first."""
        self.dropped_nonfinite = 0
        """Transitions removed from replay because an update on them had a non-finite loss."""
        self._max_depth_mm = math.ceil(cfg.sensor.max_range_m * 1000)
        self._window: collections.deque = collections.deque(maxlen=1000)  # (loss, q_mean)
        self._agreement_windows: dict[str, collections.deque] = {
            name: collections.deque(maxlen=1000) for name in ("label_agreement", "safe_agreement")}
        self._last_metrics: dict[str, Any] = {}

    # -- data in ---------------------------------------------------------------------------
    def add_transition(self, stream_id: Hashable, obs: np.ndarray | None, action: int, reward: float,
                       next_obs: np.ndarray | None, terminated: bool, truncated: bool,
                       expert_action: int | None = None, safe_commands: int = 0, step: int | None = None) -> None:
        """Store one transition (ReplayError for a reward this task does not pay: one finite but huge
        reward, stored, would make every TD target it reaches huge). ``expert_action``: the expert's
        command in ``obs`` (``explore.expert_label_prob``), None: no label; ``safe_commands``: its
        safe-set bitmask there (``explore.safe_label_prob``), 0: no mark; ``step``: its index in the
        episode, which links it only to the stream's transition of the step before (None: any)."""
        if not self.cfg.env.pays(reward):
            raise ReplayError(f"reward {reward!r} is not one this task pays "
                              f"(it pays {self.cfg.env.describe_rewards()})")
        self.replay.add(stream_id, obs, action, reward, next_obs, terminated, truncated, expert_action=expert_action,
                        safe_commands=safe_commands, step=step)
        self.received += 1

    def ingest(self, batch: TransitionBatch) -> int:
        """Store a validated TransitionBatch; returns the transitions added.

        Raises MessageError (SHAPE for frames of another sensor size, RANGE for rewards, depth or
        positions this task cannot produce); then nothing is stored.
        """
        batch.require_frame_shape(self.cfg.sensor.height, self.cfg.sensor.width)
        env = self.cfg.env
        batch.require_physical(env, max_depth_mm=self._max_depth_mm)
        # one chain per episode of an actor process; its steps tell the replay where a lost batch broke it
        stream = (batch.actor_id, batch.actor_epoch, batch.episode)
        last = batch.steps - 1
        labels = batch.expert_labels()
        marks = np.zeros(batch.steps, np.uint8) if batch.safe_commands is None else batch.safe_commands
        for i in range(batch.steps):
            self.add_transition(stream, batch.depth_mm[i], int(batch.action[i]), float(batch.reward[i]),
                                batch.next_depth(i), batch.terminated and i == last,
                                batch.truncated and i == last, None if labels[i] < 0 else int(labels[i]),
                                int(marks[i]), batch.first_step + i)
        record = self._record(batch.actor_id, batch.actor_epoch)
        record.received += batch.steps
        record.version = int(batch.policy_version[-1])  # its newest: a restarted learner's weights are lower
        return batch.steps

    def _record(self, actor_id: str, epoch: int) -> ActorRecord:
        record = self.actors.pop(actor_id, None)
        if record is None or record.epoch != epoch:  # a new actor, or a restarted one: a fresh allowance
            record = ActorRecord(epoch)
        record.seen_s = time.monotonic()
        self.actors[actor_id] = record  # the most recently heard last
        while len(self.actors) > MAX_TRACKED_ACTORS:
            self.actors.popitem(last=False)
        return record

    @property
    def received_by_actor(self) -> dict[str, int]:
        """Transitions received from each actor's current process."""
        return {a: r.received for a, r in self.actors.items()}

    def actor_epochs(self) -> dict[str, int]:
        return {a: r.epoch for a, r in self.actors.items()}

    def purge_out_of_bounds(self) -> int:
        """Remove stored transitions this task cannot produce (a reward it does not pay, or not
        finite): a replay memory saved by an older build may hold them. Returns how many."""
        ids, rewards = self.replay.stored_rewards()
        return self.replay.remove(ids[~self.cfg.env.pays(rewards)])

    def checkpoint_extra(self) -> dict[str, int]:
        """What a checkpoint keeps of the core beside the agent and replay (read by :func:`resume_from`)."""
        return {"transitions_received": self.received, "transitions_unpaced": self.unpaced}

    def save(self, checkpoints: CheckpointManager, config: dict[str, Any], *, with_replay: bool = True) -> Path:
        """A checkpoint of the agent, this core's counters and (``with_replay``) the replay memory.
        Diverged, nothing written, when a weight is not finite: said as the network's divergence, not as
        the file's refusal (the manager refuses any non-finite state, the optimiser's too: NonFiniteWeights)."""
        try:
            return checkpoints.save(self.agent, replay=self.replay if with_replay else None, config=config,
                                    extra=self.checkpoint_extra())
        except NonFiniteWeights:
            self.check_finite()  # a weight: said as the divergence it is, naming it
            raise

    def checkpoint(self, checkpoints: CheckpointManager, config: dict[str, Any], *, final: bool = False,
                   with_replay: bool = True) -> Path | None:
        """:meth:`save` where a write that fails (a full disk, a quota, a folder gone read-only) is said in
        one line naming the checkpoint the run resumes from instead. A periodic one (None) only logs it
        and training goes on: the next checkpoint tries again, and the files it cut short are gone (the
        run's earlier checkpoints stay whole: every file is written atomically). A ``final`` one raises
        it as a CheckpointError: the updates since the last checkpoint are lost, which a clean exit
        would hide."""
        try:
            return self.save(checkpoints, config, with_replay=with_replay)
        except OSError as exc:
            try:
                latest = checkpoints.latest()
            except CheckpointError:
                latest = None
            resumes = f"the run resumes from {latest}" if latest is not None else "the run has no checkpoint yet"
            what = f"checkpoint at update {self.updates} not written: {exc}; {resumes}"
            if final:
                raise CheckpointError(what) from None
            log.error("%s; training goes on and the next checkpoint tries again", what)
            return None

    # -- the ratio rule --------------------------------------------------------------------
    @property
    def updates(self) -> int:
        return self.agent.update_count

    def updates_due(self) -> int:
        """Updates that may run now without exceeding the replay ratio or the total."""
        t = self.cfg.train
        paced = self.received - self.unpaced
        # the memory's own size too: after a resume without it, the count alone let a batch be drawn from a few
        if paced < self._first_update_at or len(self.replay) < min(self.cfg.dqn.batch_size, self.cfg.replay.capacity):
            return 0
        allowed = math.floor(t.replay_ratio * (paced - t.warmup_transitions)) + 1
        return max(0, min(allowed, t.total_updates) - self.updates)

    def transitions_wanted(self, slack: int) -> int:
        """Transitions the learner wants to have received in all: enough for every update up
        to ``total_updates`` at the replay ratio, but no more than ``slack`` ahead of now."""
        t = self.cfg.train
        needed_for_next = max(self._first_update_at, t.warmup_transitions + math.ceil(self.updates / t.replay_ratio))
        return min(needed_for_next + slack, self.transitions_needed) + self.unpaced

    @property
    def transitions_needed(self) -> int:
        """Transitions the whole run needs: the warm-up (a batch at least), then every update at the
        replay ratio."""
        t = self.cfg.train
        return max(self._first_update_at, t.warmup_transitions + math.ceil(t.total_updates / t.replay_ratio))

    @property
    def _first_update_at(self) -> int:
        """Paced transitions before the first update: the warm-up, and a batch to draw. Both the ratio rule
        and the credit asked of the actors count from it: credit that stopped short of it (a warm-up under a
        batch, few updates) held the actors while the learner waited for them."""
        return max(self.cfg.train.warmup_transitions, self.cfg.dqn.batch_size)

    @property
    def done(self) -> bool:
        return self.updates >= self.cfg.train.total_updates

    # -- training --------------------------------------------------------------------------
    def train_step(self) -> dict[str, Any] | None:
        """Sample a batch and do one DQN update (prioritised replay priorities refreshed).

        When some samples make the loss non-finite, nothing is applied, those samples' transitions
        leave the replay memory (counted in ``dropped_nonfinite``) and None is returned; when every
        sample does, or a weight is NaN or infinite, the network itself has diverged: Diverged."""
        if self._pipeline is None:
            batch = self._sample()
            prepared = self.agent.prepare(batch, self.agent.draw_augmentation(batch))
        else:
            if not self._pipeline.pending:
                self._pipeline.submit(self._sample())
            batch, prepared = self._pipeline.take()
            self._pipeline.submit(self._sample())  # the next targets, while this update trains
        try:
            metrics = self.agent.apply(prepared)
        except NonFiniteLoss as exc:
            # weights gone non-finite make some samples' loss so (an infinite bias of one command): the
            # samples are not to blame, and removing them would empty the replay memory update by update
            self.check_finite()
            n_replay = self._replay_rows(batch)
            bad = exc.non_finite[:n_replay]
            if not bad.any() or exc.non_finite.all():
                raise Diverged(f"{exc}: every sample's loss is non-finite, the network has diverged "
                               "(the learning rate is probably too high)") from None
            removed = self.replay.remove(batch.indices[:n_replay][bad])
            self.dropped_nonfinite += removed
            log.warning("update %d skipped: %d sampled transition(s) gave a non-finite loss and were removed "
                        "from the replay memory", self.updates + 1, removed)
            if self._pipeline is not None:
                # the next batch was drawn before they left the memory: it would skip its update over
                # them again (or, all of them, call the network diverged)
                self._pipeline.take()
                self._pipeline.submit(self._sample())
            return None
        if self.cfg.replay.prioritized:  # the replay memory's own samples come first
            n_replay = self._replay_rows(batch)
            self.replay.update_priorities(batch.indices[:n_replay], metrics["td_errors"][:n_replay])
        self._window.append((metrics["loss"], metrics["q_mean"]))
        for name, window in self._agreement_windows.items():
            if name in metrics:
                window.append(metrics[name])
        self._last_metrics = metrics
        return metrics

    def check_finite(self) -> None:
        """Diverged when a weight of the online or target network is NaN or infinite (read where the
        weights are, not copied): such weights must reach neither an actor nor a checkpoint."""
        bad = non_finite_tensor({f"{side}.{name}": t for side, net in (("online", self.agent.online),
                                                                         ("target", self.agent.target))
                                 for name, t in net.state_dict().items()})
        if bad is not None:
            raise Diverged(f"update {self.updates}: weight {bad} holds NaN or infinite values, the network has "
                           "diverged (the learning rate is probably too high)")

    def _sample(self) -> Batch:
        """An update's batch: the replay memory's samples, then the demonstrations' (if any)."""
        dqn = self.cfg.dqn
        frames = self.cfg.model.frame_stack
        batch = self.replay.sample(dqn.batch_size, dqn.n_step, frames)
        if self.demo_replay is None:
            return batch
        return concat_batches(batch, self.demo_replay.sample(dqn.demo_batch, dqn.n_step, frames))

    @staticmethod
    def _replay_rows(batch: Batch) -> int:
        """How many of ``batch``'s samples (the first ones) come from the replay memory."""
        return len(batch) - (0 if batch.demo is None else int(batch.demo.sum()))

    def close(self) -> None:
        """Stop the target pipeline's thread (if any); the core can still train, unpipelined."""
        if self._pipeline is not None:
            self._pipeline.close()
            self._pipeline = None

    def recent(self, n: int = 100) -> tuple[float | None, float | None]:
        """Mean loss and mean Q over the last ``n`` updates."""
        if not self._window:
            return None, None
        items = list(self._window)[-n:]
        return float(np.mean([x[0] for x in items])), float(np.mean([x[1] for x in items]))

    def recent_label_agreement(self, n: int = 100) -> float | None:
        """Share of labelled samples (demonstrations, expert labels) whose greedy command was the
        labelled one, over the last ``n`` updates (None without labels)."""
        return self._recent_agreement("label_agreement", n)

    def recent_safe_agreement(self, n: int = 100) -> float | None:
        """Share of the safe-set marked samples whose greedy command has a way out, over the last
        ``n`` updates (None without marks)."""
        return self._recent_agreement("safe_agreement", n)

    def _recent_agreement(self, name: str, n: int) -> float | None:
        window = self._agreement_windows[name]
        return float(np.mean(list(window)[-n:])) if window else None

    def weight_lag(self) -> dict[str, int]:
        """Versions between the learner's weights and those each actor's newest transitions used."""
        return {actor: self.agent.policy_version - r.version for actor, r in self.actors.items()}


class RateMeter:
    """Events per second over a sliding window of wall time."""

    def __init__(self, window_s: float = 10.0):
        self.window_s = window_s
        self._points: collections.deque = collections.deque()

    def add(self, count: float, now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        self._points.append((now, count))

    def rate(self, now: float | None = None) -> float:
        now = time.monotonic() if now is None else now
        while self._points and now - self._points[0][0] > self.window_s:
            self._points.popleft()
        if len(self._points) < 2:
            return 0.0
        span = now - self._points[0][0]
        return sum(c for _, c in list(self._points)[1:]) / max(span, 1e-9)


def _saved_count(saved: Any, stored: int, most: int, name: str) -> int:
    """A checkpoint's count of transitions received: at least the ``stored`` ones its replay memory
    holds, at most ``most`` (what the run needs, and a batch in flight from each actor it tracks).
    A checkpoint without one, or with one outside that (hand-made, or forged past the tensors'
    digest), resumes from ``stored``: the count paces the replay ratio and the actors' credit, so a
    huge one would hold every actor for good, and refusing the weights over it would stop the run."""
    if saved is None:
        return stored
    if is_whole(saved) and stored <= saved <= max(stored, most):
        return int(saved)
    log.warning("%s: transitions_received %r is not a count between the %d stored and the %d this run can "
                "receive: taking %d", name, saved, stored, most, stored)
    return stored


def resume_from(checkpoints: CheckpointManager, core: LearnerCore) -> bool:
    """Restore the newest checkpoint that loads (agent, and replay when it was saved); False when
    there is none. CheckpointError when it does not fit ``core``: starting afresh there would train
    another network into the run's checkpoints and prune its work away."""
    checkpoint = checkpoints.load_latest()
    for reason in checkpoints.skipped:
        log.warning("skipped a checkpoint: %s", reason)
    if checkpoint is None:
        files = checkpoints.checkpoints()
        if files:  # all damaged (or diverged): starting afresh here would prune them away
            raise CheckpointError(f"cannot resume: none of the {len(files)} checkpoint(s) in {checkpoints.directory} "
                                  f"loads ({checkpoints.skipped[-1]}); move that folder away to start the run over")
        return False
    with_replay = checkpoint.replay_path is not None and checkpoint.replay_path.exists()
    if checkpoint.replay_path is not None and not with_replay:
        log.warning("%s's replay memory was not kept (only the newest checkpoints keep theirs): resuming with "
                    "an empty replay memory (a new warm-up fills it before the next update)", checkpoint.path.name)
    try:
        checkpoint.restore(core.agent)
    except CheckpointError as exc:
        raise CheckpointError(f"cannot resume: {exc}. If the run was trained with another network or optimiser, "
                              "train it with its own config (drop --preset and --set), or start it over "
                              "(up --fresh, or another --run)") from None
    if with_replay:
        try:
            checkpoint.restore_replay(core.replay)
        except CheckpointError as exc:
            raise CheckpointError(f"cannot resume: {exc}. Move that file away to resume with an empty replay "
                                  "memory") from None
    saved, unpaced = checkpoint.extra.get("transitions_received"), checkpoint.extra.get("transitions_unpaced", 0)
    # the ratio reads received - unpaced, which the count's own bounds below keep sane
    core.unpaced = int(unpaced) if is_whole(unpaced) and is_whole(saved) and 0 <= unpaced <= saved else 0
    core.received = _saved_count(saved, len(core.replay) + core.unpaced,
                                 core.transitions_needed + core.unpaced + MAX_TRACKED_ACTORS * MAX_BATCH_STEPS,
                                 checkpoint.path.name)
    purged = core.purge_out_of_bounds()
    if purged:
        log.warning("removed %d stored transition(s) this task cannot produce from %s's replay memory", purged,
                    checkpoint.path.name)
    if len(core.replay) == 0:
        # An empty replay memory warms up again: the ratio counts only what the updates so far used, so
        # the next update waits for a warm-up of new transitions (with the saved count it was due at the
        # first transition in, and sampled its whole batch from that one); received stays the run's count.
        core.unpaced = max(0, core.received - math.ceil(core.updates / core.cfg.train.replay_ratio))
    log.info("resumed from %s at update %d (%d transitions in replay)", checkpoint.path.name,
             core.updates, len(core.replay))
    return True
