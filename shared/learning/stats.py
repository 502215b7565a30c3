"""A run's statistics files as named records: ``stats/learner.csv`` and ``stats/episodes.csv``.

Each file has one record type, whose fields are its columns in order; the learner service and
the single-process trainer both fill a :class:`LearnerRow` by name and write it with
:class:`CsvLog`, so a new column is one new field and cannot misalign either writer. A field's
``fmt`` (a format spec) says how its cell is written; None is an empty cell.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, ClassVar, Generic, TypeVar


def _cell(fmt: str | None = None, column: str | None = None) -> Any:
    return field(metadata={"fmt": fmt, "column": column})


class _Row:
    FILE: ClassVar[str]

    @classmethod
    def columns(cls) -> tuple[str, ...]:
        return tuple(f.metadata.get("column") or f.name for f in fields(cls))  # type: ignore[arg-type]

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

    time_s: float = _cell(".3f")
    """Seconds since this process started (it restarts at a resume)."""
    update: int = _cell()
    policy_version: int = _cell()
    loss: float | None = _cell(".6g")
    """Mean TD loss over the recent updates (None before the first)."""
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
    demo_agreement: float | None = _cell(".3f")
    """Share of the demonstration samples (train.demos) whose greedy command is the demonstrated
    one, over the recent updates; None without demonstrations."""


@dataclass(frozen=True)
class EpisodeRow(_Row):
    """One row of ``stats/episodes.csv`` (single-process trainer): one training episode."""

    FILE: ClassVar[str] = "episodes.csv"

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


RowT = TypeVar("RowT", bound=_Row)


def rewind(stats_dir: Path, row_type: type[_Row], update: int) -> int:
    """Drop the rows of ``row_type``'s file logged after ``update`` (a run resumed from an older
    checkpoint logs those updates again: its column must not go back). Rewritten atomically;
    returns how many rows went."""
    path = Path(stats_dir) / row_type.FILE
    if not path.is_file():
        return 0
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows or "update" not in rows[0]:
        return 0
    col = rows[0].index("update")

    def kept(row: list[str]) -> bool:
        try:
            return int(row[col]) <= update
        except (IndexError, ValueError):
            return False  # a torn last line of a killed process

    keep = [rows[0]] + [r for r in rows[1:] if kept(r)]
    if len(keep) == len(rows):
        return 0
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as fh:
        csv.writer(fh).writerows(keep)
    tmp.replace(path)
    return len(rows) - len(keep)


class CsvLog(Generic[RowT]):
    """Appends rows of one record type to ``<stats dir>/<its FILE>``, the header first when the file
    is new; every row is flushed, so a crash loses at most the row being written."""

    def __init__(self, stats_dir: Path, row_type: type[RowT]):
        self.row_type = row_type
        self.path = Path(stats_dir) / row_type.FILE
        new = not self.path.exists()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "a", newline="")
        self._writer = csv.writer(self._file)
        if new:
            self._writer.writerow(row_type.columns())
            self._file.flush()

    def write(self, row: RowT) -> None:
        if not isinstance(row, self.row_type):
            raise TypeError(f"{self.path.name} takes {self.row_type.__name__} rows, got {type(row).__name__}")
        self._writer.writerow(row.cells())
        self._file.flush()

    def close(self) -> None:
        self._file.close()

    def __enter__(self) -> "CsvLog[RowT]":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
