"""RQ of a range-bearing follower over generated reachable sets, against a dense reference.

Each problem of the six range-bearing families of test/harness/problems.py (drawn in turn)
gets a random region of test/core/test_reach.py (a reach disc of 0.05-1.5 r, a quarter barely
meeting the slot's disc; a safety circle cutting it in half the problems); RQ's answer over
it is compared with the dense reference of that test (polar grid, samples on every circle,
corners, SLSQP under the circles). Prints per family: problems, certified (lines through the
leader), answers above the reference by more than 1e-9 (relative) and the worst excess,
answers outside the region, the slowest solve:

    .venv/bin/python scripts/check_range_bearing_region.py [--problems 600] [--seed 28]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / 'test'), str(ROOT / 'test' / 'core')]

from harness.problems import STACKED_FAMILIES, stacked_problem  # noqa: E402
from test_reach import dense_region_reference, random_region  # noqa: E402

from formopt_ros.core.strategies.region import rq_in_region  # noqa: E402
from formopt_ros.core.strategies.stacked import CERTIFICATES  # noqa: E402


def main() -> None:
    """Print the table."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--problems', type=int, default=600)
    parser.add_argument('--seed', type=int, default=28)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    rows = {family: [0, 0, 0, 0.0, 0, 0.0] for family in STACKED_FAMILIES}
    for index in range(args.problems):
        family = STACKED_FAMILIES[index % len(STACKED_FAMILIES)]
        problem = stacked_problem(rng, family)
        region = random_region(rng, problem)     # type: ignore[arg-type]
        if region.empty():
            continue
        started = time.perf_counter()
        solution = rq_in_region(problem, region)   # type: ignore[arg-type]
        elapsed = time.perf_counter() - started
        excess = (solution.cost - dense_region_reference(problem, region)) / abs(solution.cost)
        row = rows[family]
        row[0] += 1
        row[1] += solution.certificate in CERTIFICATES
        row[2] += excess > 1e-9
        row[3] = max(row[3], excess)
        row[4] += not region.contains(solution.p, 1e-9)
        row[5] = max(row[5], elapsed)
    print('| family | problems | certified | above reference (1e-9) | worst excess | outside '
          '| slowest s |')
    print('|---|---|---|---|---|---|---|')
    for family, (count, certified, above, worst, outside, slowest) in rows.items():
        print(f'| {family} | {count} | {certified} | {above} | {worst:.2g} | {outside} | '
              f'{slowest:.3f} |')


if __name__ == '__main__':
    main()
