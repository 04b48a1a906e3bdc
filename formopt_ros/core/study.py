"""Monte Carlo study of paper Sec. V: trials x strategies with common random numbers, summaries.

Two engines give the same numbers (a test checks 1e-9; in practice they are identical):
'batched' (default) advances all trials of a strategy together
(:func:`~formopt_ros.core.batched.run_trials`), one task per (measurement, strategy);
'per-trial' runs :func:`~formopt_ros.core.simulation.run_trial`, the reference the ROS nodes
equal, one task per (measurement, strategy, trial). Every trial is seeded by (seed, trial)
alone, so results depend neither on the engine nor on the number of worker processes.
"""
from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np
from scipy.stats import chi2

from formopt_ros.core.batched import run_trials
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import TrialResult, run_trial
from formopt_ros.core.strategies import STRATEGIES, make_strategy

#: Names of every strategy, in the order of the paper's comparison.
METHODS = tuple(STRATEGIES)
#: Strategy options of the study where they differ from the library defaults: a GBS cell of
#: 0.01 r (the library default is 0.005 r) keeps the study's grid search affordable.
STUDY_OPTIONS: dict[str, dict[str, object]] = {'gbs': {'cell': 0.01}}
#: Simulation engines.
ENGINES = ('batched', 'per-trial')


@dataclass(frozen=True)
class StudyConfig:
    """What to run: one measurement kind, all listed strategies, ``trials`` x ``steps``.

    Attributes:
        options: strategy name -> options (validated here); strategies not listed use
            :data:`STUDY_OPTIONS`, then the library defaults.
    """

    measurement: str
    trials: int = 50
    steps: int = 600
    seed: int = 0
    strategies: tuple[str, ...] = METHODS
    options: dict[str, dict[str, object]] = field(default_factory=dict)

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
    fallback: np.ndarray
    example: TrialResult | None = None


@dataclass
class StudyResult:
    """Results of one measurement kind."""

    config: StudyConfig
    scenario: Scenario
    records: dict[str, StrategyRecord] = field(default_factory=dict)


#: A unit of work: (config, strategy, trials).
Task = tuple[StudyConfig, str, tuple[int, ...]]


def _task(task: Task) -> tuple[StudyConfig, str, list[tuple[int, TrialResult]]]:
    config, strategy, trials = task
    scenario = Scenario.paper(config.measurement)
    options = config.strategy_options(strategy)
    if len(trials) == 1:
        return config, strategy, [(trials[0], run_trial(scenario, strategy, config.seed,
                                                        trials[0], config.steps, options))]
    batch = run_trials(scenario, strategy, config.seed, trials, config.steps, options)
    return config, strategy, [(trial, batch.trial(i)) for i, trial in enumerate(trials)]


def run_study(config: StudyConfig, jobs: int | None = None,
              progress: Callable[[int], None] | None = None,
              engine: str = 'batched') -> StudyResult:
    """Run every (strategy, trial) of ``config``; see :func:`run_studies`."""
    return run_studies([config], jobs, progress, engine)[0]


def run_studies(configs: list[StudyConfig], jobs: int | None = None,
                progress: Callable[[int], None] | None = None,
                engine: str = 'batched') -> list[StudyResult]:
    """Run every (strategy, trial) of every config, in ``jobs`` processes (default: all cores).

    Args:
        configs: the studies (e.g. one per measurement kind); their tasks share one pool.
        jobs: worker processes; 1 runs in this process. The numbers do not depend on it.
        progress: called with the number of trials after each finished task.
        engine: 'batched' (all trials of a strategy together) or 'per-trial' (the reference).
    """
    if engine not in ENGINES:
        raise ValueError(f'engine must be one of {ENGINES}, got {engine!r}')
    jobs = jobs or os.cpu_count() or 1
    results = []
    tasks: list[Task] = []
    for config in configs:
        shape = (config.trials, config.steps)
        results.append(StudyResult(config, Scenario.paper(config.measurement), {
            s: StrategyRecord(np.empty(shape), np.empty(shape), np.empty(shape),
                              np.zeros(shape, dtype=bool)) for s in config.strategies}))
        groups = ([tuple(range(config.trials))] if engine == 'batched'
                  else [(t,) for t in range(config.trials)])
        tasks.extend((config, s, trials) for s in config.strategies for trials in groups)
    # the slow tasks first, so that the pool's tail is short
    tasks.sort(key=lambda task: _expected_cost(task[0].measurement, task[1]), reverse=True)
    by_config = {id(config): result for config, result in zip(configs, results)}
    if jobs == 1 or len(tasks) == 1:
        _collect(by_config, map(_task, tasks), progress)
    else:
        with ProcessPoolExecutor(max_workers=min(jobs, len(tasks))) as pool:
            _collect(by_config, pool.map(_task, tasks, chunksize=1), progress)
    return results


def _expected_cost(measurement: str, strategy: str) -> int:
    return {'ram': 4 if measurement == 'bearing' else 2, 'gbs': 3, 'rq': 2}.get(strategy, 0)


def _collect(by_config: dict[int, StudyResult],
             outputs: Iterable[tuple[StudyConfig, str, list[tuple[int, TrialResult]]]],
             progress: Callable[[int], None] | None) -> None:
    results = list(by_config.values())
    for config, strategy, trials in outputs:
        # configs come back pickled from worker processes: match them by value
        result = by_config.get(id(config)) or next(r for r in results if r.config == config)
        record = result.records[strategy]
        for trial, out in trials:
            record.weighted_trace[trial] = out.weighted_trace
            record.nees[trial] = out.nees
            record.decision_time[trial] = out.decision_time
            if out.fallback is not None:
                record.fallback[trial] = out.fallback
            if trial == 0:
                record.example = out
        if progress:
            progress(len(trials))


def nees_band(trials: int, dof: int = 3, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the trial-averaged NEES: chi2(dof * trials) / trials quantiles."""
    tail = 0.5 * (1.0 - confidence)
    lo, hi = chi2.ppf([tail, 1.0 - tail], dof * trials)
    return float(lo / trials), float(hi / trials)


def steady_window(steps: int) -> int:
    """Steps averaged for the steady value: the last 200, or the last third when fewer."""
    return 200 if steps >= 600 else max(1, steps // 3)


def summarize(result: StudyResult) -> dict[str, Any]:
    """The summary.json content (see README): per strategy steady trace, NEES, timing and the
    number of (trial, step) decisions on which the strategy fell back (RAM to RQ)."""
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
            'nees_mean': float(record.nees.mean()),
            'nees_in_band': float(np.mean((mean_nees >= lo) & (mean_nees <= hi))),
            'decision_time_s': float(record.decision_time.mean()),
            'fallback_steps': int(record.fallback.sum()),
        }
    return {'measurement': config.measurement, 'trials': config.trials, 'steps': config.steps,
            'seed': config.seed, 'gbs_cell': config.settings('gbs')['cell'],
            'options': {name: config.settings(name) for name in strategies},
            'nees_band': [lo, hi], 'steady_window': window, 'strategies': strategies}
