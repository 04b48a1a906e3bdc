"""rosbag2-compatible MCAP bags of a formation run: writer, reader, repair and a small CLI."""
from __future__ import annotations

import argparse
import importlib
import json
import os
import re
import struct
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Iterable, Sequence

#: Message type of each formation topic (names relative to the namespace, nodes/common.TOPICS).
TOPIC_TYPES = {
    'leader/odom': 'nav_msgs/msg/Odometry',
    'follower/odom': 'nav_msgs/msg/Odometry',
    'follower/measurement': 'formopt_interfaces/msg/Measurement',
    'follower/truth': 'geometry_msgs/msg/PoseStamped',
    'follower/estimate': 'geometry_msgs/msg/PoseWithCovarianceStamped',
    'follower/waypoint': 'formopt_interfaces/msg/Waypoint',
    'follower/status': 'formopt_interfaces/msg/PlannerStatus',
}
PROFILE = 'ros2'
MESSAGE_ENCODING = 'cdr'
SCHEMA_ENCODING = 'ros2msg'
DELIMITER = '=' * 80
MAGIC = b'\x89MCAP0\r\n'
#: rmw's "infinite" duration (RMW_DURATION_INFINITE), ns.
INFINITE_NS = 2**63 - 1
LIBRARY = 'formopt_ros.bag'
REPAIR_HINT = 'python -m formopt_ros.bag repair'

# rosbag2's LocalMessageDefinitionSource: field types at the start of a .msg line.
_FIELD_TYPE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_PRIMITIVES = {'bool', 'byte', 'char', 'float32', 'float64', 'int8', 'uint8', 'int16', 'uint16',
               'int32', 'uint32', 'int64', 'uint64', 'string'}
_TYPE_NAME = re.compile(r'^([A-Za-z][A-Za-z0-9_]*)(?:/(msg|srv|action))?/([A-Za-z][A-Za-z0-9_]*)$')


class BagError(Exception):
    """A bag (or bag request) that cannot be served; the text says why, for the user."""


# --- message definitions -------------------------------------------------------------------
def share_prefixes() -> list[Path]:
    """Install prefixes searched for share/<pkg>/msg/*.msg: AMENT_PREFIX_PATH, then sys.prefix."""
    found: list[Path] = []
    for entry in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) + [sys.prefix]:
        if entry and Path(entry) not in found:
            found.append(Path(entry))
    return found


def split_type(type_name: str) -> tuple[str, str, str]:
    """('pkg', 'msg', 'Type') of 'pkg/msg/Type' or 'pkg/Type'; BagError when malformed."""
    match = _TYPE_NAME.match(type_name)
    if match is None:
        raise BagError(f'malformed message type name {type_name!r} (expected pkg/msg/Type)')
    return match.group(1), match.group(2) or 'msg', match.group(3)


def definition_file(type_name: str) -> Path:
    """The installed .msg file of a type; BagError when no prefix has it."""
    package, namespace, name = split_type(type_name)
    for prefix in share_prefixes():
        candidate = prefix / 'share' / package / namespace / f'{name}.msg'
        if candidate.is_file():
            return candidate
    raise BagError(f'unknown message type {type_name!r}: no share/{package}/{namespace}/'
                   f'{name}.msg under AMENT_PREFIX_PATH or {sys.prefix}')


def msg_dependencies(text: str, package: str) -> list[str]:
    """Non-primitive field types of a .msg text as 'pkg/Type', sorted (rosbag2's std::set)."""
    found = set()
    for match in _FIELD_TYPE.finditer(text):
        name = match.group(1)
        if name in _PRIMITIVES:
            continue
        found.add(name if '/' in name else f'{package}/{name}')
    return sorted(found)


def message_definition(type_name: str) -> str:
    """The ros2msg schema rosbag2 writes: root .msg text, then each nested type once.

    Each nested type follows a line of 80 '=' and a line 'MSG: pkg/Type', depth first in
    sorted order, exactly as rosbag2_cpp's LocalMessageDefinitionSource concatenates them.
    """
    seen: set[str] = set()

    def append(name: str, depth: int) -> str:
        if depth <= 0:
            raise BagError(f'message definition of {type_name!r} nests too deeply')
        text = definition_file(name).read_text()
        result = text
        for dependency in msg_dependencies(text, split_type(name)[0]):
            if dependency not in seen:
                seen.add(dependency)
                result += f'\n{DELIMITER}\nMSG: {dependency}\n' + append(dependency, depth - 1)
        return result

    return append(type_name, 50)


