"""What defines a run: the leader's path and one follower's scenario (paper Sec. V defaults);
a formation of followers is :mod:`formopt_ros.core.formation`.

Everything here is plain data, checked where it is made (the one boundary of a run: every
number against :data:`RANGES`) and with a JSON-friendly dict form, so that the same
description configures the simulator, the study, the nodes and is recorded in every bag.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import numpy as np

from formopt_ros.core.checks import (
    InvalidInput, as_array, as_bool, as_choice, as_integer, as_real)
from formopt_ros.core.cost import MAX_DEVIATION, MIN_DEVIATION, check_disc
from formopt_ros.core.model import (
    BEARING, EULER, EXACT, KINEMATICS, RANGE, RANGE_BEARING, SENSOR_KINDS)

#: Shapes of leader path.
PATH_KINDS = ('straight', 'arc', 's-curve', 'segments')
#: The admissible range (low, high, unit) of every number of a run, enforced where a run is
#: described (:class:`Scenario`, :class:`LeaderPath`, :class:`Formation`); the node parameters
#: and the commands' flags take their ranges from here. Each keeps a margin to the range of the
#: solvers (cost.SIGMA_RANGE, cost.SLOT_DISTANCE_RANGE), so a run that passes them never fails
#: deeper (test_boundary.py runs each bound). A bearing noise above 1 rad (57 deg) is no bearing
#: sensor: a value meant in degrees (2 for 2 deg) is refused; a range noise below 1 mm (3e-4 m
#: measured) makes the periodic strategy's covariance maps singular. A base's yaw rate above
#: 20 rad/s, a leader's above 10 rad/s (a 10 cm circle at 1 m/s), is one meant in deg/s (45 for
#: 45 deg/s); an angle (a mount's, an initial heading) beyond one turn is one meant in degrees.
RANGES: dict[str, tuple[float, float, str]] = {
    'range_sigma': (1e-3, 1e3, 'm'),
    'bearing_sigma': (1e-6, 1.0, 'rad'),
    'range_variance': (0.0, 1e6, 'm^2'),
    'dt': (1e-3, 10.0, 's'),
    'slot': (-1e4, 1e4, 'm'),
    'deviation': (MIN_DEVIATION, MAX_DEVIATION, '|p_o|'),
    'initial_covariance': (1e-12, 1e6, 'm^2 or rad^2'),
    'sigma_v': (0.0, 100.0, 'm/s'),
    'sigma_omega': (0.0, 100.0, 'rad/s'),
    'sigma_v_leader': (0.0, 100.0, 'm/s'),
    'sigma_omega_leader': (0.0, 100.0, 'rad/s'),
    'speed': (-100.0, 100.0, 'm/s'),
    'yaw_rate': (-10.0, 10.0, 'rad/s'),
    'amplitude': (-10.0, 10.0, 'rad/s'),
    'period': (1e-3, 1e6, 's'),
    'duration': (1e-3, 1e6, 's'),
    'seed': (0, 2**31 - 1, ''),
    'trial': (0, 2**31 - 1, ''),
    'max_speed': (1e-3, 1e3, 'm/s'),
    'max_yaw_rate': (1e-3, 20.0, 'rad/s'),
    'safety_distance': (0.0, 1e4, 'm'),
    'angle': (-2.0 * math.pi - 0.01, 2.0 * math.pi + 0.01, 'rad'),     # 6.2832 is one turn
}


def ranged(name: str, value: object, key: str | None = None) -> float:
    """``value`` as a float in the range ``RANGES[key or name]``, else InvalidInput naming
    ``name``."""
    low, high, unit = RANGES[key or name]
    return as_real(name, value, low, high, unit=unit)


def ranged_integer(name: str, value: object, key: str | None = None) -> int:
    """``value`` as an int in the range ``RANGES[key or name]``, else InvalidInput naming
    ``name``."""
    low, high, _ = RANGES[key or name]
    return as_integer(name, value, int(low), int(high))


@dataclass(frozen=True)
class Segment:
    """One piece of a segmented leader path: ``duration`` s at (speed m/s, yaw_rate rad/s)."""

    duration: float
    speed: float
    yaw_rate: float = 0.0

    def __post_init__(self) -> None:
        for name in ('duration', 'speed', 'yaw_rate'):
            object.__setattr__(self, name, ranged(f'segment {name}', getattr(self, name), name))

    @classmethod
    def from_dict(cls, data: object) -> 'Segment':
        """A segment from {'duration', 'speed', 'yaw_rate' (default 0)}."""
        if isinstance(data, Segment):
            return data
        if not isinstance(data, dict):
            raise InvalidInput('leader segments', f'must be mappings, got {data!r}')
        check_keys('leader segment', data, {'duration', 'speed', 'yaw_rate'})
        return cls(data.get('duration'), data.get('speed'),  # type: ignore[arg-type]
                   data.get('yaw_rate', 0.0))


#: Euler kinematics: the largest leader turn per sub-step dt, rad (the relative position grows
#: by 12 % per sub-step there; the paper's turning examples stay below 0.05 rad).
EULER_TURN_BOUND = 0.5
#: The fields of :class:`LeaderPath` each kind of path uses (the others keep their defaults).
PATH_FIELDS = {'straight': ('speed',), 'arc': ('speed', 'yaw_rate'),
               's-curve': ('speed', 'amplitude', 'period'), 'segments': ('segments', 'repeat')}
#: The field that sets how fast a path of each kind turns (segments: each segment's yaw_rate).
TURN_FIELDS = {'arc': 'yaw_rate', 's-curve': 'amplitude'}


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
        as_choice('leader path kind', self.kind, PATH_KINDS)
        for name in ('speed', 'yaw_rate', 'amplitude', 'period'):
            object.__setattr__(self, name, ranged(f'leader {name}', getattr(self, name), name))
        object.__setattr__(self, 'repeat', as_bool('leader repeat', self.repeat))
        if self.kind == 'straight' and self.yaw_rate != 0.0:
            raise InvalidInput('leader yaw_rate', f'of a straight path is 0, got '
                                                  f"{self.yaw_rate!r}; use kind 'arc'")
        for name in ('speed', 'yaw_rate', 'amplitude', 'period', 'segments', 'repeat'):
            value, default = getattr(self, name), _PATH_DEFAULTS[name]
            changed = bool(value) if name == 'segments' else value != default
            if name not in PATH_FIELDS[self.kind] and changed:
                owners = [kind for kind, used in PATH_FIELDS.items() if name in used]
                raise InvalidInput(f'leader {name}', f'is not used by a path of kind '
                                   f'{self.kind!r} (only by {owners}), got {value!r}')
        turn = TURN_FIELDS.get(self.kind)
        if turn is not None and getattr(self, turn) == 0.0:
            raise InvalidInput(f'leader {turn}', f"of a path of kind {self.kind!r} must not be 0 "
                                                 "(a leader that never turns is kind 'straight')")
        if not isinstance(self.segments, (list, tuple)):
            raise InvalidInput('leader segments', f'must be a list, got {self.segments!r}')
        if self.kind == 'segments' and not self.segments:
            raise InvalidInput('leader segments', "of a path of kind 'segments' must hold at "
                                                  'least one segment')
        object.__setattr__(self, 'segments', tuple(map(Segment.from_dict, self.segments)))

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

    def extreme_motions(self) -> list[tuple[float, float]]:
        """The (v m/s, omega rad/s) among which the path's speeds and yaw rates reach their
        extremes: each segment, an S-curve's two peaks, or the one constant motion."""
        if self.kind == 'segments':
            return [(g.speed, g.yaw_rate) for g in self.segments]
        if self.kind == 's-curve':
            return [(self.speed, self.amplitude), (self.speed, -self.amplitude)]
        return [(self.speed, self.yaw_rate)]

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
        """Inverse of :meth:`to_dict`; unknown keys raise InvalidInput naming them."""
        check_keys('leader path', data, {f.name for f in fields(cls)})
        return cls(**data)


