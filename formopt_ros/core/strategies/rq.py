"""RQ: the exact generalised-Rayleigh-quotient solver (beyond the paper), certified.

Range: the gain is g(u) = u'Au / u'(B + R I)u over unit u = [cos t, sin t]; the unconstrained
maximiser is the top generalised eigenvector of (A, B + R I) (closed form for 2x2), and the
constrained one follows from the arc logic of :func:`range_plan_from_direction`.

Bearing: with h = [q0, q1, -1], g = h'Mh / h'Nh (M = P W^2 P, N = P + R e3 e3') is homogeneous
in h, so its only local maximum over the projective plane is the top generalised eigenvector of
(M, N). If that eigenvector maps into the q-disc (the image of the feasible disc under
p -> (-y, x)/|p|^2) it is the global optimum; otherwise the optimum lies on the boundary
circle q(t) = c + rho [cos t, sin t], where num and den are trigonometric polynomials of degree
2. The fast path, in Python floats, tries the boundary first (where the optimum lies on the
study's and the benchmark's problems): Newton's method on the stationarity condition
n'd - nd' = 0 from the best of 12 samples (moved to the vertex of the parabola through it and
its neighbours). Only when that point is not proved optimal, the top eigenpair in closed form
(Cholesky reduction, the trigonometric solution of the cubic): an interior optimum, or else
Newton from the circle point nearest the eigenvector and from the second-best sample. Every
answer must pass :func:`~.certificate.certify`; when it does not, the exhaustive route runs:
numpy's generalised eigenvector and every root of the degree-6 stationarity polynomial in
z = e^{it} (companion matrix), each polished by Newton steps; its best point is certified
again, or named 'all-critical-points' unless a boundary sample, the slot or a point of the fast
path is better (rounding lost a root): that point is then returned as 'none', with the reason.
An answer still without a proof is the start of an exact local search
(:func:`~.common.refine_exactly`); a better point it finds is certified in exact arithmetic, or
returned as 'none'.

Many problems at once (the batched Monte Carlo engine's trials): :func:`rq_batch` runs the
first route and the floating-point stage of its proof on arrays, with the scalar arithmetic,
and hands every problem it does not prove to :func:`rq_optimum`; each problem gets the point
:func:`rq_optimum` gives it, bit for bit.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.formulas import Entries, point_from_q, quotient_gain
from formopt_ros.core.linalg import EPS, top_eigenpair3
from formopt_ros.core.strategies.base import (
    BatchContext, BatchPlan, PlanContext, Solution, Strategy, make_solution)
from formopt_ros.core.model import BEARING, RANGE, RANGE_BEARING
from formopt_ros.core.strategies.stacked import lines_plan
from formopt_ros.core.strategies.certificate import PROVED, proved_batch
from formopt_ros.core.strategies.common import (
    boundary_points, boundary_stationarity, check_points, gains_tie, polish_boundary_angles,
    range_plan_from_direction)
from formopt_ros.core.strategies.verify import CHECK_SAMPLES, certify, settle_unproved

#: Gains closer than this (relative to tr(W P W)) tie: the rounding of the gain formula.
GAIN_ROUNDING = 16 * EPS
#: Distance of a root of the boundary polynomial from |z| = 1 up to which it counts as real.
UNIT_CIRCLE_TOLERANCE = 1e-3
#: Samples of the boundary quotient when the start next to the eigenvector is not certified.
BOUNDARY_SAMPLES = 12
#: Newton iterations at most on the boundary stationarity condition, and the step after which it
#: stops (convergence is quadratic: after a step of 1e-9 rad the error is ~1e-18 rad).
NEWTON_ITERATIONS = 30
NEWTON_STEP_TOLERANCE = 1e-9
#: Largest Newton step on the boundary circle, rad.
NEWTON_MAX_STEP = 0.5
#: Angle between neighbouring samples, rad.
SAMPLE_STEP = 2.0 * math.pi / BOUNDARY_SAMPLES
#: (cos t, sin t, cos 2t, sin 2t) of the first half of the samples (t + pi flips cos t, sin t).
_HALF_SAMPLES = [(math.cos(t), math.sin(t), math.cos(2.0 * t), math.sin(2.0 * t))
                 for t in (SAMPLE_STEP * k for k in range(BOUNDARY_SAMPLES // 2))]
#: The same as four columns (BOUNDARY_SAMPLES // 2, 1), for a batch.
_SAMPLE_COLUMNS = tuple(np.array(column)[:, None] for column in zip(*_HALF_SAMPLES))


def generalized_eigh(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and B-orthonormal eigenvectors (columns) of A v = lambda B v.

    B must be symmetric positive definite; uses a Cholesky reduction (cheap for 2x2 and 3x3).
    """
    L_inv = np.linalg.inv(np.linalg.cholesky(B))
    values, vectors = np.linalg.eigh(L_inv @ A @ L_inv.T)
    return values, L_inv.T @ vectors


