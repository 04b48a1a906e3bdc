"""replay: republishes a recorded bag, or re-runs the estimator offline over its inputs."""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from rclpy.duration import Duration
from rclpy.node import Node
from rclpy.qos import QoSProfile

from formopt_ros import bag as bags
from formopt_ros import conversions
from formopt_ros.core.model import MEASUREMENT_KINDS, wrap_angle
from formopt_ros.core.simulation import SUBSTEPS, EstimatorPlanner, Scenario, trial_streams
from formopt_ros.core.solver import METHODS
from formopt_ros.nodes.common import Param, ParameterError, declare, qos_for, run

PARAMS = [
    Param('bag_path', '', 'the .mcap file to replay (required)'),
    Param('rate', 1.0, 'playback speed: factor on the recorded log-time deltas', 1e-3, 1e6),
    Param('fast', False, 'ignore the recorded timing: publish burst messages per executor '
          'round (in log-time order)'),
    Param('burst', 1, 'fast mode: messages per executor round', 1, 100000),
    Param('topics', ['*'], "topics to replay, as recorded ('/leader/odom') or by suffix "
          "('leader/odom'); ['*']: all"),
    Param('wait_subscribers', 0, 'before starting, wait until every publisher has this many '
          'subscribers', 0, 1000),
    Param('wait_timeout', 10.0, 'longest wait for subscribers before starting anyway, and for '
          'the last messages to be acknowledged, s', 0.0, 3600.0),
]


def select_topics(bag: bags.Bag, names: list[str]) -> list[str]:
    """The recorded topics named by ``names`` (['*']: all); BagError when one is missing."""
    if not names or list(names) == ['*']:
        topics = sorted(bag.channels)
    else:
        topics = [bag.find(name) for name in names]
    if not topics:
        raise bags.BagError(f'{bag.path}: the bag has no topics to replay')
    for topic in topics:
        bags.message_class(bag.channels[topic].type, topic)
    return list(dict.fromkeys(topics))


def replay_qos(channel: bags.ChannelInfo) -> QoSProfile:
    """QoS offered on replay: reliable/latched when every recorded publisher was."""
    offers = channel.qos
    reliable = all(q.reliability != 'best_effort' for q in offers)
    latched = bool(offers) and all(q.durability == 'transient_local' for q in offers)
    return qos_for(reliable, latched)


class Replay(Node):
    """Publishes the raw CDR bytes of a bag's topics with the recorded timing.

    Message i goes out at start + (log_time_i - log_time_0) / rate (or as fast as the executor
    turns, ``burst`` per round, with ``fast``). Publishers take the recorded type and offered
    QoS. When all are sent and acknowledged (or ``wait_timeout`` passed) the node finishes.
    """

    def __init__(self, preloaded: bags.Bag | None = None) -> None:
        super().__init__('replay')
        self.params = declare(self, PARAMS)
        p = self.params
        if not p['bag_path']:
            raise ParameterError("parameter 'bag_path' is required (the .mcap file to replay)")
        try:
            self.bag = preloaded if preloaded is not None and \
                Path(preloaded.path) == Path(p['bag_path']) else bags.read_bag(p['bag_path'])
            topics = select_topics(self.bag, p['topics'])
        except bags.BagError as error:
            raise ParameterError(f"parameter 'bag_path' or 'topics': {error}") from None
        self.publishers_ = {
            topic: self.create_publisher(
                bags.message_class(self.bag.channels[topic].type, topic), topic,
                replay_qos(self.bag.channels[topic]))
            for topic in topics}
        self.queue = [r for r in self.bag.messages if r.topic in self.publishers_]
        self.sent = 0
        self.counts = {topic: 0 for topic in topics}
        self.finished = False
        self.created = time.monotonic()
        self.start: float | None = None
        self.timer = self.create_timer(0.0 if p['fast'] else 0.001, self.on_timer)
        self.get_logger().info(
            f"replaying {len(self.queue)} messages on {len(topics)} topics from "
            f"{p['bag_path']} ({'fast' if p['fast'] else 'rate %g' % p['rate']})")

    def _ready(self) -> bool:
        want = self.params['wait_subscribers']
        if want == 0 or all(pub.get_subscription_count() >= want
                            for pub in self.publishers_.values()):
            return True
        return time.monotonic() - self.created > self.params['wait_timeout']

    def on_timer(self) -> None:
        """Publish what is due; finish once everything went out."""
        if self.finished:
            return
        if self.start is None:
            if not self._ready():
                return
            self.start = time.monotonic()
        p = self.params
        if p['fast']:
            end = min(len(self.queue), self.sent + p['burst'])
        else:
            due = self.queue[0].log_time + (time.monotonic() - self.start) * p['rate'] * 1e9 \
                if self.queue else 0
            end = self.sent
            while end < len(self.queue) and self.queue[end].log_time <= due:
                end += 1
        for record in self.queue[self.sent:end]:
            self.publishers_[record.topic].publish(record.data)
            self.counts[record.topic] += 1
        self.sent = end
        if self.sent >= len(self.queue):
            self._finish()

    def _finish(self) -> None:
        timeout = Duration(seconds=self.params['wait_timeout'])
        acked = all(pub.wait_for_all_acked(timeout) for pub in self.publishers_.values())
        elapsed = time.monotonic() - (self.start or self.created)
        self.get_logger().info(f'replayed {self.sent} messages in {elapsed:.3f} s'
                               + ('' if acked else ' (not all acknowledged)'))
        self.finished = True
        self.timer.cancel()

    def close(self) -> None:
        """Log what was sent."""
        self.get_logger().info('replay counts: ' + ', '.join(
            f'{t} {n}' for t, n in self.counts.items()))


