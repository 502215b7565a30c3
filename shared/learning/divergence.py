"""What a run remembers of its divergences, and the learning rate it resumes at after one.

A learner whose weights go NaN or infinite stops without saving them (``Diverged``); its next start
resumes from the last good checkpoint. Resumed at the same rate, the same updates would most often
diverge again, and a learner restarted on failure (compose's ``restart: on-failure``, a supervisor)
would go round that loop for ever, losing its progress each time. So each divergence is written to the
run's ``diverged.json``, and the next start resumes at half the rate it diverged at (:data:`LR_BACKOFF`;
its config's or preset's rate where that is lower), a common answer to a loss that blew up. A rate
the user chooses for the resume (``--set dqn.lr=...``) is kept as given. After :data:`MAX_BACKOFFS`
halvings in a row a run that diverges again is not resumed at all: something else is wrong (the
rewards, the preset), and a person has to look. The streak ends, and the file goes, once the run
saves a checkpoint past every update at which it diverged; the lowered rate stays in the run's config.

Pure logic and one small JSON file; the learner service and the single-process trainer call it.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

from shared.config import RunConfig, parse_override
from shared.errors import CogexploreError
from shared.files import atomic_write_text
from shared.jsontext import read_json_file

log = logging.getLogger("cogexplore.divergence")

DIVERGENCE_FILE = "diverged.json"
"""In the run's folder: the divergences since the run last trained past one."""

LR_BACKOFF = 0.5
"""The factor on the rate a run diverged at, for its next start."""

MAX_BACKOFFS = 3
"""Divergences in a row a run resumes after (at an eighth of the rate, at most); at the next it is refused."""

MAX_CAUSE_CHARS = 300
"""A divergence's cause is kept to this (one line): the record is read back at every start."""


class DivergenceStreakError(CogexploreError):
    """The run diverged again after :data:`MAX_BACKOFFS` halvings of its rate: not resumed."""


@dataclass(frozen=True)
class Divergence:
    """One divergence of a run."""

    update: int
    """The update whose weights were no longer finite."""
    resumed_from: int
    """The update of the last good checkpoint, which the next start resumes from (0: none)."""
    lr: float
    """The ``dqn.lr`` it trained at."""
    cause: str
    """What diverged, in a line (the weight or the loss)."""
    at: float
    """When (Unix time)."""


def _divergence(entry: object) -> Divergence:
    if not isinstance(entry, dict) or set(entry) != {f for f in Divergence.__dataclass_fields__}:
        raise ValueError("an entry is not a divergence")
    update, resumed_from, lr, at = entry["update"], entry["resumed_from"], entry["lr"], entry["at"]
    if not (isinstance(update, int) and isinstance(resumed_from, int) and 0 <= resumed_from <= update):
        raise ValueError("an entry's updates are not counts")
    if not (isinstance(lr, (int, float)) and not isinstance(lr, bool) and math.isfinite(lr) and lr > 0):
        raise ValueError("an entry's learning rate is not a positive number")
    if not isinstance(entry["cause"], str) or not isinstance(at, (int, float)):
        raise ValueError("an entry's cause or time is of the wrong type")
    return Divergence(update, resumed_from, float(lr), entry["cause"][:MAX_CAUSE_CHARS], float(at))


def read_streak(run_folder: Path) -> list[Divergence]:
    """The run's divergences since it last trained past one, oldest first ([] when none). A file that
    cannot be read is logged and read as none: it is advice to the next start, not the run's state."""
    path = Path(run_folder) / DIVERGENCE_FILE
    if not path.exists():
        return []
    try:
        data = read_json_file(path, "divergence record", allow_nan=False)
        if not isinstance(data, dict) or not isinstance(data.get("divergences"), list) or not data["divergences"]:
            raise ValueError("no list of divergences")
        return [_divergence(entry) for entry in data["divergences"]]
    except (CogexploreError, ValueError) as exc:
        log.warning("ignored the divergence record %s: %s", path, exc)
        return []


def record_divergence(run_folder: Path, *, update: int, resumed_from: int, lr: float,
                      cause: str) -> tuple[list[Divergence], bool]:
    """Add a divergence to the run's record (atomically); the streak with it, and whether the record was
    written. One that cannot be written (a full disk) is logged: the stop it explains goes on."""
    streak = read_streak(run_folder) + [Divergence(int(update), int(resumed_from), float(lr),
                                                   " ".join(str(cause).split())[:MAX_CAUSE_CHARS], time.time())]
    try:
        atomic_write_text(Path(run_folder) / DIVERGENCE_FILE,
                          json.dumps({"divergences": [asdict(d) for d in streak]}, indent=1) + "\n")
    except OSError as exc:  # names the file
        log.error("could not write the divergence record: %s", exc)
        return streak, False
    return streak, True


