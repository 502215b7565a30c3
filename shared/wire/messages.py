"""Wire messages of cogexplore: frozen dataclasses, a msgpack codec and validation.

Every message is a msgpack map ``{"schema": SCHEMA_VERSION, "type": <TYPE>, <field>: ...}``.
Arrays travel as ``{"dtype": "uint16", "shape": [T, H, W], "data": <bin>}``: raw little-endian
bytes with an explicit dtype and shape, never pickle. Construction validates every field
(type, dtype, shape, range, NaN/Inf, size limits), and ``decode`` builds through the same
constructor, so a decoded message is always valid; anything else raises
:class:`MessageError` whose ``cause`` is one of :data:`CAUSES`. A service counts rejects
with :class:`RejectCounter` and carries on.

Transition batch layout (:class:`TransitionBatch`): T consecutive transitions of ONE
actor within ONE episode (a batch never spans two episodes), every frame sent once::

    depth_mm[i]       observation before action i           uint16 (T, H, W), millimetres
    next_depth_mm     observation after the last action     uint16 (H, W), None iff terminated
    next obs of i     depth_mm[i + 1] for i < T - 1, next_depth_mm for i = T - 1
    action[i]         0..4 (shared.config.ACTION_NAMES)     uint8 (T,)
    reward[i]                                               float32 (T,)
    policy_version[i] weights version that chose action i   int64 (T,)
    pose[i]           (x, y, yaw) after action i            float32 (T, 3)
    expert_action[i]  the map expert's command in obs i     uint8 (T,) or None: NO_EXPERT_LABEL
                      (explore.expert_label_prob)           where it named none; None: no labels
    safe_commands[i]  bitmask (bit a: command a) of the     uint8 (T,) or None: 0 where it marked
                      commands with a way out from obs i    none; None: no marks
                      (explore.safe_label_prob)
    terminated        the LAST transition ended in a collision (no bootstrap)
    truncated         the LAST transition hit the step cap (bootstrap from next_depth_mm)

Only the last transition can end an episode, so the episode-end flags are per batch (never both). The
actor sends a batch when it holds ``MAX_BATCH_STEPS`` (or fewer, its choice) transitions or
when the episode ends. A mid-episode batch carries ``next_depth_mm`` and the next batch
starts with the same frame: one duplicate frame per batch, in exchange for batches that can
be stored without waiting for their successor.

Received arrays are read-only views of the message bytes (no copy); copy before writing.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import threading
import time
from dataclasses import dataclass, field, fields
from typing import Any, Callable, ClassVar, Mapping, Sequence, TypeVar

import msgpack
import numpy as np

from shared.config import ALL_COMMANDS_MASK, NUM_ACTIONS, ConfigError, EnvConfig, RunConfig, from_dict
from shared.depth import depth_to_mm
from shared.errors import CogexploreError
from shared.wire.keys import KeyExprError, validate_name

SCHEMA_VERSION = 4
"""Bumped on any incompatible change of a message layout; a receiver rejects other versions.
2: learner and actor epochs (weights versions are (learner epoch, update); flow credit per actor
process). 3: transitions carry the expert's labels (``TransitionBatch.expert_action``). 4: and its
safe-set marks (``TransitionBatch.safe_commands``)."""
NO_EXPERT_LABEL = 255
"""``TransitionBatch.expert_action`` of a transition the expert did not label."""

# --- size limits ----------------------------------------------------------------------------
MAX_BATCH_STEPS = 64
"""Most transitions in one TransitionBatch."""
MAX_FRAME_PIXELS = 640 * 480
"""Most pixels in one depth frame (a full Kinect depth image)."""
MAX_WEIGHTS_BYTES = 256 * 2**20
"""Most tensor bytes in one WeightsMessage."""
MAX_TENSORS = 4096
MAX_TENSOR_NDIM = 8
MAX_EVAL_EPISODES = 4096
MAX_EXTRA_ITEMS = 64
MAX_NAME_CHARS = 256
MAX_TEXT_CHARS = 1024
_ENVELOPE_SLACK = 2**20
MAX_MESSAGE_BYTES = MAX_WEIGHTS_BYTES + _ENVELOPE_SLACK
"""Nothing longer than this is even unpacked."""
_I64_MAX = 2**63 - 1
MAX_POLICY_VERSION = 2**40
"""No run makes a trillion updates: a larger weights version is an attack or a bug, refused."""
MAX_CLOCK_SKEW_NS = 10 * 60 * 10**9
"""How far ahead of a receiver's clock a process epoch may be (machines' clocks differ a little)."""


def new_epoch() -> int:
    """A process epoch: the wall clock in ns when it started. A restarted process gets a later one."""
    return time.time_ns()


def future_epoch_error(what: str) -> MessageError:
    """The refusal of ``what`` (a message) of a learner whose epoch is from the future. It names the
    clocks: a real learner on a machine whose clock runs ahead is refused for as long as it runs,
    and its actors act on their untrained networks meanwhile."""
    return MessageError(RANGE, f"{what} of a learner started in the future, more than "
                               f"{MAX_CLOCK_SKEW_NS // 60_000_000_000} minutes ahead of this machine's clock (if "
                               "that learner is real, the two machines' clocks disagree: set both from NTP)")


def epoch_from_the_future(epoch: int, now_ns: int | None = None) -> bool:
    """An epoch no process can have yet (beyond :data:`MAX_CLOCK_SKEW_NS` of this clock): an attack or
    a broken clock, whose messages would otherwise outrank every real process's for good."""
    return epoch > (time.time_ns() if now_ns is None else now_ns) + MAX_CLOCK_SKEW_NS


