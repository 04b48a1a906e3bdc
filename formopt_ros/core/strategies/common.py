"""Pieces shared by RAM and RQ: the range arc logic, the boundary Fourier series, polishing."""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch, point_from_q
from formopt_ros.core.strategies.base import Solution, make_solution
from formopt_ros.core.strategies.certificate import CRITICAL_POINTS, PROVED, certify

#: Relative spread of the gain below which every direction ties (range case): return p_o.
FLAT_TOLERANCE = 1e-12


def gains_tie(problem: Problem, gain_max: float, gain_min: float) -> bool:
    """True when the best and worst gain differ by less than FLAT_TOLERANCE of the cost."""
    return gain_max - gain_min <= FLAT_TOLERANCE * max(problem.base_cost - gain_max, 1e-300)


def range_plan_from_direction(problem: Problem, theta_star: float, flat: bool,
                              candidates: int, method: str) -> Solution:
    """Range case (paper Fig. 3): the best bearing on the feasible arc and its nearest point.

    The range gain depends on the bearing theta only, is pi-periodic and unimodal per period.
    If the unconstrained maximiser ``theta_star`` (mod pi) lies inside the arc of bearings
    ``theta_o +- delta`` under which the disc is seen, it is optimal; otherwise one of the arc's
    end points is. On the chosen ray the point nearest p_o is ``(u . p_o) u``. The answer is
    certified (:func:`~formopt_ros.core.strategies.certificate.certify`); when rounding defeats
    the proof, it is named 'all-critical-points' (the critical directions are known in closed
    form and all were examined).

    Args:
        problem: a range problem.
        theta_star: unconstrained maximiser of the gain, rad (any representative mod pi).
        flat: every direction ties; return p_o.
        candidates: critical points the caller already examined.
        method: name of the calling strategy.
    """
    x_o, y_o = problem.slot
    if flat:
        name, details = certify(problem, (x_o, y_o))
        return make_solution(problem, problem.p_o, method, False, candidates,
                             certificate=name if name in PROVED else CRITICAL_POINTS,
                             details={'flat': True, **details})
    theta_o, delta = problem.bearing_arc()
    offset = (theta_star - theta_o + 0.5 * math.pi) % math.pi - 0.5 * math.pi
    thetas = [theta_o + offset] if abs(offset) <= delta else [theta_o - delta, theta_o + delta]
    best: tuple[float, float, float, float] | None = None
    for theta in thetas:
        c, s = math.cos(theta), math.sin(theta)
        along = c * x_o + s * y_o
        x, y = along * c, along * s
        g = problem.gain_at(x, y)
        if best is None or g > best[0]:
            best = (g, x, y, theta)
    assert best is not None
    g, x, y, theta = best
    name, details = certify(problem, (x, y), g)
    return make_solution(problem, (x, y), method, len(thetas) > 1, candidates + len(thetas),
                         certificate=name if name in PROVED else CRITICAL_POINTS,
                         details={'flat': False, 'theta': theta, **details}, gain=g)


