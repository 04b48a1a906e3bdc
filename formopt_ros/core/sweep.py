"""Scenario sweeps: a grid or a list of scenarios x strategies, each cell one seeded study.

A sweep point gives a value to every axis of :data:`AXES` (the paper's Sec. V scenario where
not swept); a cell is a point, a strategy with its options, and the trials, steps and seed.
:func:`run_cell` runs a cell through the study engine (:func:`~formopt_ros.core.study.run_study`,
batched, in the calling process) and returns its row of the tidy table; a cell's numbers
depend on the cell alone, never on where or with what else it runs. :func:`cell_key` names a
cell by its content and the versions of the code that computes it, so a finished cell can be
reused.
"""
from __future__ import annotations

import hashlib
import itertools
import json
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from formopt_ros.core.checks import InvalidInput, as_choice, as_real
from formopt_ros.core.model import KINEMATICS, MEASUREMENT_KINDS
from formopt_ros.core.scenario import PATH_FIELDS, LeaderPath, Scenario
from formopt_ros.core.strategies import STRATEGIES, make_strategy
from formopt_ros.core.study import StudyConfig, run_study, summarize

#: Axis -> value where a sweep does not set it (the paper's Sec. V scenario).
DEFAULTS: dict[str, Any] = {
    'measurement': 'range',       # the follower's sensor: 'range' or 'bearing'
    'r_fraction': 0.1,            # allowed deviation r as a fraction of |p_o|
    'sigma_scale': 1.0,           # factor on the paper's 0.1 m / 0.02 rad measurement noise
    'odometry_scale': 1.0,        # factor on the follower's odometry noise 0.2 m/s, 0.1 rad/s
    'leader_path': 'straight',    # 'straight', 'arc' or 's-curve'
    'leader_speed': 1.0,          # m/s
    'leader_yaw_rate': 0.5,       # rad/s: the arc's yaw rate, the s-curve's peak
    'leader_period': 10.0,        # s: the s-curve's period
    'dt': 0.05,                   # sub-step length, s
    'kinematics': 'euler',        # the paper's eq. (9), as the study
    'max_speed': 0.0,             # m/s: the follower's speed limit (0: none, the paper)
    'safety_distance': 0.0,       # m: kept by every planned point from the leader
}
#: The scenario fields the scale axes set.
SCALE_AXES = {'r': 'r_fraction', 'sigma': 'sigma_scale', 'sigma_v': 'odometry_scale',
              'sigma_omega': 'odometry_scale'}
#: The LeaderPath fields each leader axis sets (leader_yaw_rate: an arc's yaw rate or an
#: s-curve's peak).
PATH_AXES = {'leader_yaw_rate': ('yaw_rate', 'amplitude'), 'leader_period': ('period',)}
#: The axes of a sweep, in the order of the table's columns.
AXES = tuple(DEFAULTS)
#: Axes whose values are names (the others are numbers).
NAMED_AXES = {'measurement': MEASUREMENT_KINDS, 'leader_path': ('straight', 'arc', 's-curve'),
              'kinematics': KINEMATICS}
#: Columns of a row after the axes: what :func:`run_cell` measures (decision times are the
#: only wall-clock figures; every other column depends on the cell alone).
RESULT_COLUMNS = ('strategy', 'options', 'trials', 'steps', 'seed', 'steady_trace',
                  'steady_trace_std', 'steady_growth', 'steady', 'mean_trace', 'nees_mean',
                  'nees_in_band', 'nees_band_low', 'nees_band_high', 'consistent', 'flag_reason',
                  'max_innovation_nis', 'gated_updates', 'fallback_steps',
                  'decision_time_ms', 'decision_time_median_ms')
#: Columns :func:`with_gains` adds: relative to RAM at the same point, and the winner there.
GAIN_COLUMNS = ('gain_over_ram_pct', 'mean_gain_over_ram_pct', 'best_at_point')
#: Steady traces within this relative difference of the least at a point tie (RAM and RQ find
#: the same optimum, to 1e-14 per step and about 2e-9 after 200 steps; the table prints 0.1 %).
TIE_TOLERANCE = 1e-6
#: Columns that hold wall-clock time (excluded when comparing runs).
TIMING_COLUMNS = ('decision_time_ms', 'decision_time_median_ms')

Point = dict[str, Any]


