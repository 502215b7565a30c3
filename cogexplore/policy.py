"""The shipped (or any trained) Q-network as a controller: :func:`load_policy` and :class:`Policy`.

A :class:`Policy` takes a depth image in metres from any camera with the network's field of view
(57 x 43 degrees for the shipped model), at any resolution, and sees it as the project's simulated
camera would have (``shared.depth.resize_depth``, then the camera's range gate); the network
encodes it (``shared.learning.model``) with the previous command, which the policy remembers.
"""

from __future__ import annotations

import os
from typing import Any, NamedTuple

import numpy as np

from shared.config import ACTION_NAMES, SPEED_TABLES, SensorConfig
from shared.depth import depth_from_mm, range_gate, resize_depth
from shared.evaluation.setup import EvalSetup, setup_evaluation
from shared.learning.checkpoints import LoadedModel
from shared.learning.model import InferenceRunner
from shared.learning.policy import PolicyError

COMMAND_NAMES: tuple[str, ...] = ACTION_NAMES
"""The five moving commands by index: left, half-left, straight, half-right, right."""
ASPECT_TOLERANCE = 0.05
"""How far (relative) an image's width / height may be from the network's before it is refused:
another aspect ratio is another field of view, which resizing cannot make up."""


class Command(NamedTuple):
    """A moving command as the robot drives it, for one control period."""

    linear_mps: float
    """Forward speed, m/s."""
    angular_rps: float
    """Turn rate, rad/s; positive turns left."""


def _metres(depth_m: Any) -> np.ndarray:
    """A user's depth image as (H, W) float metres (NaN and infinity kept: resizing reads them as
    no return); PolicyError for anything that is not one image of depths."""
    try:
        depth = np.asarray(depth_m)
    except (TypeError, ValueError) as exc:
        raise PolicyError(f"depth_m must be an (H, W) array of depths in metres: {exc}") from None
    if depth.ndim == 3 and depth.shape[-1] == 1:  # (H, W, 1), as many camera drivers give it
        depth = depth[..., 0]
    if depth.ndim != 2:
        raise PolicyError(f"depth_m must be one (H, W) depth image, got shape {depth.shape}")
    if depth.size == 0:
        raise PolicyError(f"depth_m is empty (shape {depth.shape})")
    if depth.dtype == np.uint16:
        return depth_from_mm(depth)
    if not np.issubdtype(depth.dtype, np.floating):
        raise PolicyError(f"depth_m must be float metres (or uint16 millimetres), got {depth.dtype}")
    if (depth < 0).any():
        raise PolicyError("depth_m has negative depths; expected metres >= 0 (0, NaN or inf: no return)")
    return depth


class Policy:
    """The greedy policy of a Q-network (dropout off), fed depth images from any resolution.

    Made by :func:`load_policy`. ``act(depth_m)`` returns the command index (see
    :data:`COMMAND_NAMES`, :meth:`twist`) and remembers it as the previous command, which the
    network reads with the next image; call :meth:`reset` when an episode starts. A Policy is
    itself a callable ``depth_m -> command`` with ``reset()``, as :func:`cogexplore.evaluate` takes.
    """

    command_names: tuple[str, ...] = COMMAND_NAMES

    def __init__(self, setup: EvalSetup):
        if setup.model is None or setup.policy != "greedy":
            raise PolicyError("a Policy needs a Q-network setup (use cogexplore.load_policy)")
        self.model: LoadedModel = setup.model
        """The loaded network and where it came from (``shared.learning.checkpoints``)."""
        self.sensor: SensorConfig = setup.sensor_cfg
        """The camera the network was trained with: its image size, field of view and range."""
        self.control_period_s: float = setup.env_cfg.control_period_s
        """How long each command is held before the next image is taken."""
        self._greedy = setup.policy_fn  # shared.evaluation.policies.GreedyPolicy: argmax and the memory
        self._runner = InferenceRunner(self.model.net)

    @property
    def label(self) -> str:
        """A short name: ``<run or file>@<policy version>``."""
        return self.model.label

    @property
    def previous_command(self) -> int | None:
        """The command the last :meth:`act` chose (None after :meth:`reset`)."""
        return self._greedy.policy.previous_action

    def observation(self, depth_m: Any) -> np.ndarray:
        """The network's camera image of ``depth_m``: float32 (H, W) metres at the network's size,
        0 = no return, as the simulated camera would have taken it.

        ``depth_m``: (H, W) (or (H, W, 1)) float metres at any size with the network's aspect
        ratio, i.e. its field of view; NaN, infinity and 0 are no return; uint16 is millimetres.
        Raises PolicyError for a wrong shape, an empty array or another aspect ratio.
        """
        depth = _metres(depth_m)
        cfg = self.sensor
        h, w = depth.shape
        if abs((w / h) / (cfg.width / cfg.height) - 1.0) > ASPECT_TOLERANCE:
            raise PolicyError(f"depth_m is {w} x {h} pixels; the network's camera is {cfg.width} x {cfg.height} "
                              f"({cfg.hfov_deg:g} x {cfg.vfov_deg:g} degrees): crop the image to that field of "
                              "view first")
        return range_gate(resize_depth(depth, cfg.height, cfg.width), cfg.min_range_m, cfg.max_range_m)

    def q_values(self, depth_m: Any) -> np.ndarray:
        """(5,) float32 Q-values of the commands for this image and the previous command;
        changes nothing (the next :meth:`act` still sees the same previous command)."""
        return self._runner.q_values(self.observation(depth_m), self.previous_command)

    def act(self, depth_m: Any) -> int:
        """The greedy command (0..4) for one depth image; it becomes the previous command."""
        action, _q = self._greedy(self.observation(depth_m))
        return action

    __call__ = act

    def reset(self) -> None:
        """A new episode: no previous command."""
        self._greedy.reset()

    def twist(self, command: int, speed_table: str = "test") -> Command:
        """The (linear m/s, angular rad/s) of a command at the paper's ``test`` speeds (the
        protocol's) or its ``train`` speeds."""
        if speed_table not in SPEED_TABLES:
            raise PolicyError(f"unknown speed table {speed_table!r}; choose {' or '.join(SPEED_TABLES)}")
        if not (isinstance(command, (int, np.integer)) and not isinstance(command, bool)
                and 0 <= command < len(COMMAND_NAMES)):
            raise PolicyError(f"command must be an index in 0..{len(COMMAND_NAMES) - 1}, got {command!r}")
        angular, linear = SPEED_TABLES[speed_table]
        return Command(float(linear), float(angular[int(command)]))

    def __repr__(self) -> str:
        return (f"Policy({self.label!r}, {self.sensor.width}x{self.sensor.height} px, "
                f"{self.model.net.model_cfg.depth_encoding} depth, {self.model.path})")


def load_policy(source: str | os.PathLike[str] = "pretrained", *, device: str = "auto") -> Policy:
    """A :class:`Policy` from ``source``: ``pretrained`` (the shipped DRL model), a checkpoint file
    or directory, a run folder or a weights export, whatever ``cogexplore evaluate --checkpoint``
    takes. ``device``: ``auto`` (CUDA when present), ``cpu``, ``cuda``, ``cuda:1``...
    Raises a CogexploreError (one line) for a missing or unreadable model."""
    if not isinstance(source, (str, os.PathLike)):
        raise PolicyError(f"source must be 'pretrained' or a path, got {type(source).__name__}")
    return Policy(setup_evaluation(None, source, device=device))
