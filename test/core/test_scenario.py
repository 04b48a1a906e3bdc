"""Scenario and leader paths: validation that names the field, JSON round trips, velocities."""
from __future__ import annotations

import json
import math
import re

import pytest

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.scenario import LeaderPath, Scenario, Segment


def test_paper_scenarios() -> None:
    """Sec. V: p_o = [-1, -2] / [-1, 2], r = 0.1 |p_o|, sigma 0.1 m / 0.02 rad, v_L = 1 m/s."""
    rng, brg = Scenario.paper('range'), Scenario.paper('bearing')
    assert (rng.p_o, rng.sigma, brg.p_o, brg.sigma) == ((-1.0, -2.0), 0.1, (-1.0, 2.0), 0.02)
    assert rng.r == pytest.approx(0.1 * math.sqrt(5), rel=1e-15)
    assert rng.leader.velocity(123, rng.dt) == (1.0, 0.0) and rng.leader.is_straight()
    assert rng.kinematics == 'euler'          # the paper simulates with its eq. (9)
    assert Scenario('range', (-1.0, -2.0), 0.2, 0.1).kinematics == 'exact'
    assert type(Scenario('range', (-1.0, -2.0), 0.2, 1).sigma) is float  # kept converted


@pytest.mark.parametrize('overrides,field', [
    ({'measurement': 'sonar'}, 'measurement'), ({'r': 0.0}, 'r'), ({'r': 3.0}, 'r'),
    ({'sigma': -1.0}, 'sigma'), ({'sigma': math.nan}, 'sigma'), ({'dt': 0.0}, 'dt'),
    ({'sigma_v': -0.1}, 'sigma_v'), ({'p_o': (0.0, 0.0)}, 'p_o'),
    ({'sigma_omega_leader': -1.0}, 'sigma_omega_leader'), ({'kinematics': 'rk4'}, 'kinematics'),
    ({'p_o': (math.inf, 1.0)}, 'p_o'), ({'initial_covariance': (0.1, 0.1, 0.0)},
                                        'initial_covariance'),
    ({'sigma': True}, 'sigma'), ({'dt': True}, 'dt'), ({'sigma': 1e300}, 'sigma'),
    ({'measurement': 'bearing', 'sigma': 4.0}, 'sigma'), ({'dt': 11.0}, 'dt'),
    ({'p_o': (2e4, 0.0), 'r': 1.0}, 'p_o'), ({'sigma_v': '0.1x'}, 'sigma_v')])
def test_bad_scenarios_name_the_field(overrides: dict, field: str) -> None:
    """Each value out of its documented range (RANGES) is refused naming the field."""
    values = dict(measurement='range', p_o=(-1.0, -2.0), r=0.2, sigma=0.1)
    values.update(overrides)
    with pytest.raises(InvalidInput) as refused:
        Scenario(**values)
    assert refused.value.name == field


def test_round_trip_through_json_and_differences() -> None:
    """to_dict -> JSON -> from_dict gives an equal scenario; differences() names fields."""
    path = LeaderPath('segments', segments=(Segment(2.0, 1.0), Segment(1.0, 0.5, 0.3)),
                      repeat=True)
    scenario = Scenario.paper('bearing', leader=path, sigma_v=0.3)
    again = Scenario.from_dict(json.loads(json.dumps(scenario.to_dict())))
    assert again == scenario
    other = Scenario.paper('bearing', leader=LeaderPath.constant(1.0, 0.5), dt=0.1)
    names = [name for name, _, _ in scenario.differences(other)]
    assert 'dt' in names and 'leader.kind' in names and 'sigma_v' in names
    assert scenario.differences(again) == []
    with pytest.raises(ValueError, match='unknown keys'):
        Scenario.from_dict({**scenario.to_dict(), 'speed': 2})


def test_leader_path_velocities() -> None:
    """Each path kind: the velocity of sub-step n is the path's value at t = n dt."""
    dt = 0.05
    assert LeaderPath.constant(2.0, 0.0).kind == 'straight'
    assert LeaderPath.constant(2.0, 0.5).velocity(7, dt) == (2.0, 0.5)
    curve = LeaderPath('s-curve', speed=1.0, amplitude=0.4, period=4.0)
    for n in (0, 10, 25, 40, 55):
        assert curve.velocity(n, dt) == (1.0, pytest.approx(
            0.4 * math.sin(2 * math.pi * n * dt / 4.0), abs=1e-15))
    segments = LeaderPath('segments', segments=(Segment(1.0, 1.0, 0.0), Segment(0.5, 2.0, 1.0)))
    assert segments.velocity(19, dt) == (1.0, 0.0)          # t = 0.95 s
    assert segments.velocity(20, dt) == (2.0, 1.0)          # t = 1.00 s
    assert segments.velocity(1000, dt) == (2.0, 1.0)        # after the end: the last held
    looped = LeaderPath('segments', segments=segments.segments, repeat=True)
    assert looped.velocity(30, dt) == (1.0, 0.0)            # t = 1.5 s = 0 s of the loop
    assert not looped.is_straight() and LeaderPath().is_straight()
    with pytest.raises(ValueError, match='segment'):
        LeaderPath('segments')
    with pytest.raises(ValueError, match="kind 'arc'"):
        LeaderPath('straight', yaw_rate=0.1)