def top_generalized_eigenvector(M: Entries, N: Entries) -> tuple[float, list[float]] | None:
    """Largest eigenvalue and an eigenvector of M h = lambda N h (3x3, N positive definite), in
    Python floats, or None when the Cholesky reduction breaks down.

    Jacobi scaling D = diag(N)^-1/2 first, then C = L^-1 (D M D) L^-T with L L' = D N D (unit
    diagonal); the eigenvector v of C maps back as h = D L^-T v.
    """
    m00, m01, m02, m11, m12, m22 = M
    n00, n01, n02, n11, n12, n22 = N
    if not (n00 > 0.0 and n11 > 0.0 and n22 > 0.0):
        return None
    d0, d1, d2 = 1.0 / math.sqrt(n00), 1.0 / math.sqrt(n11), 1.0 / math.sqrt(n22)
    # L L' = D N D with unit diagonal: L = [[1, 0, 0], [l10, l11, 0], [l20, l21, l22]]
    l10, l20 = n01 * d0 * d1, n02 * d0 * d2
    s11 = 1.0 - l10 * l10
    if not s11 > 0.0:
        return None
    l11 = math.sqrt(s11)
    l21 = (n12 * d1 * d2 - l20 * l10) / l11
    s22 = 1.0 - l20 * l20 - l21 * l21
    if not s22 > 0.0:
        return None
    l22 = math.sqrt(s22)
    # X = L^-1 (D M D), column by column (D M D is symmetric: its columns are its rows)
    cols = []
    for a, b, c in ((m00 * d0 * d0, m01 * d0 * d1, m02 * d0 * d2),
                    (m01 * d0 * d1, m11 * d1 * d1, m12 * d1 * d2),
                    (m02 * d0 * d2, m12 * d1 * d2, m22 * d2 * d2)):
        y1 = (b - l10 * a) / l11
        cols.append((a, y1, (c - l20 * a - l21 * y1) / l22))
    # C = L^-1 X' (symmetric); column k of X' is row k of X
    rows = []
    for k in range(3):
        a, b, c = cols[0][k], cols[1][k], cols[2][k]
        y1 = (b - l10 * a) / l11
        rows.append((a, y1, (c - l20 * a - l21 * y1) / l22))
    value, v = top_eigenpair3(rows)
    y2 = v[2] / l22
    y1 = (v[1] - l21 * y2) / l11
    y0 = v[0] - l10 * y1 - l20 * y2
    return value, [y0 * d0, y1 * d1, y2 * d2]


def _circle_series(X: Entries, c0: Any, c1: Any, rho: Any) -> tuple[Any, Any, Any, Any, Any]:
    """(k0, k1c, k1s, k2c, k2s) with h(t)'Xh(t) = k0 + k1c cos t + k1s sin t + k2c cos 2t
    + k2s sin 2t on h(t) = [c0 + rho cos t, c1 + rho sin t, -1] (floats, or arrays for a
    batch)."""
    x00, x01, x02, x11, x12, x22 = X
    a0 = x00 * c0 + x01 * c1 - x02
    a1 = x01 * c0 + x11 * c1 - x12
    aXa = c0 * a0 + c1 * a1 - (x02 * c0 + x12 * c1 - x22)
    r2 = rho * rho
    return (aXa + 0.5 * r2 * (x00 + x11), 2.0 * rho * a0, 2.0 * rho * a1,
            0.5 * r2 * (x00 - x11), r2 * x01)


