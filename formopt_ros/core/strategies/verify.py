"""Verification in exact arithmetic: the certificate's exact stage, exact gains and costs, and
the exact local search. Called only where the floating-point certificate
(:mod:`~formopt_ros.core.strategies.certificate`) cannot decide, and by tests and
``formopt-bench``.

:func:`certify` runs the floating-point test and, where cancellation in S defeats its rounding
bound (large entries, a small eigenvalue: ill-conditioned priors, or a gain close to
tr(W P W)), the same test again in exact arithmetic on the exact data (P, p_o, r, sigma and p
are dyadic rationals, so integers after one common scaling: :func:`exact_bound_matrix`), which
takes about 10 us; so it does where the rounding bound of the gain exceeds every rtol cost
(the gain formula cancels), with lambda just above the exact gain (:func:`exact_gain`) and the
exact cost reported. There the multiplier is decided exactly: for range the maximiser of the
concave det(S + mu G) (:func:`_best_range_multiplier`); for bearing, when the floating-point
multiplier fails, 0 or a critical point of the cubic det(S + mu G)
(:func:`_best_bearing_multiplier`), which finds a mu whenever one exists: where S cancels, the
float one can be off by more than the proof's margin.

Where no proof holds and the candidates' computed gains tie within their rounding, the best is
chosen on exact gains and an exact local search (:func:`refine_exactly`) looks for a better
point (:func:`settle_unproved`).

Where the floating-point certificate decides on its own: never where the gain's rounding
bound exceeds GAP_RTOLS[-1] (1e-10) of the cost; below that, unless cancellation in S defeats
its bound. Measured by ``scripts/measure_exact_share.py`` (docs/certification.md): in the
paper's scenarios the exact stage runs for none of RQ's range certificates and 1.4 % of its
bearing ones; in the adversarial families of the certification tests for 1-9 % of the
problems whose bound is below 1e-15 of the cost and 14-34 % from 1e-14 to 1e-11.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.model import RANGE
from formopt_ros.core.strategies.certificate import (
    BOUNDARY, CRITICAL_POINTS, GAP_RTOLS, INTERIOR, NONE, PROVED, float_test)

#: Boundary samples, equally spaced in the angle around p_o, that an answer without a proof is
#: held against (with the slot; bearing: as many again, equally spaced on the q-circle): when
#: rounding loses a critical point (condition numbers of P beyond ~1e16), a sample or the slot
#: beats every critical point found, and shows it.
CHECK_SAMPLES = 360

#: Bits of the rational approximations of the exact bearing multiplier's candidates, coarse
#: to fine (:func:`_best_bearing_multiplier`).
MULTIPLIER_BITS = (64, 256, 1024)


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
    test = float_test(problem)
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
        test = float_test(problem)
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


def exact_forms(problem: Problem, *points: float) -> tuple[
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
    (bearing); integers of :func:`exact_forms` (degrees: M 4, N 2, h 1 or 2)."""
    M, N, R, (X, Y), E = exact_forms(problem, x, y)
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
    M, N, R, (Q0, Q1), E = exact_forms(problem, q0, q1)
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


#: Relative cost (exact arithmetic) by which a sample, the slot or a Newton point may beat the
#: best critical point before the enumeration counts as having lost one.
EXACT_TIE = 1e-9


#: The exact local search (:func:`refine_exactly`): first step (as a fraction of r, and rad),
#: the step at which it stops, and the most exact gains it evaluates (about 10 us each) from
#: the answer (a quarter of that from each other start).
REFINE_FIRST_STEP = 1e-3


REFINE_LAST_STEP = 1e-15


REFINE_EVALUATIONS = 600


#: Exact gains at most per round of the compass search before Newton's method tries again.
REFINE_ROUND = 100


#: ``details['reason']`` of an answer the exact search improved on but could not prove.
REFINED_REASON = ('rounding spoilt the critical points: the point is the best an exact local '
                  'search found from them, not proved optimal')


#: Local maxima of each ring of boundary samples from which the exact search starts too (the
#: gain has at most three along the boundary, and so has a ring of its exact values).
RING_PEAKS = 3


#: Newton steps at most that the exact search tries first on a bearing problem.
REFINE_NEWTON_STEPS = 8


