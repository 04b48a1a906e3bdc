"""RQ's two routes on one problem: the scalar solver against the batched one on a batch of one.

Prints the time per problem (best of 5 runs of 200 calls) and the ratio, for one random problem
per sensor (seed 0). Usage: .venv/bin/python scripts/measure_rq_routes.py
"""
from __future__ import annotations

import timeit

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.strategies.rq import rq_batch, rq_optimum


def main() -> None:
    """Print one row per sensor."""
    rng = np.random.default_rng(0)
    print('| sensor | scalar us | batch of one us | ratio |\n|---|---|---|---|')
    for kind, sigma in (('range', 0.1), ('bearing', 0.05)):
        root = rng.normal(size=(3, 3))
        problem = Problem(0.01 * (root @ root.T + np.eye(3)), np.array([-1.5, -1.0]), 0.5,
                          sigma, kind)
        batch = ProblemBatch.stack([problem])
        scalar, batched = (min(timeit.repeat(call, number=200, repeat=5)) / 200
                           for call in (lambda: rq_optimum(problem), lambda: rq_batch(batch)))
        print(f'| {kind} | {1e6 * scalar:.1f} | {1e6 * batched:.1f} | {batched / scalar:.1f} |')


if __name__ == '__main__':
    main()
