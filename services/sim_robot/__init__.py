"""``cogexplore sim-robot``: the project's MuJoCo world as a ROS 2 robot over Zenoh, the test double
of a TurtleBot with a depth camera for ``cogexplore drive``."""
