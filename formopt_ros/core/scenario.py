"""What defines a run: the leader's path and one follower's scenario (paper Sec. V defaults).

Everything here is plain data with validation and a JSON-friendly dict form, so that the same
description configures the simulator, the study, the nodes and is recorded in every bag.
"""
from __future__ import annotations

import math
import re
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from formopt_ros.core.cost import check_disc
from formopt_ros.core.model import BEARING, EULER, EXACT, KINEMATICS, MEASUREMENT_KINDS, RANGE
from formopt_ros.core.strategies import make_strategy

#: Shapes of leader path.
PATH_KINDS = ('straight', 'arc', 's-curve', 'segments')


def _finite(name: str, value: float) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f'{name} must be a finite number, got {value!r}')
    return number


def _positive(name: str, value: float, unit: str) -> float:
    number = _finite(name, value)
    if number <= 0.0:
        raise ValueError(f'{name} must be > 0 ({unit}), got {value!r}')
    return number


def _non_negative(name: str, value: float, unit: str) -> float:
    number = _finite(name, value)
    if number < 0.0:
        raise ValueError(f'{name} must be >= 0 ({unit}), got {value!r}')
    return number


@dataclass(frozen=True)
class Segment:
    """One piece of a segmented leader path: ``duration`` s at (speed m/s, yaw_rate rad/s)."""

    duration: float
    speed: float
    yaw_rate: float = 0.0

    def __post_init__(self) -> None:
        _positive('segment duration', self.duration, 's')
        _finite('segment speed', self.speed)
        _finite('segment yaw_rate', self.yaw_rate)


@dataclass(frozen=True)
class LeaderPath:
    """The leader's velocities over time, piecewise constant per sub-step.

    Attributes:
        kind: 'straight' (speed, no turn), 'arc' (constant ``yaw_rate``), 's-curve' (yaw rate
            ``amplitude sin(2 pi t / period)``) or 'segments' (the list ``segments``, then the
            last one held, or the list repeated when ``repeat``).
        speed: forward speed, m/s (all kinds but 'segments').
        yaw_rate: yaw rate of an arc, rad/s.
        amplitude: peak yaw rate of an S-curve, rad/s.
        period: period of an S-curve, s.
        segments: pieces of a segmented path.
        repeat: repeat the segments cyclically instead of holding the last one.

    The velocity of global sub-step n (0-based, length dt) is the path's value at its start
    t = n dt.
    """

    kind: str = 'straight'
    speed: float = 1.0
    yaw_rate: float = 0.0
    amplitude: float = 0.0
    period: float = 10.0
    segments: tuple[Segment, ...] = ()
    repeat: bool = False

    def __post_init__(self) -> None:
        if self.kind not in PATH_KINDS:
            raise ValueError(f'leader path kind must be one of {PATH_KINDS}, got {self.kind!r}')
        _finite('leader speed', self.speed)
        _finite('leader yaw_rate', self.yaw_rate)
        _finite('leader amplitude', self.amplitude)
        _positive('leader period', self.period, 's')
        if self.kind == 'straight' and self.yaw_rate != 0.0:
            raise ValueError(f'a straight leader path has yaw_rate 0, got {self.yaw_rate!r}; '
                             "use kind 'arc'")
        if self.kind == 'segments' and not self.segments:
            raise ValueError("a leader path of kind 'segments' needs at least one segment")
        object.__setattr__(self, 'segments', tuple(
            s if isinstance(s, Segment) else Segment(**s) for s in self.segments))

    @classmethod
    def constant(cls, speed: float, yaw_rate: float = 0.0) -> 'LeaderPath':
        """Straight when ``yaw_rate`` is 0, else an arc."""
        return cls('straight' if yaw_rate == 0.0 else 'arc', speed, yaw_rate)

    def velocity(self, substep: int, dt: float) -> tuple[float, float]:
        """(v_L m/s, omega_L rad/s) during global sub-step ``substep`` (0-based) of length dt."""
        t = substep * dt
        if self.kind == 'straight':
            return self.speed, 0.0
        if self.kind == 'arc':
            return self.speed, self.yaw_rate
        if self.kind == 's-curve':
            return self.speed, self.amplitude * math.sin(2.0 * math.pi * t / self.period)
        total = sum(s.duration for s in self.segments)
        if self.repeat:
            t = math.fmod(t, total)
        for segment in self.segments:
            if t < segment.duration:
                return segment.speed, segment.yaw_rate
            t -= segment.duration
        last = self.segments[-1]
        return last.speed, last.yaw_rate

    def is_straight(self) -> bool:
        """True when the leader never turns (the unobservable case of the paper)."""
        if self.kind == 'segments':
            return all(s.yaw_rate == 0.0 for s in self.segments)
        return self.kind == 'straight' or (self.kind == 's-curve' and self.amplitude == 0.0)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (inverse: :meth:`from_dict`)."""
        out = asdict(self)
        out['segments'] = [asdict(s) for s in self.segments]
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> 'LeaderPath':
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError naming them."""
        _check_keys('leader path', data, {f.name for f in fields(cls)})
        values = dict(data)
        values['segments'] = tuple(Segment(**s) if isinstance(s, dict) else s
                                   for s in values.get('segments', ()))
        return cls(**values)


