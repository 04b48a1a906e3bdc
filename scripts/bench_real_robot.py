"""Time follower_estimator's work per range on simulated real robots (no ROS): the asynchronous
EKF's propagation and update, a plan of the strategy and the velocity command, with 50 Hz
odometry from both robots and 30 Hz ranges. Prints a table: median and p99 per range, and p99 as
a share of the 2 ms budget.

Usage: .venv/bin/python scripts/bench_real_robot.py [SECONDS] [STRATEGY ...]
"""
from __future__ import annotations

import sys
import time

import numpy as np

from formopt_ros.core.asynchronous import AsyncEstimator
from formopt_ros.core.controller import Limits, twist_toward
from formopt_ros.core.estimator import EstimatorPlanner, RealNoise
from formopt_ros.core.field import Base, Radio, simulate_field
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import make_strategy

BUDGET_S = 2e-3


def per_range_times(strategy: str, seconds: float) -> np.ndarray:
    """Wall time (s) of each range's update, plan and command."""
    scenario = Scenario('range', (-1.0, -2.0), 0.22, 0.1, sigma_v=0.1, sigma_omega=0.05)
    run = simulate_field(seconds, np.array([-1.0, -2.0, 0.0]), lambda t: (1.0, 0.0),
                         lambda t, pose: (1.0, 0.0), np.random.default_rng(1),
                         Base(50.0, 0.0, 0.1, 0.05), Base(50.0, 0.007), Radio())
    estimator = EstimatorPlanner(scenario, make_strategy(strategy), np.random.default_rng(0),
                                 RealNoise(0.3, 0.002, 2.5))
    tracker = AsyncEstimator(estimator, 0)
    inputs = sorted([(s, 0, 'follower', (v, w)) for s, v, w in run.follower_odometry] +
                    [(s, 0, 'leader', (v, w)) for s, v, w in run.leader_odometry] +
                    [(s, 1, 'range', (z,)) for s, z in run.ranges])
    limits, command, times = Limits(), (0.0, 0.0), []
    for stamp, _, kind, values in inputs:
        if kind != 'range':
            tracker.add_odometry(kind, stamp, *values)
            tracker.advance(stamp)
            continue
        start = time.perf_counter()
        tracker.add_measurement(stamp, values[0], 0.01)
        tracker.advance(stamp)
        target = tracker.plan(len(times) + 1).solution.p
        command = twist_toward(tracker.estimator.x, target, (1.0, 0.0), 0.5, limits, command,
                               0.05)
        times.append(time.perf_counter() - start)
    return np.array(times)


def main(argv: list[str]) -> None:
    """Print the table."""
    seconds = float(argv[0]) if argv else 60.0
    strategies = argv[1:] or ['rq', 'ram', 'periodic']
    print(f'per range (update, plan, command), {seconds:g} s of 50 Hz odometry x 2 and 30 Hz '
          'ranges')
    print('| strategy | ranges | median ms | p99 ms | p99 / 2 ms budget |')
    print('|---|---|---|---|---|')
    for name in strategies:
        times = per_range_times(name, seconds) * 1e3
        p99 = float(np.percentile(times, 99))
        print(f'| {name} | {len(times)} | {np.median(times):.3f} | {p99:.3f} | '
              f'{p99 / (BUDGET_S * 1e3):.2f} |')


if __name__ == '__main__':
    main(sys.argv[1:])
