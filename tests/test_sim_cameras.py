"""hdp_sim_bridge.cameras: D415 intrinsics, and renders that agree with CameraInfo and /tf_static.

Geometry checks go through the messages a subscriber gets: the 16UC1 image,
CameraInfo and the TransformStamped, back-projected with hdp_msgs_py.conversions.
"""

import itertools
import math

import numpy as np
import pybullet
import pytest

from hdp_msgs_py import conversions as cv
from hdp_msgs_py.msg import Time
from hdp_sim_bridge.cameras import D415Camera, d415_intrinsics, default_cameras, look_at
from hdp_sim_bridge.world import (TABLE_CENTER_XY, TABLE_HALF_EXTENTS, TABLE_TOP_Z, WORKSPACE,
                                  PandaWorld)

pytestmark = pytest.mark.unit

BOX_CENTER = np.array([0.5, -0.15, TABLE_TOP_Z + 0.04])
BOX_HALF = np.array([0.05, 0.04, 0.04])
BOX_YAW = math.radians(30)
BALL_CENTER = np.array([0.6, 0.2, TABLE_TOP_Z + 0.15])
BALL_RADIUS = 0.02
GREEN = (0.0, 1.0, 0.0, 1.0)


@pytest.fixture(scope='module')
def scene():
    """The robot at HOME, a yawed box on the table and a green ball floating above it."""
    with PandaWorld() as world:
        c = world.client
        c.createMultiBody(0.0, c.createCollisionShape(pybullet.GEOM_BOX, halfExtents=BOX_HALF),
                          c.createVisualShape(pybullet.GEOM_BOX, halfExtents=BOX_HALF),
                          basePosition=BOX_CENTER,
                          baseOrientation=c.getQuaternionFromEuler((0, 0, BOX_YAW)))
        c.createMultiBody(0.0, -1, c.createVisualShape(pybullet.GEOM_SPHERE, radius=BALL_RADIUS,
                                                       rgbaColor=GREEN),
                          basePosition=BALL_CENTER)
        yield world


def world_points(camera, depth_mm) -> np.ndarray:
    """(N, 3) world points of a depth render, through the messages a subscriber would get."""
    depth_msg = cv.numpy_to_image(depth_mm, '16UC1')
    camera_to_world = cv.transform_to_matrix(camera.transform_stamped())
    return cv.depth_image_to_points(depth_msg, camera.camera_info(), camera_to_world)


def project(camera, points) -> np.ndarray:
    """(N, 2) pixel (u, v) of world points through the CameraInfo K and the /tf_static pose."""
    k = np.asarray(camera.camera_info().k).reshape(3, 3)
    world_to_camera = np.linalg.inv(cv.transform_to_matrix(camera.transform_stamped()))
    in_camera = np.asarray(points) @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    pixels = in_camera @ k.T
    return pixels[:, :2] / pixels[:, 2:]


def test_intrinsics_follow_the_d415_fov_rule():
    vga = d415_intrinsics(640, 480)
    assert 600 <= vga.fx <= 630 and vga.fy == vga.fx          # the real D415 reports ~615
    assert (vga.cx, vga.cy) == (319.5, 239.5)
    hd = d415_intrinsics(1280, 720)
    assert math.degrees(2 * math.atan(640 / hd.fx)) == pytest.approx(69.0)
    for width, height in ((640, 480), (1280, 720), (128, 128)):  # 42.3 deg high at any size
        fy = d415_intrinsics(width, height).fy
        assert math.degrees(2 * math.atan(height / 2 / fy)) == pytest.approx(42.27, abs=0.01)


def test_camera_info_and_transform_messages():
    camera = D415Camera.looking_at('front', (1.5, 0.2, 1.8), (0.5, 0.0, 0.8),
                                   width=320, height=240)
    info = camera.camera_info(stamp=Time(sec=5, nanosec=7))
    assert info.header.frame_id == 'front_color_optical_frame'
    assert (info.header.stamp.sec, info.header.stamp.nanosec) == (5, 7)
    assert (info.width, info.height, info.distortion_model) == (320, 240, 'plumb_bob')
    np.testing.assert_allclose(np.reshape(info.k, (3, 3)), camera.intrinsics.matrix)
    np.testing.assert_allclose(np.reshape(info.p, (3, 4)),
                               np.hstack([camera.intrinsics.matrix, np.zeros((3, 1))]))
    tf = camera.transform_stamped()
    assert (tf.header.frame_id, tf.child_frame_id) == ('world', 'front_color_optical_frame')
    np.testing.assert_allclose(cv.transform_to_matrix(tf), camera.camera_to_world, atol=1e-9)


