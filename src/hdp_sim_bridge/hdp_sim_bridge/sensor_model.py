"""What a RealSense D415 does to a frame that a renderer draws perfectly: numpy only, no ROS.

``degrade`` takes an ideal render (rgb (H, W, 3) uint8, aligned depth (H, W) uint16 mm, 0 = no
reading), the intrinsics it was drawn with and a ``numpy.random.Generator``, and returns the pair a
D415 would deliver under a ``D415Profile``:

- depth noise from the stereo formula (Intel's depth-quality guidance): a disparity error of
  ``subpixel`` px, so an RMS depth error of z^2 * subpixel / (focal px * baseline), larger on
  dark surfaces, which return little of the projector's pattern;
- no depth (0) where the second imager cannot see what the first does: the occlusion shadow
  beside each near edge, on the side away from the second imager (the image's left: the left
  imager is the depth origin and the right one sits ``baseline_m`` to its right, +x);
- at depth discontinuities, a share of pixels with no depth and a share of "flying pixels"
  between the two surfaces (block matching mixes them); a random share of no depth anywhere;
- depth rounded to the 16UC1 millimetre the driver publishes;
- colour noise per pixel, and exposure and white-balance jitter per frame.

``IDEAL`` turns every part off and returns the render unchanged, bit for bit. Everything random
comes from the generator, so a generator seeded per (episode, camera, frame) gives the same frame
on every re-run. ``perturbed_pose`` moves a camera by a calibration error, for rendering from where
a camera really is while /tf_static says where it was calibrated.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import statistics

import numpy as np

_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)     # Rec. 601 luminance weights


@dataclasses.dataclass(frozen=True)
class D415Profile:
    """One sensor model; the defaults are a D415's (sources in the hdp_sim_bridge README)."""
    name: str = 'd415'
    # -- depth noise: RMS error = z^2 * subpixel / (focal px * baseline) ----------------------------
    baseline_m: float = 0.055         # between the two imagers: D415 datasheet
    subpixel: float = 0.08            # px RMS disparity error when well tuned: Intel's depth-quality guidance
    subpixel_dark: float = 0.25       # px on black surfaces: "several times" the above (Intel's guidance); ours: 3x
    dark_luminance: float = 0.15      # luminance (0-1) below which subpixel ramps up to subpixel_dark; ours
    min_focal_px: float = 310.0       # focal px of the D415's smallest depth mode, 424x240 (datasheet), under
                                      # cameras.py's FOV rule: a smaller image is resampled from that stream
    # -- no depth -----------------------------------------------------------------------------------
    occlusion_shadow: bool = True     # the second imager's shadow: geometry, from baseline_m
    edge_grazing_deg: float = 10.0    # a step between neighbours steeper than a surface this close to grazing
                                      # is a discontinuity (stereo fails on such surfaces anyway); ours
    edge_invalid_share: float = 0.5   # of discontinuity pixels with no depth; ours (Intel gives no figure)
    flying_pixel_share: float = 0.3   # of discontinuity pixels between the two surfaces; ours
    random_invalid_share: float = 0.01    # no depth anywhere; ours, after Intel's fill-rate metric (~all filled)
    # -- colour ---------------------------------------------------------------------------------------
    color_noise_std: float = 2.0      # 8-bit levels per pixel and channel; ours (read + shot noise in good light)
    exposure_jitter: float = 0.03     # brightness gain in 1 +- this per frame (auto-exposure settling); ours
    white_balance_jitter: float = 0.02    # per-channel gain in 1 +- this per frame (auto white balance); ours

    def __post_init__(self):
        numbers = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.type == 'float'}
        negative = [name for name, value in numbers.items() if not value >= 0]
        if negative:
            raise ValueError(f'sensor profile {self.name!r}: {", ".join(negative)} must be >= 0')
        if self.baseline_m <= 0 or not 0 < self.edge_grazing_deg < 90:
            raise ValueError(f'sensor profile {self.name!r}: baseline_m must be > 0 and edge_grazing_deg in (0, 90)')
        shares = (self.random_invalid_share, self.edge_invalid_share + self.flying_pixel_share,
                  self.dark_luminance, self.exposure_jitter, self.white_balance_jitter)
        if any(share > 1 for share in shares):
            raise ValueError(f'sensor profile {self.name!r}: shares, dark_luminance and jitters must be <= 1 '
                             '(edge_invalid_share + flying_pixel_share too)')


D415 = D415Profile()
IDEAL = D415Profile(name='ideal', subpixel=0.0, subpixel_dark=0.0, occlusion_shadow=False, edge_invalid_share=0.0,
                    flying_pixel_share=0.0, random_invalid_share=0.0, color_noise_std=0.0, exposure_jitter=0.0,
                    white_balance_jitter=0.0)
PROFILES = {profile.name: profile for profile in (IDEAL, D415)}


