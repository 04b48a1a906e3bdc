"""Range and bearing together: the stacked model, EKF update, gate, scenario and simulators."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from formopt_ros.core.batched import run_trials
from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.estimator import (
    INNOVATION_GATE_2, REOPEN_NIS_2, EstimatorPlanner, stacked_innovation_gate)
from formopt_ros.core.model import (
    BEARING, RANGE, RANGE_BEARING, ekf_update, ekf_update_stacked, measurement_jacobian,
    predict_measurement, stacked_nis, wrap_angle)
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.core.strategies import make_strategy

SEED = 11


def random_state(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A pose 0.5-5 m from the leader and a random SPD covariance (condition <= 1e4)."""
    d, theta = rng.uniform(0.5, 5.0), rng.uniform(-math.pi, math.pi)
    x = np.array([d * math.cos(theta), d * math.sin(theta), rng.uniform(-math.pi, math.pi)])
    q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    P = (q * 10.0 ** -rng.uniform(0.0, 4.0, 3)) @ q.T * 10.0 ** rng.uniform(-3.0, 0.0)
    return x, 0.5 * (P + P.T)


def test_stacked_prediction_and_jacobian_are_the_rows() -> None:
    """z and H of 'range-bearing' are the range's and the bearing's stacked, and H equals
    central differences of the prediction (bearing difference wrapped) to 1e-8."""
    rng = np.random.default_rng(SEED)
    for _ in range(20):
        x, _ = random_state(rng)
        z = predict_measurement(RANGE_BEARING, x)
        assert z.tolist() == [predict_measurement(RANGE, x), predict_measurement(BEARING, x)]
        H = measurement_jacobian(RANGE_BEARING, x)
        assert H.shape == (2, 3)
        np.testing.assert_array_equal(H[0], measurement_jacobian(RANGE, x))
        np.testing.assert_array_equal(H[1], measurement_jacobian(BEARING, x))
        numeric = np.empty((2, 3))
        for j in range(3):
            e = np.zeros(3)
            e[j] = 1e-6
            diff = predict_measurement(RANGE_BEARING, x + e) - \
                predict_measurement(RANGE_BEARING, x - e)
            diff[1] = wrap_angle(diff[1])
            numeric[:, j] = diff / 2e-6
        np.testing.assert_allclose(H, numeric, rtol=0, atol=1e-8)


