"""``cogexplore drive``: the process shell around :class:`services.drive.controller.DriveController`.

It subscribes to the robot's depth image and publishes ``cmd_vel`` (``shared.ros2``: either wire
format), runs the watchdog every 20 ms, publishes a :class:`shared.wire.robot.DriveDiagnostics`
per decision on ``cogexplore/@robot/<robot>/diagnostics``, resets the policy on
``cogexplore/@robot/<robot>/reset``, and sends a zero twist on SIGINT/SIGTERM and whenever the
process is about to exit, before its session closes.
"""

from __future__ import annotations

import argparse
import atexit
import logging
import threading
import time
from typing import Any

import zenoh

from services.bus.ros2 import Ros2Node, ros2_settings
from services.bus.session import open_service_session
from services.drive.controller import Decision, DriveConfig, DriveController
from services.process import setup_logging, stop_event_on_signals
from shared.config import EnvConfig
from shared.ros2.formats import make_format, qualify
from shared.ros2.messages import IMAGE, TWIST, encode_twist
from shared.wire.keys import RobotKeys
from shared.wire.robot import DriveDiagnostics

log = logging.getLogger("cogexplore.drive")
WATCHDOG_TICK_S = 0.02
RESET_LOG_EVERY_S = 1.0
"""At most one reset log line per this many seconds."""
NODE_NAME = "cogexplore_drive"


def printable_label(label: Any, max_chars: int = 200) -> str:
    """A policy's label as the diagnostics carry it: printable, at most ``max_chars``, never empty (a
    file name with a tab or a newline in it failed every diagnostics message, after its command)."""
    text = "".join(ch if ch.isprintable() else "?" for ch in str(label or ""))[:max_chars]
    return text or "unknown"


def load_drive_policy(args: argparse.Namespace) -> Any:
    """The policy: an ONNX file (onnxruntime) or any checkpoint ``cogexplore.load_policy`` takes."""
    if args.onnx:
        from cogexplore.onnx_runner import load_onnx_policy

        return load_onnx_policy(args.onnx)
    from cogexplore.policy import load_policy

    return load_policy(args.checkpoint, device=args.device)


class DriveNode:
    """The drive node on an open session: subscriptions in, twists and diagnostics out."""

    def __init__(self, session: zenoh.Session, args: argparse.Namespace, policy: Any, recorder: Any = None):
        self.args = args
        self.keys = RobotKeys(args.robot)
        self.controller = DriveController(policy, DriveConfig(
            speed_table=args.speed_table, watchdog_s=args.watchdog,
            collision_distance_m=(EnvConfig().collision_distance_m if args.collision_distance is None
                                  else args.collision_distance),
            control_period_s=args.control_period, lockstep=args.lockstep))
        self.lock = threading.Lock()
        self.recorder = recorder
        self.done = threading.Event()
        self.node = Ros2Node(session, make_format(args.ros2_format, domain_id=args.domain_id), NODE_NAME,
                             namespace=args.namespace)
        self.cmd_vel = self.node.publisher(qualify(args.namespace, args.cmd_vel_topic), TWIST, qos="default")
        self.diagnostics = session.declare_publisher(self.keys.diagnostics)
        self.image_sub = self.node.subscriber(qualify(args.namespace, args.image_topic), IMAGE, self.on_image,
                                              qos="sensor_data", max_bytes=self.controller.config.max_image_bytes,
                                              on_oversize=self.on_oversize_image)
        self.reset_sub = session.declare_subscriber(self.keys.reset, lambda _sample: self.reset())
        self.exit_sent = False
        self.last_reset_log_s: float | None = None
        self.last_stop: tuple[str | None, str | None] | None = None
        """(reason, reject cause) of the last twist if it was a stop (its log line once, not each period)."""

    def on_image(self, payload: bytes) -> None:
        received = time.monotonic()
        with self.lock:  # an image that waited for it after the exit stop decides nothing (the controller's rule)
            decision = self.controller.on_image(payload, received)
            if decision is not None:
                self._send(decision)

    def on_oversize_image(self, size: int) -> None:
        received = time.monotonic()
        with self.lock:
            decision = self.controller.on_oversize_image(size, received)
            if decision is not None:
                self._send(decision)

    def tick(self) -> None:
        with self.lock:
            decision = self.controller.on_tick()
            if decision is not None:
                self._send(decision)

    def reset(self) -> None:
        with self.lock:
            self.controller.reset()
            now = time.monotonic()
            if self.last_reset_log_s is not None and now - self.last_reset_log_s < RESET_LOG_EVERY_S:
                return  # a flood of resets is not a flood of log lines
            self.last_reset_log_s = now
        log.info("reset: a new episode, no previous command")

    def stop_at_exit(self) -> None:
        """The last word: a zero twist, sent once, before the session closes."""
        with self.lock:
            if not self.exit_sent:
                self.exit_sent = True
                self._send(self.controller.exit_stop())

    def _send(self, decision: Decision) -> None:
        self.cmd_vel.put(encode_twist(decision.linear_mps, decision.angular_rps))
        c = self.controller
        if self.args.max_decisions is not None and c.decisions >= self.args.max_decisions:
            self.done.set()
        stop = None if not decision.is_stop else (decision.stop_reason, decision.reject_cause)
        if stop is not None and decision.stop_reason != "too_close":
            # A warning when the reason changes; the reminder each control period while it stands, at debug.
            level = logging.INFO if decision.stop_reason == "exit" else logging.WARNING
            log.log(level if stop != self.last_stop else logging.DEBUG, "stop: %s%s%s", decision.stop_reason,
                    f" ({decision.reject_cause})" if decision.reject_cause else "",
                    f": {decision.error}" if decision.error else "")
        self.last_stop = stop
        message = DriveDiagnostics(
            robot=self.args.robot, decision=c.decisions, command=decision.command, linear_mps=decision.linear_mps,
            angular_rps=decision.angular_rps, stop_reason=decision.stop_reason,
            nearest_depth_m=decision.nearest_depth_m, latency_ms=decision.latency_ms, q_values=decision.q_values,
            policy=printable_label(getattr(c.policy, "label", "")), rejects=dict(c.rejects))
        self.diagnostics.put(message.encode())
        if self.recorder is not None:
            self.recorder.log_decision(message, c.last_depth_m if decision.command is not None else None)

    def close(self) -> None:
        self.stop_at_exit()
        for handle in (self.reset_sub, self.diagnostics):  # the node closes its own topics
            handle.undeclare()
        self.node.close()


def run_drive_command(args: argparse.Namespace) -> int:
    setup_logging(args.log_level)
    policy = load_drive_policy(args)
    recorder = None
    if args.rerun_connect or args.rrd:
        from services.viz.rerun import DriveRecorder

        recorder = DriveRecorder(args.rrd, connect_url=args.rerun_connect, robot=args.robot)
    stop = stop_event_on_signals()
    settings = ros2_settings(args)
    try:
        with open_service_session(settings, stop) as session:
            node = DriveNode(session, args, policy, recorder)
            atexit.register(node.stop_at_exit)  # an exception on the way out still stops the robot
            log.info("driving %s with %s (%s, %s speeds, watchdog %.2f s) on %s", args.robot, policy.label,
                     args.ros2_format, args.speed_table, args.watchdog, settings.describe())
            try:
                while not stop.is_set() and not node.done.is_set():
                    node.tick()
                    stop.wait(WATCHDOG_TICK_S)
            finally:
                node.close()
                atexit.unregister(node.stop_at_exit)
    finally:
        if recorder is not None:
            recorder.close()
    return 0