def has_header(type_name: str) -> bool:
    """Whether the type's first field is a std_msgs/Header (its stamp starts the CDR data)."""
    for line in definition_file(type_name).read_text().splitlines():
        parts = line.split('#', 1)[0].split()
        if parts and '=' not in ''.join(parts[1:]):          # skip constants (NAME=value)
            return len(parts) == 2 and parts[0] in ('std_msgs/Header', 'Header')
    return False


def header_stamp_ns(data: bytes) -> int | None:
    """Header stamp (ns) of a CDR message whose first field is a std_msgs/Header."""
    if len(data) < 12 or data[0] != 0 or data[1] not in (0, 1):
        return None
    sec, nanosec = struct.unpack_from('<iI' if data[1] == 1 else '>iI', data, 4)
    return sec * 1_000_000_000 + nanosec if sec >= 0 else None


# --- QoS ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class OfferedQos:
    """One publisher's offered QoS as rosbag2 stores it (policy names as rmw spells them)."""

    history: str = 'unknown'
    depth: int = 0
    reliability: str = 'reliable'
    durability: str = 'volatile'
    deadline_ns: int = INFINITE_NS
    lifespan_ns: int = INFINITE_NS
    liveliness: str = 'automatic'
    liveliness_lease_duration_ns: int = INFINITE_NS
    avoid_ros_namespace_conventions: bool = False


def _duration_yaml(name: str, ns: int) -> list[str]:
    return [f'  {name}:', f'    sec: {ns // 1_000_000_000}', f'    nsec: {ns % 1_000_000_000}']


def qos_yaml(profiles: Iterable[OfferedQos]) -> str:
    """offered_qos_profiles as rosbag2 (Jazzy, metadata version 9) writes it with yaml-cpp."""
    lines: list[str] = []
    for q in profiles:
        lines += [f'- history: {q.history}', f'  depth: {q.depth}',
                  f'  reliability: {q.reliability}', f'  durability: {q.durability}']
        lines += _duration_yaml('deadline', q.deadline_ns)
        lines += _duration_yaml('lifespan', q.lifespan_ns)
        lines.append(f'  liveliness: {q.liveliness}')
        lines += _duration_yaml('liveliness_lease_duration', q.liveliness_lease_duration_ns)
        lines.append('  avoid_ros_namespace_conventions: '
                     + ('true' if q.avoid_ros_namespace_conventions else 'false'))
    return '\n'.join(lines)


def parse_qos_yaml(text: str) -> list[OfferedQos]:
    """Inverse of :func:`qos_yaml`; also reads the integer policies of older bags."""
    import yaml
    if not text.strip():
        return []
    try:
        items = yaml.safe_load(text)
    except yaml.YAMLError as error:
        raise BagError(f'offered_qos_profiles is not YAML: {error}') from None
    names = {
        'history': {0: 'system_default', 1: 'keep_last', 2: 'keep_all'},
        'reliability': {0: 'system_default', 1: 'reliable', 2: 'best_effort'},
        'durability': {0: 'system_default', 1: 'transient_local', 2: 'volatile'},
        'liveliness': {0: 'system_default', 1: 'automatic', 3: 'manual_by_topic'},
    }

    def policy(item: dict, key: str) -> str:
        value = item.get(key, 'unknown')
        return names[key].get(value, 'unknown') if isinstance(value, int) else str(value)

    def duration(item: dict, key: str) -> int:
        value = item.get(key) or {}
        return int(value.get('sec', 0)) * 1_000_000_000 + int(value.get('nsec', 0))

    result = []
    for item in items or []:
        result.append(OfferedQos(
            policy(item, 'history'), int(item.get('depth', 0)), policy(item, 'reliability'),
            policy(item, 'durability'), duration(item, 'deadline'), duration(item, 'lifespan'),
            policy(item, 'liveliness'), duration(item, 'liveliness_lease_duration'),
            bool(item.get('avoid_ros_namespace_conventions', False))))
    return result


