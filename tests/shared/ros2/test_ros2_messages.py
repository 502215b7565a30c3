"""CDR of the ROS 2 messages: our bytes against rosbags' own decoding, hand-checked bytes,
round trips, and every reject cause."""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from shared.depth import depth_from_mm, depth_to_mm
from shared.ros2.messages import (
    CAUSES,
    IMAGE,
    ODOMETRY,
    TWIST,
    TYPESTORE,
    Ros2MessageError,
    Ros2TypeError,
    dds_type_name,
    decode_depth_image,
    decode_odometry,
    decode_twist,
    encode_depth_image,
    encode_image,
    encode_odometry,
    encode_twist,
    type_hash,
)
from shared.wire.messages import MessageError, RejectCounter

CDR_LE = bytes.fromhex("00010000")  # encapsulation: CDR, little endian, options 0

# Documented type hashes:
# - std_msgs/msg/String: ros2/rmw_zenoh docs/design.md, the `chatter` key expression examples.
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
# - geometry_msgs/msg/Twist: `ros2 topic info /turtle1/cmd_vel -v` on Jazzy, as captured in
#   kagenokeiyou/ros-notes start/03-topic/01-introduction.md ("Topic type hash").
TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"

STAMP_NS = 1_712_345_678_901_234_567


def depth_image(height: int = 3, width: int = 4) -> np.ndarray:
    rng = np.random.default_rng(height * 100 + width)
    return rng.uniform(0.2, 6.0, size=(height, width)).astype(np.float32)


def reject_cause(payload: bytes, **kwargs: int) -> str:
    with pytest.raises(Ros2MessageError) as info:
        decode_depth_image(payload, **kwargs)
    return info.value.cause


# --- names and hashes --------------------------------------------------------------------------

def test_type_hashes_match_the_documented_ones() -> None:
    assert type_hash("std_msgs/msg/String") == STRING_HASH
    assert type_hash(TWIST) == TWIST_HASH
    assert type_hash(IMAGE).startswith("RIHS01_") and len(type_hash(IMAGE)) == 7 + 64


def test_the_three_types_hash_alike_in_later_distributions() -> None:
    for store in (Stores.ROS2_KILTED, Stores.ROS2_LYRICAL):
        assert [get_typestore(store).hash_rihs01(t) for t in (IMAGE, TWIST, ODOMETRY)] == [
            type_hash(t) for t in (IMAGE, TWIST, ODOMETRY)]


def test_dds_type_names_are_mangled_as_rmw_zenoh_does() -> None:
    assert dds_type_name(IMAGE) == "sensor_msgs::msg::dds_::Image_"
    assert dds_type_name(TWIST) == "geometry_msgs::msg::dds_::Twist_"
    assert dds_type_name(ODOMETRY) == "nav_msgs::msg::dds_::Odometry_"


@pytest.mark.parametrize("msgtype", ["Twist", "geometry_msgs/Twist", "a/b/c/d", "geometry_msgs/msg/"])
def test_malformed_type_names_are_refused(msgtype: str) -> None:
    with pytest.raises(Ros2TypeError, match="malformed"):
        dds_type_name(msgtype)


def test_unknown_types_are_refused() -> None:
    with pytest.raises(Ros2TypeError, match="unknown"):
        type_hash("cogexplore_msgs/msg/Nothing")


# --- Twist -------------------------------------------------------------------------------------

def test_twist_bytes_by_hand() -> None:
    # header, then linear (x, y, z) and angular (x, y, z): six little-endian float64, no padding
    expected = CDR_LE + bytes.fromhex(
        "000000000000d03f" "0000000000000000" "0000000000000000"   # linear: 0.25, 0, 0
        "0000000000000000" "0000000000000000" "000000000000e0bf")  # angular: 0, 0, -0.5
    assert encode_twist(0.25, -0.5) == expected
    assert expected == CDR_LE + struct.pack("<6d", 0.25, 0, 0, 0, 0, -0.5)
    assert decode_twist(expected) == (0.25, -0.5)
    twist = TYPESTORE.deserialize_cdr(expected, TWIST)
    assert (twist.linear.x, twist.angular.z) == (0.25, -0.5)


