"""The derivation of docs/range_bearing.md, checked with sympy and against brute force."""
from __future__ import annotations

import math

import numpy as np
import pytest

from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.strategies.stacked import L2_BEARING, L2_RANGE, posterior_terms

SEED = 260


def random_problem(rng: np.random.Generator) -> StackedProblem:
    """A moderate problem (condition <= 1e4, slot 0.5-10 m, r 5-30 %, the bench's noises)."""
    q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    P = (q * 10.0 ** -rng.uniform(0.0, 4.0, 3)) @ q.T * 10.0 ** rng.uniform(-4.0, 0.0)
    d_o, theta = rng.uniform(0.5, 10.0), rng.uniform(-math.pi, math.pi)
    return StackedProblem(0.5 * (P + P.T), [d_o * math.cos(theta), d_o * math.sin(theta)],
                          d_o * rng.uniform(0.05, 0.3), rng.uniform(0.01, 0.5),
                          rng.uniform(0.002, 0.1))


def test_symbolic_gain_rows_and_inversion_identity() -> None:
    """sympy: tr(S^-1 T) = (t00 s11 - 2 t01 s01 + t11 s00) / det S for symmetric 2 x 2 S, T;
    the derivatives of the xy parts of h_d = p/|p| and h_beta = (-y, x)/|p|^2 used by the
    gradient; |p/|p|^2 - c/|c|^2|^2 = |p - c|^2 / (|p|^2 |c|^2) exactly."""
    sp = pytest.importorskip('sympy')
    s00, s01, s11, t00, t01, t11 = sp.symbols('s00 s01 s11 t00 t01 t11', real=True)
    S, T = sp.Matrix([[s00, s01], [s01, s11]]), sp.Matrix([[t00, t01], [t01, t11]])
    assert sp.simplify((S.inv() * T).trace() - (t00 * s11 - 2 * t01 * s01 + t11 * s00)
                       / (s00 * s11 - s01 ** 2)) == 0
    x, y, a, b = sp.symbols('x y a b', real=True)
    d2 = x ** 2 + y ** 2
    h_d = sp.Matrix([x, y]) / sp.sqrt(d2)
    h_b = sp.Matrix([-y, x]) / d2
    claimed = [(h_d, x, sp.Matrix([y ** 2, -x * y]) / d2 ** sp.Rational(3, 2)),
               (h_d, y, sp.Matrix([-x * y, x ** 2]) / d2 ** sp.Rational(3, 2)),
               (h_b, x, sp.Matrix([2 * x * y, y ** 2 - x ** 2]) / d2 ** 2),
               (h_b, y, sp.Matrix([y ** 2 - x ** 2, -2 * x * y]) / d2 ** 2)]
    for h, var, value in claimed:
        assert sp.simplify(h.diff(var) - value) == sp.zeros(2, 1)
    p, c = sp.Matrix([x, y]), sp.Matrix([a, b])
    lhs = (p / p.dot(p) - c / c.dot(c)).dot(p / p.dot(p) - c / c.dot(c))
    assert sp.simplify(lhs - (p - c).dot(p - c) / (p.dot(p) * c.dot(c))) == 0


def test_second_derivative_constants_by_sympy() -> None:
    """sympy, at p = (d, 0) (the rows are rotation-equivariant) and v = (cos a, sin a):
    |D^2 h_d [v, v]|^2 d^4 = sin^2 a (4 - 3 sin^2 a), whose largest value is 4/3 (L2_RANGE^2),
    and |D^2 (p / |p|^2) [v, v]|^2 d^6 = 4 (L2_BEARING^2) in every direction."""
    sp = pytest.importorskip('sympy')
    t, a, d = sp.symbols('t a d', positive=True)
    q = sp.Matrix([d + t * sp.cos(a), t * sp.sin(a)])
    norm2 = q.dot(q)
    for row, power, expected in ((q / sp.sqrt(norm2), 4, 4 * sp.sin(a) ** 2 - 3 * sp.sin(a) ** 4),
                                 (q / norm2, 6, sp.Integer(4))):
        second = sp.diff(row, t, 2).subs(t, 0)
        assert sp.simplify(sp.expand_trig(second.dot(second) * d ** power - expected)) == 0
    s2 = sp.symbols('s2')
    assert sp.maximum(4 * s2 - 3 * s2 ** 2, s2, sp.Interval(0, 1)) == sp.Rational(4, 3)
    assert math.isclose(L2_RANGE ** 2, 4 / 3) and L2_BEARING == 2.0


