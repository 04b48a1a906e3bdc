"""formopt-montecarlo: reproduce the paper's Sec. V study (Figs. 4-6) with every strategy."""
from __future__ import annotations

import csv
import json
import os
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from formopt_ros.cli.common import ArgumentParser, fail, integer, new_folder, number
from formopt_ros.core.model import MEASUREMENT_KINDS
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.core.simulation import leader_poses
from formopt_ros.core.strategies.baselines import MIN_GBS_CELL
from formopt_ros.core.study import (
    ENGINES, METHODS, STUDY_OPTIONS, StudyConfig, StudyResult, nees_band, run_studies,
    summarize)

FIGURE_NAMES = {'range': 'fig5_range_weighted_trace.png',
                'bearing': 'fig6_bearing_weighted_trace.png'}


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(
        prog='formopt-montecarlo',
        description='Monte Carlo reproduction of Sec. V of Zhou, Zhou, Roumeliotis, "Optimized '
                    'Motion Strategies for Localization in Leader-Follower Formations": every '
                    'strategy on the same random numbers, summary.json, per-step CSV, the '
                    "paper's Figs. 4-6 and a NEES plot per measurement kind.")
    parser.add_argument('--measurement', choices=(*MEASUREMENT_KINDS, 'both'), default='both',
                        help='which follower sensor to simulate (default: both)')
    parser.add_argument('--trials', type=integer(1, 100_000), default=50,
                        help='Monte Carlo trials per strategy (default: 50)')
    parser.add_argument('--steps', type=integer(1, 10_000_000), default=600,
                        help='measurement steps per trial, 0.1 s each (default: 600)')
    parser.add_argument('--seed', type=integer(0, 2**63 - 1), default=0,
                        help='seed of all random numbers; trial i uses (seed, i) (default: 0)')
    parser.add_argument('--strategies', default=','.join(METHODS),
                        help=f'comma list among {",".join(METHODS)} (default: all six)')
    parser.add_argument('--jobs', type=integer(1, 256), default=os.cpu_count() or 1,
                        help='worker processes; results do not depend on it (default: all '
                             'cores)')
    parser.add_argument('--gbs-cell', type=number(MIN_GBS_CELL, 1.0),
                        default=STUDY_OPTIONS['gbs']['cell'],
                        help=f'GBS grid spacing as a fraction of r, in [{MIN_GBS_CELL}, 1] '
                             f"(default: {STUDY_OPTIONS['gbs']['cell']}; the library default "
                             'is 0.005)')
    parser.add_argument('--engine', choices=ENGINES, default='batched',
                        help='batched: all trials of a strategy advanced together (fast); '
                             'per-trial: the reference engine the ROS nodes equal; both give '
                             'the same numbers (default: batched)')
    parser.add_argument('--out', type=new_folder, default=Path('runs/montecarlo'),
                        help='output folder, new or empty; results go to OUT/<measurement>/ '
                             '(default: runs/montecarlo)')
    parser.add_argument('--no-figures', action='store_true',
                        help='skip the PNG figures (faster, no matplotlib needed)')
    return parser


def _progress(total: int, label: str):
    """A tqdm bar on an interactive terminal outside CI, else a silent counter."""
    if sys.stderr.isatty() and not os.environ.get('CI'):
        try:
            from tqdm import tqdm
            return tqdm(total=total, desc=label, unit='trial')
        except ImportError:
            pass
    return None


def write_into(folder: Path, figures: bool, result: StudyResult) -> None:
    """:func:`write_outputs` into folder/<measurement>."""
    write_outputs(result, folder / result.config.measurement, figures)


