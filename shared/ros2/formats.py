"""How a ROS 2 topic appears on Zenoh, in the two wire formats ROS 2 speaks there.

**rmw_zenoh** (:class:`RmwZenohFormat`), the native Zenoh RMW, tier 1 since Jazzy. Every rule
below is taken from ros2/rmw_zenoh (rolling and jazzy branches, zenoh-cpp 1.x generation):

- data key ``<domain_id>/<fully qualified topic, leading '/' stripped>/<DDS type name>/<RIHS01
  hash>``, e.g. ``0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df66...``
  (``docs/design.md`` "Topic and Service name mapping to Zenoh key expressions";
  ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` ``TopicInfo::TopicInfo``, ``strip_slashes``).
  Subscriptions declare the very same key, type hash included, no wildcard
  (``rmw_zenoh_cpp/src/detail/rmw_subscription_data.cpp`` ``SubscriptionData::init``), so only
  publishers of the identical type definition are received.
- liveliness tokens ``@ros2_lv/<domain>/<zid>/<node id>/<entity id>/<NN|MP|MS>/<enclave>/
  <namespace>/<node>[/<topic>/<type>/<hash>/<qos>]``, every name "mangled" ('/' -> '%'), an
  empty namespace or enclave written ``%`` (``liveliness_utils.cpp``: ``KeyexprIndex``,
  ``ADMIN_SPACE``, ``NODE_STR``/``PUB_STR``/``SUB_STR``, ``mangle_name``; ``docs/design.md``
  "Graph Cache"). A node's token repeats its id as entity id (``design.md``: ``.../0/0/NN/...``).
  Node and entity ids come from one counter per context (``rmw_context_impl_s.cpp``
  ``get_next_entity_id``); we keep one per process, unique within every session all the same.
- the QoS component (``liveliness_utils.cpp`` ``qos_to_keyexpr``):
  ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
  <liveliness>,<lease s>,<ns>``, each field left empty when it equals rmw_zenoh's default profile
  (reliable, volatile, keep_last 42, infinite durations, automatic liveliness:
  ``rmw_zenoh_cpp/src/detail/qos.cpp``), numbers being the rmw enums (ros2/rmw
  ``rmw/include/rmw/types.h``: reliable 1, best_effort 2; transient_local 1, volatile 2;
  keep_last 1, keep_all 2). Keep-last 10 reliable thus reads ``::,10:,:,:,,`` (the ``design.md``
  listener example) and the sensor-data profile (best effort, keep_last 5) ``2::,5:,:,:,,``.
- every sample carries an attachment: int64 sequence number (from 1, +1 per sample), int64
  source timestamp (ns since the epoch), and the 16-byte publisher GID, written with zenoh-cpp's
  ``zenoh::ext::Serializer`` (``rmw_zenoh_cpp/src/detail/attachment_helpers.cpp``
  ``AttachmentData::serialize_to_zbytes``). That serializer writes integers little endian and a
  ``std::array<uint8_t, 16>`` as a sequence: LEB128 length (one byte, 0x10) then the bytes
  (eclipse-zenoh/zenoh-cpp ``include/zenoh/api/ext/serialization.hxx``), 33 bytes in all, as
  ``design.md`` "Publishers" documents. A subscription drops samples without it
  (``rmw_subscription_data.cpp``: "Unable to obtain attachment"). rmw_zenoh derives the GID from
  an XXH3-128 hash of the entity's token (``liveliness_utils.cpp`` ``Entity::Entity``); nothing
  on the receiving side checks it against the token, so ours are random per publisher.
- no encoding is set on samples (``rmw_zenoh_cpp/src/detail/rmw_publisher_data.cpp``: "The
  encoding is simply forwarded ... it does not really matter").
- not implemented: rolling's buffer-aware endpoints of 2026 (``<key>/_buf_cpu``,
  ``rmw_zenoh_cpp/src/detail/buffer_endpoint_helpers.hpp``), used only for types with rosidl
  buffer fields and by publishers that have buffer backends; Jazzy has none of it.

**zenoh-bridge-ros2dds** (:class:`Ros2DdsFormat`), eclipse-zenoh/zenoh-plugin-ros2dds, which
bridges a robot's DDS traffic to Zenoh:

- the key is the fully qualified topic without its leading '/', prefixed by the bridge's
  ``namespace`` option when it has one (``zenoh-plugin-ros2dds/src/ros2_utils.rs``
  ``ros2_name_to_key_expr``; ``DEFAULT_CONFIG.json5`` "namespace": a "cmd_vel" topic in the
  robot is seen as "namespace/cmd_vel" outside). No domain, type or hash in the key. So a robot
  whose bridge runs with ``namespace: "/bot1"`` is reached with our namespace ``/bot1``.
- payloads are the raw DDS samples, CDR with their encapsulation header
  (``src/route_publisher.rs`` ``route_dds_message_to_zenoh``; ``src/route_subscriber.rs``
  ``route_zenoh_message_to_dds`` writes what it receives with ``dds_writecdr``); no attachment.
- the bridge's own liveliness tokens (``@/<zid>/@ros2_lv/MP|MS/...``, ``src/liveliness_mgt.rs``)
  only announce routes between bridges. Data flows without them: a route towards a robot's DDS
  reader subscribes to its key as soon as that reader exists (``route_subscriber.rs``), and a
  route from a DDS writer starts reading when any Zenoh subscriber matches its key
  (``route_publisher.rs``: ``matching_listener``). So this format declares no tokens.
"""

