"""formopt-sweep: a grid or a list of scenarios x strategies on Dask, one tidy table, heat maps."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from formopt_ros.cli.common import (
    INTERRUPTED_EXIT, ArgumentParser, command, ctrl_c_deferred, fail, integer, name_list)
from formopt_ros.cli.montecarlo import ANYWAY, option_setting, progress_bar, strategy_options
from formopt_ros.core.domain import check_domain
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.core.sweep import AXES, NAMED_AXES, Cell, expand, scenario_of
from formopt_ros.wire.formation import read_yaml
from formopt_ros.wire.jsonfile import json_safe, write_json

#: Keys of a sweep file (docs/sweeps.md).
FILE_KEYS = ('grid', 'scenarios', 'base', 'strategies', 'options', 'trials', 'steps', 'seed',
             'heatmap')
#: Default strategies: the paper's analytic method and two baselines of its comparison.
DEFAULT_STRATEGIES = ('ram', 'rq', 'crm')
#: Marker of a sweep's output folder (a folder with it may be written again: a resume).
MARKER = 'sweep.json'


def axis_values(axis: str) -> Callable[[str], list[Any]]:
    """argparse type: a comma list of an axis's values (names or finite numbers)."""
    def parse(text: str) -> list[Any]:
        words = [word.strip() for word in text.split(',')]
        if not all(words):
            raise argparse.ArgumentTypeError(f'must be a comma list of values, got {text!r}')
        if axis in NAMED_AXES:
            bad = [word for word in words if word not in NAMED_AXES[axis]]
            if bad:
                raise argparse.ArgumentTypeError(
                    f'{", ".join(bad)}: the values are {", ".join(NAMED_AXES[axis])}')
            return words
        try:
            values = [float(word) for word in words]
        except ValueError:
            raise argparse.ArgumentTypeError(f'must be a comma list of numbers, got '
                                             f'{text!r}') from None
        if not all(math.isfinite(v) for v in values):
            raise argparse.ArgumentTypeError(f'must be finite numbers, got {text!r}')
        return values
    return parse


def sweep_folder(text: str) -> Path:
    """argparse type: an output folder that is new, empty, or an earlier sweep's (resumed)."""
    path = Path(text)
    if path.exists() and (not path.is_dir() or (any(path.iterdir())
                                                and not (path / MARKER).is_file())):
        raise argparse.ArgumentTypeError(f'{text} exists and is neither empty nor a sweep\'s '
                                         f'folder (no {MARKER}); refusing to write into it')
    return path


