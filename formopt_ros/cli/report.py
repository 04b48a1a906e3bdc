"""formopt-report: figures and a summary of one recorded formation run (an .mcap bag)."""
from __future__ import annotations

import sys

from formopt_ros.cli.common import (
    ArgumentParser, bag_file, command, fail, integer, new_folder)


def build_parser() -> ArgumentParser:
    """The command-line interface."""
    parser = ArgumentParser(prog='formopt-report', description='Figures (trajectory, weighted '
                            'trace, NEES) and a summary of a recorded formation run.')
    parser.add_argument('bag', type=bag_file, help='the recorded .mcap file (or its folder)')
    parser.add_argument('--out', type=new_folder, required=True,
                        help='output folder (new, or empty)')
    parser.add_argument('--follower', help='report this follower only (default: every one)')
    parser.add_argument('--trajectory-steps', type=integer(1), default=40,
                        help='steps drawn in the trajectory figure (default: first 40)')
    return parser


@command('formopt-report')
def main(argv: list[str] | None = None) -> int:
    """Console entry point: ``formopt-report BAG --out DIR``; exit 2 on a bad bag."""
    args = build_parser().parse_args(argv)
    # imported here, inside @command: a Ctrl-C during the slow imports (matplotlib, rosbags)
    # is one 'interrupted' line, not a traceback
    from formopt_ros.analysis.recording import load_recording
    from formopt_ros.analysis.report import make_report, steps_text
    from formopt_ros.bag import BagError, read_bag
    try:
        summary = make_report(load_recording(read_bag(args.bag)), args.out,
                              args.trajectory_steps, args.follower)
    except BagError as error:
        fail('formopt-report', str(error))
    for follower, row in summary['followers'].items():
        nees = 'n/a' if row['mean_nees'] is None else f"{row['mean_nees']:.3f}"
        nees += '' if row['consistent'] else ' (inconsistent)'
        print(f"{args.bag} {follower}: {steps_text(row)} steps, {row['strategy']}, "
              f"{row['measurement']}; steady tr(W P W) {row['steady_weighted_trace']:.6g} m^2; "
              f'mean NEES {nees}')
        if not row['consistent']:
            print(f"formopt-report: warning: {follower}: the filter was inconsistent "
                  f"{row['inconsistency']} (the estimator's consistency watch on the recorded "
                  'NEES): the run is not ok', file=sys.stderr)
        if row['missing_steps']:
            print(f"formopt-report: warning: {follower}: the bag lacks steps "
                  f"{row['missing_ranges']} ({row['missing_steps']} of {row['steps']}: a "
                  'damaged, repaired or cut recording); the values cover the recorded steps '
                  'only', file=sys.stderr)
    print(f"wrote {', '.join(summary['figures'])}, summary.json, summary.md to {args.out}")
    return 0


if __name__ == '__main__':
    sys.exit(main())
