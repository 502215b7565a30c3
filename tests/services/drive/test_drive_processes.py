"""``cogexplore drive`` and ``cogexplore sim-robot`` as separate processes around a real router, in both
ROS 2 wire formats: the robot explores (no collision over 200 control periods from a start the
protocol scores 200 at, on the same path as ``cogexplore evaluate``), and the drive node's safety
rules hold when this test plays the robot (zero twist on a watchdog, on garbage, at exit)."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from service_processes import cogexplore, stop, wait_for
from shared.ros2.formats import make_format, qualify
from shared.ros2.messages import IMAGE, TWIST, decode_twist, encode_depth_image, encode_twist
from services.bus.ros2 import Ros2Node

import cogexplore as api
from services.bus.session import ZenohSettings, free_tcp_port, open_session
from shared.sim.env import ExploreEnv
from shared.wire.keys import RobotKeys
from shared.wire.messages import decode_message
from shared.wire.robot import DriveDiagnostics, SimRobotStatus

PERIODS = 200
TOLERANCE_M = 0.03


@pytest.fixture(scope="module")
def reference():
    """The shipped model under the paper protocol on paper-indoor: the first start it drives 200
    steps from without a collision, and that episode's path."""
    policy = api.load_policy("pretrained", device="cpu")
    for start in range(12):
        results = api.evaluate(policy, "paper-indoor", episodes_per_start=1, max_steps=PERIODS, starts=[start],
                               protocol="paper")
        episode = results.episodes[0]
        if episode.steps == PERIODS and not episode.terminated:
            return start, np.asarray(episode.trajectory_xy)
    pytest.fail("the shipped model scores 200 from no start of paper-indoor")


@pytest.fixture
def router(tmp_path: Path):
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    log = tmp_path / "router.log"
    proc = cogexplore(["router", "--listen", endpoint], log)
    wait_for(lambda: "ready" in log.read_text(), 60, "the router", [log])
    yield endpoint
    stop(proc)


class Collector:
    """The latest messages of one cogexplore key, decoded, in arrival order."""

    def __init__(self, session, key: str):
        self.items: list = []
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample) -> None:
        with self.lock:
            self.items.append(decode_message(bytes(sample.payload)))

    def snapshot(self) -> list:
        with self.lock:
            return list(self.items)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("ros2_format, encoding, runtime", [("rmw_zenoh", "32FC1", "torch"),
                                                             ("ros2dds", "16UC1", "torch"),
                                                             ("rmw_zenoh", "16UC1", "onnx")])
def test_drive_explores_the_sim_robot_on_the_protocols_path(tmp_path, router, reference, ros2_format, encoding,
                                                             runtime):
    start_index, path = reference
    if runtime == "onnx":
        from shared.learning.onnx_export import export_onnx

        policy_args = ["--onnx", str(export_onnx(api.load_policy("pretrained", device="cpu").model,
                                                 tmp_path / "pretrained.onnx")), "--rrd", str(tmp_path / "drive.rrd"),
                       "--max-image-age", "5"]  # sim-robot's stamps are this machine's clock: none refused
    else:
        policy_args = ["--checkpoint", "pretrained", "--device", "cpu"]
    keys = RobotKeys("bot")
    common = ["--connect", router, "--ros2-format", ros2_format, "--robot", "bot", "--namespace", "/bot"]
    logs = [tmp_path / "sim.log", tmp_path / "drive.log"]
    with open_session(ZenohSettings(mode="client", connect=(router,))) as session:
        statuses = Collector(session, keys.status)
        diagnostics = Collector(session, keys.diagnostics)
        sim = cogexplore(["sim-robot", *common, "--world", "paper-indoor", "--start", str(start_index + 1),
                          "--lockstep", "--encoding", encoding, "--max-periods", str(PERIODS)], logs[0])
        drive = cogexplore(["drive", *common, *policy_args, "--lockstep"], logs[1])
        try:
            wait_for(lambda: any(s.step >= PERIODS or s.collided for s in statuses.snapshot()), 180,
                     f"{PERIODS} control periods", logs)
            assert sim.wait(30) == 0, logs[0].read_text()[-2000:]
        finally:
            stop(drive)
            stop(sim)
        assert drive.returncode == 0, logs[1].read_text()[-2000:]
        seen = [s for s in statuses.snapshot() if isinstance(s, SimRobotStatus)]
        assert not any(s.collided for s in seen), [s for s in seen if s.collided][:1]
        by_step = {s.step: (s.x, s.y) for s in seen}
        assert max(by_step) == PERIODS
        driven = np.asarray([by_step[k] for k in range(PERIODS + 1)])
        gap = np.linalg.norm(driven - path[:PERIODS + 1], axis=1)
        print(f"{ros2_format} {encoding} {runtime}: at most {gap.max() * 1000:.2f} mm from evaluate's path")
        assert gap.max() < TOLERANCE_M, f"{gap.max():.3f} m from evaluate's path at step {int(gap.argmax())}"
        moves = [d for d in diagnostics.snapshot() if isinstance(d, DriveDiagnostics) and d.command is not None]
        assert len(moves) >= PERIODS and all(not d.rejects for d in moves)
        assert "Traceback" not in logs[1].read_text() + logs[0].read_text()
        if runtime == "onnx":  # its Rerun recording: every decision's image, read back
            from rerun.chunk import RrdReader

            depth_rows = sum(chunk.num_rows for chunk in RrdReader(tmp_path / "drive.rrd").stream().to_chunks()
                             if chunk.entity_path == "/drive/depth")
            assert depth_rows >= PERIODS


