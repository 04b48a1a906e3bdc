"""Monte Carlo study of paper Sec. V: trials x strategies with common random numbers, summaries.

Two engines give the same numbers (a test checks 1e-9; in practice they are identical):
'batched' (default) advances all trials of a strategy together
(:func:`~formopt_ros.core.batched.run_trials`), one task per (measurement, strategy);
'per-trial' runs :func:`~formopt_ros.core.simulation.run_trial`, the reference the ROS nodes
equal, one task per (measurement, strategy, trial). Every trial is seeded by (seed, trial)
alone, so results depend neither on the engine nor on the number or kind of workers (a
process pool here; ``formopt-montecarlo`` passes a Dask executor).
"""
from __future__ import annotations

import multiprocessing
import os
import signal
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field, fields
from collections.abc import Callable
from typing import Any

import numpy as np
from scipy.special import gammaincinv

from formopt_ros.core.batched import run_lanes
from formopt_ros.core.checks import InvalidInput, as_integer
from formopt_ros.core.scenario import Scenario, keep_pace_speed
from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.core.simulation import TrialResult, leader_poses, run_trial
from formopt_ros.core.strategies import BUILTIN, STRATEGIES, make_strategy
from formopt_ros.core.strategies.periodic import describe_design

#: A study's default strategies: the built-in ones in the order of the paper's comparison,
#: but LOOKAHEAD, which costs about 30x RQ per step and runs when named. A study also runs the
#: plugin strategies of ``STRATEGIES`` it names.
METHODS = tuple(name for name in BUILTIN if name != 'lookahead')
#: Strategy options of the study where they differ from the library defaults: a GBS cell of
#: 0.01 r (the library default is 0.005 r) keeps the study's grid search affordable.
STUDY_OPTIONS: dict[str, dict[str, object]] = {'gbs': {'cell': 0.01}}
#: Simulation engines.
ENGINES = ('batched', 'per-trial')
#: Seconds between polls of a study's ``stop`` while its tasks run on an executor.
POLL_S = 0.1
#: A strategy is flagged inconsistent when its trial-mean NEES lies outside the 95 % band
#: (:func:`nees_band`) on more than this share of the steps (a consistent filter: about 5 %;
#: the paper's observable strategies 4-7 %, docs/results.md) ...
MAX_STEPS_OUT_OF_BAND = 0.25
#: ... or when its NEES averaged over all trials and steps lies above the band's upper edge.
FLAG_RULE = (f'the trial-mean NEES outside the 95 % band on more than '
             f'{100 * MAX_STEPS_OUT_OF_BAND:g} % of the steps, or its mean over all trials '
             'and steps above the band')