from __future__ import annotations

import re
import struct
from abc import ABC, abstractmethod
from dataclasses import dataclass

from shared.errors import CogexploreError
from shared.ros2.messages import GARBAGE, Ros2MessageError, dds_type_name, type_hash


class Ros2NameError(CogexploreError):
    """A ROS 2 node name, namespace or topic name that ROS 2 would refuse."""


class Ros2FormatError(CogexploreError):
    """An unknown ROS 2 wire format, or settings it cannot take (a negative domain id)."""


# ---------------------------------------------------------------------------------------------
# Names
# ---------------------------------------------------------------------------------------------

# A token of a ROS 2 name: letters, digits and '_', not starting with a digit (design.ros2.org
# "Topic and Service name mapping to DDS"; rcl's validate_topic_name).
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def _check_tokens(name: str, what: str, tokens: list[str]) -> None:
    for token in tokens:
        if not _TOKEN.fullmatch(token):
            raise Ros2NameError(f"{what} {name!r} is not a valid ROS 2 name: "
                                f"{'an empty part (//)' if not token else repr(token)} "
                                "(names use letters, digits, '_' and '/', no part starts with a digit, no '//')")


def check_node_name(name: str) -> str:
    """``name`` if it is a valid ROS 2 node name (one token), else Ros2NameError."""
    if not isinstance(name, str) or not name:
        raise Ros2NameError(f"node name {name!r} must be a non-empty string")
    _check_tokens(name, "node name", [name])
    return name


def normalize_namespace(namespace: str) -> str:
    """An absolute namespace: ``""`` and ``"/"`` -> ``"/"``, ``"bot1"`` -> ``"/bot1"``, ``"/a/b"`` stays."""
    if not isinstance(namespace, str):
        raise Ros2NameError(f"namespace {namespace!r} must be a string")
    if namespace in ("", "/"):
        return "/"
    absolute = namespace if namespace.startswith("/") else "/" + namespace
    if absolute.endswith("/"):
        raise Ros2NameError(f"namespace {namespace!r} must not end with '/'")
    _check_tokens(namespace, "namespace", absolute[1:].split("/"))
    return absolute


