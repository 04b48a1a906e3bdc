"""The reachable set of one measurement step: the slot's disc, the reach disc, the safety circle.

Frames: every point is in the leader frame at the end of the coming measurement step (where the
strategy's target lives), metres.

Reach disc (derivation). The follower starts the step at the estimated position x_f (leader
frame at the start); the leader drives (v_L, omega_L) per sub-step. The protocol rotates the
follower in place (v = 0) on the first sub-step and translates it on the second, so the target
p is reached by a world-frame displacement d of length |d| = v dt (the chord of the translating
sub-step). Had the follower stood still over both sub-steps, it would sit at
c = propagate(propagate(x_f, v = 0), v = 0) in the end frame (model.propagate_state, either
kinematics); the translation adds the displacement, rotated into the end frame, so p = c + R d
and |p - c| = |d|. ``max_speed`` bounds the follower's mean world-frame speed over the
measurement step, |d| <= max_speed * 2 dt: the reach disc is |p - c| <= max_speed * 2 dt. (The
protocol's translating sub-step then commands up to 2 max_speed for dt; a base that blends the
turn into the drive, as cmd_vel does, covers the same displacement at max_speed.)

Safety: |p| >= safety_distance (the leader sits at the origin of its frame).

The feasible set F = {|p - p_o| <= r} n {|p - c| <= rho} n {|p| >= s} is bounded by arcs of
these three circles; its corners are the pairwise intersections of the circles that lie in F.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from formopt_ros.core.model import propagate_state

#: Relative tolerance (of the region's scale |p_o| + r) of membership tests: a corner computed
#: in floating point lies within a few units of roundoff of both its circles.
FEASIBLE_RTOL = 1e-12

#: Clearance from the leader that keeps the linearised measurement models valid (a range's
#: Jacobian turns by 1/|p| per metre, a bearing's is 1/|p|, its curvature 1/|p|^2;
#: docs/faults.md, "Why large discs diverge for bearing"): this many initial position standard
#: deviations (the first updates) ...
CLEARANCE_SIGMAS = 3.5
#: ... and this fraction of |p_o| (the steady state near the leader).
CLEARANCE_FRACTION = 0.2

#: A circle (centre x m, centre y m, radius m, inside): inside True for |p - c| <= radius,
#: False for |p - c| >= radius.
Circle = tuple[float, float, float, bool]


@dataclass(frozen=True)
class Region:
    """The feasible set of one step (module docstring).

    Attributes:
        slot: p_o, m; r: the slot disc's radius, m.
        centre: the reach disc's centre c, m (None: no speed limit).
        radius: the reach disc's radius max_speed * 2 dt, m (inf: no speed limit).
        safety: the safety distance s from the leader, m (0: none).
    """

    slot: tuple[float, float]
    r: float
    centre: tuple[float, float] | None = None
    radius: float = math.inf
    safety: float = 0.0

    @property
    def scale(self) -> float:
        """|p_o| + r, m: the size tolerances are relative to."""
        return math.hypot(*self.slot) + self.r

    @property
    def reach_active(self) -> bool:
        """True when the reach disc cuts the slot's disc (does not contain it)."""
        if self.centre is None or not math.isfinite(self.radius):
            return False
        gap = math.hypot(self.slot[0] - self.centre[0], self.slot[1] - self.centre[1])
        return gap + self.r > self.radius

    @property
    def safety_active(self) -> bool:
        """True when the safety circle reaches into the slot's disc."""
        return self.safety > math.hypot(*self.slot) - self.r

    @property
    def restricts(self) -> bool:
        """True when the region is smaller than the slot's disc."""
        return self.reach_active or self.safety_active

    def circles(self) -> list[Circle]:
        """The circles that bound the region: the slot's, then the reach and safety circles
        when they cut it."""
        out: list[Circle] = [(self.slot[0], self.slot[1], self.r, True)]
        if self.reach_active:
            assert self.centre is not None
            out.append((self.centre[0], self.centre[1], self.radius, True))
        if self.safety_active:
            out.append((0.0, 0.0, self.safety, False))
        return out

    def contains(self, p: Sequence[float] | np.ndarray, rtol: float = FEASIBLE_RTOL) -> bool:
        """True when p (2,) (m) lies in the region, within rtol of its scale."""
        return _inside(self.circles(), float(p[0]), float(p[1]), rtol * self.scale)

    def corners(self) -> list[tuple[float, float]]:
        """The pairwise intersections of the bounding circles that lie in the region, m."""
        circles = self.circles()
        out = []
        for i in range(len(circles)):
            for j in range(i + 1, len(circles)):
                for point in circle_intersections(circles[i], circles[j]):
                    if _inside(circles, *point, FEASIBLE_RTOL * self.scale):
                        out.append(point)
        return out

    def nearest(self, p: Sequence[float] | np.ndarray) -> tuple[float, float] | None:
        """The point of the region nearest p (2,) (m), or None when the region is empty.

        The nearest point is p itself, the radial projection of p onto one bounding circle (the
        nearest point of a circle, whether the region lies inside or outside it), or a corner:
        the feasible candidate nearest p."""
        return _nearest(self.circles(), float(p[0]), float(p[1]), FEASIBLE_RTOL * self.scale)

    def empty(self) -> bool:
        """True when no point is feasible (the reach disc misses the slot's disc outside the
        safety circle)."""
        return self.nearest(self.slot) is None

    def fallback_target(self) -> tuple[float, float]:
        """Where to go when the region is empty: the point of the reach disc outside the
        safety circle nearest the slot (towards the disc at full speed); when the whole reach
        disc lies inside the safety circle, its point farthest from the leader (out at full
        speed: the speed limit holds, the safety distance is regained as fast as it can be);
        without a reach disc, the slot's nearest point outside the safety circle, m."""
        circles: list[Circle] = []
        if self.centre is not None and math.isfinite(self.radius):
            circles.append((self.centre[0], self.centre[1], self.radius, True))
        if self.safety > 0.0:
            circles.append((0.0, 0.0, self.safety, False))
        point = _nearest(circles, *self.slot, FEASIBLE_RTOL * self.scale)
        if point is not None or self.centre is None or not math.isfinite(self.radius):
            return self.slot if point is None else point
        cx, cy = self.centre
        out = math.hypot(cx, cy)
        ux, uy = (cx / out, cy / out) if out > 0.0 else (1.0, 0.0)
        return cx + self.radius * ux, cy + self.radius * uy

    def ray_interval(self, ux: float, uy: float) -> tuple[float, float]:
        """The distances t (m) for which t (ux, uy) (a unit vector) lies in the region, as
        (low, high); low > high when the ray misses it (a ray that touches a circle within
        rounding counts as touching it)."""
        low, high = self.safety, math.inf
        for cx, cy, radius, inside in self.circles():
            if not inside:
                continue
            along = ux * cx + uy * cy
            spread = radius * radius - (cx * cx + cy * cy - along * along)
            if spread < -FEASIBLE_RTOL * (cx * cx + cy * cy):    # a tangent ray rounds below 0
                return 1.0, 0.0
            root = math.sqrt(max(spread, 0.0))
            low, high = max(low, along - root), min(high, along + root)
        return low, high

    def direction_interval(self) -> tuple[float, float] | None:
        """The bearings (rad) under which the region is seen from the leader, as
        (low, high) with high - low < pi, or None when the region is empty.

        They form one interval: along a bearing the region's points are a segment whose far
        end is the nearer of the far ends on the two discs (each unimodal in the bearing), so
        the bearings whose far end clears the safety circle are an interval. Its ends lie at
        a tangent point of the slot's or the reach circle or at a corner: the bearing along
        a convex arc is extreme only where the ray touches it, along the safety circle it is
        monotonic."""
        circles = self.circles()
        tol = FEASIBLE_RTOL * self.scale
        points = list(self.corners())
        for cx, cy, radius, inside in circles:
            distance2 = cx * cx + cy * cy
            if not inside or distance2 <= radius * radius:
                continue
            theta, half = math.atan2(cy, cx), math.asin(radius / math.sqrt(distance2))
            reach = math.sqrt(distance2 - radius * radius)
            for angle in (theta - half, theta + half):
                point = (reach * math.cos(angle), reach * math.sin(angle))
                if _inside(circles, *point, tol):
                    points.append(point)
        if not points:
            return None
        theta_o = math.atan2(self.slot[1], self.slot[0])
        offsets = [(math.atan2(y, x) - theta_o + math.pi) % (2.0 * math.pi) - math.pi
                   for x, y in points]
        return theta_o + min(offsets), theta_o + max(offsets)


