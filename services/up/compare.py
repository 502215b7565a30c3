"""``cogexplore bench system --compare-single-process``: the distributed system against the
single-process trainer, the same recipe for the same minutes, on this machine.

Both run as the user runs them, one after the other: ``cogexplore up`` (router, learner, actors,
evaluator) and ``cogexplore train``, each for ``--minutes`` of wall time from its start. Each run's
own ``stats/learner.csv`` gives the updates and environment steps it made (averaged over the run,
start-up included, since that is wall time a user waits too), and its final checkpoint is then
scored by ``cogexplore evaluate`` under both protocols. The ratios are ``up`` / single process,
from one invocation: above 1, the system is faster or better. Each run starts with an empty world cache
of its own (``<runs>/<run>-world-cache``): sharing the user's, the second run would read warm the
worlds the first generated (shared.sim.world_cache).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from shared.errors import CogexploreError
from shared.learning.stats import summarize_learner_log
from shared.sim.world_cache import CACHE_DIR_ENV

PROTOCOLS = ("robust", "paper")
RUNS = {"up": "up", "single_process": "single"}
"""Each side's run folder in the runs folder."""
_STOP_S = 120.0
"""How long an interrupted run may take to stop (up: the learner's final checkpoint, then the rest)."""


class CompareError(CogexploreError, RuntimeError):
    """One of the two runs, or an evaluation, failed; the message names the log."""


def world_cache(run_dir: Path) -> Path:
    """The world cache of one side's run (its own, empty at its start: see the module)."""
    return run_dir.with_name(f"{run_dir.name}-world-cache")


def _cli(argv: list[str], log: Path, cache_dir: Path) -> float:
    """Run ``cogexplore ARGV`` to the end (output to ``log``, generated worlds kept in ``cache_dir``);
    its wall time in seconds."""
    started = time.monotonic()
    env = dict(os.environ, RERUN_ANALYTICS="0", **{CACHE_DIR_ENV: str(cache_dir)})
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "services.cli", *argv], stdout=out, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=env)
        try:
            code = proc.wait()
        except BaseException:
            # Ctrl-C: stopped as a user stops it (up's learner writes its final checkpoint) and waited for,
            # since the folder is removed next (killed, its orphaned learner wrote into it after the removal)
            proc.terminate()
            try:
                proc.wait(timeout=_STOP_S)
            except BaseException:  # it did not stop in time, or Ctrl-C again: no more waiting
                proc.kill()
                proc.wait()
            raise
    if code != 0:
        raise CompareError(f"`cogexplore {' '.join(argv[:1])}` exited {code}: see {log}")
    return time.monotonic() - started


def _learner_totals(run_dir: Path) -> dict[str, float]:
    """Updates and transitions at the last row of the run's learner.csv, and the learner's time."""
    path = run_dir / "stats" / "learner.csv"
    try:
        training = summarize_learner_log(path)
    except OSError as exc:
        raise CompareError(f"no learner statistics in {run_dir}: {exc}") from None
    if training is None or training.transitions is None or training.learner_s is None:
        raise CompareError(f"{path} has no rows: the run made no update")
    return {"updates": training.updates, "transitions": training.transitions, "learner_s": training.learner_s}


def _score(run_dir: Path, protocol: str, episodes_per_start: int, logs: Path) -> dict[str, float]:
    out = logs / f"{run_dir.name}-{protocol}.json"
    _cli(["evaluate", "--checkpoint", str(run_dir), "--protocol", protocol, "--episodes-per-start",
          str(episodes_per_start), "--device", "cpu", "--quiet", "--json", str(out)], logs / f"{out.stem}.log",
         world_cache(run_dir))
    summary = json.loads(out.read_text())["summary"]
    return {"mean_steps": float(summary["overall"]["mean_steps"]),
            "worst_start_steps": min(float(s["mean_steps"]) for s in summary["per_start"]),
            "coverage_pct": float(summary["overall"]["mean_coverage_pct"])}


def compare(minutes: float = 5.0, *, actors: int = 2, preset: str | None = None, overrides: list[str] | None = None,
            episodes_per_start: int = 2, runs_dir: str | None = None) -> dict[str, Any]:
    """Both runs, their throughput and scores, and the ratios (see the module doc)."""
    if not minutes > 0:
        raise CompareError(f"--minutes must be > 0, got {minutes}")
    root = Path(runs_dir) if runs_dir else Path(tempfile.mkdtemp(prefix="bench-compare-"))
    # `up` and `train` resume a run that exists, and its learner.csv counts the earlier session's
    # updates too: a second comparison in one --runs-dir would divide them by this session's time.
    # (and a world cache left by one would be warm)
    taken = [str(p) for run in RUNS.values() for p in (root / run, world_cache(root / run)) if p.exists()]
    if taken:
        raise CompareError(f"{' and '.join(taken)} already {'exists' if len(taken) == 1 else 'exist'}: both runs "
                           "must start from nothing (their figures would count the earlier runs' updates); give "
                           "another --runs-dir or move them away")
    root.mkdir(parents=True, exist_ok=True)
    # the minutes end both runs, not the preset's total_updates
    timed = ["train.total_updates=1000000000", *(overrides or [])]
    config = [*(["--preset", preset] if preset else []), *[a for o in timed for a in ("--set", o)]]
    common = ["--runs-dir", str(root), "--minutes", str(minutes), "--no-tensorboard", *config]
    failed = False
    try:
        runs: dict[str, dict[str, Any]] = {}
        for name, argv in (("up", ["up", "--run", RUNS["up"], "--actors", str(actors), "--no-report", "--quiet",
                                   *common]),
                           ("single_process", ["train", "--run", RUNS["single_process"], "--quiet", *common])):
            run_dir = root / RUNS[name]
            wall_s = _cli(argv, root / f"{name}.log", world_cache(run_dir))
            totals = _learner_totals(run_dir)
            runs[name] = {"wall_s": wall_s, **totals, "updates_per_s": totals["updates"] / wall_s,
                          "env_steps_per_s": totals["transitions"] / wall_s,
                          **{p: _score(run_dir, p, episodes_per_start, root) for p in PROTOCOLS}}
        up, single = runs["up"], runs["single_process"]

        def ratio(a: float, b: float) -> float | None:
            return a / b if b else None

        return {
            "minutes": minutes, "actors": actors, "preset": preset or "default", "overrides": list(overrides or []),
            "episodes_per_start": episodes_per_start, "cpu_count": os.cpu_count(), **runs,
            "ratios_up_over_single": {
                "updates_per_s": ratio(up["updates_per_s"], single["updates_per_s"]),
                "env_steps_per_s": ratio(up["env_steps_per_s"], single["env_steps_per_s"]),
                **{f"{p}_mean_steps": ratio(up[p]["mean_steps"], single[p]["mean_steps"]) for p in PROTOCOLS},
            },
            "runs_dir": str(root) if runs_dir else None,
        }
    except CompareError:
        failed = True  # its message names a log or a run in the folder: it stays
        raise
    finally:
        if not runs_dir and not failed:
            shutil.rmtree(root, ignore_errors=True)
