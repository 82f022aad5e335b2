"""Parse ROS 2 ``.msg`` definitions into field specs.

The definitions live in ``interfaces/<package>/msg/<Type>.msg`` beside this
module, in the same syntax as ROS (``type name [default]``, ``TYPE NAME=value``
constants, ``T[]`` / ``T[N]`` / ``T[<=N]`` arrays, ``string<=N``).
"""

from __future__ import annotations

import ast
import dataclasses
import re
from pathlib import Path

INTERFACES_DIR = Path(__file__).parent / 'interfaces'

# ROS primitive type -> (struct format, size in bytes). `byte` and `char` are
# octets on the wire.
PRIMITIVES = {
    'bool': ('?', 1), 'byte': ('B', 1), 'char': ('B', 1),
    'int8': ('b', 1), 'uint8': ('B', 1), 'int16': ('h', 2), 'uint16': ('H', 2),
    'int32': ('i', 4), 'uint32': ('I', 4), 'int64': ('q', 8), 'uint64': ('Q', 8),
    'float32': ('f', 4), 'float64': ('d', 8),
}
STRING = 'string'

_NAME_RE = re.compile(r'^[a-zA-Z][a-zA-Z0-9_]*$')
_TYPE_RE = re.compile(
    r'^(?P<base>[a-zA-Z][a-zA-Z0-9_/]*)(?:<=(?P<strbound>\d+))?'
    r'(?:\[(?P<bounded><=)?(?P<size>\d*)\])?$')


@dataclasses.dataclass(frozen=True)
class FieldSpec:
    """One field: ``base`` is a primitive, 'string' or 'pkg/msg/Type'.

    ``array`` is None (scalar), 'fixed' (``size`` elements), 'sequence'
    (``size`` is None, or the upper bound for ``T[<=N]``).
    """
    name: str
    base: str
    array: str | None = None
    size: int | None = None
    string_bound: int | None = None
    default: object = None

    @property
    def is_primitive(self) -> bool:
        return self.base in PRIMITIVES

    @property
    def is_message(self) -> bool:
        return self.base not in PRIMITIVES and self.base != STRING

    def type_string(self) -> str:
        """The ROS type as rclpy's ``get_fields_and_field_types`` writes it."""
        base = self.base.replace('/msg/', '/')
        if self.string_bound is not None:
            base += f'<={self.string_bound}'
        if self.array == 'fixed':
            return f'{base}[{self.size}]'
        if self.array == 'sequence':
            return f'sequence<{base}, {self.size}>' if self.size else f'sequence<{base}>'
        return base


@dataclasses.dataclass(frozen=True)
class MessageSpec:
    type_name: str                 # 'sensor_msgs/msg/Image'
    fields: tuple[FieldSpec, ...]
    constants: dict

    @property
    def package(self) -> str:
        return self.type_name.split('/')[0]

    @property
    def name(self) -> str:
        return self.type_name.split('/')[-1]


def _resolve(base: str, package: str) -> str:
    if base in PRIMITIVES or base == STRING:
        return base
    parts = base.split('/')
    if len(parts) == 1:
        return f'{package}/msg/{parts[0]}'
    if len(parts) == 2:
        return f'{parts[0]}/msg/{parts[1]}'
    if len(parts) == 3 and parts[1] == 'msg':
        return base
    raise ValueError(f'bad type name {base!r}')


def _literal(text: str, base: str):
    if base == STRING:
        text = text.strip()
        return ast.literal_eval(text) if text[:1] in '\'"' else text
    value = ast.literal_eval(text.strip()) if base != 'bool' else text.strip().lower() in ('true', '1')
    return float(value) if base.startswith('float') else value


def parse(type_name: str, text: str) -> MessageSpec:
    """Parse the text of ``pkg/msg/Type.msg``; raises ValueError naming the line."""
    package = type_name.split('/')[0]
    fields, constants = [], {}
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split('#', 1)[0].strip()   # string defaults may not hold '#'
        if not line:
            continue
        type_text, _, rest = line.partition(' ')
        match = _TYPE_RE.match(type_text)
        if not match:
            raise ValueError(f'{type_name}:{lineno}: bad type {type_text!r}')
        base = _resolve(match['base'], package)
        rest = rest.strip()
        if re.match(r'^\w+\s*=', rest):
            name, _, value = rest.partition('=')
            constants[name.strip()] = _literal(value, base)
            continue
        name, _, default = rest.partition(' ')
        if not _NAME_RE.match(name):
            raise ValueError(f'{type_name}:{lineno}: bad field name {name!r}')
        array, size = None, None
        if match.group(0).endswith(']'):
            array = 'fixed' if match['size'] and not match['bounded'] else 'sequence'
            size = int(match['size']) if match['size'] else None
        strbound = int(match['strbound']) if match['strbound'] else None
        fields.append(FieldSpec(name, base, array, size, strbound,
                                _literal(default, base) if default.strip() and array is None else None))
    return MessageSpec(type_name, tuple(fields), constants)


def load_all(root: Path = INTERFACES_DIR) -> dict[str, MessageSpec]:
    """Every ``<pkg>/msg/<Type>.msg`` under ``root``, keyed by 'pkg/msg/Type'."""
    specs = {}
    for path in sorted(root.glob('*/msg/*.msg')):
        type_name = f'{path.parent.parent.name}/msg/{path.stem}'
        specs[type_name] = parse(type_name, path.read_text())
    return specs
