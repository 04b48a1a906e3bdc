"""The planning problem of paper Sec. III-D: choose p in a disc minimising tr(W P_post W).

Every strategy and every test evaluates the cost through :class:`Problem` (one problem, on
Python floats) or :class:`ProblemBatch` (many, on arrays), both by the entry-wise formulas of
:mod:`formopt_ros.core.formulas`, so the cost lives in exactly one place. Derived quantities are
computed on first use, so building a problem is cheap.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import InitVar, dataclass
from typing import Any, Generic, TypeVar, overload

import numpy as np

from formopt_ros.core.checks import InvalidInput, as_array, as_choice, as_covariance, as_real
from formopt_ros.core.formulas import (
    Entries, gain_coefficients, gain_rounding, quotient_entries, quotient_gain, trace_entries)
from formopt_ros.core.model import MEASUREMENT_KINDS, RANGE, symmetric3

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


#: Largest allowed deviation r as a fraction of |p_o|. Closer to the leader the image of the
#: disc under the bearing's inversion (radius r / (|p_o|^2 - r^2)) grows without bound and the
#: boundary series lose every digit: at r = 0.999999 |p_o| RQ and RAM returned points worse
#: than the slot. Up to this bound the slow tier finds no wrong answer ('r near |p_o|').
MAX_DEVIATION = 0.999
#: Smallest allowed deviation r as a fraction of |p_o|: a point p_o + r u carries rounding of
#: about eps |p_o|, which for r below ~1e-7 |p_o| exceeds the 1e-9 r by which a point may lie
#: outside the disc (measured: r = 1.4e-8 |p_o| gave points 2.7e-9 r outside).
MIN_DEVIATION = 1e-6
#: Admissible variances on the diagonal of a problem's P (m^2, rad^2): the cost and its
#: certificate multiply up to six entries of P and R = sigma^2, which outside these bounds
#: leave the range of doubles (measured: 1e-120 underflows, 1e30 overflows).
VARIANCE_RANGE = (1e-100, 1e25)
#: Admissible sigma (m or rad) and |p_o| (m): beyond them the certificate's products over- or
#: underflow (sigma = 1e-197: R is 0; |p_o| = 1e-146 or 1e124); inside them, over the whole
#: VARIANCE_RANGE, a fuzz of every method found no failure.
SIGMA_RANGE = (1e-9, 1e6)
SLOT_DISTANCE_RANGE = (1e-3, 1e6)


def check_disc(x_o: float, y_o: float, r: float) -> float:
    """|p_o| (m) when the disc of radius r (m) around p_o = (x_o, y_o) is a valid feasible
    set: |p_o| in SLOT_DISTANCE_RANGE and MIN_DEVIATION |p_o| <= r <= MAX_DEVIATION |p_o|;
    else InvalidInput naming p_o or r."""
    d_o = math.hypot(x_o, y_o)
    low, high = SLOT_DISTANCE_RANGE
    if not low <= d_o <= high:
        raise InvalidInput('p_o', f'must lie at a distance in [{low:g}, {high:g}] m from the '
                                  f'leader, got |p_o| = {d_o:.6g} m')
    slack = 1.0 + 1e-12            # |p_o| from numpy's norm or math.hypot: an ulp apart
    if not MIN_DEVIATION * d_o / slack <= r <= MAX_DEVIATION * d_o * slack:
        raise InvalidInput('r', f'must lie in [{MIN_DEVIATION:g}, {MAX_DEVIATION}] |p_o| = '
                                f'[{MIN_DEVIATION * d_o!r}, {MAX_DEVIATION * d_o!r}] m (the '
                                f'disc keeps clear of the leader), got {r!r} m')
    return d_o


def check_problem(P: object, p_o: object, r: object, sigma: object, measurement: str
                  ) -> tuple[np.ndarray, np.ndarray, float, float, Entries, tuple[float, float],
                             float]:
    """(P, p_o, r, sigma, P's six distinct entries, p_o as floats, |p_o|), converted and
    checked, or InvalidInput naming the first input that is wrong."""
    as_choice('measurement', measurement, MEASUREMENT_KINDS)
    P_checked = as_covariance('P', P, *VARIANCE_RANGE)
    p_o_checked = as_array('p_o', p_o, (2,))
    r_checked = as_real('r', r, 0.0, unit='m', low_open=True)
    sigma_checked = as_real('sigma', sigma, *SIGMA_RANGE, unit='m' if measurement == RANGE
                            else 'rad')
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = P_checked.tolist()
    x_o, y_o = p_o_checked.tolist()
    return (P_checked, p_o_checked, r_checked, sigma_checked, (p00, p01, p02, p11, p12, p22),
            (x_o, y_o), check_disc(x_o, y_o, r_checked))


def check_batch(P: object, p_o: object, r: object, sigma: object,
                measurement: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The inputs of a :class:`ProblemBatch` as float arrays P (T, 3, 3), p_o (T, 2), r (T,)
    and sigma (T,), every problem checked as :func:`check_problem` checks one, or
    InvalidInput naming the array (and the problem)."""
    as_choice('measurement', measurement, MEASUREMENT_KINDS)
    arrays = [as_array(name, value, shape) for name, value, shape in (
        ('P', P, (-1, 3, 3)), ('p_o', p_o, (-1, 2)), ('r', r, (-1,)), ('sigma', sigma, (-1,)))]
    if len({len(a) for a in arrays}) != 1:
        raise InvalidInput('P, p_o, r and sigma', 'must hold one entry per problem, got '
                                                  f'{[len(a) for a in arrays]}')
    P_a, p_o_a, r_a, sigma_a = arrays
    P_a = P_a.copy()            # rows averaged to symmetry are written back
    for t in range(len(P_a)):
        try:
            P_a[t] = check_problem(P_a[t], p_o_a[t], r_a[t], sigma_a[t], measurement)[0]
        except InvalidInput as error:
            raise InvalidInput(f'{error.name} of problem {t}', error.reason) from None
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
        validate: check every input (default; :func:`check_problem`). The loops behind the
            boundary pass False: :class:`~formopt_ros.core.scenario.Scenario` has checked slot,
            r and sigma within the ranges checked here, and their EKF keeps P symmetric
            positive definite.

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
        validate: check every problem as :class:`Problem` does (default; :func:`check_batch`);
            the batched engine (behind the boundary), :meth:`stack` and :meth:`subset` pass
            False.
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
        if validate:            # numbers before np.full; cls checks every problem
            P = as_array('P', P, (-1, 3, 3))
            r, sigma = as_real('r', r), as_real('sigma', sigma)
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
