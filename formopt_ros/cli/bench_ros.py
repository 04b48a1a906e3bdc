"""Benchmark the three ROS nodes as separate processes: lockstep throughput, realtime latency."""
from __future__ import annotations

import argparse
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from formopt_ros.core.protocol import SUBSTEPS

NODES = ('leader_sim', 'follower_sim', 'estimator_planner')
DESCRIPTION = """\
Start leader_sim, follower_sim and estimator_planner as separate processes (the executables
of lib/formopt_ros, as `ros2 run` does) and measure, with a probe subscriber in this process:
  lockstep:  steps per second, from the first waypoint's arrival to the last status's;
  realtime:  at 1/dt, the latency from a measurement's publication (its header stamp, node
             clock) to the arrival of the waypoint it produced at the probe (receive time),
             median and p99; and the share of follower timer cycles that missed their period
             (a tick without its waypoint holds, which delays the measurement: counted from
             the measurement stamps), plus the share of steps longer than 1.5 step periods.
Prints a plain table. Set --domain-id to keep the run apart from other ROS users."""


def executable(node: str) -> str:
    """Path of formopt_ros's executable ``node``: AMENT_PREFIX_PATH, this prefix, PATH."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    for prefix in prefixes + [sys.prefix]:
        path = Path(prefix) / 'lib' / 'formopt_ros' / node
        if path.is_file() and os.access(path, os.X_OK):
            return str(path)
    found = shutil.which(node)
    if found is None:
        raise SystemExit(f'bench_ros: error: executable {node} not found (lib/formopt_ros under '
                         'AMENT_PREFIX_PATH or this prefix, or PATH); run scripts/setup.sh')
    return found


@dataclass
class Run:
    """One formation run: node processes, their logs and what the probe received."""

    log_dir: Path
    processes: dict[str, subprocess.Popen] = field(default_factory=dict)
    waypoints: dict[int, float] = field(default_factory=dict)      # step -> receive, s
    statuses: dict[int, float] = field(default_factory=dict)       # step -> receive, s
    measurements: dict[int, float] = field(default_factory=dict)   # step -> stamp, s

    def start(self, node: str, params: dict[str, object]) -> None:
        """Start one node with -p overrides; stdout and stderr go to <log_dir>/<node>.log."""
        args = [executable(node), '--ros-args']
        for name, value in params.items():
            args += ['-p', f'{name}:={value}']
        log = open(self.log_dir / f'{node}.log', 'w')
        self.processes[node] = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT,
                                                start_new_session=True)
        log.close()

    def log(self, node: str) -> str:
        """The node's log so far."""
        return (self.log_dir / f'{node}.log').read_text(errors='replace')

    def wait_ready(self, node: str, deadline: float) -> None:
        """Block until the node logged its ready line (or fail)."""
        while f'{node} ready' not in self.log(node):
            if self.processes[node].poll() is not None or time.monotonic() > deadline:
                raise SystemExit(f'bench_ros: error: {node} did not start:\n{self.log(node)}')
            time.sleep(0.05)

    def stop(self) -> dict[str, int]:
        """SIGINT every node still running (SIGKILL after 20 s); their exit codes."""
        for process in self.processes.values():
            if process.poll() is None:
                process.send_signal(signal.SIGINT)
        codes = {}
        for node, process in self.processes.items():
            try:
                codes[node] = process.wait(timeout=20.0)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                codes[node] = process.wait()
        return codes


