"""follower_estimator: a follower's estimator, planner and velocity controller on real robots:
standard odometry and range messages in; estimate, target, cmd_vel and diagnostics out."""
from __future__ import annotations

import dataclasses
import math
import sys
import time
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped, Twist, Vector3Stamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from sensor_msgs.msg import Range
from tf2_msgs.msg import TFMessage

from formopt_ros.core.asynchronous import AsyncEstimator, AsyncSettings
from formopt_ros.core.consistency import WARN
from formopt_ros.core.domain import check_deviation_domain
from formopt_ros.core.controller import Limits, required_velocity, twist_toward
from formopt_ros.core.estimator import EstimatorPlanner, RealNoise
from formopt_ros.core.model import direction_bearing
from formopt_ros.core.protocol import NS_PER_S
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import make_strategy
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.guard import RunGuard
from formopt_ros.ros.params import Param, ParameterError, check_angles, declare
from formopt_ros.ros.run_config import (
    BEARING_SIGMA, DEVIATION, DT, INITIAL_COVARIANCE, RANGE_SIGMA, SAFETY_DISTANCE,
    SIGMA_OMEGA, SIGMA_OMEGA_LEADER, SIGMA_V, SIGMA_V_LEADER, SLOT, SUMMARY_PATH,
    strategy_options, strategy_params, value_range)
from formopt_ros.ros.runtime import (
    Throttle, check_output_path, node_main, stops_on_a_plan_outside_the_disc, write_summary)
from formopt_ros.wire.messages import (
    StillTwist, header_ns, message_variance, mount_pose, pose_in_root, pose_values,
    range_problem, range_variance, static_transforms, twist_noise)

#: A pause of every input longer than max(reorder_lag, this) starts a catch-up, s.
MIN_PAUSE = 0.05
#: The longest catch-up after a pause, s (draining a backlog takes a fraction of the pause,
#: more on a loaded machine).
MAX_CATCH_UP = 1.0

#: Inputs dropped as late beyond this share of a status period's inputs are an ERROR (fewer:
#: a delay spike, a WARN).
LATE_FRACTION = 0.1

#: The odometry streams: the filter starts once both robots' odometry has come.
ODOMETRY_STREAMS = ('odom', 'leader_odom')
#: The filter starting this long (s) after the first input while the leader drives faster than
#: START_SPEED (m/s) is a WARN: the held follower left its slot meanwhile.
LATE_START_S, START_SPEED = 0.5, 0.05
#: More than this share of a status period's plans beyond the base's reach is a WARN.
UNREACHABLE_FRACTION = 0.5
#: The sensors a follower may carry (its measurement stream is named after the sensor).
SENSORS = ('range', 'bearing')

