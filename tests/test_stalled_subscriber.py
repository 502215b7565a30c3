"""A subscriber to the weights, or a querier of the newest weights, that stops reading (a laptop
asleep with its link open, a process stopped, an evaluator or actor whose credentials someone else
uses) does not stall the run.

Zenoh's router forwards a message on the task that reads the link it came on: a BLOCK message
(the weights) for a receiver whose queue is full holds everything else the sender puts on that
link for up to ``wait_before_close`` (5 s), until the router gives that receiver up. Were the
learner's flow control on the same link as its weights, every actor would run out of credit and the
learner out of data for those seconds (and again for each such receiver). A reply to a query blocks
the same way. Real processes on loopback.
"""

from __future__ import annotations

import csv
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from service_processes import ENV, REPO, cogexplore, stop, wait_for

from services.bus.session import free_tcp_port
from shared.wire.keys import RunKeys

RUN = "stalled"

# A client that subscribes to the weights, or asks for the newest weights a thousand times, and never
# reads another byte once it is stopped.
ROGUE = """
import os, signal, sys, time
from services.bus.session import ZenohSettings, open_session
with open_session(ZenohSettings(mode="client", connect=(sys.argv[1],))) as session:
    if sys.argv[3] == "subscriber":
        sub = session.declare_subscriber(sys.argv[2], lambda sample: None)
        print("ready", flush=True)
    else:  # stopped at once, its replies still to come
        for _ in range(1000):
            session.get(sys.argv[2], lambda reply: None, timeout=60.0)
        print("ready", flush=True)
        os.kill(os.getpid(), signal.SIGSTOP)
    while True:
        time.sleep(1)
"""


def learner_counts(path: Path) -> tuple[int, int]:
    """(updates, transitions) of the last row of the learner's CSV (a row a second), (0, 0) before one."""
    try:
        with open(path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        return (int(rows[-1]["update"]), int(rows[-1]["transitions"])) if rows else (0, 0)
    except (FileNotFoundError, KeyError, ValueError):
        return 0, 0


def longest_still(seen: list[tuple[float, int]]) -> float:
    """The longest time over which a count seen at (time, count) did not rise."""
    longest, since = 0.0, seen[0][0]
    for (_, before), (t, now) in zip(seen, seen[1:]):
        if now > before:
            since = t
        longest = max(longest, t - since)
    return longest


@pytest.mark.timeout(180)
@pytest.mark.parametrize("reader", ["subscriber", "querier"])
def test_a_stopped_weights_reader_does_not_stall_training(tmp_path: Path, reader: str):
    # the querier's replies went out on the learner's first link, the flow control's (stalled 5 s)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    common = ["--run", RUN, "--runs-dir", str(tmp_path), "--connect", endpoint, "--zenoh-mode", "client",
              "--preset", "smoke", "--set", "train.total_updates=1000000", "--set", "train.checkpoint_every=1000000"]
    stats = tmp_path / RUN / "stats" / "learner.csv"
    logs = [tmp_path / n for n in ("router.log", "learner.log", "actor.log")]
    procs: dict[str, subprocess.Popen] = {}
    try:
        procs["router"] = cogexplore(["router", "--listen", endpoint], logs[0])
        # weights after every update: megabytes a second, so that the stopped reader's buffers fill at once
        procs["learner"] = cogexplore(["learner", *common, "--weights-every", "1"], logs[1])
        procs["actor"] = cogexplore(["actor", *common, "--actor-id", "actor-0"], logs[2])
        wait_for(lambda: learner_counts(stats)[0] >= 20, 120, "20 updates", logs)

        key = RunKeys(RUN).weights if reader == "subscriber" else RunKeys(RUN).weights_latest
        procs["rogue"] = subprocess.Popen([sys.executable, "-c", ROGUE, endpoint, key, reader], cwd=REPO,
                                          env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert procs["rogue"].stdout.readline().strip() == "ready"
        time.sleep(0.5)  # its subscription or queries reach the learner: weights flow to it
        procs["rogue"].send_signal(signal.SIGSTOP)
        # the router gives it up after wait_before_close (5 s) or its lease (10 s): watch for 9 s
        updates: list[tuple[float, int]] = []
        transitions: list[tuple[float, int]] = []
        end = time.monotonic() + 9
        while time.monotonic() < end:
            now, (u, n) = time.monotonic(), learner_counts(stats)
            updates.append((now, u))
            transitions.append((now, n))
            time.sleep(0.2)
        # a row a second while the learner's loop runs (a loop held up writes none): the old learner's
        # stood still for 5 s, its weights and flow control held behind the stopped reader
        assert updates[-1][1] > updates[0][1] + 50, f"the learner hardly trained: {updates[0]} -> {updates[-1]}"
        assert longest_still(updates) < 4.0, f"updates stalled {longest_still(updates):.1f} s"
        assert longest_still(transitions) < 4.0, f"transitions stalled {longest_still(transitions):.1f} s"
        assert procs["learner"].poll() is None and procs["actor"].poll() is None
    finally:
        rogue = procs.pop("rogue", None)
        if rogue is not None:
            rogue.kill()
            rogue.wait()
        for name in ("actor", "learner", "router"):
            if name in procs:
                stop(procs[name], timeout_s=30)
