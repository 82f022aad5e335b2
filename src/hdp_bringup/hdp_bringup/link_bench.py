"""`hdp bench link`: the two cameras across a network link, robot host to workstation.

Root only: it makes two network namespaces joined by a veth pair (netns), the "robot" and the
"workstation", with the link limited by tbf to each rate asked, and removes them however it
ends. Discovery crosses the link the ROS 2 Jazzy way (ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET, or
ROS_STATIC_PEERS), with the Fast DDS profile ros.init() gives for it.

For each link rate and transport (raw, compressed) it measures, in namespaces of their own:

- at the workstation, per stream (front and side, colour and depth): the rate frames arrive,
  their age (arrival minus stamp; both namespaces share the wall clock) p50 / p95, and the
  frames lost (published in the measured window, never arrived); the bytes that came over the
  link (the veth's counters) and the UDP datagrams dropped there for a full socket receive
  buffer (/proc/net/snmp); what all streams at the full rate would need (their payload);
- on the robot host, the publisher's CPU (utime + stime from /proc over the window, 100% = one
  core) and, compressed, each frame's encode time (JPEG colour, 16-bit PNG depth).

The robot host replays a few frames the simulator's cameras rendered once, at the camera rate,
encoded per frame with the bridge's codec (link_streams), because PyBullet cannot render two
640x480 cameras at 30 Hz on a small machine: transport is measured apart from rendering.
With --episodes it also runs the same episodes with the graph split across the hosts (the bridge
on the robot, planner and controller on the workstation taking compressed frames) and on one
host (link_episodes), and compares their success.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from . import netns
from .demo.cli import pick_domain
from .link_streams import STREAMS

LINKS_MBIT = (1000.0, 100.0)
TRANSPORTS = ('raw', 'compressed')
# The goal (issue 42): both cameras at 30 Hz at the workstation over 100 Mbit/s, compressed.
GOAL_HZ, GOAL_LINK_MBIT, GOAL_TRANSPORT = 30.0, 100.0, 'compressed'
GOAL_SHARE = 0.98         # of GOAL_HZ every stream must reach: under 2% of the frames lost
STREAM_TIMEOUT_S = 120.0  # for one configuration beyond its seconds: discovery, the frames' wait


def configure(parser) -> None:
    """Measure the cameras across a network link (root: two network namespaces, a veth, tbf).

    For raw and compressed frames (JPEG colour, 16-bit PNG depth) over links of 1 Gbit/s and
    100 Mbit/s: the rate and age (p50/p95) of both cameras' colour and depth at the workstation,
    the frames lost, the bytes on the link, and on the robot host the CPU the publisher takes
    and each frame's encode time. The robot host replays frames the simulator rendered once, at
    the camera rate, as sim_bridge_node publishes them. --episodes N also runs N episodes per
    task with the graph split across the hosts and on one host, same seeds, and compares
    their success.
    """
    parser.add_argument('--seconds', type=float, default=10.0, help='measured per configuration (default 10)')
    parser.add_argument('--warmup', type=float, default=2.0, help='published before measuring (default 2 s)')
    parser.add_argument('--width', type=int, default=640, help='camera width (default 640)')
    parser.add_argument('--height', type=int, default=480, help='camera height (default 480)')
    parser.add_argument('--rate-hz', type=float, default=GOAL_HZ, help='camera rate (default 30)')
    parser.add_argument('--links', default=','.join(f'{rate:g}' for rate in LINKS_MBIT),
                        help='link rates in Mbit/s, comma-separated (default 1000,100)')
    parser.add_argument('--transports', default=','.join(TRANSPORTS), help='raw,compressed (default both)')
    parser.add_argument('--discovery', choices=netns.DISCOVERY_MODES, default='subnet',
                        help='subnet: ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET (default); '
                             'static_peers: ROS_STATIC_PEERS')
    parser.add_argument('--frames', type=int, default=4,
                        help='frames rendered per camera, replayed in turn (default 4)')
    parser.add_argument('--sensor-profile', choices=('d415', 'ideal'), default='d415',
                        help="the rendered frames' sensor model (default d415: noise and holes, as a real camera)")
    parser.add_argument('--jpeg-quality', type=int, default=95,
                        help="compressed colour's JPEG quality (the bridge's default 95)")
    parser.add_argument('--png-level', type=int, default=3, help="compressedDepth's PNG level (the bridge's default 3)")
    parser.add_argument('--episodes', type=int, default=0,
                        help='also run N episodes per task split across the hosts and on one host (default 0: none)')
    parser.add_argument('--tasks', default='reach_target,open_drawer',
                        help='tasks of --episodes (default reach_target,open_drawer)')
    parser.add_argument('--seed', type=int, default=1000, help='first seed of --episodes (default 1000)')
    parser.add_argument('--episode-link', type=float, default=GOAL_LINK_MBIT,
                        help='link rate of the split episodes, Mbit/s (default 100)')
    parser.add_argument('--episode-timeout', type=float, default=300.0, help='per episode, s (default 300)')
    parser.add_argument('-p', '--param', action='append', default=[], metavar='NODE:NAME:=VALUE',
                        help='node parameter for both graphs of --episodes (hdp launch -p; repeatable)')
    parser.add_argument('--out', type=Path, default=Path('link_out'),
                        help='rendered frames and process logs go here (default link_out/)')
    parser.add_argument('--json', action='store_true', help='print the report as JSON')
    parser.set_defaults(func=run)


def parse_list(text: str, allowed=None, convert=str) -> list:
    """Comma-separated values, each converted and (with ``allowed``) one of those; ValueError."""
    values = [convert(item.strip()) for item in text.split(',') if item.strip()]
    bad = [v for v in values if allowed is not None and v not in allowed]
    if not values or bad:
        of = f' of {", ".join(allowed)}' if allowed else ''
        raise ValueError(f'expected a comma-separated list{of}, got {text!r}')
    return values


def check_args(args) -> str | None:
    """What is wrong with the arguments, or None."""
    from hdp_data.instructions import TASKS
    try:
        links = parse_list(args.links, convert=float)
        parse_list(args.transports, TRANSPORTS)
        tasks = parse_list(args.tasks)
    except ValueError as err:
        return str(err)
    unknown = [t for t in tasks if t not in TASKS]
    checks = [(not unknown, f'unknown task(s) {unknown}; tasks: {", ".join(TASKS)}'),
              (min(links) > 0 and args.episode_link > 0, 'link rates must be > 0 Mbit/s'),
              (args.seconds > 0 and args.warmup >= 0 and args.rate_hz > 0, '--seconds and --rate-hz must be > 0'),
              (args.width > 0 and args.height > 0 and args.frames > 0, '--width, --height and --frames must be > 0'),
              (1 <= args.jpeg_quality <= 100 and 0 <= args.png_level <= 9, '--jpeg-quality 1-100, --png-level 0-9'),
              (args.episodes >= 0 and args.seed >= 0, '--episodes and --seed must be >= 0')]
    return next((why for ok, why in checks if not ok), None)


class MeasurementFailed(Exception):
    """A configuration gave no result (a process failed or timed out); the message says which."""


def run(args) -> int:
    problem = check_args(args)
    if problem:
        print(f'hdp bench link: {problem}', file=sys.stderr)
        return 2
    reason = netns.unavailable()
    if reason:
        print(f'hdp bench link: cannot make the two hosts: {reason}', file=sys.stderr)
        return 2

    def say(text: str) -> None:
        print(f'[link] {text}', file=sys.stderr if args.json else sys.stdout, flush=True)
    logs = args.out / 'logs'
    logs.mkdir(parents=True, exist_ok=True)
    domain, _ = pick_domain(os.environ, random.Random())
    load_before = os.getloadavg()[0]
    frames = args.out / 'frames.npz'
    configurations, episodes, code = [], None, 0
    try:
        say(f'rendering {args.frames} frame(s) of both cameras at {args.width}x{args.height} '
            f'({args.sensor_profile}) ...')
        render_frames(frames, args, logs)
        for link in parse_list(args.links, convert=float):
            for transport in parse_list(args.transports, TRANSPORTS):
                say(f'{link:g} Mbit/s, {transport}: {args.warmup:g} s warm-up, {args.seconds:g} s measured ...')
                configurations.append(measure_cameras(args, frames, link, transport, domain, logs))
                say(progress_line(configurations[-1]))
        if args.episodes:
            from .link_episodes import compare_episodes
            episodes = compare_episodes(args, domain, logs, say)
    except netns.NamespacesUnavailable as why:
        print(f'hdp bench link: cannot make the two hosts: {why}', file=sys.stderr)
        return 2
    except MeasurementFailed as why:
        say(f'{why} (logs: {logs}/)')
        code = 1
    except KeyboardInterrupt:
        say('interrupted: the namespaces and processes are gone')
        code = 130
    report = summarise(settings_of(args), configurations, episodes,
                       {'cpus': os.cpu_count(), 'load_1min_before': round(load_before, 2),
                        'load_1min_after': round(os.getloadavg()[0], 2)})
    print(json.dumps(report, indent=1) if args.json else format_report(report), flush=True)
    return code


def settings_of(args) -> dict:
    """The settings a reader needs beside the figures."""
    return {'width': args.width, 'height': args.height, 'rate_hz': args.rate_hz, 'seconds': args.seconds,
            'warmup_s': args.warmup, 'discovery': args.discovery, 'frames': args.frames,
            'sensor_profile': args.sensor_profile, 'jpeg_quality': args.jpeg_quality, 'png_level': args.png_level}


def measure_cameras(args, frames: Path, link_mbit: float, transport: str, domain: int, logs: Path) -> dict:
    """One configuration in namespaces of its own: the publisher on the robot, the subscriber on
    the workstation; the report of camera_report()."""
    streams = [sys.executable, '-m', 'hdp_bringup.link_streams']
    name = f'{link_mbit:g}mbit_{transport}'
    with netns.two_hosts(rate_mbit=link_mbit) as (robot, workstation), \
            open(logs / f'{name}_robot.log', 'w') as robot_log, open(logs / f'{name}_workstation.log', 'w') as ws_log:
        subscriber = workstation.popen([*streams, 'subscribe', '--transport', transport],
                                       env=netns.discovery_env(args.discovery, domain, robot),
                                       stdout=subprocess.PIPE, stderr=ws_log, text=True)
        publisher = robot.popen([*streams, 'publish', '--frames', str(frames), '--transport', transport,
                                 '--rate-hz', str(args.rate_hz), '--warmup-s', str(args.warmup),
                                 '--seconds', str(args.seconds), '--jpeg-quality', str(args.jpeg_quality),
                                 '--png-level', str(args.png_level)],
                                env=netns.discovery_env(args.discovery, domain, workstation),
                                stdout=subprocess.PIPE, stderr=robot_log, text=True)
        watchdog = _kill_after(publisher, args.warmup + args.seconds + STREAM_TIMEOUT_S)
        if publisher.stdout.readline().strip() != 'measuring':
            raise MeasurementFailed(f'{name}: the publisher ended before measuring')
        received_before, udp_before = workstation.link_bytes()[0], workstation.udp_counters()
        line = publisher.stdout.readline()
        received = workstation.link_bytes()[0] - received_before
        buffer_drops = workstation.udp_counters()['RcvbufErrors'] - udp_before['RcvbufErrors']
        watchdog.cancel()
        if not line.strip():
            raise MeasurementFailed(f'{name}: the publisher gave no result')
        time.sleep(0.5)                      # the last images still on their way
        subscriber.send_signal(signal.SIGINT)
        try:
            out, _ = subscriber.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            raise MeasurementFailed(f'{name}: the subscriber did not end within 30 s of SIGINT') from None
    if not out.strip():
        raise MeasurementFailed(f'{name}: the subscriber gave no result')
    return camera_report(link_mbit, transport, json.loads(line), json.loads(out.strip().splitlines()[-1]),
                         received, buffer_drops)


def render_frames(frames: Path, args, logs: Path) -> None:
    """The frames the robot host replays, rendered in a process of its own (PyBullet prints on stdout)."""
    with open(logs / 'render.log', 'w') as log:
        done = subprocess.run([sys.executable, '-m', 'hdp_bringup.link_streams', 'render', '--frames', str(frames),
                               '--width', str(args.width), '--height', str(args.height), '--count', str(args.frames),
                               '--sensor-profile', args.sensor_profile], stdout=log, stderr=subprocess.STDOUT)
    if done.returncode != 0:
        raise MeasurementFailed(f'rendering the frames failed (exit {done.returncode})')


def _kill_after(process, seconds: float) -> threading.Timer:
    """A hung process is killed, so that the bench ends and says which configuration failed."""
    timer = threading.Timer(seconds, process.kill)
    timer.daemon = True
    timer.start()
    return timer


# -- statistics (pure) -------------------------------------------------------------------------
def percentile(values, q: float) -> float | None:
    return round(float(np.percentile(values, q)), 2) if len(values) else None


def stream_stats(stamps_ns: list[int], arrivals: list, window_s: float) -> dict:
    """One stream's arrivals ([stamp, arrival] ns) of the frames published at ``stamps_ns`` over
    ``window_s``: the rate they arrived at, their age p50/p95 (ms) and how many never came.
    Frames from before the window (the warm-up) are not counted; a frame counts once."""
    published = set(stamps_ns)
    first_arrival = {}
    for stamp, arrival in arrivals:
        if stamp in published:
            first_arrival.setdefault(stamp, arrival)
    ages_ms = [(arrival - stamp) / 1e6 for stamp, arrival in first_arrival.items()]
    return {'published': len(published), 'received': len(first_arrival),
            'lost': len(published) - len(first_arrival),
            'hz': round(len(first_arrival) / window_s, 2) if window_s > 0 else None,
            'age_p50_ms': percentile(ages_ms, 50), 'age_p95_ms': percentile(ages_ms, 95), 'ages_ms': ages_ms}


def camera_report(link_mbit: float, transport: str, published: dict, received: dict, link_bytes: int,
                  buffer_drops: int) -> dict:
    """One configuration's figures from the publisher's and the subscriber's JSON, the bytes the
    workstation's end of the link received over the window and the UDP datagrams it dropped
    there for a full socket receive buffer."""
    window_s = published['window_s']
    stamps = published['stamps_ns']
    streams = {s: stream_stats(stamps, received['arrivals'].get(s, []), window_s) for s in STREAMS}
    ages = [age for stats in streams.values() for age in stats.pop('ages_ms')]
    for stream, stats in streams.items():
        stats['payload_kb'] = round(published['payload_bytes'][stream] / max(1, len(stamps)) / 1e3, 1)
    frame_kb = sum(stats['payload_kb'] for stats in streams.values())
    return {
        'link_mbit': link_mbit, 'transport': transport,
        'published_hz': round(len(stamps) / window_s, 2),
        'min_hz': min(stats['hz'] for stats in streams.values()),
        'lost': sum(stats['lost'] for stats in streams.values()),
        'published': sum(stats['published'] for stats in streams.values()),
        'undecodable': received.get('undecodable', 0),
        'age_p50_ms': percentile(ages, 50), 'age_p95_ms': percentile(ages, 95),
        'link_mbit_s': round(link_bytes * 8 / published['elapsed_s'] / 1e6, 1),
        'udp_receive_buffer_drops': buffer_drops,
        # What every stream at the full camera rate would put on the link (messages alone, no
        # headers): whether the link could carry it, whatever the CPUs managed.
        'payload_mbit_s_at_rate': round(frame_kb * 8e3 * published['rate_hz'] / 1e6, 1),
        'publisher_cpu_percent': round(100.0 * published['cpu_s'] / published['elapsed_s'], 1),
        'encode_ms': {codec: {'p50': percentile(times, 50), 'p95': percentile(times, 95), 'frames': len(times)}
                      for codec, times in published['encode_ms'].items() if times},
        'streams': streams,
    }


def goal(configurations: list[dict]) -> dict:
    """Whether every stream arrived at GOAL_HZ (less GOAL_SHARE) over GOAL_LINK_MBIT, GOAL_TRANSPORT."""
    measured = next((c for c in configurations
                     if c['link_mbit'] == GOAL_LINK_MBIT and c['transport'] == GOAL_TRANSPORT), None)
    text = f'{GOAL_HZ:g} Hz of both cameras at the workstation over {GOAL_LINK_MBIT:g} Mbit/s {GOAL_TRANSPORT}'
    if measured is None:
        return {'goal': text, 'met': None}
    return {'goal': text, 'met': measured['min_hz'] >= GOAL_SHARE * GOAL_HZ, 'min_hz': measured['min_hz'],
            'lost': measured['lost'], 'published': measured['published']}


def compression_cost(configurations: list[dict]) -> dict:
    """link Mbit/s -> the publisher's CPU compressed minus raw (percent of a core), where both ran."""
    cpu = {(c['link_mbit'], c['transport']): c['publisher_cpu_percent'] for c in configurations}
    return {f'{link:g}': round(cpu[(link, 'compressed')] - cpu[(link, 'raw')], 1)
            for link, transport in cpu if transport == 'raw' and (link, 'compressed') in cpu}