class LearnerEpochs:
    """Which learner process a receiver follows, by its epoch (the weights and flow-control streams).

    The first epoch heard is followed. Another epoch (a restarted learner's, newer; or the real
    learner's, older, after a forged message was followed) is taken only once the followed one has
    said nothing for ``quiet_s``: a dead learner falls silent at once, while one forged message
    among a live learner's is ignored, and a forged epoch that is followed loses it as soon as it
    stops. (Ranking epochs alone let a single message dated now outrank the real learner for good.)
    An epoch from the future is never taken. Not thread-safe: the receiver's lock holds it.
    """

    FUTURE, OTHER, SAME, NEW = "future", "other", "same", "new"

    def __init__(self, quiet_s: float, clock: Callable[[], float] = time.monotonic):
        self.quiet_s = quiet_s
        self.clock = clock
        self.followed: int | None = None
        """The epoch followed now (None: no learner heard yet)."""
        self._heard_s = 0.0

    def admit(self, epoch: int) -> str:
        """One message's epoch: ``SAME`` (the followed learner's), ``NEW`` (followed from now on:
        the first, or a learner that replaces a quiet one), ``OTHER`` (ignored: the followed one
        is speaking) or ``FUTURE`` (refused: no process can have it yet)."""
        if epoch_from_the_future(epoch):
            return self.FUTURE
        if epoch == self.followed:
            self._heard_s = self.clock()
            return self.SAME
        if not self.quiet():
            return self.OTHER
        self.follow(epoch)
        return self.NEW

    def heard(self, epoch: int) -> None:
        """The followed learner said something on another stream (its flow control, every 0.1 s):
        it is alive, however long since its last message here. Any other epoch changes nothing."""
        if self.followed is not None and epoch == self.followed:
            self._heard_s = self.clock()

    def quiet(self) -> bool:
        """No learner followed, or the followed one has said nothing for ``quiet_s``."""
        return self.followed is None or self.clock() - self._heard_s >= self.quiet_s

    def follow(self, epoch: int) -> None:
        """Follow ``epoch`` from now on (one whose message the receiver kept while another spoke)."""
        self.followed, self._heard_s = epoch, self.clock()

# --- reject causes --------------------------------------------------------------------------
TRUNCATED = "truncated"          # the bytes end inside a msgpack object (or are empty)
GARBAGE = "garbage"              # not one msgpack map: bad format, extra bytes, wrong top level
SCHEMA_VERSION_MISMATCH = "schema_version"
MESSAGE_TYPE = "message_type"    # unknown type, or not the type the caller expected
MISSING_FIELD = "missing_field"
UNKNOWN_FIELD = "unknown_field"
FIELD_TYPE = "field_type"        # a field holds the wrong kind of value (str for int, ...)
DTYPE = "dtype"                  # an array has the wrong dtype
SHAPE = "shape"                  # an array has the wrong shape, or shape x itemsize != len(data)
NON_FINITE = "non_finite"        # NaN or Inf where a finite number is required
RANGE = "range"                  # a value outside its allowed range (action 7, negative step, ...)
OVERSIZE = "oversize"            # beyond a size limit (bytes, frames, tensors, ...)
INCONSISTENT = "inconsistent"    # fields that contradict each other
FINGERPRINT = "fingerprint"      # weights built for another architecture
CAUSES: tuple[str, ...] = (TRUNCATED, GARBAGE, SCHEMA_VERSION_MISMATCH, MESSAGE_TYPE,
                           MISSING_FIELD, UNKNOWN_FIELD, FIELD_TYPE, DTYPE, SHAPE, NON_FINITE,
                           RANGE, OVERSIZE, INCONSISTENT, FINGERPRINT)

COLLISION_CAUSES: tuple[str, ...] = ("depth", "contact")

# Wire dtype names -> little-endian numpy dtypes.
_WIRE_DTYPES: dict[str, np.dtype] = {
    "uint8": np.dtype("<u1"), "uint16": np.dtype("<u2"), "int64": np.dtype("<i8"),
    "float16": np.dtype("<f2"), "float32": np.dtype("<f4"),
}
WEIGHT_DTYPES: tuple[str, ...] = ("float32", "float16")


class MessageError(CogexploreError):
    """A message is invalid. ``cause`` is one of :data:`CAUSES`; ``detail`` says what and where."""

    def __init__(self, cause: str, detail: str = "") -> None:
        if cause not in CAUSES:  # a typo here would silently create a new counter bucket
            raise ValueError(f"unknown MessageError cause {cause!r}")
        self.cause = cause
        self.detail = detail
        super().__init__(f"{cause}: {detail}" if detail else cause)


# ---------------------------------------------------------------------------------------------
# Field validation helpers: each returns the value normalised to plain Python / exact dtypes.
# ---------------------------------------------------------------------------------------------

def _int(value: Any, name: str, lo: int = 0, hi: int = _I64_MAX) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise MessageError(FIELD_TYPE, f"{name} must be an integer, got {type(value).__name__}")
    value = int(value)
    if not lo <= value <= hi:
        raise MessageError(RANGE, f"{name} = {value} is outside [{lo}, {hi}]")
    return value