def test_second_derivative_bounds_hold() -> None:
    """|D^2 h_d [v, v]| <= (2/sqrt 3) |v|^2 / d^2 and |D^2 h_beta [v, v]| <= 2 |v|^2 / d^3 (the
    solver's constants L2_RANGE, L2_BEARING) at 2000 random points and unit directions, by
    central second differences (step 1e-4 d, agreement 1e-5 relative); the largest ratios found
    come within 1 % of the constants, so the bounds are tight."""
    rng = np.random.default_rng(SEED)
    worst = [0.0, 0.0]
    for _ in range(2000):
        d, theta, phi = rng.uniform(0.1, 10.0), rng.uniform(-math.pi, math.pi), \
            rng.uniform(-math.pi, math.pi)
        p = d * np.array([math.cos(theta), math.sin(theta)])
        v = np.array([math.cos(phi), math.sin(phi)])
        step = 1e-4 * d
        for k, (h, power) in enumerate(((lambda q: q / np.hypot(*q), 2),
                                        (lambda q: np.array([-q[1], q[0]]) / (q @ q), 3))):
            second = (h(p + step * v) - 2 * h(p) + h(p - step * v)) / step ** 2
            worst[k] = max(worst[k], float(np.hypot(*second)) * d ** power)
    assert worst[0] <= L2_RANGE * (1 + 1e-5) and worst[1] <= L2_BEARING * (1 + 1e-5)
    assert worst[0] > 0.99 * L2_RANGE and worst[1] > 0.99 * L2_BEARING    # tight


def test_gradient_and_convexity_of_the_cost() -> None:
    """The gradient of :func:`posterior_terms` equals central differences of the cost (1e-3
    relative, or 1e-7 of cost / |p_o|), and the cost as a function of the information I,
    F(I) = tr(W (P^-1 + I)^-1 W), lies above its tangent (the convexity the bounds rest on)
    at 500 random pairs."""
    rng = np.random.default_rng(SEED)
    for _ in range(200):
        problem = random_problem(rng)
        point = np.array(problem.slot) + rng.uniform(-problem.r, problem.r, 2) * 0.7
        _, grad, _ = posterior_terms(problem, point[:1], point[1:])
        step = 1e-6 * problem.d_o
        numeric = [(problem.cost(point + e) - problem.cost(point - e)) / (2 * step)
                   for e in (np.array([step, 0.0]), np.array([0.0, step]))]
        scale = problem.cost(point) / problem.d_o          # m^2 per m
        np.testing.assert_allclose(grad[:, 0], numeric, rtol=1e-3, atol=1e-7 * scale)
    for _ in range(500):
        problem = random_problem(rng)
        w2 = np.diag(problem.w ** 2)
        Lam = np.linalg.inv(problem.P)

        def F(info: np.ndarray) -> float:
            return float(np.trace(w2 @ np.linalg.inv(Lam + info)))
        a, b = (rng.standard_normal((3, 2)) for _ in range(2))
        I_a, I_b = a @ a.T * rng.uniform(0, 100), b @ b.T * rng.uniform(0, 100)
        X = np.linalg.inv(Lam + I_a)
        G = -X @ w2 @ X
        assert F(I_b) >= F(I_a) + np.sum(G * (I_b - I_a)) - 1e-9 * F(I_a)
