"""Re-estimate a bag of standard message types (another team's robots, a real data set) through a
topic map: the asynchronous estimator over its odometry and ranges or bearings, the planner off,
evaluated against ground-truth poses when the bag has them.

A topic map (:class:`~formopt_ros.wire.topic_map.TopicMap`) is a YAML file::

    leader_odometry: /leader/odom        # nav_msgs/Odometry of the leader (twist used)
    follower_odometry: /follower/odom    # nav_msgs/Odometry of the follower
    range: /uwb/range                    # sensor_msgs/Range between them, or instead
    # bearing: /f1/bearing               # geometry_msgs/Vector3Stamped toward the leader
    leader_truth: /leader/mocap          # optional geometry_msgs/PoseStamped, a fixed frame
    follower_truth: /follower/mocap      # with leader_truth or neither: the same fixed frame
    # relative_truth: /f1/truth          # instead of both: PoseStamped of the follower in the
                                         # leader's frame (field_sim's truth)
    estimator:                           # optional: the filter's settings (defaults below)
      sigma_v: 0.05                      # odometry speed noise, m/s
      sigma_omega: 0.05                  # odometry yaw-rate noise, rad/s
      sigma_v_leader: null               # the leader's, where it differs (null: sigma_v)
      sigma_omega_leader: null           # (null: sigma_omega)
      range_sigma: 0.1                   # range noise, m (where a message has no variance)
      range_variance: 0.0                # every range's variance, m^2 (0: the message's when
                                         # in (0, 100], else range_sigma^2), as the live node
      bias_sigma: 0.0                    # range-bias state (0: none), m
      bias_walk: 0.0                     # m / sqrt(s)
      huber: 0.0                         # Huber threshold, standard deviations (0: off)
      gate: 0.0                          # innovation gate, standard deviations (0: 10)
      reopen_after: 0                    # gated in a row before the filter re-opens (0: 3;
                                         # the node's 10 coasts through NLOS bursts)
      initial_covariance: [0.1, 0.1, 0.01]
      initial_pose: []                   # [x m, y m, phi rad] in the leader frame at the
                                         # first range, as the node's initial_pose or slot
      bearing_sigma: 0.02                # bearing noise, rad
      sensor_mount: []                   # the sensor frame on the follower, [x m, y m, z m,
                                         # roll, pitch, yaw rad] (the node's sensor_mount;
                                         # must agree with the bag's /tf_static if it has
                                         # one); []: from /tf_static, else the body frame

The initial estimate is ``initial_pose`` when given, else the truth at the first measurement
when the bag has truth, else [|p| = the first range along -x, 0] (a range has no direction: a
follower beside the leader starts mirrored or turned, metres off, unless initial_pose says where
it was; a bearing follower without either starts along the first bearing at |p| = 2 m, a
guess). Its uncertainty is ``initial_covariance``.
"""
from __future__ import annotations

import csv
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from formopt_ros.bag import BagError
from formopt_ros.bag.reader import Bag
from formopt_ros.core.asynchronous import AsyncEstimator, AsyncSettings
from formopt_ros.core.consistency import ERROR
from formopt_ros.core.estimator import EstimatorPlanner
from formopt_ros.core.field import relative_pose
from formopt_ros.core.model import (
    direction_bearing, normalized_estimation_error, state_difference)
from formopt_ros.core.strategies import make_strategy
from formopt_ros.wire.messages import (
    estimate_values, header_ns, message_variance, mount_pose, pose_in_root, pose_values,
    range_problem, range_variance, static_transforms, twist_noise)
from formopt_ros.wire.topic_map import ESTIMATOR_DEFAULTS, TopicMap, filter_model


