"""formopt-bench-ros: the nodes as separate processes; lockstep throughput and start-up time,
realtime latency, with 1 and 2 followers."""
from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from formopt_ros.cli.common import ArgumentParser, command, integer, new_file, number
from formopt_ros.cli.supervisor import Launcher
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.wire.jsonfile import write_json

DESCRIPTION = """\
Start leader_sim and, per follower, follower_sim and estimator_planner as separate processes
(through scripts/<node>.sh, as a user does), with a probe in this process that subscribes to
every topic of the formation (the nodes wait for it as they would for a recorder), and measure:
  lockstep:  start-up: from starting the processes to the first waypoint at the probe; steps
             per second, from the first waypoint to the last step's status (every follower);
  realtime:  at 1/dt, the latency from a measurement's stamp (node clock) to the arrival at
             the probe of the waypoint it produced, median and p99, and the share of steps
             longer than 1.5 step periods.
Prints a plain table. Set --domain-id to keep the run apart from other ROS users."""


@dataclass
class Probe:
    """What the probe received: per follower, waypoint and status arrival times, measurement
    stamps (s)."""

    waypoints: dict[str, dict[int, float]] = field(default_factory=dict)
    statuses: dict[str, dict[int, float]] = field(default_factory=dict)
    measurements: dict[str, dict[int, float]] = field(default_factory=dict)


def formation_run(args: Any, mode: str, followers: int, steps: int, dt: float,
                  out: Path) -> tuple[Probe, float, dict[str, int | None]]:
    """One run: (what the probe saw, the time the processes were started, exit codes)."""
    import rclpy

    from formopt_ros.ros.runtime import fast_announcements, make_executor
    fast_announcements()

    from formopt_ros.ros import qos
    from formopt_ros.ros.conversions import message_class
    from formopt_ros.wire.messages import header_ns
    from formopt_ros.wire.topics import formation_topics

    ids = tuple(f'f{i + 1}' for i in range(followers))
    probe = Probe({f: {} for f in ids}, {f: {} for f in ids}, {f: {} for f in ids})
    prefix = f'/bench{os.getpid()}'
    launcher = Launcher(out)
    common = {'mode': mode, 'dt': dt, 'recorders': 1}
    started = time.monotonic()
    started_wall = time.time()
    launcher.start('leader_sim', 'leader_sim', f'{prefix}/leader',
                   {**common, 'followers': list(ids)})
    for i, follower in enumerate(ids):
        params = {**common, 'measurement': args.measurement, 'seed': args.seed + i}
        launcher.start(f'{follower}.follower_sim', 'follower_sim', f'{prefix}/{follower}',
                       params)
        launcher.start(f'{follower}.estimator_planner', 'estimator_planner',
                       f'{prefix}/{follower}', {**params, 'strategy': args.strategy,
                                                'steps': steps})
    # The probe's participant is created after the processes start, as a recorder started with
    # them would be: participants that start together discover each other at once, while a
    # participant that started earlier answers a newcomer only at its next periodic
    # announcement (Fast DDS: every 3 s), which would be timed as start-up.
    rclpy.init()
    try:
        node = rclpy.create_node('bench_probe')
        clock = node.get_clock()

        def receive(name: str) -> Any:
            robot, _, kind = name[len(prefix) + 1:].rpartition('/')

            def on_message(msg: Any) -> None:
                now = clock.now().nanoseconds * 1e-9
                if kind == 'waypoint':
                    probe.waypoints[robot].setdefault(msg.step, now)
                elif kind == 'status' and msg.step > 0:
                    probe.statuses[robot].setdefault(msg.step, now)
                elif kind == 'measurement':
                    probe.measurements[robot].setdefault(msg.step, header_ns(msg) * 1e-9)
            return on_message

        for name, type_name in formation_topics('leader', ids, prefix).items():
            if not name.endswith('/description') and name != '/tf_static':
                # like the recorder, raw CDR; deserialised only where the probe reads a field
                read = name.rpartition('/')[2] in ('waypoint', 'status', 'measurement')
                node.create_subscription(message_class(type_name), name, receive(name),
                                         qos.STREAM, raw=not read)
        executor = make_executor()
        executor.add_node(node)
        deadline = started + args.timeout
        while any(steps not in s for s in probe.statuses.values()):
            executor.spin_once(timeout_sec=0.05)
            dead = [p for p in launcher.processes if not p.alive()
                    and not p.name.endswith('estimator_planner')]
            if dead or time.monotonic() > deadline:
                raise SystemExit(f'formopt-bench-ros: error: the {mode} run did not finish '
                                 f'(logs in {out}): '
                                 + (f'{dead[0].name} exited' if dead else 'timeout'))
        node.destroy_node()
        # the estimators end by themselves after their last step: a SIGINT in the middle of
        # an interpreter's exit would kill it (exit code -2) and read as a failure
        ends = time.monotonic() + 10.0
        while any(p.alive() for p in launcher.processes if p.name.endswith('estimator_planner')
                  ) and time.monotonic() < ends:
            time.sleep(0.05)
    finally:
        rclpy.try_shutdown()
        launcher.stop(launcher.processes)
    return probe, started_wall, {p.name: p.code for p in launcher.processes}


