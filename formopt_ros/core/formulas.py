"""The cost of paper Sec. III-D entry by entry, for floats and arrays alike.

    cost(p) = tr(W P W) - gain(p),   gain(p) = h P W^2 P h' / (h P h' + R),   W = diag(1, 1, |p_o|)

with ``h`` the measurement Jacobian at the candidate position ``p`` (eq. 16 or 18) and
``R = sigma^2``. Both kinds reduce to a ratio of quadratic forms in a short monomial vector:

* range:   ``u = p / |p|``, gain = u' A u / (u' B u + R) with A = (P W^2 P)[:2, :2],
  B = P[:2, :2]; monomials ``[c^2, c s, s^2, 1]``.
* bearing: ``h = [q0, q1, -1]`` with ``q = (-y, x) / |p|^2``; gain = h' M h / h' N h with
  M = P W^2 P, N = P + R e3 e3'; monomials ``[q0^2, q0 q1, q1^2, q0, q1, 1]``.

The formulas are written entry by entry so that the same code serves one problem in Python
floats (the per-step fast path) and many at once in numpy arrays, with identical rounding.
"""
from __future__ import annotations

import math
import operator
from typing import Any, TypeVar

import numpy as np

from formopt_ros.core.model import RANGE

#: Float, or numpy array of floats: the entry-wise formulas below accept either.
Value = TypeVar('Value', float, np.ndarray)
#: The six distinct entries (00, 01, 02, 11, 12, 22) of a symmetric 3x3 matrix.
Entries = tuple[Any, Any, Any, Any, Any, Any]


def trace_entries(p00: Value, p11: Value, p22: Value, d2: Any) -> Value:
    """tr(W P W) = p00 + p11 + |p_o|^2 p22 from P's diagonal (floats or arrays), m^2."""
    return p00 + p11 + d2 * p22


def weight_vector(p_o: np.ndarray) -> np.ndarray:
    """Diagonal of W = diag(1, 1, |p_o|), shape (3,): heading error weighted by the slot range."""
    return np.array([1.0, 1.0, math.hypot(p_o[0], p_o[1])])


def weighted_trace(P: np.ndarray, p_o: np.ndarray) -> Any:
    """tr(W P W) (m^2), the paper's uncertainty metric (eq. 20): a float for a covariance (3, 3),
    an array (T,) for a batch (T, 3, 3)."""
    d_o = math.hypot(p_o[0], p_o[1])
    if np.ndim(P) == 2:
        return float(trace_entries(float(P[0, 0]), float(P[1, 1]), float(P[2, 2]), d_o * d_o))
    return trace_entries(P[..., 0, 0], P[..., 1, 1], P[..., 2, 2], d_o * d_o)


def quotient_entries(P: Entries, w22: Any, R: Any) -> tuple[Entries, Entries]:
    """Entries of M = P W^2 P and N = P + R e3 e3' from those of P (floats or arrays).

    Args:
        P: (p00, p01, p02, p11, p12, p22) of the prior covariance (m^2, m rad, rad^2).
        w22: |p_o|^2, m^2.
        R: measurement noise variance.
    """
    p00, p01, p02, p11, p12, p22 = P
    M = (p00 * p00 + p01 * p01 + w22 * (p02 * p02),
         p00 * p01 + p01 * p11 + w22 * (p02 * p12),
         p00 * p02 + p01 * p12 + w22 * (p02 * p22),
         p01 * p01 + p11 * p11 + w22 * (p12 * p12),
         p01 * p02 + p11 * p12 + w22 * (p12 * p22),
         p02 * p02 + p12 * p12 + w22 * (p22 * p22))
    return M, (p00, p01, p02, p11, p12, p22 + R)


def gain_coefficients(measurement: str, M: Entries, N: Entries,
                      R: Any) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
    """Coefficients of the gain's numerator and denominator on :func:`monomials`, each followed
    by the coefficient of the constant monomial 1 (floats or arrays)."""
    m00, m01, m02, m11, m12, m22 = M
    n00, n01, n02, n11, n12, n22 = N
    if measurement == RANGE:
        return (m00, 2.0 * m01, m11, 0.0), (n00, 2.0 * n01, n11, R)
    return ((m00, 2.0 * m01, m11, -2.0 * m02, -2.0 * m12, m22),
            (n00, 2.0 * n01, n11, -2.0 * n02, -2.0 * n12, n22))


