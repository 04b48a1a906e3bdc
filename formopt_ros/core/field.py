"""A simulated pair of real robots: bases that report odometry at their own rates and a UWB
radio (bias, timing jitter, heavy-tailed outliers, dropouts) or a camera measuring the bearing
to the leader from where it is mounted; the truth in a fixed frame.

The true motion is exact (each robot drives arcs of its true twist, held over each of its
odometry periods); the follower's true twist is its command plus Gaussian noise (sigma_v,
sigma_omega) drawn per period, and its odometry reports the command; the leader's true twist is
its path's, reported with its own noise. So the estimator's model (odometry = true twist - noise,
held over the interval the message ends) is the simulated one, while nothing else is shared.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from formopt_ros.core.model import integrate_unicycle, wrap_angle
from formopt_ros.core.protocol import NS_PER_S

Pose = tuple[float, float, float]


@dataclass(frozen=True)
class Base:
    """One robot's odometry: a message every 1/rate s (first at offset + 1/rate) reporting the
    twist held since the last one, the true twist differing by N(0, sigma^2) per period."""

    rate_hz: float = 50.0
    offset_s: float = 0.0
    sigma_v: float = 0.0
    sigma_omega: float = 0.0


@dataclass(frozen=True)
class Radio:
    """A UWB radio: ranges at ``rate_hz`` with uniform timing jitter (stamped when taken), a
    constant bias, Gaussian noise, a share of outliers (+U(low, high) m, one-sided like
    non-line-of-sight ranges) and of dropouts."""

    rate_hz: float = 30.0
    jitter_s: float = 0.005
    sigma: float = 0.1
    bias: float = 0.1
    outlier_rate: float = 0.02
    outlier_low: float = 1.0
    outlier_high: float = 3.0
    dropout_rate: float = 0.01


@dataclass(frozen=True)
class Camera:
    """A bearing sensor mounted at ``mount`` = (x m, y m, yaw rad) on the follower: the
    leader's direction from there, in its own frame, at ``rate_hz`` with timing jitter,
    Gaussian noise (rad), a share of false detections (a uniform bearing) and of dropouts."""

    rate_hz: float = 15.0
    jitter_s: float = 0.005
    sigma: float = 0.02
    mount: tuple[float, float, float] = (0.1, 0.0, 0.0)
    outlier_rate: float = 0.0
    dropout_rate: float = 0.01


Sensor = Radio | Camera


@dataclass
class FieldRun:
    """What the robots sent, and the truth.

    Attributes:
        follower_odometry, leader_odometry: (stamp ns, v m/s, omega rad/s) per message.
        ranges: (stamp ns, range m or bearing rad in the camera frame) per measurement sent.
        truth: stamp ns -> true pose [x, y, phi] of the follower in the leader's frame, at
            each range stamp (sent or dropped).
        outliers: ranges sent with an outlier; dropouts: ranges not sent.
        poses: robot ('follower', 'leader') -> stamp ns -> the pose its odometry message of
            that stamp carries (the true pose in the fixed frame: this base does not drift).
    """

    follower_odometry: list[tuple[int, float, float]] = field(default_factory=list)
    leader_odometry: list[tuple[int, float, float]] = field(default_factory=list)
    ranges: list[tuple[int, float]] = field(default_factory=list)
    truth: dict[int, np.ndarray] = field(default_factory=dict)
    poses: dict[str, dict[int, Pose]] = field(
        default_factory=lambda: {'follower': {}, 'leader': {}})
    outliers: int = 0
    dropouts: int = 0


def relative_pose(leader: Pose, follower: Pose) -> np.ndarray:
    """The follower's pose [x, y, phi] in the leader's frame, from both fixed-frame poses."""
    c, s = math.cos(leader[2]), math.sin(leader[2])
    dx, dy = follower[0] - leader[0], follower[1] - leader[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy,
                     float(wrap_angle(follower[2] - leader[2]))])


def dead_reckoned_estimate(start: np.ndarray, start_covariance: np.ndarray, leader: Pose,
                           follower_odometry: Pose, substeps: int, dt: float,
                           noise: tuple[float, float, float, float]
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The follower's relative pose from both robots' odometry poses alone (an estimator that
    lost its history: :meth:`EstimatorPlannerNode._rejoin`), with a covariance that covers it.

    The leader starts at the origin of the fixed frame, heading +x; the follower's odometry
    starts at the identity where its relative pose was ``start`` ~ N(start, start_covariance):
    its fixed-frame pose is F = start o follower_odometry, and the result is the pose of F in
    the frame of ``leader`` (:func:`relative_pose`). Covariance: J P0 J^T, J the Jacobian of
    that composition in ``start`` (d position / d start yaw = C(leader)^T C(start yaw) S o, S
    the 90-degree rotation, o the odometry position), plus the drift of ``substeps`` sub-steps
    of odometry noise of each robot: yaw (dt sigma_omega)^2 per sub-step; position
    (dt sigma_v)^2 per sub-step. The follower's yaw random walk (e_1 .. e_n) swings its
    displacement d sideways, as if driven at a constant pace: position error
    S d sum_i e_i (1 - i/n), yaw error sum_i e_i, so n s^2 [[S d d' S' / 3, S d / 2],
    [d' S' / 2, 1]] with s = dt sigma_omega (correlated: a range that fixes the position then
    tells the heading too). The leader's yaw walk, uncorrelated here: |L|^2 n s_L^2 / 3 for its
    own displacement L, plus |p|^2 n s_L^2 for turning the relative position p.

    Args:
        start: (3,) the relative pose [x m, y m, phi rad] at the start (the estimator's prior).
        start_covariance: (3, 3) its covariance.
        leader: the leader's odometry pose (x m, y m, yaw rad) in the fixed frame.
        follower_odometry: the follower's odometry pose in its own odometry frame.
        substeps: sub-steps of ``dt`` s driven since the start.
        noise: (sigma_v, sigma_omega) of the follower, then of the leader (m/s, rad/s).

    Returns:
        (x (3,), P (3, 3)) in the leader's frame.
    """
    c0, s0 = math.cos(start[2]), math.sin(start[2])
    ox, oy = follower_odometry[0], follower_odometry[1]
    follower = (start[0] + c0 * ox - s0 * oy, start[1] + s0 * ox + c0 * oy,
                start[2] + follower_odometry[2])
    x = relative_pose(leader, follower)
    cl, sl = math.cos(leader[2]), math.sin(leader[2])
    to_leader = np.array([[cl, sl], [-sl, cl]])
    jacobian = np.eye(3)
    jacobian[:2, :2] = to_leader
    jacobian[:2, 2] = to_leader @ np.array([-s0 * ox - c0 * oy, c0 * ox - s0 * oy])
    P = jacobian @ start_covariance @ jacobian.T
    sigma_v, sigma_omega, sigma_v_l, sigma_omega_l = noise
    yaw_f, yaw_l = (substeps * (dt * sigma) ** 2 for sigma in (sigma_omega, sigma_omega_l))
    position = (substeps * dt ** 2 * (sigma_v ** 2 + sigma_v_l ** 2)
                + (leader[0] ** 2 + leader[1] ** 2) * yaw_l / 3 + (x[0] ** 2 + x[1] ** 2) * yaw_l)
    drift = np.diag([position, position, yaw_l])
    # the follower's yaw random walk swings its displacement d (fixed frame) sideways: the
    # position error S d sum_i e_i (1 - i/n), the yaw error sum_i e_i, correlated
    swing = to_leader @ np.array([-(follower[1] - start[1]), follower[0] - start[0]])
    drift += yaw_f * np.block([[np.outer(swing, swing) / 3, swing[:, None] / 2],
                               [swing[None, :] / 2, np.ones((1, 1))]])
    return x, P + drift


