"""The ROS 2 nodes: thin adapters from messages to the core (see docs/topics.md)."""
import signal

STACK_DUMP_SIGNAL = signal.SIGUSR1
"""The signal on which every node prints all its threads' Python stacks to stderr, and goes on
(:func:`hdrqn_ros.nodes.process.run_node`)."""
