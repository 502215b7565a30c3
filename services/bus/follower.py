"""The newest weights of a run, followed without ever blocking the caller's loop.

In the spirit of Acme's ``VariableClient``: the actors and the evaluator each hold one
:class:`WeightFollower`. Zenoh threads ``offer`` every ``WeightsMessage`` from the learner's stream
(and the reply to the latest-weights query); the follower keeps only the newest that fits the
receiver's architecture, so a slow receiver skips versions instead of queueing them. Versions are
(learner epoch, update), and one learner process is followed at a time
(:class:`shared.wire.messages.LearnerEpochs`): a restarted learner's weights replace the dead one's
once the dead one has been quiet for ``WEIGHTS_QUIET_S``, a message of another epoch among the live
learner's is ignored, and an epoch from the future is refused. The learner's flow control (every
0.1 s) also says it is alive, so it is never quiet between two weights while it runs. The
receiver's own loop ``take``\\s it when it is ready and ``load``\\s it into its network; a message
that does not fit (another fingerprint, or tensors that do not load despite it) is counted by
cause in ``rejects`` and dropped, never raised.

    follower = WeightFollower(fingerprint, rejects)
    with open_session(settings) as session, follower.following(session, keys):
        ...                                  # the stream, and the query on its own thread
        message = follower.take()            # None until something newer arrives
        if message is not None and follower.load(net, message):
            policy_version = message.policy_version
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import zenoh

from services.bus.session import query_replies, subscribe_messages
from shared.learning.model import ModelError
from shared.learning.weights import load_message
from shared.wire.keys import RunKeys
from shared.wire.messages import (
    OVERSIZE,
    RANGE,
    SHAPE,
    FlowControl,
    LearnerEpochs,
    MessageError,
    RejectCounter,
    WeightsMessage,
    epoch_from_the_future,
    future_epoch_error,
)

log = logging.getLogger("cogexplore.weights")

WEIGHTS_ENVELOPE_BYTES = 2**20
"""Room for a weights message's names, shapes and fields beside its tensor bytes."""
WEIGHTS_QUIET_S = 5.0
"""How long the followed learner must have sent neither weights nor flow control before another
learner's weights are taken (its message is kept meanwhile: a restarted learner sends its start-up
weights once). A live learner puts flow control every 0.1 s, through its warm-up and between two
weights of a slow preset, so only a learner whose loop stalls this long (or a dead one) can be
replaced."""
PULSE_SLACK_UPDATES = 100
"""How far weights may be numbered ahead of the followed learner's last flow control (sent at
every update: its weights of update v can overtake its flow control of v)."""


