"""scripts/run_formation.sh: each node its own process, started the way a user starts it; the
lockstep run equals the pure simulation per follower and the recording loses nothing."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from harness.ros import REPO

from formopt_ros.bag import read_bag
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import run_formation, run_trial
from formopt_ros.wire.formation import load_formation

SCRIPT = REPO / 'scripts' / 'run_formation.sh'
FIG4 = REPO / 'config' / 'formation_fig4.yaml'
STEPS = 50
TOL = 1e-9


def run(*args: str, timeout: float = 180) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(SCRIPT), *args], capture_output=True, text=True,
                          timeout=timeout)


def test_single_follower_flags(tmp_path: Path, ros_domain: int) -> None:
    out = tmp_path / 'run'
    result = run('--measurement', 'bearing', '--strategy', 'crm', '--steps', str(STEPS),
                 '--seed', '5', '--out', str(out), '--domain-id', str(ros_domain),
                 '--no-record', '--timeout', '120')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    ref = run_trial(Scenario.paper('bearing'), 'crm', 5, 0, STEPS)
    assert summary['ok'] and summary['steps'] == STEPS and summary['recording'] is None
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(summary['final_covariance'], ref.covariance[-1], rtol=0,
                               atol=TOL)
    np.testing.assert_allclose(summary['final_truth'], ref.truth[-1], rtol=0, atol=TOL)
    assert summary['exit_codes'] == {'leader_sim': 0, 'follower.follower_sim': 0,
                                     'follower.estimator_planner': 0}
    assert summary['counters']['accepted_measurements'] == STEPS
    assert summary['wall_time_s'] > 0 and summary['steps_per_s'] > 0


def test_fig4_formation_recorded(tmp_path: Path, ros_domain: int) -> None:
    """The paper's Fig. 4 pair under a namespace prefix: every follower equals the pure
    formation simulation (1e-9), the bag holds every published message, rosbags reads it."""
    out = tmp_path / 'fig4'
    result = run('--formation', str(FIG4), '--steps', str(STEPS), '--out', str(out),
                 '--prefix', '/fig4test', '--domain-id', str(ros_domain), '--timeout', '120')
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    reference = run_formation(load_formation(FIG4), STEPS)
    assert summary['ok'] and set(summary['followers']) == {'bearing', 'range'}
    for follower, ref in reference.items():
        got = summary['followers'][follower]
        assert got['steps'] == STEPS
        np.testing.assert_allclose(got['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
        np.testing.assert_allclose(got['final_truth'], ref.truth[-1], rtol=0, atol=TOL)
    recording = summary['recording']
    assert recording['complete'] and recording['missing'] == {}
    assert recording['counts'] == recording['expected']
    counts = read_bag(out / 'run.mcap').counts()
    assert counts == recording['counts']
    assert counts['/fig4test/leader/odom'] == 2 * STEPS and counts['/clock'] == 2 * STEPS
    assert counts['/fig4test/range/estimate'] == counts['/fig4test/bearing/estimate'] == STEPS
    from rosbags.highlevel import AnyReader
    with AnyReader([out / 'run.mcap']) as reader:
        assert sum(1 for _ in reader.messages()) == sum(counts.values())
    # formopt-report draws the paper's Fig. 4 and a row per follower, top to bottom
    report = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.report',
                             str(out / 'run.mcap'), '--out', str(out / 'report')],
                            capture_output=True, text=True, timeout=120)
    assert report.returncode == 0, report.stderr
    rows = json.loads((out / 'report' / 'summary.json').read_text())['followers']
    assert list(rows) == ['bearing', 'range']
    for follower, ref in reference.items():
        assert rows[follower]['steps'] == STEPS and rows[follower]['description'] == 'recorded'
        assert rows[follower]['final_weighted_trace'] == pytest.approx(
            ref.weighted_trace[-1], abs=TOL)
        assert rows[follower]['mean_nees'] == pytest.approx(float(np.mean(ref.nees)), rel=1e-9)
    assert (out / 'report' / 'trajectory.png').stat().st_size > 20_000


@pytest.mark.parametrize('args,text', [
    (['--mode', 'warp'], "argument --mode: invalid choice: 'warp'"),
    (['--strategy', 'fast'], "argument --strategy: invalid choice: 'fast'"),
    (['--steps', '0'], 'argument --steps: must be an integer in [1,'),
    (['--domain-id', 'x'], 'argument --domain-id: must be an integer'),
    (['--formation', 'nonexistent.yaml'], 'no such formation file'),
    (['--formation', str(FIG4), '--strategy', 'rq'], 'cannot be combined with --formation'),
    (['--prefix', 'bad name'], '--prefix must look like'),
])
def test_bad_arguments_stop_before_any_node_starts(tmp_path: Path, args: list[str],
                                                   text: str) -> None:
    """Exit 2, one line naming the option and the value; no node was started (no logs)."""
    out = tmp_path / 'bad'
    result = run(*args, '--out', str(out), timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('run_formation.sh: error: ') and \
        text in lines[0], lines
    assert not out.exists() or not any(out.iterdir())


def test_an_earlier_run_is_never_overwritten(tmp_path: Path) -> None:
    out = tmp_path / 'run'
    out.mkdir()
    (out / 'summary.json').write_text('{"earlier": true}')
    result = run('--steps', '3', '--out', str(out), timeout=30)
    assert result.returncode == 2 and 'is not empty (summary.json' in result.stderr
    assert json.loads((out / 'summary.json').read_text()) == {'earlier': True}
    help_text = run('--help', timeout=30)
    assert help_text.returncode == 0 and '--formation FILE' in help_text.stdout
