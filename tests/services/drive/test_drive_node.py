"""The drive node's shell (services.drive.service.DriveNode) in this process, on a loopback router, with
the shipped model: how it copes with a flood of images and with a policy that stalls."""

from __future__ import annotations

import argparse
import contextlib
import logging
import threading
import time

import numpy as np
import pytest
from service_processes import client

from services.bus.ros2 import Ros2Node
from services.drive.options import add_drive_arguments
from services.drive.service import DriveNode
from shared.ros2.formats import make_format, qualify
from shared.ros2.messages import IMAGE, TWIST, decode_twist, encode_depth_image
from shared.wire.keys import RobotKeys
from shared.wire.robot import DriveDiagnostics


class Slow:
    """The shipped policy, whose every decision takes ``delay_s`` (a loaded CPU, a GPU stall)."""

    def __init__(self, policy, delay_s: float) -> None:
        self.policy = policy
        self.delay_s = delay_s
        self.decided = 0

    def __getattr__(self, name):
        return getattr(self.policy, name)

    def decide(self, depth_m):
        time.sleep(self.delay_s)
        self.decided += 1
        return self.policy.decide(depth_m)


def drive_args(endpoint: str, *extra: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_drive_arguments(p)
    return p.parse_args(["--connect", endpoint, "--robot", "bot", *extra])


class Robot:
    """This test as the robot: a depth image publisher and a cmd_vel listener."""

    def __init__(self, session) -> None:
        self.session = session
        self.node = Ros2Node(session, make_format("rmw_zenoh"), "test_robot")
        self.images = self.node.publisher(qualify("/", "camera/depth/image_raw"), IMAGE, qos="sensor_data")
        self.twists: list[tuple[float, float, float]] = []
        self.lock = threading.Lock()
        self.node.subscriber(qualify("/", "cmd_vel"), TWIST, self._on_twist)
        self.diagnostics: list[DriveDiagnostics] = []
        self.diagnostics_sub = session.declare_subscriber(
            RobotKeys("bot").diagnostics, lambda sample: self.diagnostics.append(
                DriveDiagnostics.decode(sample.payload.to_bytes())))

    def _on_twist(self, payload: bytes) -> None:
        with self.lock:
            self.twists.append((time.monotonic(), *decode_twist(payload)))

    def snapshot(self) -> list[tuple[float, float, float]]:
        with self.lock:
            return list(self.twists)


@contextlib.contextmanager
def driving(router: str, policy, *options: str, watchdog: bool = False, recorder=None):
    """This test as the robot and a drive node with ``options`` (and ``recorder``), on ``router``; with ``watchdog``,
    run_drive_command's loop too (the node's watchdog every 20 ms). Yields (robot, node, a function
    that stops that loop); all is stopped and closed on the way out (a node's close is idempotent)."""
    with client(router) as robot_session, client(router) as drive_session:
        robot = Robot(robot_session)
        node = DriveNode(drive_session, drive_args(router, *options), policy, recorder)
        ticking = threading.Event()

        def watch() -> None:
            while not ticking.is_set():
                node.tick()
                ticking.wait(0.02)

        ticker = threading.Thread(target=watch, daemon=True)
        if watchdog:
            ticker.start()

        def stop_watchdog() -> None:
            ticking.set()
            if ticker.is_alive():
                ticker.join()

        try:
            yield robot, node, stop_watchdog
        finally:
            stop_watchdog()
            node.close()
            robot.diagnostics_sub.undeclare()
            robot.node.close()


def wait_for_twist(robot: Robot, image: bytes, moving: bool = False) -> None:
    """Send ``image`` until a twist (a moving one) comes back: the routes take a moment across the router."""
    deadline = time.monotonic() + 30
    while not any(linear > 0 or not moving for _, linear, _ in robot.snapshot()):
        assert time.monotonic() < deadline, "no move" if moving else "no twist"
        robot.images.put(image)
        time.sleep(0.1)


def stall_on_next_image(robot: Robot, slow: Slow, image: bytes, delay_s: float) -> float:
    """The policy takes ``delay_s`` on the next image, sent once due; when it was sent."""
    slow.delay_s = delay_s
    time.sleep(0.6)  # the next image is due
    sent = time.monotonic()
    robot.images.put(image)
    return sent


@pytest.mark.timeout(120)
def test_a_flood_of_images_never_queues_and_commands_come_from_the_newest(loopback_router, policy, start_image):
    # Zenoh hands samples to a Python callback in order, through a queue: a node slower than its
    # camera decided on ever older images (9 s old after 500 of them), and measured its latency from
    # the moment each left the queue, so the diagnostics said nothing of it.
    slow = Slow(policy, 0.05)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, slow, "--lockstep", "--watchdog", "30") as (robot, _node, _stop):
        wait_for_twist(robot, good)
        time.sleep(0.5)
        before = slow.decided
        for _ in range(200):  # 200 images in about 0.2 s, each a 50 ms decision in lock step
            robot.images.put(good)
            time.sleep(0.001)
        flood_end = time.monotonic()
        time.sleep(2.0)
        decided = slow.decided - before
        assert decided < 60, f"{decided} of 200 flooded images were decided one after the other"
        last = robot.snapshot()[-1][0]
        assert last - flood_end < 1.0, f"the last command came {last - flood_end:.1f} s after the last image"


