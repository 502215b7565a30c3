"""Receptive-field maps of the Q-network (the paper's Fig. 7 and Section V-C).

The paper sums the last feature maps (pool3, 64 x 15 x 20) over channels and brings the sum
back to the 120 x 160 input with a single-channel transposed convolution whose 15 x 15 kernel
is fixed to bilinear weights, as FCN initialises its upsampling layers; the highest 10 % of the
result is then marked on the depth image.

Geometry of the upsampling (stride s = 8, kernel k = 15, pool3 of h x w cells): a transposed
convolution outputs ``(h - 1) * s - 2 * p + k + output_padding`` = ``8h + 7 - 2p + op`` rows.
For exactly ``8h`` rows we need ``2p - op = 7``, so ``p = 4, op = 1``. Equivalently: the full
output (``p = 0``) has ``8h + 7`` rows, and we keep rows ``4 .. 8h + 3``. The kernel of pool3
cell ``(r, c)`` is then centred on pixel ``(8r + 3, 8c + 3)``, within half a pixel of the centre
(``8r + 3.5``) of the 8 x 8 input block that the cell pools; an odd kernel cannot do better.

An image whose sides are not multiples of 8 (the shipped 40 x 30: pool3 is 5 x 3, since each
2 x 2 pooling drops an odd last row) has a margin of up to 7 rows or columns at its bottom and
right that no pool3 cell's block covers. The map gives that margin its own least value, so it
never enters the top 10 %.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from shared.config import ACTION_NAMES, SPEED_TABLES
from shared.errors import CogexploreError

UPSAMPLE_STRIDE = 8
KERNEL_SIZE = 15
# See the module docstring: these make the output exactly stride x the input size.
UPSAMPLE_PADDING = 4
UPSAMPLE_OUTPUT_PADDING = 1
TOP_FRACTION = 0.10
# The paper marks the strongest activations in purple.
MASK_RGBA = (0.58, 0.0, 0.83, 0.55)


class ReceptiveFieldError(CogexploreError):
    """Input of the wrong shape or kind for a receptive-field computation."""


def bilinear_kernel(size: int = KERNEL_SIZE) -> np.ndarray:
    """The FCN bilinear upsampling kernel, a float32 (size, size) array.

    ``k[i, j] = (1 - |i - c| / f) * (1 - |j - c| / f)`` with ``f = ceil(size / 2)`` and
    ``c = f - 1`` for odd sizes, ``f - 0.5`` for even ones (FCN's ``upsample_filt``).
    For size 15: f = 8, c = 7, peak 1 at the centre and 1/64 at the corners.
    """
    if not isinstance(size, int) or isinstance(size, bool) or size < 1:
        raise ReceptiveFieldError(f"kernel size must be a positive integer, got {size!r}")
    factor = (size + 1) // 2
    center = factor - 1 if size % 2 == 1 else factor - 0.5
    ramp = 1.0 - np.abs(np.arange(size) - center) / factor
    return np.outer(ramp, ramp).astype(np.float32)


def upsample_pool3(pool3: torch.Tensor | np.ndarray) -> np.ndarray:
    """Sum pool3 (B, C, h, w) over channels and upsample to (B, 8h, 8w) with the fixed
    bilinear 15 x 15 transposed convolution (stride 8, padding 4, output padding 1)."""
    x = torch.as_tensor(pool3)
    if x.ndim != 4:
        raise ReceptiveFieldError(f"pool3 must be (B, C, h, w), got shape {tuple(x.shape)}")
    summed = x.detach().to(torch.float32).sum(dim=1, keepdim=True)  # (B, 1, h, w)
    # on the map's device: a network on the GPU (report's --device auto) gives its pool3 there
    weight = torch.from_numpy(bilinear_kernel(KERNEL_SIZE)).to(summed.device)[None, None]
    out = F.conv_transpose2d(summed, weight, stride=UPSAMPLE_STRIDE, padding=UPSAMPLE_PADDING,
                             output_padding=UPSAMPLE_OUTPUT_PADDING)
    return out[:, 0].cpu().numpy()


def top_count(num_pixels: int, fraction: float) -> int:
    """How many pixels the top ``fraction`` of ``num_pixels`` is: ``ceil(fraction * N)``, with
    the product rounded to 6 decimals first so that float error (0.07 * 100 = 7.000000000000001)
    does not add a pixel, and at least 1. 10 % of 120 x 160 is exactly 1920."""
    if not (isinstance(fraction, (int, float)) and 0.0 < fraction <= 1.0):
        raise ReceptiveFieldError(f"fraction must be in (0, 1], got {fraction!r}")
    return max(1, math.ceil(round(fraction * num_pixels, 6)))


def top_fraction_mask(values: np.ndarray | torch.Tensor, fraction: float = TOP_FRACTION) -> np.ndarray:
    """Boolean mask of the highest ``fraction`` of a (H, W) or (B, H, W) map.

    Exactly ``top_count(H * W, fraction)`` pixels per image are True. Ties at the threshold
    go to the earlier pixel in row-major order (a stable sort), so the size never drifts
    with flat regions; NaN is refused.
    """
    arr = torch.as_tensor(values).detach().cpu().numpy() if isinstance(values, torch.Tensor) \
        else np.asarray(values)
    if arr.ndim not in (2, 3):
        raise ReceptiveFieldError(f"map must be (H, W) or (B, H, W), got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.isnan(arr).any():
        raise ReceptiveFieldError("map must be numeric without NaN")
    batch = arr.reshape(-1, arr.shape[-2] * arr.shape[-1])
    k = top_count(batch.shape[1], fraction)
    order = np.argsort(-batch.astype(np.float64), axis=1, kind="stable")[:, :k]
    mask = np.zeros(batch.shape, dtype=bool)
    np.put_along_axis(mask, order, True, axis=1)
    return mask.reshape(arr.shape)


def receptive_field(model: torch.nn.Module, depth_m: np.ndarray,
                    preprocess: Callable[[np.ndarray], torch.Tensor] | None = None,
                    fraction: float = TOP_FRACTION) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Receptive-field map of one depth image.

    Returns ``(map, mask, q_values, action)``: the upsampled channel-summed pool3 (H, W)
    float32, its top-``fraction`` mask (H, W) bool, the five Q-values and the greedy action.
    ``model`` needs ``features(x) -> (1, C, H // 8, W // 8)`` and ``model(x) -> (1, A)``; it is run
    in eval mode (no dropout) and its training flag is restored. ``preprocess`` defaults to
    ``shared.learning.model.preprocess_depth``.
    """
    depth = np.asarray(depth_m)
    if depth.ndim != 2:
        raise ReceptiveFieldError(f"depth_m must be one (H, W) image, got shape {depth.shape}")
    if preprocess is None:
        from shared.learning.model import preprocess_depth as preprocess
    x = preprocess(depth)
    if x.ndim == 3:  # (1, H, W) -> (1, 1, H, W)
        x = x[:, None]
    elif x.ndim == 2:
        x = x[None, None]
    stack = getattr(getattr(model, "model_cfg", None), "frame_stack", 1)
    if x.shape[1] == 1 and stack > 1:  # a network that reads several images: a robot at rest sees this one
        x = x.expand(-1, stack, -1, -1).contiguous(memory_format=torch.channels_last)
    param = next(model.parameters(), None)
    if param is not None:
        x = x.to(param.device)
    was_training = model.training
    model.eval()
    try:
        with torch.no_grad():
            pool3 = model.features(x)
            q = model(x)
    finally:
        model.train(was_training)
    upsampled = upsample_pool3(pool3)[0]
    if tuple(pool3.shape[-2:]) != (depth.shape[0] // UPSAMPLE_STRIDE, depth.shape[1] // UPSAMPLE_STRIDE):
        raise ReceptiveFieldError(
            f"pool3 {tuple(pool3.shape)} does not map onto the depth image {depth.shape}: the network "
            f"must downsample by {UPSAMPLE_STRIDE} (rounding down)")
    margin = ((0, depth.shape[0] - upsampled.shape[0]), (0, depth.shape[1] - upsampled.shape[1]))
    upsampled = np.pad(upsampled, margin, constant_values=upsampled.min())  # pixels no pool3 cell pools
    q_values = q[0].detach().cpu().numpy().astype(np.float64)
    mask = top_fraction_mask(upsampled, fraction)
    return upsampled.astype(np.float32), mask, q_values, int(np.argmax(q_values))


def command_arrow_angle_deg(action: int) -> float:
    """Screen angle of the arrow for a command: straight points up (90 deg), the full turns
    point sideways (left 180, right 0), the half turns in between, in proportion to the
    test speed table's angular velocities."""
    if not (isinstance(action, (int, np.integer)) and 0 <= action < len(ACTION_NAMES)):
        raise ReceptiveFieldError(f"action must be an index in 0..{len(ACTION_NAMES) - 1}, got {action!r}")
    omegas = SPEED_TABLES["test"][0]
    return 90.0 + 90.0 * omegas[int(action)] / max(abs(w) for w in omegas)


def render_receptive_png(depth_m: np.ndarray, mask: np.ndarray, q_values: np.ndarray | None,
                         action: int, out_path: str | Path, title: str = "") -> Path:
    """Draw a depth image (grayscale, no return in white as in the paper), the mask in purple,
    an arrow for the chosen command under the image and the Q-values as text; save a PNG."""
    import matplotlib
    from matplotlib.figure import (
        Figure,  # no pyplot: no global figure state, no GUI backend
    )

    depth = np.asarray(depth_m, dtype=np.float32)
    mask = np.asarray(mask, dtype=bool)
    if depth.ndim != 2 or mask.shape != depth.shape:
        raise ReceptiveFieldError(f"depth {depth.shape} and mask {mask.shape} must be the same (H, W)")
    angle = math.radians(command_arrow_angle_deg(action))
    h, w = depth.shape

    fig = Figure(figsize=(4.0, 3.9), dpi=100)
    ax = fig.add_axes((0.03, 0.27, 0.94, 0.64 if title else 0.70))
    # Fixed scale (far returns light gray, never white) so that "no return" stays visibly white
    # and images of one figure are comparable.
    vmax = max(float(depth.max()), 4.0) / 0.85
    cmap = matplotlib.colormaps["gray"].with_extremes(bad="white")
    ax.imshow(np.ma.masked_where(depth <= 0, depth), cmap=cmap, vmin=0.0, vmax=vmax,
              interpolation="nearest")
    overlay = np.zeros((h, w, 4), dtype=np.float32)
    overlay[mask] = MASK_RGBA
    ax.imshow(overlay, interpolation="nearest")
    ax.set_xticks([])
    ax.set_yticks([])
    if title:  # names of scenes and models, not TeX: a "$" in a file name is a dollar sign
        from shared.sim.maps import plain_text

        ax.set_title(plain_text(title), fontsize=10)

    arrow_ax = fig.add_axes((0.40, 0.12, 0.20, 0.14))
    arrow_ax.set_xlim(-1.1, 1.1)
    arrow_ax.set_ylim(-0.2, 1.1)
    arrow_ax.set_aspect("equal")
    arrow_ax.set_axis_off()
    arrow_ax.annotate("", xy=(0.9 * math.cos(angle), 0.9 * math.sin(angle)), xytext=(0.0, 0.0),
                      arrowprops=dict(arrowstyle="-|>", lw=2.5, color="black", mutation_scale=18))

    if q_values is not None:
        q = np.asarray(q_values, dtype=np.float64).reshape(-1)
        cells = [f"{name}: {v:.1f}" for name, v in zip(ACTION_NAMES, q)]
        best = int(np.argmax(q))
        for i, text in enumerate(cells):
            fig.text(0.03 + 0.192 * i, 0.02, text.replace(": ", "\n"), fontsize=7, ha="left",
                     fontweight="bold" if i == best else "normal")
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    return out