def refuse_another_sweep(prog: str, out: Path, spec: dict[str, Any]) -> None:
    """Stop (exit 2) when ``out`` holds an earlier sweep of other settings than ``spec`` (the
    heat-map axes aside): resuming writes over its table; only its own command resumes it."""
    marker = out / MARKER
    if not marker.is_file():
        return
    try:
        earlier = json.loads(marker.read_text()).get('sweep') or {}
    except (OSError, ValueError, AttributeError):
        earlier = {}
    now = json.loads(json.dumps(json_safe(spec)))
    changed = sorted(key for key in set(earlier) | set(now)
                     if key != 'heatmap' and earlier.get(key) != now.get(key))
    if changed:
        fail(prog, f'{out} holds another sweep ({marker}: its {", ".join(changed)} '
                   f'differ{"s" * (len(changed) == 1)}): run its own command to resume it, or '
                   f'choose another --out (with --cache {out / "cells"} to reuse its finished '
                   'cells)')


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(
        prog='formopt-sweep',
        description='Run a grid (or a list) of scenarios x strategies, each cell a seeded '
                    'Monte Carlo study, on Dask (a local cluster by default, or an existing '
                    'one with --scheduler): one tidy table (sweep.csv), heat maps of each '
                    "strategy's gain over RAM and of where each strategy wins. Finished cells "
                    'are cached: a re-run (after Ctrl-C, say) computes only the others.')
    parser.add_argument('--config', metavar='FILE', default=None,
                        help='a sweep file (YAML; docs/sweeps.md): grid, scenarios, base, '
                             'strategies, options, trials, steps, seed, heatmap; flags given '
                             'here override it')
    names = tuple(STRATEGIES)
    parser.add_argument('--strategies', type=name_list(names, STRATEGIES.left_out()), default=None,
                        help=f'comma list among {",".join(names)} (default: '
                             f'{",".join(DEFAULT_STRATEGIES)})')
    parser.add_argument('--option', type=option_setting, action='append', default=[],
                        metavar='STRATEGY.OPTION=VALUE',
                        help="a strategy's option, e.g. gbs.cell=0.02; repeat for several")
    axes = parser.add_argument_group('axes (comma lists; each listed axis is a grid axis; '
                                     "unlisted axes keep the paper's value)")
    helps = {'measurement': 'follower sensor: range, bearing', 'r_fraction': 'allowed '
             'deviation r / |p_o| (paper 0.1)', 'sigma_scale': 'factor on the measurement '
             'noise (paper 0.1 m, 0.02 rad)', 'odometry_scale': "factor on the follower's "
             'odometry noise (0.2 m/s, 0.1 rad/s)', 'leader_path': 'straight, arc, s-curve',
             'leader_speed': 'm/s (1)', 'leader_yaw_rate': 'rad/s: arc yaw rate, s-curve '
             'peak (0.5)', 'leader_period': 's-curve period, s (10)', 'dt': 'sub-step length, '
             's (0.05)', 'kinematics': 'euler (the paper, default) or exact',
             'max_speed': "the follower's speed limit, m/s (0: none, the paper; see "
             'formopt-montecarlo --max-speed)', 'safety_distance': 'distance every planned '
             'point keeps from the leader, m (0)'}
    for axis in AXES:
        axes.add_argument(f'--{axis.replace("_", "-")}', dest=axis, type=axis_values(axis),
                          default=None, metavar='VALUES', help=helps[axis])
    parser.add_argument('--trials', type=integer(1, 100_000), default=None,
                        help='Monte Carlo trials per cell (default: 10)')
    parser.add_argument('--steps', type=integer(1, 10_000_000), default=None,
                        help='measurement steps per trial (default: 300)')
    parser.add_argument('--seed', type=integer(0, 2**63 - 1), default=None,
                        help='seed of every cell; trial i uses (seed, i) (default: 0)')
    parser.add_argument('--heatmap', type=lambda text: [t.strip() for t in text.split(',')],
                        default=None, metavar='X,Y',
                        help='the two axes of the heat maps (default: the first two swept)')
    parser.add_argument('--workers', type=integer(1, 1024), default=None,
                        help='processes of the local Dask cluster (default: one per core); '
                             'results do not depend on it')
    parser.add_argument('--scheduler', default=None, metavar='ADDRESS',
                        help='address of an existing Dask scheduler, e.g. tcp://host:8786 '
                             '(default: $DASK_SCHEDULER_ADDRESS, else a local cluster)')
    parser.add_argument('--out', type=sweep_folder, default=Path('runs/sweep'),
                        help='output folder: new, empty, or the same sweep\'s (a resume: its '
                             'cached cells are reused) (default: runs/sweep)')
    parser.add_argument('--cache', type=Path, default=None,
                        help='folder of finished cells, may be shared by sweeps (default: '
                             'OUT/cells)')
    parser.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    parser.add_argument('--allow-inconsistent', action='store_true',
                        help='run scenarios the consistency rules refuse (a bearing disc too '
                             'close to the leader); their rows are flagged')
    return parser


def load_file(path: str) -> dict[str, Any]:
    """A sweep file's content, checked for unknown keys; ValueError naming the file."""
    data = read_yaml(path, 'sweep') or {}
    if not isinstance(data, dict):
        raise ValueError(f'{path}: a sweep file is a mapping with keys among '
                         f'{", ".join(FILE_KEYS)}')
    unknown = sorted(set(data) - set(FILE_KEYS))
    if unknown:
        raise ValueError(f'{path}: unknown keys {unknown} (known: {", ".join(FILE_KEYS)})')
    return data


