"""Figures and tables: trajectory heatmaps, the loss curve, Table II."""

from __future__ import annotations

import json

import matplotlib.image as mpimg
import numpy as np
import pytest

from services.viz.figures import (
    FigureError,
    load_loss_log,
    q_value_table_markdown,
    save_heatmap_png,
    save_heatmaps_side_by_side,
    save_loss_curve_png,
    smooth,
    trajectory_heatmap,
    trajectory_points,
)
from shared.evaluation.results import EpisodeResult, EvalResults
from shared.sim.maps import occupancy_grid
from shared.sim.world import load_world

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def world():
    return load_world("box-room")


@pytest.fixture(scope="module")
def grid(world):
    return occupancy_grid(world)


def episode(start: int, k: int, xy: list[tuple[float, float]]) -> EpisodeResult:
    return EpisodeResult(start_index=start, episode=k, steps=len(xy) - 1, terminated=False, truncated=True,
                         collision_cause=None, distance_m=0.0, path_length_m=0.0, coverage_m2=0.0,
                         coverage_fraction=0.0, trajectory_xy=tuple(xy))


def test_heatmap_counts_per_cell_normalised(grid) -> None:
    # box-room grid: origin (-2, -2), 5 cm cells. Three points in one cell, one in another.
    res = EvalResults((episode(0, 0, [(0.01, 0.01), (0.02, 0.03), (0.04, 0.04)]),
                       episode(1, 0, [(1.01, -0.51), (5.0, 5.0)])))
    assert trajectory_points(res).shape == (5, 2)
    heat = trajectory_heatmap(grid, res, cell_m=None)
    assert heat.shape == grid.shape
    ix, iy = grid.world_to_cell(0.01, 0.01)
    assert heat[iy, ix] == 1.0
    jx, jy = grid.world_to_cell(1.01, -0.51)
    assert heat[jy, jx] == pytest.approx(1 / 3)
    assert np.count_nonzero(heat) == 2  # the point outside the grid is not counted
    assert heat.min() == 0.0 and heat.max() == 1.0


