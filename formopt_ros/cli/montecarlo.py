"""formopt-montecarlo: reproduce the paper's Sec. V study (Figs. 4-6) with every strategy."""
from __future__ import annotations

import argparse
import csv
import os
import sys
import time
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from formopt_ros.cli.common import (
    ArgumentParser, command, fail, integer, name_list, new_folder, number)
from formopt_ros.core.domain import check_domain
from formopt_ros.core.estimator import INNOVATION_GATE
from formopt_ros.core.model import EULER, KINEMATICS, MEASUREMENT_KINDS
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.core.scenario import LeaderPath, Scenario
from formopt_ros.core.simulation import leader_poses
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.core.strategies.baselines import MIN_GBS_CELL
from formopt_ros.core.study import (
    ENGINES, FLAG_RULE, METHODS, STUDY_OPTIONS, StudyConfig, StudyResult, memory_estimate,
    nees_band, run_studies, summarize)
from formopt_ros.wire.jsonfile import write_json

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
    names = tuple(STRATEGIES)                   # the built-in and the plugin strategies
    parser.add_argument('--strategies', type=name_list(names), default=list(METHODS),
                        help=f'comma list among {",".join(names)}, each once (default: the '
                             f'built-in ones, {",".join(METHODS)})')
    parser.add_argument('--jobs', type=integer(1, 256), default=os.cpu_count() or 1,
                        help='worker processes; results do not depend on it (default: all '
                             'cores)')
    parser.add_argument('--gbs-cell', type=number(MIN_GBS_CELL, 1.0),
                        default=STUDY_OPTIONS['gbs']['cell'],
                        help=f'GBS grid spacing as a fraction of r, in [{MIN_GBS_CELL}, 1] '
                             f"(default: {STUDY_OPTIONS['gbs']['cell']}; the library default "
                             'is 0.005)')
    parser.add_argument('--option', type=option_setting, action='append', default=[],
                        metavar='STRATEGY.OPTION=VALUE',
                        help="a strategy's option, e.g. gbs.cell=0.02 or a plugin's; repeat "
                             'for several (values: numbers, true, false)')
    add_scenario_options(parser)
    parser.add_argument('--engine', choices=ENGINES, default='batched',
                        help='batched: all trials of a strategy advanced together (fast); '
                             'per-trial: the reference engine the ROS nodes equal; both give '
                             'the same numbers (default: batched)')
    parser.add_argument('--out', type=new_folder, default=Path('runs/montecarlo'),
                        help='output folder, new or empty; results go to OUT/<measurement>/ '
                             '(default: runs/montecarlo)')
    parser.add_argument('--no-figures', action='store_true',
                        help='skip the PNG figures (faster, no matplotlib needed)')
    parser.add_argument('--allow-inconsistent', action='store_true',
                        help='print the "vs RAM" percentages of strategies flagged inconsistent '
                             f"({FLAG_RULE.replace('%', '%%')}), marked as such; without it "
                             'they are withheld '
                             '(summary.json flags them either way)')
    return parser


def option_setting(text: str) -> tuple[str, str, float | int | bool]:
    """argparse type: 'strategy.option=value' as (strategy, option, value); the value is an
    integer, a number, true or false (the strategy checks its range)."""
    name, _, value = text.partition('=')
    strategy, _, option = name.strip().partition('.')
    if not (strategy and option and value.strip()):
        raise argparse.ArgumentTypeError(f'must be STRATEGY.OPTION=VALUE, e.g. gbs.cell=0.02, '
                                         f'got {text!r}')
    word = value.strip().lower()
    parsed: float | int | bool
    if word in ('true', 'false'):
        parsed = word == 'true'
    else:
        try:
            parsed = int(word)
        except ValueError:
            try:
                parsed = float(word)
            except ValueError:
                raise argparse.ArgumentTypeError(
                    f'{name.strip()}: the value must be a number, true or false, got '
                    f'{value!r}') from None
    return strategy, option.strip(), parsed


def strategy_options(settings: list[tuple[str, str, float | int | bool]],
                     base: dict[str, dict[str, object]] | None = None
                     ) -> dict[str, dict[str, object]]:
    """strategy -> options from ``--option`` settings, over ``base``."""
    options = {name: dict(values) for name, values in (base or {}).items()}
    for strategy, option, value in settings:
        options.setdefault(strategy, {})[option] = value
    return options