def summarise(settings: dict, configurations: list[dict], episodes: dict | None, machine: dict) -> dict:
    return {'settings': settings, 'machine': machine, 'cameras': configurations, 'goal': goal(configurations),
            'compression_cpu_percent': compression_cost(configurations), 'episodes': episodes}


# -- the table (pure) ---------------------------------------------------------------------------
def progress_line(c: dict) -> str:
    return (f"{c['link_mbit']:g} Mbit/s {c['transport']}: published {c['published_hz']:.1f} Hz, arrived "
            f"{c['min_hz']:.1f} Hz (slowest stream), lost {c['lost']}/{c['published']} "
            f"({c['udp_receive_buffer_drops']} datagrams dropped at a full receive buffer), age p50 "
            f"{_ms(c['age_p50_ms'])} / p95 {_ms(c['age_p95_ms'])} ms, {c['link_mbit_s']:.1f} Mbit/s on the link, "
            f"publisher CPU {c['publisher_cpu_percent']:.0f}%")


def _ms(value) -> str:
    return '-' if value is None else f'{value:.1f}'


def _encode(c: dict) -> str:
    times = c['encode_ms']
    if not times:
        return '-'
    return ', '.join(f"{codec.upper()} {_ms(t['p50'])} / {_ms(t['p95'])}" for codec, t in times.items())