#: Steps of the EKF's overconfident start from the paper's broad prior (range: NEES about 4).
START_STEPS = 30
#: A trial-mean tr(W P W) over the steady window more than this above the window before: no
#: steady state (relative: a slow growth over a long run can stay below it).
STEADY_GROWTH = 0.1


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
        for name, low in (('trials', 1), ('steps', 1), ('seed', 0)):
            object.__setattr__(self, name, as_integer(name, getattr(self, name), low))
        given = self.strategies
        if not isinstance(given, (list, tuple, np.ndarray)) or np.ndim(given) != 1 or \
                not len(given):
            raise InvalidInput('strategies', 'must be a non-empty list of names among '
                               f'{tuple(STRATEGIES)}, got {given!r}')
        object.__setattr__(self, 'strategies', tuple(map(str, given)))
        unknown = [s for s in self.strategies if s not in STRATEGIES]
        if unknown:
            raise InvalidInput('strategies',
                               f'must be among {tuple(STRATEGIES)}, got unknown {unknown}')
        repeated = [s for i, s in enumerate(self.strategies) if s in self.strategies[:i]]
        if repeated:
            raise InvalidInput('strategies', f'must be named once each, got {repeated} twice')
        if not isinstance(self.options, dict) or not all(
                isinstance(values, dict) and all(isinstance(key, str) for key in values)
                for values in self.options.values()):
            raise InvalidInput('options', 'must map strategy names to dicts of options, e.g. '
                               f"{{'gbs': {{'cell': 0.01}}}}, got {self.options!r}")
        stray = [name for name in self.options if name not in STRATEGIES]
        if stray:
            raise InvalidInput('options', f'are keyed by strategy names among '
                               f'{tuple(STRATEGIES)}, got unknown {stray}')
        named = (*METHODS, *(s for s in (*self.strategies, *self.options) if s not in METHODS))
        merged = {name: dict(STUDY_OPTIONS.get(name, {}), **self.options.get(name, {}))
                  for name in dict.fromkeys(named)}
        for name, values in merged.items():
            make_strategy(name, **values)           # ValueError naming a bad option
        object.__setattr__(self, 'options', merged)
        known = sorted(field.name for field in fields(Scenario) if field.name != 'measurement')
        if not isinstance(self.scenario, dict) or any(
                not isinstance(key, str) or key not in known for key in self.scenario):
            raise InvalidInput('scenario', f'must map overrides among {known} to values, got '
                               f'{self.scenario!r}')
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
    fallback: np.ndarray
    max_nis: np.ndarray            # (trials,) largest normalised innovation squared
    gated: np.ndarray              # (trials,) updates refused by the innovation gate
    example: TrialResult | None = None
    #: (trials, steps - 1) true world-frame speed between consecutive measurements, m/s
    speed: np.ndarray | None = None
    #: (trials,) least true distance to the leader at the measurements, m
    min_distance: np.ndarray | None = None
    #: (trials,) measurements at which the true follower was inside the safety distance
    inside_safety: np.ndarray | None = None


@dataclass
class StudyResult:
    """Results of one measurement kind."""

    config: StudyConfig
    scenario: Scenario
    records: dict[str, StrategyRecord] = field(default_factory=dict)
    notes: dict[str, str] = field(default_factory=dict)   # strategy -> one line (PERIODIC)


#: A unit of work: (config, strategies advanced together, trials).
Task = tuple[StudyConfig, tuple[str, ...], tuple[int, ...]]
#: Rough relative cost of a strategy in the batched engine (to balance the worker processes).
COST = {('bearing', 'ram'): 5.0, ('bearing', 'rq'): 3.3, ('bearing', 'gbs'): 2.5,
        ('bearing', 'periodic'): 6.5, ('range', 'ram'): 3.0, ('range', 'rq'): 1.9,
        ('range', 'gbs'): 2.0, ('range', 'periodic'): 8.5}


#: What a task returns: (config, [(strategy, trial, records)], notes).
Output = tuple[StudyConfig, list[tuple[str, int, TrialResult]], dict[str, str]]


def _task(task: Task) -> Output:
    config, strategies, trials = task
    scenario = config.make_scenario()
    options = {name: config.strategy_options(name) for name in strategies}
    if len(strategies) == 1 and len(trials) == 1:
        name, trial = strategies[0], trials[0]
        runs = [(name, trial, run_trial(scenario, name, config.seed, trial, config.steps,
                                        options[name]))]
    else:
        lanes = run_lanes(scenario, strategies, config.seed, trials, config.steps, options)
        runs = [(name, trial, lanes[name].trial(i)) for name in strategies
                for i, trial in enumerate(trials)]
    # the cycle PERIODIC designed in this worker (cached: no second design)
    notes = {'periodic': describe_design(scenario, options['periodic'])} \
        if 'periodic' in strategies and 0 in trials else {}
    return config, runs, notes


#: Bytes a study holds per (strategy, trial, step): the batched engine's records (estimate,
#: truth, covariance, waypoint, traces, flags: ~190 B) plus the copies returned by the
#: workers, rounded up.
BYTES_PER_STEP = 300