# --- writing -----------------------------------------------------------------------------
class BagWriter:
    """One rosbag2-compatible .mcap file: ros2 profile, cdr messages, ros2msg schemas.

    Channels are registered per topic with the offered QoS (YAML) and the type hash as channel
    metadata, like rosbag2_storage_mcap. The file is opened exclusively: an existing file is
    never overwritten. :meth:`flush` closes the current chunk and hands it to the OS, so a killed
    writer loses only what came after the last flush (see :func:`repair`).
    """

    def __init__(self, path: str | Path, chunk_size: int = 1 << 20,
                 compression: str = 'zstd') -> None:
        from mcap.writer import CompressionType, Writer
        kinds = {'zstd': CompressionType.ZSTD, 'lz4': CompressionType.LZ4,
                 'none': CompressionType.NONE}
        if compression not in kinds:
            raise BagError(f"compression must be one of {', '.join(kinds)}, got {compression!r}")
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file: IO[bytes] = open(self.path, 'xb')
        except FileExistsError:
            raise BagError(f'{self.path}: file exists; refusing to overwrite it') from None
        except OSError as error:
            raise BagError(f'{self.path}: cannot create: {error.strerror}') from None
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=kinds[compression])
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._file.flush()                  # a valid (empty) bag on disk from the start
        self._schemas: dict[str, int] = {}
        self.channels: dict[str, int] = {}
        self.types: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self._stamped: dict[str, bool] = {}
        self._dirty = False
        self.closed = False

    def add_channel(self, topic: str, type_name: str, offered_qos_profiles: str = '',
                    type_hash: str = '') -> int:
        """Register the topic (once) with its schema; returns the channel id."""
        if topic in self.channels:
            return self.channels[topic]
        if type_name not in self._schemas:
            self._schemas[type_name] = self._writer.register_schema(
                type_name, SCHEMA_ENCODING, message_definition(type_name).encode())
        metadata = {'offered_qos_profiles': offered_qos_profiles}
        if type_hash:
            metadata['topic_type_hash'] = type_hash
        self.channels[topic] = self._writer.register_channel(
            topic, MESSAGE_ENCODING, self._schemas[type_name], metadata)
        self.types[topic] = type_name
        self.counts[topic] = 0
        self._stamped[topic] = has_header(type_name)
        return self.channels[topic]

    def write(self, topic: str, data: bytes, log_time: int, publish_time: int | None = None
              ) -> None:
        """Append one serialized (CDR) message of a registered topic; times in ns.

        publish_time defaults to the header stamp when the type has a header, else log_time.
        """
        if publish_time is None:
            stamp = header_stamp_ns(data) if self._stamped[topic] else None
            publish_time = log_time if stamp is None else stamp
        self._writer.add_message(self.channels[topic], log_time, bytes(data), publish_time,
                                 sequence=self.counts[topic])
        self.counts[topic] += 1
        self._dirty = True

    def flush(self) -> bool:
        """Close the current chunk and flush it to the OS; True when something was written."""
        if not self._dirty or self.closed:
            return False
        self._writer.flush()
        self._dirty = False
        return True

    def close(self) -> None:
        """Write the summary and index and close the file (idempotent)."""
        if self.closed:
            return
        self.closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()


# --- reading -----------------------------------------------------------------------------
@dataclass
class ChannelInfo:
    """A recorded topic: name, type, schema and channel metadata."""

    topic: str
    type: str
    schema_encoding: str
    schema: str
    metadata: dict[str, str]
    message_encoding: str = MESSAGE_ENCODING

    @property
    def qos(self) -> list[OfferedQos]:
        """The offered QoS profiles recorded for the topic."""
        return parse_qos_yaml(self.metadata.get('offered_qos_profiles', ''))


@dataclass
class Record:
    """One recorded message: topic, times (ns) and the CDR bytes."""

    topic: str
    log_time: int
    publish_time: int
    data: bytes