@pytest.mark.timeout(180)
def test_drive_stops_the_robot_on_a_watchdog_on_garbage_and_at_exit(tmp_path, router):
    """This test is the robot: it sends images and listens to cmd_vel."""
    log = tmp_path / "drive.log"
    keys = RobotKeys("bot")
    drive = cogexplore(["drive", "--connect", router, "--robot", "bot", "--checkpoint", "pretrained",
                        "--device", "cpu", "--watchdog", "0.5"], log)
    twists: list[tuple[float, float, float]] = []
    got = threading.Condition()

    def on_twist(payload: bytes) -> None:
        with got:
            twists.append((time.monotonic(), *decode_twist(payload)))
            got.notify_all()

    def next_twist(after: float, timeout_s: float) -> tuple[float, float, float]:
        deadline = time.monotonic() + timeout_s
        with got:
            while True:
                later = [t for t in twists if t[0] > after]
                if later:
                    return later[0]
                if not got.wait(max(0.0, deadline - time.monotonic())):
                    pytest.fail(f"no twist within {timeout_s} s\n{log.read_text()[-2000:]}")

    env = ExploreEnv(world="paper-indoor", speed_table="test", start_index=0,
                     sensor=api.load_policy("pretrained", device="cpu").sensor)
    depth, _ = env.reset(seed=0)
    env.close()
    good = encode_depth_image(depth, encoding="16UC1", stamp_ns=1)
    with open_session(ZenohSettings(mode="client", connect=(router,))) as session:
        diagnostics = Collector(session, keys.diagnostics)
        node = Ros2Node(session, make_format("rmw_zenoh"), "test_robot")
        images = node.publisher(qualify("/", "camera/depth/image_raw"), IMAGE, qos="default")
        node.subscriber(qualify("/", "cmd_vel"), TWIST, on_twist, qos="default")
        try:
            # Until the policy is loaded it answers nothing but watchdog stops; then a move.
            deadline = time.monotonic() + 90
            while not any(d.command is not None for d in diagnostics.snapshot()):
                assert time.monotonic() < deadline and drive.poll() is None, log.read_text()[-2000:]
                images.put(good)
                time.sleep(0.6)
            # Images stop: a zero twist within the watchdog period (+ its 20 ms tick and the hop).
            last_image = time.monotonic()
            images.put(good)
            move = next_twist(last_image, 2.0)
            assert move[1] > 0  # moving
            t, linear, angular = next_twist(move[0], 2.0)
            assert (linear, angular) == (0.0, 0.0) and t - last_image < 0.5 + 0.15
            # Garbage while moving: a zero twist at once, counted, and the node lives on.
            time.sleep(0.5)  # a control period after the last command: the next image is due
            move = next_twist(time.monotonic(), 2.0)  # the watchdog's reminder, once per period while stale
            images.put(good)
            while move[1] == 0.0:
                move = next_twist(move[0], 2.0)
            sent = time.monotonic()
            images.put(b"\x00\x01\x00\x00garbage")
            t, linear, angular = next_twist(sent, 2.0)
            assert (linear, angular) == (0.0, 0.0) and t - sent < 0.2
            wait_for(lambda: any(d.rejects.get("garbage") for d in diagnostics.snapshot()), 5, "a counted reject", [log])
            assert drive.poll() is None
            # A reset request: the policy forgets its previous command.
            session.put(keys.reset, b"")
            wait_for(lambda: "reset: a new episode" in log.read_text(), 5, "the reset", [log])
            # SIGTERM: the last word is a zero twist, then a clean exit.
            before = time.monotonic()
            stop(drive, signal.SIGTERM)
            assert drive.returncode == 0, log.read_text()[-2000:]
            t, linear, angular = next_twist(before, 5.0)
            assert (linear, angular) == (0.0, 0.0)
            assert any(d.stop_reason == "exit" for d in diagnostics.snapshot())
        finally:
            stop(drive)
            node.close()


