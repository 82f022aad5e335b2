"""rclpy messages to and from YAML, as `ros2 topic pub` / `echo` write them."""

from __future__ import annotations

import array
import importlib

import numpy as np
from rosidl_parser.definition import AbstractNestedType, NamespacedType
import yaml

from .message import type_name_of


def get_message(type_name: str) -> type:
    """The rclpy class for 'pkg/msg/Type' (or 'pkg/Type'); ValueError if there is none."""
    parts = type_name.strip('/').split('/')
    if len(parts) == 2:
        parts.insert(1, 'msg')
    cls = None
    if len(parts) == 3 and parts[1] == 'msg' and parts[0]:
        try:
            cls = getattr(importlib.import_module(f'{parts[0]}.msg'), parts[2], None)
        except ImportError:
            pass
    if not hasattr(cls, 'get_fields_and_field_types'):
        raise ValueError(f"unknown message type '{type_name}' (expected e.g. std_msgs/msg/String, "
                         'from an installed interface package)')
    return cls


def _class_of(slot: NamespacedType) -> type:
    return getattr(importlib.import_module('.'.join(slot.namespaces)), slot.name)


def fill_message(msg, values: dict):
    """Set fields from a dict, recursing into nested messages; ValueError on a bad key or value."""
    if not isinstance(values, dict):
        raise ValueError(f'{type_name_of(type(msg))} needs a mapping of field values, got {values!r}')
    slots = dict(zip(msg.get_fields_and_field_types(), msg.SLOT_TYPES))
    for key, value in values.items():
        slot = slots.get(key)
        if slot is None:
            raise ValueError(f"{type_name_of(type(msg))} has no field '{key}'; fields: {', '.join(slots)}")
        try:
            setattr(msg, key, _field_value(getattr(msg, key), slot, value))
        except (AssertionError, TypeError, OverflowError) as err:
            # rclpy's setters report a wrong type by assertion (with check_fields)
            raise ValueError(f"{type_name_of(type(msg))}.{key}: {str(err) or 'wrong type'}") from None
    return msg


def _field_value(current, slot, value):
    """`value` as the field expects it: messages built, numbers widened as rclpy requires."""
    if isinstance(slot, NamespacedType):
        return fill_message(_class_of(slot)(check_fields=True), value)
    if isinstance(slot, AbstractNestedType) and isinstance(slot.value_type, NamespacedType):
        if not isinstance(value, list):
            raise ValueError(f'expected a list of {slot.value_type.name} mappings, got {value!r}')
        return [fill_message(_class_of(slot.value_type)(check_fields=True), v) for v in value]
    if isinstance(current, array.array):
        return array.array(current.typecode, value)
    if isinstance(current, np.ndarray):
        return np.array(value, dtype=current.dtype)
    if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def message_from_yaml(type_name: str, text: str):
    """A message of `type_name` from YAML field values ('' or '{}' leaves the defaults)."""
    msg_class = get_message(type_name)
    try:
        values = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as err:
        raise ValueError(f'values are not valid YAML: {err}') from None
    return fill_message(msg_class(check_fields=True), values or {})


def to_plain(value, max_items: int | None = None):
    """Nested Python builtins for YAML/JSON output; long arrays truncated if asked."""
    if hasattr(value, 'get_fields_and_field_types'):
        return {name: to_plain(getattr(value, name), max_items) for name in value.get_fields_and_field_types()}
    if isinstance(value, bytes) and len(value) == 1:    # rclpy's value of a `byte` field
        return value[0]
    if isinstance(value, (np.ndarray, array.array, bytes, bytearray, list)):
        items = value.tolist() if hasattr(value, 'tolist') else list(value)
        if max_items is not None and len(items) > max_items:
            return [to_plain(v, max_items) for v in items[:max_items]] + [f'... ({len(items)} items)']
        return [to_plain(v, max_items) for v in items]
    return value.item() if isinstance(value, np.generic) else value


def message_to_yaml(msg, max_items: int | None = 32) -> str:
    return yaml.safe_dump(to_plain(msg, max_items), sort_keys=False, allow_unicode=True)
