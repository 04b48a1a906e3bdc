"""formopt-bench: time the planners (RAM, RQ, GBS, ...) on seeded random problems.

For each measurement kind the command draws ``--problems`` moderate random problems (prior
covariance with condition number up to 1e4 and overall scale 1e-4..1, slot distance
0.5-10 m in a random direction, allowed deviation r = 5-30 % of the slot distance, noise
0.01-0.5 m for range or 0.002-0.1 rad for bearing). Every call ``solve(...)`` is timed with
``time.perf_counter`` and the best of ``--repeats`` calls is kept per problem and method; the
methods are interleaved problem by problem so that machine load affects them alike.

Every problem has its own geometry, so grid-based search (GBS) cannot reuse its grid across
problems: the GBS grid cache (``baselines._GRID_CACHE``) is cleared before each GBS call, so
a one-off solve, grid construction included, is what is measured.

The table reports per kind and method: median and 99th-percentile time (microseconds), the
speed-up over GBS (median over problems of t_gbs / t_method), the largest relative cost excess
over the best method on the same problem, and how often RAM fell back to RQ. Only numpy (and
the package's own core) is needed. Run as ``formopt-bench``.
"""
from __future__ import annotations

import argparse
import csv
import math
import os
import platform
import sys
import time
from typing import Sequence

import numpy as np

from formopt_ros.cli.common import ArgumentParser, integer, new_file
from formopt_ros.core import METHODS, Solution, solve
from formopt_ros.core.strategies import baselines

KINDS = ('range', 'bearing')


def random_problem(rng: np.random.Generator,
                   kind: str) -> tuple[np.ndarray, np.ndarray, float, float]:
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
    sigma = rng.uniform(0.01, 0.5) if kind == 'range' else rng.uniform(0.002, 0.1)
    return P, p_o, r, sigma


def time_solve(problem: tuple[np.ndarray, np.ndarray, float, float], kind: str, method: str,
               repeats: int, seed: int = 0) -> tuple[float, Solution]:
    """Best wall time (s) of ``repeats`` calls of solve(), and the last Solution.

    ``seed`` seeds the generator handed to the random strategy (CRM) so runs repeat.
    """
    P, p_o, r, sigma = problem
    best = math.inf
    solution = None
    for _ in range(repeats):
        rng = np.random.default_rng(seed) if method == 'crm' else None
        if method == 'gbs':
            baselines._GRID_CACHE.clear()   # a fresh geometry: no grid to reuse
        start = time.perf_counter()
        solution = solve(P, p_o, r, sigma, measurement=kind, method=method, rng=rng)
        best = min(best, time.perf_counter() - start)
    assert solution is not None                  # repeats >= 1
    return best, solution


def run_kind(kind: str, methods: Sequence[str], problems: int, repeats: int,
             rng: np.random.Generator) -> dict[str, dict[str, np.ndarray]]:
    """Times (s), costs (m^2) and fallback flags, arrays of shape (problems,) per method."""
    results = {m: {'time': np.zeros(problems), 'cost': np.zeros(problems),
                   'fallback': np.zeros(problems, dtype=bool)} for m in methods}
    for method in methods:                # warm-up: lazy imports, problem-independent caches
        time_solve(random_problem(np.random.default_rng(0), kind), kind, method, 1)
    for index in range(problems):
        problem = random_problem(rng, kind)
        for method in methods:
            elapsed, solution = time_solve(problem, kind, method, repeats, index)
            results[method]['time'][index] = elapsed
            results[method]['cost'][index] = solution.cost
            results[method]['fallback'][index] = solution.fallback is not None
    return results


