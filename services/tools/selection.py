"""Choosing the model to ship from one training run (``cogexplore model select``).

The greedy policy of a DQN run swings from checkpoint to checkpoint, so the shipped model is
the mean of ``window`` consecutive checkpoints' weights (``shared.learning.model.average_weights``), and
the window is chosen by a rule fixed before any test world is played:

1. every window is scored on the *gate* world (``paper-indoor``: the training world) under the
   test ``protocol`` (default the robust one: jittered starts and sensor noise, so a window
   cannot pass by remembering trajectories from exact poses) and kept when it reaches
   ``gate_min`` mean steps (the goal, 150) and, with
   ``gate_start_min``, every start of it reaches that many (the goal: 60);
2. the kept windows are scored on the *validation* worlds (procedural worlds never trained on
   and never used as test worlds) and the best mean over them wins (ties: the later window);
3. when no window reaches the gate, the best gate score wins (and the report says so).

Test worlds play no part in the choice: with ``test_worlds`` the chosen window alone is played
on them afterwards, once, and reported apart. Nor do the test's draws: the gate and validation
episodes are drawn from ``seed`` (default :data:`SELECTION_SEED`), the test's from
:data:`TEST_SEED` (``cogexplore evaluate`` and ``report``), so a window is never chosen on jittered
starts and sensor noise that its reported figures are then measured on.

Scores are cached in a JSON-lines file keyed by the window's weights digest and the protocol (with
the content of any gate or validation world that is an MJCF file), so an interrupted selection, or
one rerun with more checkpoints, only plays new windows.
:func:`windows`, :func:`choose` and :func:`window_rows_markdown` are pure; :func:`select` plays
the protocol.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from shared.config import is_finite_number
from shared.errors import CogexploreError
from shared.evaluation import (
    DEFAULT_PROTOCOL,
    PAPER_MAX_STEPS,
    PROTOCOLS,
    SELECTION_SEED,
    TEST_SEED,
    ProtocolConfig,
)
from shared.files import append_line, save_png
from shared.jsontext import parse_json

log = logging.getLogger("cogexplore.select")


class SelectionError(CogexploreError):
    """Bad selection input: no checkpoints, a bad window size or range, bad worlds."""


@dataclass(frozen=True)
class Window:
    """``size`` consecutive checkpoints of one run, named by the last one's update count."""

    end_update: int
    paths: tuple[Path, ...]


@dataclass(frozen=True)
class WindowScore:
    """One window's scores (mean moving steps of the protocol)."""

    end_update: int
    weights_sha256: str
    gate: float
    """Mean steps on the gate world."""
    validation: float | None
    """Mean over the validation worlds of each world's mean steps; None when the gate was missed
    (the validation worlds are not played then)."""
    per_world: dict[str, float]
    sources: tuple[str, ...]
    gate_worst_start: float | None = None
    """The lowest per-start mean steps on the gate world (None in scores cached before it was kept)."""

    def passes(self, gate_min: float, gate_start_min: float = 0.0) -> bool:
        """Whether the window reaches the gate: the mean and, when asked, every start."""
        return self.gate >= gate_min and (gate_start_min <= 0 or (self.gate_worst_start or 0.0) >= gate_start_min)

    def to_json(self) -> dict[str, Any]:
        return {**dataclasses.asdict(self), "sources": list(self.sources)}

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "WindowScore":
        """A cached score; ValueError for one no scoring writes (a NaN, an integer too large for a
        float, a string where a number goes), which would decide ``choose`` by chance."""
        return cls(int(d["end_update"]), str(d["weights_sha256"]), _steps(d["gate"]),
                   None if d["validation"] is None else _steps(d["validation"]),
                   {str(k): _steps(v) for k, v in d["per_world"].items()}, tuple(d["sources"]),
                   None if d.get("gate_worst_start") is None else _steps(d["gate_worst_start"]))


def _steps(value: Any) -> float:
    """A cached mean of moving steps: a finite number >= 0, else ValueError."""
    if not (is_finite_number(value) and value >= 0):
        raise ValueError(f"{value!r} is not a mean number of steps")
    return float(value)


