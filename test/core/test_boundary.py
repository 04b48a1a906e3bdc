"""The boundary holds: random and extreme values through Scenario, Formation and StudyConfig
are refused there (InvalidInput naming the field) or run 5-6 steps with finite numbers."""
from __future__ import annotations

import math
import warnings
from collections import Counter
from typing import Any

import numpy as np
import pytest

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.formation import Formation
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import TrialResult, run_formation, run_trial
from formopt_ros.core.study import StudyConfig

STRATEGIES = ('rq', 'ram', 'gbs', 'mtf', 'crm', 'mme', 'periodic')
#: Scenario fields that hold one number, and the leader path's.
NUMBERS = ('r', 'sigma', 'dt', 'sigma_v', 'sigma_omega', 'sigma_v_leader', 'sigma_omega_leader')
PATH_NUMBERS = ('speed', 'yaw_rate', 'amplitude', 'period')


def wild_value(rng: np.random.Generator) -> Any:
    """A value a user might type, or a careless program pass: extremes, the wrong type, or a
    random number over 13 decades (mostly positive)."""
    pool = (0, 0.0, -0.0, -1.0, 1, 3, -2, 10**6, 1e300, -1e300, 1e-300, 5e-324, math.nan,
            math.inf, -math.inf, True, False, None, 'abc', '0.5', '', [0.1], np.float32(0.2),
            np.int64(2), np.array(0.3))
    if rng.random() < 0.3:
        return pool[rng.integers(len(pool))]
    return float(rng.choice([-1.0, 1.0], p=[0.1, 0.9]) * 10.0 ** rng.uniform(-8.0, 5.0))


def assert_finite(result: TrialResult, label: object) -> None:
    for values in (result.weighted_trace, result.estimate, result.covariance, result.waypoints,
                   result.nees):
        assert np.all(np.isfinite(values)), label


def paper_values(rng: np.random.Generator) -> dict[str, Any]:
    """Keyword overrides of Scenario.paper with one to three fields made wild."""
    overrides: dict[str, Any] = {}
    for _ in range(rng.integers(1, 3)):
        field = rng.integers(len(NUMBERS) + 3)
        if field < len(NUMBERS):
            overrides[NUMBERS[field]] = wild_value(rng)
        elif field == len(NUMBERS):
            overrides['p_o'] = (wild_value(rng), wild_value(rng))
        elif field == len(NUMBERS) + 1:
            overrides['initial_covariance'] = (0.1, wild_value(rng), 4e-4)
        else:
            name = PATH_NUMBERS[rng.integers(len(PATH_NUMBERS))]
            kind = 'arc' if name == 'yaw_rate' else 's-curve'
            overrides['leader'] = {'kind': kind, name: wild_value(rng)}
    return overrides


def refused_or_ran(kind: str, overrides: dict[str, Any], strategy: str, seed: int,
                   steps: int) -> str:
    """'refused' when Scenario.paper refuses the overrides (InvalidInput), else 'ran' after
    ``steps`` finite steps of ``strategy`` without a RuntimeWarning."""
    try:
        scenario = Scenario.paper(kind, **overrides)
    except InvalidInput:
        return 'refused'
    with warnings.catch_warnings():
        warnings.simplefilter('error', RuntimeWarning)
        assert_finite(run_trial(scenario, strategy, seed, 0, steps), (kind, overrides, strategy))
    return 'ran'


@pytest.mark.slow
def test_scenarios_are_refused_at_the_boundary_or_run() -> None:
    """Scenario.paper with wild overrides: InvalidInput, or 5 finite steps of a strategy."""
    rng = np.random.default_rng(20240)
    outcomes = Counter(refused_or_ran(('range', 'bearing')[case % 2], paper_values(rng),
                                      STRATEGIES[case % len(STRATEGIES)], case, 5)
                       for case in range(160))
    assert outcomes['refused'] > 40 and outcomes['ran'] > 40, outcomes


