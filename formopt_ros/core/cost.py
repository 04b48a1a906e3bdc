"""The planning problem of paper Sec. III-D: W, tr(W P_post W) and the information gain.

Every strategy and every test evaluates the cost through :class:`Problem`, so the formula lives
in exactly one place:

    cost(p) = tr(W P W) - gain(p),   gain(p) = h P W^2 P h' / (h P h' + R),   W = diag(1, 1, |p_o|)

with ``h`` the measurement Jacobian at the candidate position ``p`` (eq. 16 or 18) and
``R = sigma^2``. Both kinds reduce to a ratio of quadratic forms in a short monomial vector:

* range:   ``u = p / |p|``, gain = u' A u / (u' B u + R) with A = (P W^2 P)[:2, :2],
  B = P[:2, :2]; monomials ``[c^2, c s, s^2, 1]``.
* bearing: ``h = [q0, q1, -1]`` with ``q = (-y, x) / |p|^2``; gain = h' M h / h' N h with
  M = P W^2 P, N = P + R e3 e3'; monomials ``[q0^2, q0 q1, q1^2, q0, q1, 1]``.

The formulas are written entry by entry so that the same code serves one problem in Python
floats (the per-step fast path) and many at once in numpy arrays, with identical rounding.
Derived quantities are computed on first use, so building a :class:`Problem` is cheap.
"""
from __future__ import annotations

import math
import numbers
import operator
import reprlib
import sys
from collections.abc import Callable, Sequence
from dataclasses import InitVar, dataclass
from decimal import Decimal
from fractions import Fraction
from typing import Any, Generic, TypeVar, cast, overload

import numpy as np

from formopt_ros.core.model import MEASUREMENT_KINDS, RANGE, symmetric3

#: Float, or numpy array of floats: the entry-wise formulas below accept either.
Value = TypeVar('Value', float, np.ndarray)
#: The six distinct entries (00, 01, 02, 11, 12, 22) of a symmetric 3x3 matrix.
Entries = tuple[Any, Any, Any, Any, Any, Any]


Owner = TypeVar('Owner')
Result = TypeVar('Result')


class lazy_property(Generic[Owner, Result]):
    """A property computed on first access and then stored in the instance's ``__dict__``:
    ``functools.cached_property`` without its per-access lock (Python 3.11), 0.3 us cheaper."""

    def __init__(self, function: Callable[[Owner], Result]) -> None:
        self.function = function
        self.name = function.__name__
        self.__doc__ = function.__doc__

    @overload
    def __get__(self, instance: None, owner: type | None = None) -> 'lazy_property[Owner, Result]':
        ...

    @overload
    def __get__(self, instance: Owner, owner: type | None = None) -> Result:
        ...

    def __get__(self, instance: Owner | None, owner: type | None = None) -> Any:
        if instance is None:
            return self
        value = instance.__dict__[self.name] = self.function(instance)
        return value


def weight_vector(p_o: np.ndarray) -> np.ndarray:
    """Diagonal of W = diag(1, 1, |p_o|), shape (3,): heading error weighted by the slot range."""
    return np.array([1.0, 1.0, math.hypot(p_o[0], p_o[1])])


def trace_entries(p00: Value, p11: Value, p22: Value, d2: Any) -> Value:
    """tr(W P W) = p00 + p11 + |p_o|^2 p22 from P's diagonal (floats or arrays), m^2."""
    return p00 + p11 + d2 * p22


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


#: Largest allowed deviation r as a fraction of |p_o|. Closer to the leader the image of the
#: disc under the bearing's inversion (radius r / (|p_o|^2 - r^2)) grows without bound and the
#: boundary series lose every digit: at r = 0.999999 |p_o| RQ and RAM returned points worse
#: than the slot. Up to this bound the slow tier finds no wrong answer ('r near |p_o|').
MAX_DEVIATION = 0.999
#: Smallest allowed deviation r as a fraction of |p_o|: a point p_o + r u carries rounding of
#: about eps |p_o|, which for r below ~1e-7 |p_o| exceeds the 1e-9 r by which a point may lie
#: outside the disc (measured: r = 1.4e-8 |p_o| gave points 2.7e-9 r outside).
MIN_DEVIATION = 1e-6


def check_disc(x_o: float, y_o: float, r: float) -> float:
    """|p_o| (m) when the disc of radius r (m) around p_o = (x_o, y_o) is a valid feasible
    set: |p_o| in SLOT_DISTANCE_RANGE, MIN_DEVIATION |p_o| <= r <= MAX_DEVIATION |p_o| and
    every square of the problem a normal float; else ValueError saying which."""
    d_o = math.hypot(x_o, y_o)
    if not SLOT_DISTANCE_RANGE[0] <= d_o <= SLOT_DISTANCE_RANGE[1]:
        raise ValueError(f'|p_o| = {d_o:.6g} m is outside [{SLOT_DISTANCE_RANGE[0]:g}, '
                         f'{SLOT_DISTANCE_RANGE[1]:g}] m')
    if not r <= MAX_DEVIATION * d_o:
        raise ValueError(f'r must be at most {MAX_DEVIATION} |p_o| = {MAX_DEVIATION * d_o:.6g} '
                         f'm so that the disc keeps clear of the leader, got r = {r:.6g} m')
    if not r >= MIN_DEVIATION * d_o:
        raise ValueError(f'r must be at least {MIN_DEVIATION:g} |p_o| = '
                         f'{MIN_DEVIATION * d_o:.6g} m (the points of a smaller disc carry '
                         f'rounding of ~1e-16 |p_o|, more than its 1e-9 r tolerance), '
                         f'got r = {r:.6g} m')
    margin = d_o * d_o - r * r
    if not (math.isfinite(d_o * d_o) and margin >= sys.float_info.min
            and r * r >= sys.float_info.min):
        raise ValueError(f'|p_o| = {d_o:.6g} m and r = {r:.6g} m are outside the range of '
                         'double precision (their squares overflow or underflow); give them '
                         'in metres')
    return d_o


