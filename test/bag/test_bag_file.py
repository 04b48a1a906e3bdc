"""formopt_ros.bag without ROS: schemas, QoS YAML, the MCAP writer and reader, repair, CLI."""
from __future__ import annotations

import os
import random
import struct
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip('mcap', reason='the tools extra (mcap, rosbags) is not installed')
pytest.importorskip('rosbags', reason='the tools extra (mcap, rosbags) is not installed')
from mcap.reader import NonSeekingReader, make_reader  # noqa: E402
from mcap.records import Channel, Chunk, Message, Schema  # noqa: E402
from mcap.stream_reader import StreamReader, breakup_chunk  # noqa: E402
from mcap.writer import Writer  # noqa: E402
from rosbags.rosbag2.storage_mcap import McapReader  # noqa: E402

from formopt_ros import bag  # noqa: E402
from formopt_ros.bag import qos, schema  # noqa: E402
from formopt_ros.bag.writer import TYPE_KEY  # noqa: E402
from formopt_ros.cli.bag import main as bag_main  # noqa: E402
from formopt_ros.wire.topics import formation_topics  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
ODOMETRY = 'nav_msgs/msg/Odometry'
try:
    schema.definition_file(ODOMETRY)
    schema.definition_file('formopt_interfaces/msg/Waypoint')
except bag.BagError as error:        # no ROS message definitions installed here
    pytest.skip(str(error), allow_module_level=True)


def test_definition_is_rosbag2_format() -> None:
    """Root text first, then each nested type once after 80 '=' and 'MSG: pkg/Type'."""
    text = schema.message_definition(ODOMETRY)
    root = schema.definition_file(ODOMETRY).read_text()
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
        assert body == schema.definition_file(name[len('MSG: '):]).read_text()


def test_custom_definition_has_its_nested_types() -> None:
    """Waypoint nests Header (and Time) and geometry_msgs/Point, once each."""
    text = schema.message_definition('formopt_interfaces/msg/Waypoint')
    assert text.count('MSG: geometry_msgs/Point\n') == 1
    assert text.count('MSG: std_msgs/Header\n') == 1
    assert text.count('MSG: builtin_interfaces/Time\n') == 1
    assert '/msg/' not in ''.join(line for line in text.splitlines() if line.startswith('MSG:'))


def test_dependencies_skip_primitives_constants_and_comments() -> None:
    text = ('# Pose pose in a comment\nuint8 KIND=1\nfloat64[36] covariance\nPoint[] points\n'
            'std_msgs/Header header\nstring<=8 name\n  Vector3   v\n')
    assert schema.msg_dependencies(text, 'geometry_msgs') == [
        'geometry_msgs/Point', 'geometry_msgs/Vector3', 'std_msgs/Header']


def test_unknown_type_is_a_bag_error() -> None:
    with pytest.raises(bag.BagError, match='unknown message type'):
        schema.message_definition('nosuch_msgs/msg/Thing')
    with pytest.raises(bag.BagError, match='malformed'):
        schema.split_type('not a type')


def has_tf2() -> bool:
    """tf2_msgs installed (scripts/setup.sh builds it where ROS is missing)."""
    try:
        schema.definition_file('tf2_msgs/msg/TFMessage')
        return True
    except bag.BagError:
        return False


def test_header_detection_and_stamp() -> None:
    """Every formation type but TFMessage, MarkerArray, DiagnosticArray and Clock starts with a
    Header (Measurement after its constants)."""
    headerless = {'tf2_msgs/msg/TFMessage', 'visualization_msgs/msg/MarkerArray',
                  'rosgraph_msgs/msg/Clock'}
    for type_name in set(formation_topics().values()):
        if type_name != 'tf2_msgs/msg/TFMessage' or has_tf2():
            assert schema.has_header(type_name) == (type_name not in headerless), type_name
    assert not schema.has_header('geometry_msgs/msg/Point')
    little = bytes([0, 1, 0, 0]) + struct.pack('<iI', 12, 345) + b'rest'
    big = bytes([0, 0, 0, 0]) + struct.pack('>iI', 12, 345)
    assert schema.header_stamp_ns(little) == schema.header_stamp_ns(big) == 12_000_000_345
    assert schema.header_stamp_ns(b'\x00\x01\x00\x00') is None


