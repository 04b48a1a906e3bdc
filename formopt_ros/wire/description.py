"""The run description: what one follower's run is, as JSON, latched on ``<follower>/description``
and so recorded once in every bag; replay and report read the scenario back from it."""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from formopt_ros.core.model import EULER, RANGE_BEARING
from formopt_ros.core.scenario import LeaderPath, Scenario

#: Version tags of the JSON layouts.
FORMAT = 'formopt_ros.run/1'
LEADER_FORMAT = 'formopt_ros.leader/1'
MODES = ('lockstep', 'realtime')


def _load(text: str, expected: str) -> dict[str, Any]:
    try:
        data = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f'run description is not JSON: {error}') from None
    if not isinstance(data, dict) or data.get('format') != expected:
        raise ValueError(f'run description format must be {expected!r}, got '
                         f'{data.get("format") if isinstance(data, dict) else data!r}')
    return data


@dataclass(frozen=True)
class StrategyChange:
    """A strategy that took over mid-run (``ros2 param set`` of the strategy or an option).

    Attributes:
        step: measurement steps completed when it took over; it plans the waypoints of steps
            step + 2 on (the waypoint of step + 1 was already sent).
        strategy: its name; options: its settings (defaults filled in).
    """

    step: int
    strategy: str
    options: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form."""
        return {'step': self.step, 'strategy': self.strategy, 'options': dict(self.options)}


@dataclass(frozen=True)
class RunDescription:
    """One follower's run.

    Attributes:
        follower_id: the follower (its namespace).
        scenario: everything the estimator assumes about the world.
        strategy: motion strategy name; options: its settings (defaults filled in).
        seed, trial: the random streams are seeded by (seed, trial).
        mode: 'lockstep' or 'realtime'.
        steps: measurement steps of the run (0: until stopped).
        run_id: identity of the run ('' when not set).
        leader_id: the leader (its namespace and frame).
        strategy_changes: strategies that took over mid-run, in order (``strategy`` and
            ``options`` are the first one's); the estimator publishes the description again
            with each change.
    """

    follower_id: str
    scenario: Scenario
    strategy: str
    options: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    trial: int = 0
    mode: str = 'lockstep'
    steps: int = 0
    run_id: str = ''
    leader_id: str = 'leader'
    strategy_changes: tuple[StrategyChange, ...] = ()

    def to_json(self) -> str:
        """The JSON text published in RunDescription.description ('strategy_changes' only
        when there are some: the text of a run without changes is the same as before)."""
        data = {'format': FORMAT, 'run_id': self.run_id, 'leader_id': self.leader_id,
                'follower_id': self.follower_id, 'mode': self.mode, 'strategy': self.strategy,
                'options': self.options, 'seed': self.seed, 'trial': self.trial,
                'steps': self.steps, 'scenario': self.scenario.to_dict()}
        if self.strategy_changes:
            data['strategy_changes'] = [c.to_dict() for c in self.strategy_changes]
        return json.dumps(data, sort_keys=True)

    def strategies(self) -> list[str]:
        """Every strategy the run used, in order of first use."""
        names = [self.strategy] + [c.strategy for c in self.strategy_changes]
        return list(dict.fromkeys(names))

    def leader_view(self) -> 'LeaderDescription':
        """What this follower's run assumes about its leader."""
        return LeaderDescription(self.leader_id, self.scenario.leader, self.scenario.dt,
                                 (self.follower_id,), self.mode, self.run_id)

    @classmethod
    def from_json(cls, text: str) -> 'RunDescription':
        """Inverse of :meth:`to_json`; ValueError saying what is wrong."""
        data = _load(text, FORMAT)
        try:
            return cls(follower_id=str(data['follower_id']),
                       scenario=Scenario.from_dict(
                           {'kinematics': EULER, **data['scenario']}),  # older runs: Euler
                       strategy=str(data['strategy']), options=dict(data.get('options', {})),
                       seed=int(data['seed']), trial=int(data['trial']), mode=str(data['mode']),
                       steps=int(data['steps']), run_id=str(data.get('run_id', '')),
                       leader_id=str(data.get('leader_id', 'leader')),
                       strategy_changes=tuple(
                           StrategyChange(int(c['step']), str(c['strategy']),
                                          dict(c.get('options', {})))
                           for c in data.get('strategy_changes', [])))
        except (KeyError, TypeError) as error:
            raise ValueError(f'run description lacks or mangles {error}') from None


@dataclass(frozen=True)
class LeaderDescription:
    """The leader's side of a run, latched on ``<leader>/description``.

    Attributes:
        leader_id: the leader (its namespace and frame).
        path: its path; dt: the sub-step length, s.
        followers: the ids of the followers it serves.
        mode: 'lockstep' or 'realtime'; run_id: identity of the run ('' when not set).
    """

    leader_id: str
    path: LeaderPath
    dt: float
    followers: tuple[str, ...]
    mode: str = 'lockstep'
    run_id: str = ''

    def to_json(self) -> str:
        """The JSON text published in RunDescription.description."""
        return json.dumps({'format': LEADER_FORMAT, 'leader_id': self.leader_id,
                           'path': self.path.to_dict(), 'dt': self.dt,
                           'followers': list(self.followers), 'mode': self.mode,
                           'run_id': self.run_id}, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> 'LeaderDescription':
        """Inverse of :meth:`to_json`; ValueError saying what is wrong."""
        data = _load(text, LEADER_FORMAT)
        try:
            return cls(str(data['leader_id']), LeaderPath.from_dict(data['path']),
                       float(data['dt']), tuple(data['followers']), str(data['mode']),
                       str(data.get('run_id', '')))
        except (KeyError, TypeError) as error:
            raise ValueError(f'leader description lacks or mangles {error}') from None


# --- the scenario handshake: descriptions as node parameters, and how two of them differ -----
def path_parameters(path: LeaderPath) -> dict[str, Any]:
    """The node parameters (path, v_leader, ...) that describe ``path``."""
    return {'path': path.kind, 'v_leader': path.speed, 'omega_leader': path.yaw_rate,
            'amplitude': path.amplitude, 'period': path.period,
            'segment_durations': [s.duration for s in path.segments] or [1.0],
            'segment_speeds': [s.speed for s in path.segments] or [1.0],
            'segment_yaw_rates': [s.yaw_rate for s in path.segments] or [0.0],
            'repeat_segments': path.repeat}


def scenario_parameters(scenario: Scenario) -> dict[str, Any]:
    """The node parameters that describe ``scenario`` (the sensor's noise as range_sigma or
    bearing_sigma, both with bearing_every for range-bearing; r as deviation_fraction of
    |p_o|)."""
    sigmas = {'range_sigma': scenario.sigma, 'bearing_sigma': scenario.sigma_bearing,
              'bearing_every': scenario.bearing_every} \
        if scenario.measurement == RANGE_BEARING else \
        {f'{scenario.measurement}_sigma': scenario.sigma}
    return {'measurement': scenario.measurement, 'dt': scenario.dt, **sigmas,
            'sigma_v': scenario.sigma_v,
            'sigma_omega': scenario.sigma_omega, 'sigma_v_leader': scenario.sigma_v_leader,
            'sigma_omega_leader': scenario.sigma_omega_leader, 'kinematics': scenario.kinematics,
            'formation_slot': list(scenario.p_o),
            'deviation_fraction': scenario.r / scenario.d_o,
            'initial_covariance': list(scenario.initial_covariance),
            'max_speed': scenario.max_speed or 0.0,
            'safety_distance': scenario.safety_distance,
            **path_parameters(scenario.leader)}


def follower_parameters(description: RunDescription, strategy: bool) -> dict[str, Any]:
    """The parameters of a follower node that describe its run (with the strategy and its
    options as '<strategy>_<option>' when ``strategy``)."""
    values = {'run_id': description.run_id, 'mode': description.mode,
              'follower_id': description.follower_id, 'leader_id': description.leader_id,
              'seed': description.seed, 'trial': description.trial,
              **scenario_parameters(description.scenario)}
    if strategy:
        values['strategy'] = description.strategy
        values.update({f'{description.strategy}_{k}': v
                       for k, v in description.options.items()})
    return values


def leader_parameters(description: LeaderDescription) -> dict[str, Any]:
    """The parameters of leader_sim that a follower's run must share."""
    return {'run_id': description.run_id, 'mode': description.mode,
            'leader_id': description.leader_id, 'dt': description.dt,
            **path_parameters(description.path)}


def _same(a: Any, b: Any, rtol: float = 1e-9) -> bool:
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y, rtol) for x, y in zip(a, b))
    if isinstance(a, (int, float)) and isinstance(b, (int, float)) \
            and not isinstance(a, bool) and not isinstance(b, bool):
        return a == b or abs(a - b) <= rtol * max(abs(a), abs(b))
    return bool(a == b)


