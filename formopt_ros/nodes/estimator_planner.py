"""estimator_planner: the follower's EKF and motion strategy; publishes estimate and waypoint."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
from formopt_interfaces.msg import Measurement, PlannerStatus, Waypoint
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node

from formopt_ros import conversions
from formopt_ros.core.model import normalized_estimation_error
from formopt_ros.core.simulation import SUBSTEPS, EstimatorPlanner, PlanResult, trial_streams
from formopt_ros.core.solver import METHODS
from formopt_ros.nodes.common import (
    FOLLOWER_ID, LEADER_ID, MODE, PUBLISHED, RELIABLE, SCENARIO_PARAMS, SEED, TOPICS, TRIAL, Param,
    Throttle, declare, run, scenario_from)

PARAMS = [FOLLOWER_ID, LEADER_ID, MODE, SEED, TRIAL] + SCENARIO_PARAMS + [
    Param('strategy', 'ram', 'motion strategy', choices=METHODS),
    Param('gbs_cell', 0.005, 'GBS grid spacing as a fraction of r', 1e-4, 1.0),
    Param('steps', 0, 'measurement steps to run, then exit 0 (0: run until stopped)', 0,
          10**9),
    Param('peers', 2, 'waypoint subscribers (leader_sim, follower_sim, a recorder) to wait '
          'for before the first waypoint', 0, 100),
    Param('resend_timeout', 1.0, 'lockstep: resend the last waypoint after this long without '
          'progress (a peer restarted), s', 0.01, 3600.0),
    Param('summary_path', '', 'write a JSON summary here when the run ends (empty: none)'),
]


class EstimatorPlannerNode(Node):
    """Wraps :class:`EstimatorPlanner`: odometry -> propagate, measurement -> update, plan.

    lockstep: step k is processed once its measurement and the leader's and follower's odometry
    of its sub-steps (matched by simulated-time stamps) are all in; then the waypoint of step
    k + 1 is published. The arithmetic equals :func:`run_trial` with the same seed.
    realtime: each measurement is processed on arrival with the follower odometry received
    since the last one, each paired with the latest leader odometry.
    Bad inputs (non-finite values, bad variances, stamps out of order, another follower's
    messages) are rejected with a throttled warning and counted in the status.
    """

    def __init__(self) -> None:
        super().__init__('estimator_planner')
        self.params = declare(self, PARAMS)
        p = self.params
        self.scenario = scenario_from(p)
        _, planner_rng = trial_streams(p['seed'], p['trial'])
        options = {'cell': p['gbs_cell']} if p['strategy'] == 'gbs' else {}
        self.core = EstimatorPlanner(self.scenario, p['strategy'], planner_rng, options)
        self.lockstep = p['mode'] == 'lockstep'
        self.step = 0                      # last processed measurement step
        self.plan: PlanResult | None = None
        self.last_waypoint: Waypoint | None = None
        self.follower_odom: dict[float, tuple[float, float]] = {}
        self.leader_odom: dict[float, tuple[float, float]] = {}
        self.latest_leader = (self.scenario.v_leader, self.scenario.omega_leader)
        self.measurements: dict[int, tuple[float, float, float]] = {}
        self.truth: dict[float, np.ndarray] = {}     # by stamp, s (= its measurement's)
        self.step_stamp: float | None = None          # stamp of the last processed step, s
        self.last_stamp: dict[str, float] = {}
        self.counters = {'rejected_measurements': 0, 'rejected_odometry': 0,
                         'accepted_measurements': 0}
        self.received = {name: 0 for name in ('leader_odom', 'follower_odom', 'measurement',
                                              'truth')}
        self.published = {name: 0 for name in ('estimate', 'waypoint', 'status')}
        self.nees: list[float] = []
        self.finished = False
        self.last_progress = time.monotonic()
        self.throttle = Throttle(self)
        self.estimate_pub = self.create_publisher(PoseWithCovarianceStamped,
                                                  TOPICS['estimate'], PUBLISHED)
        self.waypoint_pub = self.create_publisher(Waypoint, TOPICS['waypoint'], PUBLISHED)
        self.status_pub = self.create_publisher(PlannerStatus, TOPICS['status'], PUBLISHED)
        self.create_subscription(Odometry, TOPICS['follower_odom'], self.on_follower_odom,
                                 RELIABLE)
        self.create_subscription(Odometry, TOPICS['leader_odom'], self.on_leader_odom, RELIABLE)
        # truth before measurement: when both are ready, the executor serves the truth first
        self.create_subscription(PoseStamped, TOPICS['truth'], self.on_truth, RELIABLE)
        self.create_subscription(Measurement, TOPICS['measurement'], self.on_measurement,
                                 RELIABLE)
        self.create_timer(0.05, self.on_timer)
        self.get_logger().info(f"estimator_planner ready ({p['mode']}, {p['measurement']}, "
                               f"strategy {p['strategy']})")

    # --- inputs ----------------------------------------------------------------------------
    def _in_order(self, topic: str, stamp: float) -> bool:
        """Stamps must increase per topic (lockstep duplicates count as out of order)."""
        last = self.last_stamp.get(topic, -np.inf)
        if stamp <= last if self.lockstep else stamp < last:
            self.throttle.warn(topic, f'rejected {topic}: stamp {stamp:.9f} s not after '
                                      f'{last:.9f} s')
            return False
        self.last_stamp[topic] = stamp
        return True

    def _odometry(self, msg: Odometry, topic: str, child: str) -> tuple[float, float] | None:
        self.received[topic] += 1
        problem = conversions.odometry_problem(msg, child)
        stamp = conversions.seconds(msg.header.stamp)
        if problem is not None:
            self.throttle.warn(topic, f'rejected {topic}: {problem}')
        if problem is not None or not self._in_order(topic, stamp):
            self.counters['rejected_odometry'] += 1
            return None
        v, omega, _, _ = conversions.odometry_velocities(msg)
        return stamp, (v, omega)

    def on_follower_odom(self, msg: Odometry) -> None:
        item = self._odometry(msg, 'follower_odom', self.params['follower_id'])
        if item is not None:
            self.follower_odom[item[0]] = item[1]
            self._advance()

    def on_leader_odom(self, msg: Odometry) -> None:
        item = self._odometry(msg, 'leader_odom', self.params['leader_id'])
        if item is not None:
            self.leader_odom[item[0]] = item[1]
            self._advance()

    def on_measurement(self, msg: Measurement) -> None:
        self.received['measurement'] += 1
        problem = conversions.measurement_problem(msg, self.params['follower_id'],
                                                  self.scenario.measurement)
        stamp = conversions.seconds(msg.header.stamp)
        if problem is None and msg.step <= self.step:
            problem = f'step {msg.step} already processed'
        if problem is not None:
            self.throttle.warn('measurement', f'rejected measurement: {problem}')
        if problem is not None or not self._in_order('measurement', stamp):
            self.counters['rejected_measurements'] += 1
            return
        self.counters['accepted_measurements'] += 1
        self.measurements[msg.step] = (stamp, msg.value, msg.variance)
        self._advance()

    def on_truth(self, msg: PoseStamped) -> None:
        """Ground truth, used for evaluation only (NEES, summary).

        Matched to its measurement by the stamp (the follower stamps both alike), which works
        with simulated (lockstep) and node-clock (realtime) stamps.
        """
        self.received['truth'] += 1
        self.truth[conversions.seconds(msg.header.stamp)] = conversions.pose_of(msg.pose)

    # --- processing ------------------------------------------------------------------------
    def _advance(self) -> None:
        while not self.finished and self._process_next():
            pass

    def _process_next(self) -> bool:
        k = self.step + 1
        if k not in self.measurements:
            return False
        stamp, z, variance = self.measurements[k]
        dt = self.scenario.dt
        if self.lockstep:
            keys = [(SUBSTEPS * (k - 1) + j + 1) * dt for j in range(SUBSTEPS)]
            follower = [self._find(self.follower_odom, key) for key in keys]
            leader = [self._find(self.leader_odom, key) for key in keys]
            if any(key is None for key in follower + leader):
                return False
            pairs = [(self.follower_odom.pop(f), self.leader_odom.pop(g))
                     for f, g in zip(follower, leader)]
        else:
            earlier = sorted(t for t in self.follower_odom if t <= stamp + 1e-9)
            pairs = [(self.follower_odom.pop(t), self._leader_before(t)) for t in earlier]
        for (v, omega), (v_l, omega_l) in pairs:
            self.core.propagate(v, omega, v_l, omega_l)
            self.latest_leader = (v_l, omega_l)
        self.core.update(z, variance)
        del self.measurements[k]
        self.step = k
        self.last_progress = time.monotonic()
        self._publish_step(stamp)
        return True

    @staticmethod
    def _find(table: dict[float, tuple[float, float]], key: float) -> float | None:
        """The stamp in table within 1 us of key (lockstep stamps are exact to 1 ns)."""
        for stamp in table:
            if abs(stamp - key) < 1e-6:
                return stamp
        return None

    def _leader_before(self, stamp: float) -> tuple[float, float]:
        earlier = [t for t in self.leader_odom if t <= stamp + 1e-9]
        if earlier:
            self.latest_leader = self.leader_odom[max(earlier)]
            for t in earlier:
                del self.leader_odom[t]
        return self.latest_leader

    def _publish_step(self, stamp_s: float) -> None:
        p = self.params
        stamp = conversions.stamp(stamp_s) if self.lockstep else self.get_clock().now().to_msg()
        self.estimate_pub.publish(conversions.estimate(stamp, p['leader_id'], self.core.x,
                                                       self.core.P))
        self.published['estimate'] += 1
        self.step_stamp = stamp_s
        for old in [t for t in self.truth if t < stamp_s]:
            del self.truth[old]
        truth = self.truth.get(stamp_s)
        if truth is not None:
            self.nees.append(normalized_estimation_error(truth, self.core.x, self.core.P))
        done = p['steps'] and self.step >= p['steps']
        self.plan = None if done else self._plan_and_send(self.step + 1)
        self.status_pub.publish(conversions.status(
            stamp, p['follower_id'], self.step, p['strategy'], self.scenario.measurement,
            self.core.weighted_trace(), self.plan, self.counters))
        self.published['status'] += 1
        if done:
            self.finish()

    def _plan_and_send(self, step: int) -> PlanResult:
        plan = self.core.plan(step, [self.latest_leader] * SUBSTEPS,
                              self.latest_leader[1] == 0.0)
        dt = self.scenario.dt
        stamp = (conversions.stamp(SUBSTEPS * (step - 1) * dt) if self.lockstep
                 else self.get_clock().now().to_msg())
        self.last_waypoint = conversions.waypoint(stamp, self.params['follower_id'], step, plan,
                                                  self.scenario.slot, self.scenario.r, dt)
        self.waypoint_pub.publish(self.last_waypoint)
        self.published['waypoint'] += 1
        return plan

    def on_timer(self) -> None:
        """Start the run once the peers listen; resend a waypoint that got no answer."""
        if self.finished:
            return
        if self.plan is None and self.step == 0:
            if self.waypoint_pub.get_subscription_count() >= self.params['peers']:
                self.plan = self._plan_and_send(1)
                self.last_progress = time.monotonic()
            return
        if self.lockstep and self.last_waypoint is not None and \
                time.monotonic() - self.last_progress > self.params['resend_timeout']:
            self.throttle.warn('resend', f'no progress on step {self.step + 1}: resending '
                                         'its waypoint')
            self.waypoint_pub.publish(self.last_waypoint)
            self.last_progress = time.monotonic()

    # --- end of run --------------------------------------------------------------------------
    def summary(self) -> dict:
        """Final state, evaluation and message counts of the run."""
        truth = self.truth.get(self.step_stamp)
        return {
            'steps': self.step,
            'strategy': self.params['strategy'],
            'measurement': self.scenario.measurement,
            'mode': self.params['mode'],
            'seed': self.params['seed'],
            'final_estimate': self.core.x.tolist(),
            'final_covariance': self.core.P.tolist(),
            'final_truth': None if truth is None else truth.tolist(),
            'final_weighted_trace': self.core.weighted_trace(),
            'mean_nees': float(np.mean(self.nees)) if self.nees else None,
            'counters': dict(self.counters),
            'message_counts': {'received': dict(self.received),
                               'published': dict(self.published)},
        }

    def finish(self) -> None:
        """End the run: write the summary and let the spin loop return."""
        self.finished = True
        self.get_logger().info(f'run finished after {self.step} steps, '
                               f'tr(W P W) = {self.core.weighted_trace():.6g} m^2')

    def close(self) -> None:
        """Write the summary (also on SIGINT/SIGTERM)."""
        path = self.params['summary_path']
        if path:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            Path(path).write_text(json.dumps(self.summary(), indent=2) + '\n')


def main(args: list[str] | None = None) -> None:
    """Console entry point (ros2 run formopt_ros estimator_planner)."""
    sys.exit(run(EstimatorPlannerNode, args))


if __name__ == '__main__':
    main()
