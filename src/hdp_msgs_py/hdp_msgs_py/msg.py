"""The message classes node code uses: rclpy's when ROS 2 is installed, ours otherwise.

    from hdp_msgs_py.msg import Image, JointTrajectory, String

Both sets have the same field names and the same wire format, so a node
written against this module runs unchanged under ``ros2 run`` and on our
DDS runtime.
"""

from .runtime_select import USING_RCLPY

_TYPES = {
    'builtin_interfaces': ['Time', 'Duration'],
    'std_msgs': ['Header', 'String', 'Bool', 'Float64', 'Int32', 'Empty',
                 'Float64MultiArray', 'MultiArrayLayout', 'MultiArrayDimension'],
    'geometry_msgs': ['Point', 'Quaternion', 'Vector3', 'Pose', 'PoseArray', 'PoseStamped',
                      'Transform', 'TransformStamped'],
    'sensor_msgs': ['Image', 'CameraInfo', 'RegionOfInterest', 'JointState'],
    'trajectory_msgs': ['JointTrajectory', 'JointTrajectoryPoint'],
    'tf2_msgs': ['TFMessage'],
    'rosgraph_msgs': ['Clock'],
}

if USING_RCLPY:
    import importlib

    for _package, _names in _TYPES.items():
        _module = importlib.import_module(f'{_package}.msg')
        globals().update({name: getattr(_module, name) for name in _names})
else:
    from .message import get_message

    for _package, _names in _TYPES.items():
        globals().update({name: get_message(f'{_package}/msg/{name}') for name in _names})

__all__ = [name for names in _TYPES.values() for name in names]
