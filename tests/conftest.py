"""Test-wide settings: offline, headless, small thread counts (2-core CI)."""

import atexit
import os
import shutil
import tempfile

os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("MUJOCO_GL", "egl")  # must precede the first mujoco import
os.environ.setdefault("OMP_NUM_THREADS", "2")
# generated worlds are cached in a folder of this session's (its processes share it), never the user's
_WORLD_CACHE = tempfile.mkdtemp(prefix="cogexplore-test-cache-")
os.environ["COGEXPLORE_CACHE_DIR"] = _WORLD_CACHE
atexit.register(shutil.rmtree, _WORLD_CACHE, ignore_errors=True)


import pytest  # noqa: E402


@pytest.fixture
def one_torch_thread():
    """Tiny networks: one torch thread is faster, and far faster on a loaded 2-core machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def checkpoint_saves(monkeypatch) -> list[int]:
    """The update count of every checkpoint written from now on (each one is still written)."""
    from shared.learning.checkpoints import CheckpointManager

    saved: list[int] = []
    save = CheckpointManager.save

    def counted(self, agent, **kwargs):
        saved.append(agent.update_count)
        return save(self, agent, **kwargs)

    monkeypatch.setattr(CheckpointManager, "save", counted)
    return saved


@pytest.fixture(autouse=True)
def _restore_root_logging():
    """A CLI entry point under test may point the root logger at pytest's captured stderr, which
    pytest closes after that test; later Zenoh callback threads would then log to a closed file."""
    import logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in root.handlers[:]:
        if handler not in handlers:
            root.removeHandler(handler)
    root.setLevel(level)


class TensorBoardScalars:
    """A folder's TensorBoard scalars, read back with TensorBoard's own reader: ``tags[tag]`` is the
    list of (step, value) in the order written."""

    def __init__(self, folder) -> None:
        from tensorboard.backend.event_processing.event_accumulator import (
            EventAccumulator,
        )

        events = EventAccumulator(str(folder), size_guidance={"scalars": 0})  # 0: keep every point
        events.Reload()
        self.tags = {tag: [(e.step, e.value) for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}

    def assert_steps_increase(self) -> None:
        for tag, points in self.tags.items():
            steps = [s for s, _ in points]
            assert steps == sorted(set(steps)), f"{tag}: steps {steps}"

    def assert_match_csv(self, csv_path, row_type) -> int:
        """Every number of every row of ``csv_path`` (a file of ``row_type``) is the scalar of its
        column at the row's step, to the precision of its cell (but for the columns TensorBoard
        leaves out, which have none); returns the rows compared."""
        import csv
        from dataclasses import fields
        from pathlib import Path

        fmts = {f.metadata.get("column") or f.name: f.metadata.get("fmt") for f in fields(row_type)}
        group = Path(row_type.FILE).stem
        with open(csv_path, newline="") as fh:
            rows = list(csv.DictReader(fh))
        seen: set[str] = set()
        compared = 0
        for row in rows:
            step = int(row[row_type.STEP])
            if step in seen:
                continue  # a repeated step: TensorBoard keeps its first row
            seen.add(step)
            for column, cell in row.items():
                if column == row_type.STEP or column in row_type.unplotted() or cell == "":
                    continue
                try:
                    value = float(cell)
                except ValueError:
                    continue  # text (a world's name, a collision's cause)
                points = dict(self.tags.get(f"{group}/{column}", []))
                assert step in points, f"{group}/{column} has no point at step {step}"
                fmt = fmts[column] or ""
                half_unit = 0.5 * 10.0 ** -int(fmt[1:-1]) if fmt.endswith("f") else 0.0
                assert abs(points[step] - value) <= half_unit + 1e-5 * abs(value), (column, step, points[step], cell)
            compared += 1
        return compared


@pytest.fixture
def tensorboard_scalars():
    """``tensorboard_scalars(folder)``: that folder's TensorBoard scalars (:class:`TensorBoardScalars`)."""
    return TensorBoardScalars


@pytest.fixture(scope="module")
def loopback_router():
    """A Zenoh router in this process on a free loopback port: its endpoint."""
    from services.bus.session import free_tcp_port, open_router

    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint]):
        yield endpoint
