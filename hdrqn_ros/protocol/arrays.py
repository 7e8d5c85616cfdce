"""Array fields of messages from any source (rclpy, rosbags) as numpy; no ROS here."""
from __future__ import annotations

import array
from typing import Any

import numpy as np


def as_array(data: Any, dtype) -> np.ndarray:
    """A message's array field as a 1-D numpy array (numpy, ``array.array``, bytes or list)."""
    if isinstance(data, np.ndarray):
        return data.astype(dtype, copy=False)
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        return np.frombuffer(data, dtype=dtype)
    return np.asarray(data, dtype=dtype)