def odometry_pose_at(entries: Iterable[tuple[int, Any, float, float]], stamp_ns: int,
                     interval_ns: int | None, nearest: bool) -> tuple[float, float, float] | None:
    """An odometry pose at ``stamp_ns`` from messages (stamp ns, pose after the interval it
    ends, v, omega held over that interval): one stamped then; else one whose interval of
    ``interval_ns`` (None: any) contains it, carried back with its own twist (exact); else,
    with ``nearest``, the nearest message carried to the stamp with its twist; else None."""
    entries = list(entries)
    after = [e for e in entries if e[0] >= stamp_ns and (
        interval_ns is None or e[0] - stamp_ns <= interval_ns)]
    if after:
        chosen = min(after, key=lambda e: e[0])
    elif nearest and entries:
        chosen = min(entries, key=lambda e: abs(e[0] - stamp_ns))
    else:
        return None
    stamp, pose, v, omega = chosen
    return integrate_unicycle(tuple(pose), v, omega, (stamp_ns - stamp) * 1e-9)


class FieldWorld:
    """Two robots in a fixed frame, advanced event by event (odometry periods of either base,
    range times); the caller sets the follower's command before each of its periods.

    Args:
        start: the follower's true start pose [x, y, phi] in the leader's frame (the leader
            starts at the origin of the fixed frame, heading +x).
        leader_twist: t (s) -> the leader's true (v, omega) over its odometry period from t.
        rng: all random draws.
        duration_s: the events are scheduled up to this time, s.
    """

    def __init__(self, start: np.ndarray, leader_twist: Callable[[float], tuple[float, float]],
                 rng: np.random.Generator, duration_s: float, follower_base: Base = Base(),
                 leader_base: Base = Base(), sensor: Sensor = Radio()) -> None:
        self.leader: Pose = (0.0, 0.0, 0.0)
        self.follower: Pose = (float(start[0]), float(start[1]), float(start[2]))
        self.leader_twist, self.rng = leader_twist, rng
        self.follower_base, self.leader_base, self.sensor = follower_base, leader_base, sensor
        self.kind = 'range' if isinstance(sensor, Radio) else 'bearing'
        self.time = 0.0
        self.command = (0.0, 0.0)          # the follower's command over its current period
        self._noise_f = _noisy((0.0, 0.0), follower_base, rng)   # true twist - command
        self._reported_l = leader_twist(0.0)
        self._true_l = _noisy(self._reported_l, leader_base, rng)
        self.outliers = self.dropouts = 0
        self._events = sorted(
            [(follower_base.offset_s + k / follower_base.rate_hz, 'follower')
             for k in range(1, int(duration_s * follower_base.rate_hz))]
            + [(leader_base.offset_s + k / leader_base.rate_hz, 'leader')
               for k in range(1, int(duration_s * leader_base.rate_hz))]
            + [(k / sensor.rate_hz + rng.uniform(-sensor.jitter_s, sensor.jitter_s), self.kind)
               for k in range(1, int(duration_s * sensor.rate_hz))], reverse=True)

    def relative(self) -> np.ndarray:
        """The follower's true pose [x, y, phi] in the leader's frame now."""
        return relative_pose(self.leader, self.follower)

    def next_time(self) -> float | None:
        """When the next event happens, s (None: none left)."""
        return self._events[-1][0] if self._events else None

    def step(self) -> tuple[str, int, tuple[float, ...]] | None:
        """Advance to the next event and return what it sends: ('follower' or 'leader', stamp
        ns, (v, omega)) odometry, ('range', stamp ns, (range m,)), ('bearing', stamp ns,
        (bearing rad in the camera frame,)), or ('dropout', stamp, ());
        None when no event is left. A follower odometry event ends the period of the current
        command: set ``command`` for the next one after it."""
        if not self._events:
            return None
        when, what = self._events.pop()
        true_f = (self.command[0] + self._noise_f[0], self.command[1] + self._noise_f[1])
        self.follower = integrate_unicycle(self.follower, *true_f, when - self.time)
        self.leader = integrate_unicycle(self.leader, *self._true_l, when - self.time)
        self.time = when
        stamp = int(round(when * NS_PER_S))
        if what == 'follower':
            self._noise_f = _noisy((0.0, 0.0), self.follower_base, self.rng)
            return what, stamp, self.command
        if what == 'leader':
            sent = self._reported_l
            self._reported_l = self.leader_twist(when)
            self._true_l = _noisy(self._reported_l, self.leader_base, self.rng)
            return what, stamp, sent
        sensor, pose = self.sensor, self.relative()
        if self.rng.uniform() < sensor.dropout_rate:
            self.dropouts += 1
            return 'dropout', stamp, ()
        if isinstance(sensor, Camera):
            x, y, yaw = sensor.mount
            c, s = math.cos(self.follower[2]), math.sin(self.follower[2])
            at = (self.follower[0] + c * x - s * y, self.follower[1] + s * x + c * y)
            value = math.atan2(self.leader[1] - at[1], self.leader[0] - at[0]) - \
                self.follower[2] - yaw + sensor.sigma * self.rng.normal()
            if self.rng.uniform() < sensor.outlier_rate:
                self.outliers += 1
                value = self.rng.uniform(-math.pi, math.pi)
            return 'bearing', stamp, (float(wrap_angle(value)),)
        value = math.hypot(pose[0], pose[1]) + sensor.bias + sensor.sigma * self.rng.normal()
        if self.rng.uniform() < sensor.outlier_rate:
            self.outliers += 1
            value += self.rng.uniform(sensor.outlier_low, sensor.outlier_high)
        return 'range', stamp, (value,)


