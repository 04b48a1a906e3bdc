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
from typing import Any

import numpy as np

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.formulas import Entries
from formopt_ros.core.strategies.base import (
    BatchContext, BatchPlan, OptionSpec, PlanContext, Solution, Strategy, make_solution)
from formopt_ros.core.strategies.certificate import PROVED
from formopt_ros.core.strategies.common import (
    Poly, boundary_stationarity, gains_tie, poly_combine, poly_mul, polish_boundary_angles,
    range_plan_from_direction)
from formopt_ros.core.strategies.rq import rq_optimum
from formopt_ros.core.strategies.verify import certify
from formopt_ros.core.model import MEASUREMENT_KINDS

#: Relative KKT residual below which a back-substituted root is a candidate without polishing.
RESIDUAL_TOLERANCE = 1e-4
#: Roots of the eliminated polynomials (in 2 sigma - 1) up to this far from the real axis seed
#: Newton's method (clustered roots are perturbed to complex pairs).
ROOT_IMAG_TOLERANCE = 0.1
#: Newton iterations of the interior and boundary polishing.
INTERIOR_NEWTON = 8
BOUNDARY_NEWTON = 6
#: Interior start points are taken from bearings up to asin(r/|p_o|) + BEARING_MARGIN (rad)
#: from p_o's: a root off by 1e-2 in sigma = sin^2 t is off by up to ~0.1 rad in t.
BEARING_MARGIN = 0.3
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
Polynomials = list[np.ndarray]


def kkt_coefficients(forms: tuple[Entries, Entries]) -> tuple[list[Poly], list[Poly]]:
    """Coefficients in d of F_d/2 (zeta2, zeta1, zeta0) and F_t (gamma3..gamma0), eqs. (33-34),
    as coefficient tuples of homogeneous polynomials in (cos t, sin t) (module docstring),
    from the entries of M and N (floats for a problem, arrays (T,) for a batch)."""
    (m00, m01, m02, m11, m12, m22), (n00, n01, n02, n11, n12, n22) = forms
    cu, cv = m22, n22                                    # n22 = P33 + R
    bu, bv = (-m12, m02), (-n12, n02)                    # -X[:2, 2]' alpha, alpha = [-s, c]
    bu_t, bv_t = (m02, m12), (n02, n12)                  # d/dt
    gu, gv = (m11, -2 * m01, m00), (n11, -2 * n01, n00)  # alpha' X alpha
    gu_t, gv_t = (-2 * m01, 2 * (m00 - m11), 2 * m01), (-2 * n01, 2 * (n00 - n11), 2 * n01)
    zeta = [poly_combine((cu, bv), (-cv, bu)), poly_combine((cu, gv), (-cv, gu)),
            poly_combine((1, poly_mul(bu, gv)), (-1, poly_mul(bv, gu)))]
    gamma = [poly_combine((2 * cv, bu_t), (-2 * cu, bv_t)),
             poly_combine((4, poly_mul(bu_t, bv)), (-4, poly_mul(bu, bv_t)), (cv, gu_t),
                          (-cu, gv_t)),
             poly_combine((2, poly_mul(bu_t, gv)), (2, poly_mul(gu_t, bv)),
                          (-2, poly_mul(bu, gv_t)), (-2, poly_mul(gu, bv_t))),
             poly_combine((1, poly_mul(gu_t, gv)), (-1, poly_mul(gu, gv_t)))]
    return zeta, gamma


def active_coefficients(kkt: tuple[list[Poly], list[Poly]], x_o: Any, y_o: Any,
                        k: Any) -> tuple[list[Poly], list[Poly]]:
    """Coefficients in d of Q (degree 4, eq. 41) and of the homogenised constraint g (eq. 40),
    for the slot (x_o, y_o) and k = |p_o|^2 - r^2 (floats or arrays)."""
    zeta, gamma = kkt
    ell = (x_o, y_o)                              # x_o c + y_o s
    kappa = (-2 * y_o, 2 * x_o)                   # 2 (x_o s - y_o c): zeta holds F_d / 2
    q = [gamma[0],
         poly_combine((1, gamma[1]), (-1, poly_mul(ell, gamma[0])),
                      (-1, poly_mul(kappa, zeta[0]))),
         poly_combine((1, gamma[2]), (-1, poly_mul(ell, gamma[1])),
                      (-1, poly_mul(kappa, zeta[1]))),
         poly_combine((1, gamma[3]), (-1, poly_mul(ell, gamma[2])),
                      (-1, poly_mul(kappa, zeta[2]))),
         tuple(-c for c in poly_mul(ell, gamma[3]))]
    g = [(1.0 + 0.0 * k,), (-2.0 * x_o, -2.0 * y_o), (k, 0.0 * k, k)]
    return q, g


