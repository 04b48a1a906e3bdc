"""Monte Carlo study of paper Sec. V: trials x strategies with common random numbers, summaries.

Every (strategy, trial) task is seeded by (seed, trial) alone, so results do not depend on the
number of worker processes or on the order in which tasks finish.
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from scipy.stats import chi2

from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import TrialResult, run_trial
from formopt_ros.core.strategies import STRATEGIES, make_strategy

#: Names of every strategy, in the order of the paper's comparison.
METHODS = tuple(STRATEGIES)
#: Strategy options of the study where they differ from the library defaults: a GBS cell of
#: 0.01 r (the library default is 0.005 r) keeps the study's grid search affordable.
STUDY_OPTIONS: dict[str, dict[str, object]] = {'gbs': {'cell': 0.01}}


@dataclass(frozen=True)
class StudyConfig:
    """What to run: one measurement kind, all listed strategies, ``trials`` x ``steps``.

    Attributes:
        options: strategy name -> options (validated here); strategies not listed use
            :data:`STUDY_OPTIONS`, then the library defaults.
        scenario: overrides of the paper's Sec. V scenario (``Scenario.paper`` keywords, e.g.
            r, sigma, leader), validated here; empty: the paper's settings.
    """

    measurement: str
    trials: int = 50
    steps: int = 600
    seed: int = 0
    strategies: tuple[str, ...] = METHODS
    options: dict[str, dict[str, object]] = field(default_factory=dict)
    scenario: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = [s for s in self.strategies if s not in METHODS]
        if unknown:
            raise ValueError(f'strategies must be among {METHODS}, got unknown {unknown}')
        if self.trials < 1 or self.steps < 1:
            raise ValueError(f'trials and steps must be >= 1, got {self.trials}, {self.steps}')
        if self.seed < 0:
            raise ValueError(f'seed must be >= 0, got {self.seed}')
        merged = {name: dict(STUDY_OPTIONS.get(name, {}), **self.options.get(name, {}))
                  for name in METHODS}
        for name, values in merged.items():
            make_strategy(name, **values)           # ValueError naming a bad option
        object.__setattr__(self, 'options', merged)
        self.make_scenario()                        # ValueError naming a bad override

    def make_scenario(self) -> Scenario:
        """The scenario of this study: the paper's, with the overrides of ``scenario``."""
        return Scenario.paper(self.measurement, **self.scenario)

    def strategy_options(self, strategy: str) -> dict[str, object]:
        """Options of ``strategy`` in this study."""
        return dict(self.options.get(strategy, {}))

    def settings(self, strategy: str) -> dict[str, object]:
        """Every option of ``strategy`` with its value in this study (defaults filled in)."""
        return dict(make_strategy(strategy, **self.strategy_options(strategy)).settings)


@dataclass
class StrategyRecord:
    """All trials of one strategy: arrays of shape (trials, steps) plus trial 0 in full."""

    weighted_trace: np.ndarray
    nees: np.ndarray
    decision_time: np.ndarray
    max_nis: np.ndarray            # (trials,) largest normalised innovation squared
    gated: np.ndarray              # (trials,) updates refused by the innovation gate
    example: TrialResult | None = None


@dataclass
class StudyResult:
    """Results of one measurement kind."""

    config: StudyConfig
    scenario: Scenario
    records: dict[str, StrategyRecord] = field(default_factory=dict)


def _task(args: tuple[StudyConfig, str, int]) -> tuple[str, int, TrialResult]:
    config, strategy, trial = args
    return strategy, trial, run_trial(config.make_scenario(), strategy, config.seed, trial,
                                      config.steps, config.strategy_options(strategy))


def run_study(config: StudyConfig, jobs: int | None = None,
              progress: Callable[[int], None] | None = None) -> StudyResult:
    """Run every (strategy, trial) of ``config``, in ``jobs`` processes (default: all cores).

    Args:
        config: the study.
        jobs: worker processes; 1 runs in this process.
        progress: called with 1 after each finished task.
    """
    jobs = jobs or os.cpu_count() or 1
    scenario = config.make_scenario()
    shape = (config.trials, config.steps)
    result = StudyResult(config, scenario, {
        s: StrategyRecord(np.empty(shape), np.empty(shape), np.empty(shape),
                          np.empty(config.trials), np.zeros(config.trials, dtype=int))
        for s in config.strategies})
    # the slow strategies first, so that the pool's tail is short
    tasks = [(config, s, t) for s in sorted(config.strategies, key=_expected_cost, reverse=True)
             for t in range(config.trials)]
    if jobs == 1:
        outputs = map(_task, tasks)
        _collect(result, outputs, progress)
    else:
        with ProcessPoolExecutor(max_workers=jobs) as pool:
            _collect(result, pool.map(_task, tasks, chunksize=2), progress)
    return result


def _expected_cost(strategy: str) -> int:
    return {'ram': 3, 'gbs': 2, 'rq': 1, 'periodic': 1}.get(strategy, 0)


def _collect(result: StudyResult, outputs: Iterable[tuple[str, int, TrialResult]],
             progress: Callable[[int], None] | None) -> None:
    for strategy, trial, out in outputs:
        record = result.records[strategy]
        record.weighted_trace[trial] = out.weighted_trace
        record.nees[trial] = out.nees
        record.decision_time[trial] = out.decision_time
        record.max_nis[trial] = out.innovation_nis.max()
        record.gated[trial] = out.gated.sum()
        if trial == 0:
            record.example = out
        if progress:
            progress(1)


def nees_band(trials: int, dof: int = 3, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the trial-averaged NEES: chi2(dof * trials) / trials quantiles."""
    tail = 0.5 * (1.0 - confidence)
    lo, hi = chi2.ppf([tail, 1.0 - tail], dof * trials)
    return float(lo / trials), float(hi / trials)


def steady_window(steps: int) -> int:
    """Steps averaged for the steady value: the last 200, or the last third when fewer."""
    return 200 if steps >= 600 else max(1, steps // 3)


def summarize(result: StudyResult) -> dict[str, Any]:
    """The summary.json content (see README): per strategy steady trace, NEES, timing."""
    config = result.config
    lo, hi = nees_band(config.trials)
    window = steady_window(config.steps)
    strategies = {}
    for name, record in result.records.items():
        steady = record.weighted_trace[:, -window:].mean(axis=1)
        mean_nees = record.nees.mean(axis=0)
        strategies[name] = {
            'steady_trace': float(steady.mean()),
            'steady_trace_std': float(steady.std(ddof=1)) if config.trials > 1 else 0.0,
            'mean_trace': float(record.weighted_trace.mean()),
            'nees_mean': float(record.nees.mean()),
            'nees_in_band': float(np.mean((mean_nees >= lo) & (mean_nees <= hi))),
            'decision_time_s': float(record.decision_time.mean()),
            'decision_time_median_s': float(np.median(record.decision_time)),
            'max_innovation_nis': float(record.max_nis.max()),
            'gated_updates': int(record.gated.sum()),
        }
    return {'measurement': config.measurement, 'trials': config.trials, 'steps': config.steps,
            'seed': config.seed, 'gbs_cell': config.settings('gbs')['cell'],
            'scenario': result.scenario.to_dict(),
            'options': {name: config.settings(name) for name in strategies},
            'nees_band': [lo, hi], 'steady_window': window, 'strategies': strategies}