def windows(checkpoints: Sequence[tuple[int, Path]], size: int, *, first_end: int = 0,
            last_end: int | None = None, stride: int = 1) -> list[Window]:
    """The windows of ``size`` consecutive checkpoints (``(update_count, path)``, any order)
    whose last update lies in [first_end, last_end], every ``stride``-th one counted back from
    the newest (so the newest window is always among them)."""
    if not (isinstance(size, int) and size >= 1):
        raise SelectionError(f"window size must be an integer >= 1, got {size!r}")
    if not (isinstance(stride, int) and stride >= 1):
        raise SelectionError(f"stride must be an integer >= 1, got {stride!r}")
    ordered = sorted(checkpoints)
    if len({u for u, _ in ordered}) != len(ordered):
        raise SelectionError("two checkpoints share an update count")
    ends = [i for i in range(size - 1, len(ordered))
            if ordered[i][0] >= first_end and (last_end is None or ordered[i][0] <= last_end)]
    ends = ends[::-1][::stride][::-1]
    return [Window(ordered[i][0], tuple(p for _, p in ordered[i - size + 1:i + 1])) for i in ends]


def choose(scores: Sequence[WindowScore], gate_min: float, gate_start_min: float = 0.0
           ) -> tuple[WindowScore, str]:
    """The chosen window and the rule that chose it (see the module doc)."""
    if not scores:
        raise SelectionError("no window was scored")
    gate = f"{gate_min:g}" + (f" (every start {gate_start_min:g})" if gate_start_min > 0 else "")
    passed = [s for s in scores if s.passes(gate_min, gate_start_min) and s.validation is not None]
    if passed:
        best = max(passed, key=lambda s: (s.validation, s.end_update))
        return best, (f"{len(passed)} of {len(scores)} windows reach {gate} on the gate world; "
                      f"the best validation mean ({best.validation:.1f})")
    best = max(scores, key=lambda s: (s.gate, s.end_update))
    return best, (f"no window of {len(scores)} reaches {gate} on the gate world; "
                  f"the best gate score ({best.gate:.1f})")


def window_rows_markdown(scores: Sequence[WindowScore], chosen: WindowScore | None = None,
                         gate_world: str = "gate") -> str:
    """A Markdown table of every window's scores, the chosen one in bold."""
    lines = [f"| window ending at | {gate_world} | worst start | validation mean |", "|---:|---:|---:|---:|"]
    for s in sorted(scores, key=lambda s: s.end_update):
        val = "—" if s.validation is None else f"{s.validation:.1f}"
        worst = "—" if s.gate_worst_start is None else f"{s.gate_worst_start:.1f}"
        row = [str(s.end_update), f"{s.gate:.1f}", worst, val]
        if chosen is not None and s.end_update == chosen.end_update:
            row = [f"**{c}**" for c in row]
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines) + "\n"


