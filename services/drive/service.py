"""``cogexplore drive``: the process shell around :class:`services.drive.controller.DriveController`.

It subscribes to the robot's depth image and publishes ``cmd_vel`` (``shared.ros2``: either wire
format), runs the watchdog every 20 ms, publishes a :class:`shared.wire.robot.DriveDiagnostics`
per decision on ``cogexplore/@robot/<robot>/diagnostics``, resets the policy on
``cogexplore/@robot/<robot>/reset``, and sends a zero twist on SIGINT/SIGTERM and whenever the
process is about to exit, before its session closes.

Images are decided on a thread of their own, the newest first: one waits while the policy decides,
and a newer one replaces it (a subscriber's callback that decided in place took its images in
order, so a node slower than its camera decided on ever older images). A policy that stalls holds neither the
watchdog nor the exit stop: they stop the robot without it.
"""

from __future__ import annotations

import argparse
import atexit
import logging
import threading
import time
from collections.abc import Callable
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
EXIT_WAIT_S = 0.5
"""The exit stop waits at most this long (or the watchdog period, if shorter) for a decision under
way; then it is sent without the controller."""
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
            control_period_s=args.control_period, lockstep=args.lockstep,
            max_image_age_s=args.max_image_age))
        self.lock = threading.Lock()
        """Held around the controller, a decision included."""
        self.send_lock = threading.RLock()
        """Held around each twist sent, so that nothing follows the exit stop (reentrant: the exit
        stop holds it around its ``_send``)."""
        self.recorder = recorder
        self.done = threading.Event()
        self.pending: tuple[bytes | int, float] | None = None
        """The newest image not yet decided (its size when it was refused unread), with its arrival."""
        self.pending_ready = threading.Condition()
        self.closing = False
        self.deciding_since: float | None = None
        """Arrival of the image being decided (None: no decision under way)."""
        self.last_stall_stop_s: float | None = None
        self.decide_errors = 0
        self.exit_sent = False
        self.sent = 0
        """Twists sent so far: each one's number in the diagnostics and the recording."""
        self.last_reset_log_s: float | None = None
        self.last_stop: tuple[str | None, str | None] | None = None
        """(reason, reject cause) of the last twist if it was a stop (its log line once, not each period)."""
        self.node = Ros2Node(session, make_format(args.ros2_format, domain_id=args.domain_id), NODE_NAME,
                             namespace=args.namespace)
        self.cmd_vel = self.node.publisher(qualify(args.namespace, args.cmd_vel_topic), TWIST, qos="default")
        self.diagnostics = session.declare_publisher(self.keys.diagnostics)
        self.image_sub = self.node.subscriber(qualify(args.namespace, args.image_topic), IMAGE, self.on_image,
                                              qos="sensor_data", max_bytes=self.controller.config.max_image_bytes,
                                              on_oversize=self.on_oversize_image)
        self.reset_sub = session.declare_subscriber(self.keys.reset, lambda _sample: self.reset())
        self.decider = threading.Thread(target=self._decide_images, name="drive-decide", daemon=True)
        self.decider.start()

    def on_image(self, payload: bytes | int) -> None:
        """Zenoh's thread: the image (its size when oversize) waits for the decider, in place of any older one."""
        with self.pending_ready:
            self.pending = (payload, time.monotonic())
            self.pending_ready.notify()

    def on_oversize_image(self, size: int) -> None:
        self.on_image(size)

    def _decide_images(self) -> None:
        while True:
            with self.pending_ready:
                while self.pending is None and not self.closing:
                    self.pending_ready.wait()
                if self.closing:
                    return
                (payload, received), self.pending = self.pending, None
            self.deciding_since = received
            try:
                # read outside the lock: it changes nothing, and a large image takes longer than the
                # watchdog to read, which would hold the watchdog's stop
                reading = payload if isinstance(payload, int) else self.controller.read(payload)
                with self.lock:  # an image that waited for it after the exit stop decides nothing (the controller's rule)
                    if self.last_stall_stop_s is not None:  # nor one that arrived before the watchdog's stall stop
                        self.controller.watchdog_stopped(self.last_stall_stop_s)
                    decision = (self.controller.on_oversize_image(reading, received) if isinstance(reading, int)
                                else self.controller.decide(reading, received))
                    if decision is not None:
                        self._send(decision)
            except Exception:  # noqa: BLE001 -- the next image is decided all the same; the watchdog stops meanwhile
                self.decide_errors += 1
                if self.decide_errors == 1:
                    log.exception("deciding on an image failed (later failures are counted, not logged)")
            finally:
                self.deciding_since = None

    def tick(self) -> None:
        if not self.lock.acquire(timeout=WATCHDOG_TICK_S):  # a decision under way
            self._stall_stop()
            return
        try:
            decision = self.controller.on_tick()
            if decision is not None:
                self._send(decision)
        finally:
            self.lock.release()

    def _stall_stop(self) -> None:
        """The watchdog while the policy is deciding: a zero twist, once per control period, when
        the image it decides on is older than the watchdog allows (the controller then refuses the
        command it comes back with); not in lock step, where the robot waits for the command."""
        since, now = self.deciding_since, time.monotonic()
        c = self.controller
        # in lock step the simulator waits for the command: a stop meanwhile would be taken for it
        if since is None or now - since < c.config.watchdog_s or c.config.lockstep:
            return
        if self.last_stall_stop_s is not None and now - self.last_stall_stop_s < c.period_s:
            return
        self.last_stall_stop_s = now
        self._send(Decision(0.0, 0.0, None, "watchdog",
                            error=f"the policy has been deciding on one image for {now - since:.1f} s"))

    def reset(self) -> None:
        with self.lock:
            self.controller.reset()
            now = time.monotonic()
            if self.last_reset_log_s is not None and now - self.last_reset_log_s < RESET_LOG_EVERY_S:
                return  # a flood of resets is not a flood of log lines
            self.last_reset_log_s = now
        log.info("reset: a new episode, no previous command")

    def stop_at_exit(self) -> None:
        """The last word: a zero twist, sent once, before the session closes; without the
        controller when a decision holds it for longer than :data:`EXIT_WAIT_S` or the watchdog (a
        stalled policy): not the watchdog alone, which may be longer than a container's grace period."""
        if not self.lock.acquire(timeout=min(self.controller.config.watchdog_s, EXIT_WAIT_S)):
            self._send(Decision(0.0, 0.0, None, "exit", error="the policy is still deciding"), last=True)
            return
        try:
            with self.send_lock:
                if not self.exit_sent:
                    self._send(self.controller.exit_stop(), last=True)
        finally:
            self.lock.release()

    def _send(self, decision: Decision, last: bool = False) -> None:
        """Publish ``decision``'s twist, then report it; with ``last`` (the exit stop) nothing is sent
        after it, once it is out, even when its report fails."""
        with self.send_lock:
            if self.exit_sent:
                return
            self.cmd_vel.put(encode_twist(decision.linear_mps, decision.angular_rps))
            # numbered here, not by the controller: the stall and exit stops sent without it took the
            # number of the decision before them (a move's, whose Q-values and image a recording showed
            # beside the stop at that number)
            self.sent += 1
            number = self.sent
            self.exit_sent = last
        self._report(decision, number)

    def _report(self, decision: Decision, number: int) -> None:
        """The log line, diagnostics and recording of a twist sent, the ``number``-th."""
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
            robot=self.args.robot, decision=number, command=decision.command, linear_mps=decision.linear_mps,
            angular_rps=decision.angular_rps, stop_reason=decision.stop_reason,
            nearest_depth_m=decision.nearest_depth_m, latency_ms=decision.latency_ms, q_values=decision.q_values,
            policy=printable_label(getattr(c.policy, "label", "")), rejects=dict(c.rejects))
        self.diagnostics.put(message.encode())
        if self.recorder is not None:
            self.recorder.log_decision(message, c.last_depth_m if decision.command is not None else None)

    def close(self) -> None:
        """Stop the robot (once), end the decider and close the node's topics; a second call does
        nothing. Each step is taken even when one before it fails (a recorder that raised on the
        exit stop left the topics declared), its failure logged in one line."""
        _close_step("the exit stop", self.stop_at_exit)
        with self.pending_ready:
            if self.closing:
                return
            self.closing = True
            self.pending_ready.notify()
        self.decider.join(timeout=1.0)  # a stalled policy's thread is a daemon: it does not hold the exit
        # the node closes its own topics
        _close_step("undeclaring the reset subscriber", self.reset_sub.undeclare)
        _close_step("undeclaring the diagnostics publisher", self.diagnostics.undeclare)
        _close_step("closing the node's topics", self.node.close)


def _close_step(what: str, step: Callable[[], object]) -> None:
    """One step of :meth:`DriveNode.close`: a failure is logged in one line, and the next step runs."""
    try:
        step()
    except Exception as exc:  # noqa: BLE001 -- whatever failed, the rest is still closed
        log.error("closing the drive node: %s failed (%s: %s); closing the rest", what, type(exc).__name__,
                  " ".join(str(exc).split()))


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
