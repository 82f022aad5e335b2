"""RealSense D415-like RGB-D cameras rendered with PyBullet's TinyRenderer.

Intrinsics rule: pixels are square and the vertical field of view is always
42.3 deg, that of the D415 colour stream's 69 deg-wide 16:9 image; narrower
images are centre crops of that image. So a 16:9 image sees 69 x 42 deg
(1280x720: fx = 931), a 4:3 one 54 x 42 deg (640x480: fx = 621, the real
camera reports ~615) and a square one 42 x 42 deg. The principal point is
the image centre, ((W - 1) / 2, (H - 1) / 2) with pixel centres at integer
coordinates.

Depth is z along the optical axis (what RealSense reports), 16UC1
millimetres, 0 where nothing lies within ``max_depth_m``. Colour and depth
share one optical frame, ``<name>_color_optical_frame`` (x right, y down,
z forward), as aligned_depth_to_color does.
"""

from __future__ import annotations

import math
import zlib

import numpy as np
import pybullet

from hdp_msgs_py.conversions import Intrinsics, intrinsics_to_camera_info, matrix_to_transform
from hdp_msgs_py.msg import CameraInfo, Header, Time, TransformStamped

from .sensor_model import SensorSettings, degrade, perturbed_pose
from .world import WORKSPACE

HORIZONTAL_FOV_16_9 = 69.0    # deg, D415 colour
# tan of half the vertical FOV of the 16:9 image: tan(34.5 deg) * 9 / 16 (-> 42.3 deg).
_TAN_HALF_VFOV = math.tan(math.radians(HORIZONTAL_FOV_16_9 / 2)) * 9 / 16
# TinyRenderer needs near/far planes; the D415 sees from ~0.16 m.
NEAR, FAR = 0.1, 3.5          # m
# An OpenGL eye looks down -z with y up; the optical frame looks down +z with y down.
_OPTICAL_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def d415_intrinsics(width: int, height: int) -> Intrinsics:
    """Intrinsics of a width x height D415 colour image under the module's FOV rule."""
    f = (height / 2) / _TAN_HALF_VFOV
    return Intrinsics(fx=f, fy=f, cx=(width - 1) / 2, cy=(height - 1) / 2,
                      width=width, height=height)


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """(4, 4) camera_to_world of an optical frame at ``eye`` (3,) looking at ``target`` (3,).

    Image "up" (-y) points as close to ``up`` as possible.
    """
    eye, target, up = (np.asarray(v, dtype=float) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(-up, z)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f'view direction {z} is parallel to up {up}')
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    pose[:3, 3] = eye
    return pose


def gl_projection(intrinsics: Intrinsics, near: float = NEAR, far: float = FAR) -> np.ndarray:
    """(4, 4) OpenGL projection under which TinyRenderer draws a point where K puts it.

    TinyRenderer samples image pixel (u, v) at window coordinates
    (u, H - 1 - v) (window y runs up), not at pixel centres, so u = fx X/Z + cx
    must land on NDC x = 2u / W - 1 and v on NDC y = 1 - 2 (v + 1) / H.
    (Measured: table depths then match the analytic plane to 0.002 mm rms;
    with centre sampling they are off by half a pixel, ~1.7 mm.)
    """
    i = intrinsics
    return np.array([
        [2 * i.fx / i.width, 0.0, 1 - 2 * i.cx / i.width, 0.0],
        [0.0, 2 * i.fy / i.height, 2 * (i.cy + 1) / i.height - 1, 0.0],
        [0.0, 0.0, -(far + near) / (far - near), -2 * far * near / (far - near)],
        [0.0, 0.0, -1.0, 0.0]])


