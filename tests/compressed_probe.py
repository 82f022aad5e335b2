"""Subscribe to a running sim_bridge_node's front camera, raw and compressed, and print as JSON
how each compressed frame decoded against the raw frame of the same stamp.

    python compressed_probe.py [--frames N] [--timeout S]
"""

import argparse
import json
import sys
import time

import numpy as np
import rclpy

from hdp_msgs_py import conversions, image_transport, topics
from hdp_msgs_py.msg import CompressedImage, Image
from hdp_ros import ros


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument('--frames', type=int, default=3)
    parser.add_argument('--timeout', type=float, default=60.0)
    args = parser.parse_args(rclpy.utilities.remove_ros_args(sys.argv)[1:])
    ros.init(args=sys.argv)
    node = rclpy.create_node('compressed_probe')
    raw, compressed = {}, {}      # (kind, stamp ns) -> pixels; kind -> [(stamp ns, format, bytes, pixels)]

    def on_raw(kind):
        return lambda msg: raw.__setitem__((kind, conversions.time_to_ns(msg.header.stamp)),
                                           conversions.image_to_numpy(msg).copy())

    def on_compressed(kind, decode):
        def callback(msg):
            image = decode(msg)
            compressed.setdefault(kind, []).append((conversions.time_to_ns(msg.header.stamp), msg.format,
                                                    len(msg.data), image.encoding,
                                                    conversions.image_to_numpy(image)))
        return callback

    camera = 'front'
    node.create_subscription(Image, topics.color_image(camera), on_raw('color'), topics.SENSOR_QOS)
    node.create_subscription(Image, topics.depth_image(camera), on_raw('depth'), topics.SENSOR_QOS)
    node.create_subscription(CompressedImage, topics.color_image_compressed(camera),
                             on_compressed('color', image_transport.decode_compressed), topics.SENSOR_QOS)
    node.create_subscription(CompressedImage, topics.depth_image_compressed(camera),
                             on_compressed('depth', image_transport.decode_compressed_depth), topics.SENSOR_QOS)

    def paired(kind):
        return [(frame, raw[kind, frame[0]]) for frame in compressed.get(kind, []) if (kind, frame[0]) in raw]

    end = time.monotonic() + args.timeout
    while time.monotonic() < end and min(len(paired('color')), len(paired('depth'))) < args.frames:
        rclpy.spin_once(node, timeout_sec=0.05)
    facts = {}
    for kind in ('color', 'depth'):
        pairs = paired(kind)
        errors = [np.abs(frame[4].astype(np.int32) - pixels.astype(np.int32)) for frame, pixels in pairs]
        facts[kind] = {
            'frames': len(pairs),
            'formats': sorted({frame[1] for frame, _ in pairs}),
            'encodings': sorted({frame[3] for frame, _ in pairs}),
            'shapes': sorted({frame[4].shape for frame, _ in pairs}),
            'bytes': [frame[2] for frame, _ in pairs],
            'max_abs_error': max((int(error.max()) for error in errors), default=None),
            'mean_abs_error': max((float(error.mean()) for error in errors), default=None),
        }
    print(json.dumps(facts), flush=True)
    node.destroy_node()
    rclpy.try_shutdown()


if __name__ == '__main__':
    main()
