"""A disk that fills mid-run, for real without root: each writer runs in a process whose files may not
grow past a size (RLIMIT_FSIZE, SIGXFSZ ignored), where a write beyond it fails as a full disk's does
(EFBIG). A lost checkpoint is said and tried again, a lost log row or line is said once and training
goes on, and every file that was whole stays whole."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from service_processes import ENV, REPO, run_on_a_full_disk

from shared.learning.checkpoints import CheckpointManager


def _train(runs: Path, updates: int, limit_bytes: int | None) -> subprocess.CompletedProcess:
    argv = ["train", "--preset", "smoke", "--runs-dir", str(runs), "--run", "r", "--quiet", "--updates", str(updates)]
    if limit_bytes is None:
        return subprocess.run([sys.executable, "-m", "services.cli", *argv], cwd=REPO, env=ENV, capture_output=True,
                              text=True, timeout=120)
    return run_on_a_full_disk(f"import sys; from services.cli import main; sys.exit(main({argv!r}))", limit_bytes)


def test_a_trainer_whose_checkpoints_cannot_be_written_trains_on_and_ends_in_one_line(tmp_path: Path) -> None:
    """A checkpoint on a full disk stopped training with a traceback (safetensors' own error for the
    replay memory) and left the replay file of a checkpoint never written; the periodic one is now said
    and tried again, the final one fails the run in one line, and the run's last checkpoint stays whole."""
    first = _train(tmp_path, 25, None)
    assert first.returncode == 0, first.stderr[-2000:]
    # a checkpoint's weights are 1.7 MB, its replay memory 0.2 MB, the logs far less
    done = _train(tmp_path, 75, 1_000_000)
    assert done.returncode == 2, done.stderr[-3000:]
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    periodic = [line for line in done.stderr.splitlines() if "checkpoint at update 50 not written" in line]
    assert len(periodic) == 1 and "ERROR" in periodic[0] and "next checkpoint tries again" in periodic[0], done.stderr
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("cogexplore train: error: checkpoint at update 75 not written: "), last
    assert "ckpt-000000075.safetensors cannot be written" in last and "File too large" in last, last
    assert "resumes from" in last and "ckpt-000000025.safetensors" in last, last
    run = tmp_path / "r"
    updates = [int(line.split(",")[1]) for line in (run / "stats" / "learner.csv").read_text().splitlines()[1:]]
    assert max(updates) == 75  # trained on past the lost checkpoint
    manager = CheckpointManager(run / "checkpoints")
    assert manager.load_latest().update_count == 25 and manager.skipped == []
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names == ["ckpt-000000025.replay-" + names[0].split("replay-")[1], "ckpt-000000025.safetensors", "latest"]


CSV_CODE = """
import logging, resource, sys
from pathlib import Path
from shared.learning import stats
from shared.learning.stats import CsvLog, LearnerRow, read_csv
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
row = lambda u: LearnerRow(time_s=u, update=u, policy_version=u, loss=0.5, mean_q=1.0, updates_per_s=9.0, transitions=u,
                           transitions_per_s=None, replay_size=u, rejected=0, actors_alive=1, mean_weight_lag=0.0,
                           label_agreement=None, safe_agreement=None, lr=0.001, session=7)
log = CsvLog(Path(sys.argv[1]), LearnerRow)
for u in range(1, 101):
    log.write(row(u))
lost = log.lost
stats.CSV_RETRY_S = 0.0  # the disk has room again (below), and the next row tries at once
resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
log.write(row(101))
log.close()
rows = list(read_csv(Path(sys.argv[1]) / LearnerRow.FILE))
print("RESULT", lost, log.lost, [r[1] for r in rows[1:] if len(r) == len(rows[0])][-1])
"""


def test_a_statistics_log_that_cannot_be_written_loses_rows_not_the_process(tmp_path: Path) -> None:
    """learner.csv on a full disk raised out of the training loop (the learner and the trainer stopped for a
    log); its rows are now lost, said once, and written again once the disk has room."""
    done = run_on_a_full_disk(f"import sys; sys.argv = ['x', {str(tmp_path)!r}]\n" + CSV_CODE, 3000)
    assert done.returncode == 0, done.stderr[-3000:]
    result = done.stdout.strip().splitlines()[-1].split(" ", 3)
    assert result[0] == "RESULT" and int(result[1]) > 0 and result[2] == "0" and result[3] == "101", done.stdout
    assert done.stderr.count("cannot be written") == 1 and "rows are lost" in done.stderr, done.stderr
    assert f"written again ({result[1]} row(s) lost)" in done.stderr, done.stderr


