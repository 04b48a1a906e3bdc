"""run_formation: one formation run as separate node processes (leader_sim, a follower_sim and an
estimator_planner per follower, the MCAP recorder; or, for followers with real interfaces, a
field_sim and a follower_estimator per follower), started through scripts/<node>.sh the way a
ROS user starts them; waits for the estimators, stops the rest, checks the recording and writes
OUT/summary.json. scripts/run_formation.sh is its shell front end."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from formopt_ros.cli.common import ArgumentParser, command, fail, integer, number
from formopt_ros.cli.real_run import REAL_NODES, check_real, node_parameters, run_real
from formopt_ros.core.scenario import Formation, FollowerSpec, check_id
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.wire.formation import load_formation
from formopt_ros.wire.jsonfile import write_json
from formopt_ros.wire.topics import BY_KEY, GLOBAL_TOPICS, resolve

PROG = 'run_formation.sh'
SCRIPTS = Path(__file__).resolve().parents[2] / 'scripts'
#: Exit code of a node refusing its configuration (not respawned: it would refuse again).
CONFIGURATION_EXIT = 2


@dataclass
class Process:
    """One node process: its command, log file and (after the run) exit code and summary."""

    name: str
    process: subprocess.Popen[bytes]
    log: Path
    args: list[str]
    summary_path: Path | None = None
    code: int | None = None
    restarts: list[int] = field(default_factory=list)    # exit codes of the restarted runs

    def restart(self) -> None:
        """Start the process again (same arguments; the log continues)."""
        self.restarts.append(self.process.wait())
        with open(self.log, 'ab') as stream:
            stream.write(f'--- {PROG}: restarted after exit code {self.restarts[-1]} ---\n'
                         .encode())
            stream.flush()
            self.process = subprocess.Popen(self.args, stdout=stream, stderr=subprocess.STDOUT,
                                            start_new_session=True)

    def alive(self) -> bool:
        """True while the process runs."""
        return self.process.poll() is None

    def summary(self) -> dict[str, Any] | None:
        """The node's JSON summary (None when it wrote none)."""
        if self.summary_path is None or not self.summary_path.is_file():
            return None
        return dict(json.loads(self.summary_path.read_text()))

    def tail(self, lines: int = 5) -> str:
        """The last lines of its log."""
        text = self.log.read_text(errors='replace').splitlines() if self.log.exists() else []
        return '\n'.join(text[-lines:])


