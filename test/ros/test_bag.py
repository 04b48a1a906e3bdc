"""Recording a lockstep run to MCAP, reading it back (rosbags, mcap), replay, report, bad bags."""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import rclpy
from harness.ros import PREFIX, Formation, node_args, parameter_args, spin_until, tap
from mcap.reader import make_reader
from rclpy.executors import SingleThreadedExecutor
from rclpy.serialization import deserialize_message

from formopt_ros import bag as bags
from formopt_ros.analysis.offline import offline
from formopt_ros.analysis.recording import load_recording
from formopt_ros.bag.schema import message_definition
from formopt_ros.ros.conversions import message_class
from formopt_ros.wire.messages import estimate_values, header_ns
from formopt_ros.wire.topics import formation_topics

SEED, STEPS, KIND, STRATEGY = 3, 60, 'bearing', 'ram'
DEADLINE = 60.0                     # s, for every spin-until-condition loop
INPUTS = ['leader/odom', 'follower/odom', 'follower/measurement', 'follower/truth']


def spin(executor: SingleThreadedExecutor, condition) -> None:
    """Spin until condition() holds; fail after DEADLINE seconds."""
    assert spin_until(executor, condition, DEADLINE), 'condition not reached before the deadline'


@dataclass
class Recording:
    """A recorded lockstep run and what its nodes published."""

    path: Path
    published: dict[str, list]          # resolved topic -> messages, in publish order
    summary: dict                       # estimator summary
    recorder_counts: dict[str, int]


@pytest.fixture(scope='module')
def recording(tmp_path_factory) -> Recording:
    """60 lockstep steps (bearing, RAM, seed 3) recorded in-process, on one executor; the nodes
    wait for the recorder and the test probe (recorders:=2) before the run starts."""
    from formopt_ros.ros.nodes.recorder import Recorder
    folder = tmp_path_factory.mktemp('recording')
    path = folder / 'run.mcap'
    rclpy.init()
    try:
        formation = Formation({'measurement': KIND, 'seed': SEED, 'strategy': STRATEGY,
                               'recorders': 2, 'steps': STEPS})
        recorder = Recorder(['--ros-args', '-r', f'__ns:={PREFIX}', '-p',
                             f'output_path:={path}', '-p', 'flush_period:=0.1'])
        formation.executor.add_node(recorder)
        spin(formation.executor, lambda: formation.estimator.finished)
        total = formation.total()
        spin(formation.executor, lambda: sum(recorder.counts.values()) >= total)
        recorder.close()
        result = Recording(path, formation.published, formation.estimator.summary(),
                           dict(recorder.counts))
        formation.executor.remove_node(recorder)
        recorder.destroy_node()
        formation.destroy()
    finally:
        rclpy.try_shutdown()
    return result


def test_zero_loss(recording: Recording) -> None:
    """Every published message is in the bag, per topic; counts agree with the nodes."""
    counts = bags.read_bag(recording.path).counts()
    assert counts == {name: len(msgs) for name, msgs in recording.published.items()}
    assert counts == recording.recorder_counts
    assert set(counts) == {name if name.startswith(('/tf', '/clock', '/diag')) else PREFIX + name
                           for name in formation_topics()}
    assert recording.summary['steps'] == STEPS
    published = recording.summary['message_counts']['published']
    received = recording.summary['message_counts']['received']
    counts = {name[len(PREFIX) + 1:] if name.startswith(PREFIX) else name: n
              for name, n in counts.items()}
    assert counts['follower/description'] == counts['leader/description'] == 1
    assert counts['/clock'] == 2 * STEPS and counts['/tf_static'] == 1
    assert counts['/tf'] == 2 * STEPS + 3 * STEPS + STEPS      # leader, follower, estimator
    assert counts['follower/estimate'] == published['estimate'] == STEPS
    # a status after every step, plus the periodic ones (one when the run starts)
    assert counts['follower/status'] == published['status'] >= STEPS
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
            assert schema.data.decode() == message_definition(schema.name)
            assert channel.metadata['topic_type_hash'].startswith('RIHS01_')
            offered = channel.metadata['offered_qos_profiles']
            assert 'reliability: reliable' in offered
            latched = channel.topic.endswith(('description', '/tf_static'))
            assert ('durability: transient_local' in offered) == latched, channel.topic
        decoded: dict[str, list] = {}
        last_log_time = 0
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            msg = deserialize_message(message.data, message_class(schema.name))
            decoded.setdefault(channel.topic, []).append(msg)
            assert message.log_time >= last_log_time
            last_log_time = message.log_time
            if hasattr(msg, 'header'):          # headerless: publish_time = log_time
                assert message.publish_time == header_ns(msg)
            else:
                assert message.publish_time == message.log_time
    assert decoded.keys() == recording.published.keys()
    for topic, msgs in recording.published.items():
        assert decoded[topic] == msgs, topic


