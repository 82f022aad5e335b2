"""hdp_msgs_py.conversions against hand-computed values.

Every message a conversion builds is also put through the wire (CDR, or
rclpy's serializer under ROS) and, off ROS, checked to hold only value types
rclpy's field setters accept, so the same code runs under ``ros2 run``.
"""

import array
import math
import re
import struct

import numpy as np
import pytest

from hdp_msgs_py import conversions as cv
from hdp_msgs_py.msg import (USING_RCLPY, Duration, Header, Image, JointTrajectory, JointTrajectoryPoint,
                             Pose, Quaternion, Time, Transform, TransformStamped, Vector3)
from hdp_msgs_py.msg_spec import PRIMITIVES, STRING

pytestmark = pytest.mark.unit


def wire_round_trip(msg):
    """``msg`` serialised and deserialised again."""
    if USING_RCLPY:
        from rclpy.serialization import deserialize_message, serialize_message
        return deserialize_message(serialize_message(msg), type(msg))
    from hdp_msgs_py import cdr
    return cdr.deserialize(type(msg), cdr.serialize(msg))


def assert_rclpy_types(msg):
    """Every field holds a value of the type rclpy stores (its setters would accept it as is)."""
    if USING_RCLPY:
        return    # rclpy's own setters checked them on assignment
    for field in msg._spec.fields:
        value = getattr(msg, field.name)
        where = f'{msg._type}.{field.name}'
        if field.is_message:
            for item in value if field.array else [value]:
                assert_rclpy_types(item)
        elif field.base == STRING:
            assert all(isinstance(v, str) for v in (value if field.array else [value])), where
        elif field.array == 'fixed':
            assert isinstance(value, np.ndarray), where
            assert value.dtype == np.dtype(PRIMITIVES[field.base][0]) and value.size == field.size, where
        elif field.array:
            assert isinstance(value, array.array), where
            assert value.typecode == PRIMITIVES[field.base][0], where
        elif field.base.startswith('float'):
            assert isinstance(value, float), where
        elif field.base == 'bool':
            assert isinstance(value, bool), where
        else:
            assert isinstance(value, int) and not isinstance(value, bool), where


def raw_image(encoding, height, width, step, data, is_bigendian=0):
    return Image(height=height, width=width, encoding=encoding, is_bigendian=is_bigendian,
                 step=step, data=data)


# --- time -----------------------------------------------------------------------

@pytest.mark.parametrize('seconds, sec, nanosec', [
    (0.0, 0, 0),
    (0.1, 0, 100_000_000),
    (1.25, 1, 250_000_000),
    (1.9999999999, 2, 0),               # rounds up into the next second, not nanosec = 1e9
    (2.0000000004, 2, 0),
    (2.0000000006, 2, 1),
    (1_700_000_000.25, 1_700_000_000, 250_000_000),
    (-0.5, -1, 500_000_000),             # ROS convention for negative durations
])
def test_seconds_to_duration_rounds_to_nearest_nanosecond(seconds, sec, nanosec):
    duration = cv.seconds_to_duration(seconds)
    assert (duration.sec, duration.nanosec) == (sec, nanosec)
    assert_rclpy_types(duration)


def test_seconds_to_time_and_back():
    stamp = cv.seconds_to_time(1_700_000_000.5)
    assert (stamp.sec, stamp.nanosec) == (1_700_000_000, 500_000_000)
    assert cv.time_to_seconds(stamp) == 1_700_000_000.5
    assert cv.time_to_seconds(Time(sec=3, nanosec=1)) == pytest.approx(3.000000001, abs=1e-15)
    assert cv.duration_to_seconds(Duration(sec=1, nanosec=999_999_999)) == pytest.approx(1.999999999)
    assert cv.duration_to_seconds(cv.seconds_to_duration(-0.25)) == -0.25


@pytest.mark.parametrize('bad', [math.nan, math.inf, -math.inf, 2.0 ** 31])
def test_seconds_out_of_range_are_rejected(bad):
    with pytest.raises(ValueError, match='finite|int32'):
        cv.seconds_to_duration(bad)


def test_negative_time_is_rejected():
    with pytest.raises(ValueError, match='>= 0'):
        cv.seconds_to_time(-1.0)


# --- images -----------------------------------------------------------------------