PARAMS = [
    Param('sensor', 'range', 'what the follower measures: range (sensor_msgs/Range on range) '
          'or bearing (geometry_msgs/Vector3Stamped on bearing: a direction toward the leader '
          'in the sensor frame)', choices=SENSORS),
    Param('leader_frame', 'leader', "frame id of the published estimate and target (the "
          "leader's body frame)"),
    Param('base_frame', 'base_link', "the follower's body frame: the sensor's mount is its pose "
          'in this frame through /tf_static'),
    Param('sensor_mount', [0.0], "the sensor frame's pose on the follower, [x m, y m, z m, "
          "roll rad, pitch rad, yaw rad] ([0.0]: from /tf_static, the measurement's frame_id "
          'in base_frame; a measurement in base_frame needs none)', -100.0, 100.0),
    Param('follower_child_frame', '', "child_frame_id the follower's odometry must carry "
          "('': any)"),
    Param('leader_child_frame', '', "child_frame_id the leader's odometry must carry ('': any)"),
    SLOT, DEVIATION, RANGE_SIGMA, BEARING_SIGMA,
    Param('range_variance', 0.0, 'variance of every range, m^2 (0: the message\'s variance '
          'when in (0, 100], else range_sigma^2)', *value_range('range_variance')),
    SIGMA_V, SIGMA_OMEGA,
    # a leader's odometry reaches a follower with noise (the simulated leader's is exact)
    dataclasses.replace(SIGMA_V_LEADER, default=0.05),
    dataclasses.replace(SIGMA_OMEGA_LEADER, default=0.05), INITIAL_COVARIANCE,
    Param('initial_pose', [0.0], "initial estimate [x m, y m, phi rad] in the leader frame "
          "([0.0]: [slot, 0])", -1e4, 1e4),
    DT,
    Param('bias_sigma', 0.3, 'range only: initial std of a range-bias state, m (0: none; UWB '
          'radios carry biases of 0.1-0.4 m)', 0.0, 100.0),
    Param('bias_walk', 0.002, 'random walk of the range bias, m/sqrt(s)', 0.0, 10.0),
    Param('huber', 2.5, 'Huber threshold in innovation standard deviations (0: off)', 0.0,
          100.0),
    Param('gate', 5.0, 'innovation gate in standard deviations: a measurement further out is '
          "not used (0: 10, the simulated filter's)", 0.0, 100.0),
    Param('reopen_after', 10, 'measurements refused by the gate in a row after which the '
          'filter takes itself to be lost and re-opens with an inflated covariance (the '
          'simulated filter\'s: 3): a burst of non-line-of-sight ranges up to this long is '
          'coasted through on odometry, a longer one may be fused', 1, 10**6),
    Param('max_gated_share', 0.5, 'share of the last measurements (up to 50) the innovation '
          'gate may refuse before the filter counts as inconsistent (an ERROR; the base stops): '
          'non-line-of-sight ranges are refused rightly, a diverged filter refuses most', 0.0,
          1.0),
    Param('reorder_lag', 0.1, 'longest wait of a range for odometry and earlier ranges, s',
          0.0, 10.0),
    Param('max_gap', 0.5, 'odometry intervals longer than this count as gaps, s', 1e-3, 60.0),
    Param('future_tolerance', 0.05, 'messages stamped further ahead of this clock are refused '
          '(clocks out of sync: a message cannot arrive before it was stamped), s', 0.0, 60.0),
    Param('stale_timeout', 1.0, 'a stream silent (or stamped behind this clock) this long is an '
          'ERROR (half as long: WARN), and the base stops; the filter starts at the first input '
          'stamped within it of this clock, s', 0.05, 60.0),
    Param('stop_when_inconsistent', True, 'stop the base (zero cmd_vel) for the rest of the '
          'run once the consistency watch raised its latched ERROR, or an input topic had a '
          "second publisher for 5 s (another robot's messages mixed in; 25 s when both have one "
          'name, a restarted driver) (false: keep driving on the estimate; the run is not ok '
          'either way)'),
    Param('control_rate', 20.0, 'cmd_vel rate, Hz', 0.1, 1000.0),
    Param('horizon', 0.5, 'time the controller gives itself to reach the target, s', 0.01, 60.0),
    Param('max_speed', 2.0, 'largest forward speed of the base, m/s', 1e-3, 100.0),
    Param('plan_within_reach', False, 'plan inside the set the base reaches in 2 dt at '
          'max_speed (false: anywhere in the disc, as the paper, and the controller clips; '
          'docs/real_robots.md compares the two)'),
    SAFETY_DISTANCE,
    Param('max_yaw_rate', 3.0, 'largest yaw rate of the base, rad/s',
          *value_range('max_yaw_rate')),
    Param('max_acceleration', 2.0, 'largest acceleration of the base, m/s^2', 1e-3, 1000.0),
    Param('max_yaw_acceleration', 10.0, 'largest yaw acceleration of the base, rad/s^2', 1e-3,
          1e4),
    # the strategy is built once at start: its parameters are read-only here
    *(dataclasses.replace(spec, read_only=True) for spec in strategy_params()),
    Param('status_period', 1.0, 'publish /diagnostics this often, s', 0.05, 60.0),
    Param('duration', 0.0, 'run this long (node clock, s), then exit (0: until stopped)', 0.0,
          1e9),
    SUMMARY_PATH]
SUMMARY = ("A follower on real robots: its nav_msgs/Odometry (odom), the leader's "
           "(leader_odom, over the network) and sensor_msgs/Range (range) at any rates in; the "
           'asynchronous EKF (exact integration of each odometry interval, ranges at their '
           'stamps), the strategy re-planned every 2 dt, and geometry_msgs/Twist on cmd_vel '
           'within the base limits; estimate, target and /diagnostics out.')


def delayed_streams(delays: dict[str, list[float]], lag: float) -> tuple[list[str], list[str]]:
    """The streams whose median delay exceeds ``lag`` s (sustained: a clock behind or a slow
    link) and those whose largest delay does (a stall), as 'name delay s' texts."""
    slow = [f'{s} {np.median(d):.2f} s' for s, d in delays.items() if d and np.median(d) > lag]
    spikes = [f'{s} {max(d):.2f} s' for s, d in delays.items() if d and max(d) > lag]
    return slow, spikes


