"""The certified range-bearing optimum over a disc or a region, by lines through the leader.

See docs/range_bearing.md ("Over the disc: lines through the leader", "Over a reachable
set"). On the line through
the leader at angle theta (a = (c, s, 0), b = (-s, c, 0), points p = (c, s) / u, u = 1 / |p|)
the rows are exactly h_d = a and h_beta = u b - e3, so S = H P H' + R has entries of degree at
most two in u, and so has C = tr(W P_post W) det S = tr(W P W) det S - tr(adj(S) H M H'):

    cost = C / D,   C and D = det S quadratics in u,

with coefficients that are trigonometric polynomials of degree at most 2 in theta (S's 2 x 2
minors are (u, -c, -s): Cauchy-Binet). The disc's
u lie in [1 / (|p_o| + r), 1 / (|p_o| - r)]; the solver uses the projective coordinate w with
u = (1 + kappa w) / ((1 - kappa w) sqrt k), k = |p_o|^2 - r^2, which maps w = -1, 0, 1 to the
far end, the geometric middle and the near end; C and D times (1 - kappa w)^2 are quadratics
in w with balanced values. They are taken from Joseph-form costs (as the EKF computes them;
gains summed directly where the gain is the smaller part) in extended precision at
w = -1, 0, 1 on 8 lines, so they carry the rounding of the cost (or gain), not of tr(W P W),
and their Fourier series (harmonics 0..2) give them on any line. Where a bound of the gain
(:func:`gain_bound`) is below RTOL of the cost, every point is optimal to the gap: the slot.
A line of the wedge |delta| <= asin(r / |p_o|) (delta = theta - theta_o) meets the disc in the
chord
g(w) = g2 w^2 + g0 <= 0 with g2 = kappa^2 (a + sqrt k), g0 = sqrt k - a, a = |p_o| cos delta.

The solver maximises the gain shift - cost = N / D (N = shift D - C), with shift = tr(W P W)
where the measurement removes less than half of it and 0 otherwise, so that N keeps the digits of
whichever of gain and posterior is the smaller. A level G is beaten somewhere in the disc
iff some line's chord meets {w : L(w) = N - G D > 0}. As theta moves, that can change only
where that super-level interval appears or vanishes (the discriminant l1^2 - 4 l2 l0 of L
vanishes), where one of its ends crosses an end of the chord (the resultant
(l2 g0 - l0 g2)^2 + l1^2 g2 g0 of L and g vanishes), or at the wedge's edges. Both are
trigonometric polynomials in theta (degree 4 and 6): their real roots are among the complex
roots of a polynomial in exp(i theta), or of a Chebyshev interpolant over a narrow wedge.
Between consecutive roots one line decides. So the certificate for an incumbent of gain G* is:
at G = G* + margin no tested line (every root's angle, the midpoints between them, a fixed
grid of the wedge) holds a point of its chord with L > 0. A line that does is a witness: the
search refines the best line around it (a line's best point is in closed form: a stationary
point of N / D, a root of a quadratic, or an end of the chord) and tests again.

Over a region the reach disc (convex along a ray from the leader) and the safety circle (a
half-line) cut each chord to one interval, their boundaries are quadratics in w too, and the
events add their resultants with L and with each other.

The roots are floating-point eigenvalues; every root's angle is tested, spurious or not, so a
real root could hide a piece of the super-level set only where L is at the level of its own
rounding. The certificate's gap is RTOL plus ROUNDING, of the cost, plus the quadratics'
rounding (``Lines.rounding``).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.model import BEARING, RANGE
from formopt_ros.core.reach import Region
from formopt_ros.core.stacked import StackedProblem

#: Relative level above the incumbent at which the test closes (of the cost).
RTOL = 1e-10
#: Rounding margin of the quadratics and of each cost evaluation, relative to the cost, and
#: their rounding from the Joseph form's products (:func:`joseph_on_lines`: a bound of eps
#: times the products' sizes, for 3-term sums and two products) times SERIES_ROUNDING (a
#: sample's error moves harmonic 0 by at most itself and harmonics 1, 2 by twice it: 5 on a
#: line; the stencil's n2, n1, n0 by 2, 1, 1 of it: 4 for |w| <= 1).
ROUNDING = 1e-12
JOSEPH_ROUNDING = 8.0
SERIES_ROUNDING = 20.0
#: Lines the quadratics' Fourier series are taken from (more than twice their degree, 2; the
#: harmonics beyond it are their degree's self-check).
SERIES_SAMPLES = 8
#: Half-width of the wedge (rad) above which the events come from Fourier series over the
#: whole turn (EVENT_SAMPLES lines, more than twice their degree, 6), below which from
#: Chebyshev interpolants over the wedge of degree EVENT_DEGREE plus EVENT_FREQUENCY per
#: radian of half-width (a trigonometric polynomial of degree 10 over [-h, h] has Chebyshev
#: coefficients below 1e-13 of the largest beyond about 10 + 20 h).
FOURIER_WEDGE = 0.3
EVENT_SAMPLES = 16
EVENT_HARMONICS = 6
EVENT_DEGREE = 10
EVENT_FREQUENCY = 20.0
#: Largest coefficient beyond an event polynomial's degree in its Fourier series (measured:
#: at most 5e-12), and in the last two coefficients of a Chebyshev interpolant (measured: up to
#: 3e-6 on a tiny disc, rounding of the nearly constant values of a reach disc's resultants;
#: truncation would show orders of magnitude above it), relative to the largest, for its
#: roots to be trusted.
TAIL = 1e-6
TAIL_CHEBYSHEV = 1e-3
#: Roots within this distance of [-1, 1] on the imaginary axis count as real (a spurious one
#: only adds a tested line).
NEAR_REAL = 0.05
#: Lines of the first grid over the wedge, and of the fixed grid each test adds.
FIRST_GRID = 128
WEDGE_GRID = 8
#: Levels of the refinement at most, and the lines it tries a level (the bracket shrinks
#: (ZOOM_LINES - 1) / 2 times a level).
ZOOM_LEVELS = 20
ZOOM_LINES = 17
#: The refinement stops when the parabola promises less than this fraction of the margin.
REFINED = 0.01
#: Witnesses refined at most (a search beyond it is not certified).
MAX_ROUNDS = 12
#: Certificate name.
POLAR = 'polar-lines'

_HARMONICS = np.arange(3)
#: Offsets (fractions of the wedge's half-width, both signs) of the lines closing in on the
#: incumbent and, as wedge coordinates tau, on the edges (:meth:`Lines.to_test`).
_CLOSING = np.concatenate([-(10.0 ** -np.arange(1.0, 11.0)), 10.0 ** -np.arange(1.0, 11.0)])
_STENCIL = np.array([-1.0, 0.0, 1.0])


def chebyshev_nodes(degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Chebyshev-Lobatto points x_j = cos(pi j / degree) (degree + 1,) and the matrix
    (degree + 1, degree + 1) taking values there to Chebyshev coefficients."""
    j = np.arange(degree + 1)
    weights = np.full(degree + 1, 2.0 / degree)
    weights[[0, -1]] /= 2.0
    transform = np.cos(np.pi * np.outer(j, j) / degree) * weights
    transform[[0, -1]] /= 2.0
    return np.cos(np.pi * j / degree), transform