def write_outputs(result: StudyResult, out: Path, figures: bool) -> dict[str, Any]:
    """Write summary.json, steps.csv, report.md and the figures into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(result)
    (out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
    config, scenario = result.config, result.scenario
    time_s = (np.arange(config.steps) + 1) * SUBSTEPS * scenario.dt
    mean_trace = {n: r.weighted_trace.mean(axis=0) for n, r in result.records.items()}
    mean_nees = {n: r.nees.mean(axis=0) for n, r in result.records.items()}
    with open(out / 'steps.csv', 'w', newline='') as handle:
        writer = csv.writer(handle)
        names = list(result.records)
        writer.writerow(['step', 'time_s'] + [f'{n}_weighted_trace' for n in names]
                        + [f'{n}_nees' for n in names])
        for k in range(config.steps):
            writer.writerow([k + 1, f'{time_s[k]:.2f}']
                            + [f'{mean_trace[n][k]:.9g}' for n in names]
                            + [f'{mean_nees[n][k]:.6g}' for n in names])
    (out / 'report.md').write_text(report_markdown(summary))
    if figures:
        _figures(result, out, time_s, mean_trace, mean_nees)
    return summary


def _figures(result: StudyResult, out: Path, time_s: np.ndarray, mean_trace: dict,
             mean_nees: dict) -> None:
    from formopt_ros.analysis import figures
    config, scenario = result.config, result.scenario
    kind = config.measurement
    figures.trace_figure(time_s, mean_trace, out / FIGURE_NAMES[kind],
                         f'{kind}-only: mean weighted trace over {config.trials} trials')
    figures.nees_figure(time_s, mean_nees, nees_band(config.trials), out / 'nees.png',
                        f'{kind}-only: trial-averaged NEES ({config.trials} trials)')
    shown = [n for n in ('ram', 'gbs', 'mme', 'rq') if n in result.records][:3]
    n = min(config.steps, 40)
    leader = leader_poses(scenario, n)
    panels = {}
    for name in shown:
        example = result.records[name].example
        if example is None:
            continue
        panels[name.upper()] = {'leader': leader, 'followers': [{
            'label': f'{kind} follower', 'strategy': name, 'estimate': example.estimate[:n],
            'covariance': example.covariance[:n], 'truth': example.truth[:n],
            'waypoints': example.waypoints[:n], 'p_o': scenario.slot, 'r': scenario.r}]}
    if panels:
        figures.trajectory_figure(panels, out / 'fig4_trajectories.png',
                                  f'{kind}-only, trial 0, first {n} steps')


def report_markdown(summary: dict[str, Any]) -> str:
    """A short Markdown report with the summary table."""
    lo, hi = summary['nees_band']
    lines = [f"# Monte Carlo, {summary['measurement']}-only",
             '',
             f"{summary['trials']} trials x {summary['steps']} steps, seed {summary['seed']}, "
             f"GBS cell {summary['gbs_cell']} r. Steady value: mean over the last "
             f"{summary['steady_window']} steps. NEES band (95 %, 3 dof, trial mean): "
             f'[{lo:.3f}, {hi:.3f}].',
             '',
             '| strategy | steady tr(W P W) [m^2] | std over trials | mean NEES | '
             'steps in NEES band | decision time [ms] | fallbacks |',
             '|---|---|---|---|---|---|---|']
    for name, row in summary['strategies'].items():
        lines.append(f"| {name.upper()} | {row['steady_trace']:.6g} | "
                     f"{row['steady_trace_std']:.3g} | {row['nees_mean']:.3f} | "
                     f"{100 * row['nees_in_band']:.1f} % | "
                     f"{1e3 * row['decision_time_s']:.3f} | {row['fallback_steps']} |")
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    strategies = tuple(s.strip() for s in args.strategies.split(',') if s.strip())
    kinds = MEASUREMENT_KINDS if args.measurement == 'both' else (args.measurement,)
    start = time.perf_counter()
    try:
        configs = [StudyConfig(kind, args.trials, args.steps, args.seed, strategies,
                               {'gbs': {'cell': args.gbs_cell}}) for kind in kinds]
    except ValueError as error:
        fail(parser.prog, f'--strategies: {error}')
    bar = _progress(args.trials * len(strategies) * len(kinds), ' + '.join(kinds))
    # each kind's outputs (figures take a second) are written as soon as its runs are in
    results = run_studies(configs, args.jobs, bar.update if bar else None, args.engine,
                          partial(write_into, args.out, not args.no_figures))
    if bar:
        bar.close()
    for result in results:
        print(report_markdown(summarize(result)))
    print(f'wall time: {time.perf_counter() - start:.1f} s '
          f'({len(kinds)} kind(s) x {len(strategies)} strategies x {args.trials} trials x '
          f'{args.steps} steps, {args.engine} engine, {args.jobs} jobs); results in {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
