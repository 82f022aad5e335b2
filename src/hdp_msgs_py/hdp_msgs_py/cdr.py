"""Classic CDR (XCDR1, little endian) as ROS 2 puts it on DDS.

A payload is the 4-byte encapsulation header ``00 01 00 00`` then the fields
in order, each aligned to its own size (at most 8) counted from the end of the
header. Strings are a uint32 length including the NUL, the UTF-8 bytes, NUL;
sequences a uint32 count then the elements; fixed arrays just the elements.

``compile_codec`` turns a MessageSpec into an encoder and a decoder that work
on whole numeric arrays at once (numpy), so a 640x480 image costs one memory
copy each way instead of a Python loop per byte.
"""

from __future__ import annotations

import struct

import numpy as np

from .msg_spec import PRIMITIVES, STRING, FieldSpec, MessageSpec

HEADER = b'\x00\x01\x00\x00'
_ORIGIN = len(HEADER)
_U32 = struct.Struct('<I')


class CdrError(ValueError):
    """A payload that does not decode: truncated, bad header, bad UTF-8."""


_ZEROS = [bytes(n) for n in range(8)]


class _Writer:
    """Collects the pieces of a payload; joined once, so a large array is copied once."""
    __slots__ = ('parts', 'size')

    def __init__(self):
        self.parts, self.size = [HEADER], _ORIGIN

    def __iadd__(self, data):
        self.parts.append(data)
        self.size += data.nbytes if isinstance(data, memoryview) else len(data)
        return self

    def append(self, byte: int):
        self += _ZEROS[1] if byte == 0 else bytes((byte,))


def _pad(buf: _Writer, size: int) -> None:
    missing = -(buf.size - _ORIGIN) % size
    if missing:
        buf += _ZEROS[missing]


def _align(pos: int, size: int) -> int:
    return pos + (-(pos - _ORIGIN) % size)


def _check_len(field: FieldSpec, n: int) -> None:
    if field.array == 'fixed' and n != field.size:
        raise TypeError(f"field '{field.name}' needs exactly {field.size} elements, got {n}")
    if field.array == 'sequence' and field.size is not None and n > field.size:
        raise TypeError(f"field '{field.name}' holds at most {field.size} elements, got {n}")


def _numeric_bytes(field: FieldSpec, value, dtype: np.dtype) -> tuple[int, object]:
    if dtype.itemsize == 1 and isinstance(value, (bytes, bytearray, memoryview)):
        data = memoryview(value).cast('B')
        return len(data), data
    if isinstance(value, (str, bytes)):
        raise TypeError(f"field '{field.name}' is {field.type_string()}, got {type(value).__name__}")
    try:
        arr = np.ascontiguousarray(value, dtype=dtype)
    except (TypeError, ValueError, OverflowError) as err:
        raise TypeError(f"field '{field.name}' is {field.type_string()}: {err}") from None
    if arr.ndim == 0:
        raise TypeError(f"field '{field.name}' is {field.type_string()}, got a scalar")
    return arr.size, arr.reshape(-1).data.cast('B')


def _encode_field(field: FieldSpec, class_of):
    name = field.name
    if field.base == STRING:
        bound = field.string_bound

        def put_string(buf, text, label=name):
            if not isinstance(text, str):
                raise TypeError(f"field '{label}' is a string, got {type(text).__name__}")
            data = text.encode()
            if bound is not None and len(text) > bound:
                raise TypeError(f"field '{label}' holds at most {bound} characters")
            _pad(buf, 4)
            buf += _U32.pack(len(data) + 1)
            buf += data
            buf.append(0)
        scalar = put_string
    elif field.is_primitive:
        fmt, size = PRIMITIVES[field.base]
        packer = struct.Struct('<' + fmt)
        dtype = np.dtype('<' + fmt)

        def put_primitive(buf, value, label=name):
            _pad(buf, size)
            try:
                buf += packer.pack(value)
            except struct.error as err:
                raise TypeError(f"field '{label}' is {field.base}: {err}") from None
        scalar = put_primitive
    else:
        def put_message(buf, value, label=name):
            cls = class_of(field.base)
            if not isinstance(value, cls):
                raise TypeError(f"field '{label}' is {field.base}, got {type(value).__name__}")
            cls._encode(value, buf)
        scalar = put_message

    if field.array is None:
        return lambda msg, buf: scalar(buf, getattr(msg, name))

    if field.is_primitive:
        def put_array(msg, buf):
            count, data = _numeric_bytes(field, getattr(msg, name), dtype)
            _check_len(field, count)
            if field.array == 'sequence':
                _pad(buf, 4)
                buf += _U32.pack(count)
            if count:
                _pad(buf, size)
                buf += data
        return put_array

    def put_items(msg, buf):
        items = getattr(msg, name)
        if isinstance(items, (str, bytes)) or not hasattr(items, '__len__'):
            raise TypeError(f"field '{name}' is {field.type_string()}, got {type(items).__name__}")
        _check_len(field, len(items))
        if field.array == 'sequence':
            _pad(buf, 4)
            buf += _U32.pack(len(items))
        for item in items:
            scalar(buf, item)
    return put_items


