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
Jacobi scaling that makes B's diagonal 1). When cancellation in S defeats that bound (large
entries, a small eigenvalue: ill-conditioned priors, or a gain close to tr(W P W)), the same
test runs again in exact arithmetic on the exact data (P, p_o, r, sigma and p are dyadic
rationals, so integers after one common scaling: :func:`exact_bound_matrix`), which takes
about 10 us; so it does where e exceeds every rtol cost (the gain formula cancels), with
lambda just above the exact gain (:func:`exact_gain`) and the exact cost reported. There the
multiplier is decided exactly: for range the maximiser of the concave det(S + mu G)
(:func:`_best_range_multiplier`); for bearing, when the floating-point multiplier fails, 0 or a
critical point of the cubic det(S + mu G) (:func:`_best_bearing_multiplier`), which finds a mu
whenever one exists: where S cancels, the float one can be off by more than the proof's margin.
A point that is not optimal fails the test, however accurate the arithmetic: a better feasible
point h makes h'Sh <= mu h'Gh <= 0.

:func:`proved_batch` is the floating-point test on arrays, for many problems at once, with the
scalar test's arithmetic operation for operation (so the same verdicts).
"""
from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence
from fractions import Fraction
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
#: Bits of the rational approximations of the exact bearing multiplier's candidates, coarse
#: to fine (:func:`_best_bearing_multiplier`).
MULTIPLIER_BITS = (64, 256, 1024)
#: The entries (00, 01, 11) of a symmetric 2x2 matrix.
Entries2 = tuple[float, float, float]
#: Vectors of 3 and 2 components (floats, or arrays (T,) for a batch).
Vector3 = tuple[Any, Any, Any]
Vector2 = tuple[Any, Any]


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


def certify(problem: Problem, p: Sequence[float], gain: float | None = None,
            exact: bool | None = True) -> tuple[str, dict[str, Any]]:
    """Try to prove that p (2,) is a global optimum of ``problem`` up to a small gap.

    Args:
        problem: the problem.
        p: the candidate, m, feasible.
        gain: its gain if already known (m^2, from ``problem.gain_at``), else computed.
        exact: when the floating-point test is inconclusive, repeat it in exact arithmetic
            (about 10 us); False: never (a tentative candidate that a cheaper search may
            replace); None: only when p is a KKT point on the boundary (mu > 0), the one kind
            of tentative candidate that is likely optimal.

    Returns:
        (name, details): INTERIOR or BOUNDARY when the proof holds, NONE otherwise; details
        hold 'certificate_gap' (relative cost gap proved, or inf: the true cost at p exceeds
        the true optimum by at most this times the cost), 'certificate_multiplier' (mu) and
        'certificate_residual' (|(g B - A + mu G) h| relative to the scale of S). In floating
        point the gap is rtol + e / cost, e the bound on the computed gain's rounding
        (:meth:`~formopt_ros.core.cost.Problem.gain_error_at`), and rtol is only tried where
        rtol cost >= e; when e is too large for every rtol, the exact stage (``exact``) decides
        on the exact gain and adds 'certificate_arithmetic' = 'exact' and 'exact_cost'.
    """
    x, y = float(p[0]), float(p[1])
    g = problem.gain_at(x, y) if gain is None else gain
    cost = problem.base_cost - g
    error = problem.gain_error_at(x, y, g)
    test = _range_test if problem.measurement == RANGE else _bearing_test
    mu, residual, rtol = test(problem, x, y, g, cost, error)
    details: dict[str, Any] = {
        'certificate_gap': math.inf if rtol is None else rtol + error / cost,
        'certificate_multiplier': mu, 'certificate_residual': residual}
    name = INTERIOR if mu == 0.0 else BOUNDARY
    if rtol is not None and rtol < math.inf:
        return name, details
    # rtol None: the floating-point cost or scale broke down (the cost far below the rounding
    # of tr(W P W) - gain); only a proof requested in any case goes on, in exact arithmetic
    if exact or (exact is None and mu > 0.0 and rtol is not None):
        return _exact_stage(problem, x, y, g, mu if math.isfinite(mu) else 0.0, details)
    return NONE, details


def _exact_stage(problem: Problem, x: float, y: float, gain: float, mu: float,
                 details: dict[str, Any]) -> tuple[str, dict[str, Any]]:
    """certify's test in exact arithmetic: the exact gain g at p, then S for
    lambda >= g + rtol cost (a dyadic rational within 2^-40 rtol cost above it), for each rtol of
    GAP_RTOLS. On success, details gain the proved gap and 'exact_cost', the exact cost at
    p rounded to a float (the floating-point formula may be far off where the proof needed
    this stage)."""
    # in integer ratios, not Fractions: reducing these big integers costs more than the rest
    gn, gd = exact_gain_ratio(problem, x, y)
    cn, cd = _exact_cost_ratio(problem, (gn, gd))
    if cn <= 0:
        return NONE, details
    if gn / gd != gain:             # the multiplier belongs to the exact gain
        test = _range_test if problem.measurement == RANGE else _bearing_test
        mu = test(problem, x, y, gn / gd, cn / cd, math.inf)[0]
        mu = mu if math.isfinite(mu) else 0.0      # bearing decides exactly when it fails
    for rtol in GAP_RTOLS:
        rn, rd = rtol.as_integer_ratio()
        # target g + rtol cost, and k with 2^-k <= rtol cost 2^-40 (a positive n / d is at
        # least 2^(bits(n) - bits(d) - 1))
        tn, td = gn * rd * cd + rn * cn * gd, gd * rd * cd
        k = max(0, (rd * cd).bit_length() + 40 - (rn * cn).bit_length() + 1)
        ceiling = -((-tn << k) // td)
        bound = Fraction(ceiling, 1 << k)
        S = exact_bound_matrix(problem, bound, mu if problem.measurement != RANGE else 0.0)[0]
        multiplier: Fraction | None
        if problem.measurement == RANGE:
            multiplier = _best_range_multiplier(S, exact_bound_matrix(problem, bound, 1.0)[0])
        elif integer_positive_definite(S):
            multiplier = Fraction(mu)
        else:                   # the float multiplier may be off: decide exactly
            multiplier = _best_bearing_multiplier(exact_bound_matrix(problem, bound, 0.0)[0],
                                                  exact_bound_matrix(problem, bound, 1.0)[0])
        if multiplier is not None:
            mu = float(multiplier)
            # (bound - g) / cost; an int / int quotient is correctly rounded
            gap = (ceiling * gd - (gn << k)) * cd / ((gd << k) * cn)
            details.update(certificate_gap=math.nextafter(gap, math.inf),
                           certificate_multiplier=mu, certificate_arithmetic='exact',
                           exact_cost=cn / cd)
            return (INTERIOR if multiplier == 0 else BOUNDARY), details
    return NONE, details


def _best_range_multiplier(S: Sequence[int], S_plus_G: Sequence[int]) -> Fraction | None:
    """For a range problem's exact S (mu = 0) and S + G (mu = 1) of :func:`exact_bound_matrix`
    (the same scaling), the mu >= 0 that makes the 2x2 block of S + mu G positive definite, or
    None when none does. det(S + mu G) is a quadratic in mu, concave because det G < 0 (G has
    the eigenvalues 1 - r^2/|p_o|^2 and -r^2/|p_o|^2), so its maximiser
    mu* = -(S00 G11 + S11 G00 - 2 S01 G01) / (2 det G), clipped at 0, decides."""
    s00, s01, _, s11, _, _ = S
    g00, g01, g11 = S_plus_G[0] - s00, S_plus_G[1] - s01, S_plus_G[3] - s11
    det_g = g00 * g11 - g01 * g01
    numerator = -(s00 * g11 + s11 * g00 - 2 * s01 * g01)
    # mu = numerator / (2 det_g) as a / b with b > 0, or 0
    a, b = (-numerator, -2 * det_g) if det_g < 0 and numerator < 0 else (0, 1)
    t00, t01, t11 = b * s00 + a * g00, b * s01 + a * g01, b * s11 + a * g11
    return Fraction(a, b) if t00 > 0 and t00 * t11 > t01 * t01 else None


def _best_bearing_multiplier(S: Sequence[int], S_plus_G: Sequence[int]) -> Fraction | None:
    """For a bearing problem's exact S (mu = 0) and S + G (mu = 1) of :func:`exact_bound_matrix`
    (the same scaling), a mu >= 0 that makes S + mu G positive definite, or None when none
    does: a complete decision, as :func:`_best_range_multiplier` is for range.

    With D = (S + G) - S, det(S + mu D) = c3 mu^3 + c2 mu^2 + c1 mu + c0 (c0 = det S,
    c1 = tr(adj(S) D), c2 = tr(S adj(D)), c3 = det D). G has two positive eigenvalues and one
    negative (det G = -rho^2), so the set of mu where S + mu D is positive definite is an open
    interval, bounded above, or empty; at its ends det = 0, so an interval that lies in mu > 0
    holds a root of the derivative 3 c3 mu^2 + 2 c2 mu + c1, and one that reaches below 0
    holds mu = 0. The candidates are therefore 0 and the two critical points of the cubic,
    rational approximations with 2^-k relative error for k of MULTIPLIER_BITS (finer ones
    only when coarser ones fail: an interval narrower than the distance between the critical
    points times 2^-k would slip through the coarser ones); each is tested exactly.
    Where S cancels (P ill-conditioned, the cost far below tr(W P W)) the multiplier from
    floating point can miss the interval by far more than its width."""
    D = tuple(t1 - t0 for t0, t1 in zip(S, S_plus_G))
    if integer_positive_definite(S):
        return Fraction(0)
    c1, c2, c3 = _trace_product(_adjugate(S), D), _trace_product(S, _adjugate(D)), _det(D)
    candidates: list[tuple[int, int]] = []              # (numerator, denominator > 0)
    if c3 == 0:
        if c2 != 0:
            candidates.append((-c1, 2 * c2) if c2 > 0 else (c1, -2 * c2))
    elif c2 * c2 - 3 * c3 * c1 >= 0:
        discriminant = c2 * c2 - 3 * c3 * c1
        sign = 1 if c3 > 0 else -1
        for k in MULTIPLIER_BITS:
            root = math.isqrt(discriminant << (2 * k))
            candidates += [(sign * ((-c2 << k) + root), sign * 3 * c3 << k),
                           (sign * ((-c2 << k) - root), sign * 3 * c3 << k)]
    for a, b in candidates:
        if a > 0 and integer_positive_definite([b * t + a * d for t, d in zip(S, D)]):
            return Fraction(a, b)
    return None


def _det(T: Sequence[int]) -> int:
    """Determinant of the symmetric 3x3 matrix with entries (00, 01, 02, 11, 12, 22)."""
    t00, t01, t02, t11, t12, t22 = T
    return (t00 * (t11 * t22 - t12 * t12) - t01 * (t01 * t22 - t12 * t02)
            + t02 * (t01 * t12 - t11 * t02))


def _adjugate(T: Sequence[int]) -> tuple[int, int, int, int, int, int]:
    """Adjugate (transposed cofactors) of a symmetric 3x3 matrix, entries (00, 01, 02, 11, 12,
    22): symmetric too."""
    t00, t01, t02, t11, t12, t22 = T
    return (t11 * t22 - t12 * t12, t02 * t12 - t01 * t22, t01 * t12 - t02 * t11,
            t00 * t22 - t02 * t02, t01 * t02 - t00 * t12, t00 * t11 - t01 * t01)


def _trace_product(X: Sequence[int], Y: Sequence[int]) -> int:
    """tr(X Y) for symmetric 3x3 matrices given by entries (00, 01, 02, 11, 12, 22)."""
    return (X[0] * Y[0] + X[3] * Y[3] + X[5] * Y[5]
            + 2 * (X[1] * Y[1] + X[2] * Y[2] + X[4] * Y[4]))


def _times(X: Sequence[int], h: Sequence[int]) -> tuple[int, int, int]:
    """X h for the symmetric 3x3 X of entries (00, 01, 02, 11, 12, 22)."""
    x00, x01, x02, x11, x12, x22 = X
    return (x00 * h[0] + x01 * h[1] + x02 * h[2], x01 * h[0] + x11 * h[1] + x12 * h[2],
            x02 * h[0] + x12 * h[1] + x22 * h[2])


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


def exact_bound_matrix(problem: Problem, bound: float | Fraction,
                       mu: float) -> tuple[tuple[int, int, int, int, int, int], int]:
    """S = bound B - A + mu G (module docstring) in exact integer arithmetic on the exact data,
    up to a positive congruence: (T, E), T the six entries of an integer matrix with
    T = c K S K for a constant c > 0 and a positive diagonal K, so T is positive definite
    exactly when S is.

    Every double is an integer times a power of two: with 2^-E the finest unit of the inputs
    (P, p_o, r, sigma, bound, mu; bound may also be a dyadic Fraction), each input x is X 2^-E
    for an integer X, and a product of k inputs is an integer times 2^-kE (its degree k); a
    term of lower degree is shifted up to the degree of its entry. G's divisions are cleared
    by the congruence. Bearing: c = 2^4E, K = diag(1, 1, m 2^2E) with m = |p_o|^2 - r^2 (G's
    third column times m is (-y_o, x_o, 1), and m^2 G22 = m). Range: the leading 2x2 block
    times c = |p_o|^2 2^6E, and T22 = bound (the third row and column of S are bound e3, so
    only bound > 0 matters).
    """
    (p00, p01, p02, p11, p12, p22, x_o, y_o, r, sigma, lam, nu), E = _scaled_integers(
        (*problem.entries, *problem.slot, float(problem.r), float(problem.sigma), bound,
         float(mu)))

    def up(value: int, degrees: int) -> int:
        """value times 2^(degrees E): a term raised by ``degrees`` to the entry's degree."""
        return value << (degrees * E)

    w22 = x_o * x_o + y_o * y_o                                       # degree 2
    R = sigma * sigma                                                 # degree 2
    m00, m01, m02, m11, m12, m22 = _exact_weighted_square(p00, p01, p02, p11, p12, p22, w22, E)
    if problem.measurement == RANGE:                                   # S |p_o|^2, degree 6
        return ((up(lam * (up(p00, 1) + R), 1) - m00) * w22 + up(nu * (y_o * y_o - r * r), 3),
                up(lam * p01, 2) * w22 - m01 * w22 - up(nu * x_o * y_o, 3), 0,
                (up(lam * (up(p11, 1) + R), 1) - m11) * w22 + up(nu * (x_o * x_o - r * r), 3),
                0, lam), E
    m = w22 - r * r                                                   # degree 2
    return (up(lam * p00, 2) - m00 + up(nu, 3),
            up(lam * p01, 2) - m01,
            (up(lam * p02, 2) - m02) * m - up(nu * y_o, 4),
            up(lam * p11, 2) - m11 + up(nu, 3),
            (up(lam * p12, 2) - m12) * m + up(nu * x_o, 4),
            (up(lam * (up(p22, 1) + R), 1) - m22) * m * m + up(nu * m, 5)), E


