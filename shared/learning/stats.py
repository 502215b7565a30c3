"""A run's statistics files as named records: ``stats/learner.csv`` and ``stats/episodes.csv``.

Each file has one record type, whose fields are its columns in order; the learner service and
the single-process trainer both fill a :class:`LearnerRow` by name and write it with
:class:`CsvLog`, so a new column is one new field and cannot misalign either writer. A field's
``fmt`` (a format spec) says how its cell is written; None is an empty cell. A new column goes
last: an older log's header is a prefix of the new one, and :class:`CsvLog` widens it on resume.

:class:`TensorBoardLog` writes the same rows (and any mapping of numbers, such as an evaluation's
summary) as TensorBoard scalars, tagged ``<file stem>/<column>`` (``learner/loss``,
``episodes/steps``) at the row type's ``STEP`` column.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, fields
from numbers import Real
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar

from shared.files import atomic_write_text, ends_torn

log = logging.getLogger("cogexplore.stats")


def _cell(fmt: str | None = None, column: str | None = None, plotted: bool = True) -> Any:
    """A column; ``plotted`` False for one that is no quantity (an identifier): TensorBoard leaves it out."""
    return field(metadata={"fmt": fmt, "column": column, "plotted": plotted})


class _Row:
    FILE: ClassVar[str]
    STEP: ClassVar[str]
    """The column that is the row's x-axis in TensorBoard."""

    @classmethod
    def columns(cls) -> tuple[str, ...]:
        return tuple(f.metadata.get("column") or f.name for f in fields(cls))  # type: ignore[arg-type]

    @classmethod
    def unplotted(cls) -> frozenset[str]:
        """The columns TensorBoard leaves out."""
        return frozenset(c for c, f in zip(cls.columns(), fields(cls)) if not f.metadata["plotted"])  # type: ignore[arg-type]

    def values(self) -> dict[str, Any]:
        """The row by column name."""
        return {column: getattr(self, f.name) for column, f in zip(self.columns(), fields(self))}  # type: ignore[arg-type]

    def cells(self) -> list[str]:
        out = []
        for f in fields(self):  # type: ignore[arg-type]
            value, fmt = getattr(self, f.name), f.metadata.get("fmt")
            out.append("" if value is None else format(value, fmt) if fmt else str(value))
        return out


@dataclass(frozen=True)
class LearnerRow(_Row):
    """One row of ``stats/learner.csv``, every ``train.log_every`` updates (trainer) or every
    second (learner service)."""

    FILE: ClassVar[str] = "learner.csv"
    STEP: ClassVar[str] = "update"

    time_s: float = _cell(".3f")
    """Seconds since this process started (it restarts at a resume)."""
    update: int = _cell()
    policy_version: int = _cell()
    loss: float | None = _cell(".6g")
    """Mean loss over the recent updates (None before the first): the TD loss (importance-weighted under
    prioritised replay) plus the weighted margin losses where demonstrations, expert labels or safe-set
    marks are on (``dqn.demo_weight``, ``dqn.safe_weight``), so not comparable across such settings."""
    mean_q: float | None = _cell(".6g")
    updates_per_s: float = _cell(".3f")
    transitions: int = _cell()
    """Transitions received in all."""
    transitions_per_s: float | None = _cell(".1f")
    """None in the single-process trainer (one env step per loop, not a stream)."""
    replay_size: int = _cell()
    rejected: int = _cell()
    """Transition batches rejected (0 in the trainer: nothing comes over the wire)."""
    actors_alive: int = _cell()
    mean_weight_lag: float = _cell(".2f")
    """Policy versions between the learner's and the one the actors' newest transitions used."""
    label_agreement: float | None = _cell(".3f")
    """Share of the labelled samples (demonstrations, train.demos; expert labels,
    explore.expert_label_prob) whose greedy command is the labelled one, over the recent updates;
    None without labels."""
    lr: float | None = _cell(".4g")
    """The fully connected layers' learning rate at the newest update (dqn.lr, falling over
    dqn.lr_decay_updates where set); None before the first update."""
    safe_agreement: float | None = _cell(".3f")
    """Share of the samples the map expert marked with the commands that keep a way out
    (explore.safe_label_prob) whose greedy command is one of them, over the recent updates; None
    without marks."""
    session: int = _cell(plotted=False)
    """The writing process's epoch (``shared.wire.messages.new_epoch``): one value per session of a
    resumed run, which :class:`LearnerClock` tells apart by it (``time_s`` restarts, but a short
    session's clock need not go back). Empty in the rows of a log from before this column."""


