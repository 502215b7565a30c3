"""Ros2Node on loopback through a real Zenoh router, in both wire formats: a Twist from one
session's node reaches another's; rmw_zenoh's tokens are visible and its attachment decodes."""

from __future__ import annotations

import threading
import time

import pytest
import zenoh
from service_processes import client

from services.bus.ros2 import Ros2Node
from shared.ros2.formats import decode_attachment, make_format
from shared.ros2.messages import IMAGE, TWIST, decode_twist, encode_twist


def live_tokens(session: zenoh.Session) -> set[str]:
    return {str(reply.ok.key_expr) for reply in session.liveliness().get("@ros2_lv/**", timeout=2.0)
            if reply.ok is not None}


def put_until(publisher, payload: bytes, received: threading.Event, timeout_s: float = 30.0) -> None:  # type: ignore[no-untyped-def]
    # Declarations take a moment to cross the loopback_router: repeat until the subscriber has one.
    deadline = time.monotonic() + timeout_s
    while not received.is_set() and time.monotonic() < deadline:
        publisher.put(payload)
        received.wait(0.05)
    assert received.is_set(), f"nothing arrived on {publisher.key}"


@pytest.mark.parametrize("fmt_name", ["rmw_zenoh", "ros2dds"])
def test_a_twist_crosses_the_router(loopback_router: str, fmt_name: str) -> None:
    fmt = make_format(fmt_name, domain_id=5)
    twists: list[tuple[float, float]] = []
    attachments: list[bytes | None] = []
    received, raw_received = threading.Event(), threading.Event()

    def on_twist(payload: bytes) -> None:
        twists.append(decode_twist(payload))
        received.set()

    def on_raw(sample: zenoh.Sample) -> None:
        attachments.append(sample.attachment.to_bytes() if sample.attachment is not None else None)
        raw_received.set()

    with client(loopback_router) as robot_session, client(loopback_router) as drive_session:
        with Ros2Node(robot_session, fmt, "robot", namespace="/bot1") as robot, \
                Ros2Node(drive_session, fmt, "drive", namespace="/bot1") as drive:
            subscriber = robot.subscriber("cmd_vel", TWIST, on_twist)
            raw = robot_session.declare_subscriber(subscriber.key, on_raw)
            publisher = drive.publisher("cmd_vel", TWIST)
            assert publisher.key == subscriber.key
            put_until(publisher, encode_twist(0.2, -0.4), received)
            assert raw_received.wait(30.0)
            assert twists[0] == (0.2, -0.4)

            if fmt_name == "ros2dds":
                assert subscriber.key == "bot1/cmd_vel" and attachments[-1] is None
                assert drive.token_key is None and publisher.token_key is None
            else:
                assert subscriber.key.startswith("5/bot1/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_")
                sequence_number, timestamp_ns, gid = decode_attachment(attachments[-1])
                assert 1 <= sequence_number <= publisher.sequence_number
                assert gid == publisher.info.gid and abs(time.time_ns() - timestamp_ns) < 10**10
                tokens = live_tokens(drive_session)
                assert {robot.token_key, drive.token_key, publisher.token_key, subscriber.token_key} <= tokens
                assert publisher.token_key.startswith(
                    f"@ros2_lv/5/{drive_session.zid()}/{drive.info.node_id}/{publisher.info.entity_id}/MP/%/%bot1/drive/"
                    "%bot1%cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_")
            raw.undeclare()

        if fmt_name == "rmw_zenoh":  # closing the nodes withdrew every token
            deadline = time.monotonic() + 30.0
            while live_tokens(drive_session) and time.monotonic() < deadline:
                time.sleep(0.05)
            assert not live_tokens(drive_session)


def test_sequence_numbers_increase_and_sensor_data_is_best_effort(loopback_router: str) -> None:
    fmt = make_format("rmw_zenoh")
    attachments: list[bytes] = []
    got_three = threading.Event()

    def on_raw(sample: zenoh.Sample) -> None:
        attachments.append(sample.attachment.to_bytes())
        if len(attachments) >= 3:
            got_three.set()

    with client(loopback_router) as a, client(loopback_router) as b, Ros2Node(a, fmt, "camera") as camera:
        publisher = camera.publisher("camera/depth/image_raw", IMAGE, qos="sensor_data")
        assert publisher.token_key.endswith("/2::,5:,:,:,,")
        raw = b.declare_subscriber(publisher.key, on_raw)
        first = threading.Event()
        b2 = b.declare_subscriber(publisher.key, lambda _sample: first.set())
        put_until(publisher, b"\x00\x01\x00\x00", first)
        publisher.put(b"\x00\x01\x00\x00")
        publisher.put(b"\x00\x01\x00\x00")
        assert got_three.wait(5.0)
        numbers = [decode_attachment(x)[0] for x in attachments]
        assert numbers == sorted(numbers) and numbers[-1] == publisher.sequence_number
        raw.undeclare()
        b2.undeclare()


def test_a_failing_callback_is_counted_and_the_subscription_goes_on(loopback_router: str, caplog) -> None:  # type: ignore[no-untyped-def]
    fmt = make_format("ros2dds")
    calls: list[bytes] = []
    second = threading.Event()

    def explode(payload: bytes) -> None:
        calls.append(payload)
        if len(calls) >= 2:
            second.set()
        raise ValueError("bad callback")

    with client(loopback_router) as a, client(loopback_router) as b, Ros2Node(a, fmt, "robot") as robot, Ros2Node(b, fmt, "drive") as drive:
        subscriber = robot.subscriber("/cmd_vel", TWIST, explode)
        publisher = drive.publisher("/cmd_vel", TWIST)
        put_until(publisher, encode_twist(0.0, 0.0), second)
        assert subscriber.callback_errors >= 2 and subscriber.received >= 2
        assert sum("bad callback" in r.getMessage() or (r.exc_info and "bad callback" in str(r.exc_info[1]))
                   for r in caplog.records) == 1, "logged once, then counted"
    with pytest.raises(RuntimeError, match="closed"):
        robot.publisher("/cmd_vel", TWIST)