# --- offline re-run ----------------------------------------------------------------------
@dataclass
class OfflineResult:
    """Offline estimator run over a bag's inputs versus its recorded estimates."""

    steps: int
    recorded_steps: int
    strategy: str
    measurement: str
    mode: str
    max_state_diff: float
    max_covariance_diff: float
    max_waypoint_diff: float | None
    max_stamp_diff_ns: int
    estimates: list[np.ndarray] = field(default_factory=list, repr=False)
    covariances: list[np.ndarray] = field(default_factory=list, repr=False)

    @property
    def max_diff(self) -> float:
        """Largest difference over states and covariances (inf when step counts differ)."""
        if self.steps != self.recorded_steps:
            return math.inf
        return max(self.max_state_diff, self.max_covariance_diff)


def _first_ok(items, problem) -> list:
    """Messages that pass ``problem`` and whose stamps increase (the node's _in_order)."""
    out, last = [], -math.inf
    for record, msg in items:
        stamp = conversions.seconds(msg.header.stamp)
        if problem(msg) is None and stamp > last:
            out.append((stamp, msg))
            last = stamp
    return out


def scenario_of(data: dict, measurement: str | None = None, dt: float | None = None
                ) -> Scenario:
    """The run's Scenario from its recorded messages (flags override measurement and dt)."""
    status = [m for _, m in data['follower/status']]
    waypoints = [m for _, m in data['follower/waypoint']]
    meas = [m for _, m in data['follower/measurement']]
    follower = [m for _, m in data['follower/odom']]
    leader = [m for _, m in data['leader/odom']]
    kind = measurement or (status[-1].measurement_kind if status else
                           conversions.KIND_NAMES.get(meas[0].kind) if meas else None)
    if kind not in MEASUREMENT_KINDS:
        raise bags.BagError(f'cannot tell the measurement kind (got {kind!r}); pass '
                            '--measurement range|bearing')
    base = Scenario.paper(kind)
    if dt is None:
        dt = waypoints[0].substep_duration if waypoints else (
            conversions.seconds(follower[0].header.stamp) if follower else base.dt)
    p_o = ((waypoints[0].formation_slot.x, waypoints[0].formation_slot.y) if waypoints
           else base.p_o)
    r = waypoints[0].radius if waypoints else 0.1 * math.hypot(*p_o)
    sigma = math.sqrt(meas[0].variance) if meas and meas[0].variance > 0 else base.sigma
    sigma_v = math.sqrt(follower[0].twist.covariance[0]) if follower else base.sigma_v
    sigma_omega = math.sqrt(follower[0].twist.covariance[35]) if follower else base.sigma_omega
    v_l, omega_l = ((leader[0].twist.twist.linear.x, leader[0].twist.twist.angular.z)
                    if leader else (base.v_leader, base.omega_leader))
    return Scenario.paper(kind, p_o=p_o, r=r, sigma=sigma, v_leader=v_l, omega_leader=omega_l,
                          dt=dt, sigma_v=sigma_v, sigma_omega=sigma_omega)