def _check_keys(what: str, data: dict[str, Any], known: set[str]) -> None:
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f'{what}: unknown keys {unknown} (known: {sorted(known)})')


@dataclass(frozen=True)
class Scenario:
    """Everything that defines one follower's run except strategy and seed (paper Sec. V).

    Attributes:
        measurement: 'range' or 'bearing'.
        p_o: formation slot in the leader frame, m.
        r: allowed deviation from the slot, m; 1e-6 |p_o| <= r <= 0.999 |p_o|.
        sigma: measurement noise standard deviation, m or rad.
        leader: the leader's path.
        dt: sub-step length, s.
        sigma_v, sigma_omega: follower velocity noise standard deviations, m/s and rad/s.
        initial_covariance: diagonal of P_1|1 (m^2, m^2, rad^2); the estimate starts at
            [p_o, 0] and the truth is drawn from N(estimate, P_1|1).
        sigma_v_leader, sigma_omega_leader: noise standard deviations of the leader's odometry
            as the estimator receives it, m/s and rad/s (0: known exactly, as in the paper).
        kinematics: 'exact' (arcs of constant velocities) or 'euler' (the paper's eq. 9, as
            its Sec. V simulates), for the truth and the EKF alike.
    """

    measurement: str
    p_o: tuple[float, float]
    r: float
    sigma: float
    leader: LeaderPath = field(default_factory=LeaderPath)
    dt: float = 0.05
    sigma_v: float = 0.2
    sigma_omega: float = 0.1
    initial_covariance: tuple[float, float, float] = (0.1, 0.1, 4e-4)
    sigma_v_leader: float = 0.0
    sigma_omega_leader: float = 0.0
    kinematics: str = EXACT

    def __post_init__(self) -> None:
        if self.measurement not in MEASUREMENT_KINDS:
            raise ValueError(f'measurement must be one of {MEASUREMENT_KINDS}, '
                             f'got {self.measurement!r}')
        p_o = tuple(_finite('p_o', v) for v in self.p_o)
        if len(p_o) != 2:
            raise ValueError(f'p_o must be [x, y] in m, got {list(self.p_o)!r}')
        if math.hypot(*p_o) == 0.0:
            raise ValueError('p_o must not be the leader position [0, 0]')
        r = _positive('r', self.r, 'm')
        check_disc(p_o[0], p_o[1], r)
        _positive('sigma', self.sigma, 'm' if self.measurement == RANGE else 'rad')
        _positive('dt', self.dt, 's')
        _non_negative('sigma_v', self.sigma_v, 'm/s')
        _non_negative('sigma_omega', self.sigma_omega, 'rad/s')
        _non_negative('sigma_v_leader', self.sigma_v_leader, 'm/s')
        _non_negative('sigma_omega_leader', self.sigma_omega_leader, 'rad/s')
        if self.kinematics not in KINEMATICS:
            raise ValueError(f'kinematics must be one of {KINEMATICS}, got {self.kinematics!r}')
        covariance = tuple(_positive('initial_covariance', v, 'm^2 or rad^2')
                           for v in self.initial_covariance)
        if len(covariance) != 3:
            raise ValueError('initial_covariance must have 3 entries (x, y, phi), got '
                             f'{list(self.initial_covariance)!r}')
        leader = self.leader if isinstance(self.leader, LeaderPath) else \
            LeaderPath.from_dict(self.leader)
        object.__setattr__(self, 'p_o', p_o)
        for name in ('r', 'sigma', 'dt', 'sigma_v', 'sigma_omega', 'sigma_v_leader',
                     'sigma_omega_leader'):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, 'initial_covariance', covariance)
        object.__setattr__(self, 'leader', leader)

    @classmethod
    def paper(cls, measurement: str, **overrides: Any) -> 'Scenario':
        """The paper's Sec. V settings for 'range' (p_o = [-1, -2], sigma_d = 0.1 m) or
        'bearing' (p_o = [-1, 2], sigma_beta = 0.02 rad); r = 0.1 |p_o|, and its eq. (9) as the
        kinematics ('euler'), unless overridden."""
        if measurement not in MEASUREMENT_KINDS:
            raise ValueError(f'measurement must be one of {MEASUREMENT_KINDS}, '
                             f'got {measurement!r}')
        p_o = tuple(overrides.pop('p_o', (-1.0, -2.0) if measurement == RANGE
                                  else (-1.0, 2.0)))
        values: dict[str, Any] = dict(measurement=measurement, p_o=p_o,
                                      r=0.1 * math.hypot(*p_o),
                                      sigma=0.1 if measurement == RANGE else 0.02,
                                      kinematics=EULER)
        values.update(overrides)
        return cls(**values)

    @property
    def slot(self) -> np.ndarray:
        """p_o as a numpy array, shape (2,), m."""
        return np.array(self.p_o, dtype=float)

    @property
    def d_o(self) -> float:
        """|p_o|, m."""
        return math.hypot(*self.p_o)

    def initial_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(x_1|1 = [p_o, 0] (3,), P_1|1 (3, 3))."""
        return np.array([self.p_o[0], self.p_o[1], 0.0]), np.diag(self.initial_covariance)

    def to_dict(self) -> dict[str, Any]:
        """JSON-friendly form (inverse: :meth:`from_dict`)."""
        out = asdict(self)
        out['p_o'] = list(self.p_o)
        out['initial_covariance'] = list(self.initial_covariance)
        out['leader'] = self.leader.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> 'Scenario':
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError naming them."""
        _check_keys('scenario', data, {f.name for f in fields(cls)})
        values = dict(data)
        if isinstance(values.get('leader'), dict):
            values['leader'] = LeaderPath.from_dict(values['leader'])
        for key in ('p_o', 'initial_covariance'):
            if key in values:
                values[key] = tuple(values[key])
        return cls(**values)

    def differences(self, other: 'Scenario', rtol: float = 1e-12) -> list[tuple[str, Any, Any]]:
        """(field, this value, other value) for every field that differs (relative rtol)."""
        mine, theirs = _flatten(self.to_dict()), _flatten(other.to_dict())
        out = []
        for key in sorted(set(mine) | set(theirs)):
            a, b = mine.get(key), theirs.get(key)
            if isinstance(a, float) and isinstance(b, float):
                same = a == b or abs(a - b) <= rtol * max(abs(a), abs(b))
            else:
                same = a == b
            if not same:
                out.append((key, a, b))
        return out


