"""The planning problem of a follower measuring range and bearing at once (docs/range_bearing.md).

With H = [h_d'; h_beta'] (2, 3) at a candidate position p in {L} (eqs. 16 and 18 stacked),
S = H P H' + R and R = diag(sigma_d^2, sigma_beta^2), the update leaves

    cost(p) = tr(W P_post W) = tr(W P W) - gain(p),   gain(p) = tr(S^-1 H M H'),   M = P W^2 P,

a ratio of two polynomials in p (the 2 x 2 inverse: gain = (t00 s11 - 2 t01 s01 + t11 s00) /
det S with T = H M H'), no longer a scalar Rayleigh quotient. :class:`StackedProblem` has the
attributes and cost methods of :class:`~formopt_ros.core.cost.Problem` that the strategies use
(``slot``, ``base_cost``, ``gain_at``, ``cost``, ...), so MTF, CRM, MME and GBS run on it; the
certified solver is :mod:`formopt_ros.core.strategies.stacked`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from formopt_ros.core.checks import as_real
from formopt_ros.core.cost import SIGMA_RANGE, check_problem
from formopt_ros.core.formulas import trace_entries
from formopt_ros.core.model import RANGE, RANGE_BEARING, ekf_update_stacked


class StackedProblem:
    """Choose p with |p - p_o| <= r minimising tr(W P_post W) after a range and a bearing.

    Attributes:
        P: prior covariance of [x, y, phi], (3, 3) (m^2, m rad, rad^2).
        p_o: formation slot in {L}, (2,), m.
        r: allowed deviation, m (the bounds of :class:`~formopt_ros.core.cost.Problem`).
        sigma: range noise standard deviation, m.
        sigma_bearing: bearing noise standard deviation, rad.
        measurement: 'range-bearing'.
        validate: check the inputs as :class:`~formopt_ros.core.cost.Problem` does.

    Derived: ``slot`` (floats), ``d_o`` = |p_o|, ``R`` = (sigma_d^2, sigma_beta^2), ``w22`` =
    |p_o|^2, ``M`` = P W^2 P (3, 3), ``base_cost`` = tr(W P W) (m^2).
    """

    measurement = RANGE_BEARING

    def __init__(self, P: Any, p_o: Any, r: float, sigma: float, sigma_bearing: float,
                 validate: bool = True) -> None:
        if validate:
            P, p_o, r, sigma = check_problem(P, p_o, r, sigma, RANGE)[:4]
            sigma_bearing = as_real('sigma_bearing', sigma_bearing, *SIGMA_RANGE, unit='rad')
        self.P = np.asarray(P, dtype=float)
        self.p_o = np.asarray(p_o, dtype=float)
        self.r, self.sigma, self.sigma_bearing = float(r), float(sigma), float(sigma_bearing)
        self.slot = (float(self.p_o[0]), float(self.p_o[1]))
        self.d_o = math.hypot(*self.slot)
        self.w22 = self.d_o * self.d_o
        self.R = (self.sigma * self.sigma, self.sigma_bearing * self.sigma_bearing)
        self.w = np.array([1.0, 1.0, self.d_o])
        self.M = self.P @ np.diag(self.w * self.w) @ self.P
        self.M = 0.5 * (self.M + self.M.T)
        self._P, self._M = self.P.tolist(), self.M.tolist()
        P_ = self.P
        self.base_cost = float(trace_entries(float(P_[0, 0]), float(P_[1, 1]),
                                             float(P_[2, 2]), self.w22))

    def __repr__(self) -> str:
        return (f'StackedProblem(P={self.P.tolist()}, p_o={list(self.slot)}, r={self.r!r}, '
                f'sigma={self.sigma!r}, sigma_bearing={self.sigma_bearing!r})')

    # --- the cost -----------------------------------------------------------------------------
    def innovation_terms(self, x: Any, y: Any) -> tuple[Any, ...]:
        """(s00, s01, s11, t00, t01, t11) of S = H P H' + R and T = H M H' at points (x, y)
        (m; floats or arrays of one shape), with the rows h_d = (u_x, u_y, 0) = (x, y, 0) / d
        and h_beta = (b_x, b_y, -1) = (-y, x, 0) / d^2 - e3, their zeros and ones used."""
        d2 = x * x + y * y
        d = d2 ** 0.5
        ux, uy, bx, by = x / d, y / d, -y / d2, x / d2
        terms = []
        for A, noise in ((self._P, self.R), (self._M, (0.0, 0.0))):
            (a00, a01, a02), (_, a11, a12), (_, _, a22) = A
            ab0, ab1, ab2 = a00 * bx + a01 * by - a02, a01 * bx + a11 * by - a12, \
                a02 * bx + a12 * by - a22                                       # A h_beta
            terms.append((a00 * ux * ux + 2.0 * a01 * ux * uy + a11 * uy * uy + noise[0],
                          ux * ab0 + uy * ab1, bx * ab0 + by * ab1 - ab2 + noise[1]))
        (s00, s01, s11), (t00, t01, t11) = terms
        return s00, s01, s11, t00, t01, t11

    def gain_at(self, x: Any, y: Any) -> Any:
        """Information gain tr(W P W) - tr(W P_post W) (m^2) at points (x, y) in {L} (m), floats
        or arrays of one shape; -inf where it is not a finite number (the origin)."""
        scalar = not isinstance(x, np.ndarray) and not isinstance(y, np.ndarray)
        if scalar:
            x, y = float(x), float(y)
        with np.errstate(all='ignore'):
            try:
                s00, s01, s11, t00, t01, t11 = self.innovation_terms(
                    x if scalar else np.asarray(x, dtype=float),
                    y if scalar else np.asarray(y, dtype=float))
                gain = (t00 * s11 - 2.0 * t01 * s01 + t11 * s00) / (s00 * s11 - s01 * s01)
            except ZeroDivisionError:
                return -math.inf
        if scalar:
            return gain if -math.inf < gain < math.inf else -math.inf
        gain = np.where(np.isfinite(gain), gain, -np.inf)
        return gain if gain.ndim else gain[()]

    def gain(self, points: np.ndarray) -> np.ndarray:
        """Gain (m^2) at points (n, 2) or (2,), shape (n,)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        return self.gain_at(pts[:, 0], pts[:, 1])

    def cost_at(self, x: Any, y: Any) -> Any:
        """tr(W P_post W) (m^2) at points (x, y) (m; floats or arrays of one shape) with P_post
        in Joseph form, as the EKF computes it: accurate to a few units of rounding of the cost
        itself, where ``base_cost - gain_at`` carries rounding of tr(W P W) (the difference
        shows for very informative measurements)."""
        xa, ya = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        poses = np.stack([xa.ravel(), ya.ravel(), np.zeros(xa.size)], -1)
        P = np.broadcast_to(self.P, (xa.size, 3, 3))
        posterior = ekf_update_stacked(poses, P, np.zeros((xa.size, 2)), self.R)[1]
        values = (posterior[:, 0, 0] + posterior[:, 1, 1] + self.w22 * posterior[:, 2, 2])
        if np.ndim(x) == 0 and np.ndim(y) == 0:
            return float(values[0])
        return values.reshape(xa.shape)

    def cost(self, points: np.ndarray) -> np.ndarray | float:
        """tr(W P_post W) (m^2, :meth:`cost_at`) at points (n, 2) -> (n,), or at one point
        (2,) -> float."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        values = self.cost_at(pts[:, 0], pts[:, 1])
        return float(values[0]) if np.ndim(points) == 1 else values

    def posterior(self, p: Sequence[float]) -> np.ndarray:
        """P_post (3, 3) after the stacked update at p (2,) (Joseph form, as the EKF)."""
        x = np.array([float(p[0]), float(p[1]), 0.0])
        return ekf_update_stacked(x, self.P, np.zeros(2), self.R)[1]

    def feasible(self, point: np.ndarray | Sequence[float], tol: float = 1e-9) -> bool:
        """True when |point - p_o| <= r (1 + tol), for a point (2,) in m."""
        x_o, y_o = self.slot
        return bool(math.hypot(point[0] - x_o, point[1] - y_o) <= self.r * (1.0 + tol))


__all__ = ['StackedProblem']
