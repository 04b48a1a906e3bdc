"""formopt-bench: time the planners and the general-purpose peers on seeded random problems.

For each measurement kind the command draws ``--problems`` moderate random problems (prior
covariance with condition number up to 1e4 and overall scale 1e-4..1, slot distance
0.5-10 m in a random direction, allowed deviation r = 5-30 % of the slot distance, noise
0.01-0.5 m for range or 0.002-0.1 rad for bearing, both for range-bearing). Each problem's
reference is the certified RQ optimum (every one must carry a proof; the table header says how
many do); for range-bearing RQ is the level test on lines through the leader of
:mod:`~formopt_ros.core.strategies.polar` (RAM does not apply, rq-batch and the peers are
not offered for it: their rows are skipped).

Methods:

* ram, rq, mtf, crm, mme and the plugin strategies (docs/plugins.md): ``solve(...)`` (input
  validation included; crm and the plugins get a generator seeded 0);
* rq-loop: RQ as the simulator and the nodes call it each step, on a ``Problem`` built without
  validation (they validate their setting once per run);
* rq-batch: RQ on ``--batch-size`` problems per call (default: all the problems of a kind in
  one call), as the batched Monte Carlo engine calls it each step with its trials
  (:func:`~formopt_ros.core.strategies.rq.rq_batch`, stacking the arrays included, on a
  ``ProblemBatch`` built without validation, as the engine builds it); a
  problem's time is its call's time divided by the problems in the call (the time per problem
  falls with the batch size: the call has a fixed numpy cost);
* gbs: one-off grid search at cell 0.005 r on a new geometry (the grid cache is cleared before
  each call, so building the grid is included); gbs-cached: the same call again, grid reused;
* peers (:mod:`formopt_ros.analysis.peers`): slsqp (SciPy SLSQP from p_o, default options),
  slsqp-8 (8 starts), and with CasADi installed (``pip install .[peers]``) ipopt (from p_o,
  IPOPT defaults), ipopt-tuned (tightened tolerances) and ipopt-8 (tuned, 8 starts); the
  peers' times include building the validated Problem.

Every call is timed with ``time.perf_counter``; the best of ``--repeats`` calls (peers:
``--peer-repeats``) is kept per problem and method, and the methods are interleaved problem by
problem so that machine load affects them alike. The table reports per kind and method: median
and 99th-percentile time (microseconds), the speed-up over one-off and cached GBS (median over
problems of the time ratio), how often the method missed the certified optimum (cost above it
by more than 1e-9 relative), the largest relative excess, on how many problems the method
found a cost below the reference's proved lower bound (its cost times 1 - its certificate gap,
less 1e-9: that would contradict a certificate, and the count shows it instead of hiding it;
an unproved reference's bound is its cost),
and how often RAM fell back to RQ.
"""
from __future__ import annotations

import csv
import math
import os
import platform
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import numpy as np

from formopt_ros.analysis.peers import casadi_available, peer_methods
from formopt_ros.cli.common import ArgumentParser, command, integer, name_list, new_file
from formopt_ros.core import METHODS, STRATEGIES, Problem, solve
from formopt_ros.core.solver import DEFAULT_CONTEXT
from formopt_ros.core.strategies import baselines
from formopt_ros.core.cost import ProblemBatch
from formopt_ros.core.strategies.rq import RayleighQuotient, rq_batch
from formopt_ros.core.strategies.certificate import PROVED
from formopt_ros.core.model import RANGE_BEARING
from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.strategies import make_strategy
from formopt_ros.core.strategies.stacked import CERTIFICATES as STACKED_CERTIFICATES