def test_qos_yaml_matches_rosbag2_and_round_trips() -> None:
    """rosbag2's version-9 layout (policy names, sec/nsec durations); rosbags reads it back."""
    default = qos.Qos(qos.QosHistory.UNKNOWN, 0, qos.QosReliability.RELIABLE,
                      qos.QosDurability.VOLATILE, qos.duration(qos.INFINITE_NS),
                      qos.duration(qos.INFINITE_NS), qos.QosLiveliness.AUTOMATIC,
                      qos.duration(qos.INFINITE_NS), False)
    other = qos.Qos(qos.QosHistory.KEEP_LAST, 10, qos.QosReliability.BEST_EFFORT,
                    qos.QosDurability.TRANSIENT_LOCAL, qos.duration(0), qos.duration(5),
                    qos.QosLiveliness.AUTOMATIC, qos.duration(7), True)
    text = qos.qos_yaml([default, other])
    assert text.splitlines()[:7] == ['- history: unknown', '  depth: 0',
                                     '  reliability: reliable', '  durability: volatile',
                                     '  deadline:', '    sec: 9223372036',
                                     '    nsec: 854775807']
    assert qos.parse_qos_yaml(text) == [default, other]
    assert qos.qos_yaml([]) == '' and qos.parse_qos_yaml('') == []
    older = qos.parse_qos_yaml('- history: 1\n  depth: 5\n  reliability: 2\n  durability: 2\n'
                               '  deadline: {sec: 0, nsec: 0}\n  lifespan: {sec: 0, nsec: 0}\n'
                               '  liveliness: 1\n  liveliness_lease_duration: {sec: 0, nsec: 0}\n'
                               '  avoid_ros_namespace_conventions: false\n')
    assert older[0].reliability == qos.QosReliability.BEST_EFFORT
    with pytest.raises(bag.BagError, match='offered_qos_profiles'):
        qos.parse_qos_yaml('- depth: [')


RELIABLE = qos.Qos(qos.QosHistory.KEEP_LAST, 100, qos.QosReliability.RELIABLE,
                   qos.QosDurability.VOLATILE, qos.duration(0), qos.duration(0),
                   qos.QosLiveliness.AUTOMATIC, qos.duration(0), False)


def write_bag(path: Path, messages: int, flush_every: int = 0, chunk_size: int = 1 << 20
              ) -> list[tuple[str, int]]:
    """A bag of synthetic CDR payloads on two topics; returns (topic, log_time) per message."""
    writer = bag.BagWriter(path, chunk_size=chunk_size)
    writer.add_channel('/leader/odom', ODOMETRY, qos.qos_yaml([RELIABLE]), 'RIHS01_x')
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
    assert odom.qos == [RELIABLE]
    assert 'topic_type_hash' not in loaded.channels['/follower/status'].metadata
    assert loaded.messages[4].publish_time == 4 * 1_000_000_000     # header stamp: sec = i
    assert loaded.find('leader/odom') == '/leader/odom'
    with pytest.raises(bag.BagError, match='no topic'):
        loaded.find('follower/estimate')
    with open(path, 'rb') as stream:
        summary = make_reader(stream).get_summary()
    assert summary.statistics.message_count == 90
    assert set(summary.statistics.channel_message_counts.values()) == {60, 30}


