"""estimator_planner: one follower's EKF and motion strategy; publishes estimate and waypoint."""
from __future__ import annotations

import sys
import time
from typing import Any

from formopt_interfaces.msg import Measurement, PlannerStatus, RunDescription, Waypoint
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from formopt_ros.core.estimator import EstimatorSession, StepOutcome, StepPlan
from formopt_ros.core.protocol import Timebase
from formopt_ros.core.simulation import trial_streams
from formopt_ros.core.strategies import make_strategy
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.naming import peer_topic, robot_id
from formopt_ros.ros.params import (
    FOLLOWER_ID, LEADER_ID, MODE, SCENARIO_PARAMS, SEED, SUMMARY_PATH, TRIAL, Param,
    ParameterError, check_strategy, declare, scenario_from, strategy_options, strategy_params)
from formopt_ros.ros.runtime import Throttle, node_main, write_summary
from formopt_ros.wire import inputs
from formopt_ros.wire.description import RunDescription as Description
from formopt_ros.wire.topics import DEFAULT_FOLLOWER, BY_KEY

PARAMS = [FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS + strategy_params() + [
    Param('steps', 0, 'measurement steps to run, then exit 0 (0: run until stopped)', 0,
          10**9),
    Param('peers', 2, 'waypoint subscribers (leader_sim, follower_sim, a recorder) to wait '
          'for before the first waypoint', 0, 100),
    Param('resend_timeout', 1.0, 'lockstep: resend the last waypoint after this long without '
          'progress (a peer restarted), s', 0.01, 3600.0),
    SUMMARY_PATH,
    Param('run_id', '', 'identity of the run, published in the run description'),
]
SUMMARY = ("The follower's EKF and motion strategy: odometry and measurements in, estimate, "
           'waypoint, status and the run description out.')


class EstimatorPlannerNode(Node):
    """Feeds its inputs to an :class:`~formopt_ros.core.estimator.EstimatorSession` and
    publishes what each processed step produced.

    lockstep: step k is processed once its measurement and the leader's and follower's odometry
    of its sub-steps (matched by their integer-ns simulated-time stamps) are all in; then the
    waypoint of step k + 1 is published. The arithmetic equals :func:`run_trial`.
    realtime: each measurement is processed on arrival with the follower odometry received
    since the last one, each paired with the latest leader odometry.
    Bad inputs are refused with a throttled warning and counted in the status.
    """

    def __init__(self) -> None:
        super().__init__('estimator_planner', namespace=DEFAULT_FOLLOWER)
        self.params = p = declare(self, PARAMS)
        self.follower_id = p['follower_id'] or robot_id(self, DEFAULT_FOLLOWER)
        self.leader_id = p['leader_id']
        self.scenario = scenario_from(p)
        check_strategy(p['strategy'], p)
        options = strategy_options(p['strategy'], p)
        strategy = make_strategy(p['strategy'], **options)
        _, planner_rng = trial_streams(p['seed'], p['trial'])
        self.lockstep = p['mode'] == 'lockstep'
        self.timebase = Timebase.from_dt(self.scenario.dt)
        self.session = EstimatorSession.create(self.scenario, strategy, planner_rng,
                                               self.lockstep, p['steps'])
        self.description = Description(self.follower_id, self.scenario, p['strategy'],
                                       dict(strategy.settings), p['seed'], p['trial'],
                                       p['mode'], p['steps'], p['run_id'], self.leader_id)
        self.started = False
        self.finished = False
        self.last_plan: StepPlan | None = None
        self.last_waypoint: Waypoint | None = None
        self.last_progress = time.monotonic()
        self.received = {key: 0 for key in ('leader_odom', 'follower_odom', 'measurement',
                                            'truth')}
        self.published = {key: 0 for key in ('estimate', 'waypoint', 'status')}
        self.throttle = Throttle(self)
        self.estimate_pub = self.create_publisher(PoseWithCovarianceStamped,
                                                  BY_KEY['estimate'].name, qos.STREAM)
        self.waypoint_pub = self.create_publisher(Waypoint, BY_KEY['waypoint'].name, qos.STREAM)
        self.status_pub = self.create_publisher(PlannerStatus, BY_KEY['status'].name,
                                                qos.STREAM)
        self.description_pub = self.create_publisher(RunDescription,
                                                     BY_KEY['description'].name, qos.LATCHED)
        self.description_message = conversions.description(
            self.get_clock().now().to_msg(), p['run_id'], self.get_fully_qualified_name(),
            self.description.to_json())
        self.description_pub.publish(self.description_message)
        self.create_subscription(Odometry, BY_KEY['follower_odom'].name, self.on_follower_odom,
                                 qos.SUBSCRIBED)
        self.create_subscription(Odometry, peer_topic(self, self.leader_id, 'leader_odom'),
                                 self.on_leader_odom, qos.SUBSCRIBED)
        # truth before measurement: when both are ready, the executor serves the truth first
        self.create_subscription(PoseStamped, BY_KEY['truth'].name, self.on_truth,
                                 qos.SUBSCRIBED)
        self.create_subscription(Measurement, BY_KEY['measurement'].name, self.on_measurement,
                                 qos.SUBSCRIBED)
        self.create_timer(0.05, self.on_timer)
        self.get_logger().info(f"estimator_planner ready ({p['mode']}, {p['measurement']}, "
                               f"strategy {p['strategy']}, follower {self.follower_id})")

    # --- inputs ----------------------------------------------------------------------------
    def _now_ns(self) -> int | None:
        return None if self.lockstep else self.get_clock().now().nanoseconds

    def _refused(self, key: str, reason: str | None) -> None:
        if reason is not None:
            self.throttle.warn(key, f'rejected {key}: {reason}')
        else:
            self._advance()

    def on_follower_odom(self, msg: Odometry) -> None:
        """One sub-step of the follower's odometry."""
        self.received['follower_odom'] += 1
        self._refused('follower_odom', inputs.feed_odometry(
            self.session, 'follower', msg, self.follower_id, self._now_ns()))

    def on_leader_odom(self, msg: Odometry) -> None:
        """One sub-step of the leader's odometry."""
        self.received['leader_odom'] += 1
        self._refused('leader_odom', inputs.feed_odometry(
            self.session, 'leader', msg, self.leader_id, self._now_ns()))

    def on_measurement(self, msg: Measurement) -> None:
        """One range or bearing measurement."""
        self.received['measurement'] += 1
        self._refused('measurement', inputs.feed_measurement(
            self.session, msg, self.follower_id, self._now_ns()))

    def on_truth(self, msg: PoseStamped) -> None:
        """Ground truth, for evaluation only (NEES, summary), matched to a step by its stamp."""
        self.received['truth'] += 1
        inputs.feed_truth(self.session, msg)

    # --- processing ------------------------------------------------------------------------
    def _advance(self) -> None:
        for outcome in self.session.advance():
            self._publish(outcome)
        if self.session.finished and not self.finished:
            self.finish()

    def _stamp(self, nanoseconds: int) -> Any:
        return conversions.stamp(nanoseconds) if self.lockstep else \
            self.get_clock().now().to_msg()

    def _publish(self, outcome: StepOutcome) -> None:
        stamp = self._stamp(outcome.stamp_ns)
        self.estimate_pub.publish(conversions.estimate(stamp, self.leader_id, outcome.x,
                                                       outcome.P))
        self.published['estimate'] += 1
        self.last_progress = time.monotonic()
        self.last_plan = outcome.plan
        if outcome.plan is not None:
            self._send(outcome.plan)
        self.status_pub.publish(conversions.status(
            stamp, '', self.follower_id, outcome.step, self.description.strategy,
            self.scenario.measurement, outcome.weighted_trace, outcome.plan,
            self.session.counters.as_dict()))
        self.published['status'] += 1

    def _send(self, plan: StepPlan) -> None:
        self.last_waypoint = conversions.waypoint(
            self._stamp(self.timebase.waypoint_stamp(plan.step)), self.leader_id,
            self.follower_id, plan, self.scenario.slot, self.scenario.r, self.scenario.dt)
        self.waypoint_pub.publish(self.last_waypoint)
        self.published['waypoint'] += 1

    def on_timer(self) -> None:
        """Start the run once the peers listen; resend a waypoint that got no answer."""
        if self.finished:
            return
        if not self.started:
            if self.waypoint_pub.get_subscription_count() >= self.params['peers']:
                self.started = True
                self.last_plan = self.session.plan_next()
                self._send(self.last_plan)
                self.last_progress = time.monotonic()
            return
        if self.lockstep and self.last_waypoint is not None and \
                time.monotonic() - self.last_progress > self.params['resend_timeout']:
            self.throttle.warn('resend', f'no progress on step {self.session.step + 1}: '
                                         'resending its waypoint')
            self.waypoint_pub.publish(self.last_waypoint)
            self.last_progress = time.monotonic()

    # --- end of run --------------------------------------------------------------------------
    def summary(self) -> dict[str, Any]:
        """Final state, evaluation and message counts of the run."""
        estimator = self.session.estimator
        truth = self.session.final_truth
        return {
            'steps': self.session.step,
            'follower_id': self.follower_id,
            'strategy': self.description.strategy,
            'measurement': self.scenario.measurement,
            'mode': self.params['mode'],
            'seed': self.params['seed'],
            'final_estimate': estimator.x.tolist(),
            'final_covariance': estimator.P.tolist(),
            'final_truth': None if truth is None else truth.tolist(),
            'final_weighted_trace': estimator.weighted_trace(),
            'mean_nees': self.session.mean_nees(),
            'counters': self.session.counters.as_dict(),
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
