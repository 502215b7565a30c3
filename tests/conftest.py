"""Test-wide settings: offline, headless, small thread counts (2-core CI)."""

import os

os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("MUJOCO_GL", "egl")  # must precede the first mujoco import
os.environ.setdefault("OMP_NUM_THREADS", "2")


import pytest  # noqa: E402


@pytest.fixture
def one_torch_thread():
    """Tiny networks: one torch thread is faster, and far faster on a loaded 2-core machine."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


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
