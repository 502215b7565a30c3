"""ROS 2 on the wire, without ROS: CDR messages (``messages``, serialised by ``rosbags``) and the
key expressions, attachments and liveliness tokens of the two ways ROS 2 speaks Zenoh
(``formats``: ``rmw_zenoh`` and ``zenoh-bridge-ros2dds``). Pure: no Zenoh session here; the
node that declares publishers and subscribers on a session is ``services.bus.ros2``."""
