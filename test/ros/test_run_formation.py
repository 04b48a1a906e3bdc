"""scripts/run_formation.sh: separate processes, lockstep, summary.json equals run_trial."""
from __future__ import annotations

import json
import os
import subprocess

import numpy as np

from formopt_ros.core.simulation import Scenario, run_trial

SCRIPT = os.path.join(os.path.dirname(__file__), '..', '..', 'scripts', 'run_formation.sh')
STEPS = 50
TOL = 1e-9


def test_run_formation_lockstep(tmp_path, ros_domain: int) -> None:
    out = tmp_path / 'run'
    result = subprocess.run(
        [SCRIPT, '--measurement', 'bearing', '--strategy', 'crm', '--steps', str(STEPS),
         '--seed', '5', '--mode', 'lockstep', '--out', str(out), '--domain-id',
         str(ros_domain), '--no-record', '--timeout', '120'],
        capture_output=True, text=True, timeout=180)
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    ref = run_trial(Scenario.paper('bearing'), 'crm', 5, 0, STEPS)
    assert summary['ok'] and summary['steps'] == STEPS
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(summary['final_covariance'], ref.covariance[-1], rtol=0,
                               atol=TOL)
    np.testing.assert_allclose(summary['final_truth'], ref.truth[-1], rtol=0, atol=TOL)
    assert abs(summary['final_weighted_trace'] - ref.weighted_trace[-1]) <= TOL
    assert summary['exit_codes'] == {'leader_sim': 0, 'follower_sim': 0,
                                     'estimator_planner': 0}
    assert summary['message_counts']['received']['measurement'] == STEPS
    assert summary['message_counts']['published']['estimate'] == STEPS
    assert summary['counters']['accepted_measurements'] == STEPS
    assert summary['wall_time_s'] > 0 and summary['steps_per_s'] > 0
    assert summary['recording'] is None
    for node in ('leader_sim', 'follower_sim', 'estimator_planner'):
        log = (out / f'{node}.log').read_text()
        assert f'{node} ready' in log and 'Traceback' not in log


def test_run_formation_rejects_bad_arguments(tmp_path) -> None:
    result = subprocess.run([SCRIPT, '--out', str(tmp_path), '--mode', 'warp'],
                            capture_output=True, text=True, timeout=30)
    assert result.returncode == 2
    assert "--mode must be lockstep or realtime, got 'warp'" in result.stderr
    help_text = subprocess.run([SCRIPT, '--help'], capture_output=True, text=True, timeout=30)
    assert help_text.returncode == 0 and '--measurement range|bearing' in help_text.stdout