@dataclass
class ForeignData:
    """The inputs and the truth of a bag, decoded: stamps in ns.

    Attributes:
        odometry: per robot ('follower', 'leader'), (stamp, v m/s, omega rad/s, its own noise
            (sigma_v, sigma_omega) from the twist covariance, or None).
        measurements: (stamp, range m or bearing rad in the body frame's orientation, the
            message's variance m^2 or None when unknown (bearings: None)).
        kind: the follower's sensor, 'range' or 'bearing'.
        offset: the sensor's lever arm on the follower (x, y) m (bearings; None: at its
            centre).
        truth: per robot, (stamp, x m, y m, yaw rad) in a fixed frame, or under 'relative'
            the follower's pose in the leader's frame (empty without truth).
        refused: messages dropped as the live node drops them: {'not_finite': n,
            'out_of_range': n}.
    """

    odometry: dict[str, list[tuple[int, float, float, tuple[float, float] | None]]]
    measurements: list[tuple[int, float, float | None]]
    truth: dict[str, np.ndarray]
    refused: dict[str, int] = field(default_factory=lambda: {'not_finite': 0,
                                                             'out_of_range': 0})
    kind: str = 'range'
    offset: tuple[float, float] | None = None

    def relative_truth(self, stamp: int) -> np.ndarray | None:
        """The follower's true pose in the leader's frame at ``stamp`` (poses interpolated
        linearly, yaw unwrapped), or None outside the truth's time span."""
        poses: list[tuple[float, float, float]] = []
        if 'relative' in self.truth:
            relative = self.truth['relative']
            if not relative[0, 0] <= stamp <= relative[-1, 0]:
                return None
            return np.array([float(np.interp(stamp, relative[:, 0], relative[:, i]))
                             for i in (1, 2, 3)])
        for robot in ('leader', 'follower'):
            samples = self.truth.get(robot)
            if samples is None or not len(samples) or not \
                    samples[0, 0] <= stamp <= samples[-1, 0]:
                return None
            x, y, yaw = (float(np.interp(stamp, samples[:, 0], samples[:, i])) for i in (1, 2, 3))
            poses.append((x, y, yaw))
        return relative_pose(poses[0], poses[1])


def sensor_mount(bag: Bag, topics: TopicMap,
                 frame: str) -> tuple[tuple[float, float], np.ndarray]:
    """The measurement frame's mount on the follower: its lever arm (x, y) m and rotation
    (3, 3) from the bag's /tf_static (the frame's pose in the root of its chain, the body
    frame) or the map's sensor_mount (BagError when both give one and they differ by more than
    1 mm or 1 mrad), else the body frame itself for ranges and for bearings without a
    frame_id; BagError for bearings in a frame with no known mount (the live node refuses them
    too)."""
    given = topics.estimator['sensor_mount']
    mount = mount_pose(given) if given else None
    found = bag.find('/tf_static', required=False)
    static = static_transforms(m for _, m in bag.decode(found)) if found else {}
    chain = pose_in_root(static, frame) if frame in static else None
    if chain is not None:
        recorded = ((float(chain[1][0]), float(chain[1][1])), chain[2])
        if mount is not None and (math.dist(mount[0], recorded[0]) > 1e-3 or
                                  np.abs(mount[1] - recorded[1]).max() > 1e-3):
            raise BagError(f'estimator: sensor_mount {given} differs from the mount of frame '
                           f'{frame!r} on the bag\'s /tf_static (x, y {recorded[0][0]:.4g}, '
                           f'{recorded[0][1]:.4g} m): leave sensor_mount out, or correct it')
        return recorded
    if mount is not None:
        return mount
    if topics.kind == 'bearing' and frame:
        raise BagError(f"the bearings on {topics.bearing!r} are in frame {frame!r}, whose mount "
                       'the bag\'s /tf_static does not give: set estimator: sensor_mount '
                       '[x, y, z, roll, pitch, yaw] (the camera on the follower)')
    return (0.0, 0.0), np.eye(3)