def _rows(polys: list[Poly], T: int) -> Polynomials:
    """Coefficient tuples (floats, or arrays (T,)) as arrays (T, n + 1)."""
    if T == 1 and not any(isinstance(c, np.ndarray) for poly in polys for c in poly):
        return [np.array([poly], dtype=float) for poly in polys]
    return [np.stack(np.broadcast_arrays(*poly), axis=-1) for poly in polys]


def _polynomials(source: Problem | ProblemBatch) -> tuple[Polynomials, Polynomials,
                                                          Polynomials, Polynomials]:
    """(zeta, gamma, q, g) of a problem (in Python floats, then rows (1, n + 1)) or of a batch
    (in arrays (T,)): the same arithmetic either way."""
    T = len(source) if isinstance(source, ProblemBatch) else 1
    kkt = kkt_coefficients(source.forms)
    x_o: Any
    y_o: Any
    k: Any
    if isinstance(source, ProblemBatch):
        x_o, y_o = source.p_o[:, 0], source.p_o[:, 1]
        k = source.d_o * source.d_o - source.r * source.r
    else:
        (x_o, y_o), r = source.slot, float(source.r)
        k = source.d_o * source.d_o - r * r
    q, g = active_coefficients(kkt, x_o, y_o, k)
    return _rows(kkt[0], T), _rows(kkt[1], T), _rows(q, T), _rows(g, T)


def kkt_polynomials(problem: Problem) -> tuple[Polynomials, Polynomials]:
    """The KKT polynomials of one problem (:func:`kkt_coefficients`) as 1-D arrays."""
    zeta, gamma, _, _ = _polynomials(problem)
    return [z[0] for z in zeta], [g[0] for g in gamma]


def active_polynomials(problem: Problem) -> tuple[Polynomials, Polynomials]:
    """The active-constraint polynomials of one problem (:func:`active_coefficients`)."""
    _, _, q, g = _polynomials(problem)
    return [x[0] for x in q], [x[0] for x in g]


def _monomial_table(c: np.ndarray, s: np.ndarray, max_degree: int = 5) -> list[np.ndarray]:
    """Entry n: the monomials c^(n-k) s^k, k = 0..n, at the points, shape c.shape + (n + 1,)."""
    table = [np.ones(c.shape + (1,))]
    for _ in range(max_degree):
        last = table[-1]
        table.append(np.concatenate([last * c[..., None], last[..., -1:] * s[..., None]],
                                    axis=-1))
    return table


def _at_nodes(poly: np.ndarray, table: list[np.ndarray]) -> np.ndarray:
    """Values (T, K) of polynomials (T, n + 1) at the K points of a monomial table (entries
    (K, n + 1)): one matrix-vector product per problem, so each problem's values are those it
    gets alone."""
    return np.matmul(table[poly.shape[-1] - 1], poly[..., None])[..., 0]


def _at_points(poly: np.ndarray, owner: np.ndarray, table: list[np.ndarray]) -> np.ndarray:
    """Values (A,) of the polynomials of problems ``owner`` (A,) at A points (table entries
    (A, n + 1)): one dot product per point."""
    return np.matmul(table[poly.shape[-1] - 1][:, None, :], poly[owner][..., None])[:, 0, 0]


def _sylvester(f: Polynomials, g: Polynomials, table: list[np.ndarray]) -> np.ndarray:
    """Sylvester matrices in d of f and g (coefficient lists, highest power first) at the
    points of a monomial table; shape (T, K, m + n, m + n). Rows 0..n-1 hold f shifted."""
    m, n = len(f) - 1, len(g) - 1
    fv = np.stack([_at_nodes(poly, table) for poly in f], axis=-1)
    gv = np.stack([_at_nodes(poly, table) for poly in g], axis=-1)
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


