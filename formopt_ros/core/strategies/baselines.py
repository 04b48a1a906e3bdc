"""Baseline strategies of paper Sec. V: MTF, CRM, MME (our interpretation) and GBS."""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.strategies.common import Plan

#: Default GBS cell size as a fraction of r (the library default; the Monte Carlo uses 0.01).
DEFAULT_GBS_CELL = 0.005


def plan_mtf(problem: Problem, rng: np.random.Generator | None = None) -> Plan:
    """MTF, maintain the formation: always the slot p_o."""
    return Plan(problem.p_o.copy())


def plan_crm(problem: Problem, rng: np.random.Generator | None = None) -> Plan:
    """CRM, constrained random motion: a point uniformly distributed in the disc."""
    rng = np.random.default_rng() if rng is None else rng
    radius = problem.r * math.sqrt(rng.random())
    angle = 2.0 * math.pi * rng.random()
    return Plan(problem.p_o + radius * np.array([math.cos(angle), math.sin(angle)]))


def plan_mme(problem: Problem, rng: np.random.Generator | None = None, step: int = 0,
             leader_straight: bool = True) -> Plan:
    """MME: our documented reading of the active strategy of Mariottini et al. (paper ref. [10]).

    The public description says only that a standard controller drives the follower to its
    slot unless the system is unobservable (leader on a straight line), when an active
    controller drives it to a point slightly off the slot. We read that as: while the leader
    drives straight, step sideways by the full allowance r, perpendicular to the leader-follower
    line of sight, alternating sides on even/odd steps; otherwise go to p_o.

    Args:
        step: measurement step index; its parity chooses the side.
        leader_straight: whether the leader currently drives straight (unobservable case).
    """
    if not leader_straight:
        return Plan(problem.p_o.copy())
    theta_o = math.atan2(problem.p_o[1], problem.p_o[0])
    side = 1.0 if int(step) % 2 == 0 else -1.0
    normal = np.array([-math.sin(theta_o), math.cos(theta_o)])
    return Plan(problem.p_o + side * problem.r * normal, on_boundary=True)


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


def plan_gbs(problem: Problem, rng: np.random.Generator | None = None,
             cell: float = DEFAULT_GBS_CELL) -> Plan:
    """GBS, grid-based search: the best centre of a square grid over the disc.

    Args:
        cell: grid spacing as a fraction of r (0 < cell <= 1); the slot p_o is a grid point.
    """
    cell = float(cell)
    if not (0.0 < cell <= 1.0):
        raise ValueError(f'gbs option cell must be in (0, 1] (fraction of r), got {cell!r}')
    points, monomials = grid_monomials(problem, cell)
    best = int(np.argmax(problem.gain_from_monomials(monomials)))
    return Plan(points[best].copy(), len(points),
                bool(np.hypot(*(points[best] - problem.p_o)) >= problem.r * (1 - cell)))


_GRID_CACHE: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


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
