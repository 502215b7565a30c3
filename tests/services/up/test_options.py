"""Options of `up` and `bench system` that were taken and then misreported or dropped."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.cli import main


def test_a_runs_dir_that_is_a_file_is_named_as_such(tmp_path: Path, capsys) -> None:
    # the lock's error blamed <file>/.<run>.up.lock ("File exists") as if the run were in use
    not_a_folder = tmp_path / "runs"
    not_a_folder.write_text("")
    for command in (["up", "--updates", "1", "--quiet"], ["learner"]):
        assert main([*command, "--run", "r", "--runs-dir", str(not_a_folder)]) == 2
        err = capsys.readouterr().err
        assert err == f"cogexplore {command[0]}: error: the runs folder {not_a_folder} is not a folder (--runs-dir)\n"
    assert not_a_folder.read_text() == ""


@pytest.mark.parametrize("extra,named", [
    (["--device", "cuda"], "--device"),
    (["--learner-threads", "4"], "--learner-threads"),
    (["--device", "cpu", "--learner-threads", "1"], "--device, --learner-threads"),
    (["--seconds", "30"], "--seconds"),
    (["--warmup-s", "0"], "--warmup-s"),
    (["--startup-timeout-s", "60", "--seconds", "5"], "--seconds, --startup-timeout-s"),
])
def test_compare_single_process_refuses_the_options_its_runs_would_not_get(extra: list[str], named: str,
                                                                          tmp_path: Path, capsys) -> None:
    # they were dropped silently: both runs then trained on the preset's device and every thread
    assert main(["bench", "system", "--compare-single-process", "--minutes", "0.01", "--runs-dir", str(tmp_path),
                 *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cogexplore bench system: error: {named} do{'' if ',' in named else 'es'} not reach "
                          "--compare-single-process"), err
    assert err.count("\n") == 1 and list(tmp_path.iterdir()) == []  # refused before either run started


@pytest.mark.parametrize("extra,named", [
    (["--minutes", "2"], "--minutes"),
    (["--episodes-per-start", "1"], "--episodes-per-start"),
])
def test_a_measurement_refuses_the_comparison_options(extra: list[str], named: str, tmp_path: Path, capsys) -> None:
    # they were dropped silently: `bench system --minutes 5` measured the default 60 s
    assert main(["bench", "system", "--runs-dir", str(tmp_path), *extra]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cogexplore bench system: error: {named} does not reach a measurement without "
                          "--compare-single-process"), err
    assert list(tmp_path.iterdir()) == []


def test_up_takes_a_port_in_range() -> None:
    from services.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["up", "--port", "65535"]).port == 65535
    assert parser.parse_args(["up", "--port", "1"]).port == 1
    assert parser.parse_args(["up"]).port is None


@pytest.mark.parametrize("existing", ["up", "single", "up-world-cache", "single-world-cache"])
def test_compare_single_process_refuses_a_runs_dir_that_holds_its_runs(existing: str, tmp_path: Path, capsys,
                                                                      monkeypatch) -> None:
    # `up --run up` and `train --run single` resumed them: their learner.csv counted the earlier
    # comparison's updates too, divided by this one's minutes; a world cache left by one is warm
    from services.up import compare

    (tmp_path / existing).mkdir()
    monkeypatch.setattr(compare, "_cli", lambda argv, *_: pytest.fail(f"started `cogexplore {argv[0]}`"))
    assert main(["bench", "system", "--compare-single-process", "--minutes", "0.01", "--runs-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path / existing} already exists: both runs must start from nothing" in err, err
    assert err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == [existing]  # nothing started, nothing written
