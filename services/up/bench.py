"""``cogexplore bench system``: the whole distributed system, measured from outside.

Starts a real router, learner and N actors as separate processes (the launcher's process
handling: ``services.up.launcher.Launcher``, no evaluator), waits until the learner updates and
every actor's transitions arrive, lets it settle for ``--warmup-s``, then measures over
``--seconds`` from a monitoring Zenoh session:

- env steps/s in total and per actor: deltas of the learner's ``received.<actor>`` counters
  (transitions that reached the replay memory; an actor's env steps up to one batch);
- learner updates/s and the replay ratio achieved (updates / transitions in the window);
- mean weight lag (the learner's ``mean_weight_lag``: versions between the learner's newest
  weights and those that chose the actors' latest actions), averaged over the window;
- episodes and mean steps per episode (EpisodeStats), CPU use of every process (/proc).

With the default replay ratio 1 the learner's flow control holds the actors to the update
rate, so the env rate measured is the learner's; ``--set train.replay_ratio=0.02`` lifts that
limit to measure raw actor throughput. The run folder is a temporary directory removed at
the end unless ``--runs-dir`` is given (or a service failed). A service that crashes at the stop
(the learner's final checkpoint, an actor's last statistics) is said in one line as ``up`` says
it (``Launcher.failed_at_stop``), named in ``failed_at_stop`` and the bench exits 1.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from shared.config import DEFAULT_PRESET
from shared.errors import CogexploreError

# Defaults that keep the learner running for the whole measurement and keep periodic
# checkpoint writes out of the steady state; --set may override them.
_BENCH_OVERRIDES = ("train.total_updates=1000000000", "train.checkpoint_every=1000000000")
_RUN_PREFIX = "bench-system"


class BenchError(CogexploreError, RuntimeError):
    """The system did not come up, or a process died during the measurement."""


@dataclass
class _Observed:
    """What the monitoring session has seen (fed from Zenoh threads)."""

    lock: threading.Lock = field(default_factory=threading.Lock)
    learner: list[tuple[float, Any]] = field(default_factory=list)  # (monotonic arrival, LearnerStats)
    episodes: list[tuple[float, Any]] = field(default_factory=list)  # (monotonic arrival, EpisodeStats)
    flow: Any | None = None  # the newest FlowControl

    def on_learner(self, stats: Any, _key: str) -> None:
        with self.lock:
            self.learner.append((time.monotonic(), stats))

    def on_episode(self, stats: Any, _key: str) -> None:
        with self.lock:
            self.episodes.append((time.monotonic(), stats))

    def on_flow(self, message: Any, _key: str) -> None:
        with self.lock:
            self.flow = message

    def latest(self) -> Any | None:
        with self.lock:
            return self.learner[-1][1] if self.learner else None


def _cpu_seconds(pid: int) -> float | None:
    """User + system CPU seconds of a live process (Linux /proc), None when unreadable."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[1].split()  # the command name may hold spaces
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _env_int(name: str) -> int | None:
    value = os.environ.get(name, "")
    return int(value) if value.isdigit() else None


def _received(stats: Any, actor: str) -> float:
    return float(stats.extra.get(f"received.{actor}", 0.0))


def _launcher_args(actors: int, preset: str, overrides: list[str], runs_dir: Path,
                   device: str | None, prefix: str = _RUN_PREFIX) -> argparse.Namespace:
    """The launcher's own options, parsed by its own parser (so new options get defaults), for a run
    named ``<prefix>-<time>-<pid>``."""
    from services.up.options import add_up_arguments

    parser = argparse.ArgumentParser(add_help=False)
    add_up_arguments(parser)
    # A fresh run name each time: the learner would resume from an earlier run's checkpoint.
    run = f"{prefix}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"
    argv = ["--actors", str(actors), "--preset", preset, "--run", run, "--runs-dir", str(runs_dir),
            "--no-evaluator", "--no-report", "--quiet"]
    for override in (*_BENCH_OVERRIDES, *overrides):
        argv += ["--set", override]
    if device:
        argv += ["--device", device]
    return parser.parse_args(argv)