@dataclass(frozen=True)
class EpisodeRow(_Row):
    """One row of ``stats/episodes.csv`` (single-process trainer): one training episode. An actor
    fills one per episode too, for TensorBoard only (``env_step``: its own steps; ``update``: the
    policy version acting when it ended)."""

    FILE: ClassVar[str] = "episodes.csv"
    STEP: ClassVar[str] = "env_step"

    episode: int = _cell()
    env_step: int = _cell()
    update: int = _cell()
    start_index: int = _cell()
    steps: int = _cell()
    episode_return: float = _cell(column="return")
    epsilon: float = _cell(".4f")
    collision_cause: str | None = _cell()
    distance_m: float = _cell(".3f")
    path_length_m: float = _cell(".3f")
    time_s: float = _cell(".3f")
    expert_guided: int = _cell()
    world: str = _cell()


def episode_row(episode: Any, *, env_step: int, update: int, time_s: float, expert_guided: bool) -> EpisodeRow:
    """The row of a finished ``shared.rollout.Episode`` (its info names the rest)."""
    info = episode.info
    return EpisodeRow(
        episode=episode.index, env_step=env_step, update=update, start_index=info["start_index"],
        steps=info["step"], episode_return=episode.episode_return, epsilon=episode.last_step.choice.epsilon,
        collision_cause=info["collision_cause"], distance_m=info["distance_from_start_m"],
        path_length_m=info["path_length_m"], time_s=time_s, expert_guided=int(expert_guided), world=info["world"])


@dataclass(frozen=True)
class TrainingSummary:
    """What a run's ``stats/learner.csv`` says of its training as a whole (:func:`summarize_learner_log`)."""

    updates: int
    """The last row's update."""
    transitions: int | None
    """Transitions received by then (None: no such column)."""
    learner_s: float | None
    """The learner's seconds, summed over its sessions (:class:`LearnerClock`; None: no such column)."""
    lr_first: float | None
    """The learning rate of the first row that logs one, and of the last (None: never logged)."""
    lr_last: float | None

    @property
    def updates_per_s(self) -> float | None:
        return self.updates / self.learner_s if self.learner_s else None


def read_csv(path: str | Path) -> Iterator[list[str]]:
    """The rows of a statistics CSV file, header first. A line the csv module cannot parse is
    skipped, not fatal, and so is one of NUL bytes only: a power loss can leave a tail of NUL bytes
    (past 128 KiB, one field over the csv module's size limit), and bytes that are not UTF-8 become
    U+FFFD."""
    with open(path, newline="", errors="replace") as fh:
        reader = csv.reader(fh)
        while True:
            try:
                row = next(reader)
            except StopIteration:
                return
            except csv.Error:
                continue
            if not row or "".join(row).strip("\0"):
                yield row


def read_csv_records(path: str | Path) -> Iterator[dict[str, str | None]]:
    """:func:`read_csv`'s rows by the header's column names, as ``csv.DictReader`` gives them: a
    row short of cells (a torn last line) has None in the missing ones; blank lines are skipped."""
    rows = read_csv(path)
    header = next(rows, None)
    for row in rows if header else ():
        if row:
            yield {column: row[i] if i < len(row) else None for i, column in enumerate(header)}


