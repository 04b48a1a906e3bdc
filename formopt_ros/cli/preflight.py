"""Checks of a run_formation call before anything starts: the formation or the single-follower
flags, -p values, every value against the nodes' own parameter specs, the output folder."""
from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

from formopt_ros.cli.common import fail
from formopt_ros.cli.real_run import REAL_NODES, check_real, node_parameters
from formopt_ros.core.formation import Formation, FollowerSpec, check_id
from formopt_ros.wire.formation import load_formation
from formopt_ros.wire.outputs import broken_link_on

PROG = 'run_formation.sh'


def formation_of(args: Any) -> tuple[Formation, Path | None, dict[str, Any]]:
    """The formation to run, its file (None for the single-follower flags) and the checked -p
    values (the formation's scenario and options include them)."""
    flags = [name for name in ('measurement', 'strategy', 'seed') if getattr(args, name)
             is not None]
    if args.formation is not None:
        if flags or args.extra:
            fail(PROG, f"{('--' + flags[0]) if flags else '-p'} cannot be combined with "
                       '--formation (set it in the formation file)')
        try:
            formation = load_formation(args.formation)
        except ValueError as error:
            fail(PROG, f'--formation: {error}')
        check_formation(formation, args.formation)
        return formation, args.formation.resolve(), {}
    kind = args.measurement or 'range'
    strategy = args.strategy or ('rq' if kind == 'range-bearing' else 'ram')
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
    try:
        spec = FollowerSpec('follower', scenario, strategy, options, args.seed or 0)
    except ValueError as error:
        fail(PROG, f'--strategy {strategy}: {error}')
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


def check_discs(formation: Formation, path: Path) -> None:
    """Two followers in one slot are refused; discs that overlap (two followers may plan the
    same point) are a warning on stderr."""
    followers = formation.followers
    for i, a in enumerate(followers):
        for b in followers[i + 1:]:
            gap = math.dist(a.scenario.p_o, b.scenario.p_o)
            if gap == 0.0:
                fail(PROG, f'--formation {path}: followers {a.id!r} and {b.id!r} share the slot '
                           f'{list(a.scenario.p_o)}')
            if gap < a.scenario.r + b.scenario.r:
                print(f'{PROG}: warning: --formation {path}: the discs of {a.id!r} and {b.id!r} '
                      f'overlap (slots {gap:.3g} m apart, radii {a.scenario.r:.3g} and '
                      f'{b.scenario.r:.3g} m): both may plan the same point', file=sys.stderr)


def check_formation(formation: Formation, path: Path) -> None:
    """Refuse, before anything starts, a formation whose values a node would refuse at start
    (e.g. a noise of 1e300: the file's own checks only ask for a positive number), or whose
    followers share a slot (overlapping discs: a warning)."""
    from formopt_ros.ros.params import ParameterError
    check_discs(formation, path)
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
    """Create OUT; refuse one that is not empty (nothing is overwritten), one the nodes cannot
    be given (:func:`~formopt_ros.wire.outputs.broken_link_on`) or one the system refuses (a
    name too long)."""
    try:
        problem = broken_link_on(out)
        if problem:
            fail(PROG, f'--out: {problem}')
        if out.exists() and not out.is_dir():
            fail(PROG, f'--out {out}: exists and is not a folder')
        earlier = sorted(p.name for p in out.iterdir())[:3] if out.is_dir() else []
        if earlier:
            fail(PROG, f'--out {out}: is not empty ({", ".join(earlier)}, ...); choose a new '
                       'folder (nothing is overwritten)')
        out.mkdir(parents=True, exist_ok=True)
        probe = out / '.write-test'
        probe.write_text('')
        probe.unlink()
    except OSError as error:
        fail(PROG, f'--out {out}: cannot write there: {error.strerror or error}')
    return out.resolve()


#: The longest name ROS 2 accepts for a topic or service (rmw: 255 - 8 characters), and the
#: longest a node makes: its parameter service, under the longest node name of a run.
ROS_NAME_MAX = 247
LONGEST_NODE_SERVICE = 'follower_estimator/set_parameters_atomically'


def check_name_lengths(prefix: str, formation: Formation) -> None:
    """Refuse a --prefix and ids that each pass their rules but together make names longer
    than ROS 2 accepts (every node would fail at start)."""
    for robot in [formation.leader_id] + [f.id for f in formation.followers]:
        name = f'{prefix}/{robot}/{LONGEST_NODE_SERVICE}'
        if len(name) > ROS_NAME_MAX:
            fail(PROG, f'--prefix and the id {robot!r} make ROS names of {len(name)} '
                       f'characters, more than ROS 2 accepts ({ROS_NAME_MAX}), e.g. {name}: '
                       'shorten the prefix or the id')


def check_id_ok(part: str) -> bool:
    """True for a namespace part that is a valid id."""
    try:
        check_id('prefix', part, frame=False)
        return True
    except ValueError:
        return False


#: Leader parameters among the single-follower -p extras.
_LEADER_KEYS = {'dt', 'path', 'v_leader', 'omega_leader', 'amplitude', 'period',
                'segment_durations', 'segment_speeds', 'segment_yaw_rates', 'repeat_segments'}


def leader_extra(extra: dict[str, Any]) -> dict[str, Any]:
    """The -p extras that concern the leader."""
    return {k: v for k, v in extra.items() if k in _LEADER_KEYS}


__all__ = ['FOLLOWER_NODES', 'check_discs', 'check_extras', 'check_formation', 'check_id_ok',
           'formation_of', 'leader_extra', 'node_specs', 'prepare_out', 'real_names']