def format_report(report: dict) -> str:
    s = report['settings']
    m = report['machine']
    lines = [f"2 cameras x (rgb8 colour + 16UC1 depth) at {s['width']}x{s['height']}, {s['rate_hz']:g} Hz; "
             f"{s['frames']} frame(s) per camera rendered once ({s['sensor_profile']}) and replayed; "
             f"{s['seconds']:g} s measured per row; discovery {s['discovery']}; JPEG quality {s['jpeg_quality']}, "
             f"PNG level {s['png_level']}",
             f"machine: {m['cpus']} CPUs, load (1 min) {m['load_1min_before']} before, {m['load_1min_after']} after",
             '',
             '| link | transport | published Hz | arrived Hz (slowest stream) | lost | UDP receive-buffer drops '
             f"| age p50 / p95 ms | on the link Mbit/s | payload at {s['rate_hz']:g} Hz, Mbit/s | publisher CPU "
             '| encode p50 / p95 ms |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    for c in report['cameras']:
        lines.append(f"| {c['link_mbit']:g} Mbit/s | {c['transport']} | {c['published_hz']:.1f} | {c['min_hz']:.1f} "
                     f"| {c['lost']}/{c['published']} | {c['udp_receive_buffer_drops']} "
                     f"| {_ms(c['age_p50_ms'])} / {_ms(c['age_p95_ms'])} "
                     f"| {c['link_mbit_s']:.1f} | {c['payload_mbit_s_at_rate']:.1f} "
                     f"| {c['publisher_cpu_percent']:.0f}% | {_encode(c)} |")
    g = report['goal']
    verdict = ('not measured' if g['met'] is None else
               f"{'met' if g['met'] else 'not met'} (slowest stream {g['min_hz']:.1f} Hz, "
               f"lost {g['lost']}/{g['published']})")
    lines += ['', f"goal, {g['goal']}: {verdict}"]
    for link, percent in report['compression_cpu_percent'].items():
        lines.append(f'compression on the robot host at {link} Mbit/s: {percent:+.0f}% of a core '
                     '(publisher CPU, compressed minus raw)')
    if report['episodes']:
        lines += ['', *format_episodes(report['episodes'])]
    return '\n'.join(lines)


def format_episodes(episodes: dict) -> list[str]:
    lines = [f"| task | one host | split ({episodes['link_mbit']:g} Mbit/s, compressed) |", '|---|---|---|']
    for task, counts in episodes['tasks'].items():
        lines.append(f"| {task} | {counts['one_host']}/{counts['episodes']} | {counts['split']}/{counts['episodes']} |")
    differ = episodes['differ']
    lines.append('seeds that ended differently: ' + (', '.join(differ) if differ else 'none'))
    lines += [f'{setup}: {problem}' for setup, problem in episodes['problems'].items() if problem]
    return lines
