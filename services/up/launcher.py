"""``cogexplore up``: the embedded default. Router, learner, N actors and the evaluator as
separate local processes, one progress display, an orderly stop, everything in runs/<run>/.

It is the local twin of docker-compose.yml: the same services, started with the same
command lines, meeting at one Zenoh router.

The bus is closed to everyone but the run's own services (services.bus.security): the first ``up``
of a run writes ``runs/<run>/secure/`` (a user and password per role, the access control list), the
router loads its config and every process its role's. On loopback the links are plain TCP; a
router that listens beyond the machine (``--listen tls/0.0.0.0:7447``) needs the folder with TLS
certificates: ``--tls`` makes it so (for this machine's name and any ``--host``), as does ``cogexplore
secure init runs/<run>/secure --tls --host <name>``; ``up`` refuses to start without them, or with a
plain TCP endpoint there.
"""

from __future__ import annotations

import argparse
import collections
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from tqdm import tqdm

from services.bus.security import SecureFiles, SecurityError, init_secure
from services.bus.session import (
    LivelinessWatch,
    ZenohSettings,
    free_tcp_port,
    open_session,
    parse_endpoints,
    subscribe_messages,
)
from services.process import setup_logging
from services.runs import RunPaths, resolve_config, save_config
from shared.config import ConfigError
from shared.wire.keys import RunKeys, validate_name
from shared.wire.messages import EpisodeStats, LearnerStats, RejectCounter

log = logging.getLogger("cogexplore.up")


