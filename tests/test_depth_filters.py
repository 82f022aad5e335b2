"""librealsense's depth post-processing (hdp_data.depth_filters) on synthetic D415 frames, where the
learned levels switch it on (the planner's Observations, the controller's FilteredDepth), and the
planner's training-time depth augmentation (hdp_planner.depth_augmentation)."""

import dataclasses
import math

import numpy as np
import pytest

from hdp_controller.inputs import FilteredDepth
from hdp_data.depth_filters import PRESETS, REALSENSE, DepthFilter, FilterSettings, preset
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.conversions import Intrinsics
from hdp_planner.dataset import KeyframeDataset, frame_keys
from hdp_planner.depth_augmentation import DepthAugmentation, augment_depth, perturbed_extrinsics
from hdp_planner.planner_logic import Observations
from hdp_planner.train import TrainConfig
from hdp_planner.voxels import scene_points
from hdp_sim_bridge.sensor_model import D415, IDEAL, degrade

pytestmark = pytest.mark.unit

WIDTH, HEIGHT = 640, 480
FOCAL = 620.8                     # the sim's D415 at 640x480
SPATIAL = dataclasses.replace(REALSENSE, temporal=False, hole_filling=False)
# Every depth part of the D415 model: noise, shadow, edge holes, flying pixels, random holes.
D415_DEPTH = {f.name: getattr(D415, f.name) for f in dataclasses.fields(D415)
              if f.name not in ('name', 'color_noise_std', 'exposure_jitter', 'white_balance_jitter')}


def noisy(depth_mm: np.ndarray, seed: int, **parts) -> np.ndarray:
    """``depth_mm`` as the D415 model delivers it with only ``parts`` on (a light grey surface)."""
    profile = dataclasses.replace(IDEAL, name='test', **parts)
    rgb = np.full((*depth_mm.shape, 3), 180, np.uint8)
    return degrade(rgb, depth_mm, FOCAL, profile, np.random.default_rng(seed))[1]


def plane(z_mm: int = 1500) -> np.ndarray:
    return np.full((HEIGHT, WIDTH), z_mm, np.uint16)


