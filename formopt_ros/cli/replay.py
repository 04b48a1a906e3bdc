"""replay: republish a formation bag with its recorded timing, or (--offline, no ROS needed)
re-run a follower's estimator over the bag's inputs and compare with what it published."""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from formopt_ros.analysis.offline import offline
from formopt_ros.analysis.recording import load_recording
from formopt_ros.analysis.report import step_ranges
from formopt_ros.bag import BagError, read_bag
from formopt_ros.cli.common import (
    INTERRUPTED_EXIT, ArgumentParser, bag_file, command, existing_file, fail, integer, new_file,
    number)
from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.wire.jsonfile import write_json

PROG = 'replay'


def split_ros_args(argv: list[str]) -> tuple[list[str], list[str]]:
    """(plain arguments, ROS arguments) of a command line: ROS ones follow '--ros-args' up to
    '--' (or the end), as rcl parses them."""
    plain: list[str] = []
    ros: list[str] = []
    inside = False
    for arg in argv:
        if arg == '--ros-args':
            inside = True
            ros.append(arg)
        elif arg == '--' and inside:
            inside = False
        elif inside:
            ros.append(arg)
        else:
            plain.append(arg)
    return plain, ros


def option_value(text: str) -> tuple[str, Any]:
    """NAME=VALUE of --strategy-option, the value parsed as JSON (numbers, true/false)."""
    name, sep, value = text.partition('=')
    if not sep or not name:
        raise ValueError(f'expected NAME=VALUE, got {text!r}')
    try:
        return name, json.loads(value)
    except json.JSONDecodeError:
        return name, value


#: Defaults of --tolerance (the largest admissible difference) and --skip (measurements left
#: out).
TOLERANCE, SKIP = 1e-9, 30


def build_parser() -> ArgumentParser:
    """Command-line flags of ``replay`` (ROS arguments after --ros-args are passed through)."""
    out = ArgumentParser(prog=PROG, description=__doc__)
    out.add_argument('bag', type=bag_file, nargs='?',
                     help='the .mcap file (or -p bag_path:=... after --ros-args)')
    speed = out.add_mutually_exclusive_group()
    speed.add_argument('--rate', type=number(1e-3, 1e6), help='playback speed factor '
                       '(default 1)')
    speed.add_argument('--fast', action='store_true', help='ignore the recorded timing')
    out.add_argument('--topics', nargs='+', help='topics to replay (default: all)')
    out.add_argument('--wait-subscribers', type=integer(0, 1000),
                     help='wait for this many subscribers per topic before starting')
    out.add_argument('--clock', action='store_true',
                     help="publish /clock at the recorded time (nodes with use_sim_time:=true "
                     "then take the bag's stamps as current)")
    flags = out.add_argument_group('offline mode (no ROS needed)')
    flags.add_argument('--offline', action='store_true',
                       help="re-run a follower's estimator from the core over the bag instead")
    flags.add_argument('--follower', help='which follower (default: the only one)')
    flags.add_argument('--strategy', choices=tuple(STRATEGIES),
                       help='default: from the run description (another one is a what-if: '
                       'where its waypoints differ from the recorded ones the check fails; '
                       'RAM and RQ choose the same points, so they pass each other\'s check)')
    flags.add_argument('--strategy-option', action='append', default=[], metavar='NAME=VALUE',
                       help="a strategy option (e.g. cell=0.01), replacing the recorded one")
    flags.add_argument('--seed', type=integer(0, 2**31 - 1),
                       help='seed of the run (default: from the run description)')
    flags.add_argument('--trial', type=integer(0, 2**31 - 1),
                       help='trial index (default: from the run description)')
    flags.add_argument('--tolerance', type=number(0.0),
                       help=f'largest admissible difference (default {TOLERANCE:g})')
    flags.add_argument('--json', type=new_file, help='also write the result here (a new file)')
    flags.add_argument('--topic-map', type=existing_file, metavar='MAP',
                       help='a bag of standard types (another robot, a data set): which topic is '
                       'which input and the filter settings (YAML, see '
                       'formopt_ros/analysis/foreign.py); re-estimates it with the planner off '
                       'and reports its consistency, and NEES and RMS error against its ground '
                       'truth; exit 1 when the filter is inconsistent')
    flags.add_argument('--estimates', type=new_file, metavar='CSV',
                       help='--topic-map: write the estimate at every measurement here (a new CSV '
                       'file: stamp, pose in the leader frame, covariance)')
    flags.add_argument('--skip', type=integer(0, 10**9),
                       help='--topic-map: measurements left out of the evaluation at the start '
                       f'(default {SKIP})')
    return out


