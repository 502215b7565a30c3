"""``cogexplore up``: the embedded default. Router, learner, N actors and the evaluator as
separate local processes, one progress display, an orderly stop, everything in runs/<run>/.

It is the local twin of docker-compose.yml: the same services, started with the same
command lines, meeting at one Zenoh router.

The bus is closed to everyone but the run's own services (services.bus.security): the first ``up``
of a run writes ``runs/<run>/secure/`` (a user and password per role, the access control list), the
router loads its config and every process its role's. On loopback the links are plain TCP (TLS
once the folder has certificates: its access control then admits every role over TLS only); a
router that listens beyond the machine (``--listen tls/0.0.0.0:7447``) needs the folder with TLS
certificates: ``--tls`` makes it so (for this machine's name and any ``--host``), as does ``cogexplore
secure init runs/<run>/secure --tls --host <name>``; ``up`` refuses to start without them, or with a
plain TCP endpoint there.

The progress line (:func:`progress_line`) says what limits the run, from what the services report:
the learner's share of time waiting for data (``LearnerStats.WAITING_SHARE``) and the actors' time
held by its flow control (``EpisodeStats.HELD_S``). A run that exists resumes from its newest
checkpoint and says so; one whose learner already reached ``train.total_updates`` is refused unless
``--resume`` (its report is made again) or ``--fresh`` (the old folder is renamed, never deleted).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
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

from services.bus import ENV_LISTEN
from services.bus.security import SecureFiles, SecurityError, init_secure
from services.bus.session import (
    LivelinessWatch,
    TransportError,
    ZenohSettings,
    endpoint_host_port,
    free_tcp_port,
    open_session,
    parse_endpoints,
    port_taken,
    subscribe_messages,
)
from services.process import setup_logging, stop_signals_handled
from services.runs import RunLock, RunPaths, resolve_config, save_config, saved_config
from shared.config import RunConfig
from shared.errors import CogexploreError
from shared.learning.divergence import sets_lr
from shared.learning.stats import LearnerRow, read_csv_records
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
    log_start: int = 0
    """Where this process's output begins in ``logfile`` (a resumed run's logs are appended to)."""
    sent: signal.Signals | None = None
    """The last signal the launcher sent it to stop it: SIGTERM, then SIGKILL where it did not stop in time."""
    kill_asked: bool = False
    """Killed at a second stop signal: the user asked for it, up said so."""
    said: bool = False
    """Its exit was said while the run went on."""

    def send(self, signum: signal.Signals) -> None:
        """Send it ``signum`` to stop it, and remember it (how it ended is judged by what it was sent)."""
        self.sent = signum
        self.process.send_signal(signum)

    def ended_while_starting(self) -> bool:
        """Ended by up's SIGTERM before its own handler was in place (a service stops cleanly on it
        once it is): stopped while it was still starting, nothing of its work lost."""
        return self.sent == signal.SIGTERM and self.process.returncode == -signal.SIGTERM

    def exited(self) -> str | None:
        """None while the process runs; else its exit code and the last line it logged."""
        code = self.process.poll()
        if code is None:
            return None
        try:
            with open(self.logfile, "rb") as f:
                f.seek(self.log_start)
                lines = f.read().decode(errors="replace").strip().splitlines()
        except OSError:
            lines = []
        how = f"exited ({code})" if code >= 0 else f"was ended by {_signal_name(-code)}"
        return f"its {self.name} {how}: {lines[-1] if lines else 'no output'} (see {self.logfile})"


def _signal_name(signum: int) -> str:
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


LEARNER_WAITS = 0.1
"""From this share of its time waiting for data (no update due) the learner is fed too slowly: the
actors are the limit. Below it the learner nearly always has an update due."""
ACTORS_HELD = 0.2
"""From this share of their episodes' time held by flow control the actors wait for the learner."""
LEARNER_SILENT_S = 15.0
"""Seconds without a word from the learner (it reports every second, also while it waits for data)
from which the progress line says it is silent: stopped (SIGSTOP, a laptop asleep), stuck, or cut off."""
HELD_WINDOW_S = 60.0
"""The actors' held share is taken over the episodes that ended this long ago at most."""
ETA_AFTER_S = 60.0
"""Seconds of learning (warm-up excluded) before the end time is estimated: earlier rates still
include the first, slower updates (weights sent, caches warming)."""
ETA_AFTER_SHARE = 0.05
"""...or this share of the session's updates, whichever comes first (short runs)."""


