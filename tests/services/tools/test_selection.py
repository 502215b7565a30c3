"""``cogexplore model select``: the window rule as pure code, and the whole selection on a real
run folder (real checkpoints, real env, the exported file and its cache read back)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch

from services.cli import main
from services.tools.selection import (
    SelectionError,
    SelectOptions,
    WindowScore,
    choose,
    save_selection_png,
    select,
    wall_minutes,
    window_rows_markdown,
    windows,
)
from shared.config import load_preset
from shared.evaluation import PROTOCOLS, SELECTION_SEED, TEST_SEED
from shared.evaluation.protocol import evaluate_policy
from shared.evaluation.setup import setup_evaluation
from shared.learning.checkpoints import (
    CheckpointManager,
    load_exported_weights,
    load_model,
)
from shared.learning.dqn import DQNAgent

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def score(end: int, gate: float, validation: float | None, worst: float | None = None) -> WindowScore:
    return WindowScore(end, f"sha{end}", gate, validation, {"g": gate}, (f"ckpt-{end}",), worst)


def test_windows_are_consecutive_checkpoints_counted_back_from_the_newest() -> None:
    ckpts = [(u, Path(f"c{u}")) for u in (5000, 1000, 3000, 2000, 4000)]  # any order
    got = windows(ckpts, 3)
    assert [w.end_update for w in got] == [3000, 4000, 5000]
    assert got[0].paths == (Path("c1000"), Path("c2000"), Path("c3000"))
    # every second window, counted back from the newest: the newest is always scored
    assert [w.end_update for w in windows(ckpts, 2, stride=2)] == [3000, 5000]
    assert [w.end_update for w in windows(ckpts, 1, first_end=2000, last_end=4000)] == [2000, 3000, 4000]
    assert windows(ckpts, 6) == []
    for bad in ({"size": 0}, {"size": 2, "stride": 0}):
        with pytest.raises(SelectionError):
            windows(ckpts, bad["size"], stride=bad.get("stride", 1))
    with pytest.raises(SelectionError, match="share an update"):
        windows(ckpts + [(1000, Path("again"))], 2)


def test_choose_gates_first_then_takes_the_best_validation() -> None:
    scores = [score(1000, 170, 80.0), score(2000, 140, None), score(3000, 155, 95.0), score(4000, 190, 90.0)]
    best, rule = choose(scores, 150)
    assert best.end_update == 3000  # not the best gate score (4000), nor a window that missed the gate
    assert "3 of 4 windows" in rule and "95.0" in rule
    # ties on validation go to the later window
    best, _ = choose(scores + [score(5000, 151, 95.0)], 150)
    assert best.end_update == 5000
    # nobody passes: the best gate score, said so
    best, rule = choose([score(1000, 90, None), score(2000, 120, None)], 150)
    assert best.end_update == 2000 and rule.startswith("no window")
    with pytest.raises(SelectionError):
        choose([], 150)
    table = window_rows_markdown(scores, scores[2], "paper-indoor")
    assert "| **3000** | **155.0** | **—** | **95.0** |" in table and "| 2000 | 140.0 | — | — |" in table


def test_a_worst_start_gate_keeps_only_windows_whose_every_start_reaches_it() -> None:
    scores = [score(1000, 170, 99.0, worst=27.0), score(2000, 155, 90.0, worst=64.0),
              score(3000, 190, None, worst=20.0)]
    best, rule = choose(scores, 150, gate_start_min=60)
    assert best.end_update == 2000 and "1 of 3 windows" in rule and "every start 60" in rule
    assert choose(scores, 150)[0].end_update == 1000  # without it, the best validation
    best, rule = choose([score(1000, 170, None, worst=27.0)], 150, gate_start_min=60)
    assert rule.startswith("no window")
    assert not score(1, 170, None).passes(150, 60)  # a score cached without its worst start does not pass
    assert "| 2000 | 155.0 | 64.0 | 90.0 |" in window_rows_markdown(scores)
    assert WindowScore.from_json(scores[1].to_json()) == scores[1]


def test_a_cached_score_no_scoring_writes_is_skipped_not_a_traceback_or_a_nan(tmp_path: Path, caplog) -> None:
    from services.tools.selection import _load_cache, _protocol_key

    key = _protocol_key(SelectOptions(run=tmp_path, out=tmp_path / "o.safetensors"))
    good = score(300, 120.0, 90.0, 40.0).to_json()
    lines = [{**good, "weights_sha256": "huge", "gate": 10 ** 400},  # was an OverflowError out of select()
             {**good, "weights_sha256": "inf-update", "end_update": 1e999},
             {**good, "weights_sha256": "nan", "validation": float("nan")},  # was kept: choose() by chance
             {**good, "weights_sha256": "text", "per_world": {"g": "many"}},
             good]
    path = tmp_path / "cache.jsonl"
    path.write_text("".join(json.dumps({"protocol": key, "score": d}) + "\n" for d in lines))
    assert list(_load_cache(path, key)) == ["sha300"]
    assert caplog.text.count("skipped") == 4


def test_wall_minutes_carry_the_clock_across_a_resume(tmp_path: Path) -> None:
    csv = tmp_path / "learner.csv"
    csv.write_text("time_s,update,loss\n60,100,1\n120,200,1\n6,250,1\nbad,300,1\n66,300,1\n")
    updates, minutes = wall_minutes(csv)
    assert updates.tolist() == [100, 200, 250, 300]
    assert minutes.tolist() == pytest.approx([1.0, 2.0, 2.1, 3.1])  # the resumed run started at 2 min
    assert wall_minutes(tmp_path / "missing.csv") is None
    (tmp_path / "short.csv").write_text("time_s,update\n1,1\n")
    assert wall_minutes(tmp_path / "short.csv") is None
    # sessions told apart by their mark: the third's first row came later than the second's last,
    # so its clock did not go back and the second session's time was lost
    csv.write_text("time_s,update,session\n9.082,25,1\n0.051,30,2\n0.094,40,3\n")
    assert wall_minutes(csv)[1].tolist() == pytest.approx([9.082 / 60, 9.133 / 60, 9.227 / 60])

def make_run(root: Path, updates: tuple[int, ...]) -> Path:
    """A run folder with one checkpoint per update count, each a different random network."""
    cfg = load_preset("tiny")
    manager = CheckpointManager(root / "checkpoints", keep=len(updates))
    for seed, u in enumerate(updates):
        agent = DQNAgent(cfg.model, cfg.sensor, cfg.dqn, device="cpu", seed=seed)
        agent.update_count = agent.policy_version = u
        manager.save(agent, config=cfg.to_dict())
    return root


def test_select_scores_every_window_exports_the_choice_and_reuses_its_cache(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run", (100, 200, 300, 400))
    out = tmp_path / "sel" / "best.safetensors"
    opts = SelectOptions(run=run, out=out, window=2, gate_world="box-room", gate_min=0.0,
                         validation_worlds=("corridor", "box-room"), test_worlds=("procedural:0",), max_steps=6)
    lines: list[str] = []
    summary = select(opts, echo=lines.append)

    rows = [json.loads(line)["score"] for line in (tmp_path / "sel" / "best-windows.jsonl").read_text().splitlines()]
    scores = [WindowScore.from_json(r) for r in rows]
    assert [s.end_update for s in scores] == [200, 300, 400]
    assert all(s.validation == pytest.approx((s.per_world["corridor"] + s.per_world["box-room"]) / 2)
               for s in scores)
    chosen, rule = choose(scores, 0.0)
    assert summary["chosen"]["end_update"] == chosen.end_update and summary["rule"] == rule
    # the test world is played once, by the chosen window only, after the choice
    assert len(lines) == 5 and lines[-1].startswith(f"testing the window ending at {chosen.end_update}")
    # every window is scored under the robust protocol by default, and the export says so
    assert lines[0] == f"protocol {PROTOCOLS['robust'].describe()}" and summary["protocol"] == "robust"
    assert list(summary["test"]["per_world"]) == ["procedural:0"]
    assert 1 <= summary["test"]["mean"] <= 6

    # the export is the mean of the chosen window's checkpoints, with where it came from
    net, meta = load_exported_weights(out)
    sources = [load_model(p).net for p in chosen.sources]
    for name, t in net.state_dict().items():
        assert torch.allclose(t, (sources[0].state_dict()[name] + sources[1].state_dict()[name]) / 2, atol=1e-6)
    assert meta["selection"]["end_update"] == chosen.end_update and meta["policy_version"] == chosen.end_update
    assert meta["selection"]["protocol"] == PROTOCOLS["robust"].to_dict()
    assert meta["selection"]["test"] == summary["test"]
    assert [a["policy_version"] for a in meta["averaged_from"]] == [chosen.end_update - 100, chosen.end_update]
    assert Path(summary["figure"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert summary["chosen_minutes"] is None and summary["first_gate_update"] == 200  # no learner.csv here

    # a rerun with one more checkpoint plays only the new window
    make_run(tmp_path / "more", (500,))
    (tmp_path / "more" / "checkpoints" / "ckpt-000000500.safetensors").rename(
        run / "checkpoints" / "ckpt-000000500.safetensors")
    lines.clear()
    again = select(opts, echo=lines.append)
    assert [line.endswith("(cached)") for line in lines[1:5]] == [True, True, True, False]
    assert again["windows"] == 4
    # the run moved (the original gone): the cached scores lead to this run's checkpoints, not the old
    # run's paths the cache recorded
    run.rename(tmp_path / "moved")
    lines.clear()
    moved = select(dataclasses.replace(opts, run=tmp_path / "moved"), echo=lines.append)
    assert all(line.endswith("(cached)") for line in lines[1:5])
    assert moved["chosen"]["end_update"] == again["chosen"]["end_update"]
    assert all(Path(p).parent.parent == tmp_path / "moved" for p in moved["chosen"]["sources"])
    (tmp_path / "moved").rename(run)
    # another protocol is another score: nothing is taken from the cache
    lines.clear()
    select(dataclasses.replace(opts, protocol=PROTOCOLS["paper"], test_worlds=()), echo=lines.append)
    assert lines[0].startswith("protocol paper") and not any(line.endswith("(cached)") for line in lines)


def test_scores_on_a_world_file_are_not_reused_once_the_file_is_edited(tmp_path: Path) -> None:
    # Keyed by the file's path alone, a gate or validation world edited since kept the old file's scores.
    from services.tools.selection import _protocol_key
    from tests.shared.evaluation.test_eval_log import write_room

    gate, validation = write_room(tmp_path / "gate.xml"), write_room(tmp_path / "validation.xml")
    opts = SelectOptions(run=make_run(tmp_path / "run", (100,)), out=tmp_path / "best.safetensors", window=1,
                         gate_world=str(gate), gate_min=0.0, validation_worlds=(str(validation), "corridor"),
                         max_steps=4)
    lines: list[str] = []

    def cached() -> bool:
        lines.clear()
        select(opts, echo=lines.append)
        return lines[-1].endswith("(cached)")

    assert not cached() and cached()  # the same files: their scores stand
    for world in (gate, validation):
        write_room(world, pillar_x=-0.6)
        assert not cached() and cached()
    # built-in and procedural worlds are fixed by their names: their key is the one cached before
    assert "world_sha256" not in _protocol_key(dataclasses.replace(opts, gate_world="box-room",
                                                                   validation_worlds=("procedural:3",)))


def test_a_window_with_a_checkpoint_that_cannot_be_read_is_skipped_and_said(tmp_path: Path) -> None:
    # One damaged checkpoint ended the whole selection (hours of scoring on a long run).
    run = make_run(tmp_path / "run", (100, 200, 300))
    damaged = sorted((run / "checkpoints").glob("ckpt-*200*"))[0]
    damaged.write_bytes(b"not a checkpoint")
    said: list[str] = []
    summary = select(SelectOptions(run=run, out=tmp_path / "best.safetensors", window=1, gate_world="box-room",
                                   gate_min=1e9, validation_worlds=("corridor",), max_steps=3), echo=said.append)
    assert summary["windows"] == 2 and len(summary["windows_skipped"]) == 1
    assert summary["windows_skipped"][0].startswith("200: ") and summary["chosen"]["end_update"] in (100, 300)
    assert any("window ending at 200: skipped" in line for line in said)
    for path in (run / "checkpoints").glob("ckpt-*"):
        path.write_bytes(b"not a checkpoint")
    with pytest.raises(SelectionError, match="no window could be read: 100: .*and 2 more"):
        select(SelectOptions(run=run, out=tmp_path / "none.safetensors", window=1, gate_world="box-room",
                             validation_worlds=("corridor",), max_steps=3))


def test_select_falls_back_to_the_best_gate_score_without_playing_validation(tmp_path: Path) -> None:
    run = make_run(tmp_path / "run", (100, 200, 300))
    (run / "stats").mkdir()
    (run / "stats" / "learner.csv").write_text("time_s,update\n0,0\n600,300\n")  # 2 s per update
    out = tmp_path / "best.safetensors"
    summary = select(SelectOptions(run=run, out=out, window=1, gate_world="box-room", gate_min=1e9,
                                   validation_worlds=("corridor",), max_steps=6))
    assert summary["rule"].startswith("no window of 3 reaches")
    assert summary["chosen_minutes"] == pytest.approx(summary["chosen"]["end_update"] * 2 / 60, abs=0.05)
    assert summary["first_gate_update"] is None and Path(summary["figure"]).stat().st_size > 10_000
    rows = [json.loads(line)["score"] for line in out.with_name("best-windows.jsonl").read_text().splitlines()]
    assert all(r["validation"] is None and list(r["per_world"]) == ["box-room"] for r in rows)
    assert summary["chosen"]["gate"] == max(r["gate"] for r in rows)
    assert all(0 <= r["gate_worst_start"] <= r["gate"] for r in rows)
    # a worst-start gate no window reaches: validation is not played either
    strict = select(SelectOptions(run=run, out=out, window=1, gate_world="box-room", gate_min=0.0, gate_start_min=1e9,
                                  validation_worlds=("corridor",), max_steps=6))
    assert strict["rule"].startswith("no window of 3 reaches 0 (every start 1e+09)")
    assert strict["chosen"]["validation"] is None


def test_select_draws_its_episodes_from_its_own_seed_not_the_tests(tmp_path: Path) -> None:
    """A window chosen on the test's own start draws and noise would be chosen on its test: the
    gate is played with SELECTION_SEED (a seed the test never uses) unless told another."""
    assert SELECTION_SEED != TEST_SEED  # evaluate's, report's and the evaluator's
    run = make_run(tmp_path / "run", (100, 200))
    out = tmp_path / "best.safetensors"
    opts = SelectOptions(run=run, out=out, window=1, gate_world="paper-indoor", gate_min=1e9,
                         validation_worlds=("corridor",), max_steps=60)
    lines: list[str] = []
    summary = select(opts, echo=lines.append)
    _, meta = load_exported_weights(out)
    assert summary["chosen"]["end_update"] == meta["selection"]["end_update"]
    assert meta["selection"]["seed"] == SELECTION_SEED

    def played(seed: int, protocol: str = "robust") -> list[float]:
        gates = []
        for p in sorted((run / "checkpoints").glob("ckpt-*.safetensors")):
            setup = setup_evaluation("greedy", world="paper-indoor", model=load_model(p), device="cpu")
            gates.append(evaluate_policy(setup.policy_fn, world="paper-indoor", sensor_cfg=setup.sensor_cfg,
                                         env_cfg=setup.env_cfg, episodes_per_start=1, max_steps=60, seed=seed,
                                         progress=False, protocol=PROTOCOLS[protocol]).summary["overall"]["mean_steps"])
        return gates

    ours, the_tests = played(SELECTION_SEED), played(TEST_SEED)
    assert ours != the_tests  # the draws matter here, so the next line can tell the seeds apart
    rows = [json.loads(line) for line in out.with_name("best-windows.jsonl").read_text().splitlines()]
    assert [r["score"]["gate"] for r in rows] == pytest.approx(ours)
    # another seed is other draws: scored anew, never taken from the first seed's cache
    lines.clear()
    select(dataclasses.replace(opts, seed=TEST_SEED), echo=lines.append)
    rows = [json.loads(line) for line in out.with_name("best-windows.jsonl").read_text().splitlines()]
    assert not any(line.endswith("(cached)") for line in lines)
    assert [r["score"]["gate"] for r in rows if r["protocol"]["seed"] == TEST_SEED] == pytest.approx(the_tests)
    # --protocol paper plays the exact starts without noise: its own scores, cached apart, recorded
    exact = played(SELECTION_SEED, "paper")
    assert exact != ours
    select(dataclasses.replace(opts, protocol=PROTOCOLS["paper"]), echo=lines.append)
    rows = [json.loads(line) for line in out.with_name("best-windows.jsonl").read_text().splitlines()]
    paper = PROTOCOLS["paper"].to_dict()
    assert [r["score"]["gate"] for r in rows if r["protocol"]["protocol"] == paper] == pytest.approx(exact)
    assert load_exported_weights(out)[1]["selection"]["protocol"] == paper


def test_select_cli_errors_are_clear_and_write_nothing(tmp_path: Path, capsys) -> None:
    out = tmp_path / "best.safetensors"
    assert main(["model", "select", str(tmp_path / "nothing"), "--out", str(out)]) == 2
    assert "neither a run folder nor a checkpoints directory" in capsys.readouterr().err
    run = make_run(tmp_path / "run", (100, 200))
    for argv, message in ((["--window", "3"], "no window of 3 checkpoints"),
                          (["--window", "0"], "window size must be"),
                          (["--gate-world", "no-such-world"], "no-such-world"),
                          (["--validate", "procedural:x"], "procedural"),
                          (["--gate-min", "nan"], "finite"),
                          (["--test", "paper-indoor"], "a test world is also the gate")):
        assert main(["model", "select", str(run), "--out", str(out), *argv]) == 2, argv
        assert message in capsys.readouterr().err, argv
    assert not out.exists()
    # a damaged cache line is skipped, not fatal
    out.with_name("best-windows.jsonl").write_text("{not json\n")
    assert main(["model", "select", str(run), "--out", str(out), "--window", "2", "--gate-world", "box-room",
                 "--gate-min", "0", "--validate", "box-room", "--max-steps", "4"]) == 0
    assert json.loads(capsys.readouterr().out)["chosen"]["end_update"] == 200 and out.exists()


def test_a_damaged_clock_in_learner_csv_is_skipped_not_a_traceback(tmp_path: Path) -> None:
    # a NaN or infinite time_s reached the figure's axis: ValueError after the export was written
    csv = tmp_path / "learner.csv"
    csv.write_text("time_s,update\n0,0\nnan,100\ninf,150\n-5,170\n120,200\n")
    updates, minutes = wall_minutes(csv)
    assert updates.tolist() == [0, 200] and minutes.tolist() == pytest.approx([0.0, 2.0])
    csv.write_text("time_s,update\n5,100\n5,200\n")  # a clock that never moved: no minutes axis
    assert wall_minutes(csv) is None
    run = make_run(tmp_path / "run", (100, 200))
    (run / "stats").mkdir()
    (run / "stats" / "learner.csv").write_text("time_s,update\n0,0\ninf,100\n60,200\n")
    summary = select(SelectOptions(run=run, out=tmp_path / "best.safetensors", window=1, gate_world="box-room",
                                   gate_min=0.0, validation_worlds=("corridor",), max_steps=3))
    assert summary["chosen_minutes"] in (None, 1.0) and Path(summary["figure"]).is_file()


def test_a_test_world_written_another_way_is_still_the_gate_world(tmp_path: Path) -> None:
    # procedural:05 is the world procedural:5: as a test world it was played in the choice too
    run = make_run(tmp_path / "run", (100,))
    for gate, test in (("procedural:05", "procedural:5"), ("procedural:5", "procedural:005")):
        with pytest.raises(SelectionError, match="a test world is also the gate"):
            select(SelectOptions(run=run, out=tmp_path / "best.safetensors", window=1, gate_world=gate,
                                 validation_worlds=("corridor",), test_worlds=(test,), max_steps=3))
    assert not (tmp_path / "best.safetensors").exists()


def test_a_bad_device_is_one_error_not_every_window_skipped(tmp_path: Path, capsys) -> None:
    run = make_run(tmp_path / "run", (100, 200))
    out = tmp_path / "best.safetensors"
    assert main(["model", "select", str(run), "--out", str(out), "--window", "1", "--device", "bogus"]) == 2
    err = capsys.readouterr().err
    assert "--device" in err and "skipped" not in err and "cannot be read" not in err
    assert not out.exists()


def test_checkpoints_rewritten_while_scored_are_not_exported_as_scored(tmp_path: Path) -> None:
    # a run resumed from an older checkpoint saves the same update counts anew: the export took the new
    # weights under the old weights' scores
    run = make_run(tmp_path / "run", (100, 200))
    other = make_run(tmp_path / "other", (50, 100, 200))  # other seeds at 100 and 200: other weights

    def echo(line: str) -> None:
        if line.startswith("[2/2]"):  # every window scored, the choice not yet exported
            for u in (100, 200):
                name = f"ckpt-{u:09d}.safetensors"
                (other / "checkpoints" / name).replace(run / "checkpoints" / name)

    out = tmp_path / "best.safetensors"
    with pytest.raises(SelectionError, match="changed while the windows were scored"):
        select(SelectOptions(run=run, out=out, window=1, gate_world="box-room", gate_min=0.0,
                             validation_worlds=("corridor",), max_steps=3), echo=echo)
    assert not out.exists()
    # scored as they are now, the choice is exported with the digest it was scored with
    summary = select(SelectOptions(run=run, out=out, window=1, gate_world="box-room", gate_min=0.0,
                                   validation_worlds=("corridor",), max_steps=3))
    _, meta = load_exported_weights(out)
    assert meta["selection"]["weights_sha256"] == summary["chosen"]["weights_sha256"] \
        == load_model(summary["chosen"]["sources"][0]).weights_sha256


def test_a_figure_cut_short_by_a_full_disk_leaves_the_last_one_whole(tmp_path: Path) -> None:
    # the figure was written in place: a rerun that failed mid-file left half a PNG
    from service_processes import run_on_a_full_disk

    png = tmp_path / "best-windows.png"
    scores = [score(100, 50.0, None), score(200, 80.0, 60.0)]
    save_selection_png(scores, png, gate_min=70.0)
    before = png.read_bytes()
    done = run_on_a_full_disk("from pathlib import Path; "
                              "from services.tools.selection import WindowScore, save_selection_png; "
                              "s = [WindowScore(100, 'a', 90.0, None, {}, ()), WindowScore(200, 'b', 10.0, 5.0, {}, ())]; "
                              f"save_selection_png(s, Path({str(png)!r}), gate_min=50.0)", 4096)
    assert done.returncode != 0 and "File too large" in done.stderr, done.stderr[-2000:]
    assert png.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == [png.name]
