"""Messages to and from plain dicts/YAML, as `ros2 topic pub` / `echo` write them."""

from __future__ import annotations

import array

import numpy as np
import yaml

from .message import Message, get_message


def fill_message(msg: Message, values: dict) -> Message:
    """Set fields from a dict, recursing into nested messages; ValueError on unknown keys."""
    if not isinstance(values, dict):
        raise ValueError(f'{msg._type} needs a mapping of field values, got {values!r}')
    fields = {f.name: f for f in msg._spec.fields}
    for key, value in values.items():
        field = fields.get(key)
        if field is None:
            raise ValueError(f"{msg._type} has no field '{key}'; fields: {', '.join(fields)}")
        if field.is_message and field.array:
            value = [fill_message(get_message(field.base)(), v) for v in value]
        elif field.is_message:
            value = fill_message(getattr(msg, key), value)
        setattr(msg, key, value)
    return msg


def message_from_yaml(type_name: str, text: str) -> Message:
    try:
        values = yaml.safe_load(text) if text.strip() else {}
    except yaml.YAMLError as err:
        raise ValueError(f'values are not valid YAML: {err}') from None
    return fill_message(get_message(type_name)(), values or {})


def to_plain(value, max_items: int | None = None):
    """Nested Python builtins for YAML/JSON output; long arrays truncated if asked."""
    if isinstance(value, Message):
        return {name: to_plain(getattr(value, name), max_items) for name in value.__slots__}
    if isinstance(value, (np.ndarray, array.array, bytes, bytearray, list)):
        items = value.tolist() if hasattr(value, 'tolist') else list(value)
        if max_items is not None and len(items) > max_items:
            return [to_plain(v, max_items) for v in items[:max_items]] + [f'... ({len(items)} items)']
        return [to_plain(v, max_items) for v in items]
    return value.item() if isinstance(value, np.generic) else value


def message_to_yaml(msg: Message, max_items: int | None = 32) -> str:
    return yaml.safe_dump(to_plain(msg, max_items), sort_keys=False, allow_unicode=True)