def offline(bag: bags.Bag, strategy: str | None = None, measurement: str | None = None,
            seed: int = 0, trial: int = 0, gbs_cell: float = 0.005,
            dt: float | None = None) -> OfflineResult:
    """Re-run :class:`EstimatorPlanner` over the bag's odometry and measurements.

    Lockstep bags (stamps on the simulated-time grid) are processed exactly as the node does,
    step by step with the odometry of the step's sub-steps; realtime bags in the recorder's
    arrival order (best effort: the estimator may have seen another order). Inputs the node
    would reject are rejected alike (conversions.*_problem, non-increasing stamps).
    """
    data = bag.formation(['leader/odom', 'follower/odom', 'follower/measurement',
                          'follower/estimate'],
                         ['follower/status', 'follower/waypoint', 'follower/truth'],
                         'for the offline replay')
    scenario = scenario_of(data, measurement, dt)
    status = [m for _, m in data['follower/status']]
    waypoints = [m for _, m in data['follower/waypoint']]
    strategy = strategy or (status[-1].strategy if status else
                            waypoints[0].strategy if waypoints else None)
    if strategy not in METHODS:
        raise bags.BagError(f'cannot tell the strategy (got {strategy!r}); pass --strategy')
    follower_id = data['follower/measurement'][0][1].follower_id if \
        data['follower/measurement'] else 'follower'
    leader_id = data['leader/odom'][0][1].child_frame_id if data['leader/odom'] else 'leader'
    kind = scenario.measurement
    follower = _first_ok(data['follower/odom'],
                         lambda m: conversions.odometry_problem(m, follower_id))
    leader = _first_ok(data['leader/odom'], lambda m: conversions.odometry_problem(m, leader_id))
    meas = _first_ok(data['follower/measurement'],
                     lambda m: conversions.measurement_problem(m, follower_id, kind))
    dt = scenario.dt
    lockstep = all(abs(conversions.seconds(m.header.stamp) - SUBSTEPS * m.step * dt) < 1e-6
                   for _, m in meas)
    _, planner_rng = trial_streams(seed, trial)
    options = {'cell': gbs_cell} if strategy == 'gbs' else {}
    core = EstimatorPlanner(scenario, strategy, planner_rng, options)
    estimates, covariances, stamps, plans = [], [], [], {}
    latest_leader = (scenario.v_leader, scenario.omega_leader)
    last_plan = max((w.step for w in waypoints), default=math.inf)

    def plan(step: int) -> None:
        # as the node: plan every next step (the planner stream advances), none past the end
        if step <= last_plan:
            plans[step] = core.plan(step, [latest_leader] * SUBSTEPS,
                                    latest_leader[1] == 0.0).solution.p

    def find(table: dict[float, tuple], key: float) -> float | None:
        return next((t for t in table if abs(t - key) < 1e-6), None)

    def velocities(msg) -> tuple[float, float]:
        return msg.twist.twist.linear.x, msg.twist.twist.angular.z

    plan(1)
    step = 0
    if lockstep:
        f_table = {t: velocities(m) for t, m in follower}
        l_table = {t: velocities(m) for t, m in leader}
        by_step = {m.step: (t, m) for t, m in meas}
        while step + 1 in by_step:
            k = step + 1
            keys = [(SUBSTEPS * (k - 1) + j + 1) * dt for j in range(SUBSTEPS)]
            f_keys = [find(f_table, key) for key in keys]
            l_keys = [find(l_table, key) for key in keys]
            if any(key is None for key in f_keys + l_keys):
                break
            for fk, lk in zip(f_keys, l_keys):
                v_l, omega_l = l_table.pop(lk)
                core.propagate(*f_table.pop(fk), v_l, omega_l)
                latest_leader = (v_l, omega_l)
            msg = by_step[k][1]
            core.update(msg.value, msg.variance)
            step = k
            estimates.append(core.x.copy())
            covariances.append(core.P.copy())
            stamps.append(conversions.nanoseconds(msg.header.stamp))
            plan(k + 1)
    else:
        events = sorted([(r.log_time, 0, i) for i, (r, _) in enumerate(data['follower/odom'])]
                        + [(r.log_time, 1, i) for i, (r, _) in enumerate(data['leader/odom'])]
                        + [(r.log_time, 2, i) for i, (r, _) in
                           enumerate(data['follower/measurement'])])
        valid = {0: {id(m) for _, m in follower}, 1: {id(m) for _, m in leader},
                 2: {id(m) for _, m in meas}}
        topics = {0: 'follower/odom', 1: 'leader/odom', 2: 'follower/measurement'}
        f_table, l_table = {}, {}
        for _, kind_index, i in events:
            msg = data[topics[kind_index]][i][1]
            if id(msg) not in valid[kind_index]:
                continue
            stamp = conversions.seconds(msg.header.stamp)
            if kind_index == 0:
                f_table[stamp] = velocities(msg)
            elif kind_index == 1:
                l_table[stamp] = velocities(msg)
            elif msg.step == step + 1:
                for t in sorted(t for t in f_table if t <= stamp + 1e-9):
                    earlier = [u for u in l_table if u <= t + 1e-9]
                    if earlier:
                        latest_leader = l_table[max(earlier)]
                        for u in earlier:
                            del l_table[u]
                    core.propagate(*f_table.pop(t), *latest_leader)
                core.update(msg.value, msg.variance)
                step = msg.step
                estimates.append(core.x.copy())
                covariances.append(core.P.copy())
                stamps.append(None)
                plan(step + 1)
    recorded = [conversions.estimate_values(m) for _, m in data['follower/estimate']]
    recorded_stamps = [conversions.nanoseconds(m.header.stamp)
                       for _, m in data['follower/estimate']]
    n = min(len(recorded), len(estimates))
    state = max((float(np.max(np.abs(np.append(
        (estimates[i] - recorded[i][0])[:2], wrap_angle(estimates[i][2] - recorded[i][0][2])))))
        for i in range(n)), default=0.0)
    cov = max((float(np.max(np.abs(covariances[i] - recorded[i][1]))) for i in range(n)),
              default=0.0)
    stamp_diff = max((abs(stamps[i] - recorded_stamps[i]) for i in range(n)
                      if stamps[i] is not None), default=0)
    chosen = {w.step: np.array([w.position.x, w.position.y]) for w in waypoints}
    common = [s for s in plans if s in chosen]
    way = max((float(np.max(np.abs(plans[s] - chosen[s]))) for s in common), default=None)
    return OfflineResult(len(estimates), len(recorded), strategy, kind,
                         'lockstep' if lockstep else 'realtime', state, cov, way, stamp_diff,
                         estimates, covariances)


