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


def test_the_weights_and_the_onnx_file_of_one_export_must_be_two_files(tmp_path: Path, capsys, monkeypatch) -> None:
    # --out F --onnx F wrote the ONNX file, then the weights over it, and reported both written
    run = make_run(tmp_path / "run", (100,))
    monkeypatch.chdir(tmp_path)
    kept = tmp_path / "kept.bin"
    kept.write_bytes(b"an earlier file")
    (tmp_path / "link.bin").symlink_to(kept)
    for out, onnx in (("m.bin", "m.bin"), ("m.bin", "./sub/../m.bin"), ("kept.bin", "link.bin")):
        (tmp_path / "sub").mkdir(exist_ok=True)
        assert main(["model", "export", str(run), "--out", out, "--onnx", onnx]) == 2, (out, onnx)
        err = capsys.readouterr().err
        assert "--out and --onnx name the same file" in err and err.count("\n") == 1, err
    assert not (tmp_path / "m.bin").exists() and kept.read_bytes() == b"an earlier file"


def test_a_failed_weights_write_leaves_no_onnx_file_of_the_same_export(tmp_path: Path, capsys, monkeypatch) -> None:
    # --onnx F --out G where G cannot be written: F was written (over an earlier export of the same name)
    # and the command failed, leaving one half of an export
    run = make_run(tmp_path / "run", (100,))
    monkeypatch.chdir(tmp_path)
    (tmp_path / "afile").write_text("not a folder")
    (tmp_path / "earlier.onnx").write_bytes(b"an earlier export")
    for onnx in ("new.onnx", "earlier.onnx"):
        assert main(["model", "export", str(run), "--onnx", onnx, "--out", "afile/w.safetensors"]) == 2
        err = capsys.readouterr().err
        assert "afile" in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "earlier.onnx", "run"]
    assert (tmp_path / "earlier.onnx").read_bytes() == b"an earlier export"
    # both written when both can be
    assert main(["model", "export", str(run), "--onnx", "new.onnx", "--out", "w.safetensors"]) == 0
    from cogexplore.onnx_runner import load_onnx_policy
    from shared.learning.checkpoints import load_model

    assert load_onnx_policy(tmp_path / "new.onnx").label == load_model(tmp_path / "w.safetensors").label.replace(
        "w@", "run@")