def _scaled_integers(values: Sequence[float | Fraction]) -> tuple[list[int], int]:
    """(X, E): each value (a float or a dyadic Fraction) equals X[k] 2^-E, with 2^-E the
    finest unit among them."""
    ratios = [v.as_integer_ratio() for v in values]
    E = max(d.bit_length() for _, d in ratios) - 1
    return [n << (E - d.bit_length() + 1) for n, d in ratios], E


def _exact_weighted_square(p00: int, p01: int, p02: int, p11: int, p12: int, p22: int,
                           w22: int, E: int) -> tuple[int, int, int, int, int, int]:
    """The six entries of M = P W^2 P (degree 4) from P's (degree 1) and |p_o|^2 (degree 2),
    in the integer units of :func:`_scaled_integers`."""
    return ((p00 * p00 + p01 * p01 << 2 * E) + w22 * p02 * p02,
            (p00 * p01 + p01 * p11 << 2 * E) + w22 * p02 * p12,
            (p00 * p02 + p01 * p12 << 2 * E) + w22 * p02 * p22,
            (p01 * p01 + p11 * p11 << 2 * E) + w22 * p12 * p12,
            (p01 * p02 + p11 * p12 << 2 * E) + w22 * p12 * p22,
            (p02 * p02 + p12 * p12 << 2 * E) + w22 * p22 * p22)


