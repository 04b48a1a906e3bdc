"""Baseline strategies of paper Sec. V: MTF, CRM, MME (our interpretation) and GBS."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.strategies.base import OptionSpec, PlanContext, Solution, Strategy, \
    make_solution

#: Default GBS cell size as a fraction of r (the library default; the study uses 0.01).
DEFAULT_GBS_CELL = 0.005
#: Smallest admissible GBS cell: about pi / cell^2 = 0.8 million points (~50 MB of monomials).
MIN_GBS_CELL = 0.002


class MaintainFormation(Strategy):
    """MTF, maintain the formation: always the slot p_o."""

    name = 'mtf'

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The slot p_o."""
        return make_solution(problem, problem.p_o.copy(), self.name)


class ConstrainedRandomMotion(Strategy):
    """CRM, constrained random motion: a point uniformly distributed in the disc."""

    name = 'crm'

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """A uniform point of the disc drawn from ``context.rng`` (a fresh stream when None)."""
        rng = np.random.default_rng() if context.rng is None else context.rng
        radius = problem.r * math.sqrt(rng.random())
        angle = 2.0 * math.pi * rng.random()
        return make_solution(problem, problem.p_o + radius * np.array([math.cos(angle),
                                                                       math.sin(angle)]),
                             self.name)


class ActiveSideSteps(Strategy):
    """MME: our documented reading of the active strategy of Mariottini et al. (paper ref. [10]).

    The public description says only that a standard controller drives the follower to its
    slot unless the system is unobservable (leader on a straight line), when an active
    controller drives it to a point slightly off the slot. We read that as: while the leader
    drives straight, step sideways by ``amplitude`` r, perpendicular to the leader-follower line
    of sight, switching sides every ``period`` steps; otherwise go to p_o. The defaults (full
    amplitude, switching every step) are the reading used in README's study.
    """

    name = 'mme'
    OPTIONS = {
        'amplitude': OptionSpec(1.0, 'sideways step as a fraction of r', 0.0, 1.0),
        'period': OptionSpec(1, 'measurement steps on one side before switching', 1, 10**6),
    }

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """Sideways off the slot while the leader drives straight, else the slot."""
        if not context.leader_straight:
            return make_solution(problem, problem.p_o.copy(), self.name)
        theta_o = math.atan2(problem.p_o[1], problem.p_o[0])
        side = 1.0 if (int(context.step) // int(self.settings['period'])) % 2 == 0 else -1.0
        normal = np.array([-math.sin(theta_o), math.cos(theta_o)])
        amplitude = float(self.settings['amplitude'])
        return make_solution(problem, problem.p_o + side * amplitude * problem.r * normal,
                             self.name, on_boundary=amplitude == 1.0)


@lru_cache(maxsize=8)
def unit_grid(cell: float) -> np.ndarray:
    """Centres of a square grid of spacing ``cell`` inside the unit disc, shape (n, 2)."""
    half = int(math.floor(1.0 / cell))
    ticks = cell * np.arange(-half, half + 1)
    gx, gy = np.meshgrid(ticks, ticks)
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    inside = np.einsum('ij,ij->i', grid, grid) <= 1.0 + 1e-12
    grid = grid[inside]
    grid.setflags(write=False)
    return grid


class GridSearch(Strategy):
    """GBS, grid-based search: the best centre of a square grid over the disc (p_o included)."""

    name = 'gbs'
    OPTIONS = {'cell': OptionSpec(DEFAULT_GBS_CELL, 'grid spacing as a fraction of r',
                                  MIN_GBS_CELL, 1.0)}

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The grid point of highest gain."""
        cell = float(self.settings['cell'])
        points, monomials = grid_monomials(problem, cell)
        best = int(np.argmax(problem.gain_from_monomials(monomials)))
        return make_solution(problem, points[best].copy(), self.name,
                             bool(np.hypot(*(points[best] - problem.p_o))
                                  >= problem.r * (1 - cell)), len(points))


_GridKey = tuple[str, float, float, float, float]
_GRID_CACHE: dict[_GridKey, tuple[np.ndarray, np.ndarray]] = {}


def grid_monomials(problem: Problem, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Grid points (n, 2) over the problem's disc and their gain monomials, cached per geometry.

    The monomials depend only on the disc and the measurement kind, not on P or sigma, so a
    study with a fixed slot builds them once.
    """
    key = (problem.measurement, float(problem.p_o[0]), float(problem.p_o[1]), problem.r, cell)
    hit = _GRID_CACHE.get(key)
    if hit is None:
        points = problem.p_o + problem.r * unit_grid(cell)
        hit = (points, problem.monomials(points))
        if len(_GRID_CACHE) >= 8:
            _GRID_CACHE.pop(next(iter(_GRID_CACHE)))
        _GRID_CACHE[key] = hit
    return hit
