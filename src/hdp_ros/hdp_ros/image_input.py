"""A camera's colour or depth image, subscribed raw or through image_transport's compressed plugins.

Across a network the raw streams of two D415s (~92 MB/s at 640x480 and 30 Hz) fill most of
a 1 Gbit/s link; ``compressed`` (JPEG colour) and ``compressedDepth`` (16-bit PNG depth) carry
the same frames in a fraction of it (hdp_msgs_py.image_transport). A node chooses with its
``image_transport`` parameter and gets sensor_msgs/Image either way, so nothing behind the
subscription changes. A frame that does not decode (it came off the network) is dropped and
counted; the node warns at most every few seconds.
"""

from __future__ import annotations

from hdp_msgs_py import image_transport, topics
from hdp_msgs_py.msg import CompressedImage, Image

TRANSPORTS = ('raw', 'compressed')
_WARN_EVERY_S = 5.0


class DroppedFrames:
    """Frames that did not decode, by topic, for /diagnostics and a throttled warning."""

    def __init__(self, logger):
        self.counts: dict[str, int] = {}
        self._logger = logger

    def dropped(self, topic: str, why: str) -> None:
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self._logger.warning(f'dropped a frame on {topic} ({self.counts[topic]} so far): {why}',
                             throttle_duration_sec=_WARN_EVERY_S)


def subscribe(node, camera: str, kind: str, transport: str, callback, drops: DroppedFrames):
    """Subscribe ``callback(Image)`` to ``camera``'s ``kind`` ('color' or 'depth') image on
    ``transport`` ('raw' or 'compressed': compressedDepth for depth); returns the subscription."""
    if transport not in TRANSPORTS:
        raise ValueError(f'image transport must be one of {", ".join(TRANSPORTS)}, got {transport!r}')
    raw_topic = topics.color_image(camera) if kind == 'color' else topics.depth_image(camera)
    if transport == 'raw':
        return node.create_subscription(Image, raw_topic, callback, topics.SENSOR_QOS)
    if kind == 'color':
        topic, decode = topics.color_image_compressed(camera), image_transport.decode_compressed
    else:
        topic, decode = topics.depth_image_compressed(camera), image_transport.decode_compressed_depth

    def on_compressed(msg):
        try:
            image = decode(msg)
        except ValueError as err:
            drops.dropped(topic, str(err))
            return
        callback(image)

    return node.create_subscription(CompressedImage, topic, on_compressed, topics.SENSOR_QOS)
