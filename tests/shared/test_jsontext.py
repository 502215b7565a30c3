"""Files a user hands in, read as untrusted input: whatever is malformed is one clear error of the
reader's own class, never a traceback (tests/services/test_cli.py checks the one line)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from shared.errors import CogexploreError
from shared.jsontext import parse_json, read_json_file

DEEP = "[" * 100_000  # exhausts the parser's recursion
HUGE_INT = '{"n": ' + "9" * 5000 + "}"  # beyond Python's 4300-digit limit


@pytest.mark.parametrize("data,reason", [
    (b"\xff", "can't decode byte 0xff"), ("{", "Expecting property name"), (DEEP, "nested too deeply"),
    (HUGE_INT, "4300 digits"),
])
def test_malformed_json_is_one_error_naming_what_it_was(data: str | bytes, reason: str) -> None:
    with pytest.raises(CogexploreError, match=rf"^the card is not readable JSON: .*{reason}"):
        parse_json(data, "the card")


def test_nan_and_infinity_are_refused_where_json_must_be_standard(tmp_path: Path) -> None:
    assert parse_json('{"x": 1.5}', "x", allow_nan=False) == {"x": 1.5}
    assert np.isnan(parse_json('{"x": NaN}', "x")["x"])  # where Python's own files may hold them
    for text in ('{"x": NaN}', '{"x": -Infinity}', '{"x": 1e999}'):
        with pytest.raises(CogexploreError, match="not readable JSON"):
            parse_json(text, "x", allow_nan=False)
    folder = tmp_path / "dir.json"
    folder.mkdir()
    with pytest.raises(CogexploreError, match=r"dir.json cannot be read"):
        read_json_file(folder, "results file")


def _write(path: Path, data: str | bytes) -> Path:
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path


def _sparse(path: Path, size: int) -> Path:
    """A file of ``size`` zero bytes that takes no disk."""
    with open(path, "wb") as fh:
        fh.truncate(size)
    return path


def test_a_small_json_file_over_its_limit_is_refused_before_it_is_read(tmp_path: Path) -> None:
    # Every JSON file was read up to 256 MiB, a dataset's manifest too: a big file given by mistake
    # was read and parsed whole.
    from shared.expert.dataset import SupervisedDataset, SupervisedError
    from shared.jsontext import SMALL_JSON_BYTES

    card = _write(tmp_path / "card.json", '{"n": 123}')
    assert read_json_file(card, "card", max_bytes=10) == {"n": 123}
    with pytest.raises(CogexploreError, match=r"^card .*card.json cannot be read: too large: 10 bytes, over the "
                                              r"limit of 9 \("):
        read_json_file(card, "card", max_bytes=9)
    root = tmp_path / "data"
    root.mkdir()
    _sparse(root / "manifest.json", SMALL_JSON_BYTES + 1)
    with pytest.raises(SupervisedError) as caught:
        SupervisedDataset.open(root)
    assert f"too large: {SMALL_JSON_BYTES + 1:,} bytes" in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize("data", [b"\xff\xfe", DEEP, HUGE_INT, "[]", '{"schema": 1}'])
def test_a_stray_json_file_is_not_results_and_report_looks_past_it(data: str | bytes, tmp_path: Path) -> None:
    from services.tools.report import find_results
    from shared.evaluation.results import ResultsError, load_results

    stray = _write(tmp_path / "a-stray.json", data)
    with pytest.raises(ResultsError):
        load_results(stray)
    (tmp_path / "b-folder.json").mkdir()
    assert find_results([tmp_path], {"policy": "greedy"}) is None  # skipped, not a crash


@pytest.mark.parametrize("data", [b"x = \xff", "x = " + "[" * 100_000, "[env]\nmax_episode_steps = true\n"])
def test_a_broken_preset_file_is_a_config_error(data: str | bytes, tmp_path: Path) -> None:
    from shared.config import ConfigError, load_preset

    with pytest.raises(ConfigError, match="bad.toml"):
        load_preset(_write(tmp_path / "bad.toml", data))
    (tmp_path / "folder.toml").mkdir()
    with pytest.raises(ConfigError, match="cannot be read"):
        load_preset(tmp_path / "folder.toml")


def test_a_demonstration_file_with_forged_metadata_is_refused(tmp_path: Path) -> None:
    from shared.learning.demos import DemoError, load_demonstrations

    for meta in ({"format": "cogexplore-demos", "version": 1, "demos": 5}, [1, 2], "[" * 100_000):
        text = meta if isinstance(meta, str) else json.dumps(meta)
        path = tmp_path / "demos.npz"
        np.savez(path, meta=np.frombuffer(text.encode(), dtype=np.uint8))
        with pytest.raises(DemoError, match="metadata"):
            load_demonstrations(path)


def test_a_probe_image_that_holds_no_image_is_refused(tmp_path: Path) -> None:
    from shared.evaluation.probes import ProbeError, load_probe_image

    for shape in ((0, 0), (5, 0)):
        np.save(tmp_path / "empty.npy", np.zeros(shape))
        with pytest.raises(ProbeError, match="expected one"):
            load_probe_image(tmp_path / "empty.npy")


def test_a_procedural_seed_of_thousands_of_digits_is_a_clear_error() -> None:
    from shared.config import ConfigError, parse_world_list
    from shared.sim.world import WorldError, load_world

    seed = "9" * 5000
    with pytest.raises(WorldError, match="at most 18 digits"):
        load_world(f"procedural:{seed}")
    with pytest.raises(ConfigError, match="18 digits"):
        parse_world_list(f"procedural:1-{seed}")
    assert parse_world_list("procedural:7") == ("procedural:7",)


@pytest.mark.timeout(30)
def test_a_fifo_or_a_device_given_as_a_file_is_refused_not_waited_on(tmp_path: Path) -> None:
    # A FIFO with no writer held the read (and the command) forever; /dev/zero would never end.
    import os

    from services.viz.figures import FigureError, load_loss_log
    from shared.config import ConfigError, load_preset

    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="pipe.toml cannot be read: not a regular file"):
        load_preset(fifo)
    for path in (fifo, Path("/dev/zero")):
        with pytest.raises(CogexploreError, match="cannot be read: not a regular file"):
            read_json_file(path, "card")
    with pytest.raises(FigureError, match="not a regular file"):
        load_loss_log(fifo)
