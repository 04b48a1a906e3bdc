"""A node started with a bad parameter value exits with code 2 and names it, no traceback."""
from __future__ import annotations

import pytest

CASES = [
    ('leader_sim', 'dt', '-1.0', '-1.0'),
    ('follower_sim', 'dt', '0.0', '0.0'),
    ('estimator_planner', 'strategy', 'foo', "'foo'"),
    ('follower_sim', 'measurement', 'sonar', "'sonar'"),
    ('estimator_planner', 'seed', '-3', '-3'),
    ('leader_sim', 'mode', 'warp', "'warp'"),
    ('estimator_planner', 'sigma_v', 'fast', "'fast'"),
    ('follower_sim', 'formation_slot', '[1.0, 2.0, 3.0]', '[1.0, 2.0, 3.0]'),
]


@pytest.mark.parametrize(('node', 'name', 'value', 'shown'), CASES,
                         ids=[f'{c[0]}-{c[1]}' for c in CASES])
def test_bad_parameter_exits_2(node_process, node: str, name: str, value: str,
                               shown: str) -> None:
    process = node_process(node, {name: value})
    code = process.wait(timeout=60.0)
    stderr = process.stderr
    assert code == 2, stderr
    assert 'Traceback' not in stderr
    assert f"parameter '{name}'" in stderr
    assert f'got {shown}' in stderr
    assert ' ready ' not in stderr
