"""How much a cycle can beat greedy under a speed limit: the headroom of long-run planning.

Paper scenario (a straight leader at 1 m/s, or on an arc with ``--leader-yaw-rate``) with a
speed limit on the follower. Greedy (RQ over the reachable set) runs on the noise-free
recursion and settles into a loop that crawls around the disc (``periodic_design.greedy_loop``,
period K). That loop, and cycles of the given
lengths sampled from it (a length above K repeats points of the loop), are refined by SLSQP
on the cycle's exact mean steady tr(W P W) with its gradient (``CycleObjective``) under the
constraints of a design within reach (``cycle_margins``): PERIODIC's own search, with the
lengths free. Prints greedy's steady cost and each refined cycle's ratio to it.

With ``--hops N`` a basin-hopping search goes on from the best of those cycles: N times, the
current best is perturbed (every point moved by N(0, 1 cm^2) per axis, one point deleted, or
one inserted midway between two neighbours; each a third of the time, seeded), refined again,
and kept when it is better.

With ``--random N`` N more starts are refined: random smooth closed curves (three harmonics
of decaying random amplitude, 6-39 points, either direction, seeded, scaled to 0.3-1.0 r
about the slot), to see whether cycles unlike greedy's loop do better.

With ``--trials N`` PERIODIC (its own design) and RQ are played for N trials of 400 steps
(seed 0): their steady tr(W P W) (the last 133 steps) relative to greedy's noise-free steady
state, and the share of PERIODIC's steady waypoints that are not points of its cycle
(projected onto the reachable set: the estimated pose could not reach the cycle's point).
With ``--design-margin F`` PERIODIC plays there a cycle designed for a reach F (a fraction)
smaller than the one it moves in, leaving room for the estimate's corrections.

Local methods from greedy's own loop: the ratios are what such cycles reach, not a bound.

Usage: .venv/bin/python scripts/measure_cycle_under_limit.py range|bearing MAX_SPEED [K ...]
[--leader-yaw-rate W] [--hops N] [--random N] [--seed S] [--trials N [--design-margin F]]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import replace

import numpy as np

from formopt_ros.core.scenario import LeaderPath, Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.core.strategies import periodic as periodic_strategy
from formopt_ros.core.strategies.periodic_design import (
    CycleObjective, PatternDesign, SteadyConditions, cached_design, greedy_loop, loop_length,
    refine_cycle)

#: Standard deviation of a hop's move of every point, m.
HOP_SIGMA = 0.01


def hop(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A perturbed copy of the cycle ``points`` (m, 2): all points moved, one deleted or one
    inserted (module docstring)."""
    kind, k = int(rng.integers(3)), int(rng.integers(len(points)))
    if kind == 0:
        return points + rng.normal(0.0, HOP_SIGMA, points.shape)
    if kind == 1 and len(points) > 3:
        return np.delete(points, k, axis=0)
    return np.insert(points, k + 1, 0.5 * (points[k] + points[(k + 1) % len(points)]), axis=0)


def random_curve(conditions: SteadyConditions, rng: np.random.Generator) -> np.ndarray:
    """A random smooth closed curve about the slot (module docstring), points (m, 2), m."""
    length = int(rng.integers(6, 40))
    t = np.linspace(0.0, 2.0 * math.pi, length, endpoint=False) * rng.choice([-1.0, 1.0])
    curve = sum(np.outer(np.cos(k * t), rng.normal(size=2) / k ** 1.5)
                + np.outer(np.sin(k * t), rng.normal(size=2) / k ** 1.5) for k in (1, 2, 3))
    curve = curve - curve.mean(axis=0)
    return conditions.slot + curve * rng.uniform(0.3, 1.0) * conditions.r \
        / np.max(np.hypot(*curve.T))


