"""The ROS 2 nodes: thin adapters from messages to the core (see docs/topics.md)."""
