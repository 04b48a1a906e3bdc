"""RQ over the reachable set (slot disc n reach disc n outside the safety circle), certified;
and every other strategy's answer restricted to that set.

The feasible set F (:class:`~formopt_ros.core.reach.Region`) is bounded by arcs of up to three
circles: the slot's, the reach circle and the safety circle. The maximiser of the gain over F
(compact) is a KKT point of one of these kinds, and RQ enumerates them all:

* interior: the top generalised eigenvector (bearing) or the unconstrained best bearing
  (range), when it lies in F;
* on one arc: a stationary point of the gain along that circle (Lagrange on a circle, the
  secular machinery of the disc on another circle);
* a corner: an intersection of two circles that lies in F.

Range: the gain depends on the bearing theta only (pi-periodic, the quotient of two degree-2
trigonometric polynomials), and F is seen from the leader under one interval of bearings
(:meth:`~formopt_ros.core.reach.Region.direction_interval`); the candidates are the two
stationary bearings (K + C cos 2t + S sin 2t = 0) inside it and its two ends. The point on the
chosen ray is the one nearest p_o among the ray's feasible points.

Bearing: under q = (-y, x) / |p|^2 every circle maps to a circle (not through the leader) and the
gain is h'Mh / h'Nh with h = [q0, q1, -1]; along a q-circle both are degree-2 trigonometric
series, the stationarity condition n'd - nd' = 0 is a trigonometric polynomial of degree 4,
whose coefficients come from 16 samples (FFT) and whose roots (a degree-8 companion matrix)
are polished by Newton's method; 24 samples per circle are added as a safeguard.

Certificate (docs/certification.md): each circle is one quadratic form in h,
G_i = [[k, 0, -c_y], [0, k, c_x], [-c_y, c_x, 1]] (k = |c|^2 - rho^2) for |p - c| <= rho, its
negative for |p - c| >= rho (range: the cone of the bearing interval, one form). If
S = lambda B - A + sum_i mu_i G_i is positive definite for some mu >= 0, no feasible h has a
gain of lambda or more. lambda = g(p) + rtol cost (rtol of GAP_RTOLS with rtol cost above the
gain's rounding bound); the multipliers are KKT's (non-negative least squares of
(g B - A) h + sum mu_i G_i h = 0 over the active circles: S h is about 0 at an optimum, which
pins them down), then, one constraint at a time, 0 and the critical points of det(S + mu G_i)
(complete for one constraint). The test allows for the rounding of S's entries; when the
margin is positive but below that bound, it is repeated in exact rational arithmetic on the
exact data (the circles' forms as the floats they are). The S-lemma is complete for one
constraint: it proves an optimum that is also the optimum over one circle's side alone. Where
another circle matters (a corner, or one arc while another circle keeps the optimum from a
better point) it is sufficient only: when it fails, the lines through the leader decide
(:mod:`~formopt_ros.core.strategies.polar`, as for range-bearing: a line's cost is a ratio of
quadratics in 1/|p| for one row too), seeded with the best KKT point: certificate
'polar-lines'. A bearing optimum on the slot's arc alone goes to the lines first (the S-lemma
cannot prove it: the disc's own optimum lies outside F with a larger gain). Only if they do
not close is the answer the best of the enumerated KKT points, named 'all-critical-points',
and the solution says so (``fallback`` 'enumeration').
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from fractions import Fraction
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.linalg import EPS
from formopt_ros.core.model import RANGE, RANGE_BEARING
from formopt_ros.core.reach import Circle, Region
from formopt_ros.core.strategies.base import PlanContext, Solution, Strategy, make_solution
from formopt_ros.core.strategies.certificate import (
    BOUNDARY, CRITICAL_POINTS, GAP_RTOLS, INTERIOR, NONE, PROVED)
from formopt_ros.core.strategies.stacked import CERTIFICATES as STACKED_CERTIFICATES
from formopt_ros.core.strategies.stacked import lines_plan
from formopt_ros.core.strategies.verify import exact_forms
from formopt_ros.core.strategies.rq import (
    _circle_series, range_stationary_directions, rq_optimum, top_generalized_eigenvector)

#: Samples per circle added to the stationary points (a safeguard for lost roots).
CIRCLE_SAMPLES = 24
#: Samples of the stationarity polynomial (degree 4: 9 coefficients; 16 for the FFT).
FFT_SAMPLES = 16
#: Newton steps polishing each stationary angle.
POLISH_STEPS = 6
#: Relative rounding allowed per entry of the scaled S (a few operations each).
ENTRY_ERROR = 16 * EPS
#: A circle counts as active at p when |h'G h| is below this fraction of |G| |h|^2.
ACTIVE_TOLERANCE = 1e-7
#: Names of ``Solution.fallback`` set here.
ENUMERATION = 'enumeration'
UNREACHABLE = 'unreachable'


# --- the quadratic forms of the constraints ------------------------------------------------------
def circle_form(circle: Circle) -> np.ndarray:
    """G (3, 3) with h'Gh <= 0 for h = [q0, q1, -1] exactly when the point p of q satisfies the
    circle's constraint (module docstring), scaled to unit Frobenius norm."""
    cx, cy, radius, inside = circle
    k = cx * cx + cy * cy - radius * radius
    G = np.array([[k, 0.0, -cy], [0.0, k, cx], [-cy, cx, 1.0]])
    G /= np.linalg.norm(G)
    return G if inside else -G