def _quadratic_form(X: Sequence[int], h: Sequence[int]) -> int:
    """h'Xh for the symmetric 3x3 X of entries (00, 01, 02, 11, 12, 22)."""
    x00, x01, x02, x11, x12, x22 = X
    h0, h1, h2 = h
    return (x00 * h0 * h0 + x11 * h1 * h1 + x22 * h2 * h2
            + 2 * (x01 * h0 * h1 + x02 * h0 * h2 + x12 * h1 * h2))


#: A rational number as (numerator, denominator > 0), not reduced: reducing the exact stage's
#: big integers would cost more than the arithmetic done with them.
Ratio = tuple[int, int]


def _exact_forms(problem: Problem, *points: float) -> tuple[
        tuple[int, int, int, int, int, int], list[int], int, list[int], int]:
    """(M = P W^2 P (degree 4), P's entries (degree 2), R = sigma^2 (degree 2), ``points`` as
    integers (degree 1), E) in the integer units of :func:`_scaled_integers`: N is P plus R
    where the sensor puts it. The data's integers are computed once per problem, at their own
    finest unit, and shifted up to E when a point has a finer one (a term of degree k by k
    times the difference)."""
    data = problem.__dict__.get('_exact_data')
    if data is None:
        (p00, p01, p02, p11, p12, p22, x_o, y_o, sigma), E = _scaled_integers(
            (*problem.entries, *problem.slot, float(problem.sigma)))
        data = (_exact_weighted_square(p00, p01, p02, p11, p12, p22, x_o * x_o + y_o * y_o, E),
                [p << E for p in (p00, p01, p02, p11, p12, p22)], sigma * sigma, E)
        problem.__dict__['_exact_data'] = data      # a cache, as lazy_property keeps its own
    M, N, R, E_data = data
    ratios = [v.as_integer_ratio() for v in points]
    E = max(E_data, *(d.bit_length() - 1 for _, d in ratios))
    shift = E - E_data
    if shift:
        M = tuple(m << 4 * shift for m in M)
        N, R = [n << 2 * shift for n in N], R << 2 * shift
    return M, list(N), R, [n << (E - d.bit_length() + 1) for n, d in ratios], E


