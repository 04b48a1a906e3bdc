"""Building the formation's ROS messages from core values (reading them: formopt_ros.wire).

This is the only module that knows both message classes and core types; the conventions are
documented in :mod:`formopt_ros.wire.messages`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from formopt_interfaces.msg import Measurement, PlannerStatus, RunDescription, Waypoint
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from std_msgs.msg import Header

from formopt_ros.core.estimator import StepPlan
from formopt_ros.wire.messages import KIND_CODES, POSE_INDEX


def stamp(nanoseconds: int) -> Time:
    """builtin_interfaces/Time of an integer time in ns (>= 0)."""
    return Time(sec=nanoseconds // 1_000_000_000, nanosec=nanoseconds % 1_000_000_000)


def header(time: Time, frame_id: str) -> Header:
    """A std_msgs/Header."""
    return Header(stamp=time, frame_id=frame_id)


def _set_yaw(orientation: object, yaw: float) -> None:
    orientation.z, orientation.w = math.sin(0.5 * yaw), math.cos(0.5 * yaw)   # type: ignore
    orientation.x = orientation.y = 0.0                                        # type: ignore


def odometry(time: Time, frame_id: str, child_frame_id: str, pose: Sequence[float],
             v: float, omega: float, variances: tuple[float, float] = (0.0, 0.0)) -> Odometry:
    """Odometry with a planar pose (x m, y m, yaw rad) and velocities (m/s, rad/s)."""
    msg = Odometry(header=header(time, frame_id), child_frame_id=child_frame_id)
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(pose[0]), float(pose[1])
    _set_yaw(msg.pose.pose.orientation, pose[2])
    msg.twist.twist.linear.x, msg.twist.twist.angular.z = float(v), float(omega)
    covariance = [0.0] * 36
    covariance[0], covariance[35] = float(variances[0]), float(variances[1])
    msg.twist.covariance = covariance
    return msg


def measurement(time: Time, frame_id: str, follower_id: str, step: int, kind: str,
                value: float, variance: float) -> Measurement:
    """A range (m) or bearing (rad) measurement of measurement step ``step``."""
    return Measurement(header=header(time, frame_id), follower_id=follower_id, step=step,
                       kind=KIND_CODES[kind], value=float(value), variance=float(variance))


def pose_stamped(time: Time, frame_id: str, x: np.ndarray) -> PoseStamped:
    """The follower pose [x, y, phi] in the leader frame as PoseStamped."""
    msg = PoseStamped(header=header(time, frame_id))
    msg.pose.position.x, msg.pose.position.y = float(x[0]), float(x[1])
    _set_yaw(msg.pose.orientation, float(x[2]))
    return msg


def estimate(time: Time, frame_id: str, x: np.ndarray,
             P: np.ndarray) -> PoseWithCovarianceStamped:
    """The EKF estimate [x, y, phi] and its 3x3 covariance as PoseWithCovarianceStamped."""
    msg = PoseWithCovarianceStamped(header=header(time, frame_id))
    msg.pose.pose.position.x, msg.pose.pose.position.y = float(x[0]), float(x[1])
    _set_yaw(msg.pose.pose.orientation, float(x[2]))
    covariance = np.zeros((6, 6))
    covariance[np.ix_(POSE_INDEX, POSE_INDEX)] = P
    msg.pose.covariance = covariance.ravel().tolist()
    return msg


def waypoint(time: Time, frame_id: str, follower_id: str, plan: StepPlan, p_o: np.ndarray,
             r: float, dt: float) -> Waypoint:
    """The planner's decision for ``plan.step`` as a Waypoint with its sub-step commands."""
    solution = plan.solution
    msg = Waypoint(header=header(time, frame_id), follower_id=follower_id, step=plan.step,
                   radius=float(r), strategy=solution.method,
                   predicted_cost=solution.cost, cost_at_slot=solution.cost_at_slot,
                   substep_duration=float(dt), linear_velocity=list(plan.command.linear),
                   angular_velocity=list(plan.command.angular))
    msg.position.x, msg.position.y = float(solution.p[0]), float(solution.p[1])
    msg.formation_slot.x, msg.formation_slot.y = float(p_o[0]), float(p_o[1])
    return msg


def status(time: Time, frame_id: str, follower_id: str, step: int, strategy: str, kind: str,
           weighted_trace: float, plan: StepPlan | None,
           counters: dict[str, int]) -> PlannerStatus:
    """PlannerStatus after step ``step``; plan is the decision for the next step, if any."""
    msg = PlannerStatus(header=header(time, frame_id), follower_id=follower_id, step=step,
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


def description(time: Time, run_id: str, node: str, text: str) -> RunDescription:
    """The latched run description (``text``: formopt_ros.wire.description JSON)."""
    return RunDescription(header=header(time, ''), run_id=run_id, node=node, description=text)


def message_class(type_name: str, topic: str = '') -> type:
    """The Python class of 'pkg/msg/Type'; BagError when its package is not installed here."""
    import importlib

    from formopt_ros.bag import BagError
    from formopt_ros.bag.schema import split_type
    package, namespace, name = split_type(type_name)
    where = f' (topic {topic})' if topic else ''
    try:
        return getattr(importlib.import_module(f'{package}.{namespace}'), name)
    except (ImportError, AttributeError):
        raise BagError(f'unknown message type {type_name!r}{where}: its interface package is '
                       'not installed here') from None