def foreign_main(args: Any) -> int:
    """``replay BAG --offline --topic-map MAP``: print the evaluation; exit 1 when the filter
    is inconsistent, 2 on errors."""
    from formopt_ros.analysis.foreign import estimate_foreign, read_foreign, write_estimates
    from formopt_ros.wire.topic_map import TopicMap
    try:
        topics = TopicMap.load(args.topic_map)
        data = read_foreign(read_bag(args.bag), topics)
        if not data.measurements:
            fail(PROG, f'{args.bag}: no valid message on {topics.measurement}')
        result = estimate_foreign(data, topics.estimator)
    except (BagError, ValueError) as error:
        fail(PROG, str(error))
    summary = result.summary(args.skip)
    counters = summary['counters']
    dropped = {k: v for k, v in counters.items() if v and k in (
        'late_odometry', 'late_measurements', 'duplicates', 'refused_not_finite',
        'refused_out_of_range')}
    kind = f'{topics.kind}s'                     # 'ranges' or 'bearings'
    print(f"offline estimate of {args.bag} through {args.topic_map}: "
          f"{summary['measurements']} {kind}, {counters['odometry']} odometry messages "
          f"(bridged {counters['bridged']}, gaps {counters['gaps']}, gated "
          f"{counters['gated_measurements']}, down-weighted "
          f"{counters['downweighted_measurements']}"
          + ''.join(f', {k.replace("_", " ")} {v}' for k, v in dropped.items()) + ')')
    worst = summary['consistency']['worst']
    print('consistency of the re-estimate: ' + (
        'ok' if worst['level'] == 'ok' else
        f"{worst['level'].upper()} at {topics.kind} {worst['step']}: {worst['reason']}"))
    if args.estimates:
        write_estimates(args.estimates, result)
    if summary['mean_nees'] is None:
        if topics.relative_truth or (topics.leader_truth and topics.follower_truth):
            print(f'no applied {topics.kind} lies within the ground truth\'s time span (after '
                  f'the first {args.skip}): nothing evaluated', file=sys.stderr)
            return 1
        print('the topic map names no ground truth: no evaluation'
              + ('' if topics.estimator['initial_pose'] else
                 ' (without it the estimate starts from the first measurement, a range along '
                 '-x: give estimator initial_pose, the follower in the leader\'s frame)'))
    else:
        bias = summary['final_bias_m']
        print(f"after {args.skip} {kind}: mean NEES {summary['mean_nees']:.3f} (3 is "
              f"consistent), RMS position error {summary['rmse_m']:.3f} m over "
              f"{summary['evaluated']} {kind}" +
              ('' if bias is None else f'; estimated range bias at the end {bias:.3f} m'))
    if args.json:
        write_json(args.json, {'bag': str(args.bag), 'topic_map': str(args.topic_map),
                               **summary})
    return 0 if summary['ok'] else 1


def offline_main(args: Any) -> int:
    """``replay BAG --offline``: print the differences; exit 1 above tolerance, 2 on errors."""
    try:
        options = dict(option_value(text) for text in args.strategy_option)
    except ValueError as error:
        fail(PROG, f'--strategy-option: {error}')
    try:
        recording = load_recording(read_bag(args.bag))
        follower = recording.follower(args.follower)
        merged = None
        if options or args.strategy:
            base = {} if args.strategy and args.strategy != follower.description.strategy \
                else dict(follower.description.options)
            merged = {**base, **options}
        result = offline(recording, args.follower, strategy=args.strategy, options=merged,
                         seed=args.seed, trial=args.trial)
    except BagError as error:
        fail(PROG, str(error))
    ok = result.max_diff <= args.tolerance
    way = 'n/a' if result.max_waypoint_diff is None else f'{result.max_waypoint_diff:.3e}'
    source = 'reconstructed from the messages' if result.legacy else 'recorded'
    print(f'offline replay of {args.bag} ({result.follower_id}): {result.steps} steps '
          f're-estimated ({result.recorded_steps} recorded; strategy {result.strategy}, '
          f'{result.measurement}, {result.mode}; run description {source})')
    print(f'max |estimate - recorded|: state {result.max_state_diff:.3e}, covariance '
          f'{result.max_covariance_diff:.3e}; waypoints {way} m; stamps '
          f'{result.max_stamp_diff_ns} ns')
    worst = result.consistency['worst']
    print('consistency of the re-estimate: ' + (
        'ok' if worst['level'] == 'ok' else
        f"{worst['level'].upper()} at step {worst['step']}: {worst['reason']}"))
    planned = follower.description.steps
    absent, first = list(result.absent), result.last_step + 1
    while absent and absent[-1] == first - 1:       # missing up to the cut: part of the cut
        first = absent.pop()
    cut = planned >= first
    inconsistent = not result.consistent
    if cut:
        gone = f'step {planned} is' if first == planned else f'steps {first}-{planned} are'
        print(f'the run had {planned} steps; {gone} missing from the recording (a cut or '
              'repaired bag?)')
    if result.not_recorded or result.not_reestimated or absent:
        both = result.steps - len(result.not_recorded)
        parts = [f'{what} {step_ranges(steps)}' for what, steps in (
            ('missing from the recording:', absent),
            ('recorded but not re-estimated (their inputs are missing):',
             result.not_reestimated),
            ('re-estimated but missing from the recording:', result.not_recorded)) if steps]
        agree = result.compared_diff <= args.tolerance
        print(f'step counts differ: {result.steps} re-estimated, {result.recorded_steps} '
              f"recorded; steps {'; steps '.join(parts)} (a damaged, cut or repaired bag?). "
              f'The {both} steps both have '
              f"{'agree' if agree else 'differ'}: max difference {result.compared_diff:.3e} "
              f"{'<=' if agree else '>'} tolerance {args.tolerance:.1e}. FAILED: incomplete")
    else:
        verdict = 'FAILED' if not ok else 'FAILED: incomplete' if cut else \
            'reproduced, but the filter was inconsistent: FAILED' if inconsistent else 'OK'
        print(f"max difference {result.max_diff:.3e} {'<=' if ok else '>'} tolerance "
              f'{args.tolerance:.1e}: {verdict}')
    ok = ok and not cut and not inconsistent
    if args.json:
        write_json(args.json, {'bag': str(args.bag), **result.as_dict(),
                               'tolerance': args.tolerance, 'planned_steps': planned,
                               'ok': ok})
    return 0 if ok else 1


