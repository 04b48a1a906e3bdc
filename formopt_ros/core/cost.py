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
"""
from __future__ import annotations

import math
from dataclasses import InitVar, dataclass, field

import numpy as np

from formopt_ros.core.model import MEASUREMENT_KINDS, RANGE


def weight_vector(p_o: np.ndarray) -> np.ndarray:
    """Diagonal of W = diag(1, 1, |p_o|), shape (3,): heading error weighted by the slot range."""
    return np.array([1.0, 1.0, math.hypot(p_o[0], p_o[1])])


def weighted_trace(P: np.ndarray, p_o: np.ndarray) -> float:
    """tr(W P W) for a 3x3 covariance P (m^2); the paper's uncertainty metric (eq. 20)."""
    w = weight_vector(p_o)
    return float(np.dot(w * w, np.diag(P)))


def _check_finite(name: str, value: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(value, dtype=float)
    if arr.shape != shape:
        raise ValueError(f'{name} must have shape {shape}, got shape {arr.shape}')
    if not np.all(np.isfinite(arr)):
        raise ValueError(f'{name} must be finite, got {arr.tolist()}')
    return arr


def _check_positive(name: str, value: float, unit: str) -> float:
    number = float(value)
    if not math.isfinite(number) or number <= 0.0:
        raise ValueError(f'{name} must be a finite number > 0 ({unit}), got {value!r}')
    return number


def check_covariance(P: np.ndarray, name: str = 'P') -> np.ndarray:
    """Return P as a float (3, 3) array or raise ValueError if it is not symmetric PD."""
    P = _check_finite(name, P, (3, 3))
    scale = float(np.abs(P).max())
    asym = float(np.abs(P - P.T).max())
    if asym > 1e-9 * max(scale, 1e-300):
        raise ValueError(f'{name} must be symmetric, got max |P - P^T| = {asym:.3g} '
                         f'(max |P| = {scale:.3g})')
    P = 0.5 * (P + P.T)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        eig = np.linalg.eigvalsh(P)
        raise ValueError(f'{name} must be positive definite, got eigenvalues {eig.tolist()}'
                         ) from None
    return P


@dataclass(frozen=True)
class Problem:
    """Problem Pi_1 of the paper: choose p with |p - p_o| <= r minimising tr(W P_post W).

    Attributes:
        P: prior covariance of [x, y, phi] at the next step, shape (3, 3) (m^2, m rad, rad^2).
        p_o: formation slot in the leader frame, shape (2,), m.
        r: allowed deviation from the slot, m; 0 < r < |p_o| (the disc must not reach the leader).
        sigma: measurement noise standard deviation, m (range) or rad (bearing).
        measurement: 'range' or 'bearing'.
        (derived) w: diagonal of W; M: P W^2 P; N: P + R e3 e3'; base_cost: tr(W P W).
        validate: check every input (default). The simulator passes False for covariances its
            own EKF produced, which are symmetric positive definite by construction.
    """

    P: np.ndarray
    p_o: np.ndarray
    r: float
    sigma: float
    measurement: str
    validate: InitVar[bool] = True
    w: np.ndarray = field(init=False, repr=False)
    M: np.ndarray = field(init=False, repr=False)
    base_cost: float = field(init=False, repr=False)
    numerator_coefficients: np.ndarray = field(init=False, repr=False)
    denominator_coefficients: np.ndarray = field(init=False, repr=False)
    N: np.ndarray = field(init=False, repr=False)

    def __post_init__(self, validate: bool) -> None:
        if validate:
            if self.measurement not in MEASUREMENT_KINDS:
                raise ValueError(f'measurement must be one of {MEASUREMENT_KINDS}, '
                                 f'got {self.measurement!r}')
            P = check_covariance(self.P)
            p_o = _check_finite('p_o', self.p_o, (2,))
            r = _check_positive('r', self.r, 'm')
            unit = 'm' if self.measurement == RANGE else 'rad'
            sigma = _check_positive('sigma', self.sigma, unit)
            d_o = math.hypot(p_o[0], p_o[1])
            if r >= d_o:
                raise ValueError(f'r must be smaller than |p_o| = {d_o:.6g} m so that the disc '
                                 f'does not reach the leader, got r = {r:.6g} m')
        else:
            P, p_o, r, sigma = self.P, self.p_o, float(self.r), float(self.sigma)
        w = weight_vector(p_o)
        M = (P * (w * w)) @ P                      # P W^2 P
        R = sigma * sigma
        N = P.copy()                               # P + R e3 e3', the bearing denominator
        N[2, 2] += R
        if self.measurement == RANGE:
            num = np.array([M[0, 0], 2 * M[0, 1], M[1, 1], 0.0])
            den = np.array([P[0, 0], 2 * P[0, 1], P[1, 1], R])
        else:
            num = np.array([M[0, 0], 2 * M[0, 1], M[1, 1], -2 * M[0, 2], -2 * M[1, 2], M[2, 2]])
            den = np.array([N[0, 0], 2 * N[0, 1], N[1, 1], -2 * N[0, 2], -2 * N[1, 2], N[2, 2]])
        for name, value in (('P', P), ('p_o', p_o), ('r', r), ('sigma', sigma), ('w', w),
                            ('M', M), ('N', N), ('base_cost', weighted_trace(P, p_o)),
                            ('numerator_coefficients', num),
                            ('denominator_coefficients', den)):
            object.__setattr__(self, name, value)

    @property
    def d_o(self) -> float:
        """Distance of the formation slot from the leader, m."""
        return float(self.w[2])

    @property
    def R(self) -> float:
        """Measurement noise variance, m^2 or rad^2."""
        return self.sigma * self.sigma

    def monomials(self, points: np.ndarray) -> np.ndarray:
        """Monomials of the gain's quadratic forms at points (n, 2) in {L} (m); shape (n, k)."""
        x, y = points[:, 0], points[:, 1]
        d2 = x * x + y * y
        if self.measurement == RANGE:
            out = np.empty((len(points), 4))
            out[:, 0], out[:, 1], out[:, 2], out[:, 3] = x * x / d2, x * y / d2, y * y / d2, 1.0
            return out
        q0, q1 = -y / d2, x / d2
        out = np.empty((len(points), 6))
        out[:, 0], out[:, 1], out[:, 2] = q0 * q0, q0 * q1, q1 * q1
        out[:, 3], out[:, 4], out[:, 5] = q0, q1, 1.0
        return out

    def gain_from_monomials(self, monomials: np.ndarray) -> np.ndarray:
        """Information gain tr(W P W) - tr(W P_post W) from precomputed monomials, shape (n,)."""
        return (monomials @ self.numerator_coefficients) / (
            monomials @ self.denominator_coefficients)

    def gain(self, points: np.ndarray) -> np.ndarray:
        """Information gain (m^2) at points of shape (n, 2) or (2,) in {L}, m."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        return self.gain_from_monomials(self.monomials(pts))

    def cost(self, points: np.ndarray) -> np.ndarray | float:
        """tr(W P_post W) (m^2) at points (n, 2) -> (n,), or at one point (2,) -> float."""
        values = self.base_cost - self.gain(points)
        return float(values[0]) if np.ndim(points) == 1 else values

    def feasible(self, point: np.ndarray, tol: float = 1e-9) -> bool:
        """True when |point - p_o| <= r (1 + tol)."""
        return bool(math.hypot(point[0] - self.p_o[0], point[1] - self.p_o[1])
                    <= self.r * (1.0 + tol))

    # --- geometry of the feasible disc -------------------------------------------------------
    def bearing_arc(self) -> tuple[float, float]:
        """(theta_o, delta): the disc is seen from the leader at bearings theta_o +- delta, rad."""
        return math.atan2(self.p_o[1], self.p_o[0]), math.asin(self.r / self.d_o)

    def q_disc(self) -> tuple[np.ndarray, float]:
        """Image of the disc under p -> q = (-y, x)/|p|^2: (centre (2,), radius), 1/m.

        Inversion maps the disc |p - c| <= r (origin outside) to the disc with centre
        c / (|c|^2 - r^2) and radius r / (|c|^2 - r^2); the 90 degree turn follows.
        """
        k = 1.0 / (self.d_o ** 2 - self.r ** 2)
        return np.array([-self.p_o[1] * k, self.p_o[0] * k]), self.r * k


def point_from_q(q: np.ndarray) -> np.ndarray:
    """Inverse of p -> q = (-y, x)/|p|^2: p = (q1, -q0)/|q|^2, for q of shape (..., 2)."""
    q = np.asarray(q, dtype=float)
    n2 = np.sum(q * q, axis=-1, keepdims=True)
    return np.stack([q[..., 1], -q[..., 0]], axis=-1) / n2
