"""RAM: the paper's relaxed algebraic method (Sec. IV), with coefficients derived here.

Range (Sec. IV-A)
-----------------
f_d(theta) = -(a1 sin 2t + a2 cos 2t + a3) / (a4 sin 2t + a5 cos 2t + a6) with, for
M = P W^2 P and W = diag(1, 1, d_o):

    a1 = M12 = p1 p4 + p2 p4 + d_o^2 p5 p6
    a2 = (M11 - M22)/2 = (p1^2 - p2^2 + d_o^2 (p5^2 - p6^2)) / 2
    a3 = (M11 + M22)/2 = (p1^2 + p2^2 + 2 p4^2 + d_o^2 (p5^2 + p6^2)) / 2
    a4 = p4,  a5 = (p1 - p2)/2,  a6 = (p1 + p2)/2 + sigma_d^2.

The printed paper has d_o^4 where W^2 = diag(1, 1, d_o^2) gives d_o^2, and p5, p6 unsquared in
a2: both are typos (the tests compare these coefficients with the gain evaluated directly).
b1..b3, phi, alpha and the minimiser theta* = (pi - alpha - phi)/2 are as printed (verified).

Bearing (Sec. IV-B)
-------------------
In polar coordinates p = d [cos t, sin t] and alpha = [-sin t, cos t], after multiplying
numerator and denominator by d^2 (eq. 26):

    N(d, t) = c_u d^2 + 2 beta_u d + gamma_u,   D(d, t) = c_v d^2 + 2 beta_v d + gamma_v,
    c_u = M33, beta_u = -M[:2, 2]' alpha, gamma_u = alpha' M[:2, :2] alpha,
    c_v = P33 + R, beta_v = -P[:2, 2]' alpha, gamma_v = alpha' P[:2, :2] alpha.

Inactive constraint: grad f = 0 <=> F_d = N_d D - N D_d = 0 and F_t = N_t D - N D_t = 0, with

    F_d / 2 = (c_u b_v - c_v b_u) d^2 + (c_u g_v - c_v g_u) d + (b_u g_v - b_v g_u)
    F_t = 2 (b_u' c_v - c_u b_v') d^3 + (4 b_u' b_v - 4 b_u b_v' + c_v g_u' - c_u g_v') d^2
          + 2 (b_u' g_v + g_u' b_v - b_u g_v' - g_u b_v') d + (g_u' g_v - g_u g_v')

(b = beta, g = gamma, ' = d/dt). Both are homogeneous in (d, cos t, sin t), of degree 3 and 4
(as the paper states). The 5x5 Sylvester resultant in d is homogeneous of degree 12 in
(c, s); the paper's printed Sylvester matrix is garbled (its last two rows must hold the
cubic's four coefficients, shifted). Eliminating c with c^2 + s^2 = 1 gives
S_u = E(s^2)^2 - s^2 (1 - s^2) O(s^2)^2, where E and O are the parts of the resultant even
and odd in c: a polynomial of degree 12 in sigma = sin^2 t. Numerically its sigma^12
coefficient vanishes for every problem we tried (it is proportional to R(i, 1) R(-i, 1),
and R has the factor c^2 + s^2), which is the paper's degree 11; we keep whatever degree the
numbers give and trim leading coefficients that vanish to rounding.

Active constraint: grad f || grad g with g = d^2 - 2 d (x_o c + y_o s) + (d_o^2 - r^2)(c^2 + s^2)
(homogenised), i.e. Q = F_t g_d - F_d g_t = 0 with g_d / 2 = d - l, g_t / 2 = d k,
l = x_o c + y_o s, k = x_o s - y_o c (mind F_d = 2 zeta). Q is homogeneous of degree 5 and
quartic in d; its 6x6 Sylvester resultant with g is homogeneous of degree 10 in (c, s), so S_c
has degree <= 10 in sigma (the paper reports 8 after cancellation; again we trim what
vanishes).

Every real root sigma in [0, 1] gives up to four angles; each is back-substituted (d from F_d = 0
or from g = 0), checked against the other equation and feasibility, polished by Newton steps on
the exact stationarity conditions and evaluated. If the route loses accuracy (no admissible
candidate, non-finite coefficients, or a probe point beats the best candidate) RAM says so in
``Solution.fallback`` and returns the exact RQ optimum instead of a wrong point.
"""
from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache, reduce

import numpy as np

from formopt_ros.core.cost import Problem, point_from_q
from formopt_ros.core.strategies.base import (
    OptionSpec, PlanContext, Solution, Strategy, make_solution)
