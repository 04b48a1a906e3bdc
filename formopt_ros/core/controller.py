"""Velocity commands a differential-drive base can execute: drive the follower toward a planned
point of the leader's frame within speed, turn-rate and acceleration limits."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from formopt_ros.core.checks import as_real
from formopt_ros.core.model import wrap_angle


@dataclass(frozen=True)
class Limits:
    """What the base can do.

    Attributes:
        speed: largest forward speed, m/s (the base does not reverse).
        yaw_rate: largest |yaw rate|, rad/s.
        acceleration: largest change of speed, m/s^2.
        yaw_acceleration: largest change of yaw rate, rad/s^2.
    """

    speed: float = 2.0
    yaw_rate: float = 3.0
    acceleration: float = 2.0
    yaw_acceleration: float = 10.0

    def __post_init__(self) -> None:
        for name in ('speed', 'yaw_rate', 'acceleration', 'yaw_acceleration'):
            object.__setattr__(self, name, as_real(name, getattr(self, name), 0.0,
                                                   low_open=True))


def twist_toward(x: np.ndarray, target: np.ndarray, leader: tuple[float, float],
                 horizon: float, limits: Limits, previous: tuple[float, float],
                 period: float, heading_gain: float = 2.0) -> tuple[float, float]:
    """The follower's (v m/s, omega rad/s) for the next control period.

    The relative position should move as (target - p) / horizon. With the relative kinematics
    (core/model.py) the follower's velocity in {L} must then be
    ``u = (target - p) / horizon + [v_L - omega_L y, omega_L x]``: the base turns toward u
    (omega = omega_L + heading_gain * heading error, so it holds its heading relative to the
    leader once aligned) and drives at the projection of u on its heading, never backwards;
    both are clipped to the limits and to the accelerations from ``previous`` over ``period``.

    Args:
        x: estimated pose [x, y, phi] in {L} (m, m, rad).
        target: planned position (2,) in {L}, m.
        leader: the leader's (v m/s, omega rad/s), expected to hold.
        horizon: time to reach the target, s (> 0).
        limits: the base's limits.
        previous: the last command (v, omega).
        period: control period, s.
        heading_gain: 1/s.
    """
    phi, omega_l = float(x[2]), leader[1]
    ux, uy = required_velocity(x, target, leader, horizon)
    error = float(wrap_angle(math.atan2(uy, ux) - phi)) if (ux or uy) else 0.0
    speed = max(0.0, ux * math.cos(phi) + uy * math.sin(phi))
    return limited((speed, omega_l + heading_gain * error), previous, limits, period)


def required_velocity(x: np.ndarray, target: np.ndarray, leader: tuple[float, float],
                      horizon: float) -> tuple[float, float]:
    """The follower's velocity in {L} (m/s, 2 components) that moves its relative position
    from x[:2] to ``target`` in ``horizon`` s while the leader drives at (v_L, omega_L):
    (target - p) / horizon + [v_L - omega_L y, omega_L x] (the relative kinematics,
    core/model.py). Its norm above the base's speed limit means the target is out of reach."""
    px, py = float(x[0]), float(x[1])
    v_l, omega_l = leader
    return ((float(target[0]) - px) / horizon + v_l - omega_l * py,
            (float(target[1]) - py) / horizon + omega_l * px)


def limited(twist: tuple[float, float], previous: tuple[float, float], limits: Limits,
            period: float) -> tuple[float, float]:
    """``twist`` (v m/s, omega rad/s) clipped to the limits (no reversing) and to what the
    accelerations allow from ``previous`` within ``period`` s: what the base executes."""
    def clip(value: float, low: float, high: float, last: float, step: float) -> float:
        return min(max(value, low, last - step), high, last + step)

    return (clip(twist[0], 0.0, limits.speed, previous[0], limits.acceleration * period),
            clip(twist[1], -limits.yaw_rate, limits.yaw_rate, previous[1],
                 limits.yaw_acceleration * period))


__all__ = ['Limits', 'limited', 'required_velocity', 'twist_toward']
