"""A trained policy without torch: an ONNX export (``cogexplore model export --onnx F.onnx``) run by
onnxruntime, with the same surface as :class:`cogexplore.Policy`.

    from cogexplore.onnx_runner import load_onnx_policy

    policy = load_onnx_policy("drl.onnx")
    command = policy.act(depth_m)                       # an (H, W) image in metres, any resolution -> 0..4
    linear_mps, angular_rps = policy.twist(command)     # hold it for policy.control_period_s

Imports numpy, onnxruntime and the torch-free parts of cogexplore only, so a robot computer needs
neither torch nor MuJoCo. The image is seen exactly as ``Policy`` sees it (``cogexplore._policy_io``)
and the command is the same greedy argmax (ties to the lowest index) of the same network, whose
export was checked against torch to ``MATCH_TOLERANCE``; a file that records the Q-values its graph
gave when exported (``OnnxPolicyInfo.self_check_q_values``) is refused when this onnxruntime gives
others (damaged weights).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime

from cogexplore._policy_io import CameraPolicy, checked_q_values
from shared.config import MAX_ACTION_HISTORY, NUM_ACTIONS, SensorConfig
from shared.depth import image_stack
from shared.errors import PolicyError
from shared.learning.onnx_format import (
    DEPTH_INPUT,
    METADATA_KEY,
    NO_PREVIOUS_ACTION,
    PREVIOUS_ACTION_INPUT,
    Q_OUTPUT,
    SELF_CHECK_TOLERANCE,
    OnnxModelError,
    OnnxPolicyInfo,
    q_difference,
    self_check_inputs,
)

__all__ = ["OnnxModelError", "OnnxPolicy", "load_onnx_policy"]

MAX_THREADS = 256
"""More onnxruntime threads than this is a mistake (each is an OS thread), not a machine."""


def run_graph(session: onnxruntime.InferenceSession, feed: dict[str, np.ndarray], label: str) -> np.ndarray:
    """The graph's (5,) Q-values for a batch of one; OnnxModelError for a graph that fails on its
    own inputs (a fixed batch size, a broken node), PolicyError for one that does not give five
    finite Q-values."""
    try:
        out = session.run([Q_OUTPUT], feed)[0]
    except Exception as exc:  # noqa: BLE001  onnxruntime's run errors share no other base
        raise OnnxModelError(f"{label}: the graph fails: {' '.join(str(exc).split())[:300]}") from None
    if getattr(out, "shape", None) != (1, NUM_ACTIONS):
        raise PolicyError(f"{label} gave Q-values of shape {getattr(out, 'shape', None)}, not (1, {NUM_ACTIONS})")
    return checked_q_values(out[0], label)


class OnnxPolicy(CameraPolicy):
    """The greedy policy of an exported Q-network, fed depth images from any resolution.

    Made by :func:`load_onnx_policy`; ``observation``, ``q_values``, ``act``, ``decide``, ``reset``,
    ``previous_command``, ``twist``, ``label``, ``sensor`` and ``control_period_s`` behave as
    :class:`cogexplore.Policy`'s. Not thread-safe: it remembers the previous commands (and, for a
    network that reads several images, the images it acted on)."""

    def __init__(self, session: onnxruntime.InferenceSession, info: OnnxPolicyInfo, path: Path):
        self.info: OnnxPolicyInfo = info
        """The file's metadata: camera, architecture, control period, provenance."""
        self.path: Path = path
        """The file loaded."""
        self.sensor: SensorConfig = info.sensor
        self.control_period_s: float = info.control_period_s
        self._session = session
        shape = next(i.shape for i in session.get_inputs() if i.name == PREVIOUS_ACTION_INPUT)
        self._history_input = len(shape) == 2  # (B, K) the last K commands, or (B,) the last one
        self._history = int(shape[1]) if self._history_input else 1
        self._previous_commands: tuple[int, ...] = ()  # most recent first
        self._images = info.model.frame_stack  # images per step the graph reads
        self._previous_images: tuple[np.ndarray, ...] = ()  # observations acted on, most recent first

    @property
    def label(self) -> str:
        """A short name: ``<run or file>@<policy version>``, as the torch policy's."""
        return self.info.label

    @property
    def previous_command(self) -> int | None:
        """The command the last :meth:`act` chose (None after :meth:`reset`)."""
        return self._previous_commands[0] if self._previous_commands else None

    def q_values(self, depth_m: Any) -> np.ndarray:
        """(5,) float32 Q-values of the commands for this image and the previous command;
        changes nothing (the next :meth:`act` still sees the same previous command)."""
        return self._q_values(self.observation(depth_m))

    def _q_values(self, observation: np.ndarray) -> np.ndarray:
        missing = (NO_PREVIOUS_ACTION,) * (self._history - len(self._previous_commands))
        previous = np.array([self._previous_commands + missing], dtype=np.int64)  # (1, K)
        feed = {DEPTH_INPUT: image_stack(observation, self._previous_images, self._images)[None],
                PREVIOUS_ACTION_INPUT: previous if self._history_input else previous[:, 0]}
        return run_graph(self._session, feed, self.label)

    def decide(self, depth_m: Any) -> tuple[int, np.ndarray]:
        observation = self.observation(depth_m)
        try:
            q = self._q_values(observation)
        except PolicyError:
            self.reset()  # as the torch Policy: a network that failed forgets the episode it was in
            raise
        # np.argmax takes the first maximum: ties go to the lowest index, as GreedyPolicy's
        command = int(np.argmax(q))
        self._previous_commands = (command, *self._previous_commands[:self._history - 1])
        self._previous_images = (observation, *self._previous_images)[:self._images - 1]
        return command, q

    def self_check(self) -> None:
        """OnnxModelError (one line) when the graph no longer gives the Q-values the exporter's
        onnxruntime recorded for the format's self-check inputs (to ``SELF_CHECK_TOLERANCE``): damaged
        weights. Nothing to check in a file exported before they were recorded."""
        if self.info.self_check_q_values is None:
            return
        depth, previous = self_check_inputs(self.sensor, self._images, self._history)
        try:
            q = self._session.run([Q_OUTPUT], {DEPTH_INPUT: depth, PREVIOUS_ACTION_INPUT: previous})[0]
        except Exception as exc:  # noqa: BLE001  onnxruntime's run errors share no other base
            raise OnnxModelError(f"{self.path}: the graph fails on its self-check: "
                                 f"{' '.join(str(exc).split())[:300]}") from None
        error = q_difference(q, np.array(self.info.self_check_q_values))
        if not error <= SELF_CHECK_TOLERANCE:  # NaN (or another shape) fails too
            raise OnnxModelError(f"{self.path}: its graph no longer gives the Q-values recorded at export (by "
                                 f"{error:.2g} relative, more than {SELF_CHECK_TOLERANCE:g}): damaged weights? "
                                 "Export it again")

    def reset(self) -> None:
        """A new episode: no previous command, no earlier images."""
        self._previous_commands = ()
        self._previous_images = ()

    def __repr__(self) -> str:
        return (f"OnnxPolicy({self.label!r}, {self.sensor.width}x{self.sensor.height} px, "
                f"{self.info.model.depth_encoding} depth, {self.path})")