def limited_values(rng: np.random.Generator) -> dict[str, Any]:
    """Keyword overrides of Scenario.paper that a user of limits and paths might type: a slot
    0.3-30 m away, a disc up to 0.99 of it, any leader path, either kinematics, often a speed
    limit and a safety distance, sometimes another dt, noise or initial covariance."""
    def spread(low: float, high: float) -> float:
        return float(10.0 ** rng.uniform(math.log10(low), math.log10(high)))

    distance, angle = spread(0.3, 30.0), rng.uniform(-math.pi, math.pi)
    speed = float(rng.choice([0.0, 0.1, 0.5, 1.0, 2.0, 5.0]))
    paths = [{'kind': 'straight', 'speed': speed},
             {'kind': 'arc', 'speed': speed, 'yaw_rate': float(rng.choice([-1, 1])) *
              spread(0.01, 3.0)},
             {'kind': 's-curve', 'speed': speed, 'amplitude': spread(0.05, 2.0),
              'period': spread(0.5, 40.0)},
             {'kind': 'segments', 'repeat': bool(rng.random() < 0.5), 'segments': [
                 {'duration': spread(0.05, 5.0), 'speed': float(rng.choice([0.0, 0.5, 2.0])),
                  'yaw_rate': float(rng.uniform(-1.0, 1.0))} for _ in range(rng.integers(1, 4))]}]
    overrides: dict[str, Any] = {
        'p_o': (distance * math.cos(angle), distance * math.sin(angle)),
        'r': distance * float(rng.choice([0.05, 0.3, 0.7, 0.9, 0.99])),
        'leader': paths[rng.integers(len(paths))],
        'kinematics': ('exact', 'euler')[rng.integers(2)]}
    if rng.random() < 0.6:
        overrides['max_speed'] = spread(0.2, 30.0)
    if rng.random() < 0.4:
        overrides['safety_distance'] = distance * rng.uniform(0.0, 1.1)
    if rng.random() < 0.3:
        overrides['dt'] = spread(0.005, 0.5)
    if rng.random() < 0.3:
        overrides['sigma'] = spread(1e-4, 0.5)
    if rng.random() < 0.2:
        overrides['initial_covariance'] = (spread(1e-6, 10.0), spread(1e-6, 10.0),
                                           spread(1e-8, 1.0))
    return overrides


@pytest.mark.slow
def test_limits_and_paths_are_refused_at_the_boundary_or_run() -> None:
    """Scenario.paper for range, bearing and range-bearing with limits, safety distances and
    leader paths of every kind: InvalidInput, or 6 finite steps of a strategy (every one, and
    RAM only where it applies) without a RuntimeWarning."""
    rng = np.random.default_rng(20243)
    outcomes: Counter[str] = Counter()
    for case in range(90):
        kind = ('range', 'bearing', 'range-bearing')[case % 3]
        strategies = STRATEGIES + ('lookahead',) if kind != 'range-bearing' else \
            tuple(s for s in STRATEGIES if s != 'ram') + ('lookahead',)
        outcomes[refused_or_ran(kind, limited_values(rng), strategies[case % len(strategies)],
                                case, 6)] += 1
    assert outcomes['refused'] > 10 and outcomes['ran'] > 50, outcomes


def test_a_cycle_whose_recursion_blows_up_has_no_steady_state() -> None:
    """PERIODIC's design under a speed limit behind a turning leader, a disc of 0.95 |p_o| and a
    precise range: a candidate cycle whose covariance recursion overflows (a singular C P + D)
    counts as having no steady state, and the design goes on."""
    path = {'kind': 'segments', 'repeat': True, 'segments': [
        {'duration': 2.737249075751988, 'speed': 0.5, 'yaw_rate': 0.8096243228140538},
        {'duration': 0.8583549608083089, 'speed': 0.5, 'yaw_rate': 0.1750185746265165}]}
    scenario = Scenario.paper(
        'range-bearing', p_o=(3.62420019967808, 2.648526662944381), r=4.264380648574389,
        leader=path, kinematics='euler', max_speed=1.8084085276852833,
        safety_distance=3.1453057699906735, sigma=0.0025564280843583136)
    with warnings.catch_warnings():
        warnings.simplefilter('error', RuntimeWarning)
        assert_finite(run_trial(scenario, 'periodic', 230, 0, 6), 'blown-up cycle')


