"""Test-wide settings: offline, headless, small thread counts (2-core CI)."""

import os

os.environ.setdefault("RERUN_ANALYTICS", "0")
os.environ.setdefault("MUJOCO_GL", "egl")  # must precede the first mujoco import
os.environ.setdefault("OMP_NUM_THREADS", "2")