def test_a_split_recording_is_one_bag(tmp_path: Path) -> None:
    """The files of a split rosbag2 folder (run_2 before run_10 without metadata.yaml) are one
    bag, messages in log-time order; a topic whose type changes between files is refused."""
    def part(name: str, start: int, topic_type: str = ODOMETRY) -> None:
        writer = bag.BagWriter(tmp_path / name)
        writer.add_channel('/leader/odom', topic_type)
        for i in range(start, start + 5):
            writer.write('/leader/odom', bytes([0, 1, 0, 0]) + struct.pack('<iI', i, 0),
                         1_000_000 * i)
        writer.close()

    part('run_10.mcap', 20)
    part('run_2.mcap', 10)
    assert [p.name for p in bag.reader.bag_files(tmp_path)] == ['run_2.mcap', 'run_10.mcap']
    loaded = bag.read_bag(tmp_path)
    assert loaded.path == tmp_path and loaded.counts() == {'/leader/odom': 10}
    expected = [1_000_000 * i for i in [*range(10, 15), *range(20, 25)]]
    assert [r.log_time for r in loaded.messages] == expected
    part('run_11.mcap', 30, 'formopt_interfaces/msg/PlannerStatus')
    with pytest.raises(bag.BagError, match='has type formopt_interfaces'):
        bag.read_bag(tmp_path)


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


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_repair_skips_a_damaged_chunk_and_keeps_the_rest(
        tmp_path: Path, seed: int, capsys: pytest.CaptureFixture[str]) -> None:
    """One flipped byte inside a chunk costs that chunk only: every other message is kept, and
    the command says how many of the file's messages the damaged chunk held."""
    path = tmp_path / 'run.mcap'
    written = write_bag(path, 200, flush_every=20)          # 10 chunks of 20 messages
    data = bytearray(path.read_bytes())
    offsets = chunk_offsets(bytes(data))
    rng = random.Random(seed)
    victim = rng.randrange(1, len(offsets) - 1)
    start, end = offsets[victim]
    data[rng.randrange(start + 60, end)] ^= 0xFF             # inside the compressed records
    broken = tmp_path / 'flipped.mcap'
    broken.write_bytes(bytes(data))
    with pytest.raises(bag.BagError, match='damaged'):
        bag.read_bag(broken)
    result = bag.repair(broken, tmp_path / 'fixed.mcap')
    assert len(result.damage) == 1 and result.damage[0].offset == start
    lost = written[20 * victim:20 * (victim + 1)]
    kept = [(r.topic, r.log_time) for r in bag.read_bag(tmp_path / 'fixed.mcap').messages]
    assert kept == [w for w in written if w not in lost]
    assert result.kept == 180 and result.summary_messages == 200
    capsys.readouterr()
    assert bag_main(['repair', str(broken), str(tmp_path / 'cli.mcap')]) == 0
    assert '(20 of the 200 messages its summary counts)' in capsys.readouterr().out


def chunk_offsets(data: bytes) -> list[tuple[int, int]]:
    """(start, end) byte offsets of every chunk record of an MCAP file."""
    out, offset = [], 8
    while offset + 9 <= len(data):
        length = int.from_bytes(data[offset + 1:offset + 9], 'little')
        if data[offset] == 0x06:
            out.append((offset, offset + 9 + length))
        if data[offset] == 0x02:
            break
        offset += 9 + length
    return out


def test_garbage_between_records_is_skipped(tmp_path: Path) -> None:
    """A corrupted record length (framing lost) resumes at the next readable chunk."""
    path = tmp_path / 'run.mcap'
    written = write_bag(path, 100, flush_every=20)
    data = bytearray(path.read_bytes())
    start, _ = chunk_offsets(bytes(data))[2]
    data[start + 1:start + 9] = (2**40).to_bytes(8, 'little')     # length beyond the file
    broken = tmp_path / 'framing.mcap'
    broken.write_bytes(bytes(data))
    result = bag.repair(broken, tmp_path / 'fixed.mcap')
    assert len(result.damage) >= 1 and result.kept == 80
    kept = [(r.topic, r.log_time) for r in bag.read_bag(tmp_path / 'fixed.mcap').messages]
    assert kept == written[:40] + written[60:]


def chunk_records(path: Path) -> list[list]:
    """The records inside each chunk of an undamaged MCAP file, chunk by chunk."""
    with open(path, 'rb') as stream:
        return [breakup_chunk(record) for record in StreamReader(stream, emit_chunks=True).records
                if isinstance(record, Chunk)]


