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
from formopt_ros.wire.description import (
    LeaderDescription, RunDescription, follower_differences, leader_differences)
from formopt_ros.wire.messages import (
    estimate_values, foreign_run, header_ns, measurement_problem, odometry_problem,
    odometry_values, pose_values, twist_noise, waypoint_mismatch, waypoint_problem, yaw_of)


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
    ({'header': Msg(frame_id='f2')}, 'frame_id')])
def test_measurement_refusals(change: dict, reason: str) -> None:
    good = dict(header=Msg(frame_id='f1'), follower_id='f1', kind=0, value=2.0, variance=0.01,
                step=1)
    assert measurement_problem(Msg(**good), 'f1', 'range') is None
    assert reason in measurement_problem(Msg(**{**good, **change}), 'f1', 'range')


def test_foreign_run() -> None:
    """A message of another run is foreign; '' accepts any; a message without run_id (a 0.1.x
    bag) belongs to any run."""
    assert foreign_run(Msg(run_id='a'), 'a') is None and foreign_run(Msg(run_id='b'), '') is None
    assert "of run 'b', not 'a'" == foreign_run(Msg(run_id='b'), 'a')
    assert foreign_run(Msg(), 'a') is None


def test_odometry_and_waypoint_refusals() -> None:
    assert odometry_problem(odometry('f1', 1.0, 0.0), 'odom', 'f1') is None
    assert 'child_frame_id' in odometry_problem(odometry('f2', 1.0, 0.0), 'odom', 'f1')
    assert "frame_id 'odom' is not 'f1/odom'" in odometry_problem(odometry('f1', 1.0, 0.0),
                                                                  'f1/odom', 'f1')
    assert 'not finite' in odometry_problem(odometry('f1', math.inf, 0.0), 'odom', 'f1')
    assert 'variances' in odometry_problem(odometry('f1', 1.0, 0.0, (-1.0, 0.0)), 'odom', 'f1')
    good = dict(follower_id='f1', linear_velocity=[0.0, 1.0], angular_velocity=[0.5, 0.0])
    assert waypoint_problem(Msg(**good), 'f1') is None
    assert 'equal length' in waypoint_problem(Msg(**{**good, 'linear_velocity': [1.0]}), 'f1')
    assert 'not finite' in waypoint_problem(
        Msg(**{**good, 'angular_velocity': [math.nan, 0.0]}), 'f1')


@pytest.mark.parametrize('change,reason', [
    ({}, None), ({'substep_duration': 0.02}, "parameter 'dt' is 0.05 here and 0.02"),
    ({'formation_slot': Msg(x=-1.0, y=2.5)}, "parameter 'formation_slot'"),
    ({'radius': 0.3}, 'allowed deviation r'),
    ({'linear_velocity': [1.0]}, '1 sub-step commands, not 2'),
    ({'position': Msg(x=-1.0, y=2.3)}, 'outside the allowed deviation')])
def test_waypoint_must_fit_the_follower(change: dict, reason: str | None) -> None:
    """The waypoint carries dt, the slot and r: a follower with another scenario refuses it,
    naming the parameter (the handshake's second line of defence)."""
    r = 0.1 * 5 ** 0.5
    good = dict(substep_duration=0.05, formation_slot=Msg(x=-1.0, y=2.0), radius=r,
                linear_velocity=[0.0, 1.0], position=Msg(x=-1.0, y=2.1))
    problem = waypoint_mismatch(Msg(**{**good, **change}), 0.05, (-1.0, 2.0), r, 2)
    assert problem is None if reason is None else reason in problem


