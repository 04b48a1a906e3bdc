"""What a node runs: the parameters every formation node shares, and its leader or follower
configuration, from a formation file or from its own parameters (never both)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from rclpy.node import Node

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.domain import check_domain
from formopt_ros.core.model import EXACT, MEASUREMENT_KINDS, RANGE_BEARING
from formopt_ros.core.model import KINEMATICS as MOTION_MODELS
from formopt_ros.core.formation import FollowerSpec, check_id
from formopt_ros.core.scenario import (
    PATH_FIELDS, PATH_KINDS, RANGES, LeaderPath, Scenario, Segment)
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.ros.naming import robot_id
from formopt_ros.ros.params import Param, ParameterError
from formopt_ros.wire.description import MODES, path_parameters, scenario_parameters
from formopt_ros.wire.formation import load_formation
from formopt_ros.wire.topics import DEFAULT_FOLLOWER, DEFAULT_LEADER


def value_range(key: str) -> tuple[float, float]:
    """(low, high) of a number of a run (core.scenario.RANGES)."""
    low, high, _ = RANGES[key]
    return low, high


FORMATION_FILE = Param('formation_file', '', 'a formation YAML file (config/formation_fig4.yaml '
                       'documents it); when set, the scenario, leader path, strategy and seed '
                       'come from it and setting them here is refused')
FOLLOWER_ID = Param('follower_id', '', "id of the follower (frames, message filter); '' means "
                    "the last part of the node namespace ('follower' at the root)",
                    identifier=True)
LEADER_ID = Param('leader_id', DEFAULT_LEADER, 'id of the leader: its namespace (beside this '
                  "node's) and frame", identifier=True)
MODE = Param('mode', 'lockstep', 'lockstep: act on the awaited message, deterministic; '
             'realtime: timers at 1/dt', choices=MODES)
DT = Param('dt', 0.05, 'sub-step length, s', *value_range('dt'))
MEASUREMENT = Param('measurement', 'range', 'the follower sensor: range, bearing, or both at '
                    'each step (range-bearing: two Measurement messages per step; the bearing '
                    'every bearing_every steps)', choices=(*MEASUREMENT_KINDS, RANGE_BEARING))
BEARING_EVERY = Param('bearing_every', 1, 'range-bearing: the bearing comes at every k-th step, '
                      'the range at every step', 1, 10**6)
SEED = Param('seed', 0, 'seed of the random streams (same as formopt-montecarlo)',
             *value_range('seed'))
TRIAL = Param('trial', 0, 'trial index: the streams are seeded by (seed, trial)',
              *value_range('trial'))
SIGMA_V = Param('sigma_v', 0.2, 'follower linear velocity noise std, m/s', *value_range('sigma_v'))
SIGMA_OMEGA = Param('sigma_omega', 0.1, 'follower angular velocity noise std, rad/s',
                    *value_range('sigma_omega'))
SIGMA_V_LEADER = Param('sigma_v_leader', 0.0, "noise std of the leader's odometry speed as the "
                       'estimator receives it, m/s (0: exact, as in the paper)',
                       *value_range('sigma_v_leader'))
SIGMA_OMEGA_LEADER = Param('sigma_omega_leader', 0.0, "noise std of the leader's odometry yaw "
                           'rate, rad/s (0: exact)', *value_range('sigma_omega_leader'))
KINEMATICS = Param('kinematics', EXACT, 'motion model of the truth and the EKF: exact (arcs of '
                   "constant velocities) or euler (the paper's eq. 9, as its Sec. V simulates)",
                   choices=MOTION_MODELS)
RANGE_SIGMA = Param('range_sigma', 0.1, 'range noise std, m', *value_range('range_sigma'))
BEARING_SIGMA = Param('bearing_sigma', 0.02, 'bearing noise std, rad',
                      *value_range('bearing_sigma'))
SLOT = Param('formation_slot', [0.0], 'formation slot p_o [x, y] in the leader frame, m; '
             '[0.0] means the paper default for the measurement kind', *value_range('slot'))
DEVIATION = Param('deviation_fraction', 0.1, 'allowed deviation r as a fraction of |p_o|',
                  *value_range('deviation'))
PATH = Param('path', 'straight', "the leader's path: straight (v_leader), arc (v_leader, "
             'omega_leader), s-curve (v_leader, yaw rate amplitude * sin(2 pi t / period)) or '
             'segments (the segment_* lists)', choices=PATH_KINDS)
V_LEADER = Param('v_leader', 1.0, 'leader forward speed, m/s', *value_range('speed'))
OMEGA_LEADER = Param('omega_leader', 0.0, "leader yaw rate of an arc, rad/s (with path "
                     "'straight', a value other than 0 makes it an arc)", *value_range('yaw_rate'))
AMPLITUDE = Param('amplitude', 0.0, 'peak yaw rate of an s-curve, rad/s',
                  *value_range('amplitude'))
PERIOD = Param('period', 10.0, 'period of an s-curve, s', *value_range('period'))
SEGMENT_DURATIONS = Param('segment_durations', [1.0], 'segments: duration of each, s',
                          *value_range('duration'))
SEGMENT_SPEEDS = Param('segment_speeds', [1.0], 'segments: forward speed of each, m/s',
                       *value_range('speed'))
SEGMENT_YAW_RATES = Param('segment_yaw_rates', [0.0], 'segments: yaw rate of each, rad/s',
                          *value_range('yaw_rate'))
REPEAT = Param('repeat_segments', False, 'segments: repeat the list instead of holding the '
               'last segment')
RUN_ID = Param('run_id', '', 'identity of the run: messages and peers of another run are '
               "refused; '' accepts any (run_formation.sh sets a fresh one per run)")
RECORDERS = Param('recorders', 0, 'recorders (or other subscribers of every topic) each '
                  'publisher waits for before the first message of the run', 0, 100)
WAIT_FOR_PEERS = Param('wait_for_peers', True, "before the first message, also wait for the "
                       "formation nodes that listen to each topic and for the peers' run "
                       "descriptions, the scenario handshake (false: only for the recorders, "
                       "e.g. an estimator driven by a replayed bag; descriptions that do come "
                       "are still compared)")
SUMMARY_PATH = Param('summary_path', '', 'write a JSON summary of the node here when it ends, '
                     'also on SIGINT/SIGTERM (empty: none); checked at start: an existing file '
                     'is refused unless the node resumes from its checkpoint')
CHECKPOINT_PATH = Param('checkpoint_path', '', 'checkpoint file: the node saves its state after '
                        'every step and, restarted with the same file, resumes the run (empty: '
                        'none; a checkpoint of another or a finished run is refused)')
FOLLOWERS = Param('followers', [DEFAULT_FOLLOWER], 'ids of the followers the leader serves: '
                  'lockstep advances when each has sent its waypoint for the next step')
PATH_PARAMS = [PATH, V_LEADER, OMEGA_LEADER, AMPLITUDE, PERIOD, SEGMENT_DURATIONS,
               SEGMENT_SPEEDS, SEGMENT_YAW_RATES, REPEAT]
INITIAL_COVARIANCE = Param(
    'initial_covariance', [0.1, 0.1, 4e-4], 'diagonal of P_1|1 [x m^2, y m^2, phi rad^2]; the '
    'truth starts at N([p_o, 0], P_1|1)', *value_range('initial_covariance'))
MAX_SPEED = Param('max_speed', 0.0, "speed limit of the follower's planned motion: mean "
                  'world-frame speed over a measurement step, m/s (0: none, the paper\'s '
                  'protocol)', 0.0, value_range('max_speed')[1])
SAFETY_DISTANCE = Param('safety_distance', 0.0, 'distance from the leader no planned point '
                        "comes within, m (0: none)", *value_range('safety_distance'))
SCENARIO_PARAMS = [MEASUREMENT, DT, SIGMA_V, SIGMA_OMEGA, SIGMA_V_LEADER, SIGMA_OMEGA_LEADER,
                   KINEMATICS, RANGE_SIGMA, BEARING_SIGMA, SLOT, DEVIATION,
                   INITIAL_COVARIANCE, MAX_SPEED, SAFETY_DISTANCE, BEARING_EVERY] + PATH_PARAMS


def strategy_params() -> list[Param]:
    """The 'strategy' parameter and every strategy option as '<strategy>_<option>'."""
    params = [Param('strategy', 'ram', 'motion strategy', choices=tuple(STRATEGIES),
                    read_only=False)]
    for name, cls in STRATEGIES.items():
        for option, spec in cls.OPTIONS.items():
            bounded = not isinstance(spec.default, bool)
            params.append(Param(f'{name}_{option}', spec.default, f'{name}: {spec.description}',
                                spec.low if bounded else None, spec.high if bounded else None,
                                read_only=False))
    return params


def strategy_options(name: str, values: dict[str, Any]) -> dict[str, Any]:
    """Options of strategy ``name`` from the '<strategy>_<option>' parameter values."""
    return {option: values[f'{name}_{option}'] for option in STRATEGIES[name].OPTIONS}


#: The LeaderPath field each path parameter sets.
PATH_PARAMETERS = ((V_LEADER, 'speed'), (OMEGA_LEADER, 'yaw_rate'), (AMPLITUDE, 'amplitude'),
                   (PERIOD, 'period'), (SEGMENT_DURATIONS, 'segments'),
                   (SEGMENT_SPEEDS, 'segments'), (SEGMENT_YAW_RATES, 'segments'),
                   (REPEAT, 'repeat'))


def leader_path_from(values: dict[str, Any]) -> LeaderPath:
    """The leader path described by the path parameters; a path parameter that the chosen
    kind does not read, set away from its default, is refused (ParameterError naming it)."""
    kind = values['path']
    fields = PATH_FIELDS['arc' if kind == 'straight' else kind]  # omega_leader != 0: an arc
    used = [param.name for param, field in PATH_PARAMETERS if field in fields]
    for param, field in PATH_PARAMETERS:
        if field not in fields and values.get(param.name, param.default) != param.default:
            raise ParameterError(f"parameter '{param.name}' is not read by path {kind!r} (it "
                                 f'reads {used}), got {values[param.name]!r}')
    try:
        if kind in ('straight', 'arc'):
            return LeaderPath.constant(values['v_leader'], values['omega_leader']) \
                if kind == 'straight' else LeaderPath('arc', values['v_leader'],
                                                      values['omega_leader'])
        if kind == 's-curve':
            return LeaderPath('s-curve', values['v_leader'], amplitude=values['amplitude'],
                              period=values['period'])
        lists = [values[n] for n in ('segment_durations', 'segment_speeds',
                                     'segment_yaw_rates')]
        if len({len(v) for v in lists}) != 1:
            raise ParameterError('parameters segment_durations, segment_speeds and '
                                 'segment_yaw_rates must have the same length, got '
                                 f'{[len(v) for v in lists]}')
        return LeaderPath('segments', segments=tuple(Segment(*t) for t in zip(*lists)),
                          repeat=values['repeat_segments'])
    except InvalidInput as error:
        name = {f'leader {field}': param.name for param, field in PATH_PARAMETERS
                if field in ('speed', 'yaw_rate', 'amplitude', 'period')}.get(error.name)
        raise ParameterError('the leader path parameters are inconsistent: ' + (
            f"parameter '{name}' {error.reason}" if name else str(error))) from None


def scenario_from(values: dict[str, Any]) -> Scenario:
    """The Scenario described by the scenario parameters (paper defaults otherwise)."""
    kind = values['measurement']
    slot = values['formation_slot']
    if list(slot) != [0.0] and len(slot) != 2:
        raise ParameterError("parameter 'formation_slot' must be [x, y] in m or [0.0], got "
                             f'{slot!r}')
    p_o = Scenario.paper(kind).p_o if list(slot) == [0.0] else (float(slot[0]), float(slot[1]))
    if kind != RANGE_BEARING and values.get('bearing_every', 1) != BEARING_EVERY.default:
        raise ParameterError("parameter 'bearing_every' is for measurement range-bearing, got "
                             f"{values['bearing_every']!r} with measurement {kind!r}")
    if len(values['initial_covariance']) != 3:
        raise ParameterError("parameter 'initial_covariance' must be [x, y, phi] variances, "
                             f"got {values['initial_covariance']!r}")
    try:
        scenario = Scenario.paper(
            kind, p_o=p_o, r=values['deviation_fraction'] * math.hypot(*p_o),
            sigma=values['bearing_sigma'] if kind == 'bearing' else values['range_sigma'],
            **({'sigma_bearing': values['bearing_sigma'],
                'bearing_every': values['bearing_every']} if kind == RANGE_BEARING else {}),
            leader=leader_path_from(values), dt=values['dt'], sigma_v=values['sigma_v'],
            sigma_omega=values['sigma_omega'], sigma_v_leader=values['sigma_v_leader'],
            sigma_omega_leader=values['sigma_omega_leader'], kinematics=values['kinematics'],
            initial_covariance=tuple(values['initial_covariance']),
            max_speed=values['max_speed'] or None, safety_distance=values['safety_distance'])
    except ValueError as error:
        raise ParameterError(f'the scenario parameters are inconsistent: {error}') from None
    try:
        check_domain(scenario, 'formation_slot', 'deviation_fraction')
    except ValueError as error:
        raise ParameterError(f'parameters {error}') from None
    return scenario


def follower_values(spec: FollowerSpec, trial: int, leader_id: str) -> dict[str, Any]:
    """The parameters of a follower node that describe ``spec`` (inverse of follower_run)."""
    values = {'range_sigma': RANGE_SIGMA.default, 'bearing_sigma': BEARING_SIGMA.default,
              **scenario_parameters(spec.scenario), 'seed': spec.seed, 'trial': trial,
              'leader_id': leader_id, 'strategy': spec.strategy}
    values.update({f'{spec.strategy}_{k}': v for k, v in spec.options.items()})
    return values


def formation_defaults(node: Node, role: str) -> dict[str, Any]:
    """Parameter defaults from the file named by the node's ``formation_file`` override.

    Args:
        role: 'leader' or 'follower' (follower_sim and estimator_planner).

    Returns:
        {} without a formation file; else the values that describe this robot in the file.

    Raises:
        ParameterError: the file does not load, has no such robot, or a parameter it decides is
            also set on the node.
    """
    override = node._parameter_overrides.get('formation_file')
    path = override.value if override is not None else ''
    if not path:
        return {}
    try:
        formation = load_formation(path)
    except ValueError as error:
        raise ParameterError(f"parameter 'formation_file': {error}") from None
    if role == 'leader':
        values = {'dt': formation.dt, 'followers': [f.id for f in formation.followers],
                  **path_parameters(formation.leader)}
        leader_id = robot_id(node, DEFAULT_LEADER)
        if formation.leader_id != leader_id:
            raise ParameterError(f"parameter 'formation_file': its leader is "
                                 f'{formation.leader_id!r}, but this node runs in the namespace '
                                 f'of {leader_id!r} (start it with -r '
                                 f'__ns:=/{formation.leader_id})')
    else:
        follower_override = node._parameter_overrides.get('follower_id')
        follower_id = (follower_override.value if follower_override is not None else '') \
            or robot_id(node, DEFAULT_FOLLOWER)
        try:
            spec = formation.follower(follower_id)
        except ValueError as error:
            raise ParameterError(f"parameter 'formation_file': {error}") from None
        values = follower_values(spec, formation.trial, formation.leader_id)
    conflicts = sorted(set(values) & set(node._parameter_overrides))
    if conflicts:
        raise ParameterError(f"parameter '{conflicts[0]}' conflicts with parameter "
                             f"'formation_file': the file {path} sets it")
    return values


@dataclass(frozen=True)
class FollowerRun:
    """A follower node's configuration."""

    follower_id: str
    leader_id: str
    spec: FollowerSpec
    trial: int


