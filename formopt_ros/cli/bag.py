"""formopt-bag: describe a bag, or recover the readable chunks of a damaged one."""
from __future__ import annotations

import json
import sys

from formopt_ros.bag import BagError, read_bag, repair
from formopt_ros.bag.reader import info
from formopt_ros.cli.common import ArgumentParser, bag_file, command, fail, new_file


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(prog='formopt-bag', description='Describe a rosbag2 MCAP file, or '
                            'recover every readable chunk of a damaged or truncated one.')
    commands = parser.add_subparsers(dest='command', required=True)
    show = commands.add_parser('info', help='topics, types and counts of a bag')
    show.add_argument('bag', type=bag_file)
    show.add_argument('--json', action='store_true', help='print JSON instead of a table')
    fix = commands.add_parser('repair', help='recover the readable chunks of a damaged bag '
                              '(killed recorder, flipped bytes)')
    fix.add_argument('source', type=bag_file, metavar='IN')
    fix.add_argument('target', type=new_file, metavar='OUT', help='a new file (never '
                     'overwritten)')
    for sub in (show, fix):
        sub.error = parser.error             # type: ignore[method-assign]
    return parser


@command('formopt-bag')
def main(argv: list[str] | None = None) -> int:
    """``formopt-bag info BAG`` and ``formopt-bag repair IN OUT``; exit 2 on a bad bag.

    repair exits 1 when messages of intact chunks could not be recovered (their channel or
    schema was lost); the partial repair is still written.
    """
    args = build_parser().parse_args(argv)
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
    except BagError as error:
        fail('formopt-bag', str(error))
    skipped = (f'; skipped {len(result.damage)} damaged stretch(es) at bytes '
               + ', '.join(str(d.offset) for d in result.damage[:5]) if result.damage else '')
    if result.summary_messages is not None and result.damage:
        lost = result.summary_messages - result.kept - result.lost
        skipped += f' ({lost} of the {result.summary_messages} messages its summary counts)'
    if result.kept == 0:
        print(f'formopt-bag: nothing recoverable: no message of {args.source} could be read'
              f'{skipped}; {args.target} holds no message', file=sys.stderr)
        return 1
    state = ('the file was complete' if result.was_complete and not result.damage else
             'the file ended cleanly' if result.was_complete else
             f'dropped the tail from byte {result.stop_offset} of {result.size} '
             f'({result.stop_reason})')
    print(f'kept {result.kept} messages in {result.chunks} chunks; {state}{skipped}; '
          f'wrote {args.target}')
    for topic, count in sorted(result.counts.items()):
        print(f'  {topic:32s} {count:8d}')
    if result.rebuilt:
        print(f'rebuilt {len(result.rebuilt)} lost schema(s) from the channels\' type names: '
              + ', '.join(sorted(set(result.rebuilt.values()))))
    if result.lost:
        groups: dict[str, list[str]] = {}
        for old in result.unrecoverable:
            groups.setdefault(result.why[old], []).append(str(old))
        reasons = '; '.join(f"{why} (channel{'s' if len(ids) > 1 else ''} {', '.join(ids)})"
                            for why, ids in groups.items())
        print(f'formopt-bag: partial repair: {result.lost} messages of intact chunks could not '
              f'be recovered, their channel or schema is unknown: {reasons}; {args.target} has '
              'the rest', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