def sample_pixels(encoding, height=3, width=4):
    n = height * width
    if encoding in ('rgb8', 'bgr8'):
        return (np.arange(n * 3) * 7 % 256).astype(np.uint8).reshape(height, width, 3)
    if encoding == 'mono8':
        return (np.arange(n) * 13 % 256).astype(np.uint8).reshape(height, width)
    if encoding == '16UC1':
        return (np.arange(n) * 4099 + 258).astype(np.uint16).reshape(height, width)
    return (np.arange(n) * 0.125 - 1.0).astype(np.float32).reshape(height, width)


ENCODINGS = ['rgb8', 'bgr8', 'mono8', '16UC1', '32FC1']
PIXEL_BYTES = {'rgb8': 3, 'bgr8': 3, 'mono8': 1, '16UC1': 2, '32FC1': 4}


@pytest.mark.parametrize('encoding', ENCODINGS)
def test_image_round_trip(encoding):
    pixels = sample_pixels(encoding)
    header = Header(stamp=Time(sec=5, nanosec=6), frame_id='camera_color_optical_frame')
    msg = cv.numpy_to_image(pixels, encoding, header)
    assert (msg.height, msg.width, msg.encoding, msg.is_bigendian) == (3, 4, encoding, 0)
    assert msg.step == 4 * PIXEL_BYTES[encoding] and len(msg.data) == msg.step * 3
    assert msg.header.frame_id == 'camera_color_optical_frame' and msg.header.stamp.nanosec == 6
    assert_rclpy_types(msg)
    for m in (msg, wire_round_trip(msg)):
        out = cv.image_to_numpy(m)
        assert out.dtype == pixels.dtype and out.shape == pixels.shape
        np.testing.assert_array_equal(out, pixels)


def test_known_byte_layout():
    rgb = cv.image_to_numpy(raw_image('rgb8', 1, 2, 6, bytes([1, 2, 3, 4, 5, 6])))
    assert rgb[0, 1].tolist() == [4, 5, 6]
    depth = cv.image_to_numpy(raw_image('16UC1', 1, 2, 4, bytes([0x02, 0x01, 0xE8, 0x03])))
    assert depth.tolist() == [[258, 1000]]                  # little-endian millimetres
    depth_m = cv.image_to_numpy(raw_image('32FC1', 1, 1, 4, struct.pack('<f', 1.5)))
    assert depth_m.tolist() == [[1.5]]
    assert bytes(cv.numpy_to_image(np.array([[258]], np.uint16), '16UC1').data) == b'\x02\x01'


@pytest.mark.parametrize('encoding', ENCODINGS)
@pytest.mark.parametrize('padding', [1, 3, 8])
def test_padded_rows_are_skipped(encoding, padding):
    pixels = sample_pixels(encoding)
    row_bytes = 4 * PIXEL_BYTES[encoding]
    step = row_bytes + padding
    packed = pixels.astype(pixels.dtype.newbyteorder('<')).reshape(3, -1).view(np.uint8)
    rows = np.full((3, step), 0xEE, np.uint8)       # padding bytes hold junk
    rows[:, :row_bytes] = packed
    out = cv.image_to_numpy(raw_image(encoding, 3, 4, step, array.array('B', rows.tobytes())))
    np.testing.assert_array_equal(out, pixels)


def test_image_to_numpy_is_a_read_only_view_of_buffer_data():
    msg = cv.numpy_to_image(sample_pixels('mono8'), 'mono8')
    out = cv.image_to_numpy(msg)
    assert isinstance(msg.data, array.array)
    assert np.shares_memory(out, np.frombuffer(msg.data, np.uint8))
    assert not out.flags.writeable
    with pytest.raises(ValueError):
        out[0, 0] = 1
    for data in (bytes(msg.data), list(msg.data), np.frombuffer(msg.data, np.uint8).copy()):
        out = cv.image_to_numpy(raw_image('mono8', 3, 4, 4, data))
        assert not out.flags.writeable
        np.testing.assert_array_equal(out, sample_pixels('mono8'))


def test_big_endian_data_is_byteswapped_to_native():
    depth = cv.image_to_numpy(raw_image('16UC1', 1, 2, 4, bytes([0x01, 0x02, 0x03, 0xE8]), 1))
    assert depth.tolist() == [[258, 1000]] and depth.dtype.isnative
    depth_m = cv.image_to_numpy(raw_image('32FC1', 1, 2, 8, struct.pack('>ff', 2.5, -1.0), 1))
    assert depth_m.tolist() == [[2.5, -1.0]] and not depth_m.flags.writeable
    mono = cv.image_to_numpy(raw_image('mono8', 1, 2, 2, bytes([7, 9]), 1))
    assert mono.tolist() == [[7, 9]]


