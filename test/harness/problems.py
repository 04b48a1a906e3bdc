"""Seeded generators of hard planning problems and two independent references for them.

Generators aim at the weak spots of the solvers: ill-conditioned and mixed-unit priors, interior
optima among clustered roots of RAM's interior resultant, near-double boundary maxima, tiny r,
r close to |p_o|, huge and tiny scales, flat and nearly flat range problems.

References use ``Problem.gain_at`` (the one cost formula) only, never the solvers' algebra:
``dense_reference`` (a fine polar grid and L-BFGS-B, ~0.2 s a problem) and ``quick_reference``
(boundary samples refined by golden-section search, an interior polar grid refined by compass
search, ~2 ms a problem). Both evaluate feasible points only, so both are upper bounds on the
optimal cost: a solver's cost above them by more than the tolerance is a wrong answer.
"""
from __future__ import annotations

import math
import os
from collections.abc import Callable

import numpy as np
from scipy.optimize import minimize

from formopt_ros.core import Problem
from formopt_ros.core.cost import MAX_DEVIATION
from formopt_ros.core.model import BEARING, RANGE
from formopt_ros.core.stacked import StackedProblem

Generator = Callable[[np.random.Generator], Problem]

#: Multiplier of the counts of the generated-problem tests (environment FORMOPT_TEST_SCALE,
#: default 1: the suite's counts, minutes in all); 5 runs the families' 10,000+ per sensor
#: (docs/certification.md, "Scale runs").
TEST_SCALE = float(os.environ.get('FORMOPT_TEST_SCALE', '1'))


def scaled(count: int) -> int:
    """``count`` times TEST_SCALE, at least 1."""
    return max(1, round(count * TEST_SCALE))


