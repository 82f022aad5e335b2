"""Parse ROS command-line arguments (`--ros-args ... [--]`) and parameter YAML files."""

from __future__ import annotations

import dataclasses
import fnmatch
from pathlib import Path

import yaml


@dataclasses.dataclass
class RosArguments:
    remaps: list = dataclasses.field(default_factory=list)        # (node|None, from, to)
    # (node pattern, {name: value}) in the order given: later entries win
    parameters: list = dataclasses.field(default_factory=list)
    log_level: str | None = None

    def node_name_override(self, node_name: str) -> str | None:
        return self._special('__node', node_name)

    def namespace_override(self, node_name: str) -> str | None:
        return self._special('__ns', node_name)

    def _special(self, key: str, node_name: str) -> str | None:
        found = None
        for rule_node, src, dst in self.remaps:
            if src == key and rule_node in (None, node_name):
                found = dst
        return found

    def parameters_for(self, fully_qualified_name: str) -> dict:
        values = {}
        for pattern, params in self.parameters:
            if _node_matches(pattern, fully_qualified_name):
                values.update(params)
        return values


def _node_matches(pattern: str, fqn: str) -> bool:
    if pattern in ('/**', '**', None):
        return True
    pattern = '/' + pattern.lstrip('/')
    if '*' in pattern:
        return fnmatch.fnmatchcase(fqn, pattern.replace('/**/', '/*'))
    return pattern == fqn or pattern.lstrip('/') == fqn.rsplit('/', 1)[-1] and pattern.count('/') == 1


def _split_rule(text: str, option: str) -> tuple[str | None, str, str]:
    if ':=' not in text:
        raise ValueError(f"{option} expects 'name:=value', got {text!r}")
    lhs, value = text.split(':=', 1)
    node, _, name = lhs.rpartition(':')
    if not name:
        raise ValueError(f"{option} expects 'name:=value', got {text!r}")
    return (node or None), name, value


def _flatten(prefix: str, params: dict, out: dict) -> dict:
    for key, value in params.items():
        name = f'{prefix}.{key}' if prefix else str(key)
        if isinstance(value, dict):
            _flatten(name, value, out)
        else:
            out[name] = value
    return out


def load_params_file(path: str | Path) -> list[tuple[str, dict]]:
    """ROS YAML: `<node or /**>: {ros__parameters: {...}}`, namespaces nested or in the key."""
    path = Path(path)
    try:
        document = yaml.safe_load(path.read_text())
    except OSError as err:
        raise ValueError(f'cannot read parameters file {path}: {err.strerror}') from None
    except yaml.YAMLError as err:
        raise ValueError(f'parameters file {path} is not valid YAML: {err}') from None
    if not isinstance(document, dict):
        raise ValueError(f"parameters file {path} must map node names to 'ros__parameters'")
    entries = []

    def walk(prefix: str, node: dict):
        for key, value in node.items():
            if key == 'ros__parameters':
                if not isinstance(value, dict):
                    raise ValueError(f'{path}: ros__parameters of {prefix!r} must be a mapping')
                entries.append((prefix or '/**', _flatten('', value, {})))
            elif isinstance(value, dict):
                walk(key if key.startswith('/') else f'{prefix}/{key}', value)
            else:
                raise ValueError(f"{path}: expected 'ros__parameters' under {prefix or '/'}, found {key!r}")
    walk('', document)
    return entries


def parse_ros_args(argv: list[str] | None) -> tuple[RosArguments, list[str]]:
    """Split argv into ROS arguments and the rest (like rclpy.utilities.remove_ros_args)."""
    parsed, rest = RosArguments(), []
    args = list(argv or [])
    i, in_ros = 0, False
    while i < len(args):
        arg = args[i]
        if arg == '--ros-args':
            in_ros = True
        elif in_ros and arg == '--':
            in_ros = False
        elif not in_ros:
            rest.append(arg)
        else:
            if arg not in ('-p', '--param', '-r', '--remap', '--params-file', '--log-level',
                           '-e', '--enclave'):
                raise ValueError(f'unknown ROS argument {arg!r}')
            if i + 1 >= len(args):
                raise ValueError(f'{arg} needs a value')
            value = args[i + 1]
            i += 1
            if arg in ('-p', '--param'):
                node, name, text = _split_rule(value, arg)
                parsed.parameters.append((node or '/**', {name: yaml.safe_load(text) if text else ''}))
            elif arg in ('-r', '--remap'):
                parsed.remaps.append(_split_rule(value, arg))
            elif arg == '--params-file':
                parsed.parameters.extend(load_params_file(value))
            elif arg == '--log-level':
                parsed.log_level = value.rpartition(':=')[2] if ':=' in value else value
        i += 1
    return parsed, rest
