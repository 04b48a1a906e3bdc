"""Baseline strategies of paper Sec. V: MTF, CRM, MME (our interpretation) and GBS."""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.formulas import Entries, monomials, weighted_sum
from formopt_ros.core.model import RANGE, RANGE_BEARING
from formopt_ros.core.strategies.base import (
    BatchContext, BatchPlan, OptionSpec, PlanContext, Solution, Strategy, make_solution)

#: Default GBS cell size as a fraction of r (the library default; the study uses 0.01).
DEFAULT_GBS_CELL = 0.005
#: Smallest admissible GBS cell: about pi / cell^2 = 0.8 million points (~50 MB of monomials).
MIN_GBS_CELL = 0.002
#: Grid cells per side of a GBS pruning block.
BLOCK_CELLS = 8
#: Relative room for rounding when GBS skips a block (see :func:`grid_argmax`).
PRUNE_RTOL = 1e-9


class MaintainFormation(Strategy):
    """MTF, maintain the formation: always the slot p_o."""

    name = 'mtf'

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The slot p_o."""
        return make_solution(problem, problem.p_o, self.name)

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """Every trial's slot."""
        return BatchPlan(np.array(problems.p_o, dtype=float))


class ConstrainedRandomMotion(Strategy):
    """CRM, constrained random motion: a point uniformly distributed in the disc."""

    name = 'crm'

    @staticmethod
    def draw(p_o: np.ndarray, r: float, rng: np.random.Generator) -> tuple[float, float]:
        """A uniform point (m) of the disc |p - p_o| <= r: two draws of ``rng``."""
        radius = r * math.sqrt(rng.random())
        angle = 2.0 * math.pi * rng.random()
        return float(p_o[0] + radius * math.cos(angle)), float(p_o[1] + radius * math.sin(angle))

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """A uniform point of the disc drawn from ``context.rng`` (a fresh stream when None)."""
        rng = np.random.default_rng() if context.rng is None else context.rng
        return make_solution(problem, self.draw(problem.p_o, problem.r, rng), self.name)

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """One draw per trial from the trial's own stream."""
        return BatchPlan(np.array([self.draw(problems.p_o[t], problems.r[t], context.rngs[t])
                                   for t in range(len(problems))]))


