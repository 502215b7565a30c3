"""The run's configuration over the bus, so that an actor or the evaluator needs no preset to join.

The learner answers ``RunKeys.config`` with the configuration it trains with (a ``RunConfigMessage``).
A process started without ``--preset`` waits for that answer and takes it (``--set`` still applies);
one started with ``--preset`` starts at once and checks its own against the learner's as soon as a
learner answers (:class:`RunConfigCheck`). Either way a configuration whose data the run could not
use (``shared.config.MUST_MATCH_FIELDS``) stops the process with one line naming the difference.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time

import zenoh

from services.bus.session import TransportError, ZenohSettings, open_service_session, open_session, query_replies
from services.runs import RunPaths, resolve_config
from shared.config import ConfigError, ConfigMismatchError, RunConfig, require_same_run
from shared.wire.keys import RunKeys
from shared.wire.messages import OVERSIZE, MessageError, RejectCounter, RunConfigMessage

log = logging.getLogger("cogexplore.config")

QUERY_TIMEOUT_S = 2.0
RETRY_S = 0.5
PROGRESS_EVERY_S = 10.0


def config_rejects() -> RejectCounter:
    """A counter for the skipped answers on the config key: one for all the asks of a wait, so that
    answers from anyone, every retry, log one line per cause."""
    return RejectCounter("config answer", log)


def ask_run_config(session: zenoh.Session, keys: RunKeys, timeout_s: float = QUERY_TIMEOUT_S,
                   rejects: RejectCounter | None = None) -> RunConfigMessage | None:
    """The learner's answer on ``keys.config``, or None when no learner answers.

    Every reply is read, not the first: without the access control anyone may answer too. A reply
    this build cannot read is skipped while another can be read (one only: another build of
    cogexplore, a ConfigError); readable replies that differ are refused (a ConfigError naming
    both learners), never one of them taken on trust. Skipped replies are counted in ``rejects``
    (a new counter when None)."""
    rejects = rejects if rejects is not None else config_rejects()
    first: RunConfigMessage | None = None
    other: RunConfigMessage | None = None  # a readable answer that differs from the first
    unreadable: list[MessageError] = []  # the answers this build cannot read

    def oversize(size: int) -> None:
        rejects.reject(MessageError(OVERSIZE, f"a {size}-byte answer, more than a configuration takes"), keys.config)

    for payload in query_replies(session, keys.config, RunConfigMessage.MAX_BYTES, timeout_s=timeout_s,
                                 oversize=oversize):
        try:
            message = RunConfigMessage.decode(payload)
        except MessageError as exc:
            unreadable.append(exc)
            continue
        if first is None:
            first = message
        elif other is None and message.run_config != first.run_config:
            other = message
    if first is None:
        if unreadable:  # only the learner may answer here with security on: another build of cogexplore
            raise ConfigError(f"no answer on {keys.config} for run {keys.run!r} is a configuration this build can "
                              f"read ({unreadable[0]}): run the same cogexplore version on both sides")
        return None
    for exc in unreadable:  # beside a readable one: from someone else
        rejects.reject(exc, keys.config)
    if other is not None:
        raise ConfigError(f"run {keys.run!r} has several answers on {keys.config} that differ (learners "
                          f"{first.learner_id!r} and {other.learner_id!r}): only the run's learner should answer "
                          "there; with the access control on (cogexplore secure) no one else can")
    return first


def fetch_run_config(settings: ZenohSettings, keys: RunKeys, wait_s: float) -> RunConfigMessage:
    """Wait up to ``wait_s`` for the run's learner to answer (a log line every 10 s while it does not)."""
    started = time.monotonic()
    log.info("asking the learner of run %r for the run's configuration (%s; waiting up to %.0f s)",
             keys.run, keys.config, wait_s)
    rejects = config_rejects()
    with open_service_session(settings) as session:
        said = started
        while True:
            message = ask_run_config(session, keys, rejects=rejects)
            if message is not None:
                return message
            now = time.monotonic()
            if now - started >= wait_s:
                raise TransportError(f"no learner of run {keys.run!r} answered {keys.config} within {wait_s:.0f} s "
                                     f"({settings.describe()}): start it, check --run and --connect, or name the "
                                     "run's preset with --preset")
            if now - said >= PROGRESS_EVERY_S:
                log.info("still waiting for the learner of run %r (%.0f s of %.0f)", keys.run, now - started, wait_s)
                said = now
            time.sleep(RETRY_S)


