"""What an unknown range bias costs at best: the filter's covariance at the truth, noise-free.

For the UWB follower of config/formation_real_interfaces.yaml (slot [-1, -2] m, r = 0.2 |p_o|,
range noise 0.1 m, a bias prior of 0.1 m), on a straight and on the file's S-curve leader:
the EKF covariance recursion evaluated along the true path, without noise, is the posterior
Cramer-Rao bound of the linearised model, so its position part bounds the RMS error of any
estimator of that motion. Prints, per motion policy inside the disc, the bound with the bias
state against the bound of the same scenario without a bias (RQ), and the bias's final
standard deviation (its prior is 0.1 m: a value near it means the motion did not reveal it).

Policies: ``rq`` (the package's planner, as the node runs it), ``swing`` (the two tangential
ends of the disc in turn, every step: the widest change of direction to the leader the disc
allows), ``swing4`` (the same, every 4 steps), ``aware`` (greedy on the bias-augmented
posterior: the disc's centre and 48 points on two rings, each driven to and updated).

Usage: .venv/bin/python scripts/measure_bias_bound.py [STEPS] [RANGES_PER_STEP] [--fast]
(``--fast``: without ``aware``, which takes a minute per leader).
"""
from __future__ import annotations

import copy
import math
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from formopt_ros.core.estimator import EstimatorPlanner, RealNoise
from formopt_ros.core.protocol import SUBSTEPS, motion_commands, step_substeps
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import make_strategy
from formopt_ros.wire.formation import load_formation

REPO = Path(__file__).resolve().parents[1]
PATHS = {'straight': {'kind': 'straight', 'speed': 1.0}, 's-curve': None}
#: The bias prior of the file's UWB follower, m.
BIAS_SIGMA = 0.1
#: Steps left out of the average (3 s: the start's transient).
SKIP_STEPS = 30


def uwb_scenario(path: dict | None) -> Scenario:
    """The file's UWB follower, with the leader on ``path`` (None: the file's own)."""
    data = yaml.safe_load((REPO / 'config' / 'formation_real_interfaces.yaml').read_text())
    if path is not None:
        data['formation']['leader']['path'] = path
    data['formation']['followers'] = data['formation']['followers'][:1]
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(tmp) / 'uwb.yaml'
        target.write_text(yaml.safe_dump(data))
        return load_formation(target).followers[0].scenario


def drive(filter_: EstimatorPlanner, scenario: Scenario, target: np.ndarray, step: int) -> None:
    """Propagate ``filter_`` along the protocol's exact motion to ``target`` for ``step``."""
    substeps = step_substeps(step)
    v_l, omega_l = scenario.leader.velocity(substeps[0], scenario.dt)
    command = motion_commands(filter_.x, target, scenario.dt, v_l, omega_l, scenario.kinematics)
    for j, substep in enumerate(substeps):
        v_l, omega_l = scenario.leader.velocity(substep, scenario.dt)
        filter_.propagate(command.linear[j], command.angular[j], v_l, omega_l)


def measure(filter_: EstimatorPlanner, scenario: Scenario, step: int, count: int) -> None:
    """``count`` noise-free ranges at the truth (the estimate is the truth: no noise)."""
    bias = filter_.state[3] if filter_.state.size == 4 else 0.0
    for _ in range(count):
        filter_.update(step, float(np.hypot(*filter_.state[:2])) + bias, scenario.sigma ** 2)


def bound(scenario: Scenario, policy: str, bias_sigma: float, steps: int,
          count: int) -> tuple[float, float]:
    """The position bound sqrt(mean tr P_xy) after SKIP_STEPS (m) and the bias's final
    standard deviation (m; 0 without a bias state)."""
    filter_ = EstimatorPlanner(scenario, make_strategy('rq'),
                               noise=RealNoise(bias_sigma=bias_sigma))
    filter_.state[:3] = scenario.initial_estimate()[0]
    slot, r = np.asarray(scenario.p_o, dtype=float), scenario.r
    tangent = np.array([-slot[1], slot[0]]) / np.linalg.norm(slot)
    traces = []
    for k in range(steps):
        if policy == 'rq':
            latest = scenario.leader.velocity(step_substeps(k + 1)[0], scenario.dt)
            target = filter_.plan(k + 1, (latest,) * SUBSTEPS).solution.p
        elif policy in ('swing', 'swing4'):
            period = 1 if policy == 'swing' else 4
            target = slot + r * tangent * (1.0 if (k // period) % 2 else -1.0)
        else:
            candidates = [slot] + [slot + rho * r * np.array([math.cos(a), math.sin(a)])
                                   for rho in (0.5, 1.0)
                                   for a in np.linspace(0.0, 2 * math.pi, 24, endpoint=False)]

            def after(candidate: np.ndarray) -> float:
                trial = copy.deepcopy(filter_)
                drive(trial, scenario, candidate, k + 1)
                measure(trial, scenario, k + 1, count)
                return float(trial.covariance[0, 0] + trial.covariance[1, 1])
            target = min(candidates, key=after)
        drive(filter_, scenario, np.asarray(target, dtype=float), k + 1)
        measure(filter_, scenario, k + 1, count)
        traces.append(filter_.covariance[0, 0] + filter_.covariance[1, 1])
    bias = math.sqrt(filter_.covariance[3, 3]) if bias_sigma > 0.0 else 0.0
    return math.sqrt(float(np.mean(traces[SKIP_STEPS:]))), bias


def main(argv: list[str]) -> int:
    fast = '--fast' in argv
    numbers = [a for a in argv if a != '--fast']
    steps = int(numbers[0]) if numbers else 300
    count = int(numbers[1]) if len(numbers) > 1 else 1
    policies = ('rq', 'swing', 'swing4') if fast else ('rq', 'swing', 'swing4', 'aware')
    print(f'{steps} steps, {count} range(s) per step, bias prior {BIAS_SIGMA} m')
    print('| leader | policy | bound without bias m | bound with bias state m | ratio | '
          'bias sigma at the end m |')
    print('|---|---|---|---|---|---|')
    for name, path in PATHS.items():
        scenario = uwb_scenario(path)
        ideal, _ = bound(scenario, 'rq', 0.0, steps, count)
        for policy in policies:
            with_bias, bias = bound(scenario, policy, BIAS_SIGMA, steps, count)
            print(f'| {name} | {policy} | {ideal:.4f} | {with_bias:.4f} | '
                  f'{with_bias / ideal:.2f} | {bias:.3f} |')
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
