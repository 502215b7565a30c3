"""The torch-free half of a policy, shared by :class:`cogexplore.Policy` (torch) and
:class:`cogexplore.onnx_runner.OnnxPolicy` (onnxruntime): a user's depth image seen as the network's
camera would have seen it, and a command as the robot drives it. numpy and ``shared.depth`` only."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from shared.config import ACTION_NAMES, SPEED_TABLES, SensorConfig
from shared.depth import depth_from_mm, range_gate, resize_depth
from shared.errors import PolicyError

COMMAND_NAMES: tuple[str, ...] = ACTION_NAMES
"""The five moving commands by index: left, half-left, straight, half-right, right."""
ASPECT_TOLERANCE = 0.05
"""How far (relative) an image's width / height may be from the network's before it is refused:
another aspect ratio is another field of view, which resizing cannot make up."""
MILLIMETRES_LIKELY_M = 100.0
"""A float image whose typical return (the median) lies beyond this many metres holds millimetres, not
metres: the 16-bit image converted to float without its scale (a common ROS slip). Read as metres,
every pixel would be beyond the camera's range, no return, and the network drive blind."""


class Command(NamedTuple):
    """A moving command as the robot drives it, for one control period."""

    linear_mps: float
    """Forward speed, m/s."""
    angular_rps: float
    """Turn rate, rad/s; positive turns left."""


def metres(depth_m: Any) -> np.ndarray:
    """A user's depth image as (H, W) float metres (NaN and infinity kept: resizing reads them as
    no return, as it reads a masked array's masked pixels); PolicyError for anything that is not one
    image of depths."""
    if hasattr(depth_m, "detach") and hasattr(depth_m, "cpu"):  # a torch tensor, on a GPU or needing grad
        depth_m = depth_m.detach().cpu()
    if np.ma.isMaskedArray(depth_m):  # masked pixels are invalid: no return, not the values under the mask
        depth_m = depth_m.filled(np.nan if np.issubdtype(depth_m.dtype, np.floating) else 0)
    try:
        depth = np.asarray(depth_m)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise PolicyError(f"depth_m must be an (H, W) array of depths in metres: {exc}") from None
    if depth.ndim == 3 and depth.shape[-1] == 1:  # (H, W, 1), as many camera drivers give it
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise PolicyError(f"depth_m must be one (H, W) depth image, got shape {depth.shape}")
    if depth.size == 0:
        raise PolicyError(f"depth_m is empty (shape {depth.shape})")
    if depth.dtype.kind == "u" and depth.dtype.itemsize == 2:  # millimetres, in either byte order
        return depth_from_mm(depth.astype(np.uint16))
    if not np.issubdtype(depth.dtype, np.floating):
        raise PolicyError(f"depth_m must be float metres (or uint16 millimetres), got {depth.dtype}")
    if np.isneginf(depth).any():  # not a faulty value: an obstacle at the lens, no image to decide from
        raise PolicyError("depth_m has -inf pixels, REP 117's returns too near to measure: an obstacle nearer "
                          "than the camera sees, where no command was taught; stop the robot (cogexplore drive does)")
    if (depth < 0).any():
        raise PolicyError("depth_m has negative depths; expected metres >= 0 (0, NaN or inf: no return)")
    returns = depth[np.isfinite(depth) & (depth > 0)]
    if returns.size and float(np.median(returns)) > MILLIMETRES_LIKELY_M:
        raise PolicyError(f"depth_m's typical depth is {float(np.median(returns)):.0f} m: millimetres in a float "
                          "image? Divide by 1000, or pass the uint16 millimetres as they are")
    return depth


def checked_q_values(q_values: Any, label: str) -> np.ndarray:
    """A network's Q-values for one image as (5,) float32; PolicyError when they are not five finite
    numbers (broken weights, or a graph that computes something else): a robot must not drive on
    NaN, which argmax reads as command 0, a full-speed turn."""
    q = np.asarray(q_values, dtype=np.float32)
    if q.shape != (len(COMMAND_NAMES),):
        raise PolicyError(f"{label} gave Q-values of shape {q.shape}, not ({len(COMMAND_NAMES)},)")
    if not np.isfinite(q).all():
        raise PolicyError(f"{label} gave Q-values that are not finite ({q.tolist()}): its weights are broken")
    return q


