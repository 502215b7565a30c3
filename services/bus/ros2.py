"""A minimal ROS 2 node on a Zenoh session: publishers and subscriptions of CDR payloads on the
keys, with the liveliness tokens and attachments, of one wire format (``shared.ros2.formats``).

The caller opens the session (after any fork, like every session of the project) and closes it
after the node::

    with open_session(settings) as session, Ros2Node(session, make_format("rmw_zenoh"), "drive") as node:
        cmd_vel = node.publisher(qualify(node.namespace, "cmd_vel"), TWIST)
        node.subscriber(qualify(node.namespace, "camera/depth/image_raw"), IMAGE, on_image, qos="sensor_data")
        cmd_vel.put(encode_twist(0.2, 0.0))

It lives on the bus, not in ``shared/``, because it talks to Zenoh.
"""

from __future__ import annotations

import argparse
import itertools
import logging
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Self

import zenoh

from services.bus.session import ZenohSettings, cli_overrides
from shared.ros2.formats import (
    NodeInfo,
    PublisherInfo,
    QosProfile,
    Ros2Format,
    check_node_name,
    normalize_namespace,
    qos_profile,
    qualify,
)

log = logging.getLogger(__name__)

# rmw_zenoh numbers nodes and entities from one counter per context; one per process keeps
# them unique within every session of the process as well.
_ENTITY_IDS = itertools.count()
_ENTITY_IDS_LOCK = threading.Lock()


def _next_entity_id() -> int:
    with _ENTITY_IDS_LOCK:
        return next(_ENTITY_IDS)


def _undeclare(entity: object, what: str) -> None:
    try:
        entity.undeclare()  # type: ignore[attr-defined]
    except zenoh.ZError as exc:  # the session may already be closed: nothing left to undeclare
        log.debug("undeclaring %s: %s", what, exc)


