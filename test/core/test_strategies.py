"""Property tests of the strategies (RAM, RQ, GBS, MTF, CRM, MME) on hard random problems."""
from __future__ import annotations

import math

import numpy as np
import pytest

from formopt_ros.core import PlanContext, Problem, solve
from formopt_ros.core.model import BEARING, RANGE
from formopt_ros.core.strategies import baselines, common, make_strategy, ram
from formopt_ros.core.strategies.ram import ram_optimum
from harness import split_by_tier
from harness.problems import (
    dense_reference, flat_range_problem, hard_covariance, hard_problem, interior_bearing_problem,
    nearly_flat_range_problem, random_geometry, random_rotation, random_sigma)

KINDS = (RANGE, BEARING)
#: Allowed relative cost excess of RAM / RQ over an independent reference (the brief's 1e-9).
REFERENCE_RTOL = 1e-9
#: Allowed relative cost excess of RAM / RQ over grid-based search.
GBS_RTOL = 1e-12
#: Allowed relative violation of |p - p_o| <= r.
FEASIBILITY_RTOL = 1e-9
#: GBS cell (fraction of r) used in the 1000-problem cross check; any grid is an upper bound on
#: the optimum, the coarser one keeps the suite fast (the dense reference is much finer).
CROSS_CHECK_CELL = 0.02


def assert_feasible(problem: Problem, p: np.ndarray, label: str) -> None:
    """|p - p_o| <= r (1 + FEASIBILITY_RTOL)."""
    distance = math.hypot(*(p - problem.p_o))
    assert distance <= problem.r * (1 + FEASIBILITY_RTOL), (label, distance, problem.r)


def solve_problem(problem: Problem, method: str, **options: object):
    """solve() on an already validated Problem's data."""
    return solve(problem.P, problem.p_o, problem.r, problem.sigma,
                 measurement=problem.measurement, method=method, **options)


# --- the central property tests ------------------------------------------------------------------
@split_by_tier(250, 1000)
@pytest.mark.parametrize('kind', KINDS)
def test_ram_and_rq_agree_and_beat_gbs(kind: str, first: int, last: int) -> None:
    """1000 hard problems per kind (the fast tier the first 250): RAM and RQ agree to 1e-9,
    beat GBS, and are feasible."""
    rng = np.random.default_rng(1000 + KINDS.index(kind))
    failures = []
    for index in range(last):
        problem = hard_problem(rng, kind)
        if index < first:
            continue
        ram_solution = solve_problem(problem, 'ram')
        rq_solution = solve_problem(problem, 'rq')
        gbs_solution = solve_problem(problem, 'gbs', cell=CROSS_CHECK_CELL)
        for solution in (ram_solution, rq_solution):
            assert_feasible(problem, solution.p, f'{solution.method} #{index}')
            # The reported cost is the cost at the reported point (1e-14 relative: rounding).
            assert solution.cost == pytest.approx(problem.cost(solution.p), rel=1e-14)
            if solution.cost > gbs_solution.cost * (1 + GBS_RTOL):
                failures.append((index, solution.method, 'gbs', solution.cost / gbs_solution.cost))
        best = min(ram_solution.cost, rq_solution.cost)
        for solution in (ram_solution, rq_solution):
            if solution.cost > best * (1 + REFERENCE_RTOL):
                failures.append((index, solution.method, 'other', solution.cost / best))
    assert not failures, failures


@pytest.mark.slow
@pytest.mark.parametrize('kind', KINDS)
def test_ram_and_rq_match_dense_reference(kind: str) -> None:
    """150 hard problems per kind: RAM and RQ are within 1e-9 of an independent dense search."""
    rng = np.random.default_rng(2000 + KINDS.index(kind))
    failures = []
    for index in range(150):
        problem = hard_problem(rng, kind)
        reference = dense_reference(problem)
        for method in ('ram', 'rq'):
            solution = solve_problem(problem, method)
            assert_feasible(problem, solution.p, f'{method} #{index}')
            if solution.cost > reference * (1 + REFERENCE_RTOL):
                failures.append((index, method, solution.cost / reference - 1))
    assert not failures, failures