def _boundary_newton(num: tuple[float, ...], den: tuple[float, ...], t: float) -> float:
    """Newton's method on F = n'd - nd' (the numerator of g') from angle t (rad), safeguarded
    to climb: the angle where it stops."""
    n0, n1c, n1s, n2c, n2s = num
    d0, d1c, d1s, d2c, d2s = den
    cos, sin = math.cos, math.sin
    for _ in range(NEWTON_ITERATIONS):
        c, s = cos(t), sin(t)
        c2, s2 = c * c - s * s, 2.0 * s * c
        # each series: first harmonic a, second b; x = k0 + a + b, x'' = -a - 4 b
        n1, n2 = n1c * c + n1s * s, n2c * c2 + n2s * s2
        d1, d2 = d1c * c + d1s * s, d2c * c2 + d2s * s2
        n, d = n0 + n1 + n2, d0 + d1 + d2
        n_t = n1s * c - n1c * s + 2.0 * (n2s * c2 - n2c * s2)
        d_t = d1s * c - d1c * s + 2.0 * (d2s * c2 - d2c * s2)
        F = n_t * d - n * d_t
        slope = (-n1 - 4.0 * n2) * d + n * (d1 + 4.0 * d2)
        if slope < 0.0:
            step = -F / slope
            step = -NEWTON_MAX_STEP if step < -NEWTON_MAX_STEP else (
                NEWTON_MAX_STEP if step > NEWTON_MAX_STEP else step)
        else:                   # not concave here: climb along the gradient
            step = 0.1 if F >= 0.0 else -0.1
        t += step
        if -NEWTON_STEP_TOLERANCE <= step <= NEWTON_STEP_TOLERANCE:
            break
    return t


def _q_point(c0: float, c1: float, rho: float, t: float) -> tuple[float, float]:
    """The point p (m) whose q lies at angle t on the q-circle."""
    q0, q1 = c0 + rho * math.cos(t), c1 + rho * math.sin(t)
    n2 = q0 * q0 + q1 * q1
    return q1 / n2, -q0 / n2


def _boundary_starts(num: tuple[float, ...], den: tuple[float, ...]) -> tuple[float, float]:
    """Newton's starts on the q-circle, rad: the best of BOUNDARY_SAMPLES equally spaced samples
    of the quotient of the two degree-2 series (k0, k1c, k1s, k2c, k2s), moved to the vertex of
    the parabola through it and its neighbours (one Newton step fewer, on average); and the
    runner-up sample."""
    n0, n1c, n1s, n2c, n2s = num
    d0, d1c, d1s, d2c, d2s = den
    half = BOUNDARY_SAMPLES // 2
    values = [0.0] * BOUNDARY_SAMPLES
    for k, (c, s, c2, s2) in enumerate(_HALF_SAMPLES):
        n_even, n_odd = n0 + n2c * c2 + n2s * s2, n1c * c + n1s * s
        d_even, d_odd = d0 + d2c * c2 + d2s * s2, d1c * c + d1s * s
        # a denominator rounding to <= 0 (P huge along the sample's bearing) says nothing
        plus, minus = d_even + d_odd, d_even - d_odd
        values[k] = (n_even + n_odd) / plus if plus > 0.0 else -math.inf
        values[k + half] = (n_even - n_odd) / minus if minus > 0.0 else -math.inf
    best, second = 0, 1
    if values[1] > values[0]:
        best, second = 1, 0
    for k in range(2, BOUNDARY_SAMPLES):
        if values[k] > values[best]:
            best, second = k, best
        elif values[k] > values[second]:
            second = k
    before, here, after = values[best - 1], values[best], values[(best + 1) % BOUNDARY_SAMPLES]
    curvature = before - 2.0 * here + after
    shift = 0.0 if not curvature < 0.0 else 0.5 * (before - after) / curvature
    return SAMPLE_STEP * (best + max(-1.0, min(1.0, shift))), SAMPLE_STEP * second