@dataclass
class Launcher:
    """Starts node processes through scripts/<node>.sh with a namespace and -p parameters."""

    out: Path
    checkpoints: bool = False
    remaps: list[str] = field(default_factory=list)   # FROM:=TO for every node
    processes: list[Process] = field(default_factory=list)

    def start(self, name: str, node: str, namespace: str, params: dict[str, Any],
              summary: bool = True, remaps: list[str] | None = None) -> Process:
        """Start ``node`` as process ``name`` (log OUT/<name>.log, summary OUT/<name>.json),
        with the common remaps and ``remaps`` (FROM:=TO)."""
        summary_path = self.out / f'{name}.json' if summary else None
        if summary_path is not None:
            params = {**params, 'summary_path': str(summary_path)}
        if summary_path is not None and self.checkpoints:
            params['checkpoint_path'] = str(self.out / 'checkpoints' / f'{name}.pkl')
        args = [str(SCRIPTS / f'{node}.sh'), '-r', f'__ns:={namespace or "/"}']
        for remap in self.remaps + (remaps or []):
            args += ['-r', remap]
        for key, value in params.items():
            args += ['-p', f'{key}:={format_value(value)}']
        log = self.out / f'{name}.log'
        with open(log, 'wb') as stream:
            process = subprocess.Popen(args, stdout=stream, stderr=subprocess.STDOUT,
                                       start_new_session=True)
        self.processes.append(Process(name, process, log, args, summary_path))
        return self.processes[-1]

    def stop(self, processes: list[Process], grace: float = 10.0) -> None:
        """SIGINT the process groups, SIGTERM after ``grace`` s, SIGKILL 5 s later."""
        for sig, wait in ((signal.SIGINT, grace), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
            running = [p for p in processes if p.alive()]
            if not running:
                break
            for item in running:
                try:
                    os.killpg(item.process.pid, sig)
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            while any(p.alive() for p in running) and time.monotonic() < deadline:
                time.sleep(0.05)
        for item in processes:
            item.code = item.process.wait()


def format_value(value: Any) -> str:
    """A -p value: lists as YAML flow, bools lower case."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(format_value(v) for v in value) + ']'
    return str(value) if str(value) else "''"


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(prog=PROG, description=__doc__)
    parser.add_argument('--formation', type=Path, metavar='FILE',
                        help='a formation file (config/formation_fig4.yaml documents it); '
                             'without it one follower runs, set by the flags below')
    parser.add_argument('--measurement', choices=('range', 'bearing'),
                        help="single follower: its sensor (default range)")
    parser.add_argument('--strategy', choices=tuple(STRATEGIES),
                        help='single follower: its strategy (default ram)')
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


def formation_of(args: Any) -> tuple[Formation, Path | None, dict[str, Any]]:
    """The formation to run, its file (None for the single-follower flags) and the checked -p
    values (the formation's scenario and options include them)."""
    flags = [name for name in ('measurement', 'strategy', 'seed') if getattr(args, name)
             is not None]
    if args.formation is not None:
        if flags or args.extra:
            fail(PROG, f"--{(flags or ['p'])[0]} cannot be combined with --formation (set it "
                       'in the formation file)')
        try:
            formation = load_formation(args.formation)
        except ValueError as error:
            fail(PROG, f'--formation: {error}')
        check_formation(formation, args.formation)
        return formation, args.formation.resolve(), {}
    kind, strategy = args.measurement or 'range', args.strategy or 'ram'
    extras: dict[str, str] = {}
    for item in args.extra:
        if ':=' not in item:
            fail(PROG, f'-p must be NAME:=VALUE, got {item!r}')
        name, text = item.split(':=', 1)
        if name in extras:
            fail(PROG, f'-p {name} is given twice ({extras[name]!r} and {text!r})')
        extras[name] = text
    values = check_extras(extras)
    from formopt_ros.ros.params import ParameterError
    from formopt_ros.ros.run_config import scenario_from
    try:
        scenario = scenario_from({**{spec.name: spec.default for spec in
                                     node_specs(None, FOLLOWER_NODES + ('leader_sim',))},
                                  'measurement': kind, **values})
    except ParameterError as error:
        fail(PROG, f'-p: {error}')
    options = {name[len(strategy) + 1:]: value for name, value in values.items()
               if name.startswith(f'{strategy}_')}
    spec = FollowerSpec('follower', scenario, strategy, options, args.seed or 0)
    return Formation('leader', (spec,)), None, values


#: Node parameters that run_formation sets itself (-p of them is refused): its option for each.
_MANAGED = {'mode': '--mode', 'run_id': '--run-id', 'steps': '--steps', 'seed': '--seed',
            'measurement': '--measurement', 'strategy': '--strategy', 'recorders': '--no-record',
            'use_sim_time': '--mode', 'followers': '--formation',
            'formation_file': '--formation', 'summary_path': '--out',
            'checkpoint_path': '--respawn', 'leader_id': '--formation',
            'follower_id': '--formation'}


def check_extras(extra: dict[str, str]) -> dict[str, Any]:
    """The -p values parsed as YAML (like ``--ros-args -p``) and checked by the nodes' own
    specs (integers for floats converted); refuse, before anything starts, a -p that no node
    receiving it has, one this command sets itself, or a value a node would refuse."""
    import difflib

    from formopt_ros.ros.params import ParameterError, parse_value
    values: dict[str, Any] = {}
    for name, text in extra.items():
        if name in _MANAGED:
            fail(PROG, f'-p {name}: set by {PROG} itself; use {_MANAGED[name]}')
        nodes = FOLLOWER_NODES + (('leader_sim',) if name in _LEADER_KEYS else ())
        specs = node_specs(name, nodes)
        if not specs:
            known = sorted({spec.name for spec in node_specs(None, nodes)})
            close = difflib.get_close_matches(name, known, n=1, cutoff=0.8)
            fail(PROG, f"-p {name}: no such parameter of follower_sim or estimator_planner"
                       + (f"; did you mean '{close[0]}'?" if close else ''))
        try:
            values[name] = parse_value(name, text)
            for spec in specs:
                values[name] = spec.check(values[name])
        except ParameterError as error:
            fail(PROG, f'-p {name}:={text}: {error}')
    return values


def check_formation(formation: Formation, path: Path) -> None:
    """Refuse, before anything starts, a formation whose values a node would refuse at start
    (e.g. a noise of 1e300: the file's own checks only ask for a positive number)."""
    from formopt_ros.ros.params import ParameterError
    from formopt_ros.ros.run_config import follower_values
    from formopt_ros.wire.description import path_parameters
    robots: list[tuple[str, tuple[str, ...], dict[str, Any]]] = [
        (f'leader {formation.leader_id!r}', ('leader_sim',),
         {'dt': formation.dt, **path_parameters(formation.leader)})]
    robots += [(f'follower {f.id!r}', FOLLOWER_NODES,
                follower_values(f, formation.trial, formation.leader_id))
               for f in formation.followers]
    if formation.followers[0].interfaces == 'real':
        robots = []
        names = real_names()

        def check(node: str, name: str, value: Any) -> str | None:
            try:
                for spec in node_specs(name, (node,)):
                    spec.check(value)
            except ParameterError as error:
                return f'{node}: {error}'
            return None
        problem = check_real(formation, names, check)
        for index, follower in enumerate(formation.followers):
            for node, values in node_parameters(formation, index, '/odom', 1.0, 1.0,
                                                names).items():
                problem = problem or next(filter(None, (check(node, k, v) for k, v in
                                                        values.items())), None)
        if problem:
            fail(PROG, f'--formation {path}: {problem}')
    for robot, nodes, values in robots:
        try:
            for name, value in values.items():
                for spec in node_specs(name, nodes):
                    spec.check(value)
        except ParameterError as error:
            fail(PROG, f'--formation {path}: {robot}: {error}')


#: The nodes of a follower (a -p of the single-follower flags goes to both).
FOLLOWER_NODES = ('follower_sim', 'estimator_planner')


def node_specs(name: str | None, nodes: tuple[str, ...]) -> list[Any]:
    """The parameter specs called ``name`` (None: all) of ``nodes`` ('leader_sim',
    'follower_sim', 'estimator_planner')."""
    import importlib
    return [spec for node in nodes
            for spec in importlib.import_module(f'formopt_ros.ros.nodes.{node}').PARAMS
            if name is None or spec.name == name]


def real_names() -> dict[str, set[str]]:
    """The parameter names of field_sim and follower_estimator."""
    return {node: {spec.name for spec in node_specs(None, (node,))} for node in REAL_NODES}


def prepare_out(out: Path) -> Path:
    """Create OUT; refuse one that is not empty (nothing is overwritten)."""
    if out.exists() and not out.is_dir():
        fail(PROG, f'--out {out}: exists and is not a folder')
    earlier = sorted(p.name for p in out.iterdir())[:3] if out.is_dir() else []
    if earlier:
        fail(PROG, f'--out {out}: is not empty ({", ".join(earlier)}, ...); choose a new '
                   'folder (nothing is overwritten)')
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / '.write-test'
        probe.write_text('')
        probe.unlink()
    except OSError as error:
        fail(PROG, f'--out {out}: cannot write there: {error.strerror}')
    return out.resolve()


def expected_counts(prefix: str, leader: dict[str, Any] | None,
                    followers: dict[str, tuple[dict[str, Any] | None, dict[str, Any] | None]],
                    remapped: bool = True) -> dict[str, int]:
    """Messages per topic the nodes say they published (their summaries); the global topics
    under ``prefix`` when ``remapped`` (:func:`global_remaps`, as run_formation starts them)."""
    tf, tf_static, clock, diagnostics = (f'{prefix if remapped else ""}{name}' for name in (
        '/tf', '/tf_static', '/clock', '/diagnostics'))
    out: dict[str, int] = {tf: 0, diagnostics: 0}
    leader_ns = f"{prefix}/{leader['leader_id']}" if leader else ''
    if leader:
        out[resolve(leader_ns, BY_KEY['leader_odom'])] = leader['published']['odometry']
        out[resolve(leader_ns, BY_KEY['leader_description'])] = 1
        out[clock] = leader['published']['clock']
        out[tf] += leader['published']['tf']
    for follower_id, (sim, estimator) in followers.items():
        ns = f'{prefix}/{follower_id}'
        if sim:
            for key, name in (('follower_odom', 'odometry'), ('measurement', 'measurement'),
                              ('truth', 'truth')):
                out[resolve(ns, BY_KEY[key])] = sim['published'][name]
            out[tf] += sim['published']['tf']
            out[tf_static] = out.get(tf_static, 0) + 1
            out[resolve(ns, BY_KEY['sim_description'])] = 1
        if estimator:
            published = estimator['message_counts']['published']
            for key in ('estimate', 'waypoint', 'status', 'markers'):
                out[resolve(ns, BY_KEY[key])] = published[key]
            out[resolve(ns, BY_KEY['description'])] = 1
            out[tf] += published['tf']
            out[diagnostics] += published['diagnostics']
    if out.get(clock) == 0:
        del out[clock]
    return {k: v for k, v in out.items() if v or k == tf}


def global_remaps(prefix: str) -> list[str]:
    """-r rules that move the global topics (/tf, /tf_static, /clock, /diagnostics) under
    ``prefix``, so that two runs in one domain do not mix their transforms and clocks."""
    return [f'{t.name}:={prefix}{t.name}' for t in GLOBAL_TOPICS] if prefix else []


def run(args: Any) -> int:
    """The whole run; returns the exit code."""
    formation, formation_file, extra = formation_of(args)
    if formation.followers[0].interfaces == 'real' and (args.mode == 'lockstep' or args.respawn):
        fail(PROG, f"--{'mode lockstep' if args.mode == 'lockstep' else 'respawn'}: followers "
                   'with real interfaces run in real time and are not respawned')
    try:
        check_id('--run-id', args.run_id) if args.run_id else None
    except ValueError as error:
        fail(PROG, str(error))
    run_id = args.run_id or f'run_{uuid.uuid4().hex[:12]}'

    prefix = args.prefix.rstrip('/')
    if prefix and not (prefix.startswith('/') and
                       all(part and check_id_ok(part) for part in prefix[1:].split('/'))):
        fail(PROG, f'--prefix must look like /name or /name/name, got {args.prefix!r}')
    out = prepare_out(args.out)
    if args.domain_id is not None:
        os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    launcher = Launcher(out, checkpoints=args.respawn > 0, remaps=global_remaps(prefix))
    record = not args.no_record
    if formation.followers[0].interfaces == 'real':
        return run_real_formation(args, formation, launcher, out, prefix, run_id)
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
        estimator_params = dict(params, steps=args.steps)
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
    try:
        while not failure and not all(e.process.poll() == 0 for e in estimators):
            failure = supervise(estimators, others, recorder, args.respawn)
            if not failure and time.monotonic() - started > args.timeout:
                failure = f'timeout after {args.timeout:g} s'
            time.sleep(0.05)
        failure = failure or supervise(estimators, others, recorder, 0)
    except KeyboardInterrupt:
        failure = 'interrupted'
    wall = time.monotonic() - started
    # the formation first, the recorder last, so that it keeps their last messages
    launcher.stop(estimators + others)
    if recorder is not None:
        launcher.stop([recorder])
    return write_summary(args, formation, out, launcher, leader, nodes, recorder, failure,
                         wall, prefix, run_id)


def run_real_formation(args: Any, formation: Formation, launcher: Launcher, out: Path,
                       prefix: str, run_id: str) -> int:
    """A formation of followers with real interfaces (formopt_ros/cli/real_run.py)."""
    started = time.monotonic()
    result = run_real(formation, launcher, out, prefix, args.steps, args.timeout,
                      not args.no_record, real_names())
    wall = time.monotonic() - started
    summary = {**result, 'run_id': run_id, 'mode': 'realtime', 'steps_requested': args.steps,
               'wall_time_s': wall, 'formation': formation.to_dict()}
    write_json(out / 'summary.json', summary)
    if not summary['ok']:
        return 1
    tracking = ', '.join(
        f"{f} NEES {t['mean_nees']:.2f} RMS {t['rms_position_error_m']:.3f} m"
        if (t := r.get('tracking', {})).get('count') else f'{f} (not recorded)'
        for f, r in summary['followers'].items())
    print(f'{PROG}: real interfaces, {wall:.1f} s wall; {tracking}; {out / "summary.json"}')
    return 0


def supervise(estimators: list[Process], others: list[Process], recorder: Process | None,
              respawn: int) -> str:
    """Restart dead nodes while ``respawn`` allows; the failure when one cannot go on ('' if
    none). An estimator that exited 0 has finished; any other exit before the end is a
    failure unless the node can be restarted (not after exit code 2, a refused configuration,
    and never the recorder, whose file would be cut)."""
    for item in estimators + others + ([recorder] if recorder else []):
        code = item.process.poll()
        if code is None or (item in estimators and code == 0):
            continue
        if item is not recorder and code != CONFIGURATION_EXIT and \
                len(item.restarts) < respawn:
            print(f'{PROG}: {item.name} exited with code {code}; restarting it '
                  f'({len(item.restarts) + 1}/{respawn})', file=sys.stderr)
            item.restart()
            continue
        return f'{item.name} exited with code {code} before the run finished:\n{item.tail()}'
    return ''


def check_id_ok(part: str) -> bool:
    """True for a namespace part that is a valid id."""
    try:
        check_id('prefix', part)
        return True
    except ValueError:
        return False


#: Leader parameters among the single-follower -p extras.
_LEADER_KEYS = {'dt', 'path', 'v_leader', 'omega_leader', 'amplitude', 'period',
                'segment_durations', 'segment_speeds', 'segment_yaw_rates', 'repeat_segments'}


def leader_extra(extra: dict[str, Any]) -> dict[str, Any]:
    """The -p extras that concern the leader."""
    return {k: v for k, v in extra.items() if k in _LEADER_KEYS}


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
        followers[follower_id] = result
    bad = {name: code for name, code in codes.items() if code not in (0, None)}
    if bad and not failure:
        name = next(iter(bad))
        failure = f'{name} exited with code {bad[name]}'
    recording = None
    if recorder is not None:
        counts_file = out / 'recorder_counts.json'
        recorded = json.loads(counts_file.read_text())['counts'] if counts_file.exists() else {}
        expected = expected_counts(prefix, leader.summary(), {
            f: (sim.summary(), est.summary()) for f, (sim, est) in nodes.items()})
        missing = {topic: n - recorded.get(topic, 0) for topic, n in expected.items()
                   if recorded.get(topic, 0) < n}
        extra = {topic: n - expected.get(topic, 0) for topic, n in recorded.items()
                 if n > expected.get(topic, 0)}
        complete = bool(recorded) and not missing
        recording = {'path': str(out / 'run.mcap'), 'counts': recorded, 'expected': expected,
                     'complete': complete, 'missing': missing, 'extra': extra}
        if not complete and not failure:
            failure = f'the recording misses messages: {missing or "no counts"}'
        # a restarted node publishes again what it sent after its last checkpoint
        if extra and not failure and not any(p.restarts for p in launcher.processes):
            failure = (f'the recording holds messages that no node of this run published: '
                       f'{extra} (another run publishes on these topics in this ROS domain; '
                       'use --domain-id or --prefix)')
    steps = min((r['steps'] for r in followers.values()), default=0)
    summary: dict[str, Any] = {
        'ok': not failure, 'failure': failure or None, 'run_id': run_id, 'mode': args.mode,
        'steps': steps,
        'steps_requested': args.steps, 'wall_time_s': wall,
        'steps_per_s': steps / wall if wall > 0 else None,
        'formation': formation.to_dict(), 'followers': followers, 'exit_codes': codes,
        'restarts': {p.name: p.restarts for p in launcher.processes if p.restarts},
        'recording': recording}
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
    return 0


@command(PROG)
def main(argv: list[str] | None = None) -> int:
    """Entry point of scripts/run_formation.sh; SIGTERM stops the run like Ctrl-C (exit 1)."""
    args = build_parser().parse_args(argv)

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    return run(args)


if __name__ == '__main__':
    sys.exit(main())