@pytest.mark.slow
def test_interior_bearing_optima() -> None:
    """Family (a): 300 constructed bearing problems, most with an interior optimum (RQ's
    details['interior']); RAM and RQ agree to 1e-9, beat GBS, and the first 40 interior ones
    match the dense reference."""
    rng = np.random.default_rng(3000)
    interior = 0
    failures = []
    for index in range(300):
        problem = interior_bearing_problem(rng)
        rq_solution = solve_problem(problem, 'rq')
        if not rq_solution.details['interior']:
            continue
        interior += 1
        assert not rq_solution.on_boundary
        ram_solution = solve_problem(problem, 'ram')
        gbs_solution = solve_problem(problem, 'gbs', cell=CROSS_CHECK_CELL)
        best = min(ram_solution.cost, rq_solution.cost)
        reference = dense_reference(problem) if interior <= 40 else math.inf
        for solution in (ram_solution, rq_solution):
            assert_feasible(problem, solution.p, f'{solution.method} #{index}')
            for name, bound, rtol in (('gbs', gbs_solution.cost, GBS_RTOL),
                                      ('other', best, REFERENCE_RTOL),
                                      ('reference', reference, REFERENCE_RTOL)):
                if solution.cost > bound * (1 + rtol):
                    failures.append((index, solution.method, name, solution.cost / bound - 1,
                                     solution.fallback))
    assert interior >= 150, f'only {interior} interior optima generated'
    assert not failures, failures


def test_ram_finds_interior_optimum_regression() -> None:
    """A seeded interior-optimum bearing problem on which RAM's interior root was lost.

    Found by a random search (r 30-50% of |p_o|, sigma 0.002-0.01 rad). The interior critical
    point sits in a cluster of nearly coincident roots of S_u, so the colleague-matrix roots are
    off by ~2e-3 in sin^2 t, the back-substituted point fails the 1e-4 residual check, no
    interior candidate survives, and the probes (slot and boundary only) do not notice.
    """
    P = np.array([[5.9385035094867010e-05, 2.4659425644971799e-05, -2.7589995574295373e-03],
                  [2.4659425644971799e-05, 2.0465425532377897e-05, 7.2903560020072642e-04],
                  [-2.7589995574295373e-03, 7.2903560020072642e-04, 4.8170050755601368e-01]])
    problem = Problem(P, np.array([-5.813825142325465, -3.1765689391119225]),
                      2.9843907367078195, 0.0026647797660406002, BEARING)
    rq_solution = solve_problem(problem, 'rq')
    assert rq_solution.details['interior']
    reference = dense_reference(problem)
    # The dense search confirms RQ (1e-9 relative).
    assert rq_solution.cost <= reference * (1 + REFERENCE_RTOL)
    ram_solution = solve_problem(problem, 'ram')
    # RAM must be as good (1e-9 relative), or at least admit it failed through its fallback.
    assert ram_solution.cost <= reference * (1 + REFERENCE_RTOL), (
        ram_solution.p, ram_solution.cost / reference - 1, ram_solution.details)


def test_flat_range_returns_slot_exactly() -> None:
    """Family (b): 200 exactly flat range problems: every direction ties, so p = p_o exactly."""
    rng = np.random.default_rng(4000)
    for _ in range(200):
        problem = flat_range_problem(rng)
        gains = problem.gain(problem.p_o + problem.r * rng.uniform(-0.7, 0.7, (50, 2)))
        # The problem really is flat: gains tie to rounding (1e-13 relative).
        assert np.ptp(gains) <= 1e-13 * np.max(gains)
        for method in ('ram', 'rq'):
            solution = solve_problem(problem, method)
            assert np.array_equal(solution.p, problem.p_o), (method, solution.p, problem.p_o)
            assert solution.cost == solution.cost_at_slot


def test_nearly_flat_range() -> None:
    """Family (b'): 300 nearly flat range problems (relative perturbation 1e-14 to 1e-6): RAM
    and RQ agree, never lose to the slot or to GBS, and stay feasible."""
    rng = np.random.default_rng(5000)
    for index in range(300):
        problem = nearly_flat_range_problem(rng)
        gbs_cost = solve_problem(problem, 'gbs', cell=CROSS_CHECK_CELL).cost
        costs = {}
        for method in ('ram', 'rq'):
            solution = solve_problem(problem, method)
            assert_feasible(problem, solution.p, f'{method} #{index}')
            assert solution.cost <= solution.cost_at_slot * (1 + GBS_RTOL), (index, method)
            assert solution.cost <= gbs_cost * (1 + GBS_RTOL), (index, method)
            costs[method] = solution.cost
        # 1e-12 relative: both are optimal up to the flatness tolerance of 1e-12.
        assert costs['ram'] == pytest.approx(costs['rq'], rel=1e-12)


