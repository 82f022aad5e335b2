"""The D415 sensor model (hdp_sim_bridge.sensor_model) on synthetic planes and edges, and what the
sim does with it: calibration error, latency, deterministic frames, holes the consumers drop."""

import dataclasses
import json
import math
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from hdp_msgs_py import conversions
from hdp_sim_bridge.bridge import SimBridge
from hdp_sim_bridge.cameras import CameraRig, default_cameras
from hdp_sim_bridge.experts import reachable_scene
from hdp_sim_bridge.sensor_model import (D415, IDEAL, D415Profile, SensorSettings, degrade, perturbed_pose,
                                         profile_named, rms_depth_error_m)
from hdp_sim_bridge.world import TIME_STEP, PandaWorld

pytestmark = pytest.mark.unit

GREY = 180            # a light, well-textured surface: no dark-surface noise


def plane(z_mm: int, width: int = 640, height: int = 480, grey: int = GREY):
    return np.full((height, width, 3), grey, np.uint8), np.full((height, width), z_mm, np.uint16)


def only(**parts) -> D415Profile:
    """IDEAL with just ``parts`` of the D415 profile switched on."""
    return dataclasses.replace(IDEAL, name='test', **parts)


@pytest.fixture(scope='module')
def world():
    with PandaWorld() as world:
        yield world


def test_the_ideal_profile_returns_the_render_unchanged_bit_for_bit(world):
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = rng.integers(0, 3000, (48, 64), dtype=np.uint16)
    out_rgb, out_depth = degrade(rgb, depth, 62.0, IDEAL, rng)
    assert out_rgb is rgb and out_depth is depth
    # Through the rig as the bridge, hdp collect and the evaluations use it: the camera's own render.
    cameras = default_cameras(64, 48)
    rig = CameraRig(cameras, SensorSettings())
    for name, camera in cameras.items():
        for ours, theirs in zip(rig.render(world.client, name, 7), camera.render(world.client)):
            assert ours.dtype == theirs.dtype and np.array_equal(ours, theirs)


@pytest.mark.parametrize('width, height', [(1280, 720), (640, 480)])
def test_depth_noise_follows_intels_stereo_formula(width, height):
    focal = (height / 2) / (math.tan(math.radians(34.5)) * 9 / 16)
    for z_mm in (1000, 1500, 2000, 3000):      # from 1 m: noise above the 1 mm step, so rounding adds 1/12 mm^2
        rgb, depth = plane(z_mm, width, height)
        _, noisy = degrade(rgb, depth, focal, only(subpixel=D415.subpixel), np.random.default_rng(z_mm))
        measured = np.std(noisy.astype(float) - z_mm)
        expected = math.hypot(1e3 * rms_depth_error_m(z_mm / 1e3, focal), math.sqrt(1 / 12))   # + 1 mm rounding
        assert measured == pytest.approx(expected, rel=0.03), (z_mm, measured, expected)
    # Intel's figure: about 1.5 mm at 1 m at full resolution (1280x720: f = 931 px here).
    assert 1e3 * rms_depth_error_m(1.0, 931.0) == pytest.approx(1.56, abs=0.01)


def test_small_images_are_as_noisy_as_the_smallest_depth_mode_and_dark_surfaces_noisier():
    rgb, depth = plane(2000, 128, 96)
    profile = only(subpixel=D415.subpixel)
    _, small = degrade(rgb, depth, 124.0, profile, np.random.default_rng(1))
    assert np.std(small - 2000.0) == pytest.approx(1e3 * rms_depth_error_m(2.0, D415.min_focal_px), rel=0.05)
    dark_profile = only(subpixel=D415.subpixel, subpixel_dark=D415.subpixel_dark, dark_luminance=D415.dark_luminance)
    black, depth = plane(2000, grey=0)
    _, dark = degrade(black, depth, 621.0, dark_profile, np.random.default_rng(2))
    light, _ = plane(2000)
    _, lit = degrade(light, depth, 621.0, dark_profile, np.random.default_rng(2))
    assert np.std(dark - 2000.0) == pytest.approx(1e3 * rms_depth_error_m(2.0, 621.0, subpixel=D415.subpixel_dark),
                                                  rel=0.05)
    assert np.std(lit - 2000.0) == pytest.approx(1e3 * rms_depth_error_m(2.0, 621.0), rel=0.05)