class D415Camera:
    """One RGB-D camera: a name, a pose, a resolution and its D415 intrinsics.

    ``camera_to_world`` is the (4, 4) pose of the optical frame in the world.
    """

    def __init__(self, name: str, camera_to_world, width: int = 640, height: int = 480,
                 max_depth_m: float = FAR):
        self.name = name
        self.camera_to_world = np.array(camera_to_world, dtype=float)
        self.intrinsics = d415_intrinsics(width, height)
        if not 0 < max_depth_m <= FAR:
            raise ValueError(f'max_depth_m must be in (0, {FAR}] (the far plane), '
                             f'got {max_depth_m}')
        self.max_depth_m = float(max_depth_m)
        self._view = (_OPTICAL_TO_GL @ np.linalg.inv(self.camera_to_world)).T.reshape(-1).tolist()
        self._projection = gl_projection(self.intrinsics).T.reshape(-1).tolist()   # column-major

    @classmethod
    def looking_at(cls, name: str, eye, target, up=(0.0, 0.0, 1.0), **kwargs) -> D415Camera:
        """A camera at ``eye`` (3,) looking at ``target`` (3,); kwargs as for __init__."""
        return cls(name, look_at(eye, target, up), **kwargs)

    @property
    def frame_id(self) -> str:
        return f'{self.name}_color_optical_frame'

    def render(self, client) -> tuple[np.ndarray, np.ndarray]:
        """rgb (H, W, 3) uint8 and depth (H, W) uint16 mm (0: no reading) of ``client``'s scene."""
        width, height = self.intrinsics.width, self.intrinsics.height
        _, _, rgba, depth_buffer, _ = client.getCameraImage(
            width, height, self._view, self._projection, renderer=pybullet.ER_TINY_RENDERER,
            flags=pybullet.ER_NO_SEGMENTATION_MASK)
        rgb = np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[:, :, :3].copy()
        d = np.asarray(depth_buffer, dtype=np.float64).reshape(height, width)
        z = FAR * NEAR / (FAR - (FAR - NEAR) * d)
        depth_mm = np.round(z * 1000.0)
        # The empty background reads d = 0.9999999 (float32), z = FAR to within 1e-5.
        valid = (z < 0.999 * FAR) & (depth_mm <= 1000.0 * self.max_depth_m)
        return rgb, np.where(valid, depth_mm, 0).astype(np.uint16)

    def camera_info(self, stamp=None) -> CameraInfo:
        """sensor_msgs/CameraInfo (plumb_bob, no distortion) in ``frame_id``."""
        return intrinsics_to_camera_info(self.intrinsics, self.frame_id, stamp)

    def transform_stamped(self, parent: str = 'world', stamp=None) -> TransformStamped:
        """geometry_msgs/TransformStamped parent -> optical frame, for /tf_static."""
        header = Header(stamp=stamp if stamp is not None else Time(), frame_id=parent)
        return TransformStamped(header=header, child_frame_id=self.frame_id,
                                transform=matrix_to_transform(self.camera_to_world))


# Eye offsets from the workspace centre, m: the whole WORKSPACE box stays in view with a
# margin even in a square (42 x 42 deg) image, ~1.7 m away as a mounted D415 would be.
# "front" looks over the robot's shoulder, so it sees the faces of the objects that
# the tasks turn towards the robot (drawer handles, lids, door levers).
_EYE_OFFSETS = {'front': (-0.7, 1.0, 1.1),    # behind the robot's left shoulder, high
                'side': (0.0, -1.05, 1.25)}    # from the robot's right, looking down


def default_cameras(width: int = 640, height: int = 480, **kwargs) -> dict[str, D415Camera]:
    """The two fixed cameras, "front" and "side", both looking at the centre of WORKSPACE.

    kwargs go to D415Camera.
    """
    center = WORKSPACE.mean(axis=0)
    return {name: D415Camera.looking_at(name, center + offset, center, width=width, height=height,
                                        **kwargs)
            for name, offset in _EYE_OFFSETS.items()}


class CameraRig:
    """Cameras as a real rig delivers their frames: each renders from where it really is (its
    nominal pose, which CameraInfo and /tf_static keep, off by a calibration error drawn per
    episode) and each frame passes through the sensor model. Random draws are seeded per (episode
    seed, camera, frame), so a re-run gives the same frames whatever ran before it; with ideal
    settings a frame is the camera's own render, bit for bit.

    cameras: name -> D415Camera, nominal. settings: a SensorSettings.
    """

    def __init__(self, cameras: dict[str, D415Camera], settings: SensorSettings = SensorSettings()):
        self.cameras, self.settings = cameras, settings
        self.start_episode(0)

    def start_episode(self, seed: int) -> None:
        """Draw this episode's calibration errors from ``seed``; later frames are seeded with it."""
        self.seed = seed
        self.rendering = {name: self._as_mounted(camera) for name, camera in self.cameras.items()}

    def _as_mounted(self, camera: D415Camera) -> D415Camera:
        error_mm, error_deg = self.settings.extrinsic_error_mm, self.settings.extrinsic_error_deg
        if not (error_mm or error_deg):
            return camera
        pose = perturbed_pose(camera.camera_to_world, error_mm, error_deg, self._rng(camera.name, 0))
        return D415Camera(camera.name, pose, camera.intrinsics.width, camera.intrinsics.height, camera.max_depth_m)

    def _rng(self, name: str, *stream: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, zlib.crc32(name.encode()), *stream])

    def render(self, client, name: str, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """rgb (H, W, 3) uint8 and depth (H, W) uint16 mm of camera ``name`` as delivered; ``frame``: a
        non-negative integer naming the frame within the episode (physics steps since its start)."""
        camera = self.cameras[name]
        rgb, depth = self.rendering[name].render(client)
        return degrade(rgb, depth, camera.intrinsics.fx, self.settings.profile, self._rng(name, 1, frame))