@pytest.mark.parametrize('msg, message', [
    (raw_image('yuv422', 1, 1, 2, bytes(2)), "unsupported image encoding 'yuv422'"),
    (raw_image('rgb8', 2, 4, 11, bytes(22)), r'step 11 is less than width \* bytes per pixel = 4 \* 3 = 12'),
    (raw_image('16UC1', 2, 2, 4, bytes(7)), r'7 bytes, expected step \* height = 4 \* 2 = 8'),
    (raw_image('mono8', 2, 2, 2, bytes(5)), r'5 bytes, expected step \* height = 2 \* 2 = 4'),
    (raw_image('mono8', 0, 2, 2, bytes(0)), 'empty: height=0, width=2'),
    (raw_image('mono8', 2, 0, 0, bytes(0)), 'empty: height=2, width=0'),
])
def test_bad_images_are_rejected(msg, message):
    with pytest.raises(ValueError, match=message):
        cv.image_to_numpy(msg)


@pytest.mark.parametrize('pixels, encoding, message', [
    (np.zeros((2, 2), np.float64), '32FC1',
     r'32FC1 needs a \(H, W\) float32 array, got shape \(2, 2\) dtype float64'),
    (np.zeros((2, 2), np.uint16), 'mono8', 'mono8 needs a'),
    (np.zeros((2, 2), np.float32), '16UC1', '16UC1 needs a'),
    (np.zeros((2, 2), np.uint8), 'rgb8', r'rgb8 needs a \(H, W, 3\) uint8 array'),
    (np.zeros((2, 2, 4), np.uint8), 'bgr8', 'bgr8 needs a'),
    (np.zeros((2, 2, 3), np.uint8), 'mono8', 'mono8 needs a'),
    (np.zeros((0, 4), np.uint8), 'mono8', 'empty: height=0, width=4'),
    (np.zeros((2, 2), np.uint8), '8UC1', "unsupported image encoding '8UC1'"),
])
def test_bad_arrays_are_rejected(pixels, encoding, message):
    with pytest.raises(ValueError, match=message):
        cv.numpy_to_image(pixels, encoding)


# --- camera intrinsics --------------------------------------------------------------

def test_intrinsics_to_camera_info_known_values():
    intrinsics = cv.Intrinsics(fx=615.0, fy=615.5, cx=320.5, cy=240.25, width=640, height=480)
    info = cv.intrinsics_to_camera_info(intrinsics, 'camera_color_optical_frame', Time(sec=7, nanosec=8))
    assert_rclpy_types(info)
    assert (info.width, info.height, info.distortion_model) == (640, 480, 'plumb_bob')
    assert info.header.frame_id == 'camera_color_optical_frame'
    assert (info.header.stamp.sec, info.header.stamp.nanosec) == (7, 8)
    assert list(info.d) == [0.0] * 5
    assert list(info.k) == [615.0, 0, 320.5, 0, 615.5, 240.25, 0, 0, 1]
    assert list(info.r) == [1, 0, 0, 0, 1, 0, 0, 0, 1]
    assert list(info.p) == [615.0, 0, 320.5, 0, 0, 615.5, 240.25, 0, 0, 0, 1, 0]
    np.testing.assert_array_equal(intrinsics.matrix, [[615, 0, 320.5], [0, 615.5, 240.25], [0, 0, 1]])
    assert cv.camera_info_to_intrinsics(wire_round_trip(info)) == intrinsics
    unstamped = cv.intrinsics_to_camera_info(intrinsics, 'cam')
    assert (unstamped.header.stamp.sec, unstamped.header.stamp.nanosec) == (0, 0)


def test_intrinsics_from_matrix_accepts_3x3_and_flat():
    k = [[600.0, 0.0, 319.0], [0.0, 601.0, 239.0], [0.0, 0.0, 1.0]]
    a = cv.Intrinsics.from_matrix(k, 640, 480)
    assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (600, 601, 319, 239, 640, 480)
    assert cv.Intrinsics.from_matrix(np.ravel(k), np.uint32(640), 480) == a
    assert type(a.width) is int and type(a.fx) is float