@dataclass
class Scan:
    """Everything a sequential read of an .mcap file recovered, and where it stopped."""

    profile: str = ''
    library: str = ''
    schemas: dict = field(default_factory=dict)       # id -> mcap Schema
    channels: dict = field(default_factory=dict)      # id -> mcap Channel
    messages: list = field(default_factory=list)      # mcap Message records, file order
    chunks: int = 0
    complete: bool = False
    stop_reason: str = ''
    stop_offset: int = 0


def _check_file(path: Path) -> None:
    if not path.exists():
        raise BagError(f'{path}: no such file')
    if path.is_dir():
        raise BagError(f'{path}: is a directory; expected one .mcap file')
    with open(path, 'rb') as stream:
        head = stream.read(len(MAGIC))
    if head != MAGIC:
        raise BagError(f'{path}: not an MCAP file (bad magic bytes)')


def scan(path: str | Path) -> Scan:
    """Read an .mcap file record by record, keeping every complete chunk and message.

    Stops at the first record that is truncated or fails its CRC (a killed writer) and says so
    in ``stop_reason``; ``complete`` is True only when the footer was reached.
    """
    from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Schema
    from mcap.stream_reader import StreamReader, breakup_chunk
    path = Path(path)
    _check_file(path)
    result = Scan()
    with open(path, 'rb') as stream:
        reader = StreamReader(stream, emit_chunks=True, validate_crcs=True,
                              record_size_limit=1 << 31)
        records = reader.records
        while True:
            offset = stream.tell()
            try:
                record = next(records)
                inner = breakup_chunk(record, validate_crc=True) if isinstance(
                    record, Chunk) else [record]
            except StopIteration:
                break
            except Exception as error:  # truncated or corrupt tail: keep what came before
                result.stop_reason = (f'{type(error).__name__} {error}'.strip()
                                      or type(error).__name__)
                result.stop_offset = offset
                break
            if isinstance(record, Chunk):
                result.chunks += 1
            for item in inner:
                if isinstance(item, Header):
                    result.profile, result.library = item.profile, item.library
                elif isinstance(item, Schema):
                    result.schemas.setdefault(item.id, item)
                elif isinstance(item, Channel):
                    result.channels.setdefault(item.id, item)
                elif isinstance(item, Message):
                    result.messages.append(item)
                elif isinstance(item, DataEnd):
                    result.stop_offset = stream.tell()
                elif isinstance(item, Footer):
                    result.complete = True
    if not result.complete and not result.stop_reason:
        result.stop_reason = 'no footer'
    return result


@dataclass
class Bag:
    """A complete bag in memory: channels by topic and all messages in log-time order."""

    path: Path
    profile: str
    library: str
    channels: dict[str, ChannelInfo]
    messages: list[Record]

    def counts(self) -> dict[str, int]:
        """Messages per topic (every channel, zero included)."""
        counts = {topic: 0 for topic in self.channels}
        for record in self.messages:
            counts[record.topic] += 1
        return counts

    def find(self, name: str, required: bool = True) -> str | None:
        """The recorded topic for a name: exact ('/leader/odom') or by suffix ('leader/odom')."""
        if name in self.channels:
            return name
        matches = [t for t in self.channels if t.endswith('/' + name.lstrip('/'))]
        if len(matches) == 1:
            return matches[0]
        if len(matches) > 1:
            raise BagError(f'{self.path}: topic {name!r} is ambiguous: {", ".join(matches)}; '
                           'name it fully')
        if required:
            raise BagError(f'{self.path}: no topic {name!r} in the bag (it has: '
                           f'{", ".join(sorted(self.channels)) or "no topics"})')
        return None

    def records(self, topic: str) -> list[Record]:
        """The messages of one recorded topic, in log-time order."""
        return [r for r in self.messages if r.topic == topic]

    def decode(self, topic: str, expected_type: str | None = None) -> list[tuple[Record, object]]:
        """(record, message) pairs of a topic, deserialized with rclpy (no rclpy.init needed)."""
        from rclpy.serialization import deserialize_message
        channel = self.channels[topic]
        cls = message_class(channel.type, topic)
        if expected_type is not None and channel.type != expected_type:
            raise BagError(f'{self.path}: topic {topic} has type {channel.type}, expected '
                           f'{expected_type}')
        out = []
        for record in self.records(topic):
            try:
                out.append((record, deserialize_message(record.data, cls)))
            except Exception as error:
                raise BagError(f'{self.path}: message on {topic} at log time {record.log_time} '
                               f'ns does not deserialize as {channel.type}: {error}') from None
        return out

    def formation(self, required: Sequence[str], optional: Sequence[str] = (),
                  purpose: str = '') -> dict[str, list[tuple[Record, object]]]:
        """Decoded messages of formation topics (TOPIC_TYPES keys), found by suffix.

        Raises BagError naming the first required topic that is missing or of another type;
        optional topics that are missing map to an empty list.
        """
        why = f' (needed {purpose})' if purpose else ''
        missing = [name for name in required if self.find(name, required=False) is None]
        if missing:
            raise BagError(f'{self.path}: no {", ".join(missing)} topic{why}; the bag has: '
                           f'{", ".join(sorted(self.channels)) or "no topics"}')
        out = {}
        for name in list(required) + list(optional):
            topic = self.find(name, required=False)
            out[name] = [] if topic is None else self.decode(topic, TOPIC_TYPES[name])
        return out


