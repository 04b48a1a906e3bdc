"""Pieces shared by RAM and RQ: the range arc logic, the boundary Fourier series, polishing."""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.formulas import point_from_q
from formopt_ros.core.model import RANGE
from formopt_ros.core.strategies.base import Solution, make_solution
from formopt_ros.core.strategies.certificate import PROVED
from formopt_ros.core.strategies.verify import CHECK_SAMPLES, certify, settle_unproved

#: Relative spread of the gain below which every direction ties (range case): return p_o.
FLAT_TOLERANCE = 1e-12


def gains_tie(problem: Problem | ProblemBatch, gain_max: Any, gain_min: Any,
              maximum: Callable[[Any, Any], Any] = max) -> Any:
    """True when the best and worst gain differ by less than FLAT_TOLERANCE of the cost (floats;
    for a batch, arrays (T,) with ``maximum=numpy.maximum``)."""
    return gain_max - gain_min <= FLAT_TOLERANCE * maximum(problem.base_cost - gain_max, 1e-300)


def check_points(problem: Problem, extra: Sequence[tuple[float, float]] = ()) -> np.ndarray:
    """The CHECK_SAMPLES boundary samples, the slot and ``extra`` points, shape (n, 2), m.

    Bearing adds CHECK_SAMPLES boundary points equally spaced in angle on the q-circle (the
    disc's image under p -> (-y, x) / |p|^2): they crowd where the disc comes close to the
    leader, where a basin of the optimum can lie between two samples around p_o (a reviewer's
    problems with variances from 1e-100 to 1e22: answers 7e-6 to 0.45 above the optimum).
    """
    angles = np.linspace(0.0, 2.0 * math.pi, CHECK_SAMPLES, endpoint=False)
    ring = np.stack([np.cos(angles), np.sin(angles)], 1)
    parts = [problem.p_o + problem.r * ring]
    if problem.measurement != RANGE:
        c0, c1, rho = problem.q_circle
        parts.append(point_from_q(np.array([c0, c1]) + rho * ring))
    return np.vstack([*parts, problem.p_o[None, :], np.reshape(extra, (-1, 2))])


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
        if name in PROVED:
            return make_solution(problem, problem.p_o, method, False, candidates,
                                 certificate=name, details={'flat': True, **details})
        # not proved: the tie may be the rounding of a near-singular P; look at the arc
    theta_o, delta = problem.bearing_arc()
    offset = (theta_star - theta_o + 0.5 * math.pi) % math.pi - 0.5 * math.pi
    thetas = [theta_o + offset] if abs(offset) <= delta else [theta_o - delta, theta_o + delta]
    ends = []
    for theta in thetas:
        c, s = math.cos(theta), math.sin(theta)
        along = c * x_o + s * y_o
        x, y = along * c, along * s
        ends.append((problem.gain_at(x, y), x, y, theta))
    best = 1 if len(ends) == 2 and ends[1][0] > ends[0][0] else 0
    g, x, y, theta = ends[best]
    name, details = certify(problem, (x, y), g)
    if name in PROVED:
        return make_solution(problem, (x, y), method, len(thetas) > 1, candidates + len(thetas),
                             certificate=name, details={'flat': False, 'theta': theta, **details},
                             gain=g)
    # the formula's rounding may exceed the candidates' differences: near ties among the arc's
    # ends, the samples and the slot are decided on exact gains, and the cost is reported exactly
    others = check_points(problem)
    chosen, enumerated, p, name, details = settle_unproved(
        problem, np.array([end[1:3] for end in ends]), np.array([end[0] for end in ends]),
        others, problem.gain(others), np.array((x, y)), details)
    x, y = float(p[0]), float(p[1])
    theta = ends[chosen][3] if enumerated else math.atan2(y, x)
    if not enumerated and name not in PROVED:
        details.setdefault('reason', f'rounding lost the critical direction: the best of '
                           f'{len(ends)} arc points is not as good as the best of '
                           f'{CHECK_SAMPLES} boundary samples and the slot')
    on_boundary = abs(math.hypot(x - x_o, y - y_o) - problem.r) <= 1e-9 * problem.r
    return make_solution(problem, (x, y), method, on_boundary if not enumerated
                         else len(thetas) > 1, candidates + len(thetas) + len(others),
                         certificate=name, details={'flat': False, 'theta': theta, **details})


