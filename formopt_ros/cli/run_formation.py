"""run_formation: one formation run as separate node processes (leader_sim, a follower_sim and an
estimator_planner per follower, the MCAP recorder; or, for followers with real interfaces, a
field_sim and a follower_estimator per follower), started through scripts/<node>.sh the way a
ROS user starts them; waits for the estimators, stops the rest, checks the recording and writes
OUT/summary.json. scripts/run_formation.sh is its shell front end; the checks before the start
(cli/preflight.py), the processes (cli/supervisor.py) and the recording's audit (cli/audit.py)
live beside it."""
from __future__ import annotations

import json
import math
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Any

from formopt_ros.cli.audit import audit_recording
from formopt_ros.cli.common import ArgumentParser, command, fail, integer, number
from formopt_ros.cli.preflight import (
    check_id_ok, check_name_lengths, formation_of, leader_extra, node_specs, prepare_out,
    real_names)
from formopt_ros.cli.real_run import run_real
from formopt_ros.cli.supervisor import (
    PROG, Launcher, Process, exit_failure, global_remaps, interrupted, interrupted_by, orphaned,
    stop_on_signals, supervise, supervising)
from formopt_ros.core.formation import Formation, check_id
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.core.strategies.region import UNREACHABLE
from formopt_ros.wire.jsonfile import write_json


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(prog=PROG, description=__doc__)
    parser.add_argument('--formation', type=Path, metavar='FILE',
                        help='a formation file (config/formation_fig4.yaml documents it); '
                             'without it one follower runs, set by the flags below')
    parser.add_argument('--measurement', choices=('range', 'bearing', 'range-bearing'),
                        help='single follower: its sensor (default range; range-bearing: '
                             'both at each step)')
    parser.add_argument('--strategy', choices=tuple(STRATEGIES),
                        help='single follower: its strategy (default ram; rq for '
                             'range-bearing)')
    parser.add_argument('--seed', type=integer(0, 2**31 - 1),
                        help='single follower: seed of its random streams (default 0)')
    parser.add_argument('--steps', type=integer(1, 10**9), default=100,
                        help='measurement steps (default 100; with real interfaces the run '
                             'lasts steps * 2 dt seconds)')
    parser.add_argument('--mode', choices=('lockstep', 'realtime'),
                        help='lockstep: deterministic, equals the pure simulation; realtime: '
                             'timers at 1/dt (default lockstep; followers with real interfaces '
                             'always run in real time)')
    parser.add_argument('--out', type=Path, required=True,
                        help='output folder: <node>.log, <node>.json summaries, run.mcap, '
                             'summary.json (a folder holding an earlier run is refused)')
    parser.add_argument('--prefix', default='',
                        help='formation namespace prefix, e.g. /run7: the robots run under '
                             '/run7/<robot> and /tf, /tf_static, /clock, /diagnostics are '
                             'remapped to /run7/tf, ...; two runs with different prefixes share '
                             'a ROS domain without seeing each other')
    parser.add_argument('--run-id', default='',
                        help='identity of the run: nodes refuse messages and peers of another '
                             'run (default: a fresh random id, in summary.json)')
    parser.add_argument('--domain-id', type=integer(0, 232),
                        help='ROS_DOMAIN_ID of the run (default: $ROS_DOMAIN_ID, else 0)')
    parser.add_argument('--no-record', action='store_true', help='do not record run.mcap')
    parser.add_argument('--timeout', type=number(0.0, math.inf, low_open=True), default=600.0,
                        help='give up after this long, s (default 600)')
    parser.add_argument('--respawn', type=integer(0, 100), default=0,
                        help='restart a node that dies (crash, signal) up to this many times; '
                             'nodes then save checkpoints in OUT/checkpoints and a restarted '
                             'node resumes the run (default 0: a dead node fails the run)')
    parser.add_argument('-p', dest='extra', action='append', default=[], metavar='NAME:=VALUE',
                        help='extra parameter for the simulator and estimator nodes '
                             '(single follower only), e.g. -p dt:=0.02 (repeatable)')
    return parser


#: An estimator whose run has not started this long after it did ends the run (a peer
#: frozen or failing before the first step), s.
START_TIMEOUT = 60.0
#: Warn when a follower's slot disc was out of reach on more than this share of the steps.
UNREACHABLE_WARN_SHARE = 0.1


