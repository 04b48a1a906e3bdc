"""How every node process runs: arguments, help, the spin loop, signals and exit codes."""
from __future__ import annotations

import difflib
import faulthandler
import functools
import math
import os
import re
import signal
import sys
import textwrap
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.signals import SignalHandlerOptions

from formopt_ros.core.solver import OutsideTheDisc
from formopt_ros.ros.params import ROS_PARAMETERS, Param, ParameterError, parse_value
from formopt_ros.wire.jsonfile import write_json
from formopt_ros.wire.outputs import broken_link_on


class Throttle:
    """Log a warning at most once per ``period`` seconds per key."""

    def __init__(self, node: Node, period: float = 2.0) -> None:
        self.node, self.period = node, period
        self.last: dict[str, float] = {}

    def warn(self, key: str, text: str) -> None:
        """Log ``text`` unless a warning with this key was logged less than period s ago."""
        now = time.monotonic()
        if now - self.last.get(key, -math.inf) >= self.period:
            self.last[key] = now
            self.node.get_logger().warning(text)


#: How long a node that ends waits for its subscribers to acknowledge its last messages, s.
DELIVERY_TIMEOUT = 5.0
#: After this long (s) in its shutdown, a node prints every thread's stack to its log (a node
#: that hangs while it ends shows where; run_formation kills it 15 s after its stop).
SHUTDOWN_REPORT_AFTER = 12.0


def fast_announcements() -> None:
    """Point FASTRTPS_DEFAULT_PROFILES_FILE at config/fastdds_discovery.xml (participants
    announce every 0.25 s) unless it is set; for processes not started by scripts/*.sh."""
    if os.environ.get('FASTRTPS_DEFAULT_PROFILES_FILE'):
        return
    for folder in (Path(__file__).resolve().parents[2] / 'config',
                   Path(sys.prefix) / 'share' / 'formopt_ros' / 'config'):
        if (folder / 'fastdds_discovery.xml').is_file():
            os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(folder / 'fastdds_discovery.xml')
            return


def make_executor() -> Any:
    """rclpy's EventsExecutor (about twice the throughput of the wait-set executor in lockstep
    runs), or the SingleThreadedExecutor where it is missing or FORMOPT_EXECUTOR=single."""
    if os.environ.get('FORMOPT_EXECUTOR', 'events') != 'single':
        try:
            from rclpy.experimental import EventsExecutor
            return EventsExecutor()
        except ImportError:
            pass
    return SingleThreadedExecutor()


def deliver(node: Node, timeout: float = DELIVERY_TIMEOUT) -> bool:
    """Wait until every subscriber acknowledged the node's reliable publications (so a node
    that ends does not take its last messages with it); False when one did not in time."""
    from rclpy.duration import Duration
    from rclpy.qos import ReliabilityPolicy
    deadline = time.monotonic() + timeout
    acked = True
    for publisher in list(node.publishers):
        if publisher.qos_profile.reliability != ReliabilityPolicy.RELIABLE:
            continue
        remaining = max(deadline - time.monotonic(), 0.0)
        acked = publisher.wait_for_all_acked(Duration(seconds=remaining)) and acked
    return acked


def stop_run(node: Node, code: int, message: str) -> None:
    """End the node's run with exit code ``code``: the error is logged, kept for the summary
    (``node.error``) and printed by :func:`node_main` as one line."""
    node.get_logger().error(message)
    node.exit_code = code                   # type: ignore[attr-defined]
    node.error = message                    # type: ignore[attr-defined]
    node.finished = True                    # type: ignore[attr-defined]


def stops_on_a_plan_outside_the_disc(method: Callable[..., None]) -> Callable[..., None]:
    """Decorate a node method that plans: a strategy (a plugin) that plans outside its disc
    stops the run in one line (:func:`stop_run`, exit code 1) instead of a callback
    traceback."""
    @functools.wraps(method)
    def run(node: Node, *args: Any, **kwargs: Any) -> None:
        try:
            method(node, *args, **kwargs)
        except OutsideTheDisc as error:
            stop_run(node, 1, f'{error}; the waypoint is not sent')
    return run