def parameter_differences(mine: dict[str, Any],
                          theirs: dict[str, Any]) -> list[tuple[str, Any, Any]]:
    """(parameter, my value, their value) for every parameter both describe that differs
    (numbers: relative 1e-9), in the order of ``mine``. My run_id '' accepts any run (the
    node parameter's meaning: e.g. an estimator driven by a replayed bag); theirs '' does not
    (their messages carry '' and would be refused as another run's)."""
    return [(name, value, theirs[name]) for name, value in mine.items()
            if name in theirs and not _same(value, theirs[name])
            and not (name == 'run_id' and value == '')]


def follower_differences(mine: RunDescription, theirs: RunDescription,
                         strategy: bool = False) -> list[tuple[str, Any, Any]]:
    """How two descriptions of one follower's run differ, as node parameters."""
    return parameter_differences(follower_parameters(mine, strategy),
                                 follower_parameters(theirs, strategy))


def leader_differences(follower: RunDescription,
                       leader: LeaderDescription) -> list[tuple[str, Any, Any]]:
    """How a follower's run and its leader's description disagree, as node parameters (the
    follower's value first); 'followers' when the leader does not serve this follower."""
    out = parameter_differences(leader_parameters(follower.leader_view()),
                                leader_parameters(leader))
    if follower.follower_id not in leader.followers:
        out.append(('followers', follower.follower_id, list(leader.followers)))
    return out