class _Entity:
    """A publisher or subscription: its Zenoh handle and its liveliness token, closed together."""

    kind = "entity"
    key: str
    token_key: str | None

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._closed = False
        self._token: zenoh.LivelinessToken | None = None

    def _announce(self, session: zenoh.Session) -> None:
        """Declare the liveliness token, once the Zenoh handle exists."""
        self._token = session.liveliness().declare_token(self.token_key) if self.token_key else None

    def close(self) -> None:
        """Undeclare the token and the Zenoh handle (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._token is not None:
            _undeclare(self._token, f"token {self.token_key}")
        _undeclare(self._handle, f"{self.kind} {self.key}")


class Ros2Publisher(_Entity):
    """Publishes CDR payloads on one topic; thread-safe."""

    kind = "publisher"

    def __init__(self, session: zenoh.Session, fmt: Ros2Format, info: PublisherInfo) -> None:
        super().__init__()
        self.info = info
        self.key = fmt.data_key(info.topic, info.msgtype)
        """The Zenoh key samples go to."""
        self.token_key = fmt.publisher_token(info.node, info.topic, info.msgtype, info.qos, entity_id=info.entity_id)
        """The liveliness token announcing this publisher (None when the format has none)."""
        self._format = fmt
        # Reliable topics (commands) block rather than drop on a full queue, so that a stop is
        # never lost locally; rmw_zenoh itself blocks only for keep_all (rmw_publisher_data.cpp).
        # Sensor data is best effort and drops: a stale image is worth nothing.
        reliable = info.qos.reliable
        self._handle = session.declare_publisher(
            self.key,
            congestion_control=zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP,
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT)
        self._announce(session)
        self._sequence_number = 0

    @property
    def sequence_number(self) -> int:
        """The sequence number of the last sample put (0 before the first)."""
        with self._lock:
            return self._sequence_number

    def put(self, payload: bytes) -> None:
        """Publish one CDR payload, with the format's attachment (sequence number from 1, the
        time now in ns)."""
        with self._lock:
            if self._closed:
                raise RuntimeError(f"publisher on {self.key} is closed")
            self._sequence_number += 1
            attachment = self._format.attachment(self.info, self._sequence_number, time.time_ns())
            self._handle.put(payload, attachment=attachment)


class Ros2Subscriber(_Entity):
    """Hands the CDR payloads of one topic to a callback, on a thread of its own, the newest
    ``depth`` of them at most.

    Zenoh hands a Python callback every sample, in order, through a queue of its own that, once
    full, blocks the session's receiving thread: a callback slower than its topic (a flood of
    commands from anyone on the router) acted on ever older samples and held up every other key of
    the session. Here, as rmw_zenoh does for keep_last, the QoS depth bounds the samples waiting for
    the callback: a new one pushes out the oldest, which is dropped and counted (``dropped``); for a
    robot's commands and images the newest is what matters.
    """

    kind = "subscriber"

    def __init__(self, session: zenoh.Session, fmt: Ros2Format, node: NodeInfo, entity_id: int, topic: str,
                 msgtype: str, callback: Callable[[bytes], None], qos: QosProfile, max_bytes: int | None = None,
                 on_oversize: Callable[[int], None] | None = None) -> None:
        super().__init__()
        self.max_bytes = max_bytes
        """Larger payloads are never copied out of Zenoh: ``on_oversize(size)`` is called instead."""
        self._on_oversize = on_oversize
        self.topic = topic
        self.msgtype = msgtype
        self.key = fmt.subscriber_key(topic, msgtype)
        """The Zenoh key subscribed to."""
        self.token_key = fmt.subscriber_token(node, topic, msgtype, qos, entity_id=entity_id)
        """The liveliness token announcing this subscription (None when the format has none)."""
        self._callback = callback
        self._received = 0
        self._dropped = 0
        self._callback_errors = 0
        # keep_all is bounded too (by its depth): an unbounded queue is what a flood grows
        self.depth = max(1, qos.depth)
        """At most this many samples wait for the callback."""
        self._waiting: deque[zenoh.ZBytes] = deque(maxlen=self.depth)
        self._waiting_ready = threading.Condition(self._lock)
        self._handle = session.declare_subscriber(self.key, self._on_sample)
        self._announce(session)
        threading.Thread(target=self._deliver, name=f"ros2 {topic}", daemon=True).start()

    def _on_sample(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: the sample waits for the callback, pushing out the oldest when ``depth``
        wait already (never copied here)."""
        with self._lock:
            if self._closed:
                return
            self._received += 1
            full = len(self._waiting) == self.depth
            self._dropped += full
            first_drop = full and self._dropped == 1
            self._waiting.append(sample.payload)
            self._waiting_ready.notify()
        if first_drop:
            log.warning("%s: samples come faster than its callback takes them; beyond the %d newest they are "
                        "dropped (counted in dropped, not logged)", self.topic, self.depth)

    def _deliver(self) -> None:
        while True:
            with self._lock:
                while not self._waiting and not self._closed:
                    self._waiting_ready.wait()
                if self._closed:
                    return
                payload = self._waiting.popleft()
            try:
                size = len(payload)
                if self.max_bytes is not None and size > self.max_bytes:
                    if self._on_oversize is not None:
                        self._on_oversize(size)
                    continue
                self._callback(payload.to_bytes())
            except Exception:
                # The next sample is delivered all the same: log the first failure, count them all.
                with self._lock:
                    self._callback_errors += 1
                    first = self._callback_errors == 1
                if first:
                    log.exception("callback for %s failed (later failures are counted, not logged)", self.topic)

    def close(self) -> None:
        """Undeclare the subscription and end its delivery thread (a callback under way finishes)."""
        super().close()
        with self._lock:
            self._waiting.clear()
            self._waiting_ready.notify()

    @property
    def received(self) -> int:
        """Samples received so far."""
        with self._lock:
            return self._received

    @property
    def dropped(self) -> int:
        """Samples pushed out by newer ones before the callback took them."""
        with self._lock:
            return self._dropped

    @property
    def callback_errors(self) -> int:
        """Samples whose callback raised."""
        with self._lock:
            return self._callback_errors


