"""The recorder as a process: SIGTERM/SIGINT finalize the bag, SIGKILL + repair, refusals."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from harness.ros import PREFIX, Formation, init, spin_until
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message

from formopt_ros import bag as bags
from formopt_ros.ros.conversions import message_class

DEADLINE = 60.0                     # s, for every wait-until-condition loop
FLUSH_PERIOD = 0.25                 # s, the recorder's flush period in these tests


@pytest.fixture
def recorder_process(node_process):
    """start(path, *params) -> a recorder process with a unique node name under PREFIX."""
    count = []

    def start(path: Path, **params):
        name = f'recorder_{os.getpid()}_{len(count)}'
        count.append(name)
        process = node_process('recorder', {'output_path': str(path),
                                            'flush_period': FLUSH_PERIOD, **params},
                               robot='', extra=['-r', f'__node:={name}'])
        process.node_name = name
        return process
    return start


@pytest.fixture
def formation_in_process(ros_init):
    """make(steps, **params) -> a Formation (lockstep unless mode is given) that starts once the
    recorder and the probe are matched."""
    made = []

    def make(steps: int, **params: object) -> Formation:
        if not made:
            init()
        made.append(Formation({'measurement': 'range', 'seed': 9, 'steps': steps,
                               'recorders': 2, **params}))
        return made[-1]
    yield make
    for item in made:
        item.destroy()


def start_when_recorded(formation: Formation, recorder) -> None:
    """The run starts by itself once every publisher matched the recorder and the probe
    (recorders:=2); wait for its first step (the bag's counts then prove nothing was lost)."""
    assert formation.spin_until(lambda: recorder.process.poll() is None
                                and formation.estimator.session.step > 0, DEADLINE), \
        recorder.stderr


@pytest.mark.parametrize('stop', [signal.SIGTERM, signal.SIGINT])
def test_signal_finalizes_the_bag(recorder_process, formation_in_process, tmp_path: Path,
                                  stop: signal.Signals) -> None:
    """SIGTERM or SIGINT: exit 0, a complete bag with every message, the counts JSON."""
    path, counts = tmp_path / 'run.mcap', tmp_path / 'counts.json'
    recorder = recorder_process(path, counts_path=str(counts))
    formation = formation_in_process(30)
    start_when_recorded(formation, recorder)
    assert formation.spin_until(lambda: formation.estimator.finished, DEADLINE)
    # in the recorder's reader queue; not necessarily taken: close() drains the rest
    assert all(pub.wait_for_all_acked(Duration(seconds=DEADLINE))
               for pub in formation.publishers)
    recorder.signal(stop)
    assert recorder.wait(timeout=30) == 0, recorder.stderr
    loaded = bags.read_bag(path)
    expected = {topic: len(msgs) for topic, msgs in formation.published.items()}
    assert loaded.counts() == expected
    recorded = json.loads(counts.read_text())
    assert recorded['counts'] == expected and recorded['total'] == formation.total()


def test_sigkill_then_repair(recorder_process, formation_in_process, tmp_path: Path) -> None:
    """A killed recorder leaves an unreadable file; repair keeps all but the last ~flush.

    A realtime run (100 sub-steps a second: a rate the recorder keeps up with) is recorded for
    8 flush periods, then the recorder is killed. Kept messages are, per topic, exactly the
    first ones published; the loss is bounded by what the formation published in
    FLUSH_PERIOD + 0.5 s before the kill.
    """
    path, fixed = tmp_path / 'killed.mcap', tmp_path / 'fixed.mcap'
    recorder = recorder_process(path)
    formation = formation_in_process(0, mode='realtime', dt=0.01)
    start_when_recorded(formation, recorder)
    started = time.monotonic()
    formation.spin_until(lambda: time.monotonic() - started > 8 * FLUSH_PERIOD, DEADLINE)
    published = formation.total()
    rate = published / (time.monotonic() - started)
    recorder.kill()
    assert recorder.process.returncode == -signal.SIGKILL
    with pytest.raises(bags.BagError, match='truncated'):
        bags.read_bag(path)
    result = bags.repair(path, fixed)
    print(f'SIGKILL: published {published} ({rate:.0f}/s), repair kept {result.kept}')
    assert not result.was_complete
    assert 0 < result.kept <= published
    assert result.kept >= published - rate * (FLUSH_PERIOD + 0.5), (result.kept, published,
                                                                    rate)
    loaded = bags.read_bag(fixed)
    for topic, sent in formation.published.items():
        records = loaded.records(topic)
        cls = message_class(loaded.channels[topic].type)
        kept = [deserialize_message(r.data, cls) for r in records]
        if topic == '/tf':       # three publishers: their interleaving is the recorder's
            remaining = list(sent)
            for msg in kept:
                remaining.remove(msg)                  # ValueError if it was never sent
        else:
            assert kept == sent[:len(records)], topic
    from rosbags.highlevel import AnyReader
    with AnyReader([fixed]) as reader:
        assert sum(1 for _ in reader.messages()) == result.kept
    repaired = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.bag', 'repair', str(path),
                               str(tmp_path / 'again.mcap')], capture_output=True, text=True,
                              timeout=60)
    assert repaired.returncode == 0 and f'kept {result.kept} messages' in repaired.stdout