def sweep_spec(args: argparse.Namespace) -> dict[str, Any]:
    """The sweep of the file and the flags (flags win): grid, scenarios, base, strategies,
    options, trials, steps, seed, heatmap."""
    spec = load_file(args.config) if args.config else {}
    grid = dict(spec.get('grid') or {})
    for axis in AXES:
        if getattr(args, axis) is not None:
            grid[axis] = getattr(args, axis)
    options = strategy_options(args.option, spec.get('options') or {})
    return {'grid': grid, 'scenarios': list(spec.get('scenarios') or []),
            'base': dict(spec.get('base') or {}),
            'strategies': list(args.strategies or spec.get('strategies')
                               or DEFAULT_STRATEGIES),
            'options': options,
            'trials': args.trials or spec.get('trials', 10),
            'steps': args.steps or spec.get('steps', 300),
            'seed': args.seed if args.seed is not None else spec.get('seed', 0),
            'heatmap': args.heatmap or spec.get('heatmap')}


def make_cells(spec: dict[str, Any], allow_inconsistent: bool) -> list[Cell]:
    """The cells of a sweep spec, points first then strategies; ValueError naming what is
    wrong."""
    unknown = [name for name in spec['strategies'] if name not in STRATEGIES]
    if unknown:
        raise ValueError(f'unknown strategies {unknown} (the strategies: '
                         f'{", ".join(STRATEGIES)})')
    stray = [name for name in spec['options'] if name not in spec['strategies']]
    if stray:
        raise ValueError(f'options for strategies not in the sweep: {stray}')
    points = expand(spec['grid'], spec['scenarios'], spec['base'])
    if not allow_inconsistent:
        for point in points:
            try:
                check_domain(scenario_of(point), 'slot', 'r_fraction')
            except ValueError as error:
                raise ValueError(f'scenario {json.dumps(point)}: {error} ({ANYWAY})') from None
    return [Cell.make(point, name, spec['options'].get(name), spec['trials'], spec['steps'],
                      spec['seed']) for point in points for name in spec['strategies']]


def heatmap_axes(spec: dict[str, Any], rows: list[dict[str, Any]]) -> tuple[str, str] | None:
    """The heat maps' (x, y) axes: the spec's, else the first two swept axes; None when fewer
    than two axes vary."""
    from formopt_ros.analysis.sweep import swept_axes
    chosen = spec['heatmap']
    if chosen:
        return chosen[0], chosen[1]
    swept = swept_axes(rows)
    return (swept[0], swept[1]) if len(swept) >= 2 else None


