"""How often RQ's answers need the exact stage (core/strategies/verify.py): in the paper's
scenarios and in the generator families of the certification tests.

Usage:
    .venv/bin/python scripts/measure_exact_share.py [--trials 3] [--per-family 300]

Prints, per sensor, the exact stage's calls among RQ's certificates over ``--trials`` trials of
600 steps of the paper's scenario; then, for ``--per-family`` problems of each family of
test/harness/problems.py (seed 5), the share of problems whose certificate used exact
arithmetic, by decade of the gain's rounding bound relative to the cost.
"""
from __future__ import annotations

import argparse
import math
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'test'))

from formopt_ros.core.model import BEARING, RANGE  # noqa: E402
from formopt_ros.core.scenario import Scenario  # noqa: E402
from formopt_ros.core.simulation import run_trial  # noqa: E402
from formopt_ros.core.strategies import common, rq, verify  # noqa: E402
from harness.problems import families  # noqa: E402


def main() -> None:
    """Print both tables."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--trials', type=int, default=3)
    parser.add_argument('--per-family', type=int, default=300)
    args = parser.parse_args()
    calls = {'certify': 0, 'exact': 0}
    certify, exact_stage = verify.certify, verify._exact_stage

    def counted_certify(*a, **k):  # type: ignore[no-untyped-def]
        calls['certify'] += 1
        return certify(*a, **k)

    def counted_exact(*a, **k):  # type: ignore[no-untyped-def]
        calls['exact'] += 1
        return exact_stage(*a, **k)
    verify._exact_stage = counted_exact
    rq.certify = common.certify = counted_certify  # type: ignore[assignment]
    print('paper scenario (RQ, seed 0):')
    for kind in (RANGE, BEARING):
        calls.update(certify=0, exact=0)
        for trial in range(args.trials):
            run_trial(Scenario.paper(kind), 'rq', 0, trial, 600)
        print(f"  {kind:8s} {calls['exact']} exact stages in {calls['certify']} certificates "
              f"({100 * calls['exact'] / calls['certify']:.1f} %)")
    rows: dict[int, list[int]] = defaultdict(lambda: [0, 0])
    for kind in (RANGE, BEARING):
        rng = np.random.default_rng(5)
        for make, count in families(kind).values():
            for _ in range(min(count, args.per_family)):
                problem = make(rng)
                solution = rq.rq_optimum(problem)
                x, y = float(solution.p[0]), float(solution.p[1])
                gain = problem.gain_at(x, y)
                bound = problem.gain_error_at(x, y, gain) / max(problem.base_cost - gain, 1e-300)
                decade = max(-20, math.floor(math.log10(max(bound, 1e-300))))
                rows[decade][0] += 1
                rows[decade][1] += solution.details.get('certificate_arithmetic') == 'exact'
    print('test families (RQ, seed 5): gain rounding bound / cost -> exact stage share')
    for decade in sorted(rows):
        count, exact = rows[decade]
        label = '<= 1e-20' if decade == -20 else f'1e{decade}'
        print(f'  {label:>8s} {count:5d} problems, {exact:4d} exact ({100 * exact / count:.1f} %)')


if __name__ == '__main__':
    main()