def run(actors: int = 1, seconds: float = 60.0, *, preset: str = "fast", overrides: list[str] | None = None,
        warmup_s: float = 5.0, startup_timeout_s: float = 600.0, runs_dir: str | Path | None = None,
        device: str | None = None, learner_threads: int | None = None) -> dict[str, Any]:
    """Start router + learner + ``actors`` actors, measure for ``seconds``, stop; returns figures.

    ``learner_threads`` sets OMP_NUM_THREADS for the started processes (the learner takes
    torch's default thread count from it; actors use one thread regardless)."""
    if actors < 1:
        raise ValueError(f"actors must be >= 1, got {actors}")
    if seconds <= 0:
        raise ValueError(f"seconds must be > 0, got {seconds}")
    if warmup_s < 0:
        raise ValueError(f"warmup_s must be >= 0, got {warmup_s}")
    from services.options import MAX_TORCH_THREADS

    if learner_threads is not None and not 1 <= learner_threads <= MAX_TORCH_THREADS:
        # OMP_NUM_THREADS=100000000 crashed the learner (SIGSEGV) once everything had started
        raise ValueError(f"--learner-threads must be in 1..{MAX_TORCH_THREADS}, got {learner_threads}")
    from services.bus.session import open_session, subscribe_messages
    from services.runs import resolve_config, save_config
    from services.up.launcher import Launcher
    from shared.wire.keys import RunKeys
    from shared.wire.messages import (
        EpisodeStats,
        FlowControl,
        LearnerStats,
        RejectCounter,
    )

    overrides = list(overrides or [])
    temporary = runs_dir is None
    root = Path(tempfile.mkdtemp(prefix="cogexplore-bench-")) if temporary else Path(runs_dir)
    launcher = None
    try:
        launcher = Launcher(_launcher_args(actors, preset, overrides, root, device))
        launcher.config = resolve_config(launcher.args, launcher.paths)
        save_config(launcher.config, launcher.paths)
    except BaseException:
        if launcher is not None:
            launcher.close()
        if temporary:
            shutil.rmtree(root, ignore_errors=True)  # nothing ran: nothing to keep
        raise
    actor_ids = [f"actor-{i}" for i in range(actors)]
    load_before = os.getloadavg()[0]
    observed = _Observed()
    keys = RunKeys(launcher.run)
    started = time.monotonic()
    succeeded = unnamed_failure = False

    def check_alive() -> None:
        for child in launcher.children:
            if child.process.poll() is not None:
                # its last line says why (--device cuda without a GPU: the learner's refusal), as up says it
                raise BenchError(f"run {launcher.run!r}: {child.exited()}")

    try:
        saved_omp = os.environ.get("OMP_NUM_THREADS")
        if learner_threads is not None:
            os.environ["OMP_NUM_THREADS"] = str(learner_threads)  # the launcher's children inherit it
        try:
            launcher.start()
        finally:
            if learner_threads is not None:
                if saved_omp is None:
                    os.environ.pop("OMP_NUM_THREADS", None)
                else:
                    os.environ["OMP_NUM_THREADS"] = saved_omp
        settings = launcher.settings("viewer")
        with open_session(settings, wait_s=60.0) as session:
            rejects = RejectCounter("stats message")
            subs = [subscribe_messages(session, keys.all_stats("learner"), LearnerStats, observed.on_learner, rejects),
                    subscribe_messages(session, keys.all_stats("episode"), EpisodeStats, observed.on_episode,
                                       rejects),
                    subscribe_messages(session, keys.flow, FlowControl, observed.on_flow, rejects)]
            try:
                # 1. Up and in its steady state (see _steady): not the actors' first burst nor
                # the learner's catch-up on it.
                deadline = time.monotonic() + startup_timeout_s
                while not _steady(observed, actor_ids, launcher.config.train):
                    check_alive()
                    if time.monotonic() > deadline:
                        raise BenchError(f"not in a steady state after {startup_timeout_s:.0f} s (last learner "
                                         f"stats: {observed.latest()}); logs in {launcher.paths.logs}")
                    time.sleep(0.5)
                startup_s = time.monotonic() - started
                # 2. Settle, then measure between two learner reports.
                _sleep_checking(warmup_s, check_alive)
                first = _next_report(observed, check_alive)
                cpu_first = {c.name: _cpu_seconds(c.process.pid) for c in launcher.children}
                cpu_t0 = time.monotonic()
                _sleep_checking(seconds, check_alive)
                last = _next_report(observed, check_alive)
                cpu_last = {c.name: _cpu_seconds(c.process.pid) for c in launcher.children}
                cpu_t1 = time.monotonic()
                succeeded = True
            finally:
                for sub in subs:
                    sub.undeclare()
    except BaseException as exc:
        unnamed_failure = not isinstance(exc, BenchError)  # Ctrl-C, a session that failed: no folder named
        raise
    finally:
        try:
            launcher.stop_services()  # the launcher's order: learner first (final checkpoint), then the rest
        finally:
            launcher.close()  # the run is let go however it ended (a traceback kept would hold it)
        # A service that crashed at the stop (the learner's final checkpoint, say) is said in one line, as
        # up says it, and the figures say the run failed; a failure before it is the error raised.
        failed_at_stop = launcher.failed_at_stop() if succeeded else []
        # on failure the logs stay for the error message that names them
        if temporary and (unnamed_failure or (succeeded and not failed_at_stop)):
            shutil.rmtree(root, ignore_errors=True)

    (t_first, s_first), (t_last, s_last) = first, last
    span_s = s_last.uptime_s - s_first.uptime_s  # the learner's own clock between its two reports
    d_updates = s_last.updates - s_first.updates
    d_transitions = s_last.transitions_received - s_first.transitions_received
    per_actor = {a: (_received(s_last, a) - _received(s_first, a)) / span_s for a in actor_ids}
    with observed.lock:
        lags = [s.extra.get("mean_weight_lag", 0.0) for t, s in observed.learner if t_first <= t <= t_last]
        episodes = [e for t, e in observed.episodes if t_first < t <= t_last]
    cpu_span = cpu_t1 - cpu_t0
    cpu = {name: round(100.0 * (cpu_last[name] - cpu_first[name]) / cpu_span, 1)
           for name in cpu_first if cpu_first[name] is not None and cpu_last.get(name) is not None}
    cfg = launcher.config
    return {
        "preset": preset,
        "overrides": overrides,
        "run_dir": None if temporary and not failed_at_stop else str(launcher.paths.root),
        "failed_at_stop": failed_at_stop,
        "actors": actors,
        "world": cfg.env.world,
        "frame": f"{cfg.sensor.width}x{cfg.sensor.height}",
        "seconds": span_s,
        "time_to_steady_s": startup_s,
        "warmup_s": warmup_s,
        "env_steps_per_s": d_transitions / span_s,
        "env_steps_per_s_per_actor": per_actor,
        "updates_per_s": d_updates / span_s,
        "replay_ratio_target": cfg.train.replay_ratio,
        "replay_ratio_achieved": d_updates / d_transitions if d_transitions else None,
        "mean_weight_lag": sum(lags) / len(lags) if lags else None,
        "transitions": d_transitions,
        "updates": d_updates,
        "episodes": len(episodes),
        "mean_episode_steps": sum(e.steps for e in episodes) / len(episodes) if episodes else None,
        "omp_num_threads": learner_threads if learner_threads is not None else _env_int("OMP_NUM_THREADS"),
        "cpu_percent": cpu,
        "cpu_count": os.cpu_count(),
        "load_avg_1m_before": load_before,
    }


