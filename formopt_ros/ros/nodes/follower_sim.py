"""follower_sim: the follower robot; executes waypoints with noise, measures range or bearing."""
from __future__ import annotations

import sys
from typing import Any

from formopt_interfaces.msg import Measurement, Waypoint
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from formopt_ros.core.model import integrate_unicycle
from formopt_ros.core.protocol import SUBSTEPS, Timebase, step_substeps
from formopt_ros.core.simulation import FollowerTruth, trial_streams
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.naming import peer_topic, robot_id
from formopt_ros.ros.params import (
    FOLLOWER_ID, LEADER_ID, MODE, SCENARIO_PARAMS, SEED, SUMMARY_PATH, TRIAL, declare,
    scenario_from)
from formopt_ros.ros.runtime import Throttle, node_main, write_summary
from formopt_ros.wire.messages import header_ns, odometry_problem, odometry_values, \
    waypoint_problem
from formopt_ros.wire.topics import DEFAULT_FOLLOWER, BY_KEY

PARAMS = [FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS + [SUMMARY_PATH]
SUMMARY = ('The follower robot: executes the waypoints with noisy velocities and publishes its '
           'odometry, one range or bearing measurement per step and its true pose.')


class FollowerSim(Node):
    """The real follower: a :class:`FollowerTruth` driven by Waypoint commands.

    Per sub-step it publishes its odometry (the commanded velocities it measured, with the
    noise variances), after the motion the true relative pose and one measurement.
    lockstep: executes waypoint k once the leader's odometry for the step's sub-steps arrived
    (matched by their simulated-time stamps); a repeated waypoint republishes the cached output.
    realtime: a timer at 1/dt executes the current sub-step with the latest waypoint and leader
    velocity; a step starts only when its waypoint is in: a tick without it counts as a missed
    cycle, in which the follower holds (v = 0, turning with the leader) and the step waits.
    """

    def __init__(self) -> None:
        super().__init__('follower_sim', namespace=DEFAULT_FOLLOWER)
        self.params = p = declare(self, PARAMS)
        self.follower_id = p['follower_id'] or robot_id(self, DEFAULT_FOLLOWER)
        self.scenario = scenario_from(p)
        self.timebase = Timebase.from_dt(self.scenario.dt)
        self.lockstep = p['mode'] == 'lockstep'
        noise, _ = trial_streams(p['seed'], p['trial'])
        self.truth = FollowerTruth(self.scenario, noise)
        self.odom_pose = (0.0, 0.0, 0.0)
        self.executed = 0
        self.pending: Waypoint | None = None
        self.leader: dict[int, tuple[float, float]] = {}
        self.latest_leader = self.scenario.leader.velocity(0, self.scenario.dt)
        self.cache: list[tuple[Any, Any]] = []
        self.counters = {'published': 0, 'rejected_waypoints': 0, 'rejected_odometry': 0,
                         'missed_cycles': 0}
        self.throttle = Throttle(self)
        self.odom_pub = self.create_publisher(Odometry, BY_KEY['follower_odom'].name, qos.STREAM)
        self.meas_pub = self.create_publisher(Measurement, BY_KEY['measurement'].name,
                                              qos.STREAM)
        self.truth_pub = self.create_publisher(PoseStamped, BY_KEY['truth'].name, qos.STREAM)
        self.create_subscription(Waypoint, BY_KEY['waypoint'].name, self.on_waypoint,
                                 qos.SUBSCRIBED)
        self.create_subscription(Odometry, peer_topic(self, p['leader_id'], 'leader_odom'),
                                 self.on_leader_odom, qos.SUBSCRIBED)
        self.substep_in_step = 0
        if not self.lockstep:
            self.create_timer(self.scenario.dt, self.on_tick)
        self.get_logger().info(f"follower_sim ready ({p['mode']}, {p['measurement']}, "
                               f'follower {self.follower_id})')

    # --- inputs ----------------------------------------------------------------------------
    def on_waypoint(self, msg: Waypoint) -> None:
        """A new waypoint is executed (lockstep: once the leader moved); a repeat republishes."""
        problem = waypoint_problem(msg, self.follower_id)
        if problem is not None:
            self.counters['rejected_waypoints'] += 1
            self.throttle.warn('waypoint', f'rejected waypoint: {problem}')
            return
        if msg.step == self.executed and self.lockstep:
            for publisher, item in self.cache:
                self._publish(publisher, item)
            return
        if msg.step <= self.executed:
            return
        self.pending = msg
        if self.lockstep:
            self._try_execute()

    def on_leader_odom(self, msg: Odometry) -> None:
        """The leader's velocity of one sub-step."""
        problem = odometry_problem(msg, self.params['leader_id'])
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
        msg = conversions.odometry(stamp, f'{self.follower_id}/odom', self.follower_id,
                                   self.odom_pose, v_cmd, omega_cmd,
                                   (s.sigma_v ** 2, s.sigma_omega ** 2))
        self.cache.append((self.odom_pub, msg))
        self._publish(self.odom_pub, msg)

    def _finish_step(self, step: int, stamp: Any) -> None:
        s = self.scenario
        truth = conversions.pose_stamped(stamp, self.params['leader_id'], self.truth.x)
        meas = conversions.measurement(stamp, self.follower_id, self.follower_id, step,
                                       s.measurement, self.truth.measure(), s.sigma ** 2)
        for publisher, msg in ((self.truth_pub, truth), (self.meas_pub, meas)):
            self.cache.append((publisher, msg))
            self._publish(publisher, msg)
        self.executed = step

    def _try_execute(self) -> None:
        """Lockstep: run the pending waypoint once the leader's sub-steps are known."""
        msg = self.pending
        if msg is None:
            return
        substeps = step_substeps(msg.step)
        if any(n not in self.leader for n in substeps):
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
        if self.pending is None and self.executed == 0:
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

    def _publish(self, publisher: Any, msg: Any) -> None:
        publisher.publish(msg)
        self.counters['published'] += 1

    def summary(self) -> dict[str, Any]:
        """What the follower did: steps executed, counters, its final true pose."""
        return {'follower_id': self.follower_id, 'executed_steps': self.executed,
                'counters': dict(self.counters), 'final_truth': self.truth.x.tolist()}

    def close(self) -> None:
        """Log the totals and write the summary on shutdown."""
        self.get_logger().info(f'follower_sim: executed {self.executed} steps')
        write_summary(self.params['summary_path'], self.summary())


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros follower_sim)."""
    sys.exit(node_main(FollowerSim, 'follower_sim', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()
