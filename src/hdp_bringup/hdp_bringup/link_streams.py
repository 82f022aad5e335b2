"""The two ends of `hdp bench link`'s camera measurement, each a process on its own host.

    python -m hdp_bringup.link_streams publish --frames FRAMES.npz --transport raw|compressed ...
    python -m hdp_bringup.link_streams subscribe --transport raw|compressed
    python -m hdp_bringup.link_streams render --frames FRAMES.npz --width W ...

``render`` draws a few frames of both cameras once with the simulator's cameras (PyBullet
cannot render two 640x480 cameras at 30 Hz on a small machine; a process of its own, since
PyBullet prints on stdout). ``publish`` (the robot host) replays them at the camera rate as
sim_bridge_node publishes a frame: for each camera the rgb8 colour and 16UC1 depth Images on
the raw topics, then each compressed topic that has a subscriber gets the frame encoded with
the bridge's codec (hdp_msgs_py.image_transport), so the encoding costs what it costs the
bridge. CameraInfo (a few hundred bytes a frame) is left out. Every message of a tick is
stamped with the wall clock as the tick starts. The publisher waits until the measured topics
have a subscriber, publishes --warmup-s, prints 'measuring', publishes --seconds, and prints
one JSON line: the measured ticks' stamps, the encode times and its own CPU seconds
(/proc/self/stat, as demo.cpu reads it) over the seconds they took, the payload bytes per stream.

``subscribe`` (the workstation) takes the frames as planner_node does (hdp_ros.image_input:
compressed frames decoded to sensor_msgs/Image) and on SIGINT prints one JSON line: per
stream, [stamp, arrival] wall-clock nanoseconds of every frame it got. Network namespaces
share the machine's clock, so arrival minus stamp is a frame's age at the workstation.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from hdp_msgs_py import image_transport, topics
from hdp_msgs_py.conversions import image_to_numpy, numpy_to_image, time_to_ns
from hdp_msgs_py.msg import CompressedImage, Header, Image, Time

from .demo.cpu import parse_stat

KINDS = ('color', 'depth')
STREAMS = tuple(f'{camera}/{kind}' for camera in topics.CAMERAS for kind in KINDS)
# Scenes the replayed frames come from, one frame each, in turn: different content for the codecs.
SCENES = (('reach_target', 1000), ('open_drawer', 1000), ('pick_up_cup', 1000), ('open_box', 1000))
MATCH_TIMEOUT_S = 60.0          # for the workstation's subscriptions to be discovered across the link


def render_frames(path: Path, width: int, height: int, count: int, sensor_profile: str) -> None:
    """``count`` frames of both cameras, rendered by the simulator's cameras through the sensor
    model ``sensor_profile``, one scene each (SCENES, then their next seeds), saved to ``path``."""
    from hdp_sim_bridge.bridge import SimBridge
    from hdp_sim_bridge.sensor_model import SensorSettings, profile_named
    bridge = SimBridge(width, height, sensor=SensorSettings(profile=profile_named(sensor_profile)))
    try:
        frames = {camera: [] for camera in topics.CAMERAS}
        for i in range(count):
            task, seed = SCENES[i % len(SCENES)]
            bridge.reset(task, seed + i // len(SCENES))
            for camera in topics.CAMERAS:
                color, depth, _ = bridge.camera_messages(camera)
                frames[camera].append((image_to_numpy(color).copy(), image_to_numpy(depth).copy()))
        arrays = {}
        for camera, pairs in frames.items():
            arrays[f'{camera}_rgb'] = np.stack([rgb for rgb, _ in pairs])
            arrays[f'{camera}_depth'] = np.stack([depth for _, depth in pairs])
            arrays[f'{camera}_frame_id'] = np.array(bridge.cameras[camera].frame_id)
        np.savez(path, **arrays)
    finally:
        bridge.close()


# -- the robot host -----------------------------------------------------------------------------
class CameraReplay:
    """The frames of FRAMES.npz published as the bridge publishes a camera frame (module doc)."""

    def __init__(self, node, frames_path: Path, jpeg_quality: int, png_level: int):
        frames = np.load(frames_path)
        self.frames = {camera: (frames[f'{camera}_rgb'], frames[f'{camera}_depth']) for camera in topics.CAMERAS}
        self.frame_ids = {camera: str(frames[f'{camera}_frame_id']) for camera in topics.CAMERAS}
        self.jpeg_quality, self.png_level = jpeg_quality, png_level
        self.raw = {camera: (node.create_publisher(Image, topics.color_image(camera), topics.SENSOR_QOS),
                             node.create_publisher(Image, topics.depth_image(camera), topics.SENSOR_QOS))
                    for camera in topics.CAMERAS}
        self.compressed = {camera: (
            node.create_publisher(CompressedImage, topics.color_image_compressed(camera), topics.SENSOR_QOS),
            node.create_publisher(CompressedImage, topics.depth_image_compressed(camera), topics.SENSOR_QOS))
            for camera in topics.CAMERAS}
        self.reset_counts()

    def publishers(self, transport: str) -> list:
        """The publishers whose topics the workstation subscribes to on ``transport``."""
        chosen = self.raw if transport == 'raw' else self.compressed
        return [publisher for pair in chosen.values() for publisher in pair]

    def publish(self, tick: int, stamp_ns: int) -> None:
        """Frame ``tick`` (the rendered ones in turn) of both cameras, stamped ``stamp_ns``."""
        stamp = Time(sec=stamp_ns // 1_000_000_000, nanosec=stamp_ns % 1_000_000_000)
        for camera, (rgb, depth) in self.frames.items():
            header = Header(stamp=stamp, frame_id=self.frame_ids[camera])
            color = numpy_to_image(rgb[tick % len(rgb)], 'rgb8', header)
            depth_image = numpy_to_image(depth[tick % len(depth)], '16UC1', header)
            for publisher, message, kind in zip(self.raw[camera], (color, depth_image), KINDS):
                publisher.publish(message)
                if publisher.get_subscription_count():      # raw payload counts where raw is taken
                    self.payload_bytes[f'{camera}/{kind}'] += len(message.data)
            self._publish_compressed(camera, color, depth_image)

    def _publish_compressed(self, camera: str, color, depth) -> None:
        encoders = ((lambda: image_transport.encode_compressed(color, self.jpeg_quality), 'jpeg'),
                    (lambda: image_transport.encode_compressed_depth(depth, self.png_level), 'png'))
        for publisher, (encode, codec), kind in zip(self.compressed[camera], encoders, KINDS):
            # As the bridge (and image_transport): a transport is encoded only while it has a subscriber.
            if publisher.get_subscription_count():
                start = time.perf_counter()
                message = encode()
                self.encode_ms[codec].append(1e3 * (time.perf_counter() - start))
                publisher.publish(message)
                self.payload_bytes[f'{camera}/{kind}'] += len(message.data)

    def reset_counts(self) -> None:
        """Start counting encode times and payload afresh (after the warm-up)."""
        self.encode_ms = {'jpeg': [], 'png': []}
        self.payload_bytes = dict.fromkeys(STREAMS, 0)


def run_ticks(publish, rate_hz: float, seconds: float) -> list[int]:
    """Call ``publish(tick, stamp_ns)`` on a fixed schedule of ``rate_hz`` for ``seconds``; the
    stamps. A tick that comes late is published late; one a whole period behind is dropped, as a
    camera driver that cannot keep up drops frames, so the rate published says what the host managed."""
    period, total = 1.0 / rate_hz, round(seconds * rate_hz)
    start, tick, stamps = time.monotonic(), 0, []
    while tick < total:
        time.sleep(max(0.0, start + tick * period - time.monotonic()))
        stamps.append(time.time_ns())
        publish(len(stamps) - 1, stamps[-1])
        tick = max(tick + 1, math.floor((time.monotonic() - start) / period))
    return stamps


def cpu_seconds_self() -> float:
    """This process's CPU seconds so far (all its threads: user + system)."""
    _, ticks = parse_stat(Path('/proc/self/stat').read_text())
    return ticks / os.sysconf('SC_CLK_TCK')