def _take(mv: memoryview, pos: int, n: int) -> int:
    end = pos + n
    if end > len(mv):
        raise CdrError(f'payload truncated: needs {end} bytes, has {len(mv)}')
    return end


def _decode_field(field: FieldSpec, class_of):
    if field.base == STRING:
        def get_string(mv, pos):
            pos = _align(pos, 4)
            _take(mv, pos, 4)
            (n,) = _U32.unpack_from(mv, pos)
            end = _take(mv, pos + 4, n)
            if n == 0 or mv[end - 1] != 0:
                raise CdrError(f"field '{field.name}': string not NUL-terminated")
            try:
                return str(mv[pos + 4:end - 1], 'utf-8'), end
            except UnicodeDecodeError as err:
                raise CdrError(f"field '{field.name}': {err}") from None
        scalar = get_string
    elif field.is_primitive:
        fmt, size = PRIMITIVES[field.base]
        unpacker = struct.Struct('<' + fmt)

        def get_primitive(mv, pos):
            pos = _align(pos, size)
            end = _take(mv, pos, size)
            return unpacker.unpack_from(mv, pos)[0], end
        scalar = get_primitive
    else:
        def get_message(mv, pos):
            return class_of(field.base)._decode(mv, pos)
        scalar = get_message

    if field.array is None:
        return scalar

    def get_count(mv, pos):
        if field.array == 'fixed':
            return field.size, pos
        pos = _align(pos, 4)
        _take(mv, pos, 4)
        count = _U32.unpack_from(mv, pos)[0]
        if field.size is not None and count > field.size:
            raise CdrError(f"field '{field.name}': {count} elements exceed the bound {field.size}")
        return count, pos + 4

    if field.is_primitive:
        typecode = None if field.base == 'bool' else fmt

        def get_array(mv, pos):
            count, pos = get_count(mv, pos)
            if count:
                pos = _align(pos, size)
            end = _take(mv, pos, count * size)
            raw = mv[pos:end]
            if typecode is None:             # bool[]: a list, as in rclpy
                return [bool(b) for b in raw], end
            if field.array == 'fixed':       # rclpy: writable numpy arrays for fixed sizes
                return np.frombuffer(raw, dtype='<' + fmt).copy(), end
            # Sequences: a read-only view of the received payload, no copy. A
            # camera frame is then never copied after Cyclone hands it over.
            return np.frombuffer(raw, dtype='<' + fmt), end
        return get_array

    def get_items(mv, pos):
        count, pos = get_count(mv, pos)
        # every element takes at least one byte: refuse absurd counts early
        _take(mv, pos, count)
        items = []
        for _ in range(count):
            item, pos = scalar(mv, pos)
            items.append(item)
        return items, pos
    return get_items


def compile_codec(spec: MessageSpec, class_of):
    """(encode(msg, buf), decode(mv, pos) -> (msg, pos)) for one message type.

    ``class_of('pkg/msg/Type')`` returns the class of a nested type; it is
    looked up lazily so definitions may refer to each other in any order.
    """
    if not spec.fields:   # an empty struct is one padding octet on the wire
        def encode_empty(msg, buf):
            buf.append(0)

        def decode_empty(mv, pos):
            return class_of(spec.type_name)(), _take(mv, pos, 1)
        return encode_empty, decode_empty

    encoders = [_encode_field(f, class_of) for f in spec.fields]
    decoders = [(f.name, _decode_field(f, class_of)) for f in spec.fields]

    def encode(msg, buf):
        for put in encoders:
            put(msg, buf)

    def decode(mv, pos):
        cls = class_of(spec.type_name)
        msg = cls.__new__(cls)
        for name, get in decoders:
            value, pos = get(mv, pos)
            setattr(msg, name, value)
        return msg, pos
    return encode, decode


def serialize(msg, pad_to: int = 1) -> bytes:
    """Header + CDR body of ``msg``, zero-padded to a multiple of ``pad_to``.

    Raises TypeError naming a bad field.
    """
    buf = _Writer()
    type(msg)._encode(msg, buf)
    if -buf.size % pad_to:
        buf += bytes(-buf.size % pad_to)
    return b''.join(buf.parts)


def deserialize(cls, data):
    """Decode a payload of type ``cls``; raises CdrError on malformed input."""
    mv = memoryview(data).cast('B')
    if len(mv) < 4 or bytes(mv[:2]) != HEADER[:2]:
        raise CdrError(f'not a little-endian CDR payload (header {bytes(mv[:4]).hex()})')
    try:
        msg, _ = cls._decode(mv, _ORIGIN)
    except struct.error as err:
        raise CdrError(f'payload truncated: {err}') from None
    return msg