def test_refuses_to_overwrite_and_needs_a_path(tmp_path: Path) -> None:
    """An existing output_path or none at all: exit 2, one clear line, the file untouched."""
    path = tmp_path / 'old.mcap'
    path.write_bytes(b'precious')
    for extra, text in (([], 'exists'), (None, 'required')):
        command = [sys.executable, '-m', 'formopt_ros.ros.nodes.recorder']
        if extra is not None:
            command += ['--ros-args', '-p', f'output_path:={path}']
        result = subprocess.run(command, capture_output=True, text=True, timeout=60)
        assert result.returncode == 2, result.stderr
        assert 'Traceback' not in result.stderr
        assert result.stderr.startswith('recorder: error: ') and text in result.stderr
    assert path.read_bytes() == b'precious'


def test_records_a_topic_found_in_the_graph(recorder_process, ros_init, tmp_path: Path) -> None:
    """A topic outside the fixed table is subscribed once the graph shows its type."""
    from std_msgs.msg import String
    path = tmp_path / 'chatter.mcap'
    recorder = recorder_process(path, topics=['chatter'], discovery_period=0.05)
    ros_init(['-r', f'__ns:={PREFIX}'])
    node = rclpy.create_node('chatter')
    publisher = node.create_publisher(String, 'chatter', 10)
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    assert spin_until(executor, lambda: publisher.get_subscription_count() >= 1
                      or recorder.process.poll() is not None, DEADLINE)
    for i in range(20):
        publisher.publish(String(data=f'hello {i}'))
    assert publisher.wait_for_all_acked(Duration(seconds=DEADLINE))
    node.destroy_node()
    recorder.signal(signal.SIGINT)
    assert recorder.wait(timeout=30) == 0, recorder.stderr
    loaded = bags.read_bag(path)
    topic = f'{PREFIX}/chatter'
    assert loaded.channels[topic].type == 'std_msgs/msg/String'
    assert [m.data for _, m in loaded.decode(topic)] == [f'hello {i}' for i in range(20)]


def test_a_full_disk_names_the_file_and_the_run_still_summarises(
        formation_in_process, tmp_path: Path, monkeypatch) -> None:
    """ENOSPC on the 30th message (simulated in the writer): the recorder stops with exit
    code 1 and an error naming the .mcap and ENOSPC (log, counts file); run_formation's
    summary.json names it as the run's failure."""
    import errno
    from types import SimpleNamespace

    from formopt_ros.bag.writer import BagWriter
    from formopt_ros.cli.run_formation import write_summary
    from formopt_ros.core.formation import Formation as Plan
    from formopt_ros.core.formation import FollowerSpec
    from formopt_ros.core.scenario import Scenario
    from formopt_ros.ros.nodes.recorder import Recorder
    write = BagWriter.write
    written = []

    def full(self, topic, data, log_time, publish_time=None) -> None:
        if len(written) >= 29:
            raise OSError(errno.ENOSPC, 'No space left on device')
        written.append(topic)
        write(self, topic, data, log_time, publish_time)

    monkeypatch.setattr(BagWriter, 'write', full)
    out = tmp_path / 'run'
    formation = formation_in_process(20)
    recorder = Recorder(['--ros-args', '-r', f'__ns:={PREFIX}', '-p',
                         f'output_path:={out / "run.mcap"}', '-p',
                         f'counts_path:={out / "recorder_counts.json"}'])
    formation.executor.add_node(recorder)
    assert spin_until(formation.executor, lambda: recorder.finished, DEADLINE)
    assert recorder.exit_code == 1 and sum(recorder.counts.values()) == 29
    assert str(out / 'run.mcap') in recorder.error and 'ENOSPC' in recorder.error
    formation.run(DEADLINE)
    recorder.close()
    formation.executor.remove_node(recorder)
    recorder.destroy_node()
    counts = json.loads((out / 'recorder_counts.json').read_text())
    assert counts['error'] == recorder.error and counts['total'] == 29

    def process(name: str, summary: dict | None, code: int) -> SimpleNamespace:
        return SimpleNamespace(name=name, code=code, restarts=[], summary=lambda: summary,
                               tail=lambda: '', killed=False)
    estimator = process('follower.estimator_planner', formation.estimator.summary(), 0)
    sim = process('follower.follower_sim', formation.follower.summary(), 0)
    leader = process('leader_sim', formation.leader.summary(), 0)
    rec = process('recorder', None, 1)
    plan = Plan('leader', (FollowerSpec('follower', Scenario.paper('range')),))
    args = SimpleNamespace(steps=20, mode='lockstep')
    launcher = SimpleNamespace(processes=[rec, leader, sim, estimator])
    code = write_summary(args, plan, out, launcher, leader, {'follower': (sim, estimator)}, rec,
                         'recorder exited with code 1 before the run finished', 1.0, PREFIX,
                         'run_x')
    summary = json.loads((out / 'summary.json').read_text())
    assert code == 1 and not summary['ok']
    assert str(out / 'run.mcap') in summary['failure'] and 'ENOSPC' in summary['failure']
    assert summary['recording']['error'] == recorder.error