def memory_estimate(configs: list[StudyConfig]) -> int:
    """Bytes the records of these studies take at their peak (an upper estimate)."""
    return sum(BYTES_PER_STEP * c.trials * c.steps * len(c.strategies) for c in configs)


def _cost(config: StudyConfig, strategy: str) -> float:
    return COST.get((config.measurement, strategy), 0.5) * config.trials * config.steps


def _lane_groups(config: StudyConfig, jobs: int) -> list[tuple[str, ...]]:
    """The config's strategies split into at most ``jobs`` groups of similar cost (longest
    first, each to the cheapest group): each group is one stacked run of all trials."""
    groups: list[list[str]] = [[] for _ in range(min(jobs, len(config.strategies)))]
    load = [0.0] * len(groups)
    for name in sorted(config.strategies, key=lambda n: _cost(config, n), reverse=True):
        cheapest = load.index(min(load))
        groups[cheapest].append(name)
        load[cheapest] += _cost(config, name)
    return [tuple(group) for group in groups if group]


def run_study(config: StudyConfig, jobs: int | None = None,
              progress: Callable[[int], None] | None = None,
              engine: str = 'batched', executor: Executor | None = None) -> StudyResult:
    """Run every (strategy, trial) of ``config``; see :func:`run_studies`."""
    return run_studies([config], jobs, progress, engine, executor=executor)[0]


def run_studies(configs: list[StudyConfig], jobs: int | None = None,
                progress: Callable[[int], None] | None = None,
                engine: str = 'batched',
                finish: Callable[[StudyResult], Any] | None = None,
                executor: Executor | None = None,
                stop: Callable[[], bool] | None = None) -> list[StudyResult]:
    """Run every (strategy, trial) of every config, in parallel (default: one process per core).

    Args:
        configs: the studies (e.g. one per measurement kind); their tasks share the workers.
        jobs: parallel workers the tasks are balanced over (default: all cores). Without
            ``executor``, 1 runs in this process and more start a process pool of that size.
            The numbers do not depend on it.
        progress: called with the number of finished (strategy, trial) runs after each task.
        engine: 'batched' (all trials of groups of strategies advanced together, the groups
            balanced over the workers) or 'per-trial' (the reference, one task per trial).
        finish: called in this process on each config's result as soon as it is complete,
            while the workers go on with the other configs (e.g. drawing one kind's figures
            overlaps the other's simulation); it must not change the result.
        executor: where the tasks run, any :class:`concurrent.futures.Executor` (e.g. a Dask
            client's ``get_executor(pure=False)``: ``formopt-montecarlo`` runs on Dask), left
            open; None: see ``jobs``.
        stop: with ``executor``, polled every POLL_S s while the tasks run; True cancels the
            unfinished tasks and raises KeyboardInterrupt (a Ctrl-C recorded by the caller).
    """
    if engine not in ENGINES:
        raise ValueError(f'engine must be one of {ENGINES}, got {engine!r}')
    jobs = jobs or os.cpu_count() or 1
    results = []
    tasks: list[tuple[float, Task]] = []
    for config in configs:
        shape = (config.trials, config.steps)
        results.append(StudyResult(config, config.make_scenario(), {
            s: StrategyRecord(np.empty(shape), np.empty(shape), np.empty(shape),
                              np.zeros(shape, dtype=bool), np.empty(config.trials),
                              np.zeros(config.trials, dtype=int))
            for s in config.strategies}))
        every = tuple(range(config.trials))
        if engine == 'batched':
            tasks.extend((sum(_cost(config, s) for s in group), (config, group, every))
                         for group in _lane_groups(config, jobs))
        else:
            tasks.extend((_cost(config, s) / config.trials, (config, (s,), (t,)))
                         for s in config.strategies for t in every)
    # the slow tasks first, so that the workers' tail is short
    ordered = [task for _, task in sorted(tasks, key=lambda item: item[0], reverse=True)]
    pending = {id(result): sum(1 for task in ordered if task[0] == result.config)
               for result in results}

    def collect(output: Output) -> None:
        done = _collect(results, output, progress, pending)
        if done is not None and finish is not None:
            finish(done)

    if executor is not None:
        _run_on({executor.submit(_task, task) for task in ordered}, collect, stop)
    elif jobs == 1 or len(ordered) == 1:
        for task in ordered:
            collect(_task(task))
    else:
        with ProcessPoolExecutor(max_workers=min(jobs, len(ordered))) as pool:
            try:
                # the workers, forked while tasks are submitted, ignore SIGINT from birth:
                # Ctrl-C reaches the whole process group, only this process handles it (and
                # ends the workers, which print no traceback each)
                previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
                try:
                    futures = {pool.submit(_task, task) for task in ordered}
                finally:
                    signal.signal(signal.SIGINT, previous)
                _run_on(futures, collect)
            except KeyboardInterrupt:
                pool.shutdown(wait=False, cancel_futures=True)
                for worker in multiprocessing.active_children():   # the pool's workers
                    worker.terminate()
                raise
    return results