# --- range RAM coefficients ----------------------------------------------------------------------
def range_gain_from_coefficients(a: tuple[float, ...], theta: np.ndarray) -> np.ndarray:
    """(a1 sin 2t + a2 cos 2t + a3) / (a4 sin 2t + a5 cos 2t + a6), eq. (24)."""
    s2, c2 = np.sin(2 * theta), np.cos(2 * theta)
    return (a[0] * s2 + a[1] * c2 + a[2]) / (a[3] * s2 + a[4] * c2 + a[5])


def test_range_coefficients_reproduce_gain() -> None:
    """ram.range_coefficients give the gain at random bearings (1e-12 relative), 200 problems."""
    rng = np.random.default_rng(6000)
    for _ in range(200):
        problem = hard_problem(rng, RANGE)
        theta = rng.uniform(-math.pi, math.pi, 50)
        points = problem.d_o * np.stack([np.cos(theta), np.sin(theta)], axis=1)
        gain = problem.gain(points)
        # 1e-12 relative to the largest gain (a gain near zero is a difference of large terms).
        np.testing.assert_allclose(
            range_gain_from_coefficients(ram.range_coefficients(problem), theta), gain,
            rtol=0, atol=1e-12 * np.max(gain))


def test_printed_range_coefficients_are_typos() -> None:
    """The paper's printed a1..a3 (d_o^4, unsquared p5 and p6 in a2) do not give the gain."""
    rng = np.random.default_rng(6001)
    P = np.array([[0.04, 0.01, 0.003], [0.01, 0.02, -0.002], [0.003, -0.002, 0.01]])
    problem = Problem(P, np.array([2.0, 1.5]), 0.5, 0.1, RANGE)
    p1, p2, p4, p5, p6 = P[0, 0], P[1, 1], P[0, 1], P[0, 2], P[1, 2]
    d4 = problem.d_o ** 4
    printed = (p1 * p4 + p2 * p4 + d4 * p5 * p6,
               (p1 ** 2 - p2 ** 2 + d4 * p5 - d4 * p6) / 2,
               (p1 ** 2 + p2 ** 2 + 2 * p4 ** 2 + d4 * p5 ** 2 + d4 * p6 ** 2) / 2,
               p4, (p1 - p2) / 2, (p1 + p2) / 2 + problem.R)
    theta = rng.uniform(-math.pi, math.pi, 50)
    points = problem.d_o * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    exact = problem.gain(points)
    # The corrected coefficients agree to 1e-12; the printed ones are off by more than 1e-3.
    np.testing.assert_allclose(
        range_gain_from_coefficients(ram.range_coefficients(problem), theta), exact, rtol=1e-12)
    error = np.abs(range_gain_from_coefficients(printed, theta) / exact - 1)
    assert np.max(error) > 1e-3


# --- bearing RAM polynomials ---------------------------------------------------------------------
def homogeneous(poly: np.ndarray, c: float, s: float) -> float:
    """Value of a homogeneous polynomial whose coefficient k multiplies c^(n-k) s^k."""
    n = len(poly) - 1
    return float(sum(poly[k] * c ** (n - k) * s ** k for k in range(n + 1)))


def in_d(coefficients: list[np.ndarray], d: float, c: float, s: float) -> tuple[float, float]:
    """Value of sum_i coefficients[i](c, s) d^(n-i), and the sum of the terms' magnitudes."""
    n = len(coefficients) - 1
    terms = [homogeneous(poly, c, s) * d ** (n - i) for i, poly in enumerate(coefficients)]
    return sum(terms), sum(abs(t) for t in terms)


def five_point(f: object) -> float:
    """Fourth-order central difference of f at 0 with unit step: (f(-2) - 8 f(-1) + ...) / 12."""
    return (f(-2.0) - 8.0 * f(-1.0) + 8.0 * f(1.0) - f(2.0)) / 12.0


def moderate_bearing_problem(rng: np.random.Generator) -> Problem:
    """A bearing problem with condition number below 1e3 (for finite-difference checks)."""
    p_o, r = random_geometry(rng)
    return Problem(hard_covariance(rng, 3.0), p_o, r, random_sigma(rng, BEARING), BEARING)