def test_depth_is_rounded_to_whole_millimetres():
    rgb, depth = plane(1000)
    # 0.3 mm RMS at 1 m: rounding gives 999, 1000 and 1001 around a mean of 1000 (truncation: 999.5).
    profile = only(subpixel=0.3e-3 * 621.0 * 0.055)
    _, noisy = degrade(rgb, depth, 621.0, profile, np.random.default_rng(3))
    assert noisy.dtype == np.uint16 and set(np.unique(noisy)) == {999, 1000, 1001}
    assert noisy.mean() == pytest.approx(1000.0, abs=0.01)


def box_scene(width=400, height=300, near_mm=1000, far_mm=2000):
    """A near box (rows 100-199, columns 150-249) in front of a far wall."""
    rgb, depth = plane(far_mm, width, height)
    depth[100:200, 150:250] = near_mm
    return rgb, depth


def test_the_second_imagers_shadow_lies_left_of_a_near_edge_and_is_as_wide_as_the_geometry_says():
    rgb, depth = box_scene()
    focal = 310.0
    _, shadowed = degrade(rgb, depth, focal, only(occlusion_shadow=True), np.random.default_rng(0))
    width_px = focal * D415.baseline_m * (1 / 1.0 - 1 / 2.0)          # 8.5 px
    holes = np.argwhere(shadowed == 0)
    assert set(holes[:, 0]) == set(range(100, 200))                   # the box's rows
    # Background pixel u is hidden when u - fB / z_far > 150 - fB / z_near: u > 150 - width_px.
    assert set(holes[:, 1]) == set(range(math.floor(150 - width_px) + 1, 150))     # beside its left edge only
    # With the whole profile: the shadow stays empty; right of the box the wall keeps most of its depth.
    _, d415 = degrade(rgb, depth, focal, D415, np.random.default_rng(0))
    assert np.all(d415[100:200, 142:150] == 0)
    assert np.mean(d415[100:200, 251:259] > 0) > 0.95


def test_depth_discontinuities_lose_depth_or_fly_between_the_surfaces():
    rgb, depth = box_scene()
    profile = only(edge_invalid_share=0.5, flying_pixel_share=0.3)
    _, out = degrade(rgb, depth, 310.0, profile, np.random.default_rng(5))
    edge = np.zeros(depth.shape, bool)
    edge[99:201, [149, 150, 249, 250]] = True
    edge[[99, 100, 199, 200], 149:251] = True
    edge[[99, 99, 200, 200], [149, 250, 149, 250]] = False           # corners touch no step
    changed = out != depth
    assert not changed[~edge].any()                                   # nothing away from the edges
    assert np.mean(out[edge] == 0) == pytest.approx(0.5, abs=0.06)
    flying = (out[edge] > 1000) & (out[edge] < 2000)
    assert np.mean(flying) == pytest.approx(0.3, abs=0.06)
    # A smooth slanted surface is no discontinuity, even at a low resolution.
    slope = np.tile(np.linspace(800, 2600, 128).astype(np.uint16), (96, 1))
    assert np.array_equal(degrade(plane(0, 128, 96)[0], slope, 124.0, profile, np.random.default_rng(6))[1], slope)


def test_random_holes_are_the_share_asked():
    rgb, depth = plane(1500)
    _, out = degrade(rgb, depth, 621.0, only(random_invalid_share=0.01), np.random.default_rng(7))
    assert np.mean(out == 0) == pytest.approx(0.01, abs=0.001)