KINDS = ('range', 'bearing')
#: Every kind ('--measurement all'): the scalar two and range and bearing together.
ALL_KINDS = (*KINDS, RANGE_BEARING)
#: Methods that run on range-bearing problems.
STACKED_METHODS = ('rq', 'rq-loop', 'gbs', 'gbs-cached', 'mtf', 'crm', 'mme', 'periodic')
#: Relative cost excess over the certified optimum that counts as a miss.
MISS_RTOL = 1e-9
#: GBS cell of the one-off and cached rows, fraction of r (the library default).
GBS_CELL = baselines.DEFAULT_GBS_CELL
PEERS = ('slsqp', 'slsqp-8', 'ipopt', 'ipopt-tuned', 'ipopt-8')
EXTRA_METHODS = ('rq-loop', 'rq-batch', 'gbs-cached', *PEERS)
ALL_METHODS = (*METHODS, *EXTRA_METHODS)
DEFAULT_METHODS = ('ram', 'rq', 'rq-loop', 'rq-batch', 'gbs', 'gbs-cached', *PEERS)

ProblemData = tuple[np.ndarray, np.ndarray, float, float]


def random_problem(rng: np.random.Generator, kind: str) -> ProblemData:
    """One moderate random problem (P, p_o, r, sigma) of the given measurement kind."""
    q, upper = np.linalg.qr(rng.standard_normal((3, 3)))
    q = q * np.sign(np.diag(upper))
    eigenvalues = 10.0 ** -np.array([0.0, rng.uniform(0.0, 4.0), rng.uniform(0.0, 4.0)])
    P = (q * eigenvalues) @ q.T * 10.0 ** rng.uniform(-4.0, 0.0)
    P = 0.5 * (P + P.T)
    d_o = rng.uniform(0.5, 10.0)
    angle = rng.uniform(-math.pi, math.pi)
    p_o = d_o * np.array([math.cos(angle), math.sin(angle)])
    r = d_o * rng.uniform(0.05, 0.30)
    if kind == RANGE_BEARING:
        return P, p_o, r, (rng.uniform(0.01, 0.5), rng.uniform(0.002, 0.1))  # type: ignore
    sigma = rng.uniform(0.01, 0.5) if kind == 'range' else rng.uniform(0.002, 0.1)
    return P, p_o, r, sigma


#: A timed call: problem data -> (cost m^2, RAM fell back).
Runner = Callable[[ProblemData], tuple[float, bool]]


def runners(kind: str, methods: Sequence[str]) -> dict[str, Runner]:
    """name -> timed call for every requested method available here."""
    if kind == RANGE_BEARING:
        return {m: _stacked(m) for m in methods if m in STACKED_METHODS}
    peers = peer_methods(kind) if any(m in PEERS for m in methods) else {}
    out: dict[str, Runner] = {}
    for method in methods:
        if method in PEERS:
            if method in peers:
                out[method] = _peer(kind, peers[method])
        elif method in ('gbs', 'gbs-cached'):
            out[method] = _gbs(kind, cached=method == 'gbs-cached')
        elif method == 'rq-loop':
            out[method] = _loop(kind)
        elif method == 'rq-batch':
            continue                            # one call for all problems: run_kind
        else:
            out[method] = _solver(kind, method)
    return out


def _solver(kind: str, method: str) -> Runner:
    def run(data: ProblemData) -> tuple[float, bool]:
        P, p_o, r, sigma = data
        rng = np.random.default_rng(0) if method == 'crm' or method not in METHODS else None
        solution = solve(P, p_o, r, sigma, measurement=kind, method=method, rng=rng)
        return solution.cost, solution.fallback is not None
    return run


def _stacked(method: str) -> Runner:
    """A range-bearing method: rq (validated StackedProblem, as ``solve`` validates), rq-loop
    (unvalidated, as the simulator builds it), gbs (grid cache cleared), gbs-cached and the
    baselines (crm seeded 0)."""
    name = {'rq-loop': 'rq', 'gbs-cached': 'gbs'}.get(method, method)
    strategy = make_strategy(name, **({'cell': GBS_CELL} if name == 'gbs' else {}))

    def run(data: ProblemData) -> tuple[float, bool]:
        P, p_o, r, sigmas = data
        sigma_d, sigma_b = cast(tuple[float, float], sigmas)
        if method == 'gbs':
            baselines._GRID_CACHE.clear()
        problem = StackedProblem(P, p_o, r, sigma_d, sigma_b, method != 'rq-loop')
        context = DEFAULT_CONTEXT if name != 'crm' else \
            replace(DEFAULT_CONTEXT, rng=np.random.default_rng(0))
        solution = strategy.plan(cast(Problem, problem), context)
        return solution.cost, solution.fallback is not None
    return run