@pytest.mark.parametrize('path, field', [
    (dict(kind='s-curve', amplitude=0.5, yaw_rate=0.3), 'leader yaw_rate'),
    (dict(kind='arc', yaw_rate=0.3, amplitude=0.5), 'leader amplitude'),
    (dict(kind='straight', period=5.0), 'leader period'),
    (dict(kind='straight', segments=[{'duration': 1.0, 'speed': 1.0}]), 'leader segments'),
    (dict(kind='segments', speed=2.0, segments=[{'duration': 1.0, 'speed': 1.0}]),
     'leader speed'),
    (dict(kind='s-curve'), 'leader amplitude'), (dict(kind='arc'), 'leader yaw_rate')])
def test_a_path_setting_its_kind_does_not_use_is_refused(path: dict, field: str) -> None:
    """A leader path refuses a setting its kind ignores (an s-curve's yaw_rate, an arc's
    amplitude) and a turning kind that never turns, naming the field."""
    with pytest.raises(InvalidInput) as refused:
        LeaderPath(**path)
    assert refused.value.name == field


def test_euler_kinematics_refuses_a_leader_turning_too_fast_for_it() -> None:
    """The paper's Euler step scales |p| by sqrt(1 + (omega dt)^2) per sub-step: a leader
    turning more than 0.5 rad per dt is refused naming the rate; exact kinematics take it, and
    0.5 rad per dt passes. A leader's yaw rate above 10 rad/s (28.6 meant as deg/s) is refused
    with either."""
    fast = LeaderPath('s-curve', amplitude=8.0)
    with pytest.raises(InvalidInput) as refused:
        Scenario.paper('range', leader=fast, dt=0.1)
    assert refused.value.name == 'leader amplitude'
    assert Scenario.paper('range', leader=fast, dt=0.1, kinematics='exact').leader == fast
    Scenario.paper('range', leader=LeaderPath('arc', yaw_rate=10.0))       # dt 0.05 s
    for path in ({'kind': 's-curve', 'amplitude': 28.6}, {'kind': 'arc', 'yaw_rate': -45.0}):
        with pytest.raises(InvalidInput, match='rad/s'):
            Scenario.paper('range', leader=path, kinematics='exact')


@pytest.mark.parametrize('value, rule', [
    ('a__b', "'__'"), ('f' * 65, 'at most 64 characters'), ('odom', 'reserved frame'),
    ('base_link', 'reserved frame'), ('world', 'reserved frame'), ('1a', 'letters, digits'),
    ('a b', 'letters, digits')])
def test_ids_at_the_door_name_the_id_and_the_rule(value: str, rule: str) -> None:
    """An id with '__', longer than ID_MAX_LENGTH or a reserved frame name is refused."""
    from formopt_ros.core.formation import FollowerSpec, check_id
    with pytest.raises(InvalidInput) as refused:
        check_id('follower id', value)
    assert refused.value.name == 'follower id' and rule in refused.value.reason
    with pytest.raises(InvalidInput):
        FollowerSpec(value, Scenario.paper('range'))


def test_the_longest_id_keeps_every_derived_file_name_short() -> None:
    """64 characters pass; the longest derived file name stays under 255 bytes."""
    from formopt_ros.core.formation import ID_MAX_LENGTH, check_id
    longest = 'f' * ID_MAX_LENGTH
    assert check_id('follower id', longest) == longest
    for node in ('estimator_planner', 'follower_estimator', 'follower_sim', 'field_sim'):
        for suffix in ('json.tmp', 'pkl.tmp', 'log'):
            assert len(f'{longest}.{node}.{suffix}'.encode()) < 255
    assert check_id('run id', 'odom', frame=False) == 'odom'     # not a frame


def test_the_largest_bearing_deviation_named_in_a_refusal_passes() -> None:
    """A refused bearing deviation names the largest one allowed, and that one is accepted
    (with a 1e-4 m^2 initial covariance the steady-state rule binds: 0.78 |p_o|; with 0.11 m^2
    the first updates' rule, 0.480865 |p_o|, named rounded down), and so does the safety
    distance named (rounded up); with 0.5 m^2 it names neither, which no value would fix."""
    from formopt_ros.core.domain import check_deviation_domain
    d_o = math.hypot(*Scenario.paper('bearing').p_o)
    for covariance, limit in (((1e-4, 1e-4, 1e-4), '0.78'), ((0.11, 0.11, 4e-4), '0.4808')):
        with pytest.raises(ValueError, match=f'at most {limit}, or a safety distance of at '
                                             r'least ([0-9.]+) m$') as refused:
            check_deviation_domain(Scenario.paper('bearing', r=0.9 * d_o,
                                                  initial_covariance=covariance))
        check_deviation_domain(Scenario.paper('bearing', r=float(limit) * d_o,
                                              initial_covariance=covariance))
        safety = float(re.search(r'least ([0-9.]+) m$', str(refused.value)).group(1))
        check_deviation_domain(Scenario.paper('bearing', r=0.9 * d_o, safety_distance=safety,
                                              initial_covariance=covariance))
    # 3.5 initial standard deviations (2.47 m) beyond the disc's far edge: neither remedy fits
    with pytest.raises(ValueError, match='Use a slot farther from the leader or a smaller '
                                         'initial covariance$'):
        check_deviation_domain(Scenario.paper('bearing', r=0.1 * d_o,
                                              initial_covariance=(0.5, 0.5, 0.01)))