def read_foreign(bag: Bag, topics: TopicMap) -> ForeignData:
    """Decode the mapped topics of ``bag``; BagError naming a topic the bag lacks."""
    def resolved(topic: str) -> str:
        found = bag.find(topic, required=False)
        if found is None:
            raise BagError(f'the topic map names {topic!r}, which the bag does not have '
                           f'(it has: {", ".join(sorted(bag.counts()))})')
        return found

    def decoded(topic: str, type_name: str) -> list[Any]:
        return [m for _, m in bag.decode(resolved(topic), type_name)]

    if resolved(topics.leader_odometry) == resolved(topics.follower_odometry):
        raise BagError(f'the topic map names {resolved(topics.leader_odometry)!r} as both '
                       "leader_odometry and follower_odometry: each robot's odometry is its "
                       'own topic')

    refused = {'not_finite': 0, 'out_of_range': 0}
    odometry: dict[str, list[tuple[int, float, float, tuple[float, float] | None]]] = {}
    for robot in ('follower', 'leader'):
        odometry[robot] = []
        for m in decoded(getattr(topics, f'{robot}_odometry'), 'nav_msgs/msg/Odometry'):
            v, omega = float(m.twist.twist.linear.x), float(m.twist.twist.angular.z)
            if not (math.isfinite(v) and math.isfinite(omega)):
                refused['not_finite'] += 1
                continue
            odometry[robot].append((header_ns(m), v, omega, twist_noise(m)))
    messages = decoded(topics.measurement, 'sensor_msgs/msg/Range' if topics.kind == 'range'
                       else 'geometry_msgs/msg/Vector3Stamped')
    frame = messages[0].header.frame_id if messages else ''
    (x, y), rotation = sensor_mount(bag, topics, frame)
    offset = None if (x, y) == (0.0, 0.0) else (x, y)
    measurements = []
    for m in messages:
        if topics.kind == 'range':
            if (problem := range_problem(m)) is not None:
                refused[problem[0]] += 1
            else:
                measurements.append((header_ns(m), float(m.range),
                                     message_variance(m.variance)))
            continue
        direction = (m.vector.x, m.vector.y, m.vector.z)
        if not all(math.isfinite(c) for c in direction):
            refused['not_finite'] += 1
        elif (value := direction_bearing(direction, rotation)) is None:
            refused['out_of_range'] += 1           # vertical in the body frame
        else:
            measurements.append((header_ns(m), value, None))
    for name, stamps in (('follower_odometry', [o[0] for o in odometry['follower']]),
                         ('leader_odometry', [o[0] for o in odometry['leader']]),
                         (topics.kind, [r[0] for r in measurements])):
        if len(stamps) > 1 and min(stamps) == max(stamps):
            raise BagError(f'every message on {resolved(getattr(topics, name))!r} carries the '
                           f'header stamp {stamps[0]} ns: the estimator orders its inputs by '
                           'their stamps (record with the stamps set, e.g. by the driver)')
    truth = {}
    sources = {'relative': topics.relative_truth} if topics.relative_truth else \
        {robot: getattr(topics, f'{robot}_truth') for robot in ('leader', 'follower')
         if topics.leader_truth and topics.follower_truth}
    for key, topic in sources.items():
        rows = [(header_ns(m), *pose_values(m.pose))
                for m in decoded(topic, 'geometry_msgs/msg/PoseStamped')]
        samples = np.array(sorted(rows), dtype=float)
        samples[:, 3] = np.unwrap(samples[:, 3])
        truth[key] = samples
    return ForeignData(odometry, sorted(measurements), truth, refused, topics.kind, offset)


@dataclass
class ForeignResult:
    """What the estimator made of a foreign bag.

    Attributes:
        stamps, estimates, covariances: per applied measurement (ns, (3,), (3, 3)).
        nees, errors: per measurement with truth: NEES of [x, y, phi], position error (m).
        counters: the asynchronous estimator's counters.
        bias: the final range-bias estimate (m), None without a bias state.
        consistency: the consistency watch over every measurement's NIS and, with truth, NEES
            (:meth:`~formopt_ros.core.consistency.ConsistencyWatch.summary`); its latched
            ERROR makes the re-estimate not ok.
    """

    stamps: list[int]
    estimates: list[np.ndarray]
    covariances: list[np.ndarray]
    nees: list[float]
    errors: list[float]
    counters: dict[str, int]
    bias: float | None
    consistency: dict[str, Any] = field(default_factory=dict)

    def summary(self, skip: int = 0) -> dict[str, Any]:
        """Mean NEES and RMS error over the measurements after the first ``skip``, the consistency
        verdict and ``ok`` (no latched ERROR)."""
        nees, errors = self.nees[skip:], self.errors[skip:]
        return {'ok': self.consistency.get('worst', {}).get('level') != ERROR,
                'consistency': self.consistency,
                'measurements': len(self.stamps), 'evaluated': len(nees),
                'mean_nees': float(np.mean(nees)) if nees else None,
                'rmse_m': float(np.sqrt(np.mean(np.square(errors)))) if errors else None,
                'final_bias_m': self.bias, 'counters': self.counters}