def qualify(namespace: str, topic: str) -> str:
    """The fully qualified name of ``topic`` in ``namespace``: ``("/", "cmd_vel")`` ->
    ``"/cmd_vel"``, ``("/bot1", "cmd_vel")`` -> ``"/bot1/cmd_vel"``; an absolute topic (``"/x"``)
    stays as it is. Private (``~``) and substituted (``{node}``) names are not supported."""
    namespace = normalize_namespace(namespace)
    if not isinstance(topic, str) or not topic or topic == "/":
        raise Ros2NameError(f"topic {topic!r} must be a non-empty ROS 2 name")
    if topic.endswith("/"):
        raise Ros2NameError(f"topic {topic!r} must not end with '/'")
    if topic.startswith("/"):
        full = topic
    else:
        full = ("" if namespace == "/" else namespace) + "/" + topic
    _check_tokens(topic, "topic", full[1:].split("/"))
    return full


def _mangle(name: str) -> str:
    # rmw_zenoh's mangle_name: '/' would split a key expression chunk, '%' cannot be in a ROS name.
    return name.replace("/", "%")


# ---------------------------------------------------------------------------------------------
# QoS
# ---------------------------------------------------------------------------------------------

RELIABILITIES = ("reliable", "best_effort")
DURABILITIES = ("volatile", "transient_local")
HISTORIES = ("keep_last", "keep_all")

# rmw enum values (ros2/rmw rmw/include/rmw/types.h).
_RMW_RELIABILITY = {"reliable": 1, "best_effort": 2}
_RMW_DURABILITY = {"transient_local": 1, "volatile": 2}
_RMW_HISTORY = {"keep_last": 1, "keep_all": 2}


@dataclass(frozen=True)
class QosProfile:
    """The QoS policies of a ROS 2 publisher or subscription that cogexplore sets; deadline,
    lifespan and liveliness are always ROS 2's defaults (infinite, automatic)."""

    reliability: str = "reliable"
    """'reliable' or 'best_effort'."""
    durability: str = "volatile"
    """'volatile' or 'transient_local' (announced only: this node keeps no history)."""
    history: str = "keep_last"
    """'keep_last' or 'keep_all'."""
    depth: int = 10
    """Queue depth for keep_last (rclcpp's usual 10)."""

    def __post_init__(self) -> None:
        for field, allowed in (("reliability", RELIABILITIES), ("durability", DURABILITIES),
                               ("history", HISTORIES)):
            if getattr(self, field) not in allowed:
                raise Ros2FormatError(f"QoS {field} {getattr(self, field)!r} is invalid: use one of {list(allowed)}")
        if isinstance(self.depth, bool) or not isinstance(self.depth, int) or self.depth < 0:
            raise Ros2FormatError(f"QoS depth must be an int >= 0, got {self.depth!r}")

    @property
    def reliable(self) -> bool:
        return self.reliability == "reliable"


QOS_PROFILES: dict[str, QosProfile] = {
    "default": QosProfile(),
    "sensor_data": QosProfile(reliability="best_effort", depth=5),
}
"""Named profiles: rclcpp's ``QoS(10)`` and ``SensorDataQoS()`` (rmw_qos_profile_sensor_data)."""


def qos_profile(qos: str | QosProfile) -> QosProfile:
    """A profile by name (:data:`QOS_PROFILES`) or as given."""
    if isinstance(qos, QosProfile):
        return qos
    if qos not in QOS_PROFILES:
        raise Ros2FormatError(f"QoS profile {qos!r} is unknown: use one of {list(QOS_PROFILES)} or a QosProfile")
    return QOS_PROFILES[qos]


# rmw_zenoh's default profile (rmw_zenoh_cpp/src/detail/qos.cpp): fields equal to it are left empty.
_RMW_ZENOH_DEFAULT = QosProfile(reliability="reliable", durability="volatile", history="keep_last", depth=42)


def rmw_zenoh_qos(qos: str | QosProfile) -> str:
    """The QoS chunk of an rmw_zenoh liveliness token (``qos_to_keyexpr``)."""
    qos = qos_profile(qos)
    default = _RMW_ZENOH_DEFAULT

    def field(value: object, default_value: object, text: str) -> str:
        return "" if value == default_value else text

    reliability = field(qos.reliability, default.reliability, str(_RMW_RELIABILITY[qos.reliability]))
    durability = field(qos.durability, default.durability, str(_RMW_DURABILITY[qos.durability]))
    history = field(qos.history, default.history, str(_RMW_HISTORY[qos.history]))
    depth = field(qos.depth, default.depth, str(qos.depth))
    # deadline, lifespan (sec,nsec) and liveliness (kind,sec,nsec) are rmw_zenoh's defaults: empty
    return f"{reliability}:{durability}:{history},{depth}:,:,:,,"


