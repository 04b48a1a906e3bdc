"""Each node executable stops cleanly (exit 0, no traceback, close() ran) on SIGINT/SIGTERM."""
from __future__ import annotations

import json
import signal

import pytest

#: What the summary written by close() says of a node that never ran a step.
CLOSED = {'leader_sim': ('served_steps', 0), 'follower_sim': ('executed_steps', 0),
          'estimator_planner': ('steps', 0)}


@pytest.mark.parametrize('signum', [signal.SIGINT, signal.SIGTERM], ids=['SIGINT', 'SIGTERM'])
@pytest.mark.parametrize('node', ['leader_sim', 'follower_sim', 'estimator_planner'])
def test_signal_stops_node_cleanly(node_process, tmp_path, node: str, signum: int) -> None:
    summary = tmp_path / 'summary.json'
    process = node_process(node, {'summary_path': str(summary)})
    assert process.wait_for_line(rf'{node} ready'), process.stderr
    process.signal(signum)
    code = process.wait(timeout=20.0)
    stderr = process.stderr
    assert code == 0, stderr
    assert 'Traceback' not in stderr
    assert 'rosout' not in stderr          # logging after the context shut down
    key, value = CLOSED[node]
    assert json.loads(summary.read_text())[key] == value
