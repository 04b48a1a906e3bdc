"""Recovering a damaged or truncated bag: every readable chunk and message into a valid file."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from formopt_ros.bag.errors import BagError
from formopt_ros.bag.reader import Damage, scan
from formopt_ros.bag.schema import SCHEMA_ENCODING, message_definition
from formopt_ros.bag.writer import LIBRARY, PROFILE, TYPE_KEY


@dataclass
class RepairResult:
    """What :func:`repair` kept from a damaged file, and what it could not.

    ``unrecoverable`` counts, per channel id of the damaged file, the messages of intact chunks
    that were not written because their Channel record, or the channel's Schema record, was
    lost (the plain chunked mcap Writer puts them only into the chunk where a channel is
    registered); ``why`` says which, per channel id. ``rebuilt`` names, per channel id, the
    type whose lost schema was rebuilt from the channel's metadata (bags of BagWriter) and the
    installed message definitions.
    """

    kept: int
    chunks: int
    counts: dict[str, int]
    was_complete: bool
    stop_reason: str
    stop_offset: int
    size: int
    damage: list[Damage] = field(default_factory=list)
    unrecoverable: dict[int, int] = field(default_factory=dict)
    why: dict[int, str] = field(default_factory=dict)
    rebuilt: dict[int, str] = field(default_factory=dict)
    summary_messages: int | None = None       # messages the damaged file's summary counts

    @property
    def lost(self) -> int:
        """Messages of intact chunks that could not be written (see ``unrecoverable``)."""
        return sum(self.unrecoverable.values())


def repair(source: str | Path, target: str | Path) -> RepairResult:
    """Write a valid MCAP with every readable chunk and message of a damaged one.

    Chunks whose CRC or compression fails are skipped (and listed in ``damage``); reading
    resumes after them, so one flipped byte costs one chunk, not the rest of the file. A
    message whose channel, or whose channel's schema, is nowhere in the readable records cannot
    be written as a ROS message: it is counted in ``unrecoverable`` (never dropped silently),
    unless the channel names its type (``TYPE_KEY``) and the schema can be rebuilt from the
    installed definitions. A channel without a usable schema is left out, so the output always
    reads with :func:`~formopt_ros.bag.read_bag`.
    """
    from mcap.writer import CompressionType, Writer
    source, target = Path(source), Path(target)
    if target.exists():
        raise BagError(f'{target}: file exists; refusing to overwrite it')
    result = scan(source)
    why = {old: 'Channel record lost' for old in
           {m.channel_id for m in result.messages} - set(result.channels)}
    rebuilt: dict[int, str] = {}                   # channel id -> type of its rebuilt schema
    definitions: dict[str, str] = {}               # type -> its installed definition
    for old, channel in result.channels.items():
        if channel.schema_id in result.schemas:
            continue
        type_name = channel.metadata.get(TYPE_KEY, '')
        if channel.schema_id and type_name:
            try:
                definitions.setdefault(type_name, message_definition(type_name))
                rebuilt[old] = type_name
                continue
            except BagError as error:
                why[old] = f'Schema record of {channel.topic} lost and {error}'
        else:
            why[old] = (f'Schema record of {channel.topic} lost' if channel.schema_id else
                        f'{channel.topic} has no schema')
    usable = {old: c for old, c in result.channels.items() if old not in why}
    counts: dict[str, int] = {c.topic: 0 for c in usable.values()}
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        stream = open(target, 'xb')
    except OSError as error:
        raise BagError(f'{target}: cannot create: {error.strerror}') from None
    unrecoverable: dict[int, int] = {}
    with stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile=result.profile or PROFILE, library=result.library or LIBRARY)
        used = {c.schema_id for c in usable.values()}
        schema_ids = {old: writer.register_schema(s.name, s.encoding, s.data)
                      for old, s in result.schemas.items() if old in used}
        for type_name in sorted(definitions):
            schema_ids[('rebuilt', type_name)] = writer.register_schema(
                type_name, SCHEMA_ENCODING, definitions[type_name].encode())
        channel_ids = {}
        for old, channel in usable.items():
            schema_id = schema_ids[('rebuilt', rebuilt[old]) if old in rebuilt
                                   else channel.schema_id]
            channel_ids[old] = writer.register_channel(
                channel.topic, channel.message_encoding, schema_id, dict(channel.metadata))
        kept = 0
        for message in result.messages:
            if message.channel_id in channel_ids:
                writer.add_message(channel_ids[message.channel_id], message.log_time,
                                   message.data, message.publish_time, message.sequence)
                counts[usable[message.channel_id].topic] += 1
                kept += 1
            else:
                unrecoverable[message.channel_id] = unrecoverable.get(message.channel_id, 0) + 1
        writer.finish()
    return RepairResult(kept, result.chunks, counts, result.complete, result.stop_reason,
                        result.stop_offset, source.stat().st_size, result.damage,
                        dict(sorted(unrecoverable.items())),
                        {old: why[old] for old in sorted(unrecoverable)}, rebuilt,
                        result.summary_messages)