def steady_timer(node: Node, period: float, callback: Callable[[], None]) -> Any:
    """A timer on the steady clock: it runs while simulated time (use_sim_time) stands still."""
    from rclpy.clock import Clock, ClockType
    return node.create_timer(period, callback, clock=Clock(clock_type=ClockType.STEADY_TIME))


def check_output_path(name: str, path: str, may_exist: bool = True) -> None:
    """Refuse (ParameterError naming parameter ``name``) an output file path whose folder
    cannot be created or written, that is a folder, or (unless ``may_exist``) that exists;
    '' (no output) passes. Called at start, so a bad path never costs a run."""
    if not path:
        return
    target = Path(path)
    problem = broken_link_on(target)
    if problem:
        raise ParameterError(f"parameter '{name}': cannot write {path}: {problem}")
    if target.exists() and not may_exist and not target.is_dir():
        raise ParameterError(f"parameter '{name}': {path} exists; refusing to overwrite it "
                             '(remove it or choose another path)')
    if target.is_dir():
        raise ParameterError(f"parameter '{name}': {path} is a folder; expected a file path")
    folder = target.resolve().parent
    existing = folder
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
        raise ParameterError(f"parameter '{name}': cannot write {path} ({existing} is not a "
                             'writable folder)')
    if target.exists() and not os.access(target, os.W_OK):
        raise ParameterError(f"parameter '{name}': {path} is not writable")


#: The signals that stopped this node process (set by :func:`node_main`'s handler).
STOP_SIGNALS: list[int] = []


def write_summary(path: str, summary: dict[str, Any]) -> None:
    """Write a node's JSON summary (strict JSON: NaN and inf become null; folders created,
    written atomically), with ``stopped_by`` naming the signal that ended the process early
    (SIGINT, or SIGTERM: also the kernel's when the process that started the node died);
    nothing for an empty path."""
    if path:
        if STOP_SIGNALS:
            summary = {**summary, 'stopped_by': signal.Signals(STOP_SIGNALS[0]).name}
        write_json(path, summary)


def help_text(program: str, summary: str, specs: Sequence[Param]) -> str:
    """``--help`` of a node: usage and every parameter with default, range and meaning."""
    lines = [f'usage: {program} [--ros-args -p NAME:=VALUE ... --params-file FILE '
             '-r __ns:=/NAMESPACE]', '', summary, '', 'parameters:']
    for spec in specs:
        default = repr(spec.default)
        extra = ' (read-only)' if spec.read_only else ' (settable at run time)'
        lines.append(f'  {spec.name} = {default}{extra}')
        lines.extend(textwrap.wrap(spec.expected(), 95, initial_indent='      ',
                                   subsequent_indent='      '))
    lines += ['', 'A wrong value stops the node with exit code 2 and one line naming the '
              'parameter.']
    return '\n'.join(lines)


def unknown_parameters(argv: Sequence[str], specs: Sequence[Param]) -> list[str]:
    """Names set with ``-p NAME:=VALUE`` (inside --ros-args, node-local or not) that the node
    does not declare: refused, since a typo would otherwise leave a default in force silently.
    A parameters file may carry other nodes' parameters (``/**``): those are only warned about
    (see :func:`~formopt_ros.ros.params.declare`)."""
    known = {spec.name for spec in specs} | ROS_PARAMETERS
    names = [arg.split(':=', 1)[0].rpartition(':')[2]          # 'node:name' -> 'name'
             for arg in ros_arguments(argv, ('-p', '--param')) if ':=' in arg]
    return [name for name in names if name not in known]