def wall_minutes(learner_csv: str | Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(updates, minutes of training) from a run's ``stats/learner.csv``, across resumes (each
    restarts its clock: the time before it is carried over); None without a usable file."""
    from shared.learning.stats import LearnerClock, read_csv_records

    updates, minutes, clock = [], [], LearnerClock()
    try:
        for row in read_csv_records(learner_csv):
            try:
                u = int(row["update"])
            except (KeyError, TypeError, ValueError):
                continue
            seconds = clock.at(row)
            if seconds is None:  # a damaged clock: a NaN or infinite time broke the figure's axis
                continue
            if not updates or u > updates[-1]:
                updates.append(u)
                minutes.append(seconds / 60.0)
    except OSError:
        return None
    if len(updates) < 2 or minutes[-1] <= minutes[0]:  # a clock that never moved maps no update to a minute
        return None
    return np.asarray(updates, dtype=np.float64), np.asarray(minutes, dtype=np.float64)


def save_selection_png(scores: Sequence[WindowScore], out_path: str | Path, *, gate_min: float,
                       gate_start_min: float = 0.0, chosen: WindowScore | None = None, gate_world: str = "gate",
                       title: str | None = None, clock: tuple[np.ndarray, np.ndarray] | None = None,
                       max_steps: int = PAPER_MAX_STEPS) -> Path:
    """Gate and validation scores of every window against updates, the gate threshold dashed and
    the chosen window starred (the model card's learning curve), with ``gate_start_min`` the worst
    start's score and that threshold too; with ``clock`` (see
    :func:`wall_minutes`) a top axis in minutes of training."""
    from matplotlib.figure import Figure

    rows = sorted(scores, key=lambda s: s.end_update)
    fig = Figure(figsize=(10, 4.2), dpi=110)
    ax = fig.add_subplot(1, 1, 1)
    ax.plot([s.end_update for s in rows], [s.gate for s in rows], "o-", ms=3, label=gate_world)
    worst = [s for s in rows if s.gate_worst_start is not None]
    if worst and gate_start_min > 0:
        ax.plot([s.end_update for s in worst], [s.gate_worst_start for s in worst], ".:", ms=3, lw=0.8,
                color="tab:green", label=f"{gate_world}, worst start")
        ax.axhline(gate_start_min, ls=":", color="tab:green", lw=1, label=f"every start {gate_start_min:g}")
    val = [s for s in rows if s.validation is not None]
    if val:
        ax.plot([s.end_update for s in val], [s.validation for s in val], "s", ms=4, label="validation mean")
    ax.axhline(gate_min, ls="--", color="grey", lw=1, label=f"gate {gate_min:g}")
    if chosen is not None:
        ax.plot([chosen.end_update], [chosen.gate], "*", ms=16, color="crimson", label="chosen")
    ax.set_xlabel("updates (last checkpoint of the window)")
    if clock is not None:
        u, m = clock
        top = ax.secondary_xaxis("top", functions=(lambda x: _extrapolate(x, u, m), lambda y: _extrapolate(y, m, u)))
        top.set_xlabel("minutes of training")
    ax.set_ylabel(f"mean moving steps (of {max_steps})")
    ax.set_ylim(0, max_steps * 1.025)
    ax.grid(alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)  # outside: the lines fill the plot
    ax.set_title(title or "mean of consecutive checkpoints' weights, by window")
    fig.tight_layout()
    return save_png(fig, out_path, dpi=fig.dpi)  # a rerun cut short keeps the last figure whole


def _extrapolate(x: Any, xp: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """``np.interp`` continued linearly past both ends (at the mean slope), so that an axis
    drawn through it stays monotone beyond the data."""
    x = np.asarray(x, dtype=np.float64)
    slope = (fp[-1] - fp[0]) / (xp[-1] - xp[0])
    y = np.interp(x, xp, fp)
    return np.where(x < xp[0], fp[0] + (x - xp[0]) * slope, np.where(x > xp[-1], fp[-1] + (x - xp[-1]) * slope, y))


# ---------------------------------------------------------------------------------------------
# Playing the protocol
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SelectOptions:
    """What ``cogexplore model select`` plays and keeps."""

    run: Path
    """A run folder or its ``checkpoints`` directory."""
    out: Path
    """The chosen window's weights export (.safetensors)."""
    window: int = 4
    stride: int = 1
    first_end: int = 0
    last_end: int | None = None
    gate_world: str = "paper-indoor"
    gate_min: float = 150.0
    gate_start_min: float = 0.0
    """Every start of the gate world must reach this many mean steps too (0: no such condition)."""
    validation_worlds: tuple[str, ...] = tuple(f"procedural:{s}" for s in range(201, 211))
    test_worlds: tuple[str, ...] = ()
    """Played by the chosen window only, after the choice (none: no test)."""
    episodes_per_start: int = 1
    max_steps: int = 200
    half: bool = False
    device: str = "auto"
    protocol: ProtocolConfig = PROTOCOLS[DEFAULT_PROTOCOL]
    """The test conditions every window is scored under (the export's ``selection`` records it)."""
    seed: int = SELECTION_SEED
    """Seed of the gate and validation episodes' draws (start jitter, sensor noise); the test
    worlds are played with :data:`TEST_SEED`."""


def _protocol_key(o: SelectOptions) -> dict[str, Any]:
    """What a cached score was scored under; with the content digest of each MJCF file world, whose
    name does not fix it (none for built-in and procedural worlds: their keys stay as they were)."""
    from shared.evaluation.protocol import WORLD_META, file_world_sha256

    key = {"gate_world": o.gate_world, "gate_min": o.gate_min, "gate_start_min": o.gate_start_min,
           "validation_worlds": list(o.validation_worlds),
           "episodes_per_start": o.episodes_per_start, "max_steps": o.max_steps,
           "protocol": o.protocol.to_dict(), "seed": o.seed}
    files = {w: digest for w in (o.gate_world, *o.validation_worlds) if (digest := file_world_sha256(w)) is not None}
    return {**key, WORLD_META: files} if files else key


def _load_cache(path: Path, key: dict[str, Any]) -> dict[str, WindowScore]:
    """Cached scores by weights digest, for this protocol only; unreadable lines are skipped."""
    cache: dict[str, WindowScore] = {}
    if not path.is_file():
        return cache
    for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        try:
            d = parse_json(line, "the line", SelectionError)
            if d.get("protocol") != key:
                continue
            score = WindowScore.from_json(d["score"])
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError) as exc:  # int(1e999) overflows
            log.warning("%s line %d skipped: %s", path, n, exc)
            continue
        cache[score.weights_sha256] = score
    return cache