@pytest.mark.slow
@pytest.mark.parametrize('kind', ['range', 'bearing'])
def test_each_documented_bound_runs(kind: str) -> None:
    """Each number of RANGES at its low and at its high bound (the rest the paper's): every
    strategy runs 5 finite steps."""
    from formopt_ros.core.scenario import RANGES
    base = Scenario.paper(kind)
    cases: list[dict[str, Any]] = []
    for key, (low, high, _) in RANGES.items():
        for bound in (low, high):
            if key == f'{kind}_sigma':
                cases.append({'sigma': bound})
            elif key in NUMBERS:
                cases.append({key: bound})
            elif key == 'slot':
                cases.append({'p_o': (bound, bound), 'r': 0.1 * math.hypot(bound, bound)})
            elif key == 'deviation':
                cases.append({'r': bound * base.d_o})
            elif key == 'initial_covariance':
                cases.append({key: (bound,) * 3})
            elif key in PATH_NUMBERS:       # exact kinematics: Euler's own turn bound is lower
                path = {'kind': 'arc', key: bound} if key == 'yaw_rate' else \
                    {'kind': 's-curve', 'amplitude': 0.5, key: bound}
                cases.append({'leader': path, 'kinematics': 'exact'})
    for index, overrides in enumerate(cases):
        scenario = Scenario.paper(kind, **overrides)
        for strategy in STRATEGIES:
            assert_finite(run_trial(scenario, strategy, index, 0, 5), (overrides, strategy))


def test_formations_are_refused_at_the_boundary_or_run() -> None:
    """Formation files with wild values: InvalidInput naming the follower's field, or every
    follower runs 5 finite steps."""
    rng = np.random.default_rng(20241)
    outcomes = {'refused': 0, 'ran': 0}
    keys = ('slot', 'deviation', 'noise', 'odometry_noise', 'leader_odometry_noise',
            'initial_covariance', 'max_speed', 'safety_distance', 'seed', 'dt', 'trial',
            'options')
    for case in range(60):
        follower: dict[str, Any] = {'id': 'f1', 'sensor': ('range', 'bearing')[case % 2],
                                    'slot': [-1.0, 2.0], 'strategy': STRATEGIES[case % 7]}
        data: dict[str, Any] = {'leader': {'id': 'boss'}, 'followers': [follower]}
        key = keys[rng.integers(len(keys))]
        value = wild_value(rng)
        if key in ('slot', 'odometry_noise', 'leader_odometry_noise'):
            follower[key] = [value, 0.1]
        elif key == 'initial_covariance':
            follower[key] = [0.1, value, 4e-4]
        elif key in ('dt', 'trial'):
            data[key] = value
        elif key == 'options':
            follower['strategy'], follower['options'] = 'gbs', {'cell': value}
        else:
            follower[key] = value
        try:
            formation = Formation.from_dict(data)
        except InvalidInput as error:
            if key in ('dt', 'trial'):             # formation-level: no follower is blamed
                assert error.name == f'formation {key}', (key, error)
            assert key in error.name or key == 'slot' and 'p_o' in error.name or (
                key == 'noise' and 'sigma' in error.name) or key in ('odometry_noise',
                                                                     'leader_odometry_noise',
                                                                     'options'), (key, error)
            outcomes['refused'] += 1
            continue
        for name, result in run_formation(formation, 5).items():
            assert_finite(result, (data, name))
        outcomes['ran'] += 1
    assert outcomes['refused'] > 10 and outcomes['ran'] > 10, outcomes


def test_study_configs_are_refused_at_the_boundary_or_run() -> None:
    """StudyConfig's scenario overrides and options: InvalidInput, or its scenario runs."""
    rng = np.random.default_rng(20242)
    outcomes = {'refused': 0, 'ran': 0}
    for case in range(30):
        overrides = paper_values(rng)
        options = {'mme': {'amplitude': wild_value(rng)}} if case % 3 == 0 else {}
        try:
            config = StudyConfig('bearing', trials=1, steps=5, strategies=('mme', 'rq'),
                                 options=options, scenario=overrides)
        except InvalidInput:
            outcomes['refused'] += 1
            continue
        for strategy in config.strategies:
            assert_finite(run_trial(config.make_scenario(), strategy, case, 0, 5,
                                    config.strategy_options(strategy)), (overrides, options))
        outcomes['ran'] += 1
    assert outcomes['refused'] > 5 and outcomes['ran'] > 5, outcomes