def _die_with_parent() -> None:
    """Runs in each child before exec: SIGTERM it if the launcher dies (no orphans, Linux)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except Exception:
        pass


@dataclass
class Child:
    role: str
    name: str
    process: subprocess.Popen
    logfile: Path


@dataclass
class Progress:
    """What the display shows, fed by the stats subscribers (Zenoh threads)."""

    updates: int = 0
    loss: float | None = None
    env_steps: int = 0
    episodes: int = 0
    recent_steps: collections.deque = field(default_factory=lambda: collections.deque(maxlen=50))
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_learner(self, stats: LearnerStats, _key: str) -> None:
        with self.lock:
            self.updates = max(self.updates, stats.updates)
            self.loss = stats.loss if stats.loss is not None else self.loss

    def on_episode(self, stats: EpisodeStats, _key: str) -> None:
        with self.lock:
            self.episodes += 1
            self.env_steps += stats.steps
            if not stats.extra.get("expert_guided"):  # the network's episodes, not the expert's
                self.recent_steps.append(stats.steps)


class Launcher:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.run = args.run or time.strftime("run-%Y%m%d-%H%M%S")
        validate_name(self.run, "run name")
        self.paths = RunPaths(Path(args.runs_dir) / self.run)
        self.children: list[Child] = []
        self.listen, self.endpoint = router_endpoints(getattr(args, "listen", None) or (), args.port)
        # checked before the run folder exists: a refused start leaves nothing behind
        make_tls = getattr(args, "tls", False)
        self.secure = secure_files(self.paths.secure, self.run, tls=make_tls or not all(map(_loopback, self.listen)),
                                   make_tls=make_tls, hosts=[socket.gethostname(), *(getattr(args, "host", None) or [])])
        self.paths.make()

    def settings(self, role: str) -> ZenohSettings:
        """How a process of ``role`` joins this run's bus (the launcher's own sessions are viewers)."""
        return ZenohSettings(mode="client", connect=(self.endpoint,), config_file=str(self.secure.config(role)))

    # -- processes ------------------------------------------------------------------------

    def _spawn(self, role: str, name: str, argv: list[str]) -> Child:
        logfile = self.paths.logs / f"{name}.log"
        handle = open(logfile, "ab")
        env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1")
        if self.args.rerun_connect:
            env["COGEXPLORE_RERUN_URL"] = self.args.rerun_connect  # evaluator and actors stream there
        process = subprocess.Popen([sys.executable, "-m", "services.cli", *argv], stdout=handle,
                                   stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                   start_new_session=True, preexec_fn=_die_with_parent)
        handle.close()
        child = Child(role, name, process, logfile)
        self.children.append(child)
        return child

    def _common(self, role: str) -> list[str]:
        return ["--run", self.run, "--runs-dir", str(self.args.runs_dir), "--connect", self.endpoint,
                "--zenoh-mode", "client", "--zenoh-config", str(self.secure.config(role)),
                "--tensorboard" if self.args.tensorboard else "--no-tensorboard"]

    def start(self) -> None:
        a = self.args
        self._spawn("router", "router", ["router", "--listen", ",".join(self.listen),
                                         "--config", str(self.secure.router_config)])
        config = ["--preset", str(self.paths.config)]
        learner_argv = ["learner", *self._common("learner"), *config]
        if a.device:
            learner_argv += ["--device", a.device]
        self._spawn("learner", "learner", learner_argv)
        for i in range(a.actors):
            self._spawn("actor", f"actor-{i}", ["actor", *self._common("actor"), *config, "--actor-id", f"actor-{i}",
                                                "--actor-index", str(i), "--num-actors", str(a.actors)])
        if not a.no_evaluator:
            self._spawn("evaluator", "evaluator", ["evaluator", *self._common("evaluator"), *config,
                                                   "--every-updates", str(a.eval_every)])

    def _alive(self, role: str) -> list[Child]:
        return [c for c in self.children if c.role == role and c.process.poll() is None]

    def stop(self, roles: tuple[str, ...], timeout_s: float = 20.0) -> None:
        """SIGTERM the given roles, wait, then SIGKILL whatever is left."""
        targets = [c for c in self.children if c.role in roles and c.process.poll() is None]
        for c in targets:
            c.process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for c in targets:
            try:
                c.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", c.name, timeout_s)
                c.process.kill()
                c.process.wait()

    # -- the run ---------------------------------------------------------------------------

    def monitor(self, stop: threading.Event) -> str:
        """Show progress until the learner finishes, the time is up or the user stops.
        Returns why it ended: 'done', 'time', 'interrupted' or 'failed: <who>'."""
        a = self.args
        cfg_updates = self.total_updates
        deadline = time.monotonic() + a.minutes * 60 if a.minutes else None
        keys = RunKeys(self.run)
        progress = Progress()
        rejects = RejectCounter("stats message", log)
        with open_session(self.settings("viewer"), wait_s=30.0) as session:
            subs = [subscribe_messages(session, keys.all_stats("learner"), LearnerStats, progress.on_learner, rejects),
                    subscribe_messages(session, keys.all_stats("episode"), EpisodeStats, progress.on_episode, rejects)]
            actors = LivelinessWatch(session, keys.all_alive("actor"))
            bar = tqdm(total=cfg_updates, desc=f"{self.run}", unit="upd", dynamic_ncols=True,
                       disable=a.quiet)
            last_steps, last_t = 0, time.monotonic()
            reason = "done"
            try:
                while True:
                    if stop.is_set():
                        reason = "interrupted"
                        break
                    if deadline is not None and time.monotonic() >= deadline:
                        reason = "time"
                        break
                    learner = [c for c in self.children if c.role == "learner"][0]
                    if learner.process.poll() is not None:
                        reason = "done" if learner.process.returncode == 0 else "failed: learner"
                        break
                    if not self._alive("router"):
                        reason = "failed: router"
                        break
                    stop.wait(1.0)
                    with progress.lock:
                        now = time.monotonic()
                        rate = (progress.env_steps - last_steps) / max(1e-6, now - last_t)
                        last_steps, last_t = progress.env_steps, now
                        mean_steps = (sum(progress.recent_steps) / len(progress.recent_steps)
                                      if progress.recent_steps else 0.0)
                        bar.n = min(progress.updates, cfg_updates)
                        bar.set_postfix_str(
                            f"env {rate:5.0f} st/s | ep {progress.episodes} | steps/ep {mean_steps:5.1f} | "
                            f"loss {progress.loss if progress.loss is not None else float('nan'):.3g} | "
                            f"actors {len(actors.alive)}", refresh=True)
            finally:
                bar.close()
                actors.close()
                for s in subs:
                    s.undeclare()
        return reason

    @property
    def total_updates(self) -> int:
        return self.config.train.total_updates

    def execute(self) -> int:
        a = self.args
        overrides = {"train.total_updates": a.updates} if a.updates else {}
        self.config = resolve_config(a, self.paths)
        if overrides:
            self.config = self.config.with_overrides(overrides)
        save_config(self.config, self.paths)
        stop = threading.Event()
        previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)}
        print(f"run {self.run!r}: router {self.endpoint}, {a.actors} actor(s), logs in {self.paths.logs}",
              file=sys.stderr)
        try:
            self.start()
            reason = self.monitor(stop)
        finally:
            # Order matters: the learner writes its final checkpoint first, then the
            # producers and the evaluator go, the router last.
            self.stop(("learner",), timeout_s=60.0)
            self.stop(("actor", "evaluator"))
            self.stop(("router",))
            for s, handler in previous.items():
                signal.signal(s, handler)
        print(f"run {self.run!r} ended: {reason}", file=sys.stderr)
        if reason.startswith("failed"):
            who = reason.split(": ", 1)[1]
            print(f"see {self.paths.logs / (who + '.log')}", file=sys.stderr)
            return 1
        if not a.no_report:
            return self.final_report()
        return 0

    def final_report(self) -> int:
        """Evaluate the final checkpoint with the test protocol and write the report."""
        a = self.args
        cmd = [sys.executable, "-m", "services.cli"]
        evaluate = cmd + ["evaluate", "--checkpoint", str(self.paths.root),
                          "--episodes-per-start", str(a.final_episodes),
                          "--json", str(self.paths.stats / "final-eval.json"),
                          "--rrd", str(self.paths.recordings / "final-eval.rrd")]
        report = cmd + ["report", str(self.paths.root), "--episodes-per-start", str(a.final_episodes)]
        for argv in (evaluate, report):
            result = subprocess.run(argv, env=dict(os.environ, RERUN_ANALYTICS="0"))
            if result.returncode != 0:
                print(f"{' '.join(argv[3:5])} failed (exit {result.returncode})", file=sys.stderr)
                return result.returncode
        print(f"report: {self.paths.report / 'report.html'} (and report.md)", file=sys.stderr)
        return 0


def _loopback(endpoint: str) -> bool:
    host = endpoint.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")
    return host in ("127.0.0.1", "localhost", "::1")


def router_endpoints(listen: tuple[str, ...] | list[str], port: int | None) -> tuple[tuple[str, ...], str]:
    """(where the router listens, where this machine's processes connect). By default a free
    loopback port; with ``--listen``, those endpoints (TLS wherever they leave the machine) and the
    first one's port on localhost."""
    if not listen:
        endpoint = f"tcp/127.0.0.1:{port or free_tcp_port()}"
        return (endpoint,), endpoint
    endpoints = parse_endpoints(list(listen), "--listen")
    for e in endpoints:
        if not _loopback(e) and not e.startswith("tls/"):
            raise SecurityError(f"--listen {e}: a router reachable from other machines listens with TLS only "
                                f"(--listen tls/{e.split('/', 1)[1]})")
    protocol, address = endpoints[0].split("/", 1)
    return endpoints, f"{protocol}/localhost:{address.rsplit(':', 1)[1]}"


def secure_files(root: Path, run: str, tls: bool, *, make_tls: bool = False, hosts: Sequence[str] = ()) -> SecureFiles:
    """The run's security folder: made now on first use (credentials and access control, and with
    ``make_tls`` certificates for ``hosts``), refused when TLS is needed and it has none."""
    files = SecureFiles(root)
    if not files.credentials.exists():
        if tls and not make_tls:
            raise SecurityError(f"a router that listens beyond this machine needs TLS certificates: pass --tls "
                                f"(--host NAME for a name other machines use), or run `cogexplore secure init {root} "
                                "--tls --host <this machine's name>` first")
        init_secure(root, run, tls=make_tls, hosts=hosts if make_tls else ())
    return files.check(run, tls=tls)


def run_up_command(args: argparse.Namespace) -> int:
    setup_logging("WARNING")
    if args.actors < 1:
        raise ConfigError(f"--actors must be >= 1, got {args.actors}")
    return Launcher(args).execute()