def q_circle_of(circle: Circle) -> tuple[float, float, float]:
    """The image (centre q0, centre q1, radius; 1/m) of a circle (not through the leader) under
    q = (-y, x) / |p|^2."""
    cx, cy, radius, _ = circle
    k = cx * cx + cy * cy - radius * radius
    return -cy / k, cx / k, radius / abs(k)


def _h(x: float, y: float) -> np.ndarray:
    """h = [q0, q1, -1] of the point (x, y), m."""
    n2 = x * x + y * y
    return np.array([-y / n2, x / n2, -1.0])


# --- the certificate -----------------------------------------------------------------------------
def _pd_margin(S: np.ndarray, error: np.ndarray) -> float:
    """The smallest eigenvalue of S minus the bounds on its rounding (entries ``error``) and on
    the eigenvalue's own: positive proves every matrix within ``error`` positive definite."""
    values = np.linalg.eigvalsh(S)
    return float(values[0] - np.abs(error).sum(axis=1).max()
                 - 8.0 * S.shape[0] * EPS * np.linalg.norm(S))


def single_multipliers(S: np.ndarray, G: np.ndarray) -> list[float]:
    """The mu >= 0 to test for S + mu G positive definite with one constraint: 0 and the
    critical points of det(S + mu G), a polynomial of degree n (2 or 3). The set of mu where
    S + mu G is positive definite is an interval (G has one negative eigenvalue) at whose
    ends det vanishes, so it holds 0 or a critical point of det (the argument of
    :func:`~.certificate._best_bearing_multiplier`, here in floating point)."""
    n = S.shape[0]
    nodes = np.arange(n + 1, dtype=float)
    values = [np.linalg.det(S + m * G) for m in nodes]
    coefficients = np.polyfit(nodes, values, n)
    critical = np.roots(np.polyder(coefficients)) if n > 1 else np.empty(0)
    return [0.0] + [float(c.real) for c in critical if abs(c.imag) <= 1e-9 * abs(c)
                    and c.real > 0.0]


