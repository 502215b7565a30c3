"""``cogexplore up`` when the run's processes fail the way real machines fail: a learner of the run that
runs outside up (started by hand, or a killed `up`'s, still writing its final checkpoint), a stop signal
that comes while the services are being stopped. Real processes on loopback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from service_processes import ENV, REPO, stop

from services.runs import RunPaths
from shared.learning.stats import LearnerRow
from tests.services.up.test_resume import RUN, run_at, up


@pytest.mark.timeout(120)
def test_up_refuses_a_run_whose_learner_runs_outside_it_before_touching_it(tmp_path: Path) -> None:
    # up replaced the running learner's config.toml, started a router and actors, and then failed (exit 1)
    # on its own learner, refused by the run's lock
    paths = run_at(tmp_path, updates=10, total_updates=20)
    config = paths.config.read_bytes()
    lock = tmp_path / f".{RUN}.learner.lock"
    with open(tmp_path / "learner.out", "wb") as out:
        learner = subprocess.Popen([sys.executable, "-m", "services.cli", "learner", "--run", RUN, "--runs-dir",
                                    str(tmp_path), "--no-tensorboard"], cwd=REPO, env=ENV, stdout=out,
                                   stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while not (lock.exists() and f"pid {learner.pid} " in lock.read_text()) and time.monotonic() < deadline:
            assert learner.poll() is None, (tmp_path / "learner.out").read_text()[-2000:]
            time.sleep(0.2)
        refused = up(tmp_path, "--set", "dqn.lr=0.5", timeout_s=60)
    finally:
        stop(learner)
    message = refused.stderr.strip()
    assert refused.returncode == 2, message[-2000:]
    assert "\n" not in message and f"is in use: its learner is pid {learner.pid} " in message, message
    assert paths.config.read_bytes() == config  # the running learner's recipe stays
    assert not (paths.logs / "router.log").exists()  # nothing was started


def _recorder(path: Path) -> subprocess.Popen:
    """A process with a recording of ``path`` under way (its temporary held), until it is killed."""
    code = ("import sys, time; from services.viz.rerun import RecordingFile; "
            f"f = RecordingFile({str(path)!r}); print(f.partial, flush=True); time.sleep(300)")
    return subprocess.Popen([sys.executable, "-c", code], cwd=REPO, env=ENV, stdout=subprocess.PIPE, text=True)


@pytest.mark.timeout(120)
def test_the_next_evaluator_removes_the_recording_a_killed_one_left_and_keeps_a_live_one(tmp_path: Path,
                                                                                        caplog) -> None:
    # a SIGKILLed evaluator's .eval-<version>.rrd.tmp-* stayed for good: only a recorder of that very
    # version removed it, and a resumed run evaluates newer ones
    from services.bus.session import ZenohSettings
    from services.evaluator.service import EvaluatorService
    from shared.config import load_preset

    recordings = tmp_path / "svc" / "recordings"
    recordings.mkdir(parents=True)
    killed, live = _recorder(recordings / "eval-000005.rrd"), _recorder(recordings / "eval-000010.rrd")
    drive = _recorder(recordings / "drive.rrd")  # a killed `drive --rrd`'s partial log, which it keeps
    try:
        left, writing = Path(killed.stdout.readline().strip()), Path(live.stdout.readline().strip())
        drive_log = Path(drive.stdout.readline().strip())
        for gone in (killed, drive):
            gone.kill()
            gone.wait()
        with caplog.at_level("INFO"):
            EvaluatorService(load_preset("smoke"), "svc", tmp_path / "svc", ZenohSettings(), "ev-1")
    finally:
        live.kill()
        live.wait()
    assert f"removed 1 recording(s) a killed evaluator left unfinished ({recordings})" in caplog.text
    assert not left.exists() and writing.exists() and drive_log.exists()


def _signal_pending(pid: int, signum: int) -> bool:
    """Whether ``signum`` waits to be delivered to process ``pid`` (a stopped one takes none)."""
    status = Path(f"/proc/{pid}/status").read_text()
    pending = int(next(line.split()[1] for line in status.splitlines() if line.startswith("ShdPnd:")), 16)
    return bool(pending >> (signum - 1) & 1)


@pytest.mark.timeout(120)
def test_a_ctrl_c_while_the_run_stops_at_its_time_limit_is_said_at_once(tmp_path: Path) -> None:
    # --minutes was up and up waited for its learner's final checkpoint (up to a minute) without a word:
    # a first Ctrl-C was taken silently, a second killed everything
    proc = subprocess.Popen([sys.executable, "-m", "services.cli", "up", "--run", RUN, "--actors", "1", "--preset",
                             "smoke", "--set", "train.total_updates=1000000", "--minutes", "0.2", "--runs-dir",
                             str(tmp_path), "--quiet", "--no-tensorboard", "--no-evaluator", "--no-report"],
                            cwd=REPO, env=ENV, stderr=subprocess.PIPE, text=True)
    learner = None
    try:
        csv = RunPaths(tmp_path / RUN).stats / LearnerRow.FILE
        deadline = time.monotonic() + 60
        while not (csv.exists() and len(csv.read_text().splitlines()) >= 2) and time.monotonic() < deadline:
            time.sleep(0.2)
        (learner,) = [int(c) for c in Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
                      if " learner " in Path(f"/proc/{c}/cmdline").read_bytes().replace(b"\0", b" ").decode()]
        os.kill(learner, signal.SIGSTOP)  # its final checkpoint takes long
        while not _signal_pending(learner, signal.SIGTERM) and time.monotonic() < deadline:
            time.sleep(0.1)  # the time is up: up stops it
        assert _signal_pending(learner, signal.SIGTERM), "up never stopped its learner"
        proc.send_signal(signal.SIGINT)
        time.sleep(2.0)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
        if learner is not None and Path(f"/proc/{learner}").exists():
            os.kill(learner, signal.SIGKILL)
    lines = err.splitlines()
    heard = [i for i, line in enumerate(lines) if "stopping: its learner writes its final checkpoint" in line]
    killed = [i for i, line in enumerate(lines) if "SIGINT again: killing its services now" in line]
    assert len(heard) == 1 and len(killed) == 1 and heard[0] < killed[0], err[-2000:]


def test_up_passes_a_rate_set_for_this_start_on_to_its_learner_as_the_users_choice(tmp_path: Path) -> None:
    # up writes its --set into the run's config and starts its learner with that file alone: after a divergence
    # the learner took `up --set dqn.lr=X` for the config's own rate and halved it, or refused the run for good
    from services.cli import build_parser
    from services.up.launcher import Launcher
    from shared.learning.divergence import sets_lr

    def learner_argv(*flags: str) -> list[str]:
        launcher = Launcher(build_parser().parse_args(["up", "--run", "r", "--runs-dir", str(tmp_path), *flags]))
        try:
            return next(argv for role, _, argv in launcher.service_argvs() if role == "learner")
        finally:
            launcher.close()

    chosen = learner_argv("--set", "dqn.lr=1e-5", "--set", "train.seed=3")
    assert chosen[-2:] == ["--set", "dqn.lr=1e-05"] and sets_lr(build_parser().parse_args(chosen).overrides)
    assert "--set" not in learner_argv("--set", "train.seed=3")
