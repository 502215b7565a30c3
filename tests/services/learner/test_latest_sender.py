"""The learner's weights sender on a real Zenoh session: the newest offer goes out, and with nothing
new the latest goes out again, so a live learner never falls quiet for its receivers."""

from __future__ import annotations

import threading
import time

from services.bus.session import ZenohSettings, free_tcp_port, open_router, open_session
from services.learner.service import LatestSender


def test_the_latest_weights_are_put_again_while_nothing_new_comes():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    heard: list[tuple[float, bytes]] = []
    lock = threading.Lock()

    def on_sample(sample) -> None:
        with lock:
            heard.append((time.monotonic(), sample.payload.to_bytes()))

    with open_router([endpoint]), open_session(ZenohSettings(connect=(endpoint,))) as session:
        subscriber = session.declare_subscriber("test/weights", on_sample)  # noqa: F841
        sender = LatestSender(session.declare_publisher("test/weights"), repeat_s=0.2)
        try:
            time.sleep(0.5)  # nothing offered yet: nothing is put
            assert heard == []
            sender.offer(b"v1")
            time.sleep(1.0)
            sender.offer(b"v2")
            time.sleep(0.5)
        finally:
            sender.close()
    with lock:
        payloads = [p for _, p in heard]
        times = [t for t, _ in heard]
    first_v2 = payloads.index(b"v2")
    assert set(payloads[:first_v2]) == {b"v1"} and first_v2 >= 3  # v1, then repeats (about five in its 1 s)
    assert set(payloads[first_v2:]) == {b"v2"} and len(payloads) - first_v2 >= 2
    assert max(b - a for a, b in zip(times, times[1:])) < 1.0  # never quiet for long (0.2 s here)