def s_lemma(A: np.ndarray, B: np.ndarray, forms: Sequence[np.ndarray], h: np.ndarray,
            gain: float, cost: float, error: float,
            exact: Callable[[float, Sequence[float]], bool] | None = None
            ) -> tuple[str, dict[str, Any]]:
    """Try to prove that no h with h'G_i h <= 0 for all i has h'Ah / h'Bh >= gain + rtol cost.

    Args:
        A, B: the quotient's forms (n, n), B positive definite; forms: the constraints' G_i.
        h: the candidate's vector (n,); gain: its computed gain, cost: its cost (m^2);
        error: the bound on the computed gain's rounding (m^2).
        exact: (lambda, mu) -> whether lambda B - A + sum mu_i G_i is positive definite in
            exact arithmetic on the exact data; asked when the floating-point margin is too
            small for the rounding bound but positive.

    Returns:
        (INTERIOR or BOUNDARY, details) when proved, else (NONE, details); details hold
        'certificate_gap' and 'certificate_multiplier' (the mu, a list).
    """
    from scipy.optimize import nnls     # here: the nodes start without scipy.optimize
    d = 1.0 / np.sqrt(np.diag(B))
    scaled_a, scaled_b = A * np.outer(d, d), B * np.outer(d, d)
    scaled_g = [G * np.outer(d, d) for G in forms]
    a_size = np.sqrt(np.outer(np.abs(np.diag(scaled_a)), np.abs(np.diag(scaled_a))))
    hs = h / d
    hs /= np.linalg.norm(hs)
    active = [i for i, G in enumerate(scaled_g)
              if abs(hs @ G @ hs) <= ACTIVE_TOLERANCE * np.linalg.norm(G)]
    details: dict[str, Any] = {'certificate_gap': math.inf, 'certificate_multiplier': []}
    for rtol in GAP_RTOLS:
        if rtol * cost < error or not cost > 0.0:
            continue
        lam = gain + rtol * cost
        base = lam * scaled_b - scaled_a
        size = lam * np.abs(scaled_b) + a_size

        def margin(mu: np.ndarray) -> float:
            S = base + sum(m * G for m, G in zip(mu, scaled_g))
            bound = size + sum(m * np.abs(G) for m, G in zip(mu, scaled_g))
            return _pd_margin(S, ENTRY_ERROR * (bound + rtol * cost))

        mu = np.zeros(len(scaled_g))
        if active:
            columns = np.array([scaled_g[i] @ hs for i in active]).T
            mu[active] = nnls(columns, -(base @ hs))[0]
        best = margin(mu)
        for i, G in enumerate(scaled_g):        # one constraint alone: a complete decision
            if best > 0.0:
                break
            for value in single_multipliers(base, G):
                trial = np.zeros(len(scaled_g))
                trial[i] = value
                if (found := margin(trial)) > best:
                    mu, best = trial, found
        proved = best > 0.0
        if not proved and exact is not None:
            S = base + sum(m * G for m, G in zip(mu, scaled_g))
            if np.linalg.eigvalsh(S)[0] > 0.0 and exact(lam, mu.tolist()):
                proved = True
                details['certificate_arithmetic'] = 'exact'
        if proved:
            details.update(certificate_gap=rtol + error / cost,
                           certificate_multiplier=[float(m) for m in mu])
            return (INTERIOR if not np.any(mu > 0.0) else BOUNDARY), details
    return NONE, details


def _fraction_positive_definite(S: list[list[Fraction]]) -> bool:
    """Sylvester's test on a symmetric 2x2 or 3x3 matrix of Fractions (exact)."""
    if not S[0][0] > 0 or not S[0][0] * S[1][1] - S[0][1] * S[1][0] > 0:
        return False
    if len(S) == 2:
        return True
    (a, b, c), (_, e, f), (_, _, i) = S
    return a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) > 0


def _exact_checker(problem: Problem, forms: Sequence[np.ndarray]
                   ) -> Callable[[float, Sequence[float]], bool]:
    """(lambda, mu) -> lambda B - A + sum mu_i G_i positive definite, exactly: A and B from
    the exact data (:func:`~.certificate.exact_forms`), the G_i as the floats they are."""
    M, N, R, _, E = exact_forms(problem, *problem.slot)
    n = 2 if problem.measurement == RANGE else 3
    index = ((0, 1, 2), (1, 3, 4), (2, 4, 5))
    if n == 2:
        N = list(N)
        N[0], N[3] = N[0] + R, N[3] + R
    else:
        N = list(N)
        N[5] += R
    unit_m, unit_n = Fraction(1, 1 << 4 * E), Fraction(1, 1 << 2 * E)
    A = [[M[index[i][j]] * unit_m for j in range(n)] for i in range(n)]
    B = [[N[index[i][j]] * unit_n for j in range(n)] for i in range(n)]
    G = [[[Fraction(float(F[i, j])) for j in range(n)] for i in range(n)] for F in forms]

    def check(lam: float, mu: Sequence[float]) -> bool:
        lam_f = Fraction(lam)
        mu_f = [Fraction(m) for m in mu]
        S = [[lam_f * B[i][j] - A[i][j] + sum(m * g[i][j] for m, g in zip(mu_f, G))
              for j in range(n)] for i in range(n)]
        return _fraction_positive_definite(S)
    return check


