"""``cogexplore model export|select`` against an output path no export can take: a folder, or one of
the models they read."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli import main
from tests.services.tools.test_selection import make_run

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_an_export_over_one_of_its_sources_is_refused_and_the_checkpoint_kept(tmp_path: Path, capsys) -> None:
    # the run's checkpoint was replaced by a weights-only export: resuming or selecting lost it
    run = make_run(tmp_path / "run", (100, 200))
    ckpts = sorted((run / "checkpoints").glob("ckpt-*.safetensors"))
    before = {p: p.read_bytes() for p in ckpts}
    for argv in (["model", "export", str(ckpts[1]), "--out", str(ckpts[1])],
                 ["model", "export", str(run), "--out", str(ckpts[1])],  # the run folder reads its latest
                 ["model", "export", str(ckpts[0]), str(ckpts[1]), "--onnx", str(ckpts[0])],
                 ["model", "select", str(run), "--out", str(ckpts[0]), "--window", "1"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "a model it reads: write the export elsewhere" in err and err.count("\n") == 1, err
    assert {p: p.read_bytes() for p in ckpts} == before
    assert main(["model", "export", str(run), "--out", str(tmp_path / "w.safetensors")]) == 0


def test_a_card_too_large_to_be_one_is_refused_in_one_line(tmp_path: Path, capsys) -> None:
    # --card read and parsed up to 256 MiB into the exported file's metadata
    from shared.jsontext import SMALL_JSON_BYTES

    run = make_run(tmp_path / "run", (100,))
    card = tmp_path / "card.json"
    with open(card, "wb") as fh:
        fh.truncate(SMALL_JSON_BYTES + 1)
    out = tmp_path / "w.safetensors"
    assert main(["model", "export", str(run), "--out", str(out), "--card", str(card)]) == 2
    err = capsys.readouterr().err
    assert f"--card {card} cannot be read: too large: {SMALL_JSON_BYTES + 1:,} bytes" in err, err
    assert err.count("\n") == 1 and not out.exists()


def test_an_export_to_a_folder_is_one_line_before_any_window_is_played(tmp_path: Path, capsys, monkeypatch) -> None:
    # `--out .` was a ValueError traceback; an existing folder failed only after every window was played
    run = make_run(tmp_path / "run", (100,))
    monkeypatch.chdir(tmp_path)
    for argv in (["model", "export", str(run), "--out", "."], ["model", "export", str(run), "--onnx", ".."],
                 ["model", "select", str(run), "--out", ".", "--window", "1"],
                 ["model", "select", str(run), "--out", str(run), "--window", "1"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert "Is a directory (give a file name)" in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