def check_point(point: Point) -> Point:
    """Every axis of ``point`` (defaults filled in), checked: InvalidInput naming a bad axis
    value, ValueError naming unknown axes."""
    unknown = sorted(set(point) - set(AXES))
    if unknown:
        raise ValueError(f'unknown sweep axes {unknown} (the axes: {", ".join(AXES)})')
    full = {**DEFAULTS, **point}
    for axis in AXES:
        full[axis] = as_choice(axis, full[axis], NAMED_AXES[axis]) if axis in NAMED_AXES \
            else as_real(axis, full[axis])
    used = PATH_FIELDS[full['leader_path']]
    stray = [axis for axis, fields in PATH_AXES.items()
             if not set(fields) & set(used) and full[axis] != DEFAULTS[axis]]
    if stray:
        raise InvalidInput(stray[0], f"is not used by leader_path {full['leader_path']!r} "
                                     '(arc: leader_yaw_rate; s-curve: leader_yaw_rate, '
                                     'leader_period)')
    try:
        scenario_of(full)
    except InvalidInput as error:       # a scale axis: name the axis, not the field it sets
        scale = SCALE_AXES.get(error.name)
        if scale is None:
            raise
        raise InvalidInput(scale, f"{full[scale]:g} is out of range: the scenario's "
                                  f'{error.name} {error.reason}') from None
    return full


def leader_of(point: Point) -> LeaderPath:
    """The leader path of a (checked) point."""
    kind, speed, turn = point['leader_path'], point['leader_speed'], point['leader_yaw_rate']
    if kind == 'arc':
        return LeaderPath('arc', speed, turn)
    if kind == 's-curve':
        return LeaderPath('s-curve', speed, amplitude=turn, period=point['leader_period'])
    return LeaderPath('straight', speed)


def overrides_of(point: Point) -> dict[str, Any]:
    """The overrides of the paper's scenario (``Scenario.paper`` keywords) of a point."""
    paper = Scenario.paper(point['measurement'])
    return {'r': point['r_fraction'] * paper.d_o, 'sigma': point['sigma_scale'] * paper.sigma,
            'sigma_v': point['odometry_scale'] * paper.sigma_v,
            'sigma_omega': point['odometry_scale'] * paper.sigma_omega,
            'leader': leader_of(point), 'dt': point['dt'], 'kinematics': point['kinematics'],
            'max_speed': point['max_speed'] or None, 'safety_distance': point['safety_distance']}


def scenario_of(point: Point) -> Scenario:
    """The scenario of a point (axes not given: :data:`DEFAULTS`)."""
    full = {**DEFAULTS, **point}
    return Scenario.paper(full['measurement'], **overrides_of(full))


def expand(grid: dict[str, Sequence[Any]] | None = None,
           scenarios: Iterable[Point] = (), base: Point | None = None) -> list[Point]:
    """The points of a sweep: every combination of the ``grid``'s values (its axes in
    :data:`AXES` order, each axis's values in the order given), then each listed scenario;
    all over ``base``; a point given twice is kept once. ValueError naming a bad axis or
    value."""
    base = dict(base or {})
    points: list[Point] = []
    if grid:
        axes = [axis for axis in AXES if axis in grid]
        unknown = sorted(set(grid) - set(AXES))
        if unknown:
            raise ValueError(f'unknown sweep axes {unknown} (the axes: {", ".join(AXES)})')
        for axis in axes:
            values = grid[axis]
            if isinstance(values, (str, bytes)) or not isinstance(values, Sequence) or \
                    not values:
                raise ValueError(f'grid axis {axis} must be a non-empty list of values, got '
                                 f'{values!r}')
        for combination in itertools.product(*(grid[axis] for axis in axes)):
            points.append(check_point({**base, **dict(zip(axes, combination))}))
    for index, scenario in enumerate(scenarios):
        if not isinstance(scenario, dict):
            raise ValueError(f'scenario {index + 1} must be a mapping of axes to values, got '
                             f'{scenario!r}')
        try:
            points.append(check_point({**base, **scenario}))
        except ValueError as error:
            raise ValueError(f'scenario {index + 1}: {error}') from None
    if not grid and not points:
        points.append(check_point(base))
    unique: dict[str, Point] = {}
    for point in points:
        unique.setdefault(json.dumps(point, sort_keys=True), point)
    return list(unique.values())


@dataclass(frozen=True)
class Cell:
    """One (scenario, strategy) of a sweep.

    Attributes:
        point: every axis's value (:func:`check_point`), as sorted (axis, value) pairs.
        strategy: strategy name (built-in or plugin); options: its options as given.
        trials, steps, seed: the study of the cell (trial i uses the streams (seed, i), as
            ``formopt-montecarlo``: the strategies of one point share their random numbers).
    """

    point: tuple[tuple[str, Any], ...]
    strategy: str
    options: tuple[tuple[str, Any], ...]
    trials: int
    steps: int
    seed: int

    @classmethod
    def make(cls, point: Point, strategy: str, options: dict[str, Any] | None, trials: int,
             steps: int, seed: int) -> 'Cell':
        """A cell; ValueError for an unknown strategy or a bad option or study size."""
        cell = cls(tuple(sorted(check_point(point).items())), strategy,
                   tuple(sorted((options or {}).items())), trials, steps, seed)
        cell.config()
        return cell

    @property
    def values(self) -> Point:
        """The point as a dict, axes in :data:`AXES` order."""
        given = dict(self.point)
        return {axis: given[axis] for axis in AXES}

    def config(self) -> StudyConfig:
        """The study of this cell (one strategy)."""
        return StudyConfig(self.values['measurement'], self.trials, self.steps, self.seed,
                           (self.strategy,), {self.strategy: dict(self.options)},
                           overrides_of(self.values))

    def settings(self) -> dict[str, Any]:
        """Every option of the strategy with its value in this cell (defaults filled in)."""
        return dict(make_strategy(self.strategy, **self.config().strategy_options(
            self.strategy)).settings)


