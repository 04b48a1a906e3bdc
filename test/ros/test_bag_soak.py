"""Loss measurement, not in the default suite: a realtime run at 1/dt recorded to MCAP.

Run it with ``FORMOPT_SOAK_SECONDS=600 .venv/bin/python -m pytest -q -s
test/ros/test_bag_soak.py`` (optional FORMOPT_SOAK_OUT=DIR keeps the logs, bag and result).
Each node is its own process; the recorder starts first and stops last, after the publishers
exited, so the bag must hold exactly what the nodes say they published.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

SECONDS = float(os.environ.get('FORMOPT_SOAK_SECONDS', '0'))
pytestmark = pytest.mark.skipif(SECONDS <= 0, reason='set FORMOPT_SOAK_SECONDS to run')

REPO = Path(__file__).resolve().parents[2]
DOMAIN_ID = '26'                    # this file's DDS domain (bag tests use 20-29)
DT = 0.05                           # s: 20 Hz odometry
NAMESPACE = f'/soak_{os.getpid()}'


def wait_for(condition, timeout: float, what: str) -> None:
    """Poll condition() (every 0.1 s) until it holds; fail after timeout s."""
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f'timed out waiting for {what}'
        time.sleep(0.1)


class Process:
    """One node process with its log file."""

    def __init__(self, folder: Path, node: str, env: dict, *params: str) -> None:
        self.log = folder / f'{node}.log'
        args = [a for p in params for a in ('-p', p)]
        self.process = subprocess.Popen(
            [sys.executable, '-m', f'formopt_ros.nodes.{node}', '--ros-args', '-r',
             f'__ns:={NAMESPACE}', *args], env=env, stdout=self.log.open('w'),
            stderr=subprocess.STDOUT)

    def text(self) -> str:
        return self.log.read_text(errors='replace')

    def stop(self, timeout: float = 30.0) -> int:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGINT)
        return self.process.wait(timeout=timeout)


def test_realtime_run_records_without_loss(tmp_path: Path) -> None:
    """Bag counts per topic == the counts the nodes published, apart from the discovery window.

    leader_sim publishes from its start, before the recorder may have discovered it (cross-
    process discovery took up to a few seconds here): those leader odometry messages, counted
    from leader_sim's 'ready' log time to the first recorded stamp, cannot reach any
    subscriber. Everything after must be in the bag: published - recorded == that count (+-1
    for the tick phase), every other topic complete. (The largest stamp gaps are reported too;
    they show timer jitter of the publishers, not loss.)
    """
    from formopt_ros import bag as bags
    folder = Path(os.environ.get('FORMOPT_SOAK_OUT', tmp_path))
    folder.mkdir(parents=True, exist_ok=True)
    path, counts_path = folder / 'soak.mcap', folder / 'recorder_counts.json'
    for old in (path, counts_path):
        old.unlink(missing_ok=True)
    env = dict(os.environ, PYTHONPATH=str(REPO), ROS_DOMAIN_ID=DOMAIN_ID,
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST')
    steps = int(round(SECONDS / (2 * DT)))
    common = ['mode:=realtime', f'dt:={DT}', 'measurement:=range', 'seed:=1']
    processes = []
    try:
        recorder = Process(folder, 'recorder', env, f'output_path:={path}',
                           f'counts_path:={counts_path}')
        processes.append(recorder)
        wait_for(lambda: 'recording 7 topics' in recorder.text(), 60, 'the recorder')
        leader = Process(folder, 'leader_sim', env, *common)
        follower = Process(folder, 'follower_sim', env, *common)
        processes += [leader, follower]
        wait_for(lambda: 'ready' in leader.text() and 'ready' in follower.text(), 60,
                 'leader_sim and follower_sim')
        estimator = Process(folder, 'estimator_planner', env, *common, 'strategy:=ram',
                            f'steps:={steps}', 'peers:=3',
                            f"summary_path:={folder / 'estimator_summary.json'}")
        processes.append(estimator)
        started = time.monotonic()
        assert estimator.process.wait(timeout=SECONDS * 1.5 + 120) == 0
        run_time = time.monotonic() - started
        assert leader.stop() == 0 and follower.stop() == 0      # publishers first, ...
        assert recorder.stop() == 0                              # ... then the recorder
    finally:
        for item in processes:
            if item.process.poll() is None:
                item.process.kill()
                item.process.wait(timeout=30)
    summary = json.loads((folder / 'estimator_summary.json').read_text())
    leader_count = int(re.search(r'leader_sim published (\d+) odometry', leader.text())[1])
    match = re.search(r"executed (\d+) steps, \{'published': (\d+)", follower.text())
    executed, follower_total = int(match[1]), int(match[2])
    published = summary['message_counts']['published']
    expected = {
        'leader/odom': leader_count, 'follower/odom': follower_total - 2 * executed,
        'follower/truth': executed, 'follower/measurement': executed,
        'follower/estimate': published['estimate'], 'follower/waypoint': published['waypoint'],
        'follower/status': published['status']}
    loaded = bags.read_bag(path)
    recorded = {name: len(loaded.records(loaded.find(name))) for name in expected}
    assert json.loads(counts_path.read_text())['total'] == len(loaded.messages)
    ready = float(re.search(r'\[(\d+\.\d+)\] \[[^]]*leader_sim\]: leader_sim ready',
                            leader.text())[1])
    leader_stamps = [r.publish_time for r in loaded.records(loaded.find('leader/odom'))]
    before_discovery = round((leader_stamps[0] * 1e-9 - ready) / DT) - 1
    gaps = {name: max(b - a for a, b in zip(stamps, stamps[1:])) * 1e-9 for name, stamps in (
        (name, [r.publish_time for r in loaded.records(loaded.find(name))])
        for name in ('leader/odom', 'follower/odom'))}
    lost = {k: expected[k] - recorded[k] for k in expected}
    result = {'seconds_requested': SECONDS, 'run_time_s': run_time, 'steps': summary['steps'],
              'dt': DT, 'bag': str(path), 'bag_bytes': path.stat().st_size,
              'published': expected, 'recorded': recorded, 'lost': lost,
              'leader_odom_before_discovery': before_discovery,
              'first_leader_odom_after_ready_s': leader_stamps[0] * 1e-9 - ready,
              'max_stamp_gap_s': gaps,
              'estimator_received': summary['message_counts']['received']}
    (folder / 'soak_result.json').write_text(json.dumps(result, indent=2) + '\n')
    print(json.dumps(result, indent=2))
    assert summary['steps'] == steps
    assert abs(lost.pop('leader/odom') - before_discovery) <= 1, result
    assert all(n == 0 for n in lost.values()), result
