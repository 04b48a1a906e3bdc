"""Reading formation messages into core values, and why a message must be refused.

The functions only read attributes, so they accept rclpy messages in the nodes and the
dataclasses that rosbags decodes from a bag in the offline analysis alike (no ROS import here).

Conventions (see also ``formopt_ros.ros.conversions``, which builds the messages):

* Leader odometry (nav_msgs/Odometry): frame_id 'odom', child_frame_id the leader id;
  twist.linear.x = v_L (m/s), twist.angular.z = omega_L (rad/s).
* Follower odometry: child_frame_id the follower id; twist = the measured (commanded)
  velocities of one sub-step, twist.covariance[0] = sigma_v^2, [35] = sigma_omega^2.
* Estimate (PoseWithCovarianceStamped) and truth (PoseStamped): the follower pose [x, y, phi]
  in the leader frame; the 6x6 covariance holds P at indices x=0, y=1, yaw=5.
* Measurement.kind: 0 range (m), 1 bearing (rad).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from formopt_ros.core.model import (
    BEARING, RANGE, RANGE_BEARING, rotation_matrix, rpy_quaternion)

#: Measurement.kind codes of the message definition (RANGE=0, BEARING=1).
KIND_CODES = {RANGE: 0, BEARING: 1}
KIND_NAMES = {code: name for name, code in KIND_CODES.items()}
#: Indices of x, y, yaw in a ROS 6x6 pose covariance (x, y, z, roll, pitch, yaw).
POSE_INDEX = (0, 1, 5)


def stamp_ns(stamp: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time (exact, for matching stamps)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def header_ns(msg: Any) -> int:
    """Integer nanoseconds of a message's header stamp."""
    return stamp_ns(msg.header.stamp)


def yaw_of(orientation: Any) -> float:
    """Yaw (rad) of a quaternion message."""
    return math.atan2(2.0 * (orientation.w * orientation.z + orientation.x * orientation.y),
                      1.0 - 2.0 * (orientation.y ** 2 + orientation.z ** 2))


def pose_values(pose: Any) -> np.ndarray:
    """[x m, y m, yaw rad] of a geometry_msgs/Pose, shape (3,)."""
    return np.array([pose.position.x, pose.position.y, yaw_of(pose.orientation)])


#: Largest variance taken from a message, (m/s)^2, (rad/s)^2 or m^2: drivers write 1e3 to 1e6
#: (or -1, or 0) for 'unknown', which would be read as sigma = 30-1000 m/s.
VARIANCE_BOUND = 100.0


def message_variance(value: float) -> float | None:
    """A variance a message carries, when it is in (0, VARIANCE_BOUND]; None ('unknown': use
    the configured noise) otherwise."""
    return float(value) if 0.0 < value <= VARIANCE_BOUND else None


def range_variance(configured: float, from_message: float | None, default: float) -> float:
    """The variance of a range, m^2: ``configured`` (range_variance) when set, else its
    message's when known (``from_message``, :func:`message_variance`), else ``default``
    (range_sigma^2)."""
    return configured or from_message or default


def twist_noise(msg: Any) -> tuple[float, float] | None:
    """(sigma_v m/s, sigma_omega rad/s) of an Odometry's twist covariance (entries 0 and 35)
    when both are known (:func:`message_variance`); None (use the configured noise)
    otherwise."""
    covariance = msg.twist.covariance
    v, omega = message_variance(covariance[0]), message_variance(covariance[35])
    return None if v is None or omega is None else (math.sqrt(v), math.sqrt(omega))


def odometry_values(msg: Any) -> tuple[float, float, float, float]:
    """(v m/s, omega rad/s, var_v, var_omega) of an odometry message."""
    return (float(msg.twist.twist.linear.x), float(msg.twist.twist.angular.z),
            float(msg.twist.covariance[0]), float(msg.twist.covariance[35]))


