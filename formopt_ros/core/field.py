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
from collections.abc import Callable
from dataclasses import dataclass, field

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
    """

    follower_odometry: list[tuple[int, float, float]] = field(default_factory=list)
    leader_odometry: list[tuple[int, float, float]] = field(default_factory=list)
    ranges: list[tuple[int, float]] = field(default_factory=list)
    truth: dict[int, np.ndarray] = field(default_factory=dict)
    outliers: int = 0
    dropouts: int = 0


def relative_pose(leader: Pose, follower: Pose) -> np.ndarray:
    """The follower's pose [x, y, phi] in the leader's frame, from both fixed-frame poses."""
    c, s = math.cos(leader[2]), math.sin(leader[2])
    dx, dy = follower[0] - leader[0], follower[1] - leader[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy,
                     float(wrap_angle(follower[2] - leader[2]))])


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
            world.command = follower_command(world.time, world.relative())
        elif what == 'leader':
            out.leader_odometry.append((stamp, values[0], values[1]))
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