def _steady(observed: _Observed, actor_ids: list[str], train: Any, span_s: float = 8.0) -> bool:
    """True once the learner runs its steady state: it updates, every actor's transitions have
    arrived, its backlog of due updates is no more than flow control allows, and over the last
    reports (``span_s`` and three reports at least) transitions kept arriving with updates /
    transitions within a factor of 2 of the replay ratio.

    Why: before the first update the actors run ahead by the flow-control slack (and what
    was in flight when credit was granted), then wait while the learner catches up on that
    backlog with no transitions arriving; a window over either phase measures neither.
    """
    with observed.lock:
        reports = [s for _, s in observed.learner]
        flow = observed.flow
    if not reports or flow is None:
        return False
    last = reports[-1]
    if last.updates == 0 or any(_received(last, a) <= 0 for a in actor_ids):
        return False
    ratio, warmup = train.replay_ratio, train.warmup_transitions
    # The learner asks for transitions up to warmup + updates / ratio + slack; in its steady
    # state that is what it has, so its backlog is about ratio * slack (plus batches in flight).
    slack = flow.transitions_wanted - warmup - math.ceil(flow.updates / ratio)
    backlog = ratio * (last.transitions_received - warmup) - last.updates
    if backlog > ratio * (slack + 32 * len(actor_ids)) + 8:
        return False
    earlier = [s for s in reports[:-3] if s.updates > 0 and last.uptime_s - s.uptime_s >= span_s]
    if not earlier:
        return False
    first = earlier[-1]
    d_transitions = last.transitions_received - first.transitions_received
    d_updates = last.updates - first.updates
    return d_transitions > 0 and 0.5 <= d_updates / d_transitions / ratio <= 2.0