#: A polynomial as the tuple of its coefficients, each a float or an array (T,) (a batch).
Poly = tuple[Any, ...]


def poly_mul(a: Poly, b: Poly) -> Poly:
    """Product of two polynomials given by coefficient tuples (coefficient k multiplies the
    k-th monomial; floats or arrays); each output coefficient sums its terms in the order of
    a's index."""
    out: list[Any] = [None] * (len(a) + len(b) - 1)
    for i, ai in enumerate(a):
        for j, bj in enumerate(b):
            term = ai * bj
            out[i + j] = term if out[i + j] is None else out[i + j] + term
    return tuple(out)


def poly_combine(*terms: tuple[Any, Poly]) -> Poly:
    """sum_i weight_i poly_i for (weight, poly) pairs of polynomials of one length."""
    out = [terms[0][0] * c for c in terms[0][1]]
    for weight, poly in terms[1:]:
        out = [o + weight * c for o, c in zip(out, poly)]
    return tuple(out)


def fourier(X: Any, c0: Any, c1: Any, rho: Any) -> tuple[Any, Any, Any, Any, Any]:
    """Real and imaginary parts of the Fourier coefficients of t -> h(t)' X h(t) on
    h(t) = [c0 + rho cos t, c1 + rho sin t, -1], for X given by its six distinct entries
    (floats or arrays): (K_0, Re K_1, Im K_1, Re K_2, Im K_2); K_-k = conj(K_k).

    With a = [c0, c1, -1], b = rho e1 and c = rho e2: h'Xh = a'Xa + 2 a'Xb cos + 2 a'Xc sin
    + b'Xb cos^2 + 2 b'Xc cos sin + c'Xc sin^2, and a'Xb = rho (Xa)_0, a'Xc = rho (Xa)_1,
    b'Xb = rho^2 X_00, so K_1 = rho ((Xa)_0 - i (Xa)_1), K_2 = rho^2 ((X_00 - X_11)/4 - i X_01/2).
    """
    x00, x01, x02, x11, x12, x22 = X
    xa0, xa1 = x00 * c0 + x01 * c1 - x02, x01 * c0 + x11 * c1 - x12
    axa = c0 * xa0 + c1 * xa1 - (x02 * c0 + x12 * c1 - x22)
    r2 = rho * rho
    return (axa + 0.5 * r2 * (x00 + x11), rho * xa0, -(rho * xa1),
            0.5 * r2 * (0.5 * (x00 - x11)), -(0.5 * r2 * x01))