def _flatten(data: Any, prefix: str = '') -> dict[str, Any]:
    """Nested dicts and lists as {'a.b.0': value}; ints become floats so 1 == 1.0 compares."""
    if isinstance(data, dict):
        out: dict[str, Any] = {}
        for key, value in data.items():
            out.update(_flatten(value, f'{prefix}{key}.'))
        return out
    if isinstance(data, (list, tuple)):
        out = {}
        for index, value in enumerate(data):
            out.update(_flatten(value, f'{prefix}{index}.'))
        return out
    if isinstance(data, int) and not isinstance(data, bool):
        data = float(data)
    return {prefix[:-1]: data}


#: A robot id: a ROS name token (it is the robot's namespace and the stem of its frames).
_ID = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')


def check_id(what: str, value: object) -> str:
    """``value`` if it is a valid robot id (letters, digits, underscores; a letter first)."""
    if not isinstance(value, str) or not _ID.match(value):
        raise ValueError(f'{what} must be a name of letters, digits and underscores starting '
                         f'with a letter (it becomes a ROS namespace), got {value!r}')
    return value


@dataclass(frozen=True)
class FollowerSpec:
    """One follower of a formation.

    Attributes:
        id: its id (namespace and frame stem).
        scenario: what its estimator assumes (and its simulator does).
        strategy: motion strategy name; options: its options.
        seed: its random streams are seeded by (seed, trial).
        interfaces: 'simulated' (follower_sim and estimator_planner: the paper's protocol in
            lockstep or real time) or 'real' (field_sim and follower_estimator: standard
            messages, cmd_vel, in real time).
        real: parameters of field_sim and follower_estimator (interfaces 'real').
    """

    id: str
    scenario: Scenario
    strategy: str = 'ram'
    options: dict[str, Any] = field(default_factory=dict)
    seed: int = 0
    interfaces: str = 'simulated'
    real: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_id('follower id', self.id)
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f'follower {self.id}: seed must be an integer >= 0, '
                             f'got {self.seed!r}')
        make_strategy(self.strategy, **self.options)      # ValueError naming the option
        if self.interfaces not in INTERFACES:
            raise ValueError(f'follower {self.id}: interfaces must be one of '
                             f'{", ".join(INTERFACES)}, got {self.interfaces!r}')
        if self.real and self.interfaces != 'real':
            raise ValueError(f"follower {self.id}: 'real' settings need interfaces: real")


