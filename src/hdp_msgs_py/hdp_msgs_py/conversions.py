"""Conversions between ROS 2 messages and numpy, with no ROS runtime.

Images, camera intrinsics, depth point clouds, transforms, poses, joint
trajectories and time stamps. Messages are the classes of
``hdp_msgs_py.msg`` (rclpy's under ROS); only fields and value types that
both accept are used, so the same code runs on either. Bad input raises
ValueError naming the problem.

Conventions: quaternions are (x, y, z, w); camera frames are optical (x right,
y down, z forward) and pixel centres sit at integer (u, v); depth is 16UC1 in
millimetres (0 = no reading, as RealSense publishes) or 32FC1 in metres.
"""

from __future__ import annotations

import array
import dataclasses
import math

import numpy as np

from hdp_motion import panda
from hdp_motion.rotations import quat_to_matrix

from .msg import (CameraInfo, Duration, Header, Image, JointTrajectory, JointTrajectoryPoint, Point,
                  PointCloud2, PointField, Pose, PoseStamped, Quaternion, Time, Transform, Vector3)

_NS_PER_S = 1_000_000_000
_INT32 = (-2 ** 31, 2 ** 31 - 1)
_QUAT_NORM_TOL = 1e-3      # a quaternion further than this from unit norm is corrupt, not rounded
_ROTATION_TOL = 1e-6       # max |R^T R - I| accepted as a rotation matrix

# encoding -> (numpy dtype, channels)
_ENCODINGS = {
    'rgb8': (np.dtype(np.uint8), 3),
    'bgr8': (np.dtype(np.uint8), 3),
    'mono8': (np.dtype(np.uint8), 1),
    '16UC1': (np.dtype(np.uint16), 1),
    '32FC1': (np.dtype(np.float32), 1),
}


# --- time ---------------------------------------------------------------------

def _split_seconds(seconds: float, what: str) -> tuple[int, int]:
    seconds = float(seconds)
    if not math.isfinite(seconds):
        raise ValueError(f'{what} must be finite, got {seconds}')
    sec = math.floor(seconds)
    nanosec = round((seconds - sec) * _NS_PER_S)   # the fraction is exact; one rounding
    if nanosec == _NS_PER_S:                        # 1.9999999999 s -> 2 s 0 ns, not 1 s 1e9 ns
        sec, nanosec = sec + 1, 0
    if not _INT32[0] <= sec <= _INT32[1]:
        raise ValueError(f'{what} {seconds} s does not fit an int32 seconds field')
    return sec, nanosec


def seconds_to_duration(seconds: float) -> Duration:
    """builtin_interfaces/Duration of ``seconds``, rounded to the nearest nanosecond.

    Negative values follow ROS: sec = floor(seconds), 0 <= nanosec < 1e9.
    """
    sec, nanosec = _split_seconds(seconds, 'duration')
    return Duration(sec=sec, nanosec=nanosec)


def seconds_to_time(seconds: float) -> Time:
    """builtin_interfaces/Time of ``seconds`` (>= 0), rounded to the nearest nanosecond."""
    if seconds < 0:
        raise ValueError(f'time must be >= 0, got {seconds} s')
    sec, nanosec = _split_seconds(seconds, 'time')
    return Time(sec=sec, nanosec=nanosec)


def duration_to_seconds(duration) -> float:
    """Seconds of a builtin_interfaces/Duration."""
    return duration.sec + duration.nanosec / _NS_PER_S


