"""The drive node's decisions, without Zenoh: each depth image (ROS 2 CDR bytes) becomes a move
command or a stop, and the clock alone (the watchdog) can stop the robot.

The safety rules, in the order they are checked:

1. An image that cannot be read (garbage, truncated, another encoding, an absurd or wrong size,
   negative depths, no return within the camera's range at all: a blinded or saturated sensor
   that reads NaN, 0 or its maximum everywhere) is refused, counted by cause, and stops the robot;
   so is one whose reading fails in any other way (out of memory on a large image).
2. An image whose nearest valid depth is below the collision distance stops the robot (the task's
   collision rule, ``EnvConfig.collision_distance_m``: the policy was never taught to act there).
   A -Inf pixel, REP 117's return too near to measure, is nearer than any.
3. Otherwise the policy chooses a command from the image, at most one per control period (in lock
   step, one per image): a command always comes from the image that just arrived, never a stale one.
   A policy that fails on it (a runtime error of torch or onnxruntime) stops the robot, as a refused
   image does.
   With ``max_image_age_s`` set, an image whose header stamp lies further than that in the past
   (delayed on the way: a Wi-Fi stall, a queue) or in the future (clocks out of step) by this
   machine's clock is refused too: its arrival says nothing of when it was taken.
4. No valid image for ``watchdog_s`` stops the robot, and the stop is repeated each control period
   until images return. A command decided ``watchdog_s`` or more after its image arrived (a policy
   that stalled, a large image slow to read) is a stop too, except in lock step, where the simulator
   waits for it. A command only ever comes from an image that arrived after the last stop the
   watchdog sent (:meth:`DriveController.on_tick`'s, or the shell's while a decision stalls,
   :meth:`DriveController.watchdog_stopped`), lock step included: an image read while the watchdog
   stopped the robot decides nothing (in lock step the simulator answers that stop with the image
   again, and the command waits for it).

An image is read (decoded and checked, :meth:`DriveController.read`: it changes nothing) apart from
the decision on it (:meth:`DriveController.decide`), so that the shell's watchdog can stop the robot
while a large image is read.

A stop is sent at once when the robot was moving; while it stands, at most once per control period,
so a flood of garbage cannot flood ``cmd_vel``. After the stop at exit nothing more is decided. The
process shell (``services.drive.service``) adds the signals and sends that stop.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from shared.config import SPEED_TABLES, EnvConfig
from shared.errors import CogexploreError
from shared.ros2.messages import Ros2MessageError, decode_depth_image
from shared.wire.messages import OVERSIZE

DEFAULT_WATCHDOG_S = 0.5
MAX_IMAGE_BYTES = 64 * 2**20
"""Larger payloads are refused unread (a 1920 x 1080 32FC1 image is 8 MB)."""
NO_VALID_DEPTH = "no_valid_depth"
"""Reject cause of an image without a single valid pixel (all NaN, all zero): a blinded sensor."""
TOO_SMALL = "too_small"
"""Reject cause of an image smaller than the network's input: resizing up would invent detail."""
BAD_DEPTH = "bad_depth"
"""Reject cause of an image the policy's camera refuses: negative depths, another aspect ratio."""
POLICY_ERROR = "policy_error"
"""Reject cause of an image the policy failed on (the error is in the decision and the log)."""
READ_ERROR = "read_error"
"""Reject cause of an image whose reading failed unexpectedly (out of memory on a large image, the
policy's camera raising what it never should): it is refused and stops the robot as any other."""
STALE_STAMP = "stale_stamp"
"""Reject cause of an image stamped longer ago than ``max_image_age_s`` (or never stamped)."""
FUTURE_STAMP = "future_stamp"
"""Reject cause of an image stamped further than ``max_image_age_s`` in this machine's future."""


class DriveConfigError(CogexploreError):
    """A drive setting is invalid."""


class DrivePolicy(Protocol):
    """What the controller needs of a policy: ``cogexplore.Policy`` and ``cogexplore.onnx_runner.OnnxPolicy``."""

    sensor: Any
    control_period_s: float
    label: str

    def observation(self, depth_m: Any) -> np.ndarray: ...
    def decide(self, depth_m: Any) -> tuple[int, np.ndarray]: ...
    def reset(self) -> None: ...
    def twist(self, command: int, speed_table: str = "test") -> Any: ...


