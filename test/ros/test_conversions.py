"""ros/conversions builds the messages that wire/ reads: every value survives the round trip,
also through CDR bytes decoded by rosbags from the ros2msg schema (as the offline tools do)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from rclpy.serialization import serialize_message

from formopt_ros.bag.schema import message_definition
from formopt_ros.core.estimator import StepPlan
from formopt_ros.core.protocol import MotionCommand
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import Solution
from formopt_ros.ros import conversions
from formopt_ros.wire.description import RunDescription
from formopt_ros.wire.messages import (
    estimate_values, header_ns, measurement_problem, odometry_values, pose_values)

STAMP_NS = 1_234_567_890_123


def through_cdr(msg: object, type_name: str) -> object:
    """The message serialized by rclpy and decoded by rosbags from the bag schema."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.EMPTY)
    store.register(get_types_from_msg(message_definition(type_name), type_name))
    return store.deserialize_cdr(serialize_message(msg), type_name)


@pytest.fixture(params=['rclpy', 'rosbags'])
def decode(request: pytest.FixtureRequest):
    """Identity (the rclpy message) or the CDR round trip through rosbags."""
    if request.param == 'rclpy':
        return lambda msg, type_name: msg
    return through_cdr


def test_stamps_are_exact(decode) -> None:
    msg = conversions.pose_stamped(conversions.stamp(STAMP_NS), 'leader', np.zeros(3))
    assert header_ns(decode(msg, 'geometry_msgs/msg/PoseStamped')) == STAMP_NS


@pytest.mark.parametrize('yaw', [0.0, 1.0, -3.1, math.pi - 1e-9])
def test_estimate_and_truth_round_trip(decode, yaw: float) -> None:
    x = np.array([-1.25, 2.5, yaw])
    A = np.array([[2.0, 0.3, 0.1], [0.0, 1.0, -0.2], [0.0, 0.0, 0.5]])
    P = A @ A.T
    time = conversions.stamp(STAMP_NS)
    x_read, P_read = estimate_values(decode(conversions.estimate(time, 'leader', x, P),
                                            'geometry_msgs/msg/PoseWithCovarianceStamped'))
    # yaw through a quaternion: 1e-12 rad; positions and covariance exact
    np.testing.assert_allclose(x_read, x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(P_read, P)
    truth = decode(conversions.pose_stamped(time, 'leader', x), 'geometry_msgs/msg/PoseStamped')
    np.testing.assert_allclose(pose_values(truth.pose), x, rtol=0, atol=1e-12)


def test_odometry_and_measurement_round_trip(decode) -> None:
    time = conversions.stamp(STAMP_NS)
    odom = decode(conversions.odometry(time, 'f1/odom', 'f1', (1.0, 2.0, 0.5), 0.75, -0.25,
                                       (0.04, 0.01)), 'nav_msgs/msg/Odometry')
    assert odometry_values(odom) == (0.75, -0.25, 0.04, 0.01)
    assert (odom.header.frame_id, odom.child_frame_id) == ('f1/odom', 'f1')
    for kind, value in (('range', 2.25), ('bearing', -1.5)):
        meas = decode(conversions.measurement(time, 'f1', 'f1', 7, kind, value, 4e-4),
                      'formopt_interfaces/msg/Measurement')
        assert measurement_problem(meas, 'f1', kind) is None
        assert (meas.step, meas.value, meas.variance) == (7, value, 4e-4)


def test_waypoint_status_and_description_round_trip(decode) -> None:
    solution = Solution(p=np.array([-1.1, 2.05]), cost=0.013, cost_at_slot=0.02, method='rq',
                        measurement='bearing', solve_time_s=1.5e-4)
    plan = StepPlan(9, solution, MotionCommand((0.0, 2.5), (3.0, 0.0)))
    time = conversions.stamp(STAMP_NS)
    way = decode(conversions.waypoint(time, 'leader', 'f1', plan, np.array([-1.0, 2.0]), 0.22,
                                      0.05), 'formopt_interfaces/msg/Waypoint')
    assert (way.header.frame_id, way.step, way.strategy) == ('leader', 9, 'rq')
    assert (way.position.x, way.position.y, way.radius) == (-1.1, 2.05, 0.22)
    assert list(way.linear_velocity) == [0.0, 2.5] and list(way.angular_velocity) == [3.0, 0.0]
    status = decode(conversions.status(time, '', 'f1', 9, 'rq', 'bearing', 0.0125, plan,
                                       {'accepted_measurements': 9, 'rejected_odometry': 2}),
                    'formopt_interfaces/msg/PlannerStatus')
    assert (status.step, status.weighted_trace, status.cost_chosen) == (9, 0.0125, 0.013)
    assert (status.accepted_measurements, status.rejected_odometry) == (9, 2)
    description = RunDescription('f1', Scenario.paper('bearing'), 'rq', {}, 1, 2, 'lockstep', 9)
    msg = decode(conversions.description(time, 'run-1', '/f1/estimator_planner',
                                         description.to_json()),
                 'formopt_interfaces/msg/RunDescription')
    assert msg.run_id == 'run-1'
    assert RunDescription.from_json(msg.description) == description
