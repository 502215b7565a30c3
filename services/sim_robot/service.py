"""``cogexplore sim-robot``: an :class:`shared.sim.env.ExploreEnv` world behind ROS 2 topics.

It publishes the depth camera as ``sensor_msgs/msg/Image`` and the pose as ``nav_msgs/msg/Odometry``,
obeys ``geometry_msgs/msg/Twist`` on ``cmd_vel`` and reports each control period as a
:class:`shared.wire.robot.SimRobotStatus` (pose, collision) on ``cogexplore/@robot/<robot>/status``.

Two clocks:

- real time: every control period it drives the newest command for one period (a command older than
  ``--cmd-timeout`` is a stop, as a TurtleBot base times out), then publishes the new image;
- ``--lockstep``: each cmd_vel drives exactly one period, then the image is published, as fast as
  commands come; a zero twist drives nothing and publishes the image again (how a drive node
  that started first, and is stopped by its watchdog, gets its first image).

Either way only the newest command waits to be taken: one that a newer replaces first is counted
as a ``superseded`` reject (a flood of commands from anyone on the router neither grows a queue nor
drives stale commands ahead of the newest).

A collision (the task's rule: the body touches, or the nearest depth falls below the collision
distance) ends the episode: the robot holds still and says so until a put on
``cogexplore/@robot/<robot>/reset`` puts it back at its start pose.

A pixel without a return is 0 in ``16UC1`` (REP 118) and +Inf in ``32FC1``, REP 117's "no object
within the sensor's range" (0.0 m there reads as an obstacle at the lens to a consumer that follows
the REP, NaN as an erroneous measurement, which clears no free space).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import threading
import time

import numpy as np

from services.bus.ros2 import Ros2Node, ros2_settings
from services.bus.session import open_service_session
from services.process import setup_logging, stop_event_on_signals
from shared.config import DEFAULT_PRESET, load_preset
from shared.errors import CogexploreError
from shared.ros2.formats import make_format, qualify
from shared.ros2.messages import (
    IMAGE,
    ODOMETRY,
    TWIST,
    Ros2MessageError,
    decode_twist,
    encode_depth_image,
    encode_odometry,
)
from shared.sim.env import ExploreEnv
from shared.sim.robot import MAX_TWIST_MPS, MAX_TWIST_RPS
from shared.wire.keys import RobotKeys
from shared.wire.messages import RejectCounter
from shared.wire.robot import SimRobotStatus

log = logging.getLogger("cogexplore.sim_robot")
NODE_NAME = "cogexplore_sim_robot"


def ros_depth(depth_m: np.ndarray, encoding: str, min_range_m: float = 0.0) -> np.ndarray:
    """The env's depth image (0 = no return) as a ROS depth driver sends it in ``encoding``: in
    ``32FC1`` a pixel without a return is +Inf, nothing within range (REP 117); ``16UC1`` keeps 0.
    A camera with a ``min_range_m`` also reads 0 for what is too near, REP 117's -Inf: its
    image cannot tell the two apart, so there a pixel without a return is NaN (unknown)."""
    if encoding != "32FC1":
        return depth_m
    hole = np.float32(np.inf if min_range_m <= 0 else np.nan)
    return np.where(depth_m > 0, depth_m, hole).astype(np.float32)


class SimRobot:
    """The world, its ROS 2 node and its own keys; :meth:`run` is the loop."""

    def __init__(self, session, args: argparse.Namespace):
        self.args = args
        cfg = load_preset(args.preset or DEFAULT_PRESET)
        # the camera without a preset's training noise: what `evaluate --protocol paper` sees, so a
        # lock-step drive repeats that path
        self.env = ExploreEnv(dataclasses.replace(cfg.env, world=args.world, speed_table="test",
                                                  start_index=None, max_episode_steps=10**9),
                              cfg.sensor.noise_free(), render_mode="depth_array")
        world_starts = len(self.env.world.starts)
        if not 1 <= args.start <= world_starts:
            raise CogexploreError(f"--start {args.start}: world {self.env.world.name!r} has starts 1..{world_starts}")
        self.start_index = args.start - 1
        self.period_s = cfg.env.control_period_s
        self.keys = RobotKeys(args.robot)
        self.node = Ros2Node(session, make_format(args.ros2_format, domain_id=args.domain_id), NODE_NAME,
                             namespace=args.namespace)
        ns = args.namespace
        self.image_pub = self.node.publisher(qualify(ns, args.image_topic), IMAGE, qos="sensor_data")
        self.odom_pub = self.node.publisher(qualify(ns, args.odom_topic), ODOMETRY, qos="default")
        self.status_pub = session.declare_publisher(self.keys.status)
        self.command: tuple[float, float, float] | None = None
        """The newest cmd_vel not yet taken (linear, angular, arrival): only the newest counts."""
        self.command_ready = threading.Condition()
        self.cmd_sub = self.node.subscriber(qualify(ns, args.cmd_vel_topic), TWIST, self.on_twist, qos="default")
        self.reset_requested = threading.Event()
        self.reset_sub = session.declare_subscriber(self.keys.reset, lambda _s: self.reset_requested.set())
        self.commands_taken = 0
        self.rejects = RejectCounter("cmd_vel message", log)
        self.episode = -1
        self.periods = 0

    # -- inputs (Zenoh threads) -------------------------------------------------------------
    def on_twist(self, payload: bytes) -> None:
        try:
            linear, angular = decode_twist(payload)
            if abs(linear) > MAX_TWIST_MPS or abs(angular) > MAX_TWIST_RPS:
                raise Ros2MessageError("range", f"twist ({linear} m/s, {angular} rad/s) beyond this robot's "
                                                f"{MAX_TWIST_MPS} m/s, {MAX_TWIST_RPS} rad/s")
        except Ros2MessageError as exc:
            self.rejects.reject(exc)
            return
        with self.command_ready:
            superseded = self.command is not None
            self.command = (linear, angular, time.monotonic())
            self.command_ready.notify()
        if superseded:
            self.rejects.reject(Ros2MessageError("superseded", "a newer cmd_vel came before it was taken "
                                                               "(only the newest is driven)"))

    def take_command(self, timeout_s: float) -> tuple[float, float, float] | None:
        """The newest command not yet taken, waiting up to ``timeout_s`` for one (None: none came)."""
        with self.command_ready:
            if self.command_ready.wait_for(lambda: self.command is not None, timeout_s):
                command, self.command = self.command, None
                self.commands_taken += 1
                return command
        return None

    # -- the episode ----------------------------------------------------------------------
    def reset(self) -> None:
        self.env.reset(seed=self.episode + 1, options={"start_index": self.start_index})
        self.episode += 1
        self.step = 0
        self.collision_cause: str | None = None
        self.twist = (0.0, 0.0)
        self.publish()

    def drive(self, linear: float, angular: float) -> None:
        """One control period at this command (the robot stands once collided), then the new image."""
        self.twist = (linear, angular)
        self.periods += 1  # a collided robot's periods count too: --max-periods ends the run all the same
        if self.collision_cause is None:
            _depth, _r, terminated, _t, info = self.env.step_twist(linear, angular)
            self.step += 1
            if terminated:
                self.collision_cause = info.get("collision_cause") or "depth"
                x, y, _ = self.env.robot.pose()
                log.warning("collision (%s) at step %d, (%.2f, %.2f)", self.collision_cause, self.step, x, y)
        self.publish()

    def publish(self) -> None:
        stamp = time.time_ns()
        x, y, yaw = self.env.robot.pose()
        linear, angular = self.twist if self.collision_cause is None else (0.0, 0.0)
        encoding = self.args.encoding
        depth = ros_depth(self.env.render(), encoding, self.env.sensor_config.min_range_m)
        self.image_pub.put(encode_depth_image(depth, encoding=encoding, stamp_ns=stamp))
        self.odom_pub.put(encode_odometry(x, y, yaw, linear, angular, stamp_ns=stamp))
        self.status_pub.put(SimRobotStatus(
            robot=self.args.robot, world=self.env.world.name, episode=self.episode, step=self.step, x=x, y=y,
            yaw=yaw, linear_mps=linear, angular_rps=angular, collided=self.collision_cause is not None,
            collision_cause=self.collision_cause, commands=self.commands_taken,
            rejects=self.command_rejects()).encode())

    def command_rejects(self) -> dict[str, int]:
        """cmd_vel messages refused so far by cause; those the subscription dropped for a newer one
        before they were even read are superseded too."""
        counts = self.rejects.counts
        if dropped := self.cmd_sub.dropped:
            counts["superseded"] = counts.get("superseded", 0) + dropped
        return counts

    def run(self, stop: threading.Event) -> None:
        self.reset()
        next_tick = time.monotonic() + self.period_s
        latest: tuple[float, float, float] | None = None
        while not stop.is_set():
            if self.args.max_periods is not None and self.periods >= self.args.max_periods:
                break
            if self.reset_requested.is_set():
                self.reset_requested.clear()
                self.reset()
            if self.args.lockstep:
                command = self.take_command(0.05)
                if command is None:
                    continue
                linear, angular, _t = command
                if (linear == 0.0 and angular == 0.0) and self.collision_cause is None:
                    self.publish()  # a stop: no time passes, the image again
                else:  # a collided robot's stops (all a driver sends it) count, so --max-periods ends the run
                    self.drive(linear, angular)
                continue
            latest = self.take_command(0.0) or latest  # real time: the newest command is held
            wait = next_tick - time.monotonic()
            if wait > 0:
                stop.wait(wait)
                continue
            next_tick += self.period_s
            if next_tick < time.monotonic():  # a stall: do not try to catch up
                next_tick = time.monotonic() + self.period_s
            fresh = latest is not None and time.monotonic() - latest[2] <= self.args.cmd_timeout
            self.drive(*(latest[:2] if fresh else (0.0, 0.0)))

    def close(self) -> None:
        for handle in (self.reset_sub, self.status_pub):  # the node closes its own topics
            handle.undeclare()
        self.node.close()
        self.env.close()


def run_sim_robot_command(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    stop = stop_event_on_signals()
    settings = ros2_settings(args)
    with open_service_session(settings, stop) as session:
        robot = SimRobot(session, args)
        log.info("sim-robot %s in %s from start %d (%s, %s, %s)", args.robot, robot.env.world.name, args.start,
                 args.ros2_format, args.encoding, "lock step" if args.lockstep else "real time")
        try:
            robot.run(stop)
        finally:
            robot.close()
    return 0
