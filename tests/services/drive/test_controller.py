"""The drive node's decisions and safety rules (services.drive.controller), on the shipped model
and real ROS 2 CDR images, without Zenoh: a clock is passed in, so the watchdog is exact."""

from __future__ import annotations

import numpy as np
import pytest
from shared.ros2.messages import IMAGE, TYPESTORE, encode_depth_image

from services.drive.controller import (
    BAD_DEPTH,
    FUTURE_STAMP,
    NO_VALID_DEPTH,
    POLICY_ERROR,
    READ_ERROR,
    STALE_STAMP,
    TOO_SMALL,
    DriveConfig,
    DriveConfigError,
    DriveController,
    Reading,
    Refusal,
)
from shared.config import SPEED_TABLES


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def controller(policy, **cfg) -> tuple[DriveController, Clock]:
    clock = Clock()
    policy.reset()
    return DriveController(policy, DriveConfig(**cfg), clock=clock), clock


def image(depth: np.ndarray, encoding: str = "32FC1", **kw) -> bytes:
    return encode_depth_image(depth, encoding=encoding, stamp_ns=1, **kw)


def other_image(encoding: str, height: int, width: int, step: int, data: bytes) -> bytes:
    """An Image the encoder would not write (another encoding, a short buffer), made with the library."""
    Image = TYPESTORE.types[IMAGE]
    Header = TYPESTORE.types["std_msgs/msg/Header"]
    Time = TYPESTORE.types["builtin_interfaces/msg/Time"]
    msg = Image(header=Header(stamp=Time(sec=0, nanosec=0), frame_id="cam"), height=height, width=width,
                encoding=encoding, is_bigendian=0, step=step, data=np.frombuffer(data, np.uint8))
    return bytes(TYPESTORE.serialize_cdr(msg, IMAGE))


def test_an_image_gives_the_policys_command_at_the_test_speeds(policy, start_image):
    drive, clock = controller(policy)
    decision = drive.on_image(image(start_image), clock.t)
    policy.reset()
    expected = policy.act(start_image)
    assert decision is not None and decision.command == expected and decision.stop_reason is None
    angular, linear = SPEED_TABLES["test"]
    assert (decision.linear_mps, decision.angular_rps) == (linear, angular[expected])
    assert len(decision.q_values) == 5 and int(np.argmax(decision.q_values)) == expected
    assert decision.nearest_depth_m == pytest.approx(float(start_image[start_image > 0].min()))
    assert decision.latency_ms is not None and decision.latency_ms >= 0


def test_the_same_image_at_another_resolution_and_in_millimetres_gives_the_same_command(policy, start_image):
    from shared.depth import resize_depth

    drive, clock = controller(policy, lockstep=True)
    a = drive.on_image(image(start_image), clock.t).command
    drive.reset()
    big = resize_depth(start_image, 120, 160)
    b = drive.on_image(image(big, "16UC1", row_padding_bytes=6), clock.t).command
    assert a == b


def test_one_command_per_control_period_and_every_image_in_lock_step(policy, start_image):
    drive, clock = controller(policy)
    assert drive.on_image(image(start_image), clock.t) is not None
    clock.t += 0.1
    assert drive.on_image(image(start_image), clock.t) is None  # not due: 0.1 s of 0.5
    clock.t += 0.4
    assert drive.on_image(image(start_image), clock.t) is not None
    fast, clock = controller(policy, lockstep=True)
    assert all(fast.on_image(image(start_image), clock.t) is not None for _ in range(5))


def test_an_obstacle_nearer_than_the_collision_distance_stops_the_robot_at_once(policy, start_image):
    drive, clock = controller(policy)
    assert drive.on_image(image(start_image), clock.t).command is not None
    near = start_image.copy()
    near[10:14, 18:22] = 0.5  # a post 0.5 m ahead (the task stops at 0.55 m)
    clock.t += 0.05  # even between two control periods
    decision = drive.on_image(image(near), clock.t)
    assert decision.is_stop and decision.stop_reason == "too_close"
    assert (decision.linear_mps, decision.angular_rps) == (0.0, 0.0)
    assert decision.nearest_depth_m == pytest.approx(0.5)


