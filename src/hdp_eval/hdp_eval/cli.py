"""`hdp eval low-level` (the paper's Table 2: low-level methods on oracle next-best poses) and
`hdp plot low-level` (its Fig. 4)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from hdp_controller.methods import METHODS


def configure(parser) -> None:
    """Low-level methods on oracle next-best poses (Table 2): success % / IK-error % per task."""
    parser.add_argument('--methods', default='planner',
                        help=f'comma-separated, of {", ".join(METHODS)} (default planner)')
    parser.add_argument('--tasks', default='all', help='comma-separated task names, "all" (default) or "first_six"')
    parser.add_argument('--episodes', type=int, default=25, help='episodes per task (default 25)')
    parser.add_argument('--seed-start', type=int, required=True,
                        help='first seed; must not overlap the seeds a checkpoint was trained on')
    parser.add_argument('--checkpoint', help='checkpoint of the learned methods (rkd and its variants, pose_ik, joint, joint_guided)')
    parser.add_argument('--sampler', choices=('ddpm', 'ddim'), default='ddim',
                        help='diffusion sampler of the learned methods: ddim (5 steps, unguided; default) '
                             'or ddpm (100, guided)')
    parser.add_argument('--steps', type=int, help='sampler steps (default: 5 for ddim, 100 for ddpm)')
    parser.add_argument('--guidance', type=float,
                        help="classifier-free guidance weight (default: 1.0, i.e. none, for ddim; "
                             "the checkpoint's for ddpm)")
    parser.add_argument('--refine-steps', type=int, default=50,
                        help="rkd's Gauss-Newton refinement steps (default 50)")
    parser.add_argument('--rkd-draws', type=int,
                        help="the samples per segment at most of rkd and rkd_redraw: they draw again while "
                             "refinement leaves the end off the NBP (default: hdp_controller.policy.DRAWS, 3); "
                             "rkd_single, the paper's, draws once")
    parser.add_argument('--json', type=Path, help='also write every episode record here')
    parser.add_argument('--workers', type=int, default=1, help='parallel processes (default 1); under torchrun, '
                        'per rank: the ranks share the episodes and rank 0 prints and writes the result')
    parser.add_argument('--device', default='cpu', help='where the diffusers sample: cpu (default), cuda, cuda:N, auto')
    parser.add_argument('--threads', type=int,
                        help="torch CPU threads with --workers 1 (default: torch's choice, every core; beside "
                             'another job, 1 ran this 10x faster); each of several workers takes 1')
    add_sensor_arguments(parser, graph=False)
    add_depth_filter_argument(parser)
    parser.set_defaults(func=run)


def add_sensor_arguments(parser, graph: bool) -> None:
    """The cameras' realism, as sim_bridge_node's parameters set it (hdp_sim_bridge README: Sensor model);
    graph: also the latency and the camera rate, which only a closed loop feels."""
    parser.add_argument('--sensor-profile', choices=('ideal', 'd415'), default='ideal',
                        help='camera sensor model: ideal renders (default) or a D415\'s noise, holes and '
                             'colour jitter (hdp_sim_bridge.sensor_model)')
    parser.add_argument('--extrinsic-error-mm', type=float, default=0.0, metavar='MM',
                        help='calibration error: the cameras render from this far from where /tf_static (and '
                             'the nodes) think they are, a random direction per episode (default 0)')
    parser.add_argument('--extrinsic-error-deg', type=float, default=0.0, metavar='DEG',
                        help='calibration error: and turned this much about a random axis (default 0)')
    if graph:
        parser.add_argument('--latency-ms', type=float, default=0.0, metavar='MS',
                            help='frames reach the planner and controller this long after their exposure stamp '
                                 '(the hierarchical rows; default 0)')
        parser.add_argument('--camera-hz', type=float, default=None, metavar='HZ',
                            help='camera frames per sim second for the hierarchical rows (a D415 streams 6, 15 '
                                 "or 30; default: the graph's 2)")


def add_refine_extrinsics_argument(parser) -> None:
    parser.add_argument('--refine-extrinsics', action='store_true',
                        help="the planner checks each camera's extrinsics against the robot's body as an "
                             "instruction starts and uses the refined ones (planner_node's refine_extrinsics; "
                             'hdp_planner.extrinsics)')


def add_depth_filter_argument(parser) -> None:
    """What the learned levels do with the depth they read (hdp_data.depth_filters)."""
    parser.add_argument('--depth-filter', choices=('none', 'realsense'), default='none',
                        help="post-processing of every camera's depth before the learned levels read it: none "
                             "(default) or realsense, librealsense's spatial, temporal and hole-filling chain "
                             "with Intel's defaults")


def depth_filter_settings(args):
    """The FilterSettings --depth-filter names; None for none."""
    from hdp_data.depth_filters import preset
    return preset(args.depth_filter)


def add_min_confidence_argument(parser) -> None:
    parser.add_argument('--min-confidence', type=float, default=None,
                        help="refuse an instruction whose first prediction is less confident (default: "
                             "planner_node's min_confidence; 0 on validation seeds to choose it for a checkpoint)")


def min_confidence(args) -> float:
    """--min-confidence, or planner_node's default (imported here: the parser loads no torch)."""
    from hdp_planner.planner_logic import DEFAULT_MIN_CONFIDENCE
    return DEFAULT_MIN_CONFIDENCE if args.min_confidence is None else args.min_confidence