def resume_lr(streak: list[Divergence], configured_lr: float, *, lr_given: bool = False) -> tuple[float, str | None]:
    """The rate a run resumes at after ``streak`` (its divergences in a row) with ``configured_lr`` in
    its config, and a line that says why (None when there is nothing to say): half the rate of the last
    divergence, or the configured rate where that is lower already (a run halved before, stopped short
    of the update where it diverged). ``lr_given``: the user chose ``configured_lr`` for this start
    (``--set dqn.lr``), which is kept as given; a preset's own rate is not a choice.
    DivergenceStreakError after :data:`MAX_BACKOFFS` halvings that did not help."""
    if not streak:
        return configured_lr, None
    last = streak[-1]
    after = f"resuming after a divergence at update {last.update} (at dqn.lr={last.lr:g})"
    if lr_given:
        return configured_lr, f"{after} at the rate given, dqn.lr={configured_lr:g}"
    if len(streak) > MAX_BACKOFFS:
        raise DivergenceStreakError(
            f"the run diverged {len(streak)} times in a row, the last at update {last.update} at dqn.lr={last.lr:g}, "
            f"its rate halved after each: not resumed again. Look for the cause (the rewards, the preset, "
            f"{DIVERGENCE_FILE} in the run's folder), then resume with --set dqn.lr=<rate>")
    half = last.lr * LR_BACKOFF
    how = (f"at half that rate, dqn.lr={half:g}" if half <= configured_lr else
           f"at its configured rate, dqn.lr={configured_lr:g}, below half that")
    return min(configured_lr, half), (f"{after} {how} (divergence {len(streak)} in a row; --set dqn.lr=<rate> "
                                       f"chooses another)")


class RunDivergences:
    """A run's divergence record as its learner (or trainer) sees it: read once at its start, ended by
    a checkpoint past every divergence in it, added to when it diverges."""

    def __init__(self, run_folder: Path):
        self.folder = Path(run_folder)
        self.streak = read_streak(self.folder)

    def resume_config(self, cfg: RunConfig, *, lr_given: bool = False) -> RunConfig:
        """``cfg`` at the rate to resume at (:func:`resume_lr`, said in the log); DivergenceStreakError
        when the run is not to be resumed again."""
        lr, why = resume_lr(self.streak, cfg.dqn.lr, lr_given=lr_given)
        if why:
            log.warning("%s", why)
        return cfg if lr == cfg.dqn.lr else cfg.with_overrides({"dqn.lr": lr})

    def saved(self, update: int, lr: float) -> None:
        """After a checkpoint at ``update``: past every divergence of the streak, it is over and its
        record goes. The lowered rate ``lr`` stays the run's."""
        if not self.streak or update <= max(d.update for d in self.streak):
            return
        try:
            (self.folder / DIVERGENCE_FILE).unlink(missing_ok=True)
        except OSError as exc:
            log.warning("could not remove the divergence record in %s: %s", self.folder, exc.strerror or exc)
            return
        log.info("trained past update %d, where the run last diverged: it trains on at dqn.lr=%g",
                 max(d.update for d in self.streak), lr)
        self.streak = []

    def diverged(self, *, update: int, resumed_from: int, lr: float, cause: str) -> str:
        """Record a divergence; what the run's next start does, in a clause."""
        self.streak, written = record_divergence(self.folder, update=update, resumed_from=resumed_from, lr=lr,
                                                 cause=cause)
        if not written:
            return f"{DIVERGENCE_FILE} could not be written: its next start resumes at the same rate"
        try:
            next_lr, _ = resume_lr(self.streak, lr)
        except DivergenceStreakError:
            return (f"diverged {len(self.streak)} times in a row, it is not resumed again without "
                    f"--set dqn.lr=<rate>")
        return f"its next start resumes at dqn.lr={next_lr:g} ({DIVERGENCE_FILE})"


def sets_lr(overrides: list[str] | None) -> bool:
    """Whether a command's ``--set`` options (``section.field=value``) choose ``dqn.lr``."""
    return any(parse_override(text)[0] == "dqn.lr" for text in overrides or ())
