"""Receptive-field maps: the bilinear kernel, the upsampling geometry, the top-10 % mask."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.tools.receptive import (
    ReceptiveFieldError,
    bilinear_kernel,
    command_arrow_angle_deg,
    receptive_field,
    render_receptive_png,
    top_count,
    top_fraction_mask,
    upsample_pool3,
)
from shared.config import ModelConfig, SensorConfig


def fcn_upsample_filt(size: int) -> np.ndarray:
    # FCN's surgery.upsample_filt, verbatim in numpy.
    factor = (size + 1) // 2
    center = factor - 1 if size % 2 == 1 else factor - 0.5
    og = np.ogrid[:size, :size]
    return (1 - abs(og[0] - center) / factor) * (1 - abs(og[1] - center) / factor)


@pytest.mark.parametrize("size", [15, 16, 4, 3])
def test_kernel_matches_fcn_formula(size: int) -> None:
    np.testing.assert_allclose(bilinear_kernel(size), fcn_upsample_filt(size), rtol=0, atol=1e-7)


def test_kernel_15_values() -> None:
    k = bilinear_kernel(15)
    assert k.shape == (15, 15)
    assert k[7, 7] == 1.0
    assert k[0, 0] == pytest.approx(1 / 64)
    assert k[7, 0] == pytest.approx(1 / 8)
    np.testing.assert_allclose(k, k.T)
    np.testing.assert_allclose(k, k[::-1, ::-1])


def test_kernel_rejects_bad_size() -> None:
    with pytest.raises(ReceptiveFieldError, match="positive integer"):
        bilinear_kernel(0)


def test_upsampled_shape_is_input_size() -> None:
    pool3 = torch.rand(2, 64, 15, 20)
    out = upsample_pool3(pool3)
    assert out.shape == (2, 120, 160)


@pytest.mark.parametrize("r,c", [(7, 9), (0, 0), (14, 19), (3, 0)])
def test_single_unit_upsamples_to_kernel_at_its_block(r: int, c: int) -> None:
    pool3 = np.zeros((1, 64, 15, 20), dtype=np.float32)
    pool3[0, 5, r, c] = 2.0  # one channel: the channel sum is this unit alone
    out = upsample_pool3(pool3)[0]
    expected = np.zeros((120 + 30, 160 + 30), dtype=np.float32)  # margin for kernels off the edge
    cy, cx = 8 * r + 3, 8 * c + 3  # centre of the kernel (see the module docstring)
    expected[15 + cy - 7:15 + cy + 8, 15 + cx - 7:15 + cx + 8] = 2.0 * bilinear_kernel(15)
    np.testing.assert_allclose(out, expected[15:135, 15:175], atol=1e-6)
    assert np.unravel_index(np.argmax(out), out.shape) == (cy, cx)


def test_upsampling_sums_channels_linearly() -> None:
    rng = np.random.default_rng(0)
    pool3 = rng.random((1, 64, 15, 20)).astype(np.float32)
    summed = pool3.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(upsample_pool3(pool3), upsample_pool3(summed), rtol=1e-5)


def test_constant_pool3_is_flat_inside() -> None:
    # Bilinear weights of stride 8 tile to a constant away from the border.
    out = upsample_pool3(np.ones((1, 1, 15, 20), dtype=np.float32))[0]
    np.testing.assert_allclose(out[12:108, 12:148], 1.0, atol=1e-6)


def test_upsample_rejects_wrong_rank() -> None:
    with pytest.raises(ReceptiveFieldError, match=r"\(B, C, h, w\)"):
        upsample_pool3(np.zeros((64, 15, 20)))


def test_top_count_definition() -> None:
    assert top_count(120 * 160, 0.10) == 1920
    assert top_count(100, 0.07) == 7  # 0.07 * 100 = 7.000000000000001 in floats
    assert top_count(99, 0.10) == 10  # ceil(9.9)
    assert top_count(5, 0.01) == 1
    assert top_count(10, 1.0) == 10
    for bad in (0.0, -0.1, 1.5):
        with pytest.raises(ReceptiveFieldError, match="fraction"):
            top_count(10, bad)


def test_mask_size_and_content() -> None:
    rng = np.random.default_rng(1)
    values = rng.random((120, 160))
    mask = top_fraction_mask(values, 0.10)
    assert mask.dtype == bool and mask.shape == (120, 160)
    assert mask.sum() == 1920
    assert values[mask].min() >= values[~mask].max()


def test_mask_size_with_ties_and_batches() -> None:
    flat = np.zeros((3, 120, 160))
    flat[1, :10, :] = 5.0  # 1600 clear winners, the rest tied
    mask = top_fraction_mask(flat, 0.10)
    assert mask.shape == (3, 120, 160)
    assert mask.reshape(3, -1).sum(axis=1).tolist() == [1920, 1920, 1920]
    assert mask[1, :10, :].all()
    assert top_fraction_mask(torch.from_numpy(flat[0])).sum() == 1920


def test_mask_rejects_nan() -> None:
    values = np.zeros((4, 4))
    values[0, 0] = np.nan
    with pytest.raises(ReceptiveFieldError, match="NaN"):
        top_fraction_mask(values)


def test_receptive_field_of_real_qnetwork() -> None:
    from shared.learning.model import QNetwork

    torch.manual_seed(0)
    net = QNetwork(ModelConfig(), SensorConfig())
    net.train()
    depth = np.full((120, 160), 3.0, dtype=np.float32)
    depth[:, :40] = 0.8  # a near wall on the left
    rmap, mask, q, action = receptive_field(net, depth)
    assert rmap.shape == (120, 160) and mask.shape == (120, 160)
    assert mask.sum() == 1920
    assert q.shape == (5,) and action == int(np.argmax(q))
    assert net.training  # the training flag is restored
    # Same numbers as running the pieces by hand in eval mode.
    from shared.learning.model import preprocess_depth

    net.eval()
    with torch.no_grad():
        x = preprocess_depth(depth)
        np.testing.assert_allclose(q, net(x)[0].numpy(), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(rmap, upsample_pool3(net.features(x))[0], rtol=1e-5, atol=1e-5)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_receptive_field_of_a_network_on_the_gpu() -> None:
    # The kernel stayed on the CPU while pool3 was on the GPU: conv_transpose2d refused the mix, and
    # cogexplore report (--device auto) ended in a traceback after every evaluation had run.
    from shared.learning.model import QNetwork

    torch.manual_seed(0)
    net = QNetwork(ModelConfig(), SensorConfig())
    depth = np.full((120, 160), 3.0, dtype=np.float32)
    rmap, mask, q, action = receptive_field(net.to("cuda"), depth)
    expected = receptive_field(net.to("cpu"), depth)
    np.testing.assert_allclose(rmap, expected[0], rtol=1e-4, atol=1e-4)
    assert (mask == expected[1]).mean() > 0.99 and action == expected[3]


def test_receptive_field_of_the_shipped_image_size_leaves_the_unpooled_margin_out() -> None:
    """40 x 30 (the shipped recipe's image): pool3 is 3 x 5 and covers rows 0-23; rows 24-29, which
    no pooling block reaches, are in the map at its least value and never in the top 10 %."""
    from shared.learning.model import QNetwork, preprocess_depth

    torch.manual_seed(0)
    net = QNetwork(ModelConfig(depth_encoding="inverse", previous_action=True), SensorConfig(width=40, height=30))
    depth = np.full((30, 40), 3.0, dtype=np.float32)
    depth[:, 30:] = 0.8  # a near wall on the right
    rmap, mask, q, action = receptive_field(net, depth)
    assert rmap.shape == (30, 40) and mask.shape == (30, 40)
    assert mask.sum() == 120  # 10 % of the whole image
    assert not mask[24:].any() and (rmap[24:] == rmap.min()).all()
    net.eval()
    with torch.no_grad():
        pooled = upsample_pool3(net.features(preprocess_depth(depth)))[0]
    assert pooled.shape == (24, 40)
    np.testing.assert_allclose(rmap[:24], pooled, rtol=1e-5, atol=1e-5)


def test_receptive_field_rejects_batch() -> None:
    from shared.learning.model import QNetwork

    with pytest.raises(ReceptiveFieldError, match="one"):
        receptive_field(QNetwork(), np.zeros((2, 120, 160), dtype=np.float32))


def test_arrow_angles_follow_the_commands() -> None:
    angles = [command_arrow_angle_deg(a) for a in range(5)]
    assert angles == pytest.approx([180.0, 135.0, 90.0, 45.0, 0.0])
    with pytest.raises(ReceptiveFieldError):
        command_arrow_angle_deg(5)


def test_render_png(tmp_path) -> None:
    depth = np.linspace(0.0, 4.0, 120 * 160, dtype=np.float32).reshape(120, 160)
    mask = top_fraction_mask(depth)
    out = render_receptive_png(depth, mask, np.array([-1.0, 2.0, 0.5, -3.0, 0.0]), 1,
                               tmp_path / "fig" / "s1.png", title="S1 DRL")
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    import matplotlib.image as mpimg

    img = mpimg.imread(out)
    # Some pixel carries the purple overlay (red and blue well above green).
    rgb = img[..., :3]
    assert ((rgb[..., 0] - rgb[..., 1] > 0.2) & (rgb[..., 2] - rgb[..., 1] > 0.3)).any()
    with pytest.raises(ReceptiveFieldError, match="same"):
        render_receptive_png(depth, mask[:10], None, 0, tmp_path / "bad.png")


def test_render_takes_a_title_with_dollar_signs_as_text(tmp_path) -> None:
    # The report titles each figure "<scene> / <model>", both names of files: a probe named
    # "a$^$b.png" was parsed as TeX and its ValueError ended the whole report.
    depth = np.full((30, 40), 2.0, dtype=np.float32)
    for i, title in enumerate(("user:a$^$b / run@10", "user:cost$5 and $6 / m$\\alpha$")):
        out = render_receptive_png(depth, np.zeros(depth.shape, bool), np.zeros(5), 2, tmp_path / f"{i}.png",
                                   title=title)
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