def _reference(kind: str, data: ProblemData) -> Any:
    """The certified optimum of a problem (RQ; for range-bearing its level test on lines)."""
    if kind == RANGE_BEARING:
        P, p_o, r, sigmas = data
        sigma_d, sigma_b = cast(tuple[float, float], sigmas)
        problem = cast(Problem, StackedProblem(P, p_o, r, sigma_d, sigma_b))
        return make_strategy('rq').plan(problem, DEFAULT_CONTEXT)
    return solve(*data, measurement=kind, method='rq')


def _loop(kind: str) -> Runner:
    strategy = RayleighQuotient()

    def run(data: ProblemData) -> tuple[float, bool]:
        P, p_o, r, sigma = data
        return strategy.plan(Problem(P, p_o, r, sigma, kind, False), DEFAULT_CONTEXT).cost, False
    return run


def time_batch(kind: str, data: Sequence[ProblemData],
               repeats: int) -> tuple[float, np.ndarray]:
    """(best wall time s of ``repeats`` calls, costs (n,) m^2) of RQ on all problems at once:
    stacking them into a ProblemBatch and :func:`rq_batch`."""
    best, points = math.inf, np.empty((0, 2))
    for _ in range(repeats):
        start = time.perf_counter()
        batch = ProblemBatch(np.array([d[0] for d in data]), np.array([d[1] for d in data]),
                             np.array([d[2] for d in data]), np.array([d[3] for d in data]),
                             kind, validate=False)      # as the engine: checked beforehand
        points = rq_batch(batch)
        best = min(best, time.perf_counter() - start)
    return best, np.array([float(Problem(*d, kind).cost(p)) for d, p in zip(data, points)])


def _gbs(kind: str, cached: bool) -> Runner:
    def run(data: ProblemData) -> tuple[float, bool]:
        P, p_o, r, sigma = data
        if not cached:
            baselines._GRID_CACHE.clear()      # a fresh geometry: no grid to reuse
        return solve(P, p_o, r, sigma, measurement=kind, method='gbs', cell=GBS_CELL).cost, False
    return run


def _peer(kind: str, solver: Callable[[Problem], np.ndarray]) -> Runner:
    def run(data: ProblemData) -> tuple[float, bool]:
        problem = Problem(*data, kind)
        return float(problem.cost(solver(problem))), False
    return run


def time_call(run: Runner, data: ProblemData, repeats: int) -> tuple[float, float, bool]:
    """(best wall time s of ``repeats`` calls, cost, fallback) of one method on one problem."""
    best = math.inf
    cost, fallback = math.nan, False
    for _ in range(repeats):
        start = time.perf_counter()
        cost, fallback = run(data)
        best = min(best, time.perf_counter() - start)
    return best, cost, fallback


Results = dict[str, dict[str, np.ndarray]]


