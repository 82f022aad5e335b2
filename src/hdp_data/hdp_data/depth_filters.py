"""The depth post-processing a RealSense user switches on, in numpy: no ROS, no torch.

librealsense's recommended chain (Intel, *Librealsense Post-Processing Filters*,
librealsense/doc/post-processing-filters.md, "Using Filters in application code"):

    depth -> [decimation] -> depth to disparity -> spatial -> temporal -> disparity to depth -> hole filling

- **Spatial edge-preserving filter** (after Gastal and Oliveira's domain transform): per iteration a
  recursive exponential moving average along each row, left to right and back, then along each
  column, down and back up. A pixel is blended with the running value only when it and its
  neighbour differ by less than ``spatial_delta``: a bigger step is an edge, and the average
  restarts there. Pixels without depth are left alone and restart the average too.
- **Temporal filter**: per pixel, an exponential moving average with the last frame's value when
  the two agree within ``temporal_delta``; a pixel without depth takes the last valid value when
  its recent history meets the ``persistence`` rule (e.g. valid in 2 of the last 4 frames).
- **Hole filling**: each pixel without depth takes a value from its neighbours (in Intel's scan:
  up, up-left, left, down-left, down), the farthest (Intel's default), the nearest, or the left one.

Spatial and temporal filtering run in disparity, as Intel runs them on D400 cameras: stereo noise
is even in disparity (the same sub-pixel error at every distance), so one ``delta`` means the same
at 0.5 m and 2 m. Disparity is in librealsense's units, 1/32 px at the frame's focal length:
32 * baseline * fx / z. Decimation is not done here: it changes the frame's size and intrinsics,
and the consumers here resample frames to the size they were trained at themselves.

Run it on frames at the camera's own resolution, before anything resamples them: its averaging
works in pixels and its thresholds in disparity at the frame's focal length, so on a 128x96 frame it
blends across steps of several centimetres and smooths thin parts into what lies behind them.

A ``DepthFilter`` holds the temporal history of one camera: use one per camera (Intel: "maintaining
a filter pipe per camera source is strongly recommended"). It starts afresh by itself when the
frame size or focal length changes or a frame is stamped before the last one (a simulator reset, a
replayed bag), and on ``reset()``.
"""

from __future__ import annotations

import dataclasses

import numpy as np

# librealsense's disparity has 5 fractional bits: 1/32 px (disparity_transform, d2d_convert_factor).
DISPARITY_FRACTIONS = 32
HOLE_FILLING_MODES = ('fill_from_left', 'farthest_from_around', 'nearest_from_around')
# Intel's temporal persistence modes 0-8 as (valid frames needed, of the last frames counted);
# None: never fill. Mode 8 ("always on") fills from any earlier valid value.
PERSISTENCE_RULES = {0: None, 1: (8, 8), 2: (2, 3), 3: (2, 4), 4: (2, 8), 5: (1, 2), 6: (1, 5), 7: (1, 8), 8: (0, 8)}
_BIT_COUNT = np.array([bin(i).count('1') for i in range(256)], dtype=np.uint8)


@dataclasses.dataclass(frozen=True)
class FilterSettings:
    """One post-processing chain. Defaults are librealsense's (post-processing-filters.md and the
    filters' sources, src/proc/spatial-filter.cpp, temporal-filter.cpp, hole-filling-filter.h)."""
    baseline_m: float = 0.055            # the D415's stereo baseline (datasheet): disparity <-> depth
    spatial: bool = True
    spatial_alpha: float = 0.5           # weight of the current pixel, [0.25, 1]; Intel: 0.5
    spatial_delta: float = 20.0          # edge threshold, 1/32 px of disparity, [1, 50]; Intel: 20
    spatial_iterations: int = 2          # "filter magnitude", [1, 5]; Intel: 2
    temporal: bool = True
    temporal_alpha: float = 0.4          # weight of the current frame, [0, 1]; Intel: 0.4
    temporal_delta: float = 20.0         # 1/32 px of disparity, [1, 100]; Intel: 20
    persistence: int = 3                 # PERSISTENCE_RULES key, [0, 8]; Intel: 3, valid in 2 of the last 4
    hole_filling: bool = True
    hole_filling_mode: str = 'farthest_from_around'      # HOLE_FILLING_MODES; Intel: 1, farest from around

    def __post_init__(self):
        problems = []
        if not self.baseline_m > 0:
            problems.append(f'baseline_m must be > 0, got {self.baseline_m}')
        if not 0.25 <= self.spatial_alpha <= 1:
            problems.append(f'spatial_alpha must be in [0.25, 1], got {self.spatial_alpha}')
        if not 1 <= self.spatial_delta <= 50:
            problems.append(f'spatial_delta must be in [1, 50], got {self.spatial_delta}')
        if self.spatial_iterations not in range(1, 6):
            problems.append(f'spatial_iterations must be 1-5, got {self.spatial_iterations}')
        if not 0 <= self.temporal_alpha <= 1:
            problems.append(f'temporal_alpha must be in [0, 1], got {self.temporal_alpha}')
        if not 1 <= self.temporal_delta <= 100:
            problems.append(f'temporal_delta must be in [1, 100], got {self.temporal_delta}')
        if self.persistence not in PERSISTENCE_RULES:
            problems.append(f'persistence must be 0-8, got {self.persistence}')
        if self.hole_filling_mode not in HOLE_FILLING_MODES:
            problems.append(f'hole_filling_mode must be one of {", ".join(HOLE_FILLING_MODES)}, '
                            f'got {self.hole_filling_mode!r}')
        if problems:
            raise ValueError('depth filter: ' + '; '.join(problems))