def summarise(kind: str, results: dict[str, dict[str, np.ndarray]]) -> list[list[str]]:
    """Table rows (as strings) for one measurement kind."""
    costs = np.vstack([r['cost'] for r in results.values()])
    best = costs.min(axis=0)
    rows = []
    for method, r in results.items():
        micro = r['time'] * 1e6
        if 'gbs' in results:
            speed_up = f"{np.median(results['gbs']['time'] / r['time']):.1f}x"
        else:
            speed_up = '-'
        excess = float(np.max((r['cost'] - best) / best))
        fallbacks = str(int(r['fallback'].sum())) if method == 'ram' else '-'
        rows.append([kind, method, f'{np.median(micro):.1f}', f'{np.percentile(micro, 99):.1f}',
                     speed_up, f'{excess:.2e}', fallbacks])
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


def write_csv(path: str, all_results: dict[str, dict[str, dict[str, np.ndarray]]]) -> None:
    """One row per (kind, problem, method): time in microseconds, cost, excess, fallback."""
    with open(path, 'w', newline='', encoding='utf-8') as handle:
        writer = csv.writer(handle)
        writer.writerow(['kind', 'problem', 'method', 'time_us', 'cost_m2', 'excess',
                         'fallback'])
        for kind, results in all_results.items():
            best = np.vstack([r['cost'] for r in results.values()]).min(axis=0)
            for method, r in results.items():
                for index in range(len(r['time'])):
                    writer.writerow([kind, index, method, f"{r['time'][index] * 1e6:.3f}",
                                     repr(float(r['cost'][index])),
                                     repr(float((r['cost'][index] - best[index]) / best[index])),
                                     int(r['fallback'][index])])


def parse_methods(text: str) -> list[str]:
    """Comma-separated method names, validated against core.METHODS."""
    methods = [m.strip() for m in text.split(',') if m.strip()]
    unknown = [m for m in methods if m not in METHODS]
    if not methods or unknown:
        raise argparse.ArgumentTypeError(
            f'methods must be a comma list of {", ".join(METHODS)}; got {text!r}')
    return list(dict.fromkeys(methods))


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(
        prog='formopt-bench',
        description='Time the motion planners on seeded random problems (one new geometry per '
                    'problem; the GBS grid cache is cleared before every GBS call, so each GBS '
                    'time includes building its grid).')
    parser.add_argument('--problems', type=integer(1, 10**7), default=300,
                        help='random problems per measurement kind (default: 300)')
    parser.add_argument('--repeats', type=integer(1, 10**7), default=5,
                        help='calls per problem and method; the best time is kept (default: 5)')
    parser.add_argument('--seed', type=integer(0, 2**63 - 1), default=0,
                        help='seed of the problem generator (default: 0)')
    parser.add_argument('--methods', type=parse_methods, default=['ram', 'rq', 'gbs'],
                        help=f'comma-separated methods among {",".join(METHODS)} '
                             '(default: ram,rq,gbs)')
    parser.add_argument('--measurement', choices=('range', 'bearing', 'both'), default='both',
                        help='measurement kind(s) to benchmark (default: both)')
    parser.add_argument('--csv', metavar='PATH', type=new_file, default=None,
                        help='also write per-problem results to this CSV file (a new file)')
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark and print the table; returns the process exit status."""
    args = build_parser().parse_args(argv)
    kinds = KINDS if args.measurement == 'both' else (args.measurement,)
    all_results = {}
    rows: list[list[str]] = []
    for kind in kinds:
        rng = np.random.default_rng([args.seed, KINDS.index(kind)])
        all_results[kind] = run_kind(kind, args.methods, args.problems, args.repeats, rng)
        rows.extend(summarise(kind, all_results[kind]))
    header = ['kind', 'method', 'median us', 'p99 us', 'vs gbs', 'max excess', 'fallbacks']
    print(f'{args.problems} problems per kind, best of {args.repeats} calls, seed {args.seed}')
    print(format_table(header, rows))
    print(f'numpy {np.__version__}, python {platform.python_version()} '
          f'({sys.implementation.name}), {os.cpu_count()} CPUs')
    if args.csv:
        write_csv(args.csv, all_results)
        print(f'wrote {args.csv}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
