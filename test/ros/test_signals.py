"""Each node executable stops cleanly (exit 0, no traceback, close() ran) on SIGINT/SIGTERM."""
from __future__ import annotations

import json
import signal

import pytest

#: A line that close() logs (or the file it writes) proves the shutdown path ran.
CLOSED = {'leader_sim': 'leader_sim published 0 odometry messages',
          'follower_sim': 'follower_sim: executed 0 steps'}


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
@pytest.mark.parametrize('node', ['leader_sim', 'follower_sim', 'estimator_planner'])
def test_signal_stops_node_cleanly(node_process, tmp_path, node: str, signum: int) -> None:
    summary = tmp_path / 'summary.json'
    params = {'summary_path': str(summary)} if node == 'estimator_planner' else {}
    process = node_process(node, params)
    assert process.wait_for_line(rf'\[{node}\]: {node} ready'), process.stderr
    process.signal(signum)
    code = process.wait(timeout=20.0)
    stderr = process.stderr
    assert code == 0, stderr
    assert 'Traceback' not in stderr
    assert 'rosout' not in stderr          # logging after the context shut down
    if node == 'estimator_planner':
        assert json.loads(summary.read_text())['steps'] == 0
    else:
        assert CLOSED[node] in stderr
