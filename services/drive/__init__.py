"""``cogexplore drive``: a trained policy driving a ROS 2 robot over Zenoh (``controller``: the
decisions and safety rules; ``service``: the process shell)."""