def run(args: Any) -> int:
    """The whole run; returns the exit code."""
    formation, formation_file, extra = formation_of(args)
    if formation.followers[0].interfaces == 'real' and (args.mode == 'lockstep' or args.respawn):
        fail(PROG, f"--{'mode lockstep' if args.mode == 'lockstep' else 'respawn'}: followers "
                   'with real interfaces run in real time and are not respawned')
    try:
        check_id('--run-id', args.run_id, frame=False) if args.run_id else None
    except ValueError as error:
        fail(PROG, str(error))
    run_id = args.run_id or f'run_{uuid.uuid4().hex[:12]}'

    prefix = args.prefix.rstrip('/')
    if prefix and not (prefix.startswith('/') and
                       all(part and check_id_ok(part) for part in prefix[1:].split('/'))):
        fail(PROG, f'--prefix must look like /name or /name/name, got {args.prefix!r}')
    check_name_lengths(prefix, formation)
    out = prepare_out(args.out)
    # until the run writes its own: what a run that ends without one (a full disk, SIGKILL)
    # leaves behind
    write_json(out / 'summary.json', {
        'ok': False, 'run_id': run_id, 'failure': 'the run ended before it wrote its summary '
        '(killed, or its disk full): see the node logs in this folder'})
    # rcl's own log files too go into OUT, not ~/.ros/log
    os.environ['ROS_LOG_DIR'] = str(out / 'ros_log')
    if args.domain_id is not None:
        os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    with Launcher(out, checkpoints=args.respawn > 0, remaps=global_remaps(prefix)) as launcher:
        try:
            if formation.followers[0].interfaces == 'real':
                return run_real_formation(args, formation, launcher, out, prefix, run_id)
            return run_simulated(args, formation, formation_file, extra, launcher, out, prefix,
                                 run_id)
        except (OSError, KeyboardInterrupt) as error:
            failure = f'{interrupted()} before the run was summarised' \
                if isinstance(error, KeyboardInterrupt) else os_failure(error, out)
            launcher.stop(launcher.processes)
            try:
                write_json(out / 'summary.json', {
                    'ok': False, 'failure': failure, 'run_id': run_id,
                    'exit_codes': {p.name: p.code for p in launcher.processes}})
            except OSError as again:                # e.g. the disk is full
                failure += f'; cannot write {out / "summary.json"}: {again.strerror or again}'
            print(f'{PROG}: error: {failure}', file=sys.stderr)
            return 1


def os_failure(error: OSError, out: Path) -> str:
    """What an OSError of the run means: the recorder's own write error first (a full disk:
    it names the bag), else the error with its file."""
    try:
        recorded = json.loads((out / 'recorder_counts.json').read_text()).get('error')
    except (OSError, ValueError):
        recorded = None
    where = f': {error.filename}' if error.filename else ''
    return recorded or f'the run failed: {error.strerror or error}{where}'


def run_simulated(args: Any, formation: Formation, formation_file: Path | None,
                  extra: dict[str, Any], launcher: Launcher, out: Path, prefix: str,
                  run_id: str) -> int:
    """A formation of simulated followers (leader_sim, follower_sim, estimator_planner)."""
    record = not args.no_record
    args.mode = args.mode or 'lockstep'
    common: dict[str, Any] = {'mode': args.mode, 'run_id': run_id,
                              'recorders': 1 if record else 0,
                              'use_sim_time': args.mode == 'lockstep'}
    source = {'formation_file': str(formation_file)} if formation_file else {}
    started = time.monotonic()
    recorder = None
    if record:
        recorder = launcher.start('recorder', 'recorder', prefix, {
            'output_path': str(out / 'run.mcap'), 'counts_path': str(out / 'recorder_counts.json'),
            'leader_id': formation.leader_id,
            'followers': [f.id for f in formation.followers]}, summary=False)
    leader = launcher.start('leader_sim', 'leader_sim', f'{prefix}/{formation.leader_id}', {
        **common, **source, **({} if formation_file else {
            'followers': [f.id for f in formation.followers], **leader_extra(extra)})})
    nodes = {}
    sim_names = {spec.name for spec in node_specs(None, ('follower_sim',))}
    for follower in formation.followers:
        ns = f'{prefix}/{follower.id}'
        params = {**common, **source}
        if not formation_file:
            spec = follower
            params.update({'measurement': spec.scenario.measurement, 'seed': spec.seed,
                           **extra})
        sim = launcher.start(f'{follower.id}.follower_sim', 'follower_sim', ns,
                             {k: v for k, v in params.items()
                              if k in sim_names or k in common or k in source})
        estimator_params = dict(params, steps=args.steps, start_timeout=START_TIMEOUT)
        if not formation_file:
            estimator_params['strategy'] = follower.strategy
        estimator = launcher.start(f'{follower.id}.estimator_planner', 'estimator_planner',
                                   ns, estimator_params)
        nodes[follower.id] = (sim, estimator)
    print(f'{PROG}: started {len(launcher.processes)} processes '
          f'(ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID", "0")}, {args.mode}, '
          f'{len(formation.followers)} follower(s), {args.steps} steps); logs in {out}')
    estimators = [e for _, e in nodes.values()]
    others = [leader] + [s for s, _ in nodes.values()]
    failure = ''
    with supervising():
        while not failure and not all(e.ended for e in estimators):
            failure = interrupted_by() or \
                supervise(estimators, others, recorder, args.respawn) or \
                orphaned([(e, [leader, s]) for s, e in nodes.values()])
            if not failure and time.monotonic() - started > args.timeout:
                failure = f'timeout after {args.timeout:g} s'
            time.sleep(0.05)
        failure = failure or supervise(estimators, others, recorder, 0)
        wall = time.monotonic() - started
        # the formation first, the recorder last, so that it keeps their last messages
        launcher.stop(estimators + others)
        if recorder is not None:
            launcher.stop([recorder])
    failure = failure or interrupted_by()
    return write_summary(args, formation, out, launcher, leader, nodes, recorder, failure,
                         wall, prefix, run_id)


