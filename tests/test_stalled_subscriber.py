"""A subscriber to the weights that stops reading (a laptop asleep with its link open, a process
stopped, an evaluator or actor whose credentials someone else uses) does not stall the run.

Zenoh's router forwards a message on the task that reads the link it came on: a BLOCK message
(the weights) for a receiver whose queue is full holds everything else the sender puts on that
link for up to ``wait_before_close`` (5 s), until the router gives that receiver up. Were the
learner's flow control on the same link as its weights, every actor would run out of credit and the
learner out of data for those seconds (and again for each such receiver). Real processes on loopback.
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

# A client that subscribes to the weights and never reads another byte once it is stopped.
ROGUE = """
import sys, time
from services.bus.session import ZenohSettings, open_session
with open_session(ZenohSettings(mode="client", connect=(sys.argv[1],))) as session:
    sub = session.declare_subscriber(sys.argv[2], lambda sample: None)
    print("subscribed", flush=True)
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
def test_a_stopped_weights_subscriber_does_not_stall_training(tmp_path: Path):
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

        procs["rogue"] = subprocess.Popen([sys.executable, "-c", ROGUE, endpoint, RunKeys(RUN).weights], cwd=REPO,
                                          env=ENV, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert procs["rogue"].stdout.readline().strip() == "subscribed"
        time.sleep(0.5)  # its subscription reaches the learner: weights flow to it
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