def load_onnx_policy(path: str | os.PathLike[str], *, threads: int = 1) -> OnnxPolicy:
    """An :class:`OnnxPolicy` from a cogexplore ONNX export. ``threads``: onnxruntime's intra-op
    threads (1: the small network is fastest on one core and leaves the others to the robot).
    Raises OnnxModelError (one line) for a missing, corrupt or foreign file, and for one whose graph
    no longer gives the Q-values its metadata recorded at export (a file exported before they were
    recorded loads without that check)."""
    if not isinstance(path, (str, os.PathLike)):
        raise PolicyError(f"path must be an .onnx file path, got {type(path).__name__}")
    if not (isinstance(threads, int) and not isinstance(threads, bool) and 1 <= threads <= MAX_THREADS):
        raise PolicyError(f"threads must be an integer in 1..{MAX_THREADS}, got {threads!r}")
    path = Path(path)
    if not path.is_file():
        raise OnnxModelError(f"{path}: no such ONNX file (write one with `cogexplore model export CKPT --onnx FILE`)")
    options = onnxruntime.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only: onnxruntime's warnings would go to the robot's console
    try:
        session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as exc:  # noqa: BLE001  onnxruntime's load errors (InvalidProtobuf, Fail...) share no other base
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise OnnxModelError(f"{path}: not a readable ONNX model: {reason}") from None
    try:
        metadata = session.get_modelmeta().custom_metadata_map
    except UnicodeDecodeError:  # a damaged byte: onnxruntime decodes every entry as UTF-8
        raise OnnxModelError(f"{path}: its metadata is not UTF-8 text (a damaged file?)") from None
    if METADATA_KEY not in metadata:
        raise OnnxModelError(f"{path}: not a cogexplore ONNX export (no {METADATA_KEY!r} metadata; write one with "
                             "`cogexplore model export CKPT --onnx FILE`)")
    info = OnnxPolicyInfo.from_json(metadata[METADATA_KEY], str(path))
    _check_signature(session, info, path)
    policy = OnnxPolicy(session, info, path)
    try:  # one decision on an empty view: a graph that cannot give Q-values fails here, not on the robot
        policy.q_values(np.zeros((info.sensor.height, info.sensor.width), np.float32))
    except (PolicyError, OnnxModelError) as exc:
        raise OnnxModelError(f"{path}: {exc}") from None
    policy.self_check()
    return policy


def _check_signature(session: onnxruntime.InferenceSession, info: OnnxPolicyInfo, path: Path) -> None:
    """The graph takes and gives what the metadata's camera says (a batch axis of any name or size)."""
    s = info.sensor
    got_in = {i.name: (i.type, list(i.shape[1:])) for i in session.get_inputs()}
    # (B,) the last command, or (B, K) the last K commands: at least as many as the metadata's network
    # reads (an ensemble's metadata names its first member)
    reads = info.model.action_history
    history = got_in.get(PREVIOUS_ACTION_INPUT, (None, []))[1]
    if not (len(history) == 1 and isinstance(history[0], int) and max(2, reads) <= history[0] <= MAX_ACTION_HISTORY):
        history = [reads] if reads > 1 else []
    want_in = {DEPTH_INPUT: ("tensor(float)", [info.model.frame_stack, s.height, s.width]),
               PREVIOUS_ACTION_INPUT: ("tensor(int64)", history)}
    got_out = {o.name: (o.type, list(o.shape[1:])) for o in session.get_outputs()}
    if got_in != want_in or got_out != {Q_OUTPUT: ("tensor(float)", [NUM_ACTIONS])}:
        raise OnnxModelError(f"{path}: the graph's inputs {got_in} and outputs {got_out} are not the "
                             f"{s.width} x {s.height} policy its metadata describes")