def exact_gain_ratio(problem: Problem, x: float, y: float) -> Ratio:
    """The gain at the floats (x, y) (m) in exact rational arithmetic on the exact data (m^2):
    h'Mh / h'Nh for the homogeneous h of the module docstring, h = [x, y, 0] with
    N = P + R diag(1, 1, 0) (range), h = [-y, x, -(x^2 + y^2)] with N = P + R e3 e3'
    (bearing); integers of :func:`_exact_forms` (degrees: M 4, N 2, h 1 or 2)."""
    M, N, R, (X, Y), E = _exact_forms(problem, x, y)
    if problem.measurement == RANGE:
        N[0], N[3], h = N[0] + R, N[3] + R, (X, Y, 0)
    else:
        N[5], h = N[5] + R, (-Y << E, X << E, -(X * X + Y * Y))
    return _quadratic_form(M, h), _quadratic_form(N, h) << 2 * E


def exact_quotient_newton_step(problem: Problem, q0: float, q1: float) -> tuple[float, float]:
    """For a bearing problem, Newton's step (1/m) towards the stationary point of the gain
    h'Mh / h'Nh over h = [q0, q1, -1], from exact residuals: with Z = M - g N at the exact
    gain g, solve Z[:2, :2] delta = -(Z h)[:2] (the Hessian's leading term; the residual
    Z h vanishes at the top generalised eigenvector). Z and Z h are exact integers, rounded
    to floats only after the cancellation; the 2x2 system is solved in floating point.
    Returns (0, 0) where the system is singular."""
    M, N, R, (Q0, Q1), E = _exact_forms(problem, q0, q1)
    N[5] += R
    h = (Q0, Q1, -(1 << E))
    n, d = _quadratic_form(M, h), _quadratic_form(N, h)
    Z = [d * m - n * k for m, k in zip(M, N)]          # 2^8E d (M - g N), d > 0
    z0, z1, _ = _times(Z, h)
    shift = max(abs(v).bit_length() for v in (*Z, z0, z1)) - 512
    a, b, c, u, v = (value / (1 << shift) if shift > 0 else float(value)
                     for value in (Z[0], Z[1], Z[3], z0, z1))
    det = a * c - b * b
    if not (det != 0.0 and math.isfinite(det)):
        return 0.0, 0.0
    # delta in h's integer units 2^-E
    return (math.ldexp((-u * c + v * b) / det, -E), math.ldexp((-v * a + u * b) / det, -E))


