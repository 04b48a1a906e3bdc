"""The range-bearing solver on the 10,002 problems of the slow test, in parallel, with progress.

Runs exactly the problems of ``test_solver_matches_dense_reference_10000`` (the same generator,
seed and order), split over ``--jobs`` processes, writes one JSON line per problem to ``--out``
and prints the per-family counts of ``check_problems`` at the end:

    .venv/bin/python scripts/check_range_bearing.py --jobs 2 --out /tmp/rb10k.jsonl
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path[:0] = [str(Path(__file__).resolve().parents[1] / 'test' / part) for part in ('core', '')]
from test_stacked_solver import (  # noqa: E402
    FAMILIES, SEED, generated_problem, reference_cost)

from formopt_ros.core.strategies.stacked import CERTIFICATES, lines_plan  # noqa: E402

COUNT = 10_002


def solve_range(bounds: tuple[int, int, str]) -> list[dict[str, object]]:
    """Problems first..last-1 of the sequence: one record each (also appended to the file)."""
    first, last, path = bounds
    rng = np.random.default_rng(SEED + 1)
    out = []
    for index in range(last):
        family = FAMILIES[index % len(FAMILIES)]
        problem = generated_problem(rng, family)
        if index < first:
            continue
        start = time.perf_counter()
        solution = lines_plan(problem, 'rq')
        elapsed = time.perf_counter() - start
        reference, _ = reference_cost(problem)
        row = {'index': index, 'family': family,
               'certified': solution.certificate in CERTIFICATES,
               'fallback': solution.fallback, 'boundary': bool(solution.on_boundary),
               'gap': solution.details['certificate_gap'],
               'excess': (solution.cost - reference) / reference,
               'below_bound': reference < solution.details['lower_bound'] - 1e-12 * reference,
               'lines': solution.candidates, 'seconds': elapsed}
        out.append(row)
        with open(path, 'a', encoding='utf-8') as handle:
            handle.write(json.dumps(row) + '\n')
    return out


def main() -> int:
    """Run and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--jobs', type=int, default=2)
    parser.add_argument('--out', type=Path, required=True)
    args = parser.parse_args()
    edges = np.linspace(0, COUNT, args.jobs + 1).astype(int)
    with ProcessPoolExecutor(args.jobs) as pool:
        rows = [r for part in pool.map(solve_range, [(int(a), int(b), str(args.out)) for a, b
                                                     in zip(edges[:-1], edges[1:])])
                for r in part]
    print('| family | problems | certified | boundary optima | flagged | largest gap | '
          'largest |excess| (certified) | below bound |')
    print('|---|---|---|---|---|---|---|---|')
    ok = True
    for family in FAMILIES:
        mine = [r for r in rows if r['family'] == family]
        good = [r for r in mine if r['certified']]
        flagged = len(mine) - len(good)
        worst = max((abs(r['excess']) for r in good), default=0.0)
        print(f"| {family} | {len(mine)} | {len(good)} | {sum(r['boundary'] for r in good)} | "
              f"{flagged} | {max((r['gap'] for r in good), default=0.0):.2e} | {worst:.2e} | "
              f"{sum(r['below_bound'] for r in mine)} |")
        ok &= worst <= 1e-9 and flagged == 0
    return 0 if ok else 1


if __name__ == '__main__':
    sys.exit(main())
