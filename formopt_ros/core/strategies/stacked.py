"""Certified range-bearing optimum over a reachable set: branch and bound (docs/range_bearing.md).

Over the whole disc the optimum comes from :mod:`formopt_ros.core.strategies.polar` (lines
through the leader); this search covers a region that restricts the disc. Each square cell
(centre c, half-width w, radius rho = w sqrt 2) gets a lower bound of the cost
over the cell from the convexity of F(I) = tr(W (P^-1 + I)^-1 W) in the information
I(p) = sum_i h_i h_i' / R_i:

    f(p) >= f(c) + <G, I(p) - I(c)>,   G = -P_c W^2 P_c   (P_c the posterior at c),

and <G, I(p) - I(c)> = sum_i (2 h_i(c)' G D_i + D_i' G D_i) / R_i with D_i = h_i(p) - h_i(c).
Taylor's theorem with |D h_d| <= 1/d, |D^2 h_d| <= (2/sqrt 3)/d^2, |D h_beta| <= 1/d^2,
|D^2 h_beta| <= 2/d^3 (d the cell's least distance from the leader; both second-derivative
bounds are attained, docs/range_bearing.md) gives

    f(p) >= f(c) + grad f(c)'(p - c) - rho^2 sum_i (|(G h_i)_xy| L2_i + |G_xy| L1_i^2) / R_i,

and the linear term's minimum over cell and disc is at least the larger of its minima over the
square and over the disc. The bound is of second order in rho, so cells near a minimum are
pruned once rho^2 is below the tolerance and the search ends after a few levels. Cells are
split in SPLIT x SPLIT until every remaining lower bound is within ``RTOL`` of the best
feasible cost found (``LOOSE_RTOL`` where the cell budget would not allow RTOL); the
certificate's gap is that tolerance plus a rounding margin (``ROUNDING`` times the cost, for
the Joseph-form evaluation; an estimate, not a proof). The search is capped; a search that
hits the cap is not certified and says so (``Solution.fallback = 'grid'``).

Over a reachable set (a :class:`~formopt_ros.core.reach.Region`: the slot's disc, the reach
disc, outside the safety circle) the search prunes the cells that lie wholly outside one
of the region's circles and takes its incumbents only from feasible cell centres (and the
region's point nearest the slot, its corners, and the caller's seeds); the bounds stay valid
(each holds over the whole cell). Where a constraint is active at the optimum, the cells that
straddle it keep points beyond it that are cheaper than the optimum, so their bounds do not
close: the search stops at ``REGION_MAX_CELLS``, the best point is polished along each circle
it lies on (a bounded 1-D search in the angle), and the answer carries the gap it reached,
certified only when that gap is within ``CERTIFIED_GAP``.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from formopt_ros.core.reach import Circle, Region
from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.strategies.base import Solution, make_solution
from formopt_ros.core.strategies.polar import POLAR, polar_optimum

#: Relative tolerance the search closes to (of the best cost).
RTOL = 1e-10
#: Rounding margin of each cost evaluation (Joseph form), relative to the cost: an estimate
#: (the test compares the form with 50-digit arithmetic: below 1e-14 on every family).
ROUNDING = 1e-12
#: Gap (relative to the cost) up to which an answer counts as certified.
CERTIFIED_GAP = 1e-9
#: Tolerance the search falls back to when closing to RTOL would exceed its cell budget.
LOOSE_RTOL = 5e-10
#: Cells processed at most over a restricted region (module docstring; a search beyond it
#: falls back: uncertified, best point found).
REGION_MAX_CELLS = 20_000
#: Half-width of the angle window of the polish along a circle, in first-grid cells.
POLISH_CELLS = 2.0
#: Windows of the polish along a circle, each 16 times narrower than the one before.
POLISH_LEVELS = 5
#: Cells per side of the first grid over the disc's bounding square.
FIRST_GRID = 8
#: Each cell kept is split into SPLIT x SPLIT cells.
SPLIT = 8
#: sup |D^2 h_d [v, v]| d^2 / |v|^2 over directions (sympy: s^2 (4 - 3 s^2) <= 4/3, s the sine
#: of the angle between v and p).
L2_RANGE = 2.0 / math.sqrt(3.0)
#: |D^2 h_beta [v, v]| d^3 / |v|^2 for every direction (h_beta's xy part is a rotated inversion
#: p / |p|^2, i.e. 1 / conj(z): second derivative 2 conj(v)^2 / conj(z)^3).
L2_BEARING = 2.0
#: Certificate name of a closed search.
BRANCH_AND_BOUND = 'branch-and-bound'


def posterior_terms(problem: StackedProblem, x: np.ndarray, y: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At points (x, y) (n,) (m): the cost tr(W P_c W) (m^2), its gradient (2, n) and the
    curvature weight sum_i (|(G h_i)_xy| L2_i d^k + |G_xy| L1_i^2 d^k) / R_i of the module
    docstring with the distance factors left out, as three per-row coefficients (3, n):
    [range second-derivative term, bearing second-derivative term, |G_xy|]."""
    (p00, p01, p02), (_, p11, p12), (_, _, p22) = problem.P.tolist()
    r_d, r_b = problem.R
    w22 = problem.w22
    d2 = x * x + y * y
    d = np.sqrt(d2)
    ux, uy = x / d, y / d
    bx, by = -y / d2, x / d2
    a0, a1, a2 = p00 * ux + p01 * uy, p01 * ux + p11 * uy, p02 * ux + p12 * uy        # P h_d
    b0, b1, b2 = p00 * bx + p01 * by - p02, p01 * bx + p11 * by - p12, \
        p02 * bx + p12 * by - p22                                                   # P h_b
    s00 = ux * a0 + uy * a1 + r_d
    s01 = ux * b0 + uy * b1
    s11 = bx * b0 + by * b1 - b2 + r_b
    det = s00 * s11 - s01 * s01
    i00, i01, i11 = s11 / det, -s01 / det, s00 / det
    # Joseph form Q = A P A' + K R K', A = I - K H, K = [P h_d, P h_b] S^-1: no cancellation
    # (P - K S K' loses digits where the update removes most of tr(W P W))
    n = x.size
    K = np.empty((n, 3, 2))
    for i, (ai, bi) in enumerate(((a0, b0), (a1, b1), (a2, b2))):
        K[:, i, 0], K[:, i, 1] = ai * i00 + bi * i01, ai * i01 + bi * i11
    H = np.empty((n, 2, 3))
    H[:, 0, 0], H[:, 0, 1], H[:, 0, 2] = ux, uy, 0.0
    H[:, 1, 0], H[:, 1, 1], H[:, 1, 2] = bx, by, -1.0
    A = np.eye(3) - K @ H
    Q = A @ problem.P @ np.swapaxes(A, 1, 2) + (K * (r_d, r_b)) @ np.swapaxes(K, 1, 2)
    q00, q01, q02 = Q[:, 0, 0], 0.5 * (Q[:, 0, 1] + Q[:, 1, 0]), 0.5 * (Q[:, 0, 2] + Q[:, 2, 0])
    q11, q12, q22 = Q[:, 1, 1], 0.5 * (Q[:, 1, 2] + Q[:, 2, 1]), Q[:, 2, 2]
    cost = q00 + q11 + w22 * q22
    # G = -Q W^2 Q, the entries needed (00, 01, 11, 02, 12)
    g00 = -(q00 * q00 + q01 * q01 + w22 * q02 * q02)
    g01 = -(q00 * q01 + q01 * q11 + w22 * q02 * q12)
    g11 = -(q01 * q01 + q11 * q11 + w22 * q12 * q12)
    g02 = -(q00 * q02 + q01 * q12 + w22 * q02 * q22)
    g12 = -(q01 * q02 + q11 * q12 + w22 * q12 * q22)
    gd0, gd1 = g00 * ux + g01 * uy, g01 * ux + g11 * uy                 # (G h_d)_xy
    gb0, gb1 = g00 * bx + g01 * by - g02, g01 * bx + g11 * by - g12     # (G h_b)_xy
    d3, d4 = d2 * d, d2 * d2
    # derivatives of the xy parts: d h_d / dx = (y^2, -xy) / d^3, d h_d / dy = (-xy, x^2) / d^3,
    # d h_b / dx = (2xy, y^2 - x^2) / d^4, d h_b / dy = (y^2 - x^2, -2xy) / d^4
    xy, yy_xx = x * y, y * y - x * x
    gx = 2.0 * ((gd0 * y * y - gd1 * xy) / (d3 * r_d) + (gb0 * 2.0 * xy + gb1 * yy_xx)
                / (d4 * r_b))
    gy = 2.0 * ((-gd0 * xy + gd1 * x * x) / (d3 * r_d) + (gb0 * yy_xx - gb1 * 2.0 * xy)
                / (d4 * r_b))
    # spectral norm of G_xy, a block of the negative semidefinite G: its largest eigenvalue of -G
    g_xy = -0.5 * (g00 + g11) + np.hypot(0.5 * (g00 - g11), g01)
    return cost, np.stack([gx, gy]), np.stack([np.hypot(gd0, gd1), np.hypot(gb0, gb1), g_xy])


