"""A run's folder, ``runs/<run>/``, and the config every process of the run resolves from its
options (``--preset``, ``--set``, ``--device``) and the folder's saved ``config.toml``."""

from __future__ import annotations

import argparse
import fcntl
import os
import socket
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from shared.config import DEFAULT_PRESET, RunConfig, load_preset, parse_override, to_toml
from shared.errors import CogexploreError
from shared.files import atomic_write_text
from shared.wire.keys import validate_name

CONFIG_FILE = "config.toml"


@dataclass(frozen=True)
class RunPaths:
    """The layout of runs/<run>/."""

    root: Path

    @property
    def config(self) -> Path:
        return self.root / CONFIG_FILE

    @property
    def checkpoints(self) -> Path:
        return self.root / "checkpoints"

    @property
    def logs(self) -> Path:
        return self.root / "logs"

    @property
    def stats(self) -> Path:
        return self.root / "stats"

    @property
    def tensorboard(self) -> Path:
        """TensorBoard event files, one folder per process (``tb/learner``, ``tb/actor-0``, ...); each
        process makes its own, so ``make`` does not."""
        return self.root / "tb"

    def tensorboard_folder(self, process: str) -> Path:
        """``tb/<process>``: where the process of that id writes its TensorBoard events."""
        return self.tensorboard / validate_name(process, "process id")

    @property
    def secure(self) -> Path:
        """The run's security folder: credentials, access control, certificates (services.bus.security)."""
        return self.root / "secure"

    @property
    def recordings(self) -> Path:
        return self.root / "recordings"

    @property
    def report(self) -> Path:
        return self.root / "report"

    def make(self) -> "RunPaths":
        for d in (self.root, self.checkpoints, self.logs, self.stats, self.recordings, self.report):
            d.mkdir(parents=True, exist_ok=True)
        return self


class RunInUseError(CogexploreError):
    """Another process already holds the run in the role asked for (two `up`, two learners)."""


class RunsDirError(CogexploreError):
    """The folder that should hold the runs is something else (a file)."""


def check_runs_folder(folder: Path) -> None:
    """RunsDirError when ``folder``, the one that holds the runs, exists and is not a folder: the
    errors further on would name a file in it instead ("File exists", "Not a directory")."""
    if folder.exists() and not folder.is_dir():
        raise RunsDirError(f"the runs folder {folder} is not a folder (--runs-dir)")


class RunLock:
    """An exclusive hold on a run for one role (``up``, ``learner``): ``<runs>/.<run>.<role>.lock``, a
    lock the system drops when the process ends however it ends. Two learners writing one run's
    checkpoints, or two `up` starting one run, would corrupt it. Beside the run's folder, not in it,
    so that `up --fresh` can move the folder aside while holding it. Released by :meth:`release`, at
    the end of a ``with`` block, or when the object goes."""

    def __init__(self, paths: RunPaths, role: str):
        self.path = paths.root.parent / f".{paths.root.name}.{role}.lock"
        check_runs_folder(paths.root.parent)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # not through a symlink: the pid written below would replace whatever file it points at
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            self._file: IO[str] | None = open(fd, "r+", errors="replace")
        except OSError as exc:
            raise RunInUseError(f"cannot hold run {paths.root.name!r}: {self.path}: {exc.strerror or exc}") from None
        try:
            fcntl.flock(self._file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            self._file.seek(0)
            holder = self._file.read().strip() or "another process"
            self.release()
            if isinstance(exc, BlockingIOError):
                raise RunInUseError(f"run {paths.root.name!r} is in use: its {role} is {holder} "
                                    f"({self.path}); stop that one first") from None
            raise RunInUseError(f"cannot hold run {paths.root.name!r}: {self.path}: {exc.strerror or exc} "
                                "(a file system without locks?)") from None
        self._file.seek(0)
        self._file.truncate()
        note = f"pid {os.getpid()} on {socket.gethostname()}\n".encode()
        try:  # unbuffered: a write a full disk refuses must not wait in the buffer to fail again at release
            if os.pwrite(self._file.fileno(), note, 0) != len(note):
                os.ftruncate(self._file.fileno(), 0)  # cut short: a pid cut short would name another process
        except OSError:  # only a note for another process's refusal: the lock is held without it
            pass

    def release(self) -> None:
        if self._file is not None:
            self._file.close()  # closing drops the lock
            self._file = None

    def __enter__(self) -> "RunLock":
        return self

    def __exit__(self, *exc_info: object) -> None:
        # at once, also on an error: a traceback kept by the caller would keep the object, and the lock
        self.release()


def run_paths(args: argparse.Namespace) -> RunPaths:
    validate_name(args.run, "run name")
    check_runs_folder(Path(args.runs_dir))
    return RunPaths(Path(args.runs_dir) / args.run)


def resolve_config(args: argparse.Namespace, paths: RunPaths | None = None,
                   run_config: RunConfig | None = None, *, own_device: bool = False,
                   default_preset: str = DEFAULT_PRESET) -> RunConfig:
    """--preset if given, else ``run_config`` (the run's, from its learner), else the run's saved
    config, else ``default_preset`` (:data:`~shared.config.DEFAULT_PRESET`); then --set and --device.

    ``own_device`` (actors, the evaluator): the base's ``train.device`` reads ``auto`` (the CPU for
    them) unless --set or --device name one. A run's config names its learner's device (``up --device
    cuda`` saves it), and an actor on another machine may have no GPU."""
    if args.preset is not None:
        cfg = load_preset(args.preset)
    elif run_config is not None:
        cfg = run_config
    else:
        # a dangling symlink is a saved config that cannot be read, not a run without one
        saved = paths is not None and (paths.config.exists() or paths.config.is_symlink())
        cfg = load_preset(paths.config, complete=True) if saved else load_preset(default_preset)
    if own_device:
        cfg = cfg.with_overrides({"train.device": "auto"})
    overrides = dict(parse_override(o) for o in getattr(args, "overrides", []) or [])
    if getattr(args, "device", None):
        overrides["train.device"] = args.device
    return cfg.with_overrides(overrides) if overrides else cfg


def saved_config(paths: RunPaths) -> RunConfig | None:
    """The run's saved config; None when it has none or it cannot be read (whoever needs it says so)."""
    try:
        return load_preset(paths.config, complete=True) if paths.config.is_file() else None
    except CogexploreError:
        return None


def save_config(cfg: RunConfig, paths: RunPaths) -> None:
    """Write the run's config atomically (services started later read it back)."""
    paths.root.mkdir(parents=True, exist_ok=True)
    atomic_write_text(paths.config, to_toml(cfg))


