"""formopt-montecarlo: reproduce the paper's Sec. V study (Figs. 4-6) with every strategy."""
from __future__ import annotations

import argparse
import contextlib
import csv
import json
import os
import sys
import time
from collections.abc import Callable, Iterator
from concurrent.futures import CancelledError, Executor
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from formopt_ros.cli.common import (
    ArgumentParser, command, ctrl_c_deferred, fail, integer, name_list, new_folder, number)
from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.domain import check_domain
from formopt_ros.core.estimator import INNOVATION_GATE, INNOVATION_GATE_2
from formopt_ros.core.model import EULER, KINEMATICS, MEASUREMENT_KINDS, RANGE_BEARING, \
    SENSOR_KINDS
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.core.scenario import PATH_FIELDS, RANGES, LeaderPath, Scenario
from formopt_ros.core.simulation import leader_poses
from formopt_ros.core.solver import OutsideTheDisc
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.core.strategies.baselines import MIN_GBS_CELL
from formopt_ros.core.study import (
    ENGINES, FLAG_RULE, METHODS, STUDY_OPTIONS, StudyConfig, StudyResult, memory_estimate,
    nees_band, run_studies, steady_window, summarize)
from formopt_ros.wire.jsonfile import write_json

FIGURE_NAMES = {'range': 'fig5_range_weighted_trace.png',
                'bearing': 'fig6_bearing_weighted_trace.png',
                RANGE_BEARING: 'range_bearing_weighted_trace.png'}
#: Sensor titles of the figures and reports.
TITLES = {'range': 'range-only', 'bearing': 'bearing-only', RANGE_BEARING: 'range+bearing'}
#: The optimiser's runs of the three sensors at one slot: OUT/sensors/ (figure and summary).
COMPARISON_FOLDER = 'sensors'
COMPARISON_STRATEGIES = ('rq', 'periodic')

#: What a refusal of the domain rules adds: the way past them, and what it costs.
ANYWAY = ('--allow-inconsistent runs it anyway; the study then flags each strategy whose '
          'filter is inconsistent')


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(
        prog='formopt-montecarlo',
        description='Monte Carlo reproduction of Sec. V of Zhou, Zhou, Roumeliotis, "Optimized '
                    'Motion Strategies for Localization in Leader-Follower Formations": every '
                    'strategy on the same random numbers, summary.json, per-step CSV, the '
                    "paper's Figs. 4-6 and a NEES plot per measurement kind.")
    parser.add_argument('--measurement', choices=(*MEASUREMENT_KINDS, 'both', RANGE_BEARING,
                                                  'all'), default='both',
                        help='which follower sensor to simulate: both = range and bearing, '
                             'range-bearing = both sensors on one follower (the range '
                             "follower's slot; RAM does not apply and is left out), all = the "
                             'three; with range-bearing, RQ and PERIODIC also run range-only '
                             'and bearing-only at its slot for the sensor comparison in '
                             'OUT/sensors (default: both)')
    parser.add_argument('--bearing-every', type=integer(1, 10**6), default=1,
                        help='range-bearing: the bearing arrives every k-th step, the range '
                             'every step (default: 1)')
    parser.add_argument('--trials', type=integer(1, 100_000), default=50,
                        help='Monte Carlo trials per strategy (default: 50)')
    parser.add_argument('--steps', type=integer(1, 10_000_000), default=600,
                        help='measurement steps per trial, 0.1 s each (default: 600)')
    parser.add_argument('--seed', type=integer(0, 2**63 - 1), default=0,
                        help='seed of all random numbers; trial i uses (seed, i) (default: 0)')
    names = tuple(STRATEGIES)                   # the built-in and the plugin strategies
    parser.add_argument('--strategies', type=name_list(names, STRATEGIES.left_out()),
                        default=list(METHODS),
                        help=f'comma list among {",".join(names)}, each once (default: the '
                             f'built-in ones but lookahead, {",".join(METHODS)})')
    parser.add_argument('--jobs', type=integer(1, 256), default=os.cpu_count() or 1,
                        help='processes of the local Dask cluster the study runs on; 1 runs '
                             'in this process without Dask (unless a scheduler is given); '
                             'results do not depend on it (default: all cores; the commands '
                             'run NumPy on one BLAS thread unless OPENBLAS_NUM_THREADS / '
                             'OMP_NUM_THREADS set a count, which changes last digits)')
    parser.add_argument('--scheduler', default=None, metavar='ADDRESS',
                        help='address of an existing Dask scheduler to run on, e.g. '
                             'tcp://host:8786, --jobs ignored (default: '
                             '$DASK_SCHEDULER_ADDRESS, else a local cluster)')
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
                        help='print the "vs RAM" (or RQ) percentages of strategies flagged '
                             'inconsistent '
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