def main(argv: list[str]) -> int:
    """Print the table for one sensor, one speed limit and the given cycle lengths."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('kind', choices=('range', 'bearing'))
    parser.add_argument('max_speed', type=float, help='the follower speed limit, m/s')
    parser.add_argument('lengths', type=int, nargs='*', help='cycle lengths to sample')
    parser.add_argument('--leader-yaw-rate', type=float, default=0.0,
                        help='the leader on an arc at this rate, rad/s (0: straight)')
    parser.add_argument('--hops', type=int, default=0, help='basin-hopping rounds (0: none)')
    parser.add_argument('--random', type=int, default=0,
                        help='random smooth closed curves to refine as starts (0: none)')
    parser.add_argument('--seed', type=int, default=0, help='seed of the hops and curves')
    parser.add_argument('--trials', type=int, default=0, help='trials to play (0: none)')
    parser.add_argument('--design-margin', type=float, default=0.0,
                        help="PERIODIC's cycle designed for a reach this fraction smaller")
    args = parser.parse_args(argv)
    leader = LeaderPath('arc', 1.0, args.leader_yaw_rate) if args.leader_yaw_rate else LeaderPath()
    scenario = Scenario.paper(args.kind, max_speed=args.max_speed, leader=leader)
    conditions = SteadyConditions.from_scenario(scenario)
    assert conditions is not None
    greedy, targets = greedy_loop(conditions)
    period = loop_length(targets, 60, conditions)
    if period is None:
        raise SystemExit('greedy did not settle into a loop of at most 60 steps')
    print(f'{args.kind}, max_speed {args.max_speed:g} m/s: greedy steady tr(W P W) '
          f'{greedy:.6g} m^2, a loop of {period} steps')
    print('| cycle | points | start / greedy | refined / greedy | SLSQP s |')
    print('|---|---|---|---|---|')
    loop = targets[-period:]
    objective = CycleObjective(conditions)
    best = (math.inf, loop)
    for length in [period] + args.lengths:
        start = loop if length == period else \
            loop[np.linspace(0, period, length, endpoint=False).astype(int)]
        begin = time.perf_counter()
        refined = refine_cycle(start, objective)
        seconds = time.perf_counter() - begin
        best = min(best, refined, key=lambda found: found[0])
        name = "greedy's loop" if length == period else 'sampled from it'
        print(f'| {name} | {length} | {objective(start.ravel()) / greedy:.4f} | '
              f'{refined[0] / greedy:.4f} | {seconds:.1f} |')
    rng = np.random.default_rng(args.seed)
    begin = time.perf_counter()
    if args.random:
        found = [refine_cycle(random_curve(conditions, rng), objective)
                 for _ in range(args.random)]
        ratios = np.sort([value / greedy for value, _ in found])
        points = len(min(found, key=lambda candidate: candidate[0])[1])
        best = min([best, *found], key=lambda candidate: candidate[0])
        print(f'| {args.random} random curves (seed {args.seed}) | {points} | | best '
              f"{', '.join(f'{ratio:.4f}' for ratio in ratios[:3])}; median "
              f'{np.median(ratios):.4f} | {time.perf_counter() - begin:.1f} |')
        begin = time.perf_counter()
    for _ in range(args.hops):
        best = min(best, refine_cycle(hop(best[1], rng), objective), key=lambda found: found[0])
    if args.hops:
        print(f'| after {args.hops} hops (seed {args.seed}) | {len(best[1])} | | '
              f'{best[0] / greedy:.4f} | {time.perf_counter() - begin:.1f} |')
    if args.trials:
        play(scenario, conditions, greedy, args.trials, args.design_margin)
    return 0


def play(scenario: Scenario, conditions: SteadyConditions, greedy: float, trials: int,
         margin: float) -> None:
    """Print PERIODIC's and RQ's steady tr(W P W) in ``trials`` runs against greedy's
    noise-free steady state, and the share of PERIODIC's steady waypoints off its cycle; its
    cycle designed for a reach ``margin`` (a fraction) smaller."""
    def designed_smaller(played: SteadyConditions,
                         period: int) -> tuple[PatternDesign | None, bool]:
        return cached_design(replace(played, reach=played.reach * (1.0 - margin)), period)

    periodic_strategy.cached_design = designed_smaller     # PERIODIC's own lookup of its design
    design = designed_smaller(conditions, 4)[0]
    assert design is not None
    steady: dict[str, list[float]] = {'periodic': [], 'rq': []}
    off: list[np.ndarray] = []
    for trial in range(trials):
        for name in steady:
            result = run_trial(scenario, name, 0, trial, 400)
            steady[name].append(result.weighted_trace[267:].mean())
            if name == 'periodic':
                waypoints = result.waypoints[267:]
                gap = np.linalg.norm(waypoints[:, None] - design.points[None], axis=2).min(axis=1)
                off.append(gap > 1e-3)
    periodic, rq = (float(np.mean(steady[name])) / greedy for name in ('periodic', 'rq'))
    print(f'played, {trials} x 400 steps, designed for {1.0 - margin:g} of the reach: design '
          f'{design.steady_cost / greedy:.4f}, PERIODIC '
          f'{periodic:.4f}, RQ {rq:.4f} of greedy noise-free (PERIODIC / RQ '
          f'{periodic / rq:.4f}); steady waypoints off the cycle {np.mean(off):.1%}')


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
