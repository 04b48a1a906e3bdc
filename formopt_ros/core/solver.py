"""The stable public entry point: ``solve(P, p_o, r, sigma, *, measurement, method) -> Solution``."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.strategies import STRATEGIES

#: Names accepted by ``solve(method=...)``.
METHODS = tuple(STRATEGIES)


@dataclass(frozen=True)
class Solution:
    """The chosen next position and what it costs.

    Attributes:
        p: chosen position in the leader frame, shape (2,), m.
        cost: tr(W P_post W) after a measurement at p, m^2.
        cost_at_slot: the same cost at the formation slot p_o, m^2.
        method: strategy name.
        measurement: 'range' or 'bearing'.
        on_boundary: True when |p - p_o| = r (constraint active).
        candidates: number of critical or grid points examined.
        solve_time_s: wall time of the strategy, s.
        fallback: method used when RAM's polynomial route lost accuracy, else None.
        details: method-specific diagnostics.
    """

    p: np.ndarray
    cost: float
    cost_at_slot: float
    method: str
    measurement: str
    on_boundary: bool
    candidates: int
    solve_time_s: float
    fallback: str | None = None
    details: dict = field(default_factory=dict)


def solve_problem(problem: Problem, method: str, rng: np.random.Generator | None = None,
                  **options: object) -> Solution:
    """Run strategy ``method`` on a validated :class:`Problem` (see :func:`solve`)."""
    if method not in STRATEGIES:
        raise ValueError(f'method must be one of {METHODS}, got {method!r}')
    planner, accepted = STRATEGIES[method]
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise ValueError(f'method {method!r} accepts options {sorted(accepted)}, '
                         f'got unknown {unknown}')
    start = time.perf_counter()
    plan = planner(problem, rng, **options)
    elapsed = time.perf_counter() - start
    costs = problem.cost(np.vstack([plan.p, problem.p_o]))
    return Solution(p=plan.p, cost=float(costs[0]), cost_at_slot=float(costs[1]), method=method,
                    measurement=problem.measurement, on_boundary=plan.on_boundary,
                    candidates=plan.candidates, solve_time_s=elapsed, fallback=plan.fallback,
                    details=plan.details)


def solve(P: np.ndarray, p_o: np.ndarray, r: float, sigma: float, *, measurement: str,
          method: str, rng: np.random.Generator | None = None, **options: object) -> Solution:
    """Choose the follower's next position in the disc |p - p_o| <= r (paper problem Pi_1).

    Args:
        P: prior covariance of [x, y, phi] at the next step, shape (3, 3), symmetric positive
            definite (m^2, m rad, rad^2); the paper uses the covariance propagated to p_o.
        p_o: formation slot in the leader frame, shape (2,), m.
        r: allowed deviation, m; 0 < r < |p_o|.
        sigma: measurement noise standard deviation: m for 'range', rad for 'bearing'.
        measurement: 'range' or 'bearing'.
        method: 'ram' (paper, analytic), 'rq' (exact eigen solver), 'gbs' (grid), 'mtf'
            (stay at p_o), 'crm' (random in the disc), 'mme' (sideways, alternating).
        rng: random generator for 'crm' (a fresh unseeded one when None).
        **options: 'gbs': cell (grid spacing as a fraction of r, default 0.005);
            'mme': step (int, parity picks the side), leader_straight (bool);
            'ram': fallback (bool, default True).

    Returns:
        The :class:`Solution`; ``Solution.p`` has shape (2,), leader frame, metres.

    Raises:
        ValueError: for a non-SPD or non-finite P, bad p_o, r <= 0 or r >= |p_o|, sigma <= 0,
            or an unknown measurement, method or option.
    """
    if method not in STRATEGIES:
        raise ValueError(f'method must be one of {METHODS}, got {method!r}')
    return solve_problem(Problem(P, p_o, r, sigma, measurement), method, rng, **options)
