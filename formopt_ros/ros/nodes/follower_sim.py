"""follower_sim: the follower robot; executes waypoints with noise, measures range or bearing."""
from __future__ import annotations

import sys
import time
from typing import Any

from formopt_interfaces.msg import Measurement, Waypoint
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from formopt_ros.core.model import integrate_unicycle
from formopt_ros.core.protocol import SUBSTEPS, Timebase, hold_command, step_substeps
from formopt_ros.core.simulation import FollowerTruth, measurement_parts, trial_streams
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.checkpoint import open_checkpoint
from formopt_ros.ros.gate import PublisherGate
from formopt_ros.ros.guard import MISMATCH_EXIT, follower_guard
from formopt_ros.ros.naming import peer_topic
from formopt_ros.ros.params import declare
from formopt_ros.ros.run_config import (
    CHECKPOINT_PATH, FOLLOWER_ID, FORMATION_FILE, LEADER_ID, MODE, RECORDERS, RUN_ID,
    SCENARIO_PARAMS, SEED, SUMMARY_PATH, TRIAL, WAIT_FOR_PEERS, follower_run, formation_defaults)
from formopt_ros.ros.runtime import Throttle, node_main, steady_timer, stop_run, write_summary
from formopt_ros.wire.description import RunDescription as Description
from formopt_ros.wire.inputs import odometry_frames
from formopt_ros.wire.messages import (
    foreign_run, header_ns, odometry_problem, odometry_values, waypoint_mismatch,
    waypoint_problem)
from formopt_ros.wire.topics import BY_KEY, DEFAULT_FOLLOWER, ODOM_FRAME, follower_frames