def simulate_field(duration_s: float, start: np.ndarray,
                   leader_twist: Callable[[float], tuple[float, float]],
                   follower_command: Callable[[float, np.ndarray], tuple[float, float]],
                   rng: np.random.Generator, follower_base: Base = Base(),
                   leader_base: Base = Base(), sensor: Sensor = Radio()) -> FieldRun:
    """Simulate ``duration_s`` seconds of :class:`FieldWorld`; ``follower_command``: (t s, true
    relative pose) -> the follower's command for its odometry period from t."""
    world = FieldWorld(start, leader_twist, rng, duration_s, follower_base, leader_base, sensor)
    world.command = follower_command(0.0, world.relative())
    out = FieldRun()
    while (event := world.step()) is not None:
        what, stamp, values = event
        if what == 'follower':
            out.follower_odometry.append((stamp, values[0], values[1]))
            out.poses['follower'][stamp] = world.follower
            world.command = follower_command(world.time, world.relative())
        elif what == 'leader':
            out.leader_odometry.append((stamp, values[0], values[1]))
            out.poses['leader'][stamp] = world.leader
        else:
            out.truth[stamp] = world.relative()
            if what in ('range', 'bearing'):
                out.ranges.append((stamp, values[0]))
    out.outliers, out.dropouts = world.outliers, world.dropouts
    return out


def _noisy(twist: tuple[float, float], base: Base,
           rng: np.random.Generator) -> tuple[float, float]:
    """The true twist behind a reported one: plus N(0, sigma^2) per component."""
    return (twist[0] + base.sigma_v * rng.normal(), twist[1] + base.sigma_omega * rng.normal())


__all__ = ['Base', 'Camera', 'FieldRun', 'FieldWorld', 'Radio', 'relative_pose', 'simulate_field']