def message_class(type_name: str, topic: str = '') -> type:
    """The Python class of 'pkg/msg/Type'; BagError when the package is not installed."""
    package, namespace, name = split_type(type_name)
    where = f' (topic {topic})' if topic else ''
    try:
        return getattr(importlib.import_module(f'{package}.{namespace}'), name)
    except (ImportError, AttributeError):
        raise BagError(f'unknown message type {type_name!r}{where}: its interface package is '
                       'not installed here') from None


def read_bag(path: str | Path) -> Bag:
    """Load a complete rosbag2 MCAP file; BagError (one clear line) for anything unusable."""
    path = Path(path)
    result = scan(path)
    if not result.complete:
        raise BagError(f'{path}: truncated or corrupt MCAP at byte {result.stop_offset} '
                       f'({result.stop_reason}); was the recorder killed? Recover the complete '
                       f'chunks with: {REPAIR_HINT} {path} FIXED.mcap')
    channels: dict[str, ChannelInfo] = {}
    by_id: dict[int, str] = {}
    for channel in result.channels.values():
        schema = result.schemas.get(channel.schema_id)
        if schema is None:
            raise BagError(f'{path}: channel {channel.topic} has no schema')
        if channel.message_encoding != MESSAGE_ENCODING:
            raise BagError(f'{path}: topic {channel.topic} is encoded as '
                           f'{channel.message_encoding!r}, not {MESSAGE_ENCODING!r} (not ROS 2)')
        channels[channel.topic] = ChannelInfo(
            channel.topic, schema.name, schema.encoding,
            schema.data.decode(errors='replace'), dict(channel.metadata),
            channel.message_encoding)
        by_id[channel.id] = channel.topic
    messages = []
    for message in result.messages:
        if message.channel_id not in by_id:
            raise BagError(f'{path}: a message refers to unknown channel {message.channel_id}')
        messages.append(Record(by_id[message.channel_id], message.log_time,
                               message.publish_time, message.data))
    messages.sort(key=lambda r: r.log_time)
    return Bag(path, result.profile, result.library, channels, messages)


