"""Plain-Python linear algebra on 3x3 symmetric matrices: the per-step fast path.

numpy spends about a microsecond per call on arrays this small; the planners call these dozens
of times per step, so they work on Python floats. Checked against numpy in the tests.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from fractions import Fraction

#: Unit roundoff of IEEE double precision.
EPS = 2.0 ** -53


def top_eigenpair3(C: Sequence[Sequence[float]]) -> tuple[float, list[float]]:
    """Largest eigenvalue of a symmetric 3x3 matrix (rows C) and a unit eigenvector.

    Eigenvalue: the trigonometric solution of the characteristic cubic (Smith 1961): with
    q = tr C / 3, p = sqrt(tr((C - qI)^2) / 6) and B = (C - qI) / p, the largest eigenvalue is
    q + 2 p cos(acos(det(B) / 2) / 3); its absolute error is a few units of roundoff of |C|.
    Eigenvector: the longest cross product of two rows of C - lambda I (they span the
    orthogonal complement of the eigenvector when lambda is simple). The eigenvalue is then
    re-read as the Rayleigh quotient v'Cv of that unit vector: the cubic's solution loses
    precision near a double root (acos near +-1), the quotient only quadratically in the
    vector's error.
    """
    # on C / |C|max (eigenpairs scale with C): at scales near 1e+-100 the cube of the cubic's
    # spread and the squares of the cross products below under- or overflowed
    size = max(abs(C[0][0]), abs(C[0][1]), abs(C[0][2]), abs(C[1][1]), abs(C[1][2]),
               abs(C[2][2]))
    if size == 0.0:
        return 0.0, [1.0, 0.0, 0.0]
    c00, c01, c02 = C[0][0] / size, C[0][1] / size, C[0][2] / size
    c11, c12, c22 = C[1][1] / size, C[1][2] / size, C[2][2] / size
    q = (c00 + c11 + c22) / 3.0
    a00, a11, a22 = c00 - q, c11 - q, c22 - q
    p = math.sqrt((a00 * a00 + a11 * a11 + a22 * a22
                   + 2.0 * (c01 * c01 + c02 * c02 + c12 * c12)) / 6.0)
    if p == 0.0:
        return q * size, [1.0, 0.0, 0.0]
    det = (a00 * (a11 * a22 - c12 * c12) - c01 * (c01 * a22 - c12 * c02)
           + c02 * (c01 * c12 - a11 * c02)) / (p * p * p)
    value = q + 2.0 * p * math.cos(math.acos(max(-1.0, min(1.0, 0.5 * det))) / 3.0)
    r0 = (c00 - value, c01, c02)
    r1 = (c01, c11 - value, c12)
    r2 = (c02, c12, c22 - value)
    best, best_norm = [1.0, 0.0, 0.0], 0.0
    for a, b in ((r0, r1), (r0, r2), (r1, r2)):
        v = [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
        norm = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
        if norm > best_norm:
            best, best_norm = v, norm
    norms = [a[0] * a[0] + a[1] * a[1] + a[2] * a[2] for a in (r0, r1, r2)]
    row_norm = max(norms)
    if best_norm <= 1e-24 * row_norm * row_norm:
        row = (r0, r1, r2)[norms.index(row_norm)]
        # C - lambda I has rank <= 1 (a double top eigenvalue): any vector orthogonal to its
        # row is an eigenvector; take the cross product with the axis least along the row
        axis = min(range(3), key=lambda i: abs(row[i]))
        e = [1.0 if i == axis else 0.0 for i in range(3)]
        best = [row[1] * e[2] - row[2] * e[1], row[2] * e[0] - row[0] * e[2],
                row[0] * e[1] - row[1] * e[0]]
        best_norm = best[0] * best[0] + best[1] * best[1] + best[2] * best[2]
    if best_norm == 0.0:
        return value * size, [1.0, 0.0, 0.0]
    scale = 1.0 / math.sqrt(best_norm)
    v0, v1, v2 = best[0] * scale, best[1] * scale, best[2] * scale
    rayleigh = (c00 * v0 * v0 + c11 * v1 * v1 + c22 * v2 * v2
                + 2.0 * (c01 * v0 * v1 + c02 * v0 * v2 + c12 * v1 * v2))
    return rayleigh * size, [v0, v1, v2]


def positive_definite_entries(entries: Sequence[float]) -> bool:
    """True when the symmetric 3x3 matrix with these six entries has positive LDL' pivots."""
    a00, a01, a02, a11, a12, a22 = entries
    if not a00 > 0.0:
        return False
    l10, l20 = a01 / a00, a02 / a00
    d1 = a11 - l10 * a01
    if not d1 > 0.0:
        return False
    b12 = a12 - l20 * a01
    return a22 - l20 * a02 - b12 * b12 / d1 > 0.0


def positive_definite_exactly(entries: Sequence[float]) -> bool:
    """True when the symmetric 3x3 matrix with these six entries (floats, taken as exact) is
    positive definite: the LDL' pivots in floating point where they clear their rounding with
    room, else its leading minors in exact rational arithmetic (Sylvester).

    d1 = a11 - a01^2/a00 carries a few units of a11's rounding, and d2 that of a22 plus
    4 u a22 sqrt(a11 / d1) from b12^2 / d1 (|b12| <= sqrt(d1 a22)); the margins below are 10x
    those bounds. A float check alone accepted P with exact determinant below zero."""
    a00, a01, a02, a11, a12, a22 = entries
    if not a00 > 0.0:
        return False
    l10, l20 = a01 / a00, a02 / a00
    d1 = a11 - l10 * a01
    if d1 > 1e-12 * a11:
        b12 = a12 - l20 * a01
        d2 = a22 - l20 * a02 - b12 * b12 / d1
        if d2 > 1e-14 * a22 * (2.0 + math.sqrt(a11 / d1)):
            return True
    e00, e01, e02, e11, e12, e22 = map(Fraction, entries)
    return (e00 * e11 - e01 * e01 > 0 and e00 * (e11 * e22 - e12 * e12)
            - e01 * (e01 * e22 - e12 * e02) + e02 * (e01 * e12 - e11 * e02) > 0)