class ActiveSideSteps(Strategy):
    """MME: our documented reading of the active strategy of Mariottini et al. (paper ref. [10]).

    The public description says only that a standard controller drives the follower to its
    slot unless the system is unobservable (leader on a straight line), when an active
    controller drives it to a point slightly off the slot. We read that as: while the leader
    drives straight, step sideways by ``amplitude`` r, perpendicular to the leader-follower line
    of sight, switching sides every ``period`` steps; otherwise go to p_o. The defaults (full
    amplitude, switching every step) are the reading used in the study (docs/results.md).
    ``while_turning`` steps sideways whatever the leader does: the widest change of direction
    to the leader that the disc allows, which is what reveals a range bias (docs/real_robots.md).
    """

    name = 'mme'
    OPTIONS = {
        'amplitude': OptionSpec(1.0, 'sideways step as a fraction of r', 0.0, 1.0),
        'period': OptionSpec(1, 'measurement steps on one side before switching', 1, 10**6),
        'while_turning': OptionSpec(False, 'step sideways also while the leader turns, which '
                                    'reveals a range bias'),
    }

    def target(self, p_o: np.ndarray, r: float, context: PlanContext | BatchContext
               ) -> tuple[tuple[float, float], bool]:
        """(point m, on the boundary) for slot p_o, deviation r and the step's context."""
        x_o, y_o = float(p_o[0]), float(p_o[1])
        if not self.settings['while_turning'] and not all(
                omega == 0.0 for _, omega in context.leader_velocities):
            return (x_o, y_o), False
        theta_o = math.atan2(y_o, x_o)
        side = 1.0 if (int(context.step) // int(self.settings['period'])) % 2 == 0 else -1.0
        step = side * float(self.settings['amplitude']) * float(r)
        return (x_o + step * -math.sin(theta_o), y_o + step * math.cos(theta_o)), \
            float(self.settings['amplitude']) == 1.0

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """Sideways off the slot while the leader drives straight (or always), else the slot."""
        point, on_boundary = self.target(problem.p_o, problem.r, context)
        return make_solution(problem, point, self.name, on_boundary=on_boundary)

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """The same side step for every trial."""
        return BatchPlan(np.array([self.target(problems.p_o[t], problems.r[t], context)[0]
                                   for t in range(len(problems))]))


@lru_cache(maxsize=8)
def unit_grid(cell: float) -> np.ndarray:
    """Centres of a square grid of spacing ``cell`` inside the unit disc, shape (n, 2), in
    row-major order (y outer, x inner)."""
    half = int(math.floor(1.0 / cell))
    ticks = cell * np.arange(-half, half + 1)
    gx, gy = np.meshgrid(ticks, ticks)
    grid = np.stack([gx.ravel(), gy.ravel()], axis=1)
    inside = np.einsum('ij,ij->i', grid, grid) <= 1.0 + 1e-12
    grid = grid[inside]
    grid.setflags(write=False)
    return grid


@dataclass(frozen=True)
class Grid:
    """A GBS grid over one disc, cut into square blocks of BLOCK_CELLS x BLOCK_CELLS cells.

    Attributes:
        points: grid points in {L}, block after block, shape (n, 2), m.
        rank: position of each point in the row-major grid order (ties go to the lowest).
        monomials: the gain's monomials at the points, k arrays of shape (n,).
        starts: offsets of the blocks in ``points``, shape (B + 1,).
        centre: index (into ``points``) of each block's point nearest its centroid, shape (B,).
        features: the monomials and 1 at the block centres, shape (k + 1, B).
        centre_h: homogeneous vectors of the centres, [h0, h1, 1] (the third component enters
            as -1 (bearing) or 0 (range) through the signs of the matrix rows), shape (3, B).
        radius: largest distance of a block's homogeneous vectors from its centre's, (B,).
        position: inverse of ``rank``: the index in ``points`` of each row-major position.
    """

    points: np.ndarray
    rank: np.ndarray
    monomials: tuple[np.ndarray, ...]
    starts: np.ndarray
    centre: np.ndarray
    features: np.ndarray
    centre_h: np.ndarray
    radius: np.ndarray
    position: np.ndarray

    @classmethod
    def build(cls, measurement: str, p_o: tuple[float, float], r: float,
              cell: float) -> 'Grid':
        """The grid of spacing cell r over the disc |p - p_o| <= r (p_o included)."""
        unit = unit_grid(cell)
        lattice = np.rint(unit / cell).astype(np.int64) + int(math.floor(1.0 / cell))
        blocks_per_row = int(lattice.max()) // BLOCK_CELLS + 1
        block = (lattice[:, 1] // BLOCK_CELLS) * blocks_per_row + lattice[:, 0] // BLOCK_CELLS
        order = np.argsort(block, kind='stable')
        points = np.asarray(p_o) + r * unit[order]
        block = block[order]
        starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1], True])
        x, y = points[:, 0], points[:, 1]
        d2 = x * x + y * y
        hx, hy = (x / np.sqrt(d2), y / np.sqrt(d2)) if measurement == RANGE else (-y / d2, x / d2)
        count = np.diff(starts)
        segment = np.repeat(np.arange(len(count)), count)
        mean_x = np.add.reduceat(hx, starts[:-1]) / count
        mean_y = np.add.reduceat(hy, starts[:-1]) / count
        distance = np.hypot(hx - mean_x[segment], hy - mean_y[segment])
        centre = starts[:-1] + np.array([int(np.argmin(distance[a:b]))
                                         for a, b in zip(starts[:-1], starts[1:])])
        spread = np.hypot(hx - hx[centre][segment], hy - hy[centre][segment])
        radius = np.maximum.reduceat(spread, starts[:-1]) * (1.0 + 1e-12)
        terms = monomials(measurement, x, y)
        features = np.array([t[centre] for t in terms] + [np.ones(len(centre))])
        centre_h = np.array([hx[centre], hy[centre], np.ones(len(centre))])
        grid = cls(points, order, terms, starts, centre, features, centre_h, radius,
                   np.argsort(order))
        for array in (grid.points, grid.rank, grid.starts, grid.centre, grid.features,
                      grid.centre_h, grid.radius, grid.position, *grid.monomials):
            array.setflags(write=False)
        return grid


_GridKey = tuple[str, float, float, float, float]
_GRID_CACHE: dict[_GridKey, Grid] = {}


def grid_for(measurement: str, p_o: tuple[float, float], r: float, cell: float) -> Grid:
    """The :class:`Grid` of a geometry, built once and cached (8 geometries at most)."""
    key = (measurement, float(p_o[0]), float(p_o[1]), float(r), float(cell))
    grid = _GRID_CACHE.get(key)
    if grid is None:
        grid = Grid.build(measurement, (key[1], key[2]), key[3], cell)
        if len(_GRID_CACHE) >= 8:
            _GRID_CACHE.pop(next(iter(_GRID_CACHE)))
        _GRID_CACHE[key] = grid
    return grid