def follower_run(node: Node, values: dict[str, Any], strategy_owned: bool) -> FollowerRun:
    """The follower configuration of a follower_sim or estimator_planner from its (declared,
    effective) parameters.

    Args:
        strategy_owned: the node has the strategy parameters (estimator_planner).
    """
    follower_id = values['follower_id'] or robot_id(node, DEFAULT_FOLLOWER)
    strategy, options = 'rq', {}          # unused by a node without a strategy
    if strategy_owned:
        strategy = values['strategy']
        options = strategy_options(strategy, values)
    try:
        spec = FollowerSpec(follower_id, scenario_from(values), strategy, options,
                            values['seed'])
    except ValueError as error:
        raise ParameterError(str(error)) from None
    return FollowerRun(follower_id, values['leader_id'], spec, values['trial'])


@dataclass(frozen=True)
class LeaderRun:
    """The leader node's configuration."""

    leader_id: str
    path: LeaderPath
    dt: float
    followers: tuple[str, ...]


def leader_run(node: Node, values: dict[str, Any]) -> LeaderRun:
    """The leader_sim configuration: its path, dt and the followers it serves."""
    followers = tuple(values['followers'])
    if not followers or len(set(followers)) != len(followers):
        raise ParameterError(f"parameter 'followers' must list distinct follower ids, got "
                             f'{list(followers)!r}')
    for follower in followers:
        try:
            check_id('follower id', follower)
        except ValueError as error:
            raise ParameterError(f"parameter 'followers': {error}") from None
    return LeaderRun(robot_id(node, DEFAULT_LEADER), leader_path_from(values), values['dt'],
                     followers)


__all__ = ['FollowerRun', 'LeaderRun', 'follower_run', 'follower_values', 'formation_defaults',
           'leader_run']
