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
l = x_o c + y_o s, k = x_o s - y_o c (mind F_d = 2 zeta). Q is homogeneous of degree 5 and quartic in d; its 6x6
Sylvester resultant with g is homogeneous of degree 10 in (c, s), so S_c has degree <= 10 in
sigma (the paper reports 8 after cancellation; again we trim what vanishes).

Every real root sigma in [0, 1] gives up to four angles; each is back-substituted (d from F_d = 0
or from g = 0), checked against the other equation and feasibility, polished by Newton steps on
the exact stationarity conditions and evaluated. If the route loses accuracy (no admissible
candidate, non-finite coefficients, or a probe point beats the best candidate) RAM says so in
``Plan.fallback`` and returns the exact RQ optimum instead of a wrong point.
"""
from __future__ import annotations

import itertools
import math
from functools import lru_cache, reduce

import numpy as np

from formopt_ros.core.cost import Problem, point_from_q
from formopt_ros.core.strategies.common import (
    Plan, best_of, boundary_points, boundary_stationarity, gains_tie, polish_boundary_angles,
    range_plan_from_direction)
from formopt_ros.core.strategies.rq import plan_rq

#: Relative KKT residual above which a back-substituted root is rejected as spurious.
RESIDUAL_TOLERANCE = 1e-4
#: Relative cost gap by which a probe point may beat RAM's best before RAM falls back.
PROBE_TOLERANCE = 1e-12
#: Relative remainder of the (c^2 + s^2)^2 deflation above which the route counts as inaccurate.
REMAINDER_TOLERANCE = 1e-3
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


def _plan_range(problem: Problem) -> Plan:
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
        problem, float(g[0]), float(g[1])), 2)


# --- homogeneous bivariate polynomials in (c, s): coefficient k multiplies c^(n-k) s^k --------
def _mul(*polys: np.ndarray) -> np.ndarray:
    return reduce(np.convolve, polys)


def _evaluate(poly: np.ndarray, c: float, s: float) -> float:
    n = len(poly) - 1
    k = np.arange(n + 1)
    return float(np.sum(poly * c ** (n - k) * s ** k))


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


def active_polynomials(problem: Problem) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Coefficients in d of Q (degree 4, eq. 41) and of the homogenised constraint g (eq. 40)."""
    zeta, gamma = kkt_polynomials(problem)
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


@lru_cache(maxsize=4)
def _sylvester_terms(m: int, n: int) -> tuple[tuple[int, tuple[tuple[int, int], ...]], ...]:
    """Non-vanishing Leibniz terms of the Sylvester matrix of degree-m and degree-n polynomials.

    Rows 0..n-1 hold the degree-m coefficients shifted, rows n..n+m-1 the degree-n ones. Each
    term is (sign, ((row, coefficient index), ...)).
    """
    size = m + n
    terms = []
    for perm in itertools.permutations(range(size)):
        entries = []
        for row, col in enumerate(perm):
            shift, degree = (row, m) if row < n else (row - n, n)
            index = col - shift
            if not 0 <= index <= degree:
                break
            entries.append((row, index))
        else:
            inversions = sum(1 for i in range(size) for j in range(i + 1, size)
                             if perm[i] > perm[j])
            terms.append((-1 if inversions % 2 else 1, tuple(entries)))
    return tuple(terms)


def sylvester_resultant(f: list[np.ndarray], g: list[np.ndarray]) -> np.ndarray:
    """Res(f, g; d) for polynomials in d whose coefficients (highest first) are homogeneous
    polynomials in (c, s); returns the homogeneous coefficients of the resultant."""
    m, n = len(f) - 1, len(g) - 1
    total = None
    for sign, entries in _sylvester_terms(m, n):
        term = _mul(*[(f if row < n else g)[index] for row, index in entries])
        total = sign * term if total is None else total + sign * term
    return total


