"""Pure parts of formopt_ros.bag: schemas, QoS YAML, the MCAP writer and reader, repair."""
from __future__ import annotations

import os
import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from formopt_ros import bag

pytest.importorskip('mcap', reason='the tools extra (mcap, rosbags) is not installed')
pytest.importorskip('rosbags', reason='the tools extra (mcap, rosbags) is not installed')
from mcap.reader import make_reader  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
ODOMETRY = 'nav_msgs/msg/Odometry'
try:
    bag.definition_file(ODOMETRY)
    bag.definition_file('formopt_interfaces/msg/Waypoint')
except bag.BagError as error:        # no ROS message definitions installed here
    pytest.skip(str(error), allow_module_level=True)


def test_definition_is_rosbag2_format() -> None:
    """Root text first, then each nested type once after 80 '=' and 'MSG: pkg/Type'."""
    text = bag.message_definition(ODOMETRY)
    root = bag.definition_file(ODOMETRY).read_text()
    assert text.startswith(root)
    blocks = text[len(root):].split('\n' + '=' * 80 + '\n')
    assert blocks[0] == ''
    names = [block.split('\n', 1)[0] for block in blocks[1:]]
    # depth first, dependencies of each type in sorted order, each once (rosbag2's std::set)
    assert names == ['MSG: geometry_msgs/PoseWithCovariance', 'MSG: geometry_msgs/Pose',
                     'MSG: geometry_msgs/Point', 'MSG: geometry_msgs/Quaternion',
                     'MSG: geometry_msgs/TwistWithCovariance', 'MSG: geometry_msgs/Twist',
                     'MSG: geometry_msgs/Vector3', 'MSG: std_msgs/Header',
                     'MSG: builtin_interfaces/Time']
    for block in blocks[1:]:
        name, body = block.split('\n', 1)
        assert body == bag.definition_file(name[len('MSG: '):]).read_text()


def test_custom_definition_has_its_nested_types() -> None:
    """Waypoint nests Header (and Time) and geometry_msgs/Point, once each."""
    text = bag.message_definition('formopt_interfaces/msg/Waypoint')
    assert text.count('MSG: geometry_msgs/Point\n') == 1
    assert text.count('MSG: std_msgs/Header\n') == 1
    assert text.count('MSG: builtin_interfaces/Time\n') == 1
    assert '/msg/' not in ''.join(line for line in text.splitlines() if line.startswith('MSG:'))


def test_dependencies_skip_primitives_constants_and_comments() -> None:
    text = ('# Pose pose in a comment\nuint8 KIND=1\nfloat64[36] covariance\nPoint[] points\n'
            'std_msgs/Header header\nstring<=8 name\n  Vector3   v\n')
    assert bag.msg_dependencies(text, 'geometry_msgs') == [
        'geometry_msgs/Point', 'geometry_msgs/Vector3', 'std_msgs/Header']


def test_unknown_type_is_a_bag_error() -> None:
    with pytest.raises(bag.BagError, match='unknown message type'):
        bag.message_definition('nosuch_msgs/msg/Thing')
    with pytest.raises(bag.BagError, match='malformed'):
        bag.split_type('not a type')
    with pytest.raises(bag.BagError, match='unknown message type'):
        bag.message_class('nosuch_msgs/msg/Thing')


def test_header_detection_and_stamp() -> None:
    """Every formation type starts with a Header (Measurement after its constants)."""
    assert all(bag.has_header(t) for t in bag.TOPIC_TYPES.values())
    assert not bag.has_header('geometry_msgs/msg/Point')
    little = bytes([0, 1, 0, 0]) + struct.pack('<iI', 12, 345) + b'rest'
    big = bytes([0, 0, 0, 0]) + struct.pack('>iI', 12, 345)
    assert bag.header_stamp_ns(little) == bag.header_stamp_ns(big) == 12_000_000_345
    assert bag.header_stamp_ns(b'\x00\x01\x00\x00') is None


def test_qos_yaml_matches_rosbag2_and_round_trips() -> None:
    """The text rosbag2 (yaml-cpp, version 9) writes; rosbags parses it to the same policies."""
    from rosbags.interfaces import QosReliability
    from rosbags.rosbag2.metadata import parse_qos
    profiles = [bag.OfferedQos(), bag.OfferedQos('keep_last', 10, 'best_effort',
                                                 'transient_local', 0, 5, 'automatic', 7, True)]
    text = bag.qos_yaml(profiles)
    assert text.splitlines()[:7] == ['- history: unknown', '  depth: 0',
                                     '  reliability: reliable', '  durability: volatile',
                                     '  deadline:', '    sec: 9223372036',
                                     '    nsec: 854775807']
    assert bag.parse_qos_yaml(text) == profiles
    parsed = parse_qos(text)
    assert parsed[0].reliability == QosReliability.RELIABLE
    assert parsed[1].reliability == QosReliability.BEST_EFFORT and parsed[1].depth == 10
    assert bag.parse_qos_yaml('- history: 1\n  depth: 5\n  reliability: 2\n  durability: 2\n'
                              '  liveliness: 1\n')[0].reliability == 'best_effort'


