"""LOOKAHEAD (beyond the paper): a receding-horizon beam search over the exact moves.

Greedy strategies (RAM, RQ) minimise the cost after the next measurement only. Under a speed
limit that is short-sighted: the follower reaches a small part of its disc per step (in the
leader frame the reach disc lies ``v_L * 2 dt`` behind the follower, so it crawls forward and
jumps back), and the move that pays most now can leave it where no later move pays. PERIODIC's
cycles jump across the disc and do not survive the limit; on a turning leader it plays greedy.

LOOKAHEAD plans ``horizon`` steps ahead with the filter's own noise-free recursion: from the
posterior (x, P), each candidate target p gives the exact move-dependent prior
(:func:`~formopt_ros.core.protocol.predict_move`: the protocol's commands, the odometry noise,
the leader motion expected for the step, held over the horizon) and the update there with zero
innovation (the estimate lands on p). A level of the search expands every kept node by

* a fixed polar grid of the slot's disc (its centre, ``GRID_RINGS`` rings, ``GRID_ANGLES``
  points on the outer ring),
* ``REACH_ANGLES`` points on the node's reach circle (``max_speed * 2 dt`` around where the
  node would drift to standing still; see :mod:`formopt_ros.core.reach`), scaled into the disc,
* the node's own position (holding station in the leader frame),

keeps the candidates inside the region (reach disc, slot disc, at least the safety distance
from the leader), and keeps the ``beam`` nodes of least ``sum of tr(W P W) so far + (levels
left + terminal_weight) * tr(W P W) now`` (the cost so far plus a cost-to-go that assumes the
uncertainty stays where it is). The first move of the best path is the answer.

Greedy guard (``greedy_guard``): RQ's own path over the horizon (its certified optimum over the
region at every step, the paper's planning prior) is scored the same way, and LOOKAHEAD plays
RQ's move whenever that path is not worse. A greedy path the search cannot beat is therefore
never abandoned (range under a speed limit, where greedy's long holds are hard to beat: see
docs/lookahead.md for the measured numbers).

A range-bearing follower is planned with both rows at every step of the horizon (the stacked
update is the two scalar updates in turn); its greedy guard is off (the region solver of the
stacked problem costs too much per step). Without an estimator view (a one-off problem) the
answer is RQ's.
"""
from __future__ import annotations

import math
import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.model import BEARING, RANGE, measurement_jacobian, propagate_state
from formopt_ros.core.protocol import predict_move
from formopt_ros.core.reach import reach_region
from formopt_ros.core.strategies.base import OptionSpec, PlanContext, Solution, Strategy, \
    make_solution
from formopt_ros.core.strategies.region import rq_in_region, rq_target
from formopt_ros.core.strategies.rq import rq_optimum

#: Rings of the fixed polar grid of the slot's disc (besides its centre).
GRID_RINGS = 3
#: Points on the grid's outer ring (ring i of GRID_RINGS has i / GRID_RINGS as many, >= 6).
GRID_ANGLES = 24
#: Points on each node's reach circle.
REACH_ANGLES = 24


