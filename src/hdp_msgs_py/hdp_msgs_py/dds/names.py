"""ROS 2 name rules: node names, namespaces, topic expansion and remapping."""

from __future__ import annotations

import re

_TOKEN = re.compile(r'^[A-Za-z_][A-Za-z0-9_]*$')


def validate_node_name(name: str) -> str:
    if not _TOKEN.match(name or ''):
        raise ValueError(f'invalid node name {name!r}: use letters, digits and underscores, '
                         'not starting with a digit')
    return name


def normalize_namespace(namespace: str | None) -> str:
    """'' or None -> '/', 'a/b' -> '/a/b'; each token must be a valid name."""
    namespace = '/' + (namespace or '').strip('/') if namespace not in (None, '', '/') else '/'
    for token in namespace.strip('/').split('/'):
        if token and not _TOKEN.match(token):
            raise ValueError(f'invalid namespace {namespace!r}: bad token {token!r}')
    return namespace


def fully_qualified(namespace: str, node_name: str) -> str:
    return namespace.rstrip('/') + '/' + node_name


def expand_topic_name(name: str, node_name: str, namespace: str) -> str:
    """Resolve '~/x', 'x' and '/x' the way rcl does; ValueError if malformed."""
    if not name:
        raise ValueError('topic name must not be empty')
    if name.startswith('~'):
        name = fully_qualified(namespace, node_name) + name[1:]
    elif not name.startswith('/'):
        name = namespace.rstrip('/') + '/' + name
    if name != '/' and name.endswith('/') or '//' in name:
        raise ValueError(f'invalid topic name {name!r}')
    for token in name.strip('/').split('/'):
        if not re.match(r'^[A-Za-z0-9_]+$', token) or token[0].isdigit():
            raise ValueError(f'invalid topic name {name!r}: bad token {token!r}')
    return name


def apply_remaps(name: str, remaps: list[tuple[str | None, str, str]], node_name: str,
                 namespace: str) -> str:
    """First matching rule wins, as in rcl. A rule is (node or None, from, to)."""
    for rule_node, src, dst in remaps:
        if rule_node not in (None, node_name) or src.startswith('__'):
            continue
        if expand_topic_name(src, node_name, namespace) == name:
            return expand_topic_name(dst, node_name, namespace)
    return name
