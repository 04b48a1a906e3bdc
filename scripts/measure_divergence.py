"""Why large discs diverge: trial-mean NEES over deviation fractions, or one trial step by step.

Usage:
    .venv/bin/python scripts/measure_divergence.py sweep KIND 0.5,0.7,0.9 [--trials 50]
        [--variance 0.1] [--strategies ram,rq,periodic]
    .venv/bin/python scripts/measure_divergence.py trace bearing 0.9 --trial 1 [--steps 120]

``sweep`` prints, per fraction f (r = f |p_o|) and strategy, the study's mean NEES, the share
of steps with the trial-mean NEES in the 95 % band, the worst trial's mean NEES, the gated
updates and whether the study flags it. ``trace`` prints one RAM trial: distances of the true
follower, the estimate and the waypoint to the leader, the position error, the heading error,
the largest position standard deviation, NIS and NEES (docs/faults.md, "Why large discs
diverge for bearing").
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from formopt_ros.core.model import wrap_angle
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.core.study import StudyConfig, run_study, summarize


def sweep(kind: str, fractions: list[float], trials: int, variance: float,
          strategies: tuple[str, ...]) -> None:
    """Print one line per (fraction, strategy)."""
    d_o = Scenario.paper(kind).d_o
    for fraction in fractions:
        scenario = {'r': fraction * d_o, 'initial_covariance': (variance, variance, 4e-4)}
        config = StudyConfig(kind, trials=trials, steps=600, seed=0, strategies=strategies,
                             scenario=scenario)
        result = run_study(config, jobs=1)
        summary = summarize(result)
        for name, record in result.records.items():
            row = summary['strategies'][name]
            flag = 'FLAGGED' if name in summary['consistency']['flagged'] else 'ok'
            print(f"{kind} variance {variance:g} f {fraction:g} {name:8s} mean NEES "
                  f"{row['nees_mean']:10.4g} in band {100 * row['nees_in_band']:5.1f} % worst "
                  f'trial {record.nees.mean(axis=1).max():9.3g} gated '
                  f"{row['gated_updates']:5d} {flag}", flush=True)


def trace(kind: str, fraction: float, trial: int, steps: int) -> None:
    """Print one RAM trial step by step."""
    scenario = Scenario.paper(kind, r=fraction * Scenario.paper(kind).d_o)
    out = run_trial(scenario, 'ram', 0, trial, steps)
    for k in range(steps):
        truth, estimate, P = out.truth[k], out.estimate[k], out.covariance[k]
        sigma = math.sqrt(np.linalg.eigvalsh(P[:2, :2])[-1])
        print(f'{k + 1:4d} |truth| {np.hypot(*truth[:2]):.3f} |estimate| '
              f'{np.hypot(*estimate[:2]):.3f} |waypoint| {np.hypot(*out.waypoints[k]):.3f} '
              f'error {np.hypot(*(truth[:2] - estimate[:2])):.3f} heading error '
              f'{float(wrap_angle(truth[2] - estimate[2])):+.3f} sigma {sigma:.3f} NIS '
              f'{out.innovation_nis[k]:9.3g} gated {int(out.gated[k])} NEES {out.nees[k]:9.3g}')


def main() -> None:
    """Command line (module docstring)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('mode', choices=('sweep', 'trace'))
    parser.add_argument('kind', choices=('range', 'bearing', 'range-bearing'))
    parser.add_argument('fractions', help='comma list of r / |p_o| (trace: one)')
    parser.add_argument('--trials', type=int, default=50)
    parser.add_argument('--variance', type=float, default=0.1,
                        help='initial position variance, m^2 (default: the paper, 0.1)')
    parser.add_argument('--strategies', default='ram,rq,periodic')
    parser.add_argument('--trial', type=int, default=1)
    parser.add_argument('--steps', type=int, default=120)
    args = parser.parse_args()
    if args.mode == 'trace' and args.kind == 'range-bearing':
        parser.error('trace runs RAM, which does not apply to range-bearing')
    fractions = [float(f) for f in args.fractions.split(',')]
    if args.mode == 'sweep':
        sweep(args.kind, fractions, args.trials, args.variance,
              tuple(args.strategies.split(',')))
    else:
        trace(args.kind, fractions[0], args.trial, args.steps)


if __name__ == '__main__':
    main()
