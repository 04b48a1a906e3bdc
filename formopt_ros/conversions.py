"""Translation between ROS messages and core values: the only module that knows both.

Conventions
-----------
* Leader odometry (nav_msgs/Odometry): frame_id 'odom' (fixed frame), child_frame_id the leader
  id; twist.linear.x = v_L (m/s), twist.angular.z = omega_L (rad/s); pose = leader in 'odom'.
* Follower odometry: child_frame_id = follower id; twist = the measured (commanded) velocities
  of one sub-step, twist.covariance[0] = sigma_v^2, [35] = sigma_omega^2.
* Estimate (PoseWithCovarianceStamped) and truth (PoseStamped): the follower pose [x, y, phi]
  in the leader frame (frame_id = leader id); the 6x6 covariance holds P at indices x=0, y=1,
  yaw=5 (ROS order x, y, z, roll, pitch, yaw).
* Lockstep stamps are simulated time: sub-step j (0-based) ends at (j + 1) dt; measurement step
  k at 2 k dt. Real-time stamps come from the node clock.
"""
from __future__ import annotations

import math

import numpy as np
from builtin_interfaces.msg import Time
from formopt_interfaces.msg import Measurement, PlannerStatus, Waypoint
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import Header

from formopt_ros.core.model import BEARING, RANGE
from formopt_ros.core.simulation import PlanResult

KIND_CODES = {RANGE: Measurement.RANGE, BEARING: Measurement.BEARING}
KIND_NAMES = {code: name for name, code in KIND_CODES.items()}
_POSE_INDEX = (0, 1, 5)


def stamp(seconds: float) -> Time:
    """builtin_interfaces/Time from seconds (>= 0)."""
    nanoseconds = int(round(seconds * 1e9))
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


def seconds(time: Time) -> float:
    """Seconds of a builtin_interfaces/Time."""
    return time.sec + 1e-9 * time.nanosec


def _set_yaw(orientation, yaw: float) -> None:
    orientation.z, orientation.w = math.sin(0.5 * yaw), math.cos(0.5 * yaw)
    orientation.x = orientation.y = 0.0


def yaw_of(orientation) -> float:
    """Yaw (rad) of a quaternion message."""
    return math.atan2(2.0 * (orientation.w * orientation.z + orientation.x * orientation.y),
                      1.0 - 2.0 * (orientation.y ** 2 + orientation.z ** 2))


def odometry(time: Time, frame_id: str, child_frame_id: str, pose: tuple[float, float, float],
             v: float, omega: float, variances: tuple[float, float] = (0.0, 0.0)) -> Odometry:
    """Odometry with a planar pose (x m, y m, yaw rad) and velocities (m/s, rad/s)."""
    msg = Odometry()
    msg.header.stamp, msg.header.frame_id, msg.child_frame_id = time, frame_id, child_frame_id
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
    _set_yaw(msg.pose.pose.orientation, pose[2])
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(v), float(omega)
    covariance = [0.0] * 36
    covariance[0], covariance[35] = float(variances[0]), float(variances[1])
    msg.twist.covariance = covariance
    return msg


def odometry_velocities(msg: Odometry) -> tuple[float, float, float, float]:
    """(v m/s, omega rad/s, var_v, var_omega) of an odometry message."""
    return (msg.twist.twist.linear.x, msg.twist.twist.angular.z, msg.twist.covariance[0],
            msg.twist.covariance[35])


def measurement(time: Time, follower_id: str, step: int, kind: str, value: float,
                variance: float) -> Measurement:
    """A range (m) or bearing (rad) measurement of measurement step ``step``."""
    return Measurement(header=_header(time, follower_id), follower_id=follower_id, step=step,
                       kind=KIND_CODES[kind], value=float(value), variance=float(variance))


def _header(time: Time, frame_id: str) -> Header:
    return Header(stamp=time, frame_id=frame_id)


def pose_stamped(time: Time, frame_id: str, x: np.ndarray) -> PoseStamped:
    """The follower pose [x, y, phi] in the leader frame as PoseStamped."""
    msg = PoseStamped(header=_header(time, frame_id))
    msg.pose.position.x, msg.pose.position.y = float(x[0]), float(x[1])
    _set_yaw(msg.pose.orientation, float(x[2]))
    return msg


def pose_of(pose) -> np.ndarray:
    """[x, y, yaw] of a geometry_msgs/Pose."""
    return np.array([pose.position.x, pose.position.y, yaw_of(pose.orientation)])