def certify_in_region(problem: Problem, region: Region, p: Sequence[float], gain: float,
                      interval: tuple[float, float] | None = None) -> tuple[str, dict[str, Any]]:
    """The certificate of the module docstring for p (2,) (m) in ``region`` with computed gain
    ``gain`` (m^2): bearing, the forms of the region's circles; range, the cone of the bearing
    interval ``interval`` (rad; default the region's)."""
    x, y = float(p[0]), float(p[1])
    cost = problem.base_cost - gain
    error = problem.gain_error_at(x, y, gain)
    M, N = problem.forms
    if problem.measurement == RANGE:
        low, high = interval or region.direction_interval() or (0.0, 0.0)
        mid, half = 0.5 * (low + high), 0.5 * (high - low)
        u = np.array([math.cos(mid), math.sin(mid)])
        cone = math.cos(half) ** 2 * np.eye(2) - np.outer(u, u)
        A = np.array([[M[0], M[1]], [M[1], M[3]]])
        p00, p01, _, p11, _, _ = problem.entries
        B = np.array([[p00 + problem.R, p01], [p01, p11 + problem.R]])
        forms = [cone / np.linalg.norm(cone)]
        return s_lemma(A, B, forms, np.array([x, y]), gain, cost, error,
                       _exact_checker(problem, forms))
    A, B = (np.array([[X[0], X[1], X[2]], [X[1], X[3], X[4]], [X[2], X[4], X[5]]])
            for X in (M, N))
    forms = [circle_form(c) for c in region.circles()]
    return s_lemma(A, B, forms, _h(x, y), gain, cost, error, _exact_checker(problem, forms))


# --- the candidates ------------------------------------------------------------------------------
def _series_values(k: Sequence[float], t: np.ndarray) -> tuple[np.ndarray, ...]:
    """(x, x', x'') of the series k0 + k1c cos t + k1s sin t + k2c cos 2t + k2s sin 2t."""
    k0, k1c, k1s, k2c, k2s = k
    c, s, c2, s2 = np.cos(t), np.sin(t), np.cos(2 * t), np.sin(2 * t)
    first, second = k1c * c + k1s * s, k2c * c2 + k2s * s2
    return (k0 + first + second, k1s * c - k1c * s + 2.0 * (k2s * c2 - k2c * s2),
            -first - 4.0 * second)


def stationary_angles(num: Sequence[float], den: Sequence[float]) -> np.ndarray:
    """Angles t (rad) where n'd - nd' = 0 on a q-circle (module docstring), polished."""
    t = 2.0 * np.pi * np.arange(FFT_SAMPLES) / FFT_SAMPLES
    (n, n1, _), (d, d1, _) = _series_values(num, t), _series_values(den, t)
    c = np.fft.fft(n1 * d - n * d1) / FFT_SAMPLES
    coefficients = np.array([c[k % FFT_SAMPLES] for k in range(4, -5, -1)])
    if not np.all(np.isfinite(coefficients)) or not np.any(np.abs(coefficients) > 0.0):
        return np.empty(0)
    angles = np.angle(np.roots(coefficients))
    for _ in range(POLISH_STEPS):
        (n, n1, n2), (d, d1, d2) = _series_values(num, angles), _series_values(den, angles)
        F, slope = n1 * d - n * d1, n2 * d - n * d2
        with np.errstate(all='ignore'):
            step = np.where(slope != 0.0, -F / slope, 0.0)
        angles = angles + np.clip(np.nan_to_num(step), -0.2, 0.2)
    return angles


def _bearing_candidates(problem: Problem, region: Region) -> list[tuple[float, float]]:
    """Every KKT point of the bearing gain over the region (module docstring), with samples."""
    M, N = problem.forms
    out: list[tuple[float, float]] = []
    top = top_generalized_eigenvector(M, N)
    if top is not None and top[1][2] != 0.0:
        h = top[1]
        q0, q1 = -h[0] / h[2], -h[1] / h[2]
        n2 = q0 * q0 + q1 * q1
        if n2 > 0.0 and math.isfinite(n2):
            out.append((q1 / n2, -q0 / n2))
    samples = 2.0 * np.pi * np.arange(CIRCLE_SAMPLES) / CIRCLE_SAMPLES
    for circle in region.circles():
        c0, c1, rho = q_circle_of(circle)
        num, den = _circle_series(M, c0, c1, rho), _circle_series(N, c0, c1, rho)
        angles = np.concatenate([stationary_angles(num, den), samples])
        q0, q1 = c0 + rho * np.cos(angles), c1 + rho * np.sin(angles)
        n2 = q0 * q0 + q1 * q1
        out += list(zip((q1 / n2).tolist(), (-q0 / n2).tolist()))
    out += region.corners()
    return out