def test_a_log_file_that_cannot_be_written_is_said_once_not_a_traceback_a_line(tmp_path: Path) -> None:
    """logging's own file handler printed "--- Logging error ---" and a traceback for every line a full
    disk lost."""
    code = ("import logging; from pathlib import Path; from services.process import setup_logging\n"
            f"setup_logging('INFO', Path({str(tmp_path / 'x.log')!r}))\n"
            "for i in range(200): logging.getLogger('cogexplore.t').info('line %d of the log, long enough', i)\n")
    done = run_on_a_full_disk(code, 2000)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "Logging error" not in done.stderr and "Traceback" not in done.stderr, done.stderr[-2000:]
    said = [line for line in done.stderr.splitlines() if line.startswith("cogexplore: ")]
    assert said == [f"cogexplore: the log file {tmp_path / 'x.log'} cannot be written (File too large): its lines "
                    "are lost, the process goes on"], said
    assert "line 199 of the log" in done.stderr  # on stderr all the same


def test_tensorboard_on_a_full_disk_goes_off_in_one_line_without_its_threads_traceback(tmp_path: Path) -> None:
    """TensorBoard's writer thread died with a traceback on stderr before the process turned it off."""
    code = ("import logging, time; from pathlib import Path; from shared.learning.stats import TensorBoardLog\n"
            "logging.basicConfig(level=logging.INFO, format='%(levelname)s %(message)s')\n"
            f"board = TensorBoardLog(Path({str(tmp_path / 'tb')!r}), flush_s=0.05)\n"
            "deadline = time.monotonic() + 15\n"
            "step = 0\n"
            "while board.enabled and time.monotonic() < deadline:\n"
            "    step += 1; board.write('learner', {'loss': 1.0 / step, 'mean_q': float(step)}, step); time.sleep(0.002)\n"
            "board.close(); print('ENABLED', board.enabled)\n")
    done = run_on_a_full_disk(code, 20_000)
    assert done.returncode == 0 and "ENABLED False" in done.stdout, done.stdout + done.stderr[-2000:]
    assert "Traceback" not in done.stderr and "Exception in thread" not in done.stderr, done.stderr[-2000:]
    assert done.stderr.count("TensorBoard off: cannot write") == 1, done.stderr[-2000:]


def test_an_evaluation_whose_results_cannot_be_written_is_lost_not_the_evaluator(tmp_path: Path) -> None:
    """The evaluator service stopped at the first evaluation a full disk did not let it save (an OSError out
    of its loop); now that evaluation is said lost and the service waits for the next version, with no
    claimed, empty or half-written results file left."""
    code = f"""
import logging
from pathlib import Path
from services.bus.session import ZenohSettings
from services.evaluator.service import EvaluatorService
from shared.config import load_preset
from shared.learning.weights import to_message
from tests.services.evaluator.test_evaluator_service import OVERRIDES, small_net
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
service = EvaluatorService(load_preset("paper").with_overrides(OVERRIDES), "svc", Path({str(tmp_path / 'svc')!r}),
                           ZenohSettings(), "ev-1", every_updates=10, episodes_per_start=1, max_steps=2, record=False)
print("ROW", service.evaluate_in_service(to_message(small_net(), 5)))
"""
    done = run_on_a_full_disk(code, 1500)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "ROW None" in done.stdout, done.stdout
    lost = [line for line in done.stderr.splitlines() if "evaluation of policy version 5 lost" in line]
    assert len(lost) == 1 and "cannot be written: File too large" in lost[0], done.stderr[-3000:]
    assert str(tmp_path / "svc" / "stats" / "eval") in lost[0]
    eval_dir = tmp_path / "svc" / "stats" / "eval"
    assert not eval_dir.exists() or list(eval_dir.iterdir()) == []


