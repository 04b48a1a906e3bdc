"""The Sec. V measurement step: sub-steps, motion commands and the integer-nanosecond timebase.

One measurement step k (1-based) = ``SUBSTEPS`` sub-steps of ``dt`` (rotate in place, then
translate), then one range or bearing measurement. Global sub-step index ``n`` (0-based) of
step k is ``SUBSTEPS * (k - 1) + j`` for j = 0 .. SUBSTEPS - 1.

Lockstep timebase (simulated time, integer nanoseconds, so stamps match exactly across
processes and bags): sub-step n ends at ``(n + 1) dt_ns``; the measurement of step k is taken
at the end of its last sub-step, ``SUBSTEPS k dt_ns``; the waypoint of step k is issued at the
start of its first sub-step, ``SUBSTEPS (k - 1) dt_ns``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from formopt_ros.core.model import (
    EXACT, EULER, chord, elementwise, propagate, propagate_state, wrap_angle)

#: Sub-steps per measurement step: rotate, then translate.
SUBSTEPS = 2
#: Nanoseconds per second.
NS_PER_S = 1_000_000_000


def seconds_to_ns(seconds: float) -> int:
    """Integer nanoseconds of a time in seconds (rounded to the nearest ns)."""
    return int(round(seconds * NS_PER_S))


@dataclass(frozen=True)
class Timebase:
    """Lockstep simulated time on a grid of ``dt_ns`` nanoseconds (see module docstring)."""

    dt_ns: int

    @classmethod
    def from_dt(cls, dt: float) -> 'Timebase':
        """The timebase of sub-step length ``dt`` seconds (> 0)."""
        dt_ns = seconds_to_ns(dt)
        if dt_ns <= 0:
            raise ValueError(f'dt must be at least 1 ns, got {dt!r} s')
        return cls(dt_ns)

    def substep_end(self, substep: int) -> int:
        """Stamp (ns) at the end of global sub-step ``substep`` (0-based)."""
        return (substep + 1) * self.dt_ns

    def substep_ending_at(self, stamp_ns: int) -> int | None:
        """Global sub-step index whose end is ``stamp_ns``, or None when off the grid."""
        index, rest = divmod(stamp_ns, self.dt_ns)
        return index - 1 if rest == 0 and index >= 1 else None

    def measurement_stamp(self, step: int) -> int:
        """Stamp (ns) of the measurement of step ``step`` (1-based)."""
        return SUBSTEPS * step * self.dt_ns

    def waypoint_stamp(self, step: int) -> int:
        """Stamp (ns) at which the waypoint of step ``step`` (1-based) is issued."""
        return SUBSTEPS * (step - 1) * self.dt_ns

    def step_of_measurement(self, stamp_ns: int) -> int | None:
        """The step whose measurement is stamped ``stamp_ns``, or None off the grid."""
        step, rest = divmod(stamp_ns, SUBSTEPS * self.dt_ns)
        return step if rest == 0 and step >= 1 else None


def step_substeps(step: int) -> range:
    """Global sub-step indices (0-based) of measurement step ``step`` (1-based)."""
    return range(SUBSTEPS * (step - 1), SUBSTEPS * step)


@dataclass(frozen=True)
class MotionCommand:
    """Commanded follower velocities per sub-step of one measurement step.

    Attributes:
        linear: forward speed per sub-step, m/s, length SUBSTEPS (floats, or arrays (T,) for
            a batch of poses).
        angular: yaw rate per sub-step, rad/s, length SUBSTEPS (likewise).
    """

    linear: tuple[Any, ...]
    angular: tuple[Any, ...]


def command_velocities(x: np.ndarray, target: np.ndarray, dt: float, v_l: Any,
                       omega_l: Any, kinematics: str = EXACT) -> tuple[Any, Any]:
    """(translation speed m/s, rotation yaw rate rad/s) of :func:`motion_commands`, for one pose
    x (3,) and target (2,), or a batch of poses (T, 3) and targets (T, 2) or (2,) (and the
    leader's velocities floats or arrays (T,)).

    After the rotation (v = 0: the position moves only with the leader, to p1) the translation
    at omega_F = omega_L must satisfy C(phi1) f(v, omega_L) = C(omega_L dt) target +
    f(v_L, omega_L) - p1 =: D (model docstring), so the chord f points along D: heading
    phi1 = atan2(D) - omega_L dt / 2, speed |D| / (dt sinc(omega_L dt / 2)). With 'euler' the
    displacement of eq. (9) points along D, the straight line from p1 to the target.
    """
    x1 = propagate_state(x, 0.0, omega_l, dt, v_l, omega_l, kinematics)   # after rotating
    if kinematics == EULER:
        dx = target[..., 0] - x1[..., 0] - omega_l * x1[..., 1] * dt + v_l * dt
        dy = target[..., 1] - x1[..., 1] + omega_l * x1[..., 0] * dt
        turn = wrap_angle(elementwise(math.atan2, dy, dx) - x[..., 2])
        return elementwise(math.hypot, dx, dy) / dt, turn / dt + omega_l
    lx, ly, unit_x, unit_y = chord(v_l, omega_l, dt)[:4]        # unit_*: chord per m/s of v_F
    ca, sa = elementwise(math.cos, omega_l * dt), elementwise(math.sin, omega_l * dt)
    tx, ty = target[..., 0], target[..., 1]
    dx = ca * tx - sa * ty + lx - x1[..., 0]
    dy = sa * tx + ca * ty + ly - x1[..., 1]
    turn = wrap_angle(elementwise(math.atan2, dy, dx) - 0.5 * omega_l * dt - x[..., 2])
    return (elementwise(math.hypot, dx, dy) / elementwise(math.hypot, unit_x, unit_y),
            turn / dt + omega_l)


def motion_commands(x: np.ndarray, target: np.ndarray, dt: float, v_l: Any,
                    omega_l: Any, kinematics: str = EXACT) -> MotionCommand:
    """Commands that move the pose x = [x, y, phi] (leader frame) to position ``target`` (m);
    for poses (T, 3) the velocities of each sub-step are arrays (T,) where they differ.

    Sub-step 1 rotates in place (v = 0) to the heading of the remaining displacement; sub-step
    2 translates (omega = omega_L, i.e. no turn relative to the leader) so that the propagated
    pose (:func:`~formopt_ros.core.model.propagate_state`) lands exactly on target while the
    leader moves at (v_l m/s, omega_l rad/s).
    """
    speed, turn_rate = command_velocities(x, target, dt, v_l, omega_l, kinematics)
    if x.ndim == 1:
        speed, turn_rate = float(speed), float(turn_rate)
    return MotionCommand((0.0, speed), (turn_rate, omega_l))


def predict_move(x: np.ndarray, P: np.ndarray, target: np.ndarray,
                 leader: tuple[tuple[float, float], ...], dt: float, sigma_v: float,
                 sigma_omega: float, kinematics: str = EXACT) -> tuple[np.ndarray, np.ndarray]:
    """The EKF's prediction after driving from pose x to position ``target`` with
    :func:`motion_commands` as odometry, under the leader velocities ``leader`` (one (v m/s,
    omega rad/s) per sub-step); the estimate lands on target. This is the exact,
    move-dependent prior of the next measurement (the paper approximates it by target = p_o).

    Args:
        x, P: pose (3,) and covariance (3, 3), or batches (T, 3) and (T, 3, 3).
        target: position (2,) m, or one per pose (T, 2).
        leader: expected (v_L, omega_L) per sub-step; dt: sub-step, s.
        sigma_v, sigma_omega: odometry noise standard deviations, m/s and rad/s.
        kinematics: 'exact' or 'euler' (model docstring).

    Returns:
        (x, P) before the update, shapes of the inputs.
    """
    speed, turn_rate = command_velocities(x, target, dt, leader[0][0], leader[0][1], kinematics)
    for j, (v, omega) in enumerate(((0.0, turn_rate), (speed, leader[0][1]))):
        x, P = propagate(x, P, v, omega, dt, leader[j][0], leader[j][1], sigma_v, sigma_omega,
                         kinematics=kinematics)
    return x, P


def hold_command(omega_l: float) -> tuple[float, float]:
    """(v m/s, omega rad/s) of a follower sub-step without a waypoint: no forward motion,
    turning with the leader (so its heading relative to the leader holds)."""
    return 0.0, omega_l


def held_leader_motion(latest: tuple[float, float]) -> tuple[tuple[float, float], ...]:
    """Expected leader (v m/s, omega rad/s) per sub-step of the next step: the latest held.

    The planner knows the leader only through its odometry as it comes, so it expects the last
    reported velocity to persist over the coming sub-steps (simulator and nodes alike).
    """
    return (latest,) * SUBSTEPS