def sensor_settings(args):
    """The SensorSettings of add_sensor_arguments' flags; SystemExit on a bad value."""
    from hdp_sim_bridge.sensor_model import SensorSettings, profile_named
    try:
        return SensorSettings(profile_named(args.sensor_profile), args.extrinsic_error_mm, args.extrinsic_error_deg,
                              getattr(args, 'latency_ms', 0.0))
    except ValueError as err:
        raise SystemExit(f'--extrinsic-error-mm, --extrinsic-error-deg and --latency-ms: {err}') from None


def _tasks(text: str) -> list[str]:
    from hdp_data.instructions import task_names
    try:
        return task_names(text)
    except ValueError as err:
        raise SystemExit(str(err)) from None


def _names(text: str, known, what: str) -> list[str]:
    names = list(known) if text == 'all' else [n.strip() for n in text.split(',') if n.strip()]
    unknown = [n for n in names if n not in known]
    if unknown or not names:
        raise SystemExit(f'unknown {what} {unknown or text!r}; {what}s: {", ".join(known)}')
    return names


def run(args) -> int:
    import torch

    from hdp_controller.policy import load_policy
    from hdp_learning import distributed

    from .low_level_eval import evaluate, markdown_table
    if args.episodes < 1 or args.workers < 1 or (args.threads is not None and args.threads < 1):
        raise SystemExit('--episodes, --workers and --threads must be >= 1')
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.seed_start < 0:
        raise SystemExit(f'--seed-start must be >= 0, got {args.seed_start}')
    tasks = _tasks(args.tasks)
    if ((args.steps is not None and args.steps < 1) or args.refine_steps < 1
            or (args.rkd_draws is not None and args.rkd_draws < 1)):
        raise SystemExit('--steps, --refine-steps and --rkd-draws must be >= 1')
    sampling = dict(steps=args.steps, guidance=args.guidance, refine_steps=args.refine_steps)
    if args.rkd_draws is not None:
        sampling['draws'] = args.rkd_draws
    names = _names(args.methods, METHODS, 'method')
    sensor, depth_filter = sensor_settings(args), depth_filter_settings(args)
    start = time.monotonic()
    try:
        device = distributed.start(distributed.torch_device(args.device))[2]     # each rank its own GPU
        methods = {name: load_policy(name, args.checkpoint, args.sampler, device=device, **sampling)
                   for name in names}
        results = evaluate(methods, tasks, args.episodes, args.seed_start, args.workers, sensor=sensor,
                           depth_filter=depth_filter)
    except ValueError as err:
        print(err, file=sys.stderr)
        return 1
    if results['processes'] > 1 and torch.distributed.get_rank() != 0:
        return 0
    print(markdown_table(results))
    skipped = {task: [s['seed'] for s in seeds] for task, seeds in results['skipped'].items() if seeds}
    if skipped:
        print(f'\nSkipped (the expert failed, so there are no oracle NBPs): {skipped}')
    print(f'\nseeds {args.seed_start}-{args.seed_start + args.episodes - 1}, {args.workers} worker(s), '
          f'{(time.monotonic() - start) / 60:.1f} min; front camera: {sensor.summary()}, '
          f'depth filter {args.depth_filter}')
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0


