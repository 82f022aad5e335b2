"""Episode bags: written with our codec, read back by us and by plain `rosbags`."""

import shutil

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore

from hdp_msgs_py import topics
from hdp_msgs_py.conversions import image_to_numpy, numpy_to_image, seconds_to_time
from hdp_data.episodes import (EpisodeError, EpisodeWriter, list_episodes, read_episode,
                                  read_metadata)
from hdp_motion.panda import ARM_JOINTS, FINGER_JOINTS, HOME
from hdp_msgs_py.message import get_message

pytestmark = pytest.mark.unit

JointState = get_message('sensor_msgs/msg/JointState')
String = get_message('std_msgs/msg/String')
CameraInfo = get_message('sensor_msgs/msg/CameraInfo')
TFMessage = get_message('tf2_msgs/msg/TFMessage')
TransformStamped = get_message('geometry_msgs/msg/TransformStamped')
JointTrajectory = get_message('trajectory_msgs/msg/JointTrajectory')
JointTrajectoryPoint = get_message('trajectory_msgs/msg/JointTrajectoryPoint')

T0_NS = 1_700_000_000 * 10 ** 9          # epoch-scale stamps, as a real recording has
DT_NS = 10 ** 7                          # 100 Hz
FRAMES = 200                             # 2 s
IMAGE_FRAMES = (0, 60, 160)
GRIPPER_COMMAND_FRAME = 80
EXPECTED_KEYFRAMES = [60, 80, 160, 199]
METADATA = {'task': 'open_drawer', 'variation': 2, 'seed': 7, 'instruction': 'open the drawer',
            'extra': {'cameras': ['front', 'side']}}
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)


def synthetic_motion():
    """Velocities (T, 7): rest 0-9, move 10-59, rest 60-109, move 110-159, rest 160-199.

    Positions integrate them from HOME; the fingers close over frames 80-99,
    commanded at frame 80.
    """
    v = np.zeros((FRAMES, 7))
    v[10:60] = 0.3
    v[110:160] = -0.2
    q = HOME + np.cumsum(v, axis=0) * DT_NS / 1e9
    fingers = np.full(FRAMES, 0.04)
    fingers[80:100] = np.linspace(0.04, 0.0, 20)
    fingers[100:] = 0.0
    return q, v, fingers


def stamp(frame):
    return T0_NS + frame * DT_NS


def image(frame, encoding):
    if encoding == 'rgb8':
        pixels = np.full((48, 64, 3), frame, dtype=np.uint8)
    else:
        pixels = np.full((48, 64), 1000 + frame, dtype=np.uint16)
    msg = numpy_to_image(pixels, encoding)
    msg.header.stamp = seconds_to_time(stamp(frame) / 1e9)
    return msg


def transform(child, x):
    msg = TransformStamped(child_frame_id=child)
    msg.header.frame_id = 'world'
    msg.transform.translation.x = x
    msg.transform.rotation.w = 1.0
    return msg


def write_episode(path, metadata=METADATA, success=True, gripper_command=True, joint_state_type=None):
    q, v, fingers = synthetic_motion()
    # A real driver's name order is its own: put the fingers first and the arm reversed.
    names = list(FINGER_JOINTS) + list(reversed(ARM_JOINTS))
    with EpisodeWriter(path, metadata) as episode:
        episode.write(topics.TF_STATIC, TFMessage(transforms=[transform('front_camera', 1.0),
                                                              transform('side_camera', 2.0)]), stamp(0))
        episode.write(topics.INSTRUCTION, String(data='open the drawer'), stamp(0))
        episode.write(topics.camera_info('front'), CameraInfo(width=64, height=48), stamp(0))
        for i in range(FRAMES):
            if joint_state_type is not None:
                episode.write(topics.JOINT_STATES, joint_state_type(), stamp(i))
            else:
                msg = JointState(name=names, position=[fingers[i]] * 2 + list(q[i][::-1]),
                                 velocity=[0.0, 0.0] + list(v[i][::-1]))
                episode.write(topics.JOINT_STATES, msg, stamp(i))
            if i in IMAGE_FRAMES:
                episode.write(topics.color_image('front'), image(i, 'rgb8'), stamp(i))
                episode.write(topics.depth_image('front'), image(i, '16UC1'), stamp(i))
                episode.write(topics.color_image('side'), image(i, 'rgb8'), stamp(i) + 1)
            if gripper_command and i == GRIPPER_COMMAND_FRAME:
                point = JointTrajectoryPoint(positions=[0.0, 0.0])
                episode.write(topics.GRIPPER_TRAJECTORY,
                              JointTrajectory(joint_names=list(FINGER_JOINTS), points=[point]), stamp(i))
        if success is not None:
            episode.set_success(success)
    return path


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    return write_episode(tmp_path_factory.mktemp('episodes') / 'demo_000')