REALSENSE = FilterSettings()
# What `--depth-filter` and the nodes' parameters name: none, or Intel's chain with its defaults.
PRESETS = {'none': None, 'realsense': REALSENSE}   # not 'off': YAML and ROS read that as false


def preset(name: str) -> FilterSettings | None:
    """The FilterSettings called ``name`` (None for 'off'); ValueError naming the choices."""
    if name not in PRESETS:
        raise ValueError(f'unknown depth filter {name!r}; choices: {", ".join(PRESETS)}')
    return PRESETS[name]


class DepthFilter:
    """One camera's post-processing chain (module docstring), with the temporal filter's history.

    ``apply(depth_mm, focal_px, stamp_ns)``: depth_mm (H, W) uint16 millimetres, 0 = no depth, H and
    W >= 2; focal_px the frame's fx in pixels (CameraInfo k[0]); stamp_ns its stamp (header.stamp in
    ns), or None for frames without one. Returns a new (H, W) uint16 array in mm, 0 where there is
    still no depth. Deterministic: the same frames in the same order from a reset give the same output.
    """

    def __init__(self, settings: FilterSettings = REALSENSE):
        self.settings = settings
        self.reset()

    def reset(self) -> None:
        """Forget the frames seen: the next one is filtered as the first of a stream."""
        self._last = None          # (H, W) float32 disparity, the last valid value per pixel (0: none yet)
        self._history = None       # (H, W) uint8: bit k set = valid and agreeing k + 1 frames ago
        self._stream = None        # (shape, focal_px) the history belongs to
        self._stamp_ns = None      # of the last frame

    def apply(self, depth_mm: np.ndarray, focal_px: float, stamp_ns: int | None = None) -> np.ndarray:
        _check_frame(depth_mm, focal_px)
        settings = self.settings
        scale = np.float32(DISPARITY_FRACTIONS * settings.baseline_m * focal_px * 1000.0)   # disparity * mm
        went_back = stamp_ns is not None and self._stamp_ns is not None and stamp_ns < self._stamp_ns
        if went_back or self._stream != (depth_mm.shape, float(focal_px)):
            self.reset()
            self._stream = (depth_mm.shape, float(focal_px))
        self._stamp_ns = stamp_ns
        disparity = _depth_to_disparity(depth_mm, scale)
        if settings.spatial:
            for _ in range(settings.spatial_iterations):
                _recursive_filter(disparity.T, settings.spatial_alpha, settings.spatial_delta)   # along rows
                _recursive_filter(disparity, settings.spatial_alpha, settings.spatial_delta)     # along columns
        if settings.temporal:
            disparity = self._temporal(disparity)
        depth = _disparity_to_depth(disparity, scale)
        if settings.hole_filling:
            _fill_holes(depth, settings.hole_filling_mode)
        return depth

    def _temporal(self, disparity: np.ndarray) -> np.ndarray:
        """Intel's temporal filter (temp_jw_smooth) on one frame of disparity; updates the history."""
        settings = self.settings
        if self._last is None:
            self._last = np.zeros_like(disparity)
            self._history = np.zeros(disparity.shape, np.uint8)
        last, history = self._last, self._history
        valid, had = disparity > 0, last > 0
        agree = valid & had & (np.abs(disparity - last) < np.float32(settings.temporal_delta))
        out = np.where(agree, np.float32(settings.temporal_alpha) * disparity
                       + np.float32(1 - settings.temporal_alpha) * last, disparity)
        rule = PERSISTENCE_RULES[settings.persistence]
        if rule is not None:
            needed, frames = rule
            recent = _BIT_COUNT[history & np.uint8((1 << frames) - 1)]
            persist = ~valid & had & (recent >= needed)
            out[persist] = last[persist]
        # A valid pixel that disagrees with the last value (or follows none) starts its history afresh.
        shifted = (history << np.uint8(1)).astype(np.uint8)
        self._history = np.where(agree, shifted | np.uint8(1), np.where(valid, np.uint8(1), shifted))
        self._last = np.where(valid, out, last)
        return out