def float_lists(argv: Sequence[str], specs: Sequence[Param]) -> list[str]:
    """``argv`` with every ``-p NAME:=[...]`` of a parameter whose default is a list of floats
    written as floats: rcl refuses a list that mixes integers and floats
    (``sensor_mount:=[0.2, 0, 0, 0, 0, 0]``) and types one of integers an integer array."""
    floats = {spec.name for spec in specs if isinstance(spec.default, list) and
              any(isinstance(value, float) for value in spec.default)}
    out = list(argv)
    for index in ros_argument_positions(argv, ('-p', '--param')):
        key, assigned, text = argv[index].partition(':=')
        if not assigned or key.rpartition(':')[2] not in floats:
            continue
        try:
            values = parse_value(key, text)
        except ParameterError:
            continue                               # rcl says what is wrong with it
        if isinstance(values, list) and all(type(value) in (int, float) for value in values):
            out[index] = f"{key}:=[{', '.join(repr(float(v)) for v in values)}]"
    return out


def ros_argument_positions(argv: Sequence[str], flags: tuple[str, ...]) -> list[int]:
    """The indices in ``argv`` of the values following any of ``flags`` inside --ros-args
    sections."""
    positions, inside, previous = [], False, ''
    for index, arg in enumerate(argv):
        if arg == '--ros-args':
            inside = True
        elif arg == '--':
            inside = False
        elif inside and previous in flags:
            positions.append(index)
        previous = arg
    return positions


def ros_arguments(argv: Sequence[str], flags: tuple[str, ...]) -> list[str]:
    """The values following any of ``flags`` inside --ros-args sections of ``argv``."""
    return [argv[index] for index in ros_argument_positions(argv, flags)]


def section_applies(key: str, node: str) -> bool:
    """Whether a params file's section ``key`` applies to the node with fully qualified name
    ``node`` (e.g. ``/f1/follower_estimator``), by rcl's rule (checked against rclpy): a key
    without a leading ``/`` is in the root namespace, ``*`` is one name and ``/**`` any number
    of namespaces."""
    pattern = ''.join('(/[^/]+)*' if part == '**' else '/[^/]+' if part == '*' else
                      '/' + re.escape(part) for part in key.strip('/').split('/'))
    return re.fullmatch(pattern, node) is not None


def node_path(argv: Sequence[str], program: str) -> str:
    """The node's fully qualified name, e.g. ``/f1/follower_estimator``: ``/program`` unless
    ``-r __ns:=`` or ``-r __node:=`` remap it (the first of each, as rcl)."""
    found: dict[str, str] = {}
    for rule in ros_arguments(argv, ('-r', '--remap')):
        target, _, value = rule.partition(':=')
        found.setdefault(target.rpartition(':')[2], value)     # rcl takes the first rule
    namespace = found.get('__ns', '').strip('/')
    return f"{'/' + namespace if namespace else ''}/{found.get('__node', program)}"


def foreign_params_files(argv: Sequence[str], program: str) -> list[tuple[str, list[str]]]:
    """The --params-file files (path, their node sections) with no section that applies to
    this node (:func:`section_applies`). Files rcl cannot read are left to rcl's own
    error."""
    import yaml
    node = node_path(argv, program)
    out = []
    for path in ros_arguments(argv, ('--params-file',)):
        try:
            sections = [str(key) for key in yaml.safe_load(Path(path).read_text()) or {}]
        except (OSError, yaml.YAMLError, TypeError):
            continue
        if not any(section_applies(key, node) for key in sections):
            out.append((path, sections))
    return out


def params_file_problem(path: str, sections: Sequence[str], argv: Sequence[str],
                        program: str) -> str | None:
    """The error for a params file none of whose sections applies to this node, when a
    section was meant for it: one keyed by its name in another namespace, or a near miss of
    its name (a typo); None when the file is for other nodes only."""
    node = node_path(argv, program)
    name = node.rpartition('/')[2]
    for key in sections:
        if key.rstrip('/').rpartition('/')[2] in (name, program):
            return (f'params file {path}: section {key!r} does not apply to node {node} (a '
                    "key without a leading '/' is the root namespace's; '/**/"
                    f"{name}' applies in any namespace, and a renamed node takes only its new "
                    'name): its values would not apply')
    names = [key.rstrip('/').rpartition('/')[2] for key in sections]
    close = difflib.get_close_matches(name, names, n=1, cutoff=0.8)
    if close:
        return (f'params file {path}: section {close[0]!r} is not this node {name!r} (a '
                'typo? its values would not apply)')
    return None