def test_look_at_gives_an_optical_frame():
    pose = look_at((1.0, -1.0, 2.0), (0.0, 0.0, 1.0))
    rotation = pose[:3, :3]
    np.testing.assert_allclose(rotation.T @ rotation, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    ahead = np.array([-1.0, 1.0, -1.0]) / math.sqrt(3)
    np.testing.assert_allclose(rotation[:, 2], ahead)           # z: toward the target
    assert rotation[2, 0] == pytest.approx(0.0, abs=1e-12)      # x: level
    assert rotation[2, 1] < 0                                   # y: image down is world down
    with pytest.raises(ValueError):
        look_at((0, 0, 1), (0, 0, 0))                           # looking along "up"


@pytest.mark.parametrize('size', [(640, 480), (128, 128)])
def test_default_cameras_see_the_whole_workspace(size):
    corners = np.array(list(itertools.product(*WORKSPACE.T)))   # (8, 3)
    for camera in default_cameras(*size).values():
        u, v = project(camera, corners).T
        assert np.all((u > 0) & (u < size[0] - 1) & (v > 0) & (v < size[1] - 1)), camera.name


@pytest.mark.parametrize('name', ['front', 'side'])
def test_depth_lands_on_the_table_and_the_box(scene, name):
    camera = default_cameras(640, 480)[name]
    _, depth = camera.render(scene.client)
    points = world_points(camera, depth)

    # Table top: everything seen inside its outline and below 2 cm above it, away from the
    # robot's base and the box.
    half = np.array(TABLE_HALF_EXTENTS[:2]) - 0.02
    on_table = (np.all(np.abs(points[:, :2] - TABLE_CENTER_XY) < half, axis=1)
                & (points[:, 2] < TABLE_TOP_Z + 0.02)
                & (np.linalg.norm(points[:, :2], axis=1) > 0.2)
                & (np.linalg.norm(points[:, :2] - BOX_CENTER[:2], axis=1) > 0.1))
    assert on_table.sum() > 50_000
    np.testing.assert_allclose(points[on_table, 2], TABLE_TOP_Z, atol=0.005)

    # Box: points near it (in its own frame) lie on its faces.
    cos, sin = math.cos(BOX_YAW), math.sin(BOX_YAW)
    to_box = np.array([[cos, sin, 0.0], [-sin, cos, 0.0], [0.0, 0.0, 1.0]])
    local = (points - BOX_CENTER) @ to_box.T
    near = np.all(np.abs(local) < BOX_HALF + 0.01, axis=1) & (points[:, 2] > TABLE_TOP_Z + 0.003)
    assert near.sum() > 500
    outside = np.linalg.norm(np.maximum(np.abs(local[near]) - BOX_HALF, 0.0), axis=1)
    inside = np.min(BOX_HALF - np.abs(local[near]), axis=1)
    distance_to_surface = np.where(outside > 0, outside, inside)
    assert distance_to_surface.max() < 0.005


@pytest.mark.parametrize('size', [(640, 480), (128, 128)])
def test_ball_renders_where_camera_info_projects_it(scene, size):
    for camera in default_cameras(*size).values():
        rgb, _ = camera.render(scene.client)
        r, g, b = (rgb[:, :, i].astype(int) for i in range(3))
        rows, cols = np.nonzero((g > 40) & (g > 2 * r) & (g > 2 * b))
        assert rows.size > 3, camera.name
        centroid = np.array([cols.mean(), rows.mean()])
        # Tight enough to catch a half-pixel convention error.
        np.testing.assert_allclose(centroid, project(camera, [BALL_CENTER])[0], atol=0.3)


def test_depth_is_zero_beyond_max_range(scene):
    camera = default_cameras(128, 128)['front']
    _, full = camera.render(scene.client)
    near_only = D415Camera('front', camera.camera_to_world, 128, 128, max_depth_m=2.0)
    _, clipped = near_only.render(scene.client)
    assert np.any(full > 2000) and np.any((full > 0) & (full <= 2000))
    np.testing.assert_array_equal(clipped, np.where(full <= 2000, full, 0))

    sky = D415Camera.looking_at('up', (0.5, 0.0, TABLE_TOP_Z + 0.5), (0.5, 0.0, 3.0), up=(1, 0, 0),
                                width=64, height=48)
    _, empty = sky.render(scene.client)
    assert empty.dtype == np.uint16 and not empty.any()
