"""End to end over real Zenoh on loopback: router + learner + actors as real processes."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from service_processes import cogexplore

from services.bus.session import (
    ZenohSettings,
    free_tcp_port,
    open_session,
    put_reliable,
    query_latest,
    subscribe_messages,
)
from shared.config import load_preset
from shared.wire.keys import RunKeys
from shared.wire.messages import (
    LearnerStats,
    RejectCounter,
    TransitionBatch,
    WeightsMessage,
)

RUN = "e2e"


class Watch:
    """What the test sees on the run's keys, from its own session."""

    def __init__(self, session, keys: RunKeys):
        self.lock = threading.Lock()
        self.stats: LearnerStats | None = None
        self.batches: list[TransitionBatch] = []
        self.rejects = RejectCounter("test")
        self.subs = [
            subscribe_messages(session, keys.all_stats("learner"), LearnerStats, self._on_stats, self.rejects),
            subscribe_messages(session, keys.all_transitions, TransitionBatch, self._on_batch, self.rejects),
        ]

    def _on_stats(self, stats: LearnerStats, _key: str) -> None:
        with self.lock:
            self.stats = stats

    def _on_batch(self, batch: TransitionBatch, _key: str) -> None:
        with self.lock:
            self.batches.append(batch)

    def wait(self, predicate, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                if self.stats is not None and predicate(self):
                    return
            time.sleep(0.2)
        pytest.fail(f"timed out waiting for {what}; last learner stats: {self.stats}")

    def received(self, actor: str) -> float:
        return self.stats.extra.get(f"received.{actor}", 0.0) if self.stats else 0.0


def latest_batch(watch: Watch) -> TransitionBatch:
    """A real actor's batch, as heard on the bus (a valid message to put on a hostile key)."""
    with watch.lock:
        return watch.batches[-1]


def flood_batch(like: TransitionBatch, steps: int = 64) -> bytes:
    """A valid batch of ``steps`` physical transitions with ``like``'s frames (an outsider's flood)."""
    frame = like.depth_mm[0]
    return TransitionBatch.from_steps(
        actor_id="intruder", episode=0, first_step=0, start_index=0, depth=[frame] * steps, next_depth=frame,
        action=[0] * steps, reward=[1.0] * steps, policy_version=[0] * steps, pose=[(0, 0, 0)] * steps).encode()


@pytest.mark.timeout(300)
def test_router_learner_two_actors_churn_and_bad_input(tmp_path: Path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    common = ["--run", RUN, "--runs-dir", str(tmp_path), "--connect", endpoint, "--zenoh-mode", "client",
              "--preset", "smoke", "--set", "train.total_updates=100000", "--set", "train.checkpoint_every=100000"]
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["router"] = cogexplore(["router", "--listen", endpoint], tmp_path / "router.log")
        procs["learner"] = cogexplore(["learner", *common, "--weights-every", "5"], tmp_path / "learner.log")
        for i in (0, 1):
            procs[f"actor-{i}"] = cogexplore(["actor", *common, "--actor-id", f"actor-{i}", "--actor-index", str(i),
                                          "--num-actors", "2"], tmp_path / f"actor-{i}.log")
        keys = RunKeys(RUN)
        with open_session(ZenohSettings(mode="client", connect=(endpoint,)), wait_s=30) as session:
            watch = Watch(session, keys)
            # Transitions from both actors reach the replay memory, and updates run.
            watch.wait(lambda w: w.received("actor-0") > 0 and w.received("actor-1") > 0 and w.stats.updates >= 20,
                       180, "transitions from both actors and 20 updates")
            # Weight versions rise and later transitions carry them.
            watch.wait(lambda w: any(b.policy_version.max() > 0 for b in w.batches if b.actor_id == "actor-0")
                       and any(b.policy_version.max() > 0 for b in w.batches if b.actor_id == "actor-1"),
                       60, "transitions chosen with published weights")
            # The latest weights can be fetched by query (what a late joiner does first).
            payload = query_latest(session, keys.weights_latest, timeout_s=5)
            latest = WeightsMessage.decode(payload)
            assert latest.policy_version >= 5

            # A late-joining actor gets the latest weights: its transitions carry a version > 0.
            procs["actor-late"] = cogexplore(["actor", *common, "--actor-id", "actor-late"], tmp_path / "late.log")
            watch.wait(lambda w: any(b.actor_id == "actor-late" and b.policy_version.min() > 0 for b in w.batches),
                       120, "the late actor's transitions with fetched weights")

            # SIGKILL one actor: the learner and the others carry on.
            procs["actor-0"].send_signal(signal.SIGKILL)
            procs["actor-0"].wait(10)
            with watch.lock:
                updates_then = watch.stats.updates
                from_1_then = watch.received("actor-1")
            watch.wait(lambda w: w.stats.updates > updates_then + 10 and w.received("actor-1") > from_1_then,
                       120, "progress after an actor was killed")
            assert procs["learner"].poll() is None and procs["actor-1"].poll() is None

            # Malformed payloads on the transitions key are rejected, counted, and change nothing.
            with watch.lock:
                rejected_then = watch.stats.transitions_rejected
                replay_then = watch.stats.replay_size
            bad = [b"\x00garbage", b"", TransitionBatch.from_steps(
                actor_id="actor-evil", episode=0, first_step=0, start_index=0,
                depth=[[[1.0] * 7] * 5], next_depth=[[1.0] * 7] * 5, action=[1], reward=[1.0],
                policy_version=[0], pose=[(0, 0, 0)]).encode()]  # wrong frame size for the sensor
            for payload in bad:
                put_reliable(session, keys.transitions("actor-evil"), payload)
            # a key the transitions wildcard takes but no actor id can be: counted, not a traceback per message
            put_reliable(session, f"{keys.prefix}/transitions/actor~evil", latest_batch(watch).encode())
            watch.wait(lambda w: w.stats.transitions_rejected >= rejected_then + len(bad) + 1, 30, "rejects counted")
            with watch.lock:
                assert watch.received("actor-evil") == 0
                # nothing thrown out by them; at capacity a row that waits for its n-step successors (one
                # or two per live actor) replaces one that could be sampled, so the count may dip by those
                n_step, live_actors = load_preset("smoke").dqn.n_step, 2
                assert watch.stats.replay_size >= replay_then - n_step * live_actors
                assert {"garbage", "truncated", "shape", "range"} <= set(watch.stats.rejects)
            assert procs["learner"].poll() is None, "the learner survived bad input"
            assert "failed on a message" not in (tmp_path / RUN / "logs" / "learner-service.log").read_text()

            # A flood of valid batches, faster than the learner takes them in: its loop still gives
            # flow control, and SIGTERM in the middle of it ends the learner (it took them in until
            # its inbox was empty: neither, for as long as the flood lasted).
            flows: list[float] = []
            flow_sub = subscribe_messages(session, keys.flow, None,  # noqa: F841
                                          lambda _m, _k: flows.append(time.monotonic()), RejectCounter("t"))
            flood = flood_batch(latest_batch(watch))
            publisher = session.declare_publisher(keys.transitions("intruder"))
            started = time.monotonic()
            while time.monotonic() - started < 3.0:
                publisher.put(flood)
                time.sleep(0.002)
            during = [t for t in flows if t > started + 0.5]
            assert during and max(b - a for a, b in zip([started + 0.5, *during], [*during, time.monotonic()])) < 2.0
            procs["learner"].send_signal(signal.SIGTERM)
            terminated = time.monotonic()
            while procs["learner"].poll() is None and time.monotonic() - terminated < 3.0:
                publisher.put(flood)
                time.sleep(0.002)
            assert procs["learner"].wait(60) == 0 and time.monotonic() - terminated < 30.0

        # SIGTERM: the learner wrote a final checkpoint and exited 0.
        assert (tmp_path / RUN / "checkpoints" / "latest").exists()
    finally:
        for name, p in procs.items():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for name, p in procs.items():
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()
        for log in sorted(tmp_path.glob("*.log")):
            sys.stdout.write(f"--- {log.name}\n{log.read_text()[-2000:]}\n")
