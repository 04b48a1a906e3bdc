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


def test_lines_through_the_leader_by_sympy() -> None:
    """sympy, for a symbolic P (3 x 3), W^2 = diag(1, 1, w22) and the rows h_d = (c, s, 0),
    h_beta = u (-s, c, 0) - e3 of the line at angle theta (polar.py): det S and
    C = tr(W P_post W) det S are polynomials of degree 2 in u whose coefficients are
    trigonometric polynomials of degree at most 4 (in c, s: homogeneous after c^2 + s^2 = 1);
    on u = (1 + kappa w) / ((1 - kappa w) sqrt k) the chord |p - p_o|^2 <= r^2 becomes
    (g2 w^2 + g0) / sqrt k <= 0 times a positive factor, with g2 = kappa^2 (a + sqrt k),
    g0 = sqrt k - a, a = |p_o| cos delta, when kappa = 2 r / (sqrt(d + r) + sqrt(d - r))^2;
    and the resultant of two quadratics is (l2 g0 - l0 g2)^2 + l1^2 g2 g0 when g1 = 0."""
    sp = pytest.importorskip('sympy')
    c, s, u, w22, r_d, r_b = sp.symbols('c s u w22 r_d r_b', real=True)
    p = sp.symbols('p00 p01 p02 p11 p12 p22', real=True)
    P = sp.Matrix([[p[0], p[1], p[2]], [p[1], p[3], p[4]], [p[2], p[4], p[5]]])
    W2 = sp.diag(1, 1, w22)
    H = sp.Matrix([[c, s, 0], [-u * s, u * c, -1]])
    S = H * P * H.T + sp.diag(r_d, r_b)
    D = sp.expand(S.det())
    C = sp.expand((W2 * P).trace() * D - (S.adjugate() * H * P * W2 * P * H.T).trace())
    for form in (D, C):
        poly = sp.Poly(form, u)
        assert poly.degree() == 2
        for coefficient in poly.all_coeffs():
            assert sp.Poly(coefficient, c, s).total_degree() <= 4
    # C / D is the cost: the posterior P - P H' S^-1 H P at a numeric point
    rng = np.random.default_rng(SEED)
    q = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    P_num = (q * rng.uniform(0.1, 1.0, 3)) @ q.T
    angle, u_num, values = 0.7, 0.4, {w22: 2.0, r_d: 0.01, r_b: 0.003}
    values.update({c: math.cos(angle), s: math.sin(angle), u: u_num})
    entries = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    values.update({symbol: P_num[i, j] for symbol, (i, j) in zip(p, entries)})
    H_num = np.array([[math.cos(angle), math.sin(angle), 0.0],
                      [-u_num * math.sin(angle), u_num * math.cos(angle), -1.0]])
    S_num = H_num @ P_num @ H_num.T + np.diag([0.01, 0.003])
    posterior = P_num - P_num @ H_num.T @ np.linalg.solve(S_num, H_num @ P_num)
    cost = posterior[0, 0] + posterior[1, 1] + 2.0 * posterior[2, 2]
    assert float(C.subs(values) / D.subs(values)) == pytest.approx(cost, rel=1e-12)
    # the chord in w
    wv, d, r, delta = sp.symbols('w d r delta', positive=True)
    root_k = sp.sqrt(d ** 2 - r ** 2)
    kappa = 2 * r / (sp.sqrt(d + r) + sp.sqrt(d - r)) ** 2
    u_w = (1 + kappa * wv) / ((1 - kappa * wv) * root_k)
    a = d * sp.cos(delta)
    chord = 1 / u_w ** 2 - 2 * a / u_w + d ** 2 - r ** 2           # |p - p_o|^2 - r^2
    claimed = (kappa ** 2 * (a + root_k) * wv ** 2 + root_k - a)
    ratio = chord * u_w ** 2 * (1 - kappa * wv) ** 2 / claimed
    numeric = {wv: 0.3, d: 2.0, r: 0.7, delta: 0.2}
    assert float(ratio.subs(numeric)) > 0.0
    assert float(ratio.subs(numeric)) == pytest.approx(float(ratio.subs(
        {**numeric, wv: -0.55, delta: -0.1})), rel=1e-12)
    l2, l1, l0, g2, g0, x = sp.symbols('l2 l1 l0 g2 g0 x')
    resultant = sp.resultant(l2 * x ** 2 + l1 * x + l0, g2 * x ** 2 + g0, x)
    assert sp.expand(resultant - ((l2 * g0 - l0 * g2) ** 2 + l1 ** 2 * g2 * g0)) == 0
