"""Node parameters with rclpy's Parameter API (name, value, type_)."""

from __future__ import annotations

import enum


class ParameterType(enum.IntEnum):
    NOT_SET = 0
    BOOL = 1
    INTEGER = 2
    DOUBLE = 3
    STRING = 4
    BYTE_ARRAY = 5
    BOOL_ARRAY = 6
    INTEGER_ARRAY = 7
    DOUBLE_ARRAY = 8
    STRING_ARRAY = 9


class InvalidParameterTypeException(TypeError):
    pass


class ParameterNotDeclaredException(KeyError):
    pass


class ParameterAlreadyDeclaredException(ValueError):
    pass


_SCALARS = {bool: ParameterType.BOOL, int: ParameterType.INTEGER, float: ParameterType.DOUBLE,
            str: ParameterType.STRING}
_ARRAYS = {bool: ParameterType.BOOL_ARRAY, int: ParameterType.INTEGER_ARRAY,
           float: ParameterType.DOUBLE_ARRAY, str: ParameterType.STRING_ARRAY}


def type_of(value) -> ParameterType:
    if value is None:
        return ParameterType.NOT_SET
    if type(value) in _SCALARS:
        return _SCALARS[type(value)]
    if isinstance(value, (bytes, bytearray)):
        return ParameterType.BYTE_ARRAY
    if isinstance(value, (list, tuple)) and value:
        kinds = {type(v) for v in value}
        if kinds == {int, float}:
            return ParameterType.DOUBLE_ARRAY
        if len(kinds) == 1 and kinds <= set(_ARRAYS):
            return _ARRAYS[kinds.pop()]
    raise InvalidParameterTypeException(f'unsupported parameter value {value!r}')


def coerce(name: str, value, expected: ParameterType):
    """Check ``value`` against a declared type; ints are accepted for doubles."""
    if expected is ParameterType.NOT_SET or value is None:
        return value
    if expected is ParameterType.DOUBLE and type(value) is int:
        return float(value)
    if expected is ParameterType.DOUBLE_ARRAY and isinstance(value, (list, tuple)) \
            and all(type(v) in (int, float) for v in value):
        return [float(v) for v in value]
    if isinstance(value, (list, tuple)) and not value and expected >= ParameterType.BOOL_ARRAY:
        return []
    actual = type_of(value)
    if actual is not expected:
        raise InvalidParameterTypeException(
            f"parameter '{name}' is {expected.name}, got {actual.name} ({value!r})")
    return list(value) if isinstance(value, tuple) else value


class Parameter:
    Type = ParameterType

    def __init__(self, name: str, type_: ParameterType | None = None, value=None):
        self.name = name
        self.type_ = type_ if type_ is not None else type_of(value)
        self.value = value

    def __repr__(self):
        return f'Parameter({self.name!r}, {self.type_.name}, {self.value!r})'
