"""leader_sim: the leader robot; drives its path and publishes its odometry, /tf and /clock."""
from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import Any

from formopt_interfaces.msg import Waypoint
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from tf2_msgs.msg import TFMessage

from formopt_ros.core.model import integrate_unicycle
from formopt_ros.core.protocol import SUBSTEPS, Timebase, step_substeps
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.checkpoint import open_checkpoint
from formopt_ros.ros.gate import PublisherGate
from formopt_ros.ros.guard import RunGuard
from formopt_ros.ros.naming import peer_topic
from formopt_ros.ros.params import declare
from formopt_ros.ros.run_config import (
    CHECKPOINT_PATH, DT, FOLLOWERS, FORMATION_FILE, MODE, PATH_PARAMS, RECORDERS, RUN_ID,
    SUMMARY_PATH, WAIT_FOR_PEERS, formation_defaults, leader_run)
from formopt_ros.ros.runtime import Throttle, node_main, steady_timer, stop_run, write_summary
from formopt_ros.wire.description import LeaderDescription, RunDescription as Description
from formopt_ros.wire.description import leader_differences
from formopt_ros.wire.messages import foreign_run, waypoint_problem
from formopt_ros.wire.topics import BY_KEY, DEFAULT_LEADER, ODOM_FRAME

PARAMS = [FORMATION_FILE, FOLLOWERS, MODE, DT] + PATH_PARAMS + [
    RUN_ID, RECORDERS, WAIT_FOR_PEERS, SUMMARY_PATH, CHECKPOINT_PATH]
SUMMARY = ('The leader robot: drives its path and publishes its odometry per sub-step, '
           "odom -> leader on /tf and, in lockstep, /clock (lockstep: a step once every "
           "follower's waypoint for it is in; realtime: at 1/dt). Once every estimator "
           'finished a run of a set number of steps and left, it ends too (exit 0).')