def test_kkt_polynomials_match_polar_gradient() -> None:
    """F_d = 2 zeta(d) and F_t = gamma(d) satisfy d gain / dd = F_d / D^2 and
    d gain / dt = F_t / D^2, D = d^2 h'Nh, at random polar points (finite differences)."""
    rng = np.random.default_rng(7000)
    for _ in range(100):
        problem = moderate_bearing_problem(rng)
        zeta, gamma = ram.kkt_polynomials(problem)
        assert [len(z) - 1 for z in zeta] == [1, 2, 3]      # homogeneous degree 3 overall
        assert [len(g) - 1 for g in gamma] == [1, 2, 3, 4]  # homogeneous degree 4 overall
        for _ in range(10):
            rho, angle = problem.r * math.sqrt(rng.uniform()), rng.uniform(-math.pi, math.pi)
            p = problem.p_o + rho * np.array([math.cos(angle), math.sin(angle)])
            d, t = math.hypot(*p), math.atan2(p[1], p[0])
            c, s = math.cos(t), math.sin(t)
            v = np.array([-s, c, -d])
            D = float(v @ problem.N @ v)

            def gain(dd: float, tt: float) -> float:
                return float(problem.gain(dd * np.array([math.cos(tt), math.sin(tt)]))[0])

            step_d, step_t = 1e-3 * d, 1e-3
            grad_d = five_point(lambda e: gain(d + e * step_d, t)) / step_d
            grad_t = five_point(lambda e: gain(d, t + e * step_t)) / step_t
            F_d = 2 * in_d(zeta, d, c, s)[0]
            F_t = in_d(gamma, d, c, s)[0]
            scale = abs(grad_d) * d + abs(grad_t)
            # 1e-6 relative to the gradient's size (five-point differences with step 1e-3:
            # truncation ~1e-12, rounding ~1e-13 of the gain).
            assert abs(F_d / D ** 2 - grad_d) * d <= 1e-6 * scale
            assert abs(F_t / D ** 2 - grad_t) <= 1e-6 * scale


def test_active_polynomial_vanishes_at_rq_boundary_optimum() -> None:
    """Q (eq. 41) and the homogenised g vanish at RQ's boundary optima, not elsewhere."""
    rng = np.random.default_rng(7100)
    checked = 0
    while checked < 100:
        problem = hard_problem(rng, BEARING)
        solution = solve_problem(problem, 'rq')
        if solution.details['interior']:
            continue
        checked += 1
        q, g = ram.active_polynomials(problem)
        assert [len(x) - 1 for x in q] == [1, 2, 3, 4, 5] and len(g) == 3
        d, t = math.hypot(*solution.p), math.atan2(solution.p[1], solution.p[0])
        value, size = in_d(q, d, math.cos(t), math.sin(t))
        # 1e-9 relative residual (RQ's angle is Newton-polished; observed below 1e-12).
        assert abs(value) <= 1e-9 * size, abs(value) / size
        value, size = in_d(g, d, math.cos(t), math.sin(t))
        assert abs(value) <= 1e-9 * size      # on the circle, 1e-9 relative
        # Control: at another boundary point Q does not vanish (1e-4 relative).
        offset = solution.p - problem.p_o
        turn = math.atan2(offset[1], offset[0]) + 0.5
        other = problem.p_o + problem.r * np.array([math.cos(turn), math.sin(turn)])
        d_other, t_other = math.hypot(*other), math.atan2(other[1], other[0])
        value, size = in_d(q, d_other, math.cos(t_other), math.sin(t_other))
        assert abs(value) > 1e-4 * size