def test_descriptions_differ_by_parameter_name() -> None:
    """The scenario handshake names node parameters with both values: dt, the slot, the
    sensor's sigma, r as deviation_fraction, the run id; the leader side: its path, dt and
    whether it serves this follower."""
    base = RunDescription('f1', Scenario.paper('range'), 'ram', run_id='run_a')
    assert follower_differences(base, base) == []
    other = RunDescription('f1', Scenario.paper('range', dt=0.02, p_o=(-1.0, -2.5), sigma=0.2,
                                                r=0.5), 'mtf', run_id='run_b')
    names = {name: (mine, theirs) for name, mine, theirs in follower_differences(base, other)}
    assert names['dt'] == (0.05, 0.02) and names['formation_slot'] == ([-1.0, -2.0],
                                                                       [-1.0, -2.5])
    assert names['range_sigma'] == (0.1, 0.2) and names['run_id'] == ('run_a', 'run_b')
    assert 'deviation_fraction' in names and 'strategy' not in names
    assert 'strategy' in dict((n, 0) for n, _, _ in follower_differences(base, other, True))
    leader = LeaderDescription('leader', LeaderPath.constant(1.0, 0.5), 0.05, ('f2',),
                               run_id='run_a')
    assert {name for name, _, _ in leader_differences(base, leader)} == {
        'path', 'omega_leader', 'followers'}
    assert leader_differences(base, base.leader_view()) == []


def test_run_id_empty_accepts_any_run() -> None:
    """My run_id '' accepts a peer of any run (an estimator fed by a replayed bag); a peer
    whose run_id is '' does not match my 'run_a' (its messages would be refused)."""
    import dataclasses
    mine = RunDescription('f1', Scenario.paper('range'), 'ram', run_id='')
    recorded = dataclasses.replace(mine, run_id='run_b40')
    assert follower_differences(mine, recorded) == []
    assert leader_differences(mine, recorded.leader_view()) == []
    assert follower_differences(recorded, mine) == [('run_id', 'run_b40', '')]


@pytest.mark.parametrize('variances, expected', [
    ((0.04, 0.01), (0.2, 0.1)), ((0.0, 0.01), None), ((1e6, 1e6), None), ((-1.0, 0.01), None),
    ((math.nan, 0.01), None), ((100.0, 100.0), (10.0, 10.0))])
def test_twist_noise_takes_plausible_covariances_only(variances: tuple, expected: tuple | None
                                                      ) -> None:
    """An odometry's own twist variances are used in (0, 100]; 0, -1, NaN and the 1e6 drivers
    write for 'unknown' fall back to the configured noise (None)."""
    covariance = [0.0] * 36
    covariance[0], covariance[35] = variances
    noise = twist_noise(Msg(twist=Msg(covariance=covariance)))
    assert noise == (pytest.approx(expected) if expected else None)


def test_the_frames_of_a_run_are_reserved_ids() -> None:
    """No robot id can take a frame name of the run (a TF cycle: id 'odom')."""
    from formopt_ros.core.formation import RESERVED_FRAMES
    from formopt_ros.wire.topics import ODOM_FRAME, follower_frames, real_frames
    leaves = {name.rpartition('/')[2] for frames in (follower_frames('x'),
                                                     real_frames('x', 'range'),
                                                     real_frames('x', 'bearing'))
              for name in frames.values()} - {'x'}
    assert {ODOM_FRAME} | leaves <= set(RESERVED_FRAMES)


def test_strategy_changes_round_trip_and_old_descriptions_read() -> None:
    """A description with a mid-run change reads back equal and names both strategies; one
    without changes writes the same JSON as before (no key), so old bags read unchanged."""
    import json

    from formopt_ros.core.scenario import Scenario
    from formopt_ros.wire.description import StrategyChange
    plain = RunDescription('f1', Scenario.paper('range'), 'ram', {'cell': 0.01}, seed=3)
    assert 'strategy_changes' not in json.loads(plain.to_json())
    changed = RunDescription('f1', Scenario.paper('range'), 'mtf', strategy_changes=(
        StrategyChange(17, 'periodic', {'period': 3}), StrategyChange(40, 'mtf')))
    again = RunDescription.from_json(changed.to_json())
    assert again == changed and again.strategies() == ['mtf', 'periodic']
    assert again.strategy_changes[0].step == 17
    assert RunDescription.from_json(plain.to_json()).strategy_changes == ()