from formopt_ros.core.strategies.common import (
    best_of, boundary_points, boundary_stationarity, gains_tie, polish_boundary_angles,
    range_plan_from_direction)
from formopt_ros.core.strategies.rq import rq_optimum

#: Relative KKT residual above which a back-substituted root is rejected as spurious.
RESIDUAL_TOLERANCE = 1e-4
#: Relative residual up to which a root near the disc is still polished and re-judged.
POLISH_RESIDUAL = 0.5
#: Relative cost gap by which a probe point may beat RAM's best before RAM falls back.
PROBE_TOLERANCE = 1e-12
#: Relative size of the interpolant's coefficients above the exact degree (zero in exact
#: arithmetic) above which the polynomial route counts as inaccurate and RAM falls back.
ALIASING_TOLERANCE = 1e-3
#: Degrees in sigma = sin^2 t of the eliminated polynomials, established with exact rational
#: arithmetic (the paper prints 11 and 8; see the module docstring).
INACTIVE_DEGREE = 7
ACTIVE_DEGREE = 6
#: Boundary probe points (angles on the q-circle) used to detect a lost root.
PROBE_ANGLES = np.linspace(0.0, 2.0 * math.pi, 24, endpoint=False)


# --- range -------------------------------------------------------------------------------------
def range_coefficients(problem: Problem) -> tuple[float, ...]:
    """(a1, ..., a6) of eq. (24), with the typos corrected (see module docstring)."""
    P, d2 = problem.P, problem.d_o ** 2
    p1, p2, p4, p5, p6 = P[0, 0], P[1, 1], P[0, 1], P[0, 2], P[1, 2]
    a1 = p1 * p4 + p2 * p4 + d2 * p5 * p6
    a2 = 0.5 * (p1 * p1 - p2 * p2 + d2 * (p5 * p5 - p6 * p6))
    a3 = 0.5 * (p1 * p1 + p2 * p2 + 2 * p4 * p4 + d2 * (p5 * p5 + p6 * p6))
    return a1, a2, a3, p4, 0.5 * (p1 - p2), 0.5 * (p1 + p2) + problem.R


def _plan_range(problem: Problem) -> Solution:
    a1, a2, a3, a4, a5, a6 = range_coefficients(problem)
    b1, b2, b3 = a3 * a5 - a2 * a6, a1 * a6 - a3 * a4, a1 * a5 - a2 * a4
    rho = math.hypot(b1, b2)
    varphi = math.atan2(b2, b1)
    alpha = math.asin(max(-1.0, min(1.0, -b3 / rho))) if rho > 0 else 0.0
    theta_min_f = 0.5 * (math.pi - alpha - varphi)     # minimiser of f = maximiser of the gain
    theta_max_f = 0.5 * (alpha - varphi)
    units = np.array([[math.cos(theta_min_f), math.sin(theta_min_f)],
                      [math.cos(theta_max_f), math.sin(theta_max_f)]])
    g = problem.gain(units * problem.d_o)
    return range_plan_from_direction(problem, theta_min_f, rho == 0 or gains_tie(
        problem, float(g[0]), float(g[1])), 2, 'ram')


# --- homogeneous bivariate polynomials in (c, s): coefficient k multiplies c^(n-k) s^k --------
def _mul(*polys: np.ndarray) -> np.ndarray:
    return reduce(np.convolve, polys)


def _beta(b: np.ndarray) -> np.ndarray:          # b' alpha,      alpha = [-s, c]
    return np.array([b[1], -b[0]])


def _beta_t(b: np.ndarray) -> np.ndarray:        # d/dt b' alpha
    return np.array([-b[0], -b[1]])


def _gamma(A: np.ndarray) -> np.ndarray:         # alpha' A alpha
    return np.array([A[1, 1], -2 * A[0, 1], A[0, 0]])


def _gamma_t(A: np.ndarray) -> np.ndarray:       # d/dt alpha' A alpha
    return np.array([-2 * A[0, 1], 2 * (A[0, 0] - A[1, 1]), 2 * A[0, 1]])