def test_boundary_wronskian_degree_four_harmonics_cancel() -> None:
    """On the q-circle the Wronskian of the gain's numerator and denominator has no k = +-4
    harmonics; common.fourier is checked against direct evaluation first."""
    rng = np.random.default_rng(7200)
    for _ in range(200):
        problem = hard_problem(rng, BEARING)
        centre, rho = problem.q_disc()
        a = np.array([centre[0], centre[1], -1.0])
        t = rng.uniform(-math.pi, math.pi, 20)
        k = np.arange(-2, 3)
        spectra = []
        for X, entries in zip((problem.M, problem.N), problem.forms):
            k0, k1r, k1i, k2r, k2i = common.fourier(entries, centre[0], centre[1], rho)
            k1, k2 = k1r + 1j * k1i, k2r + 1j * k2i
            coefficients = np.array([np.conj(k2), np.conj(k1), k0, k1, k2])
            h = a + rho * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
            direct = np.einsum('ij,jk,ik->i', h, X, h)
            series = (np.exp(1j * np.outer(t, k)) @ coefficients).real
            # 1e-10 relative to the largest term |X| |h|^2 (mixed-unit, ill-conditioned X).
            bound = 1e-10 * np.abs(X).max() * np.max(np.sum(np.abs(h), axis=1)) ** 2
            assert np.max(np.abs(series - direct)) <= bound
            spectra.append(coefficients)
        num, den = spectra
        wronskian = np.convolve(1j * k * num, den) - np.convolve(num, 1j * k * den)
        scale = np.max(np.abs(np.convolve(np.abs(k * num), np.abs(den))))
        # 1e-13 relative to the size of the products: the k = +-4 harmonics cancel exactly.
        assert abs(wronskian[0]) <= 1e-13 * scale and abs(wronskian[-1]) <= 1e-13 * scale
        # 1e-14 relative: boundary_stationarity is the remaining k = -3..3 part.
        np.testing.assert_allclose(common.boundary_stationarity(problem), wronskian[1:-1],
                                   rtol=0, atol=1e-14 * scale)


def test_eliminated_polynomials_exact_degrees_with_sympy() -> None:
    """Exact rational elimination (sympy) gives S_u of degree 7 and S_c of degree 6 in
    sigma = sin^2 t, and RAM's sigma roots match the exact real roots in [0, 1] to 1e-8."""
    sp = pytest.importorskip('sympy')
    half, quarter, eighth = sp.Rational(1, 2), sp.Rational(1, 4), sp.Rational(1, 8)
    P = sp.Matrix([[half, eighth, eighth / 2], [eighth, quarter, -eighth / 4],
                   [eighth / 2, -eighth / 4, eighth]])
    x_o, y_o, r, sigma = sp.Integer(3), sp.Integer(4), sp.Integer(1), eighth   # d_o = 5
    d_o2 = x_o ** 2 + y_o ** 2
    M = P * sp.diag(1, 1, d_o2) * P
    N = P + sp.diag(0, 0, sigma ** 2)
    d, c, s, sg = sp.symbols('d c s sigma')
    v = sp.Matrix([-s, c, -d])                              # d^2 h, h = [q, -1]
    num, den = sp.expand((v.T * M * v)[0]), sp.expand((v.T * N * v)[0])

    def d_t(e: sp.Expr) -> sp.Expr:                         # d/dt with c = cos t, s = sin t
        return sp.expand(-s * sp.diff(e, c) + c * sp.diff(e, s))

    F_d = sp.expand(sp.diff(num, d) * den - num * sp.diff(den, d))
    F_t = sp.expand(d_t(num) * den - num * d_t(den))
    g = sp.expand(d ** 2 - 2 * d * (x_o * c + y_o * s) + (d_o2 - r ** 2) * (c ** 2 + s ** 2))
    Q = sp.expand(F_t * sp.diff(g, d) - F_d * d_t(g))
    assert sp.Poly(F_d, d).degree() == 2 and sp.Poly(F_t, d).degree() == 3

    def eliminate(f: sp.Expr, h: sp.Expr) -> sp.Poly:
        resultant = sp.resultant(f, h, d)
        in_s = sp.Poly(sp.resultant(resultant, c ** 2 + s ** 2 - 1, c), s)
        assert all(m[0] % 2 == 0 for m in in_s.monoms())   # only even powers of sin t
        return sp.Poly(sp.expand(in_s.as_expr().subs(s, sp.sqrt(sg))), sg)

    problem = Problem(np.array(P.tolist(), dtype=float), np.array([3.0, 4.0]), 1.0, 0.125,
                      BEARING)
    for exact, polynomials, degree in (
            (eliminate(F_d, F_t), ram.kkt_polynomials(problem), 7),
            (eliminate(Q, g), ram.active_polynomials(problem), 6)):
        assert exact.degree() == degree
        ram_degree = ram.INACTIVE_DEGREE if degree == 7 else ram.ACTIVE_DEGREE
        assert ram_degree == degree
        series, aliasing = ram.eliminated_polynomial(*polynomials, degree)
        assert aliasing < 1e-8
        exact_roots = sorted(float(x) for x in exact.real_roots() if 0 <= x <= 1)
        assert exact_roots, 'the test problem should have real roots in [0, 1]'
        # 1e-8 absolute in sigma = sin^2 t.
        np.testing.assert_allclose(np.sort(ram.sigma_roots(series)), exact_roots, rtol=0,
                                   atol=1e-8)
        # The whole polynomial agrees up to a constant factor (1e-8 relative).
        samples = np.linspace(0.05, 0.95, 7)
        ratio = [float(exact.eval(sp.Rational(x).limit_denominator(10 ** 6)))
                 / float(np.polynomial.chebyshev.chebval(
                     2 * float(sp.Rational(x).limit_denominator(10 ** 6)) - 1, series))
                 for x in samples]
        np.testing.assert_allclose(ratio, ratio[0], rtol=1e-8)