@pytest.mark.timeout(180)
def test_in_real_time_the_sim_robot_moves_at_the_control_period(tmp_path, router):
    keys = RobotKeys("rt")
    common = ["--connect", router, "--robot", "rt"]
    logs = [tmp_path / "sim.log", tmp_path / "drive.log"]
    with open_session(ZenohSettings(mode="client", connect=(router,))) as session:
        statuses = Collector(session, keys.status)
        drive = cogexplore(["drive", *common, "--checkpoint", "pretrained", "--device", "cpu"], logs[1])
        wait_for(lambda: "driving rt" in logs[1].read_text(), 90, "drive to load its policy", logs)
        sim = cogexplore(["sim-robot", *common, "--world", "paper-indoor", "--start", "1", "--encoding", "16UC1",
                          "--max-periods", "8"], logs[0])
        try:
            assert sim.wait(90) == 0, logs[0].read_text()[-2000:]
        finally:
            stop(sim)
            stop(drive)
        seen = [s for s in statuses.snapshot() if isinstance(s, SimRobotStatus) and s.step > 0]
        assert [s.step for s in seen] == list(range(1, 9))
        moving = [s for s in seen if s.linear_mps > 0]
        assert len(moving) >= 5  # the first period or two wait for drive's first command
        first, last = seen[0], seen[-1]
        assert np.hypot(last.x - first.x, last.y - first.y) > 0.3 and not any(s.collided for s in seen)


def test_a_payload_over_a_subscribers_limit_is_never_copied_out_and_is_reported_by_size(router):
    # The drive node's image subscription takes at most 64 MB; a bigger image used to be copied
    # out of Zenoh before the decoder refused it (a 400 MB one took 800 MB at its peak).
    payloads, oversize = [], []
    with open_session(ZenohSettings(mode="client", connect=(router,))) as session:
        node = Ros2Node(session, make_format("rmw_zenoh"), "limits")
        try:
            node.subscriber(qualify("/", "camera/depth/image_raw"), IMAGE, payloads.append, qos="default",
                            max_bytes=1000, on_oversize=oversize.append)
            images = node.publisher(qualify("/", "camera/depth/image_raw"), IMAGE, qos="default")
            deadline = time.monotonic() + 30
            while not payloads:  # the route is up when a 1-byte probe comes back (one key: in order after)
                assert time.monotonic() < deadline, "no route through the router"
                images.put(b"p")
                time.sleep(0.2)
            for size in (999, 1000, 1001, 2**20):
                images.put(bytes(size))

            def sized() -> list[int]:
                return [len(p) for p in payloads if len(p) > 1]  # the probes are 1 byte

            wait_for(lambda: len(sized()) >= 2 and len(oversize) >= 2, 10, "every payload", [])
            assert sized() == [999, 1000] and oversize == [1001, 2**20]
        finally:
            node.close()


@pytest.mark.timeout(120)
def test_the_sim_robot_ends_after_its_periods_even_when_it_has_collided(tmp_path, router):
    """This test is the driver: straight ahead at full speed into paper-indoor's walls, in lock step."""
    keys = RobotKeys("crash")
    log = tmp_path / "sim.log"
    with open_session(ZenohSettings(mode="client", connect=(router,))) as session:
        statuses = Collector(session, keys.status)
        node = Ros2Node(session, make_format("rmw_zenoh"), "crash_driver")
        cmd_vel = node.publisher(qualify("/", "cmd_vel"), TWIST, qos="default")
        sim = cogexplore(["sim-robot", "--connect", router, "--robot", "crash", "--lockstep", "--max-periods", "30"],
                         log)
        try:
            wait_for(lambda: statuses.snapshot(), 90, "the sim-robot's first status", [log])
            for _ in range(60):  # until it has hit a wall
                cmd_vel.put(encode_twist(0.5, 0.0))
                time.sleep(0.05)
                if any(s.collided for s in statuses.snapshot()):
                    break
            for _ in range(60):  # then stops, as the drive node sends before a wall: they count too
                cmd_vel.put(encode_twist(0.0, 0.0))
                time.sleep(0.05)
                if sim.poll() is not None:
                    break
            assert sim.wait(30) == 0, log.read_text()[-2000:]
        finally:
            stop(sim)
            node.close()
    seen = [s for s in statuses.snapshot() if isinstance(s, SimRobotStatus)]
    assert any(s.collided for s in seen) and max(s.step for s in seen) < 30  # it collided before its 30 periods