def test_twist_rejects() -> None:
    with pytest.raises(Ros2MessageError) as info:
        decode_twist(b"\x00\x01\x00\x00 not a twist")
    assert info.value.cause == "garbage"
    with pytest.raises(Ros2MessageError) as info:
        decode_twist(CDR_LE + struct.pack("<6d", 0.1, float("nan"), 0, 0, 0, 0))
    assert info.value.cause == "non_finite"
    with pytest.raises(Ros2MessageError) as info:
        encode_twist(float("inf"), 0.0)  # a robot never gets NaN or infinity from us
    assert info.value.cause == "non_finite"


# --- Image -------------------------------------------------------------------------------------

def test_image_fields_as_the_library_decodes_them() -> None:
    depth = depth_image(3, 4)
    payload = encode_depth_image(depth, encoding="16UC1", stamp_ns=STAMP_NS, frame_id="kinect_depth",
                                 row_padding_bytes=6)
    assert payload[:4] == CDR_LE
    image = TYPESTORE.deserialize_cdr(payload, IMAGE)
    assert (image.header.stamp.sec, image.header.stamp.nanosec) == (1_712_345_678, 901_234_567)
    assert image.header.frame_id == "kinect_depth"
    assert (image.height, image.width, image.encoding, image.is_bigendian) == (3, 4, "16UC1", 0)
    assert image.step == 4 * 2 + 6
    rows = np.asarray(image.data).reshape(3, image.step)
    assert not rows[:, 8:].any(), "row padding is zeros"
    np.testing.assert_array_equal(rows[:, :8].copy().view("<u2"), depth_to_mm(depth))


def test_an_image_built_by_the_library_decodes() -> None:
    types = TYPESTORE.types
    mm = np.array([[0, 1000, 65535], [250, 4000, 12]], dtype="<u2")
    header = types["std_msgs/msg/Header"](stamp=types["builtin_interfaces/msg/Time"](sec=7, nanosec=8),
                                           frame_id="f")
    image = types[IMAGE](header=header, height=2, width=3, encoding="16UC1", is_bigendian=0, step=6,
                         data=mm.view(np.uint8).ravel())
    decoded = decode_depth_image(bytes(TYPESTORE.serialize_cdr(image, IMAGE)))
    np.testing.assert_array_equal(decoded.depth_m, depth_from_mm(mm))
    assert (decoded.stamp_ns, decoded.frame_id, decoded.width, decoded.height) == (7_000_000_008, "f", 3, 2)


@pytest.mark.parametrize("encoding", ["16UC1", "mono16"])
def test_16uc1_round_trip_with_row_padding(encoding: str) -> None:
    depth = depth_image(5, 7)
    depth[0, 0], depth[1, 1], depth[2, 2], depth[3, 3] = 0.0, np.nan, np.inf, -1.0  # all "no return"
    decoded = decode_depth_image(encode_depth_image(depth, encoding=encoding, stamp_ns=STAMP_NS,
                                                    row_padding_bytes=3))
    assert decoded.encoding == encoding and decoded.stamp_ns == STAMP_NS
    expected = depth_from_mm(depth_to_mm(np.where(np.isfinite(depth) & (depth > 0), depth, 0)))
    np.testing.assert_array_equal(decoded.depth_m, expected)
    assert decoded.depth_m.dtype == np.float32 and decoded.depth_m.flags.writeable


def test_32fc1_round_trip_keeps_every_value() -> None:
    depth = depth_image(4, 6)
    depth[0, :3] = (np.nan, np.inf, 0.0)
    decoded = decode_depth_image(encode_depth_image(depth, encoding="32FC1", stamp_ns=0, row_padding_bytes=4))
    np.testing.assert_array_equal(decoded.depth_m, depth)  # NaN == NaN for this assertion
    assert (decoded.width, decoded.height) == (6, 4)