def test_forced_failure_raises_or_falls_back_to_rq() -> None:
    """On an ill-conditioned problem (cond ~1e8) whose polynomial route fails, fallback=False
    raises FloatingPointError and the default returns RQ's point with fallback == 'rq'."""
    rng = np.random.default_rng(8000)
    for _ in range(300):
        p_o, r = random_geometry(rng)
        Q = random_rotation(rng)
        P = Q @ np.diag([1.0, 10.0 ** -rng.uniform(0.0, 8.0), 1e-8]) @ Q.T
        D = np.diag(10.0 ** rng.uniform(-1.0, 1.0, 3))
        P = D @ P @ D * 10.0 ** rng.uniform(-4.0, 0.0)
        problem = Problem(0.5 * (P + P.T), p_o, r, random_sigma(rng, BEARING), BEARING)
        try:
            ram_optimum(problem, fallback=False)
        except FloatingPointError:
            break
    else:
        pytest.fail('no problem whose RAM route fails was found in 300 seeded draws')
    with pytest.raises(FloatingPointError):
        solve_problem(problem, 'ram', fallback=False)
    solution = solve_problem(problem, 'ram')
    rq_solution = solve_problem(problem, 'rq')
    assert solution.fallback == 'rq'
    assert solution.details.get('reason')
    assert np.array_equal(solution.p, rq_solution.p)
    assert rq_solution.fallback is None


# --- baselines -----------------------------------------------------------------------------------
def test_mtf_returns_slot() -> None:
    """MTF always returns p_o exactly."""
    rng = np.random.default_rng(9000)
    for kind in KINDS:
        for _ in range(20):
            problem = hard_problem(rng, kind)
            solution = solve_problem(problem, 'mtf')
            assert np.array_equal(solution.p, problem.p_o)
            assert solution.cost == solution.cost_at_slot


def test_crm_uniform_in_disc() -> None:
    """CRM: 20000 seeded draws lie in the disc; mean radius^2 / r^2 = 0.5 +- 0.01 (5 standard
    errors) and the mean unit direction is 0 +- 0.03; the same seed repeats the draw."""
    problem = Problem(np.diag([0.01, 0.02, 0.003]), np.array([1.0, -2.0]), 0.4, 0.05, RANGE)
    rng = np.random.default_rng(9100)
    crm = make_strategy('crm')
    points = np.array([crm.plan(problem, PlanContext(rng=rng)).p for _ in range(20000)])
    offsets = points - problem.p_o
    radius2 = np.sum(offsets ** 2, axis=1) / problem.r ** 2
    assert np.all(radius2 <= 1 + 1e-12)                       # in the disc up to rounding
    assert abs(np.mean(radius2) - 0.5) < 0.01
    units = offsets / np.sqrt(radius2 * problem.r ** 2)[:, None]
    assert np.all(np.abs(np.mean(units, axis=0)) < 0.03)
    first = solve_problem(problem, 'crm', rng=np.random.default_rng(5)).p
    assert np.array_equal(first, solve_problem(problem, 'crm', rng=np.random.default_rng(5)).p)


