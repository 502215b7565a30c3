"""The depth contract, in one place: float32 metres in the env and the network's input
(0 = no return), uint16 millimetres on the wire, in replay and in recordings."""

from __future__ import annotations

import numpy as np

MM_PER_M = 1000.0
UINT16_MAX = int(np.iinfo(np.uint16).max)


def depth_to_mm(depth: np.ndarray) -> np.ndarray:
    """Float metres -> uint16 millimetres (rounded; beyond 65.535 m saturates).

    uint16 input is taken as millimetres already and passes through unchanged. NaN, infinity
    or negative depth raise ValueError: no valid sensor reports them.
    """
    depth = np.asarray(depth)
    if depth.dtype == np.uint16:
        return depth
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f"depth must be float metres or uint16 millimetres, got {depth.dtype}")
    if not np.isfinite(depth).all() or (depth < 0).any():
        raise ValueError("depth must be finite (no NaN or infinity) and >= 0 (0 = no return)")
    return np.minimum(np.rint(depth * MM_PER_M), UINT16_MAX).astype(np.uint16)


def depth_from_mm(depth_mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres -> float32 metres."""
    depth_mm = np.asarray(depth_mm)
    if depth_mm.dtype != np.uint16:
        raise ValueError(f"depth_mm must be uint16, got {depth_mm.dtype}")
    return depth_mm.astype(np.float32) * np.float32(1.0 / MM_PER_M)