def step(near_mm: int = 800, far_mm: int = 1200) -> np.ndarray:
    """A near surface on the left half of the image, a far one on the right."""
    depth = plane(far_mm)
    depth[:, :WIDTH // 2] = near_mm
    return depth


def rms(error) -> float:
    return float(np.sqrt(np.mean(np.square(np.asarray(error, dtype=float)))))


def test_the_spatial_filter_takes_most_of_the_stereo_noise_off_a_plane():
    truth = plane(2000)
    frame = noisy(truth, 0, subpixel=D415.subpixel)
    before = rms(frame[frame > 0] - 2000.0)
    assert before == pytest.approx(1e3 * 2.0 ** 2 * D415.subpixel / (FOCAL * 0.055), rel=0.05)   # 9.4 mm
    out = DepthFilter(SPATIAL).apply(frame, FOCAL)
    assert out.dtype == np.uint16 and out.shape == frame.shape
    after = rms(out[8:-8, 8:-8] - 2000.0)
    assert after < before / 3, (before, after)
    assert abs(float(np.mean(out[8:-8, 8:-8])) - 2000.0) < 1.0         # smoothing, no bias


def test_the_temporal_filter_averages_a_still_scene_over_frames():
    truth = plane(2000)
    temporal = dataclasses.replace(REALSENSE, spatial=False, hole_filling=False)
    depth_filter = DepthFilter(temporal)
    errors = [rms(depth_filter.apply(noisy(truth, seed, subpixel=D415.subpixel), FOCAL, seed) - 2000.0)
              for seed in range(10)]
    # An exponential average with alpha 0.4 keeps alpha / (2 - alpha) = 1/4 of the variance: half the noise.
    assert errors[-1] == pytest.approx(errors[0] / 2, rel=0.15), errors


def test_holes_are_filled_from_the_farther_neighbour():
    truth = step()
    frame = truth.copy()
    frame[100:104, WIDTH // 2] = 0          # far pixels beside the step: far above and below, near on the left
    frame[300:310, 100:110] = 0                                # a hole inside the near surface
    frame[np.random.default_rng(3).random(frame.shape) < 0.01] = 0
    fill_only = dataclasses.replace(REALSENSE, spatial=False, temporal=False)
    out = DepthFilter(fill_only).apply(frame, FOCAL)
    inside = out[1:-1, 1:]                                      # Intel's scan leaves the border rows and column 0
    assert np.count_nonzero(inside == 0) == 0
    assert np.all(out[100:104, WIDTH // 2] == 1200)    # the farther neighbour wins
    assert np.all(out[300:310, 100:110] == 800)
    assert np.array_equal(out[frame > 0], frame[frame > 0])     # valid pixels are left as they were
    nearest = DepthFilter(dataclasses.replace(fill_only, hole_filling_mode='nearest_from_around')).apply(frame, FOCAL)
    assert np.all(nearest[100:104, WIDTH // 2] == 800)
    left = DepthFilter(dataclasses.replace(fill_only, hole_filling_mode='fill_from_left')).apply(frame, FOCAL)
    assert np.all(left[100:104, WIDTH // 2] == 800) and np.all(left[:, 1:] > 0)


def test_the_temporal_filter_keeps_a_pixel_that_was_valid_in_two_of_the_last_four_frames():
    depth_filter = DepthFilter(dataclasses.replace(REALSENSE, spatial=False, hole_filling=False))
    seen = plane(1000)
    lost = seen.copy()
    lost[10, 10] = 0
    once = plane(1000)
    once[20, 20] = 0
    depth_filter.apply(once, FOCAL, 0)
    depth_filter.apply(seen, FOCAL, 1)                       # (10, 10) valid twice, (20, 20) once
    depth_filter.apply(seen, FOCAL, 2)
    both = lost.copy()
    both[20, 20] = 0
    out = depth_filter.apply(both, FOCAL, 3)
    assert out[10, 10] == 1000 and out[20, 20] == 1000
    # Persistence 0 fills nothing; a frame stamped earlier starts the history afresh.
    strict = DepthFilter(dataclasses.replace(REALSENSE, spatial=False, hole_filling=False, persistence=0))
    for stamp in range(3):
        strict.apply(seen, FOCAL, stamp)
    assert strict.apply(lost, FOCAL, 3)[10, 10] == 0
    depth_filter.apply(seen, FOCAL, 4)
    assert depth_filter.apply(lost, FOCAL, 0)[10, 10] == 0     # a simulator reset: no history
    depth_filter.apply(seen, FOCAL, 5)
    depth_filter.reset()
    assert depth_filter.apply(lost, FOCAL, 6)[10, 10] == 0


def test_the_spatial_filter_keeps_edges_sharp():
    truth = step(800, 1200)
    out = DepthFilter(SPATIAL).apply(noisy(truth, 1, subpixel=D415.subpixel), FOCAL)
    near, far = out[:, :WIDTH // 2].astype(float), out[:, WIDTH // 2:].astype(float)
    # Right beside the edge each side keeps its own depth: no ramp from one surface to the other.
    assert np.max(np.abs(near[:, -1] - 800)) < 15 and np.max(np.abs(far[:, 0] - 1200)) < 30
    # A step below delta (20/32 px: 2.4 cm at 1 m at this focal length) is smoothed over, as in librealsense.
    small = DepthFilter(SPATIAL).apply(step(1000, 1010), FOCAL).astype(float)
    assert 1000 < small[240, WIDTH // 2 - 1] < 1010 and 1000 < small[240, WIDTH // 2] < 1010


def test_the_chain_is_deterministic_and_filters_keep_their_own_history():
    frames = [noisy(step(), seed, **D415_DEPTH) for seed in range(3)]
    first, second, other = DepthFilter(), DepthFilter(), DepthFilter()
    outputs = []
    for i, frame in enumerate(frames):
        other.apply(frames[-1 - i], FOCAL, i)                     # another camera's stream in between
        outputs.append((first.apply(frame, FOCAL, i), second.apply(frame, FOCAL, i)))
    assert all(np.array_equal(a, b) for a, b in outputs)
    assert not np.array_equal(outputs[1][0], DepthFilter().apply(frames[1], FOCAL))   # the history counts
    copy = frames[2].copy()
    DepthFilter().apply(frames[2], FOCAL, 9)
    assert np.array_equal(copy, frames[2])                         # the input is never written to


@pytest.mark.parametrize('depth, focal, message', [
    (np.zeros((4, 4), np.float32), FOCAL, 'uint16 depth in mm'),
    (np.zeros((4, 4, 1), np.uint16), FOCAL, 'uint16 depth in mm'),
    ([[1000, 1000], [1000, 1000]], FOCAL, 'got list'),
    (np.zeros((1, 8), np.uint16), FOCAL, 'at least 2 x 2'),
    (np.zeros((4, 4), np.uint16), 0.0, 'focal length'),
    (np.zeros((4, 4), np.uint16), math.nan, 'focal length'),
])
def test_bad_frames_are_refused_saying_what_is_wrong(depth, focal, message):
    with pytest.raises(ValueError, match=message):
        DepthFilter().apply(depth, focal)


def test_bad_settings_and_unknown_presets_are_refused():
    with pytest.raises(ValueError, match='spatial_alpha must be in .0.25, 1., got 2'):
        FilterSettings(spatial_alpha=2)
    with pytest.raises(ValueError, match='persistence must be 0-8, got 9'):
        FilterSettings(persistence=9)
    with pytest.raises(ValueError, match="hole_filling_mode must be one of .*got 'bogus'"):
        FilterSettings(hole_filling_mode='bogus')
    with pytest.raises(ValueError, match='unknown depth filter .median.; choices: none, realsense'):
        preset('median')
    assert preset('none') is None and preset('realsense') == REALSENSE and set(PRESETS) == {'none', 'realsense'}


def _depth_msg(depth: np.ndarray, seconds: float, camera: str = 'front'):
    return conversions.numpy_to_image(depth, '16UC1', conversions._header(f'{camera}_optical_frame',
                                                                          conversions.seconds_to_time(seconds)))


def _info(camera: str = 'front'):
    intrinsics = Intrinsics(FOCAL, FOCAL, WIDTH / 2 - 0.5, HEIGHT / 2 - 0.5, WIDTH, HEIGHT)
    return conversions.intrinsics_to_camera_info(intrinsics, f'{camera}_optical_frame')


def test_the_planner_filters_each_cameras_depth_only_when_asked():
    frame = noisy(plane(2000), 4, subpixel=D415.subpixel)
    plain = Observations(cameras=('front',))
    msg = _depth_msg(frame, 1.0)
    plain.on_depth('front', msg)
    assert plain.depth['front'] is msg                                    # off: the message as it came
    filtered = Observations(cameras=('front',), depth_filter=REALSENSE)
    filtered.on_depth('front', msg)
    assert 'front' not in filtered.depth                                 # no camera_info yet: no focal length
    filtered.on_info('front', _info())
    filtered.on_depth('front', msg)
    out = filtered.depth['front']
    assert out.header.stamp == msg.header.stamp and out.header.frame_id == msg.header.frame_id
    assert np.array_equal(conversions.image_to_numpy(out), DepthFilter().apply(frame, FOCAL))


def test_the_controllers_filtered_depth_follows_the_camera_info():
    frame = noisy(plane(2000), 5, subpixel=D415.subpixel)
    depth = FilteredDepth(REALSENSE)
    assert depth.filtered(_depth_msg(frame, 1.0)) is None
    depth.on_camera_info(_info())
    out = depth.filtered(_depth_msg(frame, 1.0))
    assert np.array_equal(conversions.image_to_numpy(out), DepthFilter().apply(frame, FOCAL))
    with pytest.raises(ValueError, match='uint16 depth in mm'):
        depth.filtered(conversions.numpy_to_image(frame.astype(np.float32) / 1000, '32FC1'))


def test_controller_node_with_depth_filter_realsense_hands_its_logic_filtered_depth_and_drops_what_it_cannot_read():
    """The node's callbacks (ControllerNode._on_camera_info/_on_depth) on a stand-in node: no ROS."""
    from types import SimpleNamespace

    from hdp_controller.controller_node import ControllerNode
    frame = noisy(plane(2000), 6, subpixel=D415.subpixel)
    seen, infos, dropped = [], [], []
    node = SimpleNamespace(_depth_rate=None, _depth_filter=FilteredDepth(REALSENSE),
                           logic=SimpleNamespace(on_depth=seen.append, on_camera_info=infos.append),
                           dropped_frames=SimpleNamespace(dropped=lambda topic, why: dropped.append(why)))
    ControllerNode._on_depth(node, _depth_msg(frame, 1.0))
    assert seen == []                                                   # no camera_info yet: no focal length
    ControllerNode._on_camera_info(node, _info())
    ControllerNode._on_depth(node, _depth_msg(frame, 1.0))
    assert len(infos) == 1 and np.array_equal(conversions.image_to_numpy(seen[0]), DepthFilter().apply(frame, FOCAL))
    ControllerNode._on_depth(node, conversions.numpy_to_image(frame.astype(np.float32) / 1000, '32FC1'))
    assert len(seen) == 1 and 'uint16 depth in mm' in dropped[0]
    node._depth_filter = None                                           # depth_filter none: as it came
    msg = _depth_msg(frame, 2.0)
    ControllerNode._on_depth(node, msg)
    assert seen[-1] is msg


# --- the planner's training augmentation (hdp_planner.depth_augmentation) -------------------------------

def test_depth_augmentation_adds_the_stereo_formulas_noise_edges_and_holes():
    settings = DepthAugmentation(probability=1.0)
    depth = step(800, 1200).astype(np.float32) / 1000
    before = depth.copy()
    out = augment_depth(depth, FOCAL, settings, np.random.default_rng(0))
    assert np.array_equal(depth, before) and out.dtype == np.float32
    far = out[:, WIDTH // 2 + 4:]
    error = far[far > 0] - 1.2
    # z^2 * subpixel / (f * B) for a subpixel drawn in [0.08, 0.25] px.
    low, high = (1e3 * 1.2 ** 2 * s / (FOCAL * 0.055) for s in (settings.subpixel, settings.subpixel_max))
    assert low * 0.9 < 1e3 * rms(error) < high * 1.1
    edge = out[:, WIDTH // 2 - 1:WIDTH // 2 + 1]
    assert 0.2 < np.mean(edge == 0) < 0.8                                  # half the edge lost, and the holes
    assert np.any((edge > 0.85) & (edge < 1.15))                           # flying pixels between the sides
    assert np.mean(far == 0) < settings.random_hole_share + 0.01
    again = augment_depth(depth, FOCAL, settings, np.random.default_rng(0))
    assert np.array_equal(out, again)
    with pytest.raises(ValueError, match='probability must be in .0, 1., got 2'):
        DepthAugmentation(probability=2)
    with pytest.raises(ValueError, match='depth_augmentation must be in|probability must be in'):
        TrainConfig(depth_augmentation=-0.5)


def _episode_with_frames() -> dict:
    """One observation of a near box on a far floor, seen by both cameras from above, as episode_samples keeps it."""
    episode = {'joint_positions': np.zeros((1, 7)), 'gripper_open': np.ones(1, bool),
               'target_xyz': np.array([[0.5, 0.0, 0.9]]), 'target_quat': np.array([[0.0, 0.0, 0.0, 1.0]]),
               'target_open': np.array([True]), 'task': np.array('open_drawer'), 'variation': np.array(0),
               'seed': np.array(3)}
    intrinsics = Intrinsics(124.2, 124.2, 63.5, 47.5, 128, 96)
    above = np.diag([1.0, -1.0, -1.0, 1.0])
    above[:3, 3] = [0.5, 0.0, 0.75 + 1.0]
    depth = np.full((96, 128), 1.0, np.float32)
    depth[30:60, 40:90] = 0.8
    frames, geometry, pose = {}, {}, {}
    for camera in topics.CAMERAS:
        depth_key, colour_key, geometry_key, pose_key = frame_keys(camera)
        episode.update({depth_key: depth[None], colour_key: np.full((1, 96, 128, 3), 90, np.uint8),
                        geometry_key: np.array([124.2, 124.2, 63.5, 47.5, 128, 96]), pose_key: above})
        frames[camera], geometry[camera], pose[camera] = (episode[colour_key][0], depth), intrinsics, above
    xyz, rgb = scene_points(frames, geometry, pose)
    return {**episode, 'xyz': xyz, 'rgb': rgb, 'starts': np.array([0, len(xyz)])}


def test_the_dataset_degrades_depth_only_when_asked_and_draws_nothing_when_off():
    episode = _episode_with_frames()
    plain = KeyframeDataset([episode], proprio='hand')
    rng, twin = np.random.default_rng(7), np.random.default_rng(7)
    item = plain.item(0, rng, augmented=True)
    assert np.array_equal(item.xyz, KeyframeDataset([episode], proprio='hand').item(0, twin, augmented=True).xyz)
    assert rng.random() == twin.random()                   # off: the same draws as before the option existed
    degraded = KeyframeDataset([episode], proprio='hand', depth_augmentation=DepthAugmentation(probability=1.0))
    noisy = degraded.item(0, np.random.default_rng(7), augmented=True)
    assert noisy.xyz.shape[1] == 3 and not np.array_equal(np.sort(noisy.xyz, axis=0), np.sort(item.xyz, axis=0))
    assert np.array_equal(degraded.item(0, np.random.default_rng(7)).xyz, episode['xyz'])   # not augmented: as cached
    no_frames = {k: v for k, v in episode.items() if not k.startswith(('depth_', 'colour_'))}
    with pytest.raises(ValueError, match='has no camera frames: depth augmentation needs'):
        KeyframeDataset([no_frames], 'hand', DepthAugmentation(probability=1.0)).item(0, np.random.default_rng(0),
                                                                                     augmented=True)


def test_extrinsic_augmentation_moves_each_camera_within_its_bounds_and_only_when_asked():
    pose = np.eye(4)
    pose[:3, 3] = [0.3, -0.2, 1.5]
    settings = DepthAugmentation(probability=1.0, extrinsic_error_mm=5.0, extrinsic_error_deg=1.0)
    rng = np.random.default_rng(0)
    moves, turns = [], []
    for _ in range(200):
        moved = perturbed_extrinsics(pose, settings, rng)
        assert np.allclose(moved[:3, :3] @ moved[:3, :3].T, np.eye(3)) and np.linalg.det(moved[:3, :3]) > 0
        moves.append(1e3 * np.linalg.norm(moved[:3, 3] - pose[:3, 3]))
        turns.append(np.degrees(np.arccos(np.clip((np.trace(moved[:3, :3]) - 1) / 2, -1, 1))))
    assert max(moves) <= 5.0 + 1e-9 and max(turns) <= 1.0 + 1e-9
    assert np.mean(moves) == pytest.approx(2.5, abs=0.4) and np.mean(turns) == pytest.approx(0.5, abs=0.08)
    rng, twin = np.random.default_rng(1), np.random.default_rng(1)
    assert np.array_equal(perturbed_extrinsics(pose, DepthAugmentation(probability=1.0), rng), pose)
    assert rng.random() == twin.random()                   # off: nothing drawn
    with pytest.raises(ValueError, match='extrinsic errors must be in'):
        DepthAugmentation(extrinsic_error_mm=-1)
    with pytest.raises(ValueError, match='set depth_augmentation > 0'):
        TrainConfig(extrinsic_augmentation_mm=5.0)
    assert TrainConfig(depth_augmentation=0.5, extrinsic_augmentation_deg=1.0).sensing().extrinsic_error_deg == 1.0


def test_the_dataset_shifts_each_cameras_points_by_its_own_calibration_error():
    """Both cameras see a flat box top at one height; with a translation error each sees it at its own."""
    episode = _episode_with_frames()
    exact = DepthAugmentation(probability=1.0, subpixel=0.0, subpixel_max=0.0, edge_hole_share=0.0,
                              flying_pixel_share=0.0, random_hole_share=0.0)
    assert np.array_equal(KeyframeDataset([episode], 'hand', exact).item(0, np.random.default_rng(3)).xyz,
                          episode['xyz'])
    dataset = KeyframeDataset([episode], 'hand', dataclasses.replace(exact, extrinsic_error_mm=20.0))
    for seed in range(3):
        plain = KeyframeDataset([episode], 'hand', exact)._degraded_points(episode, 0, np.random.default_rng(seed))[0]
        moved = dataset._degraded_points(episode, 0, np.random.default_rng(seed))[0]
        top, moved_top = (np.unique(np.round(xyz[np.abs(xyz[:, 2] - 0.95) < 0.03, 2], 5)) for xyz in (plain, moved))
        assert len(top) == 1 and len(moved_top) == 2                # one height per camera
        assert np.all(np.abs(moved_top - top) <= 0.02 + 1e-6)
