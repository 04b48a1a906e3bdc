"""The wire layer without ROS: topic table, run description, message readers and refusals
(fed with plain objects shaped like messages, as rosbags decodes them)."""
from __future__ import annotations

import json
import math
from types import SimpleNamespace as Msg

import numpy as np
import pytest

from formopt_ros.core.scenario import LeaderPath, Scenario
from formopt_ros.wire import topics
from formopt_ros.wire.description import RunDescription
from formopt_ros.wire.messages import (
    estimate_values, header_ns, measurement_problem, odometry_problem, odometry_values,
    pose_values, waypoint_problem, yaw_of)


def test_topic_table_names() -> None:
    """Robot namespaces: /leader/odom, /<follower>/...; prefixes resolve; lookups invert."""
    assert topics.leader_topic('leader_odom') == '/leader/odom'
    assert topics.follower_topic('estimate', 'f2') == '/f2/estimate'
    assert topics.resolve('/run7/f1', topics.BY_KEY['waypoint']) == '/run7/f1/waypoint'
    names = topics.formation_topics('leader', ('f1', 'f2'))
    assert len(names) == (len(topics.LEADER_TOPICS) + 2 * len(topics.FOLLOWER_TOPICS)
                          + len(topics.GLOBAL_TOPICS))
    assert '/tf' in names
    assert '/run7/f1/odom' in topics.formation_topics('leader', ('f1',), '/run7')
    assert names['/f2/description'] == 'formopt_interfaces/msg/RunDescription'
    assert topics.split_follower_topic('/run7/f1/status') == ('/run7/f1', 'status')
    assert topics.split_follower_topic('/chatter') is None
    assert {t.qos for t in topics.BY_KEY.values()} == {
        'stream', 'latched', 'tf', 'tf_static', 'clock', 'diagnostics'}


def test_run_description_round_trip_and_errors() -> None:
    description = RunDescription('f1', Scenario.paper('bearing', leader=LeaderPath.constant(
        1.0, 0.2)), 'gbs', {'cell': 0.01}, seed=3, trial=2, mode='realtime', steps=7,
        run_id='abc', leader_id='boss')
    again = RunDescription.from_json(description.to_json())
    assert again == description
    for text, match in (('{', 'not JSON'), ('{"format": "other"}', 'format'),
                        (json.dumps({'format': 'formopt_ros.run/1'}), 'lacks')):
        with pytest.raises(ValueError, match=match):
            RunDescription.from_json(text)


def stamp(ns: int) -> Msg:
    return Msg(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def odometry(child: str, v: float, omega: float, variances=(0.04, 0.01)) -> Msg:
    covariance = [0.0] * 36
    covariance[0], covariance[35] = variances
    return Msg(header=Msg(stamp=stamp(5), frame_id='odom'), child_frame_id=child,
               twist=Msg(twist=Msg(linear=Msg(x=v), angular=Msg(z=omega)),
                         covariance=covariance))


def test_readers() -> None:
    """Stamps in integer ns, yaw from quaternions, odometry twist, estimate covariance."""
    assert header_ns(Msg(header=Msg(stamp=stamp(12_000_000_345)))) == 12_000_000_345
    yaw = 2.5
    quaternion = Msg(x=0.0, y=0.0, z=math.sin(yaw / 2), w=math.cos(yaw / 2))
    assert yaw_of(quaternion) == pytest.approx(yaw, abs=1e-15)
    pose = Msg(position=Msg(x=1.0, y=-2.0), orientation=quaternion)
    np.testing.assert_allclose(pose_values(pose), [1.0, -2.0, yaw], atol=1e-15)
    assert odometry_values(odometry('leader', 1.5, 0.25)) == (1.5, 0.25, 0.04, 0.01)
    P = np.array([[1.0, 0.1, 0.2], [0.1, 2.0, 0.3], [0.2, 0.3, 3.0]])
    covariance = np.zeros((6, 6))
    covariance[np.ix_((0, 1, 5), (0, 1, 5))] = P
    x, P_read = estimate_values(Msg(pose=Msg(pose=pose, covariance=covariance.ravel())))
    np.testing.assert_array_equal(P_read, P)


@pytest.mark.parametrize('change,reason', [
    ({'follower_id': 'other'}, 'for follower'), ({'kind': 1}, 'kind'),
    ({'value': math.nan}, 'not finite'), ({'variance': 0.0}, 'variance'),
    ({'value': -1.0}, 'negative')])
def test_measurement_refusals(change: dict, reason: str) -> None:
    good = dict(follower_id='f1', kind=0, value=2.0, variance=0.01, step=1)
    assert measurement_problem(Msg(**good), 'f1', 'range') is None
    assert reason in measurement_problem(Msg(**{**good, **change}), 'f1', 'range')


def test_odometry_and_waypoint_refusals() -> None:
    assert odometry_problem(odometry('f1', 1.0, 0.0), 'f1') is None
    assert 'child_frame_id' in odometry_problem(odometry('f2', 1.0, 0.0), 'f1')
    assert 'not finite' in odometry_problem(odometry('f1', math.inf, 0.0), 'f1')
    assert 'variances' in odometry_problem(odometry('f1', 1.0, 0.0, (-1.0, 0.0)), 'f1')
    good = dict(follower_id='f1', linear_velocity=[0.0, 1.0], angular_velocity=[0.5, 0.0])
    assert waypoint_problem(Msg(**good), 'f1') is None
    assert 'equal length' in waypoint_problem(Msg(**{**good, 'linear_velocity': [1.0]}), 'f1')
    assert 'not finite' in waypoint_problem(
        Msg(**{**good, 'angular_velocity': [math.nan, 0.0]}), 'f1')