def test_minus_inf_is_an_obstacle_too_near_to_measure_not_a_bad_image(policy, start_image):
    # REP 117 (and REP 118 for depth images): -Inf is a detection too close to quantify. It was
    # refused as a "negative depth" (bad_depth), a camera fault in the diagnostics, not an obstacle.
    drive, clock = controller(policy)
    assert drive.on_image(image(start_image), clock.t).command is not None
    near = start_image.copy()
    near[10:14, 18:22] = -np.inf
    decision = drive.on_image(image(near), clock.t + 0.05)
    assert decision.is_stop and decision.stop_reason == "too_close" and decision.reject_cause is None
    assert decision.nearest_depth_m == 0.0 and drive.rejects == {}
    clock.t += 0.4  # a valid image: the watchdog does not fire on top of the stop
    assert drive.on_tick(clock.t) is None


@pytest.mark.parametrize("name, payload, cause", [
    ("garbage", b"\x00\x01\x00\x00 this is not an image", "garbage"),
    ("empty", b"", "garbage"),
    ("wrong encoding", other_image("rgb8", 30, 40, 120, bytes(3600)), "encoding"),
    ("truncated", other_image("32FC1", 30, 40, 160, bytes(1000)), "truncated"),
    ("another aspect ratio", None, BAD_DEPTH),
    ("negative depths", None, BAD_DEPTH),
    ("smaller than the network", None, TOO_SMALL),
    ("NaN-filled", None, NO_VALID_DEPTH),
    # A blinded or saturated camera that reads its maximum (or more) everywhere: the network sees
    # no return, as for NaN, so it is refused as NaN is (before, it was driven on).
    ("20 m everywhere", None, NO_VALID_DEPTH),
    ("saturated millimetres", None, NO_VALID_DEPTH),
    # Thousands of metres are millimetres in a float image (a 16-bit image converted without its
    # scale): refused as a bad image, whose message says so, not read as no return.
    ("5 km everywhere", None, BAD_DEPTH),
])
def test_a_bad_image_stops_the_robot_and_is_counted(policy, start_image, name, payload, cause):
    if payload is None:
        full = start_image.shape
        depth = {"another aspect ratio": np.full((40, 40), 2.0, np.float32),
                 "negative depths": np.where(start_image > 0, start_image, -0.5).astype(np.float32),
                 "smaller than the network": np.full((15, 20), 2.0, np.float32),
                 "NaN-filled": np.full(full, np.nan, np.float32),
                 "20 m everywhere": np.full(full, 20.0, np.float32),
                 "saturated millimetres": np.full(full, 65535, np.uint16),
                 "5 km everywhere": np.full(full, 5000.0, np.float32)}[name]
        payload = image(depth, "16UC1" if depth.dtype == np.uint16 else "32FC1")
    drive, clock = controller(policy)
    assert drive.on_image(image(start_image), clock.t).command is not None  # moving
    decision = drive.on_image(payload, clock.t + 0.01)
    assert decision is not None and decision.is_stop and decision.stop_reason == "reject"
    assert decision.reject_cause == cause and drive.rejects == {cause: 1}
    # standing still, a flood of them is counted but sends at most one stop per period
    assert drive.on_image(payload, clock.t + 0.02) is None and drive.rejects == {cause: 2}
    # and a good image afterwards drives again
    assert drive.on_image(image(start_image), clock.t + 0.6).command is not None


def test_the_watchdog_stops_the_robot_when_images_stop_and_repeats_each_period(policy, start_image):
    drive, clock = controller(policy, watchdog_s=0.5)
    assert drive.on_tick(clock.t + 0.49) is None
    first = drive.on_tick(clock.t + 0.5)
    assert first.is_stop and first.stop_reason == "no_image"  # nothing seen yet
    drive.on_image(image(start_image), clock.t + 1.0)
    assert drive.on_tick(clock.t + 1.49) is None
    stop = drive.on_tick(clock.t + 1.5)
    assert stop.stop_reason == "watchdog" and (stop.linear_mps, stop.angular_rps) == (0.0, 0.0)
    assert drive.on_tick(clock.t + 1.7) is None  # standing: reminded once per control period
    assert drive.on_tick(clock.t + 2.0).stop_reason == "watchdog"