def _is_real_number(value: object) -> bool:
    """True for a real number of any numeric type (int, float, Fraction, Decimal, numpy
    scalars), False for booleans, complex numbers, strings and other objects."""
    return (isinstance(value, (numbers.Real, Decimal))
            and not isinstance(value, (bool, np.bool_, np.timedelta64, np.datetime64)))


def _refuse_hidden_values(name: str, value: object) -> None:
    """ValueError naming ``name`` when a nested sequence holds masked values or booleans, which
    numpy's conversion to floats would hide (a masked row's data, True as 1.0)."""
    try:
        elements = np.asarray(value, dtype=object).ravel().tolist()
    except ValueError:                  # the conversion to floats names this
        return
    rows = list(value) if isinstance(value, (list, tuple)) else []
    if any(np.ma.is_masked(v) for v in rows if np.ma.isMaskedArray(v)) or any(
            np.ma.isMaskedArray(v) or v is np.ma.masked for v in elements):
        raise ValueError(f'{name} has masked entries; give every entry a value')
    if any(isinstance(v, (bool, np.bool_)) or isinstance(v, np.ndarray) and v.dtype.kind == 'b'
           for v in elements):          # a 0-d boolean array among numbers stays an array
        raise ValueError(f'{name} must hold real numbers, got a boolean among '
                         f'{reprlib.repr(value)}')


