"""formopt-periodic: PERIODIC's cycle for a scenario, the time of its offline design and of its
online decisions, and the figure of docs/periodic_pattern.md."""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import numpy as np

from formopt_ros.cli.common import ArgumentParser, command, fail, integer, new_file
from formopt_ros.cli.montecarlo import add_scenario_options, scenario_overrides
from formopt_ros.core.model import MEASUREMENT_KINDS
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.core.strategies.periodic import PeriodicPattern
from formopt_ros.core.strategies.periodic_design import (
    SteadyConditions, cached_design, clear_cache)

#: Figure formats --figure writes.
FIGURE_SUFFIXES = ('.png', '.pdf', '.svg')


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    default_period = PeriodicPattern.OPTIONS['period'].default
    parser = ArgumentParser(
        prog='formopt-periodic',
        description="PERIODIC (beyond the paper): design the cycle for the paper's Sec. V "
                    'scenario (or a variant), print it with its steady value against the greedy '
                    'optimum, the offline design time (cold cache, median of --repeats) and the '
                    'online decision time over Sec. V trials; optionally draw the figure of '
                    'docs/periodic_pattern.md.')
    parser.add_argument('--measurement', choices=(*MEASUREMENT_KINDS, 'both'), default='both',
                        help='follower sensor (default: both)')
    parser.add_argument('--period', type=integer(2, 6), default=default_period,
                        help=f'points in the cycle (default: {default_period})')
    add_scenario_options(parser)
    parser.add_argument('--repeats', type=integer(1, 1000), default=3,
                        help='cold designs timed; the median is printed (default: 3)')
    parser.add_argument('--trials', type=integer(0, 10_000), default=3,
                        help='Sec. V trials whose decisions are timed (default: 3)')
    parser.add_argument('--steps', type=integer(1, 10_000_000), default=600,
                        help='steps per timed trial (default: 600)')
    parser.add_argument('--figure', type=new_file, default=None, metavar='PNG',
                        help='draw the docs figure (paper scenarios, both sensors) to this new '
                             'file')
    return parser


def report(scenario: Scenario, period: int, repeats: int, trials: int, steps: int) -> None:
    """Print the cycle, its design time and the decision times for one scenario."""
    conditions = SteadyConditions.from_scenario(scenario)
    print(f'{scenario.measurement}: p_o {list(scenario.p_o)} m, r {scenario.r:.4g} m, sigma '
          f'{scenario.sigma:.4g}, leader {scenario.leader.speed:g} m/s, period {period}')
    if conditions is None:
        print("  the leader's velocity changes from the start: no cycle")
        return
    times = []
    for _ in range(repeats):
        clear_cache()
        start = time.perf_counter()
        design = cached_design(conditions, period)[0]    # the last one stays cached
        times.append(time.perf_counter() - start)
    print(f'  offline design: median {np.median(times):.3f} s, max {max(times):.3f} s over '
          f'{repeats} cold runs (load average {os.getloadavg()[0]:.2f})')
    if design is None:
        print('  no cycle qualifies: PERIODIC plays greedy')
        return
    angles = ', '.join(f'{a:.1f}' for a in np.degrees(design.angles))
    print(f'  cycle at [{angles}] deg around p_o; steady tr(W P W) {design.steady_cost:.6g} '
          f'm^2; convergence factor {design.decay:.4f} per period ({design.horizon} steps to '
          f'settle); {design.evaluations} cycles evaluated')
    if trials:
        decisions = np.concatenate([run_trial(scenario, 'periodic', 0, t, steps,
                                              {'period': period}).decision_time
                                    for t in range(trials)]) * 1e3
        print(f'  online decision over {trials} x {steps} steps (design cached): median '
              f'{np.median(decisions):.3f} ms, p90 {np.percentile(decisions, 90):.3f} ms, p99 '
              f'{np.percentile(decisions, 99):.3f} ms, max {decisions.max():.3f} ms, mean '
              f'{decisions.mean():.3f} ms (load average {os.getloadavg()[0]:.2f})')


@command('formopt-periodic')
def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    kinds = MEASUREMENT_KINDS if args.measurement == 'both' else (args.measurement,)
    if args.figure and Path(args.figure).suffix.lower() not in FIGURE_SUFFIXES:
        fail(parser.prog, f'argument --figure: the file must end in one of {FIGURE_SUFFIXES}, '
                          f'got {args.figure}')
    try:
        scenarios = [Scenario.paper(kind, **scenario_overrides(kind, args)) for kind in kinds]
    except ValueError as error:
        fail(parser.prog, str(error))
    for scenario in scenarios:
        report(scenario, args.period, args.repeats, args.trials, args.steps)
    if args.figure:
        from formopt_ros.analysis.periodic import periodic_figure
        path = periodic_figure([Scenario.paper(kind) for kind in MEASUREMENT_KINDS],
                               Path(args.figure), period=args.period)
        print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
