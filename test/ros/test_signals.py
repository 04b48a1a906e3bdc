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


def test_interrupted_replay_says_so(ros_domain: int) -> None:
    """Ctrl-C mid-playback: replay reports how much it sent and exits 130, not 0 (a partial
    replay is not a success), without a traceback."""
    import subprocess
    import sys

    from harness.ros import REPO
    bag = REPO / 'test' / 'data' / 'legacy_0.1.0_lockstep_bearing_crm_seed2.mcap'
    process = subprocess.Popen([sys.executable, '-m', 'formopt_ros.cli.replay', str(bag),
                                '--rate', '0.001'], stdout=subprocess.DEVNULL,
                               stderr=subprocess.PIPE, text=True)
    assert process.stderr is not None
    lines = []
    for line in process.stderr:                # blocks per line; the node logs 'replaying'
        lines.append(line)
        if 'replaying' in line:
            break
    process.send_signal(signal.SIGINT)
    _, rest = process.communicate(timeout=30.0)
    stderr = ''.join(lines) + rest
    assert process.returncode == 130, stderr
    assert 'replay: interrupted after ' in stderr and 'Traceback' not in stderr


@pytest.mark.parametrize('mode, steps', [('lockstep', 5), ('realtime', 20)])
def test_hand_started_simulators_end_with_their_run(node_process, tmp_path, mode: str,
                                                    steps: int) -> None:
    """leader_sim, follower_sim and estimator_planner started by hand (as ros2 run does) for a
    run of a set number of steps: the estimator ends with it, and both simulators, having
    driven every step, end too once it has left (ros/guard.py, END_LINGER), all with exit
    code 0 and a summary."""
    common = {'mode': mode, 'recorders': 0}
    processes = {node: node_process(node, {**common, **params,
                                           'summary_path': str(tmp_path / f'{node}.json')})
                 for node, params in (('leader_sim', {}), ('follower_sim', {}),
                                      ('estimator_planner', {'steps': steps}))}
    for node, process in processes.items():
        assert process.wait(timeout=60.0) == 0, (node, process.stderr)
    assert json.loads((tmp_path / 'estimator_planner.json').read_text())['steps'] == steps
    assert json.loads((tmp_path / 'follower_sim.json').read_text())['executed_steps'] >= steps