def check_output(out: Path, sources: Sequence[Path], what: str = "--out") -> None:
    """SelectionError for an export path no file can take (a folder: ``.``, an existing one), found
    before any work, or one of the ``sources`` being read (a run's checkpoint): the export would
    replace it, and the run would lose it."""
    out = Path(out)
    if out.name in ("", "..") or out.is_dir():
        raise SelectionError(f"{what} {str(out)!r}: Is a directory (give a file name)")
    for src in sources:
        try:
            same = out.exists() and os.path.samefile(out, src)
        except OSError:
            continue
        if same:
            raise SelectionError(f"{what} {out} is {src}, a model it reads: write the export elsewhere")


def run_checkpoints(run: Path) -> list[tuple[int, Path]]:
    """(update count, path) of every checkpoint of a run folder or checkpoints directory."""
    from shared.learning.checkpoints import CheckpointManager

    run = Path(run)
    directory = run / "checkpoints" if (run / "checkpoints").is_dir() else run
    if not directory.is_dir():
        raise SelectionError(f"{run} is neither a run folder nor a checkpoints directory")
    found = [(int(p.stem.removeprefix("ckpt-")), p) for p in CheckpointManager(directory).checkpoints()]
    if not found:
        raise SelectionError(f"no checkpoints in {directory}")
    return found


