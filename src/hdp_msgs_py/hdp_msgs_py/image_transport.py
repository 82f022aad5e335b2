"""sensor_msgs/CompressedImage as image_transport's plugins write and read it (ROS 2 Jazzy).

Each transport publishes beside the raw topic, at ``<raw topic>/<transport>`` (topics.py):

- ``compressed`` (compressed_image_transport): rgb8, bgr8 or mono8 as a JPEG of the
  image in OpenCV's order (BGR), format ``'rgb8; jpeg compressed bgr8'`` (the raw
  encoding, the codec, the order inside); mono8 is ``'mono8; jpeg compressed mono8'``.
- ``compressedDepth`` (compressed_depth_image_transport): 16UC1 depth as a 16-bit
  greyscale PNG behind a 12-byte ConfigHeader, the plugin's C struct copied as it sits
  in memory: int32 format (INV_DEPTH, 0) and float32 depthParam[2], which only 32FC1
  depth uses (the plugin leaves them unset for 16UC1; we write zeros); format
  ``'16UC1; compressedDepth png'`` (Humble wrote ``'16UC1; compressedDepth'``).

Messages come off the network: decoding checks the format string, the ConfigHeader,
the image's own header (its size, before any pixel memory is allocated) and what
OpenCV returns, and raises ValueError saying what is wrong.
"""

import array
import re
import struct

import cv2
import numpy as np

from .conversions import _data_bytes, image_to_numpy, numpy_to_image
from .msg import CompressedImage

# The plugins' parameter defaults (and OpenCV's).
DEFAULT_JPEG_QUALITY = 95
DEFAULT_PNG_LEVEL = 3
DEFAULT_DEPTH_MAX_M = 10.0        # compressedDepth's depth_max: farther readings become 0
# Decoded images larger than this are refused: a 4K frame (a D415 streams 1920x1080 at most).
MAX_PIXELS = 3840 * 2160

_CONFIG_HEADER = struct.Struct('<iff')   # enum compressionFormat (an int), float depthParam[2]
_INV_DEPTH = 0                           # the plugin's compressionFormat for every depth image
_PNG_SIGNATURE = b'\x89PNG\r\n\x1a\n'
_JPEG_START, _JPEG_END = b'\xff\xd8\xff', b'\xff\xd9'
# '<raw encoding>; <codec> compressed <order>': the order is empty for a mono8 PNG.
_COMPRESSED_FORMAT = re.compile(r'(rgb8|bgr8|mono8); (jpeg|png) compressed ?(bgr8|mono8|)')
_DEPTH_FORMAT = re.compile(r'16UC1; compressedDepth( png)?')