class LeaderSim(Node):
    """Drives the leader along its path and publishes nav_msgs/Odometry and /tf.

    lockstep: step k is served (the odometry of its sub-steps, stamped on the integer-ns
    timebase, with /clock advanced to each stamp) once every follower has sent its waypoint
    of step k; a repeated waypoint of the served step republishes the cached odometry (a
    follower restarted). realtime: one odometry per timer tick at 1/dt, stamped with the node
    clock. Nothing is published before the publishers have matched their subscribers and every
    follower's run description agrees with the leader's (ros.guard). With a checkpoint a
    restarted leader resumes its path where it stopped.
    """

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments (several in one process)."""
        super().__init__('leader_sim', namespace=DEFAULT_LEADER, cli_args=cli_args)
        self.params = p = declare(self, PARAMS, formation_defaults(self, 'leader'))
        self.run = leader_run(self, p)
        self.leader_id = self.run.leader_id
        self.lockstep = p['mode'] == 'lockstep'
        self.timebase = Timebase.from_dt(self.run.dt)
        self.pose = (0.0, 0.0, 0.0)        # x, y, yaw in the fixed 'odom' frame
        self.substep = 0
        self.served_step = 0
        self.requested = {follower: 0 for follower in self.run.followers}
        self.cache: list[tuple[int, Odometry, tuple[float, float, float]]] = []
        self.published = {'odometry': 0, 'clock': 0, 'tf': 0}
        self.foreign_waypoints = 0
        self.stale_waypoints = 0
        self.finished = False
        self.exit_code = 0
        self.error = ''
        self.description = LeaderDescription(self.leader_id, self.run.path, self.run.dt,
                                             self.run.followers, p['mode'], p['run_id'])
        self.checkpoint, state = open_checkpoint(self, p, self.description.to_json())
        self.resumed: dict[str, Any] | None = None
        if state is not None:
            for key, value in state.items():
                setattr(self, key, value)
            self.resumed = {'from_step': self.served_step, 'from_substep': self.substep}
        self.throttle = Throttle(self)
        self.gate = PublisherGate(self, p['recorders'],
                                  len(self.run.followers) if p['wait_for_peers'] else 0)
        self.odom_pub = self.gate.add(self.create_publisher(
            Odometry, BY_KEY['leader_odom'].name, qos.STREAM), 'leader_odom')
        self.tf_pub = self.gate.add(self.create_publisher(TFMessage, '/tf', qos.TF), 'tf')
        self.clock_pub = self.gate.add(self.create_publisher(Clock, '/clock', qos.CLOCK),
                                       'clock') if self.lockstep else None
        # Subscribed in both modes: the estimators count the leader among the waypoint
        # subscribers they wait for before the first waypoint.
        self.guard = RunGuard(self, p['wait_for_peers'],
                              lambda failure: stop_run(self, failure.code, failure.message))
        self.guard.announce('leader_description', self.description.to_json(), p['run_id'],
                            len(BY_KEY['leader_description'].listeners) * len(self.run.followers))
        for follower in self.run.followers:
            self.create_subscription(Waypoint, peer_topic(self, follower, 'waypoint'),
                                     self._waypoint_callback(follower), qos.SUBSCRIBED)
            self.guard.expect(peer_topic(self, follower, 'description'), self._compare)
            self.guard.watch(peer_topic(self, follower, 'waypoint'))
        self.guard.end_when([peer_topic(self, f, 'waypoint') for f in self.run.followers],
                            lambda: self._complete() is True)
        steady_timer(self, 0.05, self.on_check)
        if not self.lockstep:
            self.create_timer(self.run.dt, self.on_tick)
        self.get_logger().info(
            f"leader_sim ready ({p['mode']}, {self.run.path.kind} path at "
            f"{self.run.path.speed} m/s, followers {', '.join(self.run.followers)})")

    def _compare(self, text: str) -> list[tuple[str, Any, Any]]:
        """How a follower's description disagrees with this leader (this node's value first)."""
        return [(name, mine, theirs) for name, theirs, mine in
                leader_differences(Description.from_json(text), self.description)]

    def _complete(self) -> bool | None:
        """Whether the leader drove every step of its followers' runs (None: a run until
        stopped; False too when a follower's run was never heard of)."""
        heard = [self.guard.peer_steps(peer_topic(self, f, 'description'))
                 for f in self.run.followers]
        steps = [s for s in heard if s is not None]
        if len(steps) < len(heard):
            return False
        if min(steps) == 0:
            return None
        return (self.served_step if self.lockstep else self.substep // SUBSTEPS) >= max(steps)

    def _state(self) -> dict[str, Any]:
        return {key: getattr(self, key) for key in (
            'pose', 'substep', 'served_step', 'requested', 'cache', 'published',
            'foreign_waypoints')}

    def on_check(self) -> None:
        """Watch for intruders; lockstep: serve a step that became servable."""
        self.guard.check()
        if self.lockstep:
            self.serve()

    def _may_run(self) -> bool:
        return not self.finished and self.gate.ready() and self.guard.ready()

    def _advance(self, stamp_ns: int | None) -> Odometry:
        """Drive one sub-step; its odometry (node clock stamp when stamp_ns is None)."""
        v, omega = self.run.path.velocity(self.substep, self.run.dt)
        self.pose = integrate_unicycle(self.pose, v, omega, self.run.dt)
        self.substep += 1
        time = conversions.stamp(stamp_ns) if stamp_ns is not None else \
            self.get_clock().now().to_msg()
        return conversions.odometry(time, ODOM_FRAME, self.leader_id, self.pose, v, omega)

    def _publish(self, entries: Sequence[tuple[int | None, Odometry, tuple[float, float, float]]]
                 ) -> None:
        """Per sub-step /clock (lockstep) and the odometry, which the followers and estimators
        wait for; then the /tf of each sub-step, which no node of the run waits for."""
        for stamp_ns, odom, _ in entries:
            if self.clock_pub is not None and stamp_ns is not None:
                self.clock_pub.publish(conversions.clock(stamp_ns))
                self.published['clock'] += 1
            self.odom_pub.publish(odom)
            self.published['odometry'] += 1
        for _, odom, pose in entries:
            self.tf_pub.publish(conversions.tf_message([conversions.transform(
                odom.header.stamp, ODOM_FRAME, self.leader_id, pose)]))
            self.published['tf'] += 1

    def _waypoint_callback(self, follower: str) -> Callable[[Waypoint], None]:
        def callback(msg: Waypoint) -> None:
            self.on_waypoint(follower, msg)
        return callback

    def on_waypoint(self, follower: str, msg: Waypoint) -> None:
        """Lockstep: note the step the follower asks for; a repeat of the served step gets the
        cached odometry again."""
        if not self.lockstep:
            return                                   # realtime: the timer drives the leader
        if foreign_run(msg, self.params['run_id']) is not None:
            self.foreign_waypoints += 1
            self.throttle.warn('foreign', f'refused a waypoint of another run on {follower}')
            return
        problem = waypoint_problem(msg, follower)
        if problem is not None:
            self.throttle.warn('waypoint', f'ignoring waypoint on {follower}: {problem}')
            return
        if msg.step == self.served_step and msg.step <= self.requested[follower]:
            self._publish(self.cache)
            return
        if 0 < msg.step < self.served_step:
            # the follower's estimator restarted without a checkpoint; its follower_sim repeats
            # its last step (the estimator rejoins there), the other followers need no repeat
            self.stale_waypoints += 1
            self.throttle.warn('stale', f'waypoint of step {msg.step} on {follower}, a step '
                                        f'left behind (step {self.served_step} served): its '
                                        'estimator restarted?')
            return
        self.requested[follower] = max(self.requested[follower], int(msg.step))
        self.serve()

    def serve(self) -> None:
        """Lockstep: serve the next step once every follower asked for it (and the gate is
        open)."""
        step = self.served_step + 1
        if min(self.requested.values()) < step or not self._may_run():
            return
        substeps = step_substeps(step)
        self.substep = substeps[0]
        self.cache = []
        for n in substeps:
            stamp = self.timebase.substep_end(n)
            self.cache.append((stamp, self._advance(stamp), self.pose))
        self.served_step = step
        self.checkpoint.save(self._state())
        self._publish(self.cache)

    def on_tick(self) -> None:
        """Realtime: one sub-step per tick, once the publishers are matched."""
        if self._may_run():
            odom = self._advance(None)
            self._publish([(None, odom, self.pose)])
            self.checkpoint.save(self._state())

    def summary(self) -> dict[str, Any]:
        """What the leader did: steps served, messages published, its final pose; not ok when
        it failed or was stopped before the last step of a run of known length."""
        complete = self._complete()
        return {'ok': not self.error and complete is not False, 'error': self.error or None,
                'complete': complete,
                'run_id': self.params['run_id'], 'resumed': self.resumed,
                'foreign_waypoints': self.foreign_waypoints,
                'stale_waypoints': self.stale_waypoints,
                'leader_id': self.leader_id, 'served_steps': self.served_step,
                'substeps': self.substep, 'published': dict(self.published),
                'final_pose': list(self.pose)}

    def close(self) -> None:
        """Write the summary on shutdown."""
        write_summary(self.params['summary_path'], self.summary())


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros leader_sim)."""
    sys.exit(node_main(LeaderSim, 'leader_sim', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()
