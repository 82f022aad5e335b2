"""Cyclone DDS type descriptors for our messages.

Samples never go through cyclonedds-python's own serialiser (about 130 ms for
one 640x480 image, and lists on the way back): our CDR codec makes the bytes.
The IdlStruct built here only tells Cyclone the DDS type name and a faithful
XTypes description, so plain cyclonedds-python peers using the real ROS types
match our endpoints, and ROS peers (which send no type information) match by
name.
"""

from __future__ import annotations

import functools

from cyclonedds.idl import make_idl_struct, types

from ..message import get_message
from ..msg_spec import STRING, FieldSpec

_PRIMITIVES = {
    'bool': bool, 'byte': types.byte, 'char': types.uint8, 'int8': types.int8, 'uint8': types.uint8,
    'int16': types.int16, 'uint16': types.uint16, 'int32': types.int32, 'uint32': types.uint32,
    'int64': types.int64, 'uint64': types.uint64, 'float32': types.float32, 'float64': types.float64,
}


def _field_type(field: FieldSpec):
    if field.base == STRING:
        item = types.bounded_str[field.string_bound] if field.string_bound else str
    elif field.is_primitive:
        item = _PRIMITIVES[field.base]
    else:
        item = idl_struct(field.base)
    if field.array == 'fixed':
        return types.array[item, field.size]
    if field.array == 'sequence':
        return types.sequence[item, field.size] if field.size else types.sequence[item]
    return item


@functools.cache
def idl_struct(type_name: str):
    """The IdlStruct for 'pkg/msg/Type', named 'pkg::msg::dds_::Type_'."""
    cls = get_message(type_name)
    fields = {f.name: _field_type(f) for f in cls._spec.fields} or \
        {'structure_needs_at_least_one_member': types.uint8}
    return make_idl_struct(f'{cls.__name__}_', cls._dds_type_name, fields)