# --- building blocks ---------------------------------------------------------------------------
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A Haar-distributed random rotation matrix, shape (3, 3)."""
    Q, R = np.linalg.qr(rng.standard_normal((3, 3)))
    Q = Q * np.sign(np.diag(R))
    if np.linalg.det(Q) < 0:
        Q[:, 0] = -Q[:, 0]
    return Q


def random_geometry(rng: np.random.Generator, r_low: float = 0.01,
                    r_high: float = 0.5) -> tuple[np.ndarray, float]:
    """p_o with 0.5 m <= |p_o| <= 10 m in a random direction, r in [r_low, r_high] |p_o|."""
    d_o = rng.uniform(0.5, 10.0)
    angle = rng.uniform(-math.pi, math.pi)
    return d_o * np.array([math.cos(angle), math.sin(angle)]), d_o * rng.uniform(r_low, r_high)


def random_sigma(rng: np.random.Generator, kind: str) -> float:
    """Range noise 0.01-0.5 m, bearing noise 0.002-0.1 rad."""
    return rng.uniform(0.01, 0.5) if kind == RANGE else rng.uniform(0.002, 0.1)


def hard_covariance(rng: np.random.Generator, max_log_condition: float = 9.0) -> np.ndarray:
    """Random rotation of eigenvalues spanning condition numbers up to 10**max_log_condition,
    then a per-axis rescaling by 10**U(-1, 1) (mixed units) and an overall scale 10**U(-4, 0)."""
    log_condition = rng.uniform(0.0, max_log_condition)
    eigenvalues = 10.0 ** -np.array([0.0, rng.uniform(0.0, log_condition), log_condition])
    Q = random_rotation(rng)
    D = np.diag(10.0 ** rng.uniform(-1.0, 1.0, 3))
    P = D @ (Q @ np.diag(eigenvalues) @ Q.T) @ D * 10.0 ** rng.uniform(-4.0, 0.0)
    return 0.5 * (P + P.T)


def random_correlation(rng: np.random.Generator) -> np.ndarray:
    """A random 3x3 correlation matrix (Gram matrix of random unit vectors)."""
    V = rng.standard_normal((3, 3))
    V /= np.linalg.norm(V, axis=1, keepdims=True)
    return V @ V.T


# --- families ----------------------------------------------------------------------------------
def hard_problem(rng: np.random.Generator, kind: str) -> Problem:
    """A hard random problem of the given measurement kind (see hard_covariance)."""
    p_o, r = random_geometry(rng)
    return Problem(hard_covariance(rng), p_o, r, random_sigma(rng, kind), kind)


def interior_bearing_problem(rng: np.random.Generator) -> Problem:
    """A bearing problem built so that its optimum is (very likely) inside the disc.

    For R -> 0 the gain h'Mh / h'Nh is maximised by the top eigenvector of W^2 P; with
    P = W^-1 B W^-1 that is W times the top eigenvector of B. So B gets the top eigenvector
    W^-1 h* for h* = [q*, -1] of a random target p* inside the disc, and sigma is made small
    (1e-3 to 1e-1 of the heading standard deviation) so the target stays near the optimum.
    """
    p_o, r = random_geometry(rng, 0.05, 0.5)
    rho, angle = r * math.sqrt(rng.uniform(0.0, 0.8)), rng.uniform(-math.pi, math.pi)
    target = p_o + rho * np.array([math.cos(angle), math.sin(angle)])
    h = np.array([-target[1], target[0], -float(target @ target)])     # proportional to [q, -1]
    w = np.array([1.0, 1.0, math.hypot(*p_o)])
    Q = random_rotation(rng)
    Q[:, 0] = h / w / np.linalg.norm(h / w)
    Q, _ = np.linalg.qr(Q)
    B = Q @ np.diag([1.0, *10.0 ** -rng.uniform(0.3, 3.0, 2)]) @ Q.T
    P = B / np.outer(w, w) * 10.0 ** rng.uniform(-4.0, 0.0)
    P = 0.5 * (P + P.T)
    sigma = math.sqrt(P[2, 2]) * 10.0 ** rng.uniform(-3.0, -1.0)
    return Problem(P, p_o, r, sigma, BEARING)


def top_vector_inside(problem: Problem) -> bool:
    """True when the top generalised eigenvector of (M, N) maps into the q-disc (the bearing
    gain's unconstrained maximum is feasible), computed with numpy's eigh."""
    L = np.linalg.cholesky(problem.N)
    L_inv = np.linalg.inv(L)
    _, vectors = np.linalg.eigh(L_inv @ problem.M @ L_inv.T)
    h = L_inv.T @ vectors[:, -1]
    if h[2] == 0.0:
        return False
    q = -h[:2] / h[2]
    centre, rho = problem.q_disc()
    return bool(math.hypot(*(q - centre)) < rho)


def clustered_interior_problem(rng: np.random.Generator) -> Problem:
    """The family on which RAM used to return wrong points: bearing problems whose optimum lies
    inside the disc among clustered roots of the interior resultant S_u.

    Position well known (standard deviations 1 mm to 10 cm), heading poorly known (0.05 to
    1 rad), random correlations (condition numbers ~1e4 to 1e6), small sigma (0.002-0.01 rad),
    r 30-50 % of |p_o|; drawn until the optimum is interior (about one draw in 80). The
    interior critical points then sit at bearings where sigma = sin^2 t has clustered roots
    (near 0 or pi/2, or two critical points at nearly one bearing).
    """
    while True:
        d_o, angle = rng.uniform(0.5, 10.0), rng.uniform(-math.pi, math.pi)
        p_o = d_o * np.array([math.cos(angle), math.sin(angle)])
        D = np.diag([10.0 ** rng.uniform(-3.0, -1.0), 10.0 ** rng.uniform(-3.0, -1.0),
                     rng.uniform(0.05, 1.0)])
        P = D @ random_correlation(rng) @ D
        P = 0.5 * (P + P.T)
        if np.linalg.eigvalsh(P)[0] <= 1e-14 * np.trace(P):
            continue
        problem = Problem(P, p_o, d_o * rng.uniform(0.3, 0.5), rng.uniform(0.002, 0.01),
                          BEARING)
        if top_vector_inside(problem):
            return problem


def mirrored_problem(rng: np.random.Generator, kind: str) -> Problem:
    """Near-double boundary maxima: a configuration symmetric about the slot's axis (slot on an
    axis, P with no coupling of the across-axis coordinate), so that boundary optima come in
    mirrored pairs, then broken by a relative 10**U(-12, -3) and rotated at random.

    Reflection x -> -x maps the disc around p_o = (0, d) onto itself and the gain onto itself
    when P01 = P12 = 0 (h = [q0, q1, -1] -> diag(1, -1, 1) h, likewise u for range); rotating
    the slot and P's position block by one angle rotates the whole problem.
    """
    d_o = rng.uniform(0.5, 10.0)
    a, b, c = 10.0 ** rng.uniform(-4.0, 0.0, 3)
    rho = rng.uniform(-0.95, 0.95)
    P = np.array([[a, 0.0, 0.0], [0.0, b, rho * math.sqrt(b * c)],
                  [0.0, rho * math.sqrt(b * c), c]])
    eps = 10.0 ** rng.uniform(-12.0, -3.0)
    P[0, 1] = P[1, 0] = eps * math.sqrt(a * b) * rng.standard_normal()
    P[0, 2] = P[2, 0] = eps * math.sqrt(a * c) * rng.standard_normal()
    angle = rng.uniform(-math.pi, math.pi)
    T = np.eye(3)
    T[:2, :2] = [[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]]
    P = T @ P @ T.T
    p_o = T[:2, :2] @ np.array([0.0, d_o])
    return Problem(0.5 * (P + P.T), p_o, d_o * rng.uniform(0.05, 0.5), random_sigma(rng, kind),
                   kind)


def tiny_disc_problem(rng: np.random.Generator, kind: str) -> Problem:
    """r from 1e-6 to 1e-2 of |p_o|."""
    p_o, _ = random_geometry(rng)
    return Problem(hard_covariance(rng), p_o, math.hypot(*p_o) * 10.0 ** rng.uniform(-6.0, -2.0),
                   random_sigma(rng, kind), kind)


def wide_disc_problem(rng: np.random.Generator, kind: str) -> Problem:
    """r from 0.9 to 0.999 of |p_o|: the disc nearly reaches the leader."""
    p_o, _ = random_geometry(rng)
    r = math.hypot(*p_o) * (1.0 - 10.0 ** rng.uniform(-3.0, -1.0))
    return Problem(hard_covariance(rng), p_o, r, random_sigma(rng, kind), kind)


def scaled_problem(rng: np.random.Generator, kind: str) -> Problem:
    """Huge and tiny scales: |p_o| from 1e-2 to 1e3 m, P scaled by 10**U(-12, 4), sigma by
    10**U(-3, 2)."""
    p_o, r = random_geometry(rng, 0.05, 0.5)
    scale = 10.0 ** rng.uniform(-2.0, 3.0) / math.hypot(*p_o)
    P = hard_covariance(rng, 6.0) * 10.0 ** rng.uniform(-8.0, 4.0)
    return Problem(P, p_o * scale, r * scale, random_sigma(rng, kind) * 10.0 ** rng.uniform(
        -3.0, 2.0), kind)


def minor_axis_problem(rng: np.random.Generator, kind: str, tie: bool = False) -> Problem:
    """Where the gain formula cancels: P's 2x2 block of condition 1e3 to 1e12 (its scale
    10**U(-4, 4)), the slot's bearing within 10**U(-9, -1) rad of that block's minor axis,
    |p_o| from 1e-3 to 1e5 m, r from 1e-6 to 0.3 |p_o|, sigma down to 1e-7 (relative to the
    block's scale for range). With ``tie``: within 10**U(-14, -8) rad and r up to 1e-4 |p_o|,
    so that the two ends of the range arc nearly tie (the reviewer's wrong-end family)."""
    scale, condition = 10.0 ** rng.uniform(-4.0, 4.0), 10.0 ** rng.uniform(3.0, 12.0)
    axis = rng.uniform(0.0, 2.0 * math.pi)
    Q = np.array([[math.cos(axis), -math.sin(axis)], [math.sin(axis), math.cos(axis)]])
    P = np.zeros((3, 3))
    P[:2, :2] = Q @ np.diag([scale, scale / condition]) @ Q.T
    P[2, 2] = scale * 10.0 ** rng.uniform(-6.0, 0.0)
    if rng.uniform() < 0.5:         # a weak cross-correlation with the heading
        P[:2, 2] = np.sqrt(P[2, 2] * np.diag(P[:2, :2])) * rng.uniform(-0.5, 0.5, 2) / condition
    P = 0.5 * (P + P.T)
    low, high = (-14.0, -8.0) if tie else (-9.0, -1.0)
    bearing = axis + 0.5 * math.pi + rng.choice([-1.0, 1.0]) * 10.0 ** rng.uniform(low, high)
    d_o = 10.0 ** rng.uniform(-3.0, 5.0)
    r = d_o * 10.0 ** rng.uniform(-6.0, -4.0 if tie else -0.5)
    sigma = 10.0 ** rng.uniform(-7.0, -1.0) * (math.sqrt(scale) if kind == RANGE else 1.0)
    return Problem(P, d_o * np.array([math.cos(bearing), math.sin(bearing)]), r, sigma, kind)


def ill_conditioned_problem(rng: np.random.Generator, kind: str) -> Problem:
    """Extreme condition numbers of P: 1e9 to 1e13."""
    p_o, r = random_geometry(rng)
    while True:
        P = hard_covariance(rng, 13.0)
        if np.linalg.cond(P) > 1e9:
            try:
                return Problem(P, p_o, r, random_sigma(rng, kind), kind)
            except ValueError:      # rounding made it indefinite: draw again
                continue


def beyond_double_problem(rng: np.random.Generator, kind: str) -> Problem:
    """Condition numbers of P from 1e16 to 1e34, variances from 1e-40 to 1e4, r often at
    0.99-0.999 |p_o|, sigma from 1e-6: rounding defeats the proofs and the root finders (RQ
    once returned the worst point of the disc here). Redrawn until the Problem validates."""
    while True:
        log_condition = rng.uniform(16.0, 34.0)
        eigenvalues = 10.0 ** -np.array([0.0, rng.uniform(0.0, log_condition), log_condition])
        Q = random_rotation(rng)
        D = np.diag(10.0 ** rng.uniform(-2.0, 2.0, 3))
        P = D @ (Q @ np.diag(eigenvalues) @ Q.T) @ D * 10.0 ** rng.uniform(-3.0, 2.0)
        d_o = rng.uniform(0.1, 10.0)
        angle = rng.uniform(-math.pi, math.pi)
        fraction = (rng.uniform(0.01, 0.5), 0.99, MAX_DEVIATION)[int(rng.integers(3))]
        sigma = 10.0 ** rng.uniform(-6.0, 0.0) * (1.0 if kind == RANGE else 0.1)
        try:
            return Problem(0.5 * (P + P.T), d_o * np.array([math.cos(angle), math.sin(angle)]),
                           fraction * d_o, sigma, kind)
        except ValueError:          # not positive definite in floating point: draw again
            continue


def flat_range_problem(rng: np.random.Generator) -> Problem:
    """A range problem with P[:2, :2] = a I and P[0, 2] = P[1, 2] = 0: every direction ties."""
    a = 10.0 ** rng.uniform(-4.0, 0.0)
    P = np.diag([a, a, a * 10.0 ** rng.uniform(-3.0, 1.0)])
    p_o, r = random_geometry(rng)
    return Problem(P, p_o, r, random_sigma(rng, RANGE), RANGE)


def nearly_flat_range_problem(rng: np.random.Generator) -> Problem:
    """A flat range problem whose position block is perturbed by a relative 10**U(-14, -6)."""
    flat = flat_range_problem(rng)
    P = flat.P.copy()
    a = P[0, 0]
    eps = 10.0 ** rng.uniform(-14.0, -6.0)
    E = rng.standard_normal((2, 2))
    P[:2, :2] += a * eps * (E + E.T) / 2
    P[0, 2] = P[2, 0] = a * eps * rng.standard_normal()
    return Problem(P, flat.p_o, flat.r, flat.sigma, RANGE)


def near_rank_one_problem(rng: np.random.Generator, kind: str) -> Problem:
    """P = v v' + eps |v|^2 (I + 0.3 diag(U(0, 1))) scaled by 10**U(-20, 10), eps = 10**U(-15, -8)
    (condition 1e8 to 1e15), sigma 10**U(-9, -3) of the largest standard deviation: the
    posterior cost is 1e-8 to 1e-15 of tr(W P W), far below the rounding of the gain formula,
    and the floating-point critical points miss the optimum by up to 3e-5 of the cost (a
    reviewer's family). |p_o| from 1e-3 to 1e6 m, r from 0.3 to 0.999 |p_o|. Drawn again
    until the problem is valid (a few percent are not positive definite in exact arithmetic)."""
    while True:
        d_o = 10.0 ** rng.uniform(-3.0, 6.0)
        angle = rng.uniform(-math.pi, math.pi)
        p_o = d_o * np.array([math.cos(angle), math.sin(angle)])
        v = rng.standard_normal(3)
        v[2] /= d_o * rng.choice([1.0, 10.0, 0.1])
        eps = 10.0 ** rng.uniform(-15.0, -8.0)
        P = np.outer(v, v) + eps * (v @ v) * (np.eye(3) + 0.3 * np.diag(rng.random(3)))
        P = 0.5 * (P + P.T) * 10.0 ** rng.uniform(-20.0, 10.0)
        r = float(rng.choice([0.3, 0.7, 0.9, 0.99, 0.999]) * d_o)
        sigma = min(max(10.0 ** rng.uniform(-9.0, -3.0) * math.sqrt(P.diagonal().max()), 1e-9),
                    1e6)
        try:
            return Problem(P, p_o, r, sigma, kind)
        except ValueError:
            continue


def families(kind: str) -> dict[str, tuple[Generator, int]]:
    """name -> (generator, count): 2,000 or more problems per kind, times TEST_SCALE."""
    def of(maker: Callable[[np.random.Generator, str], Problem]) -> Generator:
        return lambda rng: maker(rng, kind)
    common = {'hard': (of(hard_problem), 600), 'mirrored': (of(mirrored_problem), 300),
              'tiny r': (of(tiny_disc_problem), 200),
              'r near |p_o|': (of(wide_disc_problem), 200),
              'scaled': (of(scaled_problem), 200),
              'ill-conditioned': (of(ill_conditioned_problem), 200)}
    table = {**common, 'nearly flat': (nearly_flat_range_problem, 300)} if kind == RANGE else \
        {**common, 'clustered interior': (clustered_interior_problem, 200),
         'interior': (interior_bearing_problem, 100)}
    return {name: (make, scaled(count)) for name, (make, count) in table.items()}


# --- range-bearing problems ------------------------------------------------------------------
#: Kinds of generated range-bearing problem, drawn in turn.
STACKED_FAMILIES = ('moderate', 'ill-conditioned', 'tiny-r', 'large-r', 'near-leader',
                    'small-noise')


def stacked_problem(rng: np.random.Generator, family: str) -> StackedProblem:
    """One random problem of a family: prior condition up to 1e4 (1e8 'ill-conditioned') and
    scale 1e-4..1, slot 0.5-10 m away (0.01-0.2 m 'near-leader', where r is 0.3-0.999 |p_o|),
    r 5-30 % of |p_o| (1e-6..1e-3 'tiny-r', 0.9-0.999 'large-r'), sigma_d 0.01-0.5 m and
    sigma_beta 0.002-0.1 rad (1e-4 m / 1e-5 rad 'small-noise')."""
    q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    spread = 8.0 if family == 'ill-conditioned' else 4.0
    eigenvalues = 10.0 ** -np.array([0.0, rng.uniform(0, spread), rng.uniform(0, spread)])
    P = (q * eigenvalues) @ q.T * 10.0 ** rng.uniform(-4.0, 0.0)
    d_o = rng.uniform(0.01, 0.2) if family == 'near-leader' else rng.uniform(0.5, 10.0)
    theta = rng.uniform(-math.pi, math.pi)
    fraction = {'tiny-r': 10.0 ** rng.uniform(-6.0, -3.0), 'large-r': rng.uniform(0.9, 0.999),
                'near-leader': rng.uniform(0.3, 0.999)}.get(family, rng.uniform(0.05, 0.3))
    sigma_d, sigma_b = (rng.uniform(0.01, 0.5), rng.uniform(0.002, 0.1))
    if family == 'small-noise':
        sigma_d, sigma_b = sigma_d * 1e-2, sigma_b * 1e-2
    return StackedProblem(0.5 * (P + P.T), [d_o * math.cos(theta), d_o * math.sin(theta)],
                          fraction * d_o, sigma_d, sigma_b)


# --- references --------------------------------------------------------------------------------
REFERENCE_RADII = 200
REFERENCE_ANGLES = 720
REFERENCE_BOUNDARY = 20000
REFERENCE_STARTS = 3


def dense_reference(problem: Problem) -> float:
    """Best cost found by a fine polar grid and local polishing, using Problem.cost only.

    Grid: p_o, 200 radii x 720 angles and 20000 boundary angles. Polishing: L-BFGS-B in
    (radius fraction u in [0, 1], angle) from the 3 best mutually distant grid points; every
    evaluated point is feasible by construction, so the result is an upper bound on the optimum.
    """
    r = problem.r
    radii = r * np.arange(1, REFERENCE_RADII + 1) / REFERENCE_RADII
    angles = np.linspace(-math.pi, math.pi, REFERENCE_ANGLES, endpoint=False)
    boundary = np.linspace(-math.pi, math.pi, REFERENCE_BOUNDARY, endpoint=False)
    rr = np.concatenate([[0.0], np.repeat(radii, REFERENCE_ANGLES),
                         np.full(REFERENCE_BOUNDARY, r)])
    aa = np.concatenate([[0.0], np.tile(angles, REFERENCE_RADII), boundary])
    costs = problem.cost(problem.p_o + rr[:, None] * np.stack([np.cos(aa), np.sin(aa)], axis=1))
    best = float(np.min(costs))

    def cost(z: np.ndarray) -> float:
        u = min(max(float(z[0]), 0.0), 1.0)
        return problem.cost(problem.p_o + u * r * np.array([math.cos(z[1]), math.sin(z[1])]))

    starts: list[np.ndarray] = []
    for index in np.argsort(costs)[:5000]:
        z = np.array([rr[index] / r, aa[index]])
        if all(abs(z[0] - s[0]) + abs(math.remainder(z[1] - s[1], 2 * math.pi)) > 0.05
               for s in starts):
            starts.append(z)
        if len(starts) == REFERENCE_STARTS:
            break
    for z in starts:
        result = minimize(cost, z, method='L-BFGS-B', bounds=[(0.0, 1.0), (None, None)],
                          options={'ftol': 1e-15, 'gtol': 1e-14, 'maxiter': 100})
        best = min(best, float(result.fun))
    return best


QUICK_BOUNDARY = 2048
QUICK_RADII = 24
QUICK_ANGLES = 96
QUICK_STARTS = 3
QUICK_POLISHED = 1
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def _boundary_gain(problem: Problem, t: np.ndarray) -> np.ndarray:
    x_o, y_o = problem.slot
    return np.asarray(problem.gain_at(x_o + problem.r * np.cos(t), y_o + problem.r * np.sin(t)))


def _disc_gain(problem: Problem, u: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Gain at radius fraction u (clipped to [0, 1]) and angle t around p_o."""
    x_o, y_o = problem.slot
    rho = problem.r * np.clip(u, 0.0, 1.0)
    return np.asarray(problem.gain_at(x_o + rho * np.cos(t), y_o + rho * np.sin(t)))


def quick_reference(problem: Problem) -> float:
    """A fast independent upper bound on the optimal cost (module docstring).

    Boundary: 2048 equally spaced angles; the 3 best local maxima are refined by 50 steps of
    golden-section search on their bracket (to ~1e-13 rad). Interior (bearing only: the range
    gain depends on the bearing alone, which the boundary covers): p_o and a 24 x 96 polar
    grid; when the grid's best comes within 1 % of the cost of the boundary's best, its best
    point is polished by L-BFGS-B on (u, t) as in dense_reference.
    """
    t = np.linspace(-math.pi, math.pi, QUICK_BOUNDARY, endpoint=False)
    g = _boundary_gain(problem, t)
    peaks = np.flatnonzero((g >= np.roll(g, 1)) & (g >= np.roll(g, -1)))
    peaks = peaks[np.argsort(g[peaks])[::-1][:QUICK_STARTS]]
    step = 2.0 * math.pi / QUICK_BOUNDARY
    lo, hi = t[peaks] - step, t[peaks] + step
    for _ in range(50):                      # golden-section search, all brackets at once
        a, b = hi - GOLDEN * (hi - lo), lo + GOLDEN * (hi - lo)
        left = _boundary_gain(problem, a) >= _boundary_gain(problem, b)
        lo, hi = np.where(left, lo, a), np.where(left, b, hi)
    best = max(float(np.max(g)), float(np.max(_boundary_gain(problem, 0.5 * (lo + hi)))))
    if problem.measurement == BEARING:
        u = np.repeat(np.arange(1, QUICK_RADII + 1) / QUICK_RADII, QUICK_ANGLES)
        a = np.tile(np.linspace(-math.pi, math.pi, QUICK_ANGLES, endpoint=False), QUICK_RADII)
        u, a = np.concatenate([[0.0], u]), np.concatenate([[0.0], a])
        g = _disc_gain(problem, u, a)
        best = max(best, float(np.max(g)))
        if float(np.max(g)) >= best - 0.01 * (problem.base_cost - best):
            def cost(z: np.ndarray) -> float:
                return float(problem.base_cost - _disc_gain(problem, z[:1], z[1:])[0])
            for index in np.argsort(g)[::-1][:QUICK_POLISHED]:
                result = minimize(cost, [u[index], a[index]], method='L-BFGS-B',
                                  bounds=[(0.0, 1.0), (None, None)],
                                  options={'ftol': 1e-15, 'gtol': 1e-14, 'maxiter': 100})
                best = max(best, problem.base_cost - float(result.fun))
    return problem.base_cost - best


__all__ = ['TEST_SCALE', 'clustered_interior_problem', 'dense_reference', 'families',
           'flat_range_problem', 'hard_covariance', 'hard_problem', 'interior_bearing_problem',
           'mirrored_problem', 'nearly_flat_range_problem', 'quick_reference', 'random_geometry',
           'random_rotation', 'random_sigma', 'scaled', 'scaled_problem', 'tiny_disc_problem',
           'top_vector_inside', 'wide_disc_problem']