def offline_main(args: argparse.Namespace) -> int:
    """The ``replay BAG --offline`` command: print the differences, exit 1 above tolerance."""
    try:
        bag = bags.read_bag(args.bag)
        result = offline(bag, args.strategy, args.measurement, args.seed, args.trial,
                         args.gbs_cell, args.dt)
    except bags.BagError as error:
        print(f'error: {error}', file=sys.stderr)
        return 2
    ok = result.max_diff <= args.tolerance
    way = 'n/a' if result.max_waypoint_diff is None else f'{result.max_waypoint_diff:.3e}'
    print(f'offline replay of {args.bag}: {result.steps} steps re-estimated '
          f'({result.recorded_steps} recorded; strategy {result.strategy}, '
          f'{result.measurement}, {result.mode})')
    print(f'max |estimate - recorded|: state {result.max_state_diff:.3e}, covariance '
          f'{result.max_covariance_diff:.3e}; waypoints {way} m; stamps '
          f'{result.max_stamp_diff_ns} ns')
    print(f"max difference {result.max_diff:.3e} {'<=' if ok else '>'} tolerance "
          f"{args.tolerance:.1e}: {'OK' if ok else 'FAILED'}")
    if args.json:
        Path(args.json).write_text(json.dumps({
            'bag': str(args.bag), 'steps': result.steps, 'recorded_steps': result.recorded_steps,
            'strategy': result.strategy, 'measurement': result.measurement,
            'mode': result.mode, 'max_state_diff': result.max_state_diff,
            'max_covariance_diff': result.max_covariance_diff,
            'max_waypoint_diff': result.max_waypoint_diff, 'max_diff': result.max_diff,
            'tolerance': args.tolerance, 'ok': ok}, indent=2) + '\n')
    return 0 if ok else 1