def same_values(published, decoded, where: str = '') -> None:
    """Field by field: an rclpy message equals a rosbags-decoded one (exactly)."""
    for name in published.get_fields_and_field_types():
        a, b = getattr(published, name), getattr(decoded, name)
        if hasattr(a, 'get_fields_and_field_types'):
            same_values(a, b, f'{where}.{name}')
        elif isinstance(a, list) and a and hasattr(a[0], 'get_fields_and_field_types'):
            assert len(a) == len(b), f'{where}.{name}: {len(a)} != {len(b)} items'
            for i, (x, y) in enumerate(zip(a, b)):
                same_values(x, y, f'{where}.{name}[{i}]')
        elif isinstance(a, (str, int, float, bool)):
            assert a == b, f'{where}.{name}: {a!r} != {b!r}'
        elif isinstance(a, bytes) and len(a) == 1:     # ROS 'byte': rclpy bytes, rosbags int
            assert a[0] == b, f'{where}.{name}: {a!r} != {b!r}'
        else:
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=where + name)


@pytest.mark.parametrize('reader', ['anyreader', 'formopt'])
def test_rosbags_reader(recording: Recording, reader: str) -> None:
    """rosbags decodes every message to the published values, with types only from the bag's
    ros2msg schemas (whose RIHS01 hashes equal the ones rclpy reported): through rosbags'
    AnyReader, and through formopt_ros.bag (no ROS)."""
    decoded: dict[str, list] = {}
    if reader == 'anyreader':
        from rosbags.highlevel import AnyReader
        with AnyReader([recording.path]) as any_reader:
            hashes = {c.topic: any_reader.typestore.hash_rihs01(c.msgtype)
                      for c in any_reader.connections}
            for connection, _, raw in any_reader.messages():
                decoded.setdefault(connection.topic, []).append(
                    any_reader.deserialize(raw, connection.msgtype))
        loaded = bags.read_bag(recording.path)
        for name, channel in loaded.channels.items():
            assert hashes[name] == channel.metadata['topic_type_hash'], name
    else:
        loaded = bags.read_bag(recording.path)
        for name in loaded.channels:
            decoded[name] = [msg for _, msg in loaded.decode(name)]
    for name, msgs in recording.published.items():
        assert len(decoded[name]) == len(msgs)
        for i, (a, b) in enumerate(zip(msgs, decoded[name])):
            same_values(a, b, f'{name}[{i}]')


