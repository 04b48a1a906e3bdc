"""formopt-montecarlo with a range-bearing follower: outputs, RAM left out, the comparison."""
from __future__ import annotations

import json

import pytest

from formopt_ros.cli import montecarlo
from formopt_ros.core.simulation import run_trial
from formopt_ros.core.scenario import Scenario


@pytest.mark.slow
def test_montecarlo_range_bearing_writes_study_and_sensor_comparison(tmp_path) -> None:
    """A small range-bearing study (2 trials x 6 steps, bearing every 2nd step): its summary
    has every built-in strategy but RAM; OUT/sensors holds RQ and PERIODIC for the three
    sensors at the range follower's slot, and RQ's range-bearing run there equals run_trial."""
    out = tmp_path / 'mc'
    assert montecarlo.main(['--measurement', 'range-bearing', '--trials', '2', '--steps', '6',
                            '--jobs', '1', '--no-figures', '--bearing-every', '2',
                            '--out', str(out)]) == 0
    summary = json.loads((out / 'range-bearing' / 'summary.json').read_text())
    assert list(summary['strategies']) == ['mtf', 'crm', 'mme', 'gbs', 'rq', 'periodic']
    assert summary['scenario']['p_o'] == [-1.0, -2.0]
    assert (summary['scenario']['sigma'], summary['scenario']['sigma_bearing'],
            summary['scenario']['bearing_every']) == (0.1, 0.02, 2)
    sensors = json.loads((out / 'sensors' / 'summary.json').read_text())
    assert list(sensors['runs']) == [f'{sensor} {name}' for sensor in (
        'range-only', 'bearing-only', 'range+bearing') for name in ('rq', 'periodic')]
    scenario = Scenario.paper('range-bearing', bearing_every=2)
    mean = sum(run_trial(scenario, 'rq', 0, t, 6).weighted_trace.mean() for t in (0, 1)) / 2
    assert abs(sensors['runs']['range+bearing rq']['mean_trace'] - mean) <= 1e-12 * mean
    assert not (out / 'range-bearing' / 'range_bearing_weighted_trace.png').exists()


@pytest.mark.slow
def test_montecarlo_range_bearing_under_limits(tmp_path) -> None:
    """The study of a range-bearing follower under a speed limit and a safety distance (2
    trials x 20 steps): every strategy runs, RQ over the reachable set included, and the true
    follower keeps the safety distance up to the odometry noise's drift (5 cm)."""
    out = tmp_path / 'mc'
    assert montecarlo.main(['--measurement', 'range-bearing', '--trials', '2', '--steps', '20',
                            '--jobs', '1', '--no-figures', '--max-speed', '1.5',
                            '--safety-distance', '2.1', '--strategies', 'rq,gbs,periodic',
                            '--out', str(out)]) == 0
    summary = json.loads((out / 'range-bearing' / 'summary.json').read_text())
    assert list(summary['strategies']) == ['rq', 'gbs', 'periodic']
    for name, row in summary['strategies'].items():
        assert row['min_leader_distance'] >= 2.1 - 0.05, (name, row)
