"""Accuracy of the simulated real stack against the ideal lockstep run of the same scenario.

For a straight and an S-curve leader, runs the UWB follower of
config/formation_real_interfaces.yaml through scripts/run_formation.sh (field_sim: cmd_vel base
with limits, odometry at 50 Hz, ranges at 30 Hz with +-5 ms jitter, 0.1 m bias, 2 % outliers of
+1-3 m, 1 % dropouts; follower_estimator with the bias state and Huber weighting), one run per
seed, and the same scenario's ideal lockstep run (run_trial: the paper's protocol, Gaussian
ranges once per step, no bias, no outliers) over 20 trials. Each leader runs twice: with the
radio of the file (its 0.1 m bias estimated by the bias state) and with the same radio without
its bias (plain filter: outliers, jitter and dropouts kept), which separates what the unknown
bias costs from what the interfaces cost, and a third time with the bias and MME's side steps
on every leader path (``while_turning``, sides switched every 5 plans: the widest swing the
base's 2 m/s reach), the motion that reveals the bias. Prints a table: mean NEES of the
real runs (3 is consistent), RMS position errors after the first 3 s and their ratio, and
the estimator's p99 wall time per input (an odometry message or a range, with the updates it
lets through and their estimates published) and per plan (with its target published) against
the 2 ms budget.

Usage: .venv/bin/python scripts/bench_real_stack.py [SEEDS] [STEPS] [DOMAIN_ID] [within-reach]

``within-reach``: the estimator plans inside the set its base reaches (``plan_within_reach``).
"""
from __future__ import annotations

import itertools
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import yaml

from formopt_ros.core.simulation import run_trial
from formopt_ros.wire.formation import load_formation

REPO = Path(__file__).resolve().parents[1]
PATHS = {'straight': {'kind': 'straight', 'speed': 1.0},
         's-curve': {'kind': 's-curve', 'speed': 1.0, 'amplitude': 0.5, 'period': 8.0}}
SKIP_STEPS = 30                       # 3 s, as the real runs' tracking skips


#: Radio variants: changes of the UWB follower's real settings, and of its strategy.
RADIOS = {'bias 0.1 m, bias state': {},
          'no bias, plain filter': {'range_bias': 0.0, 'bias_sigma': 0.0}}
STRATEGIES = {'bias 0.1 m, bias state, MME side steps': {
    'strategy': 'mme', 'options': {'while_turning': True, 'period': 5}}}


def formation_file(folder: Path, path: dict, seed: int, radio: str = '') -> Path:
    """The shipped real formation with its UWB follower only, on ``path``, seeded, with the
    ``radio`` variant."""
    data = yaml.safe_load((REPO / 'config' / 'formation_real_interfaces.yaml').read_text())
    data['formation']['leader']['path'] = path
    follower = data['formation']['followers'][0]
    follower['real'].update(RADIOS.get(radio, {}))
    follower.update(STRATEGIES.get(radio, {}))
    data['formation']['followers'] = [dict(follower, seed=seed)]
    target = folder / f"{path['kind']}_{seed}_{len(radio)}.yaml"
    target.write_text(yaml.safe_dump(data))
    return target


def real_run(folder: Path, path: dict, seed: int, steps: int, domain: int, radio: str) -> dict:
    """One real-stack run; the UWB follower's tracking (mean NEES, RMS error)."""
    out = folder / f"run_{path['kind']}_{seed}_{len(radio)}"
    result = subprocess.run([str(REPO / 'scripts' / 'run_formation.sh'), '--formation',
                             str(formation_file(folder, path, seed, radio)), '--steps', str(steps),
                             '--out', str(out), '--domain-id', str(domain)],
                            capture_output=True, text=True)
    summary = json.loads((out / 'summary.json').read_text())
    if result.returncode != 0:
        print(f'run failed: {summary["failure"]}', file=sys.stderr)
    follower = summary['followers']['ranger']
    return {**follower['tracking'], 'ok': summary['ok'],
            'unreachable': follower['unreachable_targets'], 'plans': follower['plans'],
            **{f'p99_{kind}': value['p99'] for kind, value in follower['handling_ms'].items()}}


def ideal_rms(folder: Path, path: dict, steps: int, trials: int = 20) -> float:
    """RMS position error of the same scenario's lockstep runs after SKIP_STEPS."""
    scenario = load_formation(formation_file(folder, path, 0)).followers[0].scenario
    errors = []
    for trial in range(trials):
        result = run_trial(scenario, 'rq', 0, trial, steps)
        difference = result.truth[SKIP_STEPS:, :2] - result.estimate[SKIP_STEPS:, :2]
        errors.append(np.sum(difference ** 2, axis=1))
    return float(np.sqrt(np.mean(np.concatenate(errors))))


def main(argv: list[str]) -> int:
    seeds = int(argv[0]) if argv else 4
    steps = int(argv[1]) if len(argv) > 1 else 300
    domain = int(argv[2]) if len(argv) > 2 else 42
    if argv[3:] == ['within-reach']:
        for settings in RADIOS.values():
            settings['plan_within_reach'] = True
    print('| leader | radio | real runs | all ok | mean NEES (range over runs) | real RMS m | '
          'ideal lockstep RMS m | ratio (bar 1.25) | unreachable targets | p99 input ms | '
          'p99 plan ms |')
    print('|---|---|---|---|---|---|---|---|---|---|---|')
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for (name, path), radio in itertools.product(PATHS.items(), [*RADIOS, *STRATEGIES]):
            runs = [real_run(folder, path, seed, steps, domain, radio) for seed in range(seeds)]
            nees = [r['mean_nees'] for r in runs]
            rms = float(np.sqrt(np.mean([r['rms_position_error_m'] ** 2 for r in runs])))
            ideal = ideal_rms(folder, path, steps)
            share = sum(r['unreachable'] for r in runs) / sum(r['plans'] for r in runs)
            print(f'| {name} | {radio} | {seeds} x {steps * 0.1:g} s | '
                  f'{all(r["ok"] for r in runs)} | '
                  f'{np.mean(nees):.2f} ({min(nees):.2f}-{max(nees):.2f}) | {rms:.3f} | '
                  f'{ideal:.3f} | {rms / ideal:.2f} | {100 * share:.0f} % | '
                  f"{max(r['p99_input'] for r in runs):.2f} | "
                  f"{max(r['p99_plan'] for r in runs):.2f} |")
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