def recorded_estimates(path: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    loaded = bags.read_bag(path)
    return [estimate_values(m) for _, m in loaded.decode(loaded.find('follower/estimate'))]


def test_offline_replay_agrees(recording: Recording, tmp_path: Path) -> None:
    """The core re-run over the recorded inputs equals the recorded estimates (1e-9); the run
    description in the bag supplies the scenario, strategy and seed."""
    result = offline(load_recording(bags.read_bag(recording.path)))
    assert (result.steps, result.recorded_steps, result.mode) == (STEPS, STEPS, 'lockstep')
    assert (result.strategy, result.measurement, result.legacy) == (STRATEGY, KIND, False)
    assert result.max_diff <= 1e-9 and result.max_stamp_diff_ns == 0
    assert result.max_waypoint_diff is not None and result.max_waypoint_diff <= 1e-9
    command = subprocess.run(
        [sys.executable, '-m', 'formopt_ros.cli.replay', str(recording.path), '--offline',
         '--json', str(tmp_path / 'offline.json')],
        capture_output=True, text=True, timeout=120)
    assert command.returncode == 0, command.stderr
    assert 'OK' in command.stdout
    assert json.loads((tmp_path / 'offline.json').read_text())['max_diff'] <= 1e-9


def test_offline_replay_with_another_strategy_fails(recording: Recording) -> None:
    """Another planner over the same inputs estimates the same states but sends other
    waypoints: the replay reports the waypoint difference and FAILED, exit 1."""
    other = 'mtf' if STRATEGY != 'mtf' else 'ram'
    command = subprocess.run(
        [sys.executable, '-m', 'formopt_ros.cli.replay', str(recording.path), '--offline',
         '--strategy', other], capture_output=True, text=True, timeout=120)
    assert command.returncode == 1, command.stdout + command.stderr
    assert 'FAILED' in command.stdout and 'state 0.000e+00' in command.stdout


def test_offline_replay_fails_on_a_tampered_estimate(recording: Recording,
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
            msg = deserialize_message(data, message_class(loaded.channels[record.topic].type))
            msg.pose.pose.position.x += 1e-6
            data = serialize_message(msg)
        writer.write(record.topic, data, record.log_time, record.publish_time)
    writer.close()
    command = subprocess.run(
        [sys.executable, '-m', 'formopt_ros.cli.replay', str(tmp_path / 'tampered.mcap'),
         '--offline'], capture_output=True, text=True, timeout=120)
    assert command.returncode == 1, command.stdout + command.stderr
    assert 'FAILED' in command.stdout and 'state 1.000e-06' in command.stdout


@pytest.mark.parametrize('timing', [{'rate': 5.0}, {'fast': True}])
def test_replay_into_live_estimator(recording: Recording, tmp_path: Path,
                                    timing: dict) -> None:
    """Republished inputs drive a fresh estimator_planner to the recorded estimates (1e-9)."""
    from formopt_ros.ros.nodes.estimator_planner import EstimatorPlannerNode
    from formopt_ros.ros.nodes.replay import Replay
    rclpy.init()
    try:
        estimator = EstimatorPlannerNode(node_args('estimator_planner', 'follower', {
            'measurement': KIND, 'seed': SEED, 'strategy': STRATEGY, 'steps': STEPS,
            'recorders': 0, 'wait_for_peers': False}))
        estimates: list = []
        tap(estimator.estimate_pub, estimates)
        replay = Replay(cli_args=['--ros-args', '-r', f'__ns:={PREFIX}', *parameter_args({
            'bag_path': str(recording.path), 'topics': INPUTS, 'wait_subscribers': 1,
            **timing})])
        executor = SingleThreadedExecutor()
        executor.add_node(estimator)
        executor.add_node(replay)
        spin(executor, lambda: estimator.finished and replay.finished)
        assert replay.counts == {f'{PREFIX}/{t}': n for t, n in zip(INPUTS, (
            2 * STEPS, 2 * STEPS, STEPS, STEPS))}
        for node in (estimator, replay):
            executor.remove_node(node)
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
    recorded = recorded_estimates(recording.path)
    assert len(estimates) == len(recorded) == STEPS
    for msg, (x, P) in zip(estimates, recorded):
        x_live, P_live = estimate_values(msg)
        assert np.max(np.abs(x_live - x)) <= 1e-9 and np.max(np.abs(P_live - P)) <= 1e-9


def test_report(recording: Recording, tmp_path: Path) -> None:
    """formopt-report writes the three figures and a summary consistent with the run."""
    out = tmp_path / 'report'
    command = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.report',
                              str(recording.path), '--out', str(out)], capture_output=True,
                             text=True, timeout=120)
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
    assert summary['description'] == 'recorded'
    assert '| follower | bearing | ram | [-1, 2] |' in (out / 'summary.md').read_text()


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
    """A bag whose formation topic names carry a type that is not installed here."""
    from mcap.writer import Writer
    with open(path, 'wb') as stream:
        writer = Writer(stream)
        writer.start(profile='ros2', library='test')
        schema = writer.register_schema('nosuch_msgs/msg/Estimate', 'ros2msg', b'float64 x\n')
        for name in formation_topics():
            channel = writer.register_channel(name, 'cdr', schema, {})
            writer.add_message(channel, 1, bytes([0, 1, 0, 0]) + bytes(8), 1)
        writer.finish()
    return path


