"""The robot side without ROS: the loopback robot's kinematic world and the ordered-visits bookkeeping."""
