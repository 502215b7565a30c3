"""``shared.depth``: the camera's range gate and resizing a depth image as the camera samples it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.depth import depth_to_mm, range_gate, resize_depth


def _tilted_plane(height: int, width: int, hfov_deg: float = 57.0, vfov_deg: float = 43.0) -> np.ndarray:
    """Axial depth of a tilted plane seen by a pinhole camera of this size: 1/depth is affine in the
    image-plane coordinates of each pixel centre."""
    u = math.tan(math.radians(hfov_deg) / 2) * (1 - 2 * (np.arange(width) + 0.5) / width)
    v = math.tan(math.radians(vfov_deg) / 2) * (1 - 2 * (np.arange(height) + 0.5) / height)
    return 1.0 / (0.4 + 0.15 * u[None, :] - 0.2 * v[:, None])


@pytest.mark.parametrize("source", [(480, 640), (120, 160), (75, 100), (90, 120), (15, 20)])
def test_resize_is_exact_on_a_plane(source: tuple[int, int]) -> None:
    # What the camera would have seen at 40 x 30, whether the source is finer, coarser, or an odd,
    # even or fractional multiple (15 x 20 upsamples: the outermost pixels are extrapolated, not exact).
    want = _tilted_plane(30, 40)
    got = resize_depth(_tilted_plane(*source), 30, 40)
    assert got.dtype == np.float32 and got.shape == (30, 40)
    inner = (slice(1, -1), slice(1, -1)) if source[0] < 30 else (slice(None), slice(None))
    np.testing.assert_allclose(got[inner], want[inner], rtol=1e-5)


def test_resize_invents_no_depth_at_edges_and_keeps_no_return_where_it_is() -> None:
    step = np.full((48, 64), 3.0)
    step[:, :28] = 1.0  # a near obstacle's edge: column 17's centre (source x = 27.5) lies on it
    out = resize_depth(step, 30, 40)
    assert set(np.unique(out)) == {1.0, 3.0}
    # The column straddling the edge takes the nearer side: the obstacle is never lost.
    assert (out[:, :18] == 1.0).all() and (out[:, 18:] == 3.0).all()

    holes = np.full((480, 640), 2.0)
    holes[:, :320] = 0.0
    holes[:40, 400:] = np.nan
    holes[440:, 400:] = np.inf
    out = resize_depth(holes, 30, 40)
    assert set(np.unique(out)) == {0.0, 2.0}
    # NaN and inf read as no return, and no return spreads into no pixel with a return at its centre.
    assert (out[:, :20] == 0).all() and (out[2:-2, 20:] == 2.0).all()
    assert (out[:2, 25:] == 0).all() and (out[-2:, 25:] == 0).all()


def test_resize_same_size_is_the_image_itself() -> None:
    depth = np.random.default_rng(0).uniform(0.3, 4.0, (30, 40)).astype(np.float32)
    depth[3, 4], depth[5, 6] = np.nan, -1.0
    out = resize_depth(depth, 30, 40)
    assert out[3, 4] == 0 and out[5, 6] == 0
    out[3, 4], out[5, 6] = depth[3, 4], depth[5, 6]
    np.testing.assert_array_equal(out[np.isfinite(depth) & (depth > 0)], depth[np.isfinite(depth) & (depth > 0)])
    with pytest.raises(ValueError, match="one non-empty"):
        resize_depth(np.zeros((0, 4)), 30, 40)


def test_range_gate_reads_what_the_camera_cannot_see_as_no_return() -> None:
    depth = np.array([[0.0, 0.2, 0.5, 4.0, 4.01, np.nan, np.inf]], dtype=np.float64)
    out = range_gate(depth, 0.3, 4.0)
    assert out.dtype == np.float32
    np.testing.assert_array_equal(out, np.array([[0, 0, 0.5, 4.0, 0, 0, 0]], dtype=np.float32))


def test_depth_to_mm_saturates_huge_and_half_precision_depths_without_overflow(recwarn) -> None:
    # The product overflowed to infinity (float32 1e38, float16 70 m) and float16 could not hold the
    # 65535 it was clipped to: RuntimeWarnings on an actor's every frame.
    assert depth_to_mm(np.array([1e38, 65.5351, 1.0005, 4.0], np.float32)).tolist() == [65535, 65535, 1000, 4000]
    assert depth_to_mm(np.array([70.0, 4.0, 65.5], np.float16)).tolist() == [65535, 4000, 65500]
    assert depth_to_mm(np.array([1e300])).tolist() == [65535]
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]