@pytest.mark.parametrize('kwargs, message', [
    (dict(fx=0.0), 'fx must be finite and > 0, got 0.0'),
    (dict(fy=-615.0), 'fy must be finite and > 0'),
    (dict(fx=math.nan), 'fx must be finite'),
    (dict(cx=math.inf), 'cx must be finite, got inf'),
    (dict(width=0), 'width must be a positive integer'),
    (dict(height=480.0), 'height must be a positive integer'),
])
def test_bad_intrinsics_are_rejected(kwargs, message):
    values = dict(fx=615.0, fy=615.0, cx=320.0, cy=240.0, width=640, height=480) | kwargs
    with pytest.raises(ValueError, match=message):
        cv.Intrinsics(**values)


@pytest.mark.parametrize('k, message', [
    ([615.0, 0, 320, 0, 615, 240, 0, 0], r'K must be 3x3 or 9 values, got shape \(8,\)'),
    ([615.0, 0.5, 320, 0, 615, 240, 0, 0, 1], r'K must be \[\[fx, 0, cx\]'),
    ([615.0, 0, 320, 0, 615, 240, 0, 0, 2], r'K must be \[\[fx, 0, cx\]'),
    ([615.0, 0, 320, 0, math.nan, 240, 0, 0, 1], 'K must be finite'),
    ([0.0] * 9, r'K must be \[\['),        # an uncalibrated CameraInfo
    ([0.0, 0, 320, 0, 615, 240, 0, 0, 1], 'fx must be finite and > 0'),
])
def test_bad_camera_matrices_are_rejected(k, message):
    with pytest.raises(ValueError, match=message):
        cv.Intrinsics.from_matrix(k, 640, 480)


# --- rotations and transforms ------------------------------------------------------

S = math.sqrt(0.5)


def test_quat_to_matrix_known_rotation():
    rz90 = cv.quat_to_matrix([0, 0, S, S])          # 90 degrees about z: x -> y, y -> -x
    np.testing.assert_allclose(rz90, [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(cv.quat_to_matrix([1, 0, 0, 0]), np.diag([1, -1, -1]), atol=1e-12)


@pytest.mark.parametrize('quat', [
    [0, 0, 0, 1], [0, 0, S, S], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0],   # each Shepperd branch
    [S, S, 0, 0], [0.5, -0.5, 0.5, 0.5], [0.1, 0.2, 0.3, -0.927362], [0, 0, S, -S],
    [0.9, 0.2, 0.1, 0.3], [0.2, 0.9, 0.1, 0.3], [0.1, 0.2, 0.9, 0.3],        # trace < 0, w != 0
    [0.9, 0.2, 0.1, -0.3], [0.2, 0.9, 0.1, -0.3], [0.1, 0.2, 0.9, -0.3],
])
def test_matrix_to_quat_inverts_quat_to_matrix(quat):
    quat = np.array(quat) / np.linalg.norm(quat)
    back = cv.matrix_to_quat(cv.quat_to_matrix(quat))
    assert back[3] >= 0 and abs(np.linalg.norm(back) - 1) < 1e-12
    assert min(np.abs(back - quat).max(), np.abs(back + quat).max()) < 1e-12


def test_transform_round_trip():
    msg = TransformStamped()
    msg.transform = Transform(translation=Vector3(x=1.0, y=-2.0, z=0.5),
                              rotation=Quaternion(x=0.0, y=0.0, z=S, w=S))
    matrix = cv.transform_to_matrix(msg)
    np.testing.assert_allclose(matrix, [[0, -1, 0, 1], [1, 0, 0, -2], [0, 0, 1, 0.5], [0, 0, 0, 1]],
                               atol=1e-12)
    np.testing.assert_array_equal(cv.transform_to_matrix(msg.transform), matrix)
    back = cv.matrix_to_transform(matrix)
    assert_rclpy_types(back)
    assert (back.translation.x, back.translation.y, back.translation.z) == (1.0, -2.0, 0.5)
    np.testing.assert_allclose([back.rotation.x, back.rotation.y, back.rotation.z, back.rotation.w],
                               [0, 0, S, S], atol=1e-12)
    np.testing.assert_allclose(cv.transform_to_matrix(wire_round_trip(back)), matrix, atol=1e-12)


@pytest.mark.parametrize('matrix, message', [
    (np.eye(3), r'transform must be 4x4, got shape \(3, 3\)'),
    (np.diag([2.0, 2.0, 2.0, 1.0]), 'not a rotation matrix'),
    (np.diag([1.0, 1.0, -1.0, 1.0]), r'not a rotation matrix .*det = -1'),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), r'last row \[0, 0, 0, 1\]'),
    (np.array([[1, 0, 0, math.nan], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), 'finite'),
])
def test_bad_matrices_are_rejected(matrix, message):
    with pytest.raises(ValueError, match=message):
        cv.matrix_to_transform(matrix)