def disc_grid(slot: np.ndarray, r: float) -> np.ndarray:
    """The fixed candidates: p_o and GRID_RINGS rings of radius i r / GRID_RINGS, (n, 2), m."""
    points = [slot[None, :]]
    for i in range(1, GRID_RINGS + 1):
        count = max(6, GRID_ANGLES * i // GRID_RINGS)
        angles = (np.arange(count) + 0.5 * (i % 2)) * 2.0 * math.pi / count
        points.append(slot + (r * i / GRID_RINGS) * np.stack([np.cos(angles),
                                                              np.sin(angles)], axis=1))
    return np.vstack(points)


def noise_free_updates(x: np.ndarray, P: np.ndarray, rows: tuple[tuple[str, float], ...]
                       ) -> np.ndarray:
    """Covariances (N, 3, 3) after zero-innovation updates at poses x (N, 3) from priors P
    (N, 3, 3), one scalar update per (kind, variance) in ``rows`` (two rows in turn equal the
    stacked update of independent noises)."""
    for kind, variance in rows:
        h = measurement_jacobian(kind, x)
        Ph = np.einsum('nij,nj->ni', P, h)
        innovation_variance = np.einsum('ni,ni->n', h, Ph) + variance
        P = P - np.einsum('ni,nj->nij', Ph, Ph) / innovation_variance[:, None, None]
    return P


class RecedingHorizon(Strategy):
    """LOOKAHEAD: the first move of the best ``horizon``-step path of a beam search."""

    name = 'lookahead'
    OPTIONS = {
        'horizon': OptionSpec(8, 'steps planned ahead', 1, 50),
        'beam': OptionSpec(24, 'paths kept per level of the search', 1, 512),
        'terminal_weight': OptionSpec(
            5.0, 'weight of the last step\'s tr(W P W) beyond the horizon (0: none)', 0.0,
            1000.0),
        'greedy_guard': OptionSpec(True, 'play RQ\'s move when RQ\'s own path over the '
                                         'horizon scores no worse'),
    }

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The first move of the best path (module docstring)."""
        view = context.estimator
        if view is None:
            solution = rq_optimum(problem, self.name) if context.region is None \
                else rq_in_region(problem, context.region, self.name)
            solution.details['mode'] = 'greedy (no estimator view)'
            return solution
        if context.region is not None and context.region.empty():   # RQ's fallback, tagged
            solution = rq_in_region(problem, context.region, self.name)
            solution.details['mode'] = 'unreachable'
            return solution
        rows = self._rows(problem)
        first, score, paths = self._search(problem, context, view.x, view.P, rows)
        details: dict[str, object] = {'mode': 'search', 'horizon_cost': score,
                                      'paths': paths}
        if self.settings['greedy_guard'] and len(rows) == 1:
            greedy_first, greedy_score = self._greedy_path(problem, context, view.x, view.P,
                                                           rows)
            details['greedy_horizon_cost'] = greedy_score
            if first is None or greedy_score <= score:
                first, details['mode'] = greedy_first, 'greedy guard'
        if first is None:       # no candidate reachable: RQ's optimum over the region
            return rq_in_region(problem, context.region, self.name) \
                if context.region is not None else rq_optimum(problem, self.name)
        on_boundary = math.hypot(first[0] - problem.slot[0], first[1] - problem.slot[1]) \
            >= float(problem.r) * (1.0 - 1e-12)
        return make_solution(problem, first, self.name, on_boundary, paths, details=details)

    @staticmethod
    def _rows(problem: Problem) -> tuple[tuple[str, float], ...]:
        """The scalar updates of one step: (kind, variance) per row."""
        if hasattr(problem, 'sigma_bearing'):
            return ((RANGE, float(problem.sigma) ** 2),
                    (BEARING, float(problem.sigma_bearing) ** 2))
        return ((problem.measurement, float(problem.sigma) ** 2),)

    def _search(self, problem: Problem, context: PlanContext, x0: np.ndarray, P0: np.ndarray,
                rows: tuple[tuple[str, float], ...]
                ) -> tuple[np.ndarray | None, float, int]:
        """The beam search: (first move (2,) or None, its path's score, paths scored)."""
        horizon, beam = int(self.settings['horizon']), int(self.settings['beam'])
        terminal = float(self.settings['terminal_weight'])
        slot, r = np.asarray(problem.slot, dtype=float), float(problem.r)
        region = context.region
        reach = region.radius if region is not None else math.inf
        safety = region.safety if region is not None else 0.0
        grid = disc_grid(slot, r)
        unit = np.stack([np.cos(np.arange(REACH_ANGLES) * 2.0 * math.pi / REACH_ANGLES),
                         np.sin(np.arange(REACH_ANGLES) * 2.0 * math.pi / REACH_ANGLES)], 1)
        x, P = x0[None, :3].copy(), P0[None, :3, :3].copy()
        so_far, first = np.zeros(1), np.zeros((1, 2))
        tolerance = 1e-9 * (math.hypot(*slot) + r)
        scored = 0
        for level in range(horizon):
            n = len(x)
            drift = x
            for v_l, omega_l in context.leader_velocities:
                drift = propagate_state(drift, 0.0, 0.0, context.dt, v_l, omega_l,
                                        context.kinematics)
            candidates = [np.broadcast_to(grid, (n,) + grid.shape), x[:, None, :2]]
            if math.isfinite(reach):
                ring = drift[:, None, :2] + reach * unit[None]
                offset = ring - slot
                scale = np.minimum(1.0, r / np.maximum(np.hypot(offset[..., 0],
                                                                offset[..., 1]), 1e-300))
                candidates.append(slot + offset * scale[..., None])
            targets = np.concatenate(candidates, axis=1)                       # (n, m, 2)
            feasible = (np.hypot(targets[..., 0] - drift[:, None, 0],
                                 targets[..., 1] - drift[:, None, 1]) <= reach + tolerance) \
                & (np.hypot(targets[..., 0] - slot[0], targets[..., 1] - slot[1])
                   <= r + tolerance) \
                & (np.hypot(targets[..., 0], targets[..., 1]) >= safety - tolerance)
            node, index = np.nonzero(feasible)
            if node.size == 0:
                return None, math.inf, scored
            moved, prior = predict_move(x[node], P[node], targets[node, index],
                                        context.leader_velocities, context.dt, context.sigma_v,
                                        context.sigma_omega, context.kinematics)
            posterior = noise_free_updates(moved, prior, rows)
            trace = weighted_trace(posterior, slot)
            total = so_far[node] + trace
            rank = total + (horizon - 1 - level + terminal) * trace
            keep = np.argsort(rank, kind='stable')[:beam]
            scored += node.size
            first = targets[node, index][keep] if level == 0 else first[node][keep]
            x, P, so_far = moved[keep], posterior[keep], total[keep]
            best_score = float(rank[keep[0]])
        return first[0].copy(), best_score, scored

    def _greedy_path(self, problem: Problem, context: PlanContext, x: np.ndarray,
                     P: np.ndarray, rows: tuple[tuple[str, float], ...]
                     ) -> tuple[np.ndarray, float]:
        """RQ's path over the horizon, scored as the search scores its paths:
        (its first move (2,), its score)."""
        horizon = int(self.settings['horizon'])
        terminal = float(self.settings['terminal_weight'])
        slot, r = np.asarray(problem.slot, dtype=float), float(problem.r)
        region = context.region
        steps = len(context.leader_velocities) * context.dt
        max_speed = region.radius / steps if region is not None and \
            math.isfinite(region.radius) else None
        safety = region.safety if region is not None else 0.0
        x, P = x[:3].copy(), P[:3, :3].copy()
        total, first, trace = 0.0, None, 0.0
        for level in range(horizon):
            if level == 0:
                step_problem, step_region = problem, region
            else:
                prior = predict_move(x, P, slot, context.leader_velocities, context.dt,
                                     context.sigma_v, context.sigma_omega,
                                     context.kinematics)[1]
                step_problem = Problem(prior, slot, r, problem.sigma, problem.measurement,
                                       False)
                step_region = reach_region((float(slot[0]), float(slot[1])), r, x,
                                           context.leader_velocities, context.dt,
                                           context.kinematics, max_speed, safety)
            target = rq_target(step_problem, step_region)
            if first is None:
                first = target
            moved, prior = predict_move(x[None], P[None], target[None],
                                        context.leader_velocities, context.dt,
                                        context.sigma_v, context.sigma_omega,
                                        context.kinematics)
            P = noise_free_updates(moved, prior, rows)[0]
            x = moved[0]
            trace = weighted_trace(P, slot)
            total += trace
        assert first is not None
        return first, total + terminal * trace


__all__ = ['GRID_ANGLES', 'GRID_RINGS', 'REACH_ANGLES', 'RecedingHorizon', 'disc_grid',
           'noise_free_updates']