def _interior_optimum(problem: Problem) -> tuple[tuple[float, float] | None, float | None]:
    """(the point of the top generalised eigenvector of (M, N) if it maps inside the q-disc,
    else None; the q-circle angle nearest that eigenvector, or None when there is none)."""
    top = top_generalized_eigenvector(*problem.forms)
    if top is None or top[1][2] == 0.0:
        return None, None
    c0, c1, rho = problem.q_circle
    h = top[1]
    q0, q1 = -h[0] / h[2], -h[1] / h[2]
    e0, e1 = q0 - c0, q1 - c1
    angle = math.atan2(e1, e0)
    if e0 * e0 + e1 * e1 < rho * rho:
        n2 = q0 * q0 + q1 * q1
        return (q1 / n2, -q0 / n2), angle
    return None, angle


def _plan_bearing_fast(problem: Problem, method: str,
                       tried_points: list[tuple[float, float]]) -> Solution | None:
    """The certified fast path (module docstring), or None when it cannot certify (the points
    it tried are then in ``tried_points``).

    The boundary comes first: on most problems the best sample, polished by Newton's method,
    is proved optimal at once, and the eigenvector is not needed. When it is not, the top
    eigenvector (an interior optimum, or a start next to it) and the runner-up sample follow.
    """
    M, N = problem.forms
    c0, c1, rho = problem.q_circle
    num, den = _circle_series(M, c0, c1, rho), _circle_series(N, c0, c1, rho)
    best, second = _boundary_starts(num, den)
    tried: list[tuple[float, float]] = []
    starts = [best]
    while starts:
        t = _boundary_newton(num, den, starts.pop(0))
        p = _q_point(c0, c1, rho, t)
        g = problem.gain_at(*p)
        name, details = certify(problem, p, g, exact=None if not tried else False)
        if name in PROVED:
            return make_solution(problem, p, method, True, BOUNDARY_SAMPLES + len(tried),
                                 certificate=name, details={'interior': False, **details},
                                 gain=g)
        tried.append((g, t))
        tried_points.append(p)
        if len(tried) == 1:                 # not proved: the interior, then two more starts
            inside, angle = _interior_optimum(problem)
            if inside is not None:
                tried_points.append(inside)
                g = problem.gain_at(*inside)        # once, for the proof and the record
                name, details = certify(problem, inside, g)
                if name in PROVED:
                    return make_solution(problem, inside, method, False, 2, certificate=name,
                                         details={'interior': True, **details}, gain=g)
            starts = [second] if angle is None else [angle, second]
    g, t = max(tried)
    p = _q_point(c0, c1, rho, t)
    name, details = certify(problem, p, g)
    if name not in PROVED:
        return None
    return make_solution(problem, p, method, True, BOUNDARY_SAMPLES + len(tried),
                         certificate=name, details={'interior': False, **details}, gain=g)


def boundary_candidates(problem: Problem) -> np.ndarray:
    """Stationary points of the bearing gain on the disc boundary, shape (n, 2), m."""
    F = boundary_stationarity(problem)
    if np.max(np.abs(F)) == 0.0:              # the gain is constant on the circle
        return problem.p_o[None, :] + np.array([[problem.r, 0.0]])
    companion = np.diag(np.ones(5), -1).astype(complex)      # z^3 F(z), degree 6, monic
    companion[:, -1] = -F[:6] / F[6]
    roots = np.linalg.eigvals(companion) if abs(F[6]) > 0 else np.roots(F[::-1])
    near = np.abs(np.abs(roots) - 1.0) < UNIT_CIRCLE_TOLERANCE
    t = np.angle(roots[near] if np.any(near) else roots)
    return boundary_points(problem, polish_boundary_angles(F, t))


