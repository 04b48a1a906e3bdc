"""Global-optimality certificates for RAM and RQ: a proof (S-lemma), checked with its rounding
bounded, that no feasible point beats the chosen one by more than a stated gap.

Both gains are generalised Rayleigh quotients g(h) = h'Ah / h'Bh (B positive definite) of a
homogeneous vector h of the point (see :mod:`formopt_ros.core.cost`), and the feasible set is
{h : h'Gh <= 0} for one quadratic form G:

* bearing: h = [q0, q1, -1], A = P W^2 P, B = P + R e3 e3', and the q-disc
  |q - c|^2 <= rho^2 gives G = [[1, 0, c0], [0, 1, c1], [c0, c1, |c|^2 - rho^2]];
* range: h = p (the quotient is homogeneous of degree 0 in h, so the direction p / |p| of the
  gain's formula is not needed), A = (P W^2 P)[:2, :2], B = P[:2, :2] + R I, and the bearings
  under which the disc is seen, (h . p_o)^2 >= (|p_o|^2 - r^2) |h|^2, give
  G = (1 - r^2/|p_o|^2) I - u_o u_o' with u_o = p_o / |p_o| (the gain is even in h, so the
  mirrored cone does no harm); the test runs on these 2x2 matrices (:func:`range_system`).

If ``S = lambda B - A + mu G`` is positive definite for some mu >= 0, then every feasible h has
h'(lambda B - A)h > -mu h'Gh >= 0, i.e. g(h) < lambda. With lambda = g(p) + rtol cost this
proves cost(p) <= optimum + rtol cost for the gain g(p) as computed (``problem.gain_at``);
the exact gain differs from it by at most e = ``problem.gain_error_at`` (a rigorous bound on
the formula's rounding), so the gap claimed is rtol + e / cost. The
S-lemma (one quadratic constraint, Slater point p_o) says such a
mu exists whenever p is optimal (up to the gap), and KKT names it: (g(p) B - A + mu G) h = 0, so
mu = -(Gh)'(g B - A)h / |Gh|^2 (clipped at 0; mu = 0 when the top generalised eigenvector is
feasible, mu > 0 when the constraint is active).

The residual test: S is formed in floating point, so the test demands positive definiteness of
every matrix within a rounding bound of the computed S (a shifted LDL' factorisation, after a
Jacobi scaling that makes B's diagonal 1). Where cancellation in S defeats that bound, or the
gain's rounding bound exceeds every rtol cost, this module cannot decide: the exact stage of
:mod:`~formopt_ros.core.strategies.verify` runs the same test in exact arithmetic (its
:func:`~formopt_ros.core.strategies.verify.certify` is the entry point the strategies call).
A point that is not optimal fails the test, however accurate the arithmetic: a better feasible
point h makes h'Sh <= mu h'Gh <= 0.

:func:`proved_batch` is the floating-point test on arrays, for many problems at once, with the
scalar test's arithmetic operation for operation (so the same verdicts).
"""
from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.formulas import Entries
from formopt_ros.core.linalg import EPS, positive_definite_entries
from formopt_ros.core.model import RANGE

#: Certificate names (``Solution.certificate``).
INTERIOR = 'interior-eigenvector'      # proof with mu = 0: the quotient's global maximum
BOUNDARY = 'boundary-bound'            # proof with mu > 0: no feasible point is better
CRITICAL_POINTS = 'all-critical-points'  # every stationary point enumerated and checked
NONE = 'none'
#: Names that stand for a proof.
PROVED = (INTERIOR, BOUNDARY)
#: Relative cost gaps tried, smallest first: cost(p) <= optimum + gap * cost(p).
GAP_RTOLS = (1e-12, 1e-10)
#: The largest gap a certificate claims: an rtol of GAP_RTOLS plus at most as much again for the
#: rounding of the computed gain (floating point), or plus 2^-40 of it (exact stage).
MAX_GAP = 2 * GAP_RTOLS[-1]
#: Relative rounding error allowed in each entry of the scaled S (generous: a few operations).
ENTRY_ERROR = 16 * EPS
#: The entries (00, 01, 11) of a symmetric 2x2 matrix.
Entries2 = tuple[float, float, float]
#: Vectors of 3 and 2 components (floats, or arrays (T,) for a batch).
Vector3 = tuple[Any, Any, Any]
Vector2 = tuple[Any, Any]


