"""follower_sim: the follower robot; executes waypoints with noise, measures range or bearing."""
from __future__ import annotations

import sys
from typing import Any

from formopt_interfaces.msg import Measurement, Waypoint
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from formopt_ros.core.model import integrate_unicycle
from formopt_ros.core.protocol import SUBSTEPS, Timebase, step_substeps
from formopt_ros.core.simulation import FollowerTruth, trial_streams
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.gate import PublisherGate
from formopt_ros.ros.naming import peer_topic
from formopt_ros.ros.nodes.leader_sim import ODOM_FRAME
from formopt_ros.ros.params import declare
from formopt_ros.ros.run_config import (
    FOLLOWER_ID, FORMATION_FILE, LEADER_ID, MODE, RECORDERS, RUN_ID, SCENARIO_PARAMS, SEED,
    SUMMARY_PATH, TRIAL, WAIT_FOR_PEERS, follower_run, formation_defaults)
from formopt_ros.ros.runtime import Throttle, node_main, steady_timer, write_summary
from formopt_ros.wire.messages import header_ns, odometry_problem, odometry_values, \
    waypoint_problem
from formopt_ros.wire.topics import BY_KEY, DEFAULT_FOLLOWER

PARAMS = [FORMATION_FILE, FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS + [
    RUN_ID, RECORDERS, WAIT_FOR_PEERS, SUMMARY_PATH]
SUMMARY = ('The follower robot: executes the waypoints with noisy velocities and publishes its '
           'odometry, one range or bearing measurement per step, its true pose and its frames '
           'on /tf.')


def frames(follower_id: str) -> dict[str, str]:
    """The follower's frames: its odometry frame, its body, its true and estimated poses."""
    return {'odom': f'{follower_id}/odom', 'body': follower_id,
            'truth': f'{follower_id}/truth', 'estimate': f'{follower_id}/estimate'}


class FollowerSim(Node):
    """The real follower: a :class:`FollowerTruth` driven by Waypoint commands.

    Per sub-step it publishes its odometry (the commanded velocities it measured, with the
    noise variances) and <id>/odom -> <id> on /tf; after the motion its true relative pose
    (and leader -> <id>/truth) and one measurement. /tf_static holds odom -> <id>/odom, where
    its odometry started. lockstep: executes waypoint k once the leader's odometry for the
    step's sub-steps arrived (matched by their simulated-time stamps); a repeated waypoint
    republishes the cached output. realtime: a timer at 1/dt executes the current sub-step with
    the latest waypoint and leader velocity; a step starts only when its waypoint is in: a tick
    without it counts as a missed cycle, in which the follower holds (v = 0, turning with the
    leader) and the step waits. Nothing is published before the publishers are matched.
    """

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments (several in one process)."""
        super().__init__('follower_sim', namespace=DEFAULT_FOLLOWER, cli_args=cli_args)
        self.params = p = declare(self, PARAMS, formation_defaults(self, 'follower'))
        self.run = follower_run(self, p, strategy_owned=False)
        self.follower_id, self.leader_id = self.run.follower_id, self.run.leader_id
        self.scenario = self.run.spec.scenario
        self.frames = frames(self.follower_id)
        self.timebase = Timebase.from_dt(self.scenario.dt)
        self.lockstep = p['mode'] == 'lockstep'
        noise, _ = trial_streams(self.run.spec.seed, self.run.trial)
        self.truth = FollowerTruth(self.scenario, noise)
        self.odom_pose = (0.0, 0.0, 0.0)
        self.executed = 0
        self.pending: Waypoint | None = None
        self.leader: dict[int, tuple[float, float]] = {}
        self.latest_leader = self.scenario.leader.velocity(0, self.scenario.dt)
        self.cache: list[tuple[str, Any]] = []
        self.counters = {'rejected_waypoints': 0, 'rejected_odometry': 0, 'missed_cycles': 0}
        self.published = {'odometry': 0, 'measurement': 0, 'truth': 0, 'tf': 0}
        self.throttle = Throttle(self)
        self.gate = PublisherGate(self, p['recorders'], int(p['wait_for_peers']))
        self.odom_pub = self.gate.add(self.create_publisher(
            Odometry, BY_KEY['follower_odom'].name, qos.STREAM), 'follower_odom')
        self.meas_pub = self.gate.add(self.create_publisher(
            Measurement, BY_KEY['measurement'].name, qos.STREAM), 'measurement')
        self.truth_pub = self.gate.add(self.create_publisher(
            PoseStamped, BY_KEY['truth'].name, qos.STREAM), 'truth')
        self.tf_pub = self.gate.add(self.create_publisher(TFMessage, '/tf', qos.TF), 'tf')
        self.tf_static_pub = self.create_publisher(TFMessage, '/tf_static', qos.TF_STATIC)
        self.tf_static_message = conversions.tf_message([conversions.transform(
            self.get_clock().now().to_msg(), ODOM_FRAME, self.frames['odom'],
            self.truth.x)])                  # the leader starts at the origin of 'odom'
        self.tf_static_pub.publish(self.tf_static_message)
        self.create_subscription(Waypoint, BY_KEY['waypoint'].name, self.on_waypoint,
                                 qos.SUBSCRIBED)
        self.create_subscription(Odometry, peer_topic(self, self.leader_id, 'leader_odom'),
                                 self.on_leader_odom, qos.SUBSCRIBED)
        self.substep_in_step = 0
        if self.lockstep:
            steady_timer(self, 0.05, self._try_execute)
        else:
            self.create_timer(self.scenario.dt, self.on_tick)
        self.get_logger().info(f"follower_sim ready ({p['mode']}, "
                               f'{self.scenario.measurement}, follower {self.follower_id})')

    # --- inputs ----------------------------------------------------------------------------
    def on_waypoint(self, msg: Waypoint) -> None:
        """A new waypoint is executed (lockstep: once the leader moved); a repeat republishes."""
        problem = waypoint_problem(msg, self.follower_id)
        if problem is not None:
            self.counters['rejected_waypoints'] += 1
            self.throttle.warn('waypoint', f'rejected waypoint: {problem}')
            return
        if msg.step == self.executed and self.lockstep:
            for key, item in self.cache:
                self._publish(key, item)
            return
        if msg.step <= self.executed:
            return
        self.pending = msg
        if self.lockstep:
            self._try_execute()

    def on_leader_odom(self, msg: Odometry) -> None:
        """The leader's velocity of one sub-step."""
        problem = odometry_problem(msg, self.leader_id)
        if problem is not None:
            self.counters['rejected_odometry'] += 1
            self.throttle.warn('odometry', f'rejected leader odometry: {problem}')
            return
        v, omega, _, _ = odometry_values(msg)
        self.latest_leader = (v, omega)
        if self.lockstep:
            substep = self.timebase.substep_ending_at(header_ns(msg))
            if substep is None:
                self.counters['rejected_odometry'] += 1
                self.throttle.warn('odometry', 'rejected leader odometry: stamp off the '
                                               'lockstep grid')
                return
            self.leader[substep] = (v, omega)
            self._try_execute()

    # --- motion ----------------------------------------------------------------------------
    def _substep(self, v_cmd: float, omega_cmd: float, leader: tuple[float, float],
                 stamp: Any) -> None:
        self.truth.execute(v_cmd, omega_cmd, leader[0], leader[1])
        self.odom_pose = integrate_unicycle(self.odom_pose, v_cmd, omega_cmd, self.scenario.dt)
        s = self.scenario
        odom = conversions.odometry(stamp, self.frames['odom'], self.follower_id,
                                    self.odom_pose, v_cmd, omega_cmd,
                                    (s.sigma_v ** 2, s.sigma_omega ** 2))
        tf = conversions.tf_message([conversions.transform(
            stamp, self.frames['odom'], self.frames['body'], self.odom_pose)])
        for key, msg in (('odometry', odom), ('tf', tf)):
            self.cache.append((key, msg))
            self._publish(key, msg)

    def _finish_step(self, step: int, stamp: Any) -> None:
        s = self.scenario
        truth = conversions.pose_stamped(stamp, self.leader_id, self.truth.x)
        meas = conversions.measurement(stamp, self.follower_id, self.follower_id, step,
                                       s.measurement, self.truth.measure(), s.sigma ** 2)
        tf = conversions.tf_message([conversions.transform(
            stamp, self.leader_id, self.frames['truth'], self.truth.x)])
        for key, msg in (('truth', truth), ('tf', tf), ('measurement', meas)):
            self.cache.append((key, msg))
            self._publish(key, msg)
        self.executed = step

    def _try_execute(self) -> None:
        """Lockstep: run the pending waypoint once the leader's sub-steps are known."""
        msg = self.pending
        if msg is None:
            return
        substeps = step_substeps(msg.step)
        if any(n not in self.leader for n in substeps) or not self.gate.ready():
            return
        self.cache = []
        for j, n in enumerate(substeps):
            self._substep(msg.linear_velocity[j], msg.angular_velocity[j], self.leader.pop(n),
                          conversions.stamp(self.timebase.substep_end(n)))
        self._finish_step(msg.step, conversions.stamp(self.timebase.measurement_stamp(msg.step)))
        self.pending = None

    def on_tick(self) -> None:
        """Realtime: execute one sub-step of the current step.

        The sub-steps of a waypoint are only meaningful together (rotate, then translate), so a
        step starts when its waypoint is in; a tick without it holds position instead of
        repeating an old command (repeating a translation made the formation diverge).
        """
        if (self.pending is None and self.executed == 0) or not self.gate.ready():
            return                                   # wait for the first waypoint
        j = self.substep_in_step
        msg = self.pending if (self.pending is not None
                               and self.pending.step == self.executed + 1) else None
        now = self.get_clock().now().to_msg()
        if msg is None:                              # late waypoint (only possible at j == 0)
            self.counters['missed_cycles'] += 1
            self._substep(0.0, self.latest_leader[1], self.latest_leader, now)
            return
        if j == 0:
            self.cache = []
        self._substep(msg.linear_velocity[j], msg.angular_velocity[j], self.latest_leader, now)
        self.substep_in_step = (j + 1) % SUBSTEPS
        if self.substep_in_step == 0:
            self._finish_step(self.executed + 1, now)
            self.pending = None

    def _publish(self, key: str, msg: Any) -> None:
        {'odometry': self.odom_pub, 'measurement': self.meas_pub, 'truth': self.truth_pub,
         'tf': self.tf_pub}[key].publish(msg)
        self.published[key] += 1

    def summary(self) -> dict[str, Any]:
        """What the follower did: steps executed, counters, its final true pose."""
        return {'follower_id': self.follower_id, 'executed_steps': self.executed,
                'counters': dict(self.counters), 'published': dict(self.published),
                'final_truth': self.truth.x.tolist()}

    def close(self) -> None:
        """Write the summary on shutdown."""
        write_summary(self.params['summary_path'], self.summary())


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros follower_sim)."""
    sys.exit(node_main(FollowerSim, 'follower_sim', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()
