"""Camera-stream transport benchmark: our runtime against raw Cyclone DDS.

A publisher process sends two cameras x (640x480 rgb8 colour + 16UC1 depth)
together, as fast as it can, with sensor-data QoS; this process receives.
Each message carries its send time in header.stamp, so latency is measured
end to end on one clock. Three modes, each in its own publisher process:

- ``ours``: Node/Publisher/Subscription of hdp_msgs_py, full CDR encode and
  decode of every message (what our nodes pay).
- ``raw``: the same payload bytes written and taken with cyclonedds' C calls,
  no message objects at all: the ceiling our runtime is measured against.
- ``idl``: cyclonedds-python's own IdlStruct serialiser, for reference.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import struct
import subprocess
import sys
import time

import numpy as np

STREAMS = ('/camera/front/color/image_raw', '/camera/front/aligned_depth_to_color/image_raw',
           '/camera/side/color/image_raw', '/camera/side/aligned_depth_to_color/image_raw')
_STAMP_OFFSET = 4        # header.stamp.sec/nanosec are the first 8 bytes after the CDR header
_STAMP = struct.Struct('<iI')


def make_images(width: int, height: int) -> list:
    """One Image per stream: rgb8 for colour, 16UC1 (mm) for depth, random content."""
    from .msg import Image
    rng = np.random.default_rng(0)
    images = []
    for topic in STREAMS:
        if 'depth' in topic:
            pixels = rng.integers(300, 2000, (height, width), dtype=np.uint16)
            images.append(Image(height=height, width=width, encoding='16UC1', step=width * 2,
                                data=pixels.tobytes()))
        else:
            pixels = rng.integers(0, 255, (height, width, 3), dtype=np.uint8)
            images.append(Image(height=height, width=width, encoding='rgb8', step=width * 3,
                                data=pixels.tobytes()))
    return images


def _stamp_now():
    return divmod(time.time_ns(), 1_000_000_000)


# -- publisher side (runs in the child process) ------------------------------------
def publish(mode: str, seconds: float, width: int, height: int, ready_path: str) -> None:
    from . import dds
    from .msg import Image
    from .topics import SENSOR_QOS
    images = make_images(width, height)
    dds.init(args=[])
    node = dds.Node('bench_publisher')
    if mode == 'ours':
        pubs = [node.create_publisher(Image, topic, SENSOR_QOS) for topic in STREAMS]
        writers = [p._writer for p in pubs]

        def send(i):
            msg = images[i]
            msg.header.stamp.sec, msg.header.stamp.nanosec = _stamp_now()
            pubs[i].publish(msg)
    else:
        from cyclonedds._clayer import ddspy_write
        from cyclonedds.pub import DataWriter

        from . import cdr
        from .dds.idl_types import idl_struct
        from .dds.qos import to_dds
        writers = [DataWriter(node.context.participant, node.context.dds_topic('rt' + t, Image),
                              qos=to_dds(SENSOR_QOS)) for t in STREAMS]
        if mode == 'raw':
            payloads = [bytearray(cdr.serialize(img, pad_to=4)) for img in images]

            def send(i):
                _STAMP.pack_into(payloads[i], _STAMP_OFFSET, *_stamp_now())
                ddspy_write(writers[i]._ref, payloads[i])
        else:
            IdlImage = idl_struct('sensor_msgs/msg/Image')
            samples = [IdlImage(header=_idl_header(), height=img.height,
                                width=img.width, encoding=img.encoding, is_bigendian=0,
                                step=img.step, data=list(img.data)) for img in images]

            def send(i):
                sec, nsec = _stamp_now()
                samples[i].header.stamp.sec, samples[i].header.stamp.nanosec = sec, nsec
                writers[i].write(samples[i])
    # wait until the receiver matched all four streams, then go flat out
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and not all(w.get_matched_subscriptions() for w in writers):
        time.sleep(0.02)
    open(ready_path, 'w').close()
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for i in range(len(STREAMS)):
            send(i)
    node.destroy_node()
    dds.try_shutdown()


def _idl_header():
    from .dds.idl_types import idl_struct
    Header, Time = idl_struct('std_msgs/msg/Header'), idl_struct('builtin_interfaces/msg/Time')
    return Header(stamp=Time(sec=0, nanosec=0), frame_id='')


# -- receiver side ---------------------------------------------------------------------
@dataclasses.dataclass
class StreamStats:
    topic: str
    count: int = 0
    bytes: int = 0
    latencies_ms: list = dataclasses.field(default_factory=list)


def receive(mode: str, seconds: float, width: int, height: int, domain_id: int) -> dict:
    """Start the publisher process, receive for ``seconds``, return the figures."""
    import tempfile

    from . import dds
    from .msg import Image
    from .topics import SENSOR_QOS
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id))
    os.environ['ROS_DOMAIN_ID'] = str(domain_id)
    dds.init(args=[])
    node = dds.Node(f'bench_receiver_{mode}')
    stats = [StreamStats(t) for t in STREAMS]
    measuring = [False]

    def record(i, sec, nsec, size):
        if measuring[0]:
            s = stats[i]
            s.count += 1
            s.bytes += size
            s.latencies_ms.append((time.time_ns() - (sec * 1_000_000_000 + nsec)) / 1e6)

    if mode == 'ours':
        for i, topic in enumerate(STREAMS):
            node.create_subscription(Image, topic, lambda m, i=i: record(
                i, m.header.stamp.sec, m.header.stamp.nanosec, len(m.data)), SENSOR_QOS)
        spin = lambda: dds.spin_once(node, timeout_sec=0.05)   # noqa: E731
    else:
        from cyclonedds._clayer import ddspy_take
        from cyclonedds.core import InstanceState, ReadCondition, SampleState, ViewState, WaitSet
        from cyclonedds.sub import DataReader

        from .dds.qos import to_dds
        mask = SampleState.Any | ViewState.Any | InstanceState.Any
        readers = [DataReader(node.context.participant, node.context.dds_topic('rt' + t, Image),
                              qos=to_dds(SENSOR_QOS)) for t in STREAMS]
        waitset = WaitSet(node.context.participant)
        for r in readers:
            waitset.attach(ReadCondition(r, mask))

        def spin():
            waitset.wait(50_000_000)
            for i, r in enumerate(readers):
                ret = ddspy_take(r._ref, mask, 64)
                for data, info in ([] if isinstance(ret, int) else ret):
                    if info.valid_data:
                        sec, nsec = _STAMP.unpack_from(data, _STAMP_OFFSET)
                        record(i, sec, nsec, len(data))

    with tempfile.TemporaryDirectory() as tmp:
        ready = os.path.join(tmp, 'ready')
        child = subprocess.Popen(
            [sys.executable, '-m', 'hdp_msgs_py.transport_bench', '--role', 'publisher', '--mode', mode,
             '--seconds', str(seconds + 1.0), '--width', str(width), '--height', str(height),
             '--ready', ready], env=env)
        try:
            deadline = time.monotonic() + 30
            while not os.path.exists(ready):
                if time.monotonic() > deadline or child.poll() is not None:
                    raise RuntimeError(f'benchmark publisher ({mode}) did not start')
                spin()
            warmup_end = time.monotonic() + 0.5
            while time.monotonic() < warmup_end:
                spin()
            measuring[0] = True
            start = time.monotonic()
            while time.monotonic() - start < seconds:
                spin()
            elapsed = time.monotonic() - start
            measuring[0] = False
        finally:
            child.wait(timeout=30)
    node.destroy_node()
    dds.try_shutdown()
    return summarise(mode, stats, elapsed)


def summarise(mode: str, stats: list[StreamStats], elapsed: float) -> dict:
    all_latencies = np.concatenate([np.asarray(s.latencies_ms) for s in stats]) if any(
        s.latencies_ms for s in stats) else np.zeros(0)
    return {
        'mode': mode,
        'seconds': round(elapsed, 3),
        'streams': {s.topic: {'hz': round(s.count / elapsed, 2),
                              'p50_ms': _pct(s.latencies_ms, 50), 'p99_ms': _pct(s.latencies_ms, 99)}
                    for s in stats},
        'min_hz': round(min(s.count for s in stats) / elapsed, 2),
        'latency_p50_ms': _pct(all_latencies, 50),
        'latency_p99_ms': _pct(all_latencies, 99),
        'throughput_mb_s': round(sum(s.bytes for s in stats) / elapsed / 1e6, 2),
    }


def _pct(values, q) -> float | None:
    return round(float(np.percentile(values, q)), 2) if len(values) else None


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description='benchmark publisher process (internal)')
    parser.add_argument('--role', choices=['publisher'], required=True)
    parser.add_argument('--mode', choices=['ours', 'raw', 'idl'], required=True)
    parser.add_argument('--seconds', type=float, required=True)
    parser.add_argument('--width', type=int, required=True)
    parser.add_argument('--height', type=int, required=True)
    parser.add_argument('--ready', required=True)
    args = parser.parse_args(argv)
    publish(args.mode, args.seconds, args.width, args.height, args.ready)


if __name__ == '__main__':
    main()