def progress_bar(total: int, label: str, unit: str = 'trial') -> Any:
    """A tqdm bar on an interactive terminal outside CI, else None."""
    if sys.stderr.isatty() and not os.environ.get('CI'):
        try:
            from tqdm import tqdm
            return tqdm(total=total, desc=label, unit=unit)
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
    title = TITLES[kind]
    figures.trace_figure(time_s, mean_trace, out / FIGURE_NAMES[kind],
                         f'{title}: mean weighted trace over {config.trials} trials')
    figures.nees_figure(time_s, mean_nees, nees_band(config.trials), out / 'nees.png',
                        f'{title}: trial-averaged NEES ({config.trials} trials)')
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
                                  f'{title}, trial 0, first {n} steps')


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

    The percentages compare with RAM, or with RQ (the same greedy optimum, over the reachable
    set under a limit) when RAM was not run. A strategy flagged inconsistent
    (``summary['consistency']['flagged']``) is marked in the table; its percentages (and
    everyone's when the reference is flagged) read 'withheld' unless ``allow_inconsistent``,
    then they are printed followed by '(inconsistent)'.
    """
    lo, hi = summary['nees_band']
    reference = next((n for n in ('ram', 'rq') if n in summary['strategies']), 'ram')
    versus_label = f'vs {reference.upper()}'
    flagged = summary.get('consistency', {}).get('flagged', {})
    growing = summary.get('growing', {})
    scenario = summary['scenario']
    lines = [f"# Monte Carlo, {TITLES.get(summary['measurement'], summary['measurement'])}",
             '',
             f"{summary['trials']} trials x {summary['steps']} steps, seed {summary['seed']}, "
             f"GBS cell {summary['gbs_cell']} r. Slot {scenario['p_o']} m, r = "
             f"{scenario['r']:.4g} m, sigma = {scenario['sigma']:.4g}"
             + (f", sigma_bearing = {scenario['sigma_bearing']:.4g} rad, bearing every "
                f"{scenario['bearing_every']} step(s)" if 'sigma_bearing' in scenario else '')
             + ', leader '
             f"{describe_path(scenario['leader'])}, {scenario['kinematics']} kinematics"
             f"{limits_text(scenario)}. Steady "
             f"value: mean over the last {summary['steady_window']} steps; mean: over all "
             f'steps; {versus_label}: relative difference. NEES band (95 %, 3 dof, trial '
             'mean): '
             f'[{lo:.3f}, {hi:.3f}].',
             '',
             f'| strategy | steady tr(W P W) [m^2] | {versus_label} | std over trials | mean '
             f'tr(W P W) [m^2] | {versus_label} | mean NEES | steps in NEES band | consistent '
             '| decision time '
             'mean / median [ms] | fallbacks |',
             '|---|---|---|---|---|---|---|---|---|---|---|']
    ram = summary['strategies'].get(reference)

    def versus(name: str, row: dict[str, float], key: str) -> str:
        if not ram:
            return '-'
        doubtful = name in flagged or reference in flagged
        if doubtful and not allow_inconsistent:
            return 'withheld'
        # rounded first and + 0.0: a difference in the last bits reads '+0.0 %', not '-0.0 %'
        text = f'{round(100 * (row[key] / ram[key] - 1), 1) + 0.0:+.1f} %'
        return text + ' (inconsistent)' if doubtful else text

    for name, row in summary['strategies'].items():
        lines.append(f"| {name.upper()} | {row['steady_trace']:.6g}"
                     f"{' (grows)' if name in growing else ''} | "
                     f"{versus(name, row, 'steady_trace')} | {row['steady_trace_std']:.3g} | "
                     f"{row['mean_trace']:.6g} | {versus(name, row, 'mean_trace')} | "
                     f"{row['nees_mean']:.3f} | {100 * row['nees_in_band']:.1f} % | "
                     f"{'FLAGGED' if name in flagged else 'yes'} | "
                     f"{1e3 * row['decision_time_s']:.3f} / "
                     f"{1e3 * row['decision_time_median_s']:.3f} | {row['fallback_steps']} |")
    moving = {name: row for name, row in summary['strategies'].items() if 'mean_speed' in row}
    if moving:
        safety = scenario.get('safety_distance', 0.0)
        inside = ' inside the safety distance |' if safety else ''
        lines += ['', 'True follower motion (world frame; speed = distance between consecutive '
                  'measurements / 2 dt; distance to the leader at the measurements'
                  + (f'; the safety distance {safety:g} m bounds the planned points, the true '
                     'follower comes closer by its estimate error' if safety else '') + '):', '',
                  '| strategy | mean speed [m/s] | steady mean speed [m/s] | peak speed [m/s] | '
                  'min distance to leader [m] |' + inside,
                  '|---|---|---|---|---|' + ('---|' if safety else '')]
        lines += [f"| {name.upper()} | {row['mean_speed']:.3f} | {row['steady_mean_speed']:.3f} "
                  f"| {row['peak_speed']:.3f} | {row['min_leader_distance']:.3f} |"
                  + (f" {100 * row['inside_safety_share']:.1f} % of the measurements |"
                     if safety else '')
                  for name, row in moving.items()]
    rows = summary['strategies'].values()
    updates = summary['trials'] * summary['steps'] * len(summary['strategies'])
    gated = sum(r['gated_updates'] for r in rows)
    largest = max(r['max_innovation_nis'] for r in rows)
    gate = f'{INNOVATION_GATE:g}' if summary['measurement'] != RANGE_BEARING else \
        f'2 dof: {INNOVATION_GATE_2:.4g}; 1 dof: {INNOVATION_GATE:g}'
    lines += ['', f'Innovation gate ({gate}): {gated} of {updates} updates '
              f'refused; largest normalised innovation squared {largest:.3g}.']
    lines += [f'\n{name}: {note}' for name, note in summary.get('notes', {}).items()]
    fallbacks = summary['strategies'].get('ram', {}).get('fallback_steps', 0)
    if fallbacks and (scenario.get('max_speed') or scenario.get('safety_distance')):
        decisions = summary['trials'] * summary['steps']
        lines.append(f"\nram: the paper's closed form solves over the whole disc; where its "
                     'point is out of reach or inside the safety distance RAM falls back to RQ '
                     f'over the reachable set: {fallbacks} of {decisions} decisions '
                     f'({100 * fallbacks / decisions:.1f} %)')
    if flagged:
        lines += ['', f'Flagged inconsistent ({FLAG_RULE}); "{versus_label}" of a flagged '
                  f'strategy, and of every strategy when {reference.upper()} is flagged, is '
                  + ("printed but compares an inconsistent filter's covariance:"
                     if allow_inconsistent else 'withheld (--allow-inconsistent prints it):')]
        lines += [f'- {name.upper()}: {reason}' for name, reason in flagged.items()]
    if growing:
        lines += ['', 'No steady state, marked (grows): its "steady" value is where the run '
                  'stopped, not a limit:']
        lines += [f'- {name.upper()}: {reason}' for name, reason in growing.items()]
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
                             "(the paper's protocol rotates, then drives: the driving sub-step "
                             'runs at up to twice this, the rotation is not limited; default: '
                             'none, the paper)')
    parser.add_argument('--safety-distance', type=number(0.0, 1e4), default=None,
                        help='distance every planned point keeps from the leader, m (the true '
                             'follower can come closer by its estimate error; default: none, '
                             'the paper)')
    paths = parser.add_argument_group('leader path (default: straight at 1 m/s, the paper)')
    paths.add_argument('--leader-path', choices=('straight', 'arc', 's-curve'),
                       default='straight', help='straight, arc (--leader-yaw-rate) or s-curve '
                       '(--leader-amplitude, --leader-period)')
    paths.add_argument('--leader-speed', type=number(*RANGES['speed'][:2]), default=1.0,
                       help='leader speed, m/s (default 1)')
    paths.add_argument('--leader-yaw-rate', type=number(*RANGES['yaw_rate'][:2]), default=None,
                       help='arc: yaw rate, rad/s, in [-10, 10] (default 0.5)')
    paths.add_argument('--leader-amplitude', type=number(*RANGES['amplitude'][:2]), default=None,
                       help='s-curve: peak yaw rate, rad/s, in [-10, 10] (default 0.5)')
    paths.add_argument('--leader-period', type=number(*RANGES['period'][:2]), default=None,
                       help='s-curve: period, s (default 10)')


#: The LeaderPath field each leader flag sets, and the flag's default.
PATH_FLAGS = {'leader_yaw_rate': ('yaw_rate', 0.5), 'leader_amplitude': ('amplitude', 0.5),
              'leader_period': ('period', 10.0)}


def leader_path(args: argparse.Namespace) -> LeaderPath:
    """The leader path of the command line; a flag of another kind of path is refused."""
    kind = args.leader_path
    values: dict[str, Any] = {}
    for name, (field, default) in PATH_FLAGS.items():
        value = getattr(args, name)
        if field in PATH_FIELDS[kind]:
            values[field] = default if value is None else value
        elif value is not None:
            flag = '--' + name.replace('_', '-')
            raise InvalidInput(flag, f'is not used with --leader-path {kind}')
    return LeaderPath(kind, args.leader_speed, **values)


#: The scenario fields the scale flags set.
SCALE_FLAGS = {'r': '--r-fraction', 'sigma': '--sigma-scale', 'sigma_bearing': '--sigma-scale'}


def scenario_overrides(kind: str, args: argparse.Namespace) -> dict[str, Any]:
    """Overrides of the paper's scenario of ``kind`` from the options of
    :func:`add_scenario_options` (empty: the paper's)."""
    paper = Scenario.paper(kind)
    overrides: dict[str, Any] = {}
    if args.r_fraction is not None:
        overrides['r'] = args.r_fraction * paper.d_o
    if args.sigma_scale is not None:
        overrides['sigma'] = args.sigma_scale * paper.sigma
        if kind == RANGE_BEARING:
            overrides['sigma_bearing'] = args.sigma_scale * paper.sigma_bearing
    if kind == RANGE_BEARING and getattr(args, 'bearing_every', 1) != 1:
        overrides['bearing_every'] = args.bearing_every
    path = leader_path(args)
    if path != paper.leader:
        overrides['leader'] = path
    if args.kinematics != paper.kinematics:
        overrides['kinematics'] = args.kinematics
    if getattr(args, 'max_speed', None) is not None:
        overrides['max_speed'] = args.max_speed
    if getattr(args, 'safety_distance', None):
        overrides['safety_distance'] = args.safety_distance
    try:
        Scenario.paper(kind, **overrides)
    except InvalidInput as error:       # a scale flag: name the flag, not the field it sets
        flag = SCALE_FLAGS.get(error.name)
        if flag is None:
            raise
        raise InvalidInput(flag, f'{getattr(args, flag[2:].replace("-", "_")):g} is out of '
                                 f"range: the {kind} scenario's {error.name} {error.reason}"
                           ) from None
    return overrides


def kind_strategies(kind: str, strategies: tuple[str, ...]) -> tuple[str, ...]:
    """The strategies a study of ``kind`` runs: all given, but RAM (the paper's scalar method)
    not for range-bearing."""
    if kind != RANGE_BEARING or 'ram' not in strategies:
        return strategies
    rest = tuple(s for s in strategies if s != 'ram')
    if not rest:
        raise InvalidInput('--strategies', "ram does not apply to range-bearing (the paper's "
                                           'method for one scalar measurement): add rq or '
                                           'another strategy')
    print('formopt-montecarlo: note: range-bearing leaves RAM out (the paper\'s method for one '
          'scalar measurement does not apply; RQ solves it with a certificate)')
    return rest


def comparison_configs(configs: list[StudyConfig], strategies: tuple[str, ...]
                       ) -> list[StudyConfig]:
    """For a range-bearing study: range-only and bearing-only studies of the same follower
    (its slot, r, leader, kinematics, each sensor's noise) with the optimiser and PERIODIC
    (those of COMPARISON_STRATEGIES the run has), for the sensor comparison."""
    both = next((c for c in configs if c.measurement == RANGE_BEARING), None)
    chosen = tuple(s for s in COMPARISON_STRATEGIES if s in strategies)
    if both is None or not chosen:
        return []
    scenario = both.make_scenario()
    out = []
    for kind, sigma in (('range', scenario.sigma), ('bearing', scenario.sigma_bearing)):
        overrides = {'p_o': scenario.p_o, 'r': scenario.r, 'sigma': sigma,
                     'leader': scenario.leader, 'kinematics': scenario.kinematics}
        out.append(StudyConfig(kind, both.trials, both.steps, both.seed, chosen, both.options,
                               overrides))
    return out


def write_comparison(out: Path, results: list[StudyResult], figures: bool) -> None:
    """OUT/sensors: summary.json (steady and mean tr(W P W), NEES in band, per sensor and
    strategy) and sensors_weighted_trace.png (mean tr(W P W) over time of each sensor)."""
    out.mkdir(parents=True, exist_ok=True)
    rows: dict[str, Any] = {}
    traces: dict[str, np.ndarray] = {}
    for result in results:
        kind = result.config.measurement
        summary = summarize(result)
        for name in COMPARISON_STRATEGIES:
            if name in summary['strategies']:
                row = summary['strategies'][name]
                rows[f'{TITLES[kind]} {name}'] = {
                    key: row[key] for key in ('steady_trace', 'steady_trace_std', 'mean_trace',
                                              'nees_mean', 'nees_in_band')}
                traces[f'{TITLES[kind]} {name}'] = \
                    result.records[name].weighted_trace.mean(axis=0)
    first = results[0]
    write_json(out / 'summary.json', {
        'trials': first.config.trials, 'steps': first.config.steps, 'seed': first.config.seed,
        'scenario': next(r.scenario.to_dict() for r in results
                         if r.config.measurement == RANGE_BEARING),
        'steady_window': steady_window(first.config.steps), 'runs': rows})
    if figures:
        from formopt_ros.analysis import figures as plots
        time_s = (np.arange(first.config.steps) + 1) * SUBSTEPS * first.scenario.dt
        plots.sensor_figure(time_s, traces, out / 'sensors_weighted_trace.png',
                            f'one follower at {list(first.scenario.p_o)} m, three sensors: '
                            f'mean tr(W P W) over {first.config.trials} trials')


def comparison_lines(folder: Path) -> list[str]:
    """The sensor comparison as printed lines (from OUT/sensors/summary.json)."""
    data = json.loads((folder / 'summary.json').read_text())
    lines = ['', f"# Sensors compared at slot {data['scenario']['p_o']} m (steady: last "
             f"{data['steady_window']} steps)", '',
             '| run | steady tr(W P W) [m^2] | mean tr(W P W) [m^2] | NEES in band |',
             '|---|---|---|---|']
    for name, row in data['runs'].items():
        lines.append(f"| {name} | {row['steady_trace']:.6g} | {row['mean_trace']:.6g} | "
                     f"{100 * row['nees_in_band']:.1f} % |")
    return lines


@contextlib.contextmanager
def study_workers(jobs: int, scheduler: str | None
                  ) -> Iterator[tuple[Executor | None, int, str, Callable[[], bool] | None]]:
    """(executor, number of workers, where, stop) of a study: this process for one job without
    a scheduler, else Dask (:func:`~formopt_ros.analysis.sweep.dask_executor`); without Dask
    installed, a local process pool. A scheduler that cannot be reached ends the command. On
    Dask a Ctrl-C only sets ``stop`` (:func:`~formopt_ros.cli.common.ctrl_c_deferred`): the
    study raises KeyboardInterrupt where it polls it, never inside the client's locking."""
    prog = 'formopt-montecarlo'
    try:
        from formopt_ros.analysis.sweep import dask_executor, scheduler_address
        address = scheduler_address(scheduler)
    except ImportError:
        if scheduler:
            fail(prog, "--scheduler: Dask is not installed: pip install 'dask[distributed]'")
        yield None, jobs, f'{jobs} process(es), no Dask', None
        return
    if jobs == 1 and not address:
        yield None, 1, '1 process', None
        return
    with contextlib.ExitStack() as stack:
        stop = stack.enter_context(ctrl_c_deferred())
        try:
            executor, workers = stack.enter_context(dask_executor(jobs, address))
        except OSError as error:
            fail(prog, f'--scheduler: {error}')
        try:
            yield executor, workers, f'Dask at {address}' if address else \
                f'local Dask cluster of {workers} workers', stop
        except CancelledError:
            fail(prog, 'the Dask cluster dropped the study (its scheduler or its workers '
                       'stopped); the kinds written before are complete')


def physical_memory() -> int:
    """This machine's memory, bytes."""
    return os.sysconf('SC_PAGE_SIZE') * os.sysconf('SC_PHYS_PAGES')


@command('formopt-montecarlo')
def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    strategies = tuple(args.strategies)
    kinds = {'both': MEASUREMENT_KINDS, 'all': SENSOR_KINDS}.get(
        args.measurement, (args.measurement,))
    start = time.perf_counter()
    stray = sorted({name for name, _, _ in args.option} - set(strategies))
    if stray:
        fail(parser.prog, f'argument --option: for strategies the study does not run: {stray} '
                          f'(--strategies {",".join(strategies)})')
    if args.bearing_every != 1 and RANGE_BEARING not in kinds:
        fail(parser.prog, f'argument --bearing-every: for --measurement range-bearing or all, '
                          f'got {args.bearing_every} with --measurement {args.measurement}')
    try:
        options = strategy_options(args.option, {'gbs': {'cell': args.gbs_cell}})
        configs = [StudyConfig(kind, args.trials, args.steps, args.seed,
                               kind_strategies(kind, strategies), options,
                               scenario_overrides(kind, args))
                   for kind in kinds]
        comparison = comparison_configs(configs, strategies)
    except ValueError as error:
        fail(parser.prog, str(error))
    for config in configs if not args.allow_inconsistent else []:
        try:
            check_domain(Scenario.paper(config.measurement, **config.scenario), 'slot',
                         '--r-fraction')
        except ValueError as error:
            fail(parser.prog, f'{config.measurement} follower: {error} ({ANYWAY})')
    need, have = memory_estimate(configs), physical_memory()
    if need > have // 2:
        fail(parser.prog, f'--trials {args.trials} x --steps {args.steps}: the study would hold '
                          f'about {need / 2**30:.1f} GiB of records, more than half of the '
                          f"{have / 2**30:.1f} GiB of this machine's memory; lower --trials or "
                          '--steps')
    bar = progress_bar(args.trials * sum(len(c.strategies) for c in configs + comparison),
                       ' + '.join(kinds))
    with study_workers(args.jobs, args.scheduler) as (executor, workers, where, stop):
        # each kind's outputs (figures take a second) are written as soon as its runs are in,
        # while the workers go on with the other kinds
        try:
            results = run_studies(configs, workers, bar.update if bar else None, args.engine,
                                  partial(write_into, args.out, not args.no_figures,
                                          allow_inconsistent=args.allow_inconsistent),
                                  executor, stop)
            if comparison:
                compared = run_studies(comparison, workers, bar.update if bar else None,
                                       args.engine, executor=executor, stop=stop)
        except OutsideTheDisc as error:             # a plugin's point is never scored
            if bar:
                bar.close()
            print(f'{parser.prog}: error: {error}', file=sys.stderr)
            return 1
    if comparison:
        write_comparison(args.out / COMPARISON_FOLDER, compared + [
            r for r in results if r.config.measurement == RANGE_BEARING],
            not args.no_figures)
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
        if summary['growing']:
            print(f"{parser.prog}: warning: {result.config.measurement}: "
                  f"{', '.join(n.upper() for n in summary['growing'])}: tr(W P W) still "
                  'growing at the end of the run, no steady state (see report.md)',
                  file=sys.stderr)
    for line in comparison_lines(args.out / COMPARISON_FOLDER) if comparison else ():
        print(line)
    print(f'wall time: {time.perf_counter() - start:.1f} s '
          f'({sum(len(c.strategies) for c in configs + comparison)} (sensor, strategy) runs x '
          f'{args.trials} trials x {args.steps} steps, {args.engine} engine, {where}); '
          f'results in {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
