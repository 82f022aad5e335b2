"""Training frames made to look like a RealSense D415's: numpy only, on the depth image, before it is
unprojected, so the agent trained on ideal renders learns to read noisy, holed depth.

Per frame, with probability ``probability`` (0: off):

- stereo noise from Intel's formula (depth-quality guidance): a disparity error of ``subpixel`` px
  RMS, so an RMS depth error of z^2 * subpixel / (focal px * baseline), the focal length raised to
  the D415's smallest depth mode's (a smaller image is resampled from that stream); subpixel is
  drawn per frame between ``subpixel`` and ``subpixel_max`` (texture and lighting vary, dark
  surfaces return less of the projector's pattern);
- at depth steps steeper than a surface ``edge_grazing_deg`` from grazing, a share of pixels with
  no depth and a share of flying pixels between the two sides (block matching mixes them);
- a random share of pixels with no depth, drawn per frame up to ``random_hole_share``;
- a calibration error per camera (``perturbed_extrinsics``): the frame is unprojected with extrinsics
  off from the camera's true pose by up to ``extrinsic_error_mm`` and ``extrinsic_error_deg``
  (magnitudes uniform, directions random), while the target stays where the demonstration put it,
  so the agent learns to place targets from two clouds that disagree, and from the hand it is told of.

It is written apart from the simulator's sensor model (hdp_sim_bridge.sensor_model, which the planner
may not import), and deliberately broader than it: training should not fit one simulator's noise.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class DepthAugmentation:
    """The ``depth_augmentation:`` section of the planner's training config; the defaults are a D415's."""
    probability: float = 0.0          # of a training frame being degraded; 0 (default): off
    baseline_m: float = 0.055         # D415 datasheet
    subpixel: float = 0.08            # px RMS disparity error, well-tuned (Intel's depth-quality guidance)
    subpixel_max: float = 0.25        # px: "several times" that on dark or shiny surfaces (the same guidance)
    min_focal_px: float = 310.0       # the D415's smallest depth mode, 424x240, under the sim's field of view
    edge_grazing_deg: float = 10.0
    edge_hole_share: float = 0.5
    flying_pixel_share: float = 0.3
    random_hole_share: float = 0.03
    extrinsic_error_mm: float = 0.0   # largest calibration error of an augmented frame's camera: 0, none
    extrinsic_error_deg: float = 0.0

    def __post_init__(self):
        shares = {'probability': self.probability, 'edge_hole_share': self.edge_hole_share,
                  'flying_pixel_share': self.flying_pixel_share, 'random_hole_share': self.random_hole_share,
                  'edge_hole_share + flying_pixel_share': self.edge_hole_share + self.flying_pixel_share}
        bad = [f'{name} must be in [0, 1], got {value}' for name, value in shares.items() if not 0 <= value <= 1]
        if not 0 <= self.subpixel <= self.subpixel_max:
            bad.append(f'need 0 <= subpixel <= subpixel_max, got {self.subpixel} and {self.subpixel_max}')
        if not (self.baseline_m > 0 and self.min_focal_px > 0 and 0 < self.edge_grazing_deg < 90):
            bad.append('baseline_m and min_focal_px must be > 0 and edge_grazing_deg in (0, 90)')
        if not (0 <= self.extrinsic_error_mm <= 100 and 0 <= self.extrinsic_error_deg <= 20):
            bad.append(f'extrinsic errors must be in [0, 100] mm and [0, 20] deg, got '
                       f'{self.extrinsic_error_mm} and {self.extrinsic_error_deg}')
        if bad:
            raise ValueError('depth_augmentation: ' + '; '.join(bad))


def augment_depth(depth_m: np.ndarray, focal_px: float, settings: DepthAugmentation,
                  rng: np.random.Generator) -> np.ndarray:
    """(H, W) float32 metres, 0 = no depth, degraded as the module docstring says (a new array; the
    input is left alone). focal_px: the frame's fx in pixels."""
    z = np.asarray(depth_m, dtype=np.float32)
    valid = np.isfinite(z) & (z > 0)
    z = np.where(valid, z, np.float32(0))
    z, valid = _edges(z, valid, focal_px, settings, rng)
    focal_baseline = np.float32(max(focal_px, settings.min_focal_px) * settings.baseline_m)
    subpixel = np.float32(rng.uniform(settings.subpixel, settings.subpixel_max))
    disparity = np.divide(focal_baseline, z, out=np.zeros_like(z), where=valid)
    disparity += subpixel * rng.standard_normal(z.shape, dtype=np.float32)
    valid &= disparity > 0                 # pushed through zero: no match
    valid &= rng.random(z.shape, dtype=np.float32) >= rng.uniform(0, settings.random_hole_share)
    return np.divide(focal_baseline, disparity, out=np.zeros_like(z), where=valid)


def perturbed_extrinsics(camera_to_world: np.ndarray, settings: DepthAugmentation,
                         rng: np.random.Generator) -> np.ndarray:
    """(4, 4) ``camera_to_world`` moved along a random direction by up to ``extrinsic_error_mm`` and
    turned about a random axis through the optical centre by up to ``extrinsic_error_deg`` (in the
    camera's frame, as a hand-eye calibration errs). Both 0: the pose as it is, and nothing drawn, so
    runs without it draw as before it existed."""
    if not (settings.extrinsic_error_mm or settings.extrinsic_error_deg):
        return np.asarray(camera_to_world, dtype=float)
    direction, axis = (v / np.linalg.norm(v) for v in rng.standard_normal((2, 3)))
    angle = math.radians(rng.uniform(0, settings.extrinsic_error_deg))
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    error = np.eye(4)
    error[:3, :3] = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross   # Rodrigues
    error[:3, 3] = direction * rng.uniform(0, settings.extrinsic_error_mm) * 1e-3
    return np.asarray(camera_to_world, dtype=float) @ error


def _edges(z, valid, focal_px, settings, rng):
    """Pixels beside a depth step: a share lose their depth, a share take a depth between the two sides."""
    steep = 1.0 / (focal_px * math.tan(math.radians(settings.edge_grazing_deg)))     # per pixel, relative
    known = np.where(valid, z, np.nan)
    across = np.full_like(z, np.nan)       # the other side's depth, where a pixel borders a step
    for axis in (0, 1):
        first, second = np.moveaxis(known, axis, 0)[:-1], np.moveaxis(known, axis, 0)[1:]
        with np.errstate(invalid='ignore'):
            step = np.abs(second - first) > steep * np.fmin(first, second)
        ahead, behind = np.moveaxis(across, axis, 0)[:-1], np.moveaxis(across, axis, 0)[1:]
        ahead[...] = np.where(step, second, ahead)
        behind[...] = np.where(step, first, behind)
    edge = ~np.isnan(across)
    pick = rng.random(z.shape, dtype=np.float32)
    lost = edge & (pick < settings.edge_hole_share)
    flying = edge & ~lost & (pick < settings.edge_hole_share + settings.flying_pixel_share)
    blend = rng.random(z.shape, dtype=np.float32)
    z = np.where(flying, z + blend * (np.nan_to_num(across) - z), z)
    return z, valid & ~lost