def node_main(factory: Callable[[], Node], program: str, summary: str,
              specs: Sequence[Param], args: list[str] | None = None) -> int:
    """Run one node process; returns the exit code.

    ``-h``/``--help`` (anywhere, also after ``--ros-args``) prints the parameters and exits 0;
    any other argument outside ``--ros-args``, a ``-p`` parameter the node does not have and a
    ParameterError are refused with exit code 2 and one line naming the argument. SIGINT and
    SIGTERM end the spin loop (within 0.1 s) while the context is still valid, so ``close()``
    can still publish and write; then the context shuts down.
    """
    from rclpy.utilities import remove_ros_args
    argv = list(sys.argv if args is None else [program, *args])
    if any(a in ('-h', '--help') for a in argv[1:]):     # also after --ros-args (the scripts)
        print(help_text(program, summary, specs))
        return 0
    argv = float_lists(argv, specs)
    try:
        plain = remove_ros_args(argv)[1:]
    except Exception as error:              # malformed --ros-args section
        print(f'{program}: error: bad ROS arguments: {error}', file=sys.stderr)
        return 2
    if plain:
        print(f'{program}: error: unknown argument {plain[0]!r} (node parameters go after '
              '--ros-args as -p NAME:=VALUE; see --help)', file=sys.stderr)
        return 2
    unknown = unknown_parameters(argv, specs)
    if unknown:
        close = difflib.get_close_matches(unknown[0], [spec.name for spec in specs], n=1,
                                          cutoff=0.8)
        hint = f"; did you mean '{close[0]}'?" if close else ''
        print(f'{program}: error: unknown parameter {unknown[0]!r} for {program}{hint} (see '
              '--help for its parameters)', file=sys.stderr)
        return 2
    for path, sections in foreign_params_files(argv, program):
        problem = params_file_problem(path, sections, argv, program)
        if problem:
            print(f'{program}: error: {problem}', file=sys.stderr)
            return 2
        print(f'{program}: warning: params file {path} has no section for {program} (it has '
              f"{', '.join(sections) or 'none'}): none of its values apply", file=sys.stderr)
    fast_announcements()
    try:
        rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    except Exception as error:              # e.g. a --params-file that does not exist or parse
        print(f'{program}: error: {str(error).splitlines()[0] if str(error) else error!r}',
              file=sys.stderr)
        return 2
    stop = STOP_SIGNALS
    stop.clear()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, lambda received, _frame: stop.append(received))
    node = None
    code = 0
    try:
        node = factory()
        executor = make_executor()
        executor.add_node(node)
        while rclpy.ok() and not stop and not getattr(node, 'finished', False):
            executor.spin_once(timeout_sec=0.1)
        faulthandler.dump_traceback_later(SHUTDOWN_REPORT_AFTER)
        code = int(getattr(node, 'exit_code', 0))
        if getattr(node, 'error', ''):
            print(f'{program}: error: {node.error}', file=sys.stderr)  # type: ignore[attr-defined]
        if rclpy.ok():
            deliver(node)
    except ParameterError as error:
        print(f'{program}: error: {error}', file=sys.stderr)
        code = 2
    except (KeyboardInterrupt, ExternalShutdownException):
        code = 0
    finally:
        if node is not None:
            try:
                node.close()            # type: ignore[attr-defined]
            except Exception as error:  # never turn a clean stop into a traceback
                print(f'{program}: warning: shutdown: {error}', file=sys.stderr)
                code = code or 1
            node.destroy_node()
        rclpy.try_shutdown()
    sys.stdout.flush()
    # the node is done: a SIGINT or SIGTERM now (a supervisor ending the run as this node
    # ends by itself) must not kill the interpreter's exit, which restores the default
    # handlers of the signals it handles (exit code -2 instead of the node's own)
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)
    return code
