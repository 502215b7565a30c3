"""The shipped (or any trained) Q-network as a controller: :func:`load_policy` and :class:`Policy`.

A :class:`Policy` takes a depth image in metres from any camera with the network's field of view
(57 x 43 degrees for the shipped model), at any resolution, and sees it as the project's simulated
camera would have (``shared.depth.resize_depth``, then the camera's range gate); the network
encodes it (``shared.learning.model``) with the previous command, which the policy remembers.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from cogexplore._policy_io import ASPECT_TOLERANCE, COMMAND_NAMES, CameraPolicy, Command, checked_q_values
from shared.config import SensorConfig
from shared.errors import PolicyError
from shared.evaluation.setup import EvalSetup, setup_evaluation
from shared.learning.checkpoints import LoadedModel
from shared.learning.policy import NonFiniteQValues

__all__ = ["ASPECT_TOLERANCE", "COMMAND_NAMES", "Command", "Policy", "load_policy"]


class Policy(CameraPolicy):
    """The greedy policy of a Q-network (dropout off), fed depth images from any resolution.

    Made by :func:`load_policy`. ``act(depth_m)`` returns the command index (see
    :data:`COMMAND_NAMES`, :meth:`twist`) and remembers it as the previous command, which the
    network reads with the next image; call :meth:`reset` when an episode starts. A Policy is
    itself a callable ``depth_m -> command`` with ``reset()``, as :func:`cogexplore.evaluate` takes.
    """

    def __init__(self, setup: EvalSetup):
        if setup.model is None or setup.policy != "greedy":
            raise PolicyError("a Policy needs a Q-network setup (use cogexplore.load_policy)")
        self.model: LoadedModel = setup.model
        """The loaded network and where it came from (``shared.learning.checkpoints``)."""
        self.sensor: SensorConfig = setup.sensor_cfg
        self.control_period_s: float = setup.env_cfg.control_period_s
        self._greedy = setup.policy_fn  # shared.evaluation.policies.GreedyPolicy: argmax and the memory

    @property
    def label(self) -> str:
        """A short name: ``<run or file>@<policy version>``."""
        return self.model.label

    @property
    def previous_command(self) -> int | None:
        """The command the last :meth:`act` chose (None after :meth:`reset`)."""
        return self._greedy.policy.previous_action

    def q_values(self, depth_m: Any) -> np.ndarray:
        """(5,) float32 Q-values of the commands for this image and the previous command (and
        images, for a network that reads several); changes nothing (the next :meth:`act` still
        sees the same previous command)."""
        return checked_q_values(self._greedy.policy.q_values(self.observation(depth_m)), self.label)

    def decide(self, depth_m: Any) -> tuple[int, np.ndarray]:
        try:
            command, q = self._greedy(self.observation(depth_m))
        except NonFiniteQValues as exc:  # no command chosen, none remembered: said naming this policy
            self.reset()  # nor the image, for a network that reads several
            checked_q_values(exc.q_values, self.label)
            raise
        return command, checked_q_values(q, self.label)

    def reset(self) -> None:
        """A new episode: no previous command."""
        self._greedy.reset()

    def __repr__(self) -> str:
        return (f"Policy({self.label!r}, {self.sensor.width}x{self.sensor.height} px, "
                f"{self.model.net.model_cfg.depth_encoding} depth, {self.model.path})")


def load_policy(source: str | os.PathLike[str] = "pretrained", *, device: str = "auto") -> Policy:
    """A :class:`Policy` from ``source``: ``pretrained`` (the shipped DRL model), a checkpoint file
    or directory, a run folder or a weights export, whatever ``cogexplore evaluate --checkpoint``
    takes (an ONNX export: :func:`cogexplore.load_onnx_policy`). ``device``: ``auto`` (CUDA when
    present), ``cpu``, ``cuda``, ``cuda:1``...
    Raises a CogexploreError (one line) for a missing or unreadable model."""
    if not isinstance(source, (str, os.PathLike)):
        raise PolicyError(f"source must be 'pretrained' or a path, got {type(source).__name__}")
    return Policy(setup_evaluation(None, source, device=device))
