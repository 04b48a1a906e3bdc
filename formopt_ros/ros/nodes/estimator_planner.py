"""estimator_planner: one follower's EKF and motion strategy; publishes estimate and waypoint."""
from __future__ import annotations

import math
import sys
import threading
import time
from collections import deque
from concurrent.futures import Future
from dataclasses import replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from formopt_interfaces.msg import Measurement, PlannerStatus, Waypoint
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from formopt_ros.core.estimator import StepPlan
from formopt_ros.core.session import EstimatorSession, StepOutcome
from formopt_ros.core.field import dead_reckoned_estimate, odometry_pose_at
from formopt_ros.core.protocol import SUBSTEPS, Timebase, step_substeps
from formopt_ros.core.simulation import leader_poses, trial_streams
from formopt_ros.core.strategies import make_strategy
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.checkpoint import open_checkpoint
from formopt_ros.ros.gate import PublisherGate
from formopt_ros.ros.guard import follower_guard
from formopt_ros.ros.naming import peer_topic
from formopt_ros.ros.params import Param, ParameterError, declare, validate_on_set
from formopt_ros.ros.run_config import (
    CHECKPOINT_PATH, FOLLOWER_ID, FORMATION_FILE, LEADER_ID, MODE, RECORDERS, RUN_ID,
    SCENARIO_PARAMS, SEED, SUMMARY_PATH, TRIAL, WAIT_FOR_PEERS, follower_run, formation_defaults,
    strategy_options, strategy_params)
from formopt_ros.ros.runtime import (
    Throttle, node_main, steady_timer, stop_run, stops_on_a_plan_outside_the_disc,
    write_summary)
from formopt_ros.wire import inputs
from formopt_ros.wire.description import RunDescription as Description
from formopt_ros.wire.description import StrategyChange
from formopt_ros.wire.messages import foreign_run, header_ns, pose_values
from formopt_ros.wire.topics import BY_KEY, DEFAULT_FOLLOWER, follower_frames

