"""field_sim: a simulated pair of real robots for follower_estimator: a differential-drive
follower driven by cmd_vel, a leader on its path, their odometry and a UWB radio or a camera,
in real time."""
from __future__ import annotations

import dataclasses
import math
import sys
from time import monotonic
from typing import Any

import numpy as np
from geometry_msgs.msg import PoseStamped, TransformStamped, Twist, Vector3Stamped
from nav_msgs.msg import Odometry
import rclpy
from rclpy.node import Node
from rclpy.parameter import parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from sensor_msgs.msg import Range
from tf2_msgs.msg import TFMessage

from formopt_ros.core.controller import Limits, limited
from formopt_ros.core.field import Base, Camera, FieldWorld, Radio
from formopt_ros.core.model import rpy_quaternion
from formopt_ros.core.protocol import NS_PER_S
from formopt_ros.core.scenario import Scenario
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.params import Param, ParameterError, check_angles, declare
from formopt_ros.ros.run_config import (
    INITIAL_COVARIANCE, PATH_PARAMS, SLOT, SUMMARY_PATH, leader_path_from, value_range)
from formopt_ros.ros.runtime import (
    STOP_SIGNALS, check_output_path, node_main, write_summary)
from formopt_ros.wire.topics import ODOM_FRAME

#: Limits of the UWB radio's Range messages, m.
RANGE_LIMITS = (0.05, 50.0)
#: Longest wait for the node named by sensor_of to answer, s (an estimator designing
#: PERIODIC's cycle at start-up answers only when it spins).
SENSOR_OF_TIMEOUT = 120.0

PARAMS = [
    Param('sensor', 'range', 'the follower\'s sensor: range (a UWB radio, sensor_msgs/Range on '
          'range) or bearing (a camera, geometry_msgs/Vector3Stamped toward the leader on '
          'bearing)', choices=('range', 'bearing')),
    SLOT,
    Param('sensor_of', '', "'': this node's own parameters; a follower_estimator's full name "
          '(e.g. /f1/follower_estimator): take sensor, formation_slot, base_frame and '
          "camera_mount from that running node's parameters (sensor, formation_slot, "
          'base_frame, sensor_mount), however it was configured (params file, -p), waiting for '
          f'it up to {SENSOR_OF_TIMEOUT:g} s (scripts/robot.sh --sim sets it)'),
    *PATH_PARAMS,
    dataclasses.replace(INITIAL_COVARIANCE, low=0.0, description='the true start pose is drawn '
                        'from N([slot, 0], diag(this)) [x m^2, y m^2, phi rad^2], as the '
                        "estimator's initial_covariance assumes ([0, 0, 0]: the slot itself)"),
    Param('leader_odom_topic', '/leader/odom', "where the leader's odometry is published"),
    Param('publish_leader', True, "publish the leader's odometry (in a formation, one field_sim "
          'does; all simulate the same leader when they share start_time)'),
    Param('start_time', 0.0, 'the simulated world starts at this time of the node clock, s since '
          'the epoch (0: when the node starts; the same value makes several field_sims share '
          'one leader)', 0.0, 1e10),
    Param('base_frame', 'base_link', "the follower base's frame (child_frame_id of odom)"),
    Param('sensor_frame', '', "frame of the measurements ('': uwb for range, camera for "
          'bearing); the camera\'s mount is published on /tf_static as base_frame -> '
          'sensor_frame'),
    Param('odom_rate', 50.0, "follower odometry rate, Hz", 1.0, 1000.0),
    Param('leader_odom_rate', 50.0, "leader odometry rate, Hz", 1.0, 1000.0),
    Param('leader_odom_offset', 0.007, "phase of the leader's odometry clock, s", 0.0, 1.0),
    Param('sigma_v', 0.1, "follower speed noise (true minus commanded) per odometry period, m/s",
          0.0, 10.0),
    Param('sigma_omega', 0.05, 'follower yaw-rate noise per odometry period, rad/s', 0.0, 10.0),
    Param('range_rate', 30.0, 'UWB range rate, Hz', 0.1, 1000.0),
    Param('range_jitter', 0.005, 'uniform timing jitter of the ranges, s', 0.0, 0.1),
    Param('range_sigma', 0.1, 'range noise std, m', 0.0, 10.0),
    Param('range_bias', 0.1, 'range bias, m', -10.0, 10.0),
    Param('outlier_rate', 0.02, 'share of ranges with +U(1, 3) m added (non-line-of-sight)',
          0.0, 1.0),
    Param('dropout_rate', 0.01, 'share of measurements not sent', 0.0, 1.0),
    Param('bearing_rate', 15.0, 'camera rate, Hz', 0.1, 1000.0),
    Param('bearing_sigma', 0.02, 'camera bearing noise std, rad', 0.0,
          value_range('bearing_sigma')[1]),
    Param('camera_mount', [0.1, 0.0, 0.0], "the camera's pose on the base, [x m, y m, yaw rad]",
          -100.0, 100.0),
    Param('latency', 0.02, 'delay between a cmd_vel message and the base executing it, s', 0.0,
          1.0),
    Param('max_speed', 2.5, 'largest forward speed of the base, m/s', 1e-3, 100.0),
    Param('max_yaw_rate', 4.0, 'largest yaw rate of the base, rad/s',
          *value_range('max_yaw_rate')),
    Param('max_acceleration', 4.0, 'largest acceleration of the base, m/s^2', 1e-3, 1000.0),
    Param('max_yaw_acceleration', 20.0, 'largest yaw acceleration, rad/s^2', 1e-3, 1e4),
    Param('leader_clock_offset', 0.0, "added to the leader's stamps: a leader clock out of sync, "
          's', -100.0, 100.0),
    Param('leader_outage', [0.0, 0.0], "[start, end] s of the run in which no leader odometry "
          'is sent (a link outage; [0, 0]: none)', 0.0, 1e6),
    Param('seed', 0, 'seed of the random streams', 0, 2**31 - 1),
    Param('duration', 60.0, 'run this long, s, then exit', 0.1, 1e6),
    SUMMARY_PATH,
]
SUMMARY = ('Two simulated real robots in real time: the follower base executes cmd_vel (limits, '
           'latency, noise) and publishes nav_msgs/Odometry (odom) at its rate, the leader its '
           'odometry on leader_odom_topic, a UWB radio sensor_msgs/Range (range: bias, jitter, '
           'outliers, dropouts) or a camera geometry_msgs/Vector3Stamped toward the leader '
           '(bearing, its mount on /tf_static); truth (PoseStamped in the leader frame) at each '
           'measurement time.')


