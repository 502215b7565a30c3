"""Evaluation results: the per-episode record, aggregation, the results JSON, Table III, and
the paper's test protocol.

Protocol (paper, Section V-A): from every start pose, N episodes with the greedy policy at
the test speeds, each stopped after at most 200 moving steps, from the exact or jittered start
and with the sensor noise of the protocol the results record (``meta.protocol``, a
``shared.evaluation.ProtocolConfig``: ``paper`` or ``robust``). Per start and overall we report
the mean moving steps, mean start-to-end distance, mean path length, coverage (m^2 and % of
the free area), collisions by cause and episodes that reached the cap.

Definitions:

- ``steps``: moving commands executed (``env.step`` calls), the colliding one included; an
  episode that reaches the cap has ``steps == max_steps`` and ``truncated``.
- ``distance_m``: straight-line distance from the start to the final pose (the paper's
  "moving distance"); ``path_length_m``: length of the driven path.
- ``coverage_m2`` / ``coverage_fraction``: free map cells the depth camera saw during the
  episode (``shared.sim.maps.CoverageTracker``, fed the start observation and every step's),
  in m^2 and as a fraction of the world's free area.
- ``trajectory_xy``: the start position and the position after every step (``steps + 1``
  points), or empty when a caller drops it to save space.

The results JSON (schema ``cogexplore.eval-results/2``)::

    {"schema": "cogexplore.eval-results/2",
     "meta": {"protocol": {...},    # required: the ProtocolConfig's every field (name, jitter, noise)
              ...},                 # free-form otherwise: model, policy_version, world, seed, ...
     "episodes": [EpisodeResult, ...],   # fields as in EpisodeResult, trajectory as [[x, y], ...]
     "summary": aggregate(episodes)}     # derived; checked against the episodes on load

Schema 1 (before results recorded their protocol) is refused: its figures cannot say whether the
starts were exact or jittered.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from shared.config import ConfigError, is_finite_number, is_whole
from shared.errors import CogexploreError
from shared.evaluation import ProtocolConfig
from shared.files import atomic_write_text
from shared.jsontext import parse_json, read_json_file

SCHEMA_ID = "cogexplore.eval-results/2"
_SCHEMA_WITHOUT_PROTOCOL = "cogexplore.eval-results/1"

MAX_EPISODE_COUNT = 2**31 - 1
"""The largest start index, episode index or step count a results file may hold (far beyond any protocol)."""

COLLISION_CAUSES: tuple[str, ...] = ("depth", "contact")


class ResultsError(CogexploreError):
    """Results that break the schema or the protocol's invariants; the message names the
    offending field by its JSON path (e.g. ``episodes[3].steps``)."""


# ---------------------------------------------------------------------------
# The per-episode record
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class EpisodeResult:
    """One test episode (see the module docstring for each field's definition)."""

    start_index: int
    episode: int
    steps: int
    terminated: bool
    truncated: bool
    collision_cause: str | None
    distance_m: float
    path_length_m: float
    coverage_m2: float
    coverage_fraction: float
    trajectory_xy: tuple[tuple[float, float], ...] = field(default=(), repr=False)

    def __post_init__(self) -> None:
        if isinstance(self.trajectory_xy, np.ndarray):
            object.__setattr__(self, "trajectory_xy", tuple(map(tuple, self.trajectory_xy.tolist())))
        _check_episode(asdict(self), "episode")
        object.__setattr__(self, "trajectory_xy",
                           tuple((float(x), float(y)) for x, y in self.trajectory_xy))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict (trajectory as a list of [x, y])."""
        d = asdict(self)
        d["trajectory_xy"] = [[x, y] for x, y in self.trajectory_xy]
        return d

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "episode") -> "EpisodeResult":
        """Build from a JSON object, with errors naming ``where``."""
        if not isinstance(data, Mapping):
            raise ResultsError(f"{where}: expected an object, got {type(data).__name__}")
        _check_episode(data, where)
        return cls(**{f.name: data[f.name] for f in fields(cls)})


_EPISODE_FIELDS = tuple(f.name for f in fields(EpisodeResult))


def _check_episode(d: Mapping[str, Any], where: str) -> None:
    missing = [k for k in _EPISODE_FIELDS if k not in d]
    unknown = sorted(set(d) - set(_EPISODE_FIELDS))
    if missing or unknown:
        raise ResultsError(f"{where}: missing fields {missing}, unknown fields {unknown}")

    def need(ok: bool, key: str, want: str) -> None:
        if not ok:
            raise ResultsError(f"{where}.{key}: expected {want}, got {d[key]!r}")

    for key in ("start_index", "episode", "steps"):
        # bounded: a count of hundreds of digits would overflow the float statistics built from it
        need(is_whole(d[key]) and 0 <= d[key] <= MAX_EPISODE_COUNT, key, f"an integer in [0, {MAX_EPISODE_COUNT}]")
    for key in ("terminated", "truncated"):
        need(isinstance(d[key], (bool, np.bool_)), key, "true or false")
    need(d["collision_cause"] is None or d["collision_cause"] in COLLISION_CAUSES, "collision_cause",
         f"null or one of {list(COLLISION_CAUSES)}")
    for key in ("distance_m", "path_length_m", "coverage_m2"):
        need(is_finite_number(d[key]) and d[key] >= 0, key, "a finite number >= 0")
    need(is_finite_number(d["coverage_fraction"]) and 0 <= d["coverage_fraction"] <= 1 + 1e-9, "coverage_fraction",
         "a number in [0, 1]")
    # a straight line is never longer than the path between its ends (a little float slack)
    need(d["distance_m"] <= d["path_length_m"] + 1e-6, "distance_m",
         f"at most path_length_m = {d['path_length_m']!r} (the straight line from the start to the end)")
    if d["terminated"] and d["truncated"]:
        raise ResultsError(f"{where}: an episode cannot be both terminated (collision) and truncated (cap)")
    if bool(d["terminated"]) != (d["collision_cause"] is not None):
        raise ResultsError(f"{where}: terminated is {d['terminated']} but collision_cause is "
                           f"{d['collision_cause']!r}; a collision and its cause go together")
    traj = d["trajectory_xy"]
    if not isinstance(traj, (list, tuple)):
        need(False, "trajectory_xy", "a list of [x, y] points")
    for i, p in enumerate(traj):
        if not (isinstance(p, (list, tuple)) and len(p) == 2 and all(is_finite_number(v) for v in p)):
            raise ResultsError(f"{where}.trajectory_xy[{i}]: expected [x, y] finite numbers, got {p!r}")
    if traj and len(traj) != d["steps"] + 1:
        raise ResultsError(f"{where}.trajectory_xy: {len(traj)} points for {d['steps']} steps; expected "
                           f"steps + 1 (the start and each step's position) or none")


# ---------------------------------------------------------------------------
# Aggregation
# ---------------------------------------------------------------------------


def _stats(episodes: Sequence[EpisodeResult]) -> dict[str, Any]:
    steps = np.array([e.steps for e in episodes], dtype=np.float64)
    collisions = {cause: sum(1 for e in episodes if e.collision_cause == cause) for cause in COLLISION_CAUSES}
    return {
        "episodes": len(episodes),
        "mean_steps": float(steps.mean()),
        "std_steps": float(steps.std()),
        "mean_distance_m": float(np.mean([e.distance_m for e in episodes])),
        "mean_path_length_m": float(np.mean([e.path_length_m for e in episodes])),
        "mean_coverage_m2": float(np.mean([e.coverage_m2 for e in episodes])),
        "mean_coverage_pct": float(100.0 * np.mean([e.coverage_fraction for e in episodes])),
        "collisions": collisions,
        "collision_episodes": sum(collisions.values()),
        "reached_cap": sum(1 for e in episodes if e.truncated),
    }


def aggregate(episodes: Iterable[EpisodeResult]) -> dict[str, Any]:
    """Per-start and overall statistics: ``{"overall": {...}, "per_start": [{"start_index": i,
    ...}, ...]}`` (per_start sorted by start index). Each part holds ``episodes``,
    ``mean_steps``, ``std_steps``, ``mean_distance_m``, ``mean_path_length_m``,
    ``mean_coverage_m2``, ``mean_coverage_pct``, ``collisions`` ({cause: count}),
    ``collision_episodes`` and ``reached_cap``."""
    eps = list(episodes)
    if not eps:
        raise ResultsError("cannot aggregate zero episodes")
    for i, e in enumerate(eps):
        if not isinstance(e, EpisodeResult):
            raise ResultsError(f"episodes[{i}]: expected an EpisodeResult, got {type(e).__name__}")
    by_start: dict[int, list[EpisodeResult]] = {}
    for e in eps:
        by_start.setdefault(e.start_index, []).append(e)
    return {
        "overall": _stats(eps),
        "per_start": [{"start_index": s, **_stats(by_start[s])} for s in sorted(by_start)],
    }


# ---------------------------------------------------------------------------
# The results file
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class EvalResults:
    """The episodes of one evaluation and what they were run with."""

    episodes: tuple[EpisodeResult, ...]
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "episodes", tuple(self.episodes))
        seen: set[tuple[int, int]] = set()
        for i, e in enumerate(self.episodes):
            if not isinstance(e, EpisodeResult):
                raise ResultsError(f"episodes[{i}]: expected an EpisodeResult, got {type(e).__name__}")
            key = (e.start_index, e.episode)
            if key in seen:
                raise ResultsError(f"episodes[{i}]: start_index {key[0]} episode {key[1]} appears twice")
            seen.add(key)
        try:
            json.dumps(dict(self.meta), allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ResultsError(f"meta must be a JSON object of finite values: {exc}") from None

    @property
    def summary(self) -> dict[str, Any]:
        return aggregate(self.episodes)

    @property
    def protocol(self) -> ProtocolConfig:
        """The conditions the episodes ran under (``meta.protocol``); ResultsError without one."""
        return _protocol_of(self.meta)

    def to_dict(self) -> dict[str, Any]:
        """The results document; ResultsError when ``meta`` lacks the protocol (it could not be read back)."""
        _protocol_of(self.meta)
        return {"schema": SCHEMA_ID, "meta": dict(self.meta),
                "episodes": [e.to_dict() for e in self.episodes], "summary": self.summary}


def to_json(results: EvalResults, indent: int | None = None) -> str:
    """The results document as JSON text (see the module docstring for the schema); compact
    by default, since the trajectories of a full protocol are ~50,000 numbers."""
    return json.dumps(results.to_dict(), indent=indent, allow_nan=False)


def save_results(results: EvalResults, path: str | Path) -> Path:
    """Write the results JSON atomically (a reader never sees half a file)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(out, to_json(results))


def slug(name: str) -> str:
    """A file-name-safe form of a model or scene name."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", name).strip("-") or "model"


def load_results(path: str | Path) -> EvalResults:
    """Read and validate a results JSON file."""
    p = Path(path)
    if not p.exists():
        raise ResultsError(f"results file {p} does not exist")
    document = read_json_file(p, "results file", ResultsError)
    try:
        return validate_results_json(document)
    except ResultsError as exc:
        raise ResultsError(f"{p}: {exc}") from None


def _protocol_of(meta: Mapping[str, Any]) -> ProtocolConfig:
    if "protocol" not in meta:
        raise ResultsError("meta.protocol: missing; results must say which test protocol ran (evaluate again: "
                           "--protocol paper gives the exact starts without noise)")
    try:
        return ProtocolConfig.from_dict(meta["protocol"])
    except ConfigError as exc:
        raise ResultsError(f"meta.protocol: {exc}") from None


def _close(a: Any, b: Any, where: str) -> None:
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        if set(a) != set(b):
            raise ResultsError(f"{where}: keys {sorted(a)} differ from the recomputed {sorted(b)}")
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            raise ResultsError(f"{where}: {len(a)} entries, the episodes give {len(b)}")
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{where}[{i}]")
    elif is_finite_number(a) and is_finite_number(b):
        if not math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-9):
            raise ResultsError(f"{where}: {a!r} does not match {b!r} recomputed from the episodes")
    elif a != b:
        raise ResultsError(f"{where}: {a!r} does not match {b!r} recomputed from the episodes")


def _check_run(meta: Mapping[str, Any], episodes: Sequence[EpisodeResult]) -> None:
    """The episodes a protocol run's meta promises (``starts``, ``episodes_per_start``,
    ``max_steps``, where it records them): every (start, episode) once and no step past the cap.
    A report reuses results by their meta; one missing episodes or over the cap would stand for a
    full run it is not."""
    cap = meta.get("max_steps")
    if cap is not None:
        if not (is_whole(cap) and cap >= 1):
            raise ResultsError(f"meta.max_steps: expected an integer >= 1, got {cap!r}")
        over = next((i for i, e in enumerate(episodes) if e.steps > cap), None)
        if over is not None:
            raise ResultsError(f"episodes[{over}].steps: {episodes[over].steps} is past meta.max_steps = {cap}")
        # every protocol episode ends at a collision or at the cap: "reached cap" counts the latter
        odd = next((i for i, e in enumerate(episodes) if e.truncated != (not e.terminated)
                    or (e.truncated and e.steps != cap)), None)
        if odd is not None:
            e = episodes[odd]
            raise ResultsError(f"episodes[{odd}]: {e.steps} steps, terminated {e.terminated}, truncated {e.truncated}; "
                               f"an episode ends at a collision (terminated) or at meta.max_steps = {cap} (truncated)")
    starts, per = meta.get("starts"), meta.get("episodes_per_start")
    if starts is None or per is None:
        return
    if not (isinstance(starts, list) and starts and all(is_whole(s) and s >= 0 for s in starts)):
        raise ResultsError(f"meta.starts: expected a non-empty list of start indices, got {starts!r}")
    if not (is_whole(per) and per >= 1):
        raise ResultsError(f"meta.episodes_per_start: expected an integer >= 1, got {per!r}")
    have = {(e.start_index, e.episode) for e in episodes}
    # bounded by the episodes, not by a hostile episodes_per_start
    missing = sorted((s, k) for s in set(starts) for k in range(min(per, len(episodes) + 1)) if (s, k) not in have)
    extra = sorted((s, k) for s, k in have if s not in starts or k >= per)
    if missing or extra or len(episodes) != len(set(starts)) * per:
        raise ResultsError(f"episodes: {len(episodes)} for meta.starts {starts} x {per} per start; "
                           f"(start, episode) missing {missing[:5]}, unexpected {extra[:5]}")


def validate_results_json(data: str | bytes | Mapping[str, Any]) -> EvalResults:
    """Check a results document (JSON text or the parsed object) against the schema and
    return it as :class:`EvalResults`; a :class:`ResultsError` names the first problem."""
    if isinstance(data, (str, bytes)):
        data = parse_json(data, "the document", ResultsError)
    if not isinstance(data, Mapping):
        raise ResultsError(f"a results document must be a JSON object, got {type(data).__name__}")
    want = {"schema", "meta", "episodes", "summary"}
    if set(data) != want:
        raise ResultsError(f"top-level keys must be {sorted(want)}; missing {sorted(want - set(data))}, "
                           f"unknown {sorted(set(data) - want)}")
    if data["schema"] == _SCHEMA_WITHOUT_PROTOCOL:
        raise ResultsError(f"schema {_SCHEMA_WITHOUT_PROTOCOL!r} was written before results recorded their "
                           "test protocol; evaluate again (--protocol paper gives the exact starts without noise)")
    if data["schema"] != SCHEMA_ID:
        raise ResultsError(f"schema: expected {SCHEMA_ID!r}, got {data['schema']!r}")
    if not isinstance(data["meta"], Mapping):
        raise ResultsError(f"meta: expected an object, got {type(data['meta']).__name__}")
    _protocol_of(data["meta"])
    if not isinstance(data["episodes"], list) or not data["episodes"]:
        raise ResultsError("episodes: expected a non-empty list")
    episodes = [EpisodeResult.from_dict(e, f"episodes[{i}]") for i, e in enumerate(data["episodes"])]
    _check_run(data["meta"], episodes)
    results = EvalResults(tuple(episodes), dict(data["meta"]))
    if not isinstance(data["summary"], Mapping):
        raise ResultsError(f"summary: expected an object, got {type(data['summary']).__name__}")
    _close(dict(data["summary"]), results.summary, "summary")
    return results


# ---------------------------------------------------------------------------
# Table III
# ---------------------------------------------------------------------------


def episodes_of(results: EvalResults | Mapping[str, Any] | Sequence[EpisodeResult]) -> tuple[EpisodeResult, ...]:
    """The episodes of an EvalResults, of a results JSON object (validated) or of a sequence."""
    if isinstance(results, EvalResults):
        return results.episodes
    if isinstance(results, Mapping):
        return validate_results_json(results).episodes
    return tuple(results)


_MARKDOWN_SPECIAL = re.compile(r"([\\`*_\[\]<>&~])")


def escape_text(value: object) -> str:
    """``value`` as literal Markdown text: a name holding ``]``, ``*``, ``_`` or ``<`` stays the name
    in a link, a table or a paragraph instead of becoming (or breaking) markup or an HTML tag
    (GFM's too; a table cell's ``|`` is :func:`markdown_cell`'s to escape)."""
    return _MARKDOWN_SPECIAL.sub(r"\\\1", str(value))


def one_line(text: object) -> str:
    """``text`` with its line breaks read as blanks: a Markdown heading, list item, table row or code
    span is one line, and a break would end it, leaving the rest outside it."""
    return " ".join(str(text).splitlines())


def markdown_cell(text: str) -> str:
    """``text`` as a Markdown pipe table's cell: its ``|`` escaped, as GFM reads it (in code spans
    too), so a model named ``a|b`` stays one cell, and a line break read as a space (a row is one
    line: the rest of the name would start a paragraph below the table)."""
    return one_line(str(text).replace("|", "\\|"))


def table_markdown(models: Mapping[str, EvalResults | Mapping[str, Any] | Sequence[EpisodeResult]],
                   decimals: int = 1) -> str:
    """The paper's Table III as Markdown: rows Count (mean moving steps) and Distance (mean
    start-to-end distance, m) per model, plus our Coverage (% of free area) rows; columns the
    start points numbered from 1 as in the paper, and an "All" column over every episode.
    The best value of each column within a metric is bold; a start a model has no episode
    from reads "-"."""
    if not models:
        raise ResultsError("table_markdown needs at least one model")
    summaries = {name: aggregate(episodes_of(r)) for name, r in models.items()}
    starts = sorted({p["start_index"] for s in summaries.values() for p in s["per_start"]})
    header = "| Metric | Model | " + " | ".join(str(s + 1) for s in starts) + " | All |"
    rule = "|---|---|" + "---:|" * (len(starts) + 1)
    lines = [header, rule]
    for label, key in (("Count", "mean_steps"), ("Distance (m)", "mean_distance_m"),
                       ("Coverage (%)", "mean_coverage_pct")):
        grid: dict[str, list[float | None]] = {}
        for name, summ in summaries.items():
            per = {p["start_index"]: p[key] for p in summ["per_start"]}
            grid[name] = [per.get(s) for s in starts] + [summ["overall"][key]]
        columns = list(zip(*grid.values()))
        best = [max((v for v in col if v is not None), default=None) for col in columns]
        for row, (name, values) in enumerate(grid.items()):
            cells = []
            for v, b in zip(values, best):
                if v is None:
                    cells.append("-")
                else:
                    text = f"{v:.{decimals}f}"
                    bold = len(grid) > 1 and b is not None and f"{b:.{decimals}f}" == text
                    cells.append(f"**{text}**" if bold else text)
            lines.append(f"| {label if row == 0 else ''} | {markdown_cell(escape_text(name))} | "
                         + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------
# The protocol
# ---------------------------------------------------------------------------


