"""Recording a lockstep run to MCAP, reading it back (rosbags, mcap), replay, report, bad bags."""
from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from mcap.reader import make_reader  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402

from conftest import domain_environment  # noqa: E402
from formopt_ros import bag as bags  # noqa: E402
from formopt_ros import conversions  # noqa: E402
from formopt_ros.nodes.common import TOPICS  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
DOMAIN_ID = '24'                    # this file's DDS domain (bag tests use 20-29)
SEED, STEPS, KIND, STRATEGY = 3, 40, 'bearing', 'ram'
DEADLINE = 60.0                     # s, for every spin-until-condition loop
INPUTS = ['leader/odom', 'follower/odom', 'follower/measurement', 'follower/truth']
NAMESPACE = f'/bagtest_{os.getpid()}'   # keeps concurrent runs of these tests apart


@pytest.fixture(scope='module')
def ros_env():
    """This module's domain id and localhost discovery, for in-process nodes and children."""
    with domain_environment(DOMAIN_ID, REPO) as env:
        yield env


def ros_args(path: Path, sections: dict[str, dict]) -> list[str]:
    """rclpy.init arguments: this file's namespace and a parameters file (node -> values)."""
    path.write_text(json.dumps({f'/**/{node}' if node != '*' else '/**':
                                {'ros__parameters': values}
                                for node, values in sections.items()}))
    return ['--ros-args', '-r', f'__ns:={NAMESPACE}', '--params-file', str(path)]


def spin_until(executor: SingleThreadedExecutor, condition, deadline: float = DEADLINE) -> None:
    """Spin until condition() holds; fail after deadline seconds."""
    end = time.monotonic() + deadline
    while not condition():
        assert time.monotonic() < end, 'condition not reached before the deadline'
        executor.spin_once(timeout_sec=0.01)


def tap(publisher, sink: list) -> None:
    """Keep a copy of every message the publisher sends."""
    original = publisher.publish

    def publish(msg) -> None:
        sink.append(copy.deepcopy(msg))
        original(msg)

    publisher.publish = publish


@dataclass
class Recording:
    """A recorded lockstep run and what its nodes published."""

    path: Path
    published: dict[str, list]          # resolved topic -> messages, in publish order
    summary: dict                       # estimator summary
    recorder_counts: dict[str, int]


@pytest.fixture(scope='module')
def recording(ros_env, tmp_path_factory) -> Recording:
    """40 lockstep steps (bearing, RAM, seed 3) recorded in-process, on one executor."""
    from formopt_ros.nodes.estimator_planner import EstimatorPlannerNode
    from formopt_ros.nodes.follower_sim import FollowerSim
    from formopt_ros.nodes.leader_sim import LeaderSim
    from formopt_ros.nodes.recorder import Recorder
    folder = tmp_path_factory.mktemp('recording')
    path = folder / 'run.mcap'
    rclpy.init(args=ros_args(folder / 'params.json', {
        '*': {'measurement': KIND, 'seed': SEED, 'strategy': STRATEGY},
        'estimator_planner': {'steps': STEPS, 'peers': 100},      # held until all matched
        'recorder': {'output_path': str(path), 'flush_period': 0.1}}))
    try:
        leader, follower, estimator, recorder = (LeaderSim(), FollowerSim(),
                                                 EstimatorPlannerNode(), Recorder())
        published: dict[str, list] = {}
        for pub in (leader.odom_pub, follower.odom_pub, follower.meas_pub, follower.truth_pub,
                    estimator.estimate_pub, estimator.waypoint_pub, estimator.status_pub):
            tap(pub, published.setdefault(pub.topic_name, []))
        executor = SingleThreadedExecutor()
        for node in (leader, follower, estimator, recorder):
            executor.add_node(node)
        spin_until(executor, lambda: all(s.get_publisher_count() >= 1
                                         for s in recorder.subscriptions)
                   and estimator.waypoint_pub.get_subscription_count() >= 3)
        estimator.params['peers'] = 3                 # leader, follower and the recorder
        spin_until(executor, lambda: estimator.finished)
        total = sum(len(v) for v in published.values())
        spin_until(executor, lambda: sum(recorder.counts.values()) >= total)
        recorder.close()
        result = Recording(path, published, estimator.summary(), dict(recorder.counts))
        for node in (leader, follower, estimator, recorder):
            executor.remove_node(node)
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    return result