def configure_plot(parser) -> None:
    parser.description = ('Plot pose trajectory, joint trajectory (FK), refined trajectory and planner path '
                          'for one oracle episode, like the paper\'s Fig. 4.')
    parser.add_argument('--task', default='open_box')
    parser.add_argument('--seed', type=int, default=3000, help='evaluation seed (default 3000)')
    parser.add_argument('--checkpoint', help='RK-Diffuser checkpoint (default: the released one)')
    parser.add_argument('--segment', type=int, default=-1, help='segment to show, 1-based (default: the last)')
    parser.add_argument('--out', required=True, help='PNG to write')
    parser.set_defaults(func=run_plot)


def run_plot(args) -> int:
    from hdp_controller.policy import load_policy

    from .figures import plot, segments_of_episode
    policy = load_policy('rkd', args.checkpoint, 'ddpm')
    segments = segments_of_episode(policy, args.task, args.seed)
    if not segments:
        raise SystemExit(f'hdp plot low-level: RK-Diffuser planned no segment on {args.task} seed {args.seed}')
    chosen = len(segments) - 1 if args.segment == -1 else args.segment - 1
    if not 0 <= chosen < len(segments):
        raise SystemExit(f'hdp plot low-level: --segment must be 1..{len(segments)}')
    plot(segments[chosen], f'{args.task} seed {args.seed}, segment {chosen + 1} of {len(segments)}', args.out)
    print(f'wrote {args.out}')
    return 0


def configure_hierarchy(parser) -> None:
    """Closed-loop evaluation of the whole hierarchy in the sim, like the paper's Table 1. Under torchrun
    (torchrun --nproc-per-node N -m hdp_tools.cli.main eval hierarchy ...) each process runs every
    N-th episode and rank 0 prints the table and writes the one result file."""
    parser.add_argument('--agents', default='hdp,nbp_planner,nbp_joint',
                        help='comma-separated: hdp (agent + RK-Diffuser), nbp_planner (agent + planner), '
                             'nbp_joint (agent + joint diffusion), nbp_joint_guided (agent + joint diffusion with '
                             'goal guidance), and the flat baselines diffusion_policy '
                             'and act (hdp_planner.flat); default the three hierarchical rows')
    parser.add_argument('--tasks', default='all', help='comma-separated task names, "all" or "first_six"')
    parser.add_argument('--episodes', type=int, default=10, help='episodes per task (default 10)')
    parser.add_argument('--seed-start', type=int, required=True, help='first evaluation seed (never a training seed)')
    parser.add_argument('--phrasings', default='seen',
                        help='comma-separated: seen (training phrasings), heldout (the held-out template), '
                             'paraphrase (hdp_data.instructions paraphrases, never trained on), nonsense (one '
                             'word of the seen instruction kept, the rest made up); both = seen,heldout '
                             '(default seen)')
    parser.add_argument('--no-grounding', action='store_true',
                        help='give the agent instructions as they are, not read as the nearest training '
                             'instruction first (hdp_planner.grounding)')
    add_min_confidence_argument(parser)
    parser.add_argument('--reach-tolerance', default=None, metavar='M,DEG',
                        help="refuse a plan that ends farther from its NBP (default: controller_node's "
                             "reach_tolerance_m,reach_tolerance_deg; 'off' executes every plan)")
    parser.add_argument('--plan-attempts', type=int, default=None, metavar='N',
                        help="draws of the low level before a plan ending beyond the reach tolerance is refused "
                             "(default: controller_node's plan_attempts)")
    parser.add_argument('--max-segments', type=int, default=8, help='segment budget per episode (default 8)')
    parser.add_argument('--think-s', type=float, default=0.0, metavar='S',
                        help='sim seconds each trajectory is held back after it is planned while the world runs '
                             'on, as in the graph while the nodes think (default 0)')
    parser.add_argument('--flat-max-seconds', type=float, default=30.0,
                        help="the flat rows' budget per episode, s of sim time (default 30)")
    parser.add_argument('--flat-cameras', choices=('rest', 'every'),
                        help='when the flat rows get a new camera frame: every control step, or rest (at the '
                             'start and whenever the arm comes to rest); default: as each policy\'s training '
                             'episodes held them (every with `hdp collect --camera-rate 10`)')
    add_row_arguments(parser)
    parser.add_argument('--json', type=Path, help='also write the results here')
    add_sensor_arguments(parser, graph=True)
    add_depth_filter_argument(parser)
    add_refine_extrinsics_argument(parser)
    parser.set_defaults(func=run_hierarchy)