def test_reset_forgets_the_previous_command_and_exit_always_stops(policy, start_image):
    drive, clock = controller(policy, lockstep=True)
    drive.on_image(image(start_image), clock.t)
    assert policy.previous_command is not None
    drive.reset()
    assert policy.previous_command is None
    stop = drive.exit_stop()
    assert stop.stop_reason == "exit" and (stop.linear_mps, stop.angular_rps) == (0.0, 0.0)
    # The exit stop is the last word: an image that arrives after it (waiting on the shell's lock
    # meanwhile) or a watchdog tick decides nothing.
    assert drive.on_image(image(start_image), clock.t + 1.0) is None and drive.on_tick(clock.t + 9.0) is None


def test_a_policy_that_fails_stops_the_robot_every_period_until_it_decides_again(policy, start_image):
    class Flaky:
        """The shipped policy, whose runtime fails while ``failing`` (a CUDA or onnxruntime error)."""

        def __init__(self) -> None:
            self.failing = False

        def __getattr__(self, name):
            return getattr(policy, name)

        def decide(self, depth_m):
            if self.failing:
                raise RuntimeError("CUDA error: an illegal memory access was encountered")
            return policy.decide(depth_m)

    flaky, clock = Flaky(), Clock()
    policy.reset()
    drive = DriveController(flaky, DriveConfig(watchdog_s=0.5), clock=clock)
    assert drive.on_image(image(start_image), clock.t).command is not None  # moving
    flaky.failing = True
    stop = drive.on_image(image(start_image), clock.t + 0.5)
    assert stop.is_stop and stop.reject_cause == POLICY_ERROR and "CUDA error" in stop.error
    # Images keep coming, so the watchdog never fires: the failure itself keeps the robot stopped.
    stops = [drive.on_image(image(start_image), clock.t + 0.5 + 0.1 * k) for k in range(1, 11)]
    assert [d is not None for d in stops].count(True) == 2 and all(d.is_stop for d in stops if d is not None)
    assert drive.rejects == {POLICY_ERROR: 11} and not drive.moving
    flaky.failing = False
    assert drive.on_image(image(start_image), clock.t + 2.0).command is not None


def test_an_image_whose_reading_fails_unexpectedly_stops_the_moving_robot(policy, start_image):
    # An error read() did not expect (out of memory on a large image) reached the shell, which
    # counted it and sent nothing: the robot drove on its last command until the watchdog.
    class Starved:
        def __init__(self) -> None:
            self.failing = False

        def __getattr__(self, name):
            return getattr(policy, name)

        def observation(self, depth_m):
            if self.failing:
                raise MemoryError("cannot allocate 512 MiB")
            return policy.observation(depth_m)

    starved, clock = Starved(), Clock()
    policy.reset()
    drive = DriveController(starved, DriveConfig(), clock=clock)
    assert drive.on_image(image(start_image), clock.t).command is not None and drive.moving
    starved.failing = True
    stop = drive.on_image(image(start_image), clock.t + 0.1)
    assert stop is not None and stop.is_stop and stop.reject_cause == READ_ERROR
    assert "MemoryError: cannot allocate" in stop.error and drive.rejects == {READ_ERROR: 1} and not drive.moving


def test_q_values_that_are_not_finite_stop_the_robot_as_a_policy_error(policy, start_image):
    # An ONNX model or a network run out of range gave NaN Q-values: the robot drove the argmax of
    # nothing, and the diagnostics message (finite numbers only) failed after the command was sent.
    class Broken:
        def __getattr__(self, name):
            return getattr(policy, name)

        def decide(self, depth_m):
            command, q = policy.decide(depth_m)
            return command, np.where(np.arange(len(q)) == 2, np.nan, q)

    clock = Clock()
    stop = DriveController(Broken(), DriveConfig(), clock=clock).on_image(image(start_image), clock.t)
    assert stop.is_stop and stop.reject_cause == POLICY_ERROR and "not finite" in stop.error and stop.q_values == ()
    from services.drive.service import printable_label

    assert printable_label("run\tA@1200\n") == "run?A@1200?" and printable_label("") == "unknown"
    assert printable_label("a\x00b" * 200) == ("a?b" * 67)[:200]