@dataclass(frozen=True)
class ProgressFigures:
    """One moment of a run, as the progress line shows it: plain numbers, so the line can be made
    (:func:`progress_line`) and tested without a bus or a clock."""

    updates: int
    """Learner updates so far (the run's, across resumes)."""
    total_updates: int
    """Where the learner stops (``train.total_updates``)."""
    transitions_received: int | None
    """Transitions the learner holds an account of (None: no learner statistics yet)."""
    warmup_transitions: int
    """Transitions the learner needs before its first update (``train.warmup_transitions``, at least a batch)."""
    learning_s: float | None
    """Seconds since this session's learner made its first update (None: not yet)."""
    learning_updates: int
    """Updates since then."""
    learning_goal: int
    """Updates this session had left to make when learning began (what :data:`ETA_AFTER_SHARE` is a share of)."""
    waiting_share: float | None
    """The learner's recent share of time waiting for data (LearnerStats.WAITING_SHARE; None: not reported)."""
    held_share: float | None
    """The share of the actors' recent episodes' time they were held by flow control (EpisodeStats.HELD_S;
    None: no episode of theirs ended since learning began, or none reported it)."""
    env_steps: int
    """Environment steps of the episodes finished so far (all actors)."""
    env_s: float | None
    """Seconds since the first finished episode began (None: none finished yet)."""
    episodes: int
    mean_steps: float | None
    """Mean length of the network's recent episodes (expert-guided ones left out)."""
    loss: float | None
    actors_alive: int
    clock_s: float
    """The wall clock now (``time.time()``): the end time is shown in local time."""
    time_left_s: float | None = None
    """Seconds until ``--minutes`` stops the run (None: no time limit)."""
    label_agreement: float | None = None
    """Share of the learner's recent labelled samples whose greedy command is the label (None: no labels)."""
    replay_size: int | None = None
    """Transitions in the learner's replay memory (None: not reported); what the warm-up fills, which
    after a resume without its memory is not the transitions count."""
    safe_agreement: float | None = None
    """Share of the learner's recent safe-set marked samples whose greedy command keeps a way out (None: no marks)."""
    learner_silent_s: float | None = None
    """Seconds since the learner's last report (None: no report yet)."""


def limiter(f: ProgressFigures) -> str:
    """What holds the run back now: the warm-up, the learner or the actors; or a learner gone silent."""
    if f.transitions_received is None:
        return "starting: waiting for the learner"
    if f.learner_silent_s is not None and f.learner_silent_s >= LEARNER_SILENT_S:
        return f"learner silent for {_duration(f.learner_silent_s)}: stopped or stuck?"
    if f.learning_s is None:
        filled = f.transitions_received if f.replay_size is None else f.replay_size
        return f"warm-up: filling replay {min(filled, f.warmup_transitions)}/{f.warmup_transitions}"
    if f.updates >= f.total_updates:
        return "finishing: final checkpoint"
    if f.actors_alive == 0:
        return "no actor alive: the learner waits"
    if f.waiting_share is not None and f.waiting_share >= LEARNER_WAITS:
        return f"actor-bound: the learner waits for data {f.waiting_share:.0%} of the time"
    if f.held_share is not None and f.held_share >= ACTORS_HELD:
        return f"learner-bound: actors held by flow control {f.held_share:.0%} of the time"
    if f.waiting_share is None:
        return "learning"
    if f.held_share is None:  # the actors' word comes when their episodes end
        return "learner-bound: the learner never waits for data"
    return "balanced: the learner never waits, the actors are not held"


def _duration(seconds: float) -> str:
    seconds = max(0, round(seconds))
    if seconds >= 3600:
        return f"{seconds // 3600}h{seconds % 3600 // 60:02d}m"
    if seconds >= 60:
        return f"{seconds // 60}m{seconds % 60:02d}s"
    return f"{seconds}s"


def eta(f: ProgressFigures) -> str:
    """The estimated end of training, from the updates/s since learning began (warm-up excluded),
    once there are :data:`ETA_AFTER_S` seconds or :data:`ETA_AFTER_SHARE` of the updates to go by."""
    enough = f.learning_s is not None and f.learning_updates > 0 and (
        f.learning_s >= ETA_AFTER_S or f.learning_updates >= ETA_AFTER_SHARE * max(1, f.learning_goal))
    left_s = (max(0, f.total_updates - f.updates) * f.learning_s / f.learning_updates) if enough else None
    if f.time_left_s is not None and (left_s is None or f.time_left_s < left_s):  # --minutes ends it first
        left_s = max(0.0, f.time_left_s)
        return f"ends ~{time.strftime('%H:%M', time.localtime(f.clock_s + left_s))} ({_duration(left_s)} left, --minutes)"
    if left_s is None:
        return "ETA after the first minute"
    return f"ends ~{time.strftime('%H:%M', time.localtime(f.clock_s + left_s))} ({_duration(left_s)} left)"


def progress_line(f: ProgressFigures) -> str:
    """The text beside the bar: limiter | env steps/s over the run | episodes | loss | [label agreement |]
    [safe agreement |]
    actors | ETA."""
    env = f"{f.env_steps / f.env_s:.0f}" if f.env_s else "-"
    steps = f"{f.mean_steps:.1f}" if f.mean_steps is not None else "-"
    loss = f"{f.loss:.3g}" if f.loss is not None else "-"
    label = "" if f.label_agreement is None else f"label {f.label_agreement:.2f} | "
    label += "" if f.safe_agreement is None else f"safe {f.safe_agreement:.2f} | "
    return (f"{limiter(f)} | env {env} st/s avg | ep {f.episodes} | steps/ep {steps} | loss {loss} | {label}"
            f"actors {f.actors_alive} | {eta(f)}")


