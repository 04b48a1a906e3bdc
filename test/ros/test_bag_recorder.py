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

rclpy = pytest.importorskip('rclpy')

from rclpy.duration import Duration  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402

from conftest import domain_environment  # noqa: E402
from formopt_ros import bag as bags  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
DOMAIN_ID = '25'                    # this file's DDS domain (bag tests use 20-29)
DEADLINE = 60.0                     # s, for every wait-until-condition loop
FLUSH_PERIOD = 0.25                 # s, the recorder's flush period in these tests
NAMESPACE = f'/bagtest_{os.getpid()}'   # keeps concurrent runs of these tests apart


@pytest.fixture
def ros_env():
    """This file's domain id and localhost discovery, for in-process nodes and children."""
    with domain_environment(DOMAIN_ID, REPO) as env:
        yield env


@pytest.fixture
def processes():
    """Child processes of a test; any still running at teardown is killed."""
    started: list[subprocess.Popen] = []
    yield started
    for process in started:
        if process.poll() is None:
            process.kill()
            process.communicate(timeout=30)


def start_recorder(processes: list, env: dict, path: Path, *extra: str) -> subprocess.Popen:
    """A recorder child named recorder_<n> (unique, so that the graph shows it is ours)."""
    name = f'recorder_{os.getpid()}_{len(processes)}'
    process = subprocess.Popen(
        [sys.executable, '-m', 'formopt_ros.nodes.recorder', '--ros-args', '-r',
         f'__node:={name}', '-r', f'__ns:={NAMESPACE}', '-p', f'output_path:={path}', '-p',
         f'flush_period:={FLUSH_PERIOD}', *extra],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    process.node_name = name
    processes.append(process)
    return process


class Formation:
    """leader_sim, follower_sim and estimator_planner in lockstep, in this process."""

    def __init__(self, folder: Path, steps: int) -> None:
        from formopt_ros.nodes.estimator_planner import EstimatorPlannerNode
        from formopt_ros.nodes.follower_sim import FollowerSim
        from formopt_ros.nodes.leader_sim import LeaderSim
        params = folder / 'params.json'
        params.write_text(json.dumps({
            '/**': {'ros__parameters': {'measurement': 'range', 'seed': 9}},
            '/**/estimator_planner': {'ros__parameters': {'steps': steps, 'peers': 100}}}))
        rclpy.init(args=['--ros-args', '-r', f'__ns:={NAMESPACE}', '--params-file',
                         str(params)])
        self.leader, self.follower, self.estimator = (LeaderSim(), FollowerSim(),
                                                      EstimatorPlannerNode())
        self.published: dict[str, list[bytes]] = {}
        self.publishers = [self.leader.odom_pub, self.follower.odom_pub, self.follower.meas_pub,
                           self.follower.truth_pub, self.estimator.estimate_pub,
                           self.estimator.waypoint_pub, self.estimator.status_pub]
        for pub in self.publishers:
            self._tap(pub)
        self.executor = SingleThreadedExecutor()
        for node in (self.leader, self.follower, self.estimator):
            self.executor.add_node(node)

    def _tap(self, pub) -> None:
        sink = self.published.setdefault(pub.topic_name, [])
        original = pub.publish

        def publish(msg) -> None:
            sink.append(msg)
            original(msg)

        pub.publish = publish

    def total(self) -> int:
        return sum(len(v) for v in self.published.values())

    def spin_until(self, condition, deadline: float = DEADLINE) -> None:
        end = time.monotonic() + deadline
        while not condition():
            assert time.monotonic() < end, 'condition not reached before the deadline'
            self.executor.spin_once(timeout_sec=0.01)

    def start_when_recorded(self, recorder: subprocess.Popen) -> None:
        """Wait until the recorder is matched on every topic, then let the run begin."""
        # subscribers inside this process: leader/odom by follower and estimator, ...
        inside = {'leader/odom': 2, 'follower/odom': 1, 'follower/measurement': 1,
                  'follower/truth': 1, 'follower/estimate': 0, 'follower/waypoint': 2,
                  'follower/status': 0}

        def matched(pub) -> bool:
            relative = pub.topic_name[len(NAMESPACE) + 1:]
            return pub.get_subscription_count() > inside[relative] and any(
                info.node_name == recorder.node_name
                for info in self.leader.get_subscriptions_info_by_topic(pub.topic_name))

        self.spin_until(lambda: recorder.poll() is None and all(
            matched(pub) for pub in self.publishers))
        self.estimator.params['peers'] = 3

    def close(self) -> None:
        for node in (self.leader, self.follower, self.estimator):
            self.executor.remove_node(node)
            node.destroy_node()
        rclpy.try_shutdown()


@pytest.mark.parametrize('stop', [signal.SIGTERM, signal.SIGINT])
def test_signal_finalizes_the_bag(ros_env, processes, tmp_path: Path, stop: signal.Signals
                                  ) -> None:
    """SIGTERM or SIGINT: exit 0, a complete bag with every message, the counts JSON."""
    path, counts = tmp_path / 'run.mcap', tmp_path / 'counts.json'
    recorder = start_recorder(processes, ros_env, path, '-p', f'counts_path:={counts}')
    formation = Formation(tmp_path, steps=30)
    try:
        formation.start_when_recorded(recorder)
        formation.spin_until(lambda: formation.estimator.finished)
        total = formation.total()
        # in the recorder's reader queue; not necessarily taken: close() drains the rest
        assert all(pub.wait_for_all_acked(Duration(seconds=DEADLINE))
                   for pub in formation.publishers)
    finally:
        formation.close()
    recorder.send_signal(stop)
    _, err = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, err
    loaded = bags.read_bag(path)
    expected = {topic: len(msgs) for topic, msgs in formation.published.items()}
    assert loaded.counts() == expected
    assert json.loads(counts.read_text())['counts'] == expected
    assert f'recorded {total} messages' in err


def test_sigkill_then_repair(ros_env, processes, tmp_path: Path) -> None:
    """A killed recorder leaves an unreadable file; repair keeps all but the last ~flush.

    Kept messages are, per topic, exactly the first ones published; the loss is bounded by
    what the formation published in FLUSH_PERIOD + 0.5 s before the kill.
    """
    path, fixed = tmp_path / 'killed.mcap', tmp_path / 'fixed.mcap'
    recorder = start_recorder(processes, ros_env, path)
    formation = Formation(tmp_path, steps=0)
    try:
        formation.start_when_recorded(recorder)
        started = time.monotonic()
        formation.spin_until(lambda: time.monotonic() - started > 4 * FLUSH_PERIOD
                             and formation.estimator.step >= 400)
        published = formation.total()
        rate = published / (time.monotonic() - started)
        recorder.kill()
        recorder.communicate(timeout=30)
    finally:
        formation.close()
    assert recorder.returncode == -signal.SIGKILL
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
        cls = bags.message_class(loaded.channels[topic].type)
        assert [deserialize_message(r.data, cls) for r in records] == sent[:len(records)]
    from rosbags.highlevel import AnyReader
    with AnyReader([fixed]) as reader:
        assert sum(1 for _ in reader.messages()) == result.kept
    repaired = subprocess.run([sys.executable, '-m', 'formopt_ros.bag', 'repair', str(path),
                               str(tmp_path / 'again.mcap')], capture_output=True, text=True,
                              timeout=60, env=ros_env)
    assert repaired.returncode == 0 and f'kept {result.kept} messages' in repaired.stdout


def test_refuses_to_overwrite_and_needs_a_path(ros_env, tmp_path: Path) -> None:
    """An existing output_path or none at all: exit 2, one clear line, the file untouched."""
    path = tmp_path / 'old.mcap'
    path.write_bytes(b'precious')
    for extra, text in (([], 'exists'), (None, 'required')):
        command = [sys.executable, '-m', 'formopt_ros.nodes.recorder']
        if extra is not None:
            command += ['--ros-args', '-p', f'output_path:={path}']
        result = subprocess.run(command, capture_output=True, text=True, timeout=60,
                                env=ros_env)
        assert result.returncode == 2, result.stderr
        assert 'Traceback' not in result.stderr
        assert result.stderr.startswith('error: ') and text in result.stderr
    assert path.read_bytes() == b'precious'


def test_records_a_topic_found_in_the_graph(ros_env, processes, tmp_path: Path) -> None:
    """A topic outside the fixed table is subscribed once the graph shows its type."""
    from std_msgs.msg import String
    path = tmp_path / 'chatter.mcap'
    recorder = start_recorder(processes, ros_env, path, '-p', 'topics:=[chatter]',
                              '-p', 'discovery_period:=0.05')
    rclpy.init(args=['--ros-args', '-r', f'__ns:={NAMESPACE}'])
    try:
        node = rclpy.create_node('chatter')
        publisher = node.create_publisher(String, 'chatter', 10)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        end = time.monotonic() + DEADLINE
        while publisher.get_subscription_count() < 1:
            assert time.monotonic() < end and recorder.poll() is None
            executor.spin_once(timeout_sec=0.01)
        for i in range(20):
            publisher.publish(String(data=f'hello {i}'))
        assert publisher.wait_for_all_acked(Duration(seconds=DEADLINE))
        node.destroy_node()
    finally:
        rclpy.try_shutdown()
    recorder.send_signal(signal.SIGINT)
    _, err = recorder.communicate(timeout=30)
    assert recorder.returncode == 0, err
    loaded = bags.read_bag(path)
    topic = f'{NAMESPACE}/chatter'
    assert loaded.channels[topic].type == 'std_msgs/msg/String'
    assert [m.data for _, m in loaded.decode(topic)] == [f'hello {i}' for i in range(20)]
