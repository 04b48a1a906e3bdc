"""PERIODIC behind a leader whose path repeats (an S-curve): a cycle locked to the path's phase.

A leader on an S-curve of period T changes its velocity every step, so no stationary cycle
exists; but the conditions of step n repeat with n mod N, N = T / (2 dt) steps, so the whole
planning problem is periodic with N. A cycle of N points, point k played at every step
n = k mod N, has a periodic steady state like a stationary cycle's.

Design (docs/lookahead.md, "PERIODIC on an S-curve"): greedy (RQ over the reachable set) runs on
the noise-free recursion with each step's own leader velocity (``phase_conditions``) until its
loop repeats; its last N targets are refined by SLSQP on the mean tr(W P W) of one period of the
recursion, settled period by period from the last settled posterior (the product
of N = 100 symplectic maps is too ill-conditioned for the eigenvector route of
:func:`.periodic_design.periodic_solutions`), under the constraints of a design within reach:
every move inside its step's reach disc, every point outside the safety distance and in the
slot's disc, or, in the steps where greedy itself could not reach the disc, no farther from
the slot than greedy was. The forward-difference gradient costs three move maps a coordinate
(a point enters the maps of the moves into it and the next two). The design is kept when it
is at least MIN_GAIN below greedy's steady state, and only for periods of SHORTEST_PERIOD
steps or more. A local method, like the design within reach.
"""
from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from formopt_ros.core.formulas import weight_vector, weighted_trace
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.core.reach import Region
from formopt_ros.core.strategies.periodic_design import (
    SteadyConditions, cycle_constraints, cycle_maps, forward_difference, greedy_target, lft,
    noise_free_step, perturbed_cycle_maps, reach_map)

if TYPE_CHECKING:
    from formopt_ros.core.scenario import LeaderPath, Scenario

#: Shortest and longest leader period (steps) a cycle is designed for. The design holds each
#: step's leader velocity at its value at the step's start; over a period of fewer than
#: SHORTEST_PERIOD steps the velocity changes too much within a step for that (measured: a
#: 0.5 s S-curve, 5 steps, designed 19 % below greedy, played 1.7 % above it).
SHORTEST_PERIOD = 10
LONGEST_PERIOD = 400
#: Greedy's noise-free loop counts as bounded when its last period's mean tr(W P W) is at
#: most this factor above the mean of the period half the laps before (it may repeat over
#: two periods, one 1 % apart from the other); a growing one (an unobservable turn on the
#: spot) has no steady state to improve on.
GREEDY_GROWTH = 1.5
#: Leader periods greedy runs on the noise-free recursion before its loop is taken.
GREEDY_LAPS = 20
#: A cycle's steady state is settled when a period's mean tr(W P W) moves less than SETTLED
#: (relative) from the one before, starting from the last settled posterior; at most
#: MAX_PERIODS periods.
SETTLED = 1e-12
MAX_PERIODS = 500
#: SLSQP's iterations at most and its tolerance on the cost.
ITERATIONS = 120
FTOL = 1e-12
#: A design is kept when its steady state is at least this fraction below greedy's.
MIN_GAIN = 0.01
#: Forward-difference step of the gradient, m.
GRADIENT_STEP = 1e-7
#: Passes round the cycle that move SLSQP's last points into their regions.
REPAIR_PASSES = 10


@dataclass(frozen=True)
class PhaseLockedDesign:
    """A cycle locked to the leader path's phase.

    Attributes:
        points: the point of each phase (N, 2), leader frame, m; step n (1-based) targets
            ``points[(n - 1) % N]``.
        steady_cost: the cycle's mean steady tr(W P W) on the noise-free recursion, m^2.
        greedy_cost: greedy's, on the same recursion, m^2.
        design_time_s: wall time of the design, s.
    """

    points: np.ndarray
    steady_cost: float
    greedy_cost: float
    design_time_s: float

    @property
    def period(self) -> int:
        """N, steps."""
        return len(self.points)


def _period_in_steps(path: LeaderPath, dt: float) -> tuple[int | None, str]:
    """(N, '') for an S-curve whose period is a whole number N of steps from SHORTEST_PERIOD to
    LONGEST_PERIOD; else (None, why no cycle locks to it: '' for other paths)."""
    if path.kind != 's-curve' or path.amplitude == 0.0:
        return None, ''
    step = SUBSTEPS * dt
    steps = path.period / step
    whole = round(steps)
    if abs(steps - whole) > 1e-9 * whole:
        return None, (f'its period {path.period:g} s is not a whole number of steps of '
                      f'{step:g} s, so no cycle locks to its phase')
    if not SHORTEST_PERIOD <= whole <= LONGEST_PERIOD:
        return None, (f'its period ({whole} steps) is outside the {SHORTEST_PERIOD}-'
                      f'{LONGEST_PERIOD} steps a cycle locks to')
    return whole, ''


def path_period(path: LeaderPath, dt: float) -> int | None:
    """N: the steps after which the leader's velocity repeats, for an S-curve whose period is
    a whole number of steps (SHORTEST_PERIOD to LONGEST_PERIOD); None for any other path."""
    return _period_in_steps(path, dt)[0]


def unlocked_reason(path: LeaderPath, dt: float) -> str:
    """Why no cycle locks to the phase of an S-curve ('' for other paths, or when one does)."""
    return _period_in_steps(path, dt)[1]