def _given(args: argparse.Namespace, *names: str) -> dict[str, Any]:
    """The options among ``names`` that were given (the function called has the defaults)."""
    return {name: getattr(args, name) for name in names if getattr(args, name) is not None}


def _refuse_given(args: argparse.Namespace, instead: dict[str, str | None], where: str) -> None:
    """Refuse the options in ``instead`` (flag -> what to give instead, or None) that were given."""
    from shared.config import ConfigError

    given = [flag for flag in instead if getattr(args, flag.lstrip("-").replace("-", "_")) is not None]
    if given:
        hints = [f"{flag}: give {instead[flag]} instead" for flag in given if instead[flag]]
        verb = "does" if len(given) == 1 else "do"
        raise ConfigError(f"{', '.join(given)} {verb} not reach {where}" + (f" ({'; '.join(hints)})" if hints else ""))


def _sleep_checking(seconds: float, check_alive: Any) -> None:
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        check_alive()
        time.sleep(min(0.5, left))


def _next_report(observed: _Observed, check_alive: Any, timeout_s: float = 180.0) -> tuple[float, Any]:
    """The first learner report that arrives from now on (about once a second, or once per
    learner loop of a few updates when updates are slow)."""
    with observed.lock:
        seen = len(observed.learner)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with observed.lock:
            if len(observed.learner) > seen:
                return observed.learner[-1]
        check_alive()
        time.sleep(0.05)
    raise BenchError(f"no learner statistics for {timeout_s:.0f} s")


def _print_text(result: dict[str, Any]) -> None:
    print(f"{result['actors']} actor(s), preset {result['preset']} {' '.join(result['overrides'])}, "
          f"{result['world']} {result['frame']}, {result['seconds']:.1f} s measured")
    print(f"  env steps/s      {result['env_steps_per_s']:8.1f}  "
          + "  ".join(f"{a} {r:.1f}" for a, r in result["env_steps_per_s_per_actor"].items()))
    print(f"  updates/s        {result['updates_per_s']:8.2f}")
    ratio = result["replay_ratio_achieved"]
    print(f"  replay ratio     {'n/a' if ratio is None else f'{ratio:8.3f}'} (target {result['replay_ratio_target']})")
    lag = result["mean_weight_lag"]
    print(f"  mean weight lag  {'n/a' if lag is None else f'{lag:8.1f}'} versions")
    print("  cpu %            " + "  ".join(f"{n} {p}" for n, p in result["cpu_percent"].items()))
    print(f"  load avg before  {result['load_avg_1m_before']:.2f} on {result['cpu_count']} cores")
    if result["failed_at_stop"]:
        print(f"  FAILED at stop   {', '.join(result['failed_at_stop'])} (logs in {result['run_dir']})")


def run_command(args: argparse.Namespace) -> int:
    from services.bench import interrupt_on_stop_signals
    from services.process import setup_logging
    from shared.config import ConfigError

    setup_logging("WARNING")
    interrupt_on_stop_signals()  # the measurement ends through its clean-up: the processes stop, learner first
    actors = args.actors if args.actors is not None else (2 if args.compare_single_process else 1)
    if args.compare_single_process:
        from services.up.compare import compare

        # compare() starts `up` and `train` with the same --set and environment and no other option:
        # these would reach neither run, so the figures would not be of what was asked
        instead = {"--device": "--set train.device=DEVICE", "--learner-threads": "OMP_NUM_THREADS=N in the environment",
                   "--seconds": "--minutes", "--warmup-s": None, "--startup-timeout-s": None}
        _refuse_given(args, instead, "--compare-single-process's runs")
        result = compare(actors=actors, preset=args.preset or DEFAULT_PRESET, overrides=args.overrides,
                         runs_dir=args.runs_dir, **_given(args, "minutes", "episodes_per_start"))
        print(json.dumps(result, indent=2))
        return 0
    _refuse_given(args, {"--minutes": "--seconds", "--episodes-per-start": None},
                  "a measurement without --compare-single-process")
    try:
        result = run(actors, preset=args.preset or "fast", overrides=args.overrides, runs_dir=args.runs_dir,
                     device=args.device, learner_threads=args.learner_threads,
                     **_given(args, "seconds", "warmup_s", "startup_timeout_s"))
    except (BenchError, ValueError) as exc:
        if isinstance(exc, ConfigError):
            raise
        print(f"cogexplore bench system: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        _print_text(result)
    return 1 if result["failed_at_stop"] else 0
