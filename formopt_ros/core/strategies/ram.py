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
the exact stationarity conditions and evaluated. Clustered roots (a critical point at a
near-multiple root of S_u, e.g. a bearing near 0 or pi/2 where sigma = sin^2 t is flat, or two
critical points at nearly one bearing) come out of the colleague matrix as complex pairs or
with errors of ~1e-2 in sigma; so every root within ROOT_IMAG_TOLERANCE of the real axis also
seeds Newton's method on the exact stationarity conditions, and the polished points that are
feasible join the candidates. The best candidate must pass the global-optimality certificate
of :mod:`~formopt_ros.core.strategies.certificate`; when it does not (or the route loses
accuracy: non-finite or aliased elimination polynomials), RAM says so in
``Solution.fallback`` and returns the certified RQ optimum instead, never an uncertified point.

All of it runs on a batch of T problems at once (:func:`ram_batch`, used by the batched Monte
Carlo engine); a single problem is a batch of one, so both give bit-identical answers.
"""
from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.strategies.base import (
    BatchContext, BatchPlan, OptionSpec, PlanContext, Solution, Strategy, make_solution)
from formopt_ros.core.strategies.certificate import PROVED, certify
from formopt_ros.core.strategies.common import (
    boundary_stationarity, gains_tie, poly_mul, polish_boundary_angles,
    range_plan_from_direction)
from formopt_ros.core.strategies.rq import rq_optimum

#: Relative KKT residual below which a back-substituted root is a candidate without polishing.
RESIDUAL_TOLERANCE = 1e-4
#: Roots of the eliminated polynomials (in 2 sigma - 1) up to this far from the real axis seed
#: Newton's method (clustered roots are perturbed to complex pairs).
ROOT_IMAG_TOLERANCE = 0.1
#: Interior start points up to this many r from p_o are polished.
POLISH_DISTANCE = 1.5
#: Newton iterations of the interior and boundary polishing.
INTERIOR_NEWTON = 8
BOUNDARY_NEWTON = 6
#: Relative size of the interpolant's coefficients above the exact degree (zero in exact
#: arithmetic) above which the polynomial route counts as inaccurate and RAM falls back.
ALIASING_TOLERANCE = 1e-3
#: Degrees in sigma = sin^2 t of the eliminated polynomials, established with exact rational
#: arithmetic (the paper prints 11 and 8; see the module docstring).
INACTIVE_DEGREE = 7
ACTIVE_DEGREE = 6


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
    d_o = problem.d_o
    g0 = problem.gain_at(d_o * math.cos(theta_min_f), d_o * math.sin(theta_min_f))
    g1 = problem.gain_at(d_o * math.cos(theta_max_f), d_o * math.sin(theta_max_f))
    return range_plan_from_direction(problem, theta_min_f, rho == 0 or gains_tie(
        problem, float(g0), float(g1)), 2, 'ram')


# --- homogeneous bivariate polynomials in (c, s): coefficient k multiplies c^(n-k) s^k --------
# Every polynomial carries a leading batch axis: shape (T, n + 1).
def _beta(b: np.ndarray) -> np.ndarray:          # b' alpha,      alpha = [-s, c]
    return np.stack([b[:, 1], -b[:, 0]], axis=-1)


def _beta_t(b: np.ndarray) -> np.ndarray:        # d/dt b' alpha
    return np.stack([-b[:, 0], -b[:, 1]], axis=-1)


def _gamma(A: np.ndarray) -> np.ndarray:         # alpha' A alpha
    return np.stack([A[:, 1, 1], -2 * A[:, 0, 1], A[:, 0, 0]], axis=-1)


def _gamma_t(A: np.ndarray) -> np.ndarray:       # d/dt alpha' A alpha
    return np.stack([-2 * A[:, 0, 1], 2 * (A[:, 0, 0] - A[:, 1, 1]), 2 * A[:, 0, 1]], axis=-1)


Polynomials = list[np.ndarray]


def kkt_batch(batch: ProblemBatch) -> tuple[Polynomials, Polynomials]:
    """Coefficients in d of F_d/2 (zeta2, zeta1, zeta0) and F_t (gamma3..gamma0), eqs. (33-34),
    each of shape (T, degree + 1) (see module docstring)."""
    M, P = batch.M, batch.P
    cu, cv = M[:, 2, 2:3], P[:, 2, 2:3] + batch.R[:, None]
    bu, bv = _beta(-M[:, :2, 2]), _beta(-P[:, :2, 2])
    bu_t, bv_t = _beta_t(-M[:, :2, 2]), _beta_t(-P[:, :2, 2])
    gu, gv = _gamma(M[:, :2, :2]), _gamma(P[:, :2, :2])
    gu_t, gv_t = _gamma_t(M[:, :2, :2]), _gamma_t(P[:, :2, :2])
    zeta = [cu * bv - cv * bu, cu * gv - cv * gu, poly_mul(bu, gv) - poly_mul(bv, gu)]
    gamma = [2 * (cv * bu_t - cu * bv_t),
             4 * (poly_mul(bu_t, bv) - poly_mul(bu, bv_t)) + cv * gu_t - cu * gv_t,
             2 * (poly_mul(bu_t, gv) + poly_mul(gu_t, bv) - poly_mul(bu, gv_t)
                  - poly_mul(gu, bv_t)),
             poly_mul(gu_t, gv) - poly_mul(gu, gv_t)]
    return zeta, gamma


def active_batch(batch: ProblemBatch, kkt: tuple[Polynomials, Polynomials]
                 ) -> tuple[Polynomials, Polynomials]:
    """Coefficients in d of Q (degree 4, eq. 41) and of the homogenised constraint g (eq. 40)."""
    zeta, gamma = kkt
    xo, yo = batch.p_o[:, 0:1], batch.p_o[:, 1:2]
    ell = np.concatenate([xo, yo], axis=1)              # x_o c + y_o s
    kappa = np.concatenate([-2 * yo, 2 * xo], axis=1)   # 2 (x_o s - y_o c): zeta holds F_d / 2
    q = [gamma[0],
         gamma[1] - poly_mul(ell, gamma[0]) - poly_mul(kappa, zeta[0]),
         gamma[2] - poly_mul(ell, gamma[1]) - poly_mul(kappa, zeta[1]),
         gamma[3] - poly_mul(ell, gamma[2]) - poly_mul(kappa, zeta[2]),
         -poly_mul(ell, gamma[3])]
    k = (batch.d_o * batch.d_o - batch.r * batch.r)[:, None]
    g = [np.ones_like(xo), -2.0 * ell, np.concatenate([k, np.zeros_like(k), k], axis=1)]
    return q, g


def kkt_polynomials(problem: Problem) -> tuple[Polynomials, Polynomials]:
    """:func:`kkt_batch` of one problem: lists of 1-D coefficient arrays."""
    zeta, gamma = kkt_batch(ProblemBatch.stack([problem]))
    return [z[0] for z in zeta], [g[0] for g in gamma]


def active_polynomials(problem: Problem) -> tuple[Polynomials, Polynomials]:
    """:func:`active_batch` of one problem: lists of 1-D coefficient arrays."""
    batch = ProblemBatch.stack([problem])
    q, g = active_batch(batch, kkt_batch(batch))
    return [x[0] for x in q], [x[0] for x in g]


def _monomial_table(c: np.ndarray, s: np.ndarray, max_degree: int = 5) -> list[np.ndarray]:
    """Entry n: the monomials c^(n-k) s^k, k = 0..n, at the points, shape c.shape + (n + 1,)."""
    table = [np.ones(c.shape + (1,))]
    for _ in range(max_degree):
        last = table[-1]
        table.append(np.concatenate([last * c[..., None], last[..., -1:] * s[..., None]],
                                    axis=-1))
    return table


def _evaluate(poly: np.ndarray, table: list[np.ndarray]) -> np.ndarray:
    """Values of a batch of polynomials (T, n + 1) at the points of a monomial table whose
    entries have shape (T, K, n + 1) or (K, n + 1); shape (T, K). One matrix-vector product
    per problem, so a problem's values do not depend on the rest of the batch."""
    return np.matmul(table[poly.shape[-1] - 1], poly[..., None])[..., 0]


