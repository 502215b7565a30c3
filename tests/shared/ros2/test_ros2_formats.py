"""Key expressions, liveliness tokens and attachments of both wire formats, against the strings the
repositories document (copied verbatim, source in the comment)."""

from __future__ import annotations

import pytest
import zenoh.ext

from shared.ros2.formats import (
    ATTACHMENT_BYTES,
    FORMATS,
    NodeInfo,
    PublisherInfo,
    QosProfile,
    RmwZenohFormat,
    Ros2DdsFormat,
    Ros2FormatError,
    Ros2NameError,
    decode_attachment,
    make_format,
    qualify,
    rmw_zenoh_qos,
)
from shared.ros2.messages import IMAGE, TWIST, Ros2MessageError

STRING = "std_msgs/msg/String"
ADD_TWO_INTS = "example_interfaces/srv/AddTwoInts"

# ros2/rmw_zenoh docs/design.md, "Topic and Service name mapping to Zenoh key expressions".
DESIGN_CHATTER_KEY = "0/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
DESIGN_ROBOT1_CHATTER_KEY = ("0/robot1/chatter/std_msgs::msg::dds_::String_/"
                             "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
# ros2/rmw_zenoh docs/design.md, "Graph Cache" examples (demo_nodes_cpp listener and talker).
DESIGN_LISTENER_NODE_TOKEN = "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
DESIGN_LISTENER_SUB_TOKEN = (
    "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,10:,:,:,,")
DESIGN_TALKER_PUB_TOKEN = (
    "@ros2_lv/2/8b20917502ee955ac4476e0266340d5c/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,")

# The attachment of sample 1 at t = 1700000000123456789 ns from GID 00 01 .. 0f, by the layout of
# ros2/rmw_zenoh docs/design.md "Publishers" (8 bytes LE sequence number, 8 bytes LE timestamp,
# 1 byte GID length = 16, 16 bytes GID) = what attachment_helpers.cpp writes with zenoh-cpp's
# ext::Serializer (int64, int64, std::array<uint8_t, 16> as LEB128 length + bytes).
ATTACHMENT_EXAMPLE = bytes.fromhex(
    "0100000000000000"                    # sequence_number 1
    "15cd853dfe9c9717"                    # source_timestamp 1700000000123456789 = 0x17979cfe3d85cd15
    "10"                                  # gid length 16
    "000102030405060708090a0b0c0d0e0f")  # gid


def listener(zid: str = "aac3178e146ba6f1fc6e6a4085e77f21") -> NodeInfo:
    return NodeInfo(name="listener", zid=zid, node_id=0)


# --- names -------------------------------------------------------------------------------------

@pytest.mark.parametrize(("namespace", "topic", "full"), [
    ("/", "cmd_vel", "/cmd_vel"),
    ("/bot1", "cmd_vel", "/bot1/cmd_vel"),
    ("bot1", "camera/depth/image_raw", "/bot1/camera/depth/image_raw"),
    ("", "cmd_vel", "/cmd_vel"),
    ("/bot1", "/cmd_vel", "/cmd_vel"),  # absolute topics ignore the namespace
    ("/a/b", "_private_ok9", "/a/b/_private_ok9"),
])
def test_qualify(namespace: str, topic: str, full: str) -> None:
    assert qualify(namespace, topic) == full


@pytest.mark.parametrize(("namespace", "topic"), [
    ("/", ""), ("/", "/"), ("/", "9lives"), ("/", "a//b"), ("/", "cmd vel"), ("/", "cmd_vel/"),
    ("/", "~/private"), ("/", "{node}/x"), ("/bot1/", "cmd_vel"), ("/1bot", "cmd_vel"), ("/a//b", "x"),
    ("/", "camera/2d"),
])
def test_invalid_names_are_refused_clearly(namespace: str, topic: str) -> None:
    with pytest.raises(Ros2NameError, match="ROS 2 name|must"):
        qualify(namespace, topic)


def test_invalid_node_names_are_refused() -> None:
    for name in ("", "a/b", "9node", "my-node"):
        with pytest.raises(Ros2NameError):
            NodeInfo(name=name)


# --- rmw_zenoh ---------------------------------------------------------------------------------

def test_rmw_zenoh_data_keys_match_the_design_doc() -> None:
    fmt = RmwZenohFormat(domain_id=0)
    assert fmt.data_key("/chatter", STRING) == DESIGN_CHATTER_KEY
    assert fmt.data_key(qualify("/robot1", "chatter"), STRING) == DESIGN_ROBOT1_CHATTER_KEY
    # a subscription declares the same key, type hash included (rmw_subscription_data.cpp)
    assert fmt.subscriber_key("/chatter", STRING) == DESIGN_CHATTER_KEY
    assert RmwZenohFormat(domain_id=3).data_key("/cmd_vel", TWIST) == (
        "3/cmd_vel/geometry_msgs::msg::dds_::Twist_/"
        "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a")
    with pytest.raises(Ros2NameError, match="fully qualified"):
        fmt.data_key("chatter", STRING)


def test_rmw_zenoh_tokens_match_the_design_doc() -> None:
    fmt = RmwZenohFormat(domain_id=2)
    assert fmt.node_token(listener()) == DESIGN_LISTENER_NODE_TOKEN
    assert fmt.subscriber_token(listener(), "/chatter", STRING, "default", entity_id=10) == DESIGN_LISTENER_SUB_TOKEN
    talker = NodeInfo(name="talker", zid="8b20917502ee955ac4476e0266340d5c", node_id=0)
    assert fmt.publisher_token(talker, "/chatter", STRING, QosProfile(depth=7), entity_id=10) == DESIGN_TALKER_PUB_TOKEN


def test_rmw_zenoh_tokens_mangle_namespaces_and_topics() -> None:
    node = NodeInfo(name="drive", namespace="/bot1", zid="1234", node_id=3)
    token = RmwZenohFormat().publisher_token(node, "/bot1/cmd_vel", TWIST, "default", entity_id=4)
    assert token.startswith("@ros2_lv/0/1234/3/4/MP/%/%bot1/drive/%bot1%cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_")
    image = RmwZenohFormat().subscriber_token(node, "/bot1/camera/depth", IMAGE, "sensor_data", entity_id=5)
    assert image.endswith("/%bot1%camera%depth/sensor_msgs::msg::dds_::Image_/" + image.split("/")[-2] + "/2::,5:,:,:,,")


def test_rmw_zenoh_qos_encoding() -> None:
    # qos_to_keyexpr (liveliness_utils.cpp) against rmw_zenoh's default (qos.cpp: reliable,
    # volatile, keep_last 42), numbers being the rmw enums (rmw/types.h)
    assert rmw_zenoh_qos("default") == "::,10:,:,:,,"
    assert rmw_zenoh_qos("sensor_data") == "2::,5:,:,:,,"
    assert rmw_zenoh_qos(QosProfile(depth=42)) == "::,:,:,:,,"
    assert rmw_zenoh_qos(QosProfile(durability="transient_local", history="keep_all", depth=1)) == ":1:2,1:,:,:,,"
    with pytest.raises(Ros2FormatError):
        rmw_zenoh_qos("fast")
    with pytest.raises(Ros2FormatError):
        QosProfile(reliability="maybe")


def test_rmw_zenoh_attachment_layout() -> None:
    node = listener()
    publisher = PublisherInfo(node=node, entity_id=11, topic="/cmd_vel", msgtype=TWIST, qos=QosProfile(),
                              gid=bytes(range(16)))
    attachment = RmwZenohFormat().attachment(publisher, 1, 1_700_000_000_123_456_789)
    assert attachment == ATTACHMENT_EXAMPLE and len(attachment) == ATTACHMENT_BYTES == 33
    # the same bytes as Zenoh's own serializer, which zenoh-cpp's rmw_zenoh uses
    assert attachment == zenoh.ext.z_serialize(
        (zenoh.ext.Int64(1), zenoh.ext.Int64(1_700_000_000_123_456_789), bytes(range(16)))).to_bytes()
    assert decode_attachment(attachment) == (1, 1_700_000_000_123_456_789, bytes(range(16)))
    for junk in (attachment[:-1], attachment[:16] + b"\x0f" + attachment[17:], b""):
        with pytest.raises(Ros2MessageError):
            decode_attachment(junk)
    with pytest.raises(Ros2FormatError):
        PublisherInfo(node=node, entity_id=1, topic="/x", msgtype=TWIST, qos=QosProfile(), gid=bytes(8))


# --- zenoh-bridge-ros2dds ----------------------------------------------------------------------

def test_ros2dds_keys_are_the_plain_topic() -> None:
    # zenoh-plugin-ros2dds ros2_utils.rs ros2_name_to_key_expr: '/cmd_vel' -> 'cmd_vel'; with the
    # bridge's namespace '/bot1' (DEFAULT_CONFIG.json5: "cmd_vel" seen as "namespace/cmd_vel")
    fmt = Ros2DdsFormat()
    assert fmt.data_key("/cmd_vel", TWIST) == "cmd_vel"
    assert fmt.data_key(qualify("/bot1", "cmd_vel"), TWIST) == "bot1/cmd_vel"
    assert fmt.subscriber_key(qualify("/bot1", "camera/depth/image_raw"), IMAGE) == "bot1/camera/depth/image_raw"
    node = NodeInfo(name="drive")
    publisher = PublisherInfo(node=node, entity_id=1, topic="/cmd_vel", msgtype=TWIST, qos=QosProfile(), gid=bytes(16))
    assert fmt.node_token(node) is None
    assert fmt.publisher_token(node, "/cmd_vel", TWIST, "default", entity_id=1) is None
    assert fmt.subscriber_token(node, "/cmd_vel", TWIST, "default", entity_id=2) is None
    assert fmt.attachment(publisher, 1, 0) is None


def test_make_format() -> None:
    assert set(FORMATS) == {"rmw_zenoh", "ros2dds"}
    rmw = make_format("rmw_zenoh", domain_id=7)
    assert isinstance(rmw, RmwZenohFormat) and rmw.domain_id == 7 and rmw.name == "rmw_zenoh"
    assert isinstance(make_format("ros2dds", domain_id=7), Ros2DdsFormat)
    with pytest.raises(Ros2FormatError, match="unknown: use one of"):
        make_format("dds")
    for bad in (-1, True, "0"):
        with pytest.raises(Ros2FormatError, match="domain id"):
            make_format("ros2dds", domain_id=bad)  # type: ignore[arg-type]
