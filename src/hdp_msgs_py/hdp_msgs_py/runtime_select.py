"""Decide once whether nodes run on rclpy or on our DDS runtime.

rclpy is used when importable, unless HDP_RUNTIME=dds forces our runtime
(useful on a ROS machine to test exactly what CI runs).
"""

import importlib.util
import os


def _use_rclpy() -> bool:
    choice = os.environ.get('HDP_RUNTIME', 'auto')
    if choice not in ('auto', 'rclpy', 'dds'):
        raise RuntimeError(f"HDP_RUNTIME must be 'auto', 'rclpy' or 'dds', got {choice!r}")
    if choice == 'dds':
        return False
    found = importlib.util.find_spec('rclpy') is not None
    if choice == 'rclpy' and not found:
        raise RuntimeError('HDP_RUNTIME=rclpy but rclpy is not importable (source your ROS 2 setup)')
    return found


USING_RCLPY = _use_rclpy()
