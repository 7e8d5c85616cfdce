"""hdrqn_ros: hierarchical deep recurrent Q-learning (hDRQN) for ROS 2 and plain Python.

Importing the package registers the ``hdrqn/...`` gymnasium environment ids.
"""
from hdrqn_ros.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()
