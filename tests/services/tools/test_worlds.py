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