def boundary_stationarity(problem: Problem | ProblemBatch) -> np.ndarray:
    """Fourier coefficients F_k, k = -3..3, of num'(t) den(t) - num(t) den'(t) on the q-circle;
    shape (7,) for a problem, (T, 7) for a batch.

    On the image circle q(t) = c_q + rho_q [cos t, sin t] of the disc boundary (bearing case),
    num and den are trigonometric polynomials of degree 2 (coefficients N_k, D_k, k = -2..2),
    so their Wronskian has coefficients F_m = i sum_{j + l = m} (j - l) N_j D_l; its m = +-4
    harmonics vanish identically (j = l = +-2; checked in the tests), leaving degree 3: at
    most 6 stationary points on the circle. F_-m = conj(F_m) (the Wronskian is real). Real
    arithmetic on floats or arrays, so a problem and its batch give the same bits.
    """
    c0, c1, rho = problem.q_circle
    M, N = problem.forms
    n0, n1r, n1i, n2r, n2i = fourier(M, c0, c1, rho)
    d0, d1r, d1i, d2r, d2i = fourier(N, c0, c1, rho)
    # F3 = i (N2 D1 - N1 D2); F2 = 2 i (N2 D0 - N0 D2)
    p_r = (n2r * d1r - n2i * d1i) - (n1r * d2r - n1i * d2i)
    p_i = (n2r * d1i + n2i * d1r) - (n1r * d2i + n1i * d2r)
    a_r, a_i = n2r * d0 - n0 * d2r, n2i * d0 - n0 * d2i
    # F1 = i (3 (N2 conj(D1) - conj(N1) D2) + N1 D0 - N0 D1)
    q_r = (3.0 * ((n2r * d1r + n2i * d1i) - (n1r * d2r + n1i * d2i))
           + (n1r * d0 - n0 * d1r))
    q_i = (3.0 * ((n2i * d1r - n2r * d1i) - (n1r * d2i - n1i * d2r))
           + (n1i * d0 - n0 * d1i))
    # F0 = i (4 (N2 conj(D2) - conj(N2) D2) + 2 (N1 conj(D1) - conj(N1) D1)), real
    f0 = -8.0 * (n2i * d2r - n2r * d2i) - 4.0 * (n1i * d1r - n1r * d1i)
    real = np.stack(np.broadcast_arrays(-q_i, -2.0 * a_i, -p_i, f0), axis=-1)
    imag = np.stack(np.broadcast_arrays(q_r, 2.0 * a_r, p_r), axis=-1)
    F = np.empty(real.shape[:-1] + (7,), dtype=complex)
    F[..., 4:] = real[..., :3] + 1j * imag
    F[..., 3] = real[..., 3]
    F[..., :3] = np.conj(F[..., 6:3:-1])
    return F


def polish_boundary_angles(F: np.ndarray, t: np.ndarray, iterations: int = 2) -> np.ndarray:
    """Newton steps on the real trigonometric polynomial f(t) = sum_k F_k e^{ikt} (k = -3..3),
    for F (7,) and t (n,), or F (..., 7) and t (..., n); steps are clipped to 0.1 rad, and an
    angle stops moving after a step below 1e-13 rad (Newton has converged; each result
    depends on its own start only).

    Start values from companion-matrix roots are accurate to ~1e-14 except near double roots
    (~1e-8), so two quadratically convergent steps suffice; RAM's seeds from clustered roots
    need a few more. With F_-k = conj(F_k) and w = e^{it}: f = F_0 + 2 Re(w (F_1 + w (F_2 +
    w F_3))) and f' = 2 Re(i w (F_1 + w (2 F_2 + w 3 F_3))) (Horner).
    """
    F = np.asarray(F)[..., None, :]
    f0, f1, f2, f3 = F[..., 3].real, F[..., 4], F[..., 5], F[..., 6]
    g2, g3 = 2.0 * f2, 3.0 * f3
    t = np.asarray(t, dtype=float).copy()
    moving = np.ones(t.shape, dtype=bool)
    for _ in range(iterations):
        w = np.exp(1j * t)
        value = f0 + 2.0 * (w * (f1 + w * (f2 + w * f3))).real
        slope = -2.0 * (w * (f1 + w * (g2 + w * g3))).imag
        with np.errstate(divide='ignore', invalid='ignore'):
            step = np.where(moving & (slope != 0.0), np.clip(value / slope, -0.1, 0.1), 0.0)
        t -= step
        moving &= np.abs(step) > 1e-13
        if not moving.any():
            break
    return t


def boundary_points(problem: Problem, t: np.ndarray) -> np.ndarray:
    """Points p (n, 2) on the disc boundary at q-circle angles t (rad)."""
    centre, rho = problem.q_disc()
    q = centre + rho * np.stack([np.cos(t), np.sin(t)], axis=-1)
    return point_from_q(q)
