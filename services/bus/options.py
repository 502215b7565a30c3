"""The options of ``cogexplore secure init`` and the ROS 2 options of ``drive`` and ``sim-robot``
(light: no Zenoh, no cryptography)."""

from __future__ import annotations

import argparse
import os

from services.bus import ENV_CONNECT, ROLES, ZENOHD_DIR
from services.options import add_log_level_argument, add_router_wait_argument, whole_number_argument


def add_secure_init_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", metavar="DIR", help="the folder to write, e.g. runs/<run>/secure (what `cogexplore up` uses)")
    p.add_argument("--run", default=None, help="the run the access control is for (default: the name of DIR's parent)")
    p.add_argument("--tls", action="store_true",
                   help="also a CA, the router's certificate and one per role: TLS with client certificates, needed "
                        "wherever the router listens beyond this machine")
    p.add_argument("--host", action="append", default=[], metavar="NAME",
                   help="a name or address the router's certificate is valid for, besides localhost, 127.0.0.1 and ::1 "
                        "(repeatable): the one remote actors connect to")
    p.add_argument("--zenohd-dir", default=ZENOHD_DIR, metavar="PATH",
                   help=f"where router-zenohd.json5 expects the folder in the router's container (default {ZENOHD_DIR})")
    keep = p.add_mutually_exclusive_group()
    keep.add_argument("--force", action="store_true",
                      help="replace existing credentials (every service then needs the new files)")
    keep.add_argument("--keep", action="store_true",
                      help="keep a complete folder of this run (its passwords and certificates; access rules an older "
                           "release wrote are brought up to this one's), writing one only where there is none "
                           "(what docker-compose.yml runs at every start)")


def add_secure_export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", metavar="DIR", help="the run's security folder (from `cogexplore secure init`)")
    p.add_argument("--role", default="actor", choices=ROLES, help="the role to export (default actor)")
    p.add_argument("--out", required=True, metavar="DIR", help="the folder to write (copy it to the other machine)")


ROS2_FORMATS: tuple[str, ...] = ("rmw_zenoh", "ros2dds")
DEFAULT_IMAGE_TOPIC = "camera/depth/image_raw"
DEFAULT_CMD_VEL_TOPIC = "cmd_vel"
DEFAULT_ODOM_TOPIC = "odom"
DEFAULT_ROBOT = "robot"


def add_ros2_arguments(p: argparse.ArgumentParser) -> None:
    """Where the robot's ROS 2 topics are: the wire format, domain, namespace, topic names, the router."""
    r = p.add_argument_group("ROS 2", "the robot's topics, as rmw_zenoh or zenoh-bridge-ros2dds carry them")
    r.add_argument("--ros2-format", choices=ROS2_FORMATS, default="rmw_zenoh",
                   help="rmw_zenoh: ROS 2 nodes on the Zenoh RMW (ROS 2 Jazzy and later; key "
                        "<domain>/<topic>/<type>/<hash>, attachments, liveliness tokens); ros2dds: a DDS robot "
                        "behind zenoh-bridge-ros2dds (plain <namespace>/<topic> keys). Default rmw_zenoh")
    # A string default goes through the type: a bad ROS_DOMAIN_ID is an option error, not a traceback.
    r.add_argument("--domain-id", type=whole_number_argument(0), default=os.environ.get("ROS_DOMAIN_ID") or "0", metavar="N",
                   help="the ROS 2 domain (rmw_zenoh; env ROS_DOMAIN_ID; default 0)")
    r.add_argument("--namespace", default="/", metavar="NS",
                   help="the robot's ROS 2 namespace, e.g. /tb4 (default /). With ros2dds, the bridge's own "
                        "`namespace` setting, if any, goes here too")
    r.add_argument("--image-topic", default=DEFAULT_IMAGE_TOPIC, metavar="TOPIC",
                   help=f"sensor_msgs/msg/Image depth topic, relative to the namespace (default {DEFAULT_IMAGE_TOPIC}; "
                        "TurtleBot 4: oakd/stereo/image_raw)")
    r.add_argument("--cmd-vel-topic", default=DEFAULT_CMD_VEL_TOPIC, metavar="TOPIC",
                   help=f"geometry_msgs/msg/Twist command topic (default {DEFAULT_CMD_VEL_TOPIC})")
    r.add_argument("--robot", default=DEFAULT_ROBOT, metavar="NAME",
                   help=f"name of the robot on cogexplore's own keys (cogexplore/@robot/NAME/...: diagnostics, "
                        f"status, reset; default {DEFAULT_ROBOT})")
    z = p.add_argument_group("Zenoh", f"the router the robot's topics reach (env {ENV_CONNECT})")
    z.add_argument("--connect", action="append", default=None, metavar="ENDPOINT",
                   help="router endpoint, e.g. tcp/192.168.1.10:7447 (repeatable; default tcp/127.0.0.1:7447: "
                        "the rmw_zenoh router, rmw_zenohd, or the bridge, on this machine)")
    z.add_argument("--zenoh-config", default=None, metavar="JSON5", help="a Zenoh JSON5 config file (TLS, credentials)")
    add_router_wait_argument(z)
    add_log_level_argument(p)