@pytest.mark.timeout(120)
def test_a_stalled_policy_holds_neither_the_watchdog_nor_the_exit_stop(loopback_router, policy, start_image):
    # The watchdog and the exit stop waited for the lock the decision held: a policy that stalled
    # for 3 s kept the robot on its last command for 3 s, then drove the 3 s old image's command,
    # and SIGTERM during a stall sent its stop only when the policy came back.
    slow = Slow(policy, 0.0)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, slow, "--watchdog", "0.5", watchdog=True) as (robot, node, stop_watchdog):
        wait_for_twist(robot, good, moving=True)
        sent = stall_on_next_image(robot, slow, good, 3.0)
        time.sleep(3.5)
        after = [(t - sent, linear, angular) for t, linear, angular in robot.snapshot() if t > sent]
        assert after and after[0][0] < 0.5 + 1.0, f"first twist {after[:1]} after the stalled image"
        assert all((linear, angular) == (0.0, 0.0) for _, linear, angular in after), after
        # and at exit, while the policy stalls again
        slow.delay_s = 5.0
        time.sleep(0.6)
        robot.images.put(good)
        time.sleep(0.3)
        closing = time.monotonic()
        stop_watchdog()
        node.close()
        assert time.monotonic() - closing < 2.5, "close waited for the stalled policy"
        time.sleep(0.3)
        after = [(linear, angular) for t, linear, angular in robot.snapshot() if t > closing]
        assert after and after[-1] == (0.0, 0.0), after


@pytest.mark.timeout(120)
def test_a_huge_image_being_read_does_not_hold_the_watchdogs_stop(loopback_router, policy, start_image):
    # A 4000 x 3000 32FC1 image (46 MB, under the 64 MB limit) was decoded and checked under the
    # lock the watchdog takes: the watchdog's stop waited for it, and the stall stop counted from the
    # huge image's arrival, so the robot drove on its last command 0.85 s after the last valid image
    # with a 0.5 s watchdog.
    huge = encode_depth_image(np.full((3000, 4000), 2.0, np.float32), encoding="32FC1", stamp_ns=1)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, policy, "--watchdog", "0.5", watchdog=True) as (robot, _node, _stop):
        wait_for_twist(robot, good, moving=True)
        time.sleep(0.6)  # the next command is due
        last_good = time.monotonic()
        robot.images.put(good)
        time.sleep(0.25)
        robot.images.put(huge)  # then nothing
        time.sleep(2.0)
        after = [(t - last_good, linear, angular) for t, linear, angular in robot.snapshot() if t > last_good]
        assert after and after[0][1] > 0, f"the last valid image did not move the robot: {after[:1]}"
        stops = [t for t, linear, angular in after if (linear, angular) == (0.0, 0.0)]
        assert stops and stops[0] < 0.5 + 0.2, f"the stop came {stops[:1]} s after the last valid image"