#: The flags of each mode: playback (ROS), a recorded formopt run offline, a bag of standard
#: types offline (--topic-map).
PLAYBACK_FLAGS = ('rate', 'fast', 'topics', 'wait_subscribers', 'clock')
RECORDED_FLAGS = ('follower', 'strategy', 'strategy_option', 'seed', 'trial', 'tolerance')
TOPIC_MAP_FLAGS = ('topic_map', 'skip', 'estimates')


def refuse_unused_flags(options: argparse.Namespace) -> None:
    """Stop (exit 2) on a flag the chosen mode would not read, naming it and its mode."""
    def given(names: tuple[str, ...]) -> list[str]:
        return ['--' + n.replace('_', '-') for n in names
                if getattr(options, n) not in (None, False, [])]

    if not options.offline:
        stray = given(RECORDED_FLAGS + TOPIC_MAP_FLAGS + ('json',))
        if stray:
            fail(PROG, f'{stray[0]} needs --offline (without it the bag is played back on ROS '
                       'topics)')
        return
    stray = given(PLAYBACK_FLAGS)
    if stray:
        fail(PROG, f'{stray[0]} applies to playback on ROS topics, not to --offline')
    stray = given(RECORDED_FLAGS) if options.topic_map else given(('skip', 'estimates'))
    if stray:
        fail(PROG, f'{stray[0]} applies to ' + (
            'a recorded formopt_ros run, not to --topic-map' if options.topic_map
            else '--topic-map (a bag of standard types) only'))


@command(PROG)
def main(args: list[str] | None = None) -> None:
    """Console entry point: ``replay BAG [--rate F | --fast] [--topics ...] [--offline]``."""
    argv = list(sys.argv[1:] if args is None else args)
    plain, ros = split_ros_args(argv)
    options = build_parser().parse_args(plain)
    refuse_unused_flags(options)
    if options.offline:
        if options.bag is None:
            fail(PROG, '--offline needs BAG')
        options.tolerance = TOLERANCE if options.tolerance is None else options.tolerance
        options.skip = SKIP if options.skip is None else options.skip
        sys.exit(foreign_main(options) if options.topic_map else offline_main(options))
    from formopt_ros.ros.nodes.replay import PARAMS, SUMMARY, Replay, select_topics
    from formopt_ros.ros.runtime import node_main
    preloaded = None
    extra: list[str] = []
    if options.bag is not None:
        try:
            preloaded = read_bag(options.bag)
            select_topics(preloaded, options.topics or ['*'])
        except BagError as error:
            fail(PROG, str(error))
        extra += ['-p', f'bag_path:={json.dumps(str(options.bag))}']
    if options.rate is not None:
        extra += ['-p', f'rate:={float(options.rate)!r}']
    if options.fast:
        extra += ['-p', 'fast:=true']
    if options.topics:
        extra += ['-p', f'topics:={json.dumps(options.topics)}']
    if options.wait_subscribers is not None:
        extra += ['-p', f'wait_subscribers:={options.wait_subscribers}']
    if options.clock:
        extra += ['-p', 'clock:=true']
    ros_args = (ros or ['--ros-args']) + extra if (ros or extra) else []
    made: list[Replay] = []

    def make() -> Replay:
        made.append(Replay(preloaded))
        return made[-1]
    code = node_main(make, PROG, SUMMARY, PARAMS, ros_args)
    if code == 0 and made and not made[-1].finished:       # Ctrl-C or SIGTERM mid-playback
        print(f'{PROG}: interrupted after {made[-1].sent} of {len(made[-1].queue)} messages',
              file=sys.stderr)
        code = INTERRUPTED_EXIT
    sys.exit(code)


if __name__ == '__main__':
    main()