class FieldSimNode(Node):
    """Advances a :class:`~formopt_ros.core.field.FieldWorld` to the node clock every 2 ms
    and publishes what each event sends."""

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments (several in one process)."""
        super().__init__('field_sim', cli_args=cli_args)
        self.params = p = declare(self, PARAMS)
        check_output_path('summary_path', p['summary_path'], may_exist=False)
        if p['sensor_of']:
            p.update(self._settings_of(p['sensor_of']))
        slot = Scenario.paper(p['sensor']).p_o if p['formation_slot'] == [0.0] else \
            tuple(p['formation_slot'])
        if len(slot) != 2 or len(p['leader_outage']) != 2 or len(p['camera_mount']) != 3 or \
                len(p['initial_covariance']) != 3:
            raise ParameterError("parameters 'formation_slot' and 'leader_outage' take two "
                                 "numbers, 'camera_mount' and 'initial_covariance' three")
        check_angles('camera_mount', p['camera_mount'][2:])
        if p['sensor'] == 'range' and math.hypot(*slot) > RANGE_LIMITS[1]:
            raise ParameterError(f"parameter 'formation_slot': {list(slot)} is "
                                 f'{math.hypot(*slot):.1f} m from the leader, beyond the '
                                 f'simulated radio\'s {RANGE_LIMITS[1]:g} m (a slot in cm?)')
        path = leader_path_from(p)
        step = 1.0 / p['leader_odom_rate']
        self.limits = Limits(p['max_speed'], p['max_yaw_rate'], p['max_acceleration'],
                             p['max_yaw_acceleration'])
        self.period = 1.0 / p['odom_rate']
        rng = np.random.default_rng(p['seed'])
        start = np.array([slot[0], slot[1], 0.0]) + \
            np.sqrt(p['initial_covariance']) * rng.normal(size=3)
        self.world = FieldWorld(
            start, lambda t: path.velocity(int(round(t / step)), step), rng,
            p['duration'], Base(p['odom_rate'], 0.0, p['sigma_v'], p['sigma_omega']),
            Base(p['leader_odom_rate'], p['leader_odom_offset']),
            self._sensor(p))
        self.commands: list[tuple[int, float, float]] = []     # (received ns, v, omega)
        self.executed = (0.0, 0.0)
        self.start_ns = int(p['start_time'] * NS_PER_S) or int(self.get_clock().now().nanoseconds)
        self.sensor_frame = p['sensor_frame'] or ('uwb' if p['sensor'] == 'range' else 'camera')
        self.odom_pub = self.create_publisher(Odometry, 'odom', 10)
        self.leader_pub = self.create_publisher(Odometry, p['leader_odom_topic'], 10) \
            if p['publish_leader'] else None        # a silent publisher still counts as one
        if p['sensor'] == 'range':
            self.range_pub = self.create_publisher(Range, 'range', 10)
        else:
            self.bearing_pub = self.create_publisher(Vector3Stamped, 'bearing', 10)
            self._publish_mount()
        self.truth_pub = self.create_publisher(PoseStamped, 'truth', 10)
        self.create_subscription(Twist, 'cmd_vel', self.on_cmd_vel, 10)
        self.create_timer(0.002, self.tick)
        self.finished = False
        self.sent = {'odom': 0, 'leader_odom': 0, p['sensor']: 0, 'dropouts': 0}

    def _settings_of(self, name: str) -> dict[str, Any]:
        """What this simulated robot takes from the running follower_estimator ``name`` (its
        parameter service): its sensor and slot, its base frame (the odometry's child frame and
        the camera mount's parent) and its fixed sensor_mount as the camera's mount.
        ParameterError when it does not answer, has no such parameters or asks for what this
        simulator cannot be (a tilted camera, two base frames)."""
        client = AsyncParameterClient(self, name)
        self.get_logger().info(f'taking the sensor, slot, frames and mount from {name} '
                               '(sensor_of): waiting for it')
        deadline = monotonic() + SENSOR_OF_TIMEOUT
        while not client.wait_for_services(timeout_sec=0.2):
            if STOP_SIGNALS:
                raise ParameterError(f"parameter 'sensor_of': stopped before {name} answered")
            if monotonic() > deadline:
                raise ParameterError(f"parameter 'sensor_of': no node {name} answered within "
                                     f'{SENSOR_OF_TIMEOUT:g} s (start it, or check the name '
                                     'with ros2 node list)')
        names = ['sensor', 'formation_slot', 'base_frame', 'follower_child_frame',
                 'sensor_mount']
        future = client.get_parameters(names)
        rclpy.spin_until_future_complete(self, future, timeout_sec=SENSOR_OF_TIMEOUT)
        answer = future.result()
        got = dict(zip(names, [parameter_value_to_python(value) for value in answer.values]
                       if answer else []))
        if got.get('sensor') not in ('range', 'bearing') or None in got.values() or \
                len(got) != len(names):
            raise ParameterError(f"parameter 'sensor_of': {name} gave no sensor, slot, frames "
                                 f'and mount (got {got}); is it a follower_estimator?')
        base, child = got['base_frame'], got['follower_child_frame']
        if child and child != base:
            raise ParameterError(f"parameter 'sensor_of': {name} reads odometry of "
                                 f'{child!r} and the mount in {base!r}; field_sim has one base '
                                 'frame (set both alike for the dry run)')
        settings = {'sensor': got['sensor'], 'formation_slot': list(got['formation_slot']),
                    'base_frame': base}
        mount = list(got['sensor_mount'])
        if len(mount) == 6:
            if any(abs(angle) > 1e-9 for angle in mount[3:5]):
                raise ParameterError(f"parameter 'sensor_of': {name}'s sensor_mount {mount} is "
                                     'tilted (roll, pitch); field_sim simulates a level camera')
            settings['camera_mount'] = [float(mount[0]), float(mount[1]), float(mount[5])]
        self.get_logger().info(f'{name}: ' + ', '.join(f'{k} {v}' for k, v in settings.items()))
        return settings

    @staticmethod
    def _sensor(p: dict[str, Any]) -> Radio | Camera:
        if p['sensor'] == 'range':
            return Radio(p['range_rate'], p['range_jitter'], p['range_sigma'], p['range_bias'],
                         p['outlier_rate'], dropout_rate=p['dropout_rate'])
        return Camera(p['bearing_rate'], p['range_jitter'], p['bearing_sigma'],
                      tuple(p['camera_mount']), dropout_rate=p['dropout_rate'])

    def _publish_mount(self) -> None:
        """The camera's mount on /tf_static (transient local: late joiners get it)."""
        x, y, yaw = self.params['camera_mount']
        transform = TransformStamped(header=conversions.header(
            self.get_clock().now().to_msg(), self.params['base_frame']),
            child_frame_id=self.sensor_frame)
        transform.transform.translation.x, transform.transform.translation.y = x, y
        q = transform.transform.rotation
        q.x, q.y, q.z, q.w = rpy_quaternion(0.0, 0.0, yaw)
        self.tf_static_pub = self.create_publisher(TFMessage, '/tf_static',
                                                   qos.profile('tf_static'))
        self.tf_static_pub.publish(TFMessage(transforms=[transform]))

    def on_cmd_vel(self, message: Twist) -> None:
        """Keep the command with its arrival time (executed after the latency)."""
        self.commands.append((int(self.get_clock().now().nanoseconds), message.linear.x,
                              message.angular.z))

    def _due_command(self, at_ns: int) -> tuple[float, float]:
        """The newest command received at least ``latency`` before ``at_ns`` (else the last
        executed one), within the base's limits."""
        latency = int(self.params['latency'] * NS_PER_S)
        due = [c for c in self.commands if c[0] <= at_ns - latency]
        if due:
            self.commands = self.commands[len(due) - 1:]
            wanted = due[-1][1:]
        else:
            wanted = self.executed
        self.executed = limited(wanted, self.executed, self.limits, self.period)
        return self.executed

    def tick(self) -> None:
        """Play every event up to now."""
        now = int(self.get_clock().now().nanoseconds) - self.start_ns
        if now < 0:
            return
        while (when := self.world.next_time()) is not None and when * NS_PER_S <= now:
            what, stamp, values = self.world.step()       # type: ignore[misc]
            self._publish(what, stamp, values)
        if self.world.next_time() is None:
            self.finished = True

    def _publish(self, what: str, stamp: int, values: tuple[float, ...]) -> None:
        p = self.params
        time = conversions.stamp(self.start_ns + stamp)
        if what == 'follower':
            self.odom_pub.publish(conversions.odometry(time, ODOM_FRAME, p['base_frame'],
                                                       self.world.follower, values[0],
                                                       values[1]))
            self.sent['odom'] += 1
            self.world.command = self._due_command(self.start_ns + stamp)
        elif what == 'leader':
            start, end = p['leader_outage']
            if self.leader_pub is not None and not start <= stamp / NS_PER_S < end:
                shifted = conversions.stamp(self.start_ns + stamp +
                                            int(p['leader_clock_offset'] * NS_PER_S))
                self.leader_pub.publish(conversions.odometry(
                    shifted, ODOM_FRAME, 'leader', self.world.leader, values[0], values[1]))
                self.sent['leader_odom'] += 1
        else:
            self.truth_pub.publish(conversions.pose_stamped(time, 'leader',
                                                            self.world.relative()))
            if what == 'range':
                # sensor_msgs/Range knows no radio: INFRARED is the closest of its two types
                message = Range(header=conversions.header(time, self.sensor_frame),
                                radiation_type=Range.INFRARED, field_of_view=6.28,
                                min_range=RANGE_LIMITS[0], max_range=RANGE_LIMITS[1],
                                range=float(values[0]))
                self.range_pub.publish(message)
                self.sent['range'] += 1
            elif what == 'bearing':
                direction = Vector3Stamped(header=conversions.header(time, self.sensor_frame))
                direction.vector.x, direction.vector.y = math.cos(values[0]), math.sin(values[0])
                self.bearing_pub.publish(direction)
                self.sent['bearing'] += 1
            else:
                self.sent['dropouts'] += 1

    def close(self) -> None:
        """Stop the base at the end and write the summary (messages sent, outliers)."""
        self.executed = (0.0, 0.0)
        write_summary(self.params['summary_path'], {
            'sent': dict(self.sent), 'outliers': self.world.outliers,
            'finished': self.finished})


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros field_sim)."""
    sys.exit(node_main(FieldSimNode, 'field_sim', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()


__all__ = ['FieldSimNode', 'PARAMS', 'main']