def _run_on(futures: set[Future[Output]], collect: Callable[[Output], None],
            stop: Callable[[], bool] | None = None) -> None:
    """Collect each task's output as it comes; on any exception (Ctrl-C included) the
    unfinished tasks are cancelled; ``stop`` (polled every POLL_S s) raises KeyboardInterrupt
    when it returns True."""
    try:
        while futures:
            complete, futures = wait(futures, None if stop is None else POLL_S,
                                     FIRST_COMPLETED)
            if stop is not None and stop():
                raise KeyboardInterrupt
            for future in complete:
                collect(future.result())
    except BaseException:
        for future in futures:
            future.cancel()
        raise


def _collect(results: list[StudyResult],
             output: Output, progress: Callable[[int], None] | None,
             pending: dict[int, int]) -> StudyResult | None:
    """Store one task's runs; the config's result once its last task is in, else None."""
    config, runs, notes = output
    # configs come back pickled from worker processes: match them by value
    result = next(r for r in results if r.config == config)
    result.notes.update(notes)
    for strategy, trial, out in runs:
        record = result.records[strategy]
        record.weighted_trace[trial] = out.weighted_trace
        record.nees[trial] = out.nees
        record.decision_time[trial] = out.decision_time
        record.max_nis[trial] = out.innovation_nis.max()
        record.gated[trial] = out.gated.sum()
        if out.fallback is not None:
            record.fallback[trial] = out.fallback
        speed, distance = follower_motion(result.scenario, out.truth)
        if record.speed is None:
            record.speed = np.full((config.trials, len(speed)), np.nan)
            record.min_distance = np.full(config.trials, np.nan)
            record.inside_safety = np.zeros(config.trials, dtype=int)
        assert record.min_distance is not None and record.inside_safety is not None
        record.speed[trial], record.min_distance[trial] = speed, distance.min()
        record.inside_safety[trial] = np.count_nonzero(
            distance < result.scenario.safety_distance)
        if trial == 0:
            record.example = out
    if progress:
        progress(len(runs))
    pending[id(result)] -= 1
    return result if pending[id(result)] == 0 else None


