"""The sim-robot under a flood of cmd_vel from anyone on its router (a real router on loopback, the
real MuJoCo world): it drives the newest command, not a backlog of stale ones, and counts the rest."""

from __future__ import annotations

import argparse
import threading
import time

from service_processes import client, wait_for

from services.bus.ros2 import Ros2Node
from services.sim_robot.options import add_sim_robot_arguments
from services.sim_robot.service import SimRobot
from shared.ros2.formats import make_format
from shared.ros2.messages import TWIST, encode_twist

FLOOD = 1500
"""More than the 1000 commands the robot once queued, dropping the newest beyond them."""
NEWEST = (0.0, -0.3)
MARKER = (0.0, 0.1)
"""Sent after the probes: once the robot holds it, no probe is left in flight (one key, in order)."""


def test_a_flood_of_commands_drives_the_newest_and_counts_the_rest(loopback_router: str) -> None:
    parser = argparse.ArgumentParser()
    add_sim_robot_arguments(parser)
    args = parser.parse_args(["--lockstep", "--connect", loopback_router])
    with client(loopback_router) as robot_session, client(loopback_router) as outsider_session:
        robot = SimRobot(robot_session, args)
        robot.reset()  # (its loop resets it again)
        stop = threading.Event()
        loop = threading.Thread(target=robot.run, args=(stop,), daemon=True)
        try:
            with Ros2Node(outsider_session, make_format(args.ros2_format), "outsider") as outsider:
                publisher = outsider.publisher("/cmd_vel", TWIST)
                deadline = time.monotonic() + 30.0
                while robot.cmd_sub.received == 0 and time.monotonic() < deadline:  # until matched
                    publisher.put(encode_twist(0.0, 0.0))
                    time.sleep(0.05)
                # the last of those in flight: a fixed wait counted too early on a loaded machine
                publisher.put(encode_twist(*MARKER))
                wait_for(lambda: robot.command is not None and robot.command[:2] == MARKER, 10, "the marker", [])
                sent = robot.cmd_sub.received + FLOOD + 1
                for _ in range(FLOOD):  # while the robot is busy elsewhere (its loop not yet started)
                    publisher.put(encode_twist(0.0, 0.3))
                publisher.put(encode_twist(*NEWEST))
                deadline = time.monotonic() + 10.0
                while robot.cmd_sub.received < sent and time.monotonic() < deadline:
                    time.sleep(0.01)
                assert robot.cmd_sub.received == sent
                # the subscription's thread hands the robot what it holds, the newest last
                wait_for(lambda: robot.command is not None and robot.command[:2] == NEWEST, 10, "the newest", [])
                loop.start()
                deadline = time.monotonic() + 3.0
                while robot.twist != NEWEST and time.monotonic() < deadline:
                    time.sleep(0.01)
                assert robot.twist == NEWEST, "the newest command was never driven"
                time.sleep(0.2)  # nothing stale left to drive after it
                assert robot.twist == NEWEST and robot.commands_taken == 1 and robot.periods == 1
            stop.set()
            loop.join(5.0)
            assert not loop.is_alive()
            rejects = robot.command_rejects()
            assert rejects == {"superseded": sent - 1}
        finally:
            stop.set()
            if loop.is_alive():
                loop.join(5.0)
            robot.close()