class Ros2Node:
    """A ROS 2 node named ``name`` in ``namespace`` on ``session``, speaking ``fmt``.

    Declares the node's liveliness token when the format has one; :meth:`close` (or leaving the
    ``with`` block) undeclares every token, publisher and subscriber; the session stays open.
    Topics are given fully qualified or relative to the node's namespace.
    """

    def __init__(self, session: zenoh.Session, fmt: Ros2Format, name: str, namespace: str = "/") -> None:
        self.format = fmt
        self.info = NodeInfo(name=check_node_name(name), namespace=normalize_namespace(namespace),
                             zid=str(session.zid()), node_id=_next_entity_id())
        self._session = session
        self._lock = threading.Lock()
        self._entities: list[Ros2Publisher | Ros2Subscriber] = []
        self.token_key = fmt.node_token(self.info)
        """The node's liveliness token (None when the format has none)."""
        self._token = session.liveliness().declare_token(self.token_key) if self.token_key else None
        self._closed = False

    @property
    def name(self) -> str:
        return self.info.name

    @property
    def namespace(self) -> str:
        return self.info.namespace

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"ROS 2 node {self.name} is closed")

    def _add(self, entity: Ros2Publisher | Ros2Subscriber) -> None:
        with self._lock:
            closed = self._closed
            if not closed:
                self._entities.append(entity)
        if closed:  # closed by another thread while the entity was being declared
            entity.close()
            self._check_open()

    def publisher(self, topic: str, msgtype: str, *, qos: str | QosProfile = "default") -> Ros2Publisher:
        """A publisher of ``msgtype`` payloads on ``topic``; ``qos`` 'default' (reliable, keep_last
        10) or 'sensor_data' (best effort, keep_last 5), or a QosProfile."""
        self._check_open()
        info = PublisherInfo(node=self.info, entity_id=_next_entity_id(), topic=qualify(self.namespace, topic),
                             msgtype=msgtype, qos=qos_profile(qos), gid=os.urandom(16))
        publisher = Ros2Publisher(self._session, self.format, info)
        self._add(publisher)
        return publisher

    def subscriber(self, topic: str, msgtype: str, callback: Callable[[bytes], None], *,
                   qos: str | QosProfile = "default", max_bytes: int | None = None,
                   on_oversize: Callable[[int], None] | None = None) -> Ros2Subscriber:
        """Call ``callback(payload)`` on the subscriber's own thread for each sample of ``topic``
        (at most the QoS depth of them wait while it runs: a newer one drops the oldest, counted in
        ``dropped``); an exception it raises is logged once and counted (``callback_errors``), never
        propagated. A payload over ``max_bytes`` is not copied out of Zenoh (a 400 MB one would
        double the memory it takes): ``on_oversize(its size)`` is called in place of ``callback``."""
        self._check_open()
        subscriber = Ros2Subscriber(self._session, self.format, self.info, _next_entity_id(),
                                    qualify(self.namespace, topic), msgtype, callback, qos_profile(qos),
                                    max_bytes=max_bytes, on_oversize=on_oversize)
        self._add(subscriber)
        return subscriber

    def close(self) -> None:
        """Undeclare every subscriber, publisher and token of the node (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            entities, self._entities = self._entities, []
        for entity in reversed(entities):
            entity.close()
        if self._token is not None:
            _undeclare(self._token, f"token {self.token_key}")

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def ros2_settings(args: argparse.Namespace) -> ZenohSettings:
    """``--connect`` / ``--zenoh-config`` of ``drive``, ``sim-robot`` and ``bench drive``: a client of the robot's router (rmw_zenohd, the bridge, or a plain zenohd)."""
    return ZenohSettings.from_env(mode="client", overrides=cli_overrides(args))