def _range_candidates(problem: Problem, region: Region,
                      interval: tuple[float, float]) -> list[tuple[float, float]]:
    """The range gain's KKT points over the region: the stationary bearings inside the
    interval and its ends, each at its ray's feasible point nearest p_o."""
    low, high = interval
    stationary, amplitude, K = range_stationary_directions(problem)
    thetas = [low, high]
    if amplitude > 0.0 and abs(K) <= amplitude:
        for theta in stationary:
            shifted = low + (theta - low) % math.pi
            if shifted <= high:
                thetas.append(shifted)
    x_o, y_o = problem.slot
    out = []
    for theta in thetas:
        ux, uy = math.cos(theta), math.sin(theta)
        near, far = region.ray_interval(ux, uy)
        along = ux * x_o + uy * y_o
        t = 0.5 * (near + far) if near > far else min(max(along, near), far)
        out.append((t * ux, t * uy))
    return out


def _circles_through(region: Region, p: Sequence[float]) -> list[int]:
    """The indices of the region's bounding circles (:meth:`Region.circles`) that p (2,) (m)
    lies on, within ACTIVE_TOLERANCE of the region's scale."""
    return [i for i, (cx, cy, rho, _) in enumerate(region.circles())
            if abs(math.hypot(p[0] - cx, p[1] - cy) - rho) <= ACTIVE_TOLERANCE * region.scale]


def rq_in_region(problem: Problem, region: Region, method: str = 'rq') -> Solution:
    """The certified optimum of ``problem`` over ``region`` (module docstring).

    When the region does not restrict the disc this is :func:`~.rq.rq_optimum` itself; when
    RQ's optimum over the disc lies in the region it is the region's optimum too (the region
    is a subset) with the disc's certificate. An empty region (the reach disc misses the
    slot's disc) gives :meth:`~formopt_ros.core.reach.Region.fallback_target` with certificate
    'none' and ``fallback`` 'unreachable'."""
    disc = rq_optimum(problem, method)
    stacked = problem.measurement == RANGE_BEARING
    if not region.restricts or (region.contains(disc.p) and
                                disc.certificate in (*PROVED, *STACKED_CERTIFICATES)):
        return disc
    if region.empty():
        target = region.fallback_target()
        return make_solution(problem, target, method, False, 1, fallback=UNREACHABLE,
                             details={'reason': 'the reach disc misses the slot disc outside '
                                      'the safety circle: heading for the disc',
                                      'region': 'empty'})
    if stacked:                     # range-bearing: the lines through the leader, in the region
        nearest = region.nearest(disc.p)
        return lines_plan(problem, method, region=region,
                          seeds=() if nearest is None else (nearest,))
    interval = region.direction_interval() if problem.measurement == RANGE else None
    if problem.measurement == RANGE:
        assert interval is not None
        points = _range_candidates(problem, region, interval)
    else:
        points = _bearing_candidates(problem, region)
    tol = 1e-12
    feasible = [p for p in points if all(map(math.isfinite, p)) and region.contains(p, tol)]
    if problem.measurement == RANGE:    # an end's ray that rounding made miss: its nearest point
        feasible += [q for p in points if all(map(math.isfinite, p))
                     and not region.contains(p, tol) and (q := region.nearest(p)) is not None]
    if not feasible:                # rounding put every candidate outside: the nearest point
        nearest = region.nearest(problem.slot)
        feasible = [nearest if nearest is not None else problem.slot]
    gains = [problem.gain_at(*p) for p in feasible]
    best = max(range(len(gains)), key=gains.__getitem__)
    p, g = feasible[best], gains[best]
    # bearing, p on the slot's circle alone: the only certificate tight at p is that circle's,
    # which would make p the disc's optimum; the disc's optimum lies outside the region and
    # gains more, so the lines through the leader decide (tried first)
    lines_first = problem.measurement != RANGE and _circles_through(region, p) == [0]

    def by_lines() -> Solution | None:
        lines = lines_plan(problem, method, region=region, seeds=(p,))
        return lines if lines.certificate in STACKED_CERTIFICATES else None

    if lines_first and (decided := by_lines()) is not None:
        return decided
    name, details = certify_in_region(problem, region, p, g, interval)
    details['region'] = 'restricted'
    on_boundary = not (problem.measurement != RANGE and best == 0 and points
                       and points[0] == p)
    if name in PROVED:
        return make_solution(problem, p, method, on_boundary, len(points), certificate=name,
                             details=details, gain=g)
    if not lines_first and (decided := by_lines()) is not None:
        return decided
    details['reason'] = ('the S-lemma with several constraints found no multipliers: the '
                         f'best of {len(feasible)} enumerated KKT points and samples')
    return make_solution(problem, p, method, on_boundary, len(points), fallback=ENUMERATION,
                         certificate=CRITICAL_POINTS, details=details, gain=g)