@pytest.mark.timeout(120)
def test_in_lock_step_a_slow_decision_is_waited_for_not_stopped(loopback_router, policy, start_image):
    # The simulator waits for each command in lock step: a stall stop sent while the policy decided
    # (a slow first forward pass on a loaded machine) was taken for that period's command.
    slow = Slow(policy, 0.0)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, slow, "--lockstep", "--watchdog", "0.6", watchdog=True) as (robot, _node, _stop):
        wait_for_twist(robot, good)
        slow.delay_s = 1.5  # at once: no image for the watchdog period would be a stop of its own
        sent = time.monotonic()
        robot.images.put(good)
        time.sleep(2.0)
        after = [(linear, angular) for t, linear, angular in robot.snapshot() if t > sent]
        assert after and after[0] != (0.0, 0.0), f"the period's first twist {after[:1]} was a stop"


@pytest.mark.timeout(60)
def test_a_node_closed_twice_stops_the_robot_once_and_the_second_close_does_nothing(loopback_router, policy,
                                                                                     start_image):
    # The second close undeclared topics already undeclared: an error on the way out of a caller's
    # cleanup (a `with` and a `finally` both closing) that hid the first one's.
    with driving(loopback_router, policy) as (robot, node, _stop):
        wait_for_twist(robot, encode_depth_image(start_image, encoding="32FC1", stamp_ns=1))
        node.close()
        time.sleep(0.3)
        stops = robot.snapshot()
        assert stops[-1][1:] == (0.0, 0.0)
        node.close()
        time.sleep(0.3)
        assert robot.snapshot() == stops


@pytest.mark.timeout(120)
def test_an_image_that_arrived_before_a_stall_stop_never_moves_the_robot_after_it(loopback_router, policy,
                                                                                   start_image):
    # The policy stalled on one image; the next one arrived, waited, and the watchdog stopped the
    # robot meanwhile (the stall stop). That waiting image was decided within the watchdog of its own
    # arrival, and its command undid the stop.
    class StallOnce(Slow):
        def decide(self, depth_m):
            self.delay_s, delay_s = 0.0, self.delay_s
            time.sleep(delay_s)
            return self.policy.decide(depth_m)

    stalling = StallOnce(policy, 0.0)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, stalling, "--watchdog", "2", watchdog=True) as (robot, _node, _stop):
        wait_for_twist(robot, good, moving=True)
        time.sleep(0.6)  # the next command is due
        stalling.delay_s = 3.2
        sent = time.monotonic()
        robot.images.put(good)  # decided for 3.2 s: the stall stop comes 2 s after it arrived
        time.sleep(1.6)
        robot.images.put(good)  # waits for it, and is 1.6 s old when it is decided
        time.sleep(3.5)
        after = [(round(t - sent, 2), linear, angular) for t, linear, angular in robot.snapshot() if t > sent]
        assert after and all((linear, angular) == (0.0, 0.0) for _, linear, angular in after), after


@pytest.mark.timeout(120)
def test_a_stop_sent_while_the_policy_stalls_is_a_decision_of_its_own(loopback_router, policy, start_image):
    # The stall stop (and the exit stop sent without the controller) reported the number of the
    # decision before it: the recording's decision timeline put the stop at the move's index, over the
    # move's command and beside its Q-values and image, as if the stop had been decided on them.
    slow = Slow(policy, 0.0)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, slow, "--watchdog", "0.5", watchdog=True) as (robot, node, stop_watchdog):
        wait_for_twist(robot, good, moving=True)
        stall_on_next_image(robot, slow, good, 2.0)
        time.sleep(1.5)  # the stall stops meanwhile
        stop_watchdog()
        node.close()  # the exit stop, while the policy still stalls
        deadline = time.monotonic() + 10
        while not any(d.stop_reason == "exit" for d in robot.diagnostics):
            assert time.monotonic() < deadline, "no exit stop in the diagnostics"
            time.sleep(0.05)
        numbers = [d.decision for d in robot.diagnostics]
        assert any(d.stop_reason == "watchdog" for d in robot.diagnostics)
        assert len(set(numbers)) == len(numbers), [(d.decision, d.command, d.stop_reason) for d in robot.diagnostics]


