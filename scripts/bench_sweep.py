"""Wall time of a sweep on 1 and 2 local Dask workers, and that both give the same numbers.

Usage:
    .venv/bin/python scripts/bench_sweep.py [--workers 1,2] [--trials 10] [--steps 300]

The sweep: 24 scenarios (sensor range, bearing x r fraction 0.05, 0.1, 0.2 x noise scale
0.5, 1, 2, 4) x 3 strategies (RAM, RQ, CRM), each cell a study of ``--trials`` x ``--steps``.
Each run starts its own local cluster (included in the time) with an empty cache. Prints one
line per worker count and the ratio of each wall time to the first's; exits 1 when the
numbers differ. On a shared machine other load limits the speed-up: the first line also
gives the ratio a pure CPU loop achieves on 2 processes against 1 at that moment (the bound
of any 2-worker ratio then).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from formopt_ros.analysis.sweep import CellCache, run_cells
from formopt_ros.core.sweep import TIMING_COLUMNS, Cell, expand

GRID = {'measurement': ['range', 'bearing'], 'r_fraction': [0.05, 0.1, 0.2],
        'sigma_scale': [0.5, 1.0, 2.0, 4.0]}
STRATEGIES = ('ram', 'rq', 'crm')


def _spin(n: int) -> int:
    total = 0
    for i in range(n):
        total += i * i
    return total


def cpu_ratio(n: int = 10_000_000) -> float:
    """Wall time of two CPU loops on 2 processes over the same on 1 (0.5: two free cores)."""
    with ProcessPoolExecutor(2) as pool:
        list(pool.map(_spin, [1, 1]))                  # the processes are up
        start = time.perf_counter()
        list(pool.map(_spin, [n, n]))
        both = time.perf_counter() - start
    start = time.perf_counter()
    _spin(n)
    _spin(n)
    return both / (time.perf_counter() - start)


def main() -> int:
    """Run the benchmark; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--workers', default='1,2', help='worker counts (default: 1,2)')
    parser.add_argument('--trials', type=int, default=10)
    parser.add_argument('--steps', type=int, default=300)
    parser.add_argument('--seed', type=int, default=0)
    args = parser.parse_args()
    counts = [int(n) for n in args.workers.split(',')]
    cells = [Cell.make(point, name, {}, args.trials, args.steps, args.seed)
             for point in expand(GRID) for name in STRATEGIES]
    print(f'{len(expand(GRID))} scenarios x {len(STRATEGIES)} strategies = {len(cells)} cells '
          f'of {args.trials} trials x {args.steps} steps; {os.cpu_count()} CPUs, load average '
          f'{", ".join(f"{x:.2f}" for x in os.getloadavg())}; a CPU loop on 2 processes vs 1: '
          f'{cpu_ratio():.2f}x')
    print('| workers | wall time [s] | vs 1st | cells computed | same numbers |')
    print('|---|---|---|---|---|')
    first_time, first_rows = None, None
    same_everywhere = True
    for count in counts:
        with tempfile.TemporaryDirectory() as folder:
            start = time.perf_counter()
            outcome = run_cells(cells, CellCache(Path(folder)), workers=count)
            elapsed = time.perf_counter() - start
        rows = [{k: v for k, v in (row or {}).items() if k not in TIMING_COLUMNS}
                for row in outcome.rows]
        first_time = first_time or elapsed
        first_rows = first_rows or rows
        same = rows == first_rows and not outcome.failures
        same_everywhere &= same
        print(f'| {count} | {elapsed:.1f} | {elapsed / first_time:.2f}x | '
              f'{len(outcome.computed)} | {"yes" if same else "NO"} |')
    return 0 if same_everywhere else 1


if __name__ == '__main__':
    raise SystemExit(main())
