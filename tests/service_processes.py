"""Helpers for tests that run cogexplore commands as real processes or open real sessions
(importable from any test: pytest puts tests/ on sys.path for its conftest.py)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1", OMP_NUM_THREADS="1")


def cogexplore(argv: list[str], log: Path) -> subprocess.Popen:
    """``cogexplore ARGV`` in its own process group, stdout and stderr to ``log``."""
    with open(log, "wb") as fh:
        return subprocess.Popen([sys.executable, "-m", "services.cli", *argv], cwd=REPO, env=ENV, stdout=fh,
                                stderr=subprocess.STDOUT, start_new_session=True)


def wait_for(predicate, timeout_s: float, what: str, logs: list[Path]) -> None:
    """Poll ``predicate`` until it holds; on time-out fail with the tails of ``logs``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        time.sleep(0.2)
    tails = "\n".join(f"--- {p.name}\n{p.read_text()[-2000:]}" for p in logs if p.exists())
    pytest.fail(f"timed out waiting for {what}\n{tails}")


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout_s: float = 60.0) -> None:
    """Signal ``proc`` and wait; SIGKILL its group if it does not end in ``timeout_s``."""
    if proc.poll() is None:
        proc.send_signal(sig)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def client(endpoint: str):
    """A client session of the router at ``endpoint`` (use it with ``with``)."""
    from services.bus.session import ZenohSettings, open_session

    return open_session(ZenohSettings(mode="client", connect=(endpoint,)))


def run_on_a_full_disk(code: str, limit_bytes: int) -> subprocess.CompletedProcess:
    """Python ``code`` in a process that may write no file past ``limit_bytes`` (a disk that fills: a
    write beyond it fails with "File too large")."""
    script = ("import resource, signal; signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
              f"resource.setrlimit(resource.RLIMIT_FSIZE, ({int(limit_bytes)}, resource.RLIM_INFINITY))\n" + code)
    return subprocess.run([sys.executable, "-c", script], cwd=REPO, env=ENV, capture_output=True, text=True,
                          timeout=120)
