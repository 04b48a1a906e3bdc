"""Reading rosbag2 MCAP bags (one file, or the folder of a split recording): a record scan that
survives damage, and decoding with rosbags.

Messages are decoded with a rosbags typestore built from the bag's own ros2msg schemas, so
reading a bag needs neither rclpy nor the message packages that recorded it.
"""
from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from formopt_ros.bag.errors import BagError
from formopt_ros.bag.qos import Qos, parse_qos_yaml
from formopt_ros.bag.writer import MESSAGE_ENCODING

MAGIC = b'\x89MCAP0\r\n'
REPAIR_HINT = 'formopt-bag repair'
#: Record header: opcode (1 byte) and content length (8 bytes, little endian).
_RECORD_HEADER = 9
_OP_CHUNK, _OP_FOOTER = 0x06, 0x02
_KNOWN_OPCODES = set(range(0x01, 0x10))


@dataclass
class Damage:
    """A stretch of the file that could not be read."""

    offset: int
    length: int
    reason: str


@dataclass
class Scan:
    """Everything a sequential read of an .mcap file recovered, and what it could not read.

    ``complete`` is True when the footer was reached; ``damage`` lists the unreadable stretches
    (a chunk with a bad CRC, garbage between records); a truncated tail sets ``stop_reason``.
    """

    profile: str = ''
    library: str = ''
    schemas: dict = field(default_factory=dict)       # id -> mcap Schema
    channels: dict = field(default_factory=dict)      # id -> mcap Channel
    messages: list = field(default_factory=list)      # mcap Message records, file order
    chunks: int = 0
    complete: bool = False
    damage: list[Damage] = field(default_factory=list)
    stop_reason: str = ''
    stop_offset: int = 0
    summary_messages: int | None = None                # the Statistics record's count, if read


def _check_file(path: Path) -> bytes:
    if not path.exists():
        raise BagError(f'{path}: no such file')
    if path.is_dir():
        raise BagError(f'{path}: is a directory; expected one .mcap file')
    try:
        data = path.read_bytes()
    except OSError as error:
        raise BagError(f'{path}: cannot read: {error.strerror}') from None
    if data[:len(MAGIC)] != MAGIC:
        raise BagError(f'{path}: not an MCAP file (bad magic bytes)')
    return data


def _parse(data: bytes, offset: int, end: int) -> list[Any]:
    """The records of the one framed record data[offset:end] (a chunk's contents unpacked)."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, breakup_chunk
    reader = StreamReader(io.BytesIO(data[offset:end]), skip_magic=True, emit_chunks=True,
                          validate_crcs=True, record_size_limit=None)
    record = next(iter(reader.records))
    if isinstance(record, Chunk):
        return [record] + breakup_chunk(record, validate_crc=True)
    return [record]


def _framed_end(data: bytes, offset: int) -> int | None:
    """End of the record starting at offset if its opcode and length are plausible."""
    if offset + _RECORD_HEADER > len(data) or data[offset] not in _KNOWN_OPCODES:
        return None
    end = offset + _RECORD_HEADER + int.from_bytes(data[offset + 1:offset + 9], 'little')
    return end if end <= len(data) else None


def _resync(data: bytes, start: int) -> int | None:
    """Offset of the next chunk after ``start`` that parses and passes its CRC, or None."""
    position = data.find(bytes([_OP_CHUNK]), start)
    while position != -1:
        end = _framed_end(data, position)
        if end is not None:
            try:
                _parse(data, position, end)
                return position
            except Exception:
                pass
        position = data.find(bytes([_OP_CHUNK]), position + 1)
    return None


def scan(path: str | Path) -> Scan:
    """Read an .mcap file record by record, keeping every readable chunk and message.

    A record that fails to parse (a chunk with a bad CRC or a bad compressed stream) is skipped
    by its length; where the framing itself is broken, reading resumes at the next chunk that
    parses. A tail cut short (a killed writer) ends the scan with ``stop_reason``.
    """
    from mcap.records import Channel, Chunk, Footer, Header, Message, Schema, Statistics
    path = Path(path)
    data = _check_file(path)
    result = Scan()
    offset = len(MAGIC)
    while offset < len(data):
        end = _framed_end(data, offset)
        records: list[Any] | None = None
        reason = ''
        if end is not None:
            try:
                records = _parse(data, offset, end)
            except Exception as error:       # bad CRC, bad compression, malformed content
                reason = f'{type(error).__name__} {error}'.strip()
        if records is None:
            following = _resync(data, offset + 1)
            if following is None:            # nothing readable after: a truncated tail
                if end is not None and reason:
                    result.damage.append(Damage(offset, end - offset, reason))
                    offset = end
                    continue
                result.stop_reason = reason or ('truncated record' if offset + _RECORD_HEADER
                                                <= len(data) else 'truncated file')
                result.stop_offset = offset
                break
            skip_to = end if end is not None and end <= following else following
            result.damage.append(Damage(offset, skip_to - offset,
                                        reason or 'unreadable bytes between records'))
            offset = skip_to
            continue
        for item in records:
            if isinstance(item, Header):
                result.profile, result.library = item.profile, item.library
            elif isinstance(item, Chunk):
                result.chunks += 1
            elif isinstance(item, Schema):
                result.schemas.setdefault(item.id, item)
            elif isinstance(item, Channel):
                result.channels.setdefault(item.id, item)
            elif isinstance(item, Message):
                result.messages.append(item)
            elif isinstance(item, Statistics):
                result.summary_messages = item.message_count
            elif isinstance(item, Footer):
                result.complete = True
        assert end is not None                   # records parsed: the framing was plausible
        offset = end
        if result.complete:
            break
    if not result.complete and not result.stop_reason:
        result.stop_reason = 'no footer'
        result.stop_offset = offset
    return result


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
    def qos(self) -> list[Qos]:
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
class Bag:
    """A complete bag in memory: channels by topic and all messages in log-time order."""

    path: Path
    profile: str
    library: str
    channels: dict[str, ChannelInfo]
    messages: list[Record]
    _typestore: Any = field(default=None, repr=False)

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

    def typestore(self) -> Any:
        """A rosbags typestore with every type of the bag, from the bag's own schemas."""
        if self._typestore is None:
            from rosbags.typesys import Stores, get_types_from_msg, get_typestore
            store = get_typestore(Stores.EMPTY)
            types: dict = {}
            for channel in self.channels.values():
                if channel.schema_encoding != 'ros2msg':
                    raise BagError(f'{self.path}: topic {channel.topic} has a '
                                   f'{channel.schema_encoding!r} schema; only ros2msg is read')
                try:
                    types.update(get_types_from_msg(channel.schema, channel.type))
                except Exception as error:
                    raise BagError(f'{self.path}: the schema of {channel.topic} '
                                   f'({channel.type}) does not parse: {error}') from None
            store.register(types)
            self._typestore = store
        return self._typestore

    def decode(self, topic: str, expected_type: str | None = None) -> list[tuple[Record, Any]]:
        """(record, message) pairs of a topic, decoded with rosbags (no ROS needed)."""
        channel = self.channels[topic]
        if expected_type is not None and channel.type != expected_type:
            raise BagError(f'{self.path}: topic {topic} has type {channel.type}, expected '
                           f'{expected_type}')
        store = self.typestore()
        out = []
        for record in self.records(topic):
            try:
                out.append((record, store.deserialize_cdr(record.data, channel.type)))
            except Exception as error:
                raise BagError(f'{self.path}: message on {topic} at log time {record.log_time} '
                               f'ns does not decode as {channel.type}: {error}') from None
        return out