# --- every strategy within the region ----------------------------------------------------------
def project_into(problem: Problem, region: Region, solution: Solution,
                 note: str) -> Solution:
    """``solution`` moved to the nearest point of the region (itself when inside; the region's
    fallback target when it is empty), certificate 'none', ``details['projected']`` = note."""
    if region.contains(solution.p):
        return solution
    target = region.nearest(solution.p)
    if target is None:
        target = region.fallback_target()
    details = dict(solution.details, projected=note)
    return make_solution(problem, target, solution.method, True, solution.candidates,
                         solution.fallback, details)


def _grid_in_region(strategy: Strategy, problem: Problem, region: Region) -> Solution:
    """GBS restricted: its grid's best point inside the region (the nearest point of the
    region to its unrestricted answer when no grid point is inside)."""
    from formopt_ros.core.strategies.baselines import grid_for
    cell = float(strategy.settings['cell'])
    grid = grid_for(problem.measurement, problem.slot, float(problem.r), cell)
    points = grid.points
    keep = np.ones(len(points), dtype=bool)
    tol = 1e-12 * region.scale
    for cx, cy, radius, inside in region.circles():
        distance = np.hypot(points[:, 0] - cx, points[:, 1] - cy)
        keep &= distance <= radius + tol if inside else distance >= radius - tol
    if not keep.any():
        return project_into(problem, region, strategy.plan(problem, PlanContext()),
                            'no grid point in the region')
    inside_points = points[keep]
    best = int(np.argmax(problem.gain(inside_points)))
    return make_solution(problem, inside_points[best], strategy.name, False,
                         int(keep.sum()), details={'region': 'grid restricted'})


def rq_target(problem: Problem, region: Region | None) -> np.ndarray:
    """RQ's certified optimum over the disc, or over the region when it restricts, (2,) m."""
    if region is None or not region.restricts:
        return rq_optimum(problem).p
    return rq_in_region(problem, region).p


def plan_within(strategy: Strategy, problem: Problem, context: PlanContext) -> Solution:
    """``strategy``'s answer restricted to ``context.region``:

    * RQ: :func:`rq_in_region` (the certified optimum over the region);
    * RAM: its answer when it lies in the region (the paper's method solves the disc, whose
      optimum is then the region's); otherwise RQ's over the region, ``fallback`` 'rq';
    * PERIODIC: a greedy step is RQ's over the region (it plays greedy when its cycle does
      not fit the region); a cycle point is projected onto the region (its nearest point),
      ``details['projected']``;
    * GBS: the best grid point inside the region;
    * MTF, CRM, MME, LOOKAHEAD and plugins: their point projected onto the region (LOOKAHEAD
      plans inside it: its point is its own).
    """
    region = context.region
    if region is None or not region.restricts:
        return strategy.plan(problem, context)
    name = strategy.name
    if name == 'rq':
        return rq_in_region(problem, region, name)
    if name == 'gbs':
        return _grid_in_region(strategy, problem, region)
    solution = strategy.plan(problem, context)
    if name == 'ram':
        if region.contains(solution.p) and solution.fallback is None:
            return solution
        restricted = rq_in_region(problem, region, name)
        if restricted.fallback is None:
            object.__setattr__(restricted, 'fallback', 'rq')
        return restricted
    if name == 'periodic' and solution.details.get('mode') == 'greedy':
        restricted = rq_in_region(problem, region, name)
        restricted.details.update({k: v for k, v in solution.details.items()
                                   if k not in restricted.details})
        return restricted
    return project_into(problem, region, solution, 'nearest point of the region')


__all__ = ['ENUMERATION', 'UNREACHABLE', 'certify_in_region', 'circle_form', 'plan_within',
           'project_into', 'q_circle_of', 'rq_in_region', 'rq_target', 's_lemma',
           'stationary_angles']