def cell_key(cell: Cell, versions: str) -> str:
    """A name for the cell's result: a hash of its scenario, strategy, options with their
    defaults, trials, steps, seed and ``versions`` (of this package and of the strategy's
    distribution), so that a changed input or code never reuses an old result."""
    content = {'scenario': scenario_of(cell.values).to_dict(), 'strategy': cell.strategy,
               'settings': cell.settings(), 'trials': cell.trials, 'steps': cell.steps,
               'seed': cell.seed, 'versions': versions}
    text = json.dumps(content, sort_keys=True, separators=(',', ':'))
    return f'{cell.strategy}-{hashlib.sha256(text.encode()).hexdigest()[:24]}'


def run_cell(cell: Cell) -> dict[str, Any]:
    """The cell's row: its axes, strategy, study size and the study's summary figures (steady
    and whole-run tr(W P W) in m^2, NEES, the consistency flag of
    :func:`~formopt_ros.core.study.summarize`, decision times in ms)."""
    config = cell.config()
    summary = summarize(run_study(config, jobs=1))
    row = summary['strategies'][cell.strategy]
    lo, hi = summary['nees_band']
    reason = summary['consistency']['flagged'].get(cell.strategy, '')
    return {**cell.values, 'strategy': cell.strategy,
            'options': json.dumps(summary['options'][cell.strategy], sort_keys=True),
            'trials': cell.trials, 'steps': cell.steps, 'seed': cell.seed,
            'steady_trace': row['steady_trace'], 'steady_trace_std': row['steady_trace_std'],
            'steady_growth': row['steady_growth'],
            'steady': cell.strategy not in summary['growing'],
            'mean_trace': row['mean_trace'], 'nees_mean': row['nees_mean'],
            'nees_in_band': row['nees_in_band'], 'nees_band_low': lo, 'nees_band_high': hi,
            'consistent': not reason, 'flag_reason': reason,
            'max_innovation_nis': row['max_innovation_nis'],
            'gated_updates': row['gated_updates'], 'fallback_steps': row['fallback_steps'],
            'decision_time_ms': 1e3 * row['decision_time_s'],
            'decision_time_median_ms': 1e3 * row['decision_time_median_s']}


def with_gains(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows with :data:`GAIN_COLUMNS`: 100 (1 - x / x_RAM) for the steady and the
    whole-run weighted trace (positive: lower than RAM's at that point; None where the point
    has no RAM row) and the strategy with the lowest steady trace among the consistent ones
    and steady (:data:`~formopt_ros.core.study.STEADY_GROWTH`) at the point (ties within
    TIE_TOLERANCE: their names joined by '=', e.g. 'ram=rq', which count as a win for none;
    '' when none is)."""
    by_point: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        by_point.setdefault(point_label(row), []).append(row)
    out = []
    for row in rows:
        peers = by_point[point_label(row)]
        ram = next((r for r in peers if r['strategy'] == 'ram'), None)
        consistent = [r for r in peers if r['consistent'] and r.get('steady', True)]
        least = min((r['steady_trace'] for r in consistent), default=0.0)
        best = '='.join(r['strategy'] for r in consistent
                        if r['steady_trace'] <= least * (1.0 + TIE_TOLERANCE))
        out.append({**row,
                    'gain_over_ram_pct': None if ram is None else
                    100.0 * (1.0 - row['steady_trace'] / ram['steady_trace']),
                    'mean_gain_over_ram_pct': None if ram is None else
                    100.0 * (1.0 - row['mean_trace'] / ram['mean_trace']),
                    'best_at_point': best})
    return out


def point_label(row: dict[str, Any]) -> str:
    """A row's point (its axes) as one canonical string."""
    return json.dumps({axis: row[axis] for axis in AXES}, sort_keys=True)


def strategy_names() -> tuple[str, ...]:
    """Every strategy a sweep may name (built-in and plugins)."""
    return tuple(STRATEGIES)


__all__ = ['AXES', 'Cell', 'DEFAULTS', 'GAIN_COLUMNS', 'RESULT_COLUMNS', 'TIMING_COLUMNS',
           'cell_key', 'check_point', 'expand', 'run_cell', 'scenario_of', 'with_gains']