def phase_conditions(scenario: Scenario, period: int) -> list[SteadyConditions]:
    """The conditions of each phase k (the leader's velocity at the start of step k + 1)."""
    return [SteadyConditions.at_velocity(scenario, *scenario.leader.velocity(k * SUBSTEPS,
                                                                             scenario.dt))
            for k in range(period)]


class _PeriodCost:
    """The mean tr(W P W) (m^2) of one period of a phase-locked cycle, and its gradient."""

    def __init__(self, phases: list[SteadyConditions], start: np.ndarray) -> None:
        self.phases, self.start = phases, start
        self.w2 = weight_vector(phases[0].slot) ** 2

    def settle(self, maps: np.ndarray) -> np.ndarray:
        """Mean tr(W P W) over a period of maps (B, N, 6, 6), (B,), m^2 (inf without a steady
        state): periods of the recursion from the last settled posterior until a period's mean
        moves less than SETTLED (relative), at most MAX_PERIODS."""
        P = np.repeat(self.start[None], len(maps), axis=0)
        costs = np.empty((maps.shape[1], len(maps)))
        previous = np.full(len(maps), np.inf)
        for _ in range(MAX_PERIODS):
            for k in range(maps.shape[1]):
                P = lft(maps[:, k], P)
                P = 0.5 * (P + np.swapaxes(P, 1, 2))
                costs[k] = np.einsum('i,nii->n', self.w2, P)
            means = costs.mean(axis=0)
            with np.errstate(invalid='ignore'):
                if np.all((np.abs(means - previous) <= SETTLED * means) | ~np.isfinite(means)):
                    break
            previous = means
        ok = np.all(costs > 0.0, axis=0) & np.all(np.isfinite(P), axis=(1, 2))
        if ok[0]:
            self.start = P[0]
        return np.where(ok, means, np.inf)

    def __call__(self, z: np.ndarray) -> float:
        return float(self.settle(cycle_maps(z.reshape(-1, 2), self.phases)[None])[0])

    def gradient(self, z: np.ndarray) -> np.ndarray:
        maps, points = perturbed_cycle_maps(z.reshape(-1, 2), self.phases,
                                            np.full(len(z), GRADIENT_STEP))
        return forward_difference(self.settle(maps), points)


def _into_regions(points: np.ndarray, phases: list[SteadyConditions],
                  radii: np.ndarray) -> np.ndarray:
    """The cycle (N, 2) with each point in turn moved to the nearest point of its step's
    region (radii[k] about the slot, the reach disc of the move from the point before, outside
    the safety circle), REPAIR_PASSES times round at most: SLSQP stops at its iteration cap,
    possibly a little outside its constraints. A point whose region is empty stays."""
    points = points.copy()
    for _ in range(REPAIR_PASSES):
        moved = False
        for k, phase in enumerate(phases):
            centre = None
            if phase.limited:
                offset, linear = reach_map(phase)
                centre = tuple(linear @ points[k - 1] + offset)
            region = Region(phase.p_o, float(radii[k]), centre, phase.reach, phase.safety)
            nearest = None if region.contains(points[k]) else region.nearest(points[k])
            if nearest is not None:
                points[k], moved = nearest, True
        if not moved:
            break
    return points


@functools.lru_cache(maxsize=8)
def design_phase_locked(scenario: Scenario) -> PhaseLockedDesign | None:
    """The phase-locked cycle for ``scenario``'s leader path (module docstring), or None when
    the path does not repeat or no cycle found beats greedy by MIN_GAIN. Cached per process."""
    from scipy.optimize import minimize   # here: it costs every node 0.45 s of start-up
    started = time.perf_counter()
    period = path_period(scenario.leader, scenario.dt)
    if period is None:
        return None
    phases = phase_conditions(scenario, period)
    slot = phases[0].slot
    x, P = np.array([*slot, 0.0]), np.diag([0.1, 0.1, 4e-4])
    targets, costs = np.empty((period, 2)), np.empty((GREEDY_LAPS, period))
    for lap in range(GREEDY_LAPS):
        for k, phase in enumerate(phases):
            targets[k] = greedy_target(x, P, phase)
            x, P = noise_free_step(x, P, targets[k], phase)
            costs[lap, k] = weighted_trace(P, slot)
    greedy_cost = float(costs[-2:].mean())
    if not costs[-1].mean() <= GREEDY_GROWTH * costs[GREEDY_LAPS // 2].mean():
        return None
    radii2 = np.maximum(scenario.r ** 2, np.sum((targets - slot) ** 2, axis=1))
    objective = _PeriodCost(phases, P)
    result = minimize(objective, targets.ravel(), jac=objective.gradient, method='SLSQP',
                      constraints=[cycle_constraints(phases, radii2)],
                      options={'maxiter': ITERATIONS, 'ftol': FTOL})
    points = _into_regions(result.x.reshape(-1, 2), phases, np.sqrt(radii2))
    cost = objective(points.ravel())
    if not math.isfinite(cost) or cost > (1.0 - MIN_GAIN) * greedy_cost:
        return None
    return PhaseLockedDesign(points, cost, greedy_cost, time.perf_counter() - started)


__all__ = ['PhaseLockedDesign', 'design_phase_locked', 'path_period', 'phase_conditions',
           'unlocked_reason']
