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