def run_kind(kind: str, methods: Sequence[str], problems: int, repeats: int, peer_repeats: int,
             rng: np.random.Generator,
             batch_size: int | None = None) -> tuple[Results, np.ndarray, np.ndarray]:
    """Times (s), costs (m^2) and fallback flags per method, arrays of shape (problems,); the
    certified optimum per problem; and its proved relative gap (``certificate_gap``; nan where
    it carries no proof). rq-batch solves ``batch_size`` problems per call (None: all)."""
    calls = runners(kind, methods)
    results = {m: {'time': np.zeros(problems), 'cost': np.zeros(problems),
                   'fallback': np.zeros(problems, dtype=bool)}
               for m in methods if m in calls or (m == 'rq-batch' and kind != RANGE_BEARING)}
    warm = random_problem(np.random.default_rng(0), kind)
    for run in calls.values():        # warm-up: lazy imports, problem-independent caches
        run(warm)
    optimum, gap = np.zeros(problems), np.full(problems, np.nan)
    drawn = []
    for index in range(problems):
        data = random_problem(rng, kind)
        drawn.append(data)
        reference = _reference(kind, data)
        optimum[index] = reference.cost
        if reference.certificate in (*PROVED, *STACKED_CERTIFICATES):
            gap[index] = reference.details['certificate_gap']
        for method, run in calls.items():
            if method == 'gbs-cached':
                run(data)                       # builds this geometry's grid
            elapsed, cost, fallback = time_call(
                run, data, peer_repeats if method in PEERS else repeats)
            results[method]['time'][index] = elapsed
            results[method]['cost'][index] = cost
            results[method]['fallback'][index] = fallback
    if 'rq-batch' in methods and kind != RANGE_BEARING:
        time_batch(kind, [warm], 1)
        size = batch_size or problems
        for start in range(0, problems, size):
            chunk = slice(start, min(start + size, problems))
            elapsed, costs = time_batch(kind, drawn[chunk], repeats)
            results['rq-batch']['time'][chunk] = elapsed / len(costs)
            results['rq-batch']['cost'][chunk] = costs
    return results, optimum, gap


def summarise(kind: str, results: Results, optimum: np.ndarray,
              gap: np.ndarray) -> list[list[str]]:
    """Table rows (as strings) for one measurement kind. 'below bound' counts the problems on
    which a method's cost lies below the reference's proved lower bound on the optimum,
    optimum (1 - gap), by more than MISS_RTOL: a certificate contradicted (never seen); where
    the reference carries no proof (gap nan), below the reference's cost itself."""
    rows = []
    for method, r in results.items():
        micro = r['time'] * 1e6
        speed = []
        for base in ('gbs', 'gbs-cached'):
            speed.append(f"{np.median(results[base]['time'] / r['time']):.1f}x"
                         if base in results else '-')
        excess = (r['cost'] - optimum) / optimum
        misses = int(np.sum(excess > MISS_RTOL))
        below = int(np.sum(-excess > np.nan_to_num(gap) + MISS_RTOL))
        fallbacks = str(int(r['fallback'].sum())) if method == 'ram' else '-'
        # one rq-batch call: every problem has the same (amortised) time, no percentile
        p99 = '-' if method == 'rq-batch' and np.ptp(micro) == 0.0 else \
            f'{np.percentile(micro, 99):.1f}'
        rows.append([kind, method, f'{np.median(micro):.1f}', p99,
                     *speed, f'{misses} ({100 * misses / len(excess):.1f} %)',
                     f'{max(float(np.max(excess)), 0.0):.2e}', str(below), fallbacks])
    return rows


def format_table(header: list[str], rows: list[list[str]]) -> str:
    """A plain-text table with right-aligned numeric columns."""
    widths = [max(len(str(x)) for x in column) for column in zip(header, *rows)]
    lines = ['  '.join(h.ljust(w) if i < 2 else h.rjust(w)
                       for i, (h, w) in enumerate(zip(header, widths)))]
    lines.append('  '.join('-' * w for w in widths))
    for row in rows:
        lines.append('  '.join(x.ljust(w) if i < 2 else x.rjust(w)
                               for i, (x, w) in enumerate(zip(row, widths))))
    return '\n'.join(lines)


