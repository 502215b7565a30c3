"""The ROS 2 messages cogexplore speaks, as CDR bytes: depth ``sensor_msgs/msg/Image`` in,
``geometry_msgs/msg/Twist`` out, ``nav_msgs/msg/Odometry`` from the simulated robot.

Serialisation is the ``rosbags`` library's (its typestore carries the standard message
definitions of each ROS 2 distribution), never hand-written CDR. Payloads carry the 4-byte CDR
encapsulation header (``00 01 00 00``, little endian) exactly as both wire formats put them on
Zenoh: rmw_zenoh serialises with the encapsulation (ros2/rmw_zenoh
``rmw_zenoh_cpp/src/detail/type_support.cpp``: ``ser.serialize_encapsulation()``) and
zenoh-bridge-ros2dds forwards the raw DDS sample (eclipse-zenoh/zenoh-plugin-ros2dds
``zenoh-plugin-ros2dds/src/route_publisher.rs``: ``publisher.put(sample)``).

Decoding never trusts the sender: every problem raises :class:`Ros2MessageError`, whose
``cause`` (one of :data:`CAUSES`) is what a receiver counts its rejects by.

Depth image conventions (REP 118): ``16UC1`` (and its alias ``mono16``) is uint16 millimetres
with 0 = no return; ``32FC1`` is float32 metres with REP 117's special values: NaN an invalid
measurement, +Inf nothing within range, -Inf a return too near to measure. Both come out as
float32 metres; what counts as a usable pixel is the receiver's decision.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass

import numpy as np
from rosbags.typesys import Stores, get_typestore

from shared.depth import depth_from_mm, depth_to_mm
from shared.errors import CogexploreError
from shared.wire.messages import (
    GARBAGE,
    NON_FINITE,
    OVERSIZE,
    SHAPE,
    TRUNCATED,
    MessageError,
)

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
"""Message definitions of ROS 2 Jazzy, the first distribution where rmw_zenoh is a tier-1 RMW
(Image, Twist and Odometry hash the same in rosbags' Kilted and Lyrical stores)."""

IMAGE = "sensor_msgs/msg/Image"
TWIST = "geometry_msgs/msg/Twist"
ODOMETRY = "nav_msgs/msg/Odometry"

ENCODING = "encoding"  # an image encoding this receiver does not take
CAUSES: tuple[str, ...] = (GARBAGE, TRUNCATED, ENCODING, SHAPE, NON_FINITE, OVERSIZE)
"""Why a ROS 2 message is rejected. ``non_finite`` is for receivers that refuse NaN (a Twist);
an image full of NaN is a valid message (no return everywhere), so decoding never says it."""

DEPTH_ENCODINGS: dict[str, tuple[str, int]] = {"16UC1": ("u2", 2), "mono16": ("u2", 2), "32FC1": ("f4", 4)}
"""Accepted depth image encodings -> (numpy kind and size, bytes per pixel)."""

MAX_IMAGE_BYTES = 64 * 2**20
"""Largest Image payload decoded by default (a 1920x1080 32FC1 image is 8 MB)."""

DEFAULT_DEPTH_FRAME = "camera_depth_optical_frame"

_CAUSE_NAME = re.compile(r"[a-z][a-z0-9_]*")
_NS_PER_S = 1_000_000_000
_INT32_MAX = 2**31 - 1


class Ros2MessageError(MessageError):
    """A ROS 2 message that cannot be used. Decoding here raises the causes of :data:`CAUSES`;
    a receiver may raise its own (``range``, ``too_small``...) for messages it cannot take.

    A :class:`shared.wire.messages.MessageError`, so a ``RejectCounter`` counts it by cause.
    """

    def __init__(self, cause: str, detail: str = "") -> None:
        if not isinstance(cause, str) or not _CAUSE_NAME.fullmatch(cause):  # a counter bucket name
            raise ValueError(f"Ros2MessageError cause must be a lowercase identifier, got {cause!r}")
        self.cause = cause
        self.detail = detail
        CogexploreError.__init__(self, f"{cause}: {detail}" if detail else cause)


class Ros2TypeError(CogexploreError):
    """A ROS 2 message type name that is malformed or unknown to :data:`TYPESTORE`."""


# ---------------------------------------------------------------------------------------------
# Type names and hashes
# ---------------------------------------------------------------------------------------------

def _split_type(msgtype: str) -> tuple[str, str, str]:
    parts = msgtype.split("/") if isinstance(msgtype, str) else []
    if len(parts) != 3 or not all(parts) or parts[1] not in ("msg", "srv", "action"):
        raise Ros2TypeError(f"ROS 2 type {msgtype!r} is malformed: expected <package>/msg/<Name>, "
                            "e.g. geometry_msgs/msg/Twist")
    return parts[0], parts[1], parts[2]


@functools.cache
def type_hash(msgtype: str) -> str:
    """The REP-2016 type hash of ``msgtype`` (``RIHS01_<64 hex>``), as rosidl generates it and
    rmw_zenoh puts in key expressions."""
    _split_type(msgtype)
    try:
        return str(TYPESTORE.hash_rihs01(msgtype))
    except KeyError:
        raise Ros2TypeError(f"ROS 2 type {msgtype!r} is unknown to the ROS 2 Jazzy typestore") from None


def dds_type_name(msgtype: str) -> str:
    """The DDS name of a ROS 2 type: ``sensor_msgs/msg/Image`` -> ``sensor_msgs::msg::dds_::Image_``.

    The mangling of ros2/rmw_zenoh ``rmw_zenoh_cpp/src/detail/type_support_common.cpp``
    (``_create_type_name``: ``<namespace>::dds_::<name>_``), the name rmw_zenoh puts in keys.
    """
    package, kind, name = _split_type(msgtype)
    return f"{package}::{kind}::dds_::{name}_"


# ---------------------------------------------------------------------------------------------
# (De)serialisation helpers
# ---------------------------------------------------------------------------------------------

def _serialize(message: object, msgtype: str) -> bytes:
    return bytes(TYPESTORE.serialize_cdr(message, msgtype))


def _deserialize(payload: bytes | bytearray | memoryview, msgtype: str, max_bytes: int | None = None) -> object:
    size = len(payload)
    if max_bytes is not None and size > max_bytes:
        raise Ros2MessageError(OVERSIZE, f"{msgtype} of {size} bytes, more than the {max_bytes} taken")
    try:
        return TYPESTORE.deserialize_cdr(payload, msgtype)
    except Exception as exc:  # noqa: BLE001  any failure on untrusted bytes means junk, whatever rosbags raises
        raise Ros2MessageError(GARBAGE, f"{size} bytes are not a CDR {msgtype}: {exc}") from None


def _stamp(stamp_ns: int) -> object:
    stamp_ns = int(stamp_ns)
    if not 0 <= stamp_ns // _NS_PER_S <= _INT32_MAX:
        raise Ros2MessageError(SHAPE, f"stamp {stamp_ns} ns is outside builtin_interfaces/Time")
    time_cls = TYPESTORE.types["builtin_interfaces/msg/Time"]
    return time_cls(sec=stamp_ns // _NS_PER_S, nanosec=stamp_ns % _NS_PER_S)


def _header(stamp_ns: int, frame_id: str) -> object:
    return TYPESTORE.types["std_msgs/msg/Header"](stamp=_stamp(stamp_ns), frame_id=str(frame_id))


def _stamp_ns(header: object) -> int:
    stamp = header.stamp  # type: ignore[attr-defined]
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def _require_finite(what: str, **values: float) -> None:
    bad = {name: value for name, value in values.items() if not math.isfinite(value)}
    if bad:
        raise Ros2MessageError(NON_FINITE, f"{what} with non-finite " +
                               ", ".join(f"{name}={value}" for name, value in bad.items()))


# ---------------------------------------------------------------------------------------------
# sensor_msgs/msg/Image (depth)
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class DepthImage:
    """A decoded depth image."""

    depth_m: np.ndarray
    """float32 (height, width) metres, a fresh array. 16UC1 zeros (no return) read 0; 32FC1
    values (NaN, infinities, out of range) stay as sent."""
    encoding: str
    """The encoding it was sent in: '16UC1', 'mono16' or '32FC1'."""
    stamp_ns: int
    """header.stamp in nanoseconds since the epoch."""
    frame_id: str
    """header.frame_id."""
    width: int
    """Pixels per row."""
    height: int
    """Rows."""


def encode_image(*, height: int, width: int, encoding: str, step: int, data: bytes | np.ndarray,
                 is_bigendian: int = 0, stamp_ns: int = 0, frame_id: str = DEFAULT_DEPTH_FRAME) -> bytes:
    """Any ``sensor_msgs/msg/Image`` as CDR bytes, fields as given and unchecked (tests build
    malformed images with it; cameras use :func:`encode_depth_image`)."""
    raw = np.frombuffer(data.tobytes() if isinstance(data, np.ndarray) else bytes(data), dtype=np.uint8)
    image = TYPESTORE.types[IMAGE](header=_header(stamp_ns, frame_id), height=int(height), width=int(width),
                                   encoding=str(encoding), is_bigendian=int(is_bigendian), step=int(step),
                                   data=raw)
    return _serialize(image, IMAGE)


def encode_depth_image(depth: np.ndarray, *, encoding: str, stamp_ns: int,
                       frame_id: str = DEFAULT_DEPTH_FRAME, row_padding_bytes: int = 0) -> bytes:
    """A depth image (float metres (H, W), 0 = no return) as a CDR ``sensor_msgs/msg/Image``.

    ``16UC1``/``mono16``: uint16 millimetres (``shared.depth.depth_to_mm``), NaN, infinities and
    depths <= 0 sent as 0 (no return). ``32FC1``: float32 metres as given. Each row is followed by
    ``row_padding_bytes`` zero bytes (``step`` = width x bytes per pixel + padding), little endian.
    """
    if encoding not in DEPTH_ENCODINGS:
        raise Ros2MessageError(ENCODING, f"cannot encode depth as {encoding!r}: use one of {list(DEPTH_ENCODINGS)}")
    depth = np.asarray(depth, dtype=np.float32)
    if depth.ndim != 2 or depth.size == 0:
        raise Ros2MessageError(SHAPE, f"depth must be one non-empty (H, W) image, got shape {depth.shape}")
    if int(row_padding_bytes) < 0:
        raise Ros2MessageError(SHAPE, f"row_padding_bytes must be >= 0, got {row_padding_bytes}")
    kind, bytes_per_pixel = DEPTH_ENCODINGS[encoding]
    if kind == "u2":
        returns = np.isfinite(depth) & (depth > 0)
        pixels = depth_to_mm(np.where(returns, depth, np.float32(0.0))).astype("<u2")
    else:
        pixels = depth.astype("<f4")
    height, width = depth.shape
    row_bytes = width * bytes_per_pixel
    step = row_bytes + int(row_padding_bytes)
    rows = np.zeros((height, step), dtype=np.uint8)
    rows[:, :row_bytes] = pixels.view(np.uint8).reshape(height, row_bytes)
    return encode_image(height=height, width=width, encoding=encoding, step=step, data=rows,
                        stamp_ns=stamp_ns, frame_id=frame_id)


def decode_depth_image(payload: bytes | bytearray | memoryview, *, max_bytes: int = MAX_IMAGE_BYTES) -> DepthImage:
    """A CDR ``sensor_msgs/msg/Image`` as float32 metres, honouring ``step`` (row stride) and
    ``is_bigendian``. Raises :class:`Ros2MessageError`:

    - ``oversize``: the payload is longer than ``max_bytes`` (checked before deserialising);
    - ``garbage``: not a CDR Image (bytes cut inside the CDR stream read as garbage too);
    - ``encoding``: not one of :data:`DEPTH_ENCODINGS`;
    - ``shape``: width or height 0, or ``step`` shorter than a row of pixels;
    - ``truncated``: ``data`` shorter than ``step`` x ``height``.
    """
    image = _deserialize(payload, IMAGE, max_bytes)
    encoding = str(image.encoding)  # type: ignore[attr-defined]
    if encoding not in DEPTH_ENCODINGS:
        raise Ros2MessageError(ENCODING, f"image encoding {encoding!r} is not a depth encoding: "
                               f"accepted are {', '.join(DEPTH_ENCODINGS)}")
    kind, bytes_per_pixel = DEPTH_ENCODINGS[encoding]
    height, width, step = int(image.height), int(image.width), int(image.step)  # type: ignore[attr-defined]
    if height == 0 or width == 0 or step < width * bytes_per_pixel:
        raise Ros2MessageError(SHAPE, f"{width}x{height} {encoding} image with step {step} "
                               f"(a row needs {width * bytes_per_pixel} bytes)")
    data = np.asarray(image.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if data.size < step * height:
        raise Ros2MessageError(TRUNCATED, f"{width}x{height} image with step {step} needs {step * height} "
                               f"bytes of data, got {data.size}")
    order = ">" if int(image.is_bigendian) else "<"  # type: ignore[attr-defined]
    rows = data[:step * height].reshape(height, step)[:, :width * bytes_per_pixel]
    pixels = rows.view(np.dtype(order + kind)).reshape(height, width)
    if kind == "u2":
        depth_m = depth_from_mm(pixels.astype(np.uint16))
    else:
        depth_m = pixels.astype(np.float32)
    return DepthImage(depth_m=depth_m, encoding=encoding, stamp_ns=_stamp_ns(image.header),  # type: ignore[attr-defined]
                      frame_id=str(image.header.frame_id), width=width, height=height)  # type: ignore[attr-defined]


# ---------------------------------------------------------------------------------------------
# geometry_msgs/msg/Twist
# ---------------------------------------------------------------------------------------------

def _vector3(x: float = 0.0, y: float = 0.0, z: float = 0.0) -> object:
    return TYPESTORE.types["geometry_msgs/msg/Vector3"](x=float(x), y=float(y), z=float(z))


def encode_twist(linear_x: float, angular_z: float) -> bytes:
    """A planar velocity command (m/s forward, rad/s counter-clockwise) as a CDR Twist; the other
    four components are 0. Non-finite values raise ``non_finite``: a robot never gets NaN."""
    _require_finite("Twist", linear_x=linear_x, angular_z=angular_z)
    twist = TYPESTORE.types[TWIST](linear=_vector3(x=linear_x), angular=_vector3(z=angular_z))
    return _serialize(twist, TWIST)


def decode_twist(payload: bytes | bytearray | memoryview) -> tuple[float, float]:
    """(linear.x, angular.z) of a CDR Twist; ``garbage`` for junk, ``non_finite`` when any of the
    six components is NaN or infinite."""
    twist = _deserialize(payload, TWIST, max_bytes=4096)
    linear, angular = twist.linear, twist.angular  # type: ignore[attr-defined]
    _require_finite("Twist", **{f"linear.{a}": float(getattr(linear, a)) for a in "xyz"},
                    **{f"angular.{a}": float(getattr(angular, a)) for a in "xyz"})
    return float(linear.x), float(angular.z)


# ---------------------------------------------------------------------------------------------
# nav_msgs/msg/Odometry
# ---------------------------------------------------------------------------------------------

def encode_odometry(x: float, y: float, yaw: float, linear_x: float, angular_z: float, *, stamp_ns: int,
                    frame_id: str = "odom", child_frame_id: str = "base_footprint") -> bytes:
    """A planar pose (m, m, rad about z) and velocity as a CDR Odometry (covariances 0)."""
    _require_finite("Odometry", x=x, y=y, yaw=yaw, linear_x=linear_x, angular_z=angular_z)
    types = TYPESTORE.types
    orientation = types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    pose = types["geometry_msgs/msg/Pose"](position=types["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=0.0),
                                           orientation=orientation)
    twist = types[TWIST](linear=_vector3(x=linear_x), angular=_vector3(z=angular_z))
    odometry = types[ODOMETRY](
        header=_header(stamp_ns, frame_id), child_frame_id=str(child_frame_id),
        pose=types["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))
    return _serialize(odometry, ODOMETRY)


def decode_odometry(payload: bytes | bytearray | memoryview) -> tuple[float, float, float, float, float, int]:
    """(x, y, yaw, linear_x, angular_z, stamp_ns) of a CDR Odometry; yaw in (-pi, pi] from the
    quaternion's rotation about z."""
    odometry = _deserialize(payload, ODOMETRY, max_bytes=4096)
    pose, twist = odometry.pose.pose, odometry.twist.twist  # type: ignore[attr-defined]
    q = pose.orientation
    yaw = math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))
    values = (float(pose.position.x), float(pose.position.y), yaw, float(twist.linear.x), float(twist.angular.z))
    _require_finite("Odometry", **dict(zip(("x", "y", "yaw", "linear_x", "angular_z"), values)))
    return (*values, _stamp_ns(odometry.header))  # type: ignore[attr-defined]