def test_stacked_update_equals_the_standard_and_information_forms() -> None:
    """Joseph-form P_post equals P - P H' S^-1 H P and (P^-1 + H' R^-1 H)^-1 to 1e-12
    relative; x_post = x + K nu with the bearing residual wrapped; NIS = nu' S^-1 nu."""
    rng = np.random.default_rng(SEED)
    for _ in range(200):
        x, P = random_state(rng)
        variances = (rng.uniform(0.01, 0.5) ** 2, rng.uniform(0.002, 0.1) ** 2)
        z = predict_measurement(RANGE_BEARING, x) + np.array([0.03, 0.01])
        z[1] = wrap_angle(z[1])
        x_post, P_post, nu, S = ekf_update_stacked(x, P, z, variances)
        H = measurement_jacobian(RANGE_BEARING, x)
        S_ref = H @ P @ H.T + np.diag(variances)
        standard = P - P @ H.T @ np.linalg.solve(S_ref, H @ P)
        information = np.linalg.inv(np.linalg.inv(P)
                                    + H.T @ np.diag(1 / np.array(variances)) @ H)
        scale = np.abs(P).max()
        np.testing.assert_allclose(P_post, standard, rtol=0, atol=1e-12 * scale)
        np.testing.assert_allclose(P_post, information, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(nu, [0.03, 0.01], rtol=0, atol=1e-12)
        expected_x = x + P @ H.T @ np.linalg.solve(S_ref, nu)
        expected_x[2] = wrap_angle(expected_x[2])
        np.testing.assert_allclose(x_post, expected_x, rtol=0, atol=1e-12)
        assert stacked_nis(nu, S) == pytest.approx(float(nu @ np.linalg.solve(S_ref, nu)),
                                                   rel=1e-12)


def test_stacked_bearing_residual_is_wrapped() -> None:
    """A bearing of pi - 0.001 against a predicted -pi + 0.001 is a residual of -0.002 rad."""
    x = np.array([1.0, 1e-3, 0.0])           # the leader seen at about -pi from the follower
    predicted = predict_measurement(BEARING, x)
    z = np.array([math.hypot(1.0, 1e-3), wrap_angle(predicted - 0.002)])
    assert abs(z[1] - predicted) > 6.0      # across the cut
    nu = ekf_update_stacked(x, np.eye(3) * 0.01, z, (0.01, 1e-4))[2]
    assert nu[1] == pytest.approx(-0.002, abs=1e-12)


def test_batch_update_equals_single_updates_bit_for_bit() -> None:
    """The stacked update of T poses gives each pose the bits it gets alone."""
    rng = np.random.default_rng(SEED)
    states = [random_state(rng) for _ in range(7)]
    x = np.array([s[0] for s in states])
    P = np.array([s[1] for s in states])
    z = predict_measurement(RANGE_BEARING, x) + rng.normal(0.0, 0.01, (7, 2))
    batch = ekf_update_stacked(x, P, z, (0.01, 4e-4))
    for t in range(7):
        single = ekf_update_stacked(x[t], P[t], z[t], (0.01, 4e-4))
        for a, b in zip(batch, single):
            np.testing.assert_array_equal(a[t], b)


def test_stacked_gate_levels_and_reopening() -> None:
    """The 2-dof gate has the scalar gate's tail probabilities (105.1, 11.8); a re-opening
    scales P so that the stacked NIS is REOPEN_NIS_2 (to 1e-9)."""
    assert INNOVATION_GATE_2 == pytest.approx(-2 * math.log(math.erfc(math.sqrt(50.0))),
                                              rel=1e-15)
    assert INNOVATION_GATE_2 == pytest.approx(105.08, abs=0.01)
    assert REOPEN_NIS_2 == pytest.approx(11.83, abs=0.01)
    rng = np.random.default_rng(SEED)
    for _ in range(50):
        x, P = random_state(rng)
        variances = (0.01, 4e-4)
        H = measurement_jacobian(RANGE_BEARING, x)
        S = H @ P @ H.T + np.diag(variances)
        nu = np.linalg.cholesky(S) @ rng.normal(size=2)
        nu *= 20.0 / math.sqrt(float(nu @ np.linalg.solve(S, nu)))      # NIS 400: gated
        nis, use, inflation = stacked_innovation_gate(nu, S, variances, 0)
        assert nis == pytest.approx(400.0, rel=1e-12) and not use and inflation == 1.0
        nis, use, inflation = stacked_innovation_gate(nu, S, variances, 3)
        assert use and inflation > 1.0
        S_inflated = inflation * (S - np.diag(variances)) + np.diag(variances)
        reopened = float(nu @ np.linalg.solve(S_inflated, nu))
        assert reopened == pytest.approx(REOPEN_NIS_2, rel=1e-9)


def test_estimator_uses_one_sensor_when_the_other_is_missing() -> None:
    """z = [d, NaN] is the range's scalar update, [NaN, beta] the bearing's, bit for bit."""
    s = Scenario.paper(RANGE_BEARING)
    z_true = predict_measurement(RANGE_BEARING, np.array([-1.05, -1.9, 0.01]))
    for index, kind, variance in ((0, RANGE, s.sigma ** 2), (1, BEARING, s.sigma_bearing ** 2)):
        est = EstimatorPlanner(s, make_strategy('mtf'))
        x0, P0 = est.state.copy(), est.covariance.copy()
        z = np.full(2, np.nan)
        z[index] = z_true[index]
        result = est.update(1, z)
        x_ref, P_ref, nu, _ = ekf_update(x0, P0, float(z_true[index]), kind, variance)
        np.testing.assert_array_equal(est.x, x_ref)
        np.testing.assert_array_equal(est.P, P_ref)
        assert result.used and result.innovation == nu


def test_scenario_fields() -> None:
    """The paper's range-bearing follower: the range slot, sigma_d = 0.1 m, sigma_beta = 0.02
    rad; the scalar kinds' records have no new keys; the new fields are refused for them."""
    s = Scenario.paper(RANGE_BEARING)
    assert (s.p_o, s.sigma, s.sigma_bearing, s.bearing_every) == ((-1.0, -2.0), 0.1, 0.02, 1)
    assert Scenario.from_dict(s.to_dict()) == s
    assert 'sigma_bearing' not in Scenario.paper(RANGE).to_dict()
    assert [Scenario.paper(RANGE_BEARING, bearing_every=3).bearing_at(k) for k in range(1, 7)] \
        == [False, False, True, False, False, True]
    with pytest.raises(InvalidInput, match='sigma_bearing'):
        Scenario.paper(RANGE, sigma_bearing=0.02)
    with pytest.raises(InvalidInput, match='sigma_bearing'):
        Scenario.paper(RANGE_BEARING, sigma_bearing=0.0)


@pytest.mark.parametrize('strategy, every', [
    *((strategy, every) for strategy in ('rq', 'gbs', 'mtf', 'crm', 'mme') for every in (1, 3)),
    pytest.param('periodic', 1, marks=pytest.mark.slow), ('periodic', 3)])
def test_batched_engine_equals_run_trial(strategy: str, every: int) -> None:
    """run_trials equals run_trial for a range-bearing follower (bearing every step and every
    3rd), to 1e-9 (in practice bit for bit), with a turning leader segment."""
    scenario = Scenario.paper(RANGE_BEARING, bearing_every=every,
                              leader={'kind': 'segments', 'segments': [
                                  {'duration': 0.5, 'speed': 1.0},
                                  {'duration': 1.0, 'speed': 1.0, 'yaw_rate': 0.3}]})
    options = {'cell': 0.05} if strategy == 'gbs' else None
    steps = 12
    batch = run_trials(scenario, strategy, SEED, [0, 1], steps, options)
    for t in (0, 1):
        ref = run_trial(scenario, strategy, SEED, t, steps, options)
        got = batch.trial(t)
        for name in ('covariance', 'estimate', 'truth', 'waypoints', 'nees',
                     'weighted_trace', 'innovation_nis'):
            np.testing.assert_allclose(getattr(got, name), getattr(ref, name), rtol=0,
                                       atol=1e-9, err_msg=name)
        missing = [k % every != 0 for k in range(1, steps + 1)]
        assert np.all(np.isnan(ref.measurements[:, 1]) == missing)


def test_ram_does_not_apply() -> None:
    """RAM refuses a range-bearing problem with a ValueError naming the measurement."""
    with pytest.raises(ValueError, match="range-bearing"):
        run_trial(Scenario.paper(RANGE_BEARING), 'ram', SEED, 0, 1)


def test_formation_files_take_range_bearing_followers() -> None:
    """config/formation_range_bearing.yaml loads (its third follower measures both, RQ by
    default) and round-trips; a single noise, RAM, real interfaces, or bearing_every on a
    single-sensor follower are refused naming the field."""
    from formopt_ros.core.formation import Formation
    from formopt_ros.wire.formation import load_formation
    path = Path(__file__).resolve().parents[2] / 'config' / 'formation_range_bearing.yaml'
    formation = load_formation(path)
    both = formation.follower('both').scenario
    assert (both.measurement, both.sigma, both.sigma_bearing) == (RANGE_BEARING, 0.1, 0.02)
    assert Formation.from_dict(formation.to_dict()) == formation
    follower = {'id': 'f', 'sensor': RANGE_BEARING, 'slot': [-1.0, -2.0]}
    assert Formation.from_dict({'followers': [follower]}).followers[0].strategy == 'rq'
    for change, field in (({'noise': 0.1}, 'noise'), ({'strategy': 'ram'}, 'strategy'),
                          ({'interfaces': 'real'}, 'interfaces'),
                          ({'sensor': 'range', 'bearing_every': 2}, 'bearing_every')):
        with pytest.raises(InvalidInput) as error:
            Formation.from_dict({'followers': [{**follower, **change}]})
        assert field in error.value.name, (change, error.value)


def test_a_stacked_nis_splits_into_two_independent_chi_square_1_terms() -> None:
    """whitened_squares: the two terms sum to nu' S^-1 nu (1e-12 relative) and, for nu drawn
    from N(0, S) with random S (20,000 draws, seeded), each has mean 1 and they are
    uncorrelated (within 0.05), as the consistency watch's 1-dof windows assume."""
    from formopt_ros.core.estimator import whitened_squares
    from formopt_ros.core.model import stacked_nis
    rng = np.random.default_rng(26)
    terms = []
    for _ in range(20_000):
        A = rng.normal(size=(2, 2)) * [1.0, 0.01]
        S = A @ A.T + np.diag([1e-2, 4e-4])
        nu = np.linalg.cholesky(S) @ rng.normal(size=2)
        parts = whitened_squares(nu, S)
        assert sum(parts) == pytest.approx(float(stacked_nis(nu, S)), rel=1e-12)
        terms.append(parts)
    terms_array = np.array(terms)
    assert np.all(np.abs(terms_array.mean(axis=0) - 1.0) < 0.05)
    assert abs(np.corrcoef(terms_array.T)[0, 1]) < 0.05