def kkt_polynomials(problem: Problem) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Coefficients in d of F_d/2 (zeta2, zeta1, zeta0) and F_t (gamma3..gamma0), eqs. (33-34).

    Each coefficient is a homogeneous polynomial in (cos t, sin t) (see module docstring).
    """
    M, P = problem.M, problem.P
    cu, cv = M[2, 2], P[2, 2] + problem.R
    bu, bv = _beta(-M[:2, 2]), _beta(-P[:2, 2])
    bu_t, bv_t = _beta_t(-M[:2, 2]), _beta_t(-P[:2, 2])
    gu, gv = _gamma(M[:2, :2]), _gamma(P[:2, :2])
    gu_t, gv_t = _gamma_t(M[:2, :2]), _gamma_t(P[:2, :2])
    zeta = [cu * bv - cv * bu, cu * gv - cv * gu, _mul(bu, gv) - _mul(bv, gu)]
    gamma = [2 * (cv * bu_t - cu * bv_t),
             4 * (_mul(bu_t, bv) - _mul(bu, bv_t)) + cv * gu_t - cu * gv_t,
             2 * (_mul(bu_t, gv) + _mul(gu_t, bv) - _mul(bu, gv_t) - _mul(gu, bv_t)),
             _mul(gu_t, gv) - _mul(gu, gv_t)]
    return zeta, gamma


def active_polynomials(problem: Problem, kkt: tuple[list[np.ndarray], list[np.ndarray]] | None
                       = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Coefficients in d of Q (degree 4, eq. 41) and of the homogenised constraint g (eq. 40).

    ``kkt`` is the output of :func:`kkt_polynomials`, computed here when not given.
    """
    zeta, gamma = kkt or kkt_polynomials(problem)
    xo, yo = problem.p_o
    ell = np.array([xo, yo])                      # x_o c + y_o s
    kappa = np.array([-2 * yo, 2 * xo])           # 2 (x_o s - y_o c): zeta holds F_d / 2
    q = [gamma[0],
         gamma[1] - _mul(ell, gamma[0]) - _mul(kappa, zeta[0]),
         gamma[2] - _mul(ell, gamma[1]) - _mul(kappa, zeta[1]),
         gamma[3] - _mul(ell, gamma[2]) - _mul(kappa, zeta[2]),
         -_mul(ell, gamma[3])]
    k = problem.d_o ** 2 - problem.r ** 2
    g = [np.array([1.0]), -2.0 * ell, np.array([k, 0.0, k])]
    return q, g


def _monomial_table(c: np.ndarray, s: np.ndarray, max_degree: int = 5) -> list[np.ndarray]:
    """Entry n: the monomials c^(n-k) s^k, k = 0..n, at the points, shape (len(c), n + 1)."""
    return [c[:, None] ** (n - np.arange(n + 1)) * s[:, None] ** np.arange(n + 1)
            for n in range(max_degree + 1)]


def sylvester_matrices(f: list[np.ndarray], g: list[np.ndarray],
                       table: list[np.ndarray]) -> np.ndarray:
    """Sylvester matrices in d of f and g (coefficient lists, highest power first) at the
    bearings of a monomial table; shape (K, m + n, m + n). Rows 0..n-1 hold f shifted."""
    m, n = len(f) - 1, len(g) - 1
    fv = [table[len(poly) - 1] @ poly for poly in f]
    gv = [table[len(poly) - 1] @ poly for poly in g]
    S = np.zeros((len(fv[0]), m + n, m + n))
    for row in range(n):
        S[:, row, row:row + m + 1] = np.stack(fv, axis=1)
    for row in range(m):
        S[:, n + row, row:row + n + 1] = np.stack(gv, axis=1)
    return S


@lru_cache(maxsize=4)
def _chebyshev_interpolation(count: int) -> tuple[list[np.ndarray], np.ndarray]:
    """Monomial table at the bearings (+-c0, s) of ``count`` Chebyshev points of the first kind
    in sigma = sin^2 t on [0, 1] (the +c0 ones first), and the matrix that maps values at those
    points to the coefficients of the interpolating Chebyshev series (degree count - 1)."""
    x = np.cos(np.pi * (np.arange(count) + 0.5) / count)
    sigma = 0.5 * (1.0 + x)
    sin, cos = np.sqrt(sigma), np.sqrt(1.0 - sigma)
    table = _monomial_table(np.concatenate([cos, -cos]), np.concatenate([sin, sin]))
    return table, np.linalg.inv(np.polynomial.chebyshev.chebvander(x, count - 1))