BAD_BAGS = {
    'missing': lambda p: p / 'absent.mcap',
    'not_mcap': lambda p: (p / 'notes.mcap').write_text('not a bag') and p / 'notes.mcap',
    'no_topics': lambda p: foreign_bag(p / 'chatter.mcap'),
    'unknown_type': lambda p: unknown_type_bag(p / 'unknown.mcap'),
}
#: What the one error line says, per bag and command ('info' lists any valid bag).
EXPECTED = {
    'missing': {'report': 'no such file', 'offline': 'no such file', 'replay': 'no such file',
                'info': 'no such file'},
    'not_mcap': {'report': 'not an MCAP file', 'offline': 'not an MCAP file',
                 'replay': 'not an MCAP file', 'info': 'not an MCAP file'},
    'no_topics': {'report': 'no follower topics', 'offline': 'no follower topics',
                  'replay': 'no topic'},
    'unknown_type': {'report': 'no follower topics', 'offline': 'no follower topics',
                     'replay': 'unknown message type'},
}
COMMANDS = {
    'report': ('formopt-report', ['formopt_ros.cli.report', '{bag}', '--out', '{out}']),
    'offline': ('replay', ['formopt_ros.cli.replay', '{bag}', '--offline']),
    'replay': ('replay', ['formopt_ros.cli.replay', '{bag}', '--topics', 'follower/estimate']),
    'info': ('formopt-bag', ['formopt_ros.cli.bag', 'info', '{bag}']),
}


@pytest.mark.parametrize('case,command', [(case, command) for case in sorted(EXPECTED)
                                          for command in sorted(EXPECTED[case])])
def test_bad_bag_is_a_clean_error(case: str, command: str, tmp_path: Path) -> None:
    """Exit code 2 and one 'prog: error:' line saying what is wrong; never a traceback."""
    path = BAD_BAGS[case](tmp_path)
    prog, args = COMMANDS[command]
    args = [a.format(bag=path, out=tmp_path / 'out') for a in args]
    result = subprocess.run([sys.executable, '-m', *args], capture_output=True, text=True,
                            timeout=120)
    assert result.returncode == 2, result.stdout + result.stderr
    assert 'Traceback' not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    text = EXPECTED[case][command]
    assert len(lines) == 1 and lines[0].startswith(f'{prog}: error: ') and text in lines[0], \
        lines


def test_truncated_bag_names_the_repair(recording: Recording, tmp_path: Path) -> None:
    """A bag cut short (killed recorder) is refused with the repair command in the message."""
    data = recording.path.read_bytes()
    cut = tmp_path / 'cut.mcap'
    cut.write_bytes(data[:len(data) // 2])
    for args in (['formopt_ros.cli.report', str(cut), '--out', str(tmp_path / 'o')],
                 ['formopt_ros.cli.replay', str(cut), '--offline']):
        result = subprocess.run([sys.executable, '-m', *args], capture_output=True, text=True,
                                timeout=120)
        assert result.returncode == 2 and 'Traceback' not in result.stderr
        assert 'truncated' in result.stderr and 'formopt-bag repair' in result.stderr


def copy_recording(source: Path, target: Path, keep, change=None) -> Path:
    """``source`` rewritten to ``target`` with the messages keep(topic, log_time, first, last)
    selects (first, last: the recording's first and last log times), each passed through
    change(topic, data) -> data when given."""
    from mcap.writer import Writer
    with open(source, 'rb') as stream, open(target, 'wb') as out:
        messages = list(make_reader(stream).iter_messages())
        first, last = messages[0][2].log_time, messages[-1][2].log_time
        writer = Writer(out)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in messages:
            if not keep(channel.topic, message.log_time, first, last):
                continue
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding,
                                                            schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding,
                    schemas.get(channel.schema_id, 0), channel.metadata)
            data = change(channel.topic, message.data) if change else message.data
            writer.add_message(channels[channel.id], message.log_time, data,
                               message.publish_time, message.sequence)
        writer.finish()
    return target


def test_offline_replay_of_a_cut_recording_names_the_missing_steps(recording: Recording,
                                                                   tmp_path: Path) -> None:
    """The recording without the estimates of its last 40 % (a damaged stretch of the
    estimate topic): replay --offline compares the steps both have (equal), names the steps
    missing from the recording and fails, exit 1."""
    cut = copy_recording(recording.path, tmp_path / 'cut.mcap', lambda topic, t, first, last:
                         not (t > first + 0.6 * (last - first) and topic.endswith('/estimate')))
    result = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.replay', str(cut),
                             '--offline'], capture_output=True, text=True, timeout=120)
    assert result.returncode == 1, result.stdout + result.stderr
    line = next(x for x in result.stdout.splitlines() if x.startswith('step counts differ'))
    assert 'missing from the recording' in line and 'both have agree' in line, line