def same_aspect(width: int, height: int, sensor: SensorConfig) -> bool:
    """Whether a ``width`` x ``height`` image has the aspect ratio of ``sensor``'s (to ``ASPECT_TOLERANCE``)."""
    return abs((width / height) / (sensor.width / sensor.height) - 1.0) <= ASPECT_TOLERANCE


def camera_observation(depth_m: Any, sensor: SensorConfig) -> np.ndarray:
    """``depth_m`` as the network's camera (``sensor``) sees it: float32 (H, W) metres at the
    network's size, 0 = no return (``Policy.observation``, which documents the input)."""
    depth = metres(depth_m)
    h, w = depth.shape
    if not same_aspect(w, h, sensor):
        raise PolicyError(f"depth_m is {w} x {h} pixels; the network's camera is {sensor.width} x {sensor.height} "
                          f"({sensor.hfov_deg:g} x {sensor.vfov_deg:g} degrees): crop the image to that field of "
                          "view first")
    return range_gate(resize_depth(depth, sensor.height, sensor.width), sensor.min_range_m, sensor.max_range_m)


def twist(command: int, speed_table: str = "test") -> Command:
    """The (linear m/s, angular rad/s) of a command at the paper's ``test`` speeds (the
    protocol's) or its ``train`` speeds."""
    if not isinstance(speed_table, str) or speed_table not in SPEED_TABLES:
        raise PolicyError(f"unknown speed table {speed_table!r}; choose {' or '.join(SPEED_TABLES)}")
    if not (isinstance(command, (int, np.integer)) and not isinstance(command, bool)
            and 0 <= command < len(COMMAND_NAMES)):
        raise PolicyError(f"command must be an index in 0..{len(COMMAND_NAMES) - 1}, got {command!r}")
    angular, linear = SPEED_TABLES[speed_table]
    return Command(float(linear), float(angular[int(command)]))


class CameraPolicy:
    """What :class:`cogexplore.Policy` and :class:`cogexplore.onnx_runner.OnnxPolicy` share: a user's
    image seen through the network's camera (``sensor``), the greedy command that becomes the
    previous command, and its twist. A subclass runs the network: ``decide``, ``q_values``,
    ``reset``, ``previous_command`` and ``label``."""

    command_names: tuple[str, ...] = COMMAND_NAMES
    sensor: SensorConfig
    """The camera the network was trained with: its image size, field of view and range."""
    control_period_s: float
    """How long each command is held before the next image is taken."""

    def observation(self, depth_m: Any) -> np.ndarray:
        """The network's camera image of ``depth_m``: float32 (H, W) metres at the network's size,
        0 = no return, as the simulated camera would have taken it.

        ``depth_m``: (H, W) (or (H, W, 1)) float metres at any size with the network's aspect
        ratio, i.e. its field of view; NaN, +infinity, 0 and masked pixels (``numpy.ma``) are no return
        (-infinity, too near to measure, is refused); uint16 is millimetres.
        Raises PolicyError for a wrong shape, an empty array or another aspect ratio.
        """
        return camera_observation(depth_m, self.sensor)

    def decide(self, depth_m: Any) -> tuple[int, np.ndarray]:
        """The greedy command (0..4) for one depth image with the (5,) float32 Q-values it was chosen
        from (one network pass); it becomes the previous command."""
        raise NotImplementedError

    def act(self, depth_m: Any) -> int:
        """The greedy command (0..4) for one depth image; it becomes the previous command."""
        return self.decide(depth_m)[0]

    def __call__(self, depth_m: Any) -> int:
        return self.act(depth_m)

    def twist(self, command: int, speed_table: str = "test") -> Command:
        """The (linear m/s, angular rad/s) of a command at the paper's ``test`` speeds (the
        protocol's) or its ``train`` speeds."""
        return twist(command, speed_table)
