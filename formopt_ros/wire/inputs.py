"""Feeding received messages to an estimator session: the estimator node and the offline
re-estimation of a bag call exactly these, so the offline check validates the node's logic.

Each function checks the message (wrong follower, wrong kind, non-finite values), hands its
values to :class:`~formopt_ros.core.session.EstimatorSession` and returns the reason when the
message was refused (and counted), else None. ``now_ns`` is the receiving clock (realtime stamps
far in its future are refused); None skips that check.
"""
from __future__ import annotations

from typing import Any

from formopt_ros.core.session import EstimatorSession
from formopt_ros.wire.messages import (
    KIND_NAMES, foreign_run, header_ns, measurement_problem, odometry_problem, odometry_values,
    pose_values)


def odometry_frames(robot: str, robot_id: str) -> tuple[str, str]:
    """(frame_id, child_frame_id) of the odometry of robot 'leader' or 'follower' with id
    ``robot_id``: the leader's is in the fixed 'odom' frame, a follower's in '<id>/odom'."""
    return ('odom' if robot == 'leader' else f'{robot_id}/odom', robot_id)


def feed_odometry(session: EstimatorSession, robot: str, msg: Any, robot_id: str,
                  now_ns: int | None = None) -> str | None:
    """One sub-step of the odometry of robot 'follower' or 'leader' (whose id is
    ``robot_id``; its frames must be :func:`odometry_frames`)."""
    problem = odometry_problem(msg, *odometry_frames(robot, robot_id))
    if problem is not None:
        return session.reject('rejected_odometry', f'{robot} odometry {problem}')
    v, omega, _, _ = odometry_values(msg)
    return session.add_odometry(robot, header_ns(msg), v, omega, now_ns)


def feed_measurement(session: EstimatorSession, msg: Any, follower_id: str,
                     now_ns: int | None = None, run_id: str = '') -> str | None:
    """One range or bearing measurement (of run ``run_id``; '' accepts any); for a
    range-bearing follower, one part of its step's measurement."""
    foreign = foreign_run(msg, run_id)
    if foreign is not None:
        return session.reject('foreign_messages', f'measurement {foreign}')
    problem = measurement_problem(msg, follower_id, session.estimator.scenario.measurement)
    if problem is not None:
        return session.reject('rejected_measurements', f'measurement {problem}')
    return session.add_measurement(int(msg.step), header_ns(msg), float(msg.value),
                                   float(msg.variance), now_ns, KIND_NAMES[int(msg.kind)])


def feed_truth(session: EstimatorSession, msg: Any) -> None:
    """Ground truth (PoseStamped, evaluation only)."""
    session.add_truth(header_ns(msg), pose_values(msg.pose))
