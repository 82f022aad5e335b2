"""Our message classes are byte-identical to ROS 2 Jazzy on the wire.

Random instances of every type are serialised with our CDR codec and with the
`rosbags` ROS2_JAZZY typestore (an independent implementation), both ways.
"""

import array
import dataclasses
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from rosbags.typesys import Stores, get_typestore

from hdp_msgs_py import cdr
from hdp_msgs_py.message import get_message, message_types
from hdp_msgs_py.msg_spec import PRIMITIVES, STRING, FieldSpec

pytestmark = pytest.mark.unit

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

_INT_RANGES = {'int8': 8, 'int16': 16, 'int32': 32, 'int64': 64}
_text = st.text(st.characters(blacklist_categories=('Cs',), blacklist_characters='\x00'), max_size=12)


def _scalar_strategy(field: FieldSpec):
    base = field.base
    if base == STRING:
        return _text if field.string_bound is None else st.text(
            st.characters(blacklist_categories=('Cs',), blacklist_characters='\x00',
                          max_codepoint=127), max_size=field.string_bound)
    if base == 'bool':
        return st.booleans()
    if base in ('float32', 'float64'):
        width = 32 if base == 'float32' else 64
        return st.floats(width=width, allow_nan=False)
    if base in _INT_RANGES:
        bits = _INT_RANGES[base]
        return st.integers(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)
    if base in PRIMITIVES:
        return st.integers(0, 2 ** (8 * PRIMITIVES[base][1]) - 1)
    return message_strategy(base)


def _field_strategy(field: FieldSpec):
    item = _scalar_strategy(FieldSpec(field.name, field.base, string_bound=field.string_bound))
    if field.array is None:
        return item
    if field.array == 'fixed':
        size = st.just(field.size)
    else:
        size = st.integers(0, min(field.size or 4, 4))
    lists = size.flatmap(lambda n: st.lists(item, min_size=n, max_size=n))
    if field.is_primitive and field.base != 'bool':
        fmt = PRIMITIVES[field.base][0]
        if field.array == 'fixed':
            return lists.map(lambda xs: np.array(xs, dtype='<' + fmt))
        return lists.map(lambda xs: array.array(fmt, xs))
    return lists


def message_strategy(type_name: str):
    cls = get_message(type_name)
    return st.fixed_dictionaries({f.name: _field_strategy(f) for f in cls._spec.fields}).map(
        lambda kwargs: cls(**kwargs))


def to_rosbags(msg):
    """Our message -> the rosbags dataclass of the same type."""
    rtype = TYPESTORE.types[msg._type]
    kwargs = {}
    for field in msg._spec.fields:
        value = getattr(msg, field.name)
        if field.is_message:
            value = [to_rosbags(v) for v in value] if field.array else to_rosbags(value)
        elif field.is_primitive and field.array:
            fmt = PRIMITIVES[field.base][0]
            value = np.array(value, dtype='<' + fmt) if field.base != 'bool' else np.array(value, dtype=bool)
        elif field.base == STRING and field.array:
            value = list(value)
        kwargs[field.name] = value
    if not msg._spec.fields:
        kwargs['structure_needs_at_least_one_member'] = 0
    return rtype(**kwargs)


def rosbags_equal(a, b) -> bool:
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(
            rosbags_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    if isinstance(a, list):
        return len(a) == len(b) and all(rosbags_equal(x, y) for x, y in zip(a, b))
    return a == b


ALL_TYPES = message_types()


def test_every_required_type_is_defined():
    required = """builtin_interfaces/msg/Time builtin_interfaces/msg/Duration std_msgs/msg/Header
    std_msgs/msg/String std_msgs/msg/Bool geometry_msgs/msg/Point geometry_msgs/msg/Quaternion
    geometry_msgs/msg/Vector3 geometry_msgs/msg/Pose geometry_msgs/msg/PoseStamped
    geometry_msgs/msg/Transform geometry_msgs/msg/TransformStamped sensor_msgs/msg/Image
    sensor_msgs/msg/CameraInfo sensor_msgs/msg/RegionOfInterest sensor_msgs/msg/JointState
    trajectory_msgs/msg/JointTrajectory trajectory_msgs/msg/JointTrajectoryPoint
    tf2_msgs/msg/TFMessage rosgraph_msgs/msg/Clock rmw_dds_common/msg/Gid
    rmw_dds_common/msg/NodeEntitiesInfo rmw_dds_common/msg/ParticipantEntitiesInfo
    visualization_msgs/msg/Marker sensor_msgs/msg/PointCloud2 std_msgs/msg/ColorRGBA""".split()
    assert set(required) <= set(ALL_TYPES)
    assert get_message('sensor_msgs/msg/Image')._dds_type_name == 'sensor_msgs::msg::dds_::Image_'


@pytest.mark.parametrize('type_name', ALL_TYPES)
def test_field_names_match_ros(type_name):
    ours = [f.name for f in get_message(type_name)._spec.fields]
    theirs = [name for name, _ in TYPESTORE.fielddefs[type_name][1]]
    if not ours:
        assert theirs == ['structure_needs_at_least_one_member']
    else:
        assert ours == theirs


@pytest.mark.parametrize('type_name', ALL_TYPES)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_wire_identical_both_directions(type_name, data):
    msg = data.draw(message_strategy(type_name))
    ours = bytes(cdr.serialize(msg))
    theirs = bytes(TYPESTORE.serialize_cdr(to_rosbags(msg), type_name))
    assert ours == theirs
    assert cdr.deserialize(type(msg), theirs) == msg
    assert rosbags_equal(TYPESTORE.deserialize_cdr(ours, type_name), to_rosbags(msg))


def test_defaults_match_ros():
    q = get_message('geometry_msgs/msg/Quaternion')()
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)
    info = get_message('sensor_msgs/msg/CameraInfo')()
    assert info.k.shape == (9,) and info.p.shape == (12,) and isinstance(info.d, array.array)


def test_bad_values_raise_type_error_naming_the_field():
    Image = get_message('sensor_msgs/msg/Image')
    with pytest.raises(TypeError, match="'height'"):
        cdr.serialize(Image(height=-1))
    with pytest.raises(TypeError, match="'encoding'"):
        cdr.serialize(Image(encoding=5))
    with pytest.raises(TypeError, match="'k'"):
        cdr.serialize(get_message('sensor_msgs/msg/CameraInfo')(k=[1.0, 2.0]))
    with pytest.raises(TypeError, match='no field'):
        Image(colour='red')


def test_truncated_and_foreign_payloads_raise_cdr_error():
    Image = get_message('sensor_msgs/msg/Image')
    payload = bytes(cdr.serialize(Image(height=4, width=4, encoding='mono8', step=4, data=bytes(16))))
    for cut in (3, 10, len(payload) - 1):
        with pytest.raises(cdr.CdrError):
            cdr.deserialize(Image, payload[:cut])
    with pytest.raises(cdr.CdrError):
        cdr.deserialize(Image, b'\x01\x00\x00\x00' + payload[4:])   # big-endian header
    huge_count = payload[:4] + payload[4:40] + struct.pack('<I', 2 ** 31)
    with pytest.raises(cdr.CdrError):
        cdr.deserialize(get_message('sensor_msgs/msg/JointState'), huge_count)