def test_round_trip(bag):
    episode = read_episode(bag)
    assert episode.metadata == {**METADATA, 'success': True}
    assert episode.instruction == 'open the drawer'

    q, v, fingers = synthetic_motion()
    js = episode.joint_states
    assert js.t.shape == (FRAMES,) and js.position.shape == (FRAMES, 7) and js.velocity.shape == (FRAMES, 7)
    np.testing.assert_allclose(js.t, (T0_NS + np.arange(FRAMES) * DT_NS) / 1e9)
    np.testing.assert_array_equal(js.position, q)       # reordered to ARM_JOINTS by name
    np.testing.assert_array_equal(js.velocity, v)
    np.testing.assert_allclose(js.gripper_width, 2 * fingers)
    assert js.gripper_open[:GRIPPER_COMMAND_FRAME].all() and not js.gripper_open[GRIPPER_COMMAND_FRAME:].any()

    assert sorted(episode.tf_static) == ['front_camera', 'side_camera']
    assert episode.tf_static['side_camera'].transform.translation.x == 2.0
    assert episode.camera_info('front').width == 64
    with pytest.raises(KeyError, match='side'):
        episode.camera_info('side')
    assert episode.topic_types[topics.JOINT_STATES] == 'sensor_msgs/msg/JointState'


def test_keyframes_of_a_read_episode_are_the_rests_and_the_grasp(bag):
    assert read_episode(bag).keyframes() == EXPECTED_KEYFRAMES


def test_gripper_state_without_commands_comes_from_the_finger_width(tmp_path):
    js = read_episode(write_episode(tmp_path / 'bag', gripper_command=False)).joint_states
    # the fingers leave "fully open" (within 5 mm) two frames into the closing motion
    assert js.gripper_open[:82].all() and not js.gripper_open[82:].any()


def test_images_are_read_on_demand(bag):
    episode = read_episode(bag)
    color = topics.color_image('front')
    np.testing.assert_array_equal(episode.image_stamps[color], [stamp(i) for i in IMAGE_FRAMES])

    frames = episode.frames_near(stamp(60) / 1e9 + 0.004)
    assert sorted(frames) == sorted([color, topics.depth_image('front'), topics.color_image('side')])
    t, msg = frames[color]
    assert t == stamp(60) / 1e9
    assert image_to_numpy(msg)[0, 0, 0] == 60
    assert image_to_numpy(frames[topics.depth_image('front')][1])[0, 0] == 1060
    assert frames[topics.color_image('side')][0] == (stamp(60) + 1) / 1e9

    depth = [image_to_numpy(m)[0, 0] for _, m in episode.messages(topics.depth_image('front'))]
    assert depth == [1000 + i for i in IMAGE_FRAMES]
    with pytest.raises(KeyError, match='/nope'):
        episode.messages('/nope')