def cell_bounds(problem: StackedProblem, cx: np.ndarray, cy: np.ndarray, w: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """(cost at the centres, lower bound of the cost over each cell within the disc) for
    square cells of half-width w (m) around centres (cx, cy) (n,) (m); the bound is -inf for a
    cell that may hold the leader and +inf for one that misses the disc."""
    cost, (gx, gy), norms = posterior_terms(problem, cx, cy)
    return cost, lower_bounds(problem, cx, cy, w, cost, gx, gy, norms)


def lower_bounds(problem: StackedProblem, cx: np.ndarray, cy: np.ndarray, w: float,
                 cost: np.ndarray, gx: np.ndarray, gy: np.ndarray, norms: np.ndarray
                 ) -> np.ndarray:
    """The cells' lower bounds (module docstring) from the terms of :func:`posterior_terms`:
    the larger of the second-order bound and the first-order one
    f(c) - sum_i (2 |(G h_i)_xy| D_i + |G_xy| D_i^2) / R_i, where D_i bounds |h_i(p) - h_i(c)|
    without derivatives (|p/|p| - c/|c|| <= 2 |p - c| / (|p| + |c|) and
    |p/|p|^2 - c/|c|^2| = |p - c| / (|p| |c|)), which stays useful next to the leader."""
    r_d, r_b = problem.R
    gh_d, gh_b, g_xy = norms
    rho = w * math.sqrt(2.0)
    x_o, y_o = problem.slot
    linear = linear_minimum(gx, gy, cx, cy, w, x_o, y_o, problem.r)
    d_c = np.hypot(cx, cy)
    near = np.maximum(d_c - rho, 0.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        step_d = np.minimum(2.0 * rho / (near + d_c), 2.0)
        step_b = rho / (near * d_c)
        second = cost + linear - (gh_d * L2_RANGE * rho * rho / (near * near)
                                  + g_xy * step_d * step_d) / r_d \
            - (gh_b * L2_BEARING * rho * rho / (near * near * near) + g_xy * step_b * step_b) / r_b
        first = cost - (2.0 * gh_d * step_d + g_xy * step_d * step_d) / r_d \
            - (2.0 * gh_b * step_b + g_xy * step_b * step_b) / r_b
        lower = np.maximum(np.where(np.isnan(second), -np.inf, second),
                           np.where(np.isnan(first), -np.inf, first))
    return np.where(np.isposinf(linear), np.inf,
                    np.where((near > 0.0) & np.isfinite(lower), lower, -np.inf))


_CORNERS = np.array([[-1.0, -1.0, 1.0, 1.0], [-1.0, 1.0, -1.0, 1.0]])[:, :, None]    # (2, 4, 1)
_SIDES = np.array([-1.0, 1.0])[:, None, None]                                      # (2, 1, 1)
_SIGNS = np.array([-1.0, 1.0])[None, :, None]                                      # (1, 2, 1)


def linear_minimum(gx: np.ndarray, gy: np.ndarray, cx: np.ndarray, cy: np.ndarray, w: float,
                   x_o: float, y_o: float, r: float) -> np.ndarray:
    """min of g'(p - c) over the square |p - c|_inf <= w intersected with the disc
    |p - p_o| <= r, per cell (arrays (n,)); +inf where the two do not meet.

    A linear function takes its minimum over the convex set at an extreme point: a corner of
    the square inside the disc, a crossing of a side with the circle, or the disc's own
    minimiser p_o - r g / |g| when it lies in the square. Candidates are admitted with a slack
    of 1e-12 r and the minimum lowered by 1e-12 r |g| (rounding of the candidates).
    """
    slack = 1e-12 * r
    ox, oy = cx - x_o, cy - y_o
    sx, sy = w * _CORNERS[0], w * _CORNERS[1]                                 # (4, 1)
    corner = np.where(np.hypot(ox + sx, oy + sy) <= r + slack, gx * sx + gy * sy, np.inf)
    best = corner.min(axis=0)
    side = w * _SIDES                                                          # (2, 1, 1)
    for a, b, ga, gb in ((ox, oy, gx, gy), (oy, ox, gy, gx)):      # sides a = const, along b
        reach = r * r - (a + side) ** 2                                        # (2, 1, n)
        offset = _SIGNS * np.sqrt(np.maximum(reach, 0.0)) - b                  # (2, 2, n)
        ok = (reach >= 0.0) & (np.abs(offset) <= w + slack)
        best = np.minimum(best, np.where(ok, ga * side + gb * offset, np.inf).min(axis=(0, 1)))
    norm = np.hypot(gx, gy)
    with np.errstate(divide='ignore', invalid='ignore'):
        mx, my = -r * gx / norm - ox, -r * gy / norm - oy
    ok = (norm > 0.0) & (np.abs(mx) <= w + slack) & (np.abs(my) <= w + slack)
    best = np.minimum(best, np.where(ok, gx * mx + gy * my, np.inf))
    return best - 1e-12 * r * norm


def branch_and_bound(problem: StackedProblem, rtol: float = RTOL,
                     max_cells: int = REGION_MAX_CELLS,
                     region: Region | None = None,
                     seeds: tuple[tuple[float, float], ...] = ()
                     ) -> tuple[tuple[float, float], float, float, dict[str, Any]]:
    """The global minimum of the cost over the disc (or over ``region``, a non-empty subset of
    it, with feasible ``seeds`` (m) as first incumbents), to ``rtol``.

    Returns:
        (point (m), its cost (m^2, :meth:`StackedProblem.cost_at`), proved lower bound of the
        cost over the disc or region (m^2; when the cap stopped the search, the least bound of
        the cells still open), diagnostics: cells, levels, capped).
    """
    x_o, y_o = problem.slot
    r = problem.r
    n = FIRST_GRID
    w = r / n
    offsets = (np.arange(n) - (n - 1) / 2.0) * 2.0 * w
    cx, cy = (a.ravel() for a in np.meshgrid(x_o + offsets, y_o + offsets))
    circles: list[Circle] = region.circles() if region is not None else []
    if region is None:
        best_p = problem.slot
        best = problem.cost_at(x_o, y_o)
    else:
        starts = [q for q in (region.nearest(problem.slot), *region.corners(), *seeds)
                  if q is not None]
        costs = [problem.cost_at(*q) for q in starts]
        best_p, best = starts[int(np.argmin(costs))], min(costs)
    floor = math.inf                    # least lower bound of the cells pruned
    open_floor = -math.inf              # least lower bound of the cells split last
    cells, levels = 0, 0
    while cx.size:
        rho = w * math.sqrt(2.0)
        dx, dy = cx - x_o, cy - y_o
        dist = np.hypot(dx, dy)
        inside = dist - rho <= r
        feasible = dist <= r
        for ccx, ccy, radius, within in circles[1:]:     # the reach and safety circles
            gap = np.hypot(cx - ccx, cy - ccy)
            inside &= (gap - rho <= radius) if within else (gap + rho >= radius)
            feasible &= (gap <= radius) if within else (gap >= radius)
        cx, cy, dx, dy, dist = cx[inside], cy[inside], dx[inside], dy[inside], dist[inside]
        feasible = feasible[inside]
        count = cx.size
        if not count:
            break
        if cells + count > max_cells:       # the open cells' parents bound what is left
            return best_p, best, min(floor, open_floor, best) - ROUNDING * abs(best), \
                {'cells': cells, 'levels': levels, 'capped': True}
        cells += count
        # feasible candidates: the centres in the disc and (without a region) the others
        # projected on it
        out = dist > r if region is None else np.zeros(count, dtype=bool)
        scale = r / dist[out]
        px, py = x_o + dx[out] * scale, y_o + dy[out] * scale
        cost, grad, k = posterior_terms(problem, np.concatenate([cx, px]),
                                        np.concatenate([cy, py]))
        candidates = cost.copy()
        candidates[:count][~feasible] = np.inf
        j = int(np.argmin(candidates))
        if candidates[j] < best:
            point = (float(np.concatenate([cx, px])[j]), float(np.concatenate([cy, py])[j]))
            value = problem.cost_at(*point)
            if value < best:
                best, best_p = value, point
        lower = lower_bounds(problem, cx, cy, w, cost[:count], grad[0, :count], grad[1, :count],
                             k[:, :count])
        margin = ROUNDING * abs(best)
        keep = lower < best - rtol * abs(best) - margin
        if cells + SPLIT * SPLIT * int(keep.sum()) > max_cells:    # budget tight: close to
            keep = lower < best - LOOSE_RTOL * abs(best) - margin   # the looser tolerance
        if not keep.all():
            floor = min(floor, float(lower[~keep].min()))
        cx, cy = cx[keep], cy[keep]
        open_floor = float(lower[keep].min()) if keep.any() else math.inf
        offsets = (np.arange(SPLIT) - (SPLIT - 1) / 2.0) * (2.0 * w / SPLIT)
        w /= SPLIT
        levels += 1
        cx = (cx[:, None, None] + offsets[None, :, None] + 0.0 * offsets[None, None, :]).ravel()
        cy = (cy[:, None, None] + 0.0 * offsets[None, :, None] + offsets[None, None, :]).ravel()
    return best_p, best, min(floor, best) - ROUNDING * abs(best), {'cells': cells,
                                                                   'levels': levels}


def polish_on_circles(problem: StackedProblem, region: Region, p: tuple[float, float],
                      cost: float) -> tuple[tuple[float, float], float]:
    """The best of p (m), a local minimum from p under the region's circles (SLSQP), and, for
    each circle of ``region``, the feasible points of that circle within POLISH_CELLS
    first-grid cells of p's projection on it (a bounded search in the angle): the optimum lies
    between cell centres, on a circle where a constraint is active. Returns (point m, cost
    m^2)."""
    from scipy.optimize import minimize, minimize_scalar
    window = POLISH_CELLS * 2.0 * problem.r / FIRST_GRID
    scale = problem.r * problem.r
    constraints = [{'type': 'ineq', 'fun': (lambda z, c=c: (c[2] ** 2 - (
        (z[0] - c[0]) ** 2 + (z[1] - c[1]) ** 2)) / scale * (1.0 if c[3] else -1.0))}
        for c in region.circles()]
    found = minimize(lambda z: problem.cost_at(float(z[0]), float(z[1])), np.array(p),
                     method='SLSQP', constraints=constraints,
                     options={'ftol': 1e-16, 'maxiter': 100})
    q = (float(found.x[0]), float(found.x[1]))
    if region.contains(q) and problem.cost_at(*q) < cost:
        p, cost = q, problem.cost_at(*q)

    for ccx, ccy, radius, _ in region.circles():
        if radius <= 0.0:
            continue

        def along(angle: float) -> float:
            q = (ccx + radius * math.cos(angle), ccy + radius * math.sin(angle))
            return problem.cost_at(*q) if region.contains(q) else 1e300
        theta = math.atan2(p[1] - ccy, p[0] - ccx)
        for level in range(POLISH_LEVELS):    # windows shrinking around the best angle: a wide
            half = min(math.pi, window / radius) / 16.0 ** level   # one may hold other minima
            found = minimize_scalar(along, bounds=(theta - half, theta + half),
                                    method='bounded', options={'xatol': 1e-12})
            for angle in (float(found.x), theta):
                value = along(angle)
                if value < cost:
                    p = (ccx + radius * math.cos(angle), ccy + radius * math.sin(angle))
                    cost, theta = value, angle
    return p, cost


def stacked_plan(problem: StackedProblem, method: str, max_cells: int = REGION_MAX_CELLS,
                 region: Region | None = None,
                 seeds: tuple[tuple[float, float], ...] = ()) -> Solution:
    """The certified optimum of a range-bearing problem as a Solution, with
    ``details['certificate_gap']`` and ``details['lower_bound']``.

    Over the disc (no ``region``, or one that does not restrict it) the lines through the
    leader (:func:`~formopt_ros.core.strategies.polar.polar_optimum`, certificate
    'polar-lines'); over a restricting, non-empty ``region`` the branch and bound (module
    docstring; at most ``max_cells`` cells, certificate 'branch-and-bound'), its best point
    polished along the region's circles. An answer whose gap exceeds CERTIFIED_GAP is the best
    point found, with ``fallback = 'grid'``, certificate 'none' and the gap in the reason."""
    restricted = region is not None and region.restricts
    if restricted:
        assert region is not None
        p, cost, lower, info = branch_and_bound(problem, max_cells=max_cells, region=region,
                                                seeds=seeds)
        p, cost = polish_on_circles(problem, region, p, cost)
        lower = min(lower, cost)
        name, effort, searched = BRANCH_AND_BOUND, info['cells'], f'{info["cells"]} cells'
        at_slot = problem.cost_at(*problem.slot)
    else:
        p, cost, lower, info = polar_optimum(problem)
        at_slot = info.pop('cost_at_slot')
        name, effort = POLAR, info['lines']
        searched = f'{info["lines"]} lines, {info["rounds"]} witnesses'
    gap = (cost - lower) / abs(cost) if cost else math.inf
    on_boundary = math.hypot(p[0] - problem.slot[0], p[1] - problem.slot[1]) >= problem.r * (
        1.0 - 1e-12) or (restricted and not region.contains(p, -1e-12))  # type: ignore
    certified = gap <= CERTIFIED_GAP
    details = {'certificate_gap': gap, 'lower_bound': lower, **info}
    if not certified:
        details['reason'] = f'{name} closed to a gap of {gap:.3g} only ({searched})'
    solution = make_solution(problem, p, method, on_boundary=on_boundary,  # type: ignore
                             candidates=effort, details=details,
                             fallback=None if certified else 'grid',
                             certificate=name if certified else 'none')
    # the Joseph-form costs (base_cost - gain_at carries rounding of eps tr(W P W))
    return replace(solution, cost=cost, cost_at_slot=at_slot)


#: Certificates of the range-bearing optimum: over the disc, over a reachable set.
CERTIFICATES = (POLAR, BRANCH_AND_BOUND)


__all__ = ['BRANCH_AND_BOUND', 'CERTIFICATES', 'CERTIFIED_GAP', 'branch_and_bound', 'cell_bounds',
           'polish_on_circles', 'stacked_plan']
