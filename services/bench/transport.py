"""``cogexplore bench transport``: transition throughput through a loopback Zenoh router.

Three figures for one realistic TransitionBatch (default 16 steps of 160x120 depth):

- ``codec``: encode + validated decode in one process, no network: the ceiling.
- ``loopback``: a real router (in this process) and a publisher session and a subscriber
  session, each in its own process started with the ``spawn`` method (``processes=True``,
  the default), or as two sessions on threads of this process (``processes=False``, where
  the GIL is shared). The publisher puts with CongestionControl.BLOCK as the actors do; the
  subscriber decodes and validates every batch as the learner does. Every batch sent must
  arrive (``lost`` is reported), unless Zenoh closed a link meanwhile (``links_closed``): it
  does so when a BLOCK message waits past its ``wait_before_close`` (5 s), i.e. when the
  subscriber or the router stalled that long (``max_gap_s``, ``max_put_s`` show it).
- ``bytes_per_transition``: wire bytes of one batch / its transitions.
"""

from __future__ import annotations

import argparse
import multiprocessing
import queue
import threading
import time
from typing import Any

import numpy as np

from services.bench import interrupt_on_stop_signals, print_json
from services.bus.session import (
    LinkWatch,
    ZenohSettings,
    declare_reliable_publisher,
    free_tcp_port,
    open_router,
    open_session,
    subscribe_messages,
)
from shared.config import ConfigError
from shared.errors import CogexploreError
from shared.wire.keys import RunKeys
from shared.wire.messages import MAX_BATCH_STEPS, MAX_FRAME_PIXELS, RejectCounter, TransitionBatch

_RUN = "bench-transport"
_ACTOR = "bench-actor"
_REPORT_SLACK_S = 120.0
"""How long past the measurement a side may take to start, finish and report."""


class TransportBenchError(CogexploreError, RuntimeError):
    """The publisher or the subscriber did not report in time (it died, or the router failed)."""


def _report(results: Any, timeout_s: float, what: str) -> Any:
    try:
        return results.get(timeout=timeout_s)
    except queue.Empty:
        raise TransportBenchError(f"no word from the {what} in {timeout_s:.0f} s: it died or hangs") from None


def make_batch(steps: int = 16, height: int = 120, width: int = 160, seed: int = 0) -> TransitionBatch:
    """A mid-episode batch with plausible depth (0.3-4 m, some no-returns)."""
    rng = np.random.default_rng(seed)
    depth = rng.integers(300, 4000, size=(steps + 1, height, width), dtype=np.uint16)
    depth[rng.random(depth.shape) < 0.05] = 0
    return TransitionBatch(
        actor_id=_ACTOR, episode=1, first_step=0, start_index=0, actor_epoch=0,
        depth_mm=depth[:steps], next_depth_mm=depth[steps],
        action=rng.integers(0, 5, steps).astype(np.uint8),
        reward=np.ones(steps, dtype=np.float32),
        policy_version=np.full(steps, 7, dtype=np.int64),
        pose=rng.normal(size=(steps, 3)).astype(np.float32))


def _codec(batch: TransitionBatch, seconds: float) -> dict[str, float]:
    encode_s = decode_s = 0.0
    n = 0
    nbytes = 0
    start = time.perf_counter()
    while time.perf_counter() - start < seconds or n == 0:
        t0 = time.perf_counter()
        data = batch.encode()
        t1 = time.perf_counter()
        TransitionBatch.decode(data)
        t2 = time.perf_counter()
        encode_s += t1 - t0
        decode_s += t2 - t1
        n += 1
        nbytes += len(data)
    busy = encode_s + decode_s
    return {"transitions_per_s": n * batch.steps / busy, "mb_per_s": nbytes / busy / 1e6,
            "encode_ms": encode_s / n * 1e3, "decode_ms": decode_s / n * 1e3, "batches": n}


def _subscriber(endpoint: str, seconds: float, ready: Any, control: Any, results: Any) -> None:
    """Count and validate every batch; report when told how many were sent (after the
    ``seconds`` the publisher measures)."""
    lock = threading.Lock()
    stats = {"received": 0, "bytes": 0, "first": 0.0, "last": 0.0, "max_gap": 0.0}
    rejects = RejectCounter("transition batch")

    def on_batch(batch: Any, _key: str) -> None:
        now = time.perf_counter()
        with lock:
            if stats["received"] == 0:
                stats["first"] = now
            else:
                stats["max_gap"] = max(stats["max_gap"], now - stats["last"])
            stats["received"] += 1
            stats["last"] = now

    settings = ZenohSettings(mode="client", connect=(endpoint,))
    with open_session(settings, wait_s=5.0) as session:
        subscribe_messages(session, RunKeys(_RUN).all_transitions, TransitionBatch, on_batch, rejects)
        ready.put("ready")
        expected = control.get(timeout=seconds + _REPORT_SLACK_S)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                if stats["received"] + rejects.total >= expected:
                    break
            time.sleep(0.01)
        with lock:
            results.put({"role": "subscriber", "received": stats["received"], "rejected": rejects.total,
                         "seconds": stats["last"] - stats["first"], "max_gap_s": stats["max_gap"]})


