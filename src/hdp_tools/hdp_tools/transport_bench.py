"""Camera-stream transport benchmark: rclpy on Fast DDS, against its own ceiling.

A publisher process sends two cameras x (640x480 rgb8 colour + 16UC1 depth)
together, as fast as it can, with sensor-data QoS (best effort); this process
receives. Each message carries its send time in header.stamp, so latency is
measured end to end on one clock. Each mode has its own publisher process:

- ``rclpy``: rclpy + Fast DDS with full message objects: a sensor_msgs/Image
  built with numpy_to_image and published from Python, received as a Python
  message and viewed with image_to_numpy. What the project's nodes pay.
- ``raw``: the same payload bytes through the same middleware with no Python
  message objects: bytes serialised once, stamp patched in place, published
  with ``publish(bytes)`` and taken by a ``raw=True`` subscription. The
  ceiling of the rclpy path.
- ``cyclone``: the same payload bytes written and taken with Cyclone DDS's C
  calls, for the other middleware beside Fast DDS.

Figures move with glibc's malloc. With its defaults, whether a received frame
lands in fresh, page-faulting memory depends on the allocation history (from
~0 to ~270 faults a frame between runs); MALLOC_MMAP_THRESHOLD_ alone makes that
more frequent (it pins the trim threshold at 128 KiB); adding
MALLOC_TRIM_THRESHOLD_=268435456 to it removes the faults.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import os
import struct
import subprocess
import sys
import tempfile
import time

import numpy as np

MODES = ('rclpy', 'raw', 'cyclone')
STREAMS = ('/camera/front/color/image_raw', '/camera/front/aligned_depth_to_color/image_raw',
           '/camera/side/color/image_raw', '/camera/side/aligned_depth_to_color/image_raw')
_STAMP_OFFSET = 4        # header.stamp.sec/nanosec are the first 8 bytes after the CDR header
_STAMP = struct.Struct('<iI')
TARGET_HZ = 30.0          # targets each mode is checked against: Hz on every stream, p99 latency
TARGET_P99_MS = 30.0
_SPIN_S = 0.05
# Cyclone on loopback as ROS's LOCALHOST discovery range has it (unicast to
# localhost peers: multicast may be absent), with 64 kB datagrams and 8 MB socket
# buffers: with the defaults best-effort frames are dropped piecemeal.
_CYCLONE_CONFIG = ('<CycloneDDS><Domain Id="any"><General>'
                   '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
                   '<AllowMulticast>false</AllowMulticast><MaxMessageSize>65500B</MaxMessageSize>'
                   '</General><Discovery><ParticipantIndex>auto</ParticipantIndex>'
                   '<Peers><Peer Address="localhost"/></Peers></Discovery><Internal>'
                   '<SocketReceiveBufferSize min="default" max="8MB"/>'
                   '<SocketSendBufferSize min="default" max="8MB"/>'
                   '</Internal></Domain></CycloneDDS>')


def make_images(width: int, height: int) -> list:
    """One Image per stream: rgb8 for colour, 16UC1 (mm) for depth, random content."""
    from hdp_msgs_py.conversions import numpy_to_image
    rng = np.random.default_rng(0)
    return [numpy_to_image(rng.integers(300, 2000, (height, width), dtype=np.uint16), '16UC1')
            if 'depth' in topic else
            numpy_to_image(rng.integers(0, 255, (height, width, 3), dtype=np.uint8), 'rgb8')
            for topic in STREAMS]


def _stamp_now() -> tuple[int, int]:
    return divmod(time.time_ns(), 1_000_000_000)


@contextlib.contextmanager
def _rclpy_node(name: str, domain_id: int):
    import rclpy

    from hdp_ros import ros
    context = rclpy.Context()
    ros.init(context=context, domain_id=domain_id)     # the Fast DDS profile the nodes run with
    node = rclpy.create_node(name, context=context)
    try:
        yield node
    finally:
        node.destroy_node()
        context.try_shutdown()


@functools.cache
def _cyclone_image_type():
    """sensor_msgs/Image for Cyclone, which drops received payloads that do not parse as it.

    Samples never go through its (slow, list-based) Python serialiser: the bench
    writes and takes the CDR bytes.
    """
    from cyclonedds.idl import make_idl_struct, types
    time_ = make_idl_struct('Time_', 'builtin_interfaces::msg::dds_::Time_',
                            {'sec': types.int32, 'nanosec': types.uint32})
    header = make_idl_struct('Header_', 'std_msgs::msg::dds_::Header_', {'stamp': time_, 'frame_id': str})
    return make_idl_struct('Image_', 'sensor_msgs::msg::dds_::Image_', {
        'header': header, 'height': types.uint32, 'width': types.uint32, 'encoding': str,
        'is_bigendian': types.uint8, 'step': types.uint32, 'data': types.sequence[types.uint8]})


@contextlib.contextmanager
def _cyclone_endpoints(domain_id: int, endpoint):
    """Yields (participant, a reader or writer per stream), sensor-data QoS."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.topic import Topic
    domain = Domain(domain_id, _CYCLONE_CONFIG)
    participant = DomainParticipant(domain_id)
    qos = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
    yield participant, [endpoint(participant, Topic(participant, 'rt' + topic, _cyclone_image_type()), qos=qos)
                        for topic in STREAMS]
    del domain    # deleting it deletes all in it, so it is held until the endpoints are done


