"""How much a cycle can beat greedy under a speed limit: the headroom of long-run planning.

Paper scenario (straight leader at 1 m/s) with a speed limit on the follower. Greedy (RQ over
the reachable set) runs on the noise-free recursion and settles into a loop that crawls around
the disc (``periodic_design.greedy_loop``, period K). That loop, and cycles of the given
lengths sampled from it (a length above K repeats points of the loop), are refined by SLSQP
on the cycle's exact mean steady tr(W P W) with its gradient (``CycleObjective``) under the
constraints of a design within reach (``cycle_margins``): PERIODIC's own search, with the
lengths free. Prints greedy's steady cost and each refined cycle's ratio to it.

A local method from greedy's own loop: the ratios are what such a cycle reaches, not a bound.

Usage: .venv/bin/python scripts/measure_cycle_under_limit.py range|bearing MAX_SPEED [K ...]
"""
from __future__ import annotations

import math
import sys
import time

import numpy as np

from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies.periodic_design import (
    CycleObjective, SteadyConditions, greedy_loop, loop_length, refine_cycle)


def main(argv: list[str]) -> int:
    """Print the table for one sensor, one speed limit and the given cycle lengths."""
    kind, max_speed = argv[0], float(argv[1])
    lengths = [int(a) for a in argv[2:]]
    conditions = SteadyConditions.from_scenario(Scenario.paper(kind, max_speed=max_speed))
    assert conditions is not None
    greedy, targets = greedy_loop(conditions)
    period = loop_length(targets, 60, 1e-6 * (math.hypot(*conditions.p_o) + conditions.r))
    if period is None:
        raise SystemExit('greedy did not settle into a loop of at most 60 steps')
    print(f'{kind}, max_speed {max_speed:g} m/s: greedy steady tr(W P W) {greedy:.6g} m^2, '
          f'a loop of {period} steps')
    print('| cycle | points | start / greedy | refined / greedy | SLSQP s |')
    print('|---|---|---|---|---|')
    loop = targets[-period:]
    for length in [period] + lengths:
        start = loop if length == period else \
            loop[np.linspace(0, period, length, endpoint=False).astype(int)]
        begin = time.perf_counter()
        refined = refine_cycle(start, CycleObjective(conditions))[0]
        seconds = time.perf_counter() - begin
        first = CycleObjective(conditions)(start.ravel())
        name = "greedy's loop" if length == period else 'sampled from it'
        print(f'| {name} | {length} | {first / greedy:.4f} | {refined / greedy:.4f} | '
              f'{seconds:.1f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