def test_offline_replay_of_a_recording_damaged_in_the_middle_pairs_steps_by_number(
        recording: Recording, tmp_path: Path) -> None:
    """Every topic lost over the middle fifth of the run (a damaged stretch, then repaired):
    the re-estimate stops where its inputs stop; replay --offline compares the steps both have
    by their numbers (equal), names the steps missing from the recording and those recorded
    after the gap but not re-estimated, and fails, exit 1."""
    damaged = copy_recording(recording.path, tmp_path / 'damaged.mcap',
                             lambda topic, t, first, last:
                             not first + 0.4 * (last - first) < t < first + 0.6 * (last - first))
    report = tmp_path / 'replay.json'
    result = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.replay', str(damaged),
                             '--offline', '--json', str(report)], capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 1, result.stdout + result.stderr
    data = json.loads(report.read_text())
    gap, after = data['missing_from_recording'], data['not_reestimated']
    assert gap and after and gap[-1] < after[0] and after[-1] == STEPS, data
    assert data['steps'] < gap[0] + 1 and data['not_recorded'] in ([], [data['steps']]), data
    line = next(x for x in result.stdout.splitlines() if x.startswith('step counts differ'))
    assert f'missing from the recording: {gap[0]}-{gap[-1]}' in line, line
    assert 'both have agree' in line, line


def test_a_recording_cut_at_its_end_is_not_complete(recording: Recording,
                                                    tmp_path: Path) -> None:
    """Every topic cut after half the run (a recorder killed, then repaired): the report
    counts the steps of the run's description (60), names the missing end and warns;
    replay --offline, whose re-estimate and recording agree on the steps they have, says the
    run had 60 steps and fails, exit 1."""
    cut = copy_recording(recording.path, tmp_path / 'cut.mcap', lambda topic, t, first, last:
                         t <= first + 0.5 * (last - first))
    report = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.report', str(cut),
                             '--out', str(tmp_path / 'report')], capture_output=True,
                            text=True, timeout=120)
    assert report.returncode == 0, report.stderr
    summary = json.loads((tmp_path / 'report' / 'summary.json').read_text())
    assert summary['steps'] == STEPS and 0 < summary['estimates'] < STEPS
    assert summary['missing_steps'] == STEPS - summary['estimates']
    assert summary['missing_ranges'] == f"{summary['estimates'] + 1}-{STEPS}"
    assert 'the bag lacks steps' in report.stderr
    replay = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.replay', str(cut),
                             '--offline'], capture_output=True, text=True, timeout=120)
    assert replay.returncode == 1, replay.stdout + replay.stderr
    assert f'the run had {STEPS} steps' in replay.stdout


def test_an_inconsistent_run_is_flagged_by_report_and_replay(recording: Recording,
                                                             tmp_path: Path) -> None:
    """The recording with its truth moved 1 m (a filter that lost the follower, as seen by the
    truth): formopt-report marks the follower inconsistent (summary field, table and a
    warning) and replay --offline, though it reproduces every estimate, fails (exit 1)."""
    from geometry_msgs.msg import PoseStamped
    from rclpy.serialization import serialize_message

    def moved(topic: str, data: bytes) -> bytes:
        if not topic.endswith('/truth'):
            return data
        message = deserialize_message(data, PoseStamped)
        message.pose.position.x += 1.0
        return serialize_message(message)

    bad = copy_recording(recording.path, tmp_path / 'bad.mcap', lambda *_: True, moved)
    report = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.report', str(bad),
                             '--out', str(tmp_path / 'report')], capture_output=True,
                            text=True, timeout=120)
    assert report.returncode == 0, report.stderr
    summary = json.loads((tmp_path / 'report' / 'summary.json').read_text())
    assert summary['consistent'] is False and summary['inconsistency'].startswith('at step')
    assert '(inconsistent)' in (tmp_path / 'report' / 'summary.md').read_text()
    assert 'the filter was inconsistent' in report.stderr
    replay = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.replay', str(bad),
                             '--offline'], capture_output=True, text=True, timeout=120)
    assert replay.returncode == 1, replay.stdout + replay.stderr
    assert 'reproduced, but the filter was inconsistent' in replay.stdout