def test_every_chunk_is_self_describing_and_every_reader_agrees(tmp_path: Path) -> None:
    """Each chunk has the Channel record of its messages before them, naming the type; the
    schemas are written once (first chunk); mcap (indexed and streaming), rosbags (indexed and
    scanning) and read_bag count the same 200 messages."""
    path = tmp_path / 'run.mcap'
    written = write_bag(path, 200, flush_every=20)
    chunks = chunk_records(path)
    assert len(chunks) == 10
    types = {'/leader/odom': ODOMETRY, '/follower/status': 'formopt_interfaces/msg/PlannerStatus'}
    for index, records in enumerate(chunks):
        seen: set[int] = set()
        for record in records:
            if isinstance(record, Channel):
                assert record.metadata[TYPE_KEY] == types[record.topic]
                seen.add(record.id)
            elif isinstance(record, Message):
                assert record.channel_id in seen
        assert sum(isinstance(r, Schema) for r in records) == (2 if index == 0 else 0)
    expected = {'/leader/odom': 133, '/follower/status': 67}
    assert bag.read_bag(path).counts() == expected
    assert [(r.topic, r.log_time) for r in bag.read_bag(path).messages] == written
    with open(path, 'rb') as stream:
        indexed = [(c.topic, m.log_time) for _, c, m in make_reader(stream).iter_messages()]
    with open(path, 'rb') as stream:
        streamed = [(c.topic, m.log_time) for _, c, m in NonSeekingReader(stream).iter_messages()]
    assert indexed == streamed == written
    reader = McapReader(path)
    reader.open()
    try:
        assert {c.topic: c.msgcount for c in reader.connections} == expected
        assert len(reader.connections) == 2
        by_index = [(c.topic, t) for c, t, _ in reader.messages(reader.connections)]
        by_scan = [(c.topic, t) for c, t, _ in reader.messages_scan(reader.connections)]
    finally:
        reader.close()
    assert by_index == by_scan == written


