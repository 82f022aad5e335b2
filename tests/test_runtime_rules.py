"""The runtime's pure rules: names, remapping, arguments, parameters, discovery config."""

import pytest

from hdp_msgs_py.dds.arguments import load_params_file, parse_ros_args
from hdp_msgs_py.dds.context import cyclone_config, domain_id_from_env
from hdp_msgs_py.dds.names import (apply_remaps, expand_topic_name, normalize_namespace,
                                   validate_node_name)
from hdp_msgs_py.dds.parameters import InvalidParameterTypeException, ParameterType, coerce, type_of
from hdp_msgs_py.dds.qos import QoSProfile, as_profile


@pytest.mark.parametrize('name, expected', [
    ('chatter', '/robot/chatter'), ('/chatter', '/chatter'), ('~/status', '/robot/planner/status'),
    ('a/b', '/robot/a/b')])
def test_topic_expansion(name, expected):
    assert expand_topic_name(name, 'planner', '/robot') == expected


@pytest.mark.parametrize('bad', ['', '/a//b', '/a/', '/1abc', '/a b', '/a-b'])
def test_bad_topic_names_rejected(bad):
    with pytest.raises(ValueError):
        expand_topic_name(bad, 'n', '/')


def test_node_names_and_namespaces():
    assert validate_node_name('planner_node') == 'planner_node'
    for bad in ('', '1node', 'my-node', 'a/b'):
        with pytest.raises(ValueError):
            validate_node_name(bad)
    assert normalize_namespace(None) == '/'
    assert normalize_namespace('lab/arm') == '/lab/arm'
    with pytest.raises(ValueError):
        normalize_namespace('/lab/9arm')


def test_remap_rules_first_match_and_node_specific():
    remaps = [('other', '/a', '/x'), (None, 'a', '/b'), (None, '/a', '/c')]
    assert apply_remaps('/a', remaps, 'planner', '/') == '/b'
    assert apply_remaps('/a', remaps, 'other', '/') == '/x'
    assert apply_remaps('/z', remaps, 'planner', '/') == '/z'


def test_ros_args_split_from_program_args(tmp_path):
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    a: 1\n    nested: {b: 2.5}\n')
    args, rest = parse_ros_args(['prog', '--flag', '--ros-args', '-p', 'x:=[1, 2]', '-r', 'in:=/out',
                                 '--params-file', str(params), '--log-level', 'debug', '--', 'tail'])
    assert rest == ['prog', '--flag', 'tail']
    assert args.remaps == [(None, 'in', '/out')]
    assert args.log_level == 'debug'
    assert args.parameters_for('/any_node') == {'x': [1, 2], 'a': 1, 'nested.b': 2.5}


def test_node_specific_parameters_and_name_overrides():
    args, _ = parse_ros_args(['--ros-args', '-p', 'planner_node:budget:=3', '-p', 'budget:=1',
                              '-r', 'planner_node:__node:=hl', '-r', '__ns:=/lab'])
    assert args.parameters_for('/planner_node') == {'budget': 1}      # later wins
    assert args.node_name_override('planner_node') == 'hl'
    assert args.node_name_override('controller_node') is None
    assert args.namespace_override('controller_node') == '/lab'


@pytest.mark.parametrize('argv, message', [
    (['--ros-args', '-p'], 'needs a value'),
    (['--ros-args', '-p', 'novalue'], "expects 'name:=value'"),
    (['--ros-args', '--bogus', 'x'], 'unknown ROS argument'),
])
def test_bad_ros_args(argv, message):
    with pytest.raises(ValueError, match=message):
        parse_ros_args(argv)


def test_params_file_errors(tmp_path):
    with pytest.raises(ValueError, match='cannot read'):
        load_params_file(tmp_path / 'missing.yaml')
    bad = tmp_path / 'bad.yaml'
    bad.write_text('node:\n  parameters:\n    a: 1\n')
    with pytest.raises(ValueError, match="expected 'ros__parameters'"):
        load_params_file(bad)
    nested = tmp_path / 'nested.yaml'
    nested.write_text('lab:\n  planner_node:\n    ros__parameters:\n      a: 1\n')
    assert load_params_file(nested) == [('/lab/planner_node', {'a': 1})]


def test_parameter_types():
    assert type_of(True) is ParameterType.BOOL
    assert type_of([1, 2.0]) is ParameterType.DOUBLE_ARRAY
    assert type_of(['a']) is ParameterType.STRING_ARRAY
    assert coerce('x', 2, ParameterType.DOUBLE) == 2.0
    with pytest.raises(InvalidParameterTypeException, match="'x' is INTEGER, got STRING"):
        coerce('x', 'two', ParameterType.INTEGER)
    with pytest.raises(InvalidParameterTypeException):
        type_of({'a': 1})


def test_qos_from_depth_or_profile():
    assert as_profile(5) == QoSProfile(depth=5)
    with pytest.raises(TypeError):
        as_profile('5')
    with pytest.raises(ValueError):
        QoSProfile(depth=0)


def test_discovery_is_localhost_only_by_default(monkeypatch):
    for var in ('CYCLONEDDS_URI', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_STATIC_PEERS'):
        monkeypatch.delenv(var, raising=False)
    config = cyclone_config()
    assert '<AllowMulticast>false</AllowMulticast>' in config
    assert '<Peer Address="localhost"/>' in config
    assert 'address="127.0.0.1"' in config
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'SUBNET')
    monkeypatch.setenv('ROS_STATIC_PEERS', '10.0.0.5;robot.local')
    config = cyclone_config()
    assert 'AllowMulticast' not in config and '<Peer Address="robot.local"/>' in config
    monkeypatch.setenv('CYCLONEDDS_URI', 'file:///etc/cyclone.xml')
    assert cyclone_config() is None
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'EVERYWHERE')
    monkeypatch.delenv('CYCLONEDDS_URI')
    with pytest.raises(ValueError):
        cyclone_config()


def test_domain_id_from_env(monkeypatch):
    monkeypatch.setenv('ROS_DOMAIN_ID', '17')
    assert domain_id_from_env() == 17
    monkeypatch.setenv('ROS_DOMAIN_ID', '')
    assert domain_id_from_env() == 0
    for bad in ('-1', '300', 'x'):
        monkeypatch.setenv('ROS_DOMAIN_ID', bad)
        with pytest.raises(ValueError):
            domain_id_from_env()