def write_bag(path: Path, messages: int, flush_every: int = 0, chunk_size: int = 1 << 20
              ) -> list[tuple[str, int]]:
    """A bag of synthetic CDR payloads on two topics; returns (topic, log_time) per message."""
    writer = bag.BagWriter(path, chunk_size=chunk_size)
    writer.add_channel('/leader/odom', ODOMETRY, bag.qos_yaml([bag.OfferedQos()]), 'RIHS01_x')
    writer.add_channel('/follower/status', 'formopt_interfaces/msg/PlannerStatus')
    rng = random.Random(4)
    written = []
    for i in range(messages):
        topic = '/leader/odom' if i % 3 else '/follower/status'
        payload = bytes([0, 1, 0, 0]) + struct.pack('<iI', i, 0) + rng.randbytes(rng.randrange(
            0, 200))
        writer.write(topic, payload, 1_000_000 * (i + 1))
        written.append((topic, 1_000_000 * (i + 1)))
        if flush_every and (i + 1) % flush_every == 0:
            writer.flush()
    writer.close()
    return written


def test_writer_reader_round_trip(tmp_path: Path) -> None:
    """Profile, encodings, metadata, counts and times survive; mcap's indexed reader agrees."""
    path = tmp_path / 'run.mcap'
    written = write_bag(path, 90)
    loaded = bag.read_bag(path)
    assert loaded.profile == 'ros2'
    assert loaded.counts() == {'/leader/odom': 60, '/follower/status': 30}
    assert [(r.topic, r.log_time) for r in loaded.messages] == written
    odom = loaded.channels['/leader/odom']
    assert (odom.type, odom.schema_encoding, odom.message_encoding) == (
        ODOMETRY, 'ros2msg', 'cdr')
    assert odom.metadata['topic_type_hash'] == 'RIHS01_x'
    assert odom.qos == [bag.OfferedQos()]
    assert 'topic_type_hash' not in loaded.channels['/follower/status'].metadata
    assert loaded.messages[4].publish_time == 4 * 1_000_000_000     # header stamp: sec = i
    assert loaded.find('leader/odom') == '/leader/odom'
    with pytest.raises(bag.BagError, match='no topic'):
        loaded.find('follower/estimate')
    with open(path, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    assert summary.statistics.message_count == 90
    assert set(summary.statistics.channel_message_counts.values()) == {60, 30}


def test_writer_refuses_to_overwrite(tmp_path: Path) -> None:
    path = tmp_path / 'run.mcap'
    path.write_bytes(b'keep me')
    with pytest.raises(bag.BagError, match='exists'):
        bag.BagWriter(path)
    assert path.read_bytes() == b'keep me'


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_repair_keeps_every_complete_chunk(tmp_path: Path, seed: int) -> None:
    """Cut a flushed bag anywhere: repair keeps exactly the messages of the complete chunks."""
    path = tmp_path / 'run.mcap'
    written = write_bag(path, 200, flush_every=20)          # 10 chunks of 20 messages
    data = path.read_bytes()
    rng = random.Random(seed)
    for cut in sorted(rng.sample(range(len(data) // 4, len(data) - 1), 12)):
        broken = tmp_path / f'cut{cut}.mcap'
        fixed = tmp_path / f'fixed{cut}.mcap'
        broken.write_bytes(data[:cut])
        with pytest.raises(bag.BagError, match='truncated'):
            bag.read_bag(broken)
        result = bag.repair(broken, fixed)
        assert not result.was_complete
        assert result.kept == 20 * result.chunks or result.kept == 200
        complete = bag.scan(broken)
        assert result.kept == len(complete.messages)
        loaded = bag.read_bag(fixed)
        assert [(r.topic, r.log_time) for r in loaded.messages] == written[:result.kept]
        assert loaded.channels['/leader/odom'].metadata['topic_type_hash'] == 'RIHS01_x'
    again = bag.repair(path, tmp_path / 'whole.mcap')
    assert again.was_complete and again.kept == 200


def run_module(module: str, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, '-m', module, *args], capture_output=True, text=True,
                          timeout=120, env=env, cwd=REPO)


def assert_clean_error(result: subprocess.CompletedProcess, text: str) -> None:
    """Exit code 2, one 'error:' line naming the problem, no traceback."""
    assert result.returncode == 2, result.stderr
    assert 'Traceback' not in result.stderr
    assert result.stderr.startswith('error: ') and text in result.stderr, result.stderr


def test_cli_info_repair_and_bad_files(tmp_path: Path) -> None:
    path = tmp_path / 'run.mcap'
    write_bag(path, 30, flush_every=10)
    info = run_module('formopt_ros.bag', 'info', str(path))
    assert info.returncode == 0 and '/leader/odom' in info.stdout and ' 20' in info.stdout
    data = path.read_bytes()
    (tmp_path / 'cut.mcap').write_bytes(data[:len(data) * 2 // 3])
    fixed = run_module('formopt_ros.bag', 'repair', str(tmp_path / 'cut.mcap'),
                       str(tmp_path / 'fixed.mcap'))
    assert fixed.returncode == 0 and fixed.stdout.startswith('kept ')
    assert_clean_error(run_module('formopt_ros.bag', 'repair', str(tmp_path / 'cut.mcap'),
                                  str(tmp_path / 'fixed.mcap')), 'exists')
    (tmp_path / 'text.mcap').write_text('hello')
    assert_clean_error(run_module('formopt_ros.bag', 'info', str(tmp_path / 'none.mcap')),
                       'no such file')
    assert_clean_error(run_module('formopt_ros.bag', 'info', str(tmp_path / 'text.mcap')),
                       'not an MCAP file')
    assert_clean_error(run_module('formopt_ros.bag', 'info', str(tmp_path / 'cut.mcap')),
                       'truncated')
    assert_clean_error(run_module('formopt_ros.bag', 'info', str(tmp_path)), 'directory')