def _sylvester(f: Polynomials, g: Polynomials, table: list[np.ndarray]) -> np.ndarray:
    """Sylvester matrices in d of f and g (coefficient lists, highest power first) at the
    points of a monomial table; shape (T, K, m + n, m + n). Rows 0..n-1 hold f shifted."""
    m, n = len(f) - 1, len(g) - 1
    fv = np.stack([_evaluate(poly, table) for poly in f], axis=-1)
    gv = np.stack([_evaluate(poly, table) for poly in g], axis=-1)
    S = np.zeros(fv.shape[:2] + (m + n, m + n))
    for row in range(n):
        S[:, :, row, row:row + m + 1] = fv
    for row in range(m):
        S[:, :, n + row, row:row + n + 1] = gv
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


def eliminated_batch(f: Polynomials, g: Polynomials,
                     degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Res(Res(f, g; d), c^2 + s^2 - 1; c) as Chebyshev series in sigma = sin^2 t on [0, 1].

    On the real unit circle Res(R, c^2 + s^2 - 1; c)(sigma) = R(c0, s) R(-c0, s) with
    c0 = sqrt(1 - sigma), s = sqrt(sigma) (eqs. 37 and 45), and the factor (c^2 + s^2)^2 that
    both resultants carry equals 1. So we evaluate the Sylvester determinants at Chebyshev
    nodes in sigma and interpolate: the basis is well conditioned on [0, 1], where the roots
    we need lie. We sample ``degree + 4`` nodes; the relative size of the coefficients above
    ``degree`` (zero in exact arithmetic) measures the accuracy.

    Returns:
        (series (T, degree + 1), aliasing (T,)); aliasing is inf for a degenerate series.
    """
    table, interpolation = _chebyshev_interpolation(degree + 4)
    det = np.linalg.det(_sylvester(f, g, table))
    half = det.shape[1] // 2
    series = np.matmul(interpolation, (det[:, :half] * det[:, half:])[..., None])[..., 0]
    scale = np.max(np.abs(series), axis=1)
    with np.errstate(divide='ignore', invalid='ignore'):
        aliasing = np.max(np.abs(series[:, degree + 1:]), axis=1) / scale
    aliasing[~(np.isfinite(scale) & (scale > 0.0))] = np.inf
    return series[:, :degree + 1], aliasing


def eliminated_polynomial(f: Polynomials, g: Polynomials, degree: int) -> tuple[np.ndarray, float]:
    """:func:`eliminated_batch` of one problem's 1-D polynomials: (series, aliasing)."""
    series, aliasing = eliminated_batch([p[None] for p in f], [p[None] for p in g], degree)
    return series[0], float(aliasing[0])


def chebyshev_roots(series: np.ndarray) -> np.ndarray:
    """Complex roots in x = 2 sigma - 1 of Chebyshev series (T, n + 1): eigenvalues of the
    colleague matrices (numpy's chebcompanion, batched; NaN when the leading coefficient is 0),
    shape (T, n)."""
    T, n = series.shape[0], series.shape[1] - 1
    scl = np.array([1.0] + [math.sqrt(0.5)] * (n - 1))
    mat = np.zeros((T, n, n))
    diagonal = np.full(n - 1, 0.5)
    diagonal[0] = math.sqrt(0.5)
    mat[:, np.arange(n - 1), np.arange(1, n)] = diagonal
    mat[:, np.arange(1, n), np.arange(n - 1)] = diagonal
    lead = series[:, -1:]
    good = (lead[:, 0] != 0.0) & np.all(np.isfinite(series), axis=1)
    safe = np.where(good[:, None], lead, 1.0)
    mat[:, :, -1] -= (series[:, :-1] / safe) * (scl / scl[-1]) * 0.5
    roots = np.linalg.eigvals(mat[:, ::-1, ::-1])
    roots[~good] = np.nan
    return roots


def sigma_roots(series: np.ndarray) -> np.ndarray:
    """Real roots sigma in [0, 1] of one Chebyshev series in 2 sigma - 1 (imaginary part below
    1e-6), sorted."""
    roots = chebyshev_roots(series[None])[0]
    real = roots[np.abs(roots.imag) <= 1e-6].real
    sigma = 0.5 * (real + 1.0)
    return np.sort(np.clip(sigma[(sigma >= -1e-8) & (sigma <= 1 + 1e-8)], 0.0, 1.0))


def _angles(roots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(cos t, sin t, strict, usable) for every root and sign choice, shape (T, 4 n): strict
    roots are real to 1e-6 (the paper's real roots), usable ones within ROOT_IMAG_TOLERANCE."""
    x = roots.real
    usable = (np.abs(roots.imag) <= ROOT_IMAG_TOLERANCE) & (x >= -1.1) & (x <= 1.1)
    strict = (np.abs(roots.imag) <= 1e-6) & (x >= -1.0 - 2e-8) & (x <= 1.0 + 2e-8)
    sigma = np.clip(0.5 * (np.where(usable, x, 0.0) + 1.0), 0.0, 1.0)
    s, c = np.sqrt(sigma), np.sqrt(1.0 - sigma)
    return (np.concatenate([c, -c, c, -c], axis=1), np.concatenate([s, s, -s, -s], axis=1),
            np.tile(strict, 4), np.tile(usable, 4))


def _relative_residual(coeffs: Polynomials, d: np.ndarray, table: list[np.ndarray]) -> np.ndarray:
    """|sum_i coeffs_i(c, s) d^(n-i)| / sum_i |...| at points given by a monomial table."""
    terms = [_evaluate(poly, table) * d ** (len(coeffs) - 1 - i)
             for i, poly in enumerate(coeffs)]
    size = terms[0] * 0.0
    total = terms[0] * 0.0
    for term in terms:
        total = total + term
        size = size + np.abs(term)
    return np.abs(total) / np.maximum(size, 1e-300)


def _interior_candidates(batch: ProblemBatch, zeta: Polynomials, gamma: Polynomials,
                         roots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interior critical points from the roots of S_u (d from F_d = 0, F_t checked).

    Returns:
        (points (T, C, 2), accepted (T, C): real roots that pass the residual test inside the
        disc, seeds (T, C): points near the disc to polish).
    """
    c, s, strict, usable = _angles(roots)
    table = _monomial_table(c, s, 4)
    z2, z1, z0 = (_evaluate(poly, table) for poly in zeta)
    disc = np.sqrt((z1 * z1 - 4 * z2 * z0).astype(complex))
    d = np.concatenate([(-z1 + disc) / (2 * z2), (-z1 - disc) / (2 * z2)], axis=1)
    real_d = np.isfinite(d) & (np.abs(d.imag) <= 1e-8 * np.abs(d)) & (d.real > 0)
    dd = np.where(real_d, d.real, 0.0)
    cc, ss = np.concatenate([c, c], axis=1), np.concatenate([s, s], axis=1)
    points = np.stack([dd * cc, dd * ss], axis=-1)
    distance = np.hypot(points[..., 0] - batch.p_o[:, None, 0],
                        points[..., 1] - batch.p_o[:, None, 1])
    residual = _relative_residual(gamma, dd, [np.concatenate([t, t], axis=1) for t in table])
    valid = real_d & np.concatenate([usable, usable], axis=1)
    accepted = (valid & np.concatenate([strict, strict], axis=1)
                & (distance < batch.r[:, None]) & (residual < RESIDUAL_TOLERANCE))
    seeds = valid & (distance < POLISH_DISTANCE * batch.r[:, None])
    return points, accepted, seeds


def _active_candidates(batch: ProblemBatch, q: Polynomials,
                       roots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boundary critical points from the roots of S_c (d from g = 0, Q checked).

    Returns:
        (points (T, C, 2) on the circle, accepted (T, C): real roots that pass the residual
        test, seeds (T, C): points to polish).
    """
    c, s, strict, usable = _angles(roots)
    ell = batch.p_o[:, None, 0] * c + batch.p_o[:, None, 1] * s
    k = (batch.d_o * batch.d_o - batch.r * batch.r)[:, None]
    disc = ell * ell - k
    hits = usable & (disc > -1e-12 * (batch.d_o ** 2)[:, None]) & (ell > 0)
    root = np.sqrt(np.maximum(disc, 0.0))
    d = np.where(np.concatenate([hits, hits], axis=1),
                 np.concatenate([ell - root, ell + root], axis=1), 0.0)
    cc, ss = np.concatenate([c, c], axis=1), np.concatenate([s, s], axis=1)
    table = _monomial_table(cc, ss, 5)
    good = _relative_residual(q, d, table) < RESIDUAL_TOLERANCE
    points = np.stack([d * cc, d * ss], axis=-1)
    seeds = np.concatenate([hits, hits], axis=1)
    return points, seeds & np.concatenate([strict, strict], axis=1) & good, seeds


def _polish_interior(batch: ProblemBatch, points: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Newton's method on m grad n - n grad m = 0 in q-coordinates (gain = n/m, h = [q, -1]),
    from the seed points of ``points`` (T, C, 2); NaN at the other entries and where Newton
    breaks down. A seed stops moving once its step falls below 1e-15 of |q|, so its result does
    not depend on the other seeds of the batch."""
    owner, column = np.nonzero(seeds)
    (m00, m01, m02, m11, m12, m22), (n00, n01, n02, n11, n12, n22) = (
        [e[owner] for e in part] for part in batch.forms)
    x, y = points[owner, column, 0], points[owner, column, 1]
    d2 = x * x + y * y
    q0, q1 = -y / d2, x / d2
    moving = np.ones(len(owner), dtype=bool)
    for _ in range(INTERIOR_NEWTON):
        a0, a1 = m00 * q0 + m01 * q1 - m02, m01 * q0 + m11 * q1 - m12   # (M h)_12
        b0, b1 = n00 * q0 + n01 * q1 - n02, n01 * q0 + n11 * q1 - n12   # (N h)_12
        num = q0 * a0 + q1 * a1 - (m02 * q0 + m12 * q1 - m22)
        den = q0 * b0 + q1 * b1 - (n02 * q0 + n12 * q1 - n22)
        g0, g1 = den * a0 - num * b0, den * a1 - num * b1             # gradient / 2
        cross = 2 * (a0 * b1 - b0 * a1)
        j00, j11 = den * m00 - num * n00, den * m11 - num * n11
        j01 = den * m01 - num * n01
        j10 = j01 - cross
        j01 = j01 + cross
        det = j00 * j11 - j01 * j10
        s0 = np.where(moving, (j11 * g0 - j01 * g1) / det, 0.0)
        s1 = np.where(moving, (j00 * g1 - j10 * g0) / det, 0.0)
        q0, q1 = q0 - s0, q1 - s1
        moving &= np.abs(s0) + np.abs(s1) > 1e-15 * (np.abs(q0) + np.abs(q1))
        if not moving.any():
            break
    n2 = q0 * q0 + q1 * q1
    out = np.full(points.shape, np.nan)
    out[owner, column, 0], out[owner, column, 1] = q1 / n2, -q0 / n2
    return out


def _polish_boundary(batch: ProblemBatch, points: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Newton steps in the q-circle angle on the boundary stationarity condition, from the seed
    points of ``points`` (T, C, 2) (on the circle); NaN at the other entries."""
    owner, column = np.nonzero(seeds)
    c0, c1, rho = (v[owner] for v in batch.q_circle)
    x, y = points[owner, column, 0], points[owner, column, 1]
    d2 = x * x + y * y
    t = np.arctan2(x / d2 - c1, -y / d2 - c0)
    F = boundary_stationarity(batch)[owner]
    t = polish_boundary_angles(F, t[:, None], BOUNDARY_NEWTON)[:, 0]
    q0, q1 = c0 + rho * np.cos(t), c1 + rho * np.sin(t)
    n2 = q0 * q0 + q1 * q1
    out = np.full(points.shape, np.nan)
    out[owner, column, 0], out[owner, column, 1] = q1 / n2, -q0 / n2
    return out


def _feasible(batch: ProblemBatch, points: np.ndarray, slack: float) -> np.ndarray:
    return np.hypot(points[..., 0] - batch.p_o[:, None, 0],
                    points[..., 1] - batch.p_o[:, None, 1]) <= batch.r[:, None] * (1 + slack)


def _bearing_batch(batch: ProblemBatch) -> tuple[np.ndarray, np.ndarray, list[str], np.ndarray]:
    """The polynomial route for T bearing problems.

    Returns:
        (best points (T, 2), their gains (T,), per-problem failure reasons ('' when none),
        candidates per problem (T,)).
    """
    zeta, gamma = kkt_batch(batch)
    q, g = active_batch(batch, (zeta, gamma))
    inner_series, inner_alias = eliminated_batch(zeta, gamma, INACTIVE_DEGREE)
    outer_series, outer_alias = eliminated_batch(q, g, ACTIVE_DEGREE)
    inner, inner_ok, inner_seeds = _interior_candidates(batch, zeta, gamma,
                                                        chebyshev_roots(inner_series))
    outer, outer_ok, outer_seeds = _active_candidates(batch, q, chebyshev_roots(outer_series))
    polished_inner = _polish_interior(batch, inner, inner_seeds)
    polished_outer = _polish_boundary(batch, outer, outer_seeds)
    points = np.concatenate([inner, polished_inner, outer, polished_outer], axis=1)
    usable = np.concatenate([inner_ok, _feasible(batch, polished_inner, 0.0), outer_ok,
                             outer_seeds], axis=1)
    usable &= np.all(np.isfinite(points), axis=-1)
    x, y = np.where(usable, points[..., 0], 1.0), np.where(usable, points[..., 1], 1.0)
    gains = batch.gain_at(x, y)
    gains = np.where(usable & np.isfinite(gains), gains, -np.inf)
    best = np.argmax(gains, axis=1)
    rows = np.arange(len(batch))
    reasons = ['' for _ in range(len(batch))]
    for t in range(len(batch)):
        if not inner_alias[t] < ALIASING_TOLERANCE or not outer_alias[t] < ALIASING_TOLERANCE:
            reasons[t] = (f'elimination polynomial lost accuracy '
                          f'({max(inner_alias[t], outer_alias[t]):.2g})')
        elif not np.isfinite(gains[t, best[t]]):
            reasons[t] = 'no admissible critical point'
    return points[rows, best], gains[rows, best], reasons, np.sum(usable, axis=1)


def _settle(problem: Problem, point: np.ndarray, gain: float, reason: str, candidates: int,
            fallback: bool) -> Solution:
    """RAM's answer for one problem: its best critical point if certified, else RQ's (visibly,
    ``Solution.fallback = 'rq'``), or FloatingPointError when ``fallback`` is False."""
    if not reason:
        name, proof = certify(problem, point, gain)
        if name in PROVED:
            x_o, y_o = problem.slot
            on_boundary = math.hypot(point[0] - x_o, point[1] - y_o) >= problem.r * (1 - 1e-9)
            return make_solution(problem, point, 'ram', on_boundary, candidates,
                                 certificate=name, details=proof, gain=gain)
        reason = 'best critical point not certified'
    if not fallback:
        raise FloatingPointError(reason)
    exact = rq_optimum(problem, 'ram')
    return replace(exact, fallback='rq', details={**exact.details, 'reason': reason})


def ram_batch(batch: ProblemBatch, fallback: bool = True) -> list[Solution]:
    """RAM on T problems of one kind at once (the bearing route vectorised over the batch).

    Raises:
        FloatingPointError: with ``fallback=False``, when a problem cannot be certified.
    """
    if batch.measurement == 'range':
        return [ram_optimum(batch.problem(t), fallback) for t in range(len(batch))]
    with np.errstate(all='ignore'):
        points, gains, reasons, counts = _bearing_batch(batch)
    return [_settle(batch.problem(t), points[t], float(gains[t]), reasons[t], int(counts[t]),
                    fallback) for t in range(len(batch))]


def ram_optimum(problem: Problem, fallback: bool = True) -> Solution:
    """The paper's analytic optimum (Sec. IV), certified; see the module docstring.

    Args:
        fallback: when the polynomial route loses accuracy or its answer cannot be certified,
            return the certified RQ optimum (and name it in ``Solution.fallback``); with False,
            raise FloatingPointError instead.
    """
    if problem.measurement != 'range':
        return ram_batch(ProblemBatch.stack([problem]), fallback)[0]
    solution = _plan_range(problem)
    if solution.certificate in PROVED:
        return solution
    return _settle(problem, solution.p, 0.0, 'optimum not certified: rounding defeats the '
                   'bound test', solution.candidates, fallback)


class RelaxedAlgebraicMethod(Strategy):
    """RAM: the paper's analytic method, falling back to RQ visibly when it cannot certify."""

    name = 'ram'
    OPTIONS = {'fallback': OptionSpec(True, 'fall back to RQ when the polynomial route loses '
                                            'accuracy or cannot certify its answer; false: '
                                            'raise FloatingPointError')}

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The analytic greedy optimum."""
        return ram_optimum(problem, bool(self.settings['fallback']))

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """:func:`ram_batch`: the bearing route vectorised over the trials."""
        solutions = ram_batch(problems, bool(self.settings['fallback']))
        return BatchPlan(np.array([s.p for s in solutions]),
                         np.array([s.fallback is not None for s in solutions]))