@dataclass(frozen=True)
class DriveConfig:
    """How the drive node turns images into commands."""

    speed_table: str = "test"
    """The speeds of the five commands: the paper's ``test`` table (the protocol's) or ``train``."""
    collision_distance_m: float = EnvConfig().collision_distance_m
    """Stop when the nearest valid depth is below this (the task's collision rule)."""
    watchdog_s: float = DEFAULT_WATCHDOG_S
    """Stop when no valid image has arrived for this long."""
    control_period_s: float | None = None
    """At most one command per period (None: the policy's own, 0.5 s for the shipped model)."""
    lockstep: bool = False
    """One command per image, however fast images come (a simulator that waits for each command)."""
    max_image_bytes: int = MAX_IMAGE_BYTES
    """Payloads above this are refused before they are decoded."""
    max_image_age_s: float | None = None
    """Refuse an image whose header stamp is further than this from this machine's clock, past or
    future (None, the default: stamps are not read, since a robot's clock may not be this machine's,
    or may run on simulated time). Needs the clocks kept in step (chrony, NTP)."""

    def __post_init__(self) -> None:
        if self.speed_table not in SPEED_TABLES:
            raise DriveConfigError(f"speed table {self.speed_table!r}: choose {' or '.join(SPEED_TABLES)}")
        optional = ("max_image_age_s",) if self.max_image_age_s is not None else ()
        for name in ("collision_distance_m", "watchdog_s", *optional):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise DriveConfigError(f"{name} must be a positive number, got {value!r}")
        if self.control_period_s is not None and not (np.isfinite(self.control_period_s) and self.control_period_s > 0):
            raise DriveConfigError(f"control_period_s must be positive, got {self.control_period_s!r}")


@dataclass(frozen=True)
class Decision:
    """A twist to publish now, and why."""

    linear_mps: float
    angular_rps: float
    command: int | None
    """The policy's command, None for a stop."""
    stop_reason: str | None
    """``shared.wire.robot.STOP_REASONS`` for a stop, else None."""
    nearest_depth_m: float | None = None
    latency_ms: float | None = None
    """From the image's arrival until this decision was made."""
    q_values: tuple[float, ...] = ()
    reject_cause: str | None = None
    """Set when a refused image caused this stop."""
    error: str | None = None
    """What went wrong, for a stop a refused image or the policy's failure caused (for the log)."""

    @property
    def is_stop(self) -> bool:
        return self.command is None


@dataclass(frozen=True)
class Reading:
    """An image read and checked by :meth:`DriveController.read`, ready for :meth:`DriveController.decide`."""

    depth_m: np.ndarray
    """The image in metres, as it came (for recordings)."""
    observation: np.ndarray
    """The policy's camera image of it (``DrivePolicy.observation``): what the policy decides on."""
    nearest_m: float | None
    """:func:`nearest_valid_depth` within the camera's range (None: no return at all)."""
    stamp_ns: int


@dataclass(frozen=True)
class Refusal:
    """An image :meth:`DriveController.read` refused: the reject cause, and what was wrong."""

    cause: str
    error: str | None = None


def nearest_valid_depth(depth_m: np.ndarray, max_range_m: float = np.inf) -> float | None:
    """The smallest depth above 0 and within ``max_range_m`` (None when the image has no such return);
    0.0 when a pixel is -Inf, a return too near to measure (REP 117)."""
    if np.isneginf(depth_m).any():
        return 0.0
    valid = depth_m[np.isfinite(depth_m) & (depth_m > 0) & (depth_m <= max_range_m)]
    return float(valid.min()) if valid.size else None


