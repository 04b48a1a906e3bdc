"""RQ: the exact generalised-Rayleigh-quotient solver (beyond the paper).

Range: the gain is g(u) = u'Au / u'(B + R I)u over unit u = [cos t, sin t]; the unconstrained
maximiser is the top generalised eigenvector of (A, B + R I), and the constrained one follows
from the arc logic of :func:`range_plan_from_direction`.

Bearing: with h = [q0, q1, -1], g = h'Mh / h'Nh (M = P W^2 P, N = P + R e3 e3') is homogeneous
in h, so its only local maximum over the projective plane is the top generalised eigenvector of
(M, N). If that eigenvector maps into the q-disc (the image of the feasible disc under
p -> (-y, x)/|p|^2) it is the global optimum; otherwise the optimum lies on the boundary circle,
where the stationarity condition is a degree-3 trigonometric polynomial: the roots of one
degree-6 polynomial in z = e^{it}, each polished by Newton steps and evaluated.
"""
from __future__ import annotations

import math

import numpy as np

from formopt_ros.core.cost import Problem, point_from_q
from formopt_ros.core.strategies.base import PlanContext, Solution, Strategy, make_solution
from formopt_ros.core.strategies.common import (
    best_of, boundary_points, boundary_stationarity, gains_tie, polish_boundary_angles,
    range_plan_from_direction)

#: Distance of a root of the boundary polynomial from |z| = 1 up to which it counts as real.
UNIT_CIRCLE_TOLERANCE = 1e-3


def generalized_eigh(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and B-orthonormal eigenvectors (columns) of A v = lambda B v.

    B must be symmetric positive definite; uses a Cholesky reduction (cheap for 2x2 and 3x3).
    """
    L_inv = np.linalg.inv(np.linalg.cholesky(B))
    values, vectors = np.linalg.eigh(L_inv @ A @ L_inv.T)
    return values, L_inv.T @ vectors


def boundary_candidates(problem: Problem) -> np.ndarray:
    """Stationary points of the bearing gain on the disc boundary, shape (n, 2), m."""
    F = boundary_stationarity(problem)
    if np.max(np.abs(F)) == 0.0:              # the gain is constant on the circle
        return problem.p_o[None, :] + np.array([[problem.r, 0.0]])
    companion = np.diag(np.ones(5), -1).astype(complex)      # z^3 F(z), degree 6, monic
    companion[:, -1] = -F[:6] / F[6]
    roots = np.linalg.eigvals(companion) if abs(F[6]) > 0 else np.roots(F[::-1])
    near = np.abs(np.abs(roots) - 1.0) < UNIT_CIRCLE_TOLERANCE
    t = np.angle(roots[near] if np.any(near) else roots)
    return boundary_points(problem, polish_boundary_angles(F, t))


def rq_optimum(problem: Problem, method: str = 'rq') -> Solution:
    """Exact optimum of problem Pi_1 through generalised eigenvalues (see module docstring)."""
    if problem.measurement == 'range':
        A = problem.M[:2, :2]
        B = problem.P[:2, :2] + problem.R * np.eye(2)
        values, vectors = generalized_eigh(A, B)
        theta_star = math.atan2(vectors[1, 1], vectors[0, 1])
        return range_plan_from_direction(problem, theta_star,
                                         gains_tie(problem, values[1], values[0]), 1, method)
    values, vectors = generalized_eigh(problem.M, problem.N)
    top = vectors[:, 2]
    centre, rho = problem.q_disc()
    if abs(top[2]) > 1e-300:
        q = -top[:2] / top[2]
        if math.hypot(q[0] - centre[0], q[1] - centre[1]) < rho:
            return make_solution(problem, point_from_q(q), method, False, 1,
                                 details={'interior': True})
    points = boundary_candidates(problem)
    best, _ = best_of(problem, points)
    return make_solution(problem, points[best], method, True, 1 + len(points),
                         details={'interior': False})


class RayleighQuotient(Strategy):
    """RQ: the exact generalised-Rayleigh-quotient solver (beyond the paper)."""

    name = 'rq'

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The exact greedy optimum."""
        return rq_optimum(problem, self.name)