def circle_intersections(a: Circle, b: Circle) -> list[tuple[float, float]]:
    """The (0, 1 or 2) intersection points of two circles, m."""
    ax, ay, ra = a[:3]
    bx, by, rb = b[:3]
    dx, dy = bx - ax, by - ay
    d = math.hypot(dx, dy)
    if d == 0.0 or d > ra + rb or d < abs(ra - rb):
        return []
    along = (d * d + ra * ra - rb * rb) / (2.0 * d)
    half = math.sqrt(max(0.0, ra * ra - along * along))
    mx, my = ax + along * dx / d, ay + along * dy / d
    return [(mx - half * dy / d, my + half * dx / d), (mx + half * dy / d, my - half * dx / d)]


def _inside(circles: Sequence[Circle], x: float, y: float, tol: float) -> bool:
    """True when (x, y) satisfies every circle's constraint within tol (m)."""
    for cx, cy, radius, inside in circles:
        distance = math.hypot(x - cx, y - cy)
        if (distance > radius + tol) if inside else (distance < radius - tol):
            return False
    return True


def _nearest(circles: Sequence[Circle], x: float, y: float,
             tol: float) -> tuple[float, float] | None:
    """The point satisfying every circle's constraint nearest (x, y), or None (see
    :meth:`Region.nearest`)."""
    candidates = [(x, y)]
    for cx, cy, radius, _ in circles:
        dx, dy = x - cx, y - cy
        distance = math.hypot(dx, dy)
        ux, uy = (dx / distance, dy / distance) if distance > 0.0 else (1.0, 0.0)
        candidates.append((cx + radius * ux, cy + radius * uy))
    for i in range(len(circles)):
        for j in range(i + 1, len(circles)):
            candidates += circle_intersections(circles[i], circles[j])
    feasible = [p for p in candidates if _inside(circles, *p, tol)]
    if not feasible:
        return None
    return min(feasible, key=lambda p: math.hypot(p[0] - x, p[1] - y))