def _plan_bearing_exhaustive(problem: Problem, method: str,
                             tried_points: Sequence[tuple[float, float]] = ()) -> Solution:
    """Every critical point: numpy's top generalised eigenvector (if feasible) and every boundary
    stationary point from the companion matrix; the best one, certified if possible.

    The critical points are held against the boundary samples of :func:`.common.check_points`
    (around p_o and on the q-circle), the slot and the fast path's points (``tried_points``).
    Unless the best is proved, every candidate whose gain ties with the best within the
    rounding bounds is compared exactly (:func:`.common.exact_best`):
    if a sample, the slot or a Newton point beats the best critical point by more than
    EXACT_TIE, rounding lost a critical point; the exact best is then returned with the
    certificate 'none' and the reason in ``details``, never 'all-critical-points'."""
    centre, rho = problem.q_disc()
    points = [np.empty((0, 2))]
    interior = False
    with np.errstate(all='ignore'):
        try:        # rounding can make LAPACK refuse what passed the LDL' check (cond ~1e30)
            top = generalized_eigh(problem.M, problem.N)[1][:, 2]
        except np.linalg.LinAlgError:
            top = np.zeros(3)
        try:
            points.append(boundary_candidates(problem))
        except (np.linalg.LinAlgError, ValueError):     # non-finite series: no roots
            pass
    if abs(top[2]) > 1e-300:
        with np.errstate(over='ignore'):        # an infinite q is outside the disc
            q = -top[:2] / top[2]
        if math.hypot(q[0] - centre[0], q[1] - centre[1]) < rho:
            points.insert(0, point_from_q(q)[None, :])
            interior = True
    critical = np.vstack(points)
    critical = critical[np.all(np.isfinite(critical), axis=1)]
    others = check_points(problem, tried_points)
    gains = problem.gain(critical) if len(critical) else np.array([-math.inf])
    other_gains = problem.gain(others)
    best, best_other = int(np.argmax(gains)), int(np.argmax(other_gains))
    enumerated = not other_gains[best_other] > gains[best] + GAIN_ROUNDING * problem.base_cost
    p, g = (critical[best], gains[best]) if enumerated else (others[best_other],
                                                             other_gains[best_other])
    name, details = certify(problem, p, float(g))
    if name not in PROVED:
        # the formula's rounding may exceed the candidates' differences (ill-conditioned P, a
        # cost far below tr(W P W)): near ties among all of them are decided on exact gains,
        # and the cost is reported exactly
        best, enumerated, p, name, details = settle_unproved(
            problem, critical, gains, others, other_gains, p, details)
    on_boundary = not (interior and best == 0) if enumerated else bool(
        abs(math.hypot(*(p - problem.p_o)) - problem.r) <= 1e-9 * problem.r)
    if not enumerated and name not in PROVED:
        details.setdefault('reason', f'rounding lost critical points: of {len(critical)} found, '
                           f'none is as good as the best of {2 * CHECK_SAMPLES} boundary samples, '
                           f'the slot and {len(tried_points)} Newton points')
    return make_solution(problem, p, method, on_boundary, len(critical) + len(others),
                         certificate=name,
                         details={'interior': not on_boundary, 'route': 'exhaustive',
                                  **details})


def _range_cholesky(problem: Problem | ProblemBatch,
                    sqrt: Callable[[Any], Any]) -> tuple[Any, Any, Any, Any, Any, Any]:
    """(a00, a01, a11, l00, l10, pivot): the range pencil's A = (P W^2 P)[:2, :2] and the
    Cholesky factor of B = P[:2, :2] + R I up to its last pivot (l11^2, positive unless B is
    singular to working precision); floats, or arrays for a batch (``sqrt``: math.sqrt or
    numpy.sqrt, both correctly rounded)."""
    (a00, a01, _, a11, _, _), _ = problem.forms
    p00, p01, _, p11, _, _ = problem.entries
    R = problem.R
    l00 = sqrt(p00 + R)
    l10 = p01 / l00
    return a00, a01, a11, l00, l10, p11 + R - l10 * l10


