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
network was trained with, its architecture, the control period, where it came from.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from shared.config import ConfigError, ModelConfig, SensorConfig, from_dict, is_finite_number, is_whole
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
                       cogexplore_version=str(data["cogexplore_version"]), extra=extra)
        except (ConfigError, KeyError, TypeError, ValueError, OverflowError) as exc:
            detail = f"missing {exc}" if isinstance(exc, KeyError) else str(exc)
            raise OnnxModelError(f"{where}: its {METADATA_KEY!r} metadata is invalid: {detail}") from None
        return info