def time_to_ns(stamp) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time: exact, for keys and ordering."""
    return int(stamp.sec) * _NS_PER_S + int(stamp.nanosec)


def time_to_seconds(stamp) -> float:
    """Seconds of a builtin_interfaces/Time (a float: sub-microsecond detail is lost at epoch scale)."""
    return stamp.sec + stamp.nanosec / _NS_PER_S


def _header(frame_id: str, stamp) -> Header:
    return Header(stamp=stamp if stamp is not None else Time(), frame_id=frame_id)


# --- images -------------------------------------------------------------------

def _encoding(encoding: str) -> tuple[np.dtype, int]:
    try:
        return _ENCODINGS[encoding]
    except KeyError:
        raise ValueError(f'unsupported image encoding {encoding!r}; '
                         f'supported: {", ".join(_ENCODINGS)}') from None


def _data_bytes(data) -> np.ndarray:
    """``msg.data`` as a flat uint8 array, sharing memory when it exposes a byte buffer."""
    if isinstance(data, (bytes, bytearray, memoryview)) or (
            isinstance(data, array.array) and data.typecode == 'B'):
        return np.frombuffer(data, np.uint8)
    return np.asarray(data, dtype=np.uint8).reshape(-1)   # uint8 ndarray: a view; list: a copy


def image_to_numpy(msg) -> np.ndarray:
    """The pixels of a sensor_msgs/Image, always as a read-only array.

    (H, W, 3) uint8 for rgb8 and bgr8 (channels in encoded order), (H, W) uint8
    for mono8, (H, W) uint16 for 16UC1, (H, W) float32 for 32FC1. The array is
    a zero-copy view of ``msg.data`` when that exposes a byte buffer (bytes,
    array.array('B'), uint8 ndarray) and the data is little-endian; it is a
    copy when ``msg.data`` is a list or when big-endian 16UC1/32FC1 data is
    byteswapped to native order. Row padding (step > W * bytes per pixel) is
    skipped by striding, so such a view is not contiguous. Call ``.copy()`` for
    a writable array; while a view lives, an array.array ``msg.data`` cannot
    be resized.
    """
    dtype, channels = _encoding(msg.encoding)
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    pixel_bytes = channels * dtype.itemsize
    if height == 0 or width == 0:
        raise ValueError(f'image is empty: height={height}, width={width}')
    if step < width * pixel_bytes:
        raise ValueError(f'step {step} is less than width * bytes per pixel = '
                         f'{width} * {pixel_bytes} = {width * pixel_bytes} for {msg.encoding}')
    data = _data_bytes(msg.data)
    if data.size != step * height:
        raise ValueError(f'image data has {data.size} bytes, expected step * height = '
                         f'{step} * {height} = {step * height}')
    dtype = dtype.newbyteorder('>' if msg.is_bigendian else '<')
    if channels == 1:
        shape, strides = (height, width), (step, dtype.itemsize)
    else:
        shape, strides = (height, width, channels), (step, pixel_bytes, dtype.itemsize)
    pixels = np.ndarray(shape, dtype, buffer=data, strides=strides)
    if not dtype.isnative:
        pixels = pixels.astype(dtype.newbyteorder('='))
    pixels.flags.writeable = False
    return pixels


def numpy_to_image(pixels: np.ndarray, encoding: str, header=None) -> Image:
    """A sensor_msgs/Image of ``pixels``, shaped and typed as image_to_numpy returns them.

    Little-endian, unpadded (step = W * bytes per pixel); ``data`` is an
    array.array('B') filled in one memory copy. ``header`` defaults to an
    empty std_msgs/Header.
    """
    dtype, channels = _encoding(encoding)
    pixels = np.asarray(pixels)
    shape_ok = pixels.ndim == 2 if channels == 1 else pixels.ndim == 3 and pixels.shape[2] == channels
    if pixels.dtype != dtype or not shape_ok:
        expected = '(H, W)' if channels == 1 else f'(H, W, {channels})'
        raise ValueError(f'{encoding} needs a {expected} {dtype} array, '
                         f'got shape {pixels.shape} dtype {pixels.dtype}')
    height, width = pixels.shape[:2]
    if height == 0 or width == 0:
        raise ValueError(f'image is empty: height={height}, width={width}')
    data = array.array('B')
    data.frombytes(np.ascontiguousarray(pixels, dtype=dtype.newbyteorder('<')).reshape(-1).view(np.uint8))
    return Image(header=header if header is not None else Header(), height=int(height),
                 width=int(width), encoding=encoding, is_bigendian=0,
                 step=int(width) * channels * dtype.itemsize, data=data)


# --- camera intrinsics ----------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a width x height image (pixels; no skew, no distortion)."""
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self):
        for name in ('fx', 'fy', 'cx', 'cy'):
            value = float(getattr(self, name))
            if not math.isfinite(value) or (name in ('fx', 'fy') and value <= 0):
                need = 'finite and > 0' if name in ('fx', 'fy') else 'finite'
                raise ValueError(f'{name} must be {need}, got {value}')
            object.__setattr__(self, name, value)
        for name in ('width', 'height'):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f'{name} must be a positive integer, got {value!r}')
            object.__setattr__(self, name, int(value))

    @property
    def matrix(self) -> np.ndarray:
        """K, (3, 3) float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_matrix(cls, k, width: int, height: int) -> Intrinsics:
        """From K as (3, 3) or 9 row-major values of the form [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]."""
        k = np.asarray(k, dtype=np.float64)
        if k.shape not in ((9,), (3, 3)):
            raise ValueError(f'K must be 3x3 or 9 values, got shape {k.shape}')
        k = k.reshape(3, 3)
        if not np.all(np.isfinite(k)):
            raise ValueError(f'K must be finite, got {k.tolist()}')
        if k[0, 1] != 0 or k[1, 0] != 0 or k[2].tolist() != [0.0, 0.0, 1.0]:
            raise ValueError(f'K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], got {k.tolist()}')
        return cls(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)


def camera_info_to_intrinsics(info) -> Intrinsics:
    """Intrinsics from a sensor_msgs/CameraInfo's K, width and height.

    Distortion ``d`` is ignored: use it for undistorted images (RealSense depth
    and aligned-depth streams have zero distortion).
    """
    return Intrinsics.from_matrix(info.k, info.width, info.height)


def intrinsics_to_camera_info(intrinsics: Intrinsics, frame_id: str, stamp=None) -> CameraInfo:
    """A plumb_bob sensor_msgs/CameraInfo with zero distortion, R = I and P = [K | 0].

    ``stamp`` is a builtin_interfaces/Time; None gives the zero stamp.
    """
    i = intrinsics
    return CameraInfo(
        header=_header(frame_id, stamp), height=i.height, width=i.width,
        distortion_model='plumb_bob', d=array.array('d', [0.0] * 5),
        k=i.matrix.reshape(9), r=np.eye(3).reshape(9),
        p=np.array([i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0]))


# --- rotations and transforms -------------------------------------------------------

def _finite_vector(values, size: int, what: str) -> np.ndarray:
    vector = np.asarray(values, dtype=np.float64)
    if vector.shape != (size,):
        raise ValueError(f'{what} must have shape ({size},), got {vector.shape}')
    if not np.all(np.isfinite(vector)):
        raise ValueError(f'{what} must be finite, got {vector.tolist()}')
    return vector


def normalize_quat(quat) -> np.ndarray:
    """(4,) unit copy of quaternion (x, y, z, w); ValueError for NaN/inf or zero norm."""
    q = _finite_vector(quat, 4, 'quaternion')
    norm = np.linalg.norm(q)
    if norm < 1e-9:
        raise ValueError(f'quaternion has zero norm: {q.tolist()}')
    return q / norm


def _unit_quat(quat) -> np.ndarray:
    """normalize_quat of a quaternion whose norm is within 1e-3 of 1, else ValueError."""
    q = _finite_vector(quat, 4, 'quaternion')
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > _QUAT_NORM_TOL:
        problem = 'has zero norm' if norm < 1e-9 else f'must be unit (|norm - 1| <= {_QUAT_NORM_TOL})'
        raise ValueError(f'quaternion {problem}, got norm {norm:.6g}: {q.tolist()}')
    return q / norm


def matrix_to_quat(rotation) -> np.ndarray:
    """Unit quaternion (4,) x, y, z, w with w >= 0 of a (3, 3) rotation matrix."""
    m = _rotation(rotation)
    trace = np.trace(m)
    if trace > 0:                 # Shepperd: divide by the largest of 4w^2, 4x^2, 4y^2, 4z^2
        s = 2.0 * math.sqrt(1.0 + trace)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
    q = np.array(q) / np.linalg.norm(q)
    return -q if q[3] < 0 else q


def _rotation(rotation) -> np.ndarray:
    r = np.asarray(rotation, dtype=np.float64)
    if r.shape != (3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f'rotation must be a finite 3x3 matrix, got shape {r.shape}')
    error = np.abs(r.T @ r - np.eye(3)).max()
    if error > _ROTATION_TOL or np.linalg.det(r) < 0:
        raise ValueError(f'not a rotation matrix (|R^T R - I| = {error:.3g}, det = {np.linalg.det(r):.6g})')
    return r


def _rigid_matrix(matrix) -> np.ndarray:
    t = np.asarray(matrix, dtype=np.float64)
    if t.shape != (4, 4):
        raise ValueError(f'transform must be 4x4, got shape {t.shape}')
    if not np.all(np.isfinite(t)) or t[3].tolist() != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f'transform must be finite with last row [0, 0, 0, 1], got {t.tolist()}')
    _rotation(t[:3, :3])
    return t


def transform_to_matrix(transform) -> np.ndarray:
    """(4, 4) float64 homogeneous matrix of a geometry_msgs Transform or TransformStamped."""
    transform = getattr(transform, 'transform', transform)
    v, q = transform.translation, transform.rotation
    matrix = np.eye(4)
    matrix[:3, :3] = quat_to_matrix(_unit_quat([q.x, q.y, q.z, q.w]))
    matrix[:3, 3] = _finite_vector([v.x, v.y, v.z], 3, 'translation')
    return matrix


def matrix_to_transform(matrix) -> Transform:
    """geometry_msgs/Transform of a (4, 4) rigid transform (rotation checked orthonormal)."""
    t = _rigid_matrix(matrix)
    x, y, z, w = (float(c) for c in matrix_to_quat(t[:3, :3]))
    tx, ty, tz = (float(c) for c in t[:3, 3])
    return Transform(translation=Vector3(x=tx, y=ty, z=tz), rotation=Quaternion(x=x, y=y, z=z, w=w))


# --- depth to points --------------------------------------------------------------

def depth_to_points(depth_m: np.ndarray, intrinsics: Intrinsics, camera_to_world) -> np.ndarray:
    """(N, 3) float32 world-frame points of the valid pixels (finite, > 0) of an (H, W) float depth in metres.

    Pixel (u, v) at depth z is the optical-frame point ((u - cx) z / fx,
    (v - cy) z / fy, z), mapped through the (4, 4) ``camera_to_world``. Points
    come in row-major pixel order.
    """
    depth = np.asarray(depth_m)
    if not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(f'depth must be a float array in metres, got {depth.dtype} '
                         '(use depth_image_to_points for 16UC1 millimetres)')
    expected = (intrinsics.height, intrinsics.width)
    if depth.shape != expected:
        raise ValueError(f'depth image has shape {depth.shape}, intrinsics are for (H, W) = {expected}')
    world = _rigid_matrix(camera_to_world)
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u].astype(np.float64)
    camera = np.stack([(u - intrinsics.cx) * z / intrinsics.fx,
                       (v - intrinsics.cy) * z / intrinsics.fy, z], axis=1)
    return (camera @ world[:3, :3].T + world[:3, 3]).astype(np.float32)


def depth_image_to_points(depth_msg, info_msg, camera_to_world) -> np.ndarray:
    """depth_to_points for a 16UC1 (millimetres, 0 = invalid) or 32FC1 (metres) sensor_msgs/Image."""
    if depth_msg.encoding not in ('16UC1', '32FC1'):
        raise ValueError(f"depth image must be 16UC1 (mm) or 32FC1 (m), got {depth_msg.encoding!r}")
    depth = image_to_numpy(depth_msg)
    if depth_msg.encoding == '16UC1':
        depth = depth * 0.001
    return depth_to_points(depth, camera_info_to_intrinsics(info_msg), camera_to_world)


# --- poses ----------------------------------------------------------------------

def pose_to_xyz_quat(pose) -> tuple[np.ndarray, np.ndarray]:
    """Position (3,) and unit orientation (4,) x, y, z, w, float64, of a Pose or PoseStamped.

    ValueError for NaN/inf, a zero quaternion, or one whose norm is more than
    1e-3 from 1; within that the quaternion is renormalised.
    """
    pose = getattr(pose, 'pose', pose)
    p, q = pose.position, pose.orientation
    return _finite_vector([p.x, p.y, p.z], 3, 'position'), _unit_quat([q.x, q.y, q.z, q.w])


def xyz_quat_to_pose_stamped(xyz, quat, frame_id: str, stamp=None) -> PoseStamped:
    """geometry_msgs/PoseStamped at ``xyz`` (3,) with ``quat`` (4,) x, y, z, w normalised.

    ValueError for NaN/inf or a zero quaternion. ``stamp`` is a
    builtin_interfaces/Time; None gives the zero stamp.
    """
    x, y, z = (float(c) for c in _finite_vector(xyz, 3, 'position'))
    qx, qy, qz, qw = (float(c) for c in normalize_quat(quat))
    return PoseStamped(header=_header(frame_id, stamp), pose=Pose(
        position=Point(x=x, y=y, z=z), orientation=Quaternion(x=qx, y=qy, z=qz, w=qw)))


# --- joint trajectories ----------------------------------------------------------

def _all_finite(values: np.ndarray, what: str) -> None:
    bad = np.argwhere(~np.isfinite(values))
    if bad.size:
        index = tuple(int(i) for i in bad[0])
        raise ValueError(f'{what} must be finite: {what}{list(index)} is {values[index]}')


def _check_trajectory(joint_names, positions, times, velocities):
    names = list(joint_names)
    if not names:
        raise ValueError('joint_names is empty')
    if not all(isinstance(n, str) and n for n in names):
        raise ValueError(f'joint names must be non-empty strings, got {names}')
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f'joint names must be unique, repeated: {repeated}')
    positions = np.asarray(positions, dtype=np.float64)
    if positions.ndim != 2 or positions.shape[1] != len(names):
        raise ValueError(f'positions must have shape (T, {len(names)}) for {len(names)} joint names, '
                         f'got {positions.shape}')
    count = positions.shape[0]
    if count == 0:
        raise ValueError('trajectory has no points')
    times = np.asarray(times, dtype=np.float64)
    if times.shape != (count,):
        raise ValueError(f'times_from_start must have shape ({count},) for {count} points, got {times.shape}')
    _all_finite(positions, 'positions')
    _all_finite(times, 'times_from_start')
    if velocities is not None:
        velocities = np.asarray(velocities, dtype=np.float64)
        if velocities.shape != positions.shape:
            raise ValueError(f'velocities must have the shape of positions {positions.shape}, '
                             f'got {velocities.shape}')
        _all_finite(velocities, 'velocities')
    if times[0] < 0:
        raise ValueError(f'time_from_start must be >= 0: point 0 at {times[0]:.9g} s')
    not_increasing = np.nonzero(np.diff(times) <= 0)[0]
    if not_increasing.size:
        i = int(not_increasing[0]) + 1
        raise ValueError(f'time_from_start must be strictly increasing: point {i} at {times[i]:.9g} s '
                         f'after point {i - 1} at {times[i - 1]:.9g} s')
    return names, positions, times, velocities


def build_joint_trajectory(joint_names, positions, times_from_start, velocities=None,
                           frame_id: str = '', stamp=None) -> JointTrajectory:
    """trajectory_msgs/JointTrajectory of T points over J joints.

    ``positions`` and optional ``velocities`` are (T, J), ``times_from_start``
    (T,) seconds, >= 0 and strictly increasing. ``stamp`` None gives the zero
    stamp, which joint_trajectory_controller reads as "start now".
    """
    names, positions, times, velocities = _check_trajectory(
        joint_names, positions, times_from_start, velocities)
    points = [JointTrajectoryPoint(
        positions=array.array('d', positions[i]),
        velocities=array.array('d', velocities[i] if velocities is not None else []),
        time_from_start=seconds_to_duration(times[i])) for i in range(len(times))]
    return JointTrajectory(header=_header(frame_id, stamp), joint_names=names, points=points)


def finger_trajectory(is_open: bool, finger_joints=panda.FINGER_JOINTS, stamp=None) -> JointTrajectory:
    """The gripper command as a finger JointTrajectory: both fingers (m each) open or shut in 0.5 s."""
    finger = panda.FINGER_MAX if is_open else 0.0
    return build_joint_trajectory(list(finger_joints), [[finger, finger]], [0.5], stamp=stamp)


def parse_joint_trajectory(msg) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray | None]:
    """(joint_names, positions (T, J), times (T,) s, velocities (T, J) or None) of a JointTrajectory.

    Validated as build_joint_trajectory does; velocities must be on every
    point or on none.
    """
    joints = len(msg.joint_names)
    for i, point in enumerate(msg.points):
        if len(point.positions) != joints:
            raise ValueError(f'point {i} has {len(point.positions)} positions for {joints} joint names')
    velocities = None
    if any(len(p.velocities) for p in msg.points):
        for i, point in enumerate(msg.points):
            if len(point.velocities) != joints:
                raise ValueError(f'point {i} has {len(point.velocities)} velocities for {joints} '
                                 'joint names (give velocities on every point or on none)')
        velocities = np.array([np.asarray(p.velocities, dtype=np.float64) for p in msg.points])
    positions = np.array([np.asarray(p.positions, dtype=np.float64) for p in msg.points])
    times = [duration_to_seconds(p.time_from_start) for p in msg.points]
    return _check_trajectory(msg.joint_names, positions.reshape(len(times), joints), times, velocities)


# PCL's layout, which RViz and Foxglove colour by: x, y, z float32, then rgb as the bytes of a
# uint32 0x00RRGGBB read as a float32.
_CLOUD_FIELDS = (('x', 0), ('y', 4), ('z', 8), ('rgb', 12))
_FLOAT32 = 7          # sensor_msgs/PointField.FLOAT32


def cloud_to_pointcloud2(xyz, colours, header) -> PointCloud2:
    """xyz (N, 3) m and colours (N, 3) uint8 -> an unordered sensor_msgs/PointCloud2 (x, y, z, rgb)."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    colours = np.asarray(colours, dtype=np.uint8).reshape(-1, 3)
    if len(xyz) != len(colours):
        raise ValueError(f'{len(xyz)} points but {len(colours)} colours')
    packed = (colours[:, 0].astype(np.uint32) << 16) | (colours[:, 1].astype(np.uint32) << 8) | colours[:, 2]
    data = np.concatenate([xyz.view(np.uint32), packed[:, None]], axis=1).astype('<u4')
    return PointCloud2(header=header, height=1, width=len(xyz), is_bigendian=False, point_step=16,
                       row_step=16 * len(xyz), is_dense=True, data=array.array('B', data.tobytes()),
                       fields=[PointField(name=name, offset=offset, datatype=_FLOAT32, count=1)
                               for name, offset in _CLOUD_FIELDS])


def pointcloud2_to_cloud(msg) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of cloud_to_pointcloud2: (xyz (N, 3) float32, colours (N, 3) uint8)."""
    if [(f.name, f.offset, f.datatype) for f in msg.fields] != [(n, o, _FLOAT32) for n, o in _CLOUD_FIELDS] \
            or msg.point_step != 16 or msg.is_bigendian:
        raise ValueError('expected little-endian x, y, z, rgb float32 fields, 16 bytes a point')
    words = np.frombuffer(bytes(msg.data), dtype='<u4').reshape(-1, 4)
    rgb = words[:, 3]
    colours = np.stack([(rgb >> 16) & 255, (rgb >> 8) & 255, rgb & 255], axis=1).astype(np.uint8)
    return words[:, :3].copy().view(np.float32), colours
