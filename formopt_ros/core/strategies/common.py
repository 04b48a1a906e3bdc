"""Pieces shared by RAM and RQ: the range arc logic, the boundary Fourier series, polishing."""
from __future__ import annotations

import math

import numpy as np

from formopt_ros.core.cost import Problem, point_from_q
from formopt_ros.core.strategies.base import Solution, make_solution

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
    end points is. On the chosen ray the point nearest p_o is ``(u . p_o) u``.

    Args:
        problem: a range problem.
        theta_star: unconstrained maximiser of the gain, rad (any representative mod pi).
        flat: every direction ties; return p_o.
        candidates: critical points the caller already examined.
        method: name of the calling strategy.
    """
    if flat:
        return make_solution(problem, problem.p_o.copy(), method, False, candidates,
                             details={'flat': True})
    theta_o, delta = problem.bearing_arc()
    offset = (theta_star - theta_o + 0.5 * math.pi) % math.pi - 0.5 * math.pi
    if abs(offset) <= delta:
        thetas = [theta_o + offset]
    else:
        thetas = [theta_o - delta, theta_o + delta]
    units = np.array([[math.cos(t), math.sin(t)] for t in thetas])
    points = (units @ problem.p_o)[:, None] * units
    best = int(np.argmax(problem.gain(points))) if len(thetas) > 1 else 0
    return make_solution(problem, points[best], method, len(thetas) > 1,
                         candidates + len(thetas), details={'flat': False, 'theta': thetas[best]})


def _fourier(X: np.ndarray, a: np.ndarray, rho: float) -> np.ndarray:
    """Complex Fourier coefficients (k = -2..2) of t -> h(t)' X h(t), h = a + rho [cos, sin, 0].

    With b = rho e1 and c = rho e2: h'Xh = a'Xa + 2 a'Xb cos + 2 a'Xc sin + b'Xb cos^2
    + 2 b'Xc cos sin + c'Xc sin^2, and a'Xb = rho (Xa)_0, a'Xc = rho (Xa)_1, b'Xb = rho^2 X_00.
    """
    Xa = X @ a
    r2 = rho * rho
    c0 = a @ Xa + 0.5 * r2 * (X[0, 0] + X[1, 1])
    c1 = rho * (Xa[0] - 1j * Xa[1])
    c2 = 0.5 * r2 * (0.5 * (X[0, 0] - X[1, 1]) - 1j * X[0, 1])
    return np.array([np.conj(c2), np.conj(c1), c0, c1, c2])


def boundary_stationarity(problem: Problem) -> np.ndarray:
    """Fourier coefficients F_k, k = -3..3, of num'(t) den(t) - num(t) den'(t) on the q-circle.

    On the image circle q(t) = c_q + rho_q [cos t, sin t] of the disc boundary (bearing case),
    num and den are trigonometric polynomials of degree 2, so their Wronskian has degree 4; its
    k = +-4 harmonics are 2 i (n_2 d_-2 - ...) and cancel identically (checked in the tests),
    leaving degree 3: at most 6 stationary points on the circle.
    """
    centre, rho = problem.q_disc()
    a = np.array([centre[0], centre[1], -1.0])
    num = _fourier(problem.M, a, rho)
    den = _fourier(problem.N, a, rho)
    k = np.arange(-2, 3)
    wronskian = np.convolve(1j * k * num, den) - np.convolve(num, 1j * k * den)
    return wronskian[1:-1]


def polish_boundary_angles(F: np.ndarray, t: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Newton steps on the real trigonometric polynomial sum_k F_k e^{ikt} = 0 (k = -3..3).

    The start values are angles of companion-matrix roots, accurate to ~1e-14 except near
    double roots (~1e-8), so two quadratically convergent steps suffice.
    """
    k = np.arange(-3, 4)
    t = np.asarray(t, dtype=float).copy()
    for _ in range(iterations):
        e = np.exp(1j * np.outer(t, k))
        value = (e @ F).real
        slope = (e @ (1j * k * F)).real
        step = np.where(np.abs(slope) > 0, value / np.where(slope == 0, 1.0, slope), 0.0)
        t -= np.clip(step, -0.1, 0.1)
    return t


def boundary_points(problem: Problem, t: np.ndarray) -> np.ndarray:
    """Points p (n, 2) on the disc boundary at q-circle angles t (rad)."""
    centre, rho = problem.q_disc()
    q = centre + rho * np.stack([np.cos(t), np.sin(t)], axis=-1)
    return point_from_q(q)


def best_of(problem: Problem, points: np.ndarray) -> tuple[int, np.ndarray]:
    """Index of the highest-gain point among points (n, 2), and all gains (n,)."""
    gains = problem.gain(points)
    return int(np.argmax(gains)), gains