def test_transform_with_bad_rotation_is_rejected():
    with pytest.raises(ValueError, match='zero norm'):
        cv.transform_to_matrix(Transform(rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=0.0)))
    with pytest.raises(ValueError, match='must be unit'):
        cv.transform_to_matrix(Transform(rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.1)))


# --- depth to points -------------------------------------------------------------

# A camera at (1, 2, 3) looking along world +X, mounted as a ROS camera_link -> optical frame:
# optical z -> world +X, optical x -> world -Y, optical y -> world -Z (not a symmetric rotation).
CAMERA_TO_WORLD = np.array([[0.0, 0, 1, 1], [-1, 0, 0, 2], [0, -1, 0, 3], [0, 0, 0, 1]])
SMALL = cv.Intrinsics(fx=10.0, fy=20.0, cx=3.0, cy=2.0, width=8, height=6)


def plane_depth():
    depth = np.full((6, 8), 2.0, np.float32)     # a wall 2 m in front of the camera
    depth[0, 0], depth[1, 5], depth[4, 2], depth[5, 7] = 0.0, np.nan, np.inf, -1.0
    return depth


def expected_plane_points():
    points = []
    for v in range(6):
        for u in range(8):
            if (v, u) not in ((0, 0), (1, 5), (4, 2), (5, 7)):
                points.append([1 + 2.0, 2 - (u - 3.0) * 2 / 10, 3 - (v - 2.0) * 2 / 20])
    return np.array(points)


def test_plane_lands_where_expected():
    points = cv.depth_to_points(plane_depth(), SMALL, CAMERA_TO_WORLD)
    assert points.dtype == np.float32 and points.shape == (6 * 8 - 4, 3)
    np.testing.assert_allclose(points, expected_plane_points(), atol=1e-5, rtol=0)
    # the principal point (u, v) = (3, 2) looks straight ahead onto (3, 2, 3); pixel (7, 0) is
    # right of and above it: world -Y (right) by (7 - 3) * 2 / 10, +Z (up) by 2 * 2 / 20
    np.testing.assert_allclose(points[2 * 8 + 3 - 2], [3, 2, 3], atol=1e-6)
    np.testing.assert_allclose(points[7 - 1], [3, 2 - 0.8, 3 + 0.2], atol=1e-6)


def test_vga_plane_with_realsense_intrinsics():
    intrinsics = cv.Intrinsics(fx=615.0, fy=615.0, cx=319.5, cy=239.5, width=640, height=480)
    points = cv.depth_to_points(np.full((480, 640), 1.5), intrinsics, np.eye(4))
    assert points.shape == (640 * 480, 3)
    np.testing.assert_allclose(points[:, 2], 1.5, atol=1e-6)
    np.testing.assert_allclose(points[0], [-319.5 * 1.5 / 615, -239.5 * 1.5 / 615, 1.5], atol=1e-6)
    np.testing.assert_allclose(points[-1], [319.5 * 1.5 / 615, 239.5 * 1.5 / 615, 1.5], atol=1e-6)


@pytest.mark.parametrize('encoding', ['16UC1', '32FC1'])
def test_depth_image_messages(encoding):
    depth = plane_depth()
    if encoding == '16UC1':                        # RealSense: millimetres, 0 = no reading
        depth = np.where(np.isfinite(depth) & (depth > 0), depth * 1000, 0).astype(np.uint16)
    msg = wire_round_trip(cv.numpy_to_image(depth, encoding))
    info = cv.intrinsics_to_camera_info(SMALL, 'camera_depth_optical_frame')
    points = cv.depth_image_to_points(msg, info, CAMERA_TO_WORLD)
    np.testing.assert_allclose(points, expected_plane_points(), atol=1e-5, rtol=0)


