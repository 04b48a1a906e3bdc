"""Unit tests of formopt_ros.core.model: kinematics, Jacobians, EKF update and NEES (eqs. 9-19)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from formopt_ros.core.model import (
    BEARING, RANGE, ekf_update, measurement_jacobian, normalized_estimation_error, propagate,
    propagate_state, predict_measurement, transition_matrices, wrap_angle)

SEED = 20240611


def random_spd(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """A well-conditioned random 3x3 SPD matrix (condition number below ~100)."""
    A = rng.standard_normal((3, 3))
    return scale * (A @ A.T + 0.5 * np.eye(3))


def random_pose(rng: np.random.Generator) -> np.ndarray:
    """A pose [x, y, phi] with 0.5 m <= |p| <= 10 m and phi away from the +-pi cut."""
    d = rng.uniform(0.5, 10.0)
    theta = rng.uniform(-math.pi, math.pi)
    return np.array([d * math.cos(theta), d * math.sin(theta), rng.uniform(-3.0, 3.0)])


def state_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a - b with the heading difference wrapped."""
    e = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    e[2] = wrap_angle(e[2])
    return e


def numerical_jacobians(x: np.ndarray, v_f: float, omega_f: float, dt: float, v_l: float,
                        omega_l: float, step: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Central finite differences of propagate_state w.r.t. the state (Phi, 3 x 3) and the
    velocities [v_f, omega_f, v_l, omega_l] (G, 3 x 4)."""
    def moved(x: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        return propagate_state(x, velocities[0], velocities[1], dt, velocities[2], velocities[3])

    u = np.array([v_f, omega_f, v_l, omega_l])
    Phi, G = np.zeros((3, 3)), np.zeros((3, 4))
    for j in range(3):
        e = np.zeros(3)
        e[j] = step
        Phi[:, j] = state_difference(moved(x + e, u), moved(x - e, u)) / (2 * step)
    for j in range(4):
        e = np.zeros(4)
        e[j] = step
        G[:, j] = state_difference(moved(x, u + e), moved(x, u - e)) / (2 * step)
    return Phi, G


def world_arc(pose: tuple[float, float, float], v: float, omega: float,
              dt: float) -> tuple[float, float, float]:
    """A unicycle's pose after dt at constant (v, omega) in a fixed frame, by the textbook
    centre-of-rotation formula (written independently of the package's chord)."""
    x, y, yaw = pose
    if omega == 0.0:
        return x + v * dt * math.cos(yaw), y + v * dt * math.sin(yaw), yaw
    radius = v / omega
    return (x + radius * (math.sin(yaw + omega * dt) - math.sin(yaw)),
            y - radius * (math.cos(yaw + omega * dt) - math.cos(yaw)), yaw + omega * dt)


def relative_pose(leader: tuple[float, float, float],
                  follower: tuple[float, float, float]) -> np.ndarray:
    """The follower's pose in the leader's frame from both world poses (eq. 5)."""
    c, s = math.cos(leader[2]), math.sin(leader[2])
    dx, dy = follower[0] - leader[0], follower[1] - leader[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, wrap_angle(follower[2] - leader[2])])


def test_propagate_state_matches_eq9_where_euler_is_exact() -> None:
    """With omega_L = 0 and a step that only drives (omega_F = 0) or only turns (v_F = 0), the
    protocol's two sub-steps, the step is exactly eq. (9); heading is wrapped to [-pi, pi)."""
    rng = np.random.default_rng(SEED)
    for i in range(200):
        x = random_pose(rng)
        v_f, omega_f, dt, v_l = rng.uniform(0, 2), rng.uniform(-1, 1), rng.uniform(0.01, 0.5), \
            rng.uniform(0, 2)
        v_f, omega_f = (v_f, 0.0) if i % 2 else (0.0, omega_f)
        expected = np.array([x[0] + math.cos(x[2]) * v_f * dt - v_l * dt,
                             x[1] + math.sin(x[2]) * v_f * dt,
                             wrap_angle(x[2] + omega_f * dt)])
        # 1e-12 absolute: the same few floating-point operations in a possibly different order.
        np.testing.assert_allclose(propagate_state(x, v_f, omega_f, dt, v_l), expected,
                                   rtol=0, atol=1e-12)
    wrapped = propagate_state(np.array([1.0, 1.0, 3.1]), 0.0, 1.0, 0.1, 0.0)
    # 1e-12 absolute: 3.1 + 0.1 - 2 pi exactly representable to rounding.
    assert wrapped[2] == pytest.approx(3.2 - 2 * math.pi, abs=1e-12)


def test_relative_motion_equals_both_robots_in_the_world_frame() -> None:
    """Both robots turning at about 1 rad/s for 60 s at dt 0.1 s, 5 m apart: the relative
    propagation equals the two world-frame arcs composed (1e-9 m), where Euler drifts by
    metres (it scales |p| by sqrt(1 + (omega_L dt)^2) per step)."""
    rng = np.random.default_rng(SEED + 1)
    dt, steps = 0.1, 600
    leader, follower = (0.0, 0.0, 0.0), (-3.0, -4.0, 0.0)
    x = relative_pose(leader, follower)
    euler = x.copy()
    for _ in range(steps):
        v_l, omega_l = 1.0 + 0.1 * rng.normal(), 1.0 + 0.1 * rng.normal()
        v_f, omega_f = 1.0 + 0.5 * rng.normal(), 1.0 + 0.5 * rng.normal()
        leader = world_arc(leader, v_l, omega_l, dt)
        follower = world_arc(follower, v_f, omega_f, dt)
        x = propagate_state(x, v_f, omega_f, dt, v_l, omega_l)
        euler = np.array([euler[0] + (omega_l * euler[1] + math.cos(euler[2]) * v_f - v_l) * dt,
                          euler[1] + (-omega_l * euler[0] + math.sin(euler[2]) * v_f) * dt,
                          wrap_angle(euler[2] + (omega_f - omega_l) * dt)])
    truth = relative_pose(leader, follower)
    # 1e-9 m: 600 compositions of rotations and chords, each exact to rounding.
    np.testing.assert_allclose(state_difference(x, truth), 0.0, atol=1e-9)
    assert np.hypot(*(euler - truth)[:2]) > 1.0


@pytest.mark.parametrize('omega_l', [0.0, 0.4])
def test_propagate_covariance_matches_finite_difference_jacobians(omega_l: float) -> None:
    """P_next = Phi P Phi' + G Q G' (eq. 12) with Phi and G (follower and leader velocities)
    from finite differences of the exact step."""
    rng = np.random.default_rng(SEED + 2)
    for i in range(100):
        x = random_pose(rng)
        P = random_spd(rng, 0.01)
        v_f, omega_f, dt, v_l = rng.uniform(0.1, 2), rng.uniform(-1, 1), rng.uniform(0.01, 0.5), \
            rng.uniform(0, 2)
        omega_f = (omega_f, 0.0, 1e-5)[i % 3]           # the chord's series branch too
        noise = rng.uniform(0.01, 0.2, size=4) * (1.0 if i % 2 else np.array([1, 1, 0, 0]))
        x_next, P_next = propagate(x, P, v_f, omega_f, dt, v_l, omega_l, *noise)
        # 1e-12 absolute: the mean is propagate_state itself.
        np.testing.assert_allclose(x_next, propagate_state(x, v_f, omega_f, dt, v_l, omega_l),
                                   rtol=0, atol=1e-12)
        Phi, G = numerical_jacobians(x, v_f, omega_f, dt, v_l, omega_l)
        Q = np.diag(noise ** 2)
        expected = Phi @ P @ Phi.T + G @ Q @ G.T
        # rtol 1e-6 (central differences, step 1e-6: truncation ~1e-12, rounding ~1e-10).
        np.testing.assert_allclose(P_next, expected, rtol=1e-6, atol=1e-6 * np.abs(P).max())
        assert np.array_equal(P_next, P_next.T)
        Phi_m, GQG = transition_matrices(x, v_f, omega_f, dt, v_l, omega_l, *noise)
        # 1e-7 absolute on Phi (central differences); the matrix form reproduces propagate to
        # 1e-12 relative to max |P| (same products, different summation order).
        np.testing.assert_allclose(Phi_m, Phi, rtol=0, atol=1e-7)
        np.testing.assert_allclose(GQG, G @ Q @ G.T, rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(Phi_m @ P @ Phi_m.T + GQG, P_next, rtol=0,
                                   atol=1e-12 * np.abs(P).max())


def test_propagate_covariance_matches_printed_eq11_for_a_straight_drive() -> None:
    """With omega_L = omega_F = 0, Phi and the v_F column of G are the matrices printed in eq.
    (11); the omega_F column adds the exact arc's v_F dt^2 / 2 sideways (printed: 0)."""
    rng = np.random.default_rng(SEED + 3)
    for _ in range(50):
        x = random_pose(rng)
        P = random_spd(rng, 0.01)
        v_f, dt, v_l = 1.3, 0.1, 1.0
        _, P_next = propagate(x, P, v_f, 0.0, dt, v_l, 0.0, 0.05, 0.02)
        c, s = math.cos(x[2]), math.sin(x[2])
        Phi = np.array([[1, 0, -s * v_f * dt], [0, 1, c * v_f * dt], [0, 0, 1]])
        arc = v_f * dt * dt / 2
        G = np.array([[c * dt, -s * arc], [s * dt, c * arc], [0, dt]])
        expected = Phi @ P @ Phi.T + G @ np.diag([0.05 ** 2, 0.02 ** 2]) @ G.T
        # 1e-12 relative to max |P|: same products, different summation order.
        np.testing.assert_allclose(P_next, expected, rtol=0, atol=1e-12 * np.abs(P).max())


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_measurement_jacobian_matches_finite_differences(kind: str) -> None:
    """h of eqs. (16) and (18) equals central differences of predict_measurement."""
    rng = np.random.default_rng(SEED + 4)
    step = 1e-6
    for _ in range(300):
        x = random_pose(rng)
        numeric = np.zeros(3)
        for j in range(3):
            e = np.zeros(3)
            e[j] = step
            diff = predict_measurement(kind, x + e) - predict_measurement(kind, x - e)
            numeric[j] = wrap_angle(diff) / (2 * step) if kind == BEARING else diff / (2 * step)
        # 1e-6 relative to |h| (central differences with step 1e-6; |p| >= 0.5 m).
        np.testing.assert_allclose(measurement_jacobian(kind, x), numeric, rtol=0,
                                   atol=1e-6 * np.linalg.norm(numeric))


def test_measurement_models() -> None:
    """Range is |p| (eq. 15); bearing is atan2(y, x) - phi + pi wrapped (eq. 17)."""
    x = np.array([3.0, 4.0, 0.25])
    assert predict_measurement(RANGE, x) == pytest.approx(5.0, rel=1e-15)  # exact up to rounding
    expected = math.atan2(4.0, 3.0) - 0.25 + math.pi - 2 * math.pi
    assert predict_measurement(BEARING, x) == pytest.approx(expected, abs=1e-15)
    assert -math.pi <= predict_measurement(BEARING, np.array([-1.0, 0.0, 0.0])) < math.pi


@pytest.mark.parametrize('side', [-1.0, 1.0])
def test_bearing_innovation_is_wrapped(side: float) -> None:
    """A bearing just across the +-pi cut from the prediction gives a small wrapped innovation."""
    x = np.array([3.0, 0.002, 0.0])              # predicted bearing = pi + atan(0.002/3) - 2 pi
    predicted = predict_measurement(BEARING, x)
    assert predicted < -math.pi + 0.01           # just above -pi, i.e. just above +pi unwrapped
    z = wrap_angle(predicted + side * 0.005)     # for side = -1 this is just below +pi
    if side < 0:
        assert z > math.pi - 0.01
    P = np.diag([0.01, 0.01, 0.001])
    x_post, P_post, innovation, S = ekf_update(x, P, z, BEARING, 1e-4)
    # 1e-12 absolute: the innovation is the 0.005 rad offset, not 0.005 - 2 pi.
    assert innovation == pytest.approx(side * 0.005, abs=1e-12)
    # The state moves by K * innovation, a few milliradians / millimetres, not ~2 pi worth.
    assert np.all(np.abs(state_difference(x_post, x)) < 0.01)
    assert -math.pi <= x_post[2] < math.pi


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_ekf_update_joseph_form_equals_standard_form(kind: str) -> None:
    """The Joseph-form update is symmetric PD and equals P - P h' S^-1 h P (eq. 19)."""
    rng = np.random.default_rng(SEED + 5)
    for _ in range(300):
        x = random_pose(rng)
        P = random_spd(rng, 10 ** rng.uniform(-4, 0))
        variance = (rng.uniform(0.01, 0.5) if kind == RANGE else rng.uniform(0.002, 0.1)) ** 2
        z = predict_measurement(kind, x) + 0.01
        x_post, P_post, innovation, S = ekf_update(x, P, z, kind, variance)
        h = measurement_jacobian(kind, x)
        S_expected = float(h @ P @ h) + variance
        standard = P - np.outer(P @ h, h @ P) / S_expected
        # 1e-12 relative to max |P| (a handful of rounding errors of size eps * |P|).
        np.testing.assert_allclose(P_post, standard, rtol=0, atol=1e-12 * np.abs(P).max())
        assert S == pytest.approx(S_expected, rel=1e-12)  # same expression, rounding only
        assert np.array_equal(P_post, P_post.T)
        assert np.all(np.linalg.eigvalsh(P_post) > 0)
        # 1e-12 absolute (rad or m): the innovation is z minus the prediction.
        assert innovation == pytest.approx(0.01, abs=1e-12)
        K = P @ h / S_expected
        expected_x = x + K * 0.01
        # 1e-12 absolute: same gain and innovation.
        np.testing.assert_allclose(state_difference(x_post, expected_x), 0.0, atol=1e-12)


def test_normalized_estimation_error_wraps_heading() -> None:
    """NEES uses the wrapped heading error: estimates across the +-pi cut are close."""
    P = np.diag([0.04, 0.09, 0.01])
    x_true = np.array([1.0, 2.0, math.pi - 0.01])
    x_est = np.array([1.1, 1.9, -math.pi + 0.01])
    e = np.array([-0.1, 0.1, -0.02])
    expected = float(e @ np.linalg.solve(P, e))
    # 1e-9 relative: 2 pi - 0.02 is wrapped back to -0.02 with ~1e-15 absolute rounding.
    assert normalized_estimation_error(x_true, x_est, P) == pytest.approx(expected, rel=1e-9)
    rng = np.random.default_rng(SEED + 6)
    for _ in range(50):
        A = random_spd(rng)
        e = rng.standard_normal(3)
        x_est = random_pose(rng)
        e[2] += 2 * math.pi * rng.integers(-2, 3)     # whole turns must not matter
        x_true = x_est + e
        wrapped = state_difference(x_true, x_est)
        # 1e-9 relative: quadratic form of a well-conditioned SPD matrix after wrapping.
        assert normalized_estimation_error(x_true, x_est, A) == pytest.approx(
            float(wrapped @ np.linalg.solve(A, wrapped)), rel=1e-9)
        # 1e-9 absolute (rad): the added whole turns are removed by the wrap.
        assert abs(wrap_angle(wrapped[2] - e[2])) < 1e-9