def write_csv(path: Path, all_results: dict[str, tuple[Results, np.ndarray]]) -> None:
    """One row per (kind, problem, method): time (us; rq-batch: its call's time divided by the
    problems in the call), cost, excess over the certified optimum, miss flag and fallback
    flag."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'x', newline='', encoding='utf-8') as handle:
        writer = csv.writer(handle)
        writer.writerow(['kind', 'problem', 'method', 'time_us', 'cost_m2', 'excess', 'miss',
                         'fallback'])
        for kind, (results, optimum) in all_results.items():
            for method, r in results.items():
                for index in range(len(r['time'])):
                    excess = (r['cost'][index] - optimum[index]) / optimum[index]
                    writer.writerow([kind, index, method, f"{r['time'][index] * 1e6:.3f}",
                                     repr(float(r['cost'][index])), repr(float(excess)),
                                     int(excess > MISS_RTOL), int(r['fallback'][index])])


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(
        prog='formopt-bench',
        description='Time the motion planners and general-purpose optimisers (SciPy SLSQP, '
                    'CasADi + IPOPT when installed) on seeded random problems, with their miss '
                    'rate against the certified optimum.')
    parser.add_argument('--problems', type=integer(1, 10**7), default=300,
                        help='random problems per measurement kind (default: 300)')
    parser.add_argument('--repeats', type=integer(1, 10**7), default=3,
                        help='calls per problem and method; the best time is kept (default: 3)')
    parser.add_argument('--peer-repeats', type=integer(1, 10**7), default=1,
                        help='calls per problem of the (slow) peers (default: 1)')
    parser.add_argument('--seed', type=integer(0, 2**63 - 1), default=0,
                        help='seed of the problem generator (default: 0)')
    every = (*STRATEGIES, *EXTRA_METHODS)       # with the plugin strategies
    parser.add_argument('--methods', type=name_list(every, STRATEGIES.left_out()),
                        default=list(DEFAULT_METHODS),
                        help=f'comma-separated methods among {",".join(every)} '
                             f'(default: {",".join(DEFAULT_METHODS)})')
    parser.add_argument('--batch-size', type=integer(1, 10**7), default=None,
                        help='problems per call of rq-batch (default: all the problems of a '
                             'kind in one call; the batched Monte Carlo engine passes its '
                             'trials, 50 by default)')
    parser.add_argument('--measurement', choices=('range', 'bearing', 'both', RANGE_BEARING,
                                                  'all'), default='both',
                        help='measurement kind(s) to benchmark: both = range and bearing, all '
                             '= those and range-bearing (default: both)')
    parser.add_argument('--csv', metavar='PATH', type=new_file, default=None,
                        help='also write per-problem results to this CSV file (a new file)')
    return parser


@command('formopt-bench')
def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print the table; returns the process exit status."""
    args = build_parser().parse_args(argv)
    kinds = {'both': KINDS, 'all': ALL_KINDS}.get(args.measurement, (args.measurement,))
    if any(m.startswith('ipopt') for m in args.methods) and not casadi_available():
        print('note: casadi is not installed, so the ipopt rows are skipped '
              '(pip install casadi, or the package extra [peers])')
    all_results = {}
    rows: list[list[str]] = []
    proved_text = []
    for kind in kinds:
        rng = np.random.default_rng([args.seed, ALL_KINDS.index(kind)])
        results, optimum, gap = run_kind(kind, args.methods, args.problems, args.repeats,
                                         args.peer_repeats, rng, args.batch_size)
        all_results[kind] = (results, optimum)
        rows.extend(summarise(kind, results, optimum, gap))
        proved_text.append(f'{kind} {int(np.isfinite(gap).sum())}/{args.problems}')
    header = ['kind', 'method', 'median us', 'p99 us', 'vs gbs', 'vs gbs-cached',
              'missed optimum', 'max excess', 'below bound', 'fallbacks']
    print(f'{args.problems} problems per kind, best of {args.repeats} calls '
          f'({args.peer_repeats} for the peers), seed {args.seed}; GBS cell {GBS_CELL} r; '
          f'reference: the certified RQ optimum (proved: {", ".join(proved_text)})')
    print(format_table(header, rows))
    if 'rq-batch' in args.methods:
        size = min(args.batch_size or args.problems, args.problems)
        print(f'rq-batch: {size} problems per call; a problem\'s time is its call\'s time '
              f'divided by the problems in the call')
    print(f'numpy {np.__version__}, python {platform.python_version()} '
          f'({sys.implementation.name}), {os.cpu_count()} CPUs, load average '
          f'{", ".join(f"{x:.2f}" for x in os.getloadavg())}')
    if args.csv:
        write_csv(args.csv, all_results)
        print(f'wrote {args.csv}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