def _plan_range(problem: Problem, method: str) -> Solution:
    """Range: the top generalised eigenvector of the 2x2 pencil (A, B + R I) in closed form
    (Cholesky reduction to C = L^-1 A L^-T, whose eigenvalues are mean +- spread)."""
    a00, a01, a11, l00, l10, pivot = _range_cholesky(problem, math.sqrt)
    if not pivot > 0.0:         # B is singular to working precision (P passed its LDL' check)
        return _plan_range_by_stationarity(problem, method)
    l11 = math.sqrt(pivot)
    x00, x01 = a00 / l00, a01 / l00                       # first row of L^-1 A
    x10, x11 = (a01 - l10 * x00) / l11, (a11 - l10 * x01) / l11
    c00, c01 = x00 / l00, x10 / l00                       # C = L^-1 (L^-1 A)'
    c11 = (x11 - l10 * c01) / l11
    half = 0.5 * (c00 - c11)
    spread = math.hypot(half, c01)
    mean = 0.5 * (c00 + c11)
    v0, v1 = (spread + half, c01) if half >= 0.0 else (c01, spread - half)
    u1 = v1 / l11
    u0 = (v0 - l10 * u1) / l00
    flat = spread == 0.0 or gains_tie(problem, mean + spread, mean - spread)
    solution = range_plan_from_direction(problem, math.atan2(u1, u0), flat, 1, method)
    if solution.certificate in PROVED:
        return solution
    # rounding (B near-singular) may have spoilt the direction: the stationarity route too
    other = _plan_range_by_stationarity(problem, method)
    if other.certificate in PROVED or other.cost < solution.cost:
        return other
    return solution


def range_stationary_directions(problem: Problem) -> tuple[list[float], float, float]:
    """The two solutions t [rad] of K + C cos 2t + S sin 2t = 0 (see
    :func:`_plan_range_by_stationarity`; when |K| > amplitude, the directions nearest one),
    the amplitude hypot(C, S) and K."""
    (a00, a01, _, a11, _, _), _ = problem.forms
    p00, p01, _, p11, _, _ = problem.entries
    b00, b01, b11 = p00 + problem.R, p01, p11 + problem.R
    alpha, beta, gamma = a00 * b01 - a01 * b00, a00 * b11 - a11 * b00, a01 * b11 - a11 * b01
    K, C, S = alpha + gamma, alpha - gamma, beta
    amplitude = math.hypot(C, S)
    turn = math.acos(max(-1.0, min(1.0, -K / amplitude))) if amplitude > 0.0 else 0.5 * math.pi
    return [0.5 * (math.atan2(S, C) + turn), 0.5 * (math.atan2(S, C) - turn)], amplitude, K


def _plan_range_by_stationarity(problem: Problem, method: str) -> Solution:
    """Range when the Cholesky reduction of :func:`_plan_range` breaks down: the directions
    u = (cos t, sin t) where A u and B u are parallel (the stationary points of u'Au / u'Bu),
    K + C cos 2t + S sin 2t = 0 with K = alpha + gamma, C = alpha - gamma, S = beta, where
    alpha = a00 b01 - a01 b00, beta = a00 b11 - a11 b00, gamma = a01 b11 - a11 b01."""
    thetas, amplitude, K = range_stationary_directions(problem)
    gains = [problem.gain_at(math.cos(t), math.sin(t)) for t in thetas]
    best = int(gains[1] > gains[0])
    flat = amplitude == 0.0 and K == 0.0 or gains_tie(problem, max(gains), min(gains))
    return range_plan_from_direction(problem, thetas[best], flat, 2, method)


def rq_optimum(problem: Problem, method: str = 'rq') -> Solution:
    """Certified optimum of problem Pi_1 through generalised eigenvalues (module docstring).
    A range-bearing problem (:class:`~formopt_ros.core.stacked.StackedProblem`) goes to its
    own certified solver, :func:`~formopt_ros.core.strategies.stacked.lines_plan`."""
    if problem.measurement == RANGE_BEARING:
        return lines_plan(problem, method)
    if problem.measurement == 'range':
        return _plan_range(problem, method)
    tried: list[tuple[float, float]] = []
    fast = _plan_bearing_fast(problem, method, tried)
    return fast if fast is not None else _plan_bearing_exhaustive(problem, method, tried)