def test_plain_rosbags_reads_it(bag):
    """What a ROS tool sees: version 9 MCAP with Jazzy definitions, hashes, QoS and custom data."""
    info = yaml.safe_load((bag / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert info['version'] == 9 and info['storage_identifier'] == 'mcap'
    assert info['relative_file_paths'] == ['demo_000.mcap']
    assert info['custom_data']['hdp.success'] == 'true'
    assert info['custom_data']['hdp.task'] == '"open_drawer"'
    qos = {t['topic_metadata']['name']: t['topic_metadata']['offered_qos_profiles'][0]
           for t in info['topics_with_message_count']}
    assert qos[topics.TF_STATIC]['durability'] == 'transient_local'
    assert qos[topics.color_image('front')]['reliability'] == 'best_effort'
    assert qos[topics.JOINT_STATES]['reliability'] == 'reliable'

    with Reader(bag) as reader:
        for connection in reader.connections:
            assert connection.ext.serialization_format == 'cdr'
            assert connection.digest == TYPESTORE.hash_rihs01(connection.msgtype)
        states = [TYPESTORE.deserialize_cdr(raw, c.msgtype)
                  for c, _, raw in reader.messages() if c.topic == topics.JOINT_STATES]
    assert len(states) == FRAMES
    assert list(states[0].name[2:]) == list(reversed(ARM_JOINTS))
    np.testing.assert_array_equal(states[-1].position[2:][::-1], synthetic_motion()[0][-1])

    # AnyReader without a typestore decodes with the definitions embedded in the bag.
    with AnyReader([bag]) as reader:
        decoded = {c.topic: reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages()}
    assert decoded[topics.INSTRUCTION].data == 'open the drawer'
    assert decoded[topics.depth_image('front')].encoding == '16UC1'
    assert decoded[topics.TF_STATIC].transforms[1].child_frame_id == 'side_camera'


def test_success_flag_and_listing(tmp_path):
    write_episode(tmp_path / 'a_ok', success=True)
    write_episode(tmp_path / 'b_failed', success=False)
    write_episode(tmp_path / 'c_unmarked', success=None)
    (tmp_path / 'not_a_bag').mkdir()
    with pytest.raises(RuntimeError), EpisodeWriter(tmp_path / 'd_crashed', METADATA) as episode:
        episode.set_success(True)
        raise RuntimeError('sim exploded')

    assert list_episodes(tmp_path) == [tmp_path / 'a_ok']
    assert [p.name for p in list_episodes(tmp_path, successful_only=False)] == [
        'a_ok', 'b_failed', 'c_unmarked', 'd_crashed']
    assert 'success' not in read_metadata(tmp_path / 'c_unmarked')
    crashed = read_metadata(tmp_path / 'd_crashed')
    assert crashed['success'] is False and crashed['error'] == 'RuntimeError: sim exploded'


def test_hand_written_custom_data(bag, tmp_path):
    """`ros2 bag record --custom-data hdp.task=open_drawer` stores a bare word, not JSON."""
    copy = shutil.copytree(bag, tmp_path / 'copy')
    info = yaml.safe_load((copy / 'metadata.yaml').read_text())
    custom = info['rosbag2_bagfile_information']['custom_data']
    custom.update({'hdp.task': 'open_drawer', 'hdp.success': True})
    (copy / 'metadata.yaml').write_text(yaml.safe_dump(info))
    assert read_metadata(copy)['task'] == 'open_drawer'
    assert list_episodes(tmp_path) == [copy]


def test_writer_refuses_an_existing_path_and_loses_nothing(bag):
    before = sorted((p.name, p.stat().st_size) for p in bag.iterdir())
    with pytest.raises(FileExistsError):
        EpisodeWriter(bag, METADATA)
    assert sorted((p.name, p.stat().st_size) for p in bag.iterdir()) == before


def test_writer_checks_metadata_and_types(tmp_path):
    with pytest.raises(TypeError):
        EpisodeWriter(tmp_path / 'bad', {'when': object()})
    assert not (tmp_path / 'bad').exists()
    with EpisodeWriter(tmp_path / 'ok', {}) as episode:
        episode.write('/x', String(data='a'), 0)
        with pytest.raises(TypeError, match='std_msgs/msg/String'):
            episode.write('/x', JointState(), 1)
        with pytest.raises(ValueError, match='>= 0'):
            episode.write('/x', String(data='a'), -1)


def test_refuses_a_directory_without_metadata(tmp_path):
    with pytest.raises(EpisodeError, match='no metadata.yaml'):
        read_episode(tmp_path)
    with pytest.raises(EpisodeError, match='no metadata.yaml'):
        read_episode(tmp_path / 'missing')


def test_refuses_a_bag_over_the_size_limit(bag):
    with pytest.raises(EpisodeError, match='over the limit'):
        read_episode(bag, max_bytes=10_000)
    with pytest.raises(EpisodeError, match='over the limit'):
        read_episode(bag, max_messages=100)


def test_refuses_joint_states_of_the_wrong_type(tmp_path):
    path = write_episode(tmp_path / 'bag', joint_state_type=String)
    with pytest.raises(EpisodeError, match='/joint_states has type std_msgs/msg/String'):
        read_episode(path)


def test_refuses_joint_states_without_the_arm(tmp_path):
    with EpisodeWriter(tmp_path / 'bag', {}) as episode:
        episode.write(topics.JOINT_STATES, JointState(name=['a'], position=[0.0], velocity=[0.0]), 0)
    with pytest.raises(EpisodeError, match='lacks joints'):
        read_episode(tmp_path / 'bag')


def test_damaged_files_are_value_errors(bag, tmp_path):
    truncated = shutil.copytree(bag, tmp_path / 'truncated')
    mcap = truncated / 'demo_000.mcap'
    mcap.write_bytes(mcap.read_bytes()[:-100])
    with pytest.raises(EpisodeError, match='damaged bag'):
        read_episode(truncated)

    miscounted = shutil.copytree(bag, tmp_path / 'miscounted')
    meta = miscounted / 'metadata.yaml'
    info = yaml.safe_load(meta.read_text())
    info['rosbag2_bagfile_information']['topics_with_message_count'][0]['message_count'] += 1
    meta.write_text(yaml.safe_dump(info))
    with pytest.raises(EpisodeError, match='declares'):
        read_episode(miscounted)

    garbage = shutil.copytree(bag, tmp_path / 'garbage')
    (garbage / 'metadata.yaml').write_text('rosbag2_bagfile_information: [unclosed')
    with pytest.raises(EpisodeError, match='not rosbag2 metadata'):
        read_episode(garbage)


def test_an_fr3_recording_names_its_robot_and_reads_with_the_fr3_joints(tmp_path):
    """`ros2 bag record --custom-data hdp.robot=fr3`: the joints are fr3_joint1..7 and
    fr3_finger_joint1/2, read as a Panda recording is; an unknown robot is refused."""
    q, v, fingers = synthetic_motion()
    names = [n.replace('panda', 'fr3', 1) for n in [*ARM_JOINTS, *FINGER_JOINTS]]

    def record(name, metadata):
        with EpisodeWriter(tmp_path / name, metadata) as episode:
            for i in range(FRAMES):
                episode.write(topics.JOINT_STATES, JointState(name=names, position=[*q[i], fingers[i], fingers[i]],
                                                              velocity=[*v[i], 0.0, 0.0]), stamp(i))
        return tmp_path / name
    with pytest.raises(EpisodeError, match='lacks joints'):
        read_episode(record('unnamed', {}))                  # a Panda's names by default
    episode = read_episode(record('fr3', {'robot': 'fr3'}))
    assert np.allclose(episode.joint_states.position, q)
    assert np.allclose(episode.joint_states.gripper_width, 2 * fingers)
    with pytest.raises(EpisodeError, match="hdp.robot is 'ur5'; robots: panda, fr3"):
        read_episode(record('ur5', {'robot': 'ur5'}))
