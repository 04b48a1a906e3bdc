"""leader_sim: the leader robot; publishes its odometry per sub-step (lockstep or real time)."""
from __future__ import annotations

import math
import sys

from formopt_interfaces.msg import Waypoint
from nav_msgs.msg import Odometry
from rclpy.node import Node

from formopt_ros import conversions
from formopt_ros.core.simulation import SUBSTEPS, LeaderMotion
from formopt_ros.nodes.common import (
    DT, FOLLOWER_ID, LEADER_ID, MODE, OMEGA_LEADER, PUBLISHED, RELIABLE, TOPICS, V_LEADER,
    Throttle, declare, run)

PARAMS = [FOLLOWER_ID, LEADER_ID, MODE, DT, V_LEADER, OMEGA_LEADER]


class LeaderSim(Node):
    """Drives the leader with a :class:`LeaderMotion` and publishes nav_msgs/Odometry.

    lockstep: each new Waypoint of step k makes it publish the odometry of that step's sub-steps
    (stamps (j + 1) dt); a repeated waypoint republishes the cached ones (peer restarts).
    realtime: one odometry per timer tick at 1/dt, stamped with the node clock.
    """

    def __init__(self, motion: LeaderMotion | None = None) -> None:
        super().__init__('leader_sim')
        self.params = declare(self, PARAMS)
        p = self.params
        self.motion = motion or LeaderMotion(p['v_leader'], p['omega_leader'])
        self.pose = [0.0, 0.0, 0.0]        # x, y, yaw in the fixed 'odom' frame
        self.substep = 0
        self.served_step = 0
        self.cache: list[Odometry] = []
        self.published = 0
        self.throttle = Throttle(self)
        self.odom_pub = self.create_publisher(Odometry, TOPICS['leader_odom'], PUBLISHED)
        # Subscribed in both modes: the estimator counts the leader among the waypoint
        # subscribers (peers) it waits for before the first waypoint.
        self.create_subscription(Waypoint, TOPICS['waypoint'], self.on_waypoint, RELIABLE)
        if p['mode'] == 'realtime':
            self.create_timer(p['dt'], self.on_tick)
        self.get_logger().info(f"leader_sim ready ({p['mode']}, v_L={p['v_leader']} m/s)")

    def _advance(self, stamp) -> Odometry:
        v, omega = self.motion.velocity(self.substep)
        dt = self.params['dt']
        x, y, yaw = self.pose
        self.pose = [x + v * math.cos(yaw) * dt, y + v * math.sin(yaw) * dt, yaw + omega * dt]
        self.substep += 1
        return conversions.odometry(stamp, 'odom', self.params['leader_id'], self.pose, v, omega)

    def _publish(self, msg: Odometry) -> None:
        self.odom_pub.publish(msg)
        self.published += 1

    def on_waypoint(self, msg: Waypoint) -> None:
        """Lockstep: serve the sub-steps of the waypoint's step once; repeat on duplicates."""
        if self.params['mode'] != 'lockstep':
            return                                   # realtime: the timer drives the leader
        if msg.follower_id != self.params['follower_id']:
            self.throttle.warn('foreign', f'ignoring waypoint for {msg.follower_id!r}')
            return
        if msg.step <= self.served_step:
            if msg.step == self.served_step:
                for odom in self.cache:
                    self._publish(odom)
            return
        self.substep = (msg.step - 1) * SUBSTEPS       # also after a restart mid-run
        dt = self.params['dt']
        self.cache = [self._advance(conversions.stamp((self.substep + 1) * dt))
                      for _ in range(SUBSTEPS)]
        self.served_step = msg.step
        for odom in self.cache:
            self._publish(odom)

    def on_tick(self) -> None:
        """Realtime: one sub-step per tick."""
        self._publish(self._advance(self.get_clock().now().to_msg()))

    def close(self) -> None:
        """Log the totals on shutdown."""
        self.get_logger().info(f'leader_sim published {self.published} odometry messages')


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros leader_sim)."""
    sys.exit(run(LeaderSim, args))


if __name__ == '__main__':
    main()
