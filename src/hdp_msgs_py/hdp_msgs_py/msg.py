"""The message classes code uses: rclpy's generated ones where ROS 2 is installed, ours otherwise.

    from hdp_msgs_py.msg import Image, JointTrajectory, String

Nodes need rclpy and so always get rclpy's. Everything else (conversions,
recorded episodes, datasets, training) also runs where the ROS 2 wheels do not
install (another Python, a training cluster): there these are our classes
(``hdp_msgs_py.message``), with the same field names and the same wire format.
"""

import importlib

_TYPES = {
    'builtin_interfaces': ['Time', 'Duration'],
    'std_msgs': ['Header', 'String', 'Bool', 'Float64', 'Int32', 'Empty',
                 'Float64MultiArray', 'MultiArrayLayout', 'MultiArrayDimension', 'ColorRGBA'],
    'geometry_msgs': ['Point', 'Quaternion', 'Vector3', 'Pose', 'PoseArray', 'PoseStamped',
                      'Transform', 'TransformStamped'],
    'sensor_msgs': ['Image', 'CameraInfo', 'RegionOfInterest', 'JointState', 'CompressedImage',
                    'PointCloud2', 'PointField'],
    'trajectory_msgs': ['JointTrajectory', 'JointTrajectoryPoint'],
    'tf2_msgs': ['TFMessage'],
    'rosgraph_msgs': ['Clock'],
    'visualization_msgs': ['Marker', 'MeshFile', 'UVCoordinate'],
}


def _ros_installed() -> bool:
    try:
        import rclpy  # noqa: F401
    except ImportError:
        return False
    try:
        importlib.import_module('tf2_msgs.msg')
    except ImportError as err:
        raise ImportError('rclpy is installed but tf2_msgs is not: `make setup` builds it into the '
                          'virtualenv; with ROS 2 from apt, `apt install ros-jazzy-tf2-msgs`') from err
    return True


USING_RCLPY = _ros_installed()

if USING_RCLPY:
    for _package, _names in _TYPES.items():
        _module = importlib.import_module(f'{_package}.msg')
        globals().update({name: getattr(_module, name) for name in _names})
else:
    from .message import get_message

    for _package, _names in _TYPES.items():
        globals().update({name: get_message(f'{_package}/msg/{name}') for name in _names})

__all__ = [name for names in _TYPES.values() for name in names]