class WeightFollower:
    """Holds the newest fitting weights offered since the last ``take`` (thread-safe).

    ``shapes`` (the receiving network's parameter names and shapes) also checks what a message
    carries against what its fingerprint claims, on arrival: a tensor the wrong way round is counted
    then, not only if it happens to be the newest when the receiver takes one."""

    def __init__(self, fingerprint: str, rejects: RejectCounter, shapes: dict[str, tuple[int, ...]] | None = None,
                 quiet_s: float = WEIGHTS_QUIET_S, clock: Callable[[], float] = time.monotonic):
        self.fingerprint = fingerprint
        self.rejects = rejects
        self.shapes = shapes
        # weights of this network in float32, with room for the envelope: anything longer is not for it
        self.max_bytes = (None if shapes is None else
                          4 * sum(int(np.prod(s)) for s in shapes.values()) + WEIGHTS_ENVELOPE_BYTES)
        self._arrived = threading.Condition()
        self._epochs = LearnerEpochs(quiet_s, clock)
        self._waiting: tuple[WeightsMessage, float] | None = None  # another learner's newest, and its arrival
        self._newest: WeightsMessage | None = None
        self._taken_version: tuple[int, int] = (-1, -1)
        self._pulse: tuple[int, int] | None = None
        """(epoch, updates + PULSE_SLACK_UPDATES) of the followed learner's last flow control: the
        highest version its weights can have."""
        self._queries: list[threading.Thread] = []

    # -- Zenoh threads -------------------------------------------------------------------------

    def offer(self, message: WeightsMessage, key: str = "") -> None:
        """Park ``message`` if it fits this network and is newer than any parked or taken."""
        try:
            message.check_fingerprint(self.fingerprint)
        except MessageError as exc:
            self.rejects.reject(MessageError(exc.cause, f"{exc.detail} (is the learner running another model config?)"),
                                key or None)
            return
        if self.shapes is not None and message.named_shapes() != self.shapes:
            wrong = sorted(k for k in set(self.shapes) | set(message.tensors)
                           if self.shapes.get(k) != message.named_shapes().get(k))
            self.rejects.reject(MessageError(SHAPE, f"weights v{message.policy_version}: tensors {wrong[:3]} do not "
                                                    "have the shapes their fingerprint claims"), key or None)
            return
        with self._arrived:
            verdict = self._epochs.admit(message.learner_epoch)
            ahead = (verdict == LearnerEpochs.SAME and self._pulse is not None
                     and self._pulse[0] == message.learner_epoch and message.version > self._pulse)
            newest = self._newest.version if self._newest is not None else self._taken_version
            if ahead:
                pass  # not its learner's: counted below, outside the lock
            elif verdict == LearnerEpochs.NEW or (verdict == LearnerEpochs.SAME and message.version > newest):
                self._newest = message
                self._waiting = None if verdict == LearnerEpochs.NEW else self._waiting
                self._arrived.notify_all()
            elif verdict == LearnerEpochs.OTHER:
                self._waiting = (message, self._epochs.clock())
        if verdict == LearnerEpochs.FUTURE:
            self.rejects.reject(future_epoch_error(f"weights v{message.policy_version}"), key or None)
        elif ahead:
            self._reject_ahead(message, self._pulse[1] - PULSE_SLACK_UPDATES, key)

    def on_flow(self, message: FlowControl, key: str = "") -> None:
        """The learner's flow control, its pulse: the followed learner is alive, at ``updates``.

        Weights numbered more than :data:`PULSE_SLACK_UPDATES` ahead of it did not come from it (a
        learner's version is its update count): they are refused on arrival from then on, one
        parked before is dropped, both counted, and one taken before the first pulse no longer
        holds the learner's real weights off as "older" (one forged message numbered 2^40 - 1 did,
        for the rest of the learner's life)."""
        if epoch_from_the_future(message.learner_epoch):  # not a late word of a dead learner: an impossible one
            self.rejects.reject(future_epoch_error("flow control"), key or None)
            return
        forged = None
        with self._arrived:
            self._epochs.heard(message.learner_epoch)
            if message.learner_epoch != self._epochs.followed:
                return
            ahead = self._pulse = (message.learner_epoch, message.updates + PULSE_SLACK_UPDATES)
            if self._newest is not None and self._newest.version > ahead:
                forged, self._newest = self._newest, None
            if self._taken_version > ahead:
                self._taken_version = (message.learner_epoch, message.updates)
        if forged is not None:
            self._reject_ahead(forged, message.updates, key)

    def _reject_ahead(self, message: WeightsMessage, learner_updates: int, key: str) -> None:
        self.rejects.reject(MessageError(RANGE, f"weights v{message.policy_version} are ahead of their learner, "
                                                f"at update {learner_updates}"), key or None)

    def subscribe(self, session: Any, keys: RunKeys, query_timeout_s: float = 5.0,
                  on_flow: Callable[[FlowControl, str], None] | None = None) -> list[Any]:
        """Follow the run's weights stream and the learner's flow control (its pulse), then ask the
        learner for its newest weights on a thread of its own (:meth:`fetch_latest`); returns the
        subscribers (undeclared with the session). ``on_flow`` also gets each flow message (an
        actor's credit gate: one subscription, each bad message counted once)."""

        def flow(message: FlowControl, key: str) -> None:
            self.on_flow(message, key)
            if on_flow is not None:
                on_flow(message, key)

        subscribers = [subscribe_messages(session, keys.weights, WeightsMessage, self.offer, self.rejects,
                                          max_bytes=self.max_bytes),
                       subscribe_messages(session, keys.flow, FlowControl, flow, self.rejects)]
        self.fetch_latest(session, keys, query_timeout_s, background=True)
        return subscribers

    def fetch_latest(self, session: Any, keys: RunKeys, timeout_s: float = 5.0, *, background: bool = False) -> None:
        """Query the learner's latest-weights queryable and offer every reply (each judged as the
        stream's messages are; none: the stream will bring weights); ``background``: on a daemon
        thread, so the caller never waits on it."""
        if background:
            query = threading.Thread(target=self.fetch_latest, args=(session, keys, timeout_s), name="weights-query",
                                     daemon=True)
            with self._arrived:
                self._queries = [q for q in self._queries if q.is_alive()] + [query]
            query.start()
            return

        def oversize(size: int) -> None:
            self.rejects.reject(MessageError(OVERSIZE, f"a {size}-byte answer, more than this network's weights"),
                                keys.weights_latest)

        answers = 0
        try:  # every reply, each judged as a message of the stream is (epoch, version): not the first on trust
            for payload in query_replies(session, keys.weights_latest, self.max_bytes or WeightsMessage.MAX_BYTES,
                                         timeout_s=timeout_s, oversize=oversize):
                answers += 1
                message = self.rejects.decode(payload, WeightsMessage, source=keys.weights_latest)
                if message is not None:
                    self.offer(message, keys.weights_latest)
        except zenoh.ZError as exc:  # the session closed first: the receiver is stopping
            log.debug("no query for the latest weights: %s", exc)
            return
        if not answers:
            log.info("no answer from %s yet: waiting for the weights stream", keys.weights_latest)

    @contextmanager
    def following(self, session: Any, keys: RunKeys, query_timeout_s: float = 5.0,
                  on_flow: Callable[[FlowControl, str], None] | None = None) -> Iterator[list[Any]]:
        """``subscribe`` for the length of a ``with`` block, inside the session's own ``with``; leaving
        it closes the session, which ends the queries at once, and waits for their threads.

        Both guard the process's end. ``zenoh.Session.__exit__`` needs the session to itself and
        raises "Already borrowed", leaving it open, if a query thread is inside ``get`` just then;
        ``close()`` does not. And a query thread left running may free the session while the
        interpreter shuts down: before Python 3.14 that thread is ended with pthread_exit inside
        Zenoh's Rust code, which aborts the process ("FATAL: exception not rethrown", status -6)
        instead of letting it exit with its own status."""
        subscribers = self.subscribe(session, keys, query_timeout_s, on_flow)
        try:
            yield subscribers
        finally:
            session.close()
            with self._arrived:
                queries, self._queries = self._queries, []
            for query in queries:
                query.join(timeout=query_timeout_s + 5.0)

    # -- the receiver's loop ---------------------------------------------------------------------

    def take(self, timeout_s: float = 0.0) -> WeightsMessage | None:
        """The newest parked message, waiting up to ``timeout_s`` for one; None when nothing newer
        than the last one taken has arrived."""
        with self._arrived:
            if timeout_s > 0:
                self._arrived.wait_for(lambda: self._newest is not None or self._follow_waiting(), timeout_s)
            else:
                self._follow_waiting()
            message, self._newest = self._newest, None
            if message is not None:
                self._taken_version = message.version
            return message

    def _follow_waiting(self) -> bool:
        """Park the message another learner sent while the followed one spoke, once that one has
        been quiet for ``quiet_s``: a restarted learner publishes its weights once at start-up, maybe
        within ``quiet_s`` of the dead one's last, then not again until it trains. Kept for twice
        ``quiet_s``, no longer. Under ``_arrived``; True when it parked one."""
        if self._waiting is None:
            return False
        message, arrived_s = self._waiting
        if self._epochs.clock() - arrived_s > 2 * self._epochs.quiet_s:
            self._waiting = None
            return False
        if not self._epochs.quiet():
            return False
        self._waiting = None
        self._epochs.follow(message.learner_epoch)
        self._newest = message
        return True

    def load(self, net: Any, message: WeightsMessage) -> bool:
        """Load ``message`` into ``net``; False (counted as a reject, ``net`` untouched) when its
        tensors do not fit despite the fingerprint."""
        try:
            load_message(net, message)
        except MessageError as exc:
            self.rejects.reject(exc, f"weights v{message.policy_version}")
            return False
        except ModelError as exc:
            self.rejects.reject(MessageError(SHAPE, str(exc)), f"weights v{message.policy_version}")
            return False
        return True
