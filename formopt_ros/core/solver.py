"""The public entry point: ``solve(P, p_o, r, sigma, *, measurement, method) -> Solution``."""
from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any

import numpy as np

from formopt_ros.core.checks import InvalidInput, as_choice
from formopt_ros.core.cost import Problem
from formopt_ros.core.model import MEASUREMENT_KINDS, RANGE_BEARING
from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.strategies import (
    BUILTIN, STRATEGIES, PlanContext, Solution, Strategy, make_strategy)
from formopt_ros.core.strategies.region import plan_within

#: Names of the built-in strategies; ``solve(method=...)`` also accepts the plugin strategies of
#: ``STRATEGIES``.
METHODS = BUILTIN
#: Context of a one-off problem: step 1, leader straight at 1 m/s.
DEFAULT_CONTEXT = PlanContext()


#: method -> the strategy object that serves option-less ``solve`` calls (stateless strategies
#: only: one object may answer every problem).
_SHARED: dict[str, Strategy] = {
    name: STRATEGIES[name]() for name in BUILTIN if STRATEGIES[name].stateless}


class OutsideTheDisc(ValueError):
    """A strategy (a plugin: the built-in ones stay in the disc) planned a point outside it."""


def outside_the_disc(strategy: str, point: Any, slot: Any, r: float) -> OutsideTheDisc:
    """The error of a strategy that planned ``point`` (2,) farther than r (1 + 1e-9) from
    ``slot`` (2,), m."""
    distance = math.hypot(float(point[0]) - float(slot[0]), float(point[1]) - float(slot[1]))
    return OutsideTheDisc(f'strategy {strategy!r} planned a point {distance:.6g} m from the '
                          f'slot, outside its disc (r = {r:.6g} m)')


def timed_plan(strategy: Strategy, problem: Problem, context: PlanContext) -> Solution:
    """``strategy.plan(problem, context)`` with its wall time in ``Solution.solve_time_s``;
    with a reachable set in ``context.region``, the answer restricted to it
    (:func:`~.strategies.region.plan_within`).

    A record whose time is unset is new (:func:`~.strategies.base.make_solution` made it for
    this call) and is stamped in place; a record already timed (one a strategy returned
    before) is copied first."""
    start = time.perf_counter()
    solution = strategy.plan(problem, context) if context.region is None else plan_within(
        strategy, problem, context)
    elapsed = time.perf_counter() - start
    if context.region is None and not problem.feasible(solution.p):
        raise outside_the_disc(strategy.name, solution.p, problem.slot, float(problem.r))
    if solution.solve_time_s:
        return solution.with_solve_time(elapsed)
    object.__setattr__(solution, 'solve_time_s', elapsed)
    return solution


def solve(P: np.ndarray, p_o: np.ndarray, r: float, sigma: float, *, measurement: str,
          method: str, sigma_bearing: float | None = None,
          rng: np.random.Generator | None = None, context: PlanContext | None = None,
          **options: object) -> Solution:
    """Choose the follower's next position in the disc |p - p_o| <= r (paper problem Pi_1).

    Args:
        P: prior covariance of [x, y, phi] at the next step, shape (3, 3), symmetric positive
            definite (m^2, m rad, rad^2); the paper uses the covariance propagated to p_o.
        p_o: formation slot in the leader frame, shape (2,), m.
        r: allowed deviation, m; 1e-6 |p_o| <= r <= 0.999 |p_o|.
        sigma: measurement noise standard deviation: m for 'range' and 'range-bearing', rad
            for 'bearing'.
        measurement: 'range', 'bearing' or 'range-bearing' (both at once: docs/range_bearing.md;
            every method but 'ram').
        sigma_bearing: 'range-bearing' only, and required there: the bearing noise standard
            deviation, rad.
        method: 'ram' (paper, analytic), 'rq' (exact eigen solver), 'gbs' (grid), 'mtf'
            (stay at p_o), 'crm' (random in the disc), 'mme' (sideways, alternating),
            'periodic' (plans for the long run through the estimator in ``context``; without
            one, as in a one-off problem, it is RQ).
        rng: random generator for 'crm' (a fresh unseeded one when None); shorthand for
            ``context.rng``.
        context: step index and expected leader motion (MME's side and switch); default: step
            1, leader straight at 1 m/s.
        **options: the strategy's options, e.g. 'gbs': cell (grid spacing as a fraction of r,
            default 0.005); 'mme': amplitude, period; 'ram': fallback (bool, default True).
            ``STRATEGIES[method].OPTIONS`` lists them with ranges.

    Returns:
        The :class:`Solution`; ``Solution.p`` has shape (2,), leader frame, metres. RAM and RQ
        fill ``Solution.certificate`` (what was proved about p) and, when RAM could not
        certify its own answer, return RQ's with ``Solution.fallback = 'rq'``.

    Raises:
        InvalidInput: (a ValueError naming the field) for a non-SPD or non-finite P, a
            variance of P outside ``cost.VARIANCE_RANGE`` ([1e-100, 1e25]), |p_o| outside
            ``cost.SLOT_DISTANCE_RANGE`` ([1e-3, 1e6] m), r outside [1e-6, 0.999] |p_o|,
            sigma outside ``cost.SIGMA_RANGE`` ([1e-9, 1e6]), an unknown measurement or a bad
            option value (:func:`~formopt_ros.core.cost.check_problem`, one cheap check), or
            a sigma_bearing missing for 'range-bearing', outside SIGMA_RANGE or given for
            another measurement, or a ``context.region`` built for another slot or r.
        InvalidInput: for an rng that is not a numpy Generator, a context that is not a
            PlanContext, or an unknown method or option.
    """
    if rng is not None and not isinstance(rng, np.random.Generator):
        raise InvalidInput('rng', 'must be a numpy.random.Generator (e.g. '
                                  f'numpy.random.default_rng(seed)), got {rng!r}')
    if context is not None and not isinstance(context, PlanContext):
        raise InvalidInput('context', f'must be a PlanContext, got {context!r}')
    strategy = _SHARED.get(method) if not options and isinstance(method, str) else None
    if strategy is None:
        strategy = make_strategy(method, **options)
    context = context or DEFAULT_CONTEXT
    if rng is not None:
        context = replace(context, rng=rng)
    as_choice('measurement', measurement, (*MEASUREMENT_KINDS, RANGE_BEARING))
    if measurement == RANGE_BEARING:
        if sigma_bearing is None:
            raise InvalidInput('sigma_bearing', "is required for measurement='range-bearing'")
        problem: Problem | StackedProblem = StackedProblem(P, p_o, r, sigma, sigma_bearing)
    elif sigma_bearing is not None:
        raise InvalidInput('sigma_bearing', f"is for measurement='range-bearing' only, got "
                                            f'{measurement!r}')
    else:
        problem = Problem(P, p_o, r, sigma, measurement)
    region = context.region
    if region is not None and (
            math.hypot(region.slot[0] - problem.slot[0], region.slot[1] - problem.slot[1])
            > 1e-9 * region.scale or abs(region.r - problem.r) > 1e-9 * region.scale):
        raise InvalidInput('region', f'must be built for this problem\'s slot and r '
                                     f'({problem.slot}, {problem.r!r} m), got {region.slot}, '
                                     f'{region.r!r} m')
    return timed_plan(strategy, problem, context)      # type: ignore[arg-type]