@dataclass(frozen=True)
class Formation:
    """One leader and its followers, sharing the leader's path and the sub-step length.

    Attributes:
        leader_id: the leader's id (namespace and frame).
        followers: the followers, in the order of the file.
        trial: trial index of every follower's random streams.
    """

    leader_id: str
    followers: tuple[FollowerSpec, ...]
    trial: int = 0

    def __post_init__(self) -> None:
        check_id('leader id', self.leader_id)
        if not self.followers:
            raise ValueError('a formation needs at least one follower')
        ids = [f.id for f in self.followers]
        if len(set(ids) | {self.leader_id}) != len(ids) + 1:
            raise ValueError(f'robot ids must be unique, got leader {self.leader_id!r} and '
                             f'followers {ids}')
        first = self.followers[0].scenario
        for follower in self.followers[1:]:
            shared = (follower.scenario.leader, follower.scenario.dt,
                      follower.scenario.kinematics)
            if shared != (first.leader, first.dt, first.kinematics):
                raise ValueError(f'follower {follower.id}: every follower shares the leader '
                                 'path, dt and kinematics')
            if follower.interfaces != self.followers[0].interfaces:
                raise ValueError(f'follower {follower.id}: the followers of one run share '
                                 'their interfaces (simulated or real)')

    @property
    def leader(self) -> LeaderPath:
        """The leader's path."""
        return self.followers[0].scenario.leader

    @property
    def dt(self) -> float:
        """The sub-step length, s."""
        return self.followers[0].scenario.dt

    def follower(self, follower_id: str) -> FollowerSpec:
        """The follower of that id; ValueError naming the ids there are."""
        for follower in self.followers:
            if follower.id == follower_id:
                return follower
        raise ValueError(f'no follower {follower_id!r} in the formation (it has: '
                         f"{', '.join(f.id for f in self.followers)})")

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> 'Formation':
        """A formation from its file layout (see config/formation_fig4.yaml); ValueError that
        names the key for anything unknown, missing or out of range."""
        _check_keys('formation', data, {'leader', 'dt', 'kinematics', 'seed', 'trial',
                                        'followers'})
        leader = dict(data.get('leader') or {})
        _check_keys('formation leader', leader, {'id', 'path'})
        path = LeaderPath.from_dict(dict(leader.get('path') or {}))
        dt = data.get('dt', 0.05)
        kinematics = data.get('kinematics', EXACT)
        seed = data.get('seed', 0)
        followers = data.get('followers')
        if not isinstance(followers, list) or not followers:
            raise ValueError('formation followers must be a non-empty list')
        specs = []
        for index, item in enumerate(followers):
            if not isinstance(item, dict):
                raise ValueError(f'formation follower {index + 1} must be a mapping, '
                                 f'got {item!r}')
            specs.append(_follower_from_dict(item, path, dt, kinematics, seed + index))
        return cls(str(leader.get('id', 'leader')), tuple(specs), int(data.get('trial', 0)))

    def to_dict(self) -> dict[str, Any]:
        """The file layout (inverse of :meth:`from_dict`, every value explicit)."""
        return {
            'leader': {'id': self.leader_id, 'path': self.leader.to_dict()},
            'dt': self.dt, 'kinematics': self.followers[0].scenario.kinematics,
            'trial': self.trial,
            'followers': [{
                'id': f.id, 'sensor': f.scenario.measurement, 'slot': list(f.scenario.p_o),
                'deviation': f.scenario.r / f.scenario.d_o, 'noise': f.scenario.sigma,
                'odometry_noise': [f.scenario.sigma_v, f.scenario.sigma_omega],
                'leader_odometry_noise': [f.scenario.sigma_v_leader,
                                          f.scenario.sigma_omega_leader],
                'initial_covariance': list(f.scenario.initial_covariance),
                'strategy': f.strategy, 'options': dict(f.options), 'seed': f.seed,
                **({'interfaces': f.interfaces, 'real': dict(f.real)}
                   if f.interfaces != 'simulated' else {})}
                for f in self.followers]}