def parser() -> argparse.ArgumentParser:
    """Command-line flags of ``replay`` (ROS arguments after --ros-args are passed through)."""
    out = argparse.ArgumentParser(
        prog='replay', description='Republish a formation bag with its recorded timing, or '
        're-run the estimator offline over its inputs (--offline).')
    out.add_argument('bag', type=Path, nargs='?', help='the .mcap file (or -p bag_path:=...)')
    speed = out.add_mutually_exclusive_group()
    speed.add_argument('--rate', type=float, help='playback speed factor (default 1)')
    speed.add_argument('--fast', action='store_true', help='ignore the recorded timing')
    out.add_argument('--topics', nargs='+', help='topics to replay (default: all)')
    out.add_argument('--wait-subscribers', type=int,
                     help='wait for this many subscribers per topic before starting')
    offline_flags = out.add_argument_group('offline mode')
    offline_flags.add_argument('--offline', action='store_true',
                               help='re-run the estimator from the core over the bag instead')
    offline_flags.add_argument('--strategy', choices=METHODS, help='default: from the bag')
    offline_flags.add_argument('--measurement', choices=MEASUREMENT_KINDS,
                               help='default: from the bag')
    offline_flags.add_argument('--dt', type=float, help='sub-step length, s (default: bag)')
    offline_flags.add_argument('--seed', type=int, default=0, help='seed of the run (planner '
                               'stream, for the waypoint comparison)')
    offline_flags.add_argument('--trial', type=int, default=0)
    offline_flags.add_argument('--gbs-cell', type=float, default=0.005)
    offline_flags.add_argument('--tolerance', type=float, default=1e-9,
                               help='largest admissible difference (default 1e-9)')
    offline_flags.add_argument('--json', type=Path, help='also write the result here')
    return out


def main(args: list[str] | None = None) -> None:
    """Console entry point: ``replay BAG [--rate F | --fast] [--topics ...] [--offline]``."""
    from rclpy.utilities import remove_ros_args
    argv = list(sys.argv[1:] if args is None else args)
    options = parser().parse_args(remove_ros_args(['replay'] + argv)[1:])
    if options.offline:
        if options.bag is None:
            parser().error('--offline needs BAG')
        sys.exit(offline_main(options))
    preloaded = None
    extra = []
    if options.bag is not None:
        try:
            preloaded = bags.read_bag(options.bag)
            select_topics(preloaded, options.topics or ['*'])
        except bags.BagError as error:
            print(f'error: {error}', file=sys.stderr)
            sys.exit(2)
        extra += ['-p', f'bag_path:={json.dumps(str(options.bag))}']
    if options.rate is not None:
        extra += ['-p', f'rate:={float(options.rate)!r}']
    if options.fast:
        extra += ['-p', 'fast:=true']
    if options.topics:
        extra += ['-p', f'topics:={json.dumps(options.topics)}']
    if options.wait_subscribers is not None:
        extra += ['-p', f'wait_subscribers:={options.wait_subscribers}']
    ros_args = argv + (['--ros-args'] + extra if extra else [])
    sys.exit(run(lambda: Replay(preloaded), ['replay'] + ros_args))


if __name__ == '__main__':
    main()