@pytest.mark.parametrize("field, value", [("speed_table", "fast"), ("watchdog_s", 0), ("watchdog_s", float("nan")),
                                          ("collision_distance_m", -1), ("control_period_s", 0),
                                          ("max_image_age_s", 0), ("max_image_age_s", float("inf"))])
def test_bad_settings_are_refused(field, value):
    with pytest.raises(DriveConfigError, match=field.split("_")[0]):
        DriveConfig(**{field: value})


def test_a_collision_distance_beyond_the_cameras_range_is_refused(policy, start_image):
    # It was taken, and every image then read "too close": the robot never moved, and the stops
    # were not even logged (only the diagnostics said why).
    for distance in (policy.sensor.max_range_m, policy.sensor.max_range_m + 1.0):
        with pytest.raises(DriveConfigError, match="camera range"):
            DriveController(policy, DriveConfig(collision_distance_m=distance))
    drive = DriveController(policy, DriveConfig(collision_distance_m=float(start_image[start_image > 0].min()) - 0.05))
    decision = drive.on_image(image(start_image))  # arrived now, on the controller's clock
    assert decision is not None and not decision.is_stop  # a distance within range: it drives


def test_a_command_decided_after_the_watchdog_period_is_a_stop(policy, start_image):
    # A policy that stalled (a GPU, a loaded CPU) came back with a command from an image older than
    # the watchdog allows; it was driven, after the watchdog had stopped the robot for that very image.
    class Stalling:
        def __init__(self, clock: Clock, stall_s: float) -> None:
            self.clock, self.stall_s = clock, stall_s

        def __getattr__(self, name):
            return getattr(policy, name)

        def decide(self, depth_m):
            self.clock.t += self.stall_s
            return policy.decide(depth_m)

    clock = Clock()
    policy.reset()
    stalling = Stalling(clock, 0.1)
    drive = DriveController(stalling, DriveConfig(watchdog_s=0.5), clock=clock)
    assert drive.on_image(image(start_image), clock.t).command is not None  # 0.1 s: in time
    stalling.stall_s = 0.6
    clock.t += 0.5  # the next control period
    stop = drive.on_image(image(start_image), clock.t)
    assert stop is not None and stop.is_stop and stop.stop_reason == "watchdog" and "0.60 s" in stop.error
    assert not drive.moving and drive.rejects == {}
    # in lock step the simulator waits for the command: no time passed for it
    clock = Clock()
    stalling.clock = clock
    lockstep = DriveController(stalling, DriveConfig(watchdog_s=0.5, lockstep=True), clock=clock)
    assert lockstep.on_image(image(start_image), clock.t).command is not None


def test_millimetres_in_a_float_image_stop_the_robot_and_say_why(policy, start_image):
    # The policy's camera refuses a float image of millimetres (cogexplore._policy_io); the stop
    # said only "bad_depth", and the log never told the operator to divide by 1000.
    drive, clock = controller(policy)
    assert drive.on_image(image(start_image), clock.t).command is not None  # moving
    millimetres = np.where(start_image > 0, start_image * 1000, 0).astype(np.float32)
    decision = drive.on_image(image(millimetres), clock.t + 0.6)
    assert decision.is_stop and decision.reject_cause == BAD_DEPTH and drive.rejects == {BAD_DEPTH: 1}
    assert "millimetres in a float image" in decision.error
    garbage = drive.on_image(b"\x00\x01\x00\x00junk", clock.t + 1.2)
    assert garbage.reject_cause == "garbage" and "not a CDR" in garbage.error