def estimate(time: Time, frame_id: str, x: np.ndarray,
             P: np.ndarray) -> PoseWithCovarianceStamped:
    """The EKF estimate [x, y, phi] and its 3x3 covariance as PoseWithCovarianceStamped."""
    msg = PoseWithCovarianceStamped(header=_header(time, frame_id))
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x[0]), float(x[1])
    _set_yaw(msg.pose.pose.orientation, float(x[2]))
    covariance = np.zeros((6, 6))
    covariance[np.ix_(_POSE_INDEX, _POSE_INDEX)] = P
    msg.pose.covariance = covariance.ravel().tolist()
    return msg


def estimate_values(msg: PoseWithCovarianceStamped) -> tuple[np.ndarray, np.ndarray]:
    """(x (3,), P (3, 3)) of an estimate message."""
    covariance = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
    return pose_of(msg.pose.pose), covariance[np.ix_(_POSE_INDEX, _POSE_INDEX)]


def waypoint(time: Time, follower_id: str, step: int, plan: PlanResult, p_o: np.ndarray,
             r: float, dt: float) -> Waypoint:
    """The planner's decision for ``step`` as a Waypoint with its sub-step commands."""
    msg = Waypoint(header=_header(time, follower_id), follower_id=follower_id, step=step,
                   radius=float(r), strategy=plan.solution.method,
                   predicted_cost=plan.solution.cost, cost_at_slot=plan.solution.cost_at_slot,
                   substep_duration=float(dt), linear_velocity=list(plan.v_commands),
                   angular_velocity=list(plan.omega_commands))
    msg.position.x, msg.position.y = float(plan.solution.p[0]), float(plan.solution.p[1])
    msg.formation_slot.x, msg.formation_slot.y = float(p_o[0]), float(p_o[1])
    return msg


def status(time: Time, follower_id: str, step: int, strategy: str, kind: str,
           weighted_trace: float, plan: PlanResult | None, counters: dict[str, int]
           ) -> PlannerStatus:
    """PlannerStatus after step ``step``; plan is the decision for the next step, if any."""
    msg = PlannerStatus(header=_header(time, follower_id), follower_id=follower_id, step=step,
                        strategy=strategy, measurement_kind=kind,
                        weighted_trace=float(weighted_trace),
                        rejected_measurements=counters.get('rejected_measurements', 0),
                        rejected_odometry=counters.get('rejected_odometry', 0),
                        accepted_measurements=counters.get('accepted_measurements', 0))
    if plan is not None:
        msg.cost_chosen = plan.solution.cost
        msg.cost_at_slot = plan.solution.cost_at_slot
        msg.solve_time_s = plan.solution.solve_time_s
    return msg


def measurement_problem(msg: Measurement, follower_id: str, kind: str) -> str | None:
    """Why a measurement must be rejected (None when it is acceptable)."""
    if msg.follower_id != follower_id:
        return f'for follower {msg.follower_id!r}, not {follower_id!r}'
    if KIND_NAMES.get(msg.kind) != kind:
        return f'kind {msg.kind} is not {kind}'
    if not math.isfinite(msg.value):
        return f'value {msg.value} is not finite'
    if not (math.isfinite(msg.variance) and msg.variance > 0.0):
        return f'variance {msg.variance} is not a finite number > 0'
    if kind == RANGE and msg.value < 0.0:
        return f'range {msg.value} m is negative'
    return None


def odometry_problem(msg: Odometry, child_frame_id: str) -> str | None:
    """Why an odometry message must be rejected (None when it is acceptable)."""
    if msg.child_frame_id != child_frame_id:
        return f'child_frame_id {msg.child_frame_id!r} is not {child_frame_id!r}'
    v, omega, var_v, var_omega = odometry_velocities(msg)
    if not (math.isfinite(v) and math.isfinite(omega)):
        return f'velocities ({v}, {omega}) are not finite'
    if not all(math.isfinite(x) and x >= 0.0 for x in (var_v, var_omega)):
        return f'velocity variances ({var_v}, {var_omega}) are not finite and >= 0'
    return None


def waypoint_problem(msg: Waypoint, follower_id: str) -> str | None:
    """Why a waypoint must be rejected (None when it is acceptable)."""
    if msg.follower_id != follower_id:
        return f'for follower {msg.follower_id!r}, not {follower_id!r}'
    commands = list(msg.linear_velocity) + list(msg.angular_velocity)
    if len(msg.linear_velocity) != len(msg.angular_velocity) or not commands:
        return 'linear and angular velocity lists must be non-empty and of equal length'
    if not all(math.isfinite(c) for c in commands):
        return 'commands are not finite'
    return None


def nanoseconds(time: Time) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time (exact, for matching stamps)."""
    return time.sec * 1_000_000_000 + time.nanosec
