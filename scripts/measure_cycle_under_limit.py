"""How much a cycle can beat greedy under a speed limit: the headroom of long-run planning.

Paper scenario (straight leader at 1 m/s, Euler kinematics), a speed limit on the follower.
Greedy (RQ over the reachable set) is run on the noise-free recursion (the estimate lands on
each target) for 400 steps; under a limit it settles into a loop that crawls around the disc
(period K, found from its last targets). That loop, as a cycle, is then refined by SLSQP:
the mean steady tr(W P W) of the cycle (core/strategies/periodic_design.py, the periodic
Riccati solution) under the constraints that each point lies in the disc and is reachable
from the one before it (|p_next - (p - v_L 2 dt e_x)| <= max_speed 2 dt, the reach disc of a
straight leader). Also refined: cycles of the given lengths sampled from the loop. Prints
greedy's steady cost (mean of the last 133 steps) and each refined cycle's ratio to it.

A local method from greedy's own loop: the ratios are what such a cycle reaches, not a bound.

Usage: .venv/bin/python scripts/measure_cycle_under_limit.py range|bearing MAX_SPEED [K ...]
"""
from __future__ import annotations

import sys
import time

import numpy as np
from scipy.optimize import minimize

from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.protocol import predict_move
from formopt_ros.core.reach import reach_region
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies.periodic_design import (
    SteadyConditions, cycle_maps, evaluate_cycles, noise_free_step)
from formopt_ros.core.strategies.region import rq_in_region

#: Steps of the greedy run, and the steady window at its end.
STEPS, STEADY = 400, 133


def greedy_loop(scenario: Scenario, conditions: SteadyConditions, max_speed: float
                ) -> tuple[float, np.ndarray]:
    """Greedy's steady cost (m^2) and its targets (STEPS, 2), m, leader frame."""
    c = conditions
    x, P = scenario.initial_estimate()
    costs, targets = [], []
    for _ in range(STEPS):
        prior = predict_move(x, P, c.slot, c.leader, c.dt, c.sigma_v, c.sigma_omega,
                             c.kinematics)[1]
        region = reach_region(c.p_o, c.r, x, c.leader, c.dt, c.kinematics, max_speed, 0.0)
        assert region is not None
        target = np.asarray(rq_in_region(c.problem(prior), region).p)
        x, P = noise_free_step(x, P, target, c)
        targets.append(target)
        costs.append(weighted_trace(P, c.slot))
    return float(np.mean(costs[-STEADY:])), np.array(targets)


def loop_period(targets: np.ndarray, tolerance: float = 1e-3) -> int:
    """The smallest K (2..60) with the last two targets repeated K steps earlier."""
    for period in range(2, 61):
        if all(np.hypot(*(targets[-j] - targets[-j - period])) < tolerance for j in (1, 2)):
            return period
    raise SystemExit('greedy did not settle into a loop of at most 60 steps')


def refine(start: np.ndarray, conditions: SteadyConditions, max_speed: float) -> float:
    """SLSQP on a cycle's points (K, 2) under the disc and reach constraints: its mean steady
    cost (m^2), inf when SLSQP ends outside the constraints."""
    c = conditions
    reach = max_speed * 2 * c.dt
    shift = np.array([c.v_l * 2 * c.dt, 0.0])

    def cost(z: np.ndarray) -> float:
        points = z.reshape(-1, 2)
        return float(evaluate_cycles(cycle_maps(points, c)[None], points[None], c)[0][0])

    def margins(z: np.ndarray) -> np.ndarray:
        points = z.reshape(-1, 2)
        moves = np.roll(points, -1, axis=0) - (points - shift)
        return np.concatenate([reach ** 2 - np.sum(moves ** 2, axis=1),
                               c.r ** 2 - np.sum((points - c.slot) ** 2, axis=1)])

    result = minimize(cost, start.ravel(), method='SLSQP',
                      constraints=[{'type': 'ineq', 'fun': margins}],
                      options={'maxiter': 300, 'ftol': 1e-12})
    return float(result.fun) if np.all(margins(result.x) > -1e-9) else np.inf


def main(argv: list[str]) -> int:
    kind, max_speed = argv[0], float(argv[1])
    lengths = [int(a) for a in argv[2:]]
    scenario = Scenario.paper(kind)
    conditions = SteadyConditions.from_scenario(scenario)
    assert conditions is not None
    greedy, targets = greedy_loop(scenario, conditions, max_speed)
    period = loop_period(targets)
    print(f'{kind}, max_speed {max_speed:g} m/s: greedy steady tr(W P W) {greedy:.6g} m^2, '
          f'a loop of {period} steps')
    print('| cycle | points | start / greedy | refined / greedy | SLSQP s |')
    print('|---|---|---|---|---|')
    loop = targets[-period:]
    for length in [period] + lengths:
        start = loop if length == period else \
            loop[np.linspace(0, period, length, endpoint=False).astype(int)]
        begin = time.perf_counter()
        refined = refine(start, conditions, max_speed)
        seconds = time.perf_counter() - begin
        first = float(evaluate_cycles(cycle_maps(start, conditions)[None], start[None],
                                      conditions)[0][0])
        name = "greedy's loop" if length == period else 'sampled from it'
        print(f'| {name} | {length} | {first / greedy:.4f} | {refined / greedy:.4f} | '
              f'{seconds:.1f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
