"""The depth contract, in one place: float32 metres in the env and the network's input
(0 = no return), uint16 millimetres on the wire, in replay and in recordings; the camera's range
gate, and an image of another size seen as the camera would have seen it."""

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
    # float16 has neither the millimetres (2 mm steps past 2 m) nor 65535 (its largest is 65504): in
    # float32; saturated before the scaling, so a huge depth does not overflow to infinity on the way
    depth = depth.astype(np.promote_types(depth.dtype, np.float32), copy=False)
    return np.rint(np.minimum(depth, UINT16_MAX / MM_PER_M) * MM_PER_M).astype(np.uint16)


def depth_from_mm(depth_mm: np.ndarray) -> np.ndarray:
    """uint16 millimetres -> float32 metres."""
    depth_mm = np.asarray(depth_mm)
    if depth_mm.dtype != np.uint16:
        raise ValueError(f"depth_mm must be uint16, got {depth_mm.dtype}")
    return depth_mm.astype(np.float32) * np.float32(1.0 / MM_PER_M)


SAME_SURFACE_RATIO = 1.2
"""Neighbouring returns within this depth ratio of each other are taken as one surface when
resizing (:func:`resize_depth`); farther apart, an edge."""


def range_gate(depth_m: np.ndarray, min_range_m: float, max_range_m: float) -> np.ndarray:
    """float32 depth with every pixel outside ``[min_range_m, max_range_m]`` (NaN included)
    read as 0, no return: what the depth camera reports."""
    depth = np.asarray(depth_m)
    valid = (depth >= max(min_range_m, 1e-6)) & (depth <= max_range_m)
    return np.where(valid, depth, 0.0).astype(np.float32, copy=False)


def resize_depth(depth_m: np.ndarray, height: int, width: int) -> np.ndarray:
    """A depth image (float metres, 0 = no return) resampled to ``height`` x ``width`` pixels of
    the same field of view, as the pinhole camera (``shared.sim.sensor``) would have seen it:
    each new pixel is the depth at its centre.

    A centre between source pixels interpolates their *inverse* depth bilinearly, which is exact
    on a plane (the floor, a wall: 1/depth is affine in the image coordinates), when those pixels
    all have a return within ``SAME_SURFACE_RATIO`` of each other; otherwise the centre lies on an
    edge and takes the nearest of their returns (an obstacle is never lost to the far side, and
    "no return" never smears into its neighbours). NaN, infinity and depths <= 0 read as no
    return. Returns float32 (height, width).
    """
    src = np.asarray(depth_m, dtype=np.float64)
    if src.ndim != 2 or src.size == 0:
        raise ValueError(f"depth must be one non-empty (H, W) image, got shape {src.shape}")
    inverse = np.zeros_like(src)
    np.divide(1.0, src, out=inverse, where=np.isfinite(src) & (src > 0))
    if src.shape == (height, width):
        return np.where(inverse > 0, src, 0.0).astype(np.float32)

    def taps(n_src: int, n_dst: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Pixel centres map linearly between two pinhole images of one field of view.
        pos = np.clip((np.arange(n_dst) + 0.5) * n_src / n_dst - 0.5, 0, n_src - 1)
        lo = np.floor(pos).astype(int)
        return lo, np.minimum(lo + 1, n_src - 1), pos - lo

    r0, r1, fr = taps(src.shape[0], height)
    c0, c1, fc = taps(src.shape[1], width)
    fr, fc = fr[:, None], fc[None, :]
    corners = [(inverse[np.ix_(r, c)], w) for r, c, w in (
        (r0, c0, (1 - fr) * (1 - fc)), (r0, c1, (1 - fr) * fc), (r1, c0, fr * (1 - fc)), (r1, c1, fr * fc))]
    used = [(inv, w > 0) for inv, w in corners]
    nearest = np.max([np.where(u, inv, 0.0) for inv, u in used], axis=0)  # largest inverse: nearest return
    farthest = np.min([np.where(u, inv, np.inf) for inv, u in used], axis=0)
    surface = (farthest > 0) & (nearest <= SAME_SURFACE_RATIO * farthest)
    blended = sum(inv * w for inv, w in corners)
    out = np.where(surface, blended, nearest)
    with np.errstate(divide="ignore"):
        return np.where(out > 0, 1.0 / out, 0.0).astype(np.float32)


def image_stack(depth_m: np.ndarray, earlier: tuple[np.ndarray, ...], count: int) -> np.ndarray:
    """(count, H, W): this image, then the ones acted on before it (most recent first), the oldest
    repeated where an episode has fewer: the stacks the replay samples for ``model.frame_stack``."""
    images = (depth_m, *earlier)[:count]
    return np.stack(images + images[-1:] * (count - len(images)))
