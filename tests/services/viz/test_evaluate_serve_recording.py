"""``evaluate --rerun-serve --rrd``: the recording takes its name only once closed, as every .rrd writer's does."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from services.bus.session import free_tcp_port
from tests.services.viz.test_live_rerun import CHILD_ENV, EVAL_ARGS, REPO, RERUN_BIN


def verified(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(RERUN_BIN), "rrd", "verify", str(path)], env=CHILD_ENV, capture_output=True,
                          text=True, timeout=60)


def serve(rrd: Path, seconds: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "services.cli", "evaluate", *EVAL_ARGS, "--rrd", str(rrd), "--rerun-serve",
           "--rerun-port", str(free_tcp_port()), "--rerun-web-port", str(free_tcp_port()),
           "--rerun-serve-seconds", seconds]
    return subprocess.Popen(cmd, cwd=REPO, env=CHILD_ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_served_recording_killed_while_serving_leaves_no_file_without_its_footer(tmp_path: Path) -> None:
    # The file took its name before serving, while its sink stayed open: killed then, a file under
    # the final name lacked Rerun's footer (`rerun rrd verify`: "Missing RRD footer").
    rrd = tmp_path / "s.rrd"
    proc = serve(rrd, "600")
    try:
        for line in proc.stdout:
            if line.startswith("rerun: serving at"):
                break
        else:
            raise AssertionError(proc.stderr.read())
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not rrd.exists() or verified(rrd).returncode == 0, verified(rrd).stderr
    # stopped as serving ends (the time is up; Ctrl-C alike), the file is named and whole
    done = serve(rrd, "0.5")
    out, err = done.communicate(timeout=120)
    assert done.returncode == 0, err
    check = verified(rrd)
    assert check.returncode == 0, check.stdout + check.stderr
    assert not [p.name for p in tmp_path.iterdir() if p.name != rrd.name]  # no temporary left beside it