def test_writer_needs_the_mcap_chunk_builder(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """An mcap Writer without the chunk builder to replace: one clear error, no file left."""
    monkeypatch.setattr(Writer, '__init__', lambda self, *args, **kwargs: None)
    with pytest.raises(bag.BagError, match='chunk builder'):
        bag.BagWriter(tmp_path / 'run.mcap')
    assert not (tmp_path / 'run.mcap').exists()


def damage_first_chunk_and_cut(data: bytes, rng: random.Random) -> tuple[bytes, int]:
    """Flip a byte inside the first chunk and cut the file inside a later chunk; returns the
    damaged bytes and the index of the chunk that was cut."""
    offsets = chunk_offsets(data)
    broken = bytearray(data)
    start, end = offsets[0]
    broken[rng.randrange(start + 60, end)] ^= 0xFF
    cut_chunk = rng.randrange(2, len(offsets))
    start, end = offsets[cut_chunk]
    return bytes(broken[:rng.randrange(start + 1, end)]), cut_chunk


@pytest.mark.parametrize('seed', [0, 1, 2, 3])
def test_repair_keeps_every_intact_chunk_when_the_first_is_damaged(
        tmp_path: Path, seed: int, capsys: pytest.CaptureFixture[str]) -> None:
    """The first chunk (where the channels were registered) damaged and the file cut: with
    self-describing chunks every message of every intact chunk is kept, in order."""
    path = tmp_path / 'run.mcap'
    written = write_bag(path, 200, flush_every=20)
    chunks = chunk_records(path)
    broken_data, cut_chunk = damage_first_chunk_and_cut(path.read_bytes(), random.Random(seed))
    broken = tmp_path / 'broken.mcap'
    broken.write_bytes(broken_data)
    result = bag.repair(broken, tmp_path / 'fixed.mcap')
    intact = [m for records in chunks[1:cut_chunk] for m in records if isinstance(m, Message)]
    assert len(intact) == 20 * (cut_chunk - 1)
    assert result.chunks == cut_chunk - 1 and len(result.damage) == 1
    assert result.kept == len(intact) and result.lost == 0 and result.unrecoverable == {}
    assert sorted(result.rebuilt.values()) == sorted(                # schemas were in chunk 1
        [ODOMETRY, 'formopt_interfaces/msg/PlannerStatus'])
    kept = [(r.topic, r.log_time) for r in bag.read_bag(tmp_path / 'fixed.mcap').messages]
    assert kept == written[20:20 * cut_chunk]
    assert result.counts == bag.read_bag(tmp_path / 'fixed.mcap').counts()
    assert sum(result.counts.values()) == result.kept
    assert bag_main(['repair', str(broken), str(tmp_path / 'again.mcap')]) == 0
    assert 'rebuilt 2 lost schema(s) from the channels' in capsys.readouterr().out


def write_plain_bag(path: Path, flush_every: int = 20) -> list[tuple[int, int]]:
    """A bag written the old way (plain chunked mcap Writer): /leader/odom registered in the
    first chunk; /range/odom (same schema) and /follower/status registered in the second.
    Returns (channel id, log_time) per message."""
    odometry = schema.message_definition(ODOMETRY).encode()
    status_type = 'formopt_interfaces/msg/PlannerStatus'
    rng = random.Random(7)
    written = []
    with open(path, 'xb') as stream:
        writer = Writer(stream, chunk_size=1 << 20)
        writer.start(profile='ros2', library='old')
        odom_schema = writer.register_schema(ODOMETRY, 'ros2msg', odometry)
        channels = [writer.register_channel('/leader/odom', 'cdr', odom_schema)]
        for i in range(200):
            if i == flush_every:
                channels.append(writer.register_channel('/range/odom', 'cdr', odom_schema))
                status = writer.register_schema(status_type, 'ros2msg',
                                                schema.message_definition(status_type).encode())
                channels.append(writer.register_channel('/follower/status', 'cdr', status))
            channel = channels[i % len(channels)]
            payload = bytes([0, 1, 0, 0]) + struct.pack('<iI', i, 0) + rng.randbytes(50)
            writer.add_message(channel, 1_000_000 * (i + 1), payload, 1_000_000 * (i + 1))
            written.append((channel, 1_000_000 * (i + 1)))
            if (i + 1) % flush_every == 0:
                writer.flush()
        writer.finish()
    return written


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_repair_of_an_old_bag_reports_what_it_could_not_recover(
        tmp_path: Path, seed: int, capsys: pytest.CaptureFixture[str]) -> None:
    """An old-style bag with its first chunk damaged and its tail cut: the messages of intact
    chunks whose channel (1) or schema (channel 2) was lost are counted per channel, the CLI says
    so in one line and exits 1; the partial repair reads and keeps every decodable message."""
    path = tmp_path / 'old.mcap'
    written = write_plain_bag(path)
    chunks = chunk_records(path)
    assert [type(r) for r in chunks[1][:3]] == [Channel, Schema, Channel]   # the old layout
    broken_data, cut_chunk = damage_first_chunk_and_cut(path.read_bytes(), random.Random(seed))
    broken = tmp_path / 'broken.mcap'
    broken.write_bytes(broken_data)
    intact = written[20:20 * cut_chunk]
    per_channel = {c: sum(1 for channel, _ in intact if channel == c) for c in (1, 2, 3)}
    assert per_channel[1] > 0 and per_channel[2] > 0 and per_channel[3] > 0
    result = bag.repair(broken, tmp_path / 'fixed.mcap')
    assert result.unrecoverable == {1: per_channel[1], 2: per_channel[2]}
    assert result.why == {1: 'Channel record lost', 2: 'Schema record of /range/odom lost'}
    assert result.lost == per_channel[1] + per_channel[2]
    assert result.kept == per_channel[3] and result.kept + result.lost == len(intact)
    assert result.counts == {'/follower/status': per_channel[3]}
    fixed = bag.read_bag(tmp_path / 'fixed.mcap')
    assert list(fixed.channels) == ['/follower/status']
    assert [r.log_time for r in fixed.messages] == [t for c, t in intact if c == 3]
    capsys.readouterr()
    assert bag_main(['repair', str(broken), str(tmp_path / 'cli.mcap')]) == 1
    out, err = capsys.readouterr()
    assert out.startswith(f'kept {result.kept} messages in {cut_chunk - 1} chunks')
    assert err.splitlines() == [
        f'formopt-bag: partial repair: {result.lost} messages of intact chunks could not be '
        'recovered, their channel or schema is unknown: Channel record lost (channel 1); Schema '
        f'record of /range/odom lost (channel 2); {tmp_path / "cli.mcap"} has the rest']
    assert bag.read_bag(tmp_path / 'cli.mcap').counts() == {'/follower/status': per_channel[3]}
    assert bag_main(['info', str(tmp_path / 'cli.mcap')]) == 0


def test_repair_of_an_undamaged_old_bag_keeps_everything(tmp_path: Path) -> None:
    """The summary repeats every Schema and Channel: a complete old bag loses nothing."""
    path = tmp_path / 'old.mcap'
    written = write_plain_bag(path)
    result = bag.repair(path, tmp_path / 'fixed.mcap')
    assert result.was_complete and result.kept == 200 and result.unrecoverable == {}
    by_topic = {1: '/leader/odom', 2: '/range/odom', 3: '/follower/status'}
    assert [(r.topic, r.log_time) for r in bag.read_bag(tmp_path / 'fixed.mcap').messages] == [
        (by_topic[c], t) for c, t in written]


def run_module(module: str, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, '-m', module, *args], capture_output=True, text=True,
                          timeout=120, env=env, cwd=REPO)