def ring_peaks(problem: Problem, samples: np.ndarray,
               gains: np.ndarray) -> list[tuple[float, float]]:
    """The samples (x, y) (m) of each ring of :func:`check_points` (its first rows; ``gains``:
    their computed gains, ``problem.gain(samples)``) whose exact
    gain beats both neighbours on the ring: the boundary's local maxima (at most three: the
    boundary's stationarity polynomial has degree 6), each a start for :func:`refine_exactly`
    in its own basin. Neighbours are compared on computed gains where their rounding bounds
    part them, else on exact gains.

    A basin can be far narrower than the samples' spacing and hold the optimum while its
    nearest sample is worse than another basin's best (a reviewer's bearing problem with
    variances 1e-28 to 1e10, the disc 2.5e-6 m from the leader: the optimum's basin on the
    boundary is 1e-5 rad wide; the answer, 2.7e-9 above it, lay in another)."""
    peaks: list[tuple[float, float]] = []
    for first in range(0, CHECK_SAMPLES * (1 if problem.measurement == RANGE else 2),
                       CHECK_SAMPLES):
        ring = samples[first:first + CHECK_SAMPLES].tolist()
        values = gains[first:first + CHECK_SAMPLES].tolist()
        errors = [problem.gain_error_at(x, y, g) for (x, y), g in zip(ring, values)]
        exact: dict[int, Ratio] = {}

        def beats(k: int, j: int) -> bool:
            """Sample k's exact gain exceeds sample j's."""
            if values[k] - errors[k] > values[j] + errors[j]:
                return True
            if values[k] + errors[k] < values[j] - errors[j]:
                return False
            for i in (k, j):
                if i not in exact:
                    exact[i] = exact_gain_ratio(problem, *ring[i])
            return exact[k][0] * exact[j][1] > exact[j][0] * exact[k][1]
        better = [beats(k, k - 1) for k in range(CHECK_SAMPLES)]      # k beats k - 1
        tops = [k for k in range(CHECK_SAMPLES)
                if better[k] and not better[(k + 1) % CHECK_SAMPLES]]
        tops.sort(key=values.__getitem__, reverse=True)
        peaks += [(ring[k][0], ring[k][1]) for k in tops[:RING_PEAKS]]
    return peaks


def exact_best(problem: Problem, critical: np.ndarray, gains: np.ndarray, others: np.ndarray,
               other_gains: np.ndarray) -> tuple[int, bool]:
    """(index into critical + others of the best point by exact gain among those whose computed
    gains tie within their rounding bounds, whether the best critical point is as good as it
    to EXACT_TIE of its cost): an 'all-critical-points' answer is the best critical point, and
    no sample, the slot or a Newton point beats it beyond that."""
    candidates = np.vstack([critical, others]).tolist()
    candidate_gains = [*(gains.tolist() if len(critical) else []), *other_gains.tolist()]
    chosen = best_of(problem, candidates, candidate_gains)
    if chosen < len(critical) or not len(critical):
        return chosen, bool(len(critical))
    top = best_of(problem, critical.tolist(), gains.tolist())
    g_critical = exact_gain(problem, *candidates[top])
    g_best = exact_gain(problem, *candidates[chosen])
    if g_best - g_critical <= Fraction(EXACT_TIE) * (exact_base_cost(problem) - g_critical):
        return top, True
    return chosen, False


#: The exact search's moves (d rho, d phi): the eight compass directions, and along the circle.
_COMPASS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))


_ALONG_BOUNDARY = ((0, 1), (0, -1))


def refine_exactly(problem: Problem, p: Sequence[float],
                   budget: int = REFINE_EVALUATIONS) -> tuple[tuple[float, float], Ratio]:
    """A compass search for a better point than p (2,) on exact gains: ((x, y) m, its exact
    gain as a :data:`~.certificate.Ratio`), p itself when it finds none.

    Where rounding swamps the cost (P ill-conditioned, the posterior cost 1e-8 to 1e-15 of
    tr(W P W)), the floating-point critical points can miss the optimum by 1e-9 to 1e-5 of
    the cost while their gains no longer tell them apart. The search works in the plane where
    the gain is a quotient of quadratic forms: p for range, q = (-y, x) / |p|^2 for bearing
    (where the disc is the q-disc), with the point as centre + rho (cos phi, sin phi), rho up
    to the disc's radius. It moves along the eight compass directions of (rho, phi) with
    steps from REFINE_FIRST_STEP (of the radius, and rad) halved down to REFINE_LAST_STEP,
    comparing exact gains (:func:`~.certificate.exact_gain_ratio`, by cross-multiplying), at
    most ``budget`` of them; on the boundary the phi moves follow the circle, and a start on
    the boundary moves along it first (a reviewer's problem: the boundary's basin narrower than
    the first step, the search went inwards and stopped 3.2e-8 above the optimum). Points that
    rounding puts outside the disc's tolerance (``Problem.feasible``) are passed over. For
    bearing, Newton steps on exact residuals come first (:func:`exact_quotient_newton_step`);
    the search runs in rounds of Newton steps and at most REFINE_ROUND compass evaluations
    while a round gains: on a narrow curved ridge the compass search crawls, and Newton's
    method from where it stopped reaches an interior optimum (a reviewer's problem: 2.3e-7
    above the optimum after 600 evaluations without rounds).
    """
    x, y = float(p[0]), float(p[1])
    if problem.measurement == RANGE:
        (c0, c1), radius, u, v = problem.slot, float(problem.r), x, y
    else:
        c0, c1, radius = problem.q_circle
        n2 = x * x + y * y
        u, v = -y / n2, x / n2

    def to_p(u: float, v: float) -> tuple[float, float]:
        """The point (m) of search coordinates (u, v): p itself (range) or q (bearing)."""
        if problem.measurement == RANGE:
            return u, v
        n2 = u * u + v * v
        return v / n2, -u / n2

    def point(rho: float, phi: float) -> tuple[float, float]:
        return to_p(c0 + rho * math.cos(phi), c1 + rho * math.sin(phi))

    best = exact_gain_ratio(problem, x, y)
    evaluations = 0
    improved = True
    while improved and evaluations < budget:
        before = best
        if problem.measurement != RANGE:
            # an interior optimum first: Newton steps on exact residuals, kept while they gain
            for _ in range(REFINE_NEWTON_STEPS):
                du, dv = exact_quotient_newton_step(problem, u, v)
                u_new, v_new = u + du, v + dv
                if not math.hypot(u_new - c0, v_new - c1) <= radius:
                    break
                x_new, y_new = to_p(u_new, v_new)
                if not problem.feasible((x_new, y_new)):
                    break
                gain = exact_gain_ratio(problem, x_new, y_new)
                evaluations += 1
                if not gain[0] * best[1] > best[0] * gain[1]:
                    break
                u, v, x, y, best = u_new, v_new, x_new, y_new, gain
        rho, phi = min(math.hypot(u - c0, v - c1), radius), math.atan2(v - c1, u - c0)
        # from a point on the boundary, along the boundary first: where the boundary's basin is
        # narrower than the first step, a step inwards would win and leave it for good
        for moves in ((_ALONG_BOUNDARY, _COMPASS) if rho == radius else (_COMPASS,)):
            step, round_end = REFINE_FIRST_STEP, min(budget, evaluations + REFINE_ROUND)
            while step >= REFINE_LAST_STEP and evaluations < round_end:
                moved = False
                for d_rho, d_phi in moves:
                    rho_new = min(max(rho + d_rho * step * radius, 0.0), radius)
                    phi_new = phi + d_phi * step
                    if rho_new == rho and phi_new == phi:
                        continue
                    x_new, y_new = point(rho_new, phi_new)
                    if not problem.feasible((x_new, y_new)):      # rounding, on a tiny disc
                        continue
                    gain = exact_gain_ratio(problem, x_new, y_new)
                    evaluations += 1
                    if gain[0] * best[1] > best[0] * gain[1]:
                        rho, phi, x, y, best = rho_new, phi_new, x_new, y_new, gain
                        moved = True
                        break
                if not moved:
                    step *= 0.5
        # where the compass search stalls on a narrow ridge, Newton may go on from its end
        u, v = c0 + rho * math.cos(phi), c1 + rho * math.sin(phi)
        improved = best[0] * before[1] > before[0] * best[1]
    return (x, y), best


