"""`hdp collect` and `hdp render`: the sim bridge's commands."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path


def _tasks(text: str) -> list[str]:
    from hdp_data.instructions import task_names
    try:
        return task_names(text)
    except ValueError as err:
        raise SystemExit(str(err)) from None


def configure_collect(parser) -> None:
    """Record scripted demonstrations as rosbag2 (MCAP) episodes, with a per-task summary."""
    parser.add_argument('--tasks', required=True, help='comma-separated task names, or "all"')
    parser.add_argument('--episodes', type=int, required=True, help='episodes per task')
    parser.add_argument('--seed-start', type=int, default=0, help='first seed (default 0)')
    parser.add_argument('--out', type=Path, required=True, help='directory for the episodes')
    parser.add_argument('--workers', type=int, default=1, help='parallel processes (default 1)')
    parser.add_argument('--width', type=int, default=640, help='camera width (default 640)')
    parser.add_argument('--height', type=int, default=480, help='camera height (default 480)')
    parser.add_argument('--camera-rate', type=float, default=0.0, metavar='HZ',
                        help='also record both cameras at this rate of sim time between rests, as the flat '
                             'baselines need (default 0: at the start and at rests only, where keyframes are)')
    parser.add_argument('--sensor-profile', choices=('ideal', 'd415'), default='ideal',
                        help="the cameras' sensor model: ideal renders (default) or a D415's depth noise, holes "
                             'and colour jitter, drawn per episode seed (README: Sensor model)')
    parser.add_argument('--json', type=Path, help='also write the summaries here')
    parser.set_defaults(func=run_collect)


def run_collect(args) -> int:
    from tqdm import tqdm

    from .collect import collect, summary_table
    if args.episodes < 1 or args.workers < 1 or args.camera_rate < 0:
        raise SystemExit('--episodes and --workers must be >= 1 and --camera-rate >= 0')
    tasks = _tasks(args.tasks)
    start = time.monotonic()
    summaries = []
    try:
        with tqdm(total=len(tasks) * args.episodes, unit='episode') as bar:
            for summary in collect(tasks, args.episodes, args.seed_start, args.out, args.workers,
                                   args.width, args.height, args.camera_rate, args.sensor_profile):
                summaries.append(summary)
                bar.set_postfix_str(f'{summary.task} seed {summary.seed}: '
                                    f'{"ok" if summary.success else "FAILED"}')
                bar.update()
    except FileExistsError as err:
        print(err, file=sys.stderr)
        return 1
    minutes = (time.monotonic() - start) / 60
    print(summary_table(summaries))
    print(f'\n{len(summaries)} episodes in {minutes:.1f} min ({len(summaries) / minutes:.1f} episodes/min, '
          f'{args.workers} worker(s)); failed demos are marked success=false and never used for training.')
    if args.json:
        args.json.write_text(json.dumps([s.__dict__ for s in summaries], indent=1))
    return 0


def configure_render(parser) -> None:
    """Render both cameras of a task scene to PNGs (colour and a depth colormap)."""
    parser.add_argument('--task', required=True)
    parser.add_argument('--seed', type=int, default=0)
    parser.add_argument('--out', type=Path, required=True)
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.set_defaults(func=run_render)


def run_render(args) -> int:
    import cv2
    import numpy as np

    from .cameras import default_cameras
    from .experts import reachable_scene
    from .world import PandaWorld
    _tasks(args.task)
    args.out.mkdir(parents=True, exist_ok=True)
    with PandaWorld() as world:
        reachable_scene(world, args.task, args.seed)
        world.step(24)      # let objects settle
        for name, camera in default_cameras(args.width, args.height).items():
            rgb, depth = camera.render(world.client)
            valid = depth > 0
            scaled = np.zeros(depth.shape, np.uint8)
            if valid.any():
                lo, hi = np.percentile(depth[valid], [1, 99])
                scaled[valid] = np.clip(255 * (depth[valid] - lo) / max(hi - lo, 1), 0, 255).astype(np.uint8)
            colormap = cv2.applyColorMap(255 - scaled, cv2.COLORMAP_TURBO)
            colormap[~valid] = 0
            for suffix, image in (('color', cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)), ('depth', colormap)):
                path = args.out / f'{args.task}_{args.seed}_{name}_{suffix}.png'
                cv2.imwrite(str(path), image)
                print(path)
    return 0


def configure_bench_sim(parser) -> None:
    """Real-time factor of the simulated Panda, with and without both cameras rendering."""
    parser.add_argument('--seconds', type=float, default=10.0, help='sim seconds per run (default 10)')
    parser.add_argument('--width', type=int, default=640)
    parser.add_argument('--height', type=int, default=480)
    parser.add_argument('--camera-rate', type=float, default=5.0, help='frames per sim second (default 5)')
    parser.add_argument('--task', default='open_drawer')
    parser.add_argument('--sensor-profile', choices=('ideal', 'd415'), default='ideal',
                        help="the cameras' sensor model (default ideal)")
    parser.add_argument('--json', action='store_true')
    parser.set_defaults(func=run_bench_sim)


def run_bench_sim(args) -> int:
    from .bridge import SimBridge
    from .sensor_model import SensorSettings, profile_named
    from .world import TIME_STEP
    bridge = SimBridge(args.width, args.height, sensor=SensorSettings(profile_named(args.sensor_profile)))
    results = {}
    for label, rate in (('cameras off', 0.0), (f'2 cameras {args.width}x{args.height} @ {args.camera_rate:g} Hz, '
                                                f'{args.sensor_profile}', args.camera_rate)):
        bridge.reset(args.task, 0)
        every = round(1.0 / (rate * TIME_STEP)) if rate > 0 else 0
        steps = int(args.seconds / TIME_STEP)
        start = time.perf_counter()
        for k in range(1, steps + 1):
            bridge.step()
            if k % 2 == 0:
                bridge.joint_state()
            if every and k % every == 0:
                for name in bridge.cameras:
                    bridge.camera_messages(name)
        wall = time.perf_counter() - start
        results[label] = {'sim_s': args.seconds, 'wall_s': round(wall, 3),
                          'real_time_factor': round(args.seconds / wall, 2)}
    bridge.close()
    if args.json:
        print(json.dumps(results, indent=2))
    else:
        print('| run | sim s | wall s | real-time factor |\n|---|---|---|---|')
        for label, r in results.items():
            print(f"| {label} | {r['sim_s']:g} | {r['wall_s']} | {r['real_time_factor']} |")
    return 0
