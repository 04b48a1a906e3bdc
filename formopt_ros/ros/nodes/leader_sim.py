"""leader_sim: the leader robot; publishes its odometry per sub-step (lockstep or real time)."""
from __future__ import annotations

import sys

from formopt_interfaces.msg import Waypoint
from nav_msgs.msg import Odometry
from rclpy.node import Node

from formopt_ros.core.model import integrate_unicycle
from formopt_ros.core.protocol import Timebase, step_substeps
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.naming import peer_topic, robot_id
from formopt_ros.ros.params import (
    DT, LEADER_PARAMS, MODE, SUMMARY_PATH, Param, declare, leader_path_from)
from formopt_ros.ros.runtime import Throttle, node_main, write_summary
from formopt_ros.wire.messages import waypoint_problem
from formopt_ros.wire.topics import DEFAULT_FOLLOWER, DEFAULT_LEADER, BY_KEY

PARAMS = [Param('follower_id', DEFAULT_FOLLOWER, 'id of the follower whose waypoints drive the '
                'lockstep clock (its namespace)'),
          MODE, DT] + LEADER_PARAMS + [SUMMARY_PATH]
SUMMARY = ("The leader robot: drives its path and publishes its odometry per sub-step "
           "(lockstep: when the follower's waypoint for the step is in; realtime: at 1/dt).")


class LeaderSim(Node):
    """Drives the leader along its path and publishes nav_msgs/Odometry.

    lockstep: each new Waypoint of step k makes it publish the odometry of that step's sub-steps
    (stamped on the integer-ns timebase); a repeated waypoint republishes the cached ones.
    realtime: one odometry per timer tick at 1/dt, stamped with the node clock.
    """

    def __init__(self) -> None:
        super().__init__('leader_sim', namespace=DEFAULT_LEADER)
        self.params = p = declare(self, PARAMS)
        self.leader_id = robot_id(self, DEFAULT_LEADER)
        self.path = leader_path_from(p)
        self.timebase = Timebase.from_dt(p['dt'])
        self.pose = (0.0, 0.0, 0.0)        # x, y, yaw in the fixed 'odom' frame
        self.substep = 0
        self.served_step = 0
        self.cache: list[Odometry] = []
        self.published = 0
        self.throttle = Throttle(self)
        self.odom_pub = self.create_publisher(Odometry, BY_KEY['leader_odom'].name, qos.STREAM)
        # Subscribed in both modes: the estimator counts the leader among the waypoint
        # subscribers (peers) it waits for before the first waypoint.
        self.create_subscription(Waypoint, peer_topic(self, p['follower_id'], 'waypoint'),
                                 self.on_waypoint, qos.SUBSCRIBED)
        if p['mode'] == 'realtime':
            self.create_timer(p['dt'], self.on_tick)
        self.get_logger().info(f"leader_sim ready ({p['mode']}, {self.path.kind}, "
                               f'v_L={self.path.speed} m/s)')

    def _advance(self, stamp: object) -> Odometry:
        v, omega = self.path.velocity(self.substep, self.params['dt'])
        self.pose = integrate_unicycle(self.pose, v, omega, self.params['dt'])
        self.substep += 1
        return conversions.odometry(stamp, 'odom', self.leader_id, self.pose, v, omega)

    def _publish(self, msg: Odometry) -> None:
        self.odom_pub.publish(msg)
        self.published += 1

    def on_waypoint(self, msg: Waypoint) -> None:
        """Lockstep: serve the sub-steps of the waypoint's step once; repeat on duplicates."""
        if self.params['mode'] != 'lockstep':
            return                                   # realtime: the timer drives the leader
        problem = waypoint_problem(msg, self.params['follower_id'])
        if problem is not None:
            self.throttle.warn('waypoint', f'ignoring waypoint: {problem}')
            return
        if msg.step <= self.served_step:
            if msg.step == self.served_step:
                for odom in self.cache:
                    self._publish(odom)
            return
        substeps = step_substeps(msg.step)
        self.substep = substeps[0]                   # also after a restart mid-run
        self.cache = [self._advance(conversions.stamp(self.timebase.substep_end(n)))
                      for n in substeps]
        self.served_step = msg.step
        for odom in self.cache:
            self._publish(odom)

    def on_tick(self) -> None:
        """Realtime: one sub-step per tick."""
        self._publish(self._advance(self.get_clock().now().to_msg()))

    def summary(self) -> dict[str, object]:
        """What the leader did: steps served, odometry published, its final pose."""
        return {'leader_id': self.leader_id, 'served_steps': self.served_step,
                'substeps': self.substep, 'published_odometry': self.published,
                'final_pose': list(self.pose)}

    def close(self) -> None:
        """Log the totals and write the summary on shutdown."""
        self.get_logger().info(f'leader_sim published {self.published} odometry messages')
        write_summary(self.params['summary_path'], self.summary())


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros leader_sim)."""
    sys.exit(node_main(LeaderSim, 'leader_sim', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()