def poly_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Product of polynomials given by coefficient arrays (..., n) and (..., m), batched over
    the leading axes, coefficients summed in a fixed order; shape (..., n + m - 1)."""
    n, m = a.shape[-1], b.shape[-1]
    out = np.zeros(np.broadcast_shapes(a.shape[:-1], b.shape[:-1]) + (n + m - 1,),
                   dtype=np.result_type(a, b))
    for i in range(n):
        out[..., i:i + m] += a[..., i:i + 1] * b
    return out


def fourier(X: np.ndarray, a: np.ndarray, rho: Any) -> np.ndarray:
    """Complex Fourier coefficients (k = -2..2) of t -> h(t)' X h(t), h = a + rho [cos, sin, 0],
    for X (..., 3, 3), a (..., 3), rho (...); shape (..., 5).

    With b = rho e1 and c = rho e2: h'Xh = a'Xa + 2 a'Xb cos + 2 a'Xc sin + b'Xb cos^2
    + 2 b'Xc cos sin + c'Xc sin^2, and a'Xb = rho (Xa)_0, a'Xc = rho (Xa)_1, b'Xb = rho^2 X_00.
    """
    Xa = np.matmul(X, a[..., None])[..., 0]
    r2 = rho * rho
    c0 = np.matmul(a[..., None, :], Xa[..., None])[..., 0, 0] + 0.5 * r2 * (
        X[..., 0, 0] + X[..., 1, 1])
    c1 = rho * (Xa[..., 0] - 1j * Xa[..., 1])
    c2 = 0.5 * r2 * (0.5 * (X[..., 0, 0] - X[..., 1, 1]) - 1j * X[..., 0, 1])
    return np.stack([np.conj(c2), np.conj(c1), c0 + 0j, c1, c2], axis=-1)


def boundary_stationarity(problem: Problem | ProblemBatch) -> np.ndarray:
    """Fourier coefficients F_k, k = -3..3, of num'(t) den(t) - num(t) den'(t) on the q-circle;
    shape (7,) for a problem, (T, 7) for a batch.

    On the image circle q(t) = c_q + rho_q [cos t, sin t] of the disc boundary (bearing case),
    num and den are trigonometric polynomials of degree 2, so their Wronskian has degree 4; its
    k = +-4 harmonics are 2 i (n_2 d_-2 - ...) and cancel identically (checked in the tests),
    leaving degree 3: at most 6 stationary points on the circle.
    """
    c0, c1, rho = (np.asarray(v, dtype=float) for v in problem.q_circle)
    a = np.stack([c0, c1, -np.ones_like(c0)], axis=-1)
    num, den = fourier(problem.M, a, rho), fourier(problem.N, a, rho)
    k = np.arange(-2, 3)
    wronskian = poly_mul(1j * k * num, den) - poly_mul(num, 1j * k * den)
    return wronskian[..., 1:-1]


def polish_boundary_angles(F: np.ndarray, t: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Newton steps on the real trigonometric polynomial f(t) = sum_k F_k e^{ikt} (k = -3..3),
    for F (7,) and t (n,), or F (..., 7) and t (..., n); steps are clipped to 0.1 rad, and an
    angle stops moving once its step is below 1e-15 rad (so each result depends on its own
    start only).

    Start values from companion-matrix roots are accurate to ~1e-14 except near double roots
    (~1e-8), so two quadratically convergent steps suffice; RAM's seeds from clustered roots
    need a few more. With F_-k = conj(F_k): f = F_0 + 2 sum_k (Re F_k cos kt - Im F_k sin kt).
    """
    F = np.asarray(F)[..., None, :]
    re, im = 2.0 * F.real[..., 4:], 2.0 * F.imag[..., 4:]
    t = np.asarray(t, dtype=float).copy()
    moving = np.ones(t.shape, dtype=bool)
    for _ in range(iterations):
        c1, s1 = np.cos(t), np.sin(t)
        c2, s2 = c1 * c1 - s1 * s1, 2.0 * s1 * c1
        c3, s3 = c2 * c1 - s2 * s1, s2 * c1 + c2 * s1
        value = (F.real[..., 3] + re[..., 0] * c1 - im[..., 0] * s1 + re[..., 1] * c2
                 - im[..., 1] * s2 + re[..., 2] * c3 - im[..., 2] * s3)
        slope = -(re[..., 0] * s1 + im[..., 0] * c1 + 2.0 * (re[..., 1] * s2 + im[..., 1] * c2)
                  + 3.0 * (re[..., 2] * s3 + im[..., 2] * c3))
        with np.errstate(divide='ignore', invalid='ignore'):
            step = np.where(moving & (slope != 0.0), np.clip(value / slope, -0.1, 0.1), 0.0)
        t -= step
        moving &= np.abs(step) > 1e-15
        if not moving.any():
            break
    return t


def boundary_points(problem: Problem, t: np.ndarray) -> np.ndarray:
    """Points p (n, 2) on the disc boundary at q-circle angles t (rad)."""
    centre, rho = problem.q_disc()
    q = centre + rho * np.stack([np.cos(t), np.sin(t)], axis=-1)
    return point_from_q(q)