def formation(args: argparse.Namespace, mode: str, steps: int, dt: float,
              log_dir: Path) -> tuple[Run, dict[str, int]]:
    """Run the three nodes for ``steps`` steps with a probe; return the run and exit codes."""
    import rclpy
    from formopt_interfaces.msg import Measurement, PlannerStatus, Waypoint
    from rclpy.executors import SingleThreadedExecutor

    from formopt_ros.ros import qos
    from formopt_ros.wire.messages import header_ns
    from formopt_ros.wire.topics import follower_topic

    run = Run(log_dir)
    rclpy.init()
    try:
        probe = rclpy.create_node('bench_probe')
        clock = probe.get_clock()          # system time, like the nodes' clocks

        def now() -> float:
            return clock.now().nanoseconds * 1e-9

        def on_waypoint(msg: Any) -> None:
            run.waypoints.setdefault(msg.step, now())

        def on_status(msg: Any) -> None:
            run.statuses.setdefault(msg.step, now())

        def on_measurement(msg: Any) -> None:
            run.measurements.setdefault(msg.step, header_ns(msg) * 1e-9)

        probe.create_subscription(Waypoint, follower_topic('waypoint'), on_waypoint,
                                  qos.SUBSCRIBED)
        probe.create_subscription(PlannerStatus, follower_topic('status'), on_status,
                                  qos.SUBSCRIBED)
        probe.create_subscription(Measurement, follower_topic('measurement'), on_measurement,
                                  qos.SUBSCRIBED)
        executor = SingleThreadedExecutor()
        executor.add_node(probe)
        common = {'mode': mode, 'dt': dt, 'measurement': args.measurement, 'seed': args.seed}
        deadline = time.monotonic() + args.timeout
        run.start('leader_sim', common)
        run.start('follower_sim', common)
        for node in ('leader_sim', 'follower_sim'):
            run.wait_ready(node, deadline)
        # peers: leader_sim, follower_sim and this probe listen to the waypoints
        run.start('estimator_planner', dict(common, strategy=args.strategy, steps=steps,
                                            peers=3))
        estimator = run.processes['estimator_planner']
        while steps not in run.statuses and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
            if estimator.poll() is not None and steps not in run.statuses:
                executor.spin_once(timeout_sec=1.0)      # the last status may be in flight
                break
        codes = run.stop()
        probe.destroy_node()
    finally:
        rclpy.try_shutdown()
    if steps not in run.statuses:
        raise SystemExit(f'bench_ros: error: {mode} run did not finish {steps} steps '
                         f'(last status {max(run.statuses, default=0)}); logs in {log_dir}')
    return run, codes


def resends(run: Run) -> int:
    """How often the estimator resent a waypoint (a peer was late: lockstep stalls ~1 s)."""
    return len(re.findall('resending its waypoint', run.log('estimator_planner')))


def lockstep(args: argparse.Namespace, log_dir: Path) -> list[tuple[str, str]]:
    """Rows of the lockstep throughput benchmark."""
    steps = args.steps
    run, codes = formation(args, 'lockstep', steps, args.dt, log_dir)
    first = min(run.waypoints)
    elapsed = run.statuses[steps] - run.waypoints[first]
    done = steps - first + 1
    periods = np.diff([run.statuses[k] for k in sorted(run.statuses)])
    return [
        ('lockstep steps', f'{done} (steps {first}..{steps})'),
        ('lockstep wall time', f'{elapsed:.3f} s (first waypoint -> last status)'),
        ('lockstep throughput', f'{done / elapsed:.1f} steps/s'),
        ('lockstep step time median / p99', f'{1e3 * np.median(periods):.2f} / '
                                            f'{1e3 * np.percentile(periods, 99):.2f} ms'),
        ('lockstep waypoint resends', str(resends(run))),
        ('lockstep exit codes', ' '.join(f'{n}={codes[n]}' for n in NODES)),
    ]


