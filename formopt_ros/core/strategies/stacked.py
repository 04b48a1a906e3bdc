"""The certified optimum by lines through the leader as a Solution, over a disc or a region.

The solver is :func:`formopt_ros.core.strategies.polar.polar_optimum` (docs/range_bearing.md);
it is RQ for range-bearing, and decides a scalar problem over a reachable region where the
S-lemma does not (:func:`~formopt_ros.core.strategies.region.rq_in_region`). This module turns
its answer into a :class:`~formopt_ros.core.strategies.base.Solution` and says when it is not
certified.
"""
from __future__ import annotations

import math
from dataclasses import replace

from formopt_ros.core.cost import Problem
from formopt_ros.core.reach import Region
from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.strategies.base import Solution, make_solution
from formopt_ros.core.strategies.polar import POLAR, polar_optimum

#: Gap (relative to the cost) up to which an answer counts as certified.
CERTIFIED_GAP = 1e-9
#: Certificates of the range-bearing optimum.
CERTIFICATES = (POLAR,)


def lines_plan(problem: Problem | StackedProblem, method: str, region: Region | None = None,
               seeds: tuple[tuple[float, float], ...] = ()) -> Solution:
    """The certified optimum of a range-bearing (or scalar) problem over the disc, or over a
    non-empty ``region`` that restricts it (``seeds``: feasible points (m) whose lines the
    search tries first), as a Solution with ``details['certificate_gap']`` and
    ``details['lower_bound']`` (certificate 'polar-lines'). An answer whose gap exceeds
    CERTIFIED_GAP is the best point found, with ``fallback = 'best-line'``, certificate 'none'
    and the gap in the reason."""
    p, cost, lower, info = polar_optimum(problem, region, seeds)
    at_slot = info.pop('cost_at_slot')
    restricted = region is not None and region.restricts
    gap = (cost - lower) / abs(cost) if cost else math.inf
    on_boundary = math.hypot(p[0] - problem.slot[0], p[1] - problem.slot[1]) >= problem.r * (
        1.0 - 1e-12) or (restricted and not region.contains(p, -1e-12))  # type: ignore
    certified = gap <= CERTIFIED_GAP
    details = {'certificate_gap': gap, 'lower_bound': lower, **info}
    if not certified:
        rounding = (f', the cost\'s rounding alone {info["rounding"]:.2g} of it '
                    f'(a posterior {cost / problem.base_cost:.2g} of tr(W P W))')
        details['reason'] = (f'{POLAR} closed to a gap of {gap:.3g} only ({info["lines"]} '
                             f'lines, {info["rounds"]} witnesses'
                             f'{", event polynomials unresolved" if info["unresolved"] else ""}'
                             f'{rounding if info["rounding"] > 0.1 * CERTIFIED_GAP else ""}'
                             f'{"" if info["met"] else ", no line met the region"})')
    solution = make_solution(problem, p, method, on_boundary=on_boundary,  # type: ignore
                             candidates=info['lines'], details=details,
                             fallback=None if certified else 'best-line',
                             certificate=POLAR if certified else 'none')
    # the Joseph-form costs (base_cost - gain_at carries rounding of eps tr(W P W))
    return replace(solution, cost=cost, cost_at_slot=at_slot)


__all__ = ['CERTIFICATES', 'CERTIFIED_GAP', 'lines_plan']