def _source(message: RunConfigMessage, keys: RunKeys) -> str:
    return f"learner {message.learner_id!r} of run {keys.run!r}"


class RunConfigCheck:
    """Checks a process's own configuration (from ``--preset``) against its learner's, on a thread and
    a Zenoh session of its own (the service's loop goes on meanwhile), as soon as a learner answers: a
    difference is kept in ``error`` and sets ``stop``. ``finish()`` ends the check and returns it."""

    def __init__(self, keys: RunKeys, cfg: RunConfig, who: str):
        self.keys = keys
        self.cfg = cfg
        self.who = who
        self.error: ConfigMismatchError | None = None
        self._finishing = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, settings: ZenohSettings, stop: threading.Event) -> None:
        self._thread = threading.Thread(target=self._run, args=(settings, stop), name="run-config-check", daemon=True)
        self._thread.start()

    def _run(self, settings: ZenohSettings, stop: threading.Event) -> None:
        # finish() ends the wait for a router too: a check left retrying zenoh.open past it may still be
        # inside Zenoh when the interpreter exits (see WeightFollower.following)
        def give_up() -> str | None:
            return "stopped" if stop.is_set() or self._finishing.is_set() else None

        try:
            with open_session(settings, wait_s=settings.router_wait_s, give_up=give_up) as session:
                self._check(session, stop)
        except TransportError:
            pass  # no router, or finished first: the service's own session says so
        if self.error is not None:
            stop.set()

    def _check(self, session: zenoh.Session, stop: threading.Event) -> None:
        rejects = config_rejects()
        while not (stop.is_set() or self._finishing.is_set()):
            try:
                message = ask_run_config(session, self.keys, rejects=rejects)
            except ConfigError as exc:
                self.error = ConfigMismatchError(str(exc))
                return
            if message is None:
                self._finishing.wait(RETRY_S)
                continue
            try:
                require_same_run(self.cfg, message.run_config, who=self.who, source=_source(message, self.keys),
                                 hint="drop --preset to use the run's configuration")
                log.info("the configuration matches the run's (%s)", _source(message, self.keys))
            except ConfigMismatchError as exc:
                self.error = exc
            return

    def finish(self) -> ConfigMismatchError | None:
        """End the check (its session closes); the difference it found, if any."""
        self._finishing.set()
        if self._thread is not None:
            self._thread.join(timeout=QUERY_TIMEOUT_S + 3.0)
        return self.error


def join_run_config(args: argparse.Namespace, paths: RunPaths, settings: ZenohSettings,
                    who: str) -> tuple[RunConfig, RunConfigCheck | None]:
    """The configuration an actor or the evaluator runs with, and the check to start once its session
    is open: with ``--preset``, that preset (and ``--set``), checked against the learner's later;
    without, the learner's (waiting ``--config-wait`` seconds for it) with ``--set`` over it, checked now.
    Its ``train.device`` is the process's own (``resolve_config(own_device=True)``)."""
    keys = RunKeys(args.run)
    if args.preset is not None:
        cfg = resolve_config(args, paths, own_device=True)
        return cfg, RunConfigCheck(keys, cfg, who)
    message = fetch_run_config(settings, keys, args.config_wait)
    run_cfg = message.run_config
    cfg = resolve_config(args, paths, run_cfg, own_device=True)
    require_same_run(cfg, run_cfg, who=who, source=_source(message, keys),
                     hint="leave that field to the run (drop its --set)")
    log.info("using the run's configuration (%s)", _source(message, keys))
    return cfg, None
