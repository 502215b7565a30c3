"""A benchmark stopped early (Ctrl-C, SIGTERM, a bad option) stops what it started and leaves no
temporary run folder behind, but one that fails keeps the log its error names; a bad option value
is refused, not a crash; memory stays bounded however many images a bench sends."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import pytest
from service_processes import ENV, REPO

from shared.config import ConfigError


def _descendants(pid: int) -> set[int]:
    """The live processes below ``pid`` (children in their own sessions too)."""
    found: set[int] = set()
    todo = [pid]
    while todo:
        try:
            children = Path(f"/proc/{todo.pop()}/task").glob("*/children")
            kids = {int(c) for path in children for c in path.read_text().split()}
        except OSError:
            continue
        todo += sorted(kids - found)
        found |= kids
    return found


def _alive(pids: set[int]) -> set[int]:
    """Those of ``pids`` still running (a zombie has ended)."""
    alive = set()
    for pid in pids:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.add(pid)
    return alive


def _start(argv: list[str], tmp_path: Path) -> subprocess.Popen:
    # to files, not pipes: a pipe stays open in a process left behind, and reading it to its end
    # would wait for that process
    out, err = (open(tmp_path.parent / f"{tmp_path.name}.{name}", "w+") for name in ("out", "err"))
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "bench", *argv], cwd=REPO,
                            env=dict(ENV, TMPDIR=str(tmp_path)), stdout=out, stderr=err, text=True)
    proc.out, proc.err = out, err
    return proc


def _read(file) -> str:
    file.seek(0)
    return file.read()


def _wait_for(proc: subprocess.Popen, started: Callable[[list[str]], bool], what: str, timeout_s: float = 120) -> set[int]:
    """The processes below ``proc`` once ``started(their command lines)`` holds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"the bench ended before {what}: {_read(proc.err)[-2000:]}"
        kids = _descendants(proc.pid)
        lines = []
        for pid in kids:
            try:
                lines.append(Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode())
            except OSError:
                pass
        if started(lines):
            return kids
        time.sleep(0.2)
    raise AssertionError(f"no {what} in {timeout_s:.0f} s")


def _stop_and_check(proc: subprocess.Popen, kids: set[int], signum: int, within_s: float) -> str:
    """Send ``signum`` to the bench alone (as `kill` does; a terminal's Ctrl-C also reaches its
    children); the bench must end, and every process it started with it, in ``within_s``."""
    try:
        proc.send_signal(signum)
        proc.wait(timeout=within_s)
        deadline = time.monotonic() + 10  # what the bench stopped may take a moment to be reaped
        while _alive(kids) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not _alive(kids), f"left running after {signal.Signals(signum).name}: {sorted(_alive(kids))}"
        return _read(proc.err)
    finally:
        proc.kill()
        for pid in _alive(kids):
            os.kill(pid, signal.SIGKILL)


@pytest.mark.timeout(200)
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_transport_bench_stopped_while_measuring_stops_its_processes_at_once(signum: int, tmp_path: Path) -> None:
    # Ctrl-C left the subscriber waiting for the publisher's count (seconds + 120 s) and the bench
    # waiting for it at exit; SIGTERM left both processes behind
    proc = _start(["transport", "--seconds", "3", "--height", "30", "--width", "40"], tmp_path)
    kids = _wait_for(proc, lambda lines: sum("spawn_main" in line for line in lines) >= 2, "publisher")
    _stop_and_check(proc, kids, signum, within_s=60)
    assert proc.returncode in (130, -signum) and _read(proc.out) == ""


@pytest.mark.timeout(200)
def test_a_drive_bench_terminated_stops_the_drive_it_started(tmp_path: Path) -> None:
    # SIGTERM ended the bench and left its `drive --lockstep` running, its router gone
    proc = _start(["drive", "--images", "3000"], tmp_path)
    kids = _wait_for(proc, lambda lines: any(" drive --lockstep " in line for line in lines), "drive")
    _stop_and_check(proc, kids, signal.SIGTERM, within_s=60)


@pytest.mark.timeout(300)
def test_a_system_bench_interrupted_stops_its_services_and_removes_its_temporary_run(tmp_path: Path) -> None:
    # the run folder (checkpoints, replay snapshot, logs) stayed in the temporary folder, named nowhere
    proc = _start(["system", "--preset", "smoke", "--seconds", "1", "--warmup-s", "0", "--json"], tmp_path)
    kids = _wait_for(proc, lambda lines: any(" actor " in line for line in lines), "actor")
    time.sleep(2)  # the services in their loops: their folders written
    assert list(tmp_path.glob("cogexplore-bench-*/bench-system-*/logs"))
    _stop_and_check(proc, kids, signal.SIGINT, within_s=120)
    assert proc.returncode == 130
    assert not list(tmp_path.glob("cogexplore-bench-*")), sorted(tmp_path.rglob("*"))[:20]


