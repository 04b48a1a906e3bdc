"""A formation: the leader and its followers, each with its scenario, strategy and interfaces,
as read from a formation file (the ids, the keys, every value checked where it is read)."""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.model import EXACT, RANGE_BEARING
from formopt_ros.core.scenario import (
    LeaderPath, Scenario, check_keys, ranged, ranged_integer)
from formopt_ros.core.strategies import make_strategy


#: A robot id: a ROS name token (it is the robot's namespace and the stem of its frames).
_ID = re.compile(r'^[A-Za-z][A-Za-z0-9_]*$')
#: Longest robot id, bytes: the longest file name derived from an id,
#: '<id>.follower_estimator.json.tmp' (28 bytes more), stays far under the 255 bytes of a file
#: name, and a topic '<prefix>/<id>/sim_description' under the DDS name limit (256).
ID_MAX_LENGTH = 64
#: Frame names an id may not take (the robot's body frame is its id): the REP 105 frames and
#: the frames of the run (wire/topics.py: the odometry frame and the leaves under a robot).
RESERVED_FRAMES = ('odom', 'map', 'world', 'earth', 'base_link', 'base_footprint', 'truth',
                   'estimate', 'uwb', 'camera')


def check_id(what: str, value: object, frame: bool = True) -> str:
    """``value`` if it is a valid robot id, else InvalidInput naming ``what`` and the rule.

    The rules: letters, digits and underscores, a letter first (a ROS name token), no '__'
    (ROS reserves it), at most :data:`ID_MAX_LENGTH` characters (file names derive from ids),
    and, when ``frame`` (the id names a frame), none of :data:`RESERVED_FRAMES`.
    """
    if not isinstance(value, str) or not _ID.match(value):
        raise InvalidInput(what, 'must be a name of letters, digits and underscores starting '
                                 f'with a letter (it becomes a ROS namespace), got {value!r}')
    if '__' in value:
        raise InvalidInput(what, f"must not contain '__' (ROS reserves it), got {value!r}")
    if len(value) > ID_MAX_LENGTH:
        raise InvalidInput(what, f'must be at most {ID_MAX_LENGTH} characters (file names '
                                 f'derive from it), got {len(value)}: {value[:20]!r}...')
    if frame and value in RESERVED_FRAMES:
        raise InvalidInput(what, f'must not be a reserved frame name '
                                 f"({', '.join(RESERVED_FRAMES)}), got {value!r}")
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
        if not isinstance(self.scenario, Scenario):
            raise InvalidInput('scenario', f'must be a Scenario, got {self.scenario!r}')
        object.__setattr__(self, 'seed', ranged_integer('seed', self.seed))
        if not isinstance(self.options, dict):
            raise InvalidInput('options', f'must be a mapping, got {self.options!r}')
        make_strategy(self.strategy, **self.options)      # ValueError naming the option
        if self.interfaces not in INTERFACES:
            raise InvalidInput('interfaces', f'must be one of {", ".join(INTERFACES)}, got '
                               f'{self.interfaces!r}')
        if self.real and self.interfaces != 'real':
            raise InvalidInput('real', 'settings need interfaces: real')
        if self.scenario.measurement == RANGE_BEARING:
            if self.strategy == 'ram':
                raise InvalidInput('strategy', "ram is the paper's method for one scalar "
                                   'measurement; a range-bearing follower needs another (rq '
                                   'solves it with a certificate)')
            if self.interfaces == 'real':
                raise InvalidInput('interfaces', "'real' takes range or bearing followers "
                                   '(follower_estimator has one sensor): a range-bearing '
                                   'follower runs on the simulated interfaces')


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
        object.__setattr__(self, 'trial', ranged_integer('trial', self.trial))
        if not self.followers:
            raise InvalidInput('followers', 'must hold at least one follower')
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
        check_keys('formation', data, {'leader', 'dt', 'kinematics', 'seed', 'trial',
                                       'followers'})
        leader = data.get('leader') or {}
        check_keys('formation leader', leader, {'id', 'path'})
        path = LeaderPath.from_dict(leader.get('path') or {})
        dt = data.get('dt', 0.05)
        kinematics = data.get('kinematics', EXACT)
        seed = ranged_integer('formation seed', data.get('seed', 0), 'seed')
        followers = data.get('followers')
        if not isinstance(followers, list) or not followers:
            raise InvalidInput('formation followers', f'must be a non-empty list, got '
                                                      f'{followers!r}')
        specs = []
        for index, item in enumerate(followers):
            check_keys(f'formation follower {index + 1}', item, _FOLLOWER_KEYS)
            specs.append(_follower_from_dict(item, path, dt, kinematics, seed + index))
        return cls(leader.get('id', 'leader'), tuple(specs),
                   ranged_integer('formation trial', data.get('trial', 0), 'trial'))

    def to_dict(self) -> dict[str, Any]:
        """The file layout (inverse of :meth:`from_dict`, every value explicit)."""
        return {
            'leader': {'id': self.leader_id, 'path': self.leader.to_dict()},
            'dt': self.dt, 'kinematics': self.followers[0].scenario.kinematics,
            'trial': self.trial,
            'followers': [{
                'id': f.id, 'sensor': f.scenario.measurement, 'slot': list(f.scenario.p_o),
                'deviation': f.scenario.r / f.scenario.d_o,
                **({'noise': [f.scenario.sigma, f.scenario.sigma_bearing],
                    'bearing_every': f.scenario.bearing_every}
                   if f.scenario.measurement == RANGE_BEARING else {'noise': f.scenario.sigma}),
                'odometry_noise': [f.scenario.sigma_v, f.scenario.sigma_omega],
                'leader_odometry_noise': [f.scenario.sigma_v_leader,
                                          f.scenario.sigma_omega_leader],
                'initial_covariance': list(f.scenario.initial_covariance),
                **({'max_speed': f.scenario.max_speed} if f.scenario.max_speed else {}),
                **({'safety_distance': f.scenario.safety_distance}
                   if f.scenario.safety_distance else {}),
                'strategy': f.strategy, 'options': dict(f.options), 'seed': f.seed,
                **({'interfaces': f.interfaces, 'real': dict(f.real)}
                   if f.interfaces != 'simulated' else {})}
                for f in self.followers]}


