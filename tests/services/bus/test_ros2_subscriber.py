"""Ros2Subscriber under a flood, through a real Zenoh router on loopback: a slow callback gets the
newest samples (its QoS depth), the older ones it had no time for are dropped and counted, and the
session's other keys are not held up behind them."""

from __future__ import annotations

import threading
import time

from service_processes import client, wait_for

from services.bus.ros2 import Ros2Node
from shared.ros2.formats import make_format
from shared.ros2.messages import TWIST, decode_twist, encode_twist

FLOOD = 400
"""More than Zenoh's own queue for a Python callback (256), which then blocked the session."""


def test_a_flood_reaches_a_busy_callback_as_its_newest_samples_and_holds_up_nothing(loopback_router: str) -> None:
    fmt = make_format("rmw_zenoh")
    calls: list[tuple[float, float]] = []
    busy, release, newest_taken, reset = threading.Event(), threading.Event(), threading.Event(), threading.Event()

    def on_twist(payload: bytes) -> None:  # a callback busy with its first command while the flood comes
        calls.append(decode_twist(payload))
        busy.set()
        if calls[-1] == (0.0, -0.3):
            newest_taken.set()
        release.wait(10.0)

    with client(loopback_router) as robot_session, client(loopback_router) as outsider_session, \
            Ros2Node(robot_session, fmt, "robot") as robot, Ros2Node(outsider_session, fmt, "outsider") as outsider:
        subscriber = robot.subscriber("/cmd_vel", TWIST, on_twist)
        # the same samples as the subscription, seen while its callback is busy
        arrived: list[tuple[float, float]] = []
        watcher = robot_session.declare_subscriber(subscriber.key,
                                                   lambda sample: arrived.append(decode_twist(sample.payload.to_bytes())))
        reset_sub = robot_session.declare_subscriber("robot/reset", lambda _sample: reset.set())
        publisher = outsider.publisher("/cmd_vel", TWIST)
        try:
            deadline = time.monotonic() + 30.0
            while not busy.is_set() and time.monotonic() < deadline:  # until the subscription is matched
                publisher.put(encode_twist(0.0, 0.0))
                busy.wait(0.05)
            assert busy.is_set(), "no twist arrived"
            # the last of those in flight (a fixed wait counted too early on a loaded machine): none once a
            # marker sent after them has arrived (one key, in order) and been counted
            publisher.put(encode_twist(0.0, 0.1))
            wait_for(lambda: (0.0, 0.1) in arrived and subscriber.received == len(arrived), 10, "the marker", [])
            sent = subscriber.received + FLOOD + 1
            for _ in range(FLOOD):
                publisher.put(encode_twist(0.0, 0.3))
            publisher.put(encode_twist(0.0, -0.3))
            outsider_session.put("robot/reset", b"")
            assert reset.wait(2.0), "the flood held up the session's other keys"
            deadline = time.monotonic() + 2.0
            while subscriber.received < sent and time.monotonic() < deadline:
                time.sleep(0.01)
            assert subscriber.received == sent
            release.set()
            assert newest_taken.wait(2.0), "the newest twist never reached the callback"
            # the first, then the QoS depth (10) of the newest: the rest never reached the callback
            assert calls == [(0.0, 0.0)] + [(0.0, 0.3)] * 9 + [(0.0, -0.3)]
            assert subscriber.depth == 10 and subscriber.dropped == sent - len(calls)
        finally:
            release.set()
            reset_sub.undeclare()
            watcher.undeclare()
