"""Reading a user's file whole (``shared.files.read_regular_file``): a file far too big for what
it should be is refused from its size, before it is read, with the size and the limit named."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from services.viz.figures import FigureError, load_loss_log
from shared.config import ConfigError, load_preset
from shared.errors import CogexploreError
from shared.files import MAX_READ_BYTES, read_regular_file
from shared.jsontext import read_json_file
from shared.learning.checkpoints import LATEST, LATEST_MAX_BYTES, CheckpointError, CheckpointManager


def sparse(path: Path, size: int) -> Path:
    """A file of ``size`` bytes that takes no disk (a checkpoint or video where text was meant)."""
    with open(path, "wb") as fh:
        fh.truncate(size)
    return path


def test_a_file_over_the_limit_is_refused_before_it_is_read(tmp_path: Path) -> None:
    big = sparse(tmp_path / "config.toml", 4 * 2**30)
    with pytest.raises(OSError) as caught:
        read_regular_file(big)
    assert caught.value.errno == errno.EFBIG
    assert f"{4 * 2**30:,} bytes" in caught.value.strerror and f"{MAX_READ_BYTES:,}" in caught.value.strerror
    # a caller's own limit; a file of exactly the limit is read
    (tmp_path / "ten").write_bytes(b"0123456789")
    assert read_regular_file(tmp_path / "ten", max_bytes=10) == b"0123456789"
    with pytest.raises(OSError, match="too large: 10 bytes, over the limit of 9"):
        read_regular_file(tmp_path / "ten", max_bytes=9)


def checkpoint_pointer(path: Path) -> None:
    CheckpointManager(path.parent).latest()


@pytest.mark.parametrize("name, read, error, limit", [
    ("run.toml", load_preset, ConfigError, MAX_READ_BYTES),
    ("card.json", lambda p: read_json_file(p, "--card", ConfigError), ConfigError, MAX_READ_BYTES),
    ("loss.jsonl", load_loss_log, FigureError, MAX_READ_BYTES),
    (LATEST, checkpoint_pointer, CheckpointError, LATEST_MAX_BYTES),  # a pointer is a file name
])
def test_each_reader_of_a_users_file_says_in_one_line_that_it_is_too_large(tmp_path: Path, name, read,
                                                                             error: type[CogexploreError],
                                                                             limit: int) -> None:
    path = sparse(tmp_path / name, 3 * 2**30)
    with pytest.raises(error) as caught:
        read(path)
    message = str(caught.value)
    assert "\n" not in message and str(path) in message, message
    assert f"{3 * 2**30:,} bytes" in message and f"limit of {limit:,}" in message, message