def test_colour_jitter_is_bounded_and_noise_has_its_std():
    rgb = np.full((240, 320, 3), 128, np.uint8)
    bound = (1 + D415.exposure_jitter) * (1 + D415.white_balance_jitter)
    low = (1 - D415.exposure_jitter) * (1 - D415.white_balance_jitter)
    gains = []
    for seed in range(40):
        out, _ = degrade(rgb, np.zeros((240, 320), np.uint16), 310.0, D415, np.random.default_rng(seed))
        gain = out.reshape(-1, 3).mean(axis=0) / 128
        assert np.all(gain <= bound + 2e-3) and np.all(gain >= low - 2e-3)
        assert np.std(out.astype(float) - out.reshape(-1, 3).mean(axis=0)) == pytest.approx(
            math.hypot(D415.color_noise_std, math.sqrt(1 / 12)), rel=0.05)
        gains.append(gain)
    assert np.ptp(np.array(gains)) > D415.white_balance_jitter         # it does jitter from frame to frame


def test_a_frame_is_the_same_for_the_same_seed_and_frame_whatever_ran_before(world):
    rng_frame = lambda: np.random.default_rng([3, 1, 9])     # noqa: E731
    rgb, depth = box_scene()
    first = degrade(rgb, depth, 310.0, D415, rng_frame())
    assert all(np.array_equal(a, b) for a, b in zip(first, degrade(rgb, depth, 310.0, D415, rng_frame())))
    settings = SensorSettings(D415, extrinsic_error_mm=3.0, extrinsic_error_deg=0.5)
    rig = CameraRig(default_cameras(64, 48), settings)
    rig.start_episode(11)
    later_first = [rig.render(world.client, 'front', frame) for frame in (240, 120)]
    rig.start_episode(12)
    rig.render(world.client, 'side', 120)
    rig.start_episode(11)
    again = [rig.render(world.client, 'front', frame) for frame in (120, 240)]
    for (rgb_a, depth_a), (rgb_b, depth_b) in zip(later_first, again[::-1]):
        assert np.array_equal(rgb_a, rgb_b) and np.array_equal(depth_a, depth_b)
    assert not np.array_equal(again[0][1], again[1][1])               # each frame its own noise


def test_the_calibration_error_has_the_asked_size_and_tf_static_keeps_the_nominal_pose(world):
    pose = default_cameras(64, 48)['front'].camera_to_world
    moved = perturbed_pose(pose, 5.0, 2.0, np.random.default_rng(0))
    error = np.linalg.inv(pose) @ moved
    assert np.linalg.norm(error[:3, 3]) == pytest.approx(0.005, abs=1e-12)
    angle = math.degrees(math.acos(np.clip((np.trace(error[:3, :3]) - 1) / 2, -1, 1)))
    assert angle == pytest.approx(2.0, abs=1e-9)
    assert np.allclose(moved[:3, :3].T @ moved[:3, :3], np.eye(3), atol=1e-12)

    settings = SensorSettings(D415, extrinsic_error_mm=5.0, extrinsic_error_deg=2.0)
    ideal, off = SimBridge(64, 48, world=world), SimBridge(64, 48, world=world, sensor=settings)
    assert off.tf_static() == ideal.tf_static()
    for name, camera in off.cameras.items():
        error = np.linalg.inv(camera.camera_to_world) @ off.rig.rendering[name].camera_to_world
        assert np.linalg.norm(error[:3, 3]) == pytest.approx(0.005, abs=1e-9)
        assert camera.camera_to_world.tolist() == ideal.cameras[name].camera_to_world.tolist()
    drawn = []
    for seed in (1, 2, 1):
        off.rig.start_episode(seed)
        drawn.append(off.rig.rendering['front'].camera_to_world)
    assert not np.allclose(drawn[0], drawn[1]) and np.array_equal(drawn[0], drawn[2])    # one error per episode