def _publisher(endpoint: str, steps: int, height: int, width: int, seconds: float, results: Any,
               drained: Any) -> None:
    batch = make_batch(steps, height, width)
    payload = batch.encode()  # encode cost is measured by the codec figure; this isolates transport
    settings = ZenohSettings(mode="client", connect=(endpoint,))
    with open_session(settings, wait_s=5.0) as session:
        publisher = declare_reliable_publisher(session, RunKeys(_RUN).transitions(_ACTOR))
        deadline = time.monotonic() + 10
        while not publisher.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.01)  # publishing before the route exists would measure nothing
        sent = 0
        max_put_s = 0.0
        start = before = time.perf_counter()
        while before - start < seconds:
            publisher.put(payload)
            sent += 1
            after = time.perf_counter()
            max_put_s, before = max(max_put_s, after - before), after
        results.put({"role": "publisher", "sent": sent, "seconds": before - start, "bytes": len(payload),
                     "max_put_s": max_put_s})
        # open until the subscriber has counted: a session closed with samples still queued drops them
        # (a fixed 0.2 s lost one on a loaded machine)
        drained.get(timeout=60)


def _loopback(steps: int, height: int, width: int, seconds: float, processes: bool) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]) as router:
        links = LinkWatch(router, routine=True)
        if processes:
            ctx = multiprocessing.get_context("spawn")
            ready, control, results, drained = ctx.Queue(), ctx.Queue(), ctx.Queue(), ctx.Queue()
            sub_args = (endpoint, seconds, ready, control, results)
            workers: list[Any] = [ctx.Process(target=_subscriber, args=sub_args)]
        else:
            ready, control, results, drained = queue.Queue(), queue.Queue(), queue.Queue(), queue.Queue()
            # daemons: an interrupted bench must not wait at exit for a side still measuring
            workers = [threading.Thread(target=_subscriber, args=(endpoint, seconds, ready, control, results),
                                        daemon=True)]
        workers[0].start()
        measured = False
        try:
            _report(ready, 60, "subscriber (starting)")
            pub_args = (endpoint, steps, height, width, seconds, results, drained)
            pub = (ctx.Process(target=_publisher, args=pub_args) if processes
                   else threading.Thread(target=_publisher, args=pub_args, daemon=True))
            workers.append(pub)
            pub.start()
            first = _report(results, seconds + _REPORT_SLACK_S, "publisher")
            if first["role"] != "publisher":
                raise TransportBenchError(f"the subscriber ended before the publisher: {first}")
            control.put(first["sent"])
            sub = _report(results, 60, "subscriber")
            links_closed = links.closed  # before the publisher may close: the links lost while measuring
            measured = True
        finally:
            drained.put(True)  # the publisher may close (also when the subscriber failed)
            if not measured:
                # an error or Ctrl-C: the subscriber would wait for the publisher's count (seconds + 120 s)
                # and this process for it at exit; the processes are stopped, the threads are daemons
                control.put(0)
                for worker in workers:
                    if processes and worker.is_alive():
                        worker.terminate()
            for worker in workers:
                worker.join(timeout=30)
                if processes and worker.is_alive():
                    worker.kill()  # stuck in a Zenoh close: not left behind
                    worker.join(timeout=5)
    sent, received = first["sent"], sub["received"]
    return {
        "mode": "processes (spawn)" if processes else "threads (one process, separate sessions)",
        "transitions_per_s": sent * steps / first["seconds"],
        "mb_per_s": sent * first["bytes"] / first["seconds"] / 1e6,
        "receive_transitions_per_s": (received * steps / sub["seconds"]) if sub["seconds"] > 0 else None,
        "batches_sent": sent, "batches_received": received, "lost": sent - received,
        "rejected": sub["rejected"], "seconds": first["seconds"],
        "links_closed": links_closed, "max_put_s": first["max_put_s"], "max_gap_s": sub["max_gap_s"],
    }


def run(seconds: float = 3.0, *, batch_steps: int = 16, height: int = 120, width: int = 160,
        processes: bool = True) -> dict[str, Any]:
    """Codec-only and loopback-router throughput for one batch shape (see the module doc)."""
    if not seconds > 0:
        raise ConfigError(f"--seconds must be > 0, got {seconds}")
    if not 1 <= batch_steps <= MAX_BATCH_STEPS:
        raise ConfigError(f"--batch-steps must be in 1..{MAX_BATCH_STEPS} (the wire's limit), got {batch_steps}")
    if height < 1 or width < 1 or height * width > MAX_FRAME_PIXELS:
        # before the batch is drawn: 100000 x 100000 would ask for hundreds of GiB
        raise ConfigError(f"--height x --width must be 1..{MAX_FRAME_PIXELS} pixels (the wire's limit), "
                          f"got {height} x {width}")
    batch = make_batch(batch_steps, height, width)
    wire_bytes = len(batch.encode())
    return {
        "batch_steps": batch_steps, "frame": f"{width}x{height}",
        "bytes_per_batch": wire_bytes,
        "bytes_per_transition": wire_bytes / batch_steps,
        "depth_bytes_per_transition": height * width * 2 * (batch_steps + 1) / batch_steps,
        "codec": _codec(batch, seconds),
        "loopback": _loopback(batch_steps, height, width, seconds, processes),
    }


def run_command(args: argparse.Namespace) -> int:
    """``cogexplore bench transport``."""
    interrupt_on_stop_signals()  # its spawned publisher and subscriber are stopped, not left behind
    result = run(args.seconds, batch_steps=args.batch_steps, height=args.height, width=args.width,
                 processes=not args.threads)
    print_json(result, args.json)
    return 0