@command('formopt-sweep')
def main(argv: list[str] | None = None) -> int:
    """Entry point; returns the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        spec = sweep_spec(args)
        if spec['heatmap'] is not None and (len(spec['heatmap']) != 2 or any(
                axis not in AXES for axis in spec['heatmap'])):
            raise ValueError(f'heatmap must name two axes among {", ".join(AXES)}, got '
                             f'{spec["heatmap"]}')
        cells = make_cells(spec, args.allow_inconsistent)
    except (TypeError, ValueError) as error:
        fail(parser.prog, str(error))
    try:
        import dask  # noqa: F401  (the engine of the sweep)
    except ImportError:
        fail(parser.prog, "Dask is not installed: pip install 'dask[distributed]' (or the "
                          'package extra [sweep])')
    from formopt_ros.analysis.sweep import (
        CellCache, package_version, run_cells, scheduler_address, sweep_figures, table_rows,
        write_table)
    out: Path = args.out
    refuse_another_sweep(parser.prog, out, spec)
    cache = CellCache(args.cache or out / 'cells')
    out.mkdir(parents=True, exist_ok=True)
    address = scheduler_address(args.scheduler)
    write_json(out / MARKER, {'sweep': spec, 'cells': len(cells), 'version': package_version(),
                              'scheduler': address or f'local, {args.workers or os.cpu_count()}'
                              ' workers'})
    start = time.perf_counter()
    bar = progress_bar(len(cells), 'cells', 'cell')
    try:
        with ctrl_c_deferred() as stop:
            outcome = run_cells(cells, cache, args.workers, address,
                                bar.update if bar else None, stop=stop)
    except (KeyboardInterrupt, ConnectionError) as error:
        if bar:
            bar.close()
        kept = sum(1 for cell in cells if cache.get(_key(cell)) is not None)
        kept_text = (f'{kept} of {len(cells)} cells are finished and kept in {cache.folder}: '
                     'run the same command again to compute only the others')
        if isinstance(error, KeyboardInterrupt):
            print(f'{parser.prog}: interrupted; {kept_text}', file=sys.stderr)
            return INTERRUPTED_EXIT
        fail(parser.prog, f"{'--scheduler: ' if address else ''}{error}; {kept_text}")
    if bar:
        bar.close()
    rows = table_rows(outcome.rows)
    write_table(rows, out / 'sweep.csv')
    figures: list[Path] = []
    axes = heatmap_axes(spec, rows)
    if not args.no_figures and axes and rows:
        figures = sweep_figures(rows, axes[0], axes[1], out / 'figures')
    print(summary_text(rows))
    workers = args.workers or os.cpu_count() or 1
    where = ('' if not outcome.computed and not outcome.failures else
             f" on {address or f'a local cluster of {workers} worker' + 's' * (workers > 1)}")
    print(f'{len(cells)} cells ({len(outcome.computed)} computed, {len(outcome.reused)} '
          f'reused from {cache.folder}) in {time.perf_counter() - start:.1f} s{where}; '
          f'table {out / "sweep.csv"}' + (f', {len(figures)} figures in {out / "figures"}'
                                          if figures else ''))
    if not args.no_figures and rows and 'ram' not in spec['strategies']:
        print(f'{parser.prog}: no figures: they show each strategy\'s gain over RAM; add ram '
              'to the strategies', file=sys.stderr)
    for key, message in outcome.failures.items():
        print(f'{parser.prog}: error: cell {key} failed: {message}', file=sys.stderr)
    return 1 if outcome.failures else 0


def _key(cell: Cell) -> str:
    from formopt_ros.analysis.sweep import versions_of
    from formopt_ros.core.sweep import cell_key
    return cell_key(cell, versions_of(cell.strategy))


def _signed(value: float) -> str:
    """'+1.2' or '-1.2'; a difference in the last bits reads '+0.0', not '-0.0'."""
    return f'{round(value, 1) + 0.0:+.1f}'


def summary_text(rows: list[dict[str, Any]]) -> str:
    """Per strategy: points won, mean and range of the steady gain over RAM, flagged cells."""
    points = len({json.dumps({a: r[a] for a in AXES}) for r in rows})
    lines = [f'{points} scenarios; gain over RAM: 100 (1 - steady tr(W P W) / RAM\'s), > 0 is '
             'lower', '', '| strategy | scenarios won | mean gain over RAM | min / max | '
             'flagged |', '|---|---|---|---|---|']
    for name in dict.fromkeys(row['strategy'] for row in rows):
        mine = [row for row in rows if row['strategy'] == name]
        won = sum(1 for row in mine if row['best_at_point'] == name)
        gains = [row['gain_over_ram_pct'] for row in mine if row['gain_over_ram_pct'] is not None]
        flagged = sum(1 for row in mine if not row['consistent'])
        spread = f'{_signed(min(gains))} / {_signed(max(gains))} %' if gains else '-'
        mean = f'{_signed(sum(gains) / len(gains))} %' if gains else '-'
        lines.append(f'| {name.upper()} | {won} | {mean} | {spread} | {flagged} |')
    return '\n'.join(lines)


if __name__ == '__main__':
    sys.exit(main())
