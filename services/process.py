"""What every process shell does the same way: its id, its logging, its stop signal, its priority."""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from shared.config import ConfigError


def default_process_id(role: str) -> str:
    """hostname-pid: distinct for scaled containers and for processes on one machine."""
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:40] or "host"
    return f"{role}-{host}-{os.getpid()}"


class LogFileHandler(logging.FileHandler):
    """A process's log file. A line it cannot write (a full disk) is said once on stderr, and again
    once lines get through: logging's own handler printed a traceback for every line lost."""

    def __init__(self, filename: Path):
        super().__init__(filename)
        self.failing = False
        self._failed_now = False

    def emit(self, record: logging.LogRecord) -> None:
        self._failed_now = False
        super().emit(record)  # a failure calls handleError
        if self.failing and not self._failed_now:
            self.failing = False
            self._say(f"the log file {self.baseFilename} is written again (lines since the last were lost)")

    def handleError(self, record: logging.LogRecord) -> None:
        exc = sys.exc_info()[1]
        if not isinstance(exc, OSError):  # a bad message (a bug): logging's own report
            super().handleError(record)
            return
        self._failed_now = True
        if not self.failing:
            self.failing = True
            why = exc.strerror or exc
            self._say(f"the log file {self.baseFilename} cannot be written ({why}): its lines are lost, the "
                      "process goes on")

    @staticmethod
    def _say(line: str) -> None:
        try:
            print(f"cogexplore: {line}", file=sys.stderr, flush=True)
        except (OSError, ValueError):  # stderr on the full disk too, or closed: nowhere left to say it
            pass


def setup_logging(level: str = "INFO", logfile: Path | None = None) -> None:
    handlers: list[logging.Handler] = [logging.StreamHandler()]
    if logfile is not None:
        logfile.parent.mkdir(parents=True, exist_ok=True)
        handlers.append(LogFileHandler(logfile))
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), handlers=handlers, force=True,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def stop_signals() -> tuple[signal.Signals, ...]:
    """The signals that stop a process in order: SIGINT, SIGTERM and SIGHUP (a closed terminal),
    unless SIGHUP is ignored (``nohup``: the process must outlive the terminal)."""
    hangup = () if signal.getsignal(signal.SIGHUP) == signal.SIG_IGN else (signal.SIGHUP,)
    return (signal.SIGINT, signal.SIGTERM, *hangup)


@contextmanager
def stop_signals_handled(handler: Callable[[int, Any], None], *, keep_interrupt: bool = False) -> Iterator[None]:
    """``handler`` for each of :func:`stop_signals` while the block runs (``keep_interrupt``: not for
    SIGINT, which stays KeyboardInterrupt), and the handlers from before it afterwards."""
    previous = {s: signal.signal(s, handler) for s in stop_signals() if not (keep_interrupt and s == signal.SIGINT)}
    try:
        yield
    finally:
        for s, earlier in previous.items():
            signal.signal(s, earlier)


def stop_event_on_signals() -> threading.Event:
    """An Event set by :func:`stop_signals`, so loops can finish their step and clean up: a learner
    writes its final checkpoint."""
    stop = threading.Event()

    def handler(signum: int, _frame: object) -> None:
        logging.getLogger(__name__).info("signal %s: stopping", signal.Signals(signum).name)
        stop.set()

    for signum in stop_signals():
        signal.signal(signum, handler)
    return stop


def lower_priority(niceness: int) -> int:
    """Lower this process's CPU priority by ``niceness`` (0-19; 0 leaves it) and return its nice value.

    Call it before any thread starts (Zenoh's, torch's): Linux keeps a nice value per thread, and a
    thread takes its creator's. An actor or evaluator that shares cores with the learner (``up`` on
    one machine) then takes the time the learner leaves instead of taking it from the learner."""
    if isinstance(niceness, bool) or not isinstance(niceness, int) or not 0 <= niceness <= 19:
        raise ConfigError(f"niceness {niceness!r} is invalid: an integer in [0, 19] (--nice)")
    return os.nice(niceness)
