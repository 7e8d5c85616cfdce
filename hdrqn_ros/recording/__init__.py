"""Recording of hDRQN runs into rosbag2 (MCAP) bags, without ROS."""
