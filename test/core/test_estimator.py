"""The estimator's input gate: implausible inputs refused, the chi-square innovation gate
(documented thresholds), the re-opening of a lost filter, and a study the gate leaves alone."""
from __future__ import annotations

import numpy as np
import pytest

from formopt_ros.core.estimator import (
    GATE_PATIENCE, INNOVATION_GATE, EstimatorPlanner, InputBounds)
from formopt_ros.core.model import normalized_estimation_error
from formopt_ros.core.protocol import Timebase, held_leader_motion, step_substeps
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.session import EstimatorSession
from formopt_ros.core.simulation import FollowerTruth, run_trial, trial_streams
from formopt_ros.core.strategies import make_strategy


def test_bounds_are_relative_to_the_scenario() -> None:
    """Paper range scenario (|p_o| = 2.236 m, dt = 0.05 s, sigma = 0.1 m): 20 |p_o| per
    sub-step, 10 half-turns per sub-step, 100 |p_o| of range, variance within 100x."""
    bounds = InputBounds.from_scenario(Scenario.paper('range'))
    assert bounds.speed == pytest.approx(20 * 5 ** 0.5 / 0.05, rel=1e-12)
    assert bounds.yaw_rate == pytest.approx(10 * np.pi / 0.05, rel=1e-12)
    assert bounds.range == pytest.approx(100 * 5 ** 0.5, rel=1e-12)
    assert bounds.variance == pytest.approx((1e-4, 1.0), rel=1e-12)
    assert bounds.odometry_problem(1.0, 0.5) is None
    assert 'speed' in bounds.odometry_problem(1e200, 0.0)
    assert 'yaw rate' in bounds.odometry_problem(0.0, -1e4)
    assert 'range' in bounds.measurement_problem('range', 1e300, 0.01)
    assert 'bearing' in bounds.measurement_problem('bearing', 4.0, 0.01)
    assert 'variance' in bounds.measurement_problem('range', 2.0, 1e-9)


@pytest.mark.parametrize('kind,value,variance', [('range', 1e300, 0.01),
                                                 ('range', 2.0, 1e-30),
                                                 ('bearing', 1e10, 4e-4)])
def test_absurd_inputs_leave_the_estimate_finite(kind: str, value: float,
                                                 variance: float) -> None:
    """Finite but absurd measurements and odometry are refused with a reason and counted; the
    session goes on and its estimate stays finite (it was NaN with 0.1.x)."""
    scenario = Scenario.paper(kind)
    timebase = Timebase.from_dt(scenario.dt)
    session = EstimatorSession.create(scenario, make_strategy('mtf'), None, True)
    session.plan_next()
    assert session.add_measurement(1, timebase.measurement_stamp(1), value, variance)
    assert session.add_odometry('follower', timebase.substep_end(0), 1e200, 0.0)
    for n in step_substeps(1):
        assert session.add_odometry('leader', timebase.substep_end(n), 1.0, 0.0) is None
        assert session.add_odometry('follower', timebase.substep_end(n), 1.0, 0.0) is None
    truth = np.array([*scenario.p_o, 0.0])
    bearing = float(np.arctan2(-truth[1], -truth[0]))
    z = float(np.hypot(*truth[:2])) if kind == 'range' else bearing
    assert session.add_measurement(1, timebase.measurement_stamp(1), z, scenario.sigma ** 2) \
        is None
    assert len(session.advance()) == 1
    assert np.all(np.isfinite(session.estimator.x)) and np.all(np.isfinite(session.estimator.P))
    counters = session.counters
    assert (counters.rejected_measurements, counters.rejected_odometry) == (1, 1)


def test_gate_refuses_an_outlier_and_changes_nothing() -> None:
    """A range 5 m off (15 standard deviations of the first innovation: S = 0.11 m^2) is not
    used: x and P stay the prior; the next plausible one is used as usual."""
    scenario = Scenario.paper('range')
    estimator = EstimatorPlanner(scenario, make_strategy('mtf'))
    x, P = estimator.x.copy(), estimator.P.copy()
    result = estimator.update(1, float(np.hypot(*scenario.p_o)) + 5.0)
    assert not result.used and result.nis > INNOVATION_GATE
    np.testing.assert_array_equal(estimator.x, x)
    np.testing.assert_array_equal(estimator.P, P)
    good = estimator.update(2, float(np.hypot(*scenario.p_o)) + 0.05)
    assert good.used and good.inflation == 1.0 and estimator.gated_in_a_row == 0


def test_a_lost_filter_reopens_and_recovers() -> None:
    """The truth jumps 3 m (e.g. a follower restarted without its state): after GATE_PATIENCE
    gated measurements the filter re-opens with an inflated covariance (the re-opening
    measurement at 3 standard deviations) and its NEES comes back under 20 within 200 steps
    (seed 7; it would stay gated forever without the re-opening)."""
    scenario = Scenario.paper('range')
    noise, rng = trial_streams(7, 0)
    truth = FollowerTruth(scenario, noise)
    estimator = EstimatorPlanner(scenario, make_strategy('ram'), rng)
    latest = (1.0, 0.0)
    used = []
    for k in range(1, 301):
        if k == 100:
            truth.x[:2] += (2.0, -2.2)
        plan = estimator.plan(k, held_leader_motion(latest))
        for j in range(2):
            truth.execute(plan.command.linear[j], plan.command.angular[j], *latest)
            estimator.propagate(plan.command.linear[j], plan.command.angular[j], *latest)
        result = estimator.update(k, truth.measure())
        used.append((k, result.used, result.inflation))
    gated = [k for k, ok, _ in used if not ok]
    assert gated[:GATE_PATIENCE] == [100, 101, 102]
    assert any(inflation > 1.0 for k, ok, inflation in used if k == 100 + GATE_PATIENCE)
    assert normalized_estimation_error(truth.x, estimator.x, estimator.P) < 20.0


def test_the_gate_refuses_nothing_in_a_study_trial() -> None:
    """Bearing, seed 0, trial 37: its step-3 innovation (77.7, the largest of the whole Sec. V
    study) stays under the gate of 100, so the study's numbers are those without a gate."""
    result = run_trial(Scenario.paper('bearing'), 'ram', 0, 37, 20)
    assert result.innovation_nis[2] == pytest.approx(77.7, abs=0.1)
    assert not result.gated.any() and result.innovation_nis.max() < INNOVATION_GATE