@dataclass
class Progress:
    """What the display shows, fed by the stats subscribers (Zenoh threads); ``now`` (monotonic
    seconds) is for tests, the callbacks read the clock."""

    total_updates: int
    warmup_transitions: int
    updates: int = 0
    loss: float | None = None
    label_agreement: float | None = None
    safe_agreement: float | None = None
    transitions_received: int | None = None
    replay_size: int | None = None
    session_first_updates: int | None = None
    """The updates of this session's first learner report (a resumed run's starting point)."""
    learning_since: tuple[float, int] | None = None
    """(time, updates) when this session's updates first advanced."""
    waiting: collections.deque = field(default_factory=lambda: collections.deque(maxlen=10))
    held: collections.deque = field(default_factory=lambda: collections.deque(maxlen=500))
    """(time, held_s, duration_s) of the episodes that reported their time held by flow control."""
    env_steps: int = 0
    env_since: float | None = None
    episodes: int = 0
    recent_steps: collections.deque = field(default_factory=lambda: collections.deque(maxlen=50))
    learner_heard: float | None = None
    """When the learner's last report came (monotonic seconds)."""
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_learner(self, stats: LearnerStats, _key: str = "", now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self.lock:
            self.learner_heard = now
            if self.session_first_updates is None:
                self.session_first_updates = stats.updates
            elif self.learning_since is None and stats.updates > self.session_first_updates:
                self.learning_since = (now, stats.updates)
            self.updates = max(self.updates, stats.updates)
            self.transitions_received = stats.transitions_received
            self.replay_size = stats.replay_size
            self.loss = stats.loss if stats.loss is not None else self.loss
            self.label_agreement = stats.extra.get("label_agreement", self.label_agreement)
            self.safe_agreement = stats.extra.get("safe_agreement", self.safe_agreement)
            share = stats.extra.get(LearnerStats.WAITING_SHARE)
            if share is not None:  # ~10 s of reports: one slow update does not flip the label
                self.waiting.append(share)

    def on_episode(self, stats: EpisodeStats, _key: str = "", now: float | None = None) -> None:
        now = time.monotonic() if now is None else now
        with self.lock:
            if self.env_since is None:  # the clock starts when the first episode began, not when it ended
                self.env_since = now - stats.duration_s
            self.episodes += 1
            self.env_steps += stats.steps
            held_s = stats.extra.get(EpisodeStats.HELD_S)
            if held_s is not None:
                self.held.append((now, held_s, stats.duration_s))
            if not stats.extra.get("expert_guided"):  # the network's episodes, not the expert's
                self.recent_steps.append(stats.steps)

    def figures(self, actors_alive: int, now: float | None = None, clock_s: float | None = None) -> ProgressFigures:
        now = time.monotonic() if now is None else now
        with self.lock:
            since = self.learning_since
            # episodes that ended before learning began say nothing of the learner's pace
            recent = [(h, d) for t, h, d in self.held if since is not None and t >= max(since[0], now - HELD_WINDOW_S)]
            held_time = sum(d for _, d in recent)
            return ProgressFigures(
                updates=self.updates, total_updates=self.total_updates,
                transitions_received=self.transitions_received, replay_size=self.replay_size,
                warmup_transitions=self.warmup_transitions,
                learning_s=None if since is None else now - since[0],
                learning_updates=0 if since is None else self.updates - since[1],
                learning_goal=0 if since is None else self.total_updates - since[1],
                waiting_share=sum(self.waiting) / len(self.waiting) if self.waiting else None,
                held_share=min(1.0, sum(h for h, _ in recent) / held_time) if held_time > 0 else None,
                env_steps=self.env_steps, env_s=None if self.env_since is None else max(1e-9, now - self.env_since),
                episodes=self.episodes,
                mean_steps=sum(self.recent_steps) / len(self.recent_steps) if self.recent_steps else None,
                loss=self.loss, actors_alive=actors_alive, clock_s=time.time() if clock_s is None else clock_s,
                label_agreement=self.label_agreement, safe_agreement=self.safe_agreement,
                learner_silent_s=None if self.learner_heard is None else now - self.learner_heard)


class Launcher:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.run = args.run or time.strftime("run-%Y%m%d-%H%M%S")
        validate_name(self.run, "run name")
        self.paths = RunPaths(Path(args.runs_dir) / self.run)
        self.children: list[Child] = []
        # A run whose security folder has certificates admits every role over TLS only, loopback included.
        tls = getattr(args, "tls", False) or (not getattr(args, "fresh", False) and SecureFiles(self.paths.secure).tls)
        self.listen, self.endpoint = router_endpoints(getattr(args, "listen", None) or (), args.port, tls=tls)
        if getattr(args, "resume", False) and not self.paths.root.exists():
            raise RunStateError(f"--resume: there is no run {self.run!r} in {args.runs_dir} to resume")
        self.report_only = getattr(args, "report_only", False)
        if self.report_only:
            refuse_training_options(args)
            if not self.paths.root.exists():
                raise RunStateError(f"--report-only: there is no run {self.run!r} in {args.runs_dir} to report on")
        self.lock = RunLock(self.paths, "up")  # before anything in the run folder is touched, --fresh included
        self.learner_lock: RunLock | None = None
        try:
            self.config = self._config()  # a bad option is refused before the folder changes, --fresh's move too
            if self.report_only:
                # Held while the report is made: a learner still training would rotate away the checkpoints
                # being averaged, and one started meanwhile is refused (its own RunLock).
                self.learner_lock = RunLock(self.paths, "learner")
            else:
                self._check_learner_free()
                self._check_ports()  # a refused start leaves no run folder behind, nor moves one aside
                self._prepare_folder()
        except BaseException:
            self.close()
            raise

    def _config(self) -> RunConfig:
        """The run's config: --preset, else the run's own (not with --fresh: it goes with the old
        run), else the default; with --set, --device, --updates and room for the final average."""
        a = self.args
        config = resolve_config(a, None if getattr(a, "fresh", False) else self.paths)
        overrides = {"train.total_updates": a.updates} if a.updates is not None else {}
        if config.train.keep_checkpoints < a.final_average:  # the final model averages them
            overrides["train.keep_checkpoints"] = a.final_average
        return config.with_overrides(overrides) if overrides else config

    def _check_learner_free(self) -> None:
        """RunInUseError when a learner of the run runs outside up (started by hand, or one of a killed `up`
        still writing its final checkpoint): refused before the run's config is replaced under it and a
        router and actors are started for a learner of up's own that could only fail."""
        RunLock(self.paths, "learner").release()  # up's own learner takes it when it starts

    def close(self) -> None:
        """Let go of the run (another `up` may start it); :meth:`execute` does at its end."""
        if self.learner_lock is not None:
            self.learner_lock.release()
        self.lock.release()

    def _prepare_folder(self) -> None:
        args = self.args
        moved_to = None
        if getattr(args, "fresh", False) and self.paths.root.exists():
            # A learner of the run started outside up would write its last checkpoint into the new run.
            learner_lock = RunLock(self.paths, "learner")
            try:
                moved_to = move_aside(self.paths.root)
            finally:
                learner_lock.release()
        # checked before the run folder exists: a refused start leaves nothing behind
        make_tls = getattr(args, "tls", False)
        try:
            self.secure = secure_files(self.paths.secure, self.run,
                                       tls=make_tls or not all(map(_loopback, self.listen)), make_tls=make_tls,
                                       hosts=[socket.gethostname(), *(getattr(args, "host", None) or [])])
        except SecurityError:
            if moved_to is not None:  # refused: the old run is where it was
                moved_to.rename(self.paths.root)
            raise
        if moved_to is not None:
            print(f"--fresh: the old run {self.run!r} is now {moved_to} (delete it when you no longer need it)",
                  file=sys.stderr)
        self.paths.make()

    def settings(self, role: str) -> ZenohSettings:
        """How a process of ``role`` joins this run's bus (the launcher's own sessions are viewers)."""
        return ZenohSettings(mode="client", connect=(self.endpoint,), config_file=str(self.secure.config(role)))

    # -- processes ------------------------------------------------------------------------

    def _spawn(self, role: str, name: str, argv: list[str]) -> Child:
        logfile = self.paths.logs / f"{name}.log"
        env = self.service_environment()
        with open(logfile, "ab") as handle:  # the child has its own copy: ours goes, the start failed or not
            log_start = handle.seek(0, os.SEEK_END)
            process = subprocess.Popen([sys.executable, "-m", "services.cli", *argv], stdout=handle,
                                       stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env,
                                       start_new_session=True, preexec_fn=_die_with_parent)
        child = Child(role, name, process, logfile, log_start)
        self.children.append(child)
        return child

    def service_environment(self) -> dict[str, str]:
        """The environment every service starts with: this one's, offline (no Rerun analytics), unbuffered.
        docker-compose.yml and the Dockerfile set the same (tests/test_compose.py)."""
        env = dict(os.environ, RERUN_ANALYTICS="0", PYTHONUNBUFFERED="1")
        # Only the router listens: a shell's COGEXPLORE_ZENOH_LISTEN (a compose setting) would have every
        # service bind that one endpoint, and all but the first fail.
        env.pop(ENV_LISTEN, None)
        if self.args.rerun_connect:
            env["COGEXPLORE_RERUN_URL"] = self.args.rerun_connect  # evaluator and actors stream there
        return env

    def _common(self, role: str) -> list[str]:
        return ["--run", self.run, "--runs-dir", str(self.args.runs_dir), "--connect", self.endpoint,
                "--zenoh-mode", "client", "--zenoh-config", str(self.secure.config(role)),
                "--tensorboard" if self.args.tensorboard else "--no-tensorboard"]

    def _check_ports(self) -> None:
        """TransportError naming a router endpoint something else holds (else the progress session would
        wait on whatever holds it)."""
        for endpoint in self.listen:
            if (taken := port_taken(endpoint)) is not None:
                raise TransportError(f"the router cannot listen on {endpoint}: {taken}. Another router or "
                                     "`cogexplore up`? Stop it, or choose another port (--listen, --port)")

    def start(self) -> None:
        for role, name, argv in self.service_argvs():
            self._spawn(role, name, argv)

    def service_argvs(self) -> list[tuple[str, str, list[str]]]:
        """(role, name, ``cogexplore`` arguments) of each service :meth:`start` starts, in order: the
        services of docker-compose.yml, which tests/test_compose.py holds to the same options."""
        a = self.args
        services = [("router", "router", ["router", "--listen", ",".join(self.listen),
                                          "--config", str(self.secure.router_config)])]
        config = ["--preset", str(self.paths.config)]
        learner_argv = ["learner", *self._common("learner"), *config]
        if a.device:
            learner_argv += ["--device", a.device]
        if sets_lr(getattr(a, "overrides", None)):  # in its config too; said again as the user's choice, kept after a divergence
            learner_argv += ["--set", f"dqn.lr={self.config.dqn.lr!r}"]
        services.append(("learner", "learner", learner_argv))
        for i in range(a.actors):
            services.append(("actor", f"actor-{i}", ["actor", *self._common("actor"), *config, "--actor-id",
                                                     f"actor-{i}", "--actor-index", str(i), "--num-actors",
                                                     str(a.actors)]))
        if not a.no_evaluator:
            services.append(("evaluator", "evaluator", ["evaluator", *self._common("evaluator"), *config,
                                                        "--every-updates", str(a.eval_every)]))
        return services

    def _alive(self, role: str) -> list[Child]:
        return [c for c in self.children if c.role == role and c.process.poll() is None]

    def stop(self, roles: tuple[str, ...], timeout_s: float = 20.0) -> None:
        """SIGTERM the given roles, wait, then SIGKILL whatever is left."""
        targets = [c for c in self.children if c.role in roles and c.process.poll() is None]
        for c in targets:
            c.send(signal.SIGTERM)
        deadline = time.monotonic() + timeout_s
        for c in targets:
            try:
                c.process.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log.warning("%s did not stop in %.0f s: killing it", c.name, timeout_s)
                c.send(signal.SIGKILL)
                c.process.wait()

    def stop_services(self) -> None:
        """Stop the run's services in order: the learner first (it writes its final checkpoint, up to a
        minute), then the producers and the evaluator, the router last. How they ended:
        :meth:`failed_at_stop`."""
        self.stop(("learner",), timeout_s=60.0)
        self.stop(("actor", "evaluator"))
        self.stop(("router",))

    def failed_at_stop(self) -> list[str]:
        """The services that failed at a stop asked by their starter (:meth:`stop_services`), each said
        in one line: the learner whose final checkpoint is missing or torn, an actor or the evaluator
        that crashed on its way out (up's own judgement, :meth:`finish`). For the tools that start and stop
        a run's services themselves (``bench system``, ``bench fuzz``); a service whose exit they said
        already (``Child.said``) is left out."""
        # stopped on the tool's own clock, as up's --minutes stops it
        learner = [c.name for c in self.children if c.role == "learner"] if self._final_checkpoint_failed() else []
        return learner + self._stop_failed()

    # -- the run ---------------------------------------------------------------------------

    def monitor(self, stop: threading.Event) -> str:
        """Show progress until the learner finishes, the time is up or the user stops.
        Returns why it ended: 'done', 'time', 'interrupted' or 'failed: <who>'."""
        a = self.args
        cfg_updates = self.total_updates
        deadline = time.monotonic() + a.minutes * 60 if a.minutes else None
        keys = RunKeys(self.run)
        # the learner's first update waits for both (shared.learning.learner.LearnerCore.updates_due)
        progress = Progress(cfg_updates, max(self.config.train.warmup_transitions, self.config.dqn.batch_size))
        rejects = RejectCounter("stats message", log)
        router = next(c for c in self.children if c.role == "router")
        # a router that could not start (its port taken, a bad config) says why in its log at once
        with open_session(self.settings("viewer"), wait_s=30.0, give_up=router.exited) as session:
            subs = [subscribe_messages(session, keys.all_stats("learner"), LearnerStats, progress.on_learner, rejects),
                    subscribe_messages(session, keys.all_stats("episode"), EpisodeStats, progress.on_episode, rejects)]
            actors = LivelinessWatch(session, keys.all_alive("actor"))
            # tqdm's own rate and remaining time would count the warm-up: progress_line has the estimate
            bar = tqdm(total=cfg_updates, desc=f"{self.run}", unit="upd", dynamic_ncols=True, disable=a.quiet,
                       bar_format="{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} upd [{elapsed}{postfix}]")
            reason = "done"
            learner_silent = False
            try:
                while True:
                    if stop.is_set():
                        reason = "interrupted"
                        break
                    if deadline is not None and time.monotonic() >= deadline:
                        reason = "time"
                        break
                    learner = next(c for c in self.children if c.role == "learner")
                    if learner.process.poll() is not None:
                        reason = "done" if learner.process.returncode == 0 else "failed: learner"
                        reached = checkpoint_updates(self.paths) or 0
                        if reason == "done" and reached < cfg_updates:  # stopped by someone else
                            print(f"run {self.run!r}: its learner stopped at update {reached} of {cfg_updates}",
                                  file=sys.stderr)
                            reason = "failed: learner"
                        learner.said = reason != "done"  # the run's failure names it (finish)
                        break
                    if not self._alive("router"):
                        reason = "failed: router"
                        break
                    if not self._alive("actor") and not actors.alive:  # none here, none joined from elsewhere
                        last = max((c for c in self.children if c.role == "actor"), key=lambda c: c.process.returncode)
                        reason = f"failed: {last.name}"  # the learner would wait for transitions forever
                        break
                    for c in self.children:
                        if c.role in ("actor", "evaluator") and not c.said and (why := c.exited()):
                            c.said = True
                            # the evaluator's figures are a curve: the final evaluation is up's own
                            goes_on = ("without its curve" if c.role == "evaluator" else
                                       f"with {len(self._alive('actor'))} actor(s) of this machine")
                            bar.write(f"{why}; training goes on {goes_on}", file=sys.stderr)
                    stop.wait(1.0)
                    figures = progress.figures(len(actors.alive))
                    silent = figures.learner_silent_s is not None and figures.learner_silent_s >= LEARNER_SILENT_S
                    if silent != learner_silent:  # said once each way: the bar alone may not be on screen
                        learner_silent = silent
                        bar.write(f"run {self.run!r}: its learner " + (
                            f"has said nothing for {LEARNER_SILENT_S:.0f} s: stopped or stuck? (its log: "
                            f"{learner.logfile})" if silent else "reports again"), file=sys.stderr)
                    if deadline is not None:
                        figures = dataclasses.replace(figures, time_left_s=deadline - time.monotonic())
                    bar.n = min(figures.updates, cfg_updates)
                    bar.set_postfix_str(progress_line(figures), refresh=True)
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
        try:
            return self._execute()
        finally:
            self.close()

    def _execute(self) -> int:
        a = self.args
        if self.report_only:
            done = checkpoint_updates(self.paths)
            if not done:  # none, or the learner's at update 0 (stopped in its warm-up)
                raise RunStateError(f"--report-only: run {self.run!r} has no trained checkpoint yet "
                                    f"({self.paths.checkpoints})")
            print(f"run {self.run!r}: the final evaluation and report of its training so far ({done} updates)",
                  file=sys.stderr)
            return self.final_report()
        done = checkpoint_updates(self.paths, self.config)
        finished = done is not None and done >= self.total_updates
        if finished and not getattr(a, "resume", False):
            raise RunStateError(
                f"run {self.run!r} has finished: its learner reached {done}/{self.total_updates} updates "
                f"({self.paths.checkpoints}); --resume redoes its final evaluation and report (with --updates N "
                f"above {done} it trains on to N), --fresh moves it aside to {self.paths.root.name}.old-<time> "
                "and starts over")
        if not finished:
            check_learner_sources(self.run, self.config, saved_config(self.paths) if done is not None else None)
        save_config(self.config, self.paths)
        if finished:
            print(f"run {self.run!r} has finished training ({done}/{self.total_updates} updates)"
                  + ("" if a.no_report else ": redoing its final evaluation and report"), file=sys.stderr)
            return 0 if a.no_report else self.final_report()
        if done is not None:
            print(resume_line(self.run, self.paths, done, self.total_updates), file=sys.stderr)
        stop = threading.Event()
        print(f"run {self.run!r}: router {self.endpoint}, {a.actors} actor(s), logs in {self.paths.logs}",
              file=sys.stderr)

        stopping = threading.Event()  # the monitor has ended: the services are being stopped
        said_stopping = threading.Event()

        def say_stopping() -> None:
            if said_stopping.is_set():  # a signal between the monitor's end and the stop said it already
                return
            said_stopping.set()
            if any(c.role == "learner" and c.process.poll() is None for c in self.children):
                print(f"run {self.run!r}: stopping: its learner writes its final checkpoint (Ctrl-C again "
                      "to stop at once without it)", file=sys.stderr)
            else:  # it has ended (done, failed): only the others are left to stop
                print(f"run {self.run!r}: stopping its services (Ctrl-C again to stop them at once)", file=sys.stderr)

        def on_stop_signal(signum: int, _frame: object) -> None:
            if not stop.is_set():
                stop.set()
                if stopping.is_set():  # the run stops already (--minutes, its learner done): say it was heard
                    say_stopping()
                return
            # asked again while the learner writes its final checkpoint (up to a minute): now, without it
            print(f"run {self.run!r}: {_signal_name(signum)} again: killing its services now (the last checkpoint "
                  "saved stays)", file=sys.stderr)
            for c in self.children:
                if c.process.poll() is None:
                    c.kill_asked = True
                    c.send(signal.SIGKILL)

        with stop_signals_handled(on_stop_signal):
            try:
                self.start()
                reason = self.monitor(stop)
            finally:
                # Order matters: the learner writes its final checkpoint first, then the
                # producers and the evaluator go, the router last.
                stopping.set()
                if stop.is_set():
                    say_stopping()
                self.stop_services()
        print(f"run {self.run!r} ended: {reason}", file=sys.stderr)
        return self.finish(reason)

    def finish(self, reason: str) -> int:
        """What follows the services' stop: how they ended said where it went wrong, the final evaluation
        and report, and up's exit status (``reason``: :meth:`monitor`'s)."""
        a = self.args
        # A learner stopped here (Ctrl-C, --minutes, its actors gone) writes its final checkpoint on its
        # way out: a non-zero exit then means that checkpoint is missing or torn, whatever the reason.
        final_failed = self._final_checkpoint_failed()
        if reason.startswith("failed"):
            who = reason.split(": ", 1)[1]
            child = next((c for c in self.children if c.name == who), None)
            why = child.exited() if child is not None else None
            print(why or f"see {self.paths.logs / (who + '.log')}", file=sys.stderr)
            return 1  # the others' exits at the stop would only echo this failure (a router gone takes them all)
        stop_failed = self._stop_failed()
        if a.no_report:
            return 1 if final_failed or stop_failed else 0
        if not checkpoint_updates(self.paths):  # none, or the learner's at update 0 (stopped in its warm-up)
            print(f"run {self.run!r} has no trained checkpoint yet: no final evaluation or report", file=sys.stderr)
            return 130 if reason == "interrupted" else 1
        if final_failed:
            print(f"run {self.run!r}: the final evaluation and report are of its last checkpoint that was saved",
                  file=sys.stderr)
        code = self.final_report()
        return code or (1 if final_failed or stop_failed else 0)

    def _final_checkpoint_failed(self) -> bool:
        """Whether the learner, stopped by up, exited other than cleanly (said in one line)."""
        learner = next((c for c in self.children if c.role == "learner"), None)
        if learner is None or learner.said or learner.process.returncode == 0:
            return False  # a learner that failed on its own is said as the run's failure
        if learner.ended_while_starting():
            return False  # no update yet: a checkpoint to write, none to lose
        print(f"run {self.run!r}: its final checkpoint failed: {learner.exited()}", file=sys.stderr)
        return True

    def _stop_failed(self) -> list[str]:
        """The actors and the evaluator that failed at the run's stop; each that did not end as asked is
        said in one line. A crash on its way out (a non-zero exit, a signal up did not send) fails the run:
        the evaluator's last evaluation, an actor's statistics or recording may be missing or torn. Up's own
        SIGKILL after the grace period does not: the learner, stopped first, has its final checkpoint, and
        what a hung service loses (its episode or evaluation in progress) a clean stop drops as well."""
        failed: list[str] = []
        for c in self.children:
            code = c.process.returncode
            if c.role not in ("actor", "evaluator") or c.said or not code or c.kill_asked:
                continue  # running on (not stopped), fine, said while the run went on, or killed as the user asked
            if c.ended_while_starting():
                continue
            if c.sent == signal.SIGKILL and code == -signal.SIGKILL:
                print(f"run {self.run!r}: at its stop {c.exited()}; up killed it, it did not stop in time "
                      "(the run does not fail for it)", file=sys.stderr)
                continue
            print(f"run {self.run!r}: at its stop {c.exited()}", file=sys.stderr)
            failed.append(c.name)
        return failed

    def final_model(self) -> Path:
        """What the final evaluation and report play: the mean of the run's last ``--final-average``
        trained checkpoints' weights (a DQN's greedy policy swings from one checkpoint to the next, their
        mean much less: MODEL_CARD.md), exported as ``<run>/<run>-mean<K>.safetensors`` by ``model
        export``; the run folder itself (its latest checkpoint) when there is one checkpoint only."""
        from shared.learning.checkpoints import CheckpointManager

        manager = CheckpointManager(self.paths.checkpoints)
        # A learner stopped in its warm-up saves its untrained network at update 0 and a resumed run
        # keeps it among its last K: averaged in, it would pull the final model towards random weights.
        trained = [p for p in manager.checkpoints() if p != manager.path_for(0)]
        last = trained[-self.args.final_average:]
        if len(last) < 2:  # none (the report says so) or one
            return self.paths.root
        out = self.paths.root / f"{self.run}-mean{len(last)}.safetensors"
        code = _cli(["model", "export", *map(str, last), "--out", str(out)], stdout=subprocess.DEVNULL)
        if code != 0:
            raise RunStateError(f"`model export` of the last {len(last)} checkpoints failed (exit {code})")
        print(f"final model: the mean of {', '.join(p.name for p in last)} ({out})", file=sys.stderr)
        return out

    def final_report(self) -> int:
        """Evaluate the final model (:meth:`final_model`) with the test protocol and write the report.
        A stop signal meanwhile ends it (the child it runs goes with it) with a line saying how to
        redo it, and exit status 128 + the signal's number (it ended without a word)."""

        def stopped(signum: int, _frame: object) -> None:
            print(f"run {self.run!r}: {signal.Signals(signum).name} during the final evaluation and report; "
                  f"`cogexplore up --run {self.run} --resume` redoes them", file=sys.stderr)
            raise SystemExit(128 + signum)  # subprocess.run kills its child on the way out

        with stop_signals_handled(stopped):
            return self._final_report()

    def _final_report(self) -> int:
        a = self.args
        model = str(self.final_model())
        # the services have stopped: evaluation and report have the machine to themselves (--threads 0: every core)
        evaluate = ["evaluate", "--checkpoint", model, "--episodes-per-start", str(a.final_episodes),
                    "--threads", "0", "--json", str(self.paths.stats / "final-eval.json"),
                    "--rrd", str(self.paths.recordings / "final-eval.rrd")]
        # the new model beside the shipped one (and the baselines, and the paper's figures)
        report = ["report", str(self.paths.root), "--model", model, "--episodes-per-start", str(a.final_episodes),
                  "--compare", "pretrained", "--threads", "0"]
        for argv in (evaluate, report):
            code = _cli([*argv, "--quiet"] if a.quiet else argv)
            if code != 0:
                print(f"{' '.join(argv[:2])} failed (exit {code})", file=sys.stderr)
                return code
        print(f"report: {self.paths.report / 'report.html'} (and report.md)", file=sys.stderr)
        return 0


def _cli(argv: list[str], stdout: int | None = None) -> int:
    """Run ``cogexplore ARGV`` in a child process (offline: no Rerun analytics); its exit status."""
    return subprocess.run([sys.executable, "-m", "services.cli", *argv], check=False, stdout=stdout,
                          env=dict(os.environ, RERUN_ANALYTICS="0"), preexec_fn=_die_with_parent).returncode


def refuse_training_options(args: argparse.Namespace) -> None:
    """RunStateError naming the options ``--report-only`` would ignore (it trains nothing and starts no
    service): given, they would read as having been applied."""
    given = [flag for flag, value in (("--updates", args.updates), ("--minutes", args.minutes),
                                      ("--preset", args.preset), ("--set", args.overrides),
                                      ("--device", args.device), ("--listen", args.listen), ("--tls", args.tls),
                                      ("--host", args.host), ("--port", args.port),
                                      ("--no-evaluator", args.no_evaluator), ("--no-report", args.no_report),
                                      ("--rerun-connect", args.rerun_connect)) if value]
    if given:
        raise RunStateError(f"--report-only trains nothing and starts no service: {', '.join(given)} "
                            f"would do nothing with it")


class RunStateError(CogexploreError):
    """The run folder is not what the options take it for (finished without --resume, absent with it)."""


def move_aside(root: Path) -> Path:
    """Rename a run folder to ``<run>.old-<date>-<time>`` (never deleted: it is the user's work)."""
    stem = f"{root.name}.old-{time.strftime('%Y%m%d-%H%M%S')}"
    target, n = root.with_name(stem), 1
    while target.exists():
        n += 1
        target = root.with_name(f"{stem}-{n}")
    root.rename(target)
    return target


def checkpoint_updates(paths: RunPaths, config: RunConfig | None = None) -> int | None:
    """The updates of the checkpoint the run's learner would resume from (None: it has none). With
    ``config`` (a RunConfig), RunStateError when its agent cannot load that checkpoint: refused here,
    before the config replaces the run's own (the learner would refuse it, and the run could not
    resume with its own recipe either)."""
    if not paths.checkpoints.is_dir() or not any(paths.checkpoints.iterdir()):
        return None  # a new run: no need to import torch here
    from shared.learning.checkpoints import CheckpointError, CheckpointManager

    checkpoint = CheckpointManager(paths.checkpoints).load_latest()
    if checkpoint is None:
        return None
    if config is not None:
        from shared.learning.dqn import DQNAgent
        from shared.learning.replay import ReplayMemory

        try:  # what the learner's resume loads: the agent, and the replay memory if it was kept
            checkpoint.restore(DQNAgent(config.model, config.sensor, config.dqn, device="cpu"))
            checkpoint.check_replay_fits(ReplayMemory(config.replay, (config.sensor.height, config.sensor.width)))
        except CheckpointError as exc:
            raise RunStateError(f"cannot resume run {paths.root.name!r} with this config: {exc}. Drop --preset and "
                                "--set to train it with its own, or start it over (--fresh, or another --run)") from None
    return checkpoint.update_count


def check_learner_sources(run: str, config: RunConfig, resumed_from: RunConfig | None = None) -> None:
    """RunStateError when the learner of ``config`` could not start: a transfer file (not the one the
    run resumes with from a checkpoint, ``resumed_from`` its saved config: shared.learning.learner's
    check_start_sources) or a demonstration file that is missing or does not fit (checked before the
    config is saved)."""
    if not (config.train.init_from or config.train.init_conv_from or config.train.demo_paths):
        return  # nothing to read: no need to import torch here
    from shared.learning.checkpoints import CheckpointError
    from shared.learning.demos import DemoError
    from shared.learning.learner import check_start_sources

    try:
        check_start_sources(config, resumed_from=resumed_from)
    except (CheckpointError, DemoError) as exc:
        raise RunStateError(f"run {run!r} cannot start its learner: {exc}") from None


def recorded_update_rate(learner_csv: Path) -> float | None:
    """The mean updates/s a run's learner reported while it was learning (its ``updates_per_s``
    column, one row a second, warm-up rows left out); None under a minute of them on record."""
    rates = []
    try:
        for row in read_csv_records(learner_csv):
            try:
                rate = float(row["updates_per_s"])
            except (KeyError, TypeError, ValueError):
                continue  # a torn last line of a killed learner
            if rate > 0:
                rates.append(rate)
    except OSError:
        return None
    return sum(rates) / len(rates) if len(rates) >= ETA_AFTER_S else None


def resume_line(run: str, paths: RunPaths, done: int, total: int) -> str:
    """What a resumed run says before it starts: from which update, and, where the run's own learner
    has a minute of learning on record, how long the rest should take at its rate."""
    line = f"run {run!r}: resuming from update {done}/{total}"
    rate = recorded_update_rate(paths.stats / LearnerRow.FILE)
    if rate is not None:
        line += (f"; its learner made {rate:.1f} updates/s so far: the {total - done} left should take "
                 f"~{_duration((total - done) / rate)}, then the final evaluation")
    return line


def _loopback(endpoint: str) -> bool:
    return endpoint_host_port(endpoint)[1] in ("127.0.0.1", "localhost", "::1")


def router_endpoints(listen: tuple[str, ...] | list[str], port: int | None,
                     tls: bool = False) -> tuple[tuple[str, ...], str]:
    """(where the router listens, where this machine's processes connect). By default a free
    loopback port (TLS for a run whose security folder has certificates, ``tls``); with ``--listen``,
    those endpoints (TLS wherever they leave the machine, and one at least with ``tls``) and the
    first TLS one among them (on localhost when it is this machine's), else the first one."""
    if not listen:
        listen = [f"{'tls' if tls else 'tcp'}/127.0.0.1:{port or free_tcp_port()}"]
    endpoints = parse_endpoints(list(listen), "--listen")
    for e in endpoints:
        if not _loopback(e) and not e.startswith("tls/"):
            raise SecurityError(f"--listen {e}: a router reachable from other machines listens with TLS only "
                                f"(--listen tls/{e.split('/', 1)[1]})")
    tls_endpoints = [e for e in endpoints if e.startswith("tls/")]
    if tls and not tls_endpoints:  # its access control would refuse every role: the run would hang
        raise SecurityError(f"--listen {','.join(endpoints)}: this run's security folder has TLS certificates and "
                            f"its access control admits every role over TLS only (--listen "
                            f"tls/{endpoints[0].split('/', 1)[1]})")
    if not tls_endpoints:  # loopback only, no TLS: the first as it listens (localhost may not name ::1)
        return endpoints, endpoints[0]
    # With TLS the access control admits a role over TLS only, and Zenoh's TLS checks a host name:
    # localhost for this machine's own addresses, else the name the router listens on (--host).
    _, host, _ = endpoint_host_port(tls_endpoints[0])
    if host in ("0.0.0.0", "::", "127.0.0.1", "::1", "localhost"):
        return endpoints, f"tls/localhost:{tls_endpoints[0].split('/', 1)[1].rsplit(':', 1)[1]}"
    return endpoints, tls_endpoints[0]


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
    elif files.meta().get("run") == run:
        files.refresh_rules(run)  # a folder an older release made: its rules may refuse a service its part
    return files.check(run, tls=tls)


def run_up_command(args: argparse.Namespace) -> int:
    setup_logging("WARNING")
    return Launcher(args).execute()
