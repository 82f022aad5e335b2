"""Recorded episodes: rosbag2 bags (MCAP storage) of the graph's own topics.

A bag recorded on a real Panda with ``ros2 bag record`` is valid training
data, and the sim collector writes the same format with ``EpisodeWriter``:

    <episode>/metadata.yaml         rosbag2 metadata, version 9 (Jazzy)
    <episode>/<episode>.mcap        one MCAP file, uncompressed

Messages are stored as CDR exactly as they travel on DDS; each topic carries
its ROS 2 message definition and type hash (from the rosbags Jazzy
typestore) and its offered QoS, so ``ros2 bag info`` and ``ros2 bag play``
read the bag. Episode metadata (task, variation, seed, success, instruction,
...) lives in the bag's ``custom_data`` as JSON strings under ``hdp.`` keys;
a real recording can carry it too:
``ros2 bag record --custom-data hdp.success=true hdp.task=open_drawer ...``.

Bags are untrusted input: ``read_episode`` checks sizes, counts and topic
types before it decodes anything, and every problem with the file is an
EpisodeError (a ValueError) naming the bag and topic.

Times are the bag's timestamps in seconds: the receive time under
``ros2 bag record``, the ``stamp_ns`` the collector passed to ``write``.
Read messages are always hdp_msgs_py's own classes (hdp_msgs_py.message),
whichever runtime is active.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import operator
import struct
from pathlib import Path, PurePath

import numpy as np
import yaml
from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from hdp_motion.panda import FINGER_MAX, ROBOT_LIMITS, finger_joint_names, joint_names, reads_open
from hdp_msgs_py import cdr, topics
from hdp_msgs_py.message import Message, from_rclpy, get_message, type_name_of

from .keyframes import DEFAULT_STOPPED_BUFFER, DEFAULT_STOPPING_DELTA, discover_keyframes

ROBOTS = tuple(ROBOT_LIMITS)          # the arms a recording may come from (hdp.robot)

METADATA_PREFIX = 'hdp.'
DEFAULT_MAX_BYTES = 2 * 1024 ** 3
DEFAULT_MAX_MESSAGES = 2_000_000         # > 5 h of 100 Hz joint states with cameras
_MAX_METADATA_BYTES = 1024 ** 2
# rmw's "infinite" duration, as rosbag2 writes it for default deadline/lifespan/lease.
_INFINITE = QosTime(9223372036, 854775807)

JOINT_STATE = 'sensor_msgs/msg/JointState'
IMAGE = 'sensor_msgs/msg/Image'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
STRING = 'std_msgs/msg/String'
TF_MESSAGE = 'tf2_msgs/msg/TFMessage'
JOINT_TRAJECTORY = 'trajectory_msgs/msg/JointTrajectory'

# The types the graph's own topics must have; other topics are carried along unchecked.
EXPECTED_TYPES = {
    topics.JOINT_STATES: JOINT_STATE,
    topics.INSTRUCTION: STRING,
    topics.STATUS: STRING,
    topics.TF_STATIC: TF_MESSAGE,
    topics.CLOCK: 'rosgraph_msgs/msg/Clock',
    topics.NEXT_BEST_POSE: 'geometry_msgs/msg/PoseStamped',
    topics.ARM_TRAJECTORY: JOINT_TRAJECTORY,
    topics.GRIPPER_TRAJECTORY: JOINT_TRAJECTORY,
    **{topics.color_image(c): IMAGE for c in topics.CAMERAS},
    **{topics.depth_image(c): IMAGE for c in topics.CAMERAS},
    **{topics.camera_info(c): CAMERA_INFO for c in topics.CAMERAS},
}


class EpisodeError(ValueError):
    """A bag that is missing, too large, malformed or not shaped like an episode."""


@functools.cache
def _typestore():
    return get_typestore(Stores.ROS2_JAZZY)


def offered_qos(topic: str) -> Qos:
    """The QoS our nodes publish ``topic`` with, so ``ros2 bag play`` offers the same (latched
    topics latched)."""
    named = {topics.TF_STATIC: 'TF_STATIC_QOS', topics.ROBOT_DESCRIPTION: 'LATCHED_QOS', topics.TF: 'TF_QOS',
             topics.STATUS: 'STATUS_QOS', topics.SIM_EPISODE: 'LATCHED_QOS'}
    default = 'SENSOR_QOS' if topic.startswith('/camera/') or topic == topics.PLANNER_CLOUD else 'COMMAND_QOS'
    policies = topics.QOS_POLICIES[named.get(topic, default)]
    return Qos(QosHistory.KEEP_LAST, policies.depth, QosReliability[policies.reliability],
               QosDurability[policies.durability], _INFINITE, _INFINITE, QosLiveliness.AUTOMATIC, _INFINITE,
               False)


def _serialize(msg) -> bytes:
    return cdr.serialize(msg if isinstance(msg, Message) else from_rclpy(msg))


class EpisodeWriter:
    """Writes one episode bag; use as a context manager.

        with EpisodeWriter(path, {'task': 'open_drawer', 'seed': 3}) as episode:
            episode.write('/joint_states', msg, stamp_ns)
            episode.set_success(True)

    The bag is created at once; an existing ``path`` raises FileExistsError
    (an episode is never overwritten). If the block raises, the bag is still
    closed and readable, marked success = false with the error recorded.
    """

    def __init__(self, path, metadata: dict):
        self.path = Path(path)
        if self.path.exists():
            raise FileExistsError(f'{self.path} exists; an episode is never overwritten')
        self._writer = Writer(self.path, version=Writer.VERSION_LATEST, storage_plugin=StoragePlugin.MCAP)
        self._connections = {}
        self._closed = False
        # Metadata first: a bad value raises before anything is created on disk.
        for key, value in metadata.items():
            self.set_metadata(key, value)
        self._writer.open()

    def set_metadata(self, key: str, value) -> None:
        """Store ``value`` (anything JSON-serialisable) under ``hdp.<key>``; TypeError/ValueError if not."""
        if not isinstance(key, str) or not key:
            raise TypeError(f'metadata keys are non-empty strings, got {key!r}')
        if self._closed:
            raise RuntimeError(f'{self.path} is closed; metadata is written on close')
        self._writer.set_custom_data(METADATA_PREFIX + key, json.dumps(value, allow_nan=False))

    def set_success(self, success: bool) -> None:
        self.set_metadata('success', bool(success))

    def write(self, topic: str, msg, stamp_ns: int) -> None:
        """Append ``msg`` (ours or rclpy's) on ``topic`` at bag time ``stamp_ns`` (int >= 0).

        A topic's type is fixed by its first message; TypeError on a mismatch.
        """
        stamp_ns = operator.index(stamp_ns)
        if stamp_ns < 0:
            raise ValueError(f'stamp_ns must be >= 0, got {stamp_ns}')
        type_name = type_name_of(type(msg))
        connection = self._connections.get(topic)
        if connection is None:
            connection = self._writer.add_connection(topic, type_name, typestore=_typestore(),
                                                     offered_qos_profiles=[offered_qos(topic)])
            self._connections[topic] = connection
        elif connection.msgtype != type_name:
            raise TypeError(f'{topic} carries {connection.msgtype}, got {type_name}')
        self._writer.write(connection, stamp_ns, _serialize(msg))

    def close(self) -> None:
        """Finish the MCAP file and write metadata.yaml; later calls do nothing."""
        if not self._closed:
            self._writer.close()
            self._closed = True

    def __enter__(self) -> EpisodeWriter:
        return self

    def __exit__(self, exc_type, exc, traceback) -> None:
        if exc_type is not None and not self._closed:
            self.set_metadata('error', f'{exc_type.__name__}: {exc}')
            self.set_success(False)
        self.close()


@dataclasses.dataclass(frozen=True)
class JointStates:
    """The arm's state at each /joint_states message, T frames in bag order.

    t: (T,) s. position, velocity: (T, 7) rad, rad/s in the arm joints' order (joint1..7).
    gripper_width: (T,) m between the fingers. gripper_open: (T,) bool, the
    commanded state (from the gripper command topic when recorded, else the
    fingers being fully open): what the keyframe heuristic expects. A gripper
    command is a JointTrajectory whose last point holds per-finger positions
    (0 closed .. FINGER_MAX open).
    """
    t: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    gripper_width: np.ndarray
    gripper_open: np.ndarray


@dataclasses.dataclass(frozen=True)
class Episode:
    """One read episode. Small topics are decoded; images are read on demand.

    metadata: the hdp.* custom data (task, variation, seed, success, ...).
    instruction: the last /hdp/instruction, else metadata['instruction'], else ''.
    tf_static: child frame id -> geometry_msgs/TransformStamped (the latest wins).
    camera_infos: topic -> the first sensor_msgs/CameraInfo on it.
    image_stamps: image topic -> (N,) int64 ns bag times of its frames.
    topic_types: every topic in the bag -> its message type.
    """
    path: Path
    metadata: dict
    joint_states: JointStates
    instruction: str
    tf_static: dict
    camera_infos: dict
    image_stamps: dict
    topic_types: dict

    def camera_info(self, camera: str):
        """The CameraInfo of ``camera`` ('front', 'side'); KeyError if none was recorded."""
        topic = topics.camera_info(camera)
        if topic not in self.camera_infos:
            raise KeyError(f'{self.path}: no {topic}; camera infos: {sorted(self.camera_infos)}')
        return self.camera_infos[topic]

    def messages(self, topic: str):
        """Iterator over (t, msg) on ``topic``, decoded one at a time from the file."""
        if topic not in self.topic_types:
            raise KeyError(f'{self.path}: no topic {topic}; topics: {sorted(self.topic_types)}')
        return _decoded(self.path, {topic})

    def frames_near(self, t: float) -> dict:
        """Image topic -> (t_frame, Image) of the frame nearest to ``t`` s, one per image topic."""
        frames = {}
        for topic, stamps in self.image_stamps.items():
            if not len(stamps):
                continue
            stamp = int(stamps[np.argmin(np.abs(stamps - t * 1e9))])
            # Reads only the MCAP chunk(s) holding that stamp.
            with contextlib.closing(_decoded(self.path, {topic}, stamp, stamp + 1)) as found:
                frames[topic] = next(found)
        return frames

    def keyframes(self, stopping_delta: float = DEFAULT_STOPPING_DELTA,
                  stopped_buffer: int = DEFAULT_STOPPED_BUFFER) -> list[int]:
        """Keyframe indices into joint_states (see hdp_data.keyframes)."""
        js = self.joint_states
        return discover_keyframes(js.velocity, js.gripper_open, stopping_delta, stopped_buffer)


# --- reading -------------------------------------------------------------------

# What rosbags and our decoder raise on a damaged file. MemoryError and
# OverflowError too: rosbags allocates a record's (corrupt) length before it
# finds the file is shorter.
_BAG_ERRORS = (ReaderError, cdr.CdrError, struct.error, IndexError, KeyError, UnicodeDecodeError,
               MemoryError, OverflowError)


def _bag_info(path: Path) -> dict:
    """The rosbag2_bagfile_information of metadata.yaml, size-checked before parsing."""
    meta = path / 'metadata.yaml'
    if not path.is_dir() or not meta.is_file():
        raise EpisodeError(f'{path} is not a rosbag2 directory (no metadata.yaml)')
    if meta.stat().st_size > _MAX_METADATA_BYTES:
        raise EpisodeError(f'{meta} is over {_MAX_METADATA_BYTES} bytes')
    try:
        info = yaml.safe_load(meta.read_text(encoding='utf-8'))['rosbag2_bagfile_information']
    except (yaml.YAMLError, UnicodeDecodeError, TypeError, KeyError) as err:
        raise EpisodeError(f'{meta} is not rosbag2 metadata: {err!r}') from None
    if not isinstance(info, dict):
        raise EpisodeError(f'{meta} is not rosbag2 metadata')
    return info


def _hdp_metadata(info: dict, path: Path) -> dict:
    custom = info.get('custom_data') or {}
    if not isinstance(custom, dict):
        raise EpisodeError(f'{path}: custom_data is not a mapping')
    metadata = {}
    for key, value in custom.items():
        if isinstance(key, str) and key.startswith(METADATA_PREFIX):
            metadata[key[len(METADATA_PREFIX):]] = _metadata_value(value)
    return metadata


def _metadata_value(value):
    if not isinstance(value, str):
        return value                      # YAML already typed it: an unquoted true, 3
    try:
        return json.loads(value)
    except json.JSONDecodeError:
        return value                      # a bare word: --custom-data hdp.task=open_drawer


def read_metadata(path) -> dict:
    """The hdp.* metadata of the bag at ``path``, from metadata.yaml alone (cheap)."""
    path = Path(path)
    return _hdp_metadata(_bag_info(path), path)


def list_episodes(directory, successful_only: bool = True) -> list[Path]:
    """Sorted bag directories directly under ``directory``.

    With successful_only (the default), only bags whose metadata says
    success = true: failed or unmarked demos never reach training.
    ValueError (every trainer's and evaluator's one-line refusal) when ``directory`` is not one.
    """
    if not Path(directory).is_dir():
        raise ValueError(f'{directory} is not a directory of episodes (hdp collect writes one)')
    bags = sorted(p for p in Path(directory).iterdir() if (p / 'metadata.yaml').is_file())
    if successful_only:
        bags = [p for p in bags if read_metadata(p).get('success') is True]
    return bags


def _decode(type_name: str, data, where: str):
    try:
        return cdr.deserialize(get_message(type_name), data)
    except cdr.CdrError as err:
        raise EpisodeError(f'{where}: undecodable {type_name}: {err}') from None


def _decoded(path: Path, wanted: set, start=None, stop=None):
    """(t, msg) for the messages on the ``wanted`` topics, translating file damage to EpisodeError."""
    try:
        with Reader(path) as reader:
            connections = [c for c in reader.connections if c.topic in wanted]
            for connection, stamp, data in reader.messages(connections, start, stop):
                yield stamp / 1e9, _decode(connection.msgtype, data, f'{path} {connection.topic}')
    except _BAG_ERRORS as err:
        raise EpisodeError(f'{path}: damaged bag: {err}') from err


def _check_metadata(path: Path, info: dict, max_bytes: int, max_messages: int) -> None:
    """Types of the fields rosbags relies on, then sizes and counts against the limits."""
    meta = path / 'metadata.yaml'

    def field(node, *keys, kind):
        for key in keys:
            node = node.get(key) if isinstance(node, dict) else None
        if not isinstance(node, kind) or isinstance(node, bool):
            raise EpisodeError(f'{meta}: {"/".join(keys)} is missing or not a {kind.__name__}')
        return node

    field(info, 'storage_identifier', kind=str)
    field(info, 'duration', 'nanoseconds', kind=int)
    field(info, 'starting_time', 'nanoseconds_since_epoch', kind=int)
    if 'files' in info:
        field(info, 'files', kind=list)
    for entry in field(info, 'topics_with_message_count', kind=list):
        field(entry, 'topic_metadata', 'name', kind=str)
        field(entry, 'topic_metadata', 'type', kind=str)
        field(entry, 'message_count', kind=int)
    compression = info.get('compression_mode') or 'none'
    if not isinstance(compression, str) or compression.lower() != 'none':
        # File compression would be inflated to a temporary file of unchecked size.
        raise EpisodeError(f'{path}: compressed bags are not supported (re-record without compression)')

    names = field(info, 'relative_file_paths', kind=list)
    if not all(isinstance(name, str) for name in names):
        raise EpisodeError(f'{meta}: relative_file_paths must be strings')
    files = [path / PurePath(name).name for name in names]     # as rosbags resolves them
    missing = [f.name for f in files if not f.is_file()]
    if missing:
        raise EpisodeError(f'{path}: storage files missing: {missing}')
    size = sum(f.stat().st_size for f in files) + meta.stat().st_size
    if size > max_bytes:
        raise EpisodeError(f'{path} holds {size} bytes, over the limit of {max_bytes}')
    declared = field(info, 'message_count', kind=int)
    if not 0 <= declared <= max_messages:
        raise EpisodeError(f'{path} declares {declared} messages, over the limit of {max_messages}')


def read_episode(path, max_bytes: int = DEFAULT_MAX_BYTES, max_messages: int = DEFAULT_MAX_MESSAGES,
                 arm_joints=None, finger_joints=None) -> Episode:
    """Read and validate the episode bag at ``path``; EpisodeError (ValueError) on any problem.

    One pass over the file: joint states, instruction, /tf_static, camera
    infos and gripper commands are decoded; of image topics only the times
    are kept. ``arm_joints`` and ``finger_joints`` name the joints to pick
    from /joint_states; by default the robot's that the bag's ``hdp.robot`` metadata names
    ('panda', the default, or 'fr3': `ros2 bag record --custom-data hdp.robot=fr3`).
    """
    path = Path(path)
    info = _bag_info(path)
    metadata = _hdp_metadata(info, path)
    _check_metadata(path, info, max_bytes, max_messages)
    robot = metadata.get('robot', 'panda')
    if robot not in ROBOTS:
        raise EpisodeError(f'{path}: hdp.robot is {robot!r}; robots: {", ".join(ROBOTS)}')
    rows = _JointRows(f'{path} {topics.JOINT_STATES}',
                      tuple(arm_joints or joint_names(robot)),
                      tuple(finger_joints or finger_joint_names(robot)))
    try:
        with Reader(path) as reader:
            types = {c.topic: c.msgtype for c in reader.connections}
            if len(types) != len(reader.connections):
                raise EpisodeError(f'{path}: a topic is recorded with more than one type or QoS')
            for topic, type_name in types.items():
                if EXPECTED_TYPES.get(topic, type_name) != type_name:
                    raise EpisodeError(f'{path}: {topic} has type {type_name}, '
                                       f'expected {EXPECTED_TYPES[topic]}')
            parts = _collect(path, reader, types, max_messages, rows)
    except _BAG_ERRORS as err:
        raise EpisodeError(f'{path}: damaged bag: {err}') from err

    instruction = parts['instructions'][-1] if parts['instructions'] else metadata.get('instruction', '')
    return Episode(path=path, metadata=metadata, joint_states=rows.finish(parts['gripper_commands']),
                   instruction=str(instruction), tf_static=parts['tf_static'],
                   camera_infos=parts['camera_infos'],
                   image_stamps={k: np.array(v, dtype=np.int64) for k, v in parts['image_stamps'].items()},
                   topic_types=types)


def _collect(path: Path, reader, types: dict, max_messages: int, rows: _JointRows) -> dict:
    """Decode what read_episode keeps, counting messages against the limits."""
    parts = {'gripper_commands': [], 'instructions': [], 'tf_static': {}, 'camera_infos': {},
             'image_stamps': {t: [] for t, n in types.items() if n == IMAGE}}
    counts = dict.fromkeys(types, 0)
    for total, (connection, stamp, data) in enumerate(reader.messages(), 1):
        if total > max_messages:
            raise EpisodeError(f'{path} holds more than {max_messages} messages')
        topic, t = connection.topic, stamp / 1e9
        counts[topic] += 1
        where = f'{path} {topic}'
        if topic in parts['image_stamps']:
            parts['image_stamps'][topic].append(stamp)
        elif topic == topics.JOINT_STATES:
            rows.add(t, _decode(JOINT_STATE, data, where))
        elif topic == topics.GRIPPER_TRAJECTORY:
            parts['gripper_commands'].append((t, _decode(JOINT_TRAJECTORY, data, where)))
        elif topic == topics.INSTRUCTION:
            parts['instructions'].append(_decode(STRING, data, where).data)
        elif topic == topics.TF_STATIC:
            for transform in _decode(TF_MESSAGE, data, where).transforms:
                parts['tf_static'][transform.child_frame_id] = transform
        elif types[topic] == CAMERA_INFO and topic not in parts['camera_infos']:
            parts['camera_infos'][topic] = _decode(CAMERA_INFO, data, where)
    # A short count means a truncated or spliced file, not a shorter episode.
    declared = {c.topic: c.msgcount for c in reader.connections}
    if counts != declared:
        raise EpisodeError(f'{path}: metadata.yaml declares {declared} messages per topic, '
                           f'the file holds {counts}')
    return parts


class _JointRows:
    """Picks the arm and finger joints out of each JointState by name, one row per message."""

    def __init__(self, where: str, arm_joints: tuple, finger_joints: tuple):
        self.where, self.arm_joints, self.finger_joints = where, arm_joints, finger_joints
        self.columns = {}                 # name tuple -> (arm columns, finger columns)
        self.rows = []                    # (t, position (7,), velocity (7,), gripper width)

    def add(self, t: float, msg) -> None:
        names = tuple(msg.name)
        if names not in self.columns:
            index = {name: i for i, name in enumerate(names)}
            missing = [n for n in self.arm_joints if n not in index]
            fingers = [index[n] for n in self.finger_joints if n in index]
            if missing or not fingers:
                raise EpisodeError(f'{self.where}: a message lacks joints '
                                   f'{missing or list(self.finger_joints)}')
            self.columns[names] = ([index[n] for n in self.arm_joints], fingers)
        arm, fingers = self.columns[names]
        q, dq = np.asarray(msg.position), np.asarray(msg.velocity)
        if len(q) != len(names) or len(dq) != len(names):
            raise EpisodeError(f'{self.where}: {len(names)} names but {len(q)} positions '
                               f'and {len(dq)} velocities')
        self.rows.append((t, q[arm], dq[arm], 2 * q[fingers].mean()))   # width = 2 x finger travel

    def finish(self, gripper_commands: list) -> JointStates:
        if not self.rows:
            raise EpisodeError(f'{self.where}: no messages')
        t, position, velocity, width = (np.array(column) for column in zip(*self.rows))
        if not (np.all(np.isfinite(position)) and np.all(np.isfinite(velocity))):
            raise EpisodeError(f'{self.where}: non-finite positions or velocities')
        return JointStates(t, position, velocity, width, _gripper_open(t, width, gripper_commands))


def _gripper_open(t: np.ndarray, width: np.ndarray, commands: list) -> np.ndarray:
    """(T,) bool: the last gripper command's state at each time, the measured one before any
    (panda.reads_open: a grasped object keeps the fingers apart, short of open)."""
    opened = reads_open(width)
    commanded = [(stamp, np.mean(msg.points[-1].positions) > FINGER_MAX / 2)
                 for stamp, msg in commands if msg.points and len(msg.points[-1].positions)]
    if not commanded:
        return opened
    stamps, states = (np.array(v) for v in zip(*commanded))
    last = np.searchsorted(stamps, t, side='right') - 1
    return np.where(last >= 0, states[np.maximum(last, 0)], opened)


def union_of_seeds(*seed_maps: dict) -> dict[str, list[int]]:
    """{task: [seed, ...]} maps -> their union, sorted: the seeds a fine-tuned checkpoint has seen
    (its own data's and every checkpoint it started from), all of which evaluation must avoid."""
    union: dict[str, set] = {}
    for seeds in seed_maps:
        for task, values in (seeds or {}).items():
            union.setdefault(str(task), set()).update(int(v) for v in values)
    return {task: sorted(values) for task, values in sorted(union.items())}