def add_row_arguments(parser) -> None:
    """Where Table 1's rows come from: the checkpoints, the sampler, the threads and the device."""
    parser.add_argument('--agent-checkpoint', type=Path, help='default: models/hdp_nbp_agent_11tasks.pt ($HDP_MODELS_DIR)')
    parser.add_argument('--low-level-checkpoint', help='default: models/rk_diffuser_11tasks.pt')
    parser.add_argument('--sampler', default='ddim', choices=('ddpm', 'ddim'),
                        help='RK-Diffuser sampler (default ddim)')
    parser.add_argument('--flat-diffusion-policy-checkpoint', type=Path,
                        help='the diffusion_policy row (default: models/flat_diffusion_policy.pt, $HDP_MODELS_DIR)')
    parser.add_argument('--flat-act-checkpoint', type=Path,
                        help='the act row (default: models/flat_act.pt, $HDP_MODELS_DIR)')
    parser.add_argument('--flat-act-ensemble', type=float, metavar='M',
                        help="the act row's temporal ensembling, exp(-M i) weights per control step; 0: run each "
                             'chunk open-loop, --flat-act-action-steps of it (default: as trained)')
    parser.add_argument('--flat-act-action-steps', type=int, metavar='N',
                        help="steps of each chunk the act row runs before it is asked again when it does not "
                             'ensemble (default: as trained; the whole chunk when --flat-act-ensemble 0)')
    parser.add_argument('--flat-diffusion-steps', type=int, metavar='N',
                        help="the diffusion_policy row's DDIM steps (default: as trained)")
    parser.add_argument('--threads', type=int, help='torch CPU threads')
    parser.add_argument('--device', default='cpu', help='where the diffusers sample: cpu (default), cuda, cuda:N, auto')


def flat_execution(args) -> dict:
    """flat row name -> the inference changes its --flat-* flags ask for (FlatPolicy.with_execution)."""
    act = {} if args.flat_act_ensemble is None else {'ensemble': args.flat_act_ensemble}
    if args.flat_act_action_steps is not None:
        act['n_action_steps'] = args.flat_act_action_steps
    return {'act': act, 'diffusion_policy': ({} if args.flat_diffusion_steps is None
                                             else {'inference_steps': args.flat_diffusion_steps})}


def _reach_tolerance(text: str | None) -> tuple[float, float] | None:
    from hdp_controller.segment_planning import REACH_TOLERANCE_DEG, REACH_TOLERANCE_M
    if text is None:
        return REACH_TOLERANCE_M, REACH_TOLERANCE_DEG
    if text == 'off':
        return None
    try:
        metres, degrees = (float(v) for v in text.split(','))
    except ValueError:
        raise SystemExit(f"--reach-tolerance takes M,DEG (e.g. 0.1,15) or 'off', got {text!r}") from None
    return metres, degrees


def load_rows(args, agents: list[str], command: str, grounding: bool = True) -> tuple:
    """(the next-best-pose agent or None, name -> low-level policy, name -> FlatPolicy) of Table 1's
    ``agents``, from add_row_arguments' flags; SystemExit naming ``command`` when one cannot load."""
    import torch

    from hdp_controller.policy import load_policy
    from hdp_learning.checkpoints import default_path
    from hdp_planner.agent import NextBestPoseAgent
    from hdp_planner.planner_logic import default_checkpoint

    from .hierarchy_eval import AGENTS, FLAT_AGENTS
    if args.threads:
        torch.set_num_threads(args.threads)
    hierarchical = [name for name in agents if name in AGENTS]
    try:
        agent = (NextBestPoseAgent.from_checkpoint(args.agent_checkpoint or default_checkpoint(),
                                                   ground_instructions=grounding) if hierarchical else None)
        low_levels = {name: load_policy(AGENTS[name], args.low_level_checkpoint, args.sampler, device=args.device)
                      for name in hierarchical}
        flat = {}
        if any(name in FLAT_AGENTS for name in agents):
            from hdp_planner.flat.policy import FlatPolicy
            chosen = {'diffusion_policy': args.flat_diffusion_policy_checkpoint, 'act': args.flat_act_checkpoint}
            flat = {name: FlatPolicy.from_checkpoint(chosen[name] or default_path(f'flat_{name}.pt'), args.device,
                                                     policy=FLAT_AGENTS[name])
                    for name in agents if name in FLAT_AGENTS}
            for name, changes in flat_execution(args).items():
                if name in flat and changes.get('ensemble') == 0 and 'n_action_steps' not in changes:
                    changes['n_action_steps'] = flat[name].config.horizon     # LeRobot's default: the whole chunk
                if name in flat and changes:
                    flat[name] = flat[name].with_execution(**changes)
    except ValueError as err:
        raise SystemExit(f'hdp eval {command}: {err}') from None
    return agent, low_levels, flat


