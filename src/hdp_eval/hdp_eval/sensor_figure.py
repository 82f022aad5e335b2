"""`hdp plot sensor`: the D415 sensor model beside ideal renders, and its depth error against Intel's formula.

Top: one scene's front camera, ideal and d415, colour and depth (no depth in black), cropped to
the scene at native pixels so single holes show. Bottom: the RMS depth error of rendered planes
facing the camera, measured (d415 minus ideal, valid pixels) at three resolutions and on a dark
plane, against RMS = z^2 x subpixel / (focal px x baseline).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

PLANE_DISTANCES = (0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0)       # m
RESOLUTIONS = ((1280, 720), (640, 480), (128, 96))
LIGHT, DARK = (0.75, 0.75, 0.75, 1.0), (0.03, 0.03, 0.03, 1.0)


def configure(parser) -> None:
    """Ideal vs d415 frames and the d415 depth error against Intel's stereo formula, as a PNG."""
    parser.add_argument('--out', type=Path, required=True, help='PNG to write')
    parser.add_argument('--task', default='open_drawer', help='the scene of the frames (default open_drawer)')
    parser.add_argument('--seed', type=int, default=3, help='its seed (default 3)')
    parser.set_defaults(func=run)


def plane_errors(width: int, height: int, colour, profile, seed: int = 0) -> list[tuple[float, float]]:
    """(distance m, measured RMS depth error m) of a plane facing a width x height camera at each of
    PLANE_DISTANCES: d415 render minus ideal render over the pixels where both have depth."""
    import pybullet
    from pybullet_utils.bullet_client import BulletClient

    from hdp_sim_bridge.cameras import D415Camera
    from hdp_sim_bridge.sensor_model import degrade

    client = BulletClient(connection_mode=pybullet.DIRECT)
    camera = D415Camera.looking_at('plane', (0.0, 0.0, 1.0), (1.0, 0.0, 1.0), width=width, height=height)
    shape = client.createVisualShape(pybullet.GEOM_BOX, halfExtents=(0.005, 5.0, 5.0), rgbaColor=colour)
    errors = []
    try:
        for k, distance in enumerate(PLANE_DISTANCES):
            body = client.createMultiBody(0.0, -1, shape, basePosition=(distance + 0.005, 0.0, 1.0))
            rgb, ideal = camera.render(client)
            _, noisy = degrade(rgb, ideal, camera.intrinsics.fx, profile, np.random.default_rng([seed, k]))
            both = (ideal > 0) & (noisy > 0)
            error_mm = noisy[both].astype(float) - ideal[both]
            errors.append((distance, float(np.sqrt(np.mean(error_mm ** 2))) * 1e-3))
            client.removeBody(body)
    finally:
        client.disconnect()
    return errors


def scene_frames(task: str, seed: int):
    """Ideal and d415 (rgb, depth mm) of the front camera at 640x480 on ``task``'s scene ``seed``."""
    from hdp_sim_bridge.cameras import CameraRig, default_cameras
    from hdp_sim_bridge.experts import reachable_scene
    from hdp_sim_bridge.sensor_model import D415, SensorSettings
    from hdp_sim_bridge.world import PandaWorld

    cameras = {'front': default_cameras(640, 480)['front']}
    with PandaWorld() as world:
        reachable_scene(world, task, seed)
        world.step(24)      # let objects settle, as hdp render does
        rig = CameraRig(cameras, SensorSettings(D415))
        rig.start_episode(seed)
        return cameras['front'].render(world.client), rig.render(world.client, 'front', 0)


def depth_colours(depth_mm: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(H, W, 3) float: depth through turbo between lo and hi mm, no depth black."""
    from matplotlib import colormaps
    shown = colormaps['turbo'](1.0 - np.clip((depth_mm - lo) / (hi - lo), 0, 1))[..., :3]
    shown[depth_mm == 0] = 0.0
    return shown


def plot(out: Path, task: str, seed: int) -> None:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from PIL import Image

    from hdp_sim_bridge.cameras import d415_intrinsics
    from hdp_sim_bridge.sensor_model import D415, rms_depth_error_m

    (ideal_rgb, ideal_depth), (d415_rgb, d415_depth) = scene_frames(task, seed)
    crop = np.s_[150:390, 160:480]        # the middle 320 x 240 pixels: the scene, at native pixels
    lo, hi = np.percentile(ideal_depth[crop][ideal_depth[crop] > 0], [1, 99])
    fig = plt.figure(figsize=(12, 7.4))
    grid = fig.add_gridspec(2, 4, height_ratios=[1, 1.25])
    panels = (('ideal colour', ideal_rgb[crop]), ('d415 colour', d415_rgb[crop]),
              ('ideal depth', depth_colours(ideal_depth[crop], lo, hi)),
              ('d415 depth (no depth: black)', depth_colours(d415_depth[crop], lo, hi)))
    for column, (title, image) in enumerate(panels):
        ax = fig.add_subplot(grid[0, column])
        ax.imshow(image, interpolation='nearest')
        ax.set_title(title, fontsize=10)
        ax.axis('off')

    ax = fig.add_subplot(grid[1, :])
    z = np.linspace(0.4, 3.1, 100)
    for (width, height), colour in zip(RESOLUTIONS, ('tab:blue', 'tab:orange', 'tab:green')):
        focal = d415_intrinsics(width, height).fx
        ax.plot(z, 1e3 * rms_depth_error_m(z, focal), color=colour,
                label=f'formula, {width}x{height} (f = {max(focal, D415.min_focal_px):.0f} px)')
        measured = np.array(plane_errors(width, height, LIGHT, D415))
        ax.plot(measured[:, 0], 1e3 * measured[:, 1], 'o', color=colour, label=f'rendered plane, {width}x{height}')
    focal = d415_intrinsics(640, 480).fx
    ax.plot(z, 1e3 * rms_depth_error_m(z, focal, subpixel=D415.subpixel_dark), '--', color='tab:orange',
            label=f'formula, dark surface (subpixel {D415.subpixel_dark:g}), 640x480')
    measured = np.array(plane_errors(640, 480, DARK, D415))
    ax.plot(measured[:, 0], 1e3 * measured[:, 1], 's', color='black', label='rendered dark plane, 640x480')
    ax.set_xlabel('distance (m)')
    ax.set_ylabel('RMS depth error (mm)')
    ax.set_yscale('log')
    ax.grid(alpha=0.3, which='both')
    ax.legend(fontsize=8, ncol=2)
    ax.set_title(f'd415 depth error vs distance: z^2 x subpixel / (f x {1e3 * D415.baseline_m:g} mm), '
                 f'subpixel {D415.subpixel:g}', fontsize=10)
    fig.suptitle(f'{task} seed {seed}, front camera 640x480 (middle 320x240 px)', fontsize=11)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    # A 256-colour palette keeps the noisy frames' PNG small enough to commit.
    Image.open(out).convert('RGB').quantize(256).save(out, optimize=True)


def run(args) -> int:
    from hdp_data.instructions import task_names
    try:
        task_names(args.task)
    except ValueError as err:
        raise SystemExit(str(err)) from None
    plot(args.out, args.task, args.seed)
    print(f'wrote {args.out}')
    return 0