def profile_named(name: str, **overrides) -> D415Profile:
    """The profile called ``name`` ('ideal' or 'd415') with some of its fields replaced; ValueError on
    an unknown name, field or value."""
    if name not in PROFILES:
        raise ValueError(f'unknown sensor profile {name!r}; profiles: {", ".join(PROFILES)}')
    try:
        return dataclasses.replace(PROFILES[name], **overrides)
    except TypeError as err:           # an unknown field
        raise ValueError(str(err)) from None


@dataclasses.dataclass(frozen=True)
class SensorSettings:
    """How the simulated cameras differ from ideal ones: the sensor model, and per setup a
    calibration error (the pose rendered from is off by this much from the one /tf_static gives,
    drawn per episode) and a delivery latency (a frame stamped at exposure arrives this much later)."""
    profile: D415Profile = IDEAL
    extrinsic_error_mm: float = 0.0
    extrinsic_error_deg: float = 0.0
    latency_ms: float = 0.0

    def __post_init__(self):
        if not min(self.extrinsic_error_mm, self.extrinsic_error_deg, self.latency_ms) >= 0:
            raise ValueError('extrinsic_error_mm, extrinsic_error_deg and latency_ms must be >= 0')

    @property
    def is_ideal(self) -> bool:
        return self == SensorSettings()

    def summary(self) -> str:
        """One line for logs and tables: 'd415 sensor, calibration error 5 mm / 1 deg, latency 33 ms'."""
        return (f'{self.profile.name} sensor, calibration error {self.extrinsic_error_mm:g} mm / '
                f'{self.extrinsic_error_deg:g} deg, latency {self.latency_ms:g} ms')


def rms_depth_error_m(z_m, focal_px: float, profile: D415Profile = D415, subpixel: float | None = None):
    """Intel's stereo formula: RMS depth error (m) at depth ``z_m`` for a disparity error of
    ``subpixel`` (default the profile's) at ``focal_px`` (raised to the profile's min_focal_px)."""
    subpixel = profile.subpixel if subpixel is None else subpixel
    return np.asarray(z_m) ** 2 * subpixel / (max(focal_px, profile.min_focal_px) * profile.baseline_m)