class LearnerClock:
    """The learner's seconds summed over a run's sessions, row by row of its ``learner.csv`` (each
    session's ``time_s`` starts again). A session begins where the ``session`` cell changes; in rows
    without one (a log from before that column) where ``time_s`` goes back, which merges a session
    whose rows cover less time than the next one takes to write its first row into that one."""

    def __init__(self) -> None:
        self._ended_s = 0.0  # the sessions before this one
        self._session = ""  # this session's mark ("": none)
        self._session_s = 0.0  # this session's time_s at its last row

    def at(self, row: Mapping[str, str | None]) -> float | None:
        """The learner's seconds at ``row`` (a :func:`read_csv_records` record); None for a row with
        no clock to trust: torn (cells missing), or a ``time_s`` that is no finite number >= 0."""
        if None in row.values():
            return None
        try:
            t = float(row.get("time_s") or "")
        except ValueError:
            return None
        if not (math.isfinite(t) and t >= 0):  # a damaged cell
            return None
        session = row.get("session") or ""
        if self._session.startswith(session):  # its mark, or cut short: a killed writer's torn last row
            session = self._session
        if session != self._session or (not session and t < self._session_s):
            self._ended_s += self._session_s
        self._session, self._session_s = session, t
        return self._ended_s + t


def summarize_learner_log(path: Path) -> TrainingSummary | None:
    """The training a learner log records; None where it has no readable row. Rows that do not
    parse (a torn last line, a column an older run lacks) are skipped, not fatal."""

    def number(row: dict[str, str | None], column: str, kind: type) -> Any:
        try:
            value = kind(row.get(column) or "")
        except ValueError:
            return None
        return value if math.isfinite(value) else None  # a damaged cell: "nan" read as a time or a rate

    last: dict[str, str | None] | None = None
    clock = LearnerClock()
    learner_s: float | None = None
    lr_first = lr_last = None
    for row in read_csv_records(path):
        if None in row.values() or number(row, "update", int) is None:  # torn: cells missing
            continue
        last = row
        t = clock.at(row)
        learner_s = learner_s if t is None else t
        lr = number(row, "lr", float)
        if lr is not None:
            lr_first = lr if lr_first is None else lr_first
            lr_last = lr
    if last is None:
        return None
    return TrainingSummary(updates=number(last, "update", int), transitions=number(last, "transitions", int),
                           learner_s=learner_s, lr_first=lr_first, lr_last=lr_last)


RowT = TypeVar("RowT", bound=_Row)


def rewind(stats_dir: Path, row_type: type[_Row], update: int, column: str = "update") -> int:
    """Drop the rows of ``row_type``'s file logged after ``update`` (a run resumed from an older
    checkpoint logs those updates again: its column must not go back); ``column``: the one that
    count is of (``env_step``: transitions). Rewritten atomically; returns how many rows went."""
    path = Path(stats_dir) / row_type.FILE
    if not path.is_file():
        return 0
    rows = list(read_csv(path))
    if not rows or column not in rows[0]:
        return 0
    col = rows[0].index(column)

    def kept(row: list[str]) -> bool:
        try:
            return int(row[col]) <= update
        except (IndexError, ValueError):
            return False  # a torn last line of a killed process

    keep = [rows[0]] + [r for r in rows[1:] if kept(r)]
    text = io.StringIO(newline="")
    csv.writer(text).writerows(keep)
    # Rewritten when anything goes: a row after ``update``, or damage the reader skipped (a power
    # loss's NUL tail, which the next row would otherwise be appended to and lost with).
    if text.getvalue().encode() != path.read_bytes():
        atomic_write_text(path, text.getvalue())
    return len(rows) - len(keep)


def _header(path: Path, row_type: type[_Row]) -> list[str] | None:
    """The first row of ``path`` where it is a header of ``row_type``'s (any version: it names the step column)."""
    first = next((r for r in read_csv(path) if r), None)
    return first if first is not None and row_type.STEP in first else None