# -- publisher side (runs in the child process) ------------------------------------
@contextlib.contextmanager
def _publisher(mode: str, images: list, domain_id: int):
    """Yields (send(stream index), matched()) for ``mode``."""
    from rclpy.serialization import serialize_message
    # Payload bytes of the raw modes: header + CDR exactly as rclpy sends them.
    payloads = [bytearray(serialize_message(img)) for img in images]
    if mode == 'cyclone':
        from cyclonedds._clayer import ddspy_write
        from cyclonedds.pub import DataWriter

        def send(i):
            _STAMP.pack_into(payloads[i], _STAMP_OFFSET, *_stamp_now())
            ddspy_write(writers[i]._ref, payloads[i])

        with _cyclone_endpoints(domain_id, DataWriter) as (_, writers):
            yield send, lambda: all(w.get_matched_subscriptions() for w in writers)
        return
    from hdp_msgs_py.msg import Image
    from hdp_msgs_py.topics import SENSOR_QOS
    with _rclpy_node('bench_publisher', domain_id) as node:
        pubs = [node.create_publisher(Image, topic, SENSOR_QOS) for topic in STREAMS]

        def send_message(i):
            images[i].header.stamp.sec, images[i].header.stamp.nanosec = _stamp_now()
            pubs[i].publish(images[i])

        def send_bytes(i):
            _STAMP.pack_into(payloads[i], _STAMP_OFFSET, *_stamp_now())
            pubs[i].publish(bytes(payloads[i]))    # publish() takes bytes only: one copy

        yield (send_message if mode == 'rclpy' else send_bytes,
               lambda: all(p.get_subscription_count() for p in pubs))


def publish(mode: str, seconds: float, width: int, height: int, domain_id: int, ready_path: str) -> None:
    images = make_images(width, height)
    with _publisher(mode, images, domain_id) as (send, matched):
        # wait until the receiver matched all four streams, then go flat out
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and not matched():
            time.sleep(0.02)
        open(ready_path, 'w').close()
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            for i in range(len(STREAMS)):
                send(i)


# -- receiver side ---------------------------------------------------------------------
@dataclasses.dataclass
class StreamStats:
    topic: str
    count: int = 0
    bytes: int = 0
    latencies_ms: list = dataclasses.field(default_factory=list)


class _Recorder:
    """Counts what arrives while ``measuring``; warm-up traffic is dropped."""

    def __init__(self):
        self.stats = [StreamStats(t) for t in STREAMS]
        self.measuring = False

    def __call__(self, i: int, sec: int, nsec: int, size: int) -> None:
        if self.measuring:
            s = self.stats[i]
            s.count += 1
            s.bytes += size
            s.latencies_ms.append((time.time_ns() - (sec * 1_000_000_000 + nsec)) / 1e6)


@contextlib.contextmanager
def _receiver(mode: str, domain_id: int, record: _Recorder):
    """Yields spin(): wait up to _SPIN_S for data and hand what came to ``record``."""
    if mode == 'cyclone':
        from cyclonedds.sub import DataReader
        with _cyclone_endpoints(domain_id, DataReader) as (participant, readers):
            yield _cyclone_spin(participant, readers, record)
        return
    from rclpy.executors import SingleThreadedExecutor

    from hdp_msgs_py.conversions import image_to_numpy
    from hdp_msgs_py.msg import Image
    from hdp_msgs_py.topics import SENSOR_QOS

    def on_message(i, msg):
        image_to_numpy(msg)     # what every image-consuming node does first
        record(i, msg.header.stamp.sec, msg.header.stamp.nanosec, len(msg.data))

    def on_bytes(i, data):
        record(i, *_STAMP.unpack_from(data, _STAMP_OFFSET), len(data))

    callback = on_message if mode == 'rclpy' else on_bytes
    with _rclpy_node(f'bench_receiver_{mode}', domain_id) as node:
        for i, topic in enumerate(STREAMS):
            node.create_subscription(Image, topic, functools.partial(callback, i), SENSOR_QOS,
                                     raw=mode == 'raw')
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        try:
            yield lambda: executor.spin_once(timeout_sec=_SPIN_S)
        finally:
            executor.shutdown()