@dataclass
class DriveController:
    """Images and clock ticks in, :class:`Decision` out (None: nothing to send). Not thread-safe:
    the shell holds one lock around it."""

    policy: DrivePolicy
    config: DriveConfig = field(default_factory=DriveConfig)
    clock: Any = time.monotonic
    wall_clock_ns: Any = time.time_ns
    """The clock image stamps are compared with (``max_image_age_s``)."""

    def __post_init__(self) -> None:
        max_range_m = float(self.policy.sensor.max_range_m)
        if self.config.collision_distance_m >= max_range_m:
            # Every image would read too close (or blind): the robot would never move, and say so
            # only in its diagnostics.
            raise DriveConfigError(f"collision distance {self.config.collision_distance_m:g} m must be below the "
                                   f"policy's camera range, {max_range_m:g} m")
        self.period_s = self.config.control_period_s or float(self.policy.control_period_s)
        self.started_s = self.clock()
        self.last_image_s: float | None = None  # arrival of the last valid image
        self.last_command_s: float | None = None  # the last move command
        self.last_stop_s: float | None = None
        self.last_watchdog_stop_s: float | None = None
        """When the watchdog last sent a stop: no image that arrived before it moves the robot."""
        self.moving = False
        self.decisions = 0
        self.rejects: dict[str, int] = {}
        self.last_depth_m: np.ndarray | None = None
        """The last image read (for recordings)."""
        self.exited = False
        """Set by :meth:`exit_stop`: no decision after it."""

    # -- inputs ---------------------------------------------------------------------------
    def on_image(self, payload: bytes | bytearray | memoryview, received_s: float | None = None) -> Decision | None:
        """One image message as it arrived; the decision to publish, if any (:meth:`read`, then
        :meth:`decide`)."""
        if self.exited:
            return None
        received_s = self.clock() if received_s is None else received_s
        return self.decide(self.read(payload), received_s)

    def read(self, payload: bytes | bytearray | memoryview) -> Reading | Refusal:
        """Decode and check one image message: the slow part of :meth:`on_image` (a large image takes
        longer than the watchdog), which changes nothing, so the shell runs it outside its lock."""
        try:
            image = decode_depth_image(bytes(payload), max_bytes=self.config.max_image_bytes)
            if self.config.max_image_age_s is not None:  # first, as ever (and again in decide, at decision time)
                self._check_stamp(image.stamp_ns, self.config.max_image_age_s)
            sensor = self.policy.sensor
            if image.width < sensor.width or image.height < sensor.height:
                raise Ros2MessageError(TOO_SMALL, f"{image.width} x {image.height} image; the network sees "
                                                  f"{sensor.width} x {sensor.height}")
            depth = image.depth_m
            # the checks of the policy's camera, before any decision; -Inf is too near (REP 117), not
            # a negative depth: the nearest-depth rule stops on it, the camera need not refuse it
            too_near = np.isneginf(depth)
            observation = self.policy.observation(np.where(too_near, np.float32(np.nan), depth)
                                                  if too_near.any() else depth)
        except Ros2MessageError as exc:
            return Refusal(exc.cause, str(exc))
        except CogexploreError as exc:  # the policy's camera refused it: negative depths, millimetres in metres
            return Refusal(BAD_DEPTH, str(exc))
        except Exception as exc:  # noqa: BLE001 -- whatever else failed, no command comes from this image
            return Refusal(READ_ERROR, f"{type(exc).__name__}: {exc}")
        # Beyond the camera's range is no return, as the network sees it (range-gated to 0): an image
        # that reads its maximum everywhere is as blind as one that reads NaN everywhere.
        return Reading(depth, observation, nearest_valid_depth(depth, float(self.policy.sensor.max_range_m)),
                       image.stamp_ns)

    def decide(self, reading: Reading | Refusal, received_s: float) -> Decision | None:
        """The decision on an image :meth:`read` and its arrival (``received_s``, on ``clock``)."""
        if self.exited:
            return None
        if isinstance(reading, Refusal):
            return self._reject(reading.cause, received_s, reading.error)
        if self.config.max_image_age_s is not None:
            try:  # again, now: reading a large image takes a while, and the stamp ages meanwhile
                self._check_stamp(reading.stamp_ns, self.config.max_image_age_s)
            except Ros2MessageError as exc:
                return self._reject(exc.cause, received_s, str(exc))
        self.last_depth_m = reading.depth_m
        nearest = reading.nearest_m
        if nearest is None:
            return self._reject(NO_VALID_DEPTH, received_s)
        self.last_image_s = received_s
        if nearest < self.config.collision_distance_m:
            return self._stop("too_close", received_s, nearest, received_s)
        if self.last_watchdog_stop_s is not None and received_s <= self.last_watchdog_stop_s:
            # read while the watchdog stopped the robot: a command from it would undo that stop
            # (the robot stands already: a reminder at most, as for any stop)
            decision = self._stop("watchdog", self.clock(), nearest, received_s)
            return None if decision is None else dataclasses.replace(
                decision, error=f"the image arrived {self.last_watchdog_stop_s - received_s:.2f} s before "
                                "the watchdog's stop")
        due = (self.config.lockstep or self.last_command_s is None
               or received_s - self.last_command_s >= 0.9 * self.period_s)  # 0.9: a camera's jitter
        if not due:
            return None
        try:
            # its camera image, not the image again: the camera sees it unchanged, and resizing a
            # large image once more would take as long as read's (under the shell's lock)
            command, q_values = self.policy.decide(reading.observation)
            q_values = tuple(float(q) for q in np.asarray(q_values, dtype=np.float64).reshape(-1))
            if not all(np.isfinite(q_values)):  # its command is the argmax of nothing: no command at all
                raise FloatingPointError(f"the network's Q-values are not finite: {q_values}")
            twist = self.policy.twist(int(command), self.config.speed_table)
        except Exception as exc:  # noqa: BLE001 -- whatever the network's runtime raises, the robot stops
            return self._reject(POLICY_ERROR, received_s, f"{type(exc).__name__}: {exc}")
        now = self.clock()
        if not self.config.lockstep and now - received_s >= self.config.watchdog_s:
            # The image went stale while it was read or the policy decided (a large image, a GPU
            # stall, a loaded CPU): the shell's watchdog has stopped the robot meanwhile, and a
            # command from that image would undo it.
            decision = self._stop("watchdog", now, nearest, received_s)
            return None if decision is None else dataclasses.replace(
                decision, error=f"the image was decided {now - received_s:.2f} s after it arrived")
        self.last_command_s = received_s
        self.moving = twist.linear_mps != 0 or twist.angular_rps != 0
        return self._decided(Decision(twist.linear_mps, twist.angular_rps, int(command), None, nearest,
                                      (now - received_s) * 1e3, q_values))

    def on_oversize_image(self, size: int, received_s: float | None = None) -> Decision | None:
        """An image message refused unread for its ``size`` in bytes (over ``max_image_bytes``)."""
        if self.exited:
            return None
        return self._reject(OVERSIZE, self.clock() if received_s is None else received_s)

    def on_tick(self, now_s: float | None = None) -> Decision | None:
        """The watchdog, called often (every few tens of ms): a stop when images have stopped."""
        if self.exited:
            return None
        now_s = self.clock() if now_s is None else now_s
        since = self.last_image_s if self.last_image_s is not None else self.started_s
        if now_s - since < self.config.watchdog_s:
            return None
        decision = self._stop("watchdog" if self.last_image_s is not None else "no_image", now_s)
        if decision is not None:
            self.watchdog_stopped(now_s)
        return decision

    def watchdog_stopped(self, at_s: float) -> None:
        """The watchdog sent a stop at ``at_s`` (on ``clock``): no image that arrived before it moves
        the robot. The shell calls it for the stop it sends while a decision holds the controller."""
        if self.last_watchdog_stop_s is None or at_s > self.last_watchdog_stop_s:
            self.last_watchdog_stop_s = at_s

    def exit_stop(self) -> Decision:
        """The stop sent when the process ends (always sent); nothing is decided after it."""
        self.moving = False
        self.exited = True
        return self._decided(Decision(0.0, 0.0, None, "exit"))

    def reset(self) -> None:
        """A new episode: the policy forgets its previous command."""
        self.policy.reset()

    # -- internals ------------------------------------------------------------------------
    def _check_stamp(self, stamp_ns: int, max_age_s: float) -> None:
        """Ros2MessageError unless the image was taken within ``max_age_s`` of now, by its stamp."""
        if stamp_ns == 0:
            raise Ros2MessageError(STALE_STAMP, "the image has no stamp (header.stamp 0): stamp the camera's "
                                                "images, or drop --max-image-age")
        age_s = (self.wall_clock_ns() - stamp_ns) / 1e9
        if age_s > max_age_s:
            raise Ros2MessageError(STALE_STAMP, f"the image was taken {age_s:.2f} s ago (at most {max_age_s:g} s)")
        if age_s < -max_age_s:
            raise Ros2MessageError(FUTURE_STAMP, f"the image is stamped {-age_s:.2f} s ahead of this machine's "
                                                 "clock: keep the robot's clock and this one in step (NTP), or "
                                                 "drop --max-image-age")

    def _reject(self, cause: str, now_s: float, error: str | None = None) -> Decision | None:
        self.rejects[cause] = self.rejects.get(cause, 0) + 1
        decision = self._stop("reject", now_s)
        return None if decision is None else dataclasses.replace(
            decision, reject_cause=cause, error=None if error is None else error[:300])

    def _stop(self, reason: str, now_s: float, nearest: float | None = None,
              received_s: float | None = None) -> Decision | None:
        if not self.moving and self.last_stop_s is not None and now_s - self.last_stop_s < self.period_s:
            return None  # standing still already: a reminder once per period is enough
        self.moving = False
        self.last_stop_s = now_s
        latency = None if received_s is None else (self.clock() - received_s) * 1e3
        return self._decided(Decision(0.0, 0.0, None, reason, nearest, latency))

    def _decided(self, decision: Decision) -> Decision:
        self.decisions += 1
        return decision