def test_bad_depth_inputs_are_rejected():
    with pytest.raises(ValueError, match=re.escape('depth image has shape (6, 7), '
                                                   'intrinsics are for (H, W) = (6, 8)')):
        cv.depth_to_points(np.ones((6, 7)), SMALL, np.eye(4))
    with pytest.raises(ValueError, match='float array in metres, got uint16'):
        cv.depth_to_points(np.ones((6, 8), np.uint16), SMALL, np.eye(4))
    with pytest.raises(ValueError, match='not a rotation matrix'):
        cv.depth_to_points(np.ones((6, 8)), SMALL, np.diag([1.0, 1.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="16UC1 \\(mm\\) or 32FC1 \\(m\\), got 'mono8'"):
        cv.depth_image_to_points(cv.numpy_to_image(np.ones((6, 8), np.uint8), 'mono8'),
                                 cv.intrinsics_to_camera_info(SMALL, 'cam'), np.eye(4))


# --- poses ----------------------------------------------------------------------

def test_pose_round_trip_normalises_quaternion():
    msg = cv.xyz_quat_to_pose_stamped(np.array([0.4, -0.1, 0.25]), [0, 0, 2, 0], 'base_link',
                                      Time(sec=1, nanosec=2))
    assert_rclpy_types(msg)
    assert msg.header.frame_id == 'base_link' and msg.header.stamp.sec == 1
    assert (msg.pose.orientation.z, msg.pose.orientation.w) == (1.0, 0.0)
    xyz, quat = cv.pose_to_xyz_quat(wire_round_trip(msg))
    assert xyz.tolist() == [0.4, -0.1, 0.25] and quat.tolist() == [0, 0, 1, 0]
    xyz, quat = cv.pose_to_xyz_quat(msg.pose)                         # a bare Pose too
    assert xyz.shape == (3,) and quat.shape == (4,)


def test_pose_quaternion_close_to_unit_is_renormalised():
    pose = Pose()
    pose.orientation = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0005)
    assert cv.pose_to_xyz_quat(pose)[1].tolist() == [0, 0, 0, 1]


@pytest.mark.parametrize('position, orientation, message', [
    ((math.nan, 0, 0), (0, 0, 0, 1), 'position must be finite'),
    ((0, math.inf, 0), (0, 0, 0, 1), 'position must be finite'),
    ((0, 0, 0), (0, 0, math.nan, 1), 'quaternion must be finite'),
    ((0, 0, 0), (0, 0, 0, -math.inf), 'quaternion must be finite'),
    ((0, 0, 0), (0, 0, 0, 1.01), r'quaternion must be unit .*got norm 1\.01'),
    ((0, 0, 0), (0.5, 0.5, 0, 0), 'quaternion must be unit'),
    ((0, 0, 0), (0, 0, 0, 0), 'quaternion has zero norm'),
])
def test_bad_poses_are_rejected(position, orientation, message):
    pose = Pose()
    pose.position.x, pose.position.y, pose.position.z = (float(c) for c in position)
    pose.orientation = Quaternion(**dict(zip('xyzw', (float(c) for c in orientation))))
    with pytest.raises(ValueError, match=message):
        cv.pose_to_xyz_quat(pose)


@pytest.mark.parametrize('xyz, quat, message', [
    ([0, 0, math.nan], [0, 0, 0, 1], 'position must be finite'),
    ([0, 0, 0], [math.inf, 0, 0, 1], 'quaternion must be finite'),
    ([0, 0, 0], [0, 0, 0, 0], 'quaternion has zero norm'),
    ([0, 0], [0, 0, 0, 1], r'position must have shape \(3,\)'),
    ([0, 0, 0], [0, 0, 1], r'quaternion must have shape \(4,\)'),
])
def test_bad_pose_inputs_are_rejected(xyz, quat, message):
    with pytest.raises(ValueError, match=message):
        cv.xyz_quat_to_pose_stamped(xyz, quat, 'base_link')


# --- joint trajectories ------------------------------------------------------------

JOINTS = ['shoulder', 'elbow']
POSITIONS = [[0.0, 0.1], [0.5, -0.2], [1.0, 0.3]]


@pytest.mark.parametrize('velocities', [None, [[0.0, 0.0], [1.0, -0.5], [0.0, 0.0]]])
def test_trajectory_round_trip(velocities):
    msg = cv.build_joint_trajectory(JOINTS, POSITIONS, [0.5, 1.0, 1.9999999999], velocities,
                                    frame_id='base_link')
    assert_rclpy_types(msg)
    assert msg.joint_names == JOINTS and msg.header.frame_id == 'base_link'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 0)      # "start now"
    assert [(p.time_from_start.sec, p.time_from_start.nanosec) for p in msg.points] == [
        (0, 500_000_000), (1, 0), (2, 0)]
    assert list(msg.points[1].positions) == [0.5, -0.2]
    names, positions, times, parsed_velocities = cv.parse_joint_trajectory(wire_round_trip(msg))
    assert names == JOINTS and times.tolist() == [0.5, 1.0, 2.0]
    assert positions.dtype == np.float64 and positions.tolist() == POSITIONS
    if velocities is None:
        assert parsed_velocities is None and len(msg.points[0].velocities) == 0
    else:
        assert parsed_velocities.tolist() == velocities