def float_test(problem: Problem) -> Callable[[Problem, float, float, float, float, float],
                                             'Verdict']:
    """The floating-point test of the problem's kind: (problem, x, y, gain, cost, error) ->
    (mu, residual, rtol) (:data:`Verdict`)."""
    return _range_test if problem.measurement == RANGE else _bearing_test


def bearing_system(problem: Problem | ProblemBatch) -> tuple[Entries, Entries, Entries, Any]:
    """(A, B, G, size of G's entries before cancellation) of the module docstring for a bearing
    problem, as the six distinct entries of 3x3 matrices."""
    M, N = problem.forms
    c0, c1, rho = problem.q_circle
    return (M, N, (1.0, 0.0, c0, 1.0, c1, c0 * c0 + c1 * c1 - rho * rho),
            c0 * c0 + c1 * c1 + rho * rho)


def range_system(problem: Problem | ProblemBatch) -> tuple[Entries2, Entries2, Entries2]:
    """(A, B, G) of the module docstring for a range problem, each as the entries (00, 01, 11)
    of a symmetric 2x2 matrix; G's entries are (y_o^2 - r^2, -x_o y_o, x_o^2 - r^2) / |p_o|^2,
    each term at most 1 before cancellation."""
    (a00, a01, _, a11, _, _), _ = problem.forms
    p00, p01, _, p11, _, _ = problem.entries
    R = problem.R
    x_o, y_o = problem.slot
    r = problem.r
    w22 = problem.d_o * problem.d_o
    return ((a00, a01, a11), (p00 + R, p01, p11 + R),
            ((y_o * y_o - r * r) / w22, -x_o * y_o / w22, (x_o * x_o - r * r) / w22))


#: A floating-point test's verdict: (mu, residual, rtol): rtol the smallest of GAP_RTOLS proved
#: among those with rtol cost >= ``error`` (the bound on the computed gain's rounding, which the
#: claimed gap adds), inf when none is (the exact stage may still prove one), None when the
#: test does not apply (cost <= 0, or S's scale over- or underflows).
Verdict = tuple[float, float, float | None]


def _bearing_vectors(system: tuple[Entries, Entries, Entries, Any], x: Any, y: Any, g: Any,
                     sqrt: Callable[[Any], Any]) -> tuple[Vector3, Vector3, Vector3, Vector3]:
    """(d, v, w, h_s) of the bearing test at points (x, y) (m) with gains g, floats or arrays:
    the Jacobi scaling d = diag(B)^-1/2, the residual v = D (g B - A) h, the constraint's
    gradient w = D G h and the scaled h_s = D^-1 h, for h = [q0, q1, -1] and the system of
    :func:`bearing_system`. ``sqrt`` is math.sqrt or numpy.sqrt (both correctly rounded: a
    batch gets the same numbers as each of its problems)."""
    (a00, a01, a02, a11, a12, a22), (b00, b01, b02, b11, b12, b22), \
        (k00, k01, k02, k11, k12, k22), _ = system
    d0, d1, d2 = 1.0 / sqrt(b00), 1.0 / sqrt(b11), 1.0 / sqrt(b22)
    n2 = x * x + y * y
    h0, h1, h2 = -y / n2, x / n2, -1.0
    # residuals in the scaled coordinates h_s = D^-1 h: (D X D) h_s = D (X h)
    s00, s01, s02 = g * b00 - a00, g * b01 - a01, g * b02 - a02
    s11, s12, s22 = g * b11 - a11, g * b12 - a12, g * b22 - a22
    v = (d0 * (s00 * h0 + s01 * h1 + s02 * h2), d1 * (s01 * h0 + s11 * h1 + s12 * h2),
         d2 * (s02 * h0 + s12 * h1 + s22 * h2))
    w = (d0 * (k00 * h0 + k01 * h1 + k02 * h2), d1 * (k01 * h0 + k11 * h1 + k12 * h2),
         d2 * (k02 * h0 + k12 * h1 + k22 * h2))
    return (d0, d1, d2), v, w, (h0 / d0, h1 / d1, h2 / d2)