_FOLLOWER_KEYS = {'id', 'sensor', 'slot', 'deviation', 'noise', 'bearing_every',
                  'odometry_noise', 'leader_odometry_noise', 'initial_covariance', 'max_speed',
                  'safety_distance', 'strategy', 'options', 'seed', 'interfaces', 'real'}
#: The formation file's key of each Scenario field whose name differs.
_FILE_KEYS = {'measurement': 'sensor', 'p_o': 'slot', 'r': 'deviation', 'sigma': 'noise',
              'sigma_bearing': 'noise'}
#: Formation-level keys that every follower's Scenario carries (an error names the formation).
_SHARED_KEYS = {'dt', 'kinematics', 'leader'}
#: How a follower's nodes talk (FollowerSpec.interfaces).
INTERFACES = ('simulated', 'real')


def _follower_from_dict(item: dict[str, Any], path: LeaderPath, dt: float, kinematics: str,
                        default_seed: int) -> FollowerSpec:
    name = item.get('id', '?')
    check_keys(f'formation follower {name}', item, _FOLLOWER_KEYS)
    missing = sorted({'id', 'sensor', 'slot'} - set(item))
    if missing:
        raise InvalidInput(f'formation follower {name}', f'lacks the keys {missing}')
    try:
        base = Scenario.paper(item['sensor'], p_o=item['slot'])
        both = item['sensor'] == RANGE_BEARING
        noise = item.get('noise', [base.sigma, base.sigma_bearing] if both else base.sigma)
        if both:
            sigma, sigma_bearing = _pair('noise', noise, '[range m, bearing rad]')
            sensor = {'sigma': sigma, 'sigma_bearing': sigma_bearing,
                      'bearing_every': item.get('bearing_every', 1)}
        elif 'bearing_every' in item:
            raise InvalidInput('bearing_every', 'is for a range-bearing follower only')
        else:
            sensor = {'sigma': noise}
        sigma_v, sigma_omega = _pair('odometry_noise', item.get(
            'odometry_noise', (base.sigma_v, base.sigma_omega)))
        sigma_v_leader, sigma_omega_leader = _pair('leader_odometry_noise', item.get(
            'leader_odometry_noise', (0.0, 0.0)))
        scenario = Scenario.paper(
            item['sensor'], p_o=base.p_o, r=ranged('deviation', item.get('deviation', 0.1))
            * base.d_o, **sensor, leader=path, dt=dt,
            sigma_v=sigma_v, sigma_omega=sigma_omega, sigma_v_leader=sigma_v_leader,
            sigma_omega_leader=sigma_omega_leader, kinematics=kinematics,
            initial_covariance=item.get('initial_covariance', base.initial_covariance),
            max_speed=item.get('max_speed'),
            safety_distance=item.get('safety_distance', 0.0))
        real = item.get('real') or {}
        if not isinstance(real, dict):
            raise InvalidInput('real', f'must be a mapping of parameter names, got {real!r}')
        default = 'rq' if scenario.measurement == RANGE_BEARING else 'ram'
        return FollowerSpec(name, scenario, item.get('strategy', default),
                            item.get('options') or {}, item.get('seed', default_seed),
                            str(item.get('interfaces', 'simulated')), dict(real))
    except InvalidInput as error:                   # the file's key, not the Scenario field
        key = _FILE_KEYS.get(error.name, error.name)
        where = 'formation' if key in _SHARED_KEYS else f'formation follower {name}:'
        raise InvalidInput(f'{where} {key}', error.reason) from None
    except ValueError as error:
        raise ValueError(f'formation follower {name}: {error}') from None


def _pair(name: str, value: object, units: str = '[m/s, rad/s]') -> tuple[object, object]:
    """``value`` if it is a list of two (e.g. linear, angular), else InvalidInput naming it."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise InvalidInput(name, f'must be {units}, got {value!r}')
    return value[0], value[1]


__all__ = ['Formation', 'FollowerSpec', 'ID_MAX_LENGTH', 'INTERFACES', 'RESERVED_FRAMES',
           'check_id']