@pytest.mark.timeout(120)
def test_with_a_long_watchdog_the_exit_stop_does_not_wait_for_a_stalled_policy(loopback_router, policy, start_image):
    # The exit stop waited up to the watchdog period for the decision's lock: with --watchdog 30 and
    # a policy stalled on its GPU, SIGTERM left the robot on its last command for 30 s (a container
    # stop kills after 10 s: no stop at all).
    slow = Slow(policy, 0.0)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, slow, "--watchdog", "30") as (robot, node, _stop):
        wait_for_twist(robot, good, moving=True)
        stall_on_next_image(robot, slow, good, 8.0)
        time.sleep(0.5)  # the policy is deciding on it
        closing = time.monotonic()
        node.close()
        deadline = time.monotonic() + 10
        while not any(t > closing and (linear, angular) == (0.0, 0.0) for t, linear, angular in robot.snapshot()):
            assert time.monotonic() < deadline, "no exit stop"
            time.sleep(0.05)
        stop_s = min(t for t, linear, angular in robot.snapshot() if t > closing) - closing
        assert stop_s < 2.0, f"the exit stop came {stop_s:.1f} s after close"


class FailingRecorder:
    """A recorder whose disk is full by the time the exit stop is recorded."""

    def log_decision(self, diagnostics, depth_m) -> None:
        if diagnostics.stop_reason == "exit":
            raise OSError(28, "No space left on device")


class CountingResets(Slow):
    """The shipped policy, counting its resets (the node's reset subscription calls it)."""

    resets = 0

    def reset(self) -> None:
        self.resets += 1
        self.policy.reset()


@pytest.mark.timeout(60)
def test_a_recorder_that_fails_on_the_exit_stop_leaves_no_cleanup_step_undone(loopback_router, policy, start_image,
                                                                              caplog):
    # The recorder raised inside the exit stop close() sends: the zero twist had gone out, but close()
    # stopped there, leaving the decider running and the reset subscription, the diagnostics publisher
    # and the node's topics and liveliness token declared on the session.
    counting = CountingResets(policy, 0.0)
    good = encode_depth_image(start_image, encoding="32FC1", stamp_ns=1)
    with driving(loopback_router, counting, recorder=FailingRecorder()) as (robot, node, _stop):
        wait_for_twist(robot, good, moving=True)
        reset_key = RobotKeys("bot").reset
        deadline = time.monotonic() + 10
        while not counting.resets:  # the reset subscription works before close
            assert time.monotonic() < deadline, "no reset"
            robot.session.put(reset_key, b"")
            time.sleep(0.1)
        token = node.node.token_key
        assert [r.ok for r in robot.session.liveliness().get(token, timeout=2.0)]
        closing = time.monotonic()
        with caplog.at_level(logging.ERROR, logger="cogexplore.drive"):
            node.close()
        deadline = time.monotonic() + 10
        while not any(t > closing and (linear, angular) == (0.0, 0.0) for t, linear, angular in robot.snapshot()):
            assert time.monotonic() < deadline, "no exit stop"
            time.sleep(0.05)
        failures = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(failures) == 1 and "No space left on device" in failures[0].getMessage(), caplog.text
        assert "\n" not in failures[0].getMessage() and failures[0].exc_info is None
        assert not node.decider.is_alive()
        # the node's topics are closed: its token's undeclaration reaches the router a moment after close()
        # returns (a query at once found it there 2 times in 10), so it is watched for, not read once
        deadline = time.monotonic() + 10
        while [r.ok for r in robot.session.liveliness().get(token, timeout=2.0)]:
            assert time.monotonic() < deadline, "the node's liveliness token outlived its close"
            time.sleep(0.1)
        resets = counting.resets
        robot.session.put(reset_key, b"")
        time.sleep(0.5)
        assert counting.resets == resets  # and so is its reset subscription
        twists = robot.snapshot()
        node.stop_at_exit()  # at exit, the stop is not sent again
        node.close()
        time.sleep(0.3)
        assert robot.snapshot() == twists