@pytest.mark.timeout(300)
def test_a_comparison_interrupted_removes_its_temporary_runs(tmp_path: Path) -> None:
    # `up` was killed, and its learner, stopped by its parent's death, wrote its final checkpoint and
    # replay into the temporary folder after it was removed
    proc = _start(["system", "--compare-single-process", "--preset", "smoke", "--minutes", "2",
                   "--episodes-per-start", "1"], tmp_path)
    kids = _wait_for(proc, lambda lines: any(" learner " in line for line in lines), "learner")
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob("bench-compare-*/up/stats/learner.csv")) and time.monotonic() < deadline:
        time.sleep(0.5)  # the learner in its loop: its final checkpoint is written at the stop
    assert list(tmp_path.glob("bench-compare-*/up/stats/learner.csv")), "the learner never reported"
    kids |= _descendants(proc.pid)
    _stop_and_check(proc, kids, signal.SIGTERM, within_s=150)
    assert proc.returncode == 130
    assert not list(tmp_path.glob("bench-compare-*")), sorted(tmp_path.rglob("*"))[:20]


@pytest.mark.timeout(300)
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_a_fuzz_bench_interrupted_removes_its_temporary_run(signum: int, tmp_path: Path) -> None:
    proc = _start(["fuzz", "--payloads", "100"], tmp_path)
    kids = _wait_for(proc, lambda lines: any(" evaluator " in line for line in lines), "evaluator")
    _stop_and_check(proc, kids, signum, within_s=120)
    assert proc.returncode == 130
    assert not list(tmp_path.glob("cogexplore-fuzz-*")), sorted(tmp_path.rglob("*"))[:20]


def test_a_fuzz_bench_refused_before_it_starts_removes_its_temporary_run(tmp_path: Path, monkeypatch) -> None:
    from services.up import fuzz

    # an unknown preset left an empty cogexplore-fuzz-* folder behind each time
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(ConfigError, match="unknown preset 'no-such-preset'"):
        fuzz.run(10, preset="no-such-preset")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv, option", [
    (["bench", "system", "--preset", "smoke", "--seconds", "1", "--learner-threads"], "--learner-threads"),
    (["bench", "learner", "--preset", "smoke", "--repeats", "1", "--threads"], "--threads"),
    (["evaluate", "--policy", "reactive", "--world", "box-room", "--episodes-per-start", "1", "--threads"], "--threads"),
])
def test_more_torch_threads_than_a_machine_runs_are_refused(tmp_path: Path, argv: list[str], option: str) -> None:
    # torch.set_num_threads(100000000) crashed the process (segmentation fault); bench system's
    # OMP_NUM_THREADS=100000000 reached the learner, which died so once everything had started
    proc = subprocess.run([sys.executable, "-m", "services.cli", *argv, "100000000"], cwd=tmp_path, env=ENV,
                          capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr[-2000:]
    assert f"argument {option}: must be a whole number in " in proc.stderr and "1024, got '100000000'" in proc.stderr
    assert list(tmp_path.iterdir()) == []  # refused before anything started


def _peak_rss_mb(argv: list[str]) -> float:
    """The bench's peak memory (and its drive's) over a run that must succeed."""
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "bench", *argv], cwd=REPO, env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _, status, usage = os.wait4(proc.pid, 0)
    finally:
        proc.kill()
    assert os.waitstatus_to_exitcode(status) == 0, proc.stderr.read()[-2000:]
    return usage.ru_maxrss / 1024


@pytest.mark.timeout(240)
def test_a_drive_bench_holds_each_distinct_image_once_however_many_it_sends() -> None:
    # every image sent had its own encoded payload, made before the first was sent: 1000 images of
    # 640 x 480 took 535 MB more than 100 (at 1920 x 1080, --images 10000 asked for 41 GB)
    few = _peak_rss_mb(["drive", "--images", "100", "--width", "640", "--height", "480"])
    many = _peak_rss_mb(["drive", "--images", "1000", "--width", "640", "--height", "480"])
    assert many < few + 150, (few, many)


@pytest.mark.timeout(120)
def test_a_comparison_whose_run_fails_keeps_the_log_its_error_names(tmp_path: Path, monkeypatch) -> None:
    from services.up.compare import CompareError, compare

    # the temporary folder was removed with the log the error pointed to in it
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(CompareError, match=r"`cogexplore up` exited 2: see (\S+)") as failed:
        compare(0.1, preset="smoke", overrides=["no_such.field=1"])
    log = Path(re.search(r"see (\S+)", str(failed.value)).group(1))
    assert log.parent.parent == tmp_path and "no_such" in log.read_text()


@pytest.mark.timeout(200)
def test_a_system_bench_whose_learner_refuses_its_device_says_why(tmp_path: Path) -> None:
    # it said "learner exited with status 2; see .../learner.log", the reason left in the log
    proc = subprocess.run([sys.executable, "-m", "services.cli", "bench", "system", "--preset", "smoke", "--device",
                           "cuda:99", "--seconds", "1", "--json", "--runs-dir", str(tmp_path)], cwd=REPO, env=ENV,
                          capture_output=True, text=True, timeout=180, check=False)
    assert proc.returncode == 1 and proc.stdout == "", proc.stderr[-2000:]
    (line,) = proc.stderr.splitlines()
    assert line.startswith("cogexplore bench system: run 'bench-system-") and "its learner exited (2): " in line, line
    assert "device 'cuda:99'" in line and "learner.log" in line, line


@pytest.mark.timeout(240)
def test_a_fuzz_bench_that_runs_out_of_memory_removes_its_temporary_run(tmp_path: Path, monkeypatch) -> None:
    from services.up import fuzz

    # the error (one line: out of memory) names no folder, and the run's stayed in the temporary folder
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(MemoryError):
        fuzz.run(100, big_bytes=10**15)
    assert list(tmp_path.iterdir()) == []