def estimate_foreign(data: ForeignData, settings: dict[str, Any]) -> ForeignResult:
    """Run the asynchronous estimator (planner off) over ``data`` in stamp order."""
    s = {**ESTIMATOR_DEFAULTS, **settings}
    first, value = data.measurements[0][:2]
    initial = np.array(s['initial_pose'], dtype=float) if len(s['initial_pose']) else \
        data.relative_truth(first)
    if initial is None:         # a range along -x; a bearing from the leader, 2 m out
        initial = np.array([-value, 0.0, 0.0]) if data.kind == 'range' else \
            np.array([-2.0 * math.cos(value), -2.0 * math.sin(value), 0.0])
    slot = (float(initial[0]), float(initial[1]))
    scenario, noise = filter_model(s, slot, data.kind)
    filter_ = EstimatorPlanner(scenario, make_strategy('mtf'), None, noise,
                               sensor_offset=data.offset)
    filter_.state[:3] = initial
    tracker = AsyncEstimator(filter_, first - 1, AsyncSettings())
    inputs = sorted([(t, 0, robot, (v, w, noise)) for robot, stream in data.odometry.items()
                     for t, v, w, noise in stream if t > first - 1] +
                    [(t, 1, 'z', (z, variance, None)) for t, z, variance in data.measurements],
                    key=lambda item: item[:2])
    result = ForeignResult([], [], [], [], [], {}, None)

    def record(applied: Any) -> None:
        result.stamps.append(applied.stamp_ns)
        result.estimates.append(applied.x)
        result.covariances.append(applied.P)
        truth = data.relative_truth(applied.stamp_ns)
        if truth is not None:
            nees = normalized_estimation_error(truth, applied.x, applied.P)
            result.nees.append(nees)
            result.errors.append(float(np.hypot(*state_difference(truth, applied.x)[:2])))
            tracker.watch.add_nees(nees, len(result.stamps))

    for t, _, kind, values in inputs:
        if kind == 'z':
            tracker.add_measurement(t, values[0], range_variance(
                s['range_variance'], values[1], s['range_sigma'] ** 2)
                if data.kind == 'range' else s['bearing_sigma'] ** 2)
        else:
            tracker.add_odometry(kind, t, *values)
        for applied in tracker.advance(t):
            record(applied)
    for applied in tracker.advance(inputs[-1][0] + 10**10):     # the last ones, lag passed
        record(applied)
    result.consistency = tracker.watch.summary()
    result.counters = {**tracker.counters.as_dict(),
                       **{f'refused_{k}': v for k, v in data.refused.items()}}
    result.bias = float(filter_.state[3]) if filter_.state.size == 4 else None
    return result


#: The columns of :func:`write_estimates`.
ESTIMATE_COLUMNS = ('stamp_ns', 'x_m', 'y_m', 'phi_rad', 'var_x', 'cov_xy', 'cov_xphi', 'var_y',
                    'cov_yphi', 'var_phi')


def write_estimates(path: Path, result: ForeignResult) -> None:
    """The estimate at every applied measurement as CSV (:data:`ESTIMATE_COLUMNS`): the follower's
    pose in the leader's frame (m, rad) and its covariance's upper triangle."""
    rows = [(stamp, *x[:3], P[0, 0], P[0, 1], P[0, 2], P[1, 1], P[1, 2], P[2, 2])
            for stamp, x, P in zip(result.stamps, result.estimates, result.covariances)]
    with open(path, 'w', newline='') as handle:
        writer = csv.writer(handle)
        writer.writerow(ESTIMATE_COLUMNS)
        writer.writerows([stamp, *(repr(float(v)) for v in values)] for stamp, *values in rows)


def tracking_errors(bag: Bag, estimate_topic: str, truth_topic: str,
                    skip_s: float = 3.0) -> dict[str, float | int | None]:
    """How well a live estimator tracked: its estimates (PoseWithCovarianceStamped) against
    the truth (PoseStamped, same frame) of the same stamps, after the first ``skip_s`` s.

    Returns:
        {'count', 'mean_nees' (3 is consistent), 'rms_position_error_m'}; None values when
        no stamp matches.
    """
    truth = {header_ns(m): pose_values(m.pose) for _, m in bag.decode(truth_topic)}
    first = min(truth, default=0)
    pairs = []
    for _, message in bag.decode(estimate_topic):
        stamp = header_ns(message)
        if stamp in truth and stamp - first > skip_s * 1e9:
            pairs.append((truth[stamp], *estimate_values(message)))
    if not pairs:
        return {'count': 0, 'mean_nees': None, 'rms_position_error_m': None}
    nees = [float(normalized_estimation_error(t, x, P)) for t, x, P in pairs]
    errors = [float(np.hypot(*state_difference(t, x)[:2])) for t, x, _ in pairs]
    return {'count': len(pairs), 'mean_nees': float(np.mean(nees)),
            'rms_position_error_m': float(np.sqrt(np.mean(np.square(errors))))}


__all__ = ['ESTIMATE_COLUMNS', 'ForeignData', 'ForeignResult', 'estimate_foreign', 'read_foreign',
           'tracking_errors', 'write_estimates']