def _widen(path: Path, row_type: type[_Row], header: list[str]) -> None:
    """Rewrite ``path``, a log of an older ``row_type`` (its ``header`` a prefix of the columns), with
    today's header, its rows' missing cells empty: under the old header, readers dropped the new
    cells of the rows a resumed run appends. A row short of the old header (torn) stays short, so
    readers still skip it."""
    columns = row_type.columns()
    rows = [list(columns)] + [r + [""] * (len(columns) - len(r)) if len(r) >= len(header) else r
                              for r in list(read_csv(path))[1:]]
    text = io.StringIO(newline="")
    csv.writer(text).writerows(rows)
    atomic_write_text(path, text.getvalue())


CSV_RETRY_S = 30.0
"""Seconds a statistics log that could not be written (a full disk) waits before it tries again: its
rows in between are lost, and a full disk is not asked at every row."""


class CsvLog(Generic[RowT]):
    """Appends rows of one record type to ``<stats dir>/<its FILE>``, the header first when the file
    is new (an older version's header is widened first: :func:`_widen`); every row is flushed, so a
    crash loses at most the row being written. The log is a record of training, not the training: a
    row that cannot be written (a full disk, a quota) is said once and lost, the process goes on, and
    the file is tried again :data:`CSV_RETRY_S` later (its torn last line ended first)."""

    def __init__(self, stats_dir: Path, row_type: type[RowT]):
        self.row_type = row_type
        self.path = Path(stats_dir) / row_type.FILE
        existed = self.path.exists()
        header = _header(self.path, row_type) if existed else None
        # a power loss just after a log's start can leave it empty or NULs: it needs its header again
        new = header is None
        columns = row_type.columns()
        if header is not None and len(header) < len(columns) and tuple(header) == columns[:len(header)]:
            _widen(self.path, row_type, header)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: Any = None
        self._failed_at = 0.0
        self.lost = 0
        """Rows not written since the last one that was (the file could not be written)."""
        try:
            self._open(header=new)
        except OSError as exc:
            self._fail(exc)

    def _open(self, header: bool) -> None:
        self._file = open(self.path, "a", newline="")
        self._writer = csv.writer(self._file)
        if ends_torn(self.path):
            self._file.write("\r\n")  # a killed writer's (or a full disk's) torn last line: the next row starts its own
        if header:
            self._writer.writerow(self.row_type.columns())
        self._file.flush()

    def _fail(self, exc: OSError) -> None:
        if not self.lost:
            log.warning("%s cannot be written (%s): its rows are lost, the process goes on; tried again every %.0f s",
                        self.path, exc.strerror or exc, CSV_RETRY_S)
        self._failed_at = time.monotonic()
        self._drop()

    def _drop(self) -> None:
        """Close the file; what its buffer still holds is lost (a full disk fails its flush again)."""
        handle, self._file = self._file, None
        if handle is not None:
            try:
                handle.close()
            except OSError:
                pass

    def write(self, row: RowT) -> None:
        """Append ``row``; where the file cannot be written, count it lost (:attr:`lost`) instead."""
        if not isinstance(row, self.row_type):
            raise TypeError(f"{self.path.name} takes {self.row_type.__name__} rows, got {type(row).__name__}")
        if self._file is None:
            if time.monotonic() - self._failed_at < CSV_RETRY_S:
                self.lost += 1
                return
            try:
                self._open(header=not self.path.is_file() or _header(self.path, self.row_type) is None)
            except OSError as exc:
                self._fail(exc)
                self.lost += 1
                return
        try:
            self._writer.writerow(row.cells())
            self._file.flush()
        except OSError as exc:
            self._fail(exc)  # said when it is the first row lost
            self.lost += 1
            return
        if self.lost:
            log.warning("%s written again (%d row(s) lost)", self.path, self.lost)
            self.lost = 0

    def close(self) -> None:
        self._drop()

    def __enter__(self) -> "CsvLog[RowT]":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


TENSORBOARD_FLUSH_S = 5.0
"""How often a TensorBoard writer flushes its events to disk (a killed process loses at most this)."""


def scalars(values: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, float]]:
    """The numbers of ``values`` as (name, value); a nested mapping's names join with ``/``, anything
    else (None, text, lists) is left out."""
    for name, value in values.items():
        if isinstance(value, Mapping):
            yield from scalars(value, f"{prefix}{name}/")
        elif isinstance(value, Real):  # bool too: 0 or 1
            yield f"{prefix}{name}", float(value)