class FollowerEstimatorNode(Node):
    """Feeds standard messages to an :class:`~formopt_ros.core.asynchronous.AsyncEstimator`,
    plans on a timer and drives the base (see SUMMARY and the module docstring of
    formopt_ros.core.asynchronous)."""

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments (several in one process)."""
        super().__init__('follower_estimator', cli_args=cli_args)
        self.params = p = declare(self, PARAMS)
        check_output_path('summary_path', p['summary_path'], may_exist=False)
        self.scenario = scenario = self._scenario(p)
        self.sensor = sensor = p['sensor']
        self.streams = ('odom', 'leader_odom', sensor)
        try:
            noise = RealNoise(p['bias_sigma'] if sensor == 'range' else 0.0, p['bias_walk'],
                              p['huber'], p['gate'], p['reopen_after'])
        except ValueError as error:
            raise ParameterError(str(error)) from None
        strategy = make_strategy(p['strategy'], **strategy_options(p['strategy'], p))
        strategy.prepare(scenario)
        self.estimator = EstimatorPlanner(scenario, strategy, np.random.default_rng(0), noise)

        if p['initial_pose'] != [0.0]:
            if len(p['initial_pose']) != 3:
                raise ParameterError("parameter 'initial_pose' must be [x, y, phi] or [0.0], "
                                     f"got {p['initial_pose']!r}")
            check_angles('initial_pose', p['initial_pose'][2:])
            self.estimator.state[:3] = p['initial_pose']
        self.limits = Limits(p['max_speed'], p['max_yaw_rate'], p['max_acceleration'],
                             p['max_yaw_acceleration'])
        self.settings = AsyncSettings(int(p['reorder_lag'] * NS_PER_S),
                                      int(p['max_gap'] * NS_PER_S), p['max_gated_share'])
        self.tracker: AsyncEstimator | None = None         # starts with the first message
        self.started_at_ns = 0                              # the filter's start, ns
        self.leader_speed = 0.0                             # of its last odometry, m/s
        self.start_warning = ''                             # a late start, until reported
        self.default_variance = scenario.sigma ** 2       # a measurement's, m^2 or rad^2
        #: /tf_static: child frame -> (parent frame, translation (3,) m, rotation (3, 3))
        self.static: dict[str, tuple[str, np.ndarray, np.ndarray]] = {}
        self.mounts: dict[str, tuple[tuple[float, float], np.ndarray]] = {}   # frame -> mount
        self.sensor_frame: str | None = None       # the frame of the first measurement
        self.fixed_mount: tuple[tuple[float, float], np.ndarray] | None = None
        if p['sensor_mount'] != [0.0]:
            if len(p['sensor_mount']) != 6:
                raise ParameterError("parameter 'sensor_mount' must be [x, y, z, roll, pitch, "
                                     f"yaw] or [0.0], got {p['sensor_mount']!r}")
            check_angles('sensor_mount', p['sensor_mount'][3:])
            self.fixed_mount = mount_pose(p['sensor_mount'])
        self.refused = {'frame': 0, 'future': 0, 'before_start': 0, 'unstamped': 0,
                        'out_of_range': 0, 'not_finite': 0, 'no_mount': 0}
        self.newest: dict[str, int | None] = {s: None for s in self.streams}   # stamps, ns
        self.delays: dict[str, list[float]] = {s: [] for s in self.streams}  # this period, s
        self.refusal: dict[str, str] = {}      # per stream, its refusal since it was last used
        self.unstamped: set[str] = set()       # streams that sent a header stamp 0
        self.first_input_ns: int | None = None
        # a pause of every input longer than reorder_lag (this process stalled, or every link
        # at once): until _catch_up_until (monotonic s), or until each stream in _draining
        # delivered an input within reorder_lag of its stamp, the backlog is applied as its
        # odometry covers it, not by the clock, so its own odometry is not dropped as late,
        # and its delays (the pause's, not the link's) are not judged
        self._last_input_s: float | None = None
        self._catch_up_until = 0.0
        self._draining: set[str] = set()
        self.pauses: list[float] = []                 # their lengths, s
        self._reported: dict[str, int] = {}          # counts at the last diagnostics
        self.target: np.ndarray | None = None
        self.command = (0.0, 0.0)
        self.stops = 0
        self.unreachable = 0
        self.worst = 'OK'
        self.errors: list[str] = []
        self.step = 0
        # wall time of each input (odometry or measurement, with the updates it lets through
        # and their estimates published) and of each plan (with its target published), s
        self.handling: dict[str, list[float]] = {'input': [], 'plan': []}
        self.throttle = Throttle(self)
        self.warnings_logged = Throttle(self, 10.0)     # /diagnostics WARNs, on the console
        self.started_ns = self.now_ns()
        self.finished = False
        frame = p['leader_frame']
        self.estimate_pub = self.create_publisher(PoseWithCovarianceStamped, 'estimate', 10)
        self.target_pub = self.create_publisher(PointStamped, 'target', 10)
        self.cmd_pub = self.create_publisher(Twist, 'cmd_vel', 10)
        self.diagnostics_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                                     qos.profile('diagnostics'))
        inputs = [self.create_subscription(Odometry, 'odom',
                                           lambda m: self.on_odometry('odom', m), qos.SENSOR),
                  self.create_subscription(Odometry, 'leader_odom',
                                           lambda m: self.on_odometry('leader_odom', m),
                                           qos.SENSOR),
                  self.create_subscription(Range, 'range', self.on_range, qos.SENSOR)
                  if sensor == 'range' else
                  self.create_subscription(Vector3Stamped, 'bearing', self.on_bearing,
                                           qos.SENSOR)]
        #: Per stream, the topic it resolved to (remappings and namespace applied).
        self.topics = dict(zip(self.streams, (s.topic_name for s in inputs)))
        if self.topics['odom'] == self.topics['leader_odom']:
            raise ParameterError(f"odom and leader_odom both resolve to {self.topics['odom']}: "
                                 "the leader's odometry must come from the leader (check the "
                                 'robot and leader names, or the remappings)')
        #: per odometry stream, a twist left zero by a driver that fills only the pose
        self.still_twist = {stream: StillTwist() for stream in ('odom', 'leader_odom')}
        self.twist_missing: dict[str, str] = {}          # stream -> why, while it lasts
        #: a second publisher on an input topic (another robot's driver or simulator in this
        #: domain and namespace mixes its messages in): the guard's message, once
        self.intruder = ''
        self.guard = RunGuard(self, False, lambda failure: setattr(self, 'intruder',
                                                                   failure.message))
        for topic in self.topics.values():
            self.guard.watch(topic)
        self.create_subscription(TFMessage, '/tf_static', self.on_tf_static,
                                 qos.TF_STATIC_READER)
        self.create_timer(2.0 * scenario.dt, self.plan)
        self.create_timer(1.0 / p['control_rate'], self.control)
        self.create_timer(p['status_period'], self.publish_diagnostics)
        self.frame = frame
        self.get_logger().info(f'follower_estimator ready ({sensor}, strategy {strategy.name}, '
                               f'slot {list(scenario.p_o)} m in {frame!r}; inputs '
                               f"{', '.join(self.topics.values())})")

    @staticmethod
    def _scenario(p: dict[str, Any]) -> Scenario:
        slot = p['formation_slot']
        p_o = Scenario.paper(p['sensor']).p_o if slot == [0.0] else tuple(slot)
        if len(p_o) != 2:
            raise ParameterError("parameter 'formation_slot' must be [x, y] in m or [0.0], got "
                                 f'{slot!r}')
        if len(p['initial_covariance']) != 3:
            raise ParameterError("parameter 'initial_covariance' must be [x, y, phi] "
                                 f"variances, got {p['initial_covariance']!r}")
        try:
            scenario = Scenario(
                p['sensor'], p_o, p['deviation_fraction'] * math.hypot(*p_o),
                p[f"{p['sensor']}_sigma"], dt=p['dt'], sigma_v=p['sigma_v'],
                sigma_omega=p['sigma_omega'], sigma_v_leader=p['sigma_v_leader'],
                sigma_omega_leader=p['sigma_omega_leader'],
                initial_covariance=tuple(p['initial_covariance']),
                max_speed=p['max_speed'] if p['plan_within_reach'] else None,
                safety_distance=p['safety_distance'])
            check_deviation_domain(scenario, 'deviation_fraction')
            return scenario
        except ValueError as error:
            raise ParameterError(f'the scenario parameters are inconsistent: {error}') from None

    def now_ns(self) -> int:
        """The node clock, ns."""
        return int(self.get_clock().now().nanoseconds)

    # --- inputs ------------------------------------------------------------------------------
    def _accept(self, stream: str, stamp: int) -> bool:
        """Stamp rules shared by every input; counts and warns on refusal."""
        now = self.now_ns()
        if self.tracker is None and now <= 0:
            self._refuse('before_start', stream, f'{stream} before this clock started '
                         '(use_sim_time and no /clock yet; a bag: replay --clock): the filter '
                         'does not start on it')
            return False
        if stamp > now + int(self.params['future_tolerance'] * NS_PER_S):
            self._refuse('future', stream, f'{stream} stamped {(stamp - now) / NS_PER_S:.3f} s '
                         'ahead of this clock: are the clocks synchronised?')
            return False
        behind = now - stamp
        if stamp == 0 and behind > int(self.params['stale_timeout'] * NS_PER_S):
            self._refuse('unstamped', stream, f'{stream}: header stamp 0 (its driver does not '
                         'stamp its messages)')
            self.unstamped.add(stream)
            return False
        if self.tracker is None and behind > int(self.params['stale_timeout'] * NS_PER_S):
            # the filter starts at its first input's stamp: an old one would be integrated over
            self._refuse('before_start', stream, f'{stream} stamped {behind / NS_PER_S:.3f} s '
                         'behind this clock: the filter starts only at an input stamped within '
                         'stale_timeout of it (clocks not synchronised, or a bag played back? '
                         'play it with replay --clock and use_sim_time:=true here)')
            return False
        if self.tracker is not None and stamp <= self.started_at_ns:
            self._refuse('before_start', stream, f'{stream} stamped '
                         f'{(self.started_at_ns - stamp) / NS_PER_S:.3f} s before the filter '
                         "started (at another stream's first input)")
            return False
        self.first_input_ns = self.first_input_ns or now
        wall = time.monotonic()
        pause = wall - (self._last_input_s or wall)
        self._last_input_s = wall
        if pause > max(self.params['reorder_lag'], MIN_PAUSE):
            self.pauses.append(pause)
            self._catch_up_until, self._draining = wall + MAX_CATCH_UP, set(self.streams)
        delay = (now - stamp) / NS_PER_S
        if stream in self._draining and delay <= self.params['reorder_lag']:
            self._draining.discard(stream)          # this stream's backlog is through
        if stream not in self._draining or not self.catching_up():
            self.delays[stream].append(delay)       # a backlog's are the pause's, not the link's
        self.newest[stream] = max(stamp, self.newest[stream] or stamp)
        self.refusal.pop(stream, None)          # the stream's last refusal is past
        if self.tracker is None:
            if any(self.newest[s] is None for s in ODOMETRY_STREAMS):
                return False        # the leader's motion before its first odometry is unknown
            self.started_at_ns = stamp - 1
            self.tracker = AsyncEstimator(self.estimator, self.started_at_ns, self.settings)
        return True

    def catching_up(self) -> bool:
        """Whether the backlog of a pause is still being applied (no measurement is due by the
        clock meanwhile)."""
        return bool(self._draining) and time.monotonic() < self._catch_up_until

    def _refuse(self, counter: str, stream: str, text: str) -> None:
        self.refused[counter] += 1
        self.refusal[stream] = text
        self.throttle.warn(f'{counter}:{stream}', text)

    def on_odometry(self, stream: str, message: Odometry) -> None:
        """Follower ('odom') or leader ('leader_odom') odometry: its twist over the interval
        since the previous message."""
        started = time.perf_counter()
        expected = self.params['follower_child_frame' if stream == 'odom'
                               else 'leader_child_frame']
        if expected and message.child_frame_id != expected:
            self._refuse('frame', stream, f'{stream}: child_frame_id '
                         f'{message.child_frame_id!r} is not {expected!r}')
            return
        v, omega = message.twist.twist.linear.x, message.twist.twist.angular.z
        if not (math.isfinite(v) and math.isfinite(omega)):
            self._refuse('not_finite', stream, f'{stream}: twist is not finite')
            return
        stamp = header_ns(message)
        if stream == 'leader_odom':
            self.leader_speed = abs(v)
        starting = self.tracker is None
        if not self._accept(stream, stamp):
            return
        assert self.tracker is not None
        waited = (self.now_ns() - (self.first_input_ns or 0)) / NS_PER_S
        if starting and waited > LATE_START_S and self.leader_speed > START_SPEED:
            self.start_warning = (f'the filter started {waited:.1f} s after the first input, '
                                  f'with the leader driving at {self.leader_speed:.2f} m/s: the '
                                  'follower, held meanwhile, is off its slot, where the '
                                  'estimate starts (start every driver before the leader '
                                  'moves, or give initial_pose)')
            self.get_logger().warning(self.start_warning)
        resets = self.tracker.counters.outage_resets
        x, y, yaw = (float(c) for c in pose_values(message.pose.pose))
        finite = math.isfinite(x) and math.isfinite(y) and math.isfinite(yaw)
        if not self.still_twist[stream].add(v, omega, x, y):
            self.twist_missing.pop(stream, None)       # a twist again (or not moved yet)
        elif stream not in self.twist_missing:
            self.twist_missing[stream] = (
                f'{stream} on {self.topics[stream]}: its twist is zero while its pose moved '
                f'{self.still_twist[stream].moved:.2f} m: the driver does not fill the twist, '
                'which the filter integrates')
        self.tracker.add_odometry('follower' if stream == 'odom' else 'leader', stamp, v, omega,
                                  twist_noise(message), (x, y, yaw) if finite else None)
        if self.tracker.counters.outage_resets > resets:
            self.get_logger().warning(f'{stream} is back after an outage: the estimate was made '
                                      "again from both robots' odometry poses")
        self._advance(started)

    def on_range(self, message: Range) -> None:
        """A range: dropped (counted) when :func:`~formopt_ros.wire.messages.range_problem`
        refuses it (not finite, negative, outside the driver's [min_range, max_range))."""
        problem = range_problem(message)
        if problem is not None:
            self._refuse(problem[0], 'range', problem[1])
            return
        value = float(message.range)
        frame = message.header.frame_id
        mount = self._mount('range', frame)
        if mount is None:
            return
        self._measure('range', header_ns(message), value, frame, mount[0], range_variance(
            self.params['range_variance'], message_variance(message.variance),
            self.default_variance))

    def on_bearing(self, message: Vector3Stamped) -> None:
        """A direction toward the leader in the sensor frame (any length), turned into a
        bearing in the body frame's orientation by the sensor's mounting rotation."""
        v = message.vector
        if not all(math.isfinite(c) for c in (v.x, v.y, v.z)):
            self._refuse('not_finite', 'bearing', 'bearing: direction is not finite')
            return
        frame = message.header.frame_id
        mount = self._mount('bearing', frame)
        if mount is None:
            return
        value = direction_bearing((v.x, v.y, v.z), mount[1])
        if value is None:
            self._refuse('out_of_range', 'bearing', 'bearing: the direction is vertical in the '
                         'body frame (no bearing)')
            return
        self._measure('bearing', header_ns(message), value, frame, mount[0],
                      self.default_variance)

    def on_tf_static(self, message: TFMessage) -> None:
        """Static transforms, kept by child frame, and the mount of every frame they connect to
        base_frame: its pose there (e.g. base_link -> camera_link -> camera_optical), resolved
        here rather than per measurement."""
        self.static.update(static_transforms([message]))
        resolved = {frame: self._static_mount(frame) for frame in self.static}
        self.mounts = {frame: mount for frame, mount in resolved.items() if mount is not None}

    def _static_mount(self, frame: str) -> tuple[tuple[float, float], np.ndarray] | None:
        """The pose of ``frame`` in base_frame through /tf_static, below it or on another
        branch of one tree (yaw, pitch, roll and the horizontal offset are used), or None when
        they are not connected."""
        sensor = pose_in_root(self.static, frame)
        base = pose_in_root(self.static, self.params['base_frame'])
        if sensor is None or base is None or sensor[0] != base[0]:
            return None
        offset = base[2].T @ (sensor[1] - base[1])
        return (float(offset[0]), float(offset[1])), base[2].T @ sensor[2]

    def _mount(self, stream: str, frame: str) -> tuple[tuple[float, float], np.ndarray] | None:
        """The mounting pose of the measurement frame ``frame``: the parameter, the body frame
        itself (none), or /tf_static; refused (counted) when unknown or when it is not the
        sensor frame of the first measurement accepted. Ranges from an unknown frame are taken
        at the body origin."""
        if self.sensor_frame is not None and frame != self.sensor_frame:
            self._refuse('frame', stream, f'{stream}: frame_id {frame!r} is not the sensor '
                         f'frame {self.sensor_frame!r} of the first measurement')
            return None
        mount = self.fixed_mount or self.mounts.get(frame)
        if mount is None and (frame in ('', self.params['base_frame']) or stream == 'range'):
            mount = ((0.0, 0.0), np.eye(3))
        if mount is None:
            self._refuse('no_mount', stream, f"{stream}: no mounting pose for frame {frame!r}: "
                         f"set sensor_mount or publish {self.params['base_frame']!r} -> "
                         f'{frame!r} on /tf_static')
            return None
        return mount

    def _measure(self, stream: str, stamp: int, value: float, frame: str,
                 offset: tuple[float, float], variance: float) -> None:
        """Buffer a measurement (its ``variance``, m^2 or rad^2) its stamp rules accept; the
        first one accepted fixes the sensor frame and its lever arm ``offset`` (m)."""
        started = time.perf_counter()
        if not self._accept(stream, stamp):
            return
        if self.sensor_frame is None:
            self.sensor_frame = frame
            self.estimator.sensor_offset = None if offset == (0.0, 0.0) else offset
        assert self.tracker is not None
        self.tracker.add_measurement(stamp, value, variance)
        self._advance(started)

    def _advance(self, started: float) -> None:
        """Apply what the buffer lets through, publish the estimates; time the input from
        ``started`` (perf_counter, s)."""
        assert self.tracker is not None
        for applied in self.tracker.advance(None if self.catching_up() else self.now_ns()):
            self.estimate_pub.publish(conversions.estimate(
                conversions.stamp(applied.stamp_ns), self.frame, applied.x, applied.P))
        self.handling['input'].append(time.perf_counter() - started)

    # --- planning and control ------------------------------------------------------------------
    @stops_on_a_plan_outside_the_disc
    def plan(self) -> None:
        """Re-plan the target from the current estimate (timer, every 2 dt)."""
        self._check_duration()
        if self.tracker is None or self.tracker.applied == 0:
            return
        started = time.perf_counter()
        self.step += 1
        self.target = self.tracker.plan(self.step).solution.p
        x, _ = self.tracker.estimate_at(self.now_ns())
        leader = self.tracker.timelines['leader'].last or (0.0, 0.0)
        if math.hypot(*required_velocity(x, self.target, leader, self.params['horizon'])) > \
                self.limits.speed:
            self.unreachable += 1          # the base cannot get there within the horizon
        point = PointStamped(header=conversions.header(self.get_clock().now().to_msg(),
                                                       self.frame))
        point.point.x, point.point.y = float(self.target[0]), float(self.target[1])
        self.target_pub.publish(point)
        self.handling['plan'].append(time.perf_counter() - started)

    def stale(self) -> list[str]:
        """The streams silent, or stamped behind this clock, longer than stale_timeout."""
        return [s for s, age in self.ages().items()
                if age is None or age > self.params['stale_timeout']]

    def stream_label(self, stream: str) -> str:
        """'leader_odom on /f1/leader_odom', and why its messages are refused, if they are, or
        that the other sensor's topic beside it has a publisher while this one has none."""
        label = f'{stream} on {self.topics[stream]}'
        if stream in self.refusal:
            return label + f' (its messages are refused: {self.refusal[stream]})'
        if stream in SENSORS:
            other = next(sensor for sensor in SENSORS if sensor != stream)
            beside = self.topics[stream].rsplit('/', 1)[0] + '/' + other
            if not self.count_publishers(self.topics[stream]) and self.count_publishers(beside):
                label += f' ({beside} has a publisher: is the sensor {other}?)'
        return label

    def ages(self) -> dict[str, float | None]:
        """Per stream, seconds since its newest stamp (None: nothing yet)."""
        now = self.now_ns()
        return {s: None if t is None else (now - t) / NS_PER_S for s, t in self.newest.items()}

    def control(self) -> None:
        """cmd_vel toward the target within the limits; a stop while the target or an input
        stream is stale, or once the filter is inconsistent or an input has a second publisher,
        with stop_when_inconsistent (counted)."""
        self.guard.check()
        if self.tracker is None or self.target is None or self.stale() or \
                (self.params['stop_when_inconsistent'] and
                 (self.tracker.watch.failed or self.intruder)):
            self.stops += self.command != (0.0, 0.0)       # a moving base stopped
            self.command = (0.0, 0.0)
        else:
            x, _ = self.tracker.estimate_at(self.now_ns())
            leader = self.tracker.timelines['leader'].last or (0.0, 0.0)
            self.command = twist_toward(x, self.target, leader, self.params['horizon'],
                                        self.limits, self.command,
                                        1.0 / self.params['control_rate'])
        twist = Twist()
        twist.linear.x, twist.angular.z = self.command
        self.cmd_pub.publish(twist)

    # --- health --------------------------------------------------------------------------------
    def health(self) -> list[tuple[str, str]]:
        """Every ERROR, worst first, or else the first WARN. ERROR: sustained inconsistency or
        gating (the consistency watch, latched), with an odometry twist left zero while its
        pose moved as its likely cause; a second publisher on an input topic for INTRUDER_GRACE
        s (latched); stamps ahead of this clock, stamps of 0, or inputs
        stamped more than stale_timeout behind it while the filter has not started; more than
        LATE_FRACTION of the period's inputs dropped as late, or a stream whose median delay
        (arrival minus stamp) over the period exceeds reorder_lag (a clock behind this one, or a
        slow link); a stream silent, or stamped behind this clock, for stale_timeout after its last
        input, or whose every message was refused for stale_timeout since input began. WARN:
        waiting for a stream's first input (a driver that comes up later), an odometry twist left
        zero while its pose moved STILL_TWIST_MOVE (a driver that fills only the pose; an
        odometry reset while standing looks the same), a stream older than half
        the timeout, the consistency watch's current warning (a window outside its band), a delay
        spike beyond reorder_lag or fewer inputs dropped as late (the link stalled), inputs
        refused, more than UNREACHABLE_FRACTION of the plans beyond the base's reach, a pause of
        every input (this process stalled: its backlog is applied in order, nothing dropped),
        odometry carried past its last message, gaps, gated ranges."""
        new = {k: v - self._reported.get(k, 0) for k, v in self.counts().items()}
        errors: list[str] = []
        if self.tracker is not None and self.tracker.watch.failed:
            worst = self.tracker.watch.worst
            errors.append(f'filter inconsistent at measurement {worst.step}: {worst.reason}')
            errors += self.twist_missing.values()        # the likely cause
        if self.intruder:
            errors.append(self.intruder)
        if new.get('refused_future'):
            errors.append('messages stamped ahead of this clock: clocks not synchronised')
        if new.get('refused_unstamped'):
            errors.append(f"messages on {', '.join(sorted(self.unstamped))} with header stamp 0 "
                          'are refused: their driver does not stamp them')
        if new.get('refused_before_start') and self.tracker is None:    # nothing started it
            errors.append('first inputs refused (stamped more than stale_timeout behind this '
                          'clock, or before it started): clocks not synchronised, or a bag '
                          'played back without replay --clock')
        lag = self.params['reorder_lag']
        slow, spikes = delayed_streams(self.delays, lag)
        late = new.get('late_odometry', 0) + new.get('late_measurements', 0)
        inputs = late + new.get('odometry', 0) + new.get('measurements', 0)
        if slow:
            errors.append(f'inputs arrive later than reorder_lag ({lag:g} s) after their '
                          f"stamps: a clock behind this one or a slow link ({', '.join(slow)})"
                          + f'; {late} of {inputs} dropped as late')
        elif late > LATE_FRACTION * inputs:
            errors.append(f'{late} of {inputs} inputs dropped as late (stamped before inputs '
                          'the filter had applied, by more than reorder_lag: the robots\' clocks '
                          'apart, or a slow link)')
        ages, limit = self.ages(), self.params['stale_timeout']
        if self.first_input_ns is None:
            return [('ERROR', e) for e in errors] or \
                [('WARN', 'waiting for input: ' + ', '.join(self.streams))]
        old = [s for s, a in ages.items() if a is not None and a > limit]
        refused = [s for s, a in ages.items() if a is None and s in self.refusal]
        started = (self.now_ns() - self.first_input_ns) / NS_PER_S > limit
        if old and started:
            errors.append(f'stale (silent or behind this clock for over {limit:g} s): '
                          + ', '.join(map(self.stream_label, old)))
        if refused and started:
            errors.append('no usable input (every message refused) for over '
                          f"{limit:g} s: {', '.join(map(self.stream_label, refused))}")
        if errors:
            return [('ERROR', e) for e in errors]
        if self.start_warning:
            return [('WARN', self.start_warning)]
        if self.twist_missing:
            return [('WARN', next(iter(self.twist_missing.values())))]
        never = [s for s, a in ages.items() if a is None]
        if never:       # a driver that comes up later: the base is held until it does
            return [('WARN', 'waiting for the first input: '
                             + ', '.join(map(self.stream_label, never)))]
        old_streams = [f'{s} {a:.2f} s' for s, a in ages.items()
                       if a is not None and a > limit / 2]
        if old_streams:
            return [('WARN', 'late: ' + ', '.join(old_streams))]
        if self.tracker is not None and self.tracker.watch.verdict().level == WARN:
            return [('WARN', f'filter consistency: {self.tracker.watch.verdict().reason}')]
        if spikes or late:
            return [('WARN', 'inputs delayed beyond reorder_lag (the link stalled)'
                             + (f': {late} dropped as late' if late else '')
                             + (': ' + ', '.join(spikes) if spikes else ''))]
        refusals = [f'{k[8:]} {v}' for k, v in new.items() if k.startswith('refused_') and v]
        if refusals:
            return [('WARN', 'inputs refused: ' + ', '.join(refusals)
                             + ''.join(f' ({text})' for text in self.refusal.values()))]
        if new.get('plans') and new.get('unreachable_targets', 0) > \
                UNREACHABLE_FRACTION * new['plans']:
            return [('WARN', f"{new['unreachable_targets']} of {new['plans']} targets beyond "
                             f"the base's reach (max_speed {self.params['max_speed']:g} m/s "
                             f"within horizon {self.params['horizon']:g} s)")]
        if new.get('pauses'):
            return [('WARN', f'every input paused {self.pauses[-1]:.2f} s (this process or '
                             'every link stalled); the backlog was applied in order')]
        for key, text in (('bridged', 'odometry carried past its last message (bridged)'),
                          ('gaps', f"odometry intervals longer than {self.params['max_gap']:g} "
                                   's (messages lost)'),
                          ('gated_measurements', 'measurements refused by the innovation '
                                                 'gate')):
            if new.get(key):
                return [('WARN', text)]
        return []

    def counts(self) -> dict[str, int]:
        """The filter's counters, the refusals (refused_*) and the pauses, as reported on
        /diagnostics (:meth:`health` judges what changed since the last report)."""
        counters = self.tracker.counters.as_dict() if self.tracker else {}
        return {**counters, **{f'refused_{k}': v for k, v in self.refused.items()},
                'pauses': len(self.pauses), 'plans': self.step,
                'unreachable_targets': self.unreachable}

    def publish_diagnostics(self) -> None:
        """/diagnostics every status_period; an ERROR is kept for the summary."""
        problems = self.health()
        level, message = problems[0] if problems else (
            'OK', 'tracking' if self.tracker and self.tracker.applied else 'waiting for input')
        self._reported = self.counts()
        self.start_warning = ''
        self.delays = {s: [] for s in self.streams}
        if level == 'ERROR':
            self.worst = 'ERROR'
            for _, error in problems:       # every cause, not only the worst: a latched
                if error.split(' (')[0] not in [e.split(' (')[0] for e in self.errors]:
                    self.errors.append(error)   # inconsistency does not hide an outage
                    self.get_logger().error(error)
        elif level == 'WARN' and self.worst == 'OK':
            self.worst = 'WARN'
        for _, text in (problems if level == 'WARN' else ()):
            self.warnings_logged.warn(text.split(' (')[0].split(':')[0], text)
        values: dict[str, object] = {
            **self._reported, 'stops': self.stops,
            'weighted_trace_m2': self.estimator.weighted_trace(),
            **{f'age_{s}_s': 'never' if a is None else round(a, 3)
               for s, a in self.ages().items()}}
        self.diagnostics_pub.publish(DiagnosticArray(
            header=conversions.header(self.get_clock().now().to_msg(), ''),
            status=[conversions.diagnostic(self.get_fully_qualified_name(), self.frame, level,
                                           message, values)]))

    def _check_duration(self) -> None:
        duration = self.params['duration']
        now = self.now_ns()
        if not self.started_ns:         # use_sim_time: the duration counts from the first /clock
            self.started_ns = now
        if duration and (now - self.started_ns) / NS_PER_S >= duration:
            self.finished = True

    def summary(self) -> dict[str, Any]:
        """Final estimate, counters and health: ok only if no ERROR was raised and every input
        stream delivered."""
        estimator = self.estimator
        never = [self.stream_label(s) for s, t in self.newest.items() if t is None]
        errors = list(self.errors) + ([f"no usable input ever arrived: {', '.join(never)}"]
                                      if never else [])
        return {
            'ok': self.worst != 'ERROR' and not never, 'worst_diagnostic': self.worst,
            'errors': errors,
            'final_estimate': estimator.x.tolist(), 'final_covariance': estimator.P.tolist(),
            'range_bias': float(estimator.state[3]) if estimator.state.size == 4 else None,
            'final_weighted_trace': estimator.weighted_trace(),
            'counters': self.tracker.counters.as_dict() if self.tracker else {},
            'refused': dict(self.refused), 'stops': self.stops, 'plans': self.step,
            'unreachable_targets': self.unreachable,
            'pauses': {'count': len(self.pauses),
                       'longest_s': round(max(self.pauses), 3) if self.pauses else 0.0},
            'consistency': self.tracker.watch.summary() if self.tracker else None,
            'handling_ms': {kind: {'count': len(times),
                                   'median': 1e3 * float(np.median(times)) if times else None,
                                   'p99': 1e3 * float(np.quantile(times, 0.99)) if times
                                   else None}
                            for kind, times in self.handling.items()}}

    def close(self) -> None:
        """Stop the base and write the summary (also on SIGINT/SIGTERM)."""
        self.cmd_pub.publish(Twist())
        write_summary(self.params['summary_path'], self.summary())


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros follower_estimator)."""
    sys.exit(node_main(FollowerEstimatorNode, 'follower_estimator', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()


__all__ = ['FollowerEstimatorNode', 'PARAMS', 'main']