def lockstep_rows(args: Any, followers: int, out: Path) -> list[tuple[str, str]]:
    """Rows of the lockstep benchmark with ``followers`` followers."""
    steps = args.steps
    probe, started, codes = formation_run(args, 'lockstep', followers, steps, args.dt, out)
    first = min(min(w.values()) for w in probe.waypoints.values())
    last = max(s[steps] for s in probe.statuses.values())
    periods = np.diff(sorted(max(s[k] for s in probe.statuses.values())
                             for k in range(1, steps + 1)))
    label = f'lockstep, {followers} follower{"s" if followers > 1 else ""}'
    return [
        (f'{label}: start-up to first waypoint', f'{first - started:.3f} s'),
        (f'{label}: throughput', f'{(steps - 1) / (last - first):.1f} steps/s ({steps} steps '
                                 f'in {last - first:.3f} s after the first waypoint)'),
        (f'{label}: step time median / p99', f'{1e3 * np.median(periods):.2f} / '
                                             f'{1e3 * np.percentile(periods, 99):.2f} ms'),
        (f'{label}: exit codes', ' '.join(f'{k}={v}' for k, v in codes.items())),
    ]


def realtime_rows(args: Any, out: Path) -> list[tuple[str, str]]:
    """Rows of the realtime latency benchmark (one follower)."""
    dt = args.realtime_dt
    period = SUBSTEPS * dt
    steps = max(2, round(args.duration / period))
    probe, _, codes = formation_run(args, 'realtime', 1, steps, dt, out)
    measurements, waypoints = probe.measurements['f1'], probe.waypoints['f1']
    latency = 1e3 * np.array([waypoints[k + 1] - stamp for k, stamp in measurements.items()
                              if k + 1 in waypoints])
    stamps = [measurements[k] for k in sorted(measurements)]
    intervals = np.diff(stamps)
    late = int(np.sum(intervals > 1.5 * period))
    return [
        ('realtime: rate / steps', f'{1 / dt:.0f} Hz (dt {dt} s), {steps} steps, '
                                   f'{steps * period:.0f} s'),
        ('realtime: latency median / p99 / max', f'{statistics.median(latency):.2f} / '
                                                 f'{np.percentile(latency, 99):.2f} / '
                                                 f'{latency.max():.2f} ms '
                                                 f'({len(latency)} samples)'),
        ('realtime: steps > 1.5 periods', f'{late} of {len(intervals)} '
                                          f'({100 * late / max(len(intervals), 1):.2f} %)'),
        ('realtime: exit codes', ' '.join(f'{k}={v}' for k, v in codes.items())),
    ]


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(prog='formopt-bench-ros', description=DESCRIPTION)
    parser.add_argument('--steps', type=integer(2, 10**6), default=600,
                        help='lockstep: measurement steps (default 600)')
    parser.add_argument('--dt', type=number(1e-3, 10.0), default=0.05,
                        help='lockstep: sub-step length, s (simulated; default 0.05)')
    parser.add_argument('--followers', type=integer(1, 16), nargs='+', default=[1, 2],
                        help='lockstep runs with these numbers of followers (default 1 2)')
    parser.add_argument('--realtime-dt', type=number(1e-3, 10.0), default=0.05,
                        help='realtime: sub-step length, s; timers at 1/dt (default 0.05)')
    parser.add_argument('--duration', type=number(0.5, 3600.0), default=30.0,
                        help='realtime: run length, s (default 30)')
    parser.add_argument('--measurement', choices=('range', 'bearing'), default='range',
                        help='the followers\' sensor (default range)')
    parser.add_argument('--strategy', default='ram', help='motion strategy (default ram)')
    parser.add_argument('--seed', type=integer(0, 2**31 - 1), default=0, help='seed')
    parser.add_argument('--only', choices=('lockstep', 'realtime'),
                        help='run one of the two benchmarks only')
    parser.add_argument('--domain-id', type=integer(0, 232),
                        help='ROS_DOMAIN_ID of the runs (default: $ROS_DOMAIN_ID, else 0)')
    parser.add_argument('--timeout', type=number(1.0, 3600.0), default=300.0,
                        help='give up a run after this long, s (default 300)')
    parser.add_argument('--json', type=new_file, metavar='PATH',
                        help='also write the rows here as JSON (a new file)')
    return parser


@command('formopt-bench-ros')
def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    args = build_parser().parse_args(argv)
    from formopt_ros.core.strategies import STRATEGIES
    if args.strategy not in STRATEGIES:
        build_parser().error(f'argument --strategy: invalid choice: {args.strategy!r}')
    if args.domain_id is not None:
        os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rows: list[tuple[str, str]] = []
    with tempfile.TemporaryDirectory(prefix='bench_ros_') as tmp:
        if args.only in (None, 'lockstep'):
            for followers in args.followers:
                folder = Path(tmp) / f'lockstep{followers}'
                folder.mkdir()
                rows += lockstep_rows(args, followers, folder)
        if args.only in (None, 'realtime'):
            folder = Path(tmp) / 'realtime'
            folder.mkdir()
            rows += realtime_rows(args, folder)
    width = max(len(name) for name, _ in rows)
    print(f'formopt-bench-ros: {args.measurement}, {args.strategy}, seed {args.seed}, '
          f'ROS_DOMAIN_ID={os.environ.get("ROS_DOMAIN_ID", "0")}, {os.cpu_count()} CPUs')
    for name, value in rows:
        print(f'{name:<{width}}  {value}')
    if args.json:
        write_json(args.json, dict(rows))
    return 0


if __name__ == '__main__':
    sys.exit(main())