def test_heatmap_blocks_overlay_the_grid(grid) -> None:
    # Two points in the same 25 cm block (5 x 5 cells anchored at the origin), one in another.
    res = [episode(0, 0, [(-1.99, -1.99), (-1.80, -1.80)]), episode(0, 1, [(0.3, 0.3)])]
    heat = trajectory_heatmap(grid, res, cell_m=0.25)
    assert heat.shape == grid.shape
    np.testing.assert_array_equal(heat[0:5, 0:5], 1.0)
    assert heat[5, 5] == 0.0 and heat[0, 5] == 0.0
    ix, iy = grid.world_to_cell(0.3, 0.3)
    by, bx = (iy // 5) * 5, (ix // 5) * 5
    np.testing.assert_array_equal(heat[by:by + 5, bx:bx + 5], 0.5)
    assert np.count_nonzero(heat) == 50


def test_heatmap_needs_trajectories(grid) -> None:
    bare = EpisodeResult(0, 0, 3, False, True, None, 0.0, 0.0, 0.0, 0.0)
    with pytest.raises(FigureError, match="no trajectory points"):
        trajectory_heatmap(grid, [bare])


def test_heatmap_pngs(tmp_path, world, grid) -> None:
    res = [episode(0, 0, [(-1.2 + 0.1 * i, -1.2 + 0.1 * i) for i in range(20)])]
    one = save_heatmap_png(world, grid, res, tmp_path / "a" / "heat.png", title="DRL", dpi=40)
    assert one.read_bytes()[:8] == PNG_MAGIC
    many = save_heatmaps_side_by_side(world, grid, {"A": res, "B": res, "C": res, "D": res},
                                      tmp_path / "side.png", ncols=2, dpi=40)
    img = mpimg.imread(many)
    assert img.shape[0] > 0.7 * img.shape[1]  # two rows of two panels
    wide = mpimg.imread(save_heatmaps_side_by_side(world, grid, {"A": res, "B": res, "C": res},
                                                   tmp_path / "wide.png", dpi=40))
    assert wide.shape[1] > 2 * wide.shape[0]  # one row of three
    with pytest.raises(FigureError, match="at least one model"):
        save_heatmaps_side_by_side(world, grid, {}, tmp_path / "none.png")


CORRIDOR_XML = """<mujoco><worldbody>
<geom name="wall_a" type="box" pos="{ax} {ay} 0.5" size="{along} 0.05 0.5" euler="0 0 {yaw}"/>
<geom name="wall_b" type="box" pos="{bx} {by} 0.5" size="{along} 0.05 0.5" euler="0 0 {yaw}"/>
<site name="start_a" pos="1 1 0" euler="0 0 {yaw}"/>
</worldbody></mujoco>"""


@pytest.mark.parametrize("tall", [False, True])
def test_side_by_side_heatmaps_of_a_corridor_world_keep_a_drawable_shape(tmp_path, tall: bool) -> None:
    # A world 120 m by 1.3 m made a PNG of two panels 13,000 pixels wide and 78 high at dpi 20 (110,000
    # wide for three at the default dpi); standing on end, panels 10 pixels wide.
    along = 60.2
    walls = (dict(ax=1.6, ay=60, bx=0.4, by=60, yaw=90) if tall else dict(ax=60, ay=1.6, bx=60, by=0.4, yaw=0))
    path = tmp_path / "corridor.xml"
    path.write_text(CORRIDOR_XML.format(along=along, **walls))
    world = load_world(str(path))
    grid = occupancy_grid(world)
    xmin, ymin, xmax, ymax = grid.extent
    assert max((xmax - xmin) / (ymax - ymin), (ymax - ymin) / (xmax - xmin)) > 50
    res = [episode(0, 0, [(1.0, 1.0 + 0.1 * i) if tall else (1.0 + 0.1 * i, 1.0) for i in range(20)])]
    img = mpimg.imread(save_heatmaps_side_by_side(world, grid, {"A": res, "B": res}, tmp_path / "side.png", dpi=20))
    height, width = img.shape[:2]
    assert 0.9 < width / height < 4.5  # two panels, each between 1:2 and 2:1, and the colorbar


def test_titles_holding_dollar_signs_draw_as_written(tmp_path, world, grid) -> None:
    # A run or model named "a$\\x$" (a file name may hold anything) made matplotlib parse its title as
    # mathtext: a ValueError at the end of a whole report's evaluations (and "a$x$b" set in italics).
    from shared.sim.maps import plain_text

    res = [episode(0, 0, [(-1.2 + 0.1 * i, -1.2 + 0.1 * i) for i in range(20)])]
    odd = "run$\\x$@1000"
    assert plain_text(odd) == "run\\$\\x\\$@1000"
    for png in (save_heatmap_png(world, grid, res, tmp_path / "one.png", title=odd, dpi=30),
                save_heatmaps_side_by_side(world, grid, {odd: res, "b": res}, tmp_path / "side.png", dpi=30),
                save_loss_curve_png([{"update": 0, "loss": 1.0}, {"update": 1, "loss": 0.5}], tmp_path / "loss.png",
                                    title=f"Training loss ({odd})", dpi=30)):
        assert png.read_bytes()[:8] == PNG_MAGIC


def test_a_heatmap_without_a_title_names_its_world_as_written(tmp_path, world, grid) -> None:
    # The default title is the world's name, a file world's path: one holding "$\\x$" failed to draw.
    import dataclasses

    res = [episode(0, 0, [(-1.2 + 0.1 * i, -1.2 + 0.1 * i) for i in range(20)])]
    odd = dataclasses.replace(world, name="rooms/a$\\x$.xml", kind="file")
    assert save_heatmap_png(odd, grid, res, tmp_path / "one.png", dpi=30).read_bytes()[:8] == PNG_MAGIC


# -- loss log --------------------------------------------------------------------------------


def test_load_loss_log_formats(tmp_path) -> None:
    csv_path = tmp_path / "stats.csv"
    csv_path.write_text("update,loss,mean_q\n20,1.5,3\n10,2.0,2\n30,,1\n40,nan,1\n50,0.5,0\n")
    updates, losses = load_loss_log(csv_path)
    assert updates.tolist() == [10, 20, 50] and losses.tolist() == [2.0, 1.5, 0.5]

    rows = [{"update": 1, "loss": 4.0}, {"update": 2, "loss": 3.0}]
    (tmp_path / "rows.json").write_text(json.dumps(rows))
    (tmp_path / "cols.json").write_text(json.dumps({"update": [1, 2], "loss": [4.0, 3.0]}))
    (tmp_path / "rows.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    for name in ("rows.json", "cols.json", "rows.jsonl"):
        u, v = load_loss_log(tmp_path / name)
        assert u.tolist() == [1, 2] and v.tolist() == [4.0, 3.0], name
    u, v = load_loss_log(rows)
    assert v.tolist() == [4.0, 3.0]


@pytest.mark.parametrize("content,suffix,match", [
    ("step,value\n1,2\n", ".csv", "must name 'update' and 'loss'"),
    ("update,loss\n1,abc\n", ".csv", "non-numeric"),
    ("", ".csv", "got no rows"),
    ('{"update": 5, "loss": 3}', ".json", "must be lists of numbers"),
    ("5", ".json", "got int"),
    ("null", ".json", "got NoneType"),
    ('[{"update": 1' + "0" * 400 + ', "loss": 1}]', ".json", "non-numeric"),
    ('[{"update": 1, "loss": [2]}]', ".json", "non-numeric"),
    ('{"update": [1, 2], "loss": [1]}', ".json", "2 updates but 1 losses"),
    ('[{"update": 1}]', ".json", "lacks 'update' or 'loss'"),
    ("{oops", ".json", "not readable JSON"),
    ("update,loss\n1,nan\n", ".csv", "no row with a finite loss"),
])
def test_load_loss_log_errors(tmp_path, content: str, suffix: str, match: str) -> None:
    path = tmp_path / f"log{suffix}"
    path.write_text(content)
    with pytest.raises(FigureError, match=match):
        load_loss_log(path)


def test_a_learner_log_with_a_torn_or_damaged_tail_still_plots_its_rows(tmp_path, caplog) -> None:
    # A killed learner tears its last line; a power loss leaves NUL bytes (a field past csv's limit).
    path = tmp_path / "learner.csv"
    path.write_text("time_s,update,loss\n1.0,10,2.0\n2.0,20,1.0\n" + "\0" * 200_000 + "\n3.0,30,0.5\n700.123")
    with caplog.at_level("WARNING", logger="cogexplore.figures"):
        updates, losses = load_loss_log(path)
    assert updates.tolist() == [10, 20, 30] and losses.tolist() == [2.0, 1.0, 0.5]
    assert "1 row(s) left out" in caplog.text
    # In memory, numpy columns are columns.
    u, v = load_loss_log({"update": np.array([2, 1]), "loss": np.array([1.0, 3.0])})
    assert u.tolist() == [1, 2] and v.tolist() == [3.0, 1.0]


def test_a_torn_last_row_is_left_out_not_plotted_as_its_cut_number(tmp_path, caplog) -> None:
    # "3.0,300,3,0.0123,-2.9" cut after "0.0": the loss read as 0.0 at update 300 (and a log axis lost).
    path = tmp_path / "learner.csv"
    path.write_text("time_s,update,policy_version,loss,mean_q\n1.0,100,1,0.0234,-3.1\n2.0,200,2,0.0212,-3.0\n"
                    "3.0,300,3,0.0")
    with caplog.at_level("WARNING", logger="cogexplore.figures"):
        updates, losses = load_loss_log(path)
    assert updates.tolist() == [100, 200] and losses.tolist() == [0.0234, 0.0212]
    assert "row 2 is torn" in caplog.text
    path.write_text("time_s,update,policy_version,loss,mean_q\n3.0,300,3,0.0")
    with pytest.raises(FigureError, match="row 0 is torn"):  # nothing else: named, not an empty plot
        load_loss_log(path)


def test_a_log_of_one_row_shows_its_point(tmp_path) -> None:
    # A line through one point draws nothing: the first loss curve of a run was empty axes.
    path = tmp_path / "learner.csv"
    path.write_text("time_s,update,policy_version,loss\n1.0,100,1,0.5\n")
    img = mpimg.imread(save_loss_curve_png(path, tmp_path / "loss.png"))[..., :3]
    curve = np.all(np.abs(img - np.array([0x1f, 0x77, 0xb4]) / 255) < 0.08, axis=-1)
    h, w = curve.shape
    assert curve[int(0.4 * h):int(0.6 * h), int(0.4 * w):int(0.6 * w)].sum() > 20  # the dot, mid-axes


def test_missing_log(tmp_path) -> None:
    with pytest.raises(FigureError, match="does not exist"):
        load_loss_log(tmp_path / "none.csv")


def test_smooth_is_a_trailing_mean() -> None:
    np.testing.assert_allclose(smooth(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1.0, 2.0, 4.0, 6.0])
    np.testing.assert_allclose(smooth(np.arange(5.0), 1), np.arange(5.0))
    with pytest.raises(FigureError):
        smooth(np.arange(3.0), 0)


def test_loss_curve_png(tmp_path) -> None:
    rows = [{"update": i, "loss": 1000.0 * np.exp(-i / 40) + 0.1} for i in range(400)]
    out = save_loss_curve_png(rows, tmp_path / "fig" / "loss.png", smooth_window=10, dpi=40)
    assert out.read_bytes()[:8] == PNG_MAGIC
    linear = save_loss_curve_png(rows, tmp_path / "loss_lin.png", log_y=False, dpi=40)
    assert linear.read_bytes() != out.read_bytes()


def test_a_figure_rewritten_on_a_full_disk_keeps_the_one_before(tmp_path) -> None:
    """A report rewritten while the disk fills (here: a file size limit, in a child process) keeps
    its earlier PNGs whole, and no temporary file is left beside them."""
    import subprocess
    import sys

    script = f"""
import resource, signal
from pathlib import Path
from services.viz.figures import save_heatmaps_side_by_side, save_loss_curve_png
from shared.evaluation.results import EpisodeResult
from shared.sim.maps import occupancy_grid, render_map_png
from shared.sim.world import load_world

out = Path({str(tmp_path)!r})
rows = [{{"update": i, "loss": 1.0 / (i + 1)}} for i in range(2000)]
world = load_world("box-room")
grid = occupancy_grid(world)
res = [EpisodeResult(0, 0, 19, False, True, None, 0.0, 0.0, 0.0, 0.0,
                     tuple((-1.2 + 0.1 * i, -1.2 + 0.1 * i) for i in range(20)))]
draw = [lambda: save_loss_curve_png(rows, out / "loss.png"),
        lambda: save_heatmaps_side_by_side(world, grid, {{"A": res, "B": res}}, out / "side.png"),
        lambda: render_map_png(world, grid, out / "map.png")]
for write in draw:
    write()
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))
for write in draw:
    try:
        write()
        print("written")
    except OSError as exc:
        print("failed", exc.errno)
"""
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["failed", "27"] * 3  # EFBIG: the limit was hit
    assert sorted(p.name for p in tmp_path.iterdir()) == ["loss.png", "map.png", "side.png"]
    for name in ("loss.png", "map.png", "side.png"):
        png = (tmp_path / name).read_bytes()
        assert png[:8] == PNG_MAGIC and png[-8:-4] == b"IEND", name
        assert mpimg.imread(tmp_path / name).shape[0] > 100


# -- Table II --------------------------------------------------------------------------------


def test_q_value_table_matches_paper_layout() -> None:
    table = q_value_table_markdown({
        "S1": {"SL": [23.9, 26.3, -10.6, -35.3, -34.4], "DRL": np.array([-16.3, -36.2, -31.7, -38.7, -44.5])},
        "R4": {"DRL": [-87.6, -141.1, -115.2, -134.8, -137.4]},
    })
    assert table.splitlines() == [
        "| Scene | Model | Left | H-Left | Straight | H-Right | Right |",
        "|---|---|---:|---:|---:|---:|---:|",
        "| S1 | SL | 23.9 | **26.3** | -10.6 | -35.3 | -34.4 |",
        "|  | DRL | **-16.3** | -36.2 | -31.7 | -38.7 | -44.5 |",
        "| R4 | DRL | **-87.6** | -141.1 | -115.2 | -134.8 | -137.4 |",
    ]


def test_q_value_table_errors() -> None:
    with pytest.raises(FigureError, match="need 5 finite values"):
        q_value_table_markdown({"S1": {"SL": [1.0, 2.0]}})
    with pytest.raises(FigureError, match="at least one scene"):
        q_value_table_markdown({})
    for odd in (["a", 1, 2, 3, 4], [[1, 2], [3]], {"left": 1.0}):  # text, ragged, an object: named, not a traceback
        with pytest.raises(FigureError, match="need 5 finite values"):
            q_value_table_markdown({"S1": {"SL": odd}})


def test_results_of_another_world_are_refused_not_drawn_blank(tmp_path, world, grid) -> None:
    from shared.evaluation.protocol import WORLD_META, world_sha256

    # paper-indoor's results lie mostly outside box-room's 4 m square: drawn there, the map came out blank
    xy = [(5.0 + 0.1 * i, 3.0) for i in range(20)]
    other = load_world("paper-indoor")
    elsewhere = EvalResults((episode(0, 0, xy),), meta={"world": other.name, WORLD_META: world_sha256(other)})
    with pytest.raises(FigureError, match=r"paper-indoor.*box-room") as err:
        save_heatmap_png(world, grid, elsewhere, tmp_path / "one.png")
    assert "\n" not in str(err.value)
    with pytest.raises(FigureError, match=r"paper-indoor.*box-room"):
        save_heatmaps_side_by_side(world, grid, {"ours": elsewhere}, tmp_path / "side.png")
    assert not (tmp_path / "one.png").exists() and not (tmp_path / "side.png").exists()
    # the same name, other content (a world file edited since): not the map the episodes were played on
    edited = EvalResults((episode(0, 0, xy),), meta={"world": world.name, WORLD_META: "0" * 64})
    with pytest.raises(FigureError, match="box-room"):
        save_heatmap_png(world, grid, edited, tmp_path / "edited.png")
    # results that do not say (a bare list of episodes, meta from before the world was recorded) draw
    here = EvalResults((episode(0, 0, [(0.1, 0.1), (0.2, 0.2)]),), meta={"world": world.name})
    assert save_heatmap_png(world, grid, here, tmp_path / "here.png", dpi=40).is_file()
    own = EvalResults(here.episodes, meta={"world": world.name, WORLD_META: world_sha256(world)})
    assert save_heatmaps_side_by_side(world, grid, {"a": own, "b": list(here.episodes)}, tmp_path / "s.png",
                                      dpi=40).is_file()