def settle_unproved(problem: Problem, critical: np.ndarray, gains: np.ndarray,
                    others: np.ndarray, other_gains: np.ndarray, p: np.ndarray,
                    details: dict[str, Any]) -> tuple[int, bool, np.ndarray, str, dict[str, Any]]:
    """For an answer p (2,) that :func:`certify` did not prove: the exact best of the candidates
    (:func:`exact_best`), certified afresh if it is another point; if that is no proof either,
    the best point :func:`refine_exactly` reaches from it and from the critical points whose
    gains tie with the best (``details['refined']``), certified in exact arithmetic when it is
    better. The exact cost is in details.

    Returns:
        (index into critical + others, whether it is the best critical point, the point, its
        certificate: a proof, else 'all-critical-points' or 'none', details).
    """
    index, enumerated = exact_best(problem, critical, gains, others, other_gains)
    chosen = critical[index] if enumerated else others[index - len(critical)]
    name = NONE
    if not np.array_equal(chosen, p):
        p = chosen
        name, details = certify(problem, (float(p[0]), float(p[1])))
    if name not in PROVED:
        # rounding may have spoilt the critical points themselves: search on exact gains from
        # p and from every critical point that ties with the best (another basin may hold the
        # optimum while its critical point, misplaced by rounding, looks worse)
        starts = [(float(p[0]), float(p[1]))]
        if len(critical):
            tied = tied_with_best(problem, np.vstack([critical, others]).tolist(),
                                  [*gains.tolist(), *other_gains.tolist()])
            starts += [(float(critical[k][0]), float(critical[k][1])) for k in tied
                       if k < len(critical) and not np.array_equal(critical[k], p)]
        if problem.measurement != RANGE:        # range: one basin per half-turn of bearing
            starts += [q for q in ring_peaks(problem, others, other_gains) if q not in starts]
        best: tuple[tuple[float, float], Ratio] | None = None
        for count, start in enumerate(starts):
            refined, gain = refine_exactly(problem, start, REFINE_EVALUATIONS if count == 0
                                           else REFINE_EVALUATIONS // 4)
            if best is None or gain[0] * best[1][1] > best[1][0] * gain[1]:
                best = refined, gain
        if best is not None and best[0] != starts[0]:    # a strictly better point
            p, enumerated = np.array(best[0]), False
            name, details = certify(problem, best[0])
            details['refined'] = True
            if name not in PROVED:
                details['reason'] = REFINED_REASON
    details.setdefault('exact_cost', exact_cost(problem, float(p[0]), float(p[1])))
    if name not in PROVED:
        name = CRITICAL_POINTS if enumerated else NONE
    return index, enumerated, p, name, details
