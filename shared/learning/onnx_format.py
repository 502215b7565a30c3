"""The ONNX policy file, in one place: its inputs, its output and its metadata, read by the exporter
(``shared.learning.onnx_export``, torch) and the runner (``cogexplore.onnx_runner``, no torch).

This module imports neither torch nor onnx: a robot computer reads it with numpy and onnxruntime.

The graph (opset 17, any batch size B)::

    depth_m          float32 (B, 1, H, W)  metres at the network's size, range-gated, 0 = no return;
                             (B, N, H, W)  for networks that read the last N images
                                           (``model.frame_stack``): newest first, an episode's
                                           first image repeated until there are N
    previous_action  int64   (B,)          the previous command 0..4, -1 = none (an episode's start);
                             (B, K)        for networks that read the last K commands
                                           (``model.action_history``): most recent first
    q_values         float32 (B, 5)        one Q-value per command (left ... right); greedy = argmax

and one metadata entry, ``cogexplore``, a JSON object (:class:`OnnxPolicyInfo`): the camera the
network was trained with, its architecture, the control period, where it came from, and (files
written since it was added) the Q-values the graph gave on :func:`self_check_inputs` when exported:
a file whose weights were damaged since gives others, and the runner refuses it.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from shared.config import NUM_ACTIONS, ConfigError, ModelConfig, SensorConfig, from_dict, is_finite_number, is_whole
from shared.errors import CogexploreError
from shared.jsontext import parse_json

ONNX_FORMAT = "cogexplore-onnx"
ONNX_FORMAT_VERSION = 1
METADATA_KEY = "cogexplore"
"""The ``metadata_props`` key that holds :class:`OnnxPolicyInfo` as JSON."""
DEPTH_INPUT = "depth_m"
PREVIOUS_ACTION_INPUT = "previous_action"
Q_OUTPUT = "q_values"
NO_PREVIOUS_ACTION = -1
"""``previous_action`` of an episode's first image: the network reads a zero one-hot."""
MATCH_TOLERANCE = 1e-5
"""Largest difference between the ONNX and the torch Q-values an export may show, relative to the
largest |Q| of the batch (at least 1). Relative, because float32 itself is not closer: the shipped
model's Q-values reach ~85, where one float32 step is 7.6e-6 and torch's own float32 result is
already ~1.3e-5 from the float64 one; another summation order (onnxruntime's kernels) is as far."""

SELF_CHECK_ROWS = 12
"""Inputs (rows of one batch) in :func:`self_check_inputs`."""
SELF_CHECK_TOLERANCE = MATCH_TOLERANCE
"""Largest difference, relative as ``MATCH_TOLERANCE``, between the Q-values a file records for
:func:`self_check_inputs` and those the runner's onnxruntime gives. The export's bound against torch
serves: both are float32 sums of the same terms in another order. Measured on the shipped model
(onnxruntime 1.32, x86): 2e-7 to 3e-7 from the float64 result at 1 or 2 threads, every graph
optimisation level, batch 1 or 12 (within 1.6e-7 of each other); so two onnxruntimes (another
machine, thread count or version) that each stay that close differ by under 1e-6, ten times below
this. A damaged weight that moves a Q-value by more is refused; one that moves none by
more changes the commands about as little as float32 rounding does."""


def self_check_inputs(sensor: SensorConfig, images: int, commands: int) -> tuple[np.ndarray, np.ndarray]:
    """The graph's inputs for the self-check: (SELF_CHECK_ROWS, images, H, W) float32 depth and the
    previous commands, (SELF_CHECK_ROWS,) for ``commands`` 1 or (SELF_CHECK_ROWS, commands).

    Closed-form, so the exporter and any runner build the same bytes: integer stripe patterns of
    different slopes (no random stream, no transcendental function whose last bit a numpy build may
    round otherwise) mapped to depths well inside the camera's range gate (so no pixel sits on its
    edge), with no-return holes, a first row with nothing in range, and every command -1..4."""
    h = np.arange(sensor.height, dtype=np.int64)[:, None]
    w = np.arange(sensor.width, dtype=np.int64)[None, :]
    span = sensor.max_range_m - max(sensor.min_range_m, 0.0)
    near, far = sensor.max_range_m - 0.95 * span, sensor.max_range_m - 0.05 * span
    depth = np.zeros((SELF_CHECK_ROWS, images, sensor.height, sensor.width), np.float32)
    for row in range(1, SELF_CHECK_ROWS):
        for k in range(images):
            i = row * images + k
            level = (h * (2 * i + 1) + w * (i + 3) + 7 * i) % 97  # 0..96
            image = near + (far - near) * (level / 96.0)
            image[(h * w + i) % (i % 5 + 3) == 0] = 0.0
            depth[row, k] = image
    rows = np.arange(SELF_CHECK_ROWS, dtype=np.int64)[:, None]
    previous = (rows + 3 * np.arange(commands, dtype=np.int64)[None, :]) % (NUM_ACTIONS + 1) + NO_PREVIOUS_ACTION
    return depth, (previous[:, 0] if commands == 1 else previous)