def degrade(rgb: np.ndarray, depth_mm: np.ndarray, focal_px: float, profile: D415Profile,
            rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """The frame a D415 under ``profile`` delivers for an ideal render; see the module docstring.

    rgb: (H, W, 3) uint8. depth_mm: (H, W) uint16 millimetres, 0 = no reading. focal_px: the
    render's focal length in pixels (fx; pixels are square). Returns new (rgb, depth_mm) of the same
    shapes and dtypes; with IDEAL the inputs themselves. Parts that are off draw nothing from ``rng``.
    """
    if profile == IDEAL:
        return rgb, depth_mm
    return _degrade_colour(rgb, profile, rng), _degrade_depth(rgb, depth_mm, focal_px, profile, rng)


def _degrade_depth(rgb, depth_mm, focal_px, profile, rng) -> np.ndarray:
    z = depth_mm.astype(np.float32) * np.float32(0.001)
    valid = depth_mm > 0
    if profile.occlusion_shadow:
        valid &= ~occlusion_shadow(z, valid, focal_px * profile.baseline_m)
    if profile.edge_invalid_share or profile.flying_pixel_share:
        z, valid = _discontinuities(z, valid, focal_px, profile, rng)
    if profile.subpixel or profile.subpixel_dark:
        z, valid = _stereo_noise(z, valid, rgb, focal_px, profile, rng)
    if profile.random_invalid_share:
        valid &= rng.random(z.shape, dtype=np.float32) >= profile.random_invalid_share
    millimetres = np.rint(np.where(valid, z * 1000.0, 0.0))      # 16UC1: whole millimetres
    return np.clip(millimetres, 0, np.iinfo(np.uint16).max).astype(np.uint16)


def occlusion_shadow(z: np.ndarray, valid: np.ndarray, focal_baseline_px_m: float) -> np.ndarray:
    """(H, W) bool: valid pixels the second imager, ``baseline`` to the right (+x), cannot see.

    A pixel u at depth z lands at u - f*B/z in the second image; it is hidden when a pixel to its
    right lands left of it there (a nearer surface in between). The shadow beside a near edge is
    then f*B*(1/z_near - 1/z_far) pixels wide, on the edge's left. Pixels with no depth never hide.
    z: (H, W) float metres; focal_baseline_px_m: focal length (px) x baseline (m).
    """
    columns = np.arange(z.shape[1], dtype=np.float32)
    disparity = np.divide(np.float32(focal_baseline_px_m), z, out=np.zeros_like(z), where=valid)
    in_second = columns - disparity
    # The least second-image column of any pixel strictly to the right of each pixel.
    right_min = np.full_like(in_second, np.inf)
    right_min[:, :-1] = np.minimum.accumulate(in_second[:, :0:-1], axis=1)[:, ::-1]
    return valid & (right_min < in_second)


def _discontinuities(z, valid, focal_px, profile, rng):
    """Pixels beside a depth step: a share lose their depth, a share take a depth between the two sides."""
    # A surface at angle a to the line of sight changes depth by (z / f) / tan(a) per pixel.
    steep = 1.0 / (focal_px * math.tan(math.radians(profile.edge_grazing_deg)))
    known = np.where(valid, z, np.nan)
    across = np.full_like(z, np.nan)          # the depth on the other side of a step, per pixel
    for axis in (0, 1):
        first, second = (known[:-1], known[1:]) if axis == 0 else (known[:, :-1], known[:, 1:])
        with np.errstate(invalid='ignore'):
            step = np.abs(second - first) > steep * np.fmin(first, second)     # nan (no depth): never
        ahead, behind = (across[:-1], across[1:]) if axis == 0 else (across[:, :-1], across[:, 1:])
        ahead[...] = np.where(step, second, ahead)
        behind[...] = np.where(step, first, behind)
    rows, cols = np.nonzero(~np.isnan(across))
    pick = rng.random(rows.size)
    lost = pick < profile.edge_invalid_share
    flying = ~lost & (pick < profile.edge_invalid_share + profile.flying_pixel_share)
    z, valid = z.copy(), valid.copy()
    fly_rows, fly_cols = rows[flying], cols[flying]
    here = z[fly_rows, fly_cols]
    z[fly_rows, fly_cols] = here + rng.random(here.size, dtype=np.float32) * (across[fly_rows, fly_cols] - here)
    valid[rows[lost], cols[lost]] = False
    return z, valid


def _stereo_noise(z, valid, rgb, focal_px, profile, rng):
    """Gaussian disparity error of subpixel px (more on dark pixels) -> depth error ~ z^2 * subpixel / (f B)."""
    focal_baseline = np.float32(max(focal_px, profile.min_focal_px) * profile.baseline_m)
    subpixel = np.float32(profile.subpixel)
    if profile.subpixel_dark != profile.subpixel and profile.dark_luminance > 0:
        luminance = rgb.astype(np.float32) @ (_LUMA / np.float32(255.0))
        darkness = np.clip(1.0 - luminance / np.float32(profile.dark_luminance), 0.0, 1.0)
        subpixel = subpixel + np.float32(profile.subpixel_dark - profile.subpixel) * darkness
    disparity = np.divide(focal_baseline, z, out=np.zeros_like(z), where=valid)
    disparity += subpixel * standard_normal(rng, z.shape)
    valid = valid & (disparity > 0)           # a disparity pushed through zero matches nothing
    return np.divide(focal_baseline, disparity, out=np.zeros_like(z), where=valid), valid


def _degrade_colour(rgb, profile, rng) -> np.ndarray:
    """Per frame an exposure gain and a white-balance gain per channel, then noise per pixel."""
    if not (profile.exposure_jitter or profile.white_balance_jitter or profile.color_noise_std):
        return rgb
    gain = (1.0 + profile.exposure_jitter * rng.uniform(-1.0, 1.0)) \
        * (1.0 + profile.white_balance_jitter * rng.uniform(-1.0, 1.0, 3))
    colour = rgb.astype(np.float32) * gain.astype(np.float32)
    if profile.color_noise_std:
        colour += np.float32(profile.color_noise_std) * standard_normal(rng, rgb.shape)
    return np.clip(colour + 0.5, 0, 255).astype(np.uint8)      # + 0.5, then truncation: rounded


@functools.cache
def _normal_quantiles() -> np.ndarray:
    """(65536,) float32: the standard normal's quantiles at (i + 0.5) / 65536 (to +-4.3), scaled to unit variance."""
    normal = statistics.NormalDist()
    quantiles = np.array([normal.inv_cdf((i + 0.5) / 65536) for i in range(65536)])
    return (quantiles / quantiles.std()).astype(np.float32)


def standard_normal(rng: np.random.Generator, shape) -> np.ndarray:
    """float32 standard normal draws of ``shape``, five times faster than rng.standard_normal: random
    16-bit indices into the normal's quantiles (tails cut at 4.3 sigma, unit variance kept)."""
    return _normal_quantiles().take(rng.integers(0, 65536, shape, dtype=np.uint16))


def perturbed_pose(camera_to_world: np.ndarray, error_mm: float, error_deg: float,
                   rng: np.random.Generator) -> np.ndarray:
    """(4, 4) ``camera_to_world`` off by a calibration error: moved ``error_mm`` along a random
    direction and turned ``error_deg`` about a random axis through the optical centre (both drawn
    from ``rng``, in the camera's frame)."""
    direction, axis = (v / np.linalg.norm(v) for v in rng.standard_normal((2, 3)))
    angle = math.radians(error_deg)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    error = np.eye(4)
    error[:3, :3] = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross   # Rodrigues
    error[:3, 3] = direction * error_mm * 1e-3
    return np.asarray(camera_to_world, dtype=float) @ error