@lru_cache(maxsize=4)
def _colleague_base(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The colleague matrix of degree n without its last column's correction, and the scale
    of that correction (numpy's chebcompanion)."""
    base = np.zeros((n, n))
    diagonal = np.full(n - 1, 0.5)
    diagonal[0] = math.sqrt(0.5)
    base[np.arange(n - 1), np.arange(1, n)] = diagonal
    base[np.arange(1, n), np.arange(n - 1)] = diagonal
    scl = np.array([1.0] + [math.sqrt(0.5)] * (n - 1))
    return base, scl / scl[-1] * 0.5


def chebyshev_roots(series: np.ndarray) -> np.ndarray:
    """Complex roots in x = 2 sigma - 1 of Chebyshev series (T, n + 1): eigenvalues of the
    colleague matrices (numpy's chebcompanion, batched; NaN when the leading coefficient is 0 or
    so small that the matrix overflows), shape (T, n)."""
    base, scale = _colleague_base(series.shape[1] - 1)
    mat = np.repeat(base[None], len(series), axis=0)
    lead = series[:, -1:]
    good = (lead[:, 0] != 0.0) & np.all(np.isfinite(series), axis=1)
    mat[:, :, -1] -= (series[:, :-1] / np.where(good[:, None], lead, 1.0)) * scale
    finite = np.all(np.isfinite(mat[:, :, -1]), axis=1)   # a tiny leading term overflows
    good &= finite
    mat[~finite] = base
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


class _Data:
    """What the candidate stages read per problem, for the problems ``owner`` of the candidates:
    Python floats for a single problem (no numpy per-call cost, no gathering), arrays gathered
    by owner for a batch. Element by element the arithmetic is the same."""

    NAMES = ('x_o', 'y_o', 'r', 'd_o', 'c0', 'c1', 'rho', 'm00', 'm01', 'm02', 'm11', 'm12',
             'm22', 'n00', 'n01', 'n02', 'n11', 'n12', 'n22')

    def __init__(self, source: Problem | ProblemBatch) -> None:
        self.source = source
        self.single = isinstance(source, Problem)
        if isinstance(source, Problem):
            geometry: tuple[Any, ...] = (*source.slot, float(source.r), source.d_o,
                                         *source.q_circle)
        else:
            geometry = (source.p_o[:, 0], source.p_o[:, 1], source.r, source.d_o,
                        *source.q_circle)
        self.values = dict(zip(self.NAMES, (*geometry, *source.forms[0], *source.forms[1])))

    def take(self, owner: np.ndarray, *names: str) -> list[Any]:
        """The named values for every candidate (floats when single)."""
        if self.single:
            return [self.values[name] for name in names]
        return [self.values[name][owner] for name in names]

    def gains(self, owner: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """The gains at candidate points (x, y) of problems ``owner``."""
        if isinstance(self.source, Problem):
            return np.asarray(self.source.gain_at(x, y))
        return self.source.gains_of(owner, x, y)


def _angles(roots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bearings of the usable roots (within ROOT_IMAG_TOLERANCE of the real axis; strict ones,
    real to 1e-6, are the paper's real roots): (owner, cos t, sin t, strict), flat arrays of
    the four sign choices of every usable root of every problem."""
    x = roots.real
    usable = (np.abs(roots.imag) <= ROOT_IMAG_TOLERANCE) & (x >= -1.1) & (x <= 1.1)
    strict = (np.abs(roots.imag) <= 1e-6) & (x >= -1.0 - 2e-8) & (x <= 1.0 + 2e-8)
    owner, index = np.nonzero(usable)
    sigma = np.clip(0.5 * (x[owner, index] + 1.0), 0.0, 1.0)
    s, c = np.sqrt(sigma), np.sqrt(1.0 - sigma)
    return (np.tile(owner, 4), np.concatenate([c, -c, c, -c]), np.concatenate([s, s, -s, -s]),
            np.tile(strict[owner, index], 4))


def _relative_residual(coeffs: Polynomials, owner: np.ndarray, d: np.ndarray,
                       table: list[np.ndarray]) -> np.ndarray:
    """|sum_i coeffs_i(c, s) d^(n-i)| / sum_i |...| at points given by a monomial table."""
    total = size = np.zeros(len(d))
    for i, poly in enumerate(coeffs):
        term = _at_points(poly, owner, table) * d ** (len(coeffs) - 1 - i)
        total, size = total + term, size + np.abs(term)
    return np.abs(total) / np.maximum(size, 1e-300)


def _better_of_pair(bearing: np.ndarray, residual: np.ndarray, count: int) -> np.ndarray:
    """The start points to polish: of the two back-substituted points of one bearing (two roots
    d; ``bearing`` indices < count), the one with the smaller residual, and any whose residual
    passes RESIDUAL_TOLERANCE. Near-multiple roots are off by ~sqrt(eps) or more (1e-2 in
    sigma was seen), so their points may lie far from the disc before Newton's method."""
    best = np.full(count, np.inf)
    np.minimum.at(best, bearing, residual)
    return (residual <= best[bearing]) | (residual < RESIDUAL_TOLERANCE)


Candidates = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _interior_candidates(data: _Data, zeta: Polynomials, gamma: Polynomials,
                         roots: np.ndarray) -> Candidates:
    """Interior critical points from the roots of S_u (d from F_d = 0, F_t checked).

    Returns:
        (owner (C,), points (C, 2), accepted (C,): real roots that pass the residual test
        inside the disc, seeds (C,): points to polish).
    """
    owner, c, s, strict = _angles(roots)
    # bearings that could lead into the disc: within asin(r/|p_o|) + BEARING_MARGIN of p_o's
    x_o, y_o, r, d_o = data.take(owner, 'x_o', 'y_o', 'r', 'd_o')
    reach = np.cos(np.minimum(np.arcsin(r / d_o) + BEARING_MARGIN, math.pi)) * d_o
    near = np.flatnonzero(c * x_o + s * y_o >= reach)
    owner, c, s, strict = owner[near], c[near], s[near], strict[near]
    bearings = len(c)
    table = _monomial_table(c, s, 4)
    z2, z1, z0 = (_at_points(poly, owner, table) for poly in zeta)
    disc = np.sqrt((z1 * z1 - 4 * z2 * z0).astype(complex))
    d = np.concatenate([(-z1 + disc) / (2 * z2), (-z1 - disc) / (2 * z2)])
    keep = np.flatnonzero(np.isfinite(d) & (np.abs(d.imag) <= 1e-8 * np.abs(d)) & (d.real > 0))
    angle = keep % bearings if bearings else keep
    owner, d, c, s, strict = owner[angle], d.real[keep], c[angle], s[angle], strict[angle]
    points = np.stack([d * c, d * s], axis=-1)
    x_o, y_o, r = data.take(owner, 'x_o', 'y_o', 'r')
    distance = np.hypot(points[:, 0] - x_o, points[:, 1] - y_o)
    residual = _relative_residual(gamma, owner, d, [t[angle] for t in table])
    accepted = strict & (distance < r) & (residual < RESIDUAL_TOLERANCE)
    return owner, points, accepted, _better_of_pair(angle, residual, bearings)


def _active_candidates(data: _Data, q: Polynomials, roots: np.ndarray) -> Candidates:
    """Boundary critical points from the roots of S_c (d from g = 0, Q checked).

    Returns:
        (owner (C,), points (C, 2) on the circle, accepted (C,): real roots that pass the
        residual test, seeds (C,): points to polish).
    """
    owner, c, s, strict = _angles(roots)
    x_o, y_o, r, d_o = data.take(owner, 'x_o', 'y_o', 'r', 'd_o')
    ell = x_o * c + y_o * s
    disc = ell * ell - (d_o * d_o - r * r)
    hits = np.flatnonzero((disc > -1e-12 * d_o * d_o) & (ell > 0))
    root = np.sqrt(np.maximum(disc[hits], 0.0))
    d = np.concatenate([ell[hits] - root, ell[hits] + root])
    angle = np.concatenate([hits, hits])
    owner, c, s, strict = owner[angle], c[angle], s[angle], strict[angle]
    residual = _relative_residual(q, owner, d, _monomial_table(c, s, 5))
    return (owner, np.stack([d * c, d * s], axis=-1), strict & (residual < RESIDUAL_TOLERANCE),
            _better_of_pair(angle, residual, len(ell)))


def _polish_interior(data: _Data, owner: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Newton's method on m grad n - n grad m = 0 in q-coordinates (gain = n/m, h = [q, -1])
    from points (C, 2) of problems ``owner``; NaN where Newton breaks down. A point stops
    moving after a step below 1e-13 of |q| (converged), or one larger than its previous step
    (not converging), so its result depends on itself only."""
    m00, m01, m02, m11, m12, m22, n00, n01, n02, n11, n12, n22 = data.take(
        owner, 'm00', 'm01', 'm02', 'm11', 'm12', 'm22', 'n00', 'n01', 'n02', 'n11', 'n12',
        'n22')
    x, y = points[:, 0], points[:, 1]
    d2 = x * x + y * y
    q0, q1 = -y / d2, x / d2
    moving = np.ones(len(owner), dtype=bool)
    last = np.full(len(owner), np.inf)
    for _ in range(INTERIOR_NEWTON):
        a0, a1 = m00 * q0 + m01 * q1 - m02, m01 * q0 + m11 * q1 - m12   # (M h)_12
        b0, b1 = n00 * q0 + n01 * q1 - n02, n01 * q0 + n11 * q1 - n12   # (N h)_12
        num = q0 * a0 + q1 * a1 - (m02 * q0 + m12 * q1 - m22)
        den = q0 * b0 + q1 * b1 - (n02 * q0 + n12 * q1 - n22)
        g0, g1 = den * a0 - num * b0, den * a1 - num * b1             # gradient / 2
        cross = 2 * (a0 * b1 - b0 * a1)
        j00, j11 = den * m00 - num * n00, den * m11 - num * n11
        j01 = den * m01 - num * n01
        det = j00 * j11 - (j01 + cross) * (j01 - cross)
        s0 = np.where(moving, (j11 * g0 - (j01 + cross) * g1) / det, 0.0)
        s1 = np.where(moving, (j00 * g1 - (j01 - cross) * g0) / det, 0.0)
        q0, q1 = q0 - s0, q1 - s1
        size = np.abs(s0) + np.abs(s1)
        moving &= (size > 1e-13 * (np.abs(q0) + np.abs(q1))) & (size <= last)
        last = size
        if not moving.any():
            break
    n2 = q0 * q0 + q1 * q1
    return np.stack([q1 / n2, -q0 / n2], axis=-1)


def _polish_boundary(data: _Data, F: np.ndarray, owner: np.ndarray,
                     points: np.ndarray) -> np.ndarray:
    """Newton steps in the q-circle angle on the boundary stationarity condition (Fourier
    coefficients F: (7,) for a single problem, (T, 7) for a batch) from points (C, 2) on the
    circle of problems ``owner``."""
    c0, c1, rho = data.take(owner, 'c0', 'c1', 'rho')
    x, y = points[:, 0], points[:, 1]
    d2 = x * x + y * y
    t = np.arctan2(x / d2 - c1, -y / d2 - c0)
    F = F[None] if data.single else F[owner]
    t = polish_boundary_angles(F, t[:, None], BOUNDARY_NEWTON)[:, 0]
    q0, q1 = c0 + rho * np.cos(t), c1 + rho * np.sin(t)
    n2 = q0 * q0 + q1 * q1
    return np.stack([q1 / n2, -q0 / n2], axis=-1)


def _best_per_owner(T: int, owner: np.ndarray, points: np.ndarray,
                    gains: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The highest-gain candidate of each of T problems (ties: the first), (T, 2) and (T,);
    NaN and -inf for a problem without candidates."""
    gains = np.where(np.isfinite(gains), gains, -np.inf)
    order = np.lexsort((-gains, owner))          # by problem, best first, ties in order
    first = order[np.r_[True, owner[order][1:] != owner[order][:-1]]] if len(order) else order
    best, best_gain = np.full((T, 2), np.nan), np.full(T, -np.inf)
    best[owner[first]], best_gain[owner[first]] = points[first], gains[first]
    return best, best_gain


#: RAM's best point of a problem, its gain, the reason it failed ('' if none), the number of
#: candidates, and the proof when a floating-point certificate was already checked.
Route = tuple[np.ndarray, np.ndarray, list[str], np.ndarray,
              list[tuple[str, dict[str, Any]] | None]]


def _bearing_route(source: Problem | ProblemBatch) -> Route:
    """The polynomial route for T bearing problems, or for one problem (T = 1; its
    per-problem quantities are then Python floats, bit for bit as in a batch but without
    numpy's per-call cost).

    Boundary critical points first (the active-constraint resultant S_c). The best of them is
    tested with the floating-point certificate, whose multiplier proof covers the whole disc:
    where it holds, that point is the optimum and the interior route is skipped. For the other
    problems the interior critical points (S_u) join, and the best of all is returned.

    Returns:
        (best points (T, 2), their gains (T,), per-problem failure reasons ('' when none),
        candidates per problem (T,), proofs (or None) per problem).
    """
    T = 1 if isinstance(source, Problem) else len(source)
    data = _Data(source)
    zeta, gamma, q, g = _polynomials(source)
    series, outer_alias = eliminated_batch(q, g, ACTIVE_DEGREE)
    o_owner, outer, o_ok, o_seed = _active_candidates(data, q, chebyshev_roots(series))
    seeds = np.flatnonzero(o_seed)
    polished = _polish_boundary(data, boundary_stationarity(source), o_owner[seeds],
                                outer[seeds])
    good = np.isfinite(polished[:, 0]) & np.isfinite(polished[:, 1])
    outer[seeds[good]] = polished[good]
    use = o_ok | o_seed
    o_owner, outer = o_owner[use], outer[use]
    o_gains = data.gains(o_owner, outer[:, 0], outer[:, 1])
    best, best_gain = _best_per_owner(T, o_owner, outer, o_gains)
    proofs: list[tuple[str, dict[str, Any]] | None] = [None] * T
    counts = np.bincount(o_owner, minlength=T)
    reasons = ['' for _ in range(T)]
    need = []
    for t in range(T):
        if outer_alias[t] < ALIASING_TOLERANCE and np.isfinite(best_gain[t]):
            problem = source if isinstance(source, Problem) else source.problem(t)
            name, proof = certify(problem, (float(best[t, 0]), float(best[t, 1])),
                                  float(best_gain[t]), exact=False)
            if name in PROVED:
                proofs[t] = (name, proof)
                continue
        need.append(t)
    if not need:
        return best, best_gain, reasons, counts, proofs
    # the interior route for the problems not settled on the boundary
    rows = np.array(need)
    sub = source if isinstance(source, Problem) else source.subset(rows)
    sub_data = _Data(sub)
    zeta, gamma = [z[rows] for z in zeta], [x[rows] for x in gamma]
    series, inner_alias = eliminated_batch(zeta, gamma, INACTIVE_DEGREE)
    i_owner, inner, i_ok, i_seed = _interior_candidates(sub_data, zeta, gamma,
                                                        chebyshev_roots(series))
    # a polished point replaces its seed; a seed whose polishing failed stays if it passed
    seeds = np.flatnonzero(i_seed)
    polished = _polish_interior(sub_data, i_owner[seeds], inner[seeds])
    x_o, y_o, r = sub_data.take(i_owner[seeds], 'x_o', 'y_o', 'r')
    good = np.hypot(polished[:, 0] - x_o, polished[:, 1] - y_o) <= r
    inner[seeds[good]] = polished[good]
    i_use = i_ok.copy()
    i_use[seeds[good]] = True
    i_owner, inner = rows[i_owner[i_use]], inner[i_use]
    i_gains = sub_data.gains(np.searchsorted(rows, i_owner), inner[:, 0], inner[:, 1])
    taken = np.isin(o_owner, rows)
    owner = np.concatenate([i_owner, o_owner[taken]])
    both, both_gain = _best_per_owner(T, owner, np.concatenate([inner, outer[taken]]),
                                      np.concatenate([i_gains, o_gains[taken]]))
    best[rows], best_gain[rows] = both[rows], both_gain[rows]
    counts = counts + np.bincount(i_owner, minlength=T)
    for k, t in enumerate(need):
        alias = max(inner_alias[k], outer_alias[t])
        if not alias < ALIASING_TOLERANCE:
            reasons[t] = f'elimination polynomial lost accuracy ({alias:.2g})'
        elif not np.isfinite(best_gain[t]):
            reasons[t] = 'no admissible critical point'
    return best, best_gain, reasons, counts, proofs


def _verdict(problem: Problem, point: np.ndarray, gain: float, reason: str,
             proof: tuple[str, dict[str, Any]] | None) -> tuple[str, str, dict[str, Any]]:
    """('', certificate, proof details) when RAM's best critical point is certified (``proof``
    when the route already holds one), else (the reason it is not, '', {})."""
    if proof is not None:
        return '', proof[0], proof[1]
    if not reason:
        name, details = certify(problem, (float(point[0]), float(point[1])), gain)
        if name in PROVED:
            return '', name, details
        reason = 'best critical point not certified'
    return reason, '', {}


def _fall_back(problem: Problem, reason: str, fallback: bool) -> Solution:
    """The certified RQ optimum in RAM's place (``Solution.fallback = 'rq'``), or
    FloatingPointError when ``fallback`` is False."""
    if not fallback:
        raise FloatingPointError(reason)
    exact = rq_optimum(problem, 'ram')
    return replace(exact, fallback='rq', details={**exact.details, 'reason': reason})


def ram_batch(batch: ProblemBatch, fallback: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """RAM on T problems of one kind at once (the bearing route vectorised over the batch).

    Returns:
        (chosen points (T, 2), fallback flags (T,)); point t equals
        ``ram_optimum(batch.problem(t)).p`` bit for bit.

    Raises:
        FloatingPointError: with ``fallback=False``, when a problem cannot be certified.
    """
    T = len(batch)
    if batch.measurement == 'range':
        solutions = [ram_optimum(batch.problem(t), fallback) for t in range(T)]
        return (np.array([s.p for s in solutions]),
                np.array([s.fallback is not None for s in solutions]))
    with np.errstate(all='ignore'):
        points, gains, reasons, _, proofs = _bearing_route(batch)
    flags = np.zeros(T, dtype=bool)
    for t in range(T):
        problem = batch.problem(t)
        reason, _, _ = _verdict(problem, points[t], float(gains[t]), reasons[t], proofs[t])
        if reason:
            points[t], flags[t] = _fall_back(problem, reason, fallback).p, True
    return points, flags


def ram_optimum(problem: Problem, fallback: bool = True) -> Solution:
    """The paper's analytic optimum (Sec. IV), certified; see the module docstring.

    Args:
        fallback: when the polynomial route loses accuracy or its answer cannot be certified,
            return the certified RQ optimum (and name it in ``Solution.fallback``); with False,
            raise FloatingPointError instead.
    """
    if problem.measurement == 'range':
        solution = _plan_range(problem)
        if solution.certificate in PROVED:
            return solution
        return _fall_back(problem, 'optimum not certified: rounding defeats the bound test',
                          fallback)
    with np.errstate(all='ignore'):
        points, gains, reasons, counts, proofs = _bearing_route(problem)
    point, gain = points[0], float(gains[0])
    reason, name, proof = _verdict(problem, point, gain, reasons[0], proofs[0])
    if reason:
        return _fall_back(problem, reason, fallback)
    x_o, y_o = problem.slot
    on_boundary = math.hypot(point[0] - x_o, point[1] - y_o) >= problem.r * (1 - 1e-9)
    return make_solution(problem, point, 'ram', on_boundary, int(counts[0]), certificate=name,
                         details=proof, gain=gain)


class RelaxedAlgebraicMethod(Strategy):
    """RAM: the paper's analytic method, falling back to RQ visibly when it cannot certify."""

    name = 'ram'
    OPTIONS = {'fallback': OptionSpec(True, 'fall back to RQ when the polynomial route loses '
                                            'accuracy or cannot certify its answer; false: '
                                            'raise FloatingPointError')}

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The analytic greedy optimum (scalar measurements only)."""
        if problem.measurement not in MEASUREMENT_KINDS:
            raise InvalidInput('method', f"'ram' does not apply to a {problem.measurement!r} "
                               "measurement: it is the paper's method for one scalar "
                               'measurement (range or bearing); rq solves it with a certificate')
        return ram_optimum(problem, bool(self.settings['fallback']))

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """:func:`ram_batch`: the bearing route vectorised over the trials."""
        return BatchPlan(*ram_batch(problems, bool(self.settings['fallback'])))