def realtime(args: argparse.Namespace, log_dir: Path) -> list[tuple[str, str]]:
    """Rows of the realtime latency benchmark."""
    dt = args.realtime_dt
    period = SUBSTEPS * dt
    steps = max(2, round(args.duration / period))
    run, codes = formation(args, 'realtime', steps, dt, log_dir)
    latency = [run.waypoints[k + 1] - stamp for k, stamp in run.measurements.items()
               if k + 1 in run.waypoints]
    stamps = [run.measurements[k] for k in sorted(run.measurements)]
    intervals = np.diff(stamps)
    ticks = np.maximum(np.rint(intervals / dt), SUBSTEPS)       # timer ticks per step
    missed = int(np.sum(ticks - SUBSTEPS))
    late_steps = int(np.sum(intervals > 1.5 * period))
    follower = re.findall(r"'missed_cycles': (\d+)", run.log('follower_sim'))
    lat_ms = 1e3 * np.asarray(latency)
    return [
        ('realtime rate / steps', f'{1 / dt:.0f} Hz (dt {dt} s), {steps} steps, '
                                  f'{steps * period:.0f} s'),
        ('realtime latency samples', str(len(latency))),
        ('realtime latency median', f'{statistics.median(lat_ms):.2f} ms'),
        ('realtime latency p99', f'{np.percentile(lat_ms, 99):.2f} ms'),
        ('realtime latency max', f'{lat_ms.max():.2f} ms'),
        ('realtime missed cycles', f'{missed} of {int(ticks.sum())} ticks '
                                   f'({100 * missed / max(ticks.sum(), 1):.2f} %)'),
        ('realtime steps > 1.5 periods', f'{late_steps} of {len(intervals)} '
                                         f'({100 * late_steps / max(len(intervals), 1):.2f} %)'),
        ('realtime follower missed_cycles', (follower[-1] if follower else '?')
         + ' (its counter; includes ticks after the last waypoint)'),
        ('realtime exit codes', ' '.join(f'{n}={codes[n]}' for n in NODES)),
    ]


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    parser = argparse.ArgumentParser(prog='python -m formopt_ros.cli.bench_ros',
                                     description=DESCRIPTION,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--steps', type=int, default=600,
                        help='lockstep: measurement steps (default 600)')
    parser.add_argument('--dt', type=float, default=0.05,
                        help='lockstep: sub-step length, s (simulated; default 0.05)')
    parser.add_argument('--realtime-dt', type=float, default=0.05,
                        help='realtime: sub-step length, s; the timers run at 1/dt '
                             '(default 0.05 = 20 Hz)')
    parser.add_argument('--duration', type=float, default=30.0,
                        help='realtime: run length, s (default 30)')
    parser.add_argument('--measurement', choices=('range', 'bearing'), default='range',
                        help='the follower sensor (default range)')
    parser.add_argument('--strategy', default='ram', help='motion strategy (default ram)')
    parser.add_argument('--seed', type=int, default=0, help='seed (default 0)')
    parser.add_argument('--only', choices=('lockstep', 'realtime'),
                        help='run one of the two benchmarks only')
    parser.add_argument('--domain-id', type=int,
                        help='ROS_DOMAIN_ID of the run (default: $ROS_DOMAIN_ID, else 0)')
    parser.add_argument('--timeout', type=float, default=300.0,
                        help='give up a run after this long, s (default 300)')
    parser.add_argument('--log-dir', type=Path,
                        help='keep the node logs here (default: a temporary folder)')
    args = parser.parse_args(argv)
    if args.steps < 2 or args.dt <= 0 or args.realtime_dt <= 0 or args.duration <= 0:
        parser.error('--steps must be >= 2; --dt, --realtime-dt and --duration > 0')
    if args.domain_id is not None:
        os.environ['ROS_DOMAIN_ID'] = str(args.domain_id)
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    rows: list[tuple[str, str]] = []
    with tempfile.TemporaryDirectory(prefix='bench_ros_') as tmp:
        base = args.log_dir or Path(tmp)
        for name, bench in (('lockstep', lockstep), ('realtime', realtime)):
            if args.only in (None, name):
                folder = base / name
                folder.mkdir(parents=True, exist_ok=True)
                rows += bench(args, folder)
    width = max(len(name) for name, _ in rows)
    domain = os.environ.get('ROS_DOMAIN_ID', '0')
    print(f'bench_ros: {args.measurement}, {args.strategy}, seed {args.seed}, '
          f'ROS_DOMAIN_ID={domain}, {os.cpu_count()} CPUs')
    for name, value in rows:
        print(f'{name:<{width}}  {value}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