_CHEBYSHEV = {degree: chebyshev_nodes(degree) for degree in range(
    EVENT_DEGREE, EVENT_DEGREE + int(math.ceil(EVENT_FREQUENCY * FOURIER_WEDGE)) + 1)}


class Lines:
    """The lines through the leader that meet the disc of a range-bearing problem.

    Attributes:
        problem: the :class:`StackedProblem`.
        centre, half: the slot's direction and the wedge's half-angle asin(r / |p_o|) (rad).
        root_k, kappa: sqrt(|p_o|^2 - r^2) (m) and kappa of the coordinate w (module
            docstring).
        series: Fourier coefficients (6, 3) (complex, harmonics 0..2) over theta of the
            quadratics in w: n2, n1, n0 (N = (shift - cost) D, m^2 times the unit of D) and
            d2, d1, d0.
        shift: tr(W P W) or 0 (m^2, module docstring): the gains are shift - cost.
        rounding: the quadratics' rounding in the cost (m^2): SERIES_ROUNDING times the
            largest of :func:`joseph_on_lines`'s bounds on their samples.
        region: the reachable region that restricts the disc (None: the disc).
        evaluated: lines whose best point was computed.
        unresolved: the quadratics' or an event polynomial's series did not end where its
            degree says (a harmonic beyond it, or a Chebyshev tail, above TAIL of the largest
            coefficient): their roots are not trusted and no certificate is given.
    """

    def __init__(self, problem: Problem | StackedProblem, region: Region | None = None) -> None:
        self.problem = problem
        self.region = region if region is not None and region.restricts else None
        d_o, r = problem.d_o, problem.r
        self.centre = math.atan2(problem.slot[1], problem.slot[0])
        self.half = math.asin(r / d_o)
        self.root_k = math.sqrt((d_o - r) * (d_o + r))
        self.kappa = 2.0 * r / (math.sqrt(d_o + r) + math.sqrt(d_o - r)) ** 2
        theta = np.arange(SERIES_SAMPLES) * (2.0 * math.pi / SERIES_SAMPLES)
        u = np.repeat(self.u_of(_STENCIL), SERIES_SAMPLES)
        cost, gain, det, rounding = joseph_on_lines(problem, np.tile(theta, 3), u)
        weak = 2.0 * float(np.median(cost)) > problem.base_cost      # the gain is the smaller
        self.shift = problem.base_cost if weak else 0.0
        self.rounding = SERIES_ROUNDING * float(rounding.max())
        det = det * np.repeat((1.0 - self.kappa * _STENCIL) ** 2, SERIES_SAMPLES)
        rows = []
        for values in (((gain if weak else -cost) * det).astype(float), det.astype(float)):
            low, mid, high = values.reshape(3, SERIES_SAMPLES)
            rows += [0.5 * (high + low) - mid, 0.5 * (high - low), mid]
        fourier = np.fft.fft(np.stack(rows)) * (2.0 / SERIES_SAMPLES)
        series = fourier[:, :_HARMONICS.size]
        series[:, 0] *= 0.5
        self.series = series
        self.evaluated = 0
        tail = np.abs(fourier[:, _HARMONICS.size:SERIES_SAMPLES - _HARMONICS.size + 1])
        self.unresolved = bool(any(tail[group].max() > TAIL * np.abs(fourier[group]).max()
                                   for group in (slice(0, 3), slice(3, 6))))     # N, then D

    def coefficients(self, theta: np.ndarray) -> tuple[np.ndarray, ...]:
        """(n2, n1, n0, d2, d1, d0): the quadratics N and D in w on the lines at angles theta
        (n,) (rad)."""
        return tuple((self.series @ np.exp(1j * np.outer(_HARMONICS, theta))).real)

    def chord(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(w_low, w_high, g2, g0) of the lines at angles theta (n,) (rad) of the wedge: the
        chord's ends -+ R / (kappa (a + sqrt k)) and the coefficients of g(w) = g2 w^2 + g0
        (module docstring), with R^2 = (r - |p_o| sin delta)(r + |p_o| sin delta) so that
        neither lines near the tangents nor a disc close to the leader lose digits; a line
        that rounding puts just outside the wedge gets the tangent point."""
        delta = theta - self.centre
        d_o, r = self.problem.d_o, self.problem.r
        across = d_o * np.sin(delta)
        squared = (r - across) * (r + across)
        along = d_o * np.cos(delta) + self.root_k
        end = np.sqrt(np.maximum(squared, 0.0)) / (self.kappa * along)
        return -end, end, self.kappa * self.kappa * along, -squared / along

    def interval(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(w_low, w_high) of the feasible points of each line at angles theta (n,) (rad): the
        chord of the disc, cut by the region's reach disc and safety circle (each convex along
        a ray from the leader, so one interval; low > high where a line misses the region)."""
        low, high, _, _ = self.chord(theta)
        if self.region is None:
            return low, high
        near, far = self.region.safety * np.ones_like(theta), np.full(theta.size, np.inf)
        missed = np.zeros(theta.size, dtype=bool)
        if self.region.reach_active:                   # distances t along the ray
            assert self.region.centre is not None
            cx, cy = self.region.centre
            along = np.cos(theta) * cx + np.sin(theta) * cy
            across = np.cos(theta) * cy - np.sin(theta) * cx      # the centre's offset from
            radius = self.region.radius                            # the line: no cancellation
            squared = (radius - across) * (radius + across)
            root = np.sqrt(np.maximum(squared, 0.0))
            near, far = np.maximum(near, along - root), np.minimum(far, along + root)
            missed = squared < 0.0
        missed |= far <= near
        with np.errstate(divide='ignore', invalid='ignore'):
            low = np.maximum(low, self.w_of(1.0 / far))
            high = np.minimum(high, np.where(near > 0.0, self.w_of(1.0 / near), np.inf))
        return np.where(missed, np.inf, low), np.where(missed, -np.inf, high)

    def constraints(self, theta: np.ndarray) -> list[tuple[Any, Any, Any]]:
        """The region's reach and safety boundaries on the lines at angles theta (n,) as
        quadratics (q2, q1, q0) in w (the reach disc: (|c|^2 - rho^2) u^2 - 2 (c . e) u + 1
        times k (1 - kappa w)^2; the safety circle: w - w_s), trigonometric polynomials of
        degree at most one in theta."""
        out: list[tuple[Any, Any, Any]] = []
        region, kappa, k = self.region, self.kappa, self.root_k ** 2
        if region is None:
            return out
        if region.reach_active:
            assert region.centre is not None
            cx, cy = region.centre
            a = cx * cx + cy * cy - region.radius ** 2
            b = (np.cos(theta) * cx + np.sin(theta) * cy) * self.root_k
            out.append((kappa * kappa * (a + 2.0 * b + k), 2.0 * kappa * (a - k) + 0.0 * b,
                        a - 2.0 * b + k))
        if region.safety_active:
            zero = np.zeros(theta.size)
            out.append((zero, zero + 1.0, zero - self.w_of(1.0 / region.safety)))
        return out

    def best(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(best gain shift - cost (m^2), its w, its branch) over the feasible interval of each
        line at angles theta (n,) (rad): the larger of its ends (branches 0 and 1) and the
        stationary points of N / D within it (roots of a quadratic, branches 2 and 3); -inf
        where a line misses the region. The best gain is smooth along a branch; where the
        two ends swap it has a kink."""
        self.evaluated += theta.size
        n2, n1, n0, d2, d1, d0 = self.coefficients(theta)
        low, high = self.interval(theta)
        qa, qb, qc = n2 * d1 - n1 * d2, 2.0 * (n2 * d0 - n0 * d2), n1 * d0 - n0 * d1
        with np.errstate(invalid='ignore', divide='ignore'):
            q = -0.5 * (qb + np.copysign(np.sqrt(qb * qb - 4.0 * qa * qc), qb))
            w = np.stack([low, high, q / qa, qc / q])
            gain = (n2 * w * w + n1 * w + n0) / (d2 * w * w + d1 * w + d0)
        gain = np.where((w >= low) & (w <= high) & np.isfinite(gain), gain, -np.inf)
        j = np.argmax(gain, axis=0)
        pick = np.arange(theta.size)
        return gain[j, pick], w[j, pick], j

    def u_of(self, w: Any) -> Any:
        """u = 1 / |p| (1/m) at coordinates w (module docstring)."""
        return (1.0 + self.kappa * w) / ((1.0 - self.kappa * w) * self.root_k)

    def w_of(self, u: Any) -> Any:
        """The coordinate w of u = 1 / |p| (1/m; the inverse of :meth:`u_of`)."""
        scaled = u * self.root_k
        return (scaled - 1.0) / (self.kappa * (scaled + 1.0))

    def point(self, theta: float, w: float) -> tuple[float, float]:
        """The point (m) at w on the line at angle theta (rad)."""
        u = self.u_of(w)
        return math.cos(theta) / u, math.sin(theta) / u

    def angle(self, tau: np.ndarray) -> np.ndarray:
        """Line angles theta = centre + half cos(tau) (rad) of wedge coordinates tau in
        [0, pi]: a line's best gain is smooth in tau up to the wedge's edges (in theta the
        chord's ends move like the square root of the distance to an edge)."""
        return self.centre + self.half * np.cos(tau)

    def tau_of(self, theta: np.ndarray) -> np.ndarray:
        """Wedge coordinates tau (rad) of line angles theta (the inverse of :meth:`angle`,
        clipped to the wedge)."""
        offset = np.mod(theta - self.centre + math.pi, 2.0 * math.pi) - math.pi
        return np.arccos(np.clip(offset / self.half, -1.0, 1.0))

    def beaten(self, theta: np.ndarray, level: float) -> np.ndarray:
        """Whether the feasible interval of each line at angles theta (n,) (rad) holds a point
        with L = N - level D > 0, i.e. a gain above ``level`` (m^2)."""
        n2, n1, n0, d2, d1, d0 = self.coefficients(theta)
        l2, l1, l0 = n2 - level * d2, n1 - level * d1, n0 - level * d0
        low, high = self.interval(theta)
        with np.errstate(invalid='ignore', divide='ignore'):
            vertex = np.clip(-l1 / (2.0 * l2), low, high)
            ends = np.maximum((l2 * low + l1) * low + l0, (l2 * high + l1) * high + l0)
            inner = np.where(l2 < 0.0, (l2 * vertex + l1) * vertex + l0, -np.inf)
            return (np.maximum(ends, inner) > 0.0) & (low <= high)

    def events(self, level: float) -> np.ndarray:
        """Offsets from ``centre`` (rad) of the real roots in the wedge of the discriminant of
        L and of its resultant with g (module docstring): on a wide wedge from their Fourier
        series over the whole turn (the roots of polynomials in exp(i theta)), on a narrow
        one from Chebyshev interpolants over the wedge, which resolve the wedge's own scale;
        every root near the real line counts."""
        wide = self.half > FOURIER_WEDGE
        if wide:
            theta = np.arange(EVENT_SAMPLES) * (2.0 * math.pi / EVENT_SAMPLES)
        else:
            x, transform = _CHEBYSHEV[EVENT_DEGREE + int(math.ceil(EVENT_FREQUENCY * self.half))]
            theta = self.centre + self.half * x
        n2, n1, n0, d2, d1, d0 = self.coefficients(theta)
        l2, l1, l0 = n2 - level * d2, n1 - level * d1, n0 - level * d0
        _, _, g2, g0 = self.chord(theta)
        if wide:        # g0 as the polynomial sqrt k - a over the whole turn (chord() keeps
            g0 = self.root_k - self.problem.d_o * np.cos(theta - self.centre)   # the digits)
        zero = np.zeros(theta.size)
        slot = (g2, zero, g0)
        quadratics = [(l2, l1, l0), slot, *self.constraints(theta)]
        # range: N and D are multiples of (1 - kappa w)^2 (a line's cost is constant), so L's
        # discriminant vanishes identically and only the sign of L's factor changes
        rows = [] if self.problem.measurement == RANGE else [l1 * l1 - 4.0 * l2 * l0]
        for i, first in enumerate(quadratics):     # every pair: L with each boundary, the
            for second in quadratics[i + 1:]:       # boundaries with each other
                rows.append(resultant(first, second))
        for q2, q1, q0 in quadratics[2:]:           # the reach disc's tangent lines
            rows.append(q1 * q1 - 4.0 * q2 * q0)
        values = np.stack(rows)
        offsets = []
        if wide:
            fourier = np.fft.fft(values) / EVENT_SAMPLES
            for row in fourier:
                degree = EVENT_HARMONICS
                tail = np.abs(row[degree + 1:EVENT_SAMPLES - degree]).max()
                self.unresolved |= bool(tail > TAIL * np.abs(row).max())
                coefficients = row[np.arange(degree, -degree - 1, -1) % EVENT_SAMPLES]
                large = np.flatnonzero(np.abs(coefficients) > 1e-15 * np.abs(coefficients).max())
                if large.size:
                    roots = np.roots(coefficients[large[0]:])
                    angle = np.angle(roots[np.abs(roots) > 0.0])
                    offsets.append(np.mod(angle - self.centre + math.pi, 2.0 * math.pi) - math.pi)
        else:
            for coefficients in values @ transform.T:
                self.unresolved |= bool(np.abs(coefficients[-2:]).max()
                                        > TAIL_CHEBYSHEV * np.abs(coefficients).max())
                large = np.flatnonzero(np.abs(coefficients) > 1e-15 * np.abs(coefficients).max())
                if large.size and large[-1] > 0:
                    roots = np.polynomial.chebyshev.chebroots(coefficients[:large[-1] + 1])
                    near = roots[(np.abs(roots.real) <= 1.0) & (np.abs(roots.imag) <= NEAR_REAL)]
                    offsets.append(self.half * near.real)
        found = np.concatenate(offsets) if offsets else np.zeros(0)
        return found[np.abs(found) < self.half]

    def to_test(self, level: float, incumbent: float) -> np.ndarray:
        """Sorted angles (rad) to test at ``level``: the wedge's edges, the events, the
        midpoints between consecutive ones, a fixed grid of the wedge, and lines closing in
        geometrically on the incumbent's line (rad) and on the edges, where a thin piece of the
        super-level set hides first (its ends are a near-double root, or a root next to the
        edge's own)."""
        half = self.half
        edges = np.concatenate([[-half], np.sort(self.events(level)), [half]])
        grid = np.linspace(-half, half, WEDGE_GRID + 2)[1:-1]
        near = np.clip(incumbent - self.centre + half * _CLOSING, -half, half)
        return self.centre + np.sort(np.concatenate([
            edges, 0.5 * (edges[1:] + edges[:-1]), grid, near,
            half * np.sign(_CLOSING) * np.cos(_CLOSING)]))

    def refine(self, tau: np.ndarray, gain: np.ndarray, resolution: float
               ) -> tuple[float, float, float]:
        """The best line near the best of wedge coordinates ``tau`` (sorted, rad; see
        :meth:`angle`) with gains ``gain`` (m^2). Each level tries ZOOM_LINES lines spanning
        the best's neighbours and the vertex of the parabola through the best and its
        neighbours, so the bracket shrinks ZOOM_LINES / 2 times a level and faster where the
        parabola is right; it stops when the parabola through three lines of one branch (see
        :meth:`best`) promises less than ``resolution`` (m^2) over the best (across a kink a
        parabola misjudges). Returns (tau rad, gain m^2, w of the line's best point)."""
        tau, gain = np.asarray(tau, dtype=float), np.asarray(gain, dtype=float)
        j = int(np.argmax(gain))
        best_tau, best_gain = float(tau[j]), float(gain[j])
        w, branch = np.full(tau.size, np.nan), np.full(tau.size, -1)
        _, w[j:j + 1], branch[j:j + 1] = self.best(self.angle(tau[j:j + 1]))
        for level in range(ZOOM_LEVELS):
            low = float(tau[j - 1]) if j > 0 else best_tau
            high = float(tau[j + 1]) if j + 1 < tau.size else best_tau
            vertex, promise = best_tau, math.inf
            if 0 < j < tau.size - 1 and np.isfinite(gain[j - 1]) and np.isfinite(gain[j + 1]):
                a, b = best_tau - low, high - best_tau
                rise_low = best_gain - float(gain[j - 1])
                rise_high = best_gain - float(gain[j + 1])
                denominator = b * rise_low + a * rise_high
                one_branch = branch[j - 1] == branch[j] == branch[j + 1]
                if denominator > 0.0:
                    shift = 0.5 * (a * a * rise_high - b * b * rise_low) / denominator
                    curvature = 2.0 * denominator / (a * b * (a + b))
                    vertex = best_tau + shift
                    promise = 0.5 * curvature * shift * shift if one_branch else math.inf
                elif max(rise_low, rise_high) < resolution and one_branch:
                    promise = 0.0                               # flat to the resolution
            if (promise < resolution and level > 0) or high - low <= 1e-15:
                break
            trial = np.append(np.linspace(low, high, ZOOM_LINES), vertex)
            trial_gain, trial_w, trial_branch = self.best(self.angle(trial))
            tau, first = np.unique(np.append(trial, best_tau), return_index=True)
            gain = np.append(trial_gain, best_gain)[first]
            w = np.append(trial_w, w[j])[first]
            branch = np.append(trial_branch, branch[j])[first]
            close = np.flatnonzero(np.diff(tau) <= 1e-13 * (1.0 + np.abs(tau[1:])))
            drop = np.where(gain[close] < gain[close + 1], close, close + 1)  # keep the better
            tau, gain, w, branch = (np.delete(a, drop) for a in (tau, gain, w, branch))
            j = int(np.argmax(gain))
            best_tau, best_gain = float(tau[j]), float(gain[j])
        return best_tau, best_gain, float(w[j])


def resultant(first: tuple[Any, Any, Any], second: tuple[Any, Any, Any]) -> Any:
    """The resultant of a2 w^2 + a1 w + a0 and b2 w^2 + b1 w + b0 (coefficients arrays of one
    shape): zero where they share a root (a leading coefficient 0 leaves a factor, no root
    lost)."""
    a2, a1, a0 = first
    b2, b1, b0 = second
    return (a2 * b0 - a0 * b2) ** 2 - (a2 * b1 - a1 * b2) * (a1 * b0 - a0 * b1)


def joseph_on_lines(problem: Problem | StackedProblem, theta: np.ndarray, u: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(tr(W P_post W) (m^2), the gain tr(W P H' S^-1 H P W) (m^2), det S (all three
    ``np.longdouble``), the cost's rounding (m^2)) at the points (cos theta, sin theta) / u
    (arrays (n,), rad and 1/m), with P_post in Joseph form (as
    :func:`~formopt_ros.core.model.ekf_update_stacked`), written for the rows of the problem's
    measurement on these lines: h_d = (c, s, 0) and h_beta = u (-s, c, 0) - e3, or one of them
    (then det S = S). The gain is summed directly (P H' adj(S) H P / det S), so it keeps its
    digits where it is a tiny part of tr(W P W).

    Computed in ``np.longdouble`` (extended precision on x86-64): Joseph's products cancel to
    the posterior, so their rounding is eps tr(W (|A| |P| |A|' + K^2 R) W), which exceeds the
    cost's own eps where the update removes most of the prior (a posterior 1e-7 of tr(W P W)
    leaves 1e-9 of the cost in float64). The rounding returned is JOSEPH_ROUNDING times that
    bound with the long type's eps (float64's where the long type is no longer)."""
    long = np.longdouble
    theta, u = np.asarray(theta, dtype=long), np.asarray(u, dtype=long)
    c, s = np.cos(theta), np.sin(theta)
    rows = []
    if problem.measurement != BEARING:
        rows.append(np.stack([c, s, np.zeros_like(c)], -1))
    if problem.measurement != RANGE:
        rows.append(np.stack([-u * s, u * c, -np.ones_like(c)], -1))
    variances = [long(v) for v in np.atleast_1d(problem.R)]
    H = np.stack(rows, 1)                                                  # (n, m, 3)
    P = np.asarray(problem.P, dtype=long)
    PH = P @ np.swapaxes(H, 1, 2)                                          # (n, 3, m)
    S = H @ PH + np.diag(variances)                                        # (n, m, m)
    if len(rows) == 1:
        det, adjugate = S[:, 0, 0], np.ones_like(S)
    else:
        det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
        adjugate = np.stack([np.stack([S[:, 1, 1], -S[:, 0, 1]], -1),
                             np.stack([-S[:, 1, 0], S[:, 0, 0]], -1)], 1)
    K = PH @ adjugate / det[:, None, None]                                 # (n, 3, m)
    A = np.eye(3, dtype=long) - K @ H
    noise = (K * K) @ np.array(variances, dtype=long)                      # (n, 3)
    diagonal = np.einsum('nij,jk,nik->ni', A, P, A) + noise
    size = np.einsum('nij,jk,nik->ni', np.abs(A), np.abs(P), np.abs(A)) + noise
    weights = np.array([1.0, 1.0, problem.d_o * problem.d_o], dtype=long)
    rounding = JOSEPH_ROUNDING * float(np.finfo(long).eps) * (size @ weights)
    gain = np.einsum('nim,nmk,nik->ni', PH, adjugate, PH) / det[:, None]
    return diagonal @ weights, gain @ weights, det, rounding.astype(float)


def gain_bound(problem: Problem | StackedProblem) -> float:
    """An upper bound of the gain tr(W P W) - tr(W P_post W) (m^2) over the disc:
    tr(W P H' S^-1 H P W) <= sum_j |W P h_j|^2 / sigma_j^2 (S >= R), with |W P h| <= ||W P||_2
    |h|, |h_d| = 1 and |h_beta|^2 = 1 + 1 / |p|^2 <= 1 + 1 / (|p_o| - r)^2."""
    P = np.asarray(problem.P, dtype=float)
    spectral = float(np.linalg.norm(np.array([1.0, 1.0, problem.d_o])[:, None] * P, 2)) ** 2
    bearing = 1.0 + (problem.d_o - problem.r) ** -2.0
    rows = {RANGE: [1.0], BEARING: [bearing]}.get(problem.measurement, [1.0, bearing])
    return spectral * float(np.sum(np.array(rows) / np.atleast_1d(problem.R)))


def cost_here_and_at_slot(problem: Problem | StackedProblem, x: float, y: float
                          ) -> tuple[float, float, float]:
    """(cost at (x, y), cost at the slot, the first's rounding bound) (m^2), by
    :func:`joseph_on_lines`."""
    (cost, at_slot), _, _, (rounding, _) = joseph_on_lines(
        problem, np.array([math.atan2(y, x), math.atan2(problem.slot[1], problem.slot[0])]),
        np.array([1.0 / math.hypot(x, y), 1.0 / problem.d_o]))
    return float(cost), float(at_slot), float(rounding)


def polar_optimum(problem: Problem | StackedProblem, region: Region | None = None,
                  seeds: tuple[tuple[float, float], ...] = ()
                  ) -> tuple[tuple[float, float], float, float, dict[str, Any]]:
    """The global minimum of the cost over the disc, or over a non-empty ``region`` that
    restricts it (module docstring); the lines through ``seeds`` (m) and, over a region,
    through its corners and its point nearest the slot join the first grid (a sliver of a
    region may fall between grid lines).

    Returns:
        (point (m), its cost (m^2, Joseph form), proved lower bound of the cost over the disc
        or region (m^2; -inf when MAX_ROUNDS witnesses did not close it),
        diagnostics: rounds (witnesses refined), lines (lines whose best was computed),
        unresolved (:class:`Lines`), rounding (``Lines.rounding`` relative to the cost),
        met (False: no line found to meet a region a few
        roundings wide; the point is then the region's point nearest the slot), cost_at_slot
        (m^2).)
    """
    bound = gain_bound(problem)
    if bound <= RTOL * (problem.base_cost - bound):     # every point is optimal to the gap
        restricted = region is not None and region.restricts
        nearest = region.nearest(problem.slot) if restricted else None    # type: ignore
        x, y = nearest or problem.slot
        cost, at_slot, _ = cost_here_and_at_slot(problem, x, y)
        return (x, y), cost, problem.base_cost - bound, {
            'rounds': 0, 'lines': 0, 'unresolved': False, 'rounding': 0.0, 'met': True,
            'cost_at_slot': at_slot}
    lines = Lines(problem, region)
    tau = np.linspace(0.0, math.pi, FIRST_GRID)
    through = list(seeds)
    if lines.region is not None:
        through += [q for q in (lines.region.nearest(problem.slot), *lines.region.corners())
                    if q is not None]
    if through:
        tau = np.unique(np.append(tau, lines.tau_of(np.array(
            [math.atan2(q[1], q[0]) for q in through]))))
    gain = lines.best(lines.angle(tau))[0]

    def margin(best_gain: float) -> float:
        return (RTOL + ROUNDING) * abs(lines.shift - best_gain) + lines.rounding

    best_tau, best_gain, best_w = lines.refine(tau, gain, REFINED * margin(float(gain.max())))
    lower = -math.inf
    rounds = 0
    for rounds in range(MAX_ROUNDS + 1):
        if not math.isfinite(best_gain):    # no line found to meet a region of a few roundings
            break
        level = best_gain + margin(best_gain)
        tested = lines.to_test(level, float(lines.angle(np.array([best_tau]))[0]))
        witness = lines.beaten(tested, level)
        if not witness.any():
            lower = -math.inf if lines.unresolved else lines.shift - level
            break
        if rounds == MAX_ROUNDS:
            break
        tested_tau = lines.tau_of(tested)
        order = np.argsort(tested_tau)
        tested_tau, witness = tested_tau[order], witness[order]
        tested_gain = lines.best(lines.angle(tested_tau))[0]
        j = int(np.argmax(np.where(witness, tested_gain, -np.inf)))
        around = slice(max(j - 1, 0), j + 2)
        found = lines.refine(tested_tau[around], tested_gain[around],
                             REFINED * margin(best_gain))
        if found[1] > best_gain:
            best_tau, best_gain, best_w = found
    x_o, y_o = problem.slot
    if math.isfinite(best_gain):
        x, y = lines.point(float(lines.angle(np.array([best_tau]))[0]), best_w)
    else:                                   # its point nearest the slot, uncertified
        assert lines.region is not None
        x, y = lines.region.nearest(problem.slot) or problem.slot
    outside = math.hypot(x - x_o, y - y_o) / problem.r
    if outside > 1.0:           # a chord's end off the circle by rounding: back onto it
        x, y = x_o + (x - x_o) / outside, y_o + (y - y_o) / outside
    if lines.region is not None and not lines.region.contains((x, y)):
        nearest = lines.region.nearest((x, y))          # an end off its circle by rounding
        if nearest is not None:
            x, y = nearest
    cost, at_slot, rounding = cost_here_and_at_slot(problem, x, y)
    return (x, y), cost, min(lower, cost - rounding), {
        'rounds': rounds, 'lines': lines.evaluated, 'unresolved': lines.unresolved,
        'rounding': lines.rounding / cost if cost > 0.0 else math.inf,
        'met': math.isfinite(best_gain), 'cost_at_slot': at_slot}