def test_a_line_a_full_disk_does_not_take_names_its_file(tmp_path: Path) -> None:
    """A full disk fails the write, not the open: the error said "[Errno 27] File too large" and no file."""
    out = tmp_path / "eval.jsonl"
    code = ("from shared.files import append_line, atomic_write_text\n"
            "for name, write in (('jsonl', lambda: append_line(" + repr(str(out)) + ", 'x' * 5000)),\n"
            "                    ('json', lambda: atomic_write_text(" + repr(str(tmp_path / 'r.json')) + ", 'y' * 5000))):\n"
            "    try: write()\n"
            "    except OSError as exc: print(name, exc)\n")
    done = run_on_a_full_disk(code, 1000)
    assert done.returncode == 0, done.stderr
    assert done.stdout.splitlines() == [f"jsonl [Errno 27] {out} cannot be written: File too large",
                                        f"json [Errno 27] {tmp_path / 'r.json'} cannot be written: File too large"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eval.jsonl"]  # no temporary; the line cut short


def test_a_replay_memory_a_full_disk_cuts_short_is_an_oserror_naming_it_and_leaves_no_file(tmp_path: Path) -> None:
    """safetensors' own error for a replay memory's write (a traceback, not the CLI's one line), which the
    learner's and trainer's "not written, goes on" did not take for the OSError it is."""
    code = f"""
import numpy as np
from pathlib import Path
from shared.config import load_preset
from shared.learning.checkpoints import CheckpointManager
from shared.learning.learner import LearnerCore
cfg = load_preset("smoke")
core = LearnerCore(cfg, device="cpu")
frame = np.ones((cfg.sensor.height, cfg.sensor.width), np.float32)
for i in range(64):
    core.replay.add(("a", i), frame * i, i % 5, 1.0, frame, False)
try:
    core.save(CheckpointManager(Path({str(tmp_path / 'ckpts')!r})), cfg.to_dict())
except OSError as exc:
    print("OSError", exc)
"""
    done = run_on_a_full_disk(code, 100_000)
    assert done.returncode == 0, done.stderr[-3000:]
    line = done.stdout.strip()
    assert line.startswith(f"OSError [Errno 27] {tmp_path / 'ckpts' / 'ckpt-000000000.replay-'}"), line
    assert "cannot be written: Error while serializing: I/O error: File too large" in line, line
    assert list((tmp_path / "ckpts").iterdir()) == []


def test_a_run_is_held_on_a_full_disk_without_its_holders_note(tmp_path: Path) -> None:
    """The lock's note of its holder ("pid N on HOST"), which a full disk refused, failed the hold with
    "[Errno 27] File too large", naming no file: the lock is held without it."""
    code = f"""
from pathlib import Path
from services.runs import RunInUseError, RunLock, RunPaths
paths = RunPaths(Path({str(tmp_path / 'runs' / 'r')!r}))
lock = RunLock(paths, "learner")
try:
    RunLock(paths, "learner")
except RunInUseError as exc:
    print("REFUSED", exc)
lock.release()
"""
    done = run_on_a_full_disk(code, 8)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "REFUSED run 'r' is in use: its learner is another process" in done.stdout, done.stdout


EVALUATE = ["evaluate", "--policy", "reactive", "--starts", "1", "2", "3", "--episodes-per-start", "1", "--quiet"]


def test_evaluate_says_a_recording_a_full_disk_cut_short_was_not_written(tmp_path: Path) -> None:
    """`evaluate --rrd` printed "recording: PATH" for a recording that could not be written (an earlier
    file of that name, if any, was what the path held)."""
    rrd = tmp_path / "eval.rrd"
    done = run_on_a_full_disk(f"import sys; from services.cli import main; sys.exit(main({EVALUATE + ['--rrd', str(rrd)]!r}))",
                              200_000)
    assert done.returncode == 0, done.stderr[-3000:]
    said = [line for line in done.stdout.splitlines() if line.startswith("recording: ")]
    assert said == [f"recording: {rrd} not written (the error above says why)"], done.stdout[-2000:]
    assert "could not be written" in done.stderr and not rrd.exists()


def test_a_recording_on_a_disk_with_no_room_is_refused_before_rerun_opens_it(tmp_path: Path) -> None:
    """Rerun's file sink that could not write its first bytes failed inside set_sinks: `evaluate --rrd` on a
    full disk ended in a RuntimeError's traceback (and the evaluator stopped). A real full disk: a tmpfs,
    where this process may mount one."""
    import os

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(disk)],
                                           capture_output=True).returncode != 0:
        pytest.skip("needs a tmpfs of its own (root)")
    try:
        with open(disk / "filler", "wb") as filler:  # the disk full to its last block
            try:
                while True:
                    filler.write(b"\0" * 2**16)
                    filler.flush()
            except OSError:
                pass
        done = subprocess.run([sys.executable, "-m", "services.cli", *EVALUATE, "--rrd", str(disk / "eval.rrd")],
                              cwd=REPO, env=ENV, capture_output=True, text=True, timeout=60)
    finally:
        subprocess.run(["umount", str(disk)], check=True)
    last = done.stderr.strip().splitlines()[-1]
    assert done.returncode != 0 and f"{disk / 'eval.rrd'} is not started: 0.0 MiB free on its disk, under 16 MiB" \
        in last, done.stderr[-2000:]