def q_difference(q: np.ndarray, reference: np.ndarray) -> float:
    """max |q - reference| relative to the largest |reference| (at least 1): what ``MATCH_TOLERANCE``
    and ``SELF_CHECK_TOLERANCE`` bound. NaN when ``q`` has a NaN or another shape."""
    q, reference = np.asarray(q, np.float64), np.asarray(reference, np.float64)
    if q.shape != reference.shape:
        return float("nan")
    return float(np.abs(q - reference).max() / max(1.0, float(np.abs(reference).max())))


class OnnxModelError(CogexploreError):
    """An ONNX policy file that is missing, corrupt, not cogexplore's, or not what its metadata
    says; or an export whose Q-values do not match the torch network's."""


@dataclass(frozen=True)
class OnnxPolicyInfo:
    """What an ONNX policy file says about its network (its ``cogexplore`` metadata entry)."""

    sensor: SensorConfig
    """The camera the network was trained with: image size, field of view, range gate."""
    model: ModelConfig
    """The architecture: depth encoding, whether it reads the previous command, head, fc sizes."""
    control_period_s: float
    """How long each command is held before the next image is taken."""
    label: str
    """A short name, ``<run or file>@<policy version>`` (``LoadedModel.label``)."""
    source: str
    """The file the network was loaded from (or what the caller named it)."""
    policy_version: int
    """The learner update the weights are from (0 when unknown)."""
    weights_sha256: str
    """Digest of the torch weights exported (``checkpoints.weights_sha256``)."""
    cogexplore_version: str
    """The cogexplore version that wrote the file."""
    extra: Mapping[str, Any] = field(default_factory=dict)
    """Anything else the exporter was given: a model card, the checkpoints averaged."""
    self_check_q_values: tuple[tuple[float, ...], ...] | None = None
    """(SELF_CHECK_ROWS, 5) Q-values the exported graph gave on :func:`self_check_inputs` (onnxruntime
    on the file's own bytes), which the runner compares with its own to refuse damaged weights.
    Optional: None in files exported before it was recorded, which load unchecked."""

    def to_json(self) -> str:
        body = {"format": ONNX_FORMAT, "version": ONNX_FORMAT_VERSION, **asdict(self)}
        return json.dumps(body, sort_keys=True, default=str)

    @classmethod
    def from_json(cls, text: str, where: str = "ONNX file") -> OnnxPolicyInfo:
        """Parse and check a ``cogexplore`` metadata entry; OnnxModelError (one line) if malformed."""
        if not isinstance(text, (str, bytes)):
            raise OnnxModelError(f"{where}: its {METADATA_KEY!r} metadata is not text")
        data = parse_json(text, f"{where}: its {METADATA_KEY!r} metadata", OnnxModelError, allow_nan=False)
        if not isinstance(data, dict) or data.get("format") != ONNX_FORMAT:
            raise OnnxModelError(f"{where}: its {METADATA_KEY!r} metadata is not a {ONNX_FORMAT} entry")
        if data.get("version") != ONNX_FORMAT_VERSION:
            raise OnnxModelError(f"{where}: {ONNX_FORMAT} version {data.get('version')!r}, this cogexplore reads "
                                 f"version {ONNX_FORMAT_VERSION}")
        try:
            configs = from_dict({"sensor": data["sensor"], "model": data["model"]})
            period, version = data["control_period_s"], data["policy_version"]
            if not (is_finite_number(period) and period > 0):
                raise ValueError(f"control_period_s must be a number of seconds > 0, got {period!r}")
            if not (is_whole(version) and version >= 0):
                raise ValueError(f"policy_version must be a whole number >= 0, got {version!r}")
            extra = data.get("extra") or {}
            if not isinstance(extra, dict):  # dict() would take a list of pairs, or fail on others cryptically
                raise ValueError(f"extra must be a JSON object, got {type(extra).__name__}")
            info = cls(sensor=configs.sensor, model=configs.model, control_period_s=float(period),
                       label=str(data["label"]), source=str(data["source"]),
                       policy_version=int(version), weights_sha256=str(data["weights_sha256"]),
                       cogexplore_version=str(data["cogexplore_version"]), extra=extra,
                       self_check_q_values=_self_check_q_values(data.get("self_check_q_values")))
        except (ConfigError, KeyError, TypeError, ValueError, OverflowError) as exc:
            detail = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
            raise OnnxModelError(f"{where}: its {METADATA_KEY!r} metadata is invalid: {detail}") from None
        return info


def _self_check_q_values(value: Any) -> tuple[tuple[float, ...], ...] | None:
    """The metadata's ``self_check_q_values`` checked: absent (None), or SELF_CHECK_ROWS rows of five
    finite numbers; ValueError otherwise."""
    if value is None:
        return None
    if not (isinstance(value, list) and len(value) == SELF_CHECK_ROWS
            and all(isinstance(row, list) and len(row) == NUM_ACTIONS and all(map(is_finite_number, row))
                    for row in value)):
        raise ValueError(f"self_check_q_values must be {SELF_CHECK_ROWS} lists of {NUM_ACTIONS} finite numbers")
    return tuple(tuple(float(q) for q in row) for row in value)