def rosbags_typestore(packages: Sequence[str] = ('formopt_interfaces',)):
    """A rosbags typestore (ROS 2 Jazzy) with every .msg of ``packages`` registered."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    store = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for package in packages:
        for prefix in share_prefixes():
            folder = prefix / 'share' / package / 'msg'
            if folder.is_dir():
                for path in sorted(folder.glob('*.msg')):
                    types.update(get_types_from_msg(path.read_text(),
                                                    f'{package}/msg/{path.stem}'))
                break
    store.register(types)
    return store


# --- repair ------------------------------------------------------------------------------
@dataclass
class RepairResult:
    """What :func:`repair` kept from a damaged file."""

    kept: int
    chunks: int
    counts: dict[str, int]
    was_complete: bool
    stop_reason: str
    stop_offset: int
    size: int


def repair(source: str | Path, target: str | Path) -> RepairResult:
    """Write a valid MCAP with every complete chunk and message of a truncated one."""
    from mcap.writer import CompressionType, Writer
    source, target = Path(source), Path(target)
    if target.exists():
        raise BagError(f'{target}: file exists; refusing to overwrite it')
    result = scan(source)
    counts: dict[str, int] = {c.topic: 0 for c in result.channels.values()}
    try:
        stream = open(target, 'xb')
    except OSError as error:
        raise BagError(f'{target}: cannot create: {error.strerror}') from None
    with stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile=result.profile or PROFILE, library=result.library or LIBRARY)
        schema_ids = {old: writer.register_schema(s.name, s.encoding, s.data)
                      for old, s in result.schemas.items()}
        channel_ids = {}
        for old, channel in result.channels.items():
            channel_ids[old] = writer.register_channel(
                channel.topic, channel.message_encoding, schema_ids.get(channel.schema_id, 0),
                dict(channel.metadata))
        topics = {c.id: c.topic for c in result.channels.values()}
        kept = 0
        for message in result.messages:
            if message.channel_id in channel_ids:
                writer.add_message(channel_ids[message.channel_id], message.log_time,
                                   message.data, message.publish_time, message.sequence)
                counts[topics[message.channel_id]] += 1
                kept += 1
        writer.finish()
    return RepairResult(kept, result.chunks, counts, result.complete, result.stop_reason,
                        result.stop_offset, source.stat().st_size)


# --- command line ------------------------------------------------------------------------
def info(bag: Bag) -> dict:
    """Summary of a bag: profile, library, duration and per-topic type and count."""
    counts = bag.counts()
    times = [r.log_time for r in bag.messages]
    return {
        'path': str(bag.path), 'profile': bag.profile, 'library': bag.library,
        'messages': len(bag.messages),
        'start_ns': min(times) if times else None, 'end_ns': max(times) if times else None,
        'duration_s': (max(times) - min(times)) * 1e-9 if times else 0.0,
        'topics': {topic: {'type': c.type, 'count': counts[topic],
                           'schema_encoding': c.schema_encoding,
                           'type_hash': c.metadata.get('topic_type_hash', '')}
                   for topic, c in sorted(bag.channels.items())},
    }


def main(argv: list[str] | None = None) -> int:
    """``formopt-bag info BAG`` and ``formopt-bag repair IN OUT``; exit 2 on a bad bag."""
    parser = argparse.ArgumentParser(prog='formopt-bag', description=__doc__)
    commands = parser.add_subparsers(dest='command', required=True)
    show = commands.add_parser('info', help='topics, types and counts of a bag')
    show.add_argument('bag', type=Path)
    show.add_argument('--json', action='store_true', help='print JSON instead of a table')
    fix = commands.add_parser('repair', help='recover the complete chunks of a truncated bag')
    fix.add_argument('source', type=Path, metavar='IN')
    fix.add_argument('target', type=Path, metavar='OUT')
    args = parser.parse_args(argv)
    try:
        if args.command == 'info':
            summary = info(read_bag(args.bag))
            if args.json:
                print(json.dumps(summary, indent=2))
            else:
                print(f"{summary['path']}: profile {summary['profile']!r}, "
                      f"{summary['messages']} messages, {summary['duration_s']:.3f} s")
                for topic, row in summary['topics'].items():
                    print(f"  {topic:32s} {row['type']:48s} {row['count']:8d}")
            return 0
        result = repair(args.source, args.target)
        state = ('the file was complete' if result.was_complete else
                 f'dropped the tail from byte {result.stop_offset} of {result.size} '
                 f'({result.stop_reason})')
        print(f'kept {result.kept} messages in {result.chunks} chunks; {state}; '
              f'wrote {args.target}')
        for topic, count in sorted(result.counts.items()):
            print(f'  {topic:32s} {count:8d}')
        return 0
    except BagError as error:
        print(f'error: {error}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