_PATH_DEFAULTS = {f.name: f.default for f in fields(LeaderPath)}


def check_keys(what: str, data: object, known: set[str]) -> None:
    if not isinstance(data, dict):
        raise InvalidInput(what, f'must be a mapping, got {data!r}')
    unknown = sorted(set(data) - known)
    if unknown:
        raise InvalidInput(what, f'has unknown keys {unknown} (known: {sorted(known)})')


@dataclass(frozen=True)
class Scenario:
    """Everything that defines one follower's run except strategy and seed (paper Sec. V).

    Attributes:
        measurement: 'range', 'bearing' or 'range-bearing' (both at a step).
        p_o: formation slot in the leader frame, m.
        r: allowed deviation from the slot, m; 1e-6 |p_o| <= r <= 0.999 |p_o|.
        sigma: measurement noise standard deviation, m or rad ('range-bearing': the range's).
        leader: the leader's path.
        dt: sub-step length, s.
        sigma_v, sigma_omega: follower velocity noise standard deviations, m/s and rad/s.
        initial_covariance: diagonal of P_1|1 (m^2, m^2, rad^2); the estimate starts at
            [p_o, 0] and the truth is drawn from N(estimate, P_1|1).
        sigma_v_leader, sigma_omega_leader: noise standard deviations of the leader's odometry
            as the estimator receives it, m/s and rad/s (0: known exactly, as in the paper).
        kinematics: 'exact' (arcs of constant velocities) or 'euler' (the paper's eq. 9, as
            its Sec. V simulates), for the truth and the EKF alike.
        max_speed: bound on the follower's mean world-frame speed over a measurement step,
            m/s (None: none, the paper's protocol); every strategy plans inside the disc it
            can reach (:mod:`formopt_ros.core.reach`).
        safety_distance: distance to keep from the leader, m (0: none, the paper's).
        sigma_bearing: 'range-bearing' only: the bearing noise standard deviation, rad.
        bearing_every: 'range-bearing' only: the bearing arrives at every k-th measurement step
            (steps k, 2k, ...; the range at every step); 1: both at every step.
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
    max_speed: float | None = None
    safety_distance: float = 0.0
    sigma_bearing: float = 0.0
    bearing_every: int = 1

    def __post_init__(self) -> None:
        kind = as_choice('measurement', self.measurement, SENSOR_KINDS)
        p_o = tuple(ranged('p_o', v, 'slot') for v in as_array('p_o', self.p_o, (2,)).tolist())
        r = as_real('r', self.r, unit='m')
        check_disc(p_o[0], p_o[1], r)
        covariance = as_array('initial_covariance', self.initial_covariance, (3,)).tolist()
        values: dict[str, object] = {
            'p_o': p_o, 'r': r, 'sigma': ranged('sigma', self.sigma, f'{kind}_sigma'
                                                if kind != RANGE_BEARING else 'range_sigma'),
            'initial_covariance': tuple(ranged('initial_covariance', v) for v in covariance),
            'kinematics': as_choice('kinematics', self.kinematics, KINEMATICS),
            'leader': self.leader if isinstance(self.leader, LeaderPath) else
            LeaderPath.from_dict(self.leader)}
        for name in ('dt', 'sigma_v', 'sigma_omega', 'sigma_v_leader', 'sigma_omega_leader'):
            values[name] = ranged(name, getattr(self, name))
        max_speed = self.max_speed
        if max_speed is not None and not (isinstance(max_speed, (int, float))
                                          and not isinstance(max_speed, bool)
                                          and max_speed == math.inf):
            max_speed = ranged('max_speed', max_speed)
        values['max_speed'] = None if max_speed is None or max_speed == math.inf else max_speed
        values['safety_distance'] = ranged('safety_distance', self.safety_distance)
        if kind == RANGE_BEARING:
            values['sigma_bearing'] = ranged('sigma_bearing', self.sigma_bearing, 'bearing_sigma')
            values['bearing_every'] = as_integer('bearing_every', self.bearing_every, 1, 10**6)
        elif (self.sigma_bearing, self.bearing_every) != (0.0, 1):
            raise InvalidInput('sigma_bearing', f'and bearing_every are for range-bearing only, '
                                                f'got {self.sigma_bearing!r}, '
                                                f'{self.bearing_every!r} for {kind!r}')
        for name, value in values.items():
            object.__setattr__(self, name, value)
        check_limits(self)

    @classmethod
    def paper(cls, measurement: str, **overrides: Any) -> 'Scenario':
        """The paper's Sec. V settings for 'range' (p_o = [-1, -2], sigma_d = 0.1 m) or
        'bearing' (p_o = [-1, 2], sigma_beta = 0.02 rad); r = 0.1 |p_o|, and its eq. (9) as the
        kinematics ('euler'), unless overridden. 'range-bearing': the range follower's slot
        with both of the paper's noises."""
        as_choice('measurement', measurement, SENSOR_KINDS)
        p_o = tuple(as_array('p_o', overrides.pop(
            'p_o', (-1.0, 2.0) if measurement == BEARING else (-1.0, -2.0)), (2,)).tolist())
        values: dict[str, Any] = dict(measurement=measurement, p_o=p_o,
                                      r=0.1 * math.hypot(*p_o),
                                      sigma=0.02 if measurement == BEARING else 0.1,
                                      kinematics=EULER)
        if measurement == RANGE_BEARING:
            values['sigma_bearing'] = 0.02
        values.update(overrides)
        return cls(**values)

    @property
    def slot(self) -> np.ndarray:
        """p_o as a numpy array, shape (2,), m."""
        return np.array(self.p_o, dtype=float)

    def bearing_at(self, step: int) -> bool:
        """'range-bearing': True when the bearing arrives at measurement step ``step``
        (1-based; every ``bearing_every``-th step)."""
        return step % self.bearing_every == 0

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
        if self.measurement != RANGE_BEARING:       # the scalar kinds' records stay as they were
            del out['sigma_bearing'], out['bearing_every']
        out['p_o'] = list(self.p_o)
        out['initial_covariance'] = list(self.initial_covariance)
        out['leader'] = self.leader.to_dict()
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> 'Scenario':
        """Inverse of :meth:`to_dict`; unknown keys raise InvalidInput naming them."""
        check_keys('scenario', data, {f.name for f in fields(cls)})
        return cls(**data)

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