def reach_centre(x: np.ndarray, leader: Sequence[tuple[float, float]], dt: float,
                 kinematics: str) -> tuple[float, float]:
    """Where the follower at pose x (3,) (leader frame now) would be at the end of the step,
    in the leader frame then, had it not moved: x propagated with v = 0 over the step's
    sub-steps under the leader velocities ``leader`` (one (v m/s, omega rad/s) each), m."""
    pose = np.asarray(x, dtype=float)[:3]
    for v_l, omega_l in leader:
        pose = propagate_state(pose, 0.0, 0.0, dt, v_l, omega_l, kinematics)
    return float(pose[0]), float(pose[1])


def reach_region(slot: tuple[float, float], r: float, x: np.ndarray,
                 leader: Sequence[tuple[float, float]], dt: float, kinematics: str,
                 max_speed: float | None, safety: float) -> Region | None:
    """The region of the coming step, or None when neither limit is set (the paper's protocol).

    Args:
        slot, r: the slot p_o (m, leader frame) and the deviation r (m).
        x: the follower's estimated pose [x, y, phi] now (leader frame now).
        leader: expected leader (v m/s, omega rad/s) per sub-step of the step.
        dt: sub-step length, s; kinematics: 'exact' or 'euler'.
        max_speed: bound on the follower's mean world-frame speed over the step, m/s (None or
            inf: none); safety: distance to keep from the leader, m (0: none).
    """
    limited = max_speed is not None and math.isfinite(max_speed)
    if not limited and not safety > 0.0:
        return None
    if not limited:
        return Region(slot, r, None, math.inf, safety)
    assert max_speed is not None
    return Region(slot, r, reach_centre(x, leader, dt, kinematics),
                  max_speed * len(leader) * dt, safety)


__all__ = ['Circle', 'FEASIBLE_RTOL', 'Region', 'circle_intersections', 'reach_centre',
           'reach_region']