def test_with_a_max_image_age_an_image_stamped_too_long_ago_or_ahead_stops_the_robot(policy, start_image):
    """Arrival times say nothing of an image held up on the way (a Wi-Fi stall, a queue): with
    ``max_image_age_s`` its stamp is compared with this machine's clock, both ways, and an image
    never stamped is refused too. Without it, stamps are not read (the default: clocks may differ)."""
    now_ns = 1_800_000_000 * 10**9

    def stamped(age_s: float) -> bytes:
        return encode_depth_image(start_image, encoding="32FC1", stamp_ns=int(now_ns - age_s * 1e9))

    drive, clock = controller(policy, max_image_age_s=0.3)
    drive.wall_clock_ns = lambda: now_ns
    fresh = drive.on_image(stamped(0.2), clock.t)
    assert fresh is not None and fresh.command is not None
    refusals = ((stamped(0.5), STALE_STAMP, "taken 0.50 s ago (at most 0.3 s)"),
                (stamped(-2.0), FUTURE_STAMP, "2.00 s ahead of this machine's clock"),
                (image(start_image), STALE_STAMP, "taken"),  # stamp 1 ns: 57 years ago
                (encode_depth_image(start_image, encoding="32FC1", stamp_ns=0), STALE_STAMP, "has no stamp"))
    for payload, cause, words in refusals:
        clock.t += 1.0
        decision = drive.on_image(payload, clock.t)
        assert decision is not None and decision.stop_reason == "reject" and decision.reject_cause == cause
        assert words in decision.error
    assert drive.rejects == {STALE_STAMP: 3, FUTURE_STAMP: 1}
    unchecked, clock = controller(policy)
    assert unchecked.on_image(stamped(3600.0), clock.t).command is not None



def test_reading_an_image_changes_nothing_and_its_stamp_is_checked_again_when_it_is_decided(policy, start_image):
    """The shell reads an image (slow for a large one) outside its lock, then decides on it: the
    reading counts and decides nothing, and the stamp's age is measured again at the decision."""
    now_ns = 1_800_000_000 * 10**9
    drive, clock = controller(policy, max_image_age_s=0.3)
    drive.wall_clock_ns = lambda: now_ns
    fresh = encode_depth_image(start_image, encoding="32FC1", stamp_ns=now_ns - 200_000_000)
    refused = drive.read(b"junk")
    reading = drive.read(fresh)
    assert isinstance(refused, Refusal) and refused.cause == "garbage"
    assert isinstance(reading, Reading) and reading.nearest_m == pytest.approx(float(start_image[start_image > 0].min()))
    assert drive.rejects == {} and drive.decisions == 0 and drive.last_image_s is None
    assert drive.decide(refused, clock.t).reject_cause == "garbage"
    drive.wall_clock_ns = lambda: now_ns + 200_000_000  # the reading took 0.2 s: the image is 0.4 s old
    stale = drive.decide(reading, clock.t + 1.0)
    assert stale.reject_cause == STALE_STAMP and "0.40 s ago" in stale.error and drive.last_image_s is None
    drive.wall_clock_ns = lambda: now_ns
    assert drive.decide(reading, clock.t + 2.0).command is not None  # in time, it drives


@pytest.mark.parametrize("lockstep", [False, True])
def test_an_image_that_arrived_before_a_watchdog_stop_never_moves_the_robot_after_it(policy, start_image, lockstep):
    # The shell reads an image outside its lock, so the watchdog can stop the robot between the
    # image's arrival and its decision. The image arrived 0.05 s before the stop, well within the
    # watchdog of its own arrival, and its command undid the stop.
    drive, clock = controller(policy, watchdog_s=0.5, lockstep=lockstep)
    assert drive.on_image(image(start_image), clock.t).command is not None  # moving
    arrived = clock.t + 0.45
    reading = drive.read(image(start_image))
    clock.t += 0.5
    stop = drive.on_tick(clock.t)
    assert stop is not None and stop.stop_reason == "watchdog"
    clock.t += 0.01
    late = drive.decide(reading, arrived)
    assert late is None or late.is_stop
    assert not drive.moving
    # the next image, newer than the stop, drives again
    assert drive.on_image(image(start_image), clock.t + 0.5).command is not None