def _cyclone_spin(participant, readers: list, record: _Recorder):
    from cyclonedds._clayer import ddspy_take
    from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
    mask = SampleState.Any | ViewState.Any | InstanceState.Any
    waitset = WaitSet(participant)
    for r in readers:
        waitset.attach(ReadCondition(r, mask))

    def spin():
        waitset.wait(int(_SPIN_S * 1e9))
        for i, r in enumerate(readers):
            ret = ddspy_take(r._ref, mask, 64)
            for data, info in ([] if isinstance(ret, int) else ret):
                if info.valid_data:
                    record(i, *_STAMP.unpack_from(data, _STAMP_OFFSET), len(data))
    return spin


@contextlib.contextmanager
def _publisher_process(mode: str, seconds: float, width: int, height: int, domain_id: int):
    """Starts the publisher; yields ready(), true once it matched and started sending."""
    with tempfile.TemporaryDirectory() as tmp:
        ready = os.path.join(tmp, 'ready')
        child = subprocess.Popen(
            [sys.executable, '-m', 'hdp_tools.transport_bench', '--mode', mode, '--seconds', str(seconds),
             '--width', str(width), '--height', str(height), '--domain-id', str(domain_id), '--ready', ready])

        def is_ready():
            if child.poll() is not None:
                raise RuntimeError(f'benchmark publisher ({mode}) exited with {child.returncode}')
            return os.path.exists(ready)
        try:
            yield is_ready
        finally:
            child.wait(timeout=30)


def receive(mode: str, seconds: float, width: int, height: int, domain_id: int) -> dict:
    """Start the publisher process, receive for ``seconds``, return the figures."""
    record = _Recorder()
    warmup_s = 0.5
    with _receiver(mode, domain_id, record) as spin, _publisher_process(
            mode, seconds + warmup_s + 0.5, width, height, domain_id) as ready:
        deadline = time.monotonic() + 30
        while not ready():
            if time.monotonic() > deadline:
                raise RuntimeError(f'benchmark publisher ({mode}) did not match within 30 s')
            spin()
        _spin_for(spin, warmup_s)
        record.measuring = True
        elapsed = _spin_for(spin, seconds)
        record.measuring = False
    return summarise(mode, record.stats, elapsed)


def _spin_for(spin, seconds: float) -> float:
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        spin()
    return time.monotonic() - start


def summarise(mode: str, stats: list[StreamStats], elapsed: float) -> dict:
    all_latencies = np.concatenate([np.asarray(s.latencies_ms) for s in stats])
    min_hz = round(min(s.count for s in stats) / elapsed, 2)
    p99 = _pct(all_latencies, 99)
    return {
        'mode': mode,
        'seconds': round(elapsed, 3),
        'streams': {s.topic: {'hz': round(s.count / elapsed, 2), 'received': s.count,
                              'p50_ms': _pct(s.latencies_ms, 50), 'p99_ms': _pct(s.latencies_ms, 99)}
                    for s in stats},
        'min_hz': min_hz,
        'latency_p50_ms': _pct(all_latencies, 50),
        'latency_p99_ms': p99,
        'throughput_mb_s': round(sum(s.bytes for s in stats) / elapsed / 1e6, 2),
        'targets': {f'min_hz >= {TARGET_HZ:g}': min_hz >= TARGET_HZ,
                    f'p99 <= {TARGET_P99_MS:g} ms': p99 is not None and p99 <= TARGET_P99_MS},
    }


def _pct(values, q) -> float | None:
    return round(float(np.percentile(values, q)), 2) if len(values) else None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description='benchmark publisher process (internal)')
    parser.add_argument('--mode', choices=MODES, required=True)
    parser.add_argument('--seconds', type=float, required=True)
    parser.add_argument('--width', type=int, required=True)
    parser.add_argument('--height', type=int, required=True)
    parser.add_argument('--domain-id', type=int, required=True)
    parser.add_argument('--ready', required=True)
    args = parser.parse_args(argv)
    publish(args.mode, args.seconds, args.width, args.height, args.domain_id, args.ready)


if __name__ == '__main__':
    main()
