"""Loss measurement: a realtime run at 1/dt recorded to MCAP, 8 s in the default suite.

A long run: ``FORMOPT_SOAK_SECONDS=600 .venv/bin/python -m pytest -q -s
test/ros/test_bag_soak.py`` (optional FORMOPT_SOAK_OUT=DIR keeps the logs, bag and result).
Each node is its own process; the recorder starts first and stops last, after the publishers
exited, so the bag must hold exactly what the nodes say they published (the same comparison
run_formation makes).
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

SECONDS = float(os.environ.get('FORMOPT_SOAK_SECONDS', '8'))

DT = 0.05                           # s: 20 Hz odometry


def test_realtime_run_records_without_loss(node_process, tmp_path: Path) -> None:
    """Bag counts per topic == the counts the nodes say they published (their summaries)."""
    from harness.ros import PREFIX

    from formopt_ros import bag as bags
    from formopt_ros.cli.audit import expected_counts
    folder = Path(os.environ.get('FORMOPT_SOAK_OUT', tmp_path))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / 'soak.mcap'
    path.unlink(missing_ok=True)
    steps = int(round(SECONDS / (2 * DT)))
    common = {'mode': 'realtime', 'dt': DT, 'measurement': 'range', 'seed': 1}
    summaries = {node: folder / f'{node}_summary.json'
                 for node in ('leader_sim', 'follower_sim', 'estimator_planner')}
    recorder = node_process('recorder', {'output_path': str(path),
                                         'counts_path': str(folder / 'counts.json')}, robot='')
    assert recorder.wait_for_line('recording'), recorder.stderr
    leader = node_process('leader_sim', {**common, 'summary_path': str(summaries['leader_sim'])})
    follower = node_process('follower_sim', {**common,
                                             'summary_path': str(summaries['follower_sim'])})
    assert leader.wait_for_line('ready') and follower.wait_for_line('ready')
    estimator = node_process('estimator_planner', {
        **common, 'strategy': 'ram', 'steps': steps,
        'summary_path': str(summaries['estimator_planner'])})
    started = time.monotonic()
    assert estimator.wait(timeout=SECONDS * 1.5 + 120) == 0, estimator.stderr
    run_time = time.monotonic() - started
    for process in (leader, follower):                  # publishers first, ...
        process.signal(2)
        assert process.wait(timeout=30) == 0
    recorder.signal(2)                                   # ... then the recorder
    assert recorder.wait(timeout=30) == 0
    read = {node: json.loads(p.read_text()) for node, p in summaries.items()}
    expected = expected_counts(PREFIX, read['leader_sim'], {
        'follower': (read['follower_sim'], read['estimator_planner'])}, remapped=False)
    recorded = bags.read_bag(path).counts()
    lost = {name: expected[name] - recorded.get(name, 0) for name in expected}
    result = {'seconds_requested': SECONDS, 'run_time_s': run_time, 'dt': DT, 'bag': str(path),
              'bag_bytes': path.stat().st_size, 'published': expected, 'recorded': recorded,
              'lost': lost}
    (folder / 'soak_result.json').write_text(json.dumps(result, indent=2) + '\n')
    print(json.dumps(result, indent=2))
    assert read['estimator_planner']['steps'] == steps
    assert expected[f'{PREFIX}/follower/measurement'] >= steps
    assert all(n == 0 for n in lost.values()), result