def test_zero_loss(recording: Recording) -> None:
    """Every published message is in the bag, per topic; counts agree with the nodes."""
    counts = bags.read_bag(recording.path).counts()
    assert counts == {topic: len(msgs) for topic, msgs in recording.published.items()}
    assert counts == recording.recorder_counts
    assert set(counts) == {f'{NAMESPACE}/{name}' for name in TOPICS.values()}
    assert recording.summary['steps'] == STEPS
    published = recording.summary['message_counts']['published']
    received = recording.summary['message_counts']['received']
    counts = {topic[len(NAMESPACE) + 1:]: n for topic, n in counts.items()}
    assert counts['follower/estimate'] == published['estimate'] == STEPS
    assert counts['follower/status'] == published['status'] == STEPS
    assert counts['follower/waypoint'] == published['waypoint']
    assert counts['leader/odom'] == received['leader_odom'] == 2 * STEPS
    assert counts['follower/measurement'] == received['measurement'] == STEPS


def test_mcap_reader_with_rclpy_deserialization(recording: Recording) -> None:
    """mcap's indexed reader: ros2 profile, ros2msg schemas, metadata; messages == published."""
    with open(recording.path, 'rb') as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == 'ros2'
        summary = reader.get_summary()
        for channel in summary.channels.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == 'cdr' and schema.encoding == 'ros2msg'
            assert schema.data.decode() == bags.message_definition(schema.name)
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
            assert 'reliability: reliable' in channel.metadata['offered_qos_profiles']
        decoded: dict[str, list] = {}
        last_log_time = 0
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            cls = bags.message_class(schema.name)
            msg = deserialize_message(message.data, cls)
            decoded.setdefault(channel.topic, []).append(msg)
            assert message.log_time >= last_log_time
            last_log_time = message.log_time
            assert message.publish_time == conversions.nanoseconds(msg.header.stamp)
    assert decoded.keys() == recording.published.keys()
    for topic, msgs in recording.published.items():
        assert decoded[topic] == msgs, topic


def same_values(published, decoded, where: str = '') -> None:
    """Field by field: an rclpy message equals a rosbags-decoded one (exactly)."""
    for name in published.get_fields_and_field_types():
        a, b = getattr(published, name), getattr(decoded, name)
        if hasattr(a, 'get_fields_and_field_types'):
            same_values(a, b, f'{where}.{name}')
        elif isinstance(a, (str, int, float, bool)):
            assert a == b, f'{where}.{name}: {a!r} != {b!r}'
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where + name)


@pytest.mark.parametrize('typestore', ['embedded', 'registered'])
def test_rosbags_reader(recording: Recording, typestore: str) -> None:
    """rosbags AnyReader decodes every message to the published values.

    'embedded': types only from the bag's ros2msg schemas, whose RIHS01 hashes must equal the
    ones rclpy reported; 'registered': a Jazzy typestore with our msg files registered.
    """
    from rosbags.highlevel import AnyReader
    store = bags.rosbags_typestore() if typestore == 'registered' else None
    with AnyReader([recording.path], default_typestore=store) as reader:
        hashes = {c.topic: reader.typestore.hash_rihs01(c.msgtype) for c in reader.connections}
        decoded: dict[str, list] = {}
        for connection, _, raw in reader.messages():
            decoded.setdefault(connection.topic, []).append(
                reader.deserialize(raw, connection.msgtype))
        for connection in reader.connections:
            assert connection.ext.offered_qos_profiles[0].reliability.name == 'RELIABLE'
    loaded = bags.read_bag(recording.path)
    for topic, channel in loaded.channels.items():
        assert hashes[topic] == channel.metadata['topic_type_hash'], topic
    for topic, msgs in recording.published.items():
        assert len(decoded[topic]) == len(msgs)
        for i, (a, b) in enumerate(zip(msgs, decoded[topic])):
            same_values(a, b, f'{topic}[{i}]')


