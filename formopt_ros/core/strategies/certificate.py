"""Global-optimality certificates for RAM and RQ: a floating-point-checked proof (S-lemma) that
no feasible point beats the chosen one by more than a stated gap.

Both gains are generalised Rayleigh quotients g(h) = h'Ah / h'Bh (B positive definite) of a
homogeneous vector h of the point (see :mod:`formopt_ros.core.cost`), and the feasible set is
{h : h'Gh <= 0} for one quadratic form G:

* bearing: h = [q0, q1, -1], A = P W^2 P, B = P + R e3 e3', and the q-disc
  |q - c|^2 <= rho^2 gives G = [[1, 0, c0], [0, 1, c1], [c0, c1, |c|^2 - rho^2]];
* range: h = p / |p|, A = (P W^2 P)[:2, :2], B = P[:2, :2] + R I, and the bearings under which
  the disc is seen, (u . p_o)^2 >= (|p_o|^2 - r^2) |u|^2, give G = (1 - r^2/|p_o|^2) I - u_o u_o'
  with u_o = p_o / |p_o| (the gain is even in u, so the mirrored cone does no harm).

If ``S = lambda B - A + mu G`` is positive definite for some mu >= 0, then every feasible h has
h'(lambda B - A)h > -mu h'Gh >= 0, i.e. g(h) < lambda. With lambda = g(p) + gap this proves
cost(p) <= optimum + gap. The S-lemma (one quadratic constraint, Slater point p_o) says such a
mu exists whenever p is optimal (up to the gap), and KKT names it: (g(p) B - A + mu G) h = 0, so
mu = -(Gh)'(g B - A)h / |Gh|^2 (clipped at 0; mu = 0 when the top generalised eigenvector is
feasible, mu > 0 when the constraint is active).

The residual test: S is formed in floating point, so the test demands positive definiteness of
every matrix within a rounding bound of the computed S (a shifted LDL' factorisation, after a
Jacobi scaling that makes B's diagonal 1). When cancellation in S defeats that bound (large
entries, a small eigenvalue: ill-conditioned priors, or a gain close to tr(W P W)), the same
test runs again in exact rational arithmetic on the exact data (P, p_o, r, sigma and p are
dyadic rationals), which takes about 0.3 ms. A point that is not optimal fails the test,
however accurate the arithmetic: a better feasible point h makes h'Sh <= mu h'Gh <= 0.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction
from typing import Any

from formopt_ros.core.cost import Entries, Problem, positive_definite_entries
from formopt_ros.core.linalg import EPS
from formopt_ros.core.model import RANGE

#: Certificate names (``Solution.certificate``).
INTERIOR = 'interior-eigenvector'      # proof with mu = 0: the quotient's global maximum
BOUNDARY = 'boundary-bound'            # proof with mu > 0: no feasible point is better
CRITICAL_POINTS = 'all-critical-points'  # every stationary point enumerated and checked
NONE = 'none'
#: Names that stand for a proof checked in floating point.
PROVED = (INTERIOR, BOUNDARY)
#: Relative cost gaps tried, smallest first: cost(p) <= optimum + gap * cost(p).
GAP_RTOLS = (1e-12, 1e-10)
#: Relative rounding error allowed in each entry of the scaled S (generous: a few operations).
ENTRY_ERROR = 16 * EPS


def quotient_system(problem: Problem) -> tuple[Entries, Entries, Entries, float]:
    """(A, B, G, size of G's entries before cancellation) of the module docstring, as the six
    distinct entries of 3x3 matrices; the range case is embedded as the leading 2x2 block
    (third row and column of A and G zero, of B the identity's), which changes nothing."""
    (m00, m01, m02, m11, m12, m22), N = problem.forms
    if problem.measurement == RANGE:
        p00, p01, _, p11, _, _ = problem.entries
        R = problem.R
        x_o, y_o = problem.slot
        ux, uy = x_o / problem.d_o, y_o / problem.d_o
        r_rel = float(problem.r) / problem.d_o
        cos2 = 1.0 - r_rel * r_rel
        return ((m00, m01, 0.0, m11, 0.0, 0.0), (p00 + R, p01, 0.0, p11 + R, 0.0, 1.0),
                (cos2 - ux * ux, -ux * uy, 0.0, cos2 - uy * uy, 0.0, 0.0), 1.0)
    c0, c1, rho = problem.q_circle
    return ((m00, m01, m02, m11, m12, m22), N,
            (1.0, 0.0, c0, 1.0, c1, c0 * c0 + c1 * c1 - rho * rho),
            c0 * c0 + c1 * c1 + rho * rho)


def homogeneous(problem: Problem, x: float, y: float) -> tuple[float, float, float]:
    """The vector h of the point (x, y) m: [q0, q1, -1] (bearing) or [x, y, 0]/|p| (range)."""
    d2 = x * x + y * y
    if problem.measurement == RANGE:
        d = math.sqrt(d2)
        return x / d, y / d, 0.0
    return -y / d2, x / d2, -1.0


def _times(E: Entries, v0: float, v1: float, v2: float) -> tuple[float, float, float]:
    """E v for the symmetric matrix with entries E."""
    return (E[0] * v0 + E[1] * v1 + E[2] * v2, E[1] * v0 + E[3] * v1 + E[4] * v2,
            E[2] * v0 + E[4] * v1 + E[5] * v2)


def certify(problem: Problem, p: Sequence[float], gain: float | None = None,
            exact: bool = True) -> tuple[str, dict[str, Any]]:
    """Try to prove that p (2,) is a global optimum of ``problem`` up to a small gap.

    Args:
        problem: the problem.
        p: the candidate, m, feasible.
        gain: its gain if already known (m^2, from ``problem.gain_at``), else computed.
        exact: when the floating-point test is inconclusive, repeat it in exact arithmetic
            (about 0.3 ms; False for a tentative candidate that a cheaper search may replace).

    Returns:
        (name, details): INTERIOR or BOUNDARY when the proof holds, NONE otherwise; details
        hold 'certificate_gap' (relative cost gap proved, or inf), 'certificate_multiplier'
        (mu) and 'certificate_residual' (|(g B - A + mu G) h| relative to the scale of S).
    """
    x, y = float(p[0]), float(p[1])
    g = problem.gain_at(x, y) if gain is None else gain
    cost = problem.base_cost - g
    (a00, a01, a02, a11, a12, a22), (b00, b01, b02, b11, b12, b22), G, g_size = \
        quotient_system(problem)
    # Jacobi scaling D = diag(B)^-1/2: the entries of D X D are X_ij dd_ij
    d0, d1, d2 = 1.0 / math.sqrt(b00), 1.0 / math.sqrt(b11), 1.0 / math.sqrt(b22)
    dd = (d0 * d0, d0 * d1, d0 * d2, d1 * d1, d1 * d2, d2 * d2)
    A = (a00 * dd[0], a01 * dd[1], a02 * dd[2], a11 * dd[3], a12 * dd[4], a22 * dd[5])
    B = (b00 * dd[0], b01 * dd[1], b02 * dd[2], b11 * dd[3], b12 * dd[4], b22 * dd[5])
    G = (G[0] * dd[0], G[1] * dd[1], G[2] * dd[2], G[3] * dd[3], G[4] * dd[4], G[5] * dd[5])
    h0, h1, h2 = homogeneous(problem, x, y)
    h0, h1, h2 = h0 / d0, h1 / d1, h2 / d2
    S0 = (g * B[0] - A[0], g * B[1] - A[1], g * B[2] - A[2], g * B[3] - A[3],
          g * B[4] - A[4], g * B[5] - A[5])
    v0, v1, v2 = _times(S0, h0, h1, h2)
    w0, w1, w2 = _times(G, h0, h1, h2)
    ww = w0 * w0 + w1 * w1 + w2 * w2
    hh = h0 * h0 + h1 * h1 + h2 * h2
    inside = h0 * w0 + h1 * w1 + h2 * w2 < -1e-9 * hh * math.sqrt(ww)
    # KKT multiplier; 0 inside the disc (the constraint is not active there)
    mu = 0.0 if inside or ww == 0.0 else max(0.0, -(w0 * v0 + w1 * v1 + w2 * v2) / ww)
    scale = (abs(g) * max(map(abs, B)) + max(A[0], A[3], A[5])
             + mu * max(max(map(abs, G)), g_size * max(dd[0], dd[3], dd[5])))
    residual = (math.sqrt((v0 + mu * w0) ** 2 + (v1 + mu * w1) ** 2 + (v2 + mu * w2) ** 2)
                / (scale * math.sqrt(hh)))
    details: dict[str, Any] = {'certificate_gap': math.inf, 'certificate_multiplier': mu,
                               'certificate_residual': residual}
    if not (cost > 0.0 and math.isfinite(scale)):
        return NONE, details
    name = INTERIOR if mu == 0.0 else BOUNDARY
    for rtol in GAP_RTOLS:
        bound = g + rtol * cost
        S = [bound * b - a + mu * c for a, b, c in zip(A, B, G)]
        # every matrix within the rounding bound of S is positive definite (shifted LDL')
        delta = (3.0 * ENTRY_ERROR * (scale + rtol * cost)
                 + 16.0 * EPS * max(abs(S[0]), abs(S[3]), abs(S[5])))
        if positive_definite_entries((S[0] - delta, S[1], S[2], S[3] - delta, S[4],
                                      S[5] - delta)):
            details['certificate_gap'] = rtol
            return name, details
    for rtol in GAP_RTOLS if exact else ():
        if positive_definite_entries(exact_bound_matrix(problem, g + rtol * cost, mu)):
            details.update(certificate_gap=rtol, certificate_arithmetic='exact')
            return name, details
    return NONE, details


def exact_bound_matrix(problem: Problem, bound: float, mu: float) -> Entries:
    """S = bound B - A + mu G (module docstring) in exact rational arithmetic, from the exact
    data: the float inputs are dyadic rationals, |p_o|^2 = x_o^2 + y_o^2 and R = sigma^2."""
    p00, p01, p02, p11, p12, p22 = map(Fraction, problem.entries)
    x_o, y_o = map(Fraction, problem.slot)
    r, R = Fraction(float(problem.r)), Fraction(float(problem.sigma)) ** 2
    w22 = x_o * x_o + y_o * y_o
    lam, nu = Fraction(bound), Fraction(mu)
    m00 = p00 * p00 + p01 * p01 + w22 * p02 * p02
    m01 = p00 * p01 + p01 * p11 + w22 * p02 * p12
    m11 = p01 * p01 + p11 * p11 + w22 * p12 * p12
    if problem.measurement == RANGE:
        cos2 = 1 - r * r / w22
        return (lam * (p00 + R) - m00 + nu * (cos2 - x_o * x_o / w22),
                lam * p01 - m01 - nu * x_o * y_o / w22, Fraction(0),
                lam * (p11 + R) - m11 + nu * (cos2 - y_o * y_o / w22), Fraction(0), lam)
    m02 = p00 * p02 + p01 * p12 + w22 * p02 * p22
    m12 = p01 * p02 + p11 * p12 + w22 * p12 * p22
    m22 = p02 * p02 + p12 * p12 + w22 * p22 * p22
    k = 1 / (w22 - r * r)
    c0, c1, rho = -y_o * k, x_o * k, r * k
    return (lam * p00 - m00 + nu, lam * p01 - m01, lam * p02 - m02 + nu * c0,
            lam * p11 - m11 + nu, lam * p12 - m12 + nu * c1,
            lam * (p22 + R) - m22 + nu * (c0 * c0 + c1 * c1 - rho * rho))