def _elementwise(function: Callable[..., float], *arrays: np.ndarray) -> np.ndarray:
    """``function`` (from Python's math) applied element by element: the very numbers the scalar
    solver computes (numpy's own sin, cos and atan2 may differ in the last bit)."""
    return np.fromiter(map(function, *(np.asarray(a).tolist() for a in arrays)), float,
                       len(arrays[0]))


def _range_first_route(batch: ProblemBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                     np.ndarray]:
    """:func:`_plan_range`'s closed form and arc choice on arrays (T,): (x, y, gain, usable);
    not usable where the scalar solver would take another branch (B singular to working
    precision, every direction tying) or a value is not a number."""
    a00, a01, a11, l00, l10, pivot = _range_cholesky(batch, np.sqrt)
    l11 = np.sqrt(pivot)
    x00, x01 = a00 / l00, a01 / l00
    x10, x11 = (a01 - l10 * x00) / l11, (a11 - l10 * x01) / l11
    c00, c01 = x00 / l00, x10 / l00
    c11 = (x11 - l10 * c01) / l11
    half = 0.5 * (c00 - c11)
    spread = _elementwise(math.hypot, half, c01)
    mean = 0.5 * (c00 + c11)
    upper = half >= 0.0
    v0, v1 = np.where(upper, spread + half, c01), np.where(upper, c01, spread - half)
    u1 = v1 / l11
    u0 = (v0 - l10 * u1) / l00
    flat = (spread == 0.0) | gains_tie(batch, mean + spread, mean - spread, np.maximum)
    x_o, y_o = batch.slot
    theta_o = _elementwise(math.atan2, y_o, x_o)
    delta = _elementwise(math.asin, batch.r / batch.d_o)
    offset = (_elementwise(math.atan2, u1, u0) - theta_o + 0.5 * math.pi) % math.pi \
        - 0.5 * math.pi
    inside = np.abs(offset) <= delta
    ends = []
    for theta in (np.where(inside, theta_o + offset, theta_o - delta), theta_o + delta):
        c, s = _elementwise(math.cos, theta), _elementwise(math.sin, theta)
        along = c * x_o + s * y_o
        x, y = along * c, along * s
        ends.append((x, y, quotient_gain(RANGE, batch.coefficients, x, y)))
    second = ~inside & (ends[1][2] > ends[0][2])
    x, y, g = (np.where(second, b, a) for a, b in zip(*ends))
    return x, y, g, (pivot > 0.0) & ~flat