def exact_gain(problem: Problem, x: float, y: float) -> Fraction:
    """:func:`exact_gain_ratio` as a Fraction (m^2)."""
    return Fraction(*exact_gain_ratio(problem, x, y))


def exact_cost(problem: Problem, x: float, y: float) -> float:
    """tr(W P_post W) at (x, y) (m) in exact arithmetic, rounded to the nearest float (m^2)."""
    cn, cd = _exact_cost_ratio(problem, exact_gain_ratio(problem, x, y))
    return cn / cd                                  # int / int is correctly rounded


def tied_with_best(problem: Problem, points: Sequence[Sequence[float]],
                   gains: Sequence[float]) -> list[int]:
    """Indices of the points (x, y) whose computed gain (from ``problem.gain_at``) is within the
    rounding bounds of the greatest (:meth:`~formopt_ros.core.cost.Problem.gain_error_at`):
    floating point cannot tell them apart."""
    best = max(range(len(gains)), key=gains.__getitem__)
    errors = [problem.gain_error_at(float(x), float(y), g) for (x, y), g in zip(points, gains)]
    # (not <: a gain of -inf with an infinite error bound, nan, is close)
    return [k for k, g in enumerate(gains) if not g + errors[k] < gains[best] - errors[best]]


def best_of(problem: Problem, points: Sequence[Sequence[float]], gains: Sequence[float]) -> int:
    """Index of the point (x, y) of greatest exact gain among those :func:`tied_with_best`:
    the rounding of the gain formula may exceed the difference of near ties."""
    close = tied_with_best(problem, points, gains)
    if len(close) == 1:
        return close[0]
    return max(close, key=lambda k: exact_gain(problem, float(points[k][0]),
                                               float(points[k][1])))


