"""sensor_msgs/CompressedImage as image_transport's compressed and compressedDepth plugins write it.

The conventions checked here come from image_transport_plugins (rolling, which Jazzy's 4.0
branched from unchanged in these files): compressed_image_transport's compressed_publisher.cpp
(format '<encoding>; jpeg compressed bgr8', colour stored BGR, jpeg_quality 95) and
compressed_subscriber.cpp; compressed_depth_image_transport's codec.cpp and
compression_common.h (ConfigHeader {compressionFormat format; float depthParam[2]} copied
before the PNG, format '16UC1; compressedDepth png', depth_max 10 m, png_level 3).
"""

import json
import os
import signal
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from hdp_msgs_py import cdr, conversions, image_transport, topics
from hdp_msgs_py.message import from_rclpy
from hdp_msgs_py.msg import CompressedImage, Header, Time

pytestmark = pytest.mark.unit

PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
HEADER = Header(stamp=Time(sec=12, nanosec=345), frame_id='front_color_optical_frame')


def scene(height=96, width=128) -> np.ndarray:
    """An rgb8 image as a camera sees a table: smooth shading and a few flat objects."""
    v, u = np.mgrid[0:height, 0:width]
    pixels = np.stack([80 + u * 100 // width, 90 + v * 80 // height, np.full_like(u, 120)], axis=-1)
    pixels[16:48, 24:64] = (200, 40, 30)
    pixels[56:88, 72:120] = (30, 60, 190)
    return pixels.astype(np.uint8)


def depth_scene(height=96, width=128) -> np.ndarray:
    rng = np.random.default_rng(7)
    depth = rng.integers(300, 3500, (height, width)).astype(np.uint16)   # mm, every bit pattern matters
    depth[:8] = 0                                                         # no reading
    return depth


def compressed(format_: str, data: bytes) -> CompressedImage:
    return CompressedImage(header=HEADER, format=format_, data=data)


@pytest.mark.parametrize('encoding', ['rgb8', 'bgr8', 'mono8'])
def test_colour_round_trip_within_jpeg_tolerance(encoding):
    pixels = scene()
    if encoding == 'bgr8':
        pixels = pixels[..., ::-1].copy()
    elif encoding == 'mono8':
        pixels = pixels[..., 1].copy()
    message = image_transport.encode_compressed(conversions.numpy_to_image(pixels, encoding, HEADER))
    assert message.format == f"{encoding}; jpeg compressed {'mono8' if encoding == 'mono8' else 'bgr8'}"
    image = image_transport.decode_compressed(message)
    assert image.encoding == encoding
    assert (image.header.stamp.sec, image.header.stamp.nanosec, image.header.frame_id) == (
        12, 345, 'front_color_optical_frame')
    error = conversions.image_to_numpy(image).astype(float) - pixels
    # JPEG at quality 95: within 2 levels on average, PSNR over 32 dB (colour edges blur most).
    assert np.abs(error).mean() < 2 and 10 * np.log10(255 ** 2 / max(np.mean(error ** 2), 1e-9)) > 32


def test_colour_is_stored_bgr_inside_the_jpeg_as_the_plugin_writes_it():
    red = np.zeros((16, 16, 3), np.uint8)
    red[..., 0] = 255
    message = image_transport.encode_compressed(conversions.numpy_to_image(red, 'rgb8'))
    assert bytes(message.data[:3]) == b'\xff\xd8\xff' and bytes(message.data[-2:]) == b'\xff\xd9'
    stored = cv2.imdecode(np.frombuffer(bytes(message.data), np.uint8), cv2.IMREAD_UNCHANGED)
    assert np.abs(stored[8, 8].astype(int) - [0, 0, 255]).max() <= 2          # B, G, R
    decoded = conversions.image_to_numpy(image_transport.decode_compressed(message))
    assert np.abs(decoded[8, 8].astype(int) - [255, 0, 0]).max() <= 2         # R, G, B again


def test_jpeg_quality_is_a_parameter():
    image = conversions.numpy_to_image(scene(), 'rgb8')
    sizes = [len(image_transport.encode_compressed(image, quality).data) for quality in (20, 95)]
    assert sizes[0] < sizes[1]


def test_depth_round_trip_is_exact_behind_the_plugins_config_header():
    depth = depth_scene()
    message = image_transport.encode_compressed_depth(conversions.numpy_to_image(depth, '16UC1', HEADER))
    assert message.format == '16UC1; compressedDepth png'
    data = bytes(message.data)
    # struct ConfigHeader {compressionFormat format = INV_DEPTH (0); float depthParam[2]} (12
    # bytes, little-endian as it sits in memory), then the PNG; depthParam is unused for 16UC1.
    assert struct.unpack('<iff', data[:12]) == (0, 0.0, 0.0)
    assert data[12:20] == PNG_SIGNATURE
    png = cv2.imdecode(np.frombuffer(data[12:], np.uint8), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and np.array_equal(png, depth)       # a plain 16-bit greyscale PNG
    image = image_transport.decode_compressed_depth(message)
    assert image.encoding == '16UC1' and image.header.frame_id == HEADER.frame_id
    assert np.array_equal(conversions.image_to_numpy(image), depth)


def test_depth_beyond_depth_max_becomes_no_reading_as_the_plugin_filters_it():
    depth = np.array([[0, 999, 10_000, 10_001, 65_535]], np.uint16)
    image = conversions.numpy_to_image(depth, '16UC1')
    decoded = image_transport.decode_compressed_depth(image_transport.encode_compressed_depth(image))
    assert conversions.image_to_numpy(decoded).tolist() == [[0, 999, 10_000, 0, 0]]
    near = image_transport.encode_compressed_depth(image, png_level=9, depth_max_m=1.0)
    assert conversions.image_to_numpy(image_transport.decode_compressed_depth(near)).tolist() == [[0, 999, 0, 0, 0]]


def test_humbles_depth_format_without_the_codec_name_decodes():
    message = image_transport.encode_compressed_depth(conversions.numpy_to_image(depth_scene(), '16UC1'))
    message.format = '16UC1; compressedDepth'
    assert np.array_equal(conversions.image_to_numpy(image_transport.decode_compressed_depth(message)), depth_scene())


def test_a_png_colour_message_decodes():
    pixels = scene()
    _, png = cv2.imencode('.png', pixels[..., ::-1])
    image = image_transport.decode_compressed(compressed('rgb8; png compressed bgr8', png.tobytes()))
    assert np.array_equal(conversions.image_to_numpy(image), pixels)


@pytest.mark.parametrize('kind', ['color', 'depth'])
def test_bytes_on_the_wire_match_rosbags_compressed_image(kind):
    """Our CDR of the message equals rosbags' (ROS2_JAZZY typestore) byte for byte, and a message
    rosbags reads back (as from a bag) decodes to the same pixels."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    if kind == 'color':
        message = image_transport.encode_compressed(conversions.numpy_to_image(scene(), 'rgb8', HEADER))
        decode = image_transport.decode_compressed
    else:
        message = image_transport.encode_compressed_depth(conversions.numpy_to_image(depth_scene(), '16UC1', HEADER))
        decode = image_transport.decode_compressed_depth
    types = typestore.types
    theirs = types['sensor_msgs/msg/CompressedImage'](
        header=types['std_msgs/msg/Header'](stamp=types['builtin_interfaces/msg/Time'](sec=12, nanosec=345),
                                            frame_id=HEADER.frame_id),
        format=message.format, data=np.frombuffer(bytes(message.data), np.uint8))
    wire = bytes(typestore.serialize_cdr(theirs, 'sensor_msgs/msg/CompressedImage'))
    assert cdr.serialize(from_rclpy(message)) == wire
    read_back = typestore.deserialize_cdr(wire, 'sensor_msgs/msg/CompressedImage')
    assert np.array_equal(conversions.image_to_numpy(decode(read_back)), conversions.image_to_numpy(decode(message)))


def _jpeg(pixels=None) -> bytes:
    return cv2.imencode('.jpg', scene()[..., ::-1] if pixels is None else pixels)[1].tobytes()


def _png(pixels) -> bytes:
    return cv2.imencode('.png', pixels)[1].tobytes()


def _with_jpeg_size(width: int, height: int) -> bytes:
    data = bytearray(_jpeg())
    sof = data.index(b'\xff\xc0')
    data[sof + 5:sof + 9] = struct.pack('>HH', height, width)
    return bytes(data)


def _depth_data(png: bytes, compression: int = 0) -> bytes:
    return struct.pack('<iff', compression, 0.0, 0.0) + png


def _with_png_size(png: bytes, width: int, height: int) -> bytes:
    return png[:16] + struct.pack('>II', width, height) + png[24:]


@pytest.mark.parametrize('format_, data, reason', [
    ('jpeg', _jpeg(), 'compressed format must be'),
    ('rgb8; jpeg compressed mono8', _jpeg(), 'rgb8 images are compressed as bgr8'),
    ('rgb16; jpeg compressed bgr16', _jpeg(), 'compressed format must be'),
    ('16UC1; compressedDepth png', _jpeg(), 'compressed format must be'),
    ('rgb8; jpeg compressed bgr8' + 'x' * 10_000, _jpeg(), r"\.\.\.'$"),            # long input, shortened
    ('rgb8; jpeg compressed bgr8', b'', 'not a JPEG'),
    ('rgb8; jpeg compressed bgr8', _png(scene()), 'not a JPEG'),
    ('rgb8; jpeg compressed bgr8', _jpeg()[:400], 'truncated'),
    ('rgb8; jpeg compressed bgr8', b'\xff\xd8\xff\xd9', 'no readable start-of-frame'),
    ('rgb8; jpeg compressed bgr8', _with_jpeg_size(60_000, 60_000), 'image of 60000x60000 pixels refused'),
    ('rgb8; jpeg compressed bgr8', _with_jpeg_size(128, 0), 'image of 128x0 pixels refused'),
    ('rgb8; jpeg compressed bgr8', _jpeg(scene()[..., 0].copy()), 'needs an 8-bit colour JPEG'),
    ('mono8; jpeg compressed mono8', _jpeg(), 'needs an 8-bit greyscale JPEG'),
    ('rgb8; png compressed bgr8', _png(depth_scene()), 'needs an 8-bit colour PNG'),
    ('rgb8; png compressed bgr8', _with_png_size(_png(scene()), 100_000, 100_000), 'pixels refused'),
])
def test_malformed_compressed_messages_are_refused(format_, data, reason):
    with pytest.raises(ValueError, match=reason):
        image_transport.decode_compressed(compressed(format_, data))


@pytest.mark.parametrize('format_, data, reason', [
    ('16UC1; compressedDepth rvl', _depth_data(_png(depth_scene())), 'rvl are not supported'),
    ('32FC1; compressedDepth png', _depth_data(_png(depth_scene())), '32FC1 inverse depth'),
    ('rgb8; jpeg compressed bgr8', _depth_data(_png(depth_scene())), "compressedDepth format must be"),
    ('16UC1', _depth_data(_png(depth_scene())), "compressedDepth format must be"),
    ('16UC1; compressedDepth png', b'\x00' * 12, 'has 12 bytes: not even its 12-byte ConfigHeader'),
    ('16UC1; compressedDepth png', _png(depth_scene()), 'the data starts with a PNG: no ConfigHeader'),
    ('16UC1; compressedDepth png', _depth_data(_png(depth_scene()), compression=-1), 'expected INV_DEPTH'),
    ('16UC1; compressedDepth png', _depth_data(_jpeg()), 'not a PNG'),
    ('16UC1; compressedDepth png', _depth_data(_png(depth_scene())[:300]), 'does not decode as PNG'),
    ('16UC1; compressedDepth png', _depth_data(_png(scene()[..., 0].copy())), 'needs a 16-bit greyscale PNG'),
    ('16UC1; compressedDepth png', _depth_data(_with_png_size(_png(depth_scene()), 65_536, 65_536)),
     'image of 65536x65536 pixels refused'),
])
def test_malformed_compressed_depth_messages_are_refused(format_, data, reason):
    with pytest.raises(ValueError, match=reason):
        image_transport.decode_compressed_depth(compressed(format_, data))


def test_a_receiver_sets_its_own_size_limit():
    message = image_transport.encode_compressed(conversions.numpy_to_image(scene(), 'rgb8'))
    with pytest.raises(ValueError, match='128x96 pixels refused: must be non-empty and at most 10000 pixels'):
        image_transport.decode_compressed(message, max_pixels=10_000)


def test_encoders_refuse_what_their_plugin_refuses():
    colour, depth = conversions.numpy_to_image(scene(), 'rgb8'), conversions.numpy_to_image(depth_scene(), '16UC1')
    with pytest.raises(ValueError, match='16UC1 depth goes through compressedDepth'):
        image_transport.encode_compressed(depth)
    with pytest.raises(ValueError, match='compressedDepth takes 16UC1'):
        image_transport.encode_compressed_depth(colour)
    for quality in (0, 101, 95.0, True):
        with pytest.raises(ValueError, match=r'jpeg_quality must be an integer within \[1, 100\]'):
            image_transport.encode_compressed(colour, quality)
    with pytest.raises(ValueError, match=r'png_level must be an integer within \[0, 9\]'):
        image_transport.encode_compressed_depth(depth, png_level=10)
    with pytest.raises(ValueError, match=r'depth_max_m must be within \[1, 100\]'):
        image_transport.encode_compressed_depth(depth, depth_max_m=0.5)


def test_topics_follow_image_transports_names():
    assert topics.color_image_compressed('front') == '/camera/front/color/image_raw/compressed'
    assert topics.depth_image_compressed('side') == '/camera/side/aligned_depth_to_color/image_raw/compressedDepth'


def test_the_bridges_compression_parameters_are_checked():
    from hdp_ros import ros
    from hdp_sim_bridge.sim_bridge_node import SimBridgeNode
    defaults = {name: default for name, (default, _) in SimBridgeNode.PARAMETERS.items()}
    assert (defaults['publish_compressed'], defaults['jpeg_quality'], defaults['png_level']) == (True, 95, 3)
    SimBridgeNode.check_parameters(defaults)
    for name, value, reason in (('jpeg_quality', 0, r"'jpeg_quality' must be within \[1, 100\], got 0"),
                                ('png_level', 10, r"'png_level' must be within \[0, 9\], got 10")):
        with pytest.raises(ros.StartupError, match=reason):
            SimBridgeNode.check_parameters({**defaults, name: value})


@pytest.mark.dds
def test_the_bridge_publishes_decodable_compressed_frames(ros_domain):
    env = dict(os.environ, ROS_DOMAIN_ID=str(ros_domain))
    node = subprocess.Popen([sys.executable, '-m', 'hdp_sim_bridge.sim_bridge_node', '--ros-args',
                             '-p', 'camera_width:=64', '-p', 'camera_height:=48', '-p', 'camera_rate_hz:=4.0',
                             '-p', 'jpeg_quality:=90'],
                            env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        probe = subprocess.run([sys.executable, str(Path(__file__).with_name('compressed_probe.py')),
                                '--frames', '3'], env=env, text=True, capture_output=True, timeout=120)
    finally:
        node.send_signal(signal.SIGINT)
        _, node_err = node.communicate(timeout=20)
    assert probe.returncode == 0, probe.stderr + node_err
    facts = json.loads(probe.stdout.strip().splitlines()[-1])
    color, depth = facts['color'], facts['depth']
    assert color['frames'] >= 3 and depth['frames'] >= 3, facts
    assert color['formats'] == ['rgb8; jpeg compressed bgr8'] and color['encodings'] == ['rgb8']
    assert depth['formats'] == ['16UC1; compressedDepth png'] and depth['encodings'] == ['16UC1']
    assert color['shapes'] == [[48, 64, 3]] and depth['shapes'] == [[48, 64]]
    assert color['mean_abs_error'] < 4                    # JPEG: close to the raw frame of the same stamp
    assert depth['max_abs_error'] == 0                    # PNG: the raw frame exactly
    assert max(color['bytes']) < 64 * 48 * 3 and max(depth['bytes']) < 12 + 64 * 48 * 2
    assert node.returncode == 0, node_err
