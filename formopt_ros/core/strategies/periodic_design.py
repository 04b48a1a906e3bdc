"""Offline design of the periodic boundary pattern: its exact steady state, search and cache.

A pattern is a cycle of ``m`` points on the disc boundary, ``p_k = p_o + r [cos a_k, sin a_k]``,
visited in turn. Under the noise-free recursion (the estimate lands on each target, zero
innovations) every move of the cycle has fixed Jacobians, so the covariance obeys a periodic
Riccati recursion. Each move (two propagation sub-steps, then one update) is a linear
fractional map P -> (A P + B)(C P + D)^-1 given by a 6 x 6 matrix (the symplectic form of the
Riccati map). The leader keeps one velocity (v, omega): straight, or on an arc, where the
follower's pose relative to the leader, hence every map, is as stationary as on a straight line
(the cycle lives in the leader's frame and turns with it):

    propagation  P -> Phi P Phi' + Q :  [[Phi, Q Phi^-T], [0, Phi^-T]]
    update       P -> (P^-1 + h h'/R)^-1:  [[I, 0], [h h'/R, I]]

The product over one period maps [X; Y] to [X'; Y'] with P = X Y^-1, so the periodic steady
state is P* = X Y^-1 on the invariant subspace of its three largest eigenvalues (they come in
pairs lambda, 1/lambda; the ratio of the 4th to the 3rd modulus is the convergence factor per
period). The same eigen-decomposition gives the whole future of the covariance from any start,
which the online switch test uses (:meth:`PatternDesign.future_costs`).

The search (:func:`design_pattern`): every two-point cycle of a 10 degree grid at once (batched
eigen-decompositions), Nelder-Mead on the best three; for m > 2, a short race of four seeds that
group the points near the two of the best pair, the two best refined in full, kept when better
than the pair repeated. A cycle that passes the leader closer than LINEARITY_MARGIN position
standard deviations is rejected: there the EKF's linearisation, hence the forecast, fails.
Designs are cached per :class:`SteadyConditions` and period (a study's trials share one).

Under a speed limit (or a safety distance) a boundary cycle jumps further than the follower can
go in a step; when it does not fit, :func:`design_within_reach` starts from greedy's own loop
over the reachable set and refines it (and 12 points sampled along it) by SLSQP under the
reach, disc and safety constraints, on the same exact periodic steady state.
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.formulas import weight_vector, weighted_trace
from formopt_ros.core.model import (
    EXACT, RANGE, RANGE_BEARING, ekf_update, ekf_update_stacked, measurement_jacobian,
    predict_measurement, propagate_state, transition_matrices)
from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.protocol import SUBSTEPS, motion_commands, predict_move
from formopt_ros.core.reach import CLEARANCE_FRACTION, Region, reach_centre
from formopt_ros.core.strategies.region import rq_target

if TYPE_CHECKING:
    from formopt_ros.core.scenario import Scenario

#: Coarse grid of boundary angles for the search of two-point patterns, degrees.
GRID_STEP_DEG = 10.0
#: Pairs of the coarse grid refined by Nelder-Mead.
REFINED_PAIRS = 3
#: Evaluations per angle of each seed of a longer pattern before the best seed is refined.
SEED_BUDGET = 40
#: Seeds of a longer pattern refined in full after the race.
RACE_WINNERS = 2
#: Spread of the points of one pair in the seeds of longer patterns, rad.
PAIR_SPREAD = math.radians(15.0)
#: The switch test looks ahead until the distance to the periodic regime shrinks by this factor.
SETTLE_FACTOR = 0.01
#: A cycle point must lie at least this many position standard deviations from the leader.
LINEARITY_MARGIN = 6.0
#: Designs kept in the cache.
CACHE_SIZE = 16
#: Within reach: greedy's run (steps) whose last GREEDY_STEADY steps give its steady cost and
#: loop; the longest loop refined as it is; the points of the cycle sampled along it; the
#: length, relative to the loop's, of a slower lap sampled along it; SLSQP's iteration cap, its
#: restarts from an end point outside the reachable set and the share of the reach it leaves
#: free; the relative tolerance of a cycle's moves in the reach disc.
GREEDY_STEPS, GREEDY_STEADY = 400, 133
#: A loop of greedy's targets repeats over its last LOOP_WINDOW steps (at least two laps),
#: within LOOP_TOLERANCE (|p_o| + r) (its bearing loops converge to about 1e-6 of that).
LOOP_WINDOW, LOOP_TOLERANCE = 20, 1e-5
REACH_LONGEST_LOOP = 40
REACH_SAMPLED = 12
REACH_STRETCH = 1.3
REACH_ITERATIONS = 300
REACH_RESTARTS = 2
REACH_SLACK = 1e-6
REACH_RTOL = 1e-9
REACH_FTOL = 1e-12


@dataclass(frozen=True)
class SteadyConditions:
    """The constants of a stationary planning problem: the cache key of a pattern.

    Attributes:
        measurement: 'range' or 'bearing'.
        p_o: formation slot (x, y) in the leader frame, m.
        r: disc radius, m.
        sigma: measurement noise standard deviation, m or rad.
        v_l, omega_l: the leader's constant velocity, m/s and rad/s.
        dt: sub-step length, s.
        sigma_v, sigma_omega: odometry noise standard deviations, m/s and rad/s.
        kinematics: the motion model, 'exact' or 'euler' (core/model.py).
        sigma_bearing: 'range-bearing' only: the bearing noise, rad (sigma is the range's).
        reach: the radius of the reach disc, max_speed * 2 dt, m (inf: no speed limit).
        safety: the safety distance from the leader, m (0: none).
    """

    measurement: str
    p_o: tuple[float, float]
    r: float
    sigma: float
    v_l: float
    omega_l: float
    dt: float
    sigma_v: float
    sigma_omega: float
    kinematics: str = EXACT
    sigma_bearing: float = 0.0
    reach: float = math.inf
    safety: float = 0.0

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> SteadyConditions | None:
        """The conditions at the start of ``scenario``; None when its leader's velocity
        changes from the first step to the next (an S-curve)."""
        v_l, omega_l = scenario.leader.velocity(0, scenario.dt)
        if scenario.leader.velocity(SUBSTEPS, scenario.dt) != (v_l, omega_l):
            return None
        return cls.at_velocity(scenario, v_l, omega_l)

    @classmethod
    def at_velocity(cls, scenario: Scenario, v_l: float, omega_l: float) -> SteadyConditions:
        """The conditions of ``scenario`` with the leader at (v_l m/s, omega_l rad/s)."""
        reach = math.inf if scenario.max_speed is None else \
            scenario.max_speed * SUBSTEPS * scenario.dt
        return cls(scenario.measurement, scenario.p_o, scenario.r, scenario.sigma, v_l, omega_l,
                   scenario.dt, scenario.sigma_v, scenario.sigma_omega, scenario.kinematics,
                   scenario.sigma_bearing, reach, scenario.safety_distance)

    @property
    def slot(self) -> np.ndarray:
        """p_o, shape (2,), m."""
        return np.array(self.p_o, dtype=float)

    @property
    def leader(self) -> tuple[tuple[float, float], ...]:
        """The leader velocity (v m/s, omega rad/s) per sub-step."""
        return ((self.v_l, self.omega_l),) * SUBSTEPS

    def close_to(self, other: SteadyConditions, tolerance: float) -> bool:
        """True when ``other`` has the same sensor, slot, disc and safety distance (exactly: a
        cycle must stay in the disc), a speed limit when this has one, and noise levels, leader
        velocity, dt and reach within ``tolerance`` (relative)."""
        if (self.measurement, self.p_o, self.r, self.kinematics) != \
                (other.measurement, other.p_o, other.r, other.kinematics):
            return False
        if (math.isfinite(self.reach), self.safety) != (math.isfinite(other.reach), other.safety):
            return False
        mine = (self.sigma, self.v_l, self.omega_l, self.dt, self.sigma_v, self.sigma_omega,
                self.sigma_bearing, self.reach if self.limited else 0.0)
        theirs = (other.sigma, other.v_l, other.omega_l, other.dt, other.sigma_v,
                  other.sigma_omega, other.sigma_bearing,
                  other.reach if other.limited else 0.0)
        return all(abs(a - b) <= tolerance * max(abs(a), abs(b)) for a, b in zip(mine, theirs))

    @property
    def limited(self) -> bool:
        """True under a speed limit (a finite reach)."""
        return math.isfinite(self.reach)

    def region(self, x: np.ndarray) -> Region | None:
        """The reachable set of a step from pose x (3,) (None: the paper's protocol)."""
        if not self.limited and not self.safety > 0.0:
            return None
        centre = reach_centre(x, self.leader, self.dt, self.kinematics) if self.limited \
            else None
        return Region(self.p_o, self.r, centre, self.reach, self.safety)

    def boundary_points(self, angles: np.ndarray) -> np.ndarray:
        """Points p_o + r [cos a, sin a] (n, 2), m, for angles a (n,), rad."""
        a = np.asarray(angles, dtype=float)
        return self.slot + self.r * np.stack([np.cos(a), np.sin(a)], axis=-1)

    def problem(self, P: np.ndarray) -> Problem:
        """The paper's one-step problem with prior P (3, 3) (trusted, not validated); a
        :class:`~formopt_ros.core.stacked.StackedProblem` for 'range-bearing'."""
        if self.measurement == RANGE_BEARING:
            return StackedProblem(P, self.slot, self.r, self.sigma,  # type: ignore[return-value]
                                  self.sigma_bearing, False)
        return Problem(P, self.slot, self.r, self.sigma, self.measurement, False)

    def information(self, x: np.ndarray) -> np.ndarray:
        """H' R^-1 H (3, 3) of the measurement at pose x (3,), or (B, 3, 3) at poses (B, 3)
        (both rows for 'range-bearing')."""
        if self.measurement != RANGE_BEARING:
            h = measurement_jacobian(self.measurement, x)
            return h[..., :, None] * h[..., None, :] / (self.sigma * self.sigma)
        rows = measurement_jacobian(RANGE_BEARING, x)
        h_d, h_b = rows[..., 0, :], rows[..., 1, :]
        return h_d[..., :, None] * h_d[..., None, :] / (self.sigma * self.sigma) + \
            h_b[..., :, None] * h_b[..., None, :] / (self.sigma_bearing * self.sigma_bearing)


def noise_free_step(x: np.ndarray, P: np.ndarray, target: np.ndarray,
                    conditions: SteadyConditions) -> tuple[np.ndarray, np.ndarray]:
    """Drive from pose x (3,) to target (2,) and measure there with zero innovation.

    Returns the EKF's (x, P) after the update: the covariance the filter will have when the
    estimate lands on target, the noise-free recursion of the planners.
    """
    c = conditions
    x, P = predict_move(x, P, target, c.leader, c.dt, c.sigma_v, c.sigma_omega, c.kinematics)
    if c.measurement == RANGE_BEARING:
        x, P, _, _ = ekf_update_stacked(x, P, predict_measurement(RANGE_BEARING, x),
                                        (c.sigma * c.sigma, c.sigma_bearing * c.sigma_bearing))
        return x, P
    x, P, _, _ = ekf_update(x, P, predict_measurement(c.measurement, x), c.measurement,
                            c.sigma * c.sigma)
    return x, P


def greedy_target(x: np.ndarray, P: np.ndarray, conditions: SteadyConditions) -> np.ndarray:
    """RQ's choice from posterior (x, P): the exact optimum with the paper's planning prior,
    over the step's reachable set under a speed limit or a safety distance."""
    c = conditions
    prior = predict_move(x, P, c.slot, c.leader, c.dt, c.sigma_v, c.sigma_omega,
                         c.kinematics)[1]
    return rq_target(c.problem(prior), c.region(x))


def lft(M: np.ndarray, P: np.ndarray) -> np.ndarray:
    """The linear fractional maps of 6 x 6 matrices M (n, 6, 6): (A P + B)(C P + D)^-1 for P
    (n, 3, 3); NaN rows where C P + D is singular (a recursion that blew up)."""
    X = M[:, :3, :3] @ P + M[:, :3, 3:]
    Y = M[:, 3:, :3] @ P + M[:, 3:, 3:]
    return np.swapaxes(solve_rows(np.swapaxes(Y, 1, 2), np.swapaxes(X, 1, 2)), 1, 2)


def move_maps(x: np.ndarray, targets: np.ndarray, conditions: SteadyConditions,
              leader: tuple[Any, Any] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The 6 x 6 symplectic maps (B, 6, 6) of B steps (drive from poses x (B, 3) to targets
    (B, 2), measure there) and the poses (B, 3) at the targets; see the module docstring. The
    protocol's commands (:func:`.protocol.motion_commands`), batched. ``leader``: the leader's
    (v m/s, omega rad/s) of each step, arrays (B,), in place of the conditions' own."""
    c = conditions
    v_l, omega_l = (c.v_l, c.omega_l) if leader is None else leader
    command = motion_commands(x, targets, c.dt, v_l, omega_l, c.kinematics)
    Phi, GQG = np.eye(3), np.zeros((3, 3))       # the sub-steps composed: P -> Phi P Phi' + GQG
    for v_f, omega_f in zip(command.linear, command.angular):
        Phi_j, GQG_j = transition_matrices(x, v_f, omega_f, c.dt, v_l, omega_l, c.sigma_v,
                                           c.sigma_omega, kinematics=c.kinematics)
        Phi, GQG = Phi_j @ Phi, Phi_j @ GQG @ np.swapaxes(Phi_j, 1, 2) + GQG_j
        x = propagate_state(x, v_f, omega_f, c.dt, v_l, omega_l, c.kinematics)
    Phi_inv_t = np.swapaxes(np.linalg.inv(Phi), 1, 2)
    M = np.zeros((len(x), 6, 6))
    M[:, :3, :3], M[:, :3, 3:], M[:, 3:, 3:] = Phi, GQG @ Phi_inv_t, Phi_inv_t
    M[:, 3:] += c.information(x) @ M[:, :3]
    return M, x


def arrival_poses(starts: np.ndarray, targets: np.ndarray, conditions: SteadyConditions,
                  leader: tuple[Any, Any] | None = None) -> np.ndarray:
    """The poses (B, 3) at targets (B, 2) after the protocol's moves from positions starts
    (B, 2) (the heading there does not matter: the protocol turns towards the target first);
    ``leader`` as in :func:`move_maps`."""
    c = conditions
    v_l, omega_l = (c.v_l, c.omega_l) if leader is None else leader
    x = np.concatenate([starts, np.zeros((len(starts), 1))], axis=1)
    command = motion_commands(x, targets, c.dt, v_l, omega_l, c.kinematics)
    for v_f, omega_f in zip(command.linear, command.angular):
        x = propagate_state(x, v_f, omega_f, c.dt, v_l, omega_l, c.kinematics)
    return x


def move_map(x: np.ndarray, target: np.ndarray,
             conditions: SteadyConditions) -> tuple[np.ndarray, np.ndarray]:
    """:func:`move_maps` of one step: its map (6, 6) and the pose (3,) at the target."""
    M, pose = move_maps(x[None], np.asarray(target, dtype=float)[None], conditions)
    return M[0], pose[0]


def solve_rows(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """A^-1 B for stacks A (n, k, k) and B (n, k, m); NaN rows where A is singular (an
    invariant subspace whose lower block is singular has no P = X Y^-1)."""
    try:
        return np.linalg.solve(A, B)
    except np.linalg.LinAlgError:
        out = np.full(B.shape, np.nan, dtype=np.result_type(A, B))
        for i in range(len(A)):
            try:
                out[i] = np.linalg.solve(A[i], B[i])
            except np.linalg.LinAlgError:
                pass
        return out


def periodic_solutions(M: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steady states of period maps M (n, 6, 6): P (n, 3, 3), the convergence factor per
    period (n,) and which rows have a unique positive definite steady state (n,) bool (the
    others leave a direction unobservable, or their product overflowed; their P and factor
    are meaningless)."""
    finite = np.all(np.isfinite(M), axis=(1, 2))
    values, vectors = np.linalg.eig(np.where(finite[:, None, None], M, np.eye(6)))
    order = np.argsort(-np.abs(values), axis=-1)
    moduli = np.take_along_axis(np.abs(values), order, axis=-1)
    dominant = np.take_along_axis(vectors, order[:, None, :3], axis=-1)       # (n, 6, 3)
    valid = finite & np.all(np.isfinite(moduli), axis=-1) & \
        (moduli[:, 2] > (1.0 + 1e-9) * moduli[:, 3])
    X, Y = dominant[:, :3], dominant[:, 3:]
    Y = np.where(valid[:, None, None], Y, np.eye(3))                # keep singular rows solvable
    P = np.real(np.swapaxes(solve_rows(np.swapaxes(Y, 1, 2), np.swapaxes(X, 1, 2)), 1, 2))
    P = 0.5 * (P + np.swapaxes(P, 1, 2))
    valid &= np.all(np.isfinite(P), axis=(1, 2))
    P = np.where(valid[:, None, None], P, np.eye(3))
    valid &= np.linalg.eigvalsh(P)[:, 0] > 0.0
    return P, moduli[:, 3] / np.maximum(moduli[:, 2], 1e-300), valid


@dataclass(frozen=True)
class PatternDesign:
    """A periodic boundary pattern for one :class:`SteadyConditions`, with its steady state.

    Phase k is the state just after the measurement at ``points[k]``; the next target is
    ``points[(k + 1) % m]``.

    Attributes:
        conditions: what it was designed for.
        angles: angles a_k (m,) of the points around p_o, rad (a boundary cycle:
            p_k = p_o + r [cos a_k, sin a_k]; a cycle within reach has inner points too).
        points: the pattern's points (m, 2), leader frame, m.
        posteriors: steady posterior covariance at each phase (m, 3, 3).
        costs: tr(W P W) of those posteriors (m,), m^2.
        steady_cost: their mean, the pattern's long-run value, m^2.
        decay: convergence factor of the covariance towards the steady state per period.
        horizon: steps the switch test looks ahead (until the decay reaches SETTLE_FACTOR).
        moves: symplectic map (m, 6, 6) of the move into each phase.
        design_time_s: wall time of the search, s.
        evaluations: patterns evaluated by the search.
    """

    conditions: SteadyConditions
    angles: np.ndarray
    points: np.ndarray
    posteriors: np.ndarray
    costs: np.ndarray
    steady_cost: float
    decay: float
    horizon: int
    moves: np.ndarray
    design_time_s: float
    evaluations: int

    @property
    def period(self) -> int:
        """Number of points m."""
        return len(self.points)

    def future_costs(self, phase: int, P: np.ndarray, steps: int) -> np.ndarray:
        """tr(W P W) (steps,) after each of the next ``steps`` pattern steps, m^2.

        Starts from the posterior P (3, 3) at ``phase`` (the follower at points[phase] with the
        pattern's heading) and uses the eigen-decomposition of the period map starting there,
        so the cost does not grow with ``steps``.
        """
        m = self.period
        partial = np.empty((m, 6, 6))             # maps from `phase` to phase + i + 1
        product = np.eye(6)
        for i in range(m):
            product = self.moves[(phase + 1 + i) % m] @ product
            partial[i] = product
        # [X; Y] after n periods = V_d D_d^n C_d + V_s D_s^n C_s (dominant / subdominant
        # eigenpairs, C = V^-1 [P; I]); right-multiplying by (D_d^n C_d)^-1 leaves X Y^-1
        # unchanged and gives V_d + V_s (G o R^n) with G = C_s C_d^-1, R_ij = l_s,i / l_d,j,
        # |R_ij| < 1: no overflow however long the horizon.
        values, vectors = np.linalg.eig(product)
        order = np.argsort(-np.abs(values))
        dominant, subdominant = order[:3], order[3:]
        coefficients = np.linalg.solve(vectors, np.vstack([P, np.eye(3)]))
        G = np.linalg.solve(coefficients[dominant].T, coefficients[subdominant].T).T
        ratio = values[subdominant][:, None] / values[dominant][None, :]
        periods = -(-steps // m)
        powers = ratio[None] ** np.arange(periods)[:, None, None]          # (periods, 3, 3)
        Z = vectors[:, dominant][None] + vectors[:, subdominant] @ (G * powers)
        Z = (partial[None] @ Z[:, None]).reshape(-1, 6, 3)[:steps]
        return _weighted_ratio_trace(Z[:, :3], Z[:, 3:], weight_vector(self.conditions.slot))

    def rollout_costs(self, x: np.ndarray, P: np.ndarray, phase: int,
                      steps: int) -> np.ndarray:
        """tr(W P W) (steps,) after each of the next ``steps`` steps when the follower, at pose
        x (3,) with posterior P (3, 3), joins the pattern at points[phase].

        The first two steps (into the pattern, then its first regular move, whose heading still
        comes from x) are computed exactly; the rest by :meth:`future_costs`.
        """
        m, c = self.period, self.conditions
        head = []
        for i in range(min(2, steps)):
            x, P = noise_free_step(x, P, self.points[(phase + i) % m], c)
            head.append(weighted_trace(P, c.slot))
        if steps <= 2:
            return np.array(head)
        return np.concatenate([head, self.future_costs((phase + 1) % m, P, steps - 2)])


def _weighted_ratio_trace(X: np.ndarray, Y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """tr(W X Y^-1 W) (n,) for stacks X, Y (n, 3, 3) (complex allowed; the real part), with
    Y^-1 by its adjugate: element-wise arithmetic on (n,) columns, several times faster than
    a stacked LAPACK solve of 3 x 3 systems."""
    (a, b, c), (d, e, f), (g, h, i) = (Y[:, 0, 0], Y[:, 0, 1], Y[:, 0, 2]), \
        (Y[:, 1, 0], Y[:, 1, 1], Y[:, 1, 2]), (Y[:, 2, 0], Y[:, 2, 1], Y[:, 2, 2])
    inverse = ((e * i - f * h, c * h - b * i, b * f - c * e),     # adj(Y), row by row
               (f * g - d * i, a * i - c * g, c * d - a * f),
               (d * h - e * g, b * g - a * h, a * e - b * d))
    det = a * inverse[0][0] + b * inverse[1][0] + c * inverse[2][0]
    total = sum(w[j] * w[j] * (X[:, j, 0] * inverse[0][j] + X[:, j, 1] * inverse[1][j]
                               + X[:, j, 2] * inverse[2][j]) for j in range(3))
    return np.real(total / det)


def cycle_maps(points: np.ndarray, conditions: SteadyConditions | Sequence[SteadyConditions]
               ) -> np.ndarray:
    """Symplectic maps (m, 6, 6) of the moves into each of the cycle's points (m, 2), with
    the cycle's headings (the heading at a point is that of the move into it). ``conditions``:
    one for every move, or those of each move (a cycle locked to a leader path's phase)."""
    return _cycle_moves(points, _per_move(conditions, len(points)))[1]


def perturbed_cycle_maps(points: np.ndarray,
                         conditions: SteadyConditions | Sequence[SteadyConditions],
                         steps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The move maps of a cycle (m, 2) and of its 2m forward-difference perturbations, the
    flattened coordinate i moved by steps[i] (2m,), m: maps (2m + 1, m, 6, 6) and points
    (2m + 1, m, 2), the unperturbed cycle first.

    The pose at a point does not depend on the heading before the move into it (the protocol
    turns towards the target first), so the map of the move into point k depends on points
    k-2, k-1 and k only: a perturbation costs three move maps, not a whole cycle (all of
    them computed in one batch: the leader's velocity is given per move).
    """
    m = len(points)
    phases = _per_move(conditions, m)
    starts, maps = _cycle_moves(points, phases)
    batch_maps = np.repeat(maps[None], 2 * m + 1, axis=0)
    batch_points = np.repeat(points[None], 2 * m + 1, axis=0)
    rows = np.arange(1, 2 * m + 1)
    j = np.arange(2 * m) // 2
    after, later = (j + 1) % m, (j + 2) % m
    batch_points[rows, j, np.arange(2 * m) % 2] += steps
    moved, next_point = batch_points[rows, j], batch_points[rows, after]
    batch_maps[rows, j] = _maps_into(starts[j], moved, phases[j])
    pose_j = _grouped(arrival_poses, batch_points[rows, j - 1], moved, phases[j])
    batch_maps[rows, after] = _maps_into(pose_j, next_point, phases[after])
    pose_after = _grouped(arrival_poses, moved, next_point, phases[after])
    batch_maps[rows, later] = _maps_into(pose_after, batch_points[rows, later], phases[later])
    return batch_maps, batch_points


def _cycle_moves(points: np.ndarray, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each point k of a cycle (m, 2): the pose (m, 3) at point k - 1 where the move into
    k starts, and the map (m, 6, 6) of that move, with the conditions phases[k] (m,)."""
    starts = _grouped(arrival_poses, np.roll(points, 2, axis=0), np.roll(points, 1, axis=0),
                      np.roll(phases, 1))
    return starts, _maps_into(starts, points, phases)


def _maps_into(x: np.ndarray, targets: np.ndarray, phases: np.ndarray) -> np.ndarray:
    """The maps (B, 6, 6) of moves from poses x (B, 3) into targets (B, 2), each with the
    conditions of its row of phases (B,)."""
    return _grouped(lambda *args: move_maps(*args)[0], x, targets, phases)


def forward_difference(costs: np.ndarray, points: np.ndarray) -> np.ndarray:
    """The gradient (2m,) from the costs (2m + 1,) and points (2m + 1, m, 2) of
    :func:`perturbed_cycle_maps` (the step each coordinate really moved); 0 where a perturbed
    cycle has no steady state."""
    moved = (points[1:] - points[0]).reshape(len(costs) - 1, -1).sum(axis=1)
    with np.errstate(invalid='ignore'):
        gradient = (costs[1:] - costs[0]) / moved
    return np.where(np.isfinite(gradient), gradient, 0.0)


def _per_move(conditions: SteadyConditions | Sequence[SteadyConditions],
              m: int) -> np.ndarray:
    """The conditions of each of m moves, an object array (m,)."""
    out = np.empty(m, dtype=object)
    out[:] = [conditions] * m if isinstance(conditions, SteadyConditions) else list(conditions)
    return out


def _grouped(function: Callable[..., np.ndarray], x: np.ndarray, targets: np.ndarray,
             phases: np.ndarray) -> np.ndarray:
    """function(x, targets, conditions, leader) on batches (B, ...) whose rows have their own
    conditions phases (B,): one call for all rows whose conditions differ at most in the
    leader's velocity, passed per row as ``leader`` = (v_l (n,), omega_l (n,))."""
    first = phases[0]
    if all(phase is first for phase in phases):
        return function(x, targets, first, None)
    groups: dict[SteadyConditions, int] = {}
    code_of: dict[int, int] = {}
    for phase in phases:
        if id(phase) not in code_of:
            shared = replace(phase, v_l=0.0, omega_l=0.0)
            code_of[id(phase)] = groups.setdefault(shared, len(groups))
    codes = np.array([code_of[id(phase)] for phase in phases])
    velocities = np.array([(phase.v_l, phase.omega_l) for phase in phases])
    out: np.ndarray | None = None
    for shared, code in groups.items():
        rows = np.flatnonzero(codes == code)
        result = function(x[rows], targets[rows], shared,
                          (velocities[rows, 0], velocities[rows, 1]))
        if out is None:
            out = np.empty((len(phases),) + result.shape[1:])
        out[rows] = result
    assert out is not None
    return out


def evaluate_cycles(maps: np.ndarray, points: np.ndarray, conditions: SteadyConditions
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steady states of n cycles given by their move maps (n, m, 6, 6) and points (n, m, 2).

    Returns the mean steady tr(W P W) (n,), m^2 (inf for a cycle without a steady state or
    passing the leader closer than LINEARITY_MARGIN position standard deviations), the steady
    posteriors (n, m, 3, 3) and the convergence factors per period (n,).
    """
    period_maps = maps[:, 0]
    with np.errstate(over='ignore', invalid='ignore'):    # a long unstable cycle: no state
        for k in range(1, maps.shape[1]):
            period_maps = maps[:, k] @ period_maps
    P, decay, valid = periodic_solutions(period_maps)     # posterior at the last phase
    posteriors = np.empty(maps.shape[:2] + (3, 3))
    for k in range(maps.shape[1]):
        P = lft(maps[:, k], P)
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
        posteriors[:, k] = P
    w2 = weight_vector(conditions.slot) ** 2
    costs = np.einsum('i,nmii->nm', w2, posteriors)
    valid &= np.all(np.isfinite(costs) & (costs > 0.0), axis=1)
    # the EKF linearises the measurement at each point: the position uncertainty the follower
    # carries there (that of the previous phase) must be small against its distance to the
    # leader, else the noise-free recursion is no forecast (the filter can diverge)
    spread = np.sqrt(np.abs(np.linalg.eigvalsh(
        np.where(valid[:, None, None, None], posteriors, np.eye(3))[..., :2, :2])[..., -1]))
    distance = np.hypot(points[..., 0], points[..., 1])
    valid &= np.all(distance >= LINEARITY_MARGIN * np.roll(spread, 1, axis=1), axis=1)
    return np.where(valid, costs.mean(axis=1), np.inf), posteriors, decay


def evaluate_pattern(angles: np.ndarray, conditions: SteadyConditions
                     ) -> tuple[float, np.ndarray, float, np.ndarray]:
    """One cycle with boundary angles (m,), rad: (mean steady tr(W P W) m^2 or inf, steady
    posteriors (m, 3, 3), convergence factor per period, move maps (m, 6, 6)); see
    :func:`evaluate_cycles`."""
    points = conditions.boundary_points(angles)
    maps = cycle_maps(points, conditions)
    costs, posteriors, decay = evaluate_cycles(maps[None], points[None], conditions)
    return float(costs[0]), posteriors[0], float(decay[0]), maps


def pair_grid(conditions: SteadyConditions, step_deg: float = GRID_STEP_DEG
              ) -> tuple[np.ndarray, np.ndarray]:
    """Every two-point cycle of a grid of boundary angles: pairs of angles (n, 2), rad, and
    their mean steady tr(W P W) (n,), m^2, with one move map per ordered pair of grid points."""
    angles = np.radians(np.arange(0.0, 360.0, step_deg))
    points = conditions.boundary_points(angles)
    count = len(angles)
    i, j = np.nonzero(~np.eye(count, dtype=bool))
    maps = np.empty((count, count, 6, 6))          # [i, j]: from i (arrived from j) to j
    maps[i, j] = move_maps(arrival_poses(points[j], points[i], conditions), points[j],
                           conditions)[0]
    first, second = np.triu_indices(count, 1)
    cycle = np.stack([maps[second, first], maps[first, second]], axis=1)   # into a, into b
    costs = evaluate_cycles(cycle, np.stack([points[first], points[second]], axis=1),
                            conditions)[0]
    return np.stack([angles[first], angles[second]], axis=1), costs


class _Objective:
    """Mean steady cost of a pattern (inf without a steady state), counting evaluations."""

    def __init__(self, conditions: SteadyConditions) -> None:
        self.conditions = conditions
        self.evaluations = 0

    def __call__(self, angles: np.ndarray) -> float:
        self.evaluations += 1
        return evaluate_pattern(np.asarray(angles, dtype=float), self.conditions)[0]

    def refine(self, start: np.ndarray, scale: float, step: float = 0.2, budget: int = 100,
               restart: bool = True) -> tuple[float, np.ndarray]:
        """Nelder-Mead from ``start`` (rad) with an initial simplex of ``step`` rad until the
        angles settle to 1e-3 rad and the cost to 1e-7 ``scale`` (m^2) or ``budget`` evaluations
        per angle are spent; with ``restart``, once more from its result with a smaller simplex
        (a collapsed simplex stalls early)."""
        from scipy.optimize import minimize   # here: it costs every node 0.45 s of start-up
        best = np.asarray(start, dtype=float)
        value = math.inf
        for size in (step, 0.25 * step) if restart else (step,):
            simplex = np.vstack([best, best + size * np.eye(len(best))])
            with np.errstate(invalid='ignore'):     # a simplex of no steady state: inf - inf
                result = minimize(self, best, method='Nelder-Mead',
                                  options={'initial_simplex': simplex, 'xatol': 1e-3,
                                           'fatol': 1e-7 * scale, 'maxfev': budget * len(best)})
            if result.fun <= value:
                value, best = float(result.fun), np.asarray(result.x)
        return value, best


def _seeds(pair: np.ndarray, period: int) -> list[np.ndarray]:
    """Starts of the search for ``period`` points from the best two-point pattern (a, b): the
    pair repeated, and the points split into a group near a and a group near b, each group
    stepping along the boundary one way or the other (the shape of the optima we found)."""
    a, b = pair
    seeds = [np.resize(pair, period)]
    sizes = ((period + 1) // 2, period // 2)
    for sense_a in (1.0, -1.0):
        for sense_b in (1.0, -1.0):
            seeds.append(np.concatenate([
                centre + sense * PAIR_SPREAD * np.linspace(-1.0, 1.0, size) if size > 1
                else np.array([centre])
                for centre, sense, size in ((a, sense_a, sizes[0]), (b, sense_b, sizes[1]))]))
    return seeds


def design_pattern(conditions: SteadyConditions, period: int) -> PatternDesign | None:
    """The best pattern of ``period`` (>= 2) boundary points found by the search (see module
    docstring), or None when no pattern qualifies (no steady state, e.g. without process noise,
    or too close to the leader for its uncertainty, e.g. with a tiny r)."""
    start_time = time.perf_counter()
    objective = _Objective(conditions)
    pairs, pair_costs = pair_grid(conditions)
    objective.evaluations += len(pairs)
    ranked = np.argsort(pair_costs)[:REFINED_PAIRS]
    ranked = ranked[np.isfinite(pair_costs[ranked])]
    if len(ranked) == 0:
        return None
    scale = float(pair_costs[ranked[0]])
    best_value, best = min((objective.refine(pairs[i], scale) for i in ranked),
                           key=lambda item: item[0])
    if period > 2:
        # a short race of the grouped seeds, the best RACE_WINNERS refined in full, against
        # the pair repeated (a stationary point: Nelder-Mead does not leave it)
        raced = sorted((objective.refine(seed, scale, budget=SEED_BUDGET, restart=False)
                        for seed in _seeds(best, period)[1:]), key=lambda item: item[0])
        refined = min((objective.refine(start, scale, step=0.05)
                       for _, start in raced[:RACE_WINNERS]), key=lambda item: item[0])
        if refined[0] < best_value:
            best_value, best = refined
        else:
            best = np.resize(best, period)
    if not math.isfinite(best_value):
        return None
    mean_cost, posteriors, decay, maps = evaluate_pattern(best, conditions)
    angles = np.mod(best, 2.0 * math.pi)
    horizon = period * math.ceil(math.log(SETTLE_FACTOR) / math.log(min(decay, 1.0 - 1e-9)))
    return PatternDesign(conditions, angles, conditions.boundary_points(angles), posteriors,
                         np.einsum('i,nii->n', weight_vector(conditions.slot) ** 2, posteriors),
                         mean_cost, decay, max(horizon, 4 * period), maps,
                         time.perf_counter() - start_time, objective.evaluations)


def fits_reach(points: np.ndarray, conditions: SteadyConditions,
               rtol: float = REACH_RTOL) -> bool:
    """True when each point of a cycle (m, 2) is reachable from the one before it and keeps
    the safety distance (within ``rtol`` of the reach and of the distance)."""
    c = conditions
    if np.any(np.hypot(points[:, 0], points[:, 1]) < c.safety * (1.0 - rtol)):
        return False
    if not c.limited:
        return True
    return bool(np.all(cycle_margins(points.ravel(), c)[:len(points)]
                       >= -rtol * c.reach * c.reach))


@functools.lru_cache(maxsize=1024)
def reach_map(conditions: SteadyConditions) -> tuple[np.ndarray, np.ndarray]:
    """The reach centre of a step as an affine map of the position p (2,) it starts from,
    centre = offset + linear @ p (offset (2,) m, linear (2, 2)): a follower standing still
    is carried by the leader's motion, a translation behind a straight leader, a rotation
    about the leader and a translation on an arc (for the exact and the Euler kinematics,
    which are both affine in p; its heading does not enter). Cached: do not modify."""
    c = conditions
    offset = np.array(reach_centre(np.zeros(3), c.leader, c.dt, c.kinematics))
    columns = [np.array(reach_centre(np.array([*unit, 0.0]), c.leader, c.dt, c.kinematics))
               - offset for unit in ((1.0, 0.0), (0.0, 1.0))]
    return offset, np.stack(columns, axis=1)


def _moves(points: np.ndarray, phases: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each move's offset from its reach centre (m, 2), m (move k: from point k-1 into point
    k, with the leader motion of phases[k]), and the linear parts (m, 2, 2) of the maps."""
    maps = [reach_map(phase) for phase in phases]
    offsets = np.array([offset for offset, _ in maps])
    linear = np.array([matrix for _, matrix in maps])
    centres = np.einsum('kij,kj->ki', linear, np.roll(points, 1, axis=0)) + offsets
    return points - centres, linear


def cycle_margins(z: np.ndarray, conditions: SteadyConditions | Sequence[SteadyConditions],
                  radii2: float | np.ndarray | None = None) -> np.ndarray:
    """Margins (m^2) of a cycle's flattened points z (2m,) in the constraints of a design
    within reach, >= 0 when met: each move inside its reach disc (reach^2 - |move off its
    centre|^2, under a speed limit), each point within its radius of the slot (radii2 (m,)
    m^2, default r^2: r^2 - |p - p_o|^2) and outside the safety circle (|p|^2 - safety^2,
    with a safety distance). ``conditions``: one, or those of each move."""
    points = z.reshape(-1, 2)
    phases = _per_move(conditions, len(points))
    c = phases[0]
    margins = [(c.r * c.r if radii2 is None else radii2)
               - np.sum((points - c.slot) ** 2, axis=1)]
    if c.limited:
        margins.insert(0, c.reach * c.reach - np.sum(_moves(points, phases)[0] ** 2, axis=1))
    if c.safety > 0.0:
        margins.append(np.sum(points ** 2, axis=1) - c.safety * c.safety)
    return np.concatenate(margins)


def cycle_margins_jacobian(z: np.ndarray,
                           conditions: SteadyConditions | Sequence[SteadyConditions],
                           radii2: float | np.ndarray | None = None) -> np.ndarray:
    """d :func:`cycle_margins` / d z, (margins, 2m), m: each margin is quadratic in the one
    or two points it involves."""
    points = z.reshape(-1, 2)
    m = len(points)
    phases = _per_move(conditions, m)
    c, k = phases[0], np.arange(m)
    blocks = []

    def block(rows: np.ndarray, columns: np.ndarray, values: np.ndarray) -> np.ndarray:
        out = np.zeros((m, m, 2))
        np.add.at(out, (rows, columns), values)
        return out.reshape(m, 2 * m)

    if c.limited:
        moves, linear = _moves(points, phases)
        blocks.append(block(k, k, -2.0 * moves)
                      + block(k, (k - 1) % m, 2.0 * np.einsum('kji,kj->ki', linear, moves)))
    blocks.append(block(k, k, -2.0 * (points - c.slot)))
    if c.safety > 0.0:
        blocks.append(block(k, k, 2.0 * points))
    return np.concatenate(blocks)


def cycle_constraints(conditions: SteadyConditions | Sequence[SteadyConditions],
                      radii2: float | np.ndarray | None = None) -> dict[str, Any]:
    """SLSQP's inequality constraint of a design within reach (:func:`cycle_margins` with its
    Jacobian)."""
    return {'type': 'ineq', 'fun': cycle_margins, 'jac': cycle_margins_jacobian,
            'args': (conditions, radii2)}


def greedy_loop(conditions: SteadyConditions) -> tuple[float, np.ndarray]:
    """Greedy (RQ over the reachable set) on the noise-free recursion from the slot with the
    paper's initial covariance: the mean tr(W P W) of its last GREEDY_STEADY of GREEDY_STEPS
    steps (m^2) and its last targets (GREEDY_STEADY, 2), m. Under a speed limit it settles
    into a loop that crawls around the disc."""
    c = conditions
    x, P = np.array([*c.p_o, 0.0]), np.diag([0.1, 0.1, 4e-4])
    costs, targets = [], []
    for _ in range(GREEDY_STEPS):
        target = greedy_target(x, P, c)
        x, P = noise_free_step(x, P, target, c)
        targets.append(target)
        costs.append(weighted_trace(P, c.slot))
    return float(np.mean(costs[-GREEDY_STEADY:])), np.array(targets[-GREEDY_STEADY:])


def loop_length(targets: np.ndarray, longest: int, conditions: SteadyConditions) -> int | None:
    """The period of a loop of targets (n, 2): the least K <= ``longest`` with each of the last
    max(2 K, LOOP_WINDOW) targets repeated K steps earlier within LOOP_TOLERANCE (|p_o| + r)
    of ``conditions``; None when there is none. Greedy under a speed limit holds one point for
    up to 18 steps before it jumps back: the last few targets alone would call that hold a
    loop of one."""
    tolerance = LOOP_TOLERANCE * (math.hypot(*conditions.p_o) + conditions.r)
    for period in range(1, min(longest, len(targets) - 2) + 1):
        window = min(max(2 * period, LOOP_WINDOW), len(targets) - period)
        if np.all(np.hypot(*(targets[-window:] - targets[-window - period:-period]).T)
                  <= tolerance):
            return period
    return None


class CycleObjective:
    """The mean steady tr(W P W) (m^2) of a cycle given by its flattened points z (2m,) (m),
    and its forward-difference gradient (SciPy's step, sqrt(eps) max(1, |z_i|)): three move
    maps per coordinate (:func:`perturbed_cycle_maps`) and one batched steady-state solve,
    where a plain finite difference costs a whole cycle per coordinate.
    """

    def __init__(self, conditions: SteadyConditions) -> None:
        self.conditions = conditions
        self.evaluations = 0

    def __call__(self, z: np.ndarray) -> float:
        """The cycle's mean steady tr(W P W) (:func:`evaluate_cycles`), m^2."""
        self.evaluations += 1
        points = z.reshape(-1, 2)
        c = self.conditions
        return float(evaluate_cycles(cycle_maps(points, c)[None], points[None], c)[0][0])

    def gradient(self, z: np.ndarray) -> np.ndarray:
        """d cost / d z (2m,), m^2 per m; 0 where a perturbed cycle has no steady state."""
        c = self.conditions
        steps = math.sqrt(np.finfo(float).eps) * np.where(z >= 0.0, 1.0, -1.0) \
            * np.maximum(1.0, np.abs(z))
        maps, points = perturbed_cycle_maps(z.reshape(-1, 2), c, steps)
        self.evaluations += len(maps)
        return forward_difference(evaluate_cycles(maps, points, c)[0], points)


def refine_cycle(start: np.ndarray, objective: CycleObjective) -> tuple[float, np.ndarray]:
    """SLSQP from a cycle's points (m, 2) on ``objective`` under :func:`cycle_margins` with a
    reach REACH_SLACK (relative) smaller, run again from where it stopped (up to
    REACH_RESTARTS times) while that point is outside the reachable set: (its mean steady
    tr(W P W) m^2, inf when it has none or ends outside the reachable set; the refined points
    (m, 2), m). SLSQP meets its margins to about 1e-7 of reach^2, and where it stops (also at
    its iteration cap, further out) depends on the digits the BLAS threads give: without the
    slack and the restart a design could succeed in one process and fail in another."""
    from scipy.optimize import minimize   # here: it costs every node 0.45 s of start-up
    c = objective.conditions
    constraint = cycle_constraints(replace(c, reach=c.reach * (1.0 - REACH_SLACK)))
    z = start.ravel()
    for _ in range(1 + REACH_RESTARTS):
        z = minimize(objective, z, jac=objective.gradient, method='SLSQP',
                     constraints=[constraint],
                     options={'maxiter': REACH_ITERATIONS, 'ftol': REACH_FTOL}).x
        points = z.reshape(-1, 2)
        if fits_reach(points, c):
            value = objective(z)
            return (value if np.isfinite(value) else math.inf), points
    return math.inf, points


def design_within_reach(conditions: SteadyConditions) -> PatternDesign | None:
    """The best cycle within reach (every move inside the reach disc, every point in the
    slot's disc and outside the safety circle) found from greedy's own loop, or None when none
    beats greedy's steady state.

    Greedy over the reachable set settles into a loop (its period K); that loop (when K <=
    REACH_LONGEST_LOOP), REACH_SAMPLED points sampled along it and a slower lap of
    REACH_STRETCH K points sampled along it are refined by SLSQP on the exact periodic steady
    state (:func:`evaluate_cycles`, its gradient by :class:`CycleObjective`) under the margins
    of :func:`cycle_margins`. Where greedy holds one point or never repeats (K < 2 or none),
    REACH_SAMPLED points at the slot are refined too: greedy may hold a point where its
    covariance grows without bound (a range follower at the front of its disc behind an arc),
    and its own targets then start no cycle that beats holding the slot. A local method: it
    improves on greedy's loop (docs/lookahead.md, "PERIODIC within reach"), it does not prove
    the best cycle.
    """
    start_time = time.perf_counter()
    c = conditions
    greedy_cost, targets = greedy_loop(c)
    period = loop_length(targets, REACH_LONGEST_LOOP, c)
    starts = [] if period is None or period < 2 else [targets[-period:]]
    cycle = targets[-(period or len(targets)):]
    lengths = {REACH_SAMPLED} if period is None else \
        {REACH_SAMPLED, round(REACH_STRETCH * period)} - {period}
    starts += [cycle[np.linspace(0, len(cycle), length, endpoint=False).astype(int)]
               for length in sorted(lengths)]
    if period is None or period < 2:
        starts.append(np.repeat([c.p_o], REACH_SAMPLED, axis=0))
    cost = CycleObjective(c)
    best = min((refine_cycle(start, cost) for start in starts), key=lambda found: found[0],
               default=(math.inf, np.empty((0, 2))))
    if not best[0] < greedy_cost:
        return None
    offsets = best[1] - c.slot            # into the disc: SLSQP meets its margins to ~1e-5 m
    points = c.slot + offsets * np.minimum(1.0, c.r / np.hypot(*offsets.T))[:, None]
    maps = cycle_maps(points, c)
    mean_cost, posteriors, decay = evaluate_cycles(maps[None], points[None], c)
    m, factor = len(points), min(float(decay[0]), 1.0 - 1e-9)
    angles = np.mod(np.arctan2(points[:, 1] - c.p_o[1], points[:, 0] - c.p_o[0]), 2 * math.pi)
    horizon = m * math.ceil(math.log(SETTLE_FACTOR) / math.log(factor))
    return PatternDesign(c, angles, points, posteriors[0],
                         np.einsum('i,nii->n', weight_vector(c.slot) ** 2, posteriors[0]),
                         float(mean_cost[0]), float(decay[0]), max(horizon, 4 * m), maps,
                         time.perf_counter() - start_time, cost.evaluations)


def design_for(conditions: SteadyConditions, period: int) -> PatternDesign | None:
    """The boundary cycle of :func:`design_pattern`; under a speed limit or a safety distance
    it is kept when it fits the reachable set (and is no worse than the best cycle within
    reach), else the cycle of :func:`design_within_reach`.

    A range cycle that would come closer to the leader than CLEARANCE_FRACTION |p_o| is
    designed within reach with that clearance as its safety distance: the filter of a range
    follower that plays the boundary cycle there turns inconsistent (docs/faults.md). Bearing
    and range-bearing discs are held that far from the leader at the door
    (:func:`~formopt_ros.core.domain.check_deviation_domain`)."""
    clearance = CLEARANCE_FRACTION * math.hypot(*conditions.p_o)
    design = design_pattern(conditions, period)
    if conditions.measurement == RANGE and design is not None and \
            conditions.safety < clearance and np.min(np.hypot(*design.points.T)) < clearance:
        return design_within_reach(replace(conditions, safety=clearance))
    if not conditions.limited and not conditions.safety > 0.0:
        return design
    if design is not None and fits_reach(design.points, conditions):
        return design
    return design_within_reach(conditions)


_CACHE: dict[tuple[SteadyConditions, int], PatternDesign | None] = {}


def cached_design(conditions: SteadyConditions, period: int) -> tuple[PatternDesign | None,
                                                                      bool]:
    """(design, computed now) for the conditions, from the per-process cache when possible."""
    key = (conditions, period)
    if key in _CACHE:
        return _CACHE[key], False
    if len(_CACHE) >= CACHE_SIZE:
        _CACHE.pop(next(iter(_CACHE)))
    _CACHE[key] = design_for(conditions, period)
    return _CACHE[key], True


def clear_cache() -> None:
    """Forget every cached design (benchmarks time cold designs)."""
    _CACHE.clear()