def test_mme_alternates_perpendicular_sides() -> None:
    """MME steps r sideways, perpendicular to p_o, alternating with the step parity; it
    returns p_o when the leader does not drive straight, unless told to step while it turns."""
    rng = np.random.default_rng(9200)
    for _ in range(50):
        problem = hard_problem(rng, BEARING)
        offsets = [solve_problem(problem, 'mme', context=PlanContext(step=step)).p - problem.p_o
                   for step in range(4)]
        for offset in offsets:
            # 1e-12 relative: the step length is r and the offset is perpendicular to p_o.
            assert math.hypot(*offset) == pytest.approx(problem.r, rel=1e-12)
            assert abs(float(offset @ problem.p_o)) <= 1e-12 * problem.r * problem.d_o
        np.testing.assert_allclose(offsets[1], -offsets[0], rtol=0, atol=1e-12 * problem.r)
        np.testing.assert_array_equal(offsets[2], offsets[0])
        np.testing.assert_array_equal(offsets[3], offsets[1])
        assert solve_problem(problem, 'mme', context=PlanContext(step=0)).on_boundary
        turning = PlanContext(step=1, leader_velocities=((1.0, 0.1), (1.0, 0.1)))
        straight = solve_problem(problem, 'mme', context=turning)
        assert np.array_equal(straight.p, problem.p_o)
        sideways = solve_problem(problem, 'mme', context=turning, while_turning=True)
        np.testing.assert_allclose(sideways.p - problem.p_o, offsets[1], rtol=0,
                                   atol=1e-12 * problem.r)


def test_mme_amplitude_and_period_options() -> None:
    """MME's options: amplitude 0.4 steps 0.4 r sideways; period 3 keeps a side for three
    steps (steps 0-2 one side, 3-5 the other, 6 the first again); the defaults are 1 and 1,
    and the slot while the leader turns."""
    assert make_strategy('mme').settings == {'amplitude': 1.0, 'period': 1,
                                             'while_turning': False}
    rng = np.random.default_rng(9201)
    for _ in range(20):
        problem = hard_problem(rng, RANGE)
        offsets = [solve_problem(problem, 'mme', context=PlanContext(step=step),
                                 amplitude=0.4, period=3).p - problem.p_o for step in range(7)]
        for offset in offsets:
            # 1e-12 relative: the step length is 0.4 r, perpendicular to p_o.
            assert math.hypot(*offset) == pytest.approx(0.4 * problem.r, rel=1e-12)
        for step in (1, 2, 6):
            np.testing.assert_array_equal(offsets[step], offsets[0])
        for step in (3, 4, 5):
            np.testing.assert_allclose(offsets[step], -offsets[0], rtol=0,
                                       atol=1e-12 * problem.r)
    with pytest.raises(ValueError, match='mme'):
        make_strategy('mme', period=0)


@pytest.mark.parametrize('cell', [0.5, 0.1, 0.03])
def test_gbs_grid(cell: float) -> None:
    """GBS's grid has spacing cell * r, contains p_o, lies in the disc, has the expected number
    of points, and GBS returns its best point."""
    problem = Problem(np.diag([0.01, 0.02, 0.003]), np.array([1.5, 0.5]), 0.4, 0.01, BEARING)
    baselines._GRID_CACHE.clear()
    points = baselines.grid_for(BEARING, problem.slot, problem.r, cell).points
    offsets = (points - problem.p_o) / (problem.r * cell)
    # Lattice coordinates are integers (1e-9 absolute) and the lattice includes p_o itself.
    np.testing.assert_allclose(offsets, np.round(offsets), rtol=0, atol=1e-9)
    assert np.any(np.all(np.round(offsets) == 0, axis=1))
    assert np.all(np.hypot(*(points - problem.p_o).T) <= problem.r * (1 + 1e-12))
    n = int(math.floor(1 / cell))
    expected = sum(1 for i in range(-n, n + 1) for j in range(-n, n + 1)
                   if (i * cell) ** 2 + (j * cell) ** 2 <= 1 + 1e-12)
    assert len(points) == expected
    solution = solve_problem(problem, 'gbs', cell=cell)
    assert solution.candidates == expected
    assert solution.cost == pytest.approx(float(np.min(problem.cost(points))), rel=1e-14)


@pytest.mark.parametrize('cell', [0.0, -0.1, 1.5, math.nan, 1e-4])
def test_gbs_rejects_bad_cell(cell: float) -> None:
    """GBS rejects a cell outside [0.002, 1] (smaller cells need gigabytes) with a ValueError
    naming the option."""
    problem = Problem(np.diag([0.01, 0.02, 0.003]), np.array([1.5, 0.5]), 0.4, 0.01, RANGE)
    with pytest.raises(ValueError, match='cell'):
        solve_problem(problem, 'gbs', cell=cell)