def select(o: SelectOptions, echo: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Score every window, export the chosen one to ``o.out`` and draw ``<out>-windows.png``.
    Returns the summary that ``cogexplore model select`` prints."""
    from shared.evaluation.protocol import evaluate_policy
    from shared.evaluation.setup import setup_evaluation
    from shared.learning.checkpoints import CheckpointError, average_models, export_weights, load_model
    from shared.learning.model import ModelError, resolve_device
    from shared.sim.world import canonical_world_name, load_world

    echo = echo or (lambda _msg: None)
    try:
        resolve_device(o.device)  # else every window is skipped as if its checkpoints were damaged
    except ModelError as exc:
        raise SelectionError(f"--device: {exc}") from None
    # procedural:0301 is procedural:301: a test world must not pass as another name of the gate world
    o = dataclasses.replace(o, gate_world=canonical_world_name(o.gate_world),
                            validation_worlds=tuple(dict.fromkeys(map(canonical_world_name, o.validation_worlds))),
                            test_worlds=tuple(dict.fromkeys(map(canonical_world_name, o.test_worlds))))
    for name in ("gate_min", "gate_start_min"):
        value = getattr(o, name)
        if not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise SelectionError(f"{name.replace('_', ' ')} must be a finite number, got {value!r}")
    if not o.validation_worlds:
        raise SelectionError("give at least one validation world")
    if set(o.test_worlds) & {o.gate_world, *o.validation_worlds}:
        raise SelectionError("a test world is also the gate or a validation world: "
                             + ", ".join(sorted(set(o.test_worlds) & {o.gate_world, *o.validation_worlds})))
    for w in (o.gate_world, *o.validation_worlds, *o.test_worlds):
        load_world(w)  # a bad name or a broken file fails before any window is played
    found = run_checkpoints(o.run)
    check_output(o.out, [p for _, p in found])
    todo = windows(found, o.window, first_end=o.first_end, last_end=o.last_end, stride=o.stride)
    if not todo:
        raise SelectionError(f"no window of {o.window} checkpoints ends in the given range")
    echo(f"protocol {o.protocol.describe()}")
    cache_path = o.out.with_name(o.out.stem + "-windows.jsonl")
    key = _protocol_key(o)
    cache = _load_cache(cache_path, key)
    scores: list[WindowScore] = []

    def steps(setup: Any, world: str, seed: int) -> tuple[float, float]:
        """(mean steps, the lowest start's mean steps)."""
        results = evaluate_policy(setup.policy_fn, world=world, sensor_cfg=setup.sensor_cfg, env_cfg=setup.env_cfg,
                                  episodes_per_start=o.episodes_per_start, max_steps=o.max_steps, seed=seed,
                                  progress=False, meta=setup.meta(), protocol=o.protocol)
        summary = results.summary
        return (float(summary["overall"]["mean_steps"]),
                float(min(p["mean_steps"] for p in summary["per_start"])))

    def mean_steps(setup: Any, world: str, seed: int) -> float:
        return steps(setup, world, seed)[0]

    skipped: list[str] = []
    for i, win in enumerate(todo, 1):
        try:
            model = average_models([load_model(p, o.device) for p in win.paths])
        except CheckpointError as exc:  # one damaged file must not end hours of scoring: its windows go
            skipped.append(f"{win.end_update}: {exc}")
            echo(f"[{i}/{len(todo)}] window ending at {win.end_update}: skipped, its checkpoints cannot be read or "
                 f"averaged ({exc})")
            continue
        cached = cache.get(model.weights_sha256)
        if cached is not None:  # the same weights: this window's checkpoints, not where they were then
            score = dataclasses.replace(cached, end_update=win.end_update, sources=tuple(str(p) for p in win.paths))
        else:
            setup = setup_evaluation("greedy", world=o.gate_world, model=model, device=o.device)
            gate, worst = steps(setup, o.gate_world, o.seed)
            per_world = {o.gate_world: gate}
            score = WindowScore(win.end_update, model.weights_sha256, gate, None, per_world,
                                tuple(str(p) for p in win.paths), worst)
            if score.passes(o.gate_min, o.gate_start_min):
                for w in o.validation_worlds:
                    per_world[w] = mean_steps(setup_evaluation("greedy", world=w, model=model, device=o.device), w,
                                              o.seed)
                score = dataclasses.replace(
                    score, validation=sum(per_world[w] for w in o.validation_worlds) / len(o.validation_worlds))
            cache_path.parent.mkdir(parents=True, exist_ok=True)
            append_line(cache_path, json.dumps({"protocol": key, "score": score.to_json()}))
        scores.append(score)
        val = "" if score.validation is None else f", validation {score.validation:.1f}"
        worst = "" if score.gate_worst_start is None else f" (worst start {score.gate_worst_start:.1f})"
        echo(f"[{i}/{len(todo)}] window ending at {win.end_update}: {o.gate_world} {score.gate:.1f}{worst}{val}"
             + (" (cached)" if cached is not None else ""))
    if not scores:
        raise SelectionError(f"no window could be read: {skipped[0]}" + (f" (and {len(skipped) - 1} more)"
                                                                          if len(skipped) > 1 else ""))
    chosen, rule = choose(scores, o.gate_min, o.gate_start_min)
    model = average_models([load_model(p, o.device) for p in chosen.sources])
    if model.weights_sha256 != chosen.weights_sha256:  # rewritten since it was scored: its scores are not this one's
        raise SelectionError(f"the checkpoints of the window ending at {chosen.end_update} changed while the "
                             "windows were scored (a run resumed or written meanwhile?); run the selection again")
    selection = {"rule": rule, "window": o.window, "end_update": chosen.end_update, "gate_world": o.gate_world,
                 "gate_min": o.gate_min, "gate_start_min": o.gate_start_min, "gate": chosen.gate,
                 "gate_worst_start": chosen.gate_worst_start, "weights_sha256": chosen.weights_sha256,
                 "validation_worlds": list(o.validation_worlds),
                 "validation": chosen.validation, "windows_scored": len(scores), "windows_skipped": skipped,
                 "protocol": o.protocol.to_dict(),
                 "seed": o.seed}
    if o.test_worlds:
        echo(f"testing the window ending at {chosen.end_update} on {len(o.test_worlds)} test world(s)")
        per_world = {w: mean_steps(setup_evaluation("greedy", world=w, model=model, device=o.device), w, TEST_SEED)
                     for w in o.test_worlds}
        selection["test"] = {"mean": sum(per_world.values()) / len(per_world), "per_world": per_world}
    out = export_weights(o.out, model.net, model.policy_version, half=o.half, run_config=model.run_config,
                         extra={"averaged_from": list(model.averaged_from), "selection": selection})
    run_dir = o.run.parent if o.run.name == "checkpoints" else o.run
    clock = wall_minutes(run_dir / "stats" / "learner.csv")
    png = save_selection_png(scores, o.out.with_name(o.out.stem + "-windows.png"), gate_min=o.gate_min,
                             gate_start_min=o.gate_start_min, chosen=chosen, gate_world=o.gate_world, clock=clock,
                             max_steps=o.max_steps,
                             title=f"mean of consecutive checkpoints' weights, by window ({o.protocol.name} protocol)")
    first = min((s for s in scores if s.passes(o.gate_min, o.gate_start_min)), key=lambda s: s.end_update,
                default=None)
    minutes = (lambda update: None) if clock is None else (lambda update: round(float(np.interp(update, *clock)), 1))
    timing = {"chosen_minutes": minutes(chosen.end_update),
              "first_gate_update": None if first is None else first.end_update,
              "first_gate_minutes": None if first is None else minutes(first.end_update)}
    return {"out": str(out), "protocol": o.protocol.name, "chosen": chosen.to_json(), "rule": rule,
            "test": selection.get("test"), **timing,
            "windows": len(scores), "windows_skipped": skipped,
            "figure": str(png), "scores": str(cache_path),
            "table": window_rows_markdown(scores, chosen, o.gate_world)}

