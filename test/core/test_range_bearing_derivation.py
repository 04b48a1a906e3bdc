"""The derivation of docs/range_bearing.md, checked with sympy and against brute force."""
from __future__ import annotations

import math

import numpy as np
import pytest


SEED = 260


def test_symbolic_gain_formula() -> None:
    """sympy: tr(S^-1 T) = (t00 s11 - 2 t01 s01 + t11 s00) / det S for symmetric 2 x 2 S, T
    (StackedProblem.gain_at)."""
    sp = pytest.importorskip('sympy')
    s00, s01, s11, t00, t01, t11 = sp.symbols('s00 s01 s11 t00 t01 t11', real=True)
    S, T = sp.Matrix([[s00, s01], [s01, s11]]), sp.Matrix([[t00, t01], [t01, t11]])
    assert sp.simplify((S.inv() * T).trace() - (t00 * s11 - 2 * t01 * s01 + t11 * s00)
                       / (s00 * s11 - s01 ** 2)) == 0


def test_lines_through_the_leader_by_sympy() -> None:
    """sympy, for a symbolic P (3 x 3), W^2 = diag(1, 1, w22) and the rows h_d = (c, s, 0),
    h_beta = u (-s, c, 0) - e3 of the line at angle theta (polar.py): det S and
    C = tr(W P_post W) det S are polynomials of degree 2 in u whose coefficients are
    polynomials of degree 4 in c, s but trigonometric polynomials of degree at most 2 in theta;
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
    z = sp.symbols('z')
    on_circle = {c: (z + 1 / z) / 2, s: (z - 1 / z) / (2 * sp.I)}     # z = exp(i theta)
    for form in (D, C):
        poly = sp.Poly(form, u)
        assert poly.degree() == 2
        for coefficient in poly.all_coeffs():
            assert sp.Poly(coefficient, c, s).total_degree() <= 4
            laurent = sp.Poly(sp.expand(coefficient.subs(on_circle) * z ** 4), z)
            assert {k for (k,) in laurent.monoms()} <= {2, 3, 4, 5, 6}     # harmonics <= 2
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