# ---------------------------------------------------------------------------------------------
# Entities
# ---------------------------------------------------------------------------------------------

GID_BYTES = 16
"""Size of a publisher GID in rmw_zenoh attachments."""


@dataclass(frozen=True)
class NodeInfo:
    """A ROS 2 node as the wire formats name it."""

    name: str
    """Node name (one ROS 2 name token)."""
    namespace: str = "/"
    """Absolute namespace ('/' for none)."""
    zid: str = "0"
    """Zenoh id of the session the node lives in (``str(session.zid())``)."""
    node_id: int = 0
    """Id of the node within its session."""
    enclave: str = "/"
    """SROS enclave ('/' for none, as rcl sets by default)."""

    def __post_init__(self) -> None:
        check_node_name(self.name)
        object.__setattr__(self, "namespace", normalize_namespace(self.namespace))


@dataclass(frozen=True)
class PublisherInfo:
    """One publisher of a node: what its token and attachments are made of."""

    node: NodeInfo
    """The node it belongs to."""
    entity_id: int
    """Id of the publisher within the session (never the id of another entity)."""
    topic: str
    """Fully qualified topic name (:func:`qualify`)."""
    msgtype: str
    """ROS 2 type, e.g. 'geometry_msgs/msg/Twist'."""
    qos: QosProfile
    """Its QoS."""
    gid: bytes
    """Its 16-byte GID."""

    def __post_init__(self) -> None:
        if len(self.gid) != GID_BYTES:
            raise Ros2FormatError(f"a publisher GID has {GID_BYTES} bytes, got {len(self.gid)}")


_ATTACHMENT = struct.Struct("<qqB")  # int64 LE sequence number, int64 LE timestamp, LEB128 length 16
ATTACHMENT_BYTES = _ATTACHMENT.size + GID_BYTES