def test_a_frame_stamped_at_exposure_is_delivered_the_latency_later(world):
    bridge = SimBridge(32, 24, world=world, sensor=SensorSettings(latency_ms=30.0))
    bridge.expose()
    exposed = bridge.sim_time
    arrivals = []
    while not arrivals:
        bridge.step()
        arrivals = bridge.delivered()
    assert [name for name, _ in arrivals] == ['front', 'side']
    for _, messages in arrivals:
        assert all(conversions.time_to_seconds(m.header.stamp) == pytest.approx(exposed, abs=1e-9) for m in messages)
    assert 0.030 <= bridge.sim_time - exposed < 0.030 + TIME_STEP
    assert bridge.delivered() == []                                   # each frame once


def test_profiles_by_name_and_bad_values_are_refused():
    assert profile_named('d415') == D415 and profile_named('ideal') == IDEAL
    assert profile_named('d415', subpixel=0.1).subpixel == 0.1
    for bad in ({'subpixel': -0.1}, {'edge_invalid_share': 0.8, 'flying_pixel_share': 0.3}, {'colour': 1}):
        with pytest.raises(ValueError):
            profile_named('d415', **bad)
    with pytest.raises(ValueError, match='unknown sensor profile'):
        profile_named('d435')
    with pytest.raises(ValueError):
        SensorSettings(latency_ms=-1.0)


def test_depth_without_a_reading_becomes_no_point():
    """0 depth (a hole) is dropped by every consumer's unprojection, never a point at the camera."""
    from hdp_planner.voxels import scene_points
    intrinsics = conversions.Intrinsics(fx=310.0, fy=310.0, cx=199.5, cy=149.5, width=400, height=300)
    rgb, depth = box_scene()
    _, holed = degrade(rgb, depth, 310.0, D415, np.random.default_rng(8))
    holes = int(np.sum(holed == 0))
    assert holes > 0
    camera_to_world = np.eye(4)
    info = conversions.intrinsics_to_camera_info(intrinsics, 'front_color_optical_frame')
    points = conversions.depth_image_to_points(conversions.numpy_to_image(holed, '16UC1'), info, camera_to_world)
    assert len(points) == holed.size - holes and points[:, 2].min() > 0.5
    xyz, colours = scene_points({'front': (rgb, holed * 0.001)}, {'front': intrinsics}, {'front': camera_to_world})
    assert len(xyz) == len(colours) and not np.any(np.all(xyz == 0, axis=1))


@pytest.mark.sim
def test_in_the_closed_loop_frames_reach_the_planner_and_controller_the_latency_after_their_stamp():
    from hdp_controller.low_level import PlanResult
    from hdp_eval.closed_loop import GraphSettings, InProcessGraph
    from hdp_planner.agent import NextBestPose
    from hdp_planner.grounding import Reading

    class Agent:
        vocabulary = None

        def read(self, instruction):
            return Reading(instruction, False, None, 0.0)

        def predict(self, frames, infos, to_world, instruction, proprio):
            return NextBestPose(np.array([0.5, 0.0, 1.1]), np.array([1.0, 0.0, 0.0, 0.0]), True, 1.0)

    class Stay:
        name = 'stay'

        def plan(self, request, scene=None):
            return PlanResult(np.repeat(np.asarray(request.q, dtype=float)[None], 4, axis=0))

    class Seen(Exception):
        """Six frames have arrived: enough to judge when they were stamped and delivered."""

    settings = GraphSettings(camera_hz=15.0, reach_tolerance=None, sensor=SensorSettings(D415, latency_ms=100.0))
    with PandaWorld() as world:
        bridge = SimBridge(64, 48, world=world, sensor=settings.sensor)
        bridge.reset('reach_target', 4001)
        graph = InProcessGraph(bridge, Agent(), Stay(), needs_points=False, settings=settings)
        arrivals = []

        def on_depth(camera, msg, planner_on_depth=graph.observations.on_depth):
            arrivals.append((camera, conversions.time_to_seconds(msg.header.stamp), graph.now_s))
            planner_on_depth(camera, msg)
            if len(arrivals) == 6:
                raise Seen
        graph.observations.on_depth = on_depth
        controller_frames = []
        graph.controller.on_depth = lambda msg: controller_frames.append(graph.now_s)
        with pytest.raises(Seen):
            graph.run('reach the red target', max_sim_s=5.0)
    exposures = sorted({stamp for _, stamp, _ in arrivals})
    assert exposures == pytest.approx([1 / 15, 2 / 15, 3 / 15], abs=1e-9)          # stamped at exposure
    assert all(0.1 - 1e-9 <= now - stamp < 0.1 + TIME_STEP for _, stamp, now in arrivals)   # stamps: whole ns
    assert controller_frames == [now for camera, _, now in arrivals if camera == 'front'][:len(controller_frames)]