def recorded_estimates(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    loaded = bags.read_bag(path)
    return [conversions.estimate_values(m)
            for _, m in loaded.decode(loaded.find('follower/estimate'))]


def test_offline_replay_agrees(recording: Recording, ros_env, tmp_path: Path) -> None:
    """The core re-run over the recorded inputs equals the recorded estimates (1e-9)."""
    from formopt_ros.nodes.replay import offline
    result = offline(bags.read_bag(recording.path), seed=SEED)
    assert (result.steps, result.recorded_steps, result.mode) == (STEPS, STEPS, 'lockstep')
    assert (result.strategy, result.measurement) == (STRATEGY, KIND)
    assert result.max_diff <= 1e-9 and result.max_stamp_diff_ns == 0
    assert result.max_waypoint_diff is not None and result.max_waypoint_diff <= 1e-9
    command = subprocess.run(
        [sys.executable, '-m', 'formopt_ros.nodes.replay', str(recording.path), '--offline',
         '--seed', str(SEED), '--json', str(tmp_path / 'offline.json')],
        capture_output=True, text=True, timeout=120, env=ros_env)
    assert command.returncode == 0, command.stderr
    assert 'OK' in command.stdout
    assert json.loads((tmp_path / 'offline.json').read_text())['max_diff'] <= 1e-9


def test_offline_replay_fails_on_a_tampered_estimate(recording: Recording, ros_env,
                                                     tmp_path: Path) -> None:
    """An estimate off by 1e-6 m is reported and the command exits 1."""
    from rclpy.serialization import serialize_message
    loaded = bags.read_bag(recording.path)
    writer = bags.BagWriter(tmp_path / 'tampered.mcap')
    for topic, channel in loaded.channels.items():
        writer.add_channel(topic, channel.type, channel.metadata['offered_qos_profiles'])
    for i, record in enumerate(loaded.messages):
        data = record.data
        if record.topic.endswith('/follower/estimate') and i > len(loaded.messages) // 2:
            msg = deserialize_message(data, bags.message_class(loaded.channels[record.topic]
                                                               .type))
            msg.pose.pose.position.x += 1e-6
            data = serialize_message(msg)
        writer.write(record.topic, data, record.log_time, record.publish_time)
    writer.close()
    command = subprocess.run(
        [sys.executable, '-m', 'formopt_ros.nodes.replay', str(tmp_path / 'tampered.mcap'),
         '--offline', '--seed', str(SEED)], capture_output=True, text=True, timeout=120,
        env=ros_env)
    assert command.returncode == 1, command.stdout + command.stderr
    assert 'FAILED' in command.stdout and 'state 1.000e-06' in command.stdout


@pytest.mark.parametrize('timing', [{'rate': 5.0}, {'fast': True}])
def test_replay_into_live_estimator(recording: Recording, ros_env, tmp_path: Path,
                                    timing: dict) -> None:
    """Republished inputs drive a fresh estimator_planner to the recorded estimates (1e-9)."""
    from formopt_ros.nodes.estimator_planner import EstimatorPlannerNode
    from formopt_ros.nodes.replay import Replay
    rclpy.init(args=ros_args(tmp_path / 'params.json', {
        '*': {'measurement': KIND, 'seed': SEED, 'strategy': STRATEGY},
        'estimator_planner': {'steps': STEPS, 'peers': 0},
        'replay': {'bag_path': str(recording.path), 'topics': INPUTS,
                   'wait_subscribers': 1, **timing}}))
    try:
        estimator = EstimatorPlannerNode()
        estimates: list = []
        tap(estimator.estimate_pub, estimates)
        replay = Replay()
        executor = SingleThreadedExecutor()
        executor.add_node(estimator)
        executor.add_node(replay)
        spin_until(executor, lambda: estimator.finished and replay.finished)
        assert replay.counts == {f'{NAMESPACE}/{t}': n for t, n in zip(INPUTS, (
            2 * STEPS, 2 * STEPS, STEPS, STEPS))}
        for node in (estimator, replay):
            executor.remove_node(node)
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    recorded = recorded_estimates(recording.path)
    assert len(estimates) == len(recorded) == STEPS
    for msg, (x, P) in zip(estimates, recorded):
        x_live, P_live = conversions.estimate_values(msg)
        assert np.max(np.abs(x_live - x)) <= 1e-9 and np.max(np.abs(P_live - P)) <= 1e-9


def test_report(recording: Recording, ros_env, tmp_path: Path) -> None:
    """formopt-report writes the three figures and a summary consistent with the run."""
    out = tmp_path / 'report'
    command = subprocess.run([sys.executable, '-m', 'formopt_ros.report', str(recording.path),
                              '--out', str(out)], capture_output=True, text=True, timeout=120,
                             env=ros_env)
    assert command.returncode == 0, command.stderr
    for name in ('trajectory.png', 'weighted_trace.png', 'nees.png'):
        assert (out / name).read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    summary = json.loads((out / 'summary.json').read_text())
    assert (summary['steps'], summary['strategy'], summary['measurement']) == (
        STEPS, STRATEGY, KIND)
    assert summary['message_counts'] == bags.read_bag(recording.path).counts()
    assert summary['mean_nees'] == pytest.approx(recording.summary['mean_nees'], abs=1e-9)
    assert summary['final_weighted_trace'] == pytest.approx(
        recording.summary['final_weighted_trace'], abs=1e-12)
    assert summary['rejected_measurements'] == summary['rejected_odometry'] == 0
    assert '| steps | 40 |' in (out / 'summary.md').read_text()


# --- bad bags ------------------------------------------------------------------------------
def foreign_bag(path: Path) -> Path:
    """A valid ROS 2 bag without any formation topic."""
    from rclpy.serialization import serialize_message
    from std_msgs.msg import String
    writer = bags.BagWriter(path)
    writer.add_channel('/chatter', 'std_msgs/msg/String')
    writer.write('/chatter', serialize_message(String(data='hi')), 1)
    writer.close()
    return path


def unknown_type_bag(path: Path) -> Path:
    """A bag whose formation topics have a type that is not installed here."""
    from mcap.writer import Writer
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('nosuch_msgs/msg/Estimate', 'ros2msg', b'float64 x\n')
        for topic in bags.TOPIC_TYPES:
            topic = '/' + topic
            channel = writer.register_channel(topic, 'cdr', schema, {})
            writer.add_message(channel, 1, bytes([0, 1, 0, 0]) + bytes(8), 1)
        writer.finish()
    return path


BAD_BAGS = {
    'missing': (lambda p: p / 'absent.mcap', 'no such file'),
    'not_mcap': (lambda p: (p / 'notes.mcap').write_text('not a bag') and p / 'notes.mcap',
                 'not an MCAP file'),
    'no_topics': (lambda p: foreign_bag(p / 'chatter.mcap'), 'no '),
    'unknown_type': (lambda p: unknown_type_bag(p / 'unknown.mcap'), 'unknown message type'),
}
COMMANDS = {
    'report': ['formopt_ros.report', '{bag}', '--out', '{out}'],
    'offline': ['formopt_ros.nodes.replay', '{bag}', '--offline'],
    'replay': ['formopt_ros.nodes.replay', '{bag}', '--topics', 'follower/estimate'],
    'info': ['formopt_ros.bag', 'info', '{bag}'],
}


@pytest.mark.parametrize('case,command', [
    (case, command) for case in sorted(BAD_BAGS) for command in sorted(COMMANDS)
    if not (command == 'info' and case in ('no_topics', 'unknown_type'))])  # info lists any
def test_bad_bag_is_a_clean_error(case: str, command: str, ros_env, tmp_path: Path) -> None:
    """Exit code 2 and one 'error:' line saying what is wrong; never a traceback."""
    make, text = BAD_BAGS[case]
    path = make(tmp_path)
    args = [a.format(bag=path, out=tmp_path / 'out') for a in COMMANDS[command]]
    result = subprocess.run([sys.executable, '-m', *args], capture_output=True, text=True,
                            timeout=120, env=ros_env)
    assert result.returncode == 2, result.stdout + result.stderr
    assert 'Traceback' not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith('error: ') and text in lines[0], lines


def test_truncated_bag_names_the_repair(recording: Recording, ros_env, tmp_path: Path) -> None:
    """A bag cut short (killed recorder) is refused with the repair command in the message."""
    data = recording.path.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:len(data) // 2])
    for command in ('formopt_ros.report', 'formopt_ros.nodes.replay'):
        result = subprocess.run([sys.executable, '-m', command, str(cut), '--out',
                                 str(tmp_path / 'o')] if command.endswith('report') else
                                [sys.executable, '-m', command, str(cut), '--offline'],
                                capture_output=True, text=True, timeout=120, env=ros_env)
        assert result.returncode == 2 and 'Traceback' not in result.stderr
        assert 'truncated' in result.stderr and 'formopt_ros.bag repair' in result.stderr


@pytest.mark.parametrize('node', ['recorder', 'replay'])
def test_config_lists_every_parameter_with_its_default(node: str) -> None:
    """config/<node>.yaml documents exactly the declared parameters, at their defaults."""
    import importlib

    import yaml
    module = importlib.import_module(f'formopt_ros.nodes.{node}')
    values = yaml.safe_load((REPO / 'config' / f'{node}.yaml').read_text())[node]
    assert values['ros__parameters'] == {p.name: p.default for p in module.PARAMS}