def _real_array(name: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """value as a float array of ``shape`` (-1: any length, the T problems of a batch), or
    ValueError naming ``name``; only real numbers are accepted (not booleans, complex numbers,
    strings, None or masked entries; exact numbers such as Fraction and Decimal are rounded to
    floats)."""
    wanted = str(shape) if -1 not in shape else '(' + ', '.join(
        'T' if n == -1 else str(n) for n in shape) + (',)' if len(shape) == 1 else ')') + \
        ' for T problems'
    if isinstance(value, np.ma.MaskedArray) and np.ma.is_masked(value):
        where = np.argwhere(np.ma.getmaskarray(value)).tolist()
        raise ValueError(f'{name} has masked entries (at {where}); give every entry a value')
    if not isinstance(value, np.ndarray):
        _refuse_hidden_values(name, value)
    try:
        raw = np.asarray(value)
    except ValueError as error:         # ragged nesting
        raise ValueError(f'{name} must be an array of shape {wanted}: {error}') from None
    if raw.dtype.kind == 'O':
        for entry in raw.flat:
            if not _is_real_number(entry):
                raise ValueError(f'{name} must hold real numbers, got {reprlib.repr(entry)} '
                                 f'({type(entry).__name__})')
    elif raw.dtype.kind not in 'iuf':
        raise ValueError(f'{name} must hold real numbers, got {raw.dtype} values')
    try:
        arr = raw.astype(float)
    except OverflowError:
        raise ValueError(f'{name} holds a number beyond the range of doubles') from None
    if arr.ndim != len(shape) or any(n not in (-1, m) for n, m in zip(shape, arr.shape)):
        raise ValueError(f'{name} must have shape {wanted}, got shape {arr.shape}')
    return arr


def _check_array(name: str, value: object,
                 shape: tuple[int, ...]) -> tuple[np.ndarray, list[float]]:
    """(value as a finite float array of ``shape`` (:func:`_real_array`), its entries as a flat
    list) or ValueError naming ``name``."""
    arr = _real_array(name, value, shape)
    flat = arr.ravel().tolist()
    if not math.isfinite(sum(flat)) and not all(map(math.isfinite, flat)):
        raise ValueError(f'{name} must be finite, got {arr.tolist()}')
    return arr, flat


def _check_positive(name: str, value: object, unit: str) -> float:
    """value as a float, or ValueError unless it is a finite real number > 0 (any numeric
    type, or a 0-d real array)."""
    if type(value) is float and 0.0 < value < math.inf:       # the common case, at once
        return value
    if np.ma.isMaskedArray(value) and np.ma.is_masked(value) or value is np.ma.masked:
        raise ValueError(f'{name} is masked; give it a value')
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in 'iufO':
        value = value.item()
    if not _is_real_number(value):
        raise ValueError(f'{name} must be a real number > 0 ({unit}), got '
                         f'{reprlib.repr(value)} of type {type(value).__name__}')
    shown = reprlib.repr(value)
    try:
        number = float(value)   # type: ignore[arg-type]
    except OverflowError:
        raise ValueError(f'{name} = {shown} ({unit}) is beyond the range of doubles') from None
    if number == 0.0 and value > 0:    # type: ignore[operator]
        raise ValueError(f'{name} = {shown} ({unit}) rounds to 0 as a double')
    if not math.isfinite(number) or number <= 0.0:
        raise ValueError(f'{name} must be a finite number > 0 ({unit}), got {shown}')
    return number


#: Admissible variances on the diagonal of a problem's P (m^2, rad^2) and largest sigma (m or
#: rad): the cost and its certificate multiply up to six entries of P and R = sigma^2, which
#: outside these bounds leave the range of doubles (measured: 1e-120 underflows, 1e30 and
#: sigma 1e200 overflow; a sweep of 400 correlated P with variances log-uniform in the range
#: and sigma in [1e-6, 1] solved with every method).
VARIANCE_RANGE = (1e-100, 1e25)
#: Admissible sigma (m or rad) and |p_o| (m). With sigma = 1e-197 (R underflows to 0) or
#: |p_o| = 1e-146 or 1e124 the products of the certificate over- or underflowed (a review
#: found OverflowError, IndexError and answers worse than a boundary sample there); inside
#: these ranges a fuzz over the whole VARIANCE_RANGE found none.
SIGMA_RANGE = (1e-9, 1e6)
SLOT_DISTANCE_RANGE = (1e-3, 1e6)
#: numpy's float64 dtype (the quick input checks compare by identity first; an unpickled
#: array's dtype is an equal but distinct object).
_FLOAT = np.dtype(float)
#: Scalar types the quick input checks take as they are: exact doubles.
_FLOAT_SCALARS = (float, np.float64)


#: Relative difference of P[i, j] and P[j, i] (to the pair's scale, see
#: :func:`check_covariance`) taken for rounding: an EKF that never symmetrises its covariance
#: (F P F' + Q, then P - K S K', 20 steps, condition up to 1e11) drifted up to 7.6e-7 of the
#: pair's scale on 2,000 seeded runs of a reviewer's; a difference of 1e-6 changes a
#: correlation by 5e-7 at most.
SYMMETRY_TOLERANCE = 1e-6


def check_covariance(P: object, name: str = 'P', variances: tuple[float, float] | None = None
                     ) -> tuple[np.ndarray, Entries]:
    """(P as a symmetric float (3, 3) array, its six distinct entries) or ValueError when P is
    not symmetric positive definite or, when ``variances`` = (low, high) is given, when a
    diagonal entry lies outside it.

    P[i, j] and P[j, i] may differ by rounding, up to SYMMETRY_TOLERANCE of their own scale
    max(sqrt(P[i, i] P[j, j]), |P[i, j]|, |P[j, i]|) (the first bounds |P[i, j]| of a
    covariance), and are then averaged. The scale is the pair's, not the whole matrix's: with
    variances 1e4 and 1e-16, P[1, 2] = 9e-7 and P[2, 1] = -9e-7 are a correlation of +0.9 and
    one of -0.9, not rounding."""
    arr, (p00, p01, p02, p10, p11, p12, p20, p21, p22) = _check_array(name, P, (3, 3))
    if p01 != p10 or p02 != p20 or p12 != p21:
        roots = [math.sqrt(abs(value)) for value in (p00, p11, p22)]
        for (i, j), upper, lower in (((0, 1), p01, p10), ((0, 2), p02, p20), ((1, 2), p12, p21)):
            scale = max(roots[i] * roots[j], abs(upper), abs(lower), 1e-300)
            if abs(upper - lower) > SYMMETRY_TOLERANCE * scale:
                raise ValueError(
                    f'{name} must be symmetric, got {name}[{i}, {j}] = {upper!r} and '
                    f'{name}[{j}, {i}] = {lower!r}, which differ by more than rounding '
                    f'({SYMMETRY_TOLERANCE:g} of their scale {scale:.3g}); if the difference '
                    f'is your filter\'s rounding, pass 0.5 * ({name} + {name}.T)')
        arr = 0.5 * (arr + arr.T)
        p01, p02, p12 = float(arr[0, 1]), float(arr[0, 2]), float(arr[1, 2])
    entries = (p00, p01, p02, p11, p12, p22)
    low, high = variances if variances is not None else (-math.inf, math.inf)
    if not ((p00 <= 0.0 or low <= p00 <= high) and (p11 <= 0.0 or low <= p11 <= high)
            and (p22 <= 0.0 or low <= p22 <= high)):                     # v <= 0: not PD
        raise ValueError(f'the variances on the diagonal of {name} must lie in '
                         f'[{low:g}, {high:g}] (m^2, rad^2), got '
                         f'{[p00, p11, p22]}')
    if not positive_definite_exactly(entries):
        eig = np.linalg.eigvalsh(arr)
        if eig[0] > 0.0:
            raise ValueError(f'{name} must be positive definite, but it is indefinite or '
                             'singular in exact arithmetic (numpy computes the eigenvalues '
                             f'{eig.tolist()}): its smallest eigenvalue is below rounding')
        raise ValueError(f'{name} must be positive definite, got eigenvalues {eig.tolist()}')
    return arr, entries


def positive_definite_entries(entries: Entries) -> bool:
    """True when the symmetric 3x3 matrix with these six entries has positive LDL' pivots."""
    a00, a01, a02, a11, a12, a22 = entries
    if not a00 > 0.0:
        return False
    l10, l20 = a01 / a00, a02 / a00
    d1 = a11 - l10 * a01
    if not d1 > 0.0:
        return False
    b12 = a12 - l20 * a01
    return a22 - l20 * a02 - b12 * b12 / d1 > 0.0


def positive_definite_exactly(entries: Entries) -> bool:
    """True when the symmetric 3x3 matrix with these six entries (floats, taken as exact) is
    positive definite: the LDL' pivots in floating point where they clear their rounding with
    room, else its leading minors in exact rational arithmetic (Sylvester).

    d1 = a11 - a01^2/a00 carries a few units of a11's rounding, and d2 that of a22 plus
    4 u a22 sqrt(a11 / d1) from b12^2 / d1 (|b12| <= sqrt(d1 a22)); the margins below are 10x
    those bounds. A float check alone accepted P with exact determinant below zero."""
    a00, a01, a02, a11, a12, a22 = entries
    if not a00 > 0.0:
        return False
    l10, l20 = a01 / a00, a02 / a00
    d1 = a11 - l10 * a01
    if d1 > 1e-12 * a11:
        b12 = a12 - l20 * a01
        d2 = a22 - l20 * a02 - b12 * b12 / d1
        if d2 > 1e-14 * a22 * (2.0 + math.sqrt(a11 / d1)):
            return True
    e00, e01, e02, e11, e12, e22 = map(Fraction, entries)
    return (e00 * e11 - e01 * e01 > 0 and e00 * (e11 * e22 - e12 * e12)
            - e01 * (e01 * e22 - e12 * e02) + e02 * (e01 * e12 - e11 * e02) > 0)


#: A checked problem: (P (3, 3) array, p_o (2,) array, r, sigma, P's six distinct entries,
#: p_o as floats, |p_o|).
Checked = tuple[np.ndarray, np.ndarray, float, float, Entries, tuple[float, float], float]


def check_problem(P: object, p_o: object, r: object, sigma: object,
                  measurement: str) -> Checked:
    """The inputs of a :class:`Problem`, checked, or ValueError saying what is wrong.

    Float arrays of the right shapes and float r and sigma are accepted by the quick checks
    below (about a microsecond); anything else, or a failed quick check, goes through
    :func:`check_problem_thoroughly`, which converts what it may and names what is wrong.
    """
    if (type(P) is np.ndarray and type(p_o) is np.ndarray
            and (P.dtype is _FLOAT or P.dtype == _FLOAT)
            and (p_o.dtype is _FLOAT or p_o.dtype == _FLOAT) and P.shape == (3, 3)
            and p_o.shape == (2,) and type(r) in _FLOAT_SCALARS
            and type(sigma) in _FLOAT_SCALARS):
        r, sigma = float(cast(float, r)), float(cast(float, sigma))
        (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = P.tolist()
        x_o, y_o = p_o.tolist()
        low, high = VARIANCE_RANGE
        entries = (p00, p01, p02, p11, p12, p22)
        d_o = math.hypot(x_o, y_o)
        # NaN fails every comparison; a sum with an infinite or NaN term is not finite; the
        # disc's checks are check_disc's (inside these ranges its squares are normal floats)
        if (p01 == p10 and p02 == p20 and p12 == p21 and low <= p00 <= high
                and low <= p11 <= high and low <= p22 <= high
                and SIGMA_RANGE[0] <= sigma <= SIGMA_RANGE[1]
                and SLOT_DISTANCE_RANGE[0] <= d_o <= SLOT_DISTANCE_RANGE[1]
                and MIN_DEVIATION * d_o <= r <= MAX_DEVIATION * d_o
                and math.isfinite(p01 + p02 + p12)
                and measurement in MEASUREMENT_KINDS and positive_definite_exactly(entries)):
            return P.copy(), p_o.copy(), r, sigma, entries, (x_o, y_o), d_o
    return check_problem_thoroughly(P, p_o, r, sigma, measurement)


def check_problem_thoroughly(P: object, p_o: object, r: object, sigma: object,
                             measurement: str) -> Checked:
    """:func:`check_problem` for inputs of any type: numbers and array-likes are converted."""
    if measurement not in MEASUREMENT_KINDS:
        raise ValueError(f'measurement must be one of {MEASUREMENT_KINDS}, got {measurement!r}')
    P_checked, entries = check_covariance(P, variances=VARIANCE_RANGE)
    p_o_checked, (x_o, y_o) = _check_array('p_o', p_o, (2,))
    r_checked = _check_positive('r', r, 'm')
    sigma_checked = _check_positive('sigma', sigma, 'm' if measurement == RANGE else 'rad')
    if not SIGMA_RANGE[0] <= sigma_checked <= SIGMA_RANGE[1]:
        raise ValueError(f'sigma must lie in [{SIGMA_RANGE[0]:g}, {SIGMA_RANGE[1]:g}], got '
                         f'{sigma_checked!r}')
    return (P_checked, p_o_checked, r_checked, sigma_checked, entries, (x_o, y_o),
            check_disc(x_o, y_o, r_checked))


#: A checked batch: P (T, 3, 3), p_o (T, 2), r (T,) and sigma (T,) as float64 arrays.
CheckedBatch = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def check_batch(P: object, p_o: object, r: object, sigma: object,
                measurement: str) -> CheckedBatch:
    """The inputs of a :class:`ProblemBatch`, checked: every problem as :func:`check_problem`
    checks one, or ValueError naming the first bad problem and what is wrong with it.

    The checks of :func:`check_problem`'s quick path run on the arrays at once (the same
    float comparisons and LDL' pivots); a problem that fails one of them is checked alone,
    which either names what is wrong or accepts it (P symmetric up to rounding, whose pair
    is then averaged; P positive definite only in exact arithmetic's judgement).
    """
    if measurement not in MEASUREMENT_KINDS:
        raise ValueError(f'measurement must be one of {MEASUREMENT_KINDS}, got {measurement!r}')
    arrays = [_real_array(name, value, shape) for name, value, shape in (
        ('P', P, (-1, 3, 3)), ('p_o', p_o, (-1, 2)), ('r', r, (-1,)), ('sigma', sigma, (-1,)))]
    sizes = [len(a) for a in arrays]
    if len(set(sizes)) != 1:
        raise ValueError(f'P, p_o, r and sigma must hold one entry per problem, got '
                         f'{sizes[0]}, {sizes[1]}, {sizes[2]} and {sizes[3]}')
    P_a, p_o_a, r_a, sigma_a = arrays
    low, high = VARIANCE_RANGE
    with np.errstate(all='ignore'):
        p00, p01, p02, p11, p12, p22 = (P_a[:, i, j] for i, j in (
            (0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))
        d_o = np.array([math.hypot(x, y) for x, y in p_o_a.tolist()]).reshape(len(p_o_a))
        l10, l20 = p01 / p00, p02 / p00
        d1 = p11 - l10 * p01
        b12 = p12 - l20 * p01
        d2 = p22 - l20 * p02 - b12 * b12 / d1
        quick = ((p01 == P_a[:, 1, 0]) & (p02 == P_a[:, 2, 0]) & (p12 == P_a[:, 2, 1])
                 & (low <= p00) & (p00 <= high) & (low <= p11) & (p11 <= high)
                 & (low <= p22) & (p22 <= high)
                 & (SIGMA_RANGE[0] <= sigma_a) & (sigma_a <= SIGMA_RANGE[1])
                 & (SLOT_DISTANCE_RANGE[0] <= d_o) & (d_o <= SLOT_DISTANCE_RANGE[1])
                 & (MIN_DEVIATION * d_o <= r_a) & (r_a <= MAX_DEVIATION * d_o)
                 & np.isfinite(p01 + p02 + p12)
                 & (d1 > 1e-12 * p11) & (d2 > 1e-14 * p22 * (2.0 + np.sqrt(p11 / d1))))
    others = np.flatnonzero(~quick).tolist()
    if others:
        P_a, p_o_a = P_a.copy(), p_o_a.copy()
    for t in others:
        try:
            checked = check_problem(P_a[t], p_o_a[t], float(r_a[t]), float(sigma_a[t]),
                                    measurement)
        except ValueError as error:
            raise ValueError(f'problem {t} of the batch: {error}') from None
        P_a[t], p_o_a[t] = checked[0], checked[1]
    return P_a, p_o_a, r_a, sigma_a


class _QuotientForms:
    """The gain's quadratic forms, derived on first use from ``entries`` (P's six distinct
    entries), ``d_o`` and ``R``: floats for a :class:`Problem`, arrays (T,) for a
    :class:`ProblemBatch`, by the same formulas."""

    measurement: str
    entries: Entries
    d_o: Any
    R: Any

    @lazy_property
    def forms(self) -> tuple[Entries, Entries]:
        """Entries of M = P W^2 P and N = P + R e3 e3'."""
        return quotient_entries(self.entries, self.d_o * self.d_o, self.R)

    @lazy_property
    def M(self) -> np.ndarray:
        """P W^2 P, shape (3, 3) (or (T, 3, 3) for a batch)."""
        return symmetric3(self.forms[0])

    @lazy_property
    def N(self) -> np.ndarray:
        """P + R e3 e3' (the bearing denominator), shape (3, 3) (or (T, 3, 3))."""
        return symmetric3(self.forms[1])

    @lazy_property
    def coefficients(self) -> tuple[tuple[Any, ...], tuple[Any, ...]]:
        """Coefficients of the gain's numerator and denominator (:func:`gain_coefficients`)."""
        return gain_coefficients(self.measurement, *self.forms, self.R)


class _ProblemValues:
    """The values a :class:`Problem` derives in ``__init__`` (declared here, outside the
    dataclass, so that they are not fields)."""

    #: (p00, p01, p02, p11, p12, p22) of P as Python floats.
    entries: Entries
    #: p_o as Python floats, m.
    slot: tuple[float, float]
    #: Distance of the formation slot from the leader, m.
    d_o: float
    #: Measurement noise variance, m^2 or rad^2.
    R: float
    #: tr(W P W), m^2: the cost without a measurement.
    base_cost: float


@dataclass(frozen=True, init=False)
class Problem(_QuotientForms, _ProblemValues):
    """Problem Pi_1 of the paper: choose p with |p - p_o| <= r minimising tr(W P_post W).

    Attributes:
        P: prior covariance of [x, y, phi] at the next step, shape (3, 3) (m^2, m rad, rad^2).
        p_o: formation slot in the leader frame, shape (2,), m.
        r: allowed deviation from the slot, m; 1e-6 |p_o| <= r <= 0.999 |p_o| (the disc must not
            reach the leader).
        sigma: measurement noise standard deviation, m (range) or rad (bearing).
        measurement: 'range' or 'bearing'.
        validate: check every input (default). Loops that check their setting once (the
            simulator, the nodes: :class:`~formopt_ros.core.scenario.Scenario` validates slot,
            r and sigma, and their own EKF makes P symmetric positive definite) pass False.

    Derived at construction (every strategy needs them): ``entries`` (P's six distinct
    entries as floats), ``slot``, ``d_o``, ``R``, ``forms`` (entries of M = P W^2 P and
    N = P + R e3 e3'), ``base_cost`` = tr(W P W) and the gain's ``coefficients``; on first use:
    ``w`` (diagonal of W), ``M``, ``N`` and ``q_circle``.
    """

    P: np.ndarray
    p_o: np.ndarray
    r: float
    sigma: float
    measurement: str

    def __init__(self, P: np.ndarray, p_o: np.ndarray, r: float, sigma: float,
                 measurement: str, validate: bool = True) -> None:
        if validate:
            P, p_o, r, sigma, entries, slot, d_o = check_problem(P, p_o, r, sigma, measurement)
        else:
            (p00, p01, p02), (_, p11, p12), (_, _, p22) = np.asarray(P).tolist()
            entries = (p00, p01, p02, p11, p12, p22)
            x_o, y_o = p_o.tolist() if isinstance(p_o, np.ndarray) else p_o
            slot = (float(x_o), float(y_o))
            d_o = math.hypot(*slot)
        # what every strategy needs is derived at once (a lazy property costs 0.25 us per use),
        # and the frozen record is filled in one step (its generated __init__ sets each field
        # through object.__setattr__)
        R = float(sigma) * float(sigma)
        w22 = d_o * d_o
        forms = quotient_entries(entries, w22, R)
        object.__setattr__(self, '__dict__', {
            'P': P, 'p_o': p_o, 'r': r, 'sigma': sigma, 'measurement': measurement,
            'entries': entries, 'slot': slot, 'd_o': d_o, 'R': R, 'forms': forms,
            'base_cost': trace_entries(entries[0], entries[3], entries[5], w22),
            'coefficients': gain_coefficients(measurement, *forms, R)})

    # --- derived quantities -------------------------------------------------------------------
    @lazy_property
    def w(self) -> np.ndarray:
        """Diagonal of W, shape (3,)."""
        return np.array([1.0, 1.0, self.d_o])

    @lazy_property
    def q_circle(self) -> tuple[float, float, float]:
        """Image of the disc under p -> q = (-y, x)/|p|^2: (centre x, centre y, radius), 1/m.

        Inversion maps the disc |p - c| <= r (origin outside) to the disc with centre
        c / (|c|^2 - r^2) and radius r / (|c|^2 - r^2); the 90 degree turn follows.
        """
        x_o, y_o = self.slot
        r = float(self.r)
        k = 1.0 / (self.d_o * self.d_o - r * r)
        return -y_o * k, x_o * k, r * k

    # --- the cost -----------------------------------------------------------------------------
    @overload
    def gain_at(self, x: float, y: float) -> float:
        ...

    @overload
    def gain_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        ...

    def gain_at(self, x: Any, y: Any) -> Any:
        """Information gain tr(W P W) - tr(W P_post W) (m^2) at points (x, y) in {L} (m), given as
        floats or as arrays of one shape.

        At a point where the denominator h'Nh rounds to zero (P near-singular along h) the
        formula says nothing: the gain is -inf there, so that no choice rests on it (the
        certificates' exact stage and exact tie-break evaluate such points exactly). The same
        holds where the formula is not finite (the origin, an overflow), for Python floats,
        numpy scalars and arrays alike, and no numpy warning is raised."""
        if type(x) is float and type(y) is float:           # the solvers' hot path
            try:
                gain = quotient_gain(self.measurement, self.coefficients, x, y)
            except ZeroDivisionError:
                return -math.inf
            return gain if -math.inf < gain < math.inf else -math.inf
        with np.errstate(all='ignore'):
            gains = quotient_gain(self.measurement, self.coefficients, np.asarray(x, dtype=float),
                                  np.asarray(y, dtype=float))
        gains = np.where(np.isfinite(gains), gains, -np.inf)
        return gains if gains.ndim else gains[()]

    def gain_error_at(self, x: float, y: float, gain: float) -> float:
        """A rigorous bound (m^2) on |gain - g(x, y)|, g the exact gain at the floats (x, y) on
        the exact data, for ``gain = self.gain_at(x, y)``.

        The numerator n and denominator d of :func:`quotient_gain` are h'Mh and h'Nh (h as in
        the certificate module: (x, y)/|p| for range, (q0, q1, -1) for bearing); each carries
        at most GAIN_ROUNDING_UNITS times the sum of its terms' magnitudes. M = P W^2 P is a
        Gram matrix, so every term of m_ij is at most sqrt(m_ii m_jj) in magnitude summed
        (Cauchy-Schwarz), and |n_ij| <= sqrt(n_ii n_jj) (N is positive definite): the sums
        are at most (sum_i sqrt(m_ii) |h_i|)^2 <= k sum_i m_ii h_i^2 over the k = 2 (range) or
        3 (bearing) components of h, and the same for N (range: plus R), from the diagonals
        alone and without a square root. Then g = n / d lies in
        [(n - e_n) / (d + e_d), (n + e_n) / (d - e_d)]. The bound is large exactly where the
        formula cancels: P ill-conditioned and the point's direction near its minor axis.
        Returns inf when d may vanish.
        """
        n, d, e_n, e_d = gain_rounding(self.measurement, self.coefficients, x, y)
        if not d - e_d > 0.0:
            return math.inf
        low, high = max(n - e_n, 0.0) / (d + e_d), (n + e_n) / (d - e_d)
        # the last factor covers this function's own rounding (a few units of 2^-53)
        return max(gain - low, high - gain) * (1.0 + 1e-12) + 1e-15 * abs(gain)

    def gain(self, points: np.ndarray) -> np.ndarray:
        """Information gain (m^2) at points of shape (n, 2) or (2,) in {L}, m; shape (n,);
        -inf where the formula's denominator rounds to zero (:meth:`gain_at`)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        return self.gain_at(pts[:, 0], pts[:, 1])

    def cost(self, points: np.ndarray) -> np.ndarray | float:
        """tr(W P_post W) (m^2) at points (n, 2) -> (n,), or at one point (2,) -> float."""
        values = self.base_cost - self.gain(points)
        return float(values[0]) if np.ndim(points) == 1 else values

    def feasible(self, point: np.ndarray | Sequence[float], tol: float = 1e-9) -> bool:
        """True when |point - p_o| <= r (1 + tol), for a point (2,) in m."""
        x_o, y_o = self.slot
        return bool(math.hypot(point[0] - x_o, point[1] - y_o) <= self.r * (1.0 + tol))

    # --- geometry of the feasible disc -------------------------------------------------------
    def bearing_arc(self) -> tuple[float, float]:
        """(theta_o, delta): the disc is seen from the leader at bearings theta_o +- delta, rad."""
        x_o, y_o = self.slot
        return math.atan2(y_o, x_o), math.asin(float(self.r) / self.d_o)

    def q_disc(self) -> tuple[np.ndarray, float]:
        """:attr:`q_circle` as (centre (2,), radius), 1/m."""
        c0, c1, rho = self.q_circle
        return np.array([c0, c1]), rho


def point_from_q(q: np.ndarray) -> np.ndarray:
    """Inverse of p -> q = (-y, x)/|p|^2: p = (q1, -q0)/|q|^2, for q of shape (..., 2)."""
    q = np.asarray(q, dtype=float)
    n2 = np.sum(q * q, axis=-1, keepdims=True)
    return np.stack([q[..., 1], -q[..., 0]], axis=-1) / n2


@dataclass(frozen=True)
class ProblemBatch(_QuotientForms):
    """T problems of one measurement kind, stacked for vectorised strategies and tests.

    Every derived quantity uses the same entry-wise formulas as :class:`Problem`, so problem t
    of a batch and ``batch.problem(t)`` give bit-identical numbers. The arrays are held as
    float64 (other dtypes are converted, as :class:`Problem` converts to Python floats).

    Attributes:
        P: prior covariances, shape (T, 3, 3).
        p_o: slots, shape (T, 2), m.
        r: allowed deviations, shape (T,), m.
        sigma: noise standard deviations, shape (T,).
        measurement: 'range' or 'bearing'.
        validate: check every problem as :class:`Problem` does (default; :func:`check_batch`).
            The batched Monte Carlo engine, whose setting is validated once and whose P come
            from its own EKF, passes False, as do :meth:`stack` and :meth:`subset` (their
            problems were checked when they were made).
    """

    P: np.ndarray
    p_o: np.ndarray
    r: np.ndarray
    sigma: np.ndarray
    measurement: str
    validate: InitVar[bool] = True

    def __post_init__(self, validate: bool) -> None:
        # float64 throughout (a view where the array is float64 already): problem t is built
        # from these numbers, so a float32 or longdouble batch would compute in another
        # precision than its problems
        names = ('P', 'p_o', 'r', 'sigma')
        P, p_o, r, sigma = (getattr(self, name) for name in names)
        checked = check_batch(P, p_o, r, sigma, self.measurement) if validate else [
            np.asarray(value, dtype=float) for value in (P, p_o, r, sigma)]
        for name, value in zip(names, checked):
            object.__setattr__(self, name, value)

    @classmethod
    def shared(cls, P: np.ndarray, p_o: np.ndarray, r: float, sigma: float,
               measurement: str, validate: bool = True) -> 'ProblemBatch':
        """A batch whose problems share slot, r and sigma (a study step), P of shape (T, 3, 3)."""
        if validate:            # one r and one sigma, checked as Problem checks them
            P = _real_array('P', P, (-1, 3, 3))
            unit = 'm' if measurement == RANGE else 'rad'
            r, sigma = _check_positive('r', r, 'm'), _check_positive('sigma', sigma, unit)
            p_o = _check_array('p_o', p_o, (2,))[0]
        T = len(P)
        return cls(P, np.broadcast_to(np.asarray(p_o, dtype=float), (T, 2)),
                   np.full(T, r, dtype=float), np.full(T, sigma, dtype=float), measurement,
                   validate)

    @classmethod
    def stack(cls, problems: list[Problem]) -> 'ProblemBatch':
        """The batch of the given problems (all of one measurement kind)."""
        kinds = {p.measurement for p in problems}
        if len(kinds) != 1:
            raise ValueError(f'a batch holds one measurement kind, got {sorted(kinds)}')
        return cls(np.array([p.P for p in problems], dtype=float),
                   np.array([p.p_o for p in problems], dtype=float),
                   np.array([p.r for p in problems], dtype=float),
                   np.array([p.sigma for p in problems], dtype=float), kinds.pop(), False)

    def __len__(self) -> int:
        return len(self.P)

    def subset(self, index: np.ndarray) -> 'ProblemBatch':
        """The batch of the problems ``index`` (an index array)."""
        return ProblemBatch(self.P[index], self.p_o[index], self.r[index], self.sigma[index],
                            self.measurement, False)

    def problem(self, t: int) -> Problem:
        """Problem t of the batch (not validated again)."""
        return Problem(self.P[t], self.p_o[t], float(self.r[t]), float(self.sigma[t]),
                       self.measurement, False)

    @lazy_property
    def entries(self) -> Entries:
        """(p00, p01, p02, p11, p12, p22), each of shape (T,)."""
        P = self.P
        return P[:, 0, 0], P[:, 0, 1], P[:, 0, 2], P[:, 1, 1], P[:, 1, 2], P[:, 2, 2]

    @lazy_property
    def d_o(self) -> np.ndarray:
        """|p_o| per problem, shape (T,), m (math.hypot, as :class:`Problem`)."""
        return np.array([math.hypot(x, y) for x, y in self.p_o.tolist()])

    @property
    def R(self) -> np.ndarray:
        """Noise variances, shape (T,)."""
        return self.sigma * self.sigma

    @lazy_property
    def slot(self) -> tuple[np.ndarray, np.ndarray]:
        """(x_o, y_o) per problem, two arrays (T,), m."""
        return self.p_o[:, 0], self.p_o[:, 1]

    @lazy_property
    def base_cost(self) -> np.ndarray:
        """tr(W P W) per problem, shape (T,), m^2 (the formula of :class:`Problem`)."""
        p00, _, _, p11, _, p22 = self.entries
        return trace_entries(p00, p11, p22, self.d_o * self.d_o)

    def gain_error_at(self, x: np.ndarray, y: np.ndarray, gain: np.ndarray) -> np.ndarray:
        """:meth:`Problem.gain_error_at` per problem, for arrays (T,) of points (m) and their
        gains (m^2): the same arithmetic; inf where the denominator may vanish, nan where the
        scalar bound would not be a number."""
        with np.errstate(all='ignore'):
            n, d, e_n, e_d = gain_rounding(self.measurement, self.coefficients, x, y)
            low, high = np.maximum(n - e_n, 0.0) / (d + e_d), (n + e_n) / (d - e_d)
            error = np.maximum(gain - low, high - gain) * (1.0 + 1e-12) + 1e-15 * np.abs(gain)
            return np.where(d - e_d > 0.0, error, np.inf)

    def gains_of(self, owner: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Gains (m^2) at points x, y (C,) (m) of the problems ``owner`` (C,); shape (C,).
        Point by point the arithmetic of :meth:`Problem.gain_at`."""
        num, den = self.coefficient_rows
        rows_n, rows_d = num[:, owner], den[:, owner]
        return np.asarray(quotient_gain(self.measurement, (tuple(rows_n), tuple(rows_d)), x, y))

    @lazy_property
    def coefficient_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """:attr:`coefficients` as two arrays (k + 1, T)."""
        T = len(self)
        return tuple(np.array([np.broadcast_to(np.asarray(c, dtype=float), (T,)) for c in part])
                     for part in self.coefficients)  # type: ignore[return-value]

    @lazy_property
    def q_circle(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:attr:`Problem.q_circle` per problem: three arrays of shape (T,)."""
        k = 1.0 / (self.d_o * self.d_o - self.r * self.r)
        return -self.p_o[:, 1] * k, self.p_o[:, 0] * k, self.r * k