def _range_vectors(system: tuple[Entries2, Entries2, Entries2], x: Any, y: Any, g: Any,
                   sqrt: Callable[[Any], Any]) -> tuple[Vector2, Vector2, Vector2, Vector2]:
    """:func:`_bearing_vectors` for the 2x2 system of :func:`range_system`, h = p."""
    (a00, a01, a11), (b00, b01, b11), (k00, k01, k11) = system
    d0, d1 = 1.0 / sqrt(b00), 1.0 / sqrt(b11)
    v = (d0 * ((g * b00 - a00) * x + (g * b01 - a01) * y),
         d1 * ((g * b01 - a01) * x + (g * b11 - a11) * y))
    return (d0, d1), v, (d0 * (k00 * x + k01 * y), d1 * (k01 * x + k11 * y)), (x / d0, y / d1)


def _bearing_test(problem: Problem, x: float, y: float, g: float, cost: float,
                  error: float) -> Verdict:
    """The floating-point test for a bearing problem (3x3), h = [q0, q1, -1].

    The matrices are used unscaled and only S is scaled, entry by entry, by the Jacobi scaling
    D = diag(B)^-1/2: D S D is positive definite exactly when S is, whatever the rounding of D,
    and each scaled entry carries a few more roundings than its terms, far inside the bound.
    """
    system = bearing_system(problem)
    (a00, a01, a02, a11, a12, a22), (b00, b01, b02, b11, b12, b22), \
        (k00, k01, k02, k11, k12, k22), g_size = system
    (d0, d1, d2), (v0, v1, v2), (w0, w1, w2), (h0, h1, h2) = _bearing_vectors(
        system, x, y, g, math.sqrt)
    ww = w0 * w0 + w1 * w1 + w2 * w2
    hh = h0 * h0 + h1 * h1 + h2 * h2
    inside = h0 * w0 + h1 * w1 + h2 * w2 < -1e-9 * hh * math.sqrt(ww)
    # KKT multiplier; 0 inside the disc (the constraint is not active there)
    mu = 0.0 if inside or ww == 0.0 else max(0.0, -(w0 * v0 + w1 * v1 + w2 * v2) / ww)
    e00, e01, e02, e11, e12, e22 = d0 * d0, d0 * d1, d0 * d2, d1 * d1, d1 * d2, d2 * d2
    # bound on the scaled entries' terms: D B D has unit diagonal, so its entries are <= 1
    scale = abs(g) + max(a00 * e00, a11 * e11, a22 * e22)
    if mu > 0.0:
        # G's entries c0, c1, |c|^2 - rho^2 share k = 1 / (|p_o|^2 - r^2), whose rounding is
        # (|p_o|^2 + r^2) / (|p_o|^2 - r^2) times that of its terms (the disc G describes is
        # the true one scaled by 1 + delta_k): their terms count that much more
        d2, r2 = problem.d_o * problem.d_o, problem.r * problem.r
        scale += mu * max(1.0, (d2 + r2) / (d2 - r2)) * (
            max(abs(k00) * e00, abs(k01) * e01, abs(k02) * e02, abs(k11) * e11, abs(k12) * e12,
                abs(k22) * e22) + g_size * max(e00, e11, e22))
    size = scale * math.sqrt(hh)         # 0 when the data underflow (P ~ 1e-100, sigma ~ 1e100)
    if not (cost > 0.0 and 0.0 < size < math.inf):
        return mu, math.inf, None
    residual = math.sqrt((v0 + mu * w0) ** 2 + (v1 + mu * w1) ** 2 + (v2 + mu * w2) ** 2) / size
    return mu, residual, _proved_gap(
        (b00 * e00, b01 * e01, b02 * e02, b11 * e11, b12 * e12, b22 * e22),
        ((mu * k00 - a00) * e00, (mu * k01 - a01) * e01, (mu * k02 - a02) * e02,
         (mu * k11 - a11) * e11, (mu * k12 - a12) * e12, (mu * k22 - a22) * e22),
        g, cost, error, scale)