_FOLLOWER_KEYS = {'id', 'sensor', 'slot', 'deviation', 'noise', 'odometry_noise',
                  'leader_odometry_noise', 'initial_covariance', 'strategy', 'options', 'seed',
                  'interfaces', 'real'}
#: How a follower's nodes talk (FollowerSpec.interfaces).
INTERFACES = ('simulated', 'real')


def _follower_from_dict(item: dict[str, Any], path: LeaderPath, dt: float, kinematics: str,
                        default_seed: int) -> FollowerSpec:
    name = item.get('id', '?')
    _check_keys(f'formation follower {name}', item, _FOLLOWER_KEYS)
    missing = sorted({'id', 'sensor', 'slot'} - set(item))
    if missing:
        raise ValueError(f'formation follower {name}: missing keys {missing}')
    try:
        base = Scenario.paper(item['sensor'], p_o=tuple(item['slot']))
        sigma_v, sigma_omega = item.get('odometry_noise', (base.sigma_v, base.sigma_omega))
        sigma_v_leader, sigma_omega_leader = item.get('leader_odometry_noise', (0.0, 0.0))
        scenario = Scenario.paper(
            item['sensor'], p_o=base.p_o, r=float(item.get('deviation', 0.1)) * base.d_o,
            sigma=float(item.get('noise', base.sigma)), leader=path, dt=float(dt),
            sigma_v=float(sigma_v), sigma_omega=float(sigma_omega),
            sigma_v_leader=float(sigma_v_leader), sigma_omega_leader=float(sigma_omega_leader),
            kinematics=kinematics,
            initial_covariance=tuple(item.get('initial_covariance',
                                              base.initial_covariance)))
        real = item.get('real') or {}
        if not isinstance(real, dict):
            raise ValueError(f"'real' must be a mapping of parameter names, got {real!r}")
        return FollowerSpec(str(name), scenario, str(item.get('strategy', 'ram')),
                            dict(item.get('options') or {}), item.get('seed', default_seed),
                            str(item.get('interfaces', 'simulated')), dict(real))
    except (TypeError, ValueError) as error:
        raise ValueError(f'formation follower {name}: {error}') from None


__all__ = ['BEARING', 'Formation', 'FollowerSpec', 'LeaderPath', 'PATH_KINDS', 'RANGE',
           'Scenario', 'Segment', 'check_id']
