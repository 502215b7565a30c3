"""The Q-network (Tai & Liu 2016, Fig. 2) and its supervised sibling, with one depth preprocessing.

Input: one depth image, 1 x H x W (120 x 160 for the paper's Kinect), in metres with 0 = no return.
``preprocess_depth`` is the only place where depth becomes network input: metres are divided by
``DEPTH_SCALE_M`` (4 m, the Kinect's usable range) and clipped to [0, 1], so "no return" stays 0 and
the network sees the same numbers whatever the sensor's configured ``max_range_m``. The conv
stack's first, parameter-free step re-encodes that input (``ModelConfig.depth_encoding``, see
:func:`encode_depth`), so every caller feeds the same tensor whatever the encoding.

Layers (``ConvTrunk`` is the conv stack of the authors' supervised model, IROS 2016)::

    conv1 32 @ 5x5 (pad 2) + ReLU + 2x2 max-pool    -> 32 x 60 x 80
    conv2 32 @ 5x5 (pad 2) + ReLU + 2x2 max-pool    -> 32 x 30 x 40
    conv3 64 @ 5x5 (pad 2) + ReLU + 2x2 max-pool    -> 64 x 15 x 20   ("pool3", the paper's 64 x 20 x 15)
    fc1 (ModelConfig.fc1, default 512) + ReLU + dropout
    fc2 (ModelConfig.fc2, default 256) + ReLU + dropout
    fc3 5 (one Q-value per moving command; 5 x N return quantiles with ModelConfig.quantiles),
        or a dueling value/advantage head

Speed on CPU (``cogexplore bench learner``): three things, all in this module, matter on the
2-core dev VM. Measured as the share of the in-process fp32 matmul peak that a batch-32 Double-DQN
update achieves (3 runs each, separate processes, machine shared with other jobs): plain PyTorch
0.25-0.34; + channels-last (oneDNN's native NHWC convolutions) 0.36-0.45; + pooling before ReLU
(same values, 4x smaller ReLU tensors) 0.38-0.44; + ``reduce_allocator_page_faults`` 0.51-0.59,
i.e. about 2x the plain version. ``torch.compile`` (67 s to compile, no faster), a NCHW conv1
(C_in = 1) and TorchScript freezing for inference did not help and were dropped. The networks
are created channels-last and ``.to(...)`` keeps that; single-image inference goes through
:class:`InferenceRunner` (eval mode, ``torch.inference_mode``).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Iterable
from dataclasses import asdict
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from shared.config import DEPTH_ENCODINGS, MUST_MATCH_FIELDS, NUM_ACTIONS, ModelConfig, SensorConfig
from shared.depth import MM_PER_M
from shared.errors import CogexploreError
from shared.wire.messages import shape_fingerprint

DEPTH_SCALE_M = 4.0
"""Depth that maps to network input 1.0; farther returns are clipped to 1."""
INVERSE_DEPTH_NEAR_M = 0.5
"""The 'inverse' encoding's depth that maps to 1.0 (just inside the 0.55 m collision distance)."""
CONV_CHANNELS: tuple[int, int, int] = (32, 32, 64)
CONV_KERNEL = 5


class ModelError(CogexploreError):
    """Bad network input, incompatible weights or an image too small for the conv stack."""


MAX_FC1_WEIGHTS = 2**29
"""The most weights fc1 may have (2 GiB in float32; a learner holds four such: the network, its
target and Adam's two moments): exactly a 1024 x 1024 image at the default fc1 (512); the paper's
160 x 120 image at the largest fc1 (8192) has 157 million."""


def pool3_shape(sensor_cfg: SensorConfig) -> tuple[int, int, int]:
    """(C, H, W) of pool3 for images of the sensor's size (each pool floors odd sizes)."""
    h, w = sensor_cfg.height, sensor_cfg.width
    for _ in range(3):
        h, w = h // 2, w // 2
    if h < 1 or w < 1:
        raise ModelError(f"a {sensor_cfg.width}x{sensor_cfg.height} image is too small for three "
                         "2x2 poolings (need at least 8x8)")
    return CONV_CHANNELS[2], h, w


def preprocess_depth(depth: Any, device: torch.device | str | None = None) -> torch.Tensor:
    """Depth image(s) -> network input (B, 1, H, W) float32 in [0, 1], channels-last.

    ``depth`` is (H, W) or (B, H, W), a numpy array or tensor, or (B, K, H, W) stacks of K images
    (``model.frame_stack``), which give (B, K, H, W). Floating-point input is metres; integer input
    (``uint16`` from the wire and replay) is millimetres. 0 (no return) stays 0.
    """
    if isinstance(depth, np.ndarray):
        if depth.dtype == np.uint16:  # torch's uint16 support is partial: widen first
            depth = depth.astype(np.int32)
        t = torch.from_numpy(np.ascontiguousarray(depth))
    elif isinstance(depth, torch.Tensor):
        t = depth
    else:
        raise ModelError(f"depth must be a numpy array or torch tensor, got {type(depth).__name__}")
    if t.dim() == 2:
        t = t.unsqueeze(0)
    if t.dim() not in (3, 4):
        raise ModelError(f"depth must be (H, W), (B, H, W) or (B, K, H, W), got shape {tuple(t.shape)}")
    if t.dtype == torch.bool or t.is_complex():
        raise ModelError(f"depth must be float metres or integer millimetres, got {t.dtype}")
    scale = 1.0 / DEPTH_SCALE_M if t.dtype.is_floating_point else 1.0 / (DEPTH_SCALE_M * MM_PER_M)
    if device is not None:
        t = t.to(device, non_blocking=True)
    x = (t.to(torch.float32) * scale).clamp_(0.0, 1.0)
    if x.dim() == 3:
        x = x.unsqueeze(1)
    # NaN (a broken frame) would poison every Q-value: read it as "no return"
    x = torch.nan_to_num_(x, nan=0.0)
    return x.contiguous(memory_format=torch.channels_last)


