"""The paper's figures and tables from evaluation results and training logs.

- Fig. 6: trajectory heatmaps -- visits per map cell of every trajectory point of every test
  episode, normalised to [0, 1] by the busiest cell, drawn over the world map; one PNG per
  model (``save_heatmap_png``) or several models side by side (``save_heatmaps_side_by_side``).
- A loss curve (raw and smoothed) from the learner's log (``save_loss_curve_png``).
- Table II: Q-values of the five commands for given scenes (``q_value_table_markdown``).

Everything draws on ``matplotlib.figure.Figure`` directly (no pyplot): no global figure
state and no GUI backend, so it is safe in services and threads.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from shared.errors import CogexploreError
from shared.evaluation.results import EpisodeResult, EvalResults, episodes_of, escape_text, markdown_cell, one_line
from shared.files import read_regular_file, save_png
from shared.jsontext import parse_json
from shared.learning.stats import read_csv_records
from shared.sim.maps import (
    OccupancyGrid,
    draw_map,
    drawable_aspect,
    normalize_heatmap,
    plain_text,
    render_map_png,
    visit_counts,
)
from shared.sim.world import World

logger = logging.getLogger("cogexplore.figures")

# Column labels of the paper's Table II.
PAPER_COMMAND_LABELS: tuple[str, ...] = ("Left", "H-Left", "Straight", "H-Right", "Right")


class FigureError(CogexploreError):
    """Bad input to a figure or table: empty results, a malformed log, wrong lengths."""


# ---------------------------------------------------------------------------
# Heatmaps
# ---------------------------------------------------------------------------


def trajectory_points(results: EvalResults | Sequence[EpisodeResult]) -> np.ndarray:
    """(N, 2) every trajectory point of every episode (start and each step's position)."""
    episodes = episodes_of(results)
    pts = [p for e in episodes for p in e.trajectory_xy]
    if not pts:
        raise FigureError("the results hold no trajectory points (were they run with keep_trajectories=False?)")
    return np.asarray(pts, dtype=np.float64)


HEATMAP_CELL_M = 0.25
"""Heatmap cell side: coarser than the 5 cm occupancy grid, so that paths 12.5 cm a step
apart read as bands rather than dotted lines."""


def trajectory_heatmap(grid: OccupancyGrid, results: EvalResults | Sequence[EpisodeResult],
                       cell_m: float | None = HEATMAP_CELL_M) -> np.ndarray:
    """Visit counts of all trajectory points over all episodes, normalised to [0, 1] by the
    busiest cell (the paper's Fig. 6), as a (ny, nx) array on ``grid``'s cells (row 0 the
    lowest y, like ``grid.occupied``).

    Points are counted in square cells of about ``cell_m`` (a whole number ``k`` of grid cells,
    blocks anchored at the grid's origin); every grid cell of a block carries the block's
    value, so the result overlays the map exactly. ``cell_m=None`` counts per grid cell."""
    counts = visit_counts(grid, trajectory_points(results))
    k = 1 if cell_m is None else max(1, int(round(cell_m / grid.resolution_m)))
    if k > 1:
        ny, nx = counts.shape
        by, bx = -(-ny // k), -(-nx // k)
        padded = np.zeros((by * k, bx * k), dtype=counts.dtype)
        padded[:ny, :nx] = counts
        blocks = padded.reshape(by, k, bx, k).sum(axis=(1, 3))
        counts = np.kron(blocks, np.ones((k, k), dtype=counts.dtype))[:ny, :nx]
    return normalize_heatmap(counts)


def check_results_world(world: World, results: EvalResults | Sequence[EpisodeResult], what: str = "the results") -> None:
    """FigureError when ``results`` say they were played in another world than ``world`` (their
    ``meta.world_sha256``, else their ``meta.world`` name): their points drawn on this map would be
    off it (a blank map) or in the wrong rooms. Results that do not say are taken as they come."""
    from shared.evaluation.protocol import WORLD_META, world_sha256

    meta = results.meta if isinstance(results, EvalResults) else {}
    played_in, digest = meta.get("world"), meta.get(WORLD_META)
    # the content, not the name, when recorded: a file world edited since is another map under its old name
    same = digest == world_sha256(world) if isinstance(digest, str) else played_in in (None, world.name)
    if not same:
        named = f"world '{one_line(played_in)}'" if isinstance(played_in, str) else "another world"
        edited = " as it was before an edit" if played_in == world.name else ""
        raise FigureError(f"{one_line(what)} were played in {named}{edited}, not {world.label} being "
                          f"drawn: draw them on their own world")


def save_heatmap_png(world: World, grid: OccupancyGrid, results: EvalResults | Sequence[EpisodeResult],
                     out_path: str | Path, title: str | None = None,
                     cell_m: float | None = HEATMAP_CELL_M, dpi: int = 120) -> Path:
    """One model's trajectory heatmap over the world map (starts numbered from 1); ``title`` (default
    the world's name, a file world's path) is plain text. FigureError for results of another world."""
    check_results_world(world, results)
    return render_map_png(world, grid, out_path, heatmap=trajectory_heatmap(grid, results, cell_m),
                          title=title, dpi=dpi)


def save_heatmaps_side_by_side(world: World, grid: OccupancyGrid,
                               models: Mapping[str, EvalResults | Sequence[EpisodeResult]],
                               out_path: str | Path, ncols: int | None = None, dpi: int = 110,
                               cell_m: float | None = HEATMAP_CELL_M) -> Path:
    """Several models' heatmaps in one PNG (the paper's Fig. 6 panels), one shared colour
    scale: each panel is normalised to its own busiest cell, as in the paper. FigureError when a
    model's results are of another world."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not models:
        raise FigureError("save_heatmaps_side_by_side needs at least one model")
    for name, results in models.items():  # before anything is drawn
        check_results_world(world, results, f"{name}'s results")
    n = len(models)
    ncols = ncols or min(n, 3)
    nrows = math.ceil(n / ncols)
    xmin, ymin, xmax, ymax = grid.extent
    aspect = drawable_aspect((xmax - xmin) / (ymax - ymin))  # a corridor world's PNG was 110,000 pixels wide
    panel = 3.6
    fig = Figure(figsize=(panel * aspect * ncols + 0.9, panel * nrows + 0.3))
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    im = None
    for ax, (name, results) in zip(axes.flat, models.items()):
        im = draw_map(ax, world, grid, heatmap=trajectory_heatmap(grid, results, cell_m), title=name, small=True)
    for ax in list(axes.flat)[n:]:
        ax.set_axis_off()
    fig.colorbar(im, ax=axes.ravel().tolist(), fraction=0.025, pad=0.02, label="normalised visits")
    return save_png(fig, out_path, dpi)


# ---------------------------------------------------------------------------
# Loss curve
# ---------------------------------------------------------------------------


def _row_numbers(row: Any, i: int, source: str) -> tuple[float, float]:
    if not isinstance(row, Mapping):
        raise FigureError(f"{source}: row {i} is not an object with 'update' and 'loss'")
    if "update" not in row or "loss" not in row:
        raise FigureError(f"{source}: row {i} lacks 'update' or 'loss' (has {sorted(map(str, row))})")
    update, loss = row["update"], row["loss"]
    try:
        return float(update), float(loss) if loss not in ("", None) else math.nan
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer past float's range
        raise FigureError(f"{source}: row {i} has a non-numeric update or loss: "
                          f"{str(update)[:40]!r}, {str(loss)[:40]!r}") from None


def _rows_to_arrays(rows: Iterable[Any], source: str, skip_bad: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The rows' updates and losses; with ``skip_bad`` (a learner's own log, whose last line a
    killed process can tear) a row that is not two numbers, or is short of cells, is left out,
    unless every row is."""
    updates, losses, bad = [], [], []
    for i, row in enumerate(rows):
        try:
            if skip_bad and isinstance(row, Mapping) and None in row.values():
                # short of the header's cells (read_csv_records' None): a killed writer's torn line,
                # whose last cell may be cut short too ("0.0123" read as 0.0)
                raise FigureError(f"{source}: row {i} is torn (cells missing)")
            update, loss = _row_numbers(row, i, source)
        except FigureError as exc:
            if not skip_bad:
                raise
            bad.append(exc)
            continue
        updates.append(update)
        losses.append(loss)
    if bad and not updates:
        raise bad[0]
    if bad:
        logger.warning("%s: %d row(s) left out, torn or not numbers (first: %s)", source, len(bad), bad[0])
    return np.asarray(updates, dtype=np.float64), np.asarray(losses, dtype=np.float64)


def load_loss_log(log: str | Path | Sequence[Mapping[str, Any]] | Mapping[str, Sequence[float]]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(updates, losses) sorted by update from a CSV file (header with ``update`` and
    ``loss``; other columns ignored), a JSON file (a list of row objects or an object of
    columns), a JSON Lines file (``.jsonl``, one row per line), or those objects in memory.
    Rows with an empty or non-finite loss are dropped (a diverged run still plots); so are a CSV
    file's rows that do not parse or are short of cells (the learner's log after a crash: its torn
    last line), unless all of them are."""
    source = "loss log"
    if isinstance(log, (str, Path)):
        path = Path(log)
        source = str(path)
        try:
            if path.suffix == ".csv":
                records = list(read_csv_records(path))
            else:
                text = read_regular_file(path).decode()
        except FileNotFoundError:
            raise FigureError(f"loss log {path} does not exist") from None
        except (OSError, UnicodeDecodeError) as exc:  # a folder, no permission, binary bytes
            raise FigureError(f"loss log {path} cannot be read as text: {exc}") from None
        if path.suffix == ".csv":
            columns = list(records[0]) if records else []
            if not {"update", "loss"} <= set(columns):
                raise FigureError(f"{path}: the CSV header must name 'update' and 'loss' and rows must "
                                  f"follow it, got {columns or 'no rows'}")
            updates, losses = _rows_to_arrays(records, source, skip_bad=True)
            return _finite_sorted(updates, losses, source)
        if path.suffix == ".jsonl":
            log = [parse_json(line, str(path), FigureError) for line in text.splitlines() if line.strip()]
        else:
            log = parse_json(text, str(path), FigureError)
    if isinstance(log, Mapping):
        if "update" not in log or "loss" not in log:
            raise FigureError(f"{source}: a column object needs 'update' and 'loss', has {sorted(map(str, log))}")
        if not all(isinstance(log[k], (Sequence, np.ndarray)) and not isinstance(log[k], str)
                   for k in ("update", "loss")):
            raise FigureError(f"{source}: a column object's 'update' and 'loss' must be lists of numbers")
        if len(log["update"]) != len(log["loss"]):
            raise FigureError(f"{source}: {len(log['update'])} updates but {len(log['loss'])} losses")
        log = [{"update": u, "loss": v} for u, v in zip(log["update"], log["loss"])]
    if not isinstance(log, Sequence) or isinstance(log, str):
        raise FigureError(f"{source}: a loss log is a list of rows or an object of columns, "
                          f"got {type(log).__name__}")
    updates, losses = _rows_to_arrays(log, source)
    return _finite_sorted(updates, losses, source)


def _finite_sorted(updates: np.ndarray, losses: np.ndarray, source: str) -> tuple[np.ndarray, np.ndarray]:
    keep = np.isfinite(updates) & np.isfinite(losses)
    if not keep.any():
        raise FigureError(f"{source}: no row with a finite loss")
    order = np.argsort(updates[keep], kind="stable")
    return updates[keep][order], losses[keep][order]


def smooth(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average over ``window`` points (fewer at the start), same length."""
    if not (isinstance(window, int) and window >= 1):
        raise FigureError(f"smoothing window must be an integer >= 1, got {window!r}")
    v = np.asarray(values, dtype=np.float64)
    csum = np.concatenate([[0.0], np.cumsum(v)])
    idx = np.arange(1, len(v) + 1)
    lo = np.maximum(0, idx - window)
    return (csum[idx] - csum[lo]) / (idx - lo)


def save_loss_curve_png(log: Any, out_path: str | Path, smooth_window: int | None = None,
                        log_y: bool | str = "auto", title: str = "Training loss", dpi: int = 110) -> Path:
    """Loss against learner updates: raw points faint, a trailing moving average bold.
    ``smooth_window`` defaults to 1/50 of the rows (at least 1); ``log_y='auto'`` uses a log
    axis when all losses are positive and span more than two decades. ``title`` is plain text."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    updates, losses = load_loss_log(log)
    window = smooth_window if smooth_window is not None else max(1, len(losses) // 50)
    smoothed = smooth(losses, window)
    if log_y == "auto":
        log_y = bool(losses.min() > 0 and losses.max() / losses.min() > 100)
    fig = Figure(figsize=(7.0, 4.0))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    # a line through one point draws nothing: a log of one row shows its point as a dot
    marker = "o" if len(losses) == 1 else None
    ax.plot(updates, losses, color="#1f77b4", alpha=0.3, lw=0.8, label="raw")
    ax.plot(updates, smoothed, color="#1f77b4", lw=2.0, marker=marker, label=f"moving average ({window})")
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel("learner update")
    ax.set_ylabel("loss")
    ax.set_title(plain_text(title))
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return save_png(fig, out_path, dpi)


# ---------------------------------------------------------------------------
# Table II
# ---------------------------------------------------------------------------


def q_value_table_markdown(scenes: Mapping[str, Mapping[str, Sequence[float] | np.ndarray]],
                           decimals: int = 1) -> str:
    """The paper's Table II: for each scene (S1, R1, ...) and model (SL, DRL, ...), the five
    commands' values, the chosen (highest) one bold.

    ``scenes`` maps scene name -> {model name -> five values}."""
    if not scenes:
        raise FigureError("q_value_table_markdown needs at least one scene")
    lines = ["| Scene | Model | " + " | ".join(PAPER_COMMAND_LABELS) + " |",
             "|---|---|" + "---:|" * len(PAPER_COMMAND_LABELS)]
    for scene, models in scenes.items():
        if not models:
            raise FigureError(f"scene {scene!r} has no model")
        for row, (model, values) in enumerate(models.items()):
            try:
                q = np.asarray(values, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):  # text, a ragged list, an object
                q = np.full(1, np.nan)
            if q.shape != (len(PAPER_COMMAND_LABELS),) or not np.all(np.isfinite(q)):
                raise FigureError(f"scene {scene!r} model {model!r}: need {len(PAPER_COMMAND_LABELS)} finite "
                                  f"values, got {str(values)[:80]}")
            best = int(np.argmax(q))
            cells = [f"**{v:.{decimals}f}**" if i == best else f"{v:.{decimals}f}" for i, v in enumerate(q)]
            name = markdown_cell(escape_text(scene)) if row == 0 else ""
            lines.append(f"| {name} | {markdown_cell(escape_text(model))} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
