"""Recovering a damaged or truncated bag: every readable chunk and message into a valid file."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from formopt_ros.bag.errors import BagError
from formopt_ros.bag.reader import Damage, scan
from formopt_ros.bag.writer import LIBRARY, PROFILE


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
    damage: list[Damage] = field(default_factory=list)


def repair(source: str | Path, target: str | Path) -> RepairResult:
    """Write a valid MCAP with every readable chunk and message of a damaged one.

    Chunks whose CRC or compression fails are skipped (and listed in ``damage``); reading
    resumes after them, so one flipped byte costs one chunk, not the rest of the file.
    """
    from mcap.writer import CompressionType, Writer
    source, target = Path(source), Path(target)
    if target.exists():
        raise BagError(f'{target}: file exists; refusing to overwrite it')
    result = scan(source)
    counts: dict[str, int] = {c.topic: 0 for c in result.channels.values()}
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
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
                        result.stop_offset, source.stat().st_size, result.damage)
