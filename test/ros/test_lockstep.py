"""Lockstep in one process equals the pure simulation run_trial (estimates, covariances)."""
from __future__ import annotations

import numpy as np
import pytest

from harness.ros import node_scenario
from formopt_ros.core.scenario import LeaderPath
from formopt_ros.core.simulation import run_trial

STEPS = 60
SEED = 3
#: Equality tolerance: same arithmetic; yaw makes a round trip through a quaternion.
TOL = 1e-9


#: A speed limit and a safety distance (node parameters; the scenario's fields).
LIMITS = {'max_speed': 1.5, 'safety_distance': 2.0}


@pytest.mark.parametrize('kind, strategy, limits', [
    ('range', 'ram', {}), ('bearing', 'ram', {}), ('range', 'rq', LIMITS),
    ('range-bearing', 'rq', {'bearing_every': 3}),
    *(pytest.param(*case, marks=pytest.mark.slow) for case in (
        ('range', 'crm', {}), ('bearing', 'crm', {}), ('bearing', 'periodic', LIMITS),
        ('range-bearing', 'rq', {}), ('range-bearing', 'rq', LIMITS),
        ('bearing', 'lookahead', LIMITS)))])
def test_lockstep_equals_run_trial(formation, kind: str, strategy: str,
                                   limits: dict[str, float]) -> None:
    """Estimates, covariances, truth and statuses of every step equal run_trial's, also with
    the limits given as node parameters, and for a range-bearing follower (two messages per
    step, the bearing at every step or every third)."""
    run = formation({'measurement': kind, 'strategy': strategy, 'seed': SEED, 'steps': STEPS,
                     'resend_timeout': 60.0, **limits})
    assert run.run(timeout=30.0), f'estimator at step {run.estimator.session.step} of {STEPS}'
    ref = run_trial(node_scenario(kind, **limits), strategy, SEED, 0, STEPS)
    if 'max_speed' in limits:      # the limits reached the nodes: they change the run
        free = run_trial(node_scenario(kind), strategy, SEED, 0, STEPS)
        assert np.max(np.abs(free.waypoints - ref.waypoints)) > 0.05
        assert np.min(np.hypot(*ref.waypoints.T)) >= LIMITS['safety_distance'] - 1e-9
    summary = run.estimator.summary()
    assert summary['steps'] == STEPS
    fell_back = 0 if ref.fallback is None else int(np.sum(ref.fallback))
    assert sum(summary['plan_fallbacks'].values()) == fell_back, summary['plan_fallbacks']
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(summary['final_covariance'], ref.covariance[-1], rtol=0,
                               atol=TOL)
    assert summary['final_truth'] == pytest.approx(ref.truth[-1].tolist(), abs=TOL)
    # every step, as published on the estimate topic
    assert len(run.probe.estimates) == STEPS
    for k, (x, P) in enumerate(run.probe.estimates):
        np.testing.assert_allclose(x, ref.estimate[k], rtol=0, atol=TOL, err_msg=f'step {k + 1}')
        np.testing.assert_allclose(P, ref.covariance[k], rtol=0, atol=TOL,
                                   err_msg=f'step {k + 1}')
    statuses = run.probe.step_statuses()
    assert [s.step for s in statuses] == list(range(1, STEPS + 1))
    assert [s.weighted_trace for s in statuses] == pytest.approx(
        ref.weighted_trace.tolist(), abs=TOL)
    last = statuses[-1]
    every = limits.get('bearing_every', 1)
    parts = STEPS + (len(range(every, STEPS + 1, every)) if kind == 'range-bearing' else 0)
    assert (last.accepted_measurements, last.rejected_measurements,
            last.rejected_odometry) == (parts, 0, 0)
    assert summary['mean_nees'] == pytest.approx(float(np.mean(ref.nees)), rel=1e-9)
    assert summary['message_counts']['received'] == {
        'leader_odom': 2 * STEPS, 'follower_odom': 2 * STEPS, 'measurement': parts,
        'truth': STEPS}


@pytest.mark.slow
def test_periodic_behind_an_s_curve_equals_run_trial(formation) -> None:
    """PERIODIC behind an S-curve of 2 s (20 steps) at 2 m/s: the estimator node designs the
    cycle locked to the path before step 1 and plays it from decision 21; every estimate and
    covariance equals run_trial's (which designs inside decision 21), whose moves after the
    first period are not greedy's."""
    curve = {'path': 's-curve', 'amplitude': 0.5, 'period': 2.0, 'max_speed': 2.0}
    run = formation({'measurement': 'bearing', 'strategy': 'periodic', 'seed': SEED,
                     'steps': STEPS, 'resend_timeout': 60.0, **curve})
    assert run.run(timeout=120.0), f'estimator at step {run.estimator.session.step} of {STEPS}'
    scenario = node_scenario('bearing', leader=LeaderPath('s-curve', 1.0, amplitude=0.5,
                                                          period=2.0), max_speed=2.0)
    ref = run_trial(scenario, 'periodic', SEED, 0, STEPS)
    greedy = run_trial(scenario, 'rq', SEED, 0, STEPS)
    np.testing.assert_array_equal(ref.waypoints[:20], greedy.waypoints[:20])
    assert np.max(np.hypot(*(ref.waypoints[20:] - greedy.waypoints[20:]).T)) > 0.01
    assert len(run.probe.estimates) == STEPS
    for k, (x, P) in enumerate(run.probe.estimates):
        np.testing.assert_allclose(x, ref.estimate[k], rtol=0, atol=TOL, err_msg=f'step {k + 1}')
        np.testing.assert_allclose(P, ref.covariance[k], rtol=0, atol=TOL,
                                   err_msg=f'step {k + 1}')


def test_diagnostics_every_status_period_while_steps_complete(formation) -> None:
    """/diagnostics comes every status_period (here 0.5 s) also while every step completes
    (per-step status messages do not hold it back): >= 4 OK diagnostics with rising step
    counts while the run advances. (At 0.1 s a 0.2 s hiccup of a loaded machine already reads
    as a stall, WARN, by design.)"""
    run = formation({'measurement': 'range', 'seed': SEED, 'steps': 10**6,
                     'status_period': 0.5})
    diagnostics = run.published.setdefault('/diagnostics', [])
    assert run.spin_until(lambda: len(diagnostics) >= 5, 30.0), len(diagnostics)
    status = [message.status[0] for message in diagnostics[1:]]     # [0]: maybe before start
    steps = [int(next(v.value for v in s.values if v.key == 'step')) for s in status]
    assert all(s.level == b'\x00' for s in status), [s.message for s in status]
    assert steps == sorted(steps) and steps[-1] > steps[0] > 0, steps