def _range_test(problem: Problem, x: float, y: float, g: float, cost: float,
                error: float) -> Verdict:
    """The floating-point test of :func:`_bearing_test` for the 2x2 system of
    :func:`range_system`, h = p; positive definiteness of the shifted S by its 2x2 pivots."""
    system = range_system(problem)
    (a00, a01, a11), (b00, b01, b11), (k00, k01, k11) = system
    (d0, d1), (v0, v1), (w0, w1), (h0, h1) = _range_vectors(system, x, y, g, math.sqrt)
    ww, hh = w0 * w0 + w1 * w1, h0 * h0 + h1 * h1
    inside = h0 * w0 + h1 * w1 < -1e-9 * hh * math.sqrt(ww)
    mu = 0.0 if inside or ww == 0.0 else max(0.0, -(w0 * v0 + w1 * v1) / ww)
    e00, e01, e11 = d0 * d0, d0 * d1, d1 * d1
    scale = abs(g) + max(a00 * e00, a11 * e11)
    if mu > 0.0:        # G's terms are at most 1 before cancellation
        scale += mu * (max(abs(k00) * e00, abs(k01) * e01, abs(k11) * e11) + max(e00, e11))
    size = scale * math.sqrt(hh)
    if not (cost > 0.0 and 0.0 < size < math.inf):
        return mu, math.inf, None
    residual = math.hypot(v0 + mu * w0, v1 + mu * w1) / size
    u00, u01, u11 = b00 * e00, b01 * e01, b11 * e11
    v00, v01, v11 = (mu * k00 - a00) * e00, (mu * k01 - a01) * e01, (mu * k11 - a11) * e11
    for rtol in GAP_RTOLS:
        if rtol * cost < error:
            continue
        bound = g + rtol * cost
        S00, S11 = bound * u00 + v00, bound * u11 + v11
        S01 = bound * u01 + v01
        delta = _rounding_shift(scale, rtol * cost, max(abs(S00), abs(S11)))
        if S00 > delta and (S00 - delta) * (S11 - delta) > S01 * S01:
            return mu, residual, rtol
    return mu, residual, math.inf


#: The rows and the columns of the distinct entries of a symmetric 2x2 and 3x3 matrix, in the
#: order of Entries2 and Entries, and the positions of the diagonal among them.
_PAIRS = {2: (np.array([0, 0, 1]), np.array([0, 1, 1])),
          3: (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))}
_DIAGONAL = {2: np.array([0, 2]), 3: np.array([0, 3, 5])}


def _stacked(values: Sequence[Any], size: int) -> np.ndarray:
    """Floats or arrays (size,) as the rows of one array (len(values), size)."""
    out = np.empty((len(values), size))
    for index, value in enumerate(values):
        out[index] = value
    return out