def estimate_values(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(x (3,), P (3, 3)) of a PoseWithCovarianceStamped estimate."""
    covariance = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
    return pose_values(msg.pose.pose), covariance[np.ix_(POSE_INDEX, POSE_INDEX)]


def foreign_run(msg: Any, run_id: str) -> str | None:
    """Why a message belongs to another run: its run_id differs from ``run_id`` (None when it
    is this run's, when ``run_id`` is '' (accept any) or the message has no run_id)."""
    theirs = getattr(msg, 'run_id', None)
    if run_id and theirs is not None and theirs != run_id:
        return f'of run {theirs!r}, not {run_id!r}'
    return None


def measurement_problem(msg: Any, follower_id: str, kind: str) -> str | None:
    """Why a measurement must be refused (None when it is acceptable): another follower, its
    header frame not the follower's body frame (``follower_id``), another kind, a value or
    variance that is not finite (the plausibility of a value is the session's rule:
    :class:`~formopt_ros.core.estimator.InputBounds`)."""
    if msg.follower_id != follower_id:
        return f'for follower {msg.follower_id!r}, not {follower_id!r}'
    if msg.header.frame_id != follower_id:
        return f'frame_id {msg.header.frame_id!r} is not the follower frame {follower_id!r}'
    kinds = (RANGE, BEARING) if kind == RANGE_BEARING else (kind,)
    if KIND_NAMES.get(int(msg.kind)) not in kinds:
        return f"kind {msg.kind} is not {' or '.join(kinds)}"
    if not math.isfinite(msg.value):
        return f'value {msg.value} is not finite'
    if not (math.isfinite(msg.variance) and msg.variance > 0.0):
        return f'variance {msg.variance} is not a finite number > 0'
    return None


def odometry_problem(msg: Any, frame_id: str, child_frame_id: str) -> str | None:
    """Why an odometry message must be refused (None when it is acceptable): frames other than
    ``frame_id`` / ``child_frame_id``, velocities or variances that are not finite."""
    if msg.child_frame_id != child_frame_id:
        return f'child_frame_id {msg.child_frame_id!r} is not {child_frame_id!r}'
    if msg.header.frame_id != frame_id:
        return f'frame_id {msg.header.frame_id!r} is not {frame_id!r}'
    v, omega, var_v, var_omega = odometry_values(msg)
    if not (math.isfinite(v) and math.isfinite(omega)):
        return f'velocities ({v}, {omega}) are not finite'
    if not all(math.isfinite(x) and x >= 0.0 for x in (var_v, var_omega)):
        return f'velocity variances ({var_v}, {var_omega}) are not finite and >= 0'
    return None


#: How far (m) an odometry pose may move while its twist stays exactly zero before the twist
#: counts as missing (a driver that fills the pose only; the filter integrates the twist).
STILL_TWIST_MOVE = 0.1


class StillTwist:
    """Watches one odometry stream for a twist that stays exactly zero while its pose moves.

    Attributes:
        moved: how far (m) the pose moved while the twist stayed zero, since it first did.
    """

    def __init__(self) -> None:
        self.start: tuple[float, float] | None = None
        self.moved = 0.0

    def add(self, v: float, omega: float, x: float, y: float) -> bool:
        """One message's twist (m/s, rad/s) and pose position (m, its odometry frame); True
        once the pose moved more than STILL_TWIST_MOVE with every twist zero."""
        if v != 0.0 or omega != 0.0 or not (math.isfinite(x) and math.isfinite(y)):
            self.start, self.moved = None, 0.0
            return False
        if self.start is None:
            self.start = (x, y)
        self.moved = math.hypot(x - self.start[0], y - self.start[1])
        return self.moved > STILL_TWIST_MOVE


#: Static transforms by child frame: (parent frame, the child's translation (3,) m and
#: rotation (3, 3) in the parent).
StaticTransforms = dict[str, tuple[str, np.ndarray, np.ndarray]]


def static_transforms(messages: Any) -> StaticTransforms:
    """The transforms of tf2_msgs/TFMessage ``messages`` (/tf_static), by child frame (a
    later one for the same child replaces the earlier)."""
    static: StaticTransforms = {}
    for message in messages:
        for transform in message.transforms:
            t, q = transform.transform.translation, transform.transform.rotation
            static[transform.child_frame_id] = (
                transform.header.frame_id, np.array([t.x, t.y, t.z]),
                rotation_matrix((q.x, q.y, q.z, q.w)))
    return static


def mount_pose(mount: Any) -> tuple[tuple[float, float], np.ndarray]:
    """A sensor mount [x m, y m, z m, roll, pitch, yaw rad] on the follower as the estimator
    takes it: its lever arm (x, y) m and rotation (3, 3), body from sensor."""
    return (float(mount[0]), float(mount[1])), rotation_matrix(rpy_quaternion(*mount[3:6]))


def pose_in_root(static: StaticTransforms,
                 frame: str) -> tuple[str, np.ndarray, np.ndarray] | None:
    """(the root of ``frame``'s chain of static transforms, its offset (3,) m and rotation
    (3, 3) in that root), or None for a loop."""
    offset, rotation, seen = np.zeros(3), np.eye(3), {frame}
    while frame in static:
        frame, t, R = static[frame]           # parent; the child's pose in it
        offset, rotation = R @ offset + t, R @ rotation
        if frame in seen:
            return None
        seen.add(frame)
    return frame, offset, rotation


def range_problem(msg: Any) -> tuple[str, str] | None:
    """Why a sensor_msgs/Range must be refused, as (counter, text), or None when it is
    acceptable: a range that is not finite, negative, or outside [min_range, max_range)
    (drivers report max_range for 'no reading'). The interval applies when the driver gives
    one (max_range > min_range): many UWB drivers leave both at 0."""
    value = float(msg.range)
    if not math.isfinite(value):
        return 'not_finite', 'range: not finite'
    low, high = float(msg.min_range), float(msg.max_range)
    if high > low and not low <= value < high:
        return 'out_of_range', f'range {value:.3f} m outside [{low:.3f}, {high:.3f}) m'
    if value < 0.0:
        return 'out_of_range', f'range {value:.3f} m is negative'
    return None


def waypoint_problem(msg: Any, follower_id: str) -> str | None:
    """Why a waypoint must be refused (None when it is acceptable): another follower, command
    lists empty, of unequal length or not finite."""
    if msg.follower_id != follower_id:
        return f'for follower {msg.follower_id!r}, not {follower_id!r}'
    commands = list(msg.linear_velocity) + list(msg.angular_velocity)
    if len(msg.linear_velocity) != len(msg.angular_velocity) or not commands:
        return 'linear and angular velocity lists must be non-empty and of equal length'
    if not all(math.isfinite(c) for c in commands):
        return 'commands are not finite'
    return None


def waypoint_mismatch(msg: Any, dt: float, p_o: tuple[float, float], r: float,
                      substeps: int, limited: bool = False) -> str | None:
    """Why a well-formed waypoint does not fit this follower's scenario (None when it does):
    its sub-step duration, slot or radius differ from ``dt``, ``p_o``, ``r`` (relative 1e-9),
    it has not ``substeps`` commands, or its position lies outside the disc (unless
    ``limited``: under a speed limit a follower away from its disc is sent to the reachable
    point nearest the slot). Names the parameter whose values differ, as the scenario
    handshake does."""
    def differs(a: float, b: float) -> bool:
        return not abs(a - b) <= 1e-9 * max(abs(a), abs(b), 1e-300)

    if differs(float(msg.substep_duration), dt):
        return (f"parameter 'dt' is {dt!r} here and {msg.substep_duration!r} in the "
                'waypoint')
    slot = (float(msg.formation_slot.x), float(msg.formation_slot.y))
    if differs(slot[0], p_o[0]) or differs(slot[1], p_o[1]):
        return (f"parameter 'formation_slot' is {list(p_o)!r} here and {list(slot)!r} in the "
                'waypoint')
    if differs(float(msg.radius), r):
        return f'the allowed deviation r is {r!r} m here and {msg.radius!r} m in the waypoint'
    if len(msg.linear_velocity) != substeps:
        return f'the waypoint has {len(msg.linear_velocity)} sub-step commands, not {substeps}'
    distance = math.hypot(msg.position.x - p_o[0], msg.position.y - p_o[1])
    if distance > r * (1.0 + 1e-9) and not limited:
        return (f'the waypoint position is {distance:.6g} m from the slot, outside the '
                f'allowed deviation r = {r:.6g} m')
    return None
