"""How consistent an estimator is after rejoining a run without its history, against the run.

Usage:
    .venv/bin/python scripts/measure_rejoin.py [--kind range] [--trials 40] [--window 30]
        [--at 2,40,89] [--inflation 1,2,4]

Each trial is the Sec. V protocol with RAM (seeded by (0, trial)); at step ``at`` the
estimator is replaced as a restarted estimator_planner replaces itself: that step's
measurement is dropped and the estimate is re-made from both robots' odometry poses
(:func:`formopt_ros.core.field.dead_reckoned_estimate`, covariance times the inflation), with
a fresh strategy. Prints, per rejoin step and inflation, the mean NEES of the re-made prior
and, over the ``window`` steps after it, the median, 90th percentile and largest per-trial
mean NEES, beside the same figures of the uninterrupted runs over the same steps
(docs/faults.md, "restarts").
"""
from __future__ import annotations

import argparse

import numpy as np

from formopt_ros.core.estimator import EstimatorPlanner
from formopt_ros.core.field import dead_reckoned_estimate
from formopt_ros.core.model import integrate_unicycle, normalized_estimation_error
from formopt_ros.core.protocol import SUBSTEPS, held_leader_motion, step_substeps
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import FollowerTruth, received, trial_streams
from formopt_ros.core.strategies import make_strategy


def nees_after_rejoin(scenario: Scenario, trial: int, at: int, inflation: float | None,
                      steps: int) -> np.ndarray:
    """NEES at steps at .. steps of one trial (at: the re-made prior's); no rejoin when
    ``inflation`` is None."""
    noise, planner_rng = trial_streams(0, trial)
    truth = FollowerTruth(scenario, noise)
    estimator = EstimatorPlanner(scenario, make_strategy('ram'), planner_rng)
    latest = scenario.leader.velocity(0, scenario.dt)
    leader, odometry = (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    out = []
    for k in range(1, steps + 1):
        plan = estimator.plan(k, held_leader_motion(latest))
        for j, substep in enumerate(step_substeps(k)):
            latest = v_l, omega_l = scenario.leader.velocity(substep, scenario.dt)
            v, omega = plan.command.linear[j], plan.command.angular[j]
            truth.execute(v, omega, v_l, omega_l)
            estimator.propagate(v, omega, v_l, omega_l)
            leader = integrate_unicycle(leader, v_l, omega_l, scenario.dt)
            odometry = integrate_unicycle(odometry, v, omega, scenario.dt)
        z = received(scenario, k, truth.measure())
        if k == at and inflation is not None:
            x0, P0 = scenario.initial_estimate()
            x, P = dead_reckoned_estimate(
                x0, P0, leader, odometry, SUBSTEPS * k, scenario.dt,
                (scenario.sigma_v, scenario.sigma_omega, scenario.sigma_v_leader,
                 scenario.sigma_omega_leader))
            estimator = EstimatorPlanner(scenario, make_strategy('ram'), planner_rng)
            estimator.state, estimator.covariance = x, inflation * P
        else:
            estimator.update(k, z)
        if k >= at:
            out.append(normalized_estimation_error(truth.x, estimator.x, estimator.P))
    return np.array(out)


def main() -> None:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--kind', default='range', choices=('range', 'bearing'))
    parser.add_argument('--trials', type=int, default=40)
    parser.add_argument('--window', type=int, default=30)
    parser.add_argument('--at', default='2,40,89')
    parser.add_argument('--inflation', default='1,2,4')
    args = parser.parse_args()
    scenario = Scenario.paper(args.kind)
    print('| rejoin step | inflation | prior NEES | after: median | p90 | max |')
    print('|---|---|---|---|---|---|')
    for at in map(int, args.at.split(',')):
        for inflation in [None, *map(float, args.inflation.split(','))]:
            runs = np.array([nees_after_rejoin(scenario, t, at, inflation, at + args.window)
                             for t in range(args.trials)])
            window = runs[:, 1:].mean(axis=1)
            prior = '-' if inflation is None else f'{runs[:, 0].mean():.2f}'
            print(f"| {at} | {'none (the run)' if inflation is None else f'{inflation:g}'} | "
                  f'{prior} | {np.median(window):.2f} | {np.percentile(window, 90):.2f} | '
                  f'{window.max():.2f} |')


if __name__ == '__main__':
    main()