def grid_argmax(grid: Grid, measurement: str, forms: tuple[Entries, Entries],
                coefficients: tuple[tuple[Any, ...], tuple[Any, ...]], R: Any) -> np.ndarray:
    """Index (into ``grid.points``) of the highest-gain grid point of each of T problems.

    Exact (the same point as evaluating every grid point, ties to the lowest row-major rank),
    but only blocks that may hold the best point are evaluated. With lambda the best gain among
    the block centres and K = A - lambda B the quotient's matrices (module
    :mod:`~formopt_ros.core.strategies.certificate`), a block can hold a point of gain above
    lambda only if h'Kh > 0 somewhere in it; for h = h_c + delta with |delta| <= radius,

        h'Kh <= h_c'K h_c + 2 radius |(K h_c)_12| + radius^2 max(0, lambda_max(K_12,12)),

    so blocks where this bound is below -1e-9 lambda h_c'B h_c (room for rounding) are skipped.
    Gains are evaluated with :func:`~formopt_ros.core.formulas.weighted_sum` point by point, so a
    batch and its single problems give bit-identical results.

    Args:
        grid: the geometry's grid.
        measurement: 'range' or 'bearing'.
        forms: entries of M and N (floats, or arrays of shape (T,)).
        coefficients: the gain's coefficients (same shapes).
        R: noise variance (float or (T,)).

    Returns:
        Indices, shape (T,) (T = 1 for float inputs).
    """
    T = max(np.size(c) for part in coefficients for c in part)

    def columns(values: tuple[Any, ...]) -> np.ndarray:
        """Floats or arrays (T,) as the columns of an array (T, len(values))."""
        return np.stack(np.broadcast_arrays(*(np.asarray(v, dtype=float).reshape(-1)
                                              for v in values), np.zeros(T)), axis=1)[:, :-1]

    num, den = (columns(part) for part in coefficients)
    # the bounds (BLAS products, any rounding: PRUNE_RTOL leaves room)
    num_c, den_c = num @ grid.features, den @ grid.features
    lam = np.max(num_c / den_c, axis=1, keepdims=True)
    (m00, m01, m02, m11, m12, _), (n00, n01, n02, n11, n12, _) = forms
    if measurement == RANGE:         # h = u (two components): A = M_12,12, B = P_12,12 + R I
        n00, n11 = n00 + R, n11 + R
        m02 = m12 = n02 = n12 = 0.0
    K = (columns((m00, m01, -m02, m01, m11, -m12))
         - lam * columns((n00, n01, -n02, n01, n11, -n12)))       # rows of (M - lam N)_12,:
    g0, g1 = K[:, 0:3] @ grid.centre_h, K[:, 3:6] @ grid.centre_h
    k00, k01, k11 = K[:, 0:1], K[:, 1:2], K[:, 4:5]
    curvature = np.maximum(0.0, 0.5 * (k00 + k11) + np.hypot(0.5 * (k00 - k11), k01))
    bound = (num_c - lam * den_c + 2.0 * grid.radius * np.hypot(g0, g1)
             + grid.radius * grid.radius * curvature)
    trial, block = np.nonzero(bound >= -PRUNE_RTOL * lam * den_c)
    num_t, den_t = num.T, den.T
    # every point of the kept blocks, trial by trial
    count = grid.starts[block + 1] - grid.starts[block]
    first = np.repeat(grid.starts[block] - np.cumsum(count) + count, count)
    index = first + np.arange(int(count.sum()))
    owner = np.repeat(trial, count)
    terms = tuple(m[index] for m in grid.monomials)
    gains = (weighted_sum(tuple(c[owner] for c in num_t[:-1]), terms, num_t[-1][owner])
             / weighted_sum(tuple(c[owner] for c in den_t[:-1]), terms, den_t[-1][owner]))
    segments = np.flatnonzero(np.r_[True, owner[1:] != owner[:-1]])
    best = np.maximum.reduceat(gains, segments)
    rank = np.where(gains == np.repeat(best, np.diff(np.r_[segments, len(gains)])),
                    grid.rank[index], np.iinfo(np.int64).max)
    best_rank = np.minimum.reduceat(rank, segments)
    return grid.position[best_rank]


class GridSearch(Strategy):
    """GBS, grid-based search: the best point of a square grid over the disc (p_o included)."""

    name = 'gbs'
    OPTIONS = {'cell': OptionSpec(DEFAULT_GBS_CELL, 'grid spacing as a fraction of r',
                                  MIN_GBS_CELL, 1.0)}

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The grid point of highest gain (range-bearing: the gain evaluated at every grid
        point of the same grid)."""
        cell = float(self.settings['cell'])
        if problem.measurement == RANGE_BEARING:
            grid = grid_for(RANGE, problem.slot, float(problem.r), cell)
            gains = problem.gain_at(grid.points[:, 0], grid.points[:, 1])
            return self._solution(problem, grid, int(np.argmax(gains)), cell)
        grid = grid_for(problem.measurement, problem.slot, float(problem.r), cell)
        best = int(grid_argmax(grid, problem.measurement, problem.forms, problem.coefficients,
                               problem.R)[0])
        return self._solution(problem, grid, best, cell)

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """The grid point of highest gain of every problem of a batch sharing one geometry."""
        cell = float(self.settings['cell'])
        slot = (float(problems.p_o[0, 0]), float(problems.p_o[0, 1]))
        grid = grid_for(problems.measurement, slot, float(problems.r[0]), cell)
        best = grid_argmax(grid, problems.measurement, problems.forms, problems.coefficients,
                           problems.R)
        return BatchPlan(grid.points[best])

    @staticmethod
    def _solution(problem: Problem, grid: Grid, best: int, cell: float) -> Solution:
        point = grid.points[best]
        return make_solution(problem, point, GridSearch.name,
                             bool(math.hypot(point[0] - problem.slot[0],
                                             point[1] - problem.slot[1])
                                  >= problem.r * (1 - cell)), len(grid.points))
