"""Message classes built from the ``.msg`` definitions, shaped like rclpy's.

Field values follow rclpy's Python mapping: numbers and strings for scalars,
``array.array`` for numeric sequences, numpy arrays for numeric fixed-size
arrays, lists for strings, bools and nested messages. One difference, for
speed: a numeric sequence in a *received* message is a read-only numpy view
of the sample (a 640x480 frame is never copied after DDS delivers it); it
supports everything reading code does (len, indexing, iteration,
np.asarray); assign a new sequence to change it. Any sequence or numpy array
is accepted on assignment; types are checked when the message is serialised.
"""

from __future__ import annotations

import array
import functools

import numpy as np

from . import cdr
from .msg_spec import PRIMITIVES, STRING, FieldSpec, MessageSpec, load_all

_REPR_ITEMS = 8


class Message:
    """Base of every generated message class."""
    __slots__ = ()
    _spec: MessageSpec
    _type: str            # 'sensor_msgs/msg/Image'
    _dds_type_name: str   # 'sensor_msgs::msg::dds_::Image_'

    def __init__(self, **kwargs):
        unknown = set(kwargs) - set(self.__slots__)
        if unknown:
            raise TypeError(f'{self._type} has no field(s) {sorted(unknown)}; '
                            f'fields are {list(self.__slots__)}')
        for field in self._spec.fields:
            setattr(self, field.name, kwargs[field.name] if field.name in kwargs else _default(field))

    @classmethod
    def get_fields_and_field_types(cls) -> dict[str, str]:
        return {f.name: f.type_string() for f in cls._spec.fields}

    def __eq__(self, other):
        if type(other) is not type(self):
            return NotImplemented
        return all(_values_equal(getattr(self, n), getattr(other, n)) for n in self.__slots__)

    def __repr__(self):
        parts = ', '.join(f'{n}={_short_repr(getattr(self, n))}' for n in self.__slots__)
        return f"{self._type.replace('/', '.', 1).rsplit('/', 1)[0]}.{type(self).__name__}({parts})"


def _default(field: FieldSpec):
    if field.array is None:
        if field.default is not None:
            return field.default
        if field.base == STRING:
            return ''
        if field.is_primitive:
            return False if field.base == 'bool' else 0.0 if field.base.startswith('float') else 0
        return get_message(field.base)()
    if field.array == 'fixed':
        if field.is_primitive:
            return np.zeros(field.size, dtype='<' + PRIMITIVES[field.base][0])
        item = FieldSpec(field.name, field.base, string_bound=field.string_bound)
        return [_default(item) for _ in range(field.size)]
    if field.is_primitive and field.base != 'bool':
        return array.array(PRIMITIVES[field.base][0])
    return []


def _values_equal(a, b) -> bool:
    if isinstance(a, (np.ndarray, array.array)) or isinstance(b, (np.ndarray, array.array)):
        return np.array_equal(np.asarray(a), np.asarray(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b))
    return a == b


def _short_repr(value) -> str:
    if isinstance(value, (np.ndarray, array.array)):
        value = value.tolist()
    if isinstance(value, (list, bytes, bytearray)) and len(value) > _REPR_ITEMS:
        head = ', '.join(repr(v) for v in list(value[:_REPR_ITEMS]))
        return f'[{head}, ... ({len(value)} items)]'
    return repr(value)


def _canonical(type_name: str) -> str:
    parts = type_name.strip('/').split('/')
    if len(parts) == 2:
        parts.insert(1, 'msg')
    if len(parts) != 3 or parts[1] != 'msg':
        raise ValueError(f"message type must look like 'pkg/msg/Type', got {type_name!r}")
    return '/'.join(parts)


@functools.cache
def _specs() -> dict[str, MessageSpec]:
    return load_all()


def message_types() -> list[str]:
    """All type names this package defines, e.g. 'std_msgs/msg/String'."""
    return sorted(_specs())


@functools.cache
def get_message(type_name: str) -> type[Message]:
    """The class for 'pkg/msg/Type' (or 'pkg/Type'); ValueError if unknown."""
    name = _canonical(type_name)
    if name != type_name:
        return get_message(name)
    spec = _specs().get(name)
    if spec is None:
        raise ValueError(f'unknown message type {type_name!r}; known: {", ".join(message_types())}')
    package, _, short = name.split('/')
    cls = type(short, (Message,), {
        '__slots__': tuple(f.name for f in spec.fields),
        '__module__': f'{package}.msg',
        '__doc__': f'{name} (wire-compatible with ROS 2 Jazzy).',
        '_spec': spec,
        '_type': name,
        '_dds_type_name': f'{package}::msg::dds_::{short}_',
    })
    for const, value in spec.constants.items():
        setattr(cls, const, value)
    cls._encode, cls._decode = (staticmethod(f) for f in cdr.compile_codec(spec, get_message))
    return cls


def type_name_of(msg_type: type) -> str:
    """'pkg/msg/Type' for our classes and for rclpy's generated ones."""
    if isinstance(msg_type, type) and issubclass(msg_type, Message):
        return msg_type._type
    return f"{msg_type.__module__.split('.')[0]}/msg/{msg_type.__name__}"


def from_rclpy(msg) -> Message:
    """Our message equal to an rclpy-generated ``msg`` (same type and fields, nested ones too).

    Recorded episodes are serialised with our codec: rclpy's ``serialize_message`` (Jazzy,
    Fast DDS) returns its size estimate's worth of bytes, so some messages (JointTrajectory)
    come out longer than their CDR, the tail uninitialised memory, which rosbags rejects.
    """
    cls = get_message(type_name_of(type(msg)))
    values = {}
    for field in cls._spec.fields:
        value = getattr(msg, field.name)
        if field.is_message:
            value = [from_rclpy(item) for item in value] if field.array else from_rclpy(value)
        values[field.name] = value
    return cls(**values)

