"""Formations in one process on an rclpy executor: several followers and turning leaders equal
the pure simulation per follower; /clock, use_sim_time, parameters refused or validated at run
time, and a late subscriber that gets live messages only."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from formopt_interfaces.msg import PlannerStatus
from harness.ros import PREFIX, set_parameters, topic
from rcl_interfaces.msg import ParameterType

from formopt_ros.core.protocol import Timebase
from formopt_ros.core.simulation import run_formation
from formopt_ros.ros import qos
from formopt_ros.wire.formation import load_formation

STEPS = 40
TOL = 1e-9
FOUR = {'leader': {'path': {'kind': 's-curve', 'speed': 1.0, 'amplitude': 0.4, 'period': 3.0}},
        'seed': 11,
        'followers': [
            {'id': 'north', 'sensor': 'bearing', 'slot': [-1.0, 2.0], 'strategy': 'ram'},
            {'id': 'south', 'sensor': 'range', 'slot': [-1.0, -2.0], 'strategy': 'rq'},
            {'id': 'east', 'sensor': 'range', 'slot': [-2.5, 0.5], 'deviation': 0.2,
             'noise': 0.05, 'strategy': 'mme'},
            {'id': 'west', 'sensor': 'bearing', 'slot': [-3.0, -1.0], 'strategy': 'crm',
             'odometry_noise': [0.1, 0.05]}]}


def formation_file(tmp_path: Path, content: dict[str, Any]) -> Path:
    path = tmp_path / 'formation.yaml'
    path.write_text(yaml.safe_dump({'formation': content}))
    return path


def assert_equals_simulation(run: Any, path: Path, steps: int) -> None:
    """Every follower's published estimates and statuses equal run_formation (1e-9)."""
    reference = run_formation(load_formation(path), steps)
    assert set(run.estimators) == set(reference)
    for follower, ref in reference.items():
        estimates = run.probe.by_follower[follower]['estimates']
        assert len(estimates) == steps, follower
        for k, (x, P) in enumerate(estimates):
            np.testing.assert_allclose(x, ref.estimate[k], rtol=0, atol=TOL,
                                       err_msg=f'{follower} step {k + 1}')
            np.testing.assert_allclose(P, ref.covariance[k], rtol=0, atol=TOL)
        summary = run.estimators[follower].summary()
        assert summary['final_truth'] == pytest.approx(ref.truth[-1].tolist(), abs=TOL)
        assert summary['mean_nees'] == pytest.approx(float(np.mean(ref.nees)), rel=1e-9)
        assert [s.step for s in run.probe.step_statuses(follower)] == list(range(1, steps + 1))


@pytest.mark.parametrize('content', [
    yaml.safe_load((Path(__file__).resolve().parents[2] / 'config' / 'formation_fig4.yaml')
                   .read_text())['formation'], FOUR], ids=['fig4', 'four-s-curve'])
def test_formation_lockstep_equals_the_simulation(formation, tmp_path: Path,
                                                  content: dict[str, Any]) -> None:
    """Two followers (the paper's Fig. 4) and four followers behind an S-curve leader."""
    path = formation_file(tmp_path, content)
    followers = tuple(f['id'] for f in content['followers'])
    run = formation({'formation_file': str(path), 'steps': STEPS}, followers=followers)
    assert run.run(timeout=60.0), {f: e.session.step for f, e in run.estimators.items()}
    assert_equals_simulation(run, path, STEPS)
    assert run.leader.summary()['served_steps'] == STEPS


def test_turning_leader_and_clock(formation, tmp_path: Path) -> None:
    """An arc at 0.5 rad/s from the leader's parameters (one follower, bearing, MME): equal to
    the simulation; /clock carries each sub-step's end, and a node with use_sim_time follows
    it."""
    content = {'leader': {'path': {'kind': 'arc', 'speed': 1.0, 'yaw_rate': 0.5}},
               'followers': [{'id': 'follower', 'sensor': 'bearing', 'slot': [-1.0, 2.0],
                              'strategy': 'mme'}]}
    path = formation_file(tmp_path, content)
    run = formation({'formation_file': str(path), 'steps': STEPS, 'use_sim_time': True})
    assert run.run(timeout=60.0)
    assert_equals_simulation(run, path, STEPS)
    timebase = Timebase.from_dt(0.05)
    assert run.probe.counts['/clock'] == 2 * STEPS
    end = timebase.measurement_stamp(STEPS)
    assert run.spin_until(lambda: run.estimator.get_clock().now().nanoseconds == end, 5.0), \
        run.estimator.get_clock().now().nanoseconds
    assert run.leader.get_clock().now().nanoseconds == end
    assert run.probe.get_clock().now().nanoseconds != end         # no use_sim_time there


def test_parameters_read_only_or_validated_on_set(formation) -> None:
    """ros2 param set: a read-only parameter is refused, a bad strategy is refused with the
    reason, a good one is accepted and used from the next step; get returns what runs."""
    run = formation({'measurement': 'range', 'steps': 30, 'resend_timeout': 60.0})
    assert run.spin_until(lambda: run.estimator.session.step >= 5, 30.0)
    refused = set_parameters(run, run.estimator, {'dt': 0.02})
    assert not refused[0].successful and 'read-only' in refused[0].reason
    bogus = set_parameters(run, run.estimator, {'strategy': 'bogus'})
    assert not bogus[0].successful and "'bogus'" in bogus[0].reason
    assert run.estimator.get_parameter('strategy').value == 'ram'
    cell = set_parameters(run, run.estimator, {'gbs_cell': 1e-9})
    assert not cell[0].successful and 'gbs_cell' in cell[0].reason
    accepted = set_parameters(run, run.estimator, {'strategy': 'mtf'})
    assert accepted[0].successful
    assert run.estimator.get_parameter('strategy').value == 'mtf'
    assert run.run(timeout=60.0)
    statuses = run.probe.step_statuses()
    assert statuses[-1].strategy == 'mtf' and statuses[0].strategy == 'ram'
    descriptor = run.estimator.describe_parameter('dt')
    assert descriptor.read_only and descriptor.type == ParameterType.PARAMETER_DOUBLE


def test_late_subscriber_gets_live_messages_only(formation) -> None:
    """Streaming topics are volatile: a subscriber that joins at step k never sees earlier
    statuses (the old transient-local depth-1000 topics replayed up to 1000 of them)."""
    run = formation({'measurement': 'bearing', 'steps': 60, 'resend_timeout': 60.0})
    assert run.spin_until(lambda: run.estimator.session.step >= 20, 30.0)
    joined_at = run.estimator.session.step
    late: list[PlannerStatus] = []
    run.probe.create_subscription(PlannerStatus, topic('follower', 'status'), late.append,
                                  qos.STREAM)          # what ros2 topic echo adapts to
    assert run.run(timeout=60.0)
    assert late and min(s.step for s in late) >= joined_at
    assert PREFIX in run.estimator.get_fully_qualified_name()
