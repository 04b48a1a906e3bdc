"""follower_sim: the follower robot; executes waypoints with noise, measures range or bearing."""
from __future__ import annotations

import math
import sys

from formopt_interfaces.msg import Measurement, Waypoint
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from formopt_ros import conversions
from formopt_ros.core.simulation import SUBSTEPS, FollowerTruth, trial_streams
from formopt_ros.nodes.common import (
    FOLLOWER_ID, LEADER_ID, MODE, PUBLISHED, RELIABLE, SCENARIO_PARAMS, SEED, TOPICS, TRIAL,
    Throttle, declare, run, scenario_from)

PARAMS = [FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS


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
        super().__init__('follower_sim')
        self.params = declare(self, PARAMS)
        p = self.params
        self.scenario = scenario_from(p)
        noise, _ = trial_streams(p['seed'], p['trial'])
        self.truth = FollowerTruth(self.scenario, noise)
        self.odom_pose = [0.0, 0.0, 0.0]
        self.executed = 0
        self.pending: Waypoint | None = None
        self.leader: dict[int, tuple[float, float]] = {}
        self.latest_leader = (self.scenario.v_leader, self.scenario.omega_leader)
        self.cache: list = []
        self.counters = {'published': 0, 'rejected_waypoints': 0, 'rejected_odometry': 0,
                         'missed_cycles': 0}
        self.throttle = Throttle(self)
        self.odom_pub = self.create_publisher(Odometry, TOPICS['follower_odom'], PUBLISHED)
        self.meas_pub = self.create_publisher(Measurement, TOPICS['measurement'], PUBLISHED)
        self.truth_pub = self.create_publisher(PoseStamped, TOPICS['truth'], PUBLISHED)
        self.create_subscription(Waypoint, TOPICS['waypoint'], self.on_waypoint, RELIABLE)
        self.create_subscription(Odometry, TOPICS['leader_odom'], self.on_leader_odom,
                                 RELIABLE)
        self.substep_in_step = 0
        if p['mode'] == 'realtime':
            self.create_timer(self.scenario.dt, self.on_tick)
        self.get_logger().info(f"follower_sim ready ({p['mode']}, {p['measurement']})")

    # --- inputs ----------------------------------------------------------------------------
    def on_waypoint(self, msg: Waypoint) -> None:
        problem = conversions.waypoint_problem(msg, self.params['follower_id'])
        if problem is not None:
            self.counters['rejected_waypoints'] += 1
            self.throttle.warn('waypoint', f'rejected waypoint: {problem}')
            return
        if msg.step == self.executed and self.params['mode'] == 'lockstep':
            for publisher, item in self.cache:
                self._publish(publisher, item)
            return
        if msg.step <= self.executed:
            return
        self.pending = msg
        if self.params['mode'] == 'lockstep':
            self._try_execute()

    def on_leader_odom(self, msg: Odometry) -> None:
        problem = conversions.odometry_problem(msg, self.params['leader_id'])
        if problem is not None:
            self.counters['rejected_odometry'] += 1
            self.throttle.warn('odometry', f'rejected leader odometry: {problem}')
            return
        v, omega, _, _ = conversions.odometry_velocities(msg)
        self.latest_leader = (v, omega)
        if self.params['mode'] == 'lockstep':
            substep = round(conversions.seconds(msg.header.stamp) / self.scenario.dt) - 1
            self.leader[substep] = (v, omega)
            self._try_execute()

    # --- motion ----------------------------------------------------------------------------
    def _substep(self, v_cmd: float, omega_cmd: float, leader: tuple[float, float],
                 stamp) -> None:
        self.truth.execute(v_cmd, omega_cmd, leader[0], leader[1])
        dt = self.scenario.dt
        x, y, yaw = self.odom_pose
        self.odom_pose = [x + v_cmd * math.cos(yaw) * dt, y + v_cmd * math.sin(yaw) * dt,
                          yaw + omega_cmd * dt]
        s = self.scenario
        msg = conversions.odometry(stamp, self.params['follower_id'] + '/odom',
                                   self.params['follower_id'], self.odom_pose, v_cmd, omega_cmd,
                                   (s.sigma_v ** 2, s.sigma_omega ** 2))
        self.cache.append((self.odom_pub, msg))
        self._publish(self.odom_pub, msg)

    def _finish_step(self, step: int, stamp) -> None:
        s = self.scenario
        truth = conversions.pose_stamped(stamp, self.params['leader_id'], self.truth.x)
        meas = conversions.measurement(stamp, self.params['follower_id'], step, s.measurement,
                                       self.truth.measure(), s.sigma ** 2)
        for publisher, msg in ((self.truth_pub, truth), (self.meas_pub, meas)):
            self.cache.append((publisher, msg))
            self._publish(publisher, msg)
        self.executed = step

    def _try_execute(self) -> None:
        """Lockstep: run the pending waypoint once the leader's sub-steps are known."""
        msg = self.pending
        if msg is None:
            return
        first = (msg.step - 1) * SUBSTEPS
        if any(first + j not in self.leader for j in range(SUBSTEPS)):
            return
        dt = self.scenario.dt
        self.cache = []
        for j in range(SUBSTEPS):
            self._substep(msg.linear_velocity[j], msg.angular_velocity[j],
                          self.leader.pop(first + j), conversions.stamp((first + j + 1) * dt))
        self._finish_step(msg.step, conversions.stamp((first + SUBSTEPS) * dt))
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

    def _publish(self, publisher, msg) -> None:
        publisher.publish(msg)
        self.counters['published'] += 1

    def close(self) -> None:
        """Log the totals on shutdown."""
        self.get_logger().info(f'follower_sim: executed {self.executed} steps, {self.counters}')


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros follower_sim)."""
    sys.exit(run(FollowerSim, args))


if __name__ == '__main__':
    main()