def publish_main(args) -> int:
    import rclpy

    from hdp_ros import ros
    ros.init(args=[])
    node = rclpy.create_node('link_bench_cameras')
    replay = CameraReplay(node, args.frames, args.jpeg_quality, args.png_level)
    waiting = replay.publishers(args.transport)
    deadline = time.monotonic() + MATCH_TIMEOUT_S
    while not all(publisher.get_subscription_count() for publisher in waiting):
        if time.monotonic() > deadline:
            print(f'no subscriber on the {args.transport} topics within {MATCH_TIMEOUT_S:.0f} s', file=sys.stderr)
            return 1
        time.sleep(0.1)
    run_ticks(replay.publish, args.rate_hz, args.warmup_s)
    replay.reset_counts()
    print('measuring', flush=True)
    cpu_before, started = cpu_seconds_self(), time.monotonic()
    stamps = run_ticks(replay.publish, args.rate_hz, args.seconds)
    result = {'stamps_ns': stamps, 'rate_hz': args.rate_hz, 'window_s': args.seconds,
              'elapsed_s': time.monotonic() - started, 'cpu_s': cpu_seconds_self() - cpu_before,
              'encode_ms': replay.encode_ms, 'payload_bytes': replay.payload_bytes}
    print(json.dumps(result), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


# -- the workstation ---------------------------------------------------------------------------
def subscribe_main(args) -> int:
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from hdp_ros import image_input, ros
    ros.init(args=[])
    node = rclpy.create_node('link_bench_workstation')
    drops = image_input.DroppedFrames(node.get_logger())
    arrivals = {stream: [] for stream in STREAMS}

    def recorder(stream):
        def on_image(image):
            arrivals[stream].append((time_to_ns(image.header.stamp), time.time_ns()))
        return on_image
    for stream in STREAMS:
        camera, kind = stream.split('/')
        image_input.subscribe(node, camera, kind, args.transport, recorder(stream), drops)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass                       # SIGINT: the bench is done publishing
    print(json.dumps({'arrivals': arrivals, 'undecodable': sum(drops.counts.values())}), flush=True)
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description='one end of hdp bench link (internal; see the module doc)')
    sides = parser.add_subparsers(dest='side', required=True)
    publish = sides.add_parser('publish')
    publish.add_argument('--frames', type=Path, required=True)
    publish.add_argument('--transport', choices=('raw', 'compressed'), required=True)
    publish.add_argument('--rate-hz', type=float, required=True)
    publish.add_argument('--warmup-s', type=float, required=True)
    publish.add_argument('--seconds', type=float, required=True)
    publish.add_argument('--jpeg-quality', type=int, required=True)
    publish.add_argument('--png-level', type=int, required=True)
    subscribe = sides.add_parser('subscribe')
    subscribe.add_argument('--transport', choices=('raw', 'compressed'), required=True)
    render = sides.add_parser('render')
    render.add_argument('--frames', type=Path, required=True)
    render.add_argument('--width', type=int, required=True)
    render.add_argument('--height', type=int, required=True)
    render.add_argument('--count', type=int, required=True)
    render.add_argument('--sensor-profile', required=True)
    args = parser.parse_args(argv)
    if args.side == 'render':
        render_frames(args.frames, args.width, args.height, args.count, args.sensor_profile)
        return 0
    return publish_main(args) if args.side == 'publish' else subscribe_main(args)


if __name__ == '__main__':
    sys.exit(main())