def eliminated_polynomial(f: list[np.ndarray], g: list[np.ndarray],
                          degree: int) -> tuple[np.ndarray, float]:
    """Res(Res(f, g; d), c^2 + s^2 - 1; c) as a Chebyshev series in sigma = sin^2 t on [0, 1].

    On the real unit circle Res(R, c^2 + s^2 - 1; c)(sigma) = R(c0, s) R(-c0, s) with
    c0 = sqrt(1 - sigma), s = sqrt(sigma) (eqs. 37 and 45), and the factor (c^2 + s^2)^2 that
    both resultants carry equals 1. So we evaluate the Sylvester determinants at Chebyshev
    nodes in sigma and interpolate: the basis is well conditioned on [0, 1], where the roots
    we need lie. We sample ``degree + 4`` nodes; the relative size of the coefficients above
    ``degree`` (zero in exact arithmetic) is returned as an accuracy measure.
    """
    table, interpolation = _chebyshev_interpolation(degree + 4)
    det = np.linalg.det(sylvester_matrices(f, g, table))
    half = len(det) // 2
    series = interpolation @ (det[:half] * det[half:])
    scale = np.max(np.abs(series))
    if not np.isfinite(scale) or scale == 0.0:
        raise FloatingPointError('degenerate elimination polynomial')
    return series[:degree + 1], float(np.max(np.abs(series[degree + 1:])) / scale)


def sigma_roots(series: np.ndarray) -> np.ndarray:
    """Real roots in [0, 1] of a Chebyshev series in 2 sigma - 1, from the eigenvalues of its
    colleague matrix (the companion matrix of the Chebyshev basis)."""
    roots = np.polynomial.chebyshev.chebroots(series)
    real = roots[np.abs(roots.imag) <= 1e-6].real
    sigma = 0.5 * (real + 1.0)
    return np.clip(sigma[(sigma >= -1e-8) & (sigma <= 1 + 1e-8)], 0.0, 1.0)