def _progress(total: int, label: str):
    """A tqdm bar on an interactive terminal outside CI, else a silent counter."""
    if sys.stderr.isatty() and not os.environ.get('CI'):
        try:
            from tqdm import tqdm
            return tqdm(total=total, desc=label, unit='trial')
        except ImportError:
            pass
    return None


def write_into(folder: Path, figures: bool, result: StudyResult,
               allow_inconsistent: bool = False) -> None:
    """:func:`write_outputs` into folder/<measurement>."""
    write_outputs(result, folder / result.config.measurement, figures, allow_inconsistent)


def write_outputs(result: StudyResult, out: Path, figures: bool,
                  allow_inconsistent: bool = False) -> dict[str, Any]:
    """Write summary.json, steps.csv, report.md and the figures into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(result)
    write_json(out / 'summary.json', summary)
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
    (out / 'report.md').write_text(report_markdown(summary, allow_inconsistent))
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
    shown = [n for n in ('ram', 'gbs', 'mme', 'rq', 'periodic') if n in result.records][:3]
    if 'periodic' in result.records and 'periodic' not in shown:
        shown.append('periodic')
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


def describe_path(path: dict[str, Any]) -> str:
    """'straight at 1 m/s', 'arc at 1 m/s, 0.5 rad/s', ..."""
    text = f"{path['kind']} at {path['speed']:g} m/s"
    if path['kind'] == 'arc':
        text += f", {path['yaw_rate']:g} rad/s"
    elif path['kind'] == 's-curve':
        text += f", {path['amplitude']:g} rad/s peak, period {path['period']:g} s"
    return text


def limits_text(scenario: dict[str, Any]) -> str:
    """', speed limit 1.5 m/s, safety distance 0.3 m' for the limits set, else ''."""
    text = ''
    if scenario.get('max_speed') is not None:
        text += f", speed limit {scenario['max_speed']:g} m/s"
    if scenario.get('safety_distance'):
        text += f", safety distance {scenario['safety_distance']:g} m"
    return text


def report_markdown(summary: dict[str, Any], allow_inconsistent: bool = False) -> str:
    """A short Markdown report with the summary table.

    A strategy flagged inconsistent (``summary['consistency']['flagged']``) is marked in the
    table; its "vs RAM" percentages (and everyone's when RAM is flagged) read 'withheld'
    unless ``allow_inconsistent``, then they are printed followed by '(inconsistent)'.
    """
    lo, hi = summary['nees_band']
    flagged = summary.get('consistency', {}).get('flagged', {})
    scenario = summary['scenario']
    lines = [f"# Monte Carlo, {summary['measurement']}-only",
             '',
             f"{summary['trials']} trials x {summary['steps']} steps, seed {summary['seed']}, "
             f"GBS cell {summary['gbs_cell']} r. Slot {scenario['p_o']} m, r = "
             f"{scenario['r']:.4g} m, sigma = {scenario['sigma']:.4g}, leader "
             f"{describe_path(scenario['leader'])}, {scenario['kinematics']} kinematics"
             f"{limits_text(scenario)}. Steady "
             f"value: mean over the last {summary['steady_window']} steps; mean: over all "
             f'steps; vs RAM: relative difference. NEES band (95 %, 3 dof, trial mean): '
             f'[{lo:.3f}, {hi:.3f}].',
             '',
             '| strategy | steady tr(W P W) [m^2] | vs RAM | std over trials | mean tr(W P W) '
             '[m^2] | vs RAM | mean NEES | steps in NEES band | consistent | decision time '
             'mean / median [ms] | fallbacks |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    ram = summary['strategies'].get('ram')

    def versus(name: str, row: dict[str, float], key: str) -> str:
        if not ram:
            return '-'
        doubtful = name in flagged or 'ram' in flagged
        if doubtful and not allow_inconsistent:
            return 'withheld'
        # rounded first and + 0.0: a difference in the last bits reads '+0.0 %', not '-0.0 %'
        text = f'{round(100 * (row[key] / ram[key] - 1), 1) + 0.0:+.1f} %'
        return text + ' (inconsistent)' if doubtful else text

    for name, row in summary['strategies'].items():
        lines.append(f"| {name.upper()} | {row['steady_trace']:.6g} | "
                     f"{versus(name, row, 'steady_trace')} | {row['steady_trace_std']:.3g} | "
                     f"{row['mean_trace']:.6g} | {versus(name, row, 'mean_trace')} | "
                     f"{row['nees_mean']:.3f} | {100 * row['nees_in_band']:.1f} % | "
                     f"{'FLAGGED' if name in flagged else 'yes'} | "
                     f"{1e3 * row['decision_time_s']:.3f} / "
                     f"{1e3 * row['decision_time_median_s']:.3f} | {row['fallback_steps']} |")
    moving = {name: row for name, row in summary['strategies'].items() if 'mean_speed' in row}
    if moving:
        lines += ['', 'True follower motion (world frame; speed = distance between consecutive '
                  'measurements / 2 dt; distance to the leader at the measurements):', '',
                  '| strategy | mean speed [m/s] | steady mean speed [m/s] | peak speed [m/s] | '
                  'min distance to leader [m] |', '|---|---|---|---|---|']
        lines += [f"| {name.upper()} | {row['mean_speed']:.3f} | {row['steady_mean_speed']:.3f} "
                  f"| {row['peak_speed']:.3f} | {row['min_leader_distance']:.3f} |"
                  for name, row in moving.items()]
    rows = summary['strategies'].values()
    updates = summary['trials'] * summary['steps'] * len(summary['strategies'])
    gated = sum(r['gated_updates'] for r in rows)
    largest = max(r['max_innovation_nis'] for r in rows)
    lines += ['', f'Innovation gate ({INNOVATION_GATE:g}): {gated} of {updates} updates '
              f'refused; largest normalised innovation squared {largest:.3g}.']
    lines += [f'\n{name}: {note}' for name, note in summary.get('notes', {}).items()]
    if flagged:
        lines += ['', f'Flagged inconsistent ({FLAG_RULE}); "vs RAM" of a flagged strategy, '
                  'and of every strategy when RAM is flagged, is '
                  + ("printed but compares an inconsistent filter's covariance:"
                     if allow_inconsistent else 'withheld (--allow-inconsistent prints it):')]
        lines += [f'- {name.upper()}: {reason}' for name, reason in flagged.items()]
    return '\n'.join(lines) + '\n'


def add_scenario_options(parser: ArgumentParser) -> None:
    """--r-fraction, --sigma-scale and the leader path: variants of the paper's scenario."""
    parser.add_argument('--r-fraction', type=number(1e-6, 0.999), default=None,
                        help='allowed deviation r as a fraction of |p_o|, in [1e-6, 0.999] '
                             '(default: the paper, 0.1)')
    parser.add_argument('--sigma-scale', type=number(0.0, 1e6, low_open=True), default=None,
                        help="factor on the paper's range / bearing noise std 0.1 m / 0.02 rad "
                             '(default: 1)')
    parser.add_argument('--kinematics', choices=KINEMATICS, default=EULER,
                        help="motion model of the truth and the EKF: euler (the paper's eq. 9, "
                             'with which its Sec. V simulates; default) or exact (arcs of '
                             'constant velocities, as the ROS nodes run)')
    parser.add_argument('--max-speed', type=number(1e-3, 1e3), default=None,
                        help="bound on the follower's mean world-frame speed over a measurement "
                             'step, m/s: every strategy plans inside the disc it can reach '
                             '(default: none, the paper)')
    parser.add_argument('--safety-distance', type=number(0.0, 1e4), default=None,
                        help='distance every planned point keeps from the leader, m (default: '
                             'none, the paper)')
    paths = parser.add_argument_group('leader path (default: straight at 1 m/s, the paper)')
    paths.add_argument('--leader-path', choices=('straight', 'arc', 's-curve'),
                       default='straight', help='straight, arc (--leader-yaw-rate) or s-curve '
                       '(--leader-amplitude, --leader-period)')
    paths.add_argument('--leader-speed', type=number(-100.0, 100.0), default=1.0,
                       help='leader speed, m/s (default 1)')
    paths.add_argument('--leader-yaw-rate', type=number(-100.0, 100.0), default=0.5,
                       help='arc: yaw rate, rad/s (default 0.5)')
    paths.add_argument('--leader-amplitude', type=number(-100.0, 100.0), default=0.5,
                       help='s-curve: peak yaw rate, rad/s (default 0.5)')
    paths.add_argument('--leader-period', type=number(1e-3, 1e6), default=10.0,
                       help='s-curve: period, s (default 10)')


def leader_path(args: argparse.Namespace) -> LeaderPath:
    """The leader path of the command line."""
    if args.leader_path == 'arc':
        return LeaderPath('arc', args.leader_speed, args.leader_yaw_rate)
    if args.leader_path == 's-curve':
        return LeaderPath('s-curve', args.leader_speed, amplitude=args.leader_amplitude,
                          period=args.leader_period)
    return LeaderPath('straight', args.leader_speed)


def scenario_overrides(kind: str, args: argparse.Namespace) -> dict[str, Any]:
    """Overrides of the paper's scenario of ``kind`` from the options of
    :func:`add_scenario_options` (empty: the paper's)."""
    paper = Scenario.paper(kind)
    overrides: dict[str, Any] = {}
    if args.r_fraction is not None:
        overrides['r'] = args.r_fraction * paper.d_o
    if args.sigma_scale is not None:
        overrides['sigma'] = args.sigma_scale * paper.sigma
    path = leader_path(args)
    if path != paper.leader:
        overrides['leader'] = path
    if args.kinematics != paper.kinematics:
        overrides['kinematics'] = args.kinematics
    if getattr(args, 'max_speed', None) is not None:
        overrides['max_speed'] = args.max_speed
    if getattr(args, 'safety_distance', None):
        overrides['safety_distance'] = args.safety_distance
    return overrides


def physical_memory() -> int:
    """This machine's memory, bytes."""
    return os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES')


@command('formopt-montecarlo')
def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    strategies = tuple(args.strategies)
    kinds = MEASUREMENT_KINDS if args.measurement == 'both' else (args.measurement,)
    start = time.perf_counter()
    try:
        options = strategy_options(args.option, {'gbs': {'cell': args.gbs_cell}})
        configs = [StudyConfig(kind, args.trials, args.steps, args.seed, strategies, options,
                               scenario_overrides(kind, args))
                   for kind in kinds]
        if not args.allow_inconsistent:
            for config in configs:
                check_domain(Scenario.paper(config.measurement, **config.scenario), 'slot',
                             '--r-fraction')
    except ValueError as error:
        fail(parser.prog, f'{error}' + ('' if args.allow_inconsistent else
                                        ' (--allow-inconsistent runs it anyway, flagged)'))
    need, have = memory_estimate(configs), physical_memory()
    if need > have // 2:
        fail(parser.prog, f'--trials {args.trials} x --steps {args.steps}: the study would hold '
                          f'about {need / 2**30:.1f} GiB of records, more than half of the '
                          f"{have / 2**30:.1f} GiB of this machine's memory; lower --trials or "
                          '--steps')
    bar = _progress(args.trials * len(strategies) * len(kinds), ' + '.join(kinds))
    # each kind's outputs (figures take a second) are written as soon as its runs are in
    results = run_studies(configs, args.jobs, bar.update if bar else None, args.engine,
                          partial(write_into, args.out, not args.no_figures,
                                  allow_inconsistent=args.allow_inconsistent))
    if bar:
        bar.close()
    for result in results:
        summary = summarize(result)
        print(report_markdown(summary, args.allow_inconsistent))
        flagged = summary['consistency']['flagged']
        if flagged:
            print(f"{parser.prog}: warning: {result.config.measurement}: "
                  f"{', '.join(n.upper() for n in flagged)} flagged inconsistent (the filter's "
                  'NEES left its band; see report.md)', file=sys.stderr)
    print(f'wall time: {time.perf_counter() - start:.1f} s '
          f'({len(kinds)} kind(s) x {len(strategies)} strategies x {args.trials} trials x '
          f'{args.steps} steps, {args.engine} engine, {args.jobs} jobs); results in {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