def assert_clean_error(result: subprocess.CompletedProcess, text: str) -> None:
    """Exit code 2, one 'formopt-bag: error:' line naming the problem, no traceback."""
    assert result.returncode == 2, result.stderr
    assert 'Traceback' not in result.stderr
    assert result.stderr.startswith('formopt-bag: error: ') and text in result.stderr, \
        result.stderr
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr


@pytest.mark.slow
def test_cli_info_repair_and_bad_files(tmp_path: Path) -> None:
    path = tmp_path / 'run.mcap'
    write_bag(path, 30, flush_every=10)
    cli = 'formopt_ros.cli.bag'
    info = run_module(cli, 'info', str(path))
    assert info.returncode == 0 and '/leader/odom' in info.stdout and ' 20' in info.stdout
    data = path.read_bytes()
    (tmp_path / 'cut.mcap').write_bytes(data[:len(data) * 2 // 3])
    fixed = run_module(cli, 'repair', str(tmp_path / 'cut.mcap'), str(tmp_path / 'fixed.mcap'))
    assert fixed.returncode == 0 and fixed.stdout.startswith('kept ')
    before = (tmp_path / 'fixed.mcap').read_bytes()
    assert_clean_error(run_module(cli, 'repair', str(tmp_path / 'cut.mcap'),
                                  str(tmp_path / 'fixed.mcap')), 'exists')
    assert (tmp_path / 'fixed.mcap').read_bytes() == before
    (tmp_path / 'text.mcap').write_text('hello')
    assert_clean_error(run_module(cli, 'info', str(tmp_path / 'none.mcap')), 'no such file')
    assert_clean_error(run_module(cli, 'info', str(tmp_path / 'text.mcap')), 'not an MCAP file')
    assert_clean_error(run_module(cli, 'info', str(tmp_path / 'cut.mcap')), 'truncated')
    assert_clean_error(run_module(cli, 'info', str(tmp_path)), 'holds 4 .mcap files that')
    assert_clean_error(run_module(cli, 'bogus'), 'invalid choice')


def test_repair_with_nothing_recoverable_says_so(tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Every chunk damaged: the command says 'nothing recoverable', not 'complete', exit 1."""
    path = tmp_path / 'run.mcap'
    write_bag(path, 200, flush_every=20)
    data = bytearray(path.read_bytes())
    for start, end in chunk_offsets(bytes(data)):
        data[start + 60] ^= 0xFF
    broken = tmp_path / 'ruined.mcap'
    broken.write_bytes(bytes(data))
    assert bag_main(['repair', str(broken), str(tmp_path / 'fixed.mcap')]) == 1
    captured = capsys.readouterr()
    assert 'nothing recoverable' in captured.err and 'complete' not in captured.out
