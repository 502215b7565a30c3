"""Actors that just work: a local ``cogexplore up`` run, joined by actors started as separate
processes with nothing but ``--connect`` and ``--run`` (their credentials from the run folder, their
configuration from the learner), and one with a preset the run's data cannot use, refused."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from service_processes import ENV, REPO, cogexplore, stop, wait_for

from services.actor.options import DEFAULT_NICENESS
from services.bus.session import (
    ZenohSettings,
    free_tcp_port,
    open_session,
    subscribe_messages,
)
from shared.wire.keys import RunKeys
from shared.wire.messages import LearnerStats, RejectCounter

RUN = "join"


def _thread_niceness(pid: int) -> set[int]:
    """The nice values of a process's threads (field 19 of /proc/<pid>/task/<tid>/stat)."""
    found = set()
    for stat in Path(f"/proc/{pid}/task").glob("*/stat"):
        found.add(int(stat.read_text().rsplit(")", 1)[1].split()[16]))
    return found


@pytest.mark.timeout(240)
def test_an_actor_with_only_connect_and_run_joins_and_a_mismatched_preset_stops_in_one_line(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    up_log, joiner_log = tmp_path / "up.log", tmp_path / "joiner.log"
    learner_log = tmp_path / RUN / "logs" / "learner.log"
    logs = [up_log, learner_log, joiner_log]
    up = cogexplore(["up", "--listen", endpoint, "--preset", "smoke", "--run", RUN, "--runs-dir", str(tmp_path),
                     "--actors", "1", "--no-evaluator", "--no-report", "--updates", "100000", "--quiet",
                     "--no-tensorboard", "--set", "train.replay_ratio=0.25"], up_log)
    joiner = None
    try:
        viewer = tmp_path / RUN / "secure" / "viewer.json5"  # the launcher writes the run's credentials first
        wait_for(viewer.is_file, 60, "the run's security folder", logs)
        latest: list[LearnerStats] = []
        lock = threading.Lock()

        def on_stats(stats: LearnerStats, _key: str) -> None:
            with lock:
                latest[:] = [stats]

        def received() -> dict[str, float]:
            with lock:
                extra = latest[0].extra if latest else {}
            return {k.removeprefix("received."): v for k, v in extra.items() if k.startswith("received.")}

        with open_session(ZenohSettings(connect=(endpoint,), config_file=str(viewer)), wait_s=30) as session:
            sub = subscribe_messages(session, RunKeys(RUN).all_stats("learner"), LearnerStats, on_stats,  # noqa: F841
                                     RejectCounter("learner stats"))
            wait_for(lambda: bool(latest), 90, "the learner's statistics", logs)

            # An actor with nothing but where the router is and the run's name.
            joiner = cogexplore(["actor", "--connect", endpoint, "--run", RUN, "--runs-dir", str(tmp_path),
                                 "--no-tensorboard"], joiner_log)
            wait_for(lambda: any(n > 0 for a, n in received().items() if a != "actor-0"), 90,
                     "the joining actor's transitions in the learner's replay", logs)
            # the learner goes first: every thread of the actor (its Zenoh and torch threads too) runs
            # at the actor's niceness, above the learner's 0
            expected = min(19, os.nice(0) + DEFAULT_NICENESS)  # on top of this test's own
            assert _thread_niceness(joiner.pid) == {expected}, _thread_niceness(joiner.pid)
            text = joiner_log.read_text()
            assert f"Zenoh credentials of role actor: {tmp_path / RUN / 'secure' / 'actor.json5'}" in text
            assert f"using the run's configuration (learner 'learner' of run '{RUN}')" in text

            # An actor told another preset: refused at once, in one line naming the difference.
            started, children = time.monotonic(), resource.getrusage(resource.RUSAGE_CHILDREN)
            refused = subprocess.run([sys.executable, "-m", "services.cli", "actor", "--connect", endpoint, "--run",
                                      RUN, "--runs-dir", str(tmp_path), "--preset", "paper", "--no-tensorboard"],
                                     cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
            elapsed = time.monotonic() - started
            after = resource.getrusage(resource.RUSAGE_CHILDREN)  # the refused actor's, the one child reaped since
            cpu_s = after.ru_utime + after.ru_stime - children.ru_utime - children.ru_stime
            last = refused.stderr.strip().splitlines()[-1]
            assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr
            assert last.startswith("cogexplore actor: error: this actor's sensor.width=160 differs from the run's 40 "
                                   f"(learner 'learner' of run '{RUN}'; also differ: sensor.height"), last
            assert last.endswith("; drop --preset to use the run's configuration"), last
            # "At once" in its own work, which a loaded machine does not stretch (its start, one query,
            # the refusal); the wall clock only catches a wait (22 s of it on a loaded 2-core machine)
            assert cpu_s < 10.0 and elapsed < 45.0, f"the refused actor took {cpu_s:.1f} s of CPU, {elapsed:.1f} s"
            with lock:
                rejects = latest[0].rejects
            assert "shape" not in rejects, rejects  # it stopped before sending anything
            assert up.poll() is None and joiner.poll() is None
    finally:
        if joiner is not None:
            stop(joiner)
        stop(up, signal.SIGINT, timeout_s=120)
    assert up.returncode == 0, up_log.read_text()[-2000:]