@pytest.mark.parametrize(("encoding", "dtype"), [("16UC1", ">u2"), ("32FC1", ">f4")])
def test_big_endian_image_data(encoding: str, dtype: str) -> None:
    values = np.array([[500, 1500], [2500, 0]]) if encoding == "16UC1" else np.array([[0.5, 1.5], [2.5, np.nan]])
    pixels = values.astype(dtype)
    payload = encode_image(height=2, width=2, encoding=encoding, step=2 * pixels.itemsize + 2,
                           data=np.pad(pixels.view(np.uint8), ((0, 0), (0, 2))), is_bigendian=1)
    expected = depth_from_mm(values.astype(np.uint16)) if encoding == "16UC1" else values.astype(np.float32)
    np.testing.assert_array_equal(decode_depth_image(payload).depth_m, expected)


def test_each_image_reject_has_its_cause() -> None:
    good = {"height": 2, "width": 3, "encoding": "16UC1", "step": 6, "data": bytes(12)}
    assert decode_depth_image(encode_image(**good)).depth_m.shape == (2, 3)
    assert reject_cause(b"definitely not CDR") == "garbage"
    assert reject_cause(CDR_LE + bytes(3)) == "garbage"
    assert reject_cause(encode_image(**{**good, "data": bytes(11)})) == "truncated"
    cut = encode_image(**good)[:-5]  # cut inside the CDR stream: the decoder cannot tell it from junk
    assert reject_cause(cut) == "garbage"
    assert reject_cause(encode_image(**{**good, "encoding": "rgb8"})) == "encoding"
    assert reject_cause(encode_image(**{**good, "width": 0, "step": 0, "data": b""})) == "shape"
    assert reject_cause(encode_image(**{**good, "height": 0, "data": b""})) == "shape"
    assert reject_cause(encode_image(**{**good, "step": 5})) == "shape"
    assert reject_cause(encode_image(**good), max_bytes=40) == "oversize"
    with pytest.raises(Ros2MessageError, match="16UC1, mono16, 32FC1"):
        decode_depth_image(encode_image(**{**good, "encoding": "bgr8"}))


def test_an_all_nan_image_is_a_valid_message() -> None:
    depth = np.full((2, 2), np.nan, np.float32)
    assert np.isnan(decode_depth_image(encode_depth_image(depth, encoding="32FC1", stamp_ns=1)).depth_m).all()


def test_rejects_are_counted_like_every_wire_message() -> None:
    counter = RejectCounter("image")
    for payload in (b"junk", encode_image(height=1, width=1, encoding="rgb8", step=3, data=bytes(3))):
        try:
            decode_depth_image(payload)
        except MessageError as exc:
            counter.reject(exc)
    assert counter.counts == {"garbage": 1, "encoding": 1}
    assert set(CAUSES) == {"garbage", "truncated", "encoding", "shape", "non_finite", "oversize"}
    assert Ros2MessageError("too_small", "a receiver's own cause").cause == "too_small"
    with pytest.raises(ValueError, match="lowercase identifier, got 'Not A Cause'"):
        Ros2MessageError("Not A Cause")


# --- Odometry ----------------------------------------------------------------------------------

@pytest.mark.parametrize("yaw", [0.0, 1.2, 3.0, -2.5, math.pi])
def test_odometry_round_trip(yaw: float) -> None:
    payload = encode_odometry(1.5, -2.0, yaw, 0.3, -0.7, stamp_ns=STAMP_NS)
    x, y, decoded_yaw, linear_x, angular_z, stamp_ns = decode_odometry(payload)
    assert (x, y, linear_x, angular_z, stamp_ns) == (1.5, -2.0, 0.3, -0.7, STAMP_NS)
    assert math.isclose(math.remainder(decoded_yaw - yaw, 2 * math.pi), 0.0, abs_tol=1e-12)
    odometry = TYPESTORE.deserialize_cdr(payload, ODOMETRY)
    q = odometry.pose.pose.orientation
    assert (q.x, q.y) == (0.0, 0.0) and math.isclose(q.z, math.sin(yaw / 2)) and math.isclose(q.w, math.cos(yaw / 2))
    assert (odometry.header.frame_id, odometry.child_frame_id) == ("odom", "base_footprint")


def test_odometry_garbage_is_refused() -> None:
    with pytest.raises(Ros2MessageError) as info:
        decode_odometry(encode_twist(0.1, 0.2))
    assert info.value.cause == "garbage"