def _check_frame(depth_mm, focal_px) -> None:
    if not isinstance(depth_mm, np.ndarray) or depth_mm.dtype != np.uint16 or depth_mm.ndim != 2:
        what = (f'{depth_mm.dtype} array of shape {depth_mm.shape}' if isinstance(depth_mm, np.ndarray)
                else type(depth_mm).__name__)
        raise ValueError(f'depth filter takes (H, W) uint16 depth in mm (16UC1), got {what}')
    if min(depth_mm.shape) < 2:
        raise ValueError(f'depth filter needs at least 2 x 2 pixels, got {depth_mm.shape[1]} x {depth_mm.shape[0]}')
    if not (isinstance(focal_px, (int, float, np.floating, np.integer)) and np.isfinite(focal_px) and focal_px > 0):
        raise ValueError(f'depth filter needs the focal length in pixels (> 0, finite), got {focal_px!r}')


def _depth_to_disparity(depth_mm: np.ndarray, scale: np.float32) -> np.ndarray:
    """(H, W) float32 disparity in 1/32 px, 0 where there is no depth."""
    depth = depth_mm.astype(np.float32)
    return np.divide(scale, depth, out=np.zeros_like(depth), where=depth_mm > 0)


def _disparity_to_depth(disparity: np.ndarray, scale: np.float32) -> np.ndarray:
    depth = np.divide(scale, disparity, out=np.zeros_like(disparity), where=disparity > 0)
    return np.clip(np.rint(depth), 0, np.iinfo(np.uint16).max).astype(np.uint16)


def _recursive_filter(lines: np.ndarray, alpha: float, delta: float) -> None:
    """Intel's recursive edge-preserving pass (recursive_filter_horizontal_fp), in place along axis 0
    of ``lines`` (N, M): forward, then backward over the forward pass's output. Each step blends a
    pixel with the running value when it and the previous pixel (as this pass found them) are both
    valid and differ by less than ``delta``; otherwise the running value restarts at the pixel."""
    alpha, keep, delta = np.float32(alpha), np.float32(1 - alpha), np.float32(delta)
    for ordered in (lines, lines[::-1]):
        state = ordered[0].copy()
        previous = ordered[0].copy()
        for k in range(1, len(ordered)):
            current = ordered[k].copy()
            smooth = (previous > 0) & (current > 0) & (np.abs(previous - current) < delta)
            state = np.where(smooth, alpha * current + keep * state, current)
            ordered[k] = state
            previous = current


def _fill_holes(depth: np.ndarray, mode: str) -> None:
    """Intel's hole-filling filter, in place on (H, W) depth, scanning row by row from the top left
    so that a filled pixel feeds the holes after it. farthest/nearest_from_around: the largest /
    smallest valid value among up, up-left, left, down-left and down (what Intel's scan reads; the
    frame's border rows and first column stay as they are). Intel's nearest_from_around starts from
    the up neighbour even when it has no depth, and then fills nothing; this takes the documented
    rule, the nearest valid neighbour. fill_from_left: the left neighbour."""
    height, width = depth.shape
    if mode == 'fill_from_left':
        for row in depth:
            holes = np.flatnonzero(row == 0)
            if holes.size:
                filled = np.where(row > 0, np.arange(width), 0)       # column of the last valid value so far
                np.maximum.accumulate(filled, out=filled)
                row[holes] = row[filled[holes]]                      # column 0 holes stay 0 (row[0] == 0)
        return
    pick = max if mode == 'farthest_from_around' else min
    flat = depth.ravel().tolist()               # Python ints: the scan is sequential, lists are fast
    holes = np.flatnonzero(depth[1:-1, 1:] == 0)
    rows, cols = holes // (width - 1) + 1, holes % (width - 1) + 1
    for i in (rows * width + cols).tolist():
        around = [v for v in (flat[i - width], flat[i - width - 1], flat[i - 1], flat[i + width - 1], flat[i + width])
                  if v]
        if around:
            flat[i] = pick(around)
    depth[...] = np.asarray(flat, dtype=np.uint16).reshape(height, width)