def test_trajectory_stamp_is_kept():
    msg = cv.build_joint_trajectory(JOINTS, POSITIONS, [1, 2, 3], stamp=Time(sec=10, nanosec=5))
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (10, 5)


@pytest.mark.parametrize('kwargs, message', [
    (dict(times_from_start=[0.0, 0.1, 0.2, 0.2]),
     'time_from_start must be strictly increasing: point 3 at 0.2 s after point 2 at 0.2 s'),
    (dict(times_from_start=[1.0, 0.5, 2.0, 3.0]),
     'strictly increasing: point 1 at 0.5 s after point 0 at 1 s'),
    (dict(times_from_start=[-0.1, 0.5, 2.0, 3.0]), 'time_from_start must be >= 0: point 0 at -0.1 s'),
    (dict(times_from_start=[0.1, math.nan, 2.0, 3.0]),
     'times_from_start must be finite: times_from_start[1] is nan'),
    (dict(times_from_start=[0.1, 0.2, 0.3]), 'times_from_start must have shape (4,) for 4 points'),
    (dict(joint_names=['a', 'b', 'c']),
     'positions must have shape (T, 3) for 3 joint names, got (4, 2)'),
    (dict(joint_names=['a', 'a']), "joint names must be unique, repeated: ['a']"),
    (dict(joint_names=[]), 'joint_names is empty'),
    (dict(joint_names=['a', '']), 'joint names must be non-empty strings'),
    (dict(positions=[[0, 0], [0, math.inf], [0, 0], [0, 0]]),
     'positions must be finite: positions[1, 1] is inf'),
    (dict(positions=np.zeros((0, 2)), times_from_start=[]), 'trajectory has no points'),
    (dict(velocities=np.zeros((4, 3))),
     'velocities must have the shape of positions (4, 2), got (4, 3)'),
    (dict(velocities=np.full((4, 2), math.nan)), 'velocities must be finite: velocities[0, 0] is nan'),
])
def test_bad_trajectories_are_rejected(kwargs, message):
    args = dict(joint_names=['a', 'b'], positions=np.zeros((4, 2)),
                times_from_start=[0.0, 0.1, 0.2, 0.3]) | kwargs
    with pytest.raises(ValueError, match=re.escape(message)):
        cv.build_joint_trajectory(**args)


def trajectory_msg(points, joint_names=('a', 'b')):
    return JointTrajectory(joint_names=list(joint_names), points=[
        JointTrajectoryPoint(positions=array.array('d', positions), velocities=array.array('d', velocities),
                             time_from_start=cv.seconds_to_duration(t))
        for positions, velocities, t in points])


@pytest.mark.parametrize('points, message', [
    ([([0, 0], [], 0.2), ([1, 1], [], 0.2)],
     'time_from_start must be strictly increasing: point 1 at 0.2 s after point 0 at 0.2 s'),
    ([([0, 0], [], 0.1), ([1], [], 0.2)], 'point 1 has 1 positions for 2 joint names'),
    ([([0, 0], [1, 1], 0.1), ([1, 1], [], 0.2)], 'point 1 has 0 velocities for 2 joint names'),
    ([([0, 0], [], 0.1), ([1, math.nan], [], 0.2)], 'positions must be finite: positions[1, 1] is nan'),
    ([], 'trajectory has no points'),
])
def test_bad_trajectory_messages_are_rejected(points, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        cv.parse_joint_trajectory(trajectory_msg(points))


def test_trajectory_message_with_repeated_joint_is_rejected():
    with pytest.raises(ValueError, match='joint names must be unique'):
        cv.parse_joint_trajectory(trajectory_msg([([0, 0], [], 0.1)], joint_names=('a', 'a')))