@lru_cache(maxsize=4)
def _sigma_basis(n: int) -> np.ndarray:
    """Row k: ascending coefficients of (1 - sigma)^((n-k)//2) sigma^(k//2), k = 0..n."""
    rows = np.zeros((n + 1, n // 2 + 1))
    for k in range(n + 1):
        poly = np.convolve(np.polynomial.polynomial.polypow([1.0, -1.0], (n - k) // 2),
                           np.eye(k // 2 + 1)[k // 2])
        rows[k, :len(poly)] = poly
    return rows


def eliminate_cosine(resultant: np.ndarray) -> np.ndarray:
    """Res(R, c^2 + s^2 - 1; c) as a polynomial in sigma = sin^2 t, ascending coefficients.

    Split R(c, s) = sum_k r_k c^(n-k) s^k by the parity of the power of c: with c^2 = 1 - sigma
    and s^2 = sigma, R = s^e A(sigma) + c s^o B(sigma) where (e, o) = (0, 1) for even n and
    (1, 0) for odd n. Then Res = R(c0, s) R(-c0, s) = s^2e A^2 - (1 - sigma) s^2o B^2, a
    polynomial in sigma of degree n // 2 * 2 + (n odd) = n: 11 for the inactive case as the
    paper states (eqs. 37-38), 10 for the active one (eqs. 45-46).
    """
    n = len(resultant) - 1
    basis = _sigma_basis(n)
    even_c = (n - np.arange(n + 1)) % 2 == 0
    A = resultant[even_c] @ basis[even_c]
    B = resultant[~even_c] @ basis[~even_c]
    A2, B2 = np.convolve(A, A), np.convolve(B, B)
    if n % 2 == 0:
        return np.polynomial.polynomial.polysub(A2, np.convolve([0.0, 1.0, -1.0], B2))
    return np.polynomial.polynomial.polysub(np.convolve([0.0, 1.0], A2),
                                            np.convolve([1.0, -1.0], B2))


def deflate_unit_circle(resultant: np.ndarray, times: int = 2) -> tuple[np.ndarray, float]:
    """Divide a homogeneous polynomial in (c, s) by (c^2 + s^2)^times.

    Both resultants carry the factor (c^2 + s^2)^2 (shown with exact rational arithmetic); it
    equals 1 on the unit circle and only raises the degree, so it is removed before the
    elimination. Returns the quotient and the relative size of the remainder (an accuracy
    check: it vanishes in exact arithmetic).
    """
    quotient = resultant[::-1]                     # ascending in s  ==  R(1, s) highest first
    scale = np.max(np.abs(resultant))
    remainder = 0.0
    for _ in range(times):
        quotient, rest = np.polydiv(quotient, [1.0, 0.0, 1.0])
        remainder = max(remainder, float(np.max(np.abs(rest))) / scale)
    return quotient[::-1], remainder


def sigma_roots(coefficients: np.ndarray) -> tuple[np.ndarray, int]:
    """Real roots in [0, 1] of a polynomial in sigma (ascending coefficients), via the
    eigenvalues of its companion matrix; leading coefficients below 1e-13 of the largest are
    treated as zero. Returns the roots and the degree used."""
    scale = np.max(np.abs(coefficients))
    if not np.isfinite(scale) or scale == 0.0:
        raise FloatingPointError('degenerate elimination polynomial')
    c = coefficients / scale
    degree = int(np.max(np.nonzero(np.abs(c) > 1e-13)[0]))
    if degree == 0:
        return np.zeros(0), 0
    companion = np.zeros((degree, degree))
    companion[1:, :-1] = np.eye(degree - 1)
    companion[:, -1] = -c[:degree] / c[degree]
    roots = np.linalg.eigvals(companion)
    real = roots[np.abs(roots.imag) <= 1e-6 * (1 + np.abs(roots.real))].real
    return np.clip(real[(real >= -1e-8) & (real <= 1 + 1e-8)], 0.0, 1.0), degree


def _check_remainder(remainder: float) -> None:
    if not remainder < REMAINDER_TOLERANCE:
        raise FloatingPointError(f'resultant deflation remainder {remainder:.2g}')


def _angles(sigmas: np.ndarray) -> list[tuple[float, float]]:
    """All (cos t, sin t) with sin^2 t = sigma."""
    out = set()
    for sigma in sigmas:
        s, c = math.sqrt(sigma), math.sqrt(1.0 - sigma)
        out.update({(c, s), (-c, s), (c, -s), (-c, -s)})
    return sorted(out)


def _relative_residual(coeffs: list[np.ndarray], d: float, c: float, s: float) -> float:
    terms = [_evaluate(poly, c, s) * d ** (len(coeffs) - 1 - i) for i, poly in enumerate(coeffs)]
    return abs(sum(terms)) / max(sum(abs(t) for t in terms), 1e-300)


def _interior_candidates(problem: Problem) -> tuple[list[np.ndarray], int]:
    zeta, gamma = kkt_polynomials(problem)
    reduced, remainder = deflate_unit_circle(sylvester_resultant(zeta, gamma))
    _check_remainder(remainder)
    roots, degree = sigma_roots(eliminate_cosine(reduced))
    points = []
    for c, s in _angles(roots):
        z = [_evaluate(poly, c, s) for poly in zeta]
        for d in np.roots(z) if abs(z[0]) > 0 else np.roots(z[1:]):
            if abs(d.imag) > 1e-8 * abs(d) or d.real <= 0:
                continue
            p = d.real * np.array([c, s])
            if problem.feasible(p, 0.0) and _relative_residual(gamma, d.real, c, s) \
                    < RESIDUAL_TOLERANCE:
                points.append(p)
    return points, degree


def _active_candidates(problem: Problem) -> tuple[list[np.ndarray], int]:
    q, g = active_polynomials(problem)
    reduced, remainder = deflate_unit_circle(sylvester_resultant(q, g))
    _check_remainder(remainder)
    roots, degree = sigma_roots(eliminate_cosine(reduced))
    points = []
    k = problem.d_o ** 2 - problem.r ** 2
    for c, s in _angles(roots):
        ell = problem.p_o[0] * c + problem.p_o[1] * s
        disc = ell * ell - k
        if disc < -1e-12 * problem.d_o ** 2 or ell <= 0:
            continue
        for d in {ell - math.sqrt(max(disc, 0.0)), ell + math.sqrt(max(disc, 0.0))}:
            if _relative_residual(q, d, c, s) < RESIDUAL_TOLERANCE:
                points.append(d * np.array([c, s]))
    return points, degree


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


def _plan_bearing(problem: Problem) -> Plan:
    interior, degree_u = _interior_candidates(problem)
    active, degree_c = _active_candidates(problem)
    polished = [_polish_interior(problem, p) for p in interior]
    polished = [p for p in polished if problem.feasible(p, 0.0)]
    centre, rho = problem.q_disc()
    t = []
    for p in active:
        q = np.array([-p[1], p[0]]) / (p @ p)
        t.append(math.atan2(q[1] - centre[1], q[0] - centre[0]))
    F = boundary_stationarity(problem)
    boundary = list(boundary_points(problem, polish_boundary_angles(F, np.array(t)))) if t else []
    candidates = interior + polished + active + boundary
    details = {'degree_inactive': degree_u, 'degree_active': degree_c,
               'interior_roots': len(interior), 'active_roots': len(active)}
    if not candidates:
        raise FloatingPointError('no admissible critical point')
    points = np.array(candidates)
    best, gains = best_of(problem, points)
    probes = np.vstack([problem.p_o, boundary_points(problem, PROBE_ANGLES)])
    probe_gain = float(np.max(problem.gain(probes)))
    if probe_gain - gains[best] > PROBE_TOLERANCE * max(problem.base_cost - probe_gain, 1e-300):
        raise FloatingPointError('a probe point beats every critical point')
    on_boundary = best >= len(interior) + len(polished)
    return Plan(points[best], len(points), on_boundary, details=details)


def plan_ram(problem: Problem, rng: np.random.Generator | None = None,
             fallback: bool = True) -> Plan:
    """The paper's analytic optimum (Sec. IV); see the module docstring.

    Args:
        fallback: when the polynomial route loses accuracy, return the exact RQ optimum (and
            name it in ``Plan.fallback``); with False, raise FloatingPointError instead.
    """
    if problem.measurement == 'range':
        return _plan_range(problem)
    try:
        with np.errstate(all='ignore'):
            return _plan_bearing(problem)
    except (FloatingPointError, np.linalg.LinAlgError) as error:
        if not fallback:
            raise
        plan = plan_rq(problem)
        plan.fallback = 'rq'
        plan.details['reason'] = str(error)
        return plan
