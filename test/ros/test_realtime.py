"""Realtime mode in one process: timers at 1/dt drive a run that produces sane estimates."""
from __future__ import annotations

import time

import numpy as np

from formopt_ros.core.formulas import weight_vector
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.core.scenario import Scenario

STEPS = 20
DT = 0.01      # s per sub-step: 20 steps take 0.4 s of timer time


def test_realtime_runs_and_estimates(formation) -> None:
    run = formation({'mode': 'realtime', 'dt': DT, 'steps': STEPS, 'measurement': 'bearing'})
    start = time.monotonic()
    assert run.run(timeout=30.0), f'estimator at step {run.estimator.session.step} of {STEPS}'
    elapsed = time.monotonic() - start
    # Timers drive it: at least STEPS * SUBSTEPS ticks of the follower (10 % timer slack).
    assert elapsed >= 0.9 * STEPS * SUBSTEPS * DT
    est, follower = run.estimator, run.follower
    assert est.session.step == STEPS
    statuses = run.probe.step_statuses()
    assert [s.step for s in statuses] == list(range(1, STEPS + 1))
    assert [s.accepted_measurements for s in statuses] == list(range(1, STEPS + 1))
    assert all(s.rejected_measurements == 0 and s.rejected_odometry == 0 for s in statuses)
    assert all(s.strategy == 'ram' and s.measurement_kind == 'bearing' for s in statuses)
    # The follower executed at least the estimator's steps and counted every tick it ran.
    assert follower.executed >= STEPS
    assert 0 <= follower.counters['missed_cycles'] <= SUBSTEPS * follower.executed
    assert follower.counters['rejected_waypoints'] == 0
    # Estimates: one per step, finite, covariance symmetric positive definite, and the
    # measurements reduced the weighted trace below its initial value.
    assert len(run.probe.estimates) == STEPS
    for x, P in run.probe.estimates:
        assert np.all(np.isfinite(x)) and np.all(np.isfinite(P))
        np.testing.assert_allclose(P, P.T, rtol=0, atol=1e-12)
        assert np.all(np.linalg.eigvalsh(P) > 0)
    scenario = Scenario.paper('bearing', dt=DT)
    w = weight_vector(scenario.slot)
    initial = float(np.dot(w * w, scenario.initial_covariance))
    assert statuses[-1].weighted_trace < initial
    summary = est.summary()
    assert summary['final_truth'] is not None and summary['mean_nees'] is not None
    assert summary['message_counts']['received']['measurement'] >= STEPS
