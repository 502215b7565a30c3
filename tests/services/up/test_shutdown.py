"""How `cogexplore up` and the tools built on its launcher (``bench system``, ``bench fuzz``) end:
a learner whose final checkpoint fails at the stop is said and exits non-zero, and the run is let go
(another `up` may start it) whichever way the tool ends."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from service_processes import ENV, REPO

from services.runs import RunLock, RunPaths, save_config
from services.up import bench, fuzz
from shared.config import load_preset
from shared.learning.stats import LearnerRow

RUN = "stopped"


@pytest.mark.timeout(240)
def test_a_final_checkpoint_that_fails_after_ctrl_c_is_said_and_up_exits_non_zero(tmp_path: Path) -> None:
    # up reported "ended: interrupted" and exited 0 over a learner that had exited 2 at its last write
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--run", RUN, "--actors", "1", "--preset",
                             "smoke", "--updates", "1000000", "--set", "train.checkpoint_every=1000000", "--runs-dir",
                             str(tmp_path), "--quiet", "--no-tensorboard", "--no-evaluator", "--no-report"],
                            cwd=REPO, env=ENV, stderr=subprocess.PIPE, text=True)
    try:
        paths = RunPaths(tmp_path / RUN)
        csv = paths.stats / LearnerRow.FILE
        deadline = time.monotonic() + 120
        # a row of its statistics: the learner is in its loop, its stop handler in place
        while not (csv.exists() and len(csv.read_text().splitlines()) >= 2) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert csv.exists(), "the learner never reported"
        # a folder where the final checkpoint's pointer goes: its last write fails (root included,
        # whom a read-only folder would not stop)
        (paths.checkpoints / "latest").mkdir(parents=True)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 1, err[-2000:]
    assert f"run {RUN!r} ended: interrupted" in err, err[-2000:]
    said = [line for line in err.splitlines() if "final checkpoint failed" in line]
    assert len(said) == 1 and "its learner exited (2): " in said[0] and "Is a directory" in said[0], err[-2000:]


def _children(pid: int) -> list[int]:
    return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def _cmdline(pid: int) -> str:
    return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()


@pytest.mark.timeout(240)
def test_a_second_ctrl_c_stops_at_once_without_the_final_checkpoint(tmp_path: Path) -> None:
    # up waited up to a minute for a learner that did not stop, whatever the user pressed meanwhile
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--run", RUN, "--actors", "1", "--preset",
                             "smoke", "--updates", "1000000", "--runs-dir", str(tmp_path), "--quiet",
                             "--no-tensorboard", "--no-evaluator", "--no-report"],
                            cwd=REPO, env=ENV, stderr=subprocess.PIPE, text=True)
    learner = None
    try:
        csv = RunPaths(tmp_path / RUN).stats / LearnerRow.FILE
        deadline = time.monotonic() + 120
        while not (csv.exists() and len(csv.read_text().splitlines()) >= 2) and time.monotonic() < deadline:
            time.sleep(0.5)
        assert csv.exists(), "the learner never reported"
        (learner,) = [c for c in _children(proc.pid) if " learner " in _cmdline(c)]
        os.kill(learner, signal.SIGSTOP)  # a learner that does not get round to its last write
        proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(1.0)  # the first stops the run: up asks the learner, which does not answer
            proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=45)  # not the minute up gives a learner
    finally:
        proc.kill()
        if learner is not None and Path(f"/proc/{learner}").exists():
            os.kill(learner, signal.SIGKILL)
    assert "Ctrl-C again to stop at once" in err and "SIGINT again: killing its services now" in err, err[-2000:]
    assert proc.returncode == 1, err[-2000:]
    said = [line for line in err.splitlines() if "final checkpoint failed" in line]
    assert len(said) == 1 and "SIGKILL" in said[0], err[-2000:]


def _free_to_start(runs_dir: Path, prefix: str) -> None:
    """The run the tool made (its name has the time and pid) can be held by another `up` now."""
    (lock,) = runs_dir.glob(f".{prefix}-*.up.lock")
    RunLock(RunPaths(runs_dir / lock.name[1:-len(".up.lock")]), "up").release()


@pytest.mark.timeout(180)
def test_bench_system_lets_the_run_go_when_it_fails(tmp_path: Path) -> None:
    # the launcher's hold on the run stayed as long as anything kept the error (its traceback)
    with pytest.raises(bench.BenchError, match="not in a steady state") as failed:
        bench.run(1, 1.0, preset="smoke", startup_timeout_s=0.0, runs_dir=tmp_path)
    _free_to_start(tmp_path, bench._RUN_PREFIX)
    assert failed.traceback  # kept until here


@pytest.mark.timeout(240)
def test_bench_fuzz_lets_the_run_go_when_it_fails(tmp_path: Path) -> None:
    paths = RunPaths(tmp_path / "recipe").make()  # a learner that cannot start: the run fails at once
    save_config(load_preset("smoke").with_overrides({"train.init_from": str(tmp_path / "missing.safetensors")}), paths)
    runs = tmp_path / "runs"
    with pytest.raises(fuzz.FuzzError, match="the run did not start") as failed:
        fuzz.run(10, preset=str(paths.config), runs_dir=runs)
    _free_to_start(runs, fuzz.RUN_PREFIX)
    assert failed.traceback


def _bench_whose_final_checkpoint_fails(argv: list[str], runs: Path) -> tuple[int, dict, str]:
    """``cogexplore bench ARGV --runs-dir RUNS`` whose learner's final checkpoint fails (a folder where its
    pointer goes, made once the learner is in its loop); (exit status, its JSON, its stderr)."""
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "bench", *argv, "--runs-dir", str(runs)],
                            cwd=REPO, env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    csv: list[Path] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            csv = [c for c in runs.glob(f"*/stats/{LearnerRow.FILE}") if len(c.read_text().splitlines()) >= 2]
            if csv:
                (csv[0].parents[1] / "checkpoints" / "latest").mkdir(parents=True)
                break
            time.sleep(0.2)
        assert csv, "the learner never reported"
        out, err = proc.communicate(timeout=180)
    finally:
        proc.kill()
    return proc.returncode, json.loads(out[out.index("{"):]), err


@pytest.mark.timeout(300)
def test_bench_system_says_a_final_checkpoint_that_fails_and_exits_non_zero(tmp_path: Path) -> None:
    # bench system printed its figures and exited 0 over a learner that had exited 2 at its last write
    code, result, err = _bench_whose_final_checkpoint_fails(
        ["system", "--preset", "smoke", "--seconds", "1", "--warmup-s", "0", "--json"], tmp_path)
    said = [line for line in err.splitlines() if "final checkpoint failed" in line]
    assert code == 1 and result["failed_at_stop"] == ["learner"], err[-2000:]
    assert len(said) == 1 and "its learner exited (2): " in said[0] and "Is a directory" in said[0], err[-2000:]
    assert result["run_dir"] and Path(result["run_dir"], "logs", "learner.log").exists()  # the log it names stays


@pytest.mark.timeout(300)
def test_bench_fuzz_says_a_final_checkpoint_that_fails_and_exits_non_zero(tmp_path: Path) -> None:
    # bench fuzz counted only the crashes before the stop: the learner's exit 2 at its last write passed
    code, result, err = _bench_whose_final_checkpoint_fails(["fuzz", "--payloads", "100"], tmp_path)
    said = [line for line in err.splitlines() if "final checkpoint failed" in line]
    assert code == 1 and result["crashes"] == [] and result["failed_at_stop"] == ["learner"], err[-2000:]
    assert len(said) == 1 and "its learner exited (2): " in said[0] and "Is a directory" in said[0], err[-2000:]


def test_a_process_that_cannot_be_started_leaves_no_log_file_open(tmp_path: Path) -> None:
    # the log opened for the child stayed open while anything kept the error (its traceback)
    import argparse

    from services.up.launcher import Launcher
    from services.up.options import add_up_arguments

    parser = argparse.ArgumentParser()
    add_up_arguments(parser)
    launcher = Launcher(parser.parse_args(["--run", RUN, "--runs-dir", str(tmp_path), "--quiet"]))
    try:
        launcher.args.rerun_connect = "rerun+http://\0"  # no environment holds it: the start fails
        with pytest.raises(ValueError) as failed:
            launcher.start()
        opened = []
        for fd in Path("/proc/self/fd").iterdir():
            try:
                opened.append(fd.readlink())
            except OSError:  # the listing's own
                continue
        assert launcher.paths.logs / "router.log" not in opened and failed.traceback
    finally:
        launcher.close()


# How each stand-in service meets up's SIGTERM: it says "ready" once its handler is in place.
_AT_SIGTERM = {
    "clean": "signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))",
    "starting": "",  # no handler yet (still importing): SIGTERM ends it
    "traceback": "signal.signal(signal.SIGTERM, lambda *_: exec('raise RuntimeError(\"no room for its last row\")'))",
    "exit 3": "signal.signal(signal.SIGTERM, lambda *_: sys.exit(3))",
    "hung": "signal.signal(signal.SIGTERM, signal.SIG_IGN)",
}


@pytest.mark.parametrize("evaluator, code", [("traceback", 1), ("hung", 0), ("exit 3", 1)])
def test_an_actor_or_evaluator_that_fails_at_the_stop_is_said_and_a_crash_fails_the_run(
        tmp_path: Path, capsys, evaluator: str, code: int) -> None:
    # up stopped them and exited 0 whatever they exited with: only the learner's exit was looked at
    import argparse

    from services.up.launcher import Child, Launcher
    from services.up.options import add_up_arguments

    parser = argparse.ArgumentParser()
    add_up_arguments(parser)
    launcher = Launcher(parser.parse_args(["--run", RUN, "--runs-dir", str(tmp_path), "--quiet", "--no-report"]))
    try:
        for role, name, how in (("learner", "learner", "starting"), ("actor", "actor-0", "clean"),
                                ("actor", "actor-1", "starting"),
                                ("actor", "actor-2", "hung"), ("evaluator", "evaluator", evaluator)):
            log = tmp_path / f"{name}.log"
            with open(log, "wb") as out:
                script = "; ".join(filter(None, ("import signal, sys, time", _AT_SIGTERM[how],
                                                 "print('ready')", "time.sleep(30)")))
                launcher.children.append(Child(role, name, subprocess.Popen(
                    [sys.executable, "-u", "-c", script], stdout=out, stderr=subprocess.STDOUT), log))
        deadline = time.monotonic() + 10
        while not all("ready" in c.logfile.read_text() for c in launcher.children) and time.monotonic() < deadline:
            time.sleep(0.05)
        launcher.stop(("learner",), timeout_s=1.0)  # a Ctrl-C at once: no update yet, no checkpoint lost
        launcher.stop(("actor", "evaluator"), timeout_s=1.0)
        assert launcher.finish("time") == code
    finally:
        for c in launcher.children:
            c.process.kill()
            c.process.wait()
        launcher.close()
    err = capsys.readouterr().err
    assert "final checkpoint failed" not in err
    said = [line for line in err.splitlines() if "at its stop" in line]
    killed = f"run {RUN!r}: at its stop its actor-2 was ended by SIGKILL: ready (see {tmp_path / 'actor-2.log'}); " \
             "up killed it, it did not stop in time (the run does not fail for it)"
    if evaluator == "hung":
        assert said == [killed, killed.replace("actor-2", "evaluator")]
        return
    status = "exited (1): RuntimeError: no room for its last row" if evaluator == "traceback" else "exited (3): ready"
    assert said == [killed, f"run {RUN!r}: at its stop its evaluator {status} (see {tmp_path / 'evaluator.log'})"]
