"""``services.runs``: a run's lock and its saved config, against files a user or a crash left there."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from services.runs import RunInUseError, RunLock, RunPaths, resolve_config, save_config
from shared.config import ConfigError, load_preset


def test_a_lock_file_that_is_a_symlink_is_refused_and_its_target_kept(tmp_path: Path) -> None:
    # the lock was opened through the link, and the holder's pid written over the file it named
    paths = RunPaths(tmp_path / "runs" / "r").make()
    save_config(load_preset("tiny"), paths)
    saved = paths.config.read_bytes()
    (tmp_path / "runs" / ".r.up.lock").symlink_to(paths.config)
    with pytest.raises(RunInUseError, match="cannot hold run 'r'"):
        RunLock(paths, "up")
    assert paths.config.read_bytes() == saved
    RunLock(paths, "learner").release()  # another role's lock, a plain file, is taken as before


def test_a_held_lock_with_unreadable_text_still_names_the_run_in_use(tmp_path: Path) -> None:
    paths = RunPaths(tmp_path / "r")
    held = RunLock(paths, "up")
    try:
        held.path.write_bytes(b"\xff\xfe pid ?\n")  # not UTF-8: was a UnicodeDecodeError
        with pytest.raises(RunInUseError, match="is in use: its up is"):
            RunLock(paths, "up")
    finally:
        held.release()
    RunLock(paths, "up").release()  # released: free again


def test_a_saved_config_that_is_a_dangling_symlink_is_an_error_not_the_default_preset(tmp_path: Path) -> None:
    # the run resumed silently with the default preset, and `up` then saved that over the link
    paths = RunPaths(tmp_path / "r").make()
    paths.config.symlink_to(tmp_path / "moved-away.toml")
    args = argparse.Namespace(preset=None, overrides=[], device=None)
    with pytest.raises(ConfigError, match="config.toml"):
        resolve_config(args, paths)
    save_config(load_preset("tiny"), paths)  # a config saved anew replaces the link
    assert resolve_config(args, paths).to_dict() == load_preset("tiny").to_dict()