def _read_file(path: Path) -> Bag:
    """One complete rosbag2 MCAP file; BagError (one clear line) for anything unusable."""
    result = scan(path)
    if not result.complete or result.damage:
        where = (f'damaged at byte {result.damage[0].offset} ({result.damage[0].reason})'
                 if result.damage else
                 f'truncated or corrupt at byte {result.stop_offset} ({result.stop_reason})')
        raise BagError(f'{path}: {where}; was the recorder killed? Recover the readable '
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


def _split_index(path: Path) -> tuple[str, int]:
    """Sort key of a split file: its stem without the _N suffix, then N (run_2 before run_10)."""
    match = re.fullmatch(r'(.*)_(\d+)', path.stem)
    return (match.group(1), int(match.group(2))) if match else (path.stem, -1)


def bag_files(path: str | Path) -> list[Path]:
    """The .mcap files of a bag in recording order: the file itself, or those of a rosbag2
    folder (its metadata.yaml's ``relative_file_paths``, else every .mcap file by split
    index); BagError for a folder without one or of another storage (sqlite3)."""
    path = Path(path)
    if not path.is_dir():
        return [path]
    metadata = path / 'metadata.yaml'
    convert = ('record with `ros2 bag record -s mcap`, or convert the bag with `ros2 bag '
               'convert`')
    if metadata.is_file():
        try:
            information = yaml.safe_load(metadata.read_text())['rosbag2_bagfile_information']
            storage = information.get('storage_identifier', 'mcap')
            files = [path / name for name in information['relative_file_paths']]
        except (yaml.YAMLError, OSError, KeyError, TypeError, AttributeError):
            raise BagError(f'{metadata}: not a rosbag2 metadata file') from None
        if storage != 'mcap':
            raise BagError(f'{path}: a {storage} bag; only MCAP is read: {convert}')
        return files
    found = sorted(path.glob('*.mcap'), key=_split_index)
    if not found:
        raise BagError(f'{path}: a folder without an .mcap file ({convert})')
    keys = [_split_index(file) for file in found]
    if len(found) > 1 and (len({name for name, _ in keys}) > 1 or
                           any(index < 0 for _, index in keys)):
        raise BagError(f'{path}: holds {len(found)} .mcap files that are not the parts of one '
                       'split recording (NAME_0.mcap, NAME_1.mcap, ...): pass one of them')
    return found


def read_bag(path: str | Path) -> Bag:
    """Load a complete rosbag2 MCAP bag: one file, or the files of a split recording's folder
    (:func:`bag_files`) as one bag; BagError (one clear line) for anything unusable."""
    path = Path(path)
    parts = [_read_file(file) for file in bag_files(path)]
    if len(parts) == 1:
        return parts[0]
    channels: dict[str, ChannelInfo] = {}
    for part in parts:
        for topic, channel in part.channels.items():
            if channels.setdefault(topic, channel).type != channel.type:
                raise BagError(f'{part.path}: topic {topic} has type {channel.type}, '
                               f'{channels[topic].type} in an earlier file of {path}')
    messages = sorted((record for part in parts for record in part.messages),
                      key=lambda record: record.log_time)
    return Bag(path, parts[0].profile, parts[0].library, channels, messages)


def info(bag: Bag) -> dict[str, Any]:
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