PARAMS = [FORMATION_FILE, FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS + \
    strategy_params() + [
        Param('steps', 0, 'measurement steps to run, then exit 0 (0: run until stopped)', 0,
              10**9),
        Param('resend_timeout', 1.0, 'resend the last waypoint after this long without progress '
              '(a peer restarted, a message was lost), s', 0.01, 3600.0, read_only=False),
        Param('status_period', 1.0, 'publish /diagnostics this often and the status at least '
              'this often (also while no step completes), s', 0.05, 60.0, read_only=False),
        Param('start_timeout', 0.0, 'end the node (exit 1, naming what it waits for) when its '
              'run has not started this long after the node did (a peer missing or frozen), '
              's; 0: wait for good (run_formation.sh sets 60)', 0.0, 86400.0),
        Param('stall_timeout', 20.0, 'end the run (exit 1, naming the inputs not heard) when '
              'no step completes for this long once one did (a peer frozen or gone; before, '
              'start_timeout), s; 0: wait for good', 0.0, 86400.0, read_only=False),
        RUN_ID, RECORDERS, WAIT_FOR_PEERS, SUMMARY_PATH, CHECKPOINT_PATH]
SUMMARY = ("The follower's EKF and motion strategy: odometry and measurements in; estimate, "
           'waypoint, status, markers, leader -> <follower>/estimate on /tf, /diagnostics and '
           'the run description out.')
#: The inputs a stalled run names when nothing came on them since the last step.
STALL_INPUTS = {'leader_odom': 'leader odometry (leader_sim)',
                'follower_odom': 'follower odometry (follower_sim)',
                'measurement': 'measurements (follower_sim)'}
#: Publish the markers at most this often (wall time, s): a lockstep run makes hundreds of
#: steps a second, a 3D view needs a few frames.
MARKER_PERIOD = 0.1
#: A rejoining estimator's prior (see :meth:`EstimatorPlannerNode._rejoin`): the relative pose
#: dead-reckoned from both robots' odometry poses
#: (:func:`~formopt_ros.core.field.dead_reckoned_estimate`), its covariance times
#: REJOIN_INFLATION: the drift terms are approximations, and a broader prior makes the range
#: EKF's linearisation worse (``scripts/measure_rejoin.py``: 1.5 keeps the steps after a rejoin
#: as consistent as the run's own; 4 lets late rejoins diverge more often).
REJOIN_INFLATION = 1.5
#: Odometry poses kept per robot for a rejoin (the last few steps' messages).
REJOIN_POSES = 8 * SUBSTEPS


class EstimatorPlannerNode(Node):
    """Feeds its inputs to an :class:`~formopt_ros.core.session.EstimatorSession` and
    publishes what each processed step produced.

    lockstep: step k is processed once its measurement and the leader's and follower's odometry
    of its sub-steps (matched by their integer-ns simulated-time stamps) are all in; then the
    waypoint of step k + 1 is published. The arithmetic equals :func:`run_trial`.
    realtime: each measurement is processed on arrival with the follower odometry received
    since the last one, each paired with the latest leader odometry.
    Bad inputs are refused with a throttled warning and counted in the status. The run starts
    (waypoint 1) once every publisher has matched its subscribers (leader_sim and follower_sim
    on the waypoint, plus the recorders) and the descriptions of follower_sim and leader_sim
    agree with this node's (a mismatch stops it with exit code 2; see ros.guard). With a
    checkpoint it resumes where a previous instance stopped.
    """

    def __init__(self, cli_args: list[str] | None = None) -> None:
        """The node; ``cli_args`` are node-local ROS arguments (several in one process)."""
        super().__init__('estimator_planner', namespace=DEFAULT_FOLLOWER, cli_args=cli_args)
        self.params = p = declare(self, PARAMS, formation_defaults(self, 'follower'))
        self.run = follower_run(self, p, strategy_owned=True)
        self.follower_id, self.leader_id = self.run.follower_id, self.run.leader_id
        self.scenario = self.run.spec.scenario
        self.frames = follower_frames(self.follower_id)
        strategy = make_strategy(self.run.spec.strategy, **self.run.spec.options)
        strategy.prepare(self.scenario)           # e.g. PERIODIC's cycle design, before step 1
        _, planner_rng = trial_streams(self.run.spec.seed, self.run.trial)
        self.lockstep = p['mode'] == 'lockstep'
        self.timebase = Timebase.from_dt(self.scenario.dt)
        self.session = EstimatorSession.create(self.scenario, strategy, planner_rng,
                                               self.lockstep, p['steps'])
        self.description = Description(self.follower_id, self.scenario, self.run.spec.strategy,
                                       dict(strategy.settings), self.run.spec.seed,
                                       self.run.trial, p['mode'], p['steps'], p['run_id'],
                                       self.leader_id)
        self.started = False
        self.finished = False
        self.exit_code = 0
        self.error = ''
        self.resumed: dict[str, Any] | None = None
        self.rejoined: dict[str, Any] | None = None
        #: (stamp ns, odometry pose (3,), v m/s, omega rad/s) of the last messages of each
        #: robot, while no step is processed (what a rejoin re-initialises the estimate from)
        self.odometry_poses: dict[str, deque[tuple[int, Any, float, float]]] = {
            robot: deque(maxlen=REJOIN_POSES) for robot in ('follower', 'leader')}
        self.last_plan: StepPlan | None = None
        self.last_waypoint: Waypoint | None = None
        self.last_progress = self.last_step_at = self.created_at = time.monotonic()
        self.stepped = False            # a step completed in this process
        self.heard_at_step: dict[str, int] = {}     # self.received at the last completed step
        #: per stall input: (messages received, when that count was first seen) on the timer
        self.heard = {key: (0, time.monotonic()) for key in STALL_INPUTS}
        self.last_status = 0.0
        self.last_diagnostics = 0.0
        self.last_markers = -math.inf
        self.watch_reported = False
        #: a strategy being designed off the executor: (future of the design's seconds, the
        #: strategy, the step at the request); the current strategy plans meanwhile
        self.pending: tuple[Future, Any, int] | None = None
        self.strategy_changes: list[dict[str, Any]] = []
        self.solve_times: list[float] = []
        self.slow_plans = 0                    # realtime plans that took longer than a step
        #: plans that fell back, by kind (e.g. 'unreachable': the reach disc missed the slot's
        #: disc; 'rq': RAM could not prove its answer; 'best-line': a range-bearing search that did
        #: not close)
        self.plan_fallbacks: dict[str, int] = {}
        self.last_planned = 0                 # the step of the last plan counted
        self.received = {key: 0 for key in ('leader_odom', 'follower_odom', 'measurement',
                                            'truth')}
        self.published = {key: 0 for key in ('estimate', 'waypoint', 'status', 'markers', 'tf',
                                             'diagnostics', 'description')}
        self.checkpoint, state = open_checkpoint(self, p, self.description.to_json())
        if state is not None:
            self._restore(state)
        self.throttle = Throttle(self)
        self.gate = PublisherGate(self, p['recorders'], int(p['wait_for_peers']))
        stream = qos.STREAM
        self.estimate_pub = self.gate.add(self.create_publisher(
            PoseWithCovarianceStamped, BY_KEY['estimate'].name, stream), 'estimate')
        self.waypoint_pub = self.gate.add(self.create_publisher(
            Waypoint, BY_KEY['waypoint'].name, stream), 'waypoint')
        self.status_pub = self.gate.add(self.create_publisher(
            PlannerStatus, BY_KEY['status'].name, stream), 'status')
        self.markers_pub = self.gate.add(self.create_publisher(
            MarkerArray, BY_KEY['markers'].name, stream), 'markers')
        self.tf_pub = self.gate.add(self.create_publisher(TFMessage, '/tf', qos.TF), 'tf')
        self.diagnostics_pub = self.gate.add(self.create_publisher(
            DiagnosticArray, '/diagnostics', qos.DIAGNOSTICS), 'diagnostics')
        self.input_topics = {'follower_odom': BY_KEY['follower_odom'].name,
                             'leader_odom': peer_topic(self, self.leader_id, 'leader_odom'),
                             'measurement': BY_KEY['measurement'].name}
        self.create_subscription(Odometry, self.input_topics['follower_odom'],
                                 self.on_follower_odom, qos.SUBSCRIBED)
        self.create_subscription(Odometry, self.input_topics['leader_odom'],
                                 self.on_leader_odom, qos.SUBSCRIBED)
        # truth before measurement: when both are ready, the executor serves the truth first
        self.create_subscription(PoseStamped, BY_KEY['truth'].name, self.on_truth,
                                 qos.SUBSCRIBED)
        self.create_subscription(Measurement, self.input_topics['measurement'],
                                 self.on_measurement, qos.SUBSCRIBED)
        self.guard = follower_guard(self, self.description, self.leader_id, 'description',
                                    'sim_description', ('follower_odom', 'measurement', 'truth'))
        self.published['description'] = 1                # announced by the guard
        validate_on_set(self, PARAMS, self.on_set)
        steady_timer(self, 0.05, self.on_timer)
        self.get_logger().info(f"estimator_planner ready ({p['mode']}, "
                               f'{self.scenario.measurement}, strategy '
                               f'{self.run.spec.strategy}, follower {self.follower_id})')

    # --- run-time parameter changes ----------------------------------------------------------
    def on_set(self, change: dict[str, Any]) -> str | None:
        """Accept a new strategy or strategy option (validated here; designed off the executor,
        see :meth:`_design`) and the timing parameters; refuse anything that does not build a
        strategy."""
        values = {**self.params, **change}
        if any(name == 'strategy' or name.startswith(f"{values['strategy']}_")
               for name in change):
            options = strategy_options(values['strategy'], values)
            try:           # the rules of the door (a range-bearing follower refuses RAM)
                replace(self.run.spec, strategy=values['strategy'], options=options)
                strategy = make_strategy(values['strategy'], **options)
            except ValueError as error:
                return str(error)
            self._design(strategy)
        self.params.update(change)
        return None

    def _design(self, strategy: Any) -> None:
        """Prepare ``strategy`` (e.g. PERIODIC's cycle design, 10-20 s) on a daemon thread: the
        executor keeps serving inputs and the current strategy keeps planning; the new one
        takes over in :meth:`_take_ready` (a later request supersedes this one)."""
        future: Future = Future()
        scenario = self.scenario

        def work() -> None:
            started = time.monotonic()
            try:
                strategy.prepare(scenario)
            except Exception as error:          # reported by _take_ready, the node goes on
                future.set_exception(error)
                return
            future.set_result(time.monotonic() - started)

        if self.pending is not None:
            self.get_logger().warning(f'strategy {self.pending[1]!r} superseded before it was '
                                      'ready')
        self.pending = (future, strategy, self.session.step)
        threading.Thread(target=work, name='strategy-design', daemon=True).start()
        self.get_logger().info(f'preparing strategy {strategy!r} off the executor; '
                               f'{self.session.estimator.strategy.name} plans until it is ready')

    def _take_ready(self) -> None:
        """Switch to the pending strategy once its design is done (after the run started and
        before it ends); the change (step, old, new) goes to the log, the summary and, with a
        new latched description, the bag."""
        if self.pending is None or not self.pending[0].done() or not self.started or \
                self.session.finished:
            return
        future, strategy, requested = self.pending
        self.pending = None
        old = self.session.estimator.strategy.name
        error = future.exception()
        if error is not None:
            self.get_logger().error(f'strategy {strategy!r} not taken, its preparation failed: '
                                    f'{type(error).__name__}: {error}; {old} goes on')
            return
        step = self.session.step
        self.session.estimator.strategy = strategy
        change = StrategyChange(step, strategy.name, dict(strategy.settings))
        self.strategy_changes.append({'step': step, 'from': old, 'to': strategy.name,
                                      'options': dict(strategy.settings),
                                      'requested_at_step': requested,
                                      'prepared_in_s': round(future.result(), 3)})
        self._describe(replace(self.description, strategy_changes=(
            *self.description.strategy_changes, change)))
        self.get_logger().info(f'strategy {old} -> {strategy!r} after step {step} (requested '
                               f'at step {requested}, prepared in {future.result():.2f} s); it '
                               f'plans from step {step + 2}')

    def _describe(self, description: Description) -> None:
        """Publish the run description again (latched): the same run, with its changes."""
        self.description = description
        self.guard.reannounce(description.to_json())
        self.published['description'] += 1

    # --- inputs ----------------------------------------------------------------------------
    def _now_ns(self) -> int | None:
        return None if self.lockstep else self.get_clock().now().nanoseconds

    def _refused(self, key: str, reason: str | None) -> None:
        """Warn of a refused input; advance either way (a refused input may stand in for its
        step in lockstep: core/session.py)."""
        if reason is not None:
            self.throttle.warn(key, f'rejected {key}: {reason}')
        self._advance()

    def on_follower_odom(self, msg: Odometry) -> None:
        """One sub-step of the follower's odometry."""
        self.received['follower_odom'] += 1
        if self._left_behind('follower odometry', msg):
            return
        self._refused('follower_odom', inputs.feed_odometry(
            self.session, 'follower', msg, self.follower_id, self._now_ns()))

    def on_leader_odom(self, msg: Odometry) -> None:
        """One sub-step of the leader's odometry."""
        self.received['leader_odom'] += 1
        if self._left_behind('leader odometry', msg):
            return
        self._refused('leader_odom', inputs.feed_odometry(
            self.session, 'leader', msg, self.leader_id, self._now_ns()))

    def on_measurement(self, msg: Measurement) -> None:
        """One range or bearing measurement."""
        self.received['measurement'] += 1
        if foreign_run(msg, self.params['run_id']) is None and \
                self._left_behind('measurement', msg, int(msg.step)):
            return
        self._refused('measurement', inputs.feed_measurement(
            self.session, msg, self.follower_id, self._now_ns(), self.params['run_id']))

    def on_truth(self, msg: PoseStamped) -> None:
        """Ground truth, for evaluation only (NEES, summary), matched to a step by its stamp."""
        self.received['truth'] += 1
        inputs.feed_truth(self.session, msg)

    # --- rejoin ----------------------------------------------------------------------------
    def _left_behind(self, source: str, msg: Any, step: int | None = None) -> bool:
        """Whether to drop an input because this estimator rejoined after it.

        A started estimator that processed no step and resumed no checkpoint (a restart
        without one) and hears of step k >= 2 was left behind by its peers: it rejoins after
        step k (lockstep: k of any input's stamp, the peers repeat step k; realtime: k of a
        measurement, follower_sim re-sends its last one when it hears waypoint 1). Inputs of
        step k and before are then dropped and counted in the summary's ``rejoined``.
        """
        stamp_ns = header_ns(msg)
        rejoining = self._rejoining()
        if source != 'measurement' and (self.session.step == 0 or rejoining):
            robot = 'leader' if source == 'leader odometry' else 'follower'
            self.odometry_poses[robot].append((stamp_ns, pose_values(msg.pose.pose),
                                               msg.twist.twist.linear.x,
                                               msg.twist.twist.angular.z))
        if self.lockstep and step is None:
            step = self._stamp_step(stamp_ns)
        if self.rejoined is None:
            if step is None or step < 2 or self.resumed is not None or not self.started or \
                    self.finished or self.session.step != 0 or \
                    (not self.lockstep and source != 'measurement'):
                return False
            self._rejoin(step, source, self.timebase.measurement_stamp(step) if self.lockstep
                         else stamp_ns)
        elif rejoining:
            self._settle_rejoin()
        rejoined = self.rejoined
        if rejoined is None:                # a finished run: nothing to rejoin (stopped)
            return True
        dropped = step <= rejoined['at_step'] if step is not None else \
            not self.lockstep and stamp_ns <= rejoined['stamp_ns']
        rejoined['dropped_inputs'] += dropped
        return dropped

    def _rejoining(self) -> bool:
        """A rejoin waits for the odometry poses its estimate is made from."""
        return self.rejoined is not None and self.rejoined['prior_covariance_diagonal'] is None

    def _stamp_step(self, stamp_ns: int) -> int | None:
        """The step of a lockstep odometry stamp (None off the grid)."""
        substep = self.timebase.substep_ending_at(stamp_ns)
        return None if substep is None else substep // SUBSTEPS + 1

    def _rejoin(self, step: int, source: str, stamp_ns: int) -> None:
        """Continue the run after the peers' step ``step`` (its measurement stamped
        ``stamp_ns``): the next step is step + 1; the estimate is re-initialised at that stamp
        from both robots' odometry poses (:meth:`_settle_rejoin`, once they are in); the
        estimate of the steps missed is lost. Realtime: the time the follower held still while
        this node was down is filled with hold sub-steps (counted)."""
        session = self.session
        if session.steps and step >= session.steps:
            stop_run(self, 1, f'the run had finished (the peers are at its last step, {step}) '
                              'before this estimator started: nothing to rejoin')
            return
        leader = None
        if self.lockstep:
            leader = self.scenario.leader.velocity(step_substeps(step)[-1], self.scenario.dt)
        session.assembler.rejoin(step + 1, stamp_ns, leader)
        if not self.lockstep:
            session.assembler.open_gap(self.get_clock().now().nanoseconds, since_ns=stamp_ns)
        self.rejoined = {'at_step': step, 'heard_from': source, 'stamp_ns': stamp_ns,
                         'prior_covariance_diagonal': None, 'dropped_inputs': 0,
                         'since': time.monotonic()}
        self.get_logger().warning(
            f'rejoining the run after step {step} (heard from the {source}; no checkpoint): '
            f'steps 1-{step} are not estimated here; the estimate restarts from both robots\' '
            'odometry poses')
        self._settle_rejoin()

    @stops_on_a_plan_outside_the_disc
    def _settle_rejoin(self, force: bool = False) -> None:
        """Once both robots' odometry poses at the rejoin stamp T are known (or with ``force``,
        from the nearest the follower sent): the estimate at T from them, covariance times
        :data:`REJOIN_INFLATION`; then the plan of the next step is sent. The leader's pose is
        its path's in lockstep (leader_sim drives it exactly), else its odometry's nearest
        to T carried to T with its twist."""
        rejoined = self.rejoined
        if rejoined is None or not self._rejoining():
            return
        T, step = rejoined['stamp_ns'], rejoined['at_step']
        follower = odometry_pose_at(self.odometry_poses['follower'], T, self.timebase.dt_ns,
                                    force)
        leader = tuple(leader_poses(self.scenario, step)[-1]) if self.lockstep else \
            odometry_pose_at(self.odometry_poses['leader'], T, None, True)
        if follower is None or leader is None:
            return
        scenario, estimator = self.scenario, self.session.estimator
        x0, P0 = scenario.initial_estimate()
        x, P = dead_reckoned_estimate(
            x0, P0, leader, follower, SUBSTEPS * step, scenario.dt,
            (scenario.sigma_v, scenario.sigma_omega, scenario.sigma_v_leader,
             scenario.sigma_omega_leader))
        estimator.state, estimator.covariance = x, REJOIN_INFLATION * P
        rejoined['prior_covariance_diagonal'] = np.diag(estimator.covariance).tolist()
        del rejoined['since']
        self.get_logger().warning(
            f'rejoined after step {step}: estimate {np.round(x, 3).tolist()} from the '
            'odometry poses, covariance diag '
            f'{np.round(np.diag(estimator.covariance), 6).tolist()}')
        self.last_plan = self.session.plan_next()
        self._send(self.last_plan)
        self.last_progress = self.last_step_at = time.monotonic()

    # --- processing ------------------------------------------------------------------------
    @stops_on_a_plan_outside_the_disc
    def _advance(self) -> None:
        if self.finished:
            return
        self._take_ready()
        outcomes = self.session.advance()
        if outcomes:
            self.last_plan = outcomes[-1].plan
            self.checkpoint.save(self._state(), finished=self.session.finished)
        for outcome in outcomes:
            self._publish(outcome)
        watch = self.session.watch
        if watch.failed and not self.watch_reported:
            self.watch_reported = True
            self.get_logger().error(f'filter inconsistent at step {watch.worst.step}: '
                                    f'{watch.worst.reason}; the run will not end ok')
        if self.session.finished and not self.finished:
            self.finish()

    # --- checkpoint --------------------------------------------------------------------------
    def _state(self) -> dict[str, Any]:
        return {'session': self.session, 'last_plan': self.last_plan,
                'solve_times': self.solve_times, 'received': self.received,
                'plan_fallbacks': self.plan_fallbacks, 'last_planned': self.last_planned,
                'slow_plans': self.slow_plans, 'published': self.published,
                'strategy_changes': self.strategy_changes,
                'description': self.description.to_json()}

    def _restore(self, state: dict[str, Any]) -> None:
        """Continue a run from a checkpoint: lockstep exactly (the peers repeat what was lost);
        realtime with the odometry lost while down filled by hold sub-steps (reported)."""
        self.session = state['session']
        self.last_plan = state['last_plan']
        self.solve_times = state['solve_times']
        self.plan_fallbacks = state.get('plan_fallbacks', {})
        self.last_planned = state.get('last_planned', 0)
        self.slow_plans = state.get('slow_plans', 0)
        self.received, self.published = state['received'], state['published']
        self.published.setdefault('description', 0)
        self.strategy_changes = state.get('strategy_changes', [])
        if 'description' in state:
            self.description = Description.from_json(state['description'])
        gap = time.time() - (self.checkpoint.saved_at or time.time())
        if not self.lockstep:
            self.session.assembler.open_gap(self.get_clock().now().nanoseconds)
        self.resumed = {'from_step': self.session.step, 'down_s': round(gap, 3)}

    def _stamp(self, nanoseconds: int) -> Any:
        return conversions.stamp(nanoseconds) if self.lockstep else \
            self.get_clock().now().to_msg()

    def _publish(self, outcome: StepOutcome) -> None:
        stamp = self._stamp(outcome.stamp_ns)
        if outcome.plan is not None:
            self._send(outcome.plan)        # first: the leader and the follower wait for it
        self.estimate_pub.publish(conversions.estimate(stamp, self.leader_id, outcome.x,
                                                       outcome.P))
        self.tf_pub.publish(conversions.tf_message([conversions.transform(
            stamp, self.leader_id, self.frames['estimate'], outcome.x)]))
        self.published['estimate'] += 1
        self.published['tf'] += 1
        self.last_progress = self.last_step_at = time.monotonic()
        self.stepped = True
        self.heard_at_step = dict(self.received)
        self._publish_status(stamp, outcome.step, outcome.weighted_trace)
        if time.monotonic() - self.last_markers >= MARKER_PERIOD or outcome.plan is None:
            self.last_markers = time.monotonic()
            self.markers_pub.publish(conversions.markers(
                stamp, self.leader_id, self.follower_id, self.scenario.slot, self.scenario.r,
                None if outcome.plan is None else outcome.plan.solution.p, outcome.x,
                outcome.P))
            self.published['markers'] += 1

    def _publish_status(self, stamp: Any, step: int, weighted_trace: float) -> None:
        self.status_pub.publish(conversions.status(
            stamp, '', self.follower_id, step, self.session.estimator.strategy.name,
            self.scenario.measurement, weighted_trace, self.last_plan,
            self.session.counters.as_dict(), self.params['run_id']))
        self.published['status'] += 1
        self.last_status = time.monotonic()

    def _send(self, plan: StepPlan) -> None:
        self.solve_times.append(plan.solution.solve_time_s)
        if plan.step > self.last_planned:      # each plan once, however often it is resent
            self.last_planned = plan.step
            step_period = SUBSTEPS * self.scenario.dt
            if not self.lockstep and plan.solution.solve_time_s > step_period:
                self.slow_plans += 1
                self.throttle.warn('slow plan', (
                    f'planning step {plan.step} took {plan.solution.solve_time_s:.2f} s, longer '
                    f'than a step ({step_period:g} s): the node falls behind the run and its '
                    'status and /diagnostics wait meanwhile; choose cheaper strategy settings '
                    '(e.g. a smaller lookahead_beam or lookahead_horizon)'))
            if plan.solution.fallback:
                kind = str(plan.solution.fallback)
                self.plan_fallbacks[kind] = self.plan_fallbacks.get(kind, 0) + 1
        self.last_waypoint = conversions.waypoint(
            self._stamp(self.timebase.waypoint_stamp(plan.step)), self.leader_id,
            self.follower_id, plan, self.scenario.slot, self.scenario.r, self.scenario.dt,
            self.params['run_id'])
        self.waypoint_pub.publish(self.last_waypoint)
        self.published['waypoint'] += 1

    @stops_on_a_plan_outside_the_disc
    def on_timer(self) -> None:
        """Start the run once the publishers are matched and the peers agree; resend a waypoint
        that got no answer; watch for intruders; publish the status while no step completes
        and /diagnostics every status_period."""
        now = time.monotonic()
        self.guard.check()
        self._take_ready()
        if not self.finished and not self.started:
            if self.gate.ready() and self.guard.ready():
                self.started = True
                if self.last_plan is None:               # a new run (else: resumed)
                    self.last_plan = self.session.plan_next()
                self._send(self.last_plan)
                self.last_progress = self.last_step_at = now
                self.heard = {key: (self.received[key], now) for key in STALL_INPUTS}
            elif 0 < self.params['start_timeout'] < now - self.created_at:
                waiting = [f'subscribers on {m}' for m in self.gate.missing()] \
                    if not self.gate.ready() else \
                    [f'the description on {topic}' for topic in self.guard.missing()]
                stop_run(self, 1, f"the run did not start within {self.params['start_timeout']:g}"
                                  ' s (start_timeout): waiting for '
                                  + (', '.join(waiting) or 'the peers'))
        elif self.rejoined is not None and self._rejoining() and \
                now - self.rejoined['since'] > self.params['resend_timeout']:
            self._settle_rejoin(force=True)     # the odometry of the rejoin step was lost
        elif self.started and not self.finished and self._stalled(now):
            pass
        elif not self.finished and self.last_waypoint is not None and \
                now - self.last_progress > self.params['resend_timeout']:
            self.throttle.warn('resend', f'no progress on step {self.session.step + 1}: '
                                         'resending its waypoint')
            self.waypoint_pub.publish(self.last_waypoint)
            self.published['waypoint'] += 1
            self.last_progress = now
        if self.gate.open and now - self.last_status >= self.params['status_period']:
            self._publish_status(self.get_clock().now().to_msg(), self.session.step,
                                 self.session.estimator.weighted_trace())
        if self.gate.open and now - self.last_diagnostics >= self.params['status_period']:
            self.last_diagnostics = now              # every period, whether steps complete
            self.diagnostics_pub.publish(DiagnosticArray(
                header=conversions.header(self.get_clock().now().to_msg(), ''),
                status=[self.diagnostic()]))
            self.published['diagnostics'] += 1

    def _stalled(self, now: float) -> bool:
        """End the run (exit 1) when no step completed, or one input was not heard, for
        stall_timeout s (a peer frozen or gone; in realtime the steps go on without the
        leader's odometry); the message names the silent inputs, those whose publisher left
        the ROS graph first. True when it ended the run. Until a step completes the limit is
        start_timeout: a peer may still be preparing (PERIODIC designs a cycle locked to an
        S-curve, 10-40 s, before its step 1)."""
        name = 'stall_timeout' if self.stepped else 'start_timeout'
        limit = self.params[name]
        for key in STALL_INPUTS:
            if self.received[key] != self.heard[key][0]:
                self.heard[key] = (self.received[key], now)
        quiet = [key for key in STALL_INPUTS if now - self.heard[key][1] > limit]
        if limit <= 0 or not quiet and now - self.last_step_at <= limit:
            return False
        silent = quiet or [key for key in STALL_INPUTS
                           if self.received[key] == self.heard_at_step.get(key, 0)]
        gone = [key for key in silent if self.count_publishers(self.input_topics[key]) == 0]
        names = [f'{STALL_INPUTS[key]}, no publisher left on {self.input_topics[key]}'
                 for key in gone] + [STALL_INPUTS[key] for key in silent if key not in gone]
        what = f'nothing heard for {limit:g} s' if quiet else \
            f'no step completed for {now - self.last_step_at:.0f} s'
        stop_run(self, 1, f'{what} ({name}) after step {self.session.step}: '
                          + (f"silent: {'; '.join(names)}" if names else
                             'inputs arrive but do not complete the step'))
        return True

    def diagnostic(self) -> Any:
        """OK while steps complete; WARN when inputs were refused, the run stalls or waits for
        subscribers, or the consistency watch warns; ERROR when the estimate is not finite or
        the watch saw sustained inconsistency or sustained gating (for the rest of the run)."""
        estimator, counters = self.session.estimator, self.session.counters
        watch = self.session.watch
        stalled = time.monotonic() - self.last_progress
        level, message = 'OK', f'step {self.session.step}'
        if self.rejoined is not None:
            message += f" (rejoined at step {self.rejoined['at_step']}, no checkpoint)"
        if not (np.all(np.isfinite(estimator.x)) and np.all(np.isfinite(estimator.P))):
            level, message = 'ERROR', 'the estimate is not finite'
        elif self.error:
            level, message = 'ERROR', self.error
        elif watch.failed:
            current = watch.verdict()
            level, message = 'ERROR', current.reason if current.level == 'error' else \
                f'inconsistent since step {watch.worst.step}: {watch.worst.reason}'
        elif not self.gate.open:
            level, message = 'WARN', 'waiting for subscribers: ' + ', '.join(self.gate.missing())
        elif not self.guard.ready():
            level, message = 'WARN', 'waiting for the descriptions on: ' + ', '.join(
                self.guard.missing())
        elif self.started and not self.finished and stalled > 2 * self.params['status_period']:
            level, message = 'WARN', f'no progress for {stalled:.1f} s at step ' \
                                     f'{self.session.step}'
        elif counters.rejected_measurements or counters.rejected_odometry or \
                counters.gated_measurements or counters.foreign_messages:
            level, message = 'WARN', f'inputs refused, last: {self.session.last_reason}'
        elif watch.verdict().level == 'warn':
            level, message = 'WARN', watch.verdict().reason
        solve = self.solve_times[-1] if self.solve_times else 0.0
        return conversions.diagnostic(
            self.get_fully_qualified_name(), self.follower_id, level, message, {
                'step': self.session.step, 'strategy': estimator.strategy.name,
                'mode': self.params['mode'], 'weighted_trace_m2': estimator.weighted_trace(),
                'solve_time_ms': 1e3 * solve,
                'mean_solve_time_ms': 1e3 * float(np.mean(self.solve_times))
                if self.solve_times else 0.0,
                **counters.as_dict(), 'seconds_since_progress': round(stalled, 3),
                'consistency': watch.verdict().level,
                'inconsistent_steps': watch.counters['inconsistent_steps'],
                'gating_steps': watch.counters['gating_steps'],
                'rejoined_at_step': self.rejoined['at_step'] if self.rejoined else 0})

    # --- end of run --------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Final state, evaluation and message counts of the run; not ok after an error or
        after sustained inconsistency or gating (``consistency``)."""
        estimator = self.session.estimator
        truth = self.session.final_truth
        watch = self.session.watch
        inconsistent = f'filter inconsistent at step {watch.worst.step}: {watch.worst.reason}' \
            if watch.failed else ''
        return {
            'ok': not self.error and not watch.failed and (
                self.session.finished or not self.params['steps']),
            'error': self.error or inconsistent or None,
            'run_id': self.params['run_id'],
            'steps': self.session.step,
            'resumed': self.resumed,
            'rejoined': self.rejoined,
            'follower_id': self.follower_id,
            'strategy': estimator.strategy.name,
            'strategies': self.description.strategies(),
            'strategy_changes': self.strategy_changes,
            'strategy_pending': None if self.pending is None else self.pending[1].name,
            'measurement': self.scenario.measurement,
            'mode': self.params['mode'],
            'seed': self.run.spec.seed,
            'final_estimate': estimator.x.tolist(),
            'final_covariance': estimator.P.tolist(),
            'final_truth': None if truth is None else truth.tolist(),
            'final_weighted_trace': estimator.weighted_trace(),
            'mean_nees': self.session.mean_nees(),
            'counters': self.session.counters.as_dict(),
            'plan_fallbacks': dict(self.plan_fallbacks), 'slow_plans': self.slow_plans,
            'consistency': watch.summary(),
            'message_counts': {'received': dict(self.received),
                               'published': dict(self.published)},
        }

    def finish(self) -> None:
        """End the run: the spin loop returns and ``close`` writes the summary."""
        self.finished = True
        self.get_logger().info(f'run finished after {self.session.step} steps, '
                               f'tr(W P W) = {self.session.estimator.weighted_trace():.6g} m^2')

    def close(self) -> None:
        """Write the summary (also on SIGINT/SIGTERM)."""
        write_summary(self.params['summary_path'], self.summary())


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros estimator_planner)."""
    sys.exit(node_main(EstimatorPlannerNode, 'estimator_planner', SUMMARY, PARAMS, args))


if __name__ == '__main__':
    main()


__all__ = ['EstimatorPlannerNode', 'PARAMS', 'ParameterError', 'main']