def decode_attachment(data: bytes | bytearray | memoryview) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, GID) of an rmw_zenoh attachment."""
    data = bytes(data)
    if len(data) != ATTACHMENT_BYTES or data[_ATTACHMENT.size - 1] != GID_BYTES:
        raise Ros2MessageError(GARBAGE, f"an rmw_zenoh attachment has {ATTACHMENT_BYTES} bytes "
                               f"(int64, int64, 0x10, 16-byte gid), got {data.hex()}")
    sequence_number, timestamp_ns, _ = _ATTACHMENT.unpack_from(data)
    return sequence_number, timestamp_ns, data[_ATTACHMENT.size:]


# ---------------------------------------------------------------------------------------------
# The formats
# ---------------------------------------------------------------------------------------------

class Ros2Format(ABC):
    """Key expressions, liveliness tokens and attachments of one ROS 2 wire format. Topics are
    fully qualified names (:func:`qualify`); a method returning None means the format has no
    such thing."""

    name: str = ""

    @abstractmethod
    def data_key(self, topic: str, msgtype: str) -> str:
        """The key samples of ``topic`` are put on."""

    def subscriber_key(self, topic: str, msgtype: str) -> str:
        """The key a subscriber declares to receive ``topic`` from ROS 2 publishers."""
        return self.data_key(topic, msgtype)

    def node_token(self, node: NodeInfo) -> str | None:
        """The liveliness token announcing ``node``."""
        return None

    def publisher_token(self, node: NodeInfo, topic: str, msgtype: str, qos: str | QosProfile, *,
                        entity_id: int) -> str | None:
        """The liveliness token announcing a publisher of ``node`` on ``topic``."""
        return None

    def subscriber_token(self, node: NodeInfo, topic: str, msgtype: str, qos: str | QosProfile, *,
                         entity_id: int) -> str | None:
        """The liveliness token announcing a subscription of ``node`` to ``topic``."""
        return None

    def attachment(self, publisher: PublisherInfo, sequence_number: int, timestamp_ns: int) -> bytes | None:
        """The attachment of a sample ``publisher`` sends."""
        return None

    def __repr__(self) -> str:
        return f"{type(self).__name__}()"


def _check_domain_id(domain_id: int) -> int:
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise Ros2FormatError(f"ROS domain id must be an int >= 0, got {domain_id!r}")
    return domain_id


def _fully_qualified(topic: str) -> str:
    if not isinstance(topic, str) or not topic.startswith("/"):
        raise Ros2NameError(f"topic {topic!r} must be fully qualified (see qualify())")
    return qualify("/", topic)


class RmwZenohFormat(Ros2Format):
    """rmw_zenoh's keys, tokens and attachments (see the module docstring for the sources)."""

    name = "rmw_zenoh"

    def __init__(self, domain_id: int = 0) -> None:
        self.domain_id = _check_domain_id(domain_id)

    def data_key(self, topic: str, msgtype: str) -> str:
        topic = _fully_qualified(topic)
        return f"{self.domain_id}/{topic[1:]}/{dds_type_name(msgtype)}/{type_hash(msgtype)}"

    def _node_prefix(self, node: NodeInfo, entity_id: int, kind: str) -> str:
        return (f"@ros2_lv/{self.domain_id}/{node.zid}/{node.node_id}/{entity_id}/{kind}/"
                f"{_mangle(node.enclave)}/{_mangle(node.namespace)}/{_mangle(node.name)}")

    def node_token(self, node: NodeInfo) -> str:
        return self._node_prefix(node, node.node_id, "NN")

    def _topic_token(self, node: NodeInfo, topic: str, msgtype: str, qos: str | QosProfile,
                     entity_id: int, kind: str) -> str:
        topic = _fully_qualified(topic)
        return (f"{self._node_prefix(node, entity_id, kind)}/{_mangle(topic)}/"
                f"{dds_type_name(msgtype)}/{type_hash(msgtype)}/{rmw_zenoh_qos(qos)}")

    def publisher_token(self, node: NodeInfo, topic: str, msgtype: str, qos: str | QosProfile, *,
                        entity_id: int) -> str:
        return self._topic_token(node, topic, msgtype, qos, entity_id, "MP")

    def subscriber_token(self, node: NodeInfo, topic: str, msgtype: str, qos: str | QosProfile, *,
                         entity_id: int) -> str:
        return self._topic_token(node, topic, msgtype, qos, entity_id, "MS")

    def attachment(self, publisher: PublisherInfo, sequence_number: int, timestamp_ns: int) -> bytes:
        return _ATTACHMENT.pack(sequence_number, timestamp_ns, GID_BYTES) + bytes(publisher.gid)

    def __repr__(self) -> str:
        return f"RmwZenohFormat(domain_id={self.domain_id})"


class Ros2DdsFormat(Ros2Format):
    """zenoh-bridge-ros2dds' plain topic keys (see the module docstring for the sources)."""

    name = "ros2dds"

    def data_key(self, topic: str, msgtype: str) -> str:
        return _fully_qualified(topic)[1:]


FORMATS: dict[str, type[Ros2Format]] = {RmwZenohFormat.name: RmwZenohFormat, Ros2DdsFormat.name: Ros2DdsFormat}
"""The wire formats by their ``--ros2-format`` name."""


def make_format(name: str, *, domain_id: int = 0) -> Ros2Format:
    """The format called ``name``; ``domain_id`` is rmw_zenoh's ROS_DOMAIN_ID (the bridge's DDS
    domain is set on the bridge, and never appears in its keys)."""
    _check_domain_id(domain_id)  # in either format, so a bad --domain-id never passes unnoticed
    if name == RmwZenohFormat.name:
        return RmwZenohFormat(domain_id)
    if name == Ros2DdsFormat.name:
        return Ros2DdsFormat()
    raise Ros2FormatError(f"ROS 2 wire format {name!r} is unknown: use one of {list(FORMATS)}")