def resolve_device(device: str | torch.device = "auto") -> torch.device:
    """'auto' -> CUDA when present, else CPU; 'cpu', 'cuda' or 'cuda:N' (checked against this
    machine's GPUs). Other torch device types (meta, mps...) are refused: nothing here runs on them."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if not isinstance(device, (str, torch.device)):
        raise ModelError(f"device must be 'auto', 'cpu', 'cuda' or 'cuda:N', got {type(device).__name__}")
    try:
        dev = torch.device(device)
    except RuntimeError as exc:
        raise ModelError(f"unknown device {device!r}: {exc}") from None
    if dev.type not in ("cpu", "cuda"):
        raise ModelError(f"device {device!r}: cogexplore runs on 'cpu' or 'cuda' (or 'auto')")
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ModelError(f"device {device!r} requested but CUDA is not available")
    if dev.type == "cuda" and dev.index is not None and dev.index >= torch.cuda.device_count():
        raise ModelError(f"device {device!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return dev


_ALLOCATOR_TUNED = False


def reduce_allocator_page_faults() -> bool:
    """Keep freed memory in the process heap instead of returning it to the OS (glibc only).

    glibc serves large blocks (a batch's 78 MB conv1 activation) with fresh mmaps and unmaps them
    on free, so every update page-faults its activations in again: measured on the dev VM, this
    made a 32x32x120x160 conv 6x and a zero-fill 8x slower. Raising the mmap and trim thresholds
    keeps those blocks in the heap for reuse. Process-wide and idempotent; returns whether set.
    """
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return True
    try:
        import ctypes
        import platform
        if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
            return False
        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        ok = libc.mallopt(m_mmap_threshold, 1 << 30) == 1 and libc.mallopt(m_trim_threshold, 1 << 30) == 1
    except (OSError, AttributeError):
        return False
    _ALLOCATOR_TUNED = ok
    return ok


def bfloat16_is_native(device: torch.device) -> bool:
    """Whether ``device`` computes bfloat16 convolutions natively (a CPU with AVX512-BF16 or AMX,
    through oneDNN; a CUDA GPU that supports bfloat16), rather than emulating them."""
    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        try:
            return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
        except (AttributeError, RuntimeError):
            return False
    return False


def conv_autocast_dtype(precision: str, device: torch.device) -> torch.dtype | None:
    """The dtype the conv layers run in for ``dqn.conv_precision`` on ``device`` (None: float32)."""
    if precision == "float32":
        return None
    if precision == "bfloat16" or (precision == "auto" and bfloat16_is_native(device)):
        return torch.bfloat16
    if precision == "auto":
        return None
    raise ModelError(f"unknown conv precision {precision!r}")


def encode_depth(x: torch.Tensor, encoding: str) -> torch.Tensor:
    """Re-encode ``preprocess_depth`` output (depth / 4 m, 0 = no return) for the conv layers.

    'metric' returns it unchanged (the paper). 'inverse' gives ``INVERSE_DEPTH_NEAR_M / depth``
    capped at 1 and keeps "no return" at 0: in the metric input, open space beyond 4 m (0) and a
    wall at the collision distance (0.14) are neighbours, so a small shift of the far region
    looks like a nearby obstacle; inverse depth is monotone (0 far, 1 at the threshold), is
    nearly continuous at the range limit (0.125 -> 0) and spends its range on the near
    obstacles that decide a collision."""
    if encoding == "metric":
        return x
    if encoding == "inverse":
        near = INVERSE_DEPTH_NEAR_M / DEPTH_SCALE_M
        return torch.where(x > 0, near / x.clamp(min=near), 0.0)
    raise ModelError(f"unknown depth encoding {encoding!r}")


def mirror_images(x: torch.Tensor, flip: torch.Tensor) -> torch.Tensor:
    """Network input (B, 1, H, W) with the images where ``flip`` (B,) is true mirrored left-right
    (channels-last, as the networks take it)."""
    return torch.where(flip[:, None, None, None], x.flip(-1), x).contiguous(memory_format=torch.channels_last)


def shift_images(x: torch.Tensor, shift: torch.Tensor) -> torch.Tensor:
    """Network input (B, C, H, W) with image b moved by ``shift[b] = (dy, dx)`` pixels (integers):
    output pixel (i, j) is input pixel (i + dy, j + dx), the border pixels repeated beyond the
    edges (padding by replication, then cropping, as DrQ does). Channels-last, as the networks
    take it."""
    b, _, h, w = x.shape
    rows = (torch.arange(h, device=x.device)[None, :] + shift[:, 0:1]).clamp_(0, h - 1)  # (B, H)
    cols = (torch.arange(w, device=x.device)[None, :] + shift[:, 1:2]).clamp_(0, w - 1)  # (B, W)
    batch = torch.arange(b, device=x.device)[:, None, None]
    # advanced indices around the channel slice put their (B, H, W) first: (B, H, W, C)
    moved = x[batch, :, rows[:, :, None], cols[:, None, :]]
    return moved.permute(0, 3, 1, 2).contiguous(memory_format=torch.channels_last)


def previous_action_input(previous_action: Any, batch: int, device: torch.device | str | None = None,
                          dtype: torch.dtype = torch.float32, history: int = 1) -> torch.Tensor:
    """(B, 5 * history) one-hots of the previous commands (``model.previous_action``), one block per
    command, most recent first. ``previous_action`` is None (no previous command: every row zeros),
    an int or (B,) ints (the last command; older ones read as none), or (B, J) ints (the last J
    commands, most recent first: the first ``history`` columns are read, missing ones read as none);
    -1 means none."""
    if previous_action is None:
        return torch.zeros(batch, NUM_ACTIONS * history, dtype=dtype, device=device)
    prev = torch.as_tensor(previous_action, dtype=torch.int64, device=device)
    prev = prev[:, :history] if prev.dim() == 2 else prev.reshape(-1, 1)
    if prev.shape[0] == 1 and batch != 1:
        prev = prev.expand(batch, -1)
    if prev.shape[0] != batch or bool(((prev < -1) | (prev >= NUM_ACTIONS)).any()):
        raise ModelError(f"previous_action must be None, {batch} command indices or ({batch}, J) command "
                         f"histories, in [-1, {NUM_ACTIONS}) (-1: none), got {previous_action!r}")
    if prev.shape[1] < history:
        prev = F.pad(prev, (0, history - prev.shape[1]), value=-1)
    one_hot = F.one_hot(prev.clamp(min=0), NUM_ACTIONS).to(dtype) * (prev >= 0).to(dtype)[..., None]
    return one_hot.reshape(batch, NUM_ACTIONS * history)


def _check_network_input(x: torch.Tensor, frames: int, sensor_cfg: SensorConfig, hint: str) -> None:
    """ModelError unless ``x`` is (B, frames, H, W) for the sensor's image size."""
    want = (frames, sensor_cfg.height, sensor_cfg.width)
    if x.dim() != 4 or tuple(x.shape[1:]) != want:
        raise ModelError(f"network input must be (B, {want[0]}, {want[1]}, {want[2]}) ({hint}), got {tuple(x.shape)}")


class ConvTrunk(nn.Module):
    """Depth encoding, then conv1-conv3, each + ReLU + 2x2 max-pool; output is pool3."""

    def __init__(self, depth_encoding: str = "metric", in_channels: int = 1) -> None:
        super().__init__()
        if depth_encoding not in DEPTH_ENCODINGS:  # fail here, not at the first forward
            raise ModelError(f"unknown depth encoding {depth_encoding!r}")
        self.depth_encoding = depth_encoding
        c1, c2, c3 = CONV_CHANNELS
        pad = CONV_KERNEL // 2
        self.conv1 = nn.Conv2d(in_channels, c1, CONV_KERNEL, padding=pad)  # one per image read
        self.conv2 = nn.Conv2d(c1, c2, CONV_KERNEL, padding=pad)
        self.conv3 = nn.Conv2d(c2, c3, CONV_KERNEL, padding=pad)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # The paper's order is conv -> ReLU -> pool. max-pool and ReLU commute (both monotone),
        # so pooling first gives the same values and gradients while ReLU and its backward touch
        # a 4x smaller tensor: about 10% of an update's time on CPU.
        x = encode_depth(x, self.depth_encoding)
        x = F.relu(F.max_pool2d(self.conv1(x), 2), inplace=True)
        x = F.relu(F.max_pool2d(self.conv2(x), 2), inplace=True)
        return F.relu(F.max_pool2d(self.conv3(x), 2), inplace=True)


def command_values(fc3_out: torch.Tensor, quantiles: int) -> torch.Tensor:
    """(..., 5) Q-values from fc3's output: itself, or for a ``model.quantiles`` network (..., 5 * N)
    the mean of each command's N return quantiles."""
    return fc3_out.unflatten(-1, (NUM_ACTIONS, quantiles)).mean(-1) if quantiles else fc3_out


class QNetwork(nn.Module):
    """Depth image -> 5 Q-values (left, half-left, straight, half-right, right).

    With ``model.previous_action`` the previous command (the last ``model.action_history``
    commands) also enters fc1, through its own bias-free layer (``previous_action_fc``) added to
    fc1's output: the same as widening fc1's input by the one-hots, while fc1 keeps the shape the
    frozen-conv and probe code expect. ``previous_action`` is what :func:`previous_action_input`
    takes; None reads as "no previous command" (an episode's first step).
    ``conv_autocast`` (None: float32) runs the conv layers under ``torch.autocast`` in that dtype
    (the learner's ``dqn.conv_precision``); pool3 comes back as float32 for the fc layers.
    """

    conv_autocast: torch.dtype | None = None

    def __init__(self, model_cfg: ModelConfig | None = None, sensor_cfg: SensorConfig | None = None):
        super().__init__()
        self.model_cfg = model_cfg or ModelConfig()
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self.pool3_shape = pool3_shape(self.sensor_cfg)
        flat = int(np.prod(self.pool3_shape))
        cfg = self.model_cfg
        if flat * cfg.fc1 > MAX_FC1_WEIGHTS:  # each field in its range, together more than a machine holds
            raise ModelError(f"fc1 would have {flat * cfg.fc1:,} weights ({flat:,} pool3 values of a "
                             f"{self.sensor_cfg.width}x{self.sensor_cfg.height} image x model.fc1 = {cfg.fc1}), "
                             f"more than {MAX_FC1_WEIGHTS:,}: lower sensor.width/height or model.fc1")
        self.trunk = ConvTrunk(cfg.depth_encoding, cfg.frame_stack)
        self.fc1 = nn.Linear(flat, cfg.fc1)
        self.previous_action_fc = (nn.Linear(NUM_ACTIONS * cfg.action_history, cfg.fc1, bias=False)
                                   if cfg.previous_action else None)
        self.fc2 = nn.Linear(cfg.fc1, cfg.fc2)
        self.dropout = nn.Dropout(cfg.dropout)
        if cfg.dueling:
            self.value = nn.Linear(cfg.fc2, 1)
            self.advantage = nn.Linear(cfg.fc2, NUM_ACTIONS)
        else:
            self.fc3 = nn.Linear(cfg.fc2, NUM_ACTIONS * max(1, cfg.quantiles))
        self.to(memory_format=torch.channels_last)

    def features(self, x: torch.Tensor, *, float32: bool = False) -> torch.Tensor:
        """pool3 activations (B, 64, H/8, W/8) of preprocessed input x (B, K, H, W), K the images the
        network reads (``model.frame_stack``); ``float32``: in float32 whatever ``conv_autocast``
        says (acting and evaluation)."""
        self._check_input(x)
        if self.conv_autocast is None or float32:
            return self.trunk(x)
        with torch.autocast(x.device.type, dtype=self.conv_autocast):
            pool3 = self.trunk(x)
        return pool3.float()

    def head(self, pool3: torch.Tensor, previous_action: Any = None) -> torch.Tensor:
        """pool3 activations (and the previous commands, see the class) -> (B, 5) Q-values (a
        ``model.quantiles`` network's: the mean of each command's return quantiles)."""
        out = self.head_outputs(pool3, previous_action)
        return out if out.dim() == 2 else out.mean(dim=2)

    def return_quantiles(self, x: torch.Tensor, previous_action: Any = None) -> torch.Tensor:
        """(B, 5, N) return quantiles of preprocessed input x for a ``model.quantiles`` network
        (what its learner trains; ``forward`` gives their mean)."""
        if not self.model_cfg.quantiles:
            raise ModelError("return_quantiles needs a model.quantiles network; this one gives Q-values")
        return self.head_outputs(self.features(x), previous_action)

    def head_outputs(self, pool3: torch.Tensor, previous_action: Any = None) -> torch.Tensor:
        """What the head computes: (B, 5) Q-values, or (B, 5, N) return quantiles."""
        # flatten in NCHW order whatever the memory format, so fc1 weights are format-independent
        h = self.fc1(torch.flatten(pool3.contiguous(), 1))
        if self.previous_action_fc is not None:
            h = h + self.previous_action_fc(previous_action_input(previous_action, h.shape[0], h.device, h.dtype,
                                                                  self.model_cfg.action_history))
        h = self.dropout(F.relu(h, inplace=True))
        h = self.dropout(F.relu(self.fc2(h), inplace=True))
        if self.model_cfg.dueling:
            adv = self.advantage(h)
            return self.value(h) + adv - adv.mean(dim=1, keepdim=True)
        out = self.fc3(h)
        return out.unflatten(-1, (NUM_ACTIONS, self.model_cfg.quantiles)) if self.model_cfg.quantiles else out

    def forward(self, x: torch.Tensor, previous_action: Any = None, *, float32: bool = False) -> torch.Tensor:
        return self.head(self.features(x, float32=float32), previous_action)

    def _check_input(self, x: torch.Tensor) -> None:
        _check_network_input(x, self.model_cfg.frame_stack, self.sensor_cfg,
                             "use preprocess_depth" + (" on stacks of images" if self.model_cfg.frame_stack > 1 else ""))

    def conv_parameters(self) -> list[nn.Parameter]:
        return list(self.trunk.parameters())

    def head_parameters(self) -> list[nn.Parameter]:
        return [p for n, p in self.named_parameters() if not n.startswith("trunk.")]


MAX_ENSEMBLE_MEMBERS = 16
"""The most networks one :class:`QEnsemble` (and an ensemble weights file) may hold."""


class QEnsemble(nn.Module):
    """Several independently trained Q-networks that read one camera, acting as one network: the
    Q-values are the mean of the members', each member fed the same previous command (the one the
    ensemble chose last). Averaging cuts the variance that makes one DQN's greedy policy swing
    between runs of the same recipe (Osband et al. 2016; Anschel et al. 2017, Averaged-DQN).

    It plays wherever a QNetwork is played (greedy policies, ``InferenceRunner``, ``cogexplore
    drive``, ONNX export); ``features`` stacks the members' pool3 maps along the channels, so a
    receptive-field map sums every member's. ``model_cfg`` is the first member's (members may
    differ in their fc layers or depth encoding) with the most images any member reads
    (``frame_stack``): the ensemble takes that many, each member the newest of them. It is never
    trained: a learner trains one QNetwork.

    Without autograd (acting, evaluation) the members that share a model config run as one network:
    conv1 with every member's filters, conv2 and conv3 as grouped convolutions, the fc layers as
    batched matrix products (:class:`_FusedMembers`). Members of different heads (scalar and
    quantile, say) form one such group per config, and the ensemble is the member-weighted mean of
    the groups. Same Q-values to float rounding, and one pass per config instead of one per member: a
    single image's latency grows far less than the member count.
    """

    def __init__(self, members: Any):
        super().__init__()
        members = list(members)
        flat: list[QNetwork] = []
        for m in members:  # an ensemble of ensembles is the ensemble of all their networks
            flat += list(m.members) if isinstance(m, QEnsemble) else [m]
        if not all(isinstance(m, QNetwork) for m in flat):
            raise ModelError("an ensemble's members must be Q-networks, got "
                             + ", ".join(sorted({type(m).__name__ for m in flat})))
        if not 2 <= len(flat) <= MAX_ENSEMBLE_MEMBERS:
            raise ModelError(f"an ensemble holds 2 to {MAX_ENSEMBLE_MEMBERS} networks, got {len(flat)}")
        camera = camera_fields(flat[0].sensor_cfg)
        for m in flat[1:]:
            if camera_fields(m.sensor_cfg) != camera:
                raise ModelError(f"an ensemble's networks must read the same camera: {camera} against "
                                 f"{camera_fields(m.sensor_cfg)}")
        self.members = nn.ModuleList(flat)
        self.sensor_cfg = flat[0].sensor_cfg
        # what the ensemble is fed: the most images any member reads (each member reads the newest of them)
        self.model_cfg = dataclasses.replace(flat[0].model_cfg, frame_stack=most_images_read(flat))
        self._fused: list[_FusedMembers] | None = None  # one per model config, built on first use

    def features(self, x: torch.Tensor, *, float32: bool = False) -> torch.Tensor:
        """Every member's pool3, stacked along the channels: (B, 64 * members, H/8, W/8)."""
        self._check_input(x)
        return torch.cat([m.features(newest_images(x, m.model_cfg.frame_stack), float32=float32)
                          for m in self.members], dim=1)

    def forward(self, x: torch.Tensor, previous_action: Any = None, *, float32: bool = False) -> torch.Tensor:
        self._check_input(x)
        if not torch.is_grad_enabled() and self._fusable(float32):
            if self._fused is None or not all(group.matches() for group in self._fused):
                self._fused = [_FusedMembers(group) for group in _fusable_groups(self.members)]
            return sum(group(x, previous_action) * len(group.members) for group in self._fused) / len(self.members)
        return torch.stack([m(newest_images(x, m.model_cfg.frame_stack), previous_action, float32=float32)
                            for m in self.members]).mean(0)

    def _check_input(self, x: torch.Tensor) -> None:
        _check_network_input(x, self.model_cfg.frame_stack, self.sensor_cfg,
                             "the ensemble takes the most images a member reads; use preprocess_depth")

    def _fusable(self, float32: bool) -> bool:
        return ((float32 or all(m.conv_autocast is None for m in self.members))
                and not any(m.training and m.model_cfg.dropout > 0 for m in self.members))


def most_images_read(members: Iterable[QNetwork]) -> int:
    """How many images a group of networks needs per step: the most any of them reads
    (``model.frame_stack``; a network that reads fewer reads the newest ones)."""
    return max(m.model_cfg.frame_stack for m in members)


def newest_images(x: torch.Tensor, count: int) -> torch.Tensor:
    """The newest ``count`` of a (B, N, H, W) stack of input images (newest first): what a network
    that reads ``count`` images takes from an ensemble's input, which holds the most any member reads."""
    return x[:, :count]  # a view, also when it is all of them (and no branch on a shape for the ONNX trace)


def most_commands_read(members: Iterable[QNetwork]) -> int:
    """How many previous commands a group of networks needs per image: the most any of them reads
    (``model.action_history``; a network that reads fewer gives the older ones zero weight)."""
    return max(m.model_cfg.action_history for m in members)


def _fused_config(cfg: ModelConfig) -> ModelConfig:
    """What members must share to run fused: all but the command history and the images read, since
    a network that reads K commands (or images) is one that reads more with zero weights on the
    older ones."""
    return dataclasses.replace(cfg, action_history=1, frame_stack=1)


def _fusable_groups(members: Iterable[QNetwork]) -> list[list[QNetwork]]:
    """An ensemble's members grouped by what they must share to run fused (``_fused_config``), in
    order of first appearance."""
    groups: dict[ModelConfig, list[QNetwork]] = {}
    for m in members:
        groups.setdefault(_fused_config(m.model_cfg), []).append(m)
    return list(groups.values())


class _FusedMembers:
    """An ensemble's members of one model config (but the command history and images read) as one network (see
    :class:`QEnsemble`): their weights stacked once, re-stacked when any member's weights change
    (``matches``). Called, it returns the mean of its members' Q-values."""

    def __init__(self, members: list[QNetwork]):
        self.members = members
        self.key = self._key(members)
        self.groups = len(members)
        self.depth_encoding = members[0].model_cfg.depth_encoding
        self.action_history = most_commands_read(members)
        self.dueling = members[0].model_cfg.dueling
        self.quantiles = members[0].model_cfg.quantiles
        with torch.no_grad():
            def cat(name: str) -> torch.Tensor:
                return torch.cat([m.get_parameter(name) for m in members])

            def stack(name: str) -> torch.Tensor:
                return torch.stack([m.get_parameter(name) for m in members])

            self.images = most_images_read(members)  # conv1 of a member that reads fewer: zero weights on the older
            conv1 = torch.cat([F.pad(m.trunk.conv1.weight, (0, 0, 0, 0, 0, self.images - m.trunk.conv1.in_channels))
                               for m in members])
            self.convs = [(w.contiguous(memory_format=torch.channels_last), cat(f"trunk.{c}.bias"))
                          for c, w in (("conv1", conv1), ("conv2", cat("trunk.conv2.weight")),
                                       ("conv3", cat("trunk.conv3.weight")))]
            # (G, in, out) views of (G, out, in) and (G, 1, out): h @ W + b for every member at once
            linear = ["fc1", "fc2"] + (["value", "advantage"] if self.dueling else ["fc3"])
            self.linear = {n: (stack(f"{n}.weight").transpose(1, 2), stack(f"{n}.bias")[:, None]) for n in linear}
            width = NUM_ACTIONS * self.action_history  # shorter histories padded with zero weights
            self.previous_action = (torch.stack([F.pad(m.previous_action_fc.weight,
                                                       (0, width - m.previous_action_fc.in_features))
                                                 for m in members]).transpose(1, 2)
                                    if members[0].previous_action_fc is not None else None)

    @staticmethod
    def _key(members: list[QNetwork]) -> tuple:
        return tuple((p.data_ptr(), p._version, p.dtype) for m in members for p in m.parameters())

    def matches(self) -> bool:
        """Whether the stacked weights are still the members' (none loaded or trained in place since)."""
        return self._key(self.members) == self.key

    def __call__(self, x: torch.Tensor, previous_action: Any = None) -> torch.Tensor:
        h = encode_depth(newest_images(x, self.images), self.depth_encoding)
        for i, (w, b) in enumerate(self.convs):
            h = F.conv2d(h, w, b, padding=CONV_KERNEL // 2, groups=1 if i == 0 else self.groups)
            h = F.relu(F.max_pool2d(h, 2), inplace=True)  # pool before ReLU, as ConvTrunk
        batch = h.shape[0]
        # each member's channels flattened in NCHW order, as QNetwork.head does: (G, B, 64*h*w)
        # (unflatten, not reshape(batch, G, -1): that cannot infer -1 for an empty batch)
        h = h.contiguous().unflatten(1, (self.groups, -1)).flatten(2).transpose(0, 1)

        def linear(name: str, a: torch.Tensor) -> torch.Tensor:
            w, b = self.linear[name]
            return torch.baddbmm(b, a, w)

        h = linear("fc1", h)
        if self.previous_action is not None:
            h = h + previous_action_input(previous_action, batch, h.device, h.dtype,
                                          self.action_history) @ self.previous_action
        h = F.relu(linear("fc2", F.relu(h)))
        if self.dueling:
            adv = linear("advantage", h)
            q = linear("value", h) + adv - adv.mean(dim=2, keepdim=True)
        else:
            q = command_values(linear("fc3", h), self.quantiles)
        return q.mean(0)


class SupervisedNet(nn.Module):
    """The authors' supervised obstacle-avoidance model: the same ConvTrunk + one fc to 5 classes."""

    def __init__(self, sensor_cfg: SensorConfig | None = None, depth_encoding: str = "metric"):
        super().__init__()
        self.sensor_cfg = sensor_cfg or SensorConfig()
        self.pool3_shape = pool3_shape(self.sensor_cfg)
        self.trunk = ConvTrunk(depth_encoding)
        self.fc = nn.Linear(int(np.prod(self.pool3_shape)), NUM_ACTIONS)
        self.to(memory_format=torch.channels_last)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        return self.trunk(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 1, H, W) -> (B, 5) class logits."""
        return self.fc(torch.flatten(self.trunk(x).contiguous(), 1))


def copy_conv_weights(src: nn.Module, dst: nn.Module) -> None:
    """Copy the ConvTrunk weights of ``src`` into ``dst`` (QNetwork <-> SupervisedNet)."""
    for m, name in ((src, "src"), (dst, "dst")):
        if not isinstance(getattr(m, "trunk", None), ConvTrunk):
            raise ModelError(f"{name} ({type(m).__name__}) has no ConvTrunk")
    if src.trunk.depth_encoding != dst.trunk.depth_encoding:
        raise ModelError(f"the conv layers were trained on {src.trunk.depth_encoding!r} depth input, the "
                         f"network reads {dst.trunk.depth_encoding!r} (model.depth_encoding)")
    with torch.no_grad():
        for (n, ps), pd in zip(src.trunk.named_parameters(), dst.trunk.parameters()):
            # a one-image conv1 into one that reads a stack: the current image gets its filters and the
            # older ones start at zero weight, so the network first acts as the one-image one
            into = pd[:, :1] if n == "conv1.weight" and ps.shape[1] == 1 else pd
            if ps.shape != into.shape:
                raise ModelError(f"conv weight {n}: shape {tuple(ps.shape)} != {tuple(pd.shape)}")
            pd.zero_()
            into.copy_(ps)


def architecture_fingerprint(net: nn.Module) -> str:
    """Hash of the class, parameter names and shapes (and a non-metric depth encoding): equal iff
    weights are interchangeable (the wire's definition, shared.wire.messages.shape_fingerprint,
    applied to ``net``)."""
    shapes = named_shapes(net)
    extra = {"class": type(net).__name__}
    encoding = getattr(getattr(net, "trunk", None), "depth_encoding", "metric")
    if encoding != "metric":  # same shapes, different meaning; metric keeps the older fingerprints
        extra["depth_encoding"] = encoding
    return shape_fingerprint(shapes, extra)


def named_shapes(net: nn.Module) -> dict[str, tuple[int, ...]]:
    """Parameter (and buffer) names and shapes: what weights for ``net`` must carry."""
    return {n: tuple(t.shape) for n, t in net.state_dict().items()}


def weights_to_tensors(net: nn.Module) -> dict[str, torch.Tensor]:
    """Parameters as contiguous CPU tensors in NCHW order (for messages, safetensors, other devices)."""
    return {n: t.detach().to("cpu").contiguous() for n, t in net.state_dict().items()}


def average_weights(nets: list[nn.Module]) -> dict[str, torch.Tensor]:
    """The element-wise mean of the weights of networks of one architecture (float32, CPU):
    averaging the checkpoints of one run's later updates smooths the greedy policy's
    checkpoint-to-checkpoint swings. ModelError when the architectures differ."""
    if not nets:
        raise ModelError("nothing to average")
    prints = {architecture_fingerprint(n) for n in nets}
    if len(prints) != 1:
        raise ModelError(f"cannot average networks of different architectures ({len(prints)} fingerprints)")
    # equal shapes are not equal meaning: another camera (field of view, range, an image size that pools
    # to the same pool3) or, in an ensemble, members of other depth encodings; the mean would play with the
    # last network's
    first = _what_it_reads(nets[0])
    for other in nets[1:]:
        theirs = _what_it_reads(other)
        differences = [f"{k} = {theirs.get(k)!r} against {v!r}" for k, v in first.items() if theirs.get(k) != v]
        if differences:
            raise ModelError(f"cannot average networks that read different cameras or depth: {differences[0]}")
    states = [weights_to_tensors(n) for n in nets]
    return {name: torch.stack([s[name].float() for s in states]).mean(0) for name in states[0]}


def camera_fields(sensor: SensorConfig) -> dict[str, Any]:
    """What a network's camera is, as networks joined into one model (an ensemble, a mean of weights)
    must share it: :data:`shared.config.MUST_MATCH_FIELDS`'s sensor fields (noise, a training condition,
    and the backend, which agrees to 2 cm, aside)."""
    return {name: getattr(sensor, name.partition(".")[2]) for name in MUST_MATCH_FIELDS if name.startswith("sensor.")}


def _what_it_reads(net: nn.Module) -> dict[str, Any]:
    """A network's camera (:func:`camera_fields`) and its members' model configs (dropout
    aside: off when it plays), as far as the network records them, by setting: what networks must share
    to be averaged."""
    out: dict[str, Any] = {}
    sensor = getattr(net, "sensor_cfg", None)
    if isinstance(sensor, SensorConfig):
        out.update(camera_fields(sensor))
    members = list(getattr(net, "members", None) or [net])
    for i, m in enumerate(members):
        cfg = getattr(m, "model_cfg", None)
        if isinstance(cfg, ModelConfig):
            where = f"member {i} " if len(members) > 1 else ""
            out.update({f"{where}model.{k}": v for k, v in asdict(cfg).items() if k != "dropout"})
    return out


def check_weights_fit(net: nn.Module, tensors: dict[str, torch.Tensor]) -> None:
    """ModelError unless ``tensors`` has exactly ``net``'s names, shapes and a dtype it takes (works
    on a network built on the meta device, before any memory is spent on it)."""
    own = net.state_dict()
    missing = sorted(set(own) - set(tensors))
    extra = sorted(set(tensors) - set(own))
    if missing or extra:
        raise ModelError(f"weights do not fit {type(net).__name__}: missing {missing}, unexpected {extra}")
    for n, t in own.items():
        if tuple(tensors[n].shape) != tuple(t.shape):
            raise ModelError(f"weight {n}: shape {tuple(tensors[n].shape)}, network wants {tuple(t.shape)}")
        # copy_ casts anything: integers or booleans would load as weights, complex ones lose a part
        if t.is_floating_point() and not tensors[n].is_floating_point():
            raise ModelError(f"weight {n}: dtype {tensors[n].dtype}, network wants floating-point weights")


def load_tensors(net: nn.Module, tensors: dict[str, torch.Tensor]) -> None:
    """Load ``weights_to_tensors`` output into ``net`` with a clear error on any mismatch; every
    name, shape and dtype is checked before the first copy, so a misfit leaves ``net`` as it was."""
    check_weights_fit(net, tensors)
    own = net.state_dict()
    with torch.no_grad():
        for n, t in own.items():
            t.copy_(tensors[n])  # copy_ keeps the destination's (channels-last) layout and device


class InferenceRunner:
    """Fast greedy evaluation of a QNetwork on one or a few depth images (actors, evaluator).

    Keeps the network in eval mode (dropout off) and runs under ``torch.inference_mode``. It
    shares the network's parameters, so weight updates loaded into ``net`` are seen at once.
    """

    def __init__(self, net: QNetwork):
        reduce_allocator_page_faults()
        self.net = net

    @property
    def device(self) -> torch.device:
        return next(self.net.parameters()).device

    def q_values(self, depth: Any, previous_action: Any = None) -> np.ndarray:
        """(H, W) -> (5,) or (B, H, W) -> (B, 5) Q-values as float32 numpy; ``previous_action``
        (None, an int, (B,) ints or (B, J) histories, -1 = none: see :func:`previous_action_input`)
        is read only by a ``model.previous_action`` net."""
        single = getattr(depth, "ndim", 0) == 2
        # an actor's net stays in eval mode: setting the mode walks every module (5% of an actor's
        # CPU), so only a net in training mode, the learner's, is switched (and switched back)
        was_training = self.net.training
        if was_training:
            self.net.eval()
        try:
            with torch.inference_mode():
                q = self.net(preprocess_depth(depth, self.device), previous_action, float32=True)
        finally:
            if was_training:
                self.net.train()
        out = q.float().cpu().numpy()
        return out[0] if single else out


def layer_summary(model_cfg: ModelConfig | None = None, sensor_cfg: SensorConfig | None = None,
                  net: QNetwork | None = None) -> list[dict[str, Any]]:
    """One row per layer: name, output shape (without batch) and parameter count.

    This is what ``cogexplore model summary --json`` prints.
    """
    net = net or QNetwork(model_cfg, sensor_cfg)
    s = net.sensor_cfg
    rows: list[dict[str, Any]] = []

    def row(name: str, out: torch.Tensor, module: nn.Module | None = None) -> torch.Tensor:
        params = sum(p.numel() for p in module.parameters()) if module is not None else 0
        rows.append({"layer": name, "output_shape": list(out.shape[1:]), "params": params})
        return out

    was_training = net.training
    net.eval()
    try:
        with torch.no_grad():
            x = row("input", torch.zeros(1, net.model_cfg.frame_stack, s.height, s.width))
            t = net.trunk
            for i, conv in enumerate((t.conv1, t.conv2, t.conv3), start=1):
                x = row(f"conv{i}", F.relu(conv(x)), conv)
                x = row(f"pool{i}", F.max_pool2d(x, 2))
            h = torch.flatten(x, 1)
            if net.previous_action_fc is not None:
                fc = net.previous_action_fc
                row("previous_action_fc", fc(torch.zeros(1, fc.in_features)), fc)
            h = row("fc1", F.relu(net.fc1(h)), net.fc1)
            h = row("fc2", F.relu(net.fc2(h)), net.fc2)
            if net.model_cfg.dueling:
                row("value", net.value(h), net.value)
                row("advantage", net.advantage(h), net.advantage)
                row("q", net.head(x), None)
            else:
                row("fc3", net.fc3(h), net.fc3)
    finally:
        net.train(was_training)
    rows.append({"layer": "total", "output_shape": [NUM_ACTIONS],
                 "params": sum(p.numel() for p in net.parameters())})
    return rows


summary = layer_summary


def forward_flops(net: QNetwork | SupervisedNet) -> dict[str, int]:
    """Multiply-add FLOPs (2 per MAC) of one single-image forward pass, per conv/fc layer."""
    flops: dict[str, int] = {}
    hooks = []

    def record(name: str):
        def hook(m: nn.Module, _inp: Any, out: torch.Tensor) -> None:
            if isinstance(m, nn.Conv2d):
                k = m.in_channels * m.kernel_size[0] * m.kernel_size[1] // m.groups
                flops[name] = 2 * k * out[0].numel()
            else:
                flops[name] = 2 * m.in_features * m.out_features
        return hook

    for name, m in net.named_modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            hooks.append(m.register_forward_hook(record(name.removeprefix("trunk."))))
    was_training = net.training
    net.eval()
    try:
        with torch.no_grad():
            net(torch.zeros(1, net.trunk.conv1.in_channels, net.sensor_cfg.height, net.sensor_cfg.width))
    finally:
        for h in hooks:
            h.remove()
        net.train(was_training)
    return flops


def config_json(model_cfg: ModelConfig, sensor_cfg: SensorConfig) -> str:
    """The configs that define a network's architecture, as JSON (for weight files)."""
    return json.dumps({"model": asdict(model_cfg), "sensor": asdict(sensor_cfg)}, sort_keys=True)
