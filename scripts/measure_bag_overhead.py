"""What self-describing chunks cost: rewrite a recorded bag at its own chunk boundaries with and
without them (formopt_ros.bag.writer) and print both sizes.

Usage: .venv/bin/python scripts/measure_bag_overhead.py RUN.mcap [RUN.mcap ...]
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from mcap.records import Chunk
from mcap.stream_reader import StreamReader

from formopt_ros.bag import writer
from formopt_ros.bag.reader import read_bag


def chunk_end_times(path: Path) -> list[int]:
    """The last message time (ns) of every chunk of ``path``, in file order."""
    with open(path, 'rb') as stream:
        return [record.message_end_time for record in
                StreamReader(stream, emit_chunks=True).records if isinstance(record, Chunk)]


def rewrite(source: Path, target: Path, described: bool) -> int:
    """Write the messages of ``source`` to ``target`` with the same chunk boundaries, with or
    without self-describing chunks; the size of ``target`` in bytes."""
    loaded, ends = read_bag(source), chunk_end_times(source)
    original = writer._self_describing_chunks
    if not described:
        writer._self_describing_chunks = lambda mcap_writer: None
    try:
        out = writer.BagWriter(target)
        for topic, channel in loaded.channels.items():
            out.add_channel(topic, channel.type,
                            channel.metadata.get('offered_qos_profiles', ''),
                            channel.metadata.get('topic_type_hash', ''))
        for record in loaded.messages:
            while ends and record.log_time > ends[0]:
                out.flush()
                ends.pop(0)
            out.write(record.topic, record.data, record.log_time)
        out.close()
    finally:
        writer._self_describing_chunks = original
    return target.stat().st_size


def main(paths: list[str]) -> None:
    """Print one line per bag."""
    for name in paths:
        source = Path(name)
        with tempfile.TemporaryDirectory() as folder:
            plain = rewrite(source, Path(folder) / 'plain.mcap', False)
            described = rewrite(source, Path(folder) / 'described.mcap', True)
        print(f'{source}: {len(chunk_end_times(source))} chunks; plain {plain} B, '
              f'self-describing {described} B (+{100 * (described - plain) / plain:.1f} %)')


if __name__ == '__main__':
    main(sys.argv[1:])
