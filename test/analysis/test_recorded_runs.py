"""The offline tools without ROS, on a bag recorded by formopt_ros 0.1.0 (before the run
description existed): the description is reconstructed, the offline re-estimation reproduces
every recorded estimate exactly, the report and the commands work, nothing is overwritten."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rosbags')
pytest.importorskip('mcap')

from formopt_ros.analysis.offline import offline  # noqa: E402
from formopt_ros.analysis.recording import load_recording  # noqa: E402
from formopt_ros.bag import read_bag  # noqa: E402
from formopt_ros.core.scenario import Scenario  # noqa: E402
from formopt_ros.core.simulation import run_trial  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / 'data'
#: scripts/run_formation.sh --measurement bearing --strategy crm --steps 20 --seed 2 of 0.1.0.
LEGACY = DATA / 'legacy_0.1.0_lockstep_bearing_crm_seed2.mcap'
#: Its summary.json: the final estimate (m, m, rad) and mean NEES.
FINAL_ESTIMATE = [-0.7809831396564715, 2.0463658646430702, 0.4991763456520051]
MEAN_NEES = 2.295959755852919


def test_legacy_description_is_reconstructed() -> None:
    recording = load_recording(read_bag(LEGACY))
    follower = recording.follower()
    assert follower.legacy and follower.namespace == '/follower'
    description = follower.description
    assert (description.strategy, description.mode, description.follower_id) == (
        'crm', 'lockstep', 'follower')
    assert description.scenario == Scenario.paper('bearing')
    assert recording.leader_topic == '/leader/odom'


def test_legacy_offline_reproduces_every_estimate_and_the_simulation() -> None:
    """With the seed of the run (not recorded in 0.1.0 bags) even CRM's waypoints match; with
    another seed the estimates still match but the waypoints do not, and the verdict fails."""
    recording = load_recording(read_bag(LEGACY))
    result = offline(recording, seed=2)
    assert (result.steps, result.recorded_steps, result.max_stamp_diff_ns) == (20, 20, 0)
    assert result.max_diff <= 1e-12 and result.max_waypoint_diff <= 1e-12
    np.testing.assert_allclose(result.estimates[-1], FINAL_ESTIMATE, rtol=0, atol=1e-12)
    ref = run_trial(Scenario.paper('bearing'), 'crm', 2, 0, 20)
    np.testing.assert_allclose(np.array(result.estimates), ref.estimate, rtol=0, atol=1e-9)
    wrong_seed = offline(recording, seed=3)
    # the estimates follow the recorded inputs; CRM's draws differ: the verdict fails
    assert wrong_seed.max_state_diff <= 1e-12 and wrong_seed.max_covariance_diff <= 1e-12
    assert wrong_seed.max_waypoint_diff > 1e-3
    assert wrong_seed.max_diff == wrong_seed.max_waypoint_diff


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', *args], capture_output=True, text=True,
                          timeout=120)


def test_commands_on_the_legacy_bag(tmp_path: Path) -> None:
    """replay --offline and formopt-report run without ROS; outputs are never overwritten."""
    out = tmp_path / 'offline.json'
    result = run('formopt_ros.cli.replay', str(LEGACY), '--offline', '--seed', '2',
                 '--json', str(out))
    assert result.returncode == 0, result.stderr
    assert 'OK' in result.stdout and json.loads(out.read_text())['ok'] is True
    again = run('formopt_ros.cli.replay', str(LEGACY), '--offline', '--json', str(out))
    assert again.returncode == 2 and 'exists' in again.stderr
    report = tmp_path / 'report'
    result = run('formopt_ros.cli.report', str(LEGACY), '--out', str(report))
    assert result.returncode == 0, result.stderr
    summary = json.loads((report / 'summary.json').read_text())
    assert summary['steps'] == 20 and summary['description'] == 'reconstructed from the messages'
    assert summary['mean_nees'] == pytest.approx(MEAN_NEES, rel=1e-12)
    for name in ('trajectory.png', 'weighted_trace.png', 'nees.png'):
        assert (report / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    before = (report / 'summary.json').read_bytes()
    again = run('formopt_ros.cli.report', str(LEGACY), '--out', str(report))
    assert again.returncode == 2 and 'not an empty folder' in again.stderr
    assert (report / 'summary.json').read_bytes() == before
