"""Wire messages beside a ROS 2 robot (keys: ``shared.wire.keys.RobotKeys``): what ``cogexplore
drive`` decided and why, and what ``cogexplore sim-robot`` did. Same codec and validation as every
other cogexplore message (``shared.wire.messages``); the ROS 2 messages themselves are CDR
(``shared.ros2.messages``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from shared.config import NUM_ACTIONS
from shared.wire.messages import (
    _WIRE_TUPLE,
    COLLISION_CAUSES,
    FIELD_TYPE,
    INCONSISTENT,
    RANGE,
    Message,
    MessageError,
    _bool,
    _chunk,
    _extra,
    _float,
    _int,
    _opt_float,
    _register,
    _set,
    _text,
)

STOP_REASONS: tuple[str, ...] = ("too_close", "watchdog", "reject", "exit", "no_image")
"""Why ``drive`` sent a zero twist: an obstacle nearer than the collision distance, no image for
the watchdog period, a malformed or wrong-sized image, the process ending, nothing seen yet."""


@_register
@dataclass(frozen=True)
class DriveDiagnostics(Message):
    """One decision of the drive node: the command it sent (or the stop) and what it saw."""

    TYPE: ClassVar[str] = "drive_diagnostics"

    robot: str
    decision: int
    """Twists the node has sent so far, this one included (each stop one of its own, also those sent
    without the policy: the watchdog's while a decision stalls, the exit's): the recording's timeline."""
    command: int | None
    """The policy's command 0..4, None for a stop."""
    linear_mps: float
    angular_rps: float
    stop_reason: str | None
    """One of :data:`STOP_REASONS` for a zero twist, else None."""
    nearest_depth_m: float | None
    """The nearest valid depth of the image (None: no image, or no valid pixel)."""
    latency_ms: float | None
    """From the image's arrival to the command's publication (None for a stop with no image)."""
    q_values: tuple[float, ...] = field(default=(), metadata={"wire": _WIRE_TUPLE})
    """The network's Q-values for the image (empty when it did not run)."""
    policy: str = "unknown"
    """The policy's label (file or run @ version)."""
    rejects: dict[str, float] = field(default_factory=dict)
    """Images refused so far, by cause."""

    def __post_init__(self) -> None:
        _set(self, "robot", _chunk(self.robot, "robot"))
        _set(self, "decision", _int(self.decision, "decision"))
        if self.command is not None:
            _set(self, "command", _int(self.command, "command", 0, NUM_ACTIONS - 1))
        _set(self, "linear_mps", _float(self.linear_mps, "linear_mps", -10.0, 10.0))
        _set(self, "angular_rps", _float(self.angular_rps, "angular_rps", -20.0, 20.0))
        if self.stop_reason is not None and self.stop_reason not in STOP_REASONS:
            raise MessageError(RANGE, f"stop_reason {self.stop_reason!r} is not one of {list(STOP_REASONS)}")
        if (self.command is None) == (self.stop_reason is None):
            raise MessageError(INCONSISTENT, "exactly one of command and stop_reason is set")
        _set(self, "nearest_depth_m", _opt_float(self.nearest_depth_m, "nearest_depth_m", 0.0, 1e3))
        _set(self, "latency_ms", _opt_float(self.latency_ms, "latency_ms", 0.0, 1e7))
        if not isinstance(self.q_values, (tuple, list)) or len(self.q_values) not in (0, NUM_ACTIONS):
            raise MessageError(FIELD_TYPE, f"q_values must be empty or {NUM_ACTIONS} numbers")
        _set(self, "q_values", tuple(_float(q, "q_values") for q in self.q_values))
        _set(self, "policy", _text(self.policy, "policy"))
        _set(self, "rejects", _extra(self.rejects, "rejects"))


@_register
@dataclass(frozen=True)
class SimRobotStatus(Message):
    """The simulated robot after one control period (or at an episode's start, ``step`` 0)."""

    TYPE: ClassVar[str] = "sim_robot_status"

    robot: str
    world: str
    episode: int
    step: int
    """Control periods driven this episode."""
    x: float
    y: float
    yaw: float
    linear_mps: float
    """The command it held this period."""
    angular_rps: float
    collided: bool
    """The episode ended in a collision (it then holds still until a reset)."""
    collision_cause: str | None
    """'depth' or 'contact' when collided."""
    commands: int
    """cmd_vel messages taken so far (all episodes)."""
    rejects: dict[str, float] = field(default_factory=dict)
    """cmd_vel messages refused so far, by cause."""

    def __post_init__(self) -> None:
        _set(self, "robot", _chunk(self.robot, "robot"))
        _set(self, "world", _text(self.world, "world"))
        for name in ("episode", "step", "commands"):
            _set(self, name, _int(getattr(self, name), name))
        for name in ("x", "y", "yaw", "linear_mps", "angular_rps"):
            _set(self, name, _float(getattr(self, name), name, -1e6, 1e6))
        _set(self, "collided", _bool(self.collided, "collided"))
        if self.collision_cause is not None and self.collision_cause not in COLLISION_CAUSES:
            raise MessageError(RANGE, f"collision_cause {self.collision_cause!r} is not one of {list(COLLISION_CAUSES)}")
        if (self.collision_cause is not None) != self.collided:
            raise MessageError(INCONSISTENT, "collision_cause must be set exactly when collided")
        _set(self, "rejects", _extra(self.rejects, "rejects"))