class _HeldRecords:
    """The record writer of a TensorBoard writer's thread, whose failed write (a full disk) it keeps in
    :attr:`error` for the process's thread to find, writing nothing more: raised in that thread, it
    ended it with a traceback on stderr."""

    def __init__(self, records: Any):
        self.records = records
        self.error: OSError | None = None

    def _do(self, step: Callable[[], None]) -> None:
        if self.error is None:
            try:
                step()
            except OSError as exc:
                self.error = exc

    def write(self, data: bytes) -> None:
        self._do(lambda: self.records.write(data))

    def flush(self) -> None:
        self._do(self.records.flush)

    def close(self) -> None:
        self._do(self.records.close)


def _hold_records(writer: Any) -> _HeldRecords | None:
    """Put a :class:`_HeldRecords` between ``writer`` (a ``SummaryWriter``) and its file; None where
    this tensorboard's insides differ (its thread then fails as it does)."""
    try:
        events = writer.file_writer.event_writer._async_writer
        held = _HeldRecords(events._writer)
        events._writer = events._worker._record_writer = held
        return held
    except AttributeError:
        return None


class TensorBoardLog:
    """One process's scalars as TensorBoard event files in ``folder`` (``runs/<run>/tb/<process>/``,
    so that no two writers share a file); ``folder`` None writes nothing.

    Tags are ``<group>/<name>``; a row's group is its file's stem and its step its ``STEP`` column,
    so ``learner.csv``'s ``loss`` at update 200 is ``learner/loss`` at step 200. A row whose step is
    the one its group wrote last is skipped (the learner logs every second, also while no update
    runs: one point per step); a lower step is written (a resumed run goes back, and TensorBoard
    drops the orphaned points after it, as ``rewind`` does the CSV rows). TensorBoard is a view, not
    the record: no ``tensorboard`` package or a folder that cannot be written is logged once and the
    process goes on without it. The writer (torch's ``SummaryWriter``, imported only here) flushes
    every ``flush_s`` seconds and on :meth:`close`.
    """

    def __init__(self, folder: Path | None, flush_s: float = TENSORBOARD_FLUSH_S):
        self.folder = None if folder is None else Path(folder)
        self._writer: Any = None
        self._held: _HeldRecords | None = None
        self._last_step: dict[str, int] = {}
        if self.folder is None:
            return
        try:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(self.folder), flush_secs=flush_s)
            self._held = _hold_records(self._writer)
        except Exception as exc:  # ImportError, OSError, ...: whatever it is, training goes on
            self._give_up(exc)

    @property
    def enabled(self) -> bool:
        return self._writer is not None

    def write_row(self, row: _Row) -> None:
        unplotted = row.unplotted()
        values = {column: value for column, value in row.values().items() if column not in unplotted}
        step = int(values.pop(row.STEP))
        group = Path(row.FILE).stem
        if self._last_step.get(group) != step:
            self.write(group, values, step)

    def write(self, group: str, values: Mapping[str, Any], step: int) -> None:
        """``values``' numbers (see :func:`scalars`) as ``<group>/<name>`` at ``step``."""
        if self._writer is None:
            return
        try:
            for name, value in scalars(values):
                self._writer.add_scalar(f"{group}/{name}", value, step)
            if self._held is not None and self._held.error is not None:  # its thread's write failed
                raise self._held.error
        except Exception as exc:
            self._give_up(exc)
        self._last_step[group] = step

    def _give_up(self, exc: BaseException) -> None:
        log.warning("TensorBoard off: cannot write %s (%s: %s)", self.folder, type(exc).__name__, exc)
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except Exception:
                pass

    def close(self) -> None:
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except Exception as exc:
                log.warning("TensorBoard: closing %s failed (%s: %s)", self.folder, type(exc).__name__, exc)

    def __enter__(self) -> "TensorBoardLog":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