PARAMS = [FORMATION_FILE, FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS + [
    RUN_ID, RECORDERS, WAIT_FOR_PEERS, SUMMARY_PATH, CHECKPOINT_PATH]
SUMMARY = ('The follower robot: executes the waypoints with noisy velocities and publishes its '
           'odometry, its range or bearing measurement per step (range-bearing: both), its true '
           'pose and its frames on /tf. Once its estimator finished a run of a set '
           'number of steps and left, it ends too (exit 0).')
#: Publication order of a step's messages: what the estimator reads first (a lockstep step is
#: published when complete): odometry, the truth (before the measurement, so that the
#: estimator knows the truth of a step when it processes it, also the last one), the
#: measurement; /tf, which no node of the run reads, follows off the critical path.
WAITED_FOR = {'odometry': 0, 'truth': 1, 'measurement': 2}


class FollowerSim(Node):
    """The real follower: a :class:`FollowerTruth` driven by Waypoint commands.

    Per sub-step it publishes its odometry (the commanded velocities it measured, with the
    noise variances) and <id>/odom -> <id> on /tf; after the motion its true relative pose
    (and leader -> <id>/truth) and its measurement (range-bearing: two messages, range then
    bearing). /tf_static holds odom -> <id>/odom, where
    its odometry started. A waypoint of the step last executed (the estimator resends it after
    a restart or a lost message) republishes that step's messages.

    lockstep: executes waypoint k once the leader's odometry for the step's sub-steps arrived
    (matched by their simulated-time stamps). realtime: a timer at 1/dt executes the current
    sub-step with the latest waypoint and leader velocity; a step starts with the newest
    waypoint not yet executed (a step number may be skipped), and a tick without one holds
    (v = 0, turning with the leader) and counts as a missed cycle.

    Nothing is published before the publishers are matched and the estimator's and leader's
    descriptions agree with this node's (ros.guard). With a checkpoint (saved every sub-step)
    a restarted follower resumes its true pose; in realtime the time it was down is spent
    standing still, published as zero-velocity odometry.
    """

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments (several in one process)."""
        super().__init__('follower_sim', namespace=DEFAULT_FOLLOWER, cli_args=cli_args)
        self.params = p = declare(self, PARAMS, formation_defaults(self, 'follower'))
        self.run = follower_run(self, p, strategy_owned=False)
        self.follower_id, self.leader_id = self.run.follower_id, self.run.leader_id
        self.scenario = self.run.spec.scenario
        self.frames = follower_frames(self.follower_id)
        self.timebase = Timebase.from_dt(self.scenario.dt)
        self.lockstep = p['mode'] == 'lockstep'
        noise, _ = trial_streams(self.run.spec.seed, self.run.trial)
        self.truth = FollowerTruth(self.scenario, noise)
        self.description = Description(self.follower_id, self.scenario, '', {},
                                       self.run.spec.seed, self.run.trial, p['mode'], 0,
                                       p['run_id'], self.leader_id)
        self.odom_pose = (0.0, 0.0, 0.0)
        self.executed = 0
        self.current: Waypoint | None = None       # realtime: the step being executed
        self.pending: Waypoint | None = None       # the next waypoint to execute
        self.leader: dict[int, tuple[float, float]] = {}
        self.latest_leader = self.scenario.leader.velocity(0, self.scenario.dt)
        self.step_messages: list[tuple[str, Any]] = []   # the step in progress
        self.cache: list[tuple[str, Any]] = []           # the last executed step
        self.substep_in_step = 0
        self.counters = {'rejected_waypoints': 0, 'foreign_waypoints': 0, 'stale_waypoints': 0,
                         'rejected_odometry': 0, 'missed_cycles': 0, 'repeated_steps': 0,
                         'parked_substeps': 0}
        self.published = {'odometry': 0, 'measurement': 0, 'truth': 0, 'tf': 0}
        self.finished = False
        self.exit_code = 0
        self.error = ''
        self.resumed: dict[str, Any] | None = None
        self.parked: list[Odometry] = []     # realtime resume: odometry of the time down
        self.checkpoint, state = open_checkpoint(self, p, self.description.to_json())
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
        if state is not None:
            self._restore(state)
        self.tf_static_pub.publish(self.tf_static_message)
        self.create_subscription(Waypoint, BY_KEY['waypoint'].name, self.on_waypoint,
                                 qos.SUBSCRIBED)
        self.create_subscription(Odometry, peer_topic(self, self.leader_id, 'leader_odom'),
                                 self.on_leader_odom, qos.SUBSCRIBED)
        self.guard = follower_guard(self, self.description, self.leader_id, 'sim_description',
                                    'description', ('waypoint',))
        self.guard.end_when([self.resolve_topic_name(BY_KEY['waypoint'].name)],
                            lambda: self._complete() is True)
        steady_timer(self, 0.05, self.on_check)
        if not self.lockstep:
            self.create_timer(self.scenario.dt, self.on_tick)
        self.get_logger().info(f"follower_sim ready ({p['mode']}, "
                               f'{self.scenario.measurement}, follower {self.follower_id})')

    # --- checkpoint --------------------------------------------------------------------------
    def _state(self) -> dict[str, Any]:
        return {key: getattr(self, key) for key in (
            'truth', 'odom_pose', 'executed', 'current', 'pending', 'leader', 'latest_leader',
            'step_messages', 'cache', 'substep_in_step', 'counters', 'published',
            'tf_static_message')}

    def _restore(self, state: dict[str, Any]) -> None:
        """Continue from a checkpoint; realtime: stand still for the time the node was down
        (the zero-velocity odometry of those sub-steps goes out once the run is under way)."""
        for key, value in state.items():
            setattr(self, key, value)
        down = time.time() - (self.checkpoint.saved_at or time.time())
        if not self.lockstep:
            start = int((self.checkpoint.saved_at or time.time()) * 1e9)
            for i in range(1, int(down / self.scenario.dt) + 1):
                self.truth.park(*self.latest_leader)
                self.odom_pose = integrate_unicycle(self.odom_pose, 0.0, 0.0, self.scenario.dt)
                self.parked.append(self._odometry(conversions.stamp(
                    start + i * self.timebase.dt_ns), 0.0, 0.0))
            self.counters['parked_substeps'] += len(self.parked)
        self.resumed = {'from_step': self.executed, 'down_s': round(down, 3),
                        'parked_substeps': len(self.parked)}

    # --- inputs ----------------------------------------------------------------------------
    def on_waypoint(self, msg: Waypoint) -> None:
        """A new waypoint is executed (lockstep: once the leader moved); the waypoint of the
        step last executed republishes that step's messages; a waypoint that does not fit this
        follower's scenario stops the run (exit 2)."""
        foreign = foreign_run(msg, self.params['run_id'])
        if foreign is not None:
            self.counters['foreign_waypoints'] += 1
            self.throttle.warn('foreign', f'refused waypoint {foreign}')
            return
        problem = waypoint_problem(msg, self.follower_id)
        if problem is not None:
            self.counters['rejected_waypoints'] += 1
            self.throttle.warn('waypoint', f'rejected waypoint: {problem}')
            return
        s = self.scenario
        mismatch = waypoint_mismatch(msg, s.dt, s.p_o, s.r, SUBSTEPS, s.max_speed is not None)
        if mismatch is not None:
            stop_run(self, MISMATCH_EXIT, f'the waypoint of step {msg.step} does not fit this '
                                          f'follower: {mismatch}')
            return
        if msg.step == self.executed and self.executed > 0:
            self.counters['repeated_steps'] += 1
            for key, item in self.cache:
                self._publish(key, item)
            return
        if 0 < msg.step < self.executed:
            # an estimator restarted without a checkpoint: the repeat of the last executed
            # step tells it where the run is (it rejoins there)
            self.counters['stale_waypoints'] = self.counters.get('stale_waypoints', 0) + 1
            self.throttle.warn('stale', f'waypoint of step {msg.step}, a step left behind (step '
                                        f'{self.executed} executed): its estimator restarted?'
                                        f' repeating step {self.executed}')
            for key, item in self.cache:
                self._publish(key, item)
            return
        if msg.step <= self.executed or (self.pending is not None
                                         and msg.step <= self.pending.step):
            return
        self.pending = msg
        if self.lockstep:
            self._try_execute()

    def on_leader_odom(self, msg: Odometry) -> None:
        """The leader's velocity of one sub-step."""
        problem = odometry_problem(msg, *odometry_frames('leader', self.leader_id))
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

    def on_check(self) -> None:
        """Watch for intruders; lockstep: execute what became executable once the run may
        start; send the odometry of a parked restart."""
        self.guard.check()
        if self.parked and self._may_run():
            for msg in self.parked:
                self._publish('odometry', msg)
            self.parked = []
        if self.lockstep:
            self._try_execute()

    def _may_run(self) -> bool:
        return not self.finished and self.gate.ready() and self.guard.ready()

    # --- motion ----------------------------------------------------------------------------
    def _odometry(self, stamp: Any, v_cmd: float, omega_cmd: float) -> Odometry:
        s = self.scenario
        return conversions.odometry(stamp, self.frames['odom'], self.follower_id,
                                    self.odom_pose, v_cmd, omega_cmd,
                                    (s.sigma_v ** 2, s.sigma_omega ** 2))

    def _substep(self, v_cmd: float, omega_cmd: float, leader: tuple[float, float],
                 stamp: Any, keep: bool = True) -> None:
        """Drive one sub-step; its odometry and /tf are kept for the step's cache and, in
        realtime, published at once (lockstep: by _try_execute, when the step is complete)."""
        self.truth.execute(v_cmd, omega_cmd, leader[0], leader[1])
        self.odom_pose = integrate_unicycle(self.odom_pose, v_cmd, omega_cmd, self.scenario.dt)
        odom = self._odometry(stamp, v_cmd, omega_cmd)
        tf = conversions.tf_message([conversions.transform(
            stamp, self.frames['odom'], self.frames['body'], self.odom_pose)])
        for key, msg in (('odometry', odom), ('tf', tf)):
            if keep:
                self.step_messages.append((key, msg))
            if not self.lockstep:
                self._publish(key, msg)

    def _finish_step(self, step: int, stamp: Any) -> None:
        """Measure; the step's cache holds its messages in the order of WAITED_FOR."""
        s = self.scenario
        truth = conversions.pose_stamped(stamp, self.leader_id, self.truth.x)
        parts = measurement_parts(s, step, self.truth.measure())
        meas = [conversions.measurement(stamp, self.follower_id, self.follower_id, step, kind,
                                        value, variance, self.params['run_id'])
                for kind, value, variance in parts]
        tf = conversions.tf_message([conversions.transform(
            stamp, self.leader_id, self.frames['truth'], self.truth.x)])
        for key, msg in (('truth', truth), *(('measurement', m) for m in meas), ('tf', tf)):
            self.step_messages.append((key, msg))
            if not self.lockstep:
                self._publish(key, msg)
        self.executed = step
        self.cache = sorted(self.step_messages, key=lambda item: WAITED_FOR.get(item[0], 3))
        self.step_messages = []

    def _try_execute(self) -> None:
        """Lockstep: run the pending waypoint once the leader's sub-steps are known."""
        msg = self.pending
        if msg is None or not self._may_run():
            return
        substeps = step_substeps(msg.step)
        if any(n not in self.leader for n in substeps):
            return
        self.step_messages = []
        for j, n in enumerate(substeps):
            self._substep(msg.linear_velocity[j], msg.angular_velocity[j], self.leader.pop(n),
                          conversions.stamp(self.timebase.substep_end(n)))
        self._finish_step(msg.step, conversions.stamp(self.timebase.measurement_stamp(msg.step)))
        for key, item in self.cache:
            self._publish(key, item)
        self.pending = None
        self.checkpoint.save(self._state())

    def on_tick(self) -> None:
        """Realtime: execute one sub-step of the current step.

        The sub-steps of a waypoint are only meaningful together (rotate, then translate), so a
        step starts with a waypoint; a tick without one holds position instead of repeating an
        old command (repeating a translation made the formation diverge).
        """
        if not self._may_run():
            return
        if self.substep_in_step == 0:
            if self.pending is not None and self.pending.step > self.executed:
                self.current, self.pending = self.pending, None
                self.step_messages = []
            else:
                self.current = None
        now = self.get_clock().now().to_msg()
        if self.current is None:
            if self.executed == 0:
                return                               # wait for the first waypoint
            self.counters['missed_cycles'] += 1
            self._substep(*hold_command(self.latest_leader[1]), self.latest_leader, now,
                          keep=False)
        else:
            j = self.substep_in_step
            self._substep(self.current.linear_velocity[j], self.current.angular_velocity[j],
                          self.latest_leader, now)
            self.substep_in_step = (j + 1) % SUBSTEPS
            if self.substep_in_step == 0:
                self._finish_step(self.current.step, now)
                self.current = None
        self.checkpoint.save(self._state())

    def _publish(self, key: str, msg: Any) -> None:
        {'odometry': self.odom_pub, 'measurement': self.meas_pub, 'truth': self.truth_pub,
         'tf': self.tf_pub}[key].publish(msg)
        self.published[key] += 1

    def _complete(self) -> bool | None:
        """Whether the follower executed every step of its estimator's run (None: a run until
        stopped; False too when the estimator's run was never heard of)."""
        steps = self.guard.peer_steps(self.resolve_topic_name(BY_KEY['description'].name))
        return None if steps == 0 else steps is not None and self.executed >= steps

    def summary(self) -> dict[str, Any]:
        """What the follower did: steps executed, counters, its final true pose; not ok when
        it failed or was stopped before the last step of a run of known length."""
        complete = self._complete()
        return {'ok': not self.error and complete is not False, 'error': self.error or None,
                'complete': complete,
                'run_id': self.params['run_id'], 'follower_id': self.follower_id,
                'executed_steps': self.executed, 'resumed': self.resumed,
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