def monomials(measurement: str, x: Any, y: Any) -> tuple[Any, ...]:
    """Monomials of the gain's quadratic forms at points (x, y) in {L} (m), floats or arrays."""
    d2 = x * x + y * y
    if measurement == RANGE:
        return x * x / d2, x * y / d2, y * y / d2
    q0, q1 = -y / d2, x / d2
    return q0 * q0, q0 * q1, q1 * q1, q0, q1


def weighted_sum(coefficients: tuple[Any, ...], terms: tuple[Any, ...], constant: Any) -> Any:
    """constant + sum_k coefficients[k] terms[k], summed left to right (floats or arrays)."""
    return sum(map(operator.mul, coefficients, terms), constant)


def quotient_gain(measurement: str, coefficients: tuple[tuple[Any, ...], tuple[Any, ...]],
                  x: Any, y: Any) -> Any:
    """The gain at points (x, y) in {L} (m): the ratio of the two weighted sums of monomials.

    The coefficients broadcast against the points (floats, or e.g. arrays (T, 1) against
    points (T, C) for a batch), and the arithmetic is the same element by element; any type
    with + - * / works (CasADi symbols build the peers' objective from this formula).
    """
    num, den = coefficients
    # the sums of weighted_sum, written out (twice as fast on floats, the same rounding)
    if measurement == RANGE:
        t0, t1, t2 = monomials(measurement, x, y)
        return ((num[3] + num[0] * t0 + num[1] * t1 + num[2] * t2)
                / (den[3] + den[0] * t0 + den[1] * t1 + den[2] * t2))
    t0, t1, t2, t3, t4 = monomials(measurement, x, y)
    return ((num[5] + num[0] * t0 + num[1] * t1 + num[2] * t2 + num[3] * t3 + num[4] * t4)
            / (den[5] + den[0] * t0 + den[1] * t1 + den[2] * t2 + den[3] * t3 + den[4] * t4))


#: Rounding of :func:`quotient_gain`'s numerator and denominator, relative to the same sums
#: taken over the magnitudes of every term: a term of the bearing numerator passes through at
#: most 20 roundings of u = 2^-53 (|p_o|^2 3, an entry of M 7 with its sum, a monomial 7, the
#: product 1, the sum of six terms 5; range: 15), so gamma_20 = 20u / (1 - 20u) < 24u bounds it.
GAIN_ROUNDING_UNITS = 24 * 2.0 ** -53


def gain_rounding(measurement: str, coefficients: tuple[tuple[Any, ...], tuple[Any, ...]],
                  x: Any, y: Any) -> tuple[Any, Any, Any, Any]:
    """(n, d, e_n, e_d): the numerator and denominator of :func:`quotient_gain` at points
    (x, y) (m, floats or arrays) and bounds on their rounding (see
    :meth:`Problem.gain_error_at`)."""
    num, den = coefficients
    terms = monomials(measurement, x, y)
    n, d = weighted_sum(num, terms, num[-1]), weighted_sum(den, terms, den[-1])
    # x_ii h_i^2: a diagonal coefficient (>= 0) times a squared monomial
    if measurement == RANGE:
        t0, _, t2 = terms
        n_abs = 2.0 * (num[0] * t0 + num[2] * t2)
        d_abs = 2.0 * (den[0] * t0 + den[2] * t2) + den[3]
    else:
        t0, _, t2, _, _ = terms
        n_abs = 3.0 * (num[0] * t0 + num[2] * t2 + num[5])
        d_abs = 3.0 * (den[0] * t0 + den[2] * t2 + den[5])
    return n, d, GAIN_ROUNDING_UNITS * n_abs, GAIN_ROUNDING_UNITS * d_abs


def point_from_q(q: np.ndarray) -> np.ndarray:
    """Inverse of p -> q = (-y, x)/|p|^2: p = (q1, -q0)/|q|^2, for q of shape (..., 2)."""
    q = np.asarray(q, dtype=float)
    n2 = np.sum(q * q, axis=-1, keepdims=True)
    return np.stack([q[..., 1], -q[..., 0]], axis=-1) / n2