def _bearing_first_route(batch: ProblemBatch) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                       np.ndarray]:
    """The first try of :func:`_plan_bearing_fast` on arrays (T,): the best boundary sample
    moved to its parabola's vertex (:func:`_boundary_starts`), then Newton's method
    (:func:`_boundary_newton`), each problem stopping where the scalar loop stops: (x, y,
    gain, usable); not usable where a sample or a step is not a number."""
    M, N = batch.forms
    c0, c1, rho = batch.q_circle
    num, den = _circle_series(M, c0, c1, rho), _circle_series(N, c0, c1, rho)
    n0, n1c, n1s, n2c, n2s = num
    d0, d1c, d1s, d2c, d2s = den
    ck, sk, c2k, s2k = _SAMPLE_COLUMNS          # (half, 1) against (T,): rows of samples
    n_even, n_odd = n0 + n2c * c2k + n2s * s2k, n1c * ck + n1s * sk
    d_even, d_odd = d0 + d2c * c2k + d2s * s2k, d1c * ck + d1s * sk
    plus, minus = d_even + d_odd, d_even - d_odd
    values = np.concatenate([np.where(plus > 0.0, (n_even + n_odd) / plus, -np.inf),
                             np.where(minus > 0.0, (n_even - n_odd) / minus, -np.inf)])
    usable = np.isfinite(values).all(axis=0)
    best = np.argmax(values, axis=0)             # the first of equal maxima, as the scalar
    lanes = np.arange(len(batch))
    before, here = values[best - 1, lanes], values[best, lanes]
    after = values[(best + 1) % BOUNDARY_SAMPLES, lanes]
    curvature = before - 2.0 * here + after
    shift = np.where(curvature < 0.0, 0.5 * (before - after) / curvature, 0.0)
    t = SAMPLE_STEP * (best + np.clip(shift, -1.0, 1.0))
    series = np.array([num, den])               # (2, 5, T): both series, one operation each
    moving = lanes                              # the problems whose Newton loop runs on
    for _ in range(NEWTON_ITERATIONS):
        k0, k1c, k1s, k2c, k2s = series[:, :, moving].transpose(1, 0, 2)
        angle = t[moving]
        c, s = _elementwise(math.cos, angle), _elementwise(math.sin, angle)
        c2, s2 = c * c - s * s, 2.0 * s * c
        x1, x2 = k1c * c + k1s * s, k2c * c2 + k2s * s2      # rows: numerator, denominator
        (n, d), (n_t, d_t) = k0 + x1 + x2, k1s * c - k1c * s + 2.0 * (k2s * c2 - k2c * s2)
        (n1, d1), (n2, d2) = x1, x2
        F = n_t * d - n * d_t
        slope = (-n1 - 4.0 * n2) * d + n * (d1 + 4.0 * d2)
        step = np.where(slope < 0.0, np.clip(-F / slope, -NEWTON_MAX_STEP, NEWTON_MAX_STEP),
                        np.where(F >= 0.0, 0.1, -0.1))
        t[moving] = angle + step
        moving = moving[(step < -NEWTON_STEP_TOLERANCE) | (step > NEWTON_STEP_TOLERANCE)]
        if not len(moving):
            break
    q0 = c0 + rho * _elementwise(math.cos, t)
    q1 = c1 + rho * _elementwise(math.sin, t)
    n2 = q0 * q0 + q1 * q1
    x, y = q1 / n2, -q0 / n2
    return x, y, quotient_gain(BEARING, batch.coefficients, x, y), usable & np.isfinite(t)


def rq_batch(batch: ProblemBatch, method: str = 'rq') -> np.ndarray:
    """RQ on T problems at once: the points (T, 2) (m) that :func:`rq_optimum` returns for
    ``batch.problem(t)``, bit for bit.

    The scalar solver's first route (range: the closed-form direction and the arc; bearing:
    the best boundary sample polished by Newton's method) and the floating-point stage of its
    certificate (:func:`~.certificate.proved_batch`) run on arrays, operation for operation
    in the scalar order (sin, cos, atan2, asin and hypot from Python's math, element by
    element), so each problem gets the numbers and the decisions of the scalar solver. A
    problem whose answer that stage proves is done; any other (an interior optimum, a
    proof that needs exact arithmetic, a tie, a value that is not a number) is solved by
    :func:`rq_optimum`, which repeats the first route and goes on."""
    with np.errstate(all='ignore'):
        route = _range_first_route if batch.measurement == RANGE else _bearing_first_route
        x, y, g, usable = route(batch)
        usable &= np.isfinite(x) & np.isfinite(y) & np.isfinite(g)
    done = usable & proved_batch(batch, x, y, g)
    points = np.stack([x, y], axis=1)
    for t in np.flatnonzero(~done).tolist():
        points[t] = rq_optimum(batch.problem(t), method).p
    return points


class RayleighQuotient(Strategy):
    """RQ: the exact generalised-Rayleigh-quotient solver (beyond the paper)."""

    name = 'rq'

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The exact greedy optimum."""
        return rq_optimum(problem, self.name)

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """:func:`rq_batch`: the first route and its proof vectorised over the trials."""
        return BatchPlan(rq_batch(problems, self.name))


__all__ = ['RayleighQuotient', 'boundary_candidates', 'generalized_eigh', 'rq_batch', 'rq_optimum',
           'top_generalized_eigenvector']
