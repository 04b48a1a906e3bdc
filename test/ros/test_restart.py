"""Peer restart in lockstep: follower_sim is killed mid-run and restarted; the run finishes."""
from __future__ import annotations

import json
import signal
from pathlib import Path

import numpy as np

STEPS = 40
KILL_AFTER = 10            # steps processed before the follower is killed
RESEND = 0.3               # s, the estimator's resend_timeout


def test_follower_restart_mid_run(formation, node_process, tmp_path: Path) -> None:
    params = {'measurement': 'range', 'strategy': 'ram', 'seed': 1, 'steps': STEPS,
              'resend_timeout': RESEND}
    follower_params = {'measurement': 'range', 'seed': 1}
    # leader_sim, estimator_planner and the probe in this process, follower_sim outside
    run = formation(params, follower=False)
    follower = node_process('follower_sim', follower_params)
    est = run.estimator.session
    assert run.spin_until(lambda: est.step >= KILL_AFTER, 60.0), \
        f'estimator at step {est.step} before the kill; follower: {follower.stderr}'
    follower.signal(signal.SIGKILL)
    assert follower.wait(timeout=10.0) == -signal.SIGKILL
    # Without a follower the run stalls: no progress over several resend periods.
    stalled_at = est.step
    run.spin_until(lambda: est.step > stalled_at + 1, 5 * RESEND)
    assert est.step <= stalled_at + 1 < STEPS
    summary = tmp_path / 'follower.json'
    restarted = node_process('follower_sim', dict(follower_params, summary_path=str(summary)))
    assert run.run(timeout=60.0), \
        f'estimator at step {est.step} after the restart; follower: {restarted.stderr}'
    assert est.step == STEPS
    statuses = run.probe.step_statuses()
    assert [s.step for s in statuses] == list(range(1, STEPS + 1))
    assert statuses[-1].accepted_measurements == STEPS
    # while stalled the estimator kept publishing its status (periodic, same step)
    assert len(run.probe.statuses) > len(statuses)
    x, P = run.probe.estimates[-1]
    assert np.all(np.isfinite(x)) and np.all(np.linalg.eigvalsh(P) > 0)
    restarted.signal(signal.SIGINT)
    assert restarted.wait(timeout=20.0) == 0
    assert 'Traceback' not in restarted.stderr
    # the restarted follower executed the resent waypoint and every later one
    assert json.loads(summary.read_text())['executed_steps'] == STEPS