def run_hierarchy(args) -> int:
    import torch

    from hdp_controller.segment_planning import PLAN_ATTEMPTS

    from .closed_loop import GraphSettings
    from .hierarchy_eval import AGENTS, FLAT_AGENTS, PHRASINGS, evaluate, markdown_table
    agents, tasks = _names(args.agents, {**AGENTS, **FLAT_AGENTS}, 'agent'), _tasks(args.tasks)
    phrasings = _names('seen,heldout' if args.phrasings == 'both' else args.phrasings, PHRASINGS, 'phrasing')
    reach_tolerance = _reach_tolerance(args.reach_tolerance)
    plan_attempts = PLAN_ATTEMPTS if args.plan_attempts is None else args.plan_attempts
    if args.flat_max_seconds <= 0 or args.think_s < 0 or plan_attempts < 1 or args.max_segments < 1:
        raise SystemExit('--flat-max-seconds must be > 0, --think-s >= 0, --plan-attempts >= 1 and '
                         '--max-segments >= 1')
    if args.camera_hz is not None and not args.camera_hz > 0:
        raise SystemExit(f'--camera-hz must be > 0, got {args.camera_hz}')
    sensor = sensor_settings(args)
    agent, low_levels, flat = load_rows(args, agents, 'hierarchy', grounding=not args.no_grounding)
    threshold = min_confidence(args)
    try:
        cameras = {} if args.camera_hz is None else {'camera_hz': args.camera_hz}
        settings = GraphSettings(max_segments=args.max_segments, min_confidence=threshold,
                                 reach_tolerance=reach_tolerance, plan_attempts=plan_attempts, think_s=args.think_s,
                                 sensor=sensor, depth_filter=depth_filter_settings(args),
                                 refine_extrinsics=args.refine_extrinsics, **cameras)
        results = evaluate(agent, low_levels, tasks, args.episodes, args.seed_start, phrasings, settings, flat=flat,
                           flat_max_seconds=args.flat_max_seconds, flat_cameras=args.flat_cameras)
    except ValueError as err:
        print(f'hdp eval hierarchy: {err}', file=sys.stderr)
        return 1
    if results['processes'] > 1 and torch.distributed.get_rank() != 0:
        return 0
    print(markdown_table(results))
    first, last = results['seeds']
    print(f"\nagent inference p50 {results['agent_predict_ms_p50']} ms; seeds {first}-{last}; "
          f"{results['wall_s'] / 60:.1f} min, {results['processes']} process(es); cameras at "
          f"{settings.camera_hz:g} Hz, {sensor.summary()}, depth filter {args.depth_filter}, extrinsics "
          f"{'refined from the robot' if args.refine_extrinsics else 'as /tf_static says'}; "
          f"min_confidence {threshold:g}")
    if 'flat' in results:
        cameras = ', '.join(f'{name} {when}' for name, when in results['flat']['cameras'].items())
        print(f"flat rows: {results['flat']['max_seconds']:g} s budget, new camera frames ({cameras}), "
              f"inference {results['flat']['execution']}, p50 (ms): {results['flat']['predict_ms_p50']}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0



def configure_ladder(parser) -> None:
    """The robustness ladder (issue 40): Table 1's and Table 2's rows on the same episodes under
    ideal cameras, a D415's, + calibration error, + latency at a D415's rate; every rung in one run."""
    parser.add_argument('--agents', default='hdp,nbp_planner,diffusion_policy,act',
                        help="Table 1's rows, comma-separated, as `hdp eval hierarchy --agents`; '' for none "
                             '(default hdp,nbp_planner,diffusion_policy,act)')
    parser.add_argument('--methods', default='rkd',
                        help=f"Table 2's rows, comma-separated, of {', '.join(METHODS)}; '' for none (default rkd)")
    parser.add_argument('--tasks', default='all', help='comma-separated task names, "all" or "first_six"')
    parser.add_argument('--episodes', type=int, default=10, help='episodes per task and rung (default 10)')
    parser.add_argument('--seed-start', type=int, required=True, help='first evaluation seed (never a training seed)')
    parser.add_argument('--extrinsic-error-mm', type=float, default=5.0, metavar='MM',
                        help='the calibration rung: each camera renders this far from /tf_static (default 5)')
    parser.add_argument('--extrinsic-error-deg', type=float, default=1.0, metavar='DEG',
                        help='and turned this much about a random axis (default 1)')
    parser.add_argument('--latency-ms', type=float, default=60.0, metavar='MS',
                        help='the latency rung: frames delivered this long after exposure (default 60)')
    parser.add_argument('--camera-hz', type=float, default=15.0, metavar='HZ',
                        help="and the cameras at this rate, a D415's 6, 15 or 30 (default 15)")
    parser.add_argument('--rungs', default='ideal,d415,calibration,latency',
                        help='the rungs to run, comma-separated, each adding to the one before: ideal, d415, '
                             'calibration (+ the extrinsic error), latency (+ the latency and camera rate); '
                             'the losses are counted against the first (default: all four)')
    add_min_confidence_argument(parser)
    add_row_arguments(parser)
    parser.add_argument('--json', type=Path, help='also write the results, every episode record, here')
    add_depth_filter_argument(parser)
    add_refine_extrinsics_argument(parser)
    parser.set_defaults(func=run_ladder)


def run_ladder(args) -> int:
    import torch

    from hdp_controller.policy import load_policy

    from . import ladder
    from .closed_loop import GraphSettings
    from .hierarchy_eval import AGENTS, FLAT_AGENTS
    agents = _names(args.agents, {**AGENTS, **FLAT_AGENTS}, 'agent') if args.agents else []
    methods = _names(args.methods, METHODS, 'method') if args.methods else []
    if not (agents or methods):
        raise SystemExit('hdp eval ladder: nothing to run: give --agents or --methods')
    if args.episodes < 1 or args.seed_start < 0:
        raise SystemExit('--episodes must be >= 1 and --seed-start >= 0')
    if not args.camera_hz > 0:
        raise SystemExit(f'--camera-hz must be > 0, got {args.camera_hz}')
    tasks = _tasks(args.tasks)
    try:
        rungs = ladder.rungs(args.extrinsic_error_mm, args.extrinsic_error_deg, args.latency_ms, args.camera_hz,
                             [key.strip() for key in args.rungs.split(',') if key.strip()])
    except ValueError as err:
        raise SystemExit(f'hdp eval ladder: {err}') from None
    if not rungs:
        raise SystemExit('hdp eval ladder: --rungs names none')
    agent, low_levels, flat = load_rows(args, agents, 'ladder')
    threshold = min_confidence(args)
    start = time.monotonic()
    try:
        table2 = {name: load_policy(name, args.low_level_checkpoint, args.sampler, device=args.device)
                  for name in methods}
        results = ladder.evaluate(agent, low_levels, table2, tasks, args.episodes, args.seed_start, rungs,
                                  GraphSettings(depth_filter=depth_filter_settings(args),
                                                refine_extrinsics=args.refine_extrinsics,
                                                min_confidence=threshold), flat)
    except ValueError as err:
        print(f'hdp eval ladder: {err}', file=sys.stderr)
        return 1
    if torch.distributed.is_initialized() and torch.distributed.get_rank() != 0:
        return 0                          # under torchrun every rank ran its share; rank 0 reports
    results['wall_s'] = round(time.monotonic() - start, 1)
    print(ladder.markdown_table(results))
    print(f"\nseeds {args.seed_start}-{args.seed_start + args.episodes - 1}, {results['wall_s'] / 60:.1f} min; "
          f"depth filter {args.depth_filter}; extrinsics "
          f"{'refined from the robot' if args.refine_extrinsics else 'as /tf_static says'}; "
          f"min_confidence {threshold:g}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0