def encode_compressed(image, jpeg_quality: int = DEFAULT_JPEG_QUALITY) -> CompressedImage:
    """The ``compressed`` transport's message of an rgb8, bgr8 or mono8 sensor_msgs/Image (JPEG)."""
    if image.encoding not in ('rgb8', 'bgr8', 'mono8'):
        raise ValueError(f"compressed takes rgb8, bgr8 or mono8 images, got {image.encoding!r} "
                         '(16UC1 depth goes through compressedDepth)')
    _check_range('jpeg_quality', jpeg_quality, 1, 100)
    pixels = image_to_numpy(image)
    if image.encoding == 'rgb8':
        pixels = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
    order = 'mono8' if image.encoding == 'mono8' else 'bgr8'
    jpeg = _encode('.jpg', pixels, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
    return CompressedImage(header=image.header, format=f'{image.encoding}; jpeg compressed {order}',
                           data=jpeg)


def encode_compressed_depth(image, png_level: int = DEFAULT_PNG_LEVEL,
                            depth_max_m: float = DEFAULT_DEPTH_MAX_M) -> CompressedImage:
    """The ``compressedDepth`` transport's message of a 16UC1 (mm) sensor_msgs/Image.

    As the plugin does, readings beyond ``depth_max_m`` become 0 (no reading); the rest
    arrive exactly.
    """
    if image.encoding != '16UC1':
        raise ValueError(f"compressedDepth takes 16UC1 depth images, got {image.encoding!r}")
    _check_range('png_level', png_level, 0, 9)
    if not 1.0 <= depth_max_m <= 100.0:       # the plugin's own range for depth_max
        raise ValueError(f'depth_max_m must be within [1, 100] m, got {depth_max_m}')
    depth = image_to_numpy(image)
    too_far = depth > int(depth_max_m * 1000.0)
    if too_far.any():
        depth = np.where(too_far, 0, depth).astype(np.uint16)
    png = _encode('.png', depth, [cv2.IMWRITE_PNG_COMPRESSION, png_level])
    data = array.array('B', _CONFIG_HEADER.pack(_INV_DEPTH, 0.0, 0.0))
    data.extend(png)
    return CompressedImage(header=image.header, format='16UC1; compressedDepth png', data=data)


def decode_compressed(msg, max_pixels: int = MAX_PIXELS):
    """The sensor_msgs/Image (header, raw encoding) a ``compressed`` message carries, or ValueError.

    JPEG or PNG, of rgb8, bgr8 or mono8 images, as compressed_image_transport writes them.
    """
    match = _COMPRESSED_FORMAT.fullmatch(msg.format)
    if match is None:
        raise ValueError(f"compressed format must be '<rgb8|bgr8|mono8>; <jpeg|png> compressed <bgr8|mono8>', "
                         f'got {_shorten(msg.format)}')
    encoding, codec, order = match.groups()
    if order not in (('mono8', '') if encoding == 'mono8' else ('bgr8',)):
        raise ValueError(f'compressed format {msg.format!r}: {encoding} images are compressed as '
                         f'{"mono8" if encoding == "mono8" else "bgr8"}')
    data = _data_bytes(msg.data)
    width, height = _jpeg_size(data) if codec == 'jpeg' else _png_size(data)
    _check_size(width, height, max_pixels)
    pixels = _decode(data, codec)
    expected_shape = (height, width) if encoding == 'mono8' else (height, width, 3)
    if pixels.dtype != np.uint8 or pixels.shape != expected_shape:
        raise ValueError(f'{msg.format!r} needs an 8-bit {"greyscale" if encoding == "mono8" else "colour"} '
                         f'{codec.upper()}, got {pixels.dtype} of shape {pixels.shape}')
    if encoding == 'rgb8':
        pixels = cv2.cvtColor(pixels, cv2.COLOR_BGR2RGB)
    return numpy_to_image(pixels, encoding, header=msg.header)


def decode_compressed_depth(msg, max_pixels: int = MAX_PIXELS):
    """The 16UC1 sensor_msgs/Image (header, millimetres) a ``compressedDepth`` message carries, or ValueError."""
    if _DEPTH_FORMAT.fullmatch(msg.format) is None:
        raise ValueError(f"compressedDepth format must be '16UC1; compressedDepth png' (32FC1 inverse depth "
                         f'and rvl are not supported), got {_shorten(msg.format)}')
    data = _data_bytes(msg.data)
    if data.size <= _CONFIG_HEADER.size:
        raise ValueError(f'compressedDepth data has {data.size} bytes: not even its {_CONFIG_HEADER.size}-byte '
                         'ConfigHeader and an image')
    compression, _, _ = _CONFIG_HEADER.unpack(data[:_CONFIG_HEADER.size].tobytes())
    if compression != _INV_DEPTH:
        no_header = ' (the data starts with a PNG: no ConfigHeader)' if data[:4].tobytes() == _PNG_SIGNATURE[:4] else ''
        raise ValueError(f'compressedDepth ConfigHeader format is {compression}, expected INV_DEPTH '
                         f'({_INV_DEPTH}){no_header}')
    png = data[_CONFIG_HEADER.size:]
    width, height = _png_size(png)
    _check_size(width, height, max_pixels)
    depth = _decode(png, 'png')
    if depth.dtype != np.uint16 or depth.shape != (height, width):
        raise ValueError(f'compressedDepth needs a 16-bit greyscale PNG, got {depth.dtype} of shape {depth.shape}')
    return numpy_to_image(depth, '16UC1', header=msg.header)


def _check_range(name: str, value, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f'{name} must be an integer within [{low}, {high}], got {value!r}')


def _encode(extension: str, pixels: np.ndarray, params: list) -> array.array:
    ok, encoded = cv2.imencode(extension, pixels, params)
    if not ok:
        raise ValueError(f'OpenCV could not encode a {pixels.dtype} image of shape {pixels.shape} as {extension}')
    return array.array('B', encoded.tobytes())    # rclpy takes array.array('B') without a per-byte check


def _png_size(data: np.ndarray) -> tuple[int, int]:
    """(width, height) from a PNG's IHDR chunk, which the format puts first."""
    if data.size < 24 or data[:8].tobytes() != _PNG_SIGNATURE or data[12:16].tobytes() != b'IHDR':
        raise ValueError('image data is not a PNG (no PNG signature and IHDR chunk)')
    return struct.unpack('>II', data[16:24].tobytes())


def _jpeg_size(data: np.ndarray) -> tuple[int, int]:
    """(width, height) from a JPEG's start-of-frame segment, found by walking the segments before it."""
    raw = data.tobytes()
    if not raw.startswith(_JPEG_START):
        raise ValueError('image data is not a JPEG (no start-of-image marker)')
    if not raw.endswith(_JPEG_END):
        raise ValueError('JPEG is truncated (no end-of-image marker)')
    pos = 2
    while pos + 4 <= len(raw):
        if raw[pos] != 0xFF:
            break
        marker = raw[pos + 1]
        if marker == 0xFF:               # fill byte before a marker
            pos += 1
            continue
        (length,) = struct.unpack_from('>H', raw, pos + 2)
        # SOF0..SOF15 (C4 = DHT, C8 = JPG, CC = DAC are not frames): precision, height, width.
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 9 > len(raw):
                break
            height, width = struct.unpack_from('>HH', raw, pos + 5)
            return width, height
        if marker == 0xDA:               # image data before any frame header
            break
        pos += 2 + length
    raise ValueError('JPEG has no readable start-of-frame segment')


def _check_size(width: int, height: int, max_pixels: int) -> None:
    if width == 0 or height == 0 or width * height > max_pixels:
        raise ValueError(f'image of {width}x{height} pixels refused: must be non-empty and at most '
                         f'{max_pixels} pixels')


def _decode(data: np.ndarray, codec: str) -> np.ndarray:
    # IMREAD_UNCHANGED: the depth and channels as stored, no EXIF rotation (image_transport's 'unchanged').
    pixels = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if pixels is None:
        raise ValueError(f'image data does not decode as {codec.upper()}')
    return pixels


def _shorten(text: str, limit: int = 80) -> str:
    return repr(text if len(text) <= limit else text[:limit] + '...')