def run_real_formation(args: Any, formation: Formation, launcher: Launcher, out: Path,
                       prefix: str, run_id: str) -> int:
    """A formation of followers with real interfaces (formopt_ros/cli/real_run.py)."""
    started = time.monotonic()
    result = run_real(formation, launcher, out, prefix, args.steps, not args.no_record,
                      real_names())
    wall = time.monotonic() - started
    summary = {**result, 'run_id': run_id, 'mode': 'realtime', 'steps_requested': args.steps,
               'wall_time_s': wall, 'formation': formation.to_dict()}
    write_json(out / 'summary.json', summary)
    if not summary['ok']:
        return 1
    tracking = ', '.join(
        f"{f} NEES {t['mean_nees']:.2f} RMS {t['rms_position_error_m']:.3f} m"
        if (t := r.get('tracking') or {}).get('count') else f'{f} (not recorded)'
        for f, r in summary['followers'].items())
    print(f'{PROG}: real interfaces, {wall:.1f} s wall; {tracking}; {out / "summary.json"}')
    return 0


def write_summary(args: Any, formation: Formation, out: Path, launcher: Launcher,
                  leader: Process, nodes: dict[str, tuple[Process, Process]],
                  recorder: Process | None, failure: str, wall: float, prefix: str,
                  run_id: str) -> int:
    """Collect the node summaries, check the recording, write OUT/summary.json."""
    codes = {p.name: p.code for p in launcher.processes}
    followers = {}
    for follower_id, (sim, estimator) in nodes.items():
        result = estimator.summary()
        if result is None:
            failure = failure or f'{estimator.name} wrote no summary:\n{estimator.tail()}'
            continue
        if result['steps'] != args.steps:
            failure = failure or (f"{follower_id}: the estimator processed {result['steps']} of "
                                  f'{args.steps} steps')
        if not result.get('ok', True):
            failure = failure or (f'{follower_id}: '
                                  f"{result.get('error') or 'the estimator did not end ok'}")
        followers[follower_id] = result
    exited, late = exit_failure(launcher.processes)
    failure = failure or exited
    recording = None
    if recorder is not None:
        recording, problem = audit_recording(out, prefix, leader.summary(), {
            f: (sim.summary(), est.summary()) for f, (sim, est) in nodes.items()},
            sum(len(p.restarts) for p in launcher.processes))
        # the recorder's own write error (a full disk) names the file: it comes first
        failure = problem if recording.get('error') else failure or problem
    steps = min((r['steps'] for r in followers.values()), default=0)
    summary: dict[str, Any] = {
        'ok': not failure, 'failure': failure or None, 'run_id': run_id, 'mode': args.mode,
        'steps': steps,
        'steps_requested': args.steps, 'wall_time_s': wall,
        'steps_per_s': steps / wall if wall > 0 else None,
        'formation': formation.to_dict(), 'followers': followers, 'exit_codes': codes,
        'restarts': {p.name: p.restarts for p in launcher.processes if p.restarts},
        'killed_after_its_part': late, 'recording': recording}
    if len(followers) == 1:                   # the single follower's results at the top too
        summary.update({k: v for k, v in next(iter(followers.values())).items()
                        if k not in summary})
    write_json(out / 'summary.json', summary)
    if failure:
        print(f'{PROG}: error: {failure}', file=sys.stderr)
        return 1
    traces = ', '.join(f"{f} {r['final_weighted_trace']:.6g}" for f, r in followers.items())
    print(f'{PROG}: {steps} steps, final tr(W P W) m^2: {traces}; {wall:.2f} s wall '
          f'({steps / wall:.1f} steps/s); {out / "summary.json"}')
    for follower_id, result in followers.items():
        unreachable = (result.get('plan_fallbacks') or {}).get(UNREACHABLE, 0)
        if unreachable > UNREACHABLE_WARN_SHARE * max(result['steps'], 1):
            print(f"{PROG}: warning: {follower_id}: its slot's disc was out of reach on "
                  f"{unreachable} of {result['steps']} steps, so it headed back to the disc "
                  'instead of planning: max_speed leaves too little margin over what keeping '
                  'pace with the leader needs (or safety_distance cuts the disc)',
                  file=sys.stderr)
    return 0


@command(PROG)
def main(argv: list[str] | None = None) -> int:
    """Entry point of scripts/run_formation.sh; SIGINT, SIGTERM and SIGHUP (the terminal
    closed) stop the run like Ctrl-C: every node ends, the summary is written (naming the
    signal), exit 1; signals after the first are ignored while the run stops. SIGINT too when
    the shell started the run in the background (`&`), which ignores it by default. A stop
    still running STOP_REPORT_AFTER s after the signal prints every thread's stack to stderr."""
    args = build_parser().parse_args(argv)

    stop_on_signals()
    return run(args)


if __name__ == '__main__':
    sys.exit(main())