def _float(value: Any, name: str, lo: float = -math.inf, hi: float = math.inf) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise MessageError(FIELD_TYPE, f"{name} must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise MessageError(NON_FINITE, f"{name} = {value} is not finite")
    if not lo <= value <= hi:
        raise MessageError(RANGE, f"{name} = {value} is outside [{lo}, {hi}]")
    return value


def _opt_float(value: Any, name: str, lo: float = -math.inf, hi: float = math.inf) -> float | None:
    return None if value is None else _float(value, name, lo, hi)


def _bool(value: Any, name: str) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise MessageError(FIELD_TYPE, f"{name} must be a bool, got {type(value).__name__}")
    return bool(value)


def _text(value: Any, name: str, max_chars: int = MAX_TEXT_CHARS) -> str:
    if not isinstance(value, str):
        raise MessageError(FIELD_TYPE, f"{name} must be a string, got {type(value).__name__}")
    if len(value) > max_chars:
        raise MessageError(OVERSIZE, f"{name} is {len(value)} characters (max {max_chars})")
    if not value or not value.isprintable():
        raise MessageError(RANGE, f"{name} = {value!r} must be non-empty printable text")
    return value


def _chunk(value: Any, name: str) -> str:
    """A process / actor id: a single key chunk (see shared.wire.keys.validate_name)."""
    if not isinstance(value, str):
        raise MessageError(FIELD_TYPE, f"{name} must be a string, got {type(value).__name__}")
    try:
        return validate_name(value, name)
    except KeyExprError as exc:
        raise MessageError(RANGE, str(exc)) from None


def _array(value: Any, name: str, dtype: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Check dtype and shape (None = any length on that axis)."""
    if not isinstance(value, np.ndarray):
        raise MessageError(FIELD_TYPE, f"{name} must be a numpy array, got {type(value).__name__}")
    if value.dtype != _WIRE_DTYPES[dtype]:
        raise MessageError(DTYPE, f"{name} must be {dtype}, got {value.dtype}")
    if value.ndim != len(shape) or any(e is not None and e != n for e, n in zip(shape, value.shape)):
        want = "(" + ", ".join("*" if e is None else str(e) for e in shape) + ")"
        raise MessageError(SHAPE, f"{name} has shape {value.shape}, expected {want}")
    return value


def _finite_array(value: np.ndarray, name: str) -> None:
    if not np.isfinite(value).all():
        raise MessageError(NON_FINITE, f"{name} contains NaN or Inf")


def _extra(value: Any, name: str = "extra") -> dict[str, float]:
    """Free-form named scalars, for figures a schema does not name yet."""
    if not isinstance(value, Mapping):
        raise MessageError(FIELD_TYPE, f"{name} must be a map of name -> number")
    if len(value) > MAX_EXTRA_ITEMS:
        raise MessageError(OVERSIZE, f"{name} has {len(value)} items (max {MAX_EXTRA_ITEMS})")
    return {_text(k, f"{name} key", MAX_NAME_CHARS): _float(v, f"{name}[{k!r}]")
            for k, v in value.items()}


def _set(obj: Any, name: str, value: Any) -> None:
    object.__setattr__(obj, name, value)  # normalise fields of a frozen dataclass in __post_init__


# ---------------------------------------------------------------------------------------------
# Array and envelope codec
# ---------------------------------------------------------------------------------------------

def _array_to_wire(arr: np.ndarray) -> dict[str, Any]:
    name = next(k for k, v in _WIRE_DTYPES.items() if v == arr.dtype.newbyteorder("<"))
    data = np.ascontiguousarray(arr, dtype=_WIRE_DTYPES[name]).tobytes()
    return {"dtype": name, "shape": list(arr.shape), "data": data}


def _array_from_wire(obj: Any, name: str) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise MessageError(FIELD_TYPE, f"{name} must be a map with exactly dtype, shape and data")
    dtype_name, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if not isinstance(dtype_name, str) or dtype_name not in _WIRE_DTYPES:
        raise MessageError(DTYPE, f"{name} has unknown dtype {dtype_name!r}; known: {list(_WIRE_DTYPES)}")
    if not isinstance(data, bytes):
        raise MessageError(FIELD_TYPE, f"{name}.data must be bin, got {type(data).__name__}")
    if (not isinstance(shape, list) or len(shape) > MAX_TENSOR_NDIM
            or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)):
        raise MessageError(SHAPE, f"{name}.shape must be a list of at most {MAX_TENSOR_NDIM} "
                                  f"non-negative integers, got {shape!r}")
    dtype = _WIRE_DTYPES[dtype_name]
    expected = math.prod(shape) * dtype.itemsize  # Python ints: no overflow on hostile shapes
    if expected != len(data):
        raise MessageError(SHAPE, f"{name}: shape {shape} x {dtype.itemsize} bytes = {expected} "
                                  f"but data holds {len(data)} bytes")
    try:
        return np.frombuffer(data, dtype=dtype).reshape(shape)
    except ValueError as exc:  # an empty array of absurd dimensions ([0, 2**40, 2**40]): numpy's limits
        raise MessageError(SHAPE, f"{name}: shape {shape}: {exc}") from None


def _unpack(data: bytes | bytearray | memoryview, max_bytes: int) -> dict[str, Any]:
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise TypeError(f"decode expects bytes, got {type(data).__name__}")
    size = len(data) if not isinstance(data, memoryview) else data.nbytes
    if size > max_bytes:
        raise MessageError(OVERSIZE, f"message is {size} bytes (max {max_bytes})")
    unpacker = msgpack.Unpacker(
        raw=False, strict_map_key=True, max_buffer_size=max(size, 1), max_bin_len=max_bytes,
        max_str_len=2**20, max_array_len=2**20, max_map_len=2**16, max_ext_len=0)
    unpacker.feed(data)
    try:
        obj = unpacker.unpack()
    except msgpack.OutOfData:
        raise MessageError(TRUNCATED, f"the {size} bytes end inside a msgpack object") from None
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        raise MessageError(GARBAGE, f"not msgpack: {exc}") from None
    if unpacker.tell() != size:
        raise MessageError(GARBAGE, f"{size - unpacker.tell()} bytes after the message")
    if not isinstance(obj, dict):
        raise MessageError(GARBAGE, f"top level must be a map, got {type(obj).__name__}")
    return obj


_WIRE_ARRAY = "array"        # ndarray <-> {"dtype", "shape", "data"}
_WIRE_TUPLE = "tuple"        # tuple <-> list
_WIRE_TENSORS = "tensors"    # {name: ndarray} <-> {name: {"dtype", "shape", "data"}}

M = TypeVar("M", bound="Message")


class Message:
    """Base of every wire message: ``encode()`` and ``decode(bytes)``."""

    TYPE: ClassVar[str] = ""
    MAX_BYTES: ClassVar[int] = 2**20

    def encode(self) -> bytes:
        """The message as msgpack bytes."""
        body: dict[str, Any] = {"schema": SCHEMA_VERSION, "type": self.TYPE}
        for f in fields(self):  # type: ignore[arg-type]
            value, wire = getattr(self, f.name), f.metadata.get("wire")
            if value is None:
                body[f.name] = None
            elif wire == _WIRE_ARRAY:
                body[f.name] = _array_to_wire(value)
            elif wire == _WIRE_TUPLE:
                body[f.name] = list(value)
            elif wire == _WIRE_TENSORS:
                body[f.name] = {k: _array_to_wire(v) for k, v in value.items()}
            else:
                body[f.name] = value
        return msgpack.packb(body, use_bin_type=True)

    @classmethod
    def decode(cls: type[M], data: bytes | bytearray | memoryview) -> M:
        """Parse and validate ``data``; raises :class:`MessageError` for anything invalid."""
        obj = _unpack(data, cls.MAX_BYTES)
        msg = _from_body(obj)
        if not isinstance(msg, cls):
            raise MessageError(MESSAGE_TYPE, f"expected a {cls.TYPE!r} message, got {msg.TYPE!r}")
        return msg


_REGISTRY: dict[str, type[Message]] = {}


def _register(cls: type[M]) -> type[M]:
    _REGISTRY[cls.TYPE] = cls
    return cls


def _from_body(obj: dict[str, Any]) -> Message:
    if "schema" not in obj:
        raise MessageError(SCHEMA_VERSION_MISMATCH, "no schema version")
    if obj["schema"] != SCHEMA_VERSION or isinstance(obj["schema"], bool):
        raise MessageError(SCHEMA_VERSION_MISMATCH,
                           f"schema version {obj['schema']!r}, this build speaks {SCHEMA_VERSION}")
    cls = _REGISTRY.get(obj.get("type")) if isinstance(obj.get("type"), str) else None
    if cls is None:
        raise MessageError(MESSAGE_TYPE, f"unknown message type {obj.get('type')!r}; "
                                         f"known: {sorted(_REGISTRY)}")
    specs = {f.name: f for f in fields(cls)}  # type: ignore[arg-type]
    body = {k: v for k, v in obj.items() if k not in ("schema", "type")}
    unknown = sorted(set(body) - set(specs), key=repr)  # names may be str and bytes: not comparable
    if unknown:
        raise MessageError(UNKNOWN_FIELD, f"{cls.TYPE}: unknown field(s) {unknown}")
    missing = sorted(set(specs) - set(body))
    if missing:
        raise MessageError(MISSING_FIELD, f"{cls.TYPE}: missing field(s) {missing}")
    values: dict[str, Any] = {}
    for name, raw in body.items():
        wire = specs[name].metadata.get("wire")
        if raw is None:
            values[name] = None
        elif wire == _WIRE_ARRAY:
            values[name] = _array_from_wire(raw, name)
        elif wire == _WIRE_TUPLE:
            if not isinstance(raw, list):
                raise MessageError(FIELD_TYPE, f"{name} must be a list, got {type(raw).__name__}")
            values[name] = tuple(raw)
        elif wire == _WIRE_TENSORS:
            if not isinstance(raw, dict):
                raise MessageError(FIELD_TYPE, f"{name} must be a map, got {type(raw).__name__}")
            if len(raw) > MAX_TENSORS:
                raise MessageError(OVERSIZE, f"{len(raw)} tensors (max {MAX_TENSORS})")
            values[name] = {k: _array_from_wire(v, f"{name}[{k!r}]") for k, v in raw.items()}
        else:
            values[name] = raw
    return cls(**values)


def decode_message(data: bytes | bytearray | memoryview) -> Message:
    """Decode any message type (dispatching on its ``type``)."""
    obj = _unpack(data, MAX_MESSAGE_BYTES)
    cls = _REGISTRY.get(obj.get("type")) if isinstance(obj.get("type"), str) else None
    if cls is not None and len(data) > cls.MAX_BYTES:
        raise MessageError(OVERSIZE, f"{cls.TYPE} message is {len(data)} bytes (max {cls.MAX_BYTES})")
    return _from_body(obj)


def _arr() -> Any:
    return field(metadata={"wire": _WIRE_ARRAY})


def _tup() -> Any:
    return field(metadata={"wire": _WIRE_TUPLE})


# ---------------------------------------------------------------------------------------------
# Messages
# ---------------------------------------------------------------------------------------------

@_register
@dataclass(frozen=True, eq=False)
class TransitionBatch(Message):
    """T consecutive transitions of one actor in one episode (layout: see the module doc)."""

    TYPE: ClassVar[str] = "transitions"
    MAX_BYTES: ClassVar[int] = (MAX_BATCH_STEPS + 1) * MAX_FRAME_PIXELS * 2 + _ENVELOPE_SLACK

    actor_id: str
    episode: int
    """The actor's episode counter (from 0)."""
    first_step: int
    """Step index of transition 0 within its episode (0 = the first step after reset)."""
    start_index: int
    """The world start pose the episode began from."""
    actor_epoch: int
    """When this actor process started (ns since the epoch): a restart under the same id is a new
    process, with its own flow-control allowance."""
    depth_mm: np.ndarray = _arr()
    next_depth_mm: np.ndarray | None = _arr()
    action: np.ndarray = _arr()
    reward: np.ndarray = _arr()
    policy_version: np.ndarray = _arr()
    pose: np.ndarray = _arr()
    terminated: bool = False
    truncated: bool = False
    expert_action: np.ndarray | None = field(default=None, metadata={"wire": _WIRE_ARRAY})
    """The map expert's command in each transition's obs (``NO_EXPERT_LABEL``: none); None: no labels."""
    safe_commands: np.ndarray | None = field(default=None, metadata={"wire": _WIRE_ARRAY})
    """Bitmask of the commands the map expert found a way out after, per transition's obs (0: no
    mark); None: no marks."""

    def __post_init__(self) -> None:
        _set(self, "actor_id", _chunk(self.actor_id, "actor_id"))
        _set(self, "episode", _int(self.episode, "episode"))
        _set(self, "first_step", _int(self.first_step, "first_step"))
        _set(self, "start_index", _int(self.start_index, "start_index"))
        _set(self, "actor_epoch", _int(self.actor_epoch, "actor_epoch"))
        _set(self, "terminated", _bool(self.terminated, "terminated"))
        _set(self, "truncated", _bool(self.truncated, "truncated"))
        depth = _array(self.depth_mm, "depth_mm", "uint16", (None, None, None))
        t, h, w = depth.shape
        if t > MAX_BATCH_STEPS:
            raise MessageError(OVERSIZE, f"{t} transitions in a batch (max {MAX_BATCH_STEPS})")
        if h * w > MAX_FRAME_PIXELS:
            raise MessageError(OVERSIZE, f"frames of {h}x{w} pixels (max {MAX_FRAME_PIXELS})")
        if t == 0 or h == 0 or w == 0:
            raise MessageError(SHAPE, f"depth_mm has an empty axis: {depth.shape}")
        if self.next_depth_mm is not None:
            _array(self.next_depth_mm, "next_depth_mm", "uint16", (h, w))
        if self.terminated and self.truncated:  # no receiver can store it: the batcher never sends both
            raise MessageError(INCONSISTENT, "the last transition cannot be both terminated (collision) and truncated")
        if (self.next_depth_mm is None) != self.terminated:
            raise MessageError(INCONSISTENT, "next_depth_mm must be present exactly when the last "
                                             f"transition is not terminal (terminated={self.terminated})")
        action = _array(self.action, "action", "uint8", (t,))
        if (action >= NUM_ACTIONS).any():
            raise MessageError(RANGE, f"action {int(action.max())} is outside [0, {NUM_ACTIONS - 1}]")
        reward = _array(self.reward, "reward", "float32", (t,))
        _finite_array(reward, "reward")
        version = _array(self.policy_version, "policy_version", "int64", (t,))
        if (version < 0).any() or (version > MAX_POLICY_VERSION).any():
            raise MessageError(RANGE, f"policy_version must be in [0, {MAX_POLICY_VERSION}]")
        pose = _array(self.pose, "pose", "float32", (t, 3))
        _finite_array(pose, "pose")
        if self.expert_action is not None:
            label = _array(self.expert_action, "expert_action", "uint8", (t,))
            if ((label >= NUM_ACTIONS) & (label != NO_EXPERT_LABEL)).any():
                raise MessageError(RANGE, f"expert_action holds {sorted(set(label.tolist()))}: commands are "
                                          f"0-{NUM_ACTIONS - 1}, {NO_EXPERT_LABEL} is no label")
        if self.safe_commands is not None:
            marks = _array(self.safe_commands, "safe_commands", "uint8", (t,))
            if (marks > ALL_COMMANDS_MASK).any():
                raise MessageError(RANGE, f"safe_commands holds {int(marks.max())}: a bitmask of "
                                          f"{NUM_ACTIONS} commands is at most {ALL_COMMANDS_MASK}")

    @property
    def steps(self) -> int:
        """Number of transitions T."""
        return int(self.depth_mm.shape[0])

    @property
    def frame_shape(self) -> tuple[int, int]:
        return int(self.depth_mm.shape[1]), int(self.depth_mm.shape[2])

    def next_depth(self, i: int) -> np.ndarray | None:
        """Next observation of transition ``i`` (None only for a terminal last transition)."""
        if not 0 <= i < self.steps:
            raise IndexError(f"transition {i} of a batch of {self.steps}")
        return self.depth_mm[i + 1] if i + 1 < self.steps else self.next_depth_mm

    def expert_labels(self) -> np.ndarray:
        """Per-transition expert command, int64, -1 where the expert named none."""
        if self.expert_action is None:
            return np.full(self.steps, -1, dtype=np.int64)
        label = self.expert_action.astype(np.int64)
        label[label == NO_EXPERT_LABEL] = -1
        return label

    def terminated_flags(self) -> np.ndarray:
        """Per-transition ``terminated`` (only the last can be True)."""
        flags = np.zeros(self.steps, dtype=bool)
        flags[-1] = self.terminated
        return flags

    def truncated_flags(self) -> np.ndarray:
        """Per-transition ``truncated`` (only the last can be True)."""
        flags = np.zeros(self.steps, dtype=bool)
        flags[-1] = self.truncated
        return flags

    def require_physical(self, env: EnvConfig, *, max_depth_mm: int, max_abs_xy_m: float = 1e4) -> None:
        """Raise MessageError(RANGE) unless the batch could have come from the receiver's task ``env``:
        every reward one ``env`` pays for a move (``EnvConfig.pays_for_a_move``), except a terminal
        last one, which is its collision reward; no depth beyond the sensor's range; positions within
        ``max_abs_xy_m``. A finite reward of 3e38 passes the schema, and would still poison every TD
        target it reaches."""
        ok = env.pays_for_a_move(self.reward)
        if self.terminated:
            ok[-1] = self.reward[-1] == np.float32(env.reward_collision)
        if not ok.all():
            bad = int(np.flatnonzero(~ok)[0])
            raise MessageError(RANGE, f"reward[{bad}] = {float(self.reward[bad])!r}: this task pays "
                                      f"{env.describe_rewards()}")
        deepest = max(int(self.depth_mm.max()), 0 if self.next_depth_mm is None else int(self.next_depth_mm.max()))
        if deepest > max_depth_mm:
            raise MessageError(RANGE, f"depth {deepest} mm is beyond the sensor's range ({max_depth_mm} mm)")
        if float(np.abs(self.pose[:, :2]).max()) > max_abs_xy_m:
            raise MessageError(RANGE, f"a position is more than {max_abs_xy_m} m from the origin")

    def require_frame_shape(self, height: int, width: int) -> None:
        """Raise MessageError(SHAPE) unless frames are ``height`` x ``width`` (the receiver's sensor)."""
        if self.frame_shape != (height, width):
            raise MessageError(SHAPE, f"frames are {self.frame_shape[0]}x{self.frame_shape[1]}, "
                                      f"this receiver expects {height}x{width}")

    @classmethod
    def from_steps(cls, *, actor_id: str, episode: int, first_step: int, start_index: int,
                   depth: Sequence[np.ndarray] | np.ndarray, next_depth: np.ndarray | None,
                   action: Sequence[int], reward: Sequence[float], policy_version: Sequence[int],
                   pose: Sequence[Sequence[float]], terminated: bool = False,
                   truncated: bool = False, actor_epoch: int = 0,
                   expert_action: Sequence[int | None] | None = None,
                   safe_commands: Sequence[int] | None = None) -> "TransitionBatch":
        """Build from per-step lists. Float depth is taken as metres and converted to mm;
        uint16 depth is taken as mm already. ``expert_action``: the expert's command per step
        (None where it named none); None, or None at every step: no labels. ``safe_commands``: the
        expert's safe-set bitmask per step (0: no mark); None, or 0 at every step: no marks."""

        def frames(x: Any) -> np.ndarray:
            x = np.asarray(x)
            return depth_to_mm(x)

        action_list = [int(a) for a in action]
        if any(not 0 <= a < NUM_ACTIONS for a in action_list):
            raise MessageError(RANGE, f"actions {action_list} must be in [0, {NUM_ACTIONS - 1}]")
        if safe_commands is not None and any(not 0 <= int(m) <= ALL_COMMANDS_MASK for m in safe_commands):
            raise MessageError(RANGE, f"safe_commands {list(safe_commands)} must be bitmasks in [0, {ALL_COMMANDS_MASK}]")
        return cls(actor_id=actor_id, episode=episode, first_step=first_step,
                   start_index=start_index, actor_epoch=actor_epoch, depth_mm=frames(depth),
                   next_depth_mm=None if next_depth is None else frames(next_depth),
                   action=np.asarray(action_list, dtype=np.uint8),
                   reward=np.asarray(reward, dtype=np.float32),
                   policy_version=np.asarray(policy_version, dtype=np.int64),
                   pose=np.asarray(pose, dtype=np.float32).reshape(-1, 3),
                   terminated=terminated, truncated=truncated,
                   expert_action=None if expert_action is None or all(a is None for a in expert_action) else
                   np.asarray([NO_EXPERT_LABEL if a is None else int(a) for a in expert_action], dtype=np.uint8),
                   safe_commands=None if safe_commands is None or not any(safe_commands) else
                   np.asarray(safe_commands, dtype=np.uint8))


def shape_fingerprint(named_shapes: Mapping[str, Sequence[int]],
                             config: Mapping[str, Any] | None = None) -> str:
    """A short stable hash of parameter names and shapes (and optionally a config mapping).

    Two models get the same fingerprint exactly when their tensors line up name by name and
    shape by shape (and their configs match), so weights can be loaded without surprises.
    Pass e.g. ``{k: tuple(v.shape) for k, v in model.state_dict().items()}``.
    """
    if not isinstance(named_shapes, Mapping) or not named_shapes:
        raise ValueError("named_shapes must be a non-empty mapping of name -> shape")
    items = []
    for name, shape in sorted(named_shapes.items()):
        dims = [int(n) for n in shape]
        if not isinstance(name, str) or any(n < 0 for n in dims):
            raise ValueError(f"bad entry {name!r}: {shape!r} (want str -> non-negative ints)")
        items.append([name, dims])
    canonical = json.dumps({"params": items, "config": config or {}}, sort_keys=True,
                           separators=(",", ":"), default=str)
    return "sha256:" + hashlib.sha256(canonical.encode()).hexdigest()[:16]


@_register
@dataclass(frozen=True, eq=False)
class WeightsMessage(Message):
    """Network weights: ``(policy_version, architecture_fingerprint, tensors)``, from the learner
    process that started at ``learner_epoch``.

    ``tensors`` maps parameter names to float32/float16 arrays (e.g. a state_dict moved to
    numpy); NaN and Inf are rejected. A receiver follows one learner process
    (:class:`LearnerEpochs`) and, within it, the highest update: a restarted learner's weights
    replace a dead one's once it has fallen quiet, whatever their updates.
    """

    TYPE: ClassVar[str] = "weights"
    MAX_BYTES: ClassVar[int] = MAX_MESSAGE_BYTES

    policy_version: int
    architecture_fingerprint: str
    tensors: dict[str, np.ndarray] = field(metadata={"wire": _WIRE_TENSORS})
    learner_epoch: int = 0
    """When the learner process started (ns since the epoch)."""

    def __post_init__(self) -> None:
        _set(self, "policy_version", _int(self.policy_version, "policy_version", hi=MAX_POLICY_VERSION))
        _set(self, "learner_epoch", _int(self.learner_epoch, "learner_epoch"))
        _set(self, "architecture_fingerprint",
             _text(self.architecture_fingerprint, "architecture_fingerprint", 128))
        if not isinstance(self.tensors, Mapping):
            raise MessageError(FIELD_TYPE, "tensors must be a map of name -> array")
        if not self.tensors:
            raise MessageError(RANGE, "tensors must not be empty")
        if len(self.tensors) > MAX_TENSORS:
            raise MessageError(OVERSIZE, f"{len(self.tensors)} tensors (max {MAX_TENSORS})")
        total = 0
        for name, arr in self.tensors.items():
            _text(name, "tensor name", MAX_NAME_CHARS)
            if not isinstance(arr, np.ndarray):
                raise MessageError(FIELD_TYPE, f"tensor {name!r} must be a numpy array")
            if arr.dtype.newbyteorder("<") not in (np.dtype("<f4"), np.dtype("<f2")):
                raise MessageError(DTYPE, f"tensor {name!r} is {arr.dtype}; allowed: {list(WEIGHT_DTYPES)}")
            if arr.ndim > MAX_TENSOR_NDIM:
                raise MessageError(SHAPE, f"tensor {name!r} has {arr.ndim} dims (max {MAX_TENSOR_NDIM})")
            total += arr.nbytes
            if total > MAX_WEIGHTS_BYTES:
                raise MessageError(OVERSIZE, f"tensors exceed {MAX_WEIGHTS_BYTES} bytes")
        for name, arr in self.tensors.items():  # after the cheap checks: isfinite reads everything
            _finite_array(arr, f"tensor {name!r}")
        _set(self, "tensors", dict(self.tensors))

    @property
    def version(self) -> tuple[int, int]:
        """(learner epoch, update): the order in which receivers take weights."""
        return self.learner_epoch, self.policy_version

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.tensors.values())

    def named_shapes(self) -> dict[str, tuple[int, ...]]:
        return {k: tuple(int(n) for n in v.shape) for k, v in self.tensors.items()}

    def check_fingerprint(self, expected: str) -> None:
        """Raise MessageError(FINGERPRINT) unless these weights fit the receiver's architecture."""
        if self.architecture_fingerprint != expected:
            raise MessageError(FINGERPRINT, f"weights v{self.policy_version} are for architecture "
                                            f"{self.architecture_fingerprint}, this model is {expected}")


@_register
@dataclass(frozen=True)
class EpisodeStats(Message):
    """One finished episode of an actor. Figures without a field of their own travel in ``extra``
    (old peers decode them as it is), under the names below."""

    TYPE: ClassVar[str] = "episode_stats"
    HELD_S: ClassVar[str] = "held_s"
    """``extra`` key: seconds of the episode in which the actor was held by the learner's flow
    control (out of credit: the learner is behind the replay ratio)."""
    REJECTED: ClassVar[str] = "rejected_messages"
    """``extra`` key: the messages (weights, flow control) the actor has rejected since it started,
    so an operator, or ``bench fuzz``, sees them while the run goes on."""

    actor_id: str
    episode: int
    start_index: int
    steps: int
    """Transitions in the episode."""
    episode_return: float
    terminated: bool
    """Ended in a collision."""
    truncated: bool
    """Hit the step cap."""
    collision_cause: str | None
    """'depth' or 'contact' when terminated, else None."""
    path_length_m: float
    distance_from_start_m: float
    epsilon: float
    """Exploration rate at the episode's end."""
    policy_version: int
    """Weights version at the episode's end."""
    duration_s: float
    """Wall-clock seconds the episode took."""
    extra: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _set(self, "actor_id", _chunk(self.actor_id, "actor_id"))
        for name in ("episode", "start_index", "steps", "policy_version"):
            _set(self, name, _int(getattr(self, name), name))
        _set(self, "episode_return", _float(self.episode_return, "episode_return"))
        _set(self, "terminated", _bool(self.terminated, "terminated"))
        _set(self, "truncated", _bool(self.truncated, "truncated"))
        if self.collision_cause is not None and self.collision_cause not in COLLISION_CAUSES:
            raise MessageError(RANGE, f"collision_cause {self.collision_cause!r} is not one of "
                                      f"{list(COLLISION_CAUSES)} or None")
        if (self.collision_cause is not None) != self.terminated:
            raise MessageError(INCONSISTENT, "collision_cause must be set exactly when terminated")
        for name in ("path_length_m", "distance_from_start_m", "duration_s"):
            _set(self, name, _float(getattr(self, name), name, lo=0.0))
        _set(self, "epsilon", _float(self.epsilon, "epsilon", 0.0, 1.0))
        _set(self, "extra", _extra(self.extra))


@_register
@dataclass(frozen=True)
class LearnerStats(Message):
    """A periodic report of the learner. Figures without a field of their own travel in ``extra``
    (old peers decode them as it is), under the names below."""

    TYPE: ClassVar[str] = "learner_stats"
    WAITING_SHARE: ClassVar[str] = "waiting_share"
    """``extra`` key: the share of the time since the last report in which no update was due, so the
    learner waited for data (warm-up, or actors slower than the replay ratio allows). Near 0 the
    learner is the limit and the actors are held by flow control."""

    learner_id: str
    updates: int
    policy_version: int
    replay_size: int
    transitions_received: int
    transitions_rejected: int
    loss: float | None
    """Mean loss since the last report (None before the first update)."""
    mean_q: float | None
    updates_per_s: float
    transitions_per_s: float
    uptime_s: float
    rejects: dict[str, int] = field(default_factory=dict)
    """Rejected messages by cause (see CAUSES)."""
    extra: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _set(self, "learner_id", _chunk(self.learner_id, "learner_id"))
        for name in ("updates", "policy_version", "replay_size", "transitions_received",
                     "transitions_rejected"):
            _set(self, name, _int(getattr(self, name), name))
        _set(self, "loss", _opt_float(self.loss, "loss"))
        _set(self, "mean_q", _opt_float(self.mean_q, "mean_q"))
        for name in ("updates_per_s", "transitions_per_s", "uptime_s"):
            _set(self, name, _float(getattr(self, name), name, lo=0.0))
        if not isinstance(self.rejects, Mapping):
            raise MessageError(FIELD_TYPE, "rejects must be a map of cause -> count")
        if len(self.rejects) > MAX_EXTRA_ITEMS:
            raise MessageError(OVERSIZE, f"rejects has {len(self.rejects)} items")
        _set(self, "rejects", {_text(k, "rejects key", MAX_NAME_CHARS): _int(v, f"rejects[{k!r}]")
                               for k, v in self.rejects.items()})
        _set(self, "extra", _extra(self.extra))


@_register
@dataclass(frozen=True)
class FlowControl(Message):
    """The learner's credit to the actors: it wants transitions until it has received
    ``transitions_wanted`` in all, which keeps updates per inserted transition at the
    configured replay ratio instead of letting fast actors flood a slow learner (and take its
    CPU). ``received_from`` counts what the learner has received from each actor process (the one
    of ``actor_epochs``), so that an actor can tell its transitions still in flight from those
    already counted, and a restarted actor starts from nothing, not from its predecessor's count."""

    TYPE: ClassVar[str] = "flow"

    learner_id: str
    updates: int
    transitions_received: int
    transitions_wanted: int
    received_from: dict[str, int] = field(default_factory=dict)
    actor_epochs: dict[str, int] = field(default_factory=dict)
    """The actor process (its ``actor_epoch``) each ``received_from`` count belongs to."""
    learner_epoch: int = 0
    """When the learner process started (ns since the epoch)."""

    def __post_init__(self) -> None:
        _set(self, "learner_id", _chunk(self.learner_id, "learner_id"))
        for name in ("updates", "transitions_received", "transitions_wanted", "learner_epoch"):
            _set(self, name, _int(getattr(self, name), name))
        for name in ("received_from", "actor_epochs"):
            value = getattr(self, name)
            if not isinstance(value, Mapping):
                raise MessageError(FIELD_TYPE, f"{name} must be a map of actor id -> integer")
            if len(value) > MAX_TENSORS:
                raise MessageError(OVERSIZE, f"{name} has {len(value)} actors")
            _set(self, name, {_chunk(k, f"{name} key"): _int(v, f"{name}[{k!r}]") for k, v in value.items()})

    @property
    def credit(self) -> int:
        """Transitions the learner still wants (<= 0: hold)."""
        return self.transitions_wanted - self.transitions_received


@_register
@dataclass(frozen=True)
class EvalResult(Message):
    """The test protocol run on one weights version: one entry per episode (start pose)."""

    TYPE: ClassVar[str] = "eval_result"
    MAX_BYTES: ClassVar[int] = 4 * 2**20

    evaluator_id: str
    policy_version: int
    world: str
    speed_table: str
    max_steps: int
    start_index: tuple[int, ...] = _tup()
    steps: tuple[int, ...] = _tup()
    """Steps before the episode ended (== max_steps when it never collided)."""
    collided: tuple[bool, ...] = _tup()
    path_length_m: tuple[float, ...] = _tup()
    extra: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _set(self, "evaluator_id", _chunk(self.evaluator_id, "evaluator_id"))
        _set(self, "policy_version", _int(self.policy_version, "policy_version"))
        _set(self, "world", _text(self.world, "world"))
        _set(self, "speed_table", _text(self.speed_table, "speed_table", MAX_NAME_CHARS))
        _set(self, "max_steps", _int(self.max_steps, "max_steps", lo=1))
        columns = ("start_index", "steps", "collided", "path_length_m")
        for name in columns:
            value = getattr(self, name)
            if not isinstance(value, (tuple, list)):
                raise MessageError(FIELD_TYPE, f"{name} must be a sequence")
            if len(value) > MAX_EVAL_EPISODES:
                raise MessageError(OVERSIZE, f"{name} has {len(value)} entries (max {MAX_EVAL_EPISODES})")
        n = len(self.start_index)
        if n == 0 or any(len(getattr(self, c)) != n for c in columns):
            raise MessageError(INCONSISTENT, "start_index, steps, collided and path_length_m must "
                                             "have the same non-zero length")
        _set(self, "start_index", tuple(_int(v, "start_index") for v in self.start_index))
        _set(self, "steps", tuple(_int(v, "steps", 0, self.max_steps) for v in self.steps))
        _set(self, "collided", tuple(_bool(v, "collided") for v in self.collided))
        _set(self, "path_length_m", tuple(_float(v, "path_length_m", lo=0.0) for v in self.path_length_m))
        _set(self, "extra", _extra(self.extra))

    @property
    def episodes(self) -> int:
        return len(self.steps)

    @property
    def mean_steps(self) -> float:
        """The paper's figure of merit: mean steps before collision (capped at max_steps)."""
        return sum(self.steps) / len(self.steps)


@_register
@dataclass(frozen=True)
class RunConfigMessage(Message):
    """The configuration a run's learner trains with, the whole :class:`~shared.config.RunConfig` as
    its sections' tables: what an actor or the evaluator started without a preset takes, and what one
    started with a preset is checked against (``shared.config.require_same_run``). Built from a
    RunConfig or its ``to_dict()``; every field is validated as a preset's are."""

    TYPE: ClassVar[str] = "run_config"
    MAX_BYTES: ClassVar[int] = 64 * 1024

    learner_id: str
    config: dict[str, dict[str, Any]]

    def __post_init__(self) -> None:
        _set(self, "learner_id", _chunk(self.learner_id, "learner_id"))
        config = self.config
        if not isinstance(config, RunConfig):
            try:
                config = from_dict(config)
            except ConfigError as exc:
                raise MessageError(RANGE, f"config: {exc}") from None
            except TypeError as exc:  # names that are not all text (msgpack keys may be bytes)
                raise MessageError(FIELD_TYPE, f"config: {exc}") from None
        _set(self, "config", config.to_dict())

    @property
    def run_config(self) -> RunConfig:
        return from_dict(self.config)


# ---------------------------------------------------------------------------------------------
# Counting rejects
# ---------------------------------------------------------------------------------------------

MAX_LOGGED_CHARS = 500
"""The most characters of a key or reject message a log line carries."""


def printable(text: object, max_chars: int = MAX_LOGGED_CHARS) -> str:
    """``text`` for a log line: every character printable or escaped (``\\n``, ``\\x1b``), at most
    ``max_chars``. A key or a field value is chosen by whoever sent the message: raw, a line break in it
    wrote a log line of the sender's own making, and an escape code recoloured the operator's terminal."""
    text = str(text)
    if not text.isprintable():
        text = "".join(ch if ch.isprintable() else repr(ch)[1:-1] for ch in text)
    return text if len(text) <= max_chars else text[:max_chars] + "..."


class RejectCounter:
    """Counts rejected messages by cause and logs the first reject of each cause.

    Thread-safe: Zenoh callbacks run on Zenoh's threads.
    """

    def __init__(self, what: str = "message", logger: logging.Logger | None = None) -> None:
        self.what = what
        self._log = logger or logging.getLogger(__name__)
        self._counts: dict[str, int] = {}
        self._lock = threading.Lock()

    def reject(self, error: MessageError, source: str | None = None) -> None:
        """Count ``error``; log it if it is the first of its cause."""
        with self._lock:
            first = error.cause not in self._counts
            self._counts[error.cause] = self._counts.get(error.cause, 0) + 1
        if first:
            origin = f" from {printable(source)}" if source else ""
            self._log.warning("rejected %s%s: %s (later '%s' rejects are counted, not logged)",
                              self.what, origin, printable(error), error.cause)

    def decode(self, data: bytes | bytearray | memoryview, cls: type[M] | None = None,
               source: str | None = None) -> M | Message | None:
        """Decode ``data`` as ``cls`` (any type if None); on MessageError count it and return None.
        Any other exception is a decoder bug that bytes from the network reached: counted as
        garbage, never raised into a Zenoh thread (which logs a traceback per message, uncounted)."""
        try:
            return cls.decode(data) if cls is not None else decode_message(data)
        except MessageError as exc:
            self.reject(exc, source)
        except Exception as exc:  # noqa: BLE001 (see above)
            self.reject(MessageError(GARBAGE, f"undecodable ({type(exc).__name__}: {exc})"), source)
        return None

    @property
    def counts(self) -> dict[str, int]:
        """A copy of the counts by cause."""
        with self._lock:
            return dict(self._counts)

    @property
    def total(self) -> int:
        with self._lock:
            return sum(self._counts.values())