@pytest.mark.sim
def test_collect_records_d415_frames_of_the_same_demonstration_deterministically(tmp_path):
    from hdp_data.episodes import read_episode
    from hdp_msgs_py import topics
    from hdp_sim_bridge.collect import record_episode

    with PandaWorld() as world:
        for out, profile in (('ideal', 'ideal'), ('d415', 'd415'), ('again', 'd415')):
            record_episode(world, 'reach_target', 4, tmp_path / out, 32, 24, sensor_profile=profile)
    ideal, d415, again = (read_episode(tmp_path / out / 'reach_target_000004') for out in ('ideal', 'd415', 'again'))
    assert (ideal.metadata['sensor_profile'], d415.metadata['sensor_profile']) == ('ideal', 'd415')
    assert np.array_equal(ideal.joint_states.position, d415.joint_states.position)    # the same demonstration

    def depths(episode):
        return [conversions.image_to_numpy(msg) for _, msg in episode.messages(topics.depth_image('front'))]
    assert all(np.array_equal(a, b) for a, b in zip(depths(d415), depths(again)))
    assert sum(np.sum(d == 0) for d in depths(d415)) > sum(np.sum(d == 0) for d in depths(ideal))


@pytest.mark.dds
def test_sim_bridge_node_with_the_d415_profile_publishes_depth_with_holes(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                             '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=6.0',
                             '-p', 'sensor_profile:=d415', '-p', 'latency_ms:=50.0'],
                            env=env, text=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    reader = """
import json, sys, time
import numpy as np, rclpy
from hdp_msgs_py import conversions, topics
from hdp_msgs_py.msg import Image
from hdp_ros import ros
ros.init(args=sys.argv)
node = ros.Node('depth_reader')
frames = []
node.create_subscription(Image, topics.depth_image('front'), frames.append, topics.SENSOR_QOS)
end = time.monotonic() + 60
while len(frames) < 2 and time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.1)
print(json.dumps([[m.encoding, float(np.mean(conversions.image_to_numpy(m) == 0)),
                   conversions.time_to_seconds(m.header.stamp)] for m in frames]))
"""
    try:
        result = subprocess.run([sys.executable, '-c', reader], env=env, text=True, capture_output=True, timeout=120)
    finally:
        node.send_signal(signal.SIGINT)
        _, node_err = node.communicate(timeout=20)
    assert result.returncode == 0, result.stderr + node_err
    frames = json.loads(result.stdout.strip().splitlines()[-1])
    assert len(frames) == 2, node_err
    with PandaWorld() as world:
        reachable_scene(world, 'reach_target', 0)
        ideal_holes = np.mean(default_cameras(64, 48)['front'].render(world.client)[1] == 0)
    for encoding, holes, stamp in frames:
        assert encoding == '16UC1' and holes > ideal_holes
        assert round(stamp * 6, 6) == round(stamp * 6)                # stamped at an exposure, 6 Hz
    assert node.returncode == 0, node_err