def _exact_base_ratio(problem: Problem) -> Ratio:
    """tr(W P W) = p00 + p11 + |p_o|^2 p22 in exact rational arithmetic (m^2)."""
    (p00, p11, p22, x_o, y_o), E = _scaled_integers(
        (problem.entries[0], problem.entries[3], problem.entries[5], *problem.slot))
    return (p00 + p11 << 2 * E) + (x_o * x_o + y_o * y_o) * p22, 1 << 3 * E


def _exact_cost_ratio(problem: Problem, gain: Ratio) -> Ratio:
    """tr(W P W) - gain for an exact gain (m^2), as a ratio with a positive denominator."""
    (bn, bd), (gn, gd) = _exact_base_ratio(problem), gain
    return bn * gd - gn * bd, bd * gd


def exact_base_cost(problem: Problem) -> Fraction:
    """:func:`_exact_base_ratio` as a Fraction (m^2)."""
    return Fraction(*_exact_base_ratio(problem))


def integer_positive_definite(T: Sequence[int]) -> bool:
    """True when the symmetric integer matrix with entries (00, 01, 02, 11, 12, 22) is positive
    definite: its leading principal minors are positive (Sylvester), in exact arithmetic."""
    return T[0] > 0 and T[0] * T[3] - T[1] * T[1] > 0 and _det(T) > 0
