"""``cogexplore worlds``: options refused in one line, before any planning."""

from __future__ import annotations

from pathlib import Path

from services.cli import main


def test_demo_refuses_a_negative_seed_in_one_line(tmp_path: Path, capsys) -> None:
    # It was a numpy traceback from the first start draw (SeedSequence of a negative number).
    out = tmp_path / "d.npz"
    assert main(["worlds", "demo", "box-room", "--start", "1", "--horizon", "2", "--beam", "5", "--protocol",
                 "robust", "--episodes", "2", "--seed", "-1", "--quiet", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("cogexplore worlds demo: error: --seed must be an integer >= 0") and err.count("\n") == 1
    assert not out.exists()


def test_demo_plans_a_start_given_twice_once_and_says_so(tmp_path: Path, capsys) -> None:
    # It planned and recorded start 2 twice: two identical demonstrations in the file.
    import json

    from shared.learning.demos import load_demonstrations

    out = tmp_path / "d.npz"
    assert main(["worlds", "demo", "box-room", "--start", "2", "--start", "1", "--start", "2", "--horizon", "2",
                 "--beam", "5", "--quiet", "--out", str(out)]) == 0
    captured = capsys.readouterr()
    plans = [json.loads(line) for line in captured.out.splitlines() if line.startswith("{")]
    assert [p["start"] for p in plans] == [2, 1]  # in the order given
    assert [d.start_index for d in load_demonstrations(out)] == [1, 0]
    assert captured.err == "cogexplore worlds demo: note: start 2 given more than once; planned once\n"


def test_demo_refuses_no_episodes_as_a_count(tmp_path: Path, capsys) -> None:
    # It blamed the protocol's exact starts, also under the robust protocol, whose starts are drawn.
    out = tmp_path / "d.npz"
    assert main(["worlds", "demo", "box-room", "--start", "1", "--protocol", "robust", "--episodes", "0",
                 "--quiet", "--out", str(out)]) == 2
    assert capsys.readouterr().err == "cogexplore worlds demo: error: --episodes must be an integer >= 1, got 0\n"
    assert not out.exists()