def slowest_speed_in_disc(p_o: tuple[float, float], r: float, speed: float,
                          yaw_rate: float) -> float:
    """The least world-frame speed (m/s) of a point held fixed in the leader frame inside the
    disc |p - p_o| <= r while the leader drives (speed m/s, yaw_rate rad/s): a point p moves
    at (v - omega y, omega x), of length |omega| times its distance from the instantaneous
    centre of rotation (0, v / omega); |v| when the leader drives straight."""
    if yaw_rate == 0.0:
        return abs(speed)
    distance = math.hypot(p_o[0], p_o[1] - speed / yaw_rate)
    return abs(yaw_rate) * max(0.0, distance - r)


def keep_pace_speed(scenario: 'Scenario') -> float:
    """The least world-frame speed (m/s) at which a point of the slot's disc keeps pace with
    the leader through every motion of its path (:func:`slowest_speed_in_disc` at the path's
    extreme motions): a speed limit below it is refused."""
    return max(slowest_speed_in_disc(scenario.p_o, scenario.r, v, w)
               for v, w in scenario.leader.extreme_motions())


def check_limits(scenario: 'Scenario') -> None:
    """Refuse limits no follower can meet, naming the field: a leader turning faster than the
    Euler kinematics can describe, a safety distance that leaves no point of the slot's disc,
    a speed limit below the least speed at which any point of the disc keeps pace with the
    leader (for the leader's extreme motions)."""
    s = scenario
    path = s.leader
    motions = path.extreme_motions()
    turn = max(abs(w) for _, w in motions)
    if s.kinematics == EULER and turn * s.dt > EULER_TURN_BOUND:
        name = TURN_FIELDS.get(path.kind, 'segments')
        raise InvalidInput(f'leader {name}', f'{turn:g} rad/s turns {turn * s.dt:.3g} rad per dt '
                           f"= {s.dt:g} s: the paper's Euler kinematics (eq. 9) is no model of "
                           'that (it scales the relative position by sqrt(1 + (omega dt)^2) '
                           f'= {math.hypot(1.0, turn * s.dt):.3g} per dt); use exact kinematics '
                           f'or at most {EULER_TURN_BOUND / s.dt:.3g} rad/s (rad/s, not deg/s)')
    d_o = math.hypot(*s.p_o)
    if s.safety_distance >= d_o + s.r:
        raise InvalidInput('safety_distance', f'{s.safety_distance:g} m leaves no point of the '
                           f"slot's disc (it reaches {d_o + s.r:.6g} m from the leader): use "
                           f'less than {d_o + s.r:.6g} m')
    if s.max_speed is None:
        return
    need = keep_pace_speed(s)
    if s.max_speed < need:
        step = 10.0 ** (math.floor(math.log10(need)) - 5)      # 6 significant digits, up
        shown = math.ceil(need / step) * step
        raise InvalidInput('max_speed', f'{s.max_speed:g} m/s is below {shown:.6g} m/s, the '
                           "least world-frame speed at which a point of the slot's disc keeps "
                           "pace with the leader's motion (the follower would fall behind its "
                           f'disc for good): use at least {shown:.6g} m/s')


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


__all__ = ['BEARING', 'LeaderPath', 'PATH_KINDS', 'RANGE', 'Scenario', 'Segment', 'check_keys',
           'ranged', 'ranged_integer']