def follower_motion(scenario: Scenario, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(speed (steps - 1,), m/s; distance to the leader (steps,), m) of a true follower track
    ``truth`` (steps, 3) (poses in the leader frame at each measurement): the world positions
    are the leader's pose (:func:`~.simulation.leader_poses`, dead reckoning of its path)
    composed with the relative position, and the speed is the distance between consecutive
    ones over the measurement step's 2 dt (the world-frame mean speed over the step)."""
    leader = leader_poses(scenario, len(truth))
    c, s = np.cos(leader[:, 2]), np.sin(leader[:, 2])
    world = leader[:, :2] + np.stack([c * truth[:, 0] - s * truth[:, 1],
                                      s * truth[:, 0] + c * truth[:, 1]], axis=1)
    step = SUBSTEPS * scenario.dt
    return (np.hypot(*np.diff(world, axis=0).T) / step,
            np.hypot(truth[:, 0], truth[:, 1]))


def nees_band(trials: int, dof: int = 3, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band of the trial-averaged NEES: chi2(dof * trials) / trials quantiles."""
    tail = 0.5 * (1.0 - confidence)
    # chi2.ppf(q, k) = 2 gammaincinv(k / 2, q); scipy.special loads 0.6 s faster than stats
    lo, hi = 2.0 * gammaincinv(0.5 * dof * trials, [tail, 1.0 - tail])
    return float(lo / trials), float(hi / trials)


def steady_window(steps: int) -> int:
    """Steps averaged for the steady value: the last 200, or the last third when fewer."""
    return 200 if steps >= 600 else max(1, steps // 3)


def summarize(result: StudyResult) -> dict[str, Any]:
    """The summary.json content (docs/results.md): per strategy steady trace, NEES, timing and the
    number of (trial, step) decisions on which the strategy fell back (RAM to RQ)."""
    config = result.config
    lo, hi = nees_band(config.trials)
    window = steady_window(config.steps)
    growth = growth_window(result.scenario, window)
    strategies = {}
    for name, record in result.records.items():
        steady = record.weighted_trace[:, -window:].mean(axis=1)
        mean_nees = record.nees.mean(axis=0)
        out_of_band = (mean_nees < lo) | (mean_nees > hi)
        later = out_of_band[START_STEPS:]
        strategies[name] = {
            'steady_trace': float(steady.mean()),
            'steady_trace_std': float(steady.std(ddof=1)) if config.trials > 1 else 0.0,
            'steady_growth': steady_growth(record.weighted_trace, growth),
            'mean_trace': float(record.weighted_trace.mean()),
            'nees_mean': float(record.nees.mean()),
            'nees_in_band': float(1.0 - out_of_band.mean()),
            'nees_out_of_band_steps': int(out_of_band.sum()),
            'nees_out_of_band_at_start': int(out_of_band[:START_STEPS].sum()),
            'nees_in_band_after_start': float(1.0 - later.mean()) if later.size else 1.0,
            'decision_time_s': float(record.decision_time.mean()),
            'decision_time_median_s': float(np.median(record.decision_time)),
            'max_innovation_nis': float(record.max_nis.max()),
            'gated_updates': int(record.gated.sum()),
            'fallback_steps': int(record.fallback.sum()),
            **_motion_summary(record, window),
        }
    flagged = {name: reason + fallback_note(result.scenario, row, config.trials * config.steps)
               for name, row in strategies.items() if (reason := inconsistency(row, (lo, hi)))}
    growing = {name: f"its tr(W P W) is {100 * row['steady_growth']:.0f} % higher over the "
                     f'last {growth} steps than over the {growth} before: no steady state (its '
                     'covariance grows; a longer run grows further)'
               for name, row in strategies.items() if row['steady_growth'] > STEADY_GROWTH}
    return {'measurement': config.measurement, 'trials': config.trials, 'steps': config.steps,
            'seed': config.seed, 'gbs_cell': config.settings('gbs')['cell'],
            'scenario': result.scenario.to_dict(),
            'options': {name: config.settings(name) for name in strategies},
            'nees_band': [lo, hi], 'steady_window': window, 'strategies': strategies,
            'notes': dict(result.notes), 'ok': not flagged,
            'consistency': {'rule': FLAG_RULE, 'flagged': flagged}, 'growing': growing}


def growth_window(scenario: Scenario, window: int) -> int:
    """Steps compared by :func:`steady_growth`: the steady ``window``, or behind a leader whose
    motion repeats (an S-curve, repeated segments) the whole periods that fit in it (at least
    one): the trace follows the path's phase, and windows of other lengths hold other phases."""
    path = scenario.leader
    duration = path.period if path.kind == 's-curve' and path.amplitude != 0.0 else \
        sum(piece.duration for piece in path.segments) if path.repeat else None
    period = None if duration is None else duration / (SUBSTEPS * scenario.dt)
    return window if period is None else max(1, round(max(1, window // period) * period))


def steady_growth(weighted_trace: np.ndarray, window: int) -> float:
    """The trial-mean tr(W P W) (``weighted_trace``: trials x steps) over the last ``window``
    steps relative to the ``window`` steps before, minus 1 (0.0 when the run is shorter than
    two windows)."""
    trace = weighted_trace.mean(axis=0)
    if trace.size < 2 * window:
        return 0.0
    return float(trace[-window:].mean() / trace[-2 * window:-window].mean() - 1.0)


def fallback_note(scenario: Scenario, row: dict[str, Any], decisions: int) -> str:
    """What a flagged strategy's fallbacks say under a speed limit ('' without a limit or
    fallbacks): the share of its ``decisions`` on which it fell back, and the margin of the
    limit above :func:`~.scenario.keep_pace_speed`. Just above that speed
    the follower rides the disc's edge and a bearing filter can lose consistency
    (docs/lookahead.md)."""
    if scenario.max_speed is None or not row['fallback_steps']:
        return ''
    need = keep_pace_speed(scenario)
    return (f'; under the speed limit {scenario.max_speed:g} m/s, '
            f'{scenario.max_speed - need:.3g} m/s above the {need:.4g} m/s at which the slot\'s '
            f"disc keeps pace with the leader, it fell back on "
            f"{100 * row['fallback_steps'] / decisions:.1f} % of its steps: a higher limit "
            'gives the filter room (docs/lookahead.md)')


def _motion_summary(record: StrategyRecord, window: int) -> dict[str, float]:
    """Mean, steady mean and peak true follower speed (m/s), the least distance to the
    leader (m) and the share of measurements at which the true follower was inside the safety
    distance (which bounds the planned point, not the follower) of a record
    (:func:`follower_motion`); empty without tracks."""
    if record.speed is None or record.min_distance is None or not record.speed.size:
        return {}
    assert record.inside_safety is not None
    return {'mean_speed': float(np.nanmean(record.speed)),
            'steady_mean_speed': float(np.nanmean(record.speed[:, -window:])),
            'peak_speed': float(np.nanmax(record.speed)),
            'min_leader_distance': float(np.nanmin(record.min_distance)),
            'inside_safety_share': float(record.inside_safety.sum()
                                         / (record.speed.shape[0] * (record.speed.shape[1] + 1)))}


def inconsistency(row: dict[str, Any], band: tuple[float, float]) -> str:
    """Why a strategy's summary row (:func:`summarize`) is flagged inconsistent
    (:data:`FLAG_RULE`), or '' when it is not."""
    lo, hi = band
    out = 1.0 - row['nees_in_band']
    reasons = []
    if out > MAX_STEPS_OUT_OF_BAND:
        reasons.append(f'trial-mean NEES outside the 95 % band [{lo:.3g}, {hi:.3g}] on '
                       f'{100 * out:.1f} % of the steps (more than '
                       f'{100 * MAX_STEPS_OUT_OF_BAND:g} %)')
    if not row['nees_mean'] <= hi:
        reasons.append(f"mean NEES {row['nees_mean']:.4g} above the band's upper edge "
                       f'{hi:.3g}')
    start = row.get('nees_out_of_band_at_start', 0)
    if reasons and start and start >= 0.5 * row['nees_out_of_band_steps'] and \
            1.0 - row['nees_in_band_after_start'] <= MAX_STEPS_OUT_OF_BAND:
        reasons.append(f"{start} of its {row['nees_out_of_band_steps']} steps out of the band "
                       f'are among the first '
                       f'{START_STEPS}: the filter\'s start from the broad initial prior, '
                       'overconfident until its estimate settles; a longer run judges the '
                       'strategy')
    return '; '.join(reasons)