def proved_batch(batch: ProblemBatch, x: np.ndarray, y: np.ndarray,
                 g: np.ndarray) -> np.ndarray:
    """Per problem of a batch, True where :func:`certify` proves the point (x[t], y[t]) (m) with
    gain g[t] (m^2, from the gain formula) in floating point: the tests of :func:`_range_test`
    and :func:`_bearing_test` on arrays (T,), operation for operation, so that a problem's
    verdict is the one :func:`certify` reaches on ``batch.problem(t)``. False where that
    test fails or meets a value that is not a number (then :func:`certify` itself, with its
    exact stage, decides): never True where :func:`certify` would not prove. x, y and g are
    taken as float64 (float32 points would be rounded differently from the scalar's); no
    numpy warning is raised."""
    x, y, g = (np.asarray(v, dtype=float) for v in (x, y, g))
    A: Sequence[Any]
    B: Sequence[Any]
    K: Sequence[Any]
    d: Sequence[Any]
    v: Sequence[Any]
    w: Sequence[Any]
    h: Sequence[Any]
    with np.errstate(all='ignore'):
        cost = batch.base_cost - g
        error = batch.gain_error_at(x, y, g)
        if batch.measurement == RANGE:
            range_terms = range_system(batch)
            A, B, K = range_terms
            d, v, w, h = _range_vectors(range_terms, x, y, g, np.sqrt)
            factor, g_size = 1.0, 1.0
        else:
            bearing_terms = bearing_system(batch)
            A, B, K, g_size = bearing_terms
            d, v, w, h = _bearing_vectors(bearing_terms, x, y, g, np.sqrt)
            d2, r2 = batch.d_o * batch.d_o, batch.r * batch.r
            factor = np.maximum(1.0, (d2 + r2) / (d2 - r2))
        n = len(d)
        ww, hh = sum(map(operator.mul, w, w)), sum(map(operator.mul, h, h))
        inside = sum(map(operator.mul, h, w)) < -1e-9 * hh * np.sqrt(ww)
        mu = np.where(inside | (ww == 0.0), 0.0,
                      np.maximum(0.0, -sum(map(operator.mul, w, v)) / ww))
        # the entries as rows (entries, T), each entry's arithmetic as in the scalar test
        rows, columns = _PAIRS[n]
        diagonal = _DIAGONAL[n]
        D = _stacked(d, len(batch))
        E = D[rows] * D[columns]
        A2, B2, K2 = (_stacked(X, len(batch)) for X in (A, B, K))
        scale = np.abs(g) + (A2[diagonal] * E[diagonal]).max(axis=0)
        scale = np.where(mu > 0.0, scale + mu * factor * (
            (np.abs(K2) * E).max(axis=0) + g_size * E[diagonal].max(axis=0)), scale)
        size = scale * np.sqrt(hh)
        proved = np.zeros(len(batch), dtype=bool)
        U, V = B2 * E, (mu * K2 - A2) * E
        for rtol in GAP_RTOLS:
            gap = rtol * cost
            S = (g + gap) * U + V
            S[diagonal] -= _rounding_shift(scale, gap, np.abs(S[diagonal]).max(axis=0))
            proved |= ~(gap < error) & _positive_definite_pivots(S)
    return proved & (cost > 0.0) & (0.0 < size) & (size < math.inf)


def _positive_definite_pivots(S: np.ndarray) -> np.ndarray:
    """Where the symmetric 2x2 or 3x3 matrices whose entries are the rows of S (3 or 6, in
    Entries2 or Entries order) have positive pivots, by the arithmetic of the scalar tests."""
    if len(S) == 3:
        s00, s01, s11 = S
        return (s00 > 0.0) & (s00 * s11 > s01 * s01)
    s00, s01, s02, s11, s12, s22 = S
    l10, l20 = s01 / s00, s02 / s00
    d1 = s11 - l10 * s01
    b12 = s12 - l20 * s01
    return (s00 > 0.0) & (d1 > 0.0) & (s22 - l20 * s02 - b12 * b12 / d1 > 0.0)


def _rounding_shift(scale: Any, gap: Any, largest: Any) -> Any:
    """Shift of S's diagonal that covers the rounding of S's entries (each within ENTRY_ERROR
    of ``scale`` + ``gap``, the bound on their terms) and of the pivots (16 EPS of the largest
    magnitude on the diagonal, ``largest``); floats or arrays."""
    return 3.0 * ENTRY_ERROR * (scale + gap) + 16.0 * EPS * largest


def _proved_gap(U: Entries, V: Entries, g: float, cost: float, error: float,
                scale: float) -> float:
    """The smallest rtol of GAP_RTOLS with rtol cost >= error for which every symmetric matrix
    within the rounding bound of the scaled S = bound U + V, bound = g + rtol cost, is positive
    definite (a shifted LDL' factorisation), else inf. U = D B D and V = D (mu G - A) D,
    entry by entry; ``scale`` bounds the scaled entries' terms."""
    u00, u01, u02, u11, u12, u22 = U
    v00, v01, v02, v11, v12, v22 = V
    for rtol in GAP_RTOLS:
        if rtol * cost < error:
            continue
        bound = g + rtol * cost
        S00, S11, S22 = bound * u00 + v00, bound * u11 + v11, bound * u22 + v22
        delta = _rounding_shift(scale, rtol * cost, max(abs(S00), abs(S11), abs(S22)))
        if positive_definite_entries((S00 - delta, bound * u01 + v01, bound * u02 + v02,
                                      S11 - delta, bound * u12 + v12, S22 - delta)):
            return rtol
    return math.inf