def _angles(sigmas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All (cos t, sin t) with sin^2 t = sigma, as two arrays."""
    s, c = np.sqrt(sigmas), np.sqrt(1.0 - sigmas)
    return np.concatenate([c, -c, c, -c]), np.concatenate([s, s, -s, -s])


def _relative_residual(coeffs: list[np.ndarray], d: np.ndarray,
                       table: list[np.ndarray]) -> np.ndarray:
    """|sum_i coeffs_i(c, s) d^(n-i)| / sum_i |...| at points given by a monomial table."""
    terms = [(table[len(poly) - 1] @ poly) * d ** (len(coeffs) - 1 - i)
             for i, poly in enumerate(coeffs)]
    return np.abs(sum(terms)) / np.maximum(sum(np.abs(t) for t in terms), 1e-300)


def _check_accuracy(aliasing: float) -> None:
    if not aliasing < ALIASING_TOLERANCE:
        raise FloatingPointError(f'elimination polynomial lost accuracy ({aliasing:.2g})')


def _interior_candidates(problem: Problem, zeta: list[np.ndarray],
                         gamma: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Interior critical points from the roots of S_u (d from F_d = 0, F_t checked): those
    that pass (n, 2), and doubtful ones near the disc that need polishing (m, 2)."""
    series, aliasing = eliminated_polynomial(zeta, gamma, INACTIVE_DEGREE)
    _check_accuracy(aliasing)
    c, s = _angles(sigma_roots(series))
    table = _monomial_table(c, s, 4)
    z2, z1, z0 = (table[len(poly) - 1] @ poly for poly in zeta)
    disc = np.sqrt((z1 * z1 - 4 * z2 * z0).astype(complex))
    with np.errstate(divide='ignore', invalid='ignore'):
        d = np.concatenate([(-z1 + disc) / (2 * z2), (-z1 - disc) / (2 * z2)])
    ok = np.isfinite(d) & (np.abs(d.imag) <= 1e-8 * np.abs(d)) & (d.real > 0)
    d, both = d.real[ok], np.concatenate([np.arange(len(c))] * 2)[ok]
    points = d[:, None] * np.stack([c[both], s[both]], axis=1)
    distance = np.hypot(*(points - problem.p_o).T)
    residual = _relative_residual(gamma, d, [t[both] for t in table])
    accepted = (distance < problem.r) & (residual < RESIDUAL_TOLERANCE)
    # Near-multiple roots of S_u are computed with ~sqrt(eps) error and can fail the residual
    # test: such points near the disc are polished by Newton before being judged.
    doubtful = ~accepted & (distance < 1.5 * problem.r) & (residual < POLISH_RESIDUAL)
    return points[accepted], points[doubtful]


def _active_candidates(problem: Problem, q: list[np.ndarray], g: list[np.ndarray]) -> np.ndarray:
    """Critical points on the boundary (n, 2): roots of S_c, d from g = 0, Q checked."""
    series, aliasing = eliminated_polynomial(q, g, ACTIVE_DEGREE)
    _check_accuracy(aliasing)
    c, s = _angles(sigma_roots(series))
    ell = problem.p_o[0] * c + problem.p_o[1] * s
    disc = ell * ell - (problem.d_o ** 2 - problem.r ** 2)
    hits = np.flatnonzero((disc > -1e-12 * problem.d_o ** 2) & (ell > 0))
    root = np.sqrt(np.maximum(disc[hits], 0.0))
    d = np.concatenate([ell[hits] - root, ell[hits] + root])
    both = np.concatenate([hits, hits])
    table = _monomial_table(c[both], s[both], 5)
    good = _relative_residual(q, d, table) < RESIDUAL_TOLERANCE
    return d[good, None] * np.stack([c[both][good], s[both][good]], axis=1)


def _polish_interior(problem: Problem, p: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Newton steps on m grad n - n grad m = 0 in q-coordinates (gain = n/m, h = [q, -1])."""
    M, N = problem.M, problem.N
    q = np.array([-p[1], p[0]]) / (p @ p)
    for _ in range(iterations):
        h = np.array([q[0], q[1], -1.0])
        Mh, Nh = M @ h, N @ h
        n, m = h @ Mh, h @ Nh
        gn, gm = 2 * Mh[:2], 2 * Nh[:2]
        G = m * gn - n * gm
        J = np.outer(gn, gm) + 2 * m * M[:2, :2] - np.outer(gm, gn) - 2 * n * N[:2, :2]
        try:
            q = q - np.linalg.solve(J, G)
        except np.linalg.LinAlgError:
            break
    return point_from_q(q)


def _plan_bearing(problem: Problem) -> Solution:
    kkt = kkt_polynomials(problem)
    interior, doubtful = _interior_candidates(problem, *kkt)
    active = _active_candidates(problem, *active_polynomials(problem, kkt))
    polished = [_polish_interior(problem, p) for p in np.vstack([interior, doubtful])]
    polished = [p for p in polished if problem.feasible(p, 0.0)]
    centre, rho = problem.q_disc()
    q = np.stack([-active[:, 1], active[:, 0]], axis=1) / np.sum(active * active, 1)[:, None]
    t = np.arctan2(q[:, 1] - centre[1], q[:, 0] - centre[0])
    boundary = boundary_points(problem, polish_boundary_angles(boundary_stationarity(problem), t))
    points = np.vstack([interior.reshape(-1, 2), np.reshape(polished, (-1, 2)), active,
                        boundary])
    details = {'interior_roots': len(interior), 'active_roots': len(active)}
    if len(points) == 0:
        raise FloatingPointError('no admissible critical point')
    best, gains = best_of(problem, points)
    probes = np.vstack([problem.p_o, boundary_points(problem, PROBE_ANGLES)])
    probe_gain = float(np.max(problem.gain(probes)))
    if probe_gain - gains[best] > PROBE_TOLERANCE * max(problem.base_cost - probe_gain, 1e-300):
        raise FloatingPointError('a probe point beats every critical point')
    on_boundary = best >= len(interior) + len(polished)
    return make_solution(problem, points[best], 'ram', on_boundary, len(points),
                         details=details)


def ram_optimum(problem: Problem, fallback: bool = True) -> Solution:
    """The paper's analytic optimum (Sec. IV); see the module docstring.

    Args:
        fallback: when the polynomial route loses accuracy, return the exact RQ optimum (and
            name it in ``Solution.fallback``); with False, raise FloatingPointError instead.
    """
    if problem.measurement == 'range':
        return _plan_range(problem)
    try:
        with np.errstate(all='ignore'):
            return _plan_bearing(problem)
    except (FloatingPointError, np.linalg.LinAlgError) as error:
        if not fallback:
            raise
        exact = rq_optimum(problem, 'ram')
        return replace(exact, fallback='rq', details={**exact.details, 'reason': str(error)})


class RelaxedAlgebraicMethod(Strategy):
    """RAM: the paper's analytic method, falling back to RQ visibly when it loses accuracy."""

    name = 'ram'
    OPTIONS = {'fallback': OptionSpec(True, 'fall back to RQ when the polynomial route loses '
                                            'accuracy; false: raise FloatingPointError')}

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The analytic greedy optimum."""
        return ram_optimum(problem, bool(self.settings['fallback']))
