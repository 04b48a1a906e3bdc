"""Building the formation's ROS messages from core values (reading them: formopt_ros.wire).

This is the only module that knows both message classes and core types; the conventions are
documented in :mod:`formopt_ros.wire.messages`.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from formopt_interfaces.msg import Measurement, PlannerStatus, RunDescription, Waypoint
from geometry_msgs.msg import Point, PoseStamped, PoseWithCovarianceStamped, TransformStamped
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock
from std_msgs.msg import ColorRGBA, Header
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import Marker, MarkerArray

from formopt_ros.core.estimator import StepPlan
from formopt_ros.core.model import ellipse_points
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
                value: float, variance: float, run_id: str = '') -> Measurement:
    """A range (m) or bearing (rad) measurement of measurement step ``step``."""
    return Measurement(header=header(time, frame_id), follower_id=follower_id, run_id=run_id,
                       step=step, kind=KIND_CODES[kind], value=float(value),
                       variance=float(variance))


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
             r: float, dt: float, run_id: str = '') -> Waypoint:
    """The planner's decision for ``plan.step`` as a Waypoint with its sub-step commands."""
    solution = plan.solution
    msg = Waypoint(header=header(time, frame_id), follower_id=follower_id, run_id=run_id,
                   step=plan.step,
                   radius=float(r), strategy=solution.method,
                   predicted_cost=solution.cost, cost_at_slot=solution.cost_at_slot,
                   substep_duration=float(dt), linear_velocity=list(plan.command.linear),
                   angular_velocity=list(plan.command.angular))
    msg.position.x, msg.position.y = float(solution.p[0]), float(solution.p[1])
    msg.formation_slot.x, msg.formation_slot.y = float(p_o[0]), float(p_o[1])
    return msg


def status(time: Time, frame_id: str, follower_id: str, step: int, strategy: str, kind: str,
           weighted_trace: float, plan: StepPlan | None, counters: dict[str, int],
           run_id: str = '') -> PlannerStatus:
    """PlannerStatus after step ``step``; plan is the decision for the next step, if any."""
    msg = PlannerStatus(header=header(time, frame_id), follower_id=follower_id, run_id=run_id,
                        step=step,
                        strategy=strategy, measurement_kind=kind,
                        weighted_trace=float(weighted_trace),
                        rejected_measurements=counters.get('rejected_measurements', 0),
                        rejected_odometry=counters.get('rejected_odometry', 0),
                        accepted_measurements=counters.get('accepted_measurements', 0),
                        gated_measurements=counters.get('gated_measurements', 0),
                        foreign_messages=counters.get('foreign_messages', 0))
    if plan is not None:
        msg.cost_chosen = plan.solution.cost
        msg.cost_at_slot = plan.solution.cost_at_slot
        msg.solve_time_s = plan.solution.solve_time_s
    return msg


def description(time: Time, run_id: str, node: str, text: str) -> RunDescription:
    """The latched run description (``text``: formopt_ros.wire.description JSON)."""
    return RunDescription(header=header(time, ''), run_id=run_id, node=node, description=text)


def clock(nanoseconds: int) -> Clock:
    """rosgraph_msgs/Clock of a simulated time in ns."""
    return Clock(clock=stamp(nanoseconds))


def transform(time: Time, parent: str, child: str,
              pose: Sequence[float] | np.ndarray) -> TransformStamped:
    """parent -> child as a planar pose (x m, y m, yaw rad) of child in parent."""
    msg = TransformStamped(header=header(time, parent), child_frame_id=child)
    msg.transform.translation.x = float(pose[0])
    msg.transform.translation.y = float(pose[1])
    _set_yaw(msg.transform.rotation, float(pose[2]))
    return msg


def tf_message(transforms: Sequence[TransformStamped]) -> TFMessage:
    """A /tf (or /tf_static) message."""
    return TFMessage(transforms=list(transforms))


#: RGBA per marker (exact in float32, so recorded markers compare equal).
_COLOURS = {'slot': (0.5, 0.5, 0.5, 1.0), 'disc': (0.5, 0.5, 0.5, 0.75),
            'waypoint': (0.125, 0.375, 0.875, 1.0), 'ellipse': (0.875, 0.25, 0.125, 1.0)}


def _marker(time: Time, frame: str, namespace: str, kind: str, marker_type: int,
            scale: float) -> Marker:
    marker = Marker(header=header(time, frame), ns=f'{namespace}/{kind}', id=0,
                    type=marker_type, action=Marker.ADD)
    marker.pose.orientation.w = 1.0
    marker.scale.x = marker.scale.y = marker.scale.z = float(scale)
    marker.color = ColorRGBA(r=_COLOURS[kind][0], g=_COLOURS[kind][1], b=_COLOURS[kind][2],
                             a=_COLOURS[kind][3])
    return marker


def _line(marker: Marker, points: np.ndarray) -> Marker:
    marker.points = [Point(x=float(x), y=float(y), z=0.0) for x, y in points]
    return marker


def markers(time: Time, frame: str, namespace: str, p_o: np.ndarray, r: float,
            waypoint: np.ndarray | None, x: np.ndarray, P: np.ndarray) -> MarkerArray:
    """The follower's slot, feasible disc, chosen waypoint and 3-sigma position ellipse of the
    estimate, all in the leader frame ``frame`` (namespaces '<follower>/slot', ...)."""
    size = 0.05 * r
    slot = _marker(time, frame, namespace, 'slot', Marker.SPHERE, 2 * size)
    slot.pose.position.x, slot.pose.position.y = float(p_o[0]), float(p_o[1])
    circle = p_o + r * np.stack([np.cos(np.linspace(0, 2 * np.pi, 65)),
                                 np.sin(np.linspace(0, 2 * np.pi, 65))], axis=1)
    disc = _line(_marker(time, frame, namespace, 'disc', Marker.LINE_STRIP, 0.2 * size), circle)
    ellipse = _line(_marker(time, frame, namespace, 'ellipse', Marker.LINE_STRIP, 0.2 * size),
                    ellipse_points(x[:2], P[:2, :2], 3.0, 64))
    out = [slot, disc, ellipse]
    if waypoint is not None:
        chosen = _marker(time, frame, namespace, 'waypoint', Marker.SPHERE, 2 * size)
        chosen.pose.position.x, chosen.pose.position.y = float(waypoint[0]), float(waypoint[1])
        out.append(chosen)
    return MarkerArray(markers=out)


#: Diagnostic levels by name.
LEVELS = {'OK': DiagnosticStatus.OK, 'WARN': DiagnosticStatus.WARN,
          'ERROR': DiagnosticStatus.ERROR, 'STALE': DiagnosticStatus.STALE}


def diagnostic(name: str, hardware_id: str, level: str, message: str,
               values: dict[str, object]) -> DiagnosticStatus:
    """One diagnostic_msgs/DiagnosticStatus; values become key/value strings."""
    return DiagnosticStatus(level=LEVELS[level], name=name, message=message,
                            hardware_id=hardware_id,
                            values=[KeyValue(key=k, value=str(v)) for k, v in values.items()])


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
