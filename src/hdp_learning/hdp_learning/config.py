"""YAML configs made of sections, each one dataclass: the one mechanism behind every ``--config``.

Every trainer reads a file with a ``model:`` and a ``train:`` section
(``hdp train low-level``: RKDConfig and TrainConfig; ``hdp train high-level``:
ModelConfig and TrainConfig; ``hdp train flat``: the policy's config and
FlatTrainConfig). Precedence, lowest first: the dataclass's
defaults, ``defaults`` given by the caller (what only code knows, such as the
agent's vocabulary), the file, then ``overrides`` (command-line flags; a
None value is a flag not given). An unknown section or key, a value of the
wrong type, or a value the dataclass refuses is one ``ConfigError`` line
that names the file, the section and what is known. YAML lists become tuples
for the fields annotated ``tuple``. No torch here: the CLI imports it.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import yaml


class ConfigError(ValueError):
    """A config file, section or value refused; the message is one line."""


# Annotation (as written, or its __name__) -> (accepted types, what the message calls it).
_TYPES = {'int': ((int,), 'an integer'), 'float': ((int, float), 'a number'), 'str': ((str,), 'a string'),
          'bool': ((bool,), 'true or false'), 'tuple': ((list, tuple), 'a list')}


def load_sections(path, sections: dict[str, type], overrides: dict[str, dict] | None = None,
                  defaults: dict[str, dict] | None = None) -> dict[str, object]:
    """{section: an instance of ``sections[section]``} for every section named, from the YAML
    file at ``path`` (None: no file) with ``defaults`` beneath and ``overrides`` on top."""
    where = str(path) if path is not None else 'the configuration'
    values = _read(path, sections) if path is not None else {}
    built = {}
    for name, cls in sections.items():
        merged = {**(defaults or {}).get(name, {}), **values.get(name, {}),
                  **{k: v for k, v in (overrides or {}).get(name, {}).items() if v is not None}}
        built[name] = _build(cls, merged, f'{where}: {name}')
    return built


def as_dict(configs: dict[str, object]) -> dict[str, dict]:
    """{section: its fields as plain JSON values (tuples as lists)}: what a run prints and records."""
    return json.loads(json.dumps({name: dataclasses.asdict(config) for name, config in configs.items()}))


def _read(path, sections: dict[str, type]) -> dict[str, dict]:
    known = ', '.join(sections)
    try:
        text = Path(path).read_text(encoding='utf-8')
    except OSError as err:
        raise ConfigError(f'{path}: cannot read it ({err.strerror or err})') from None
    try:
        values = yaml.safe_load(text)
    except yaml.YAMLError as err:
        raise ConfigError(f'{path}: not YAML ({" ".join(str(err).split())})') from None
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ConfigError(f'{path}: expected a mapping of sections ({known})')
    unknown = sorted(str(k) for k in values if k not in sections)
    if unknown:
        raise ConfigError(f'{path}: unknown section{"s" if len(unknown) > 1 else ""} {", ".join(unknown)}; '
                          f'known: {known}')
    for name, section in values.items():
        if section is not None and not isinstance(section, dict):
            raise ConfigError(f'{path}: section {name} must be a mapping of keys to values')
    return {name: section or {} for name, section in values.items()}


def _build(cls, values: dict, where: str):
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(str(k) for k in values if k not in fields)
    if unknown:
        raise ConfigError(f'{where}: unknown key{"s" if len(unknown) > 1 else ""} {", ".join(unknown)}; '
                          f'known: {", ".join(fields)}')
    converted = {key: _convert(value, fields[key], where) for key, value in values.items()}
    missing = [f.name for f in fields.values() if f.name not in converted and f.default is dataclasses.MISSING
               and f.default_factory is dataclasses.MISSING]
    if missing:
        raise ConfigError(f'{where}: missing {", ".join(missing)}')
    try:
        return cls(**converted)
    except (TypeError, ValueError) as err:
        raise ConfigError(f'{where}: {" ".join(str(err).split())}') from None


def _convert(value, field: dataclasses.Field, where: str):
    """``value`` for ``field``: checked against a plain annotation (int, float, str, bool, tuple);
    lists become tuples, integers floats where a float is annotated; other annotations pass it as is."""
    annotation = field.type if isinstance(field.type, str) else getattr(field.type, '__name__', '')
    if annotation not in _TYPES:
        return value
    accepted, called = _TYPES[annotation]
    if not isinstance(value, accepted) or (isinstance(value, bool) and annotation != 'bool'):
        hint = ' (YAML reads 5e-4 as a string: write 0.0005 or 5.0e-4)' if annotation == 'float' and isinstance(
            value, str) else ''
        raise ConfigError(f'{where}.{field.name}: expected {called}, got {value!r}{hint}')
    if annotation == 'tuple':
        return tuple(value)
    if annotation == 'float':
        return float(value)
    return value
