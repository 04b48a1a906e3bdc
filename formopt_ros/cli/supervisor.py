"""The processes of a run: start nodes through scripts/<node>.sh, restart or stop them, and never
leave one behind (every started process group is ended when the run ends, however it ends; if
run_formation itself is killed, the kernel ends its nodes: :func:`die_with_parent`)."""
from __future__ import annotations

import ctypes
import faulthandler
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from formopt_ros.wire.topics import GLOBAL_TOPICS

PROG = 'run_formation.sh'
SCRIPTS = Path(__file__).resolve().parents[2] / 'scripts'
#: How long (s) an estimator may outlive a peer it needs before the run fails.
ORPHAN_GRACE = 5.0
#: How a stop ends processes: each signal, then how long (s) it waits for them to exit.
STOP_WAITS = ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0))
#: Exit code of a node refusing its configuration (not respawned: it would refuse again).
CONFIGURATION_EXIT = 2
#: prctl option that asks the kernel to signal a process when its parent dies (Linux).
PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Run in a started node before it executes (``preexec_fn``): when the process that
    started it dies, even by SIGKILL, the node receives SIGTERM (Linux; it survives the exec
    of scripts/<node>.sh into the node, which ends its run and writes its summary). A parent
    already gone gets the same answer at once. Elsewhere: nothing."""
    parent = os.getppid()
    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))
    except (AttributeError, OSError):          # no prctl: not Linux
        return
    if os.getppid() != parent:
        os.kill(os.getpid(), signal.SIGTERM)


#: Names of the signals that stopped the run (set by :func:`stop_on_signals`'s handler).
RECEIVED_SIGNALS: list[str] = []
#: Seconds after the first signal (two stops of at most 20 s, then the summary) at which a stop
#: still running prints every thread's stack to stderr: a stop that hangs shows where.
STOP_REPORT_AFTER = 45.0
#: True while a loop polls the processes (:func:`supervising`).
_polling = False


def stop_on_signals() -> None:
    """SIGINT, SIGTERM and SIGHUP stop the run like Ctrl-C, once: the first is recorded in
    RECEIVED_SIGNALS, later ones are ignored (the stop that follows, bounded by its grace
    periods, must not be cut short, or nothing would write the summary). Outside
    :func:`supervising` the handler raises KeyboardInterrupt; inside, the polling loop ends
    the run at its next poll. A stop still running STOP_REPORT_AFTER s later prints every
    thread's stack to stderr."""
    def interrupt(signum: int, frame: Any) -> None:
        RECEIVED_SIGNALS.append(signal.Signals(signum).name)
        for other in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
            signal.signal(other, signal.SIG_IGN)
        faulthandler.dump_traceback_later(STOP_REPORT_AFTER)
        if not _polling:
            raise KeyboardInterrupt

    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, interrupt)


@contextmanager
def supervising() -> Iterator[None]:
    """A block that polls processes: a signal only records itself there (the block checks
    :func:`interrupted_by`), because a KeyboardInterrupt raised inside Popen.poll() between
    its lock's acquire and its try would leave the lock held, and every later wait() of that
    process would block forever."""
    global _polling
    _polling = True
    try:
        yield
    finally:
        _polling = False


def interrupted_by() -> str:
    """'interrupted by SIGHUP' once a signal came, else ''."""
    return interrupted() if RECEIVED_SIGNALS else ''


def interrupted() -> str:
    """'interrupted by SIGHUP' (the first signal received), or 'interrupted'."""
    return f'interrupted by {RECEIVED_SIGNALS[0]}' if RECEIVED_SIGNALS else 'interrupted'


@dataclass
class Process:
    """One node process: its command, log file and (after the run) exit code and summary."""

    name: str
    process: subprocess.Popen[bytes]
    log: Path
    args: list[str]
    summary_path: Path | None = None
    code: int | None = None
    restarts: list[int] = field(default_factory=list)    # exit codes of the restarted runs
    ended_at: float | None = None        # time.monotonic() when seen exited 0, its part done
    killed: bool = False                 # the stop had to SIGKILL it (Launcher.stop)

    @property
    def ended(self) -> bool:
        """Exited 0 having done its part (seen by :func:`supervise`)."""
        return self.ended_at is not None

    def stopped_by(self) -> str:
        """The signal that stopped the node before it had done its part (its summary says
        ``stopped_by`` and not ok: a ``kill`` from outside the run), else ''."""
        summary = self.summary()
        if summary is None or summary.get('ok', True) or 'stopped_by' not in summary:
            return ''
        return str(summary['stopped_by'])

    def exit_text(self) -> str:
        """'was stopped by SIGTERM' (:meth:`stopped_by`) or 'exited with code N'."""
        code = self.process.poll()
        signal_name = self.stopped_by() if code == 0 else ''
        return f'was stopped by {signal_name}' if signal_name else f'exited with code {code}'

    def restart(self) -> None:
        """Start the process again (same arguments; the log continues)."""
        self.restarts.append(self.process.wait())
        with open(self.log, 'ab') as stream:
            stream.write(f'--- {PROG}: restarted after exit code {self.restarts[-1]} ---\n'
                         .encode())
            stream.flush()
            self.process = subprocess.Popen(self.args, stdout=stream, stderr=subprocess.STDOUT,
                                            start_new_session=True, preexec_fn=die_with_parent)

    def alive(self) -> bool:
        """True while the process runs."""
        return self.process.poll() is None

    def summary(self) -> dict[str, Any] | None:
        """The node's JSON summary (None when it wrote none)."""
        if self.summary_path is None or not self.summary_path.is_file():
            return None
        return dict(json.loads(self.summary_path.read_text()))

    def tail(self, lines: int = 5) -> str:
        """The last lines of its log."""
        text = self.log.read_text(errors='replace').splitlines() if self.log.exists() else []
        return '\n'.join(text[-lines:])


@dataclass
class Launcher:
    """Starts node processes through scripts/<node>.sh with a namespace and -p parameters."""

    out: Path
    checkpoints: bool = False
    remaps: list[str] = field(default_factory=list)   # FROM:=TO for every node
    processes: list[Process] = field(default_factory=list)

    def start(self, name: str, node: str, namespace: str, params: dict[str, Any],
              summary: bool = True, remaps: list[str] | None = None) -> Process:
        """Start ``node`` as process ``name`` (log OUT/<name>.log, summary OUT/<name>.json),
        with the common remaps and ``remaps`` (FROM:=TO)."""
        summary_path = self.out / f'{name}.json' if summary else None
        if summary_path is not None:
            params = {**params, 'summary_path': str(summary_path)}
        if summary_path is not None and self.checkpoints:
            params['checkpoint_path'] = str(self.out / 'checkpoints' / f'{name}.pkl')
        args = [str(SCRIPTS / f'{node}.sh'), '-r', f'__ns:={namespace or "/"}']
        for remap in self.remaps + (remaps or []):
            args += ['-r', remap]
        for key, value in params.items():
            args += ['-p', f'{key}:={format_value(value)}']
        log = self.out / f'{name}.log'
        with open(log, 'wb') as stream:
            process = subprocess.Popen(args, stdout=stream, stderr=subprocess.STDOUT,
                                       start_new_session=True, preexec_fn=die_with_parent)
        self.processes.append(Process(name, process, log, args, summary_path))
        return self.processes[-1]

    def __enter__(self) -> 'Launcher':
        return self

    def __exit__(self, *exc: object) -> None:
        """However the run ends (an error while starting, a signal), no process outlives it."""
        self.stop([p for p in self.processes if p.alive()])

    def stop(self, processes: list[Process]) -> None:
        """SIGINT the process groups, SIGTERM 10 s later, SIGKILL 5 s after that
        (:data:`STOP_WAITS`; each signal with a SIGCONT, so that a stopped process handles it
        at once)."""
        for sig, wait in STOP_WAITS:
            running = [p for p in processes if p.alive()]
            if not running:
                break
            for item in running:
                item.killed = sig == signal.SIGKILL
                try:
                    os.killpg(item.process.pid, sig)
                    os.killpg(item.process.pid, signal.SIGCONT)   # a frozen (stopped) node too
                except ProcessLookupError:
                    pass
            deadline = time.monotonic() + wait
            while any(p.alive() for p in running) and time.monotonic() < deadline:
                time.sleep(0.05)
        for item in processes:
            item.code = item.process.wait()


def exit_failure(processes: list[Process]) -> tuple[str, list[str]]:
    """The failure of the first process that exited with a code other than 0 ('' if none), and
    the names of those the stop killed after their part was done (their summary is ok: nothing
    was lost; the run does not fail for them, it names them and warns on stderr)."""
    late = [p for p in processes if p.killed and (p.summary() or {}).get('ok')]
    for item in late:
        print(f"{PROG}: warning: {item.name} did its part but outlived the stop's SIGINT and "
              f'SIGTERM and was killed (its log shows where it hung: {item.log})',
              file=sys.stderr)
    bad = [p for p in processes if p.code not in (0, None) and p not in late]
    return (f'{bad[0].name} exited with code {bad[0].code}' if bad else ''), \
        [p.name for p in late]


def format_value(value: Any) -> str:
    """A -p value as rcl reads it (YAML): lists as flow sequences, bools lower case, strings
    single-quoted (a '#' or ': ' in a path would otherwise start a comment or a mapping)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(format_value(v) for v in value) + ']'
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return str(value)


def supervise(estimators: list[Process], others: list[Process], recorder: Process | None,
              respawn: int) -> str:
    """Restart dead nodes while ``respawn`` allows; the failure when one cannot go on ('' if
    none). A node that exited 0 has finished (an estimator its steps, a simulator once its
    estimators finished and left: ros/guard.py), unless its summary says a signal stopped it
    first (a ``kill`` from outside the run); any other exit before the end is a failure
    unless the node can be restarted (not after exit code 2, a refused configuration, and
    never the recorder, whose file would be cut)."""
    for item in estimators + others + ([recorder] if recorder else []):
        code = item.process.poll()
        if code is None or item.ended:
            continue
        if code == 0 and item is not recorder and not item.stopped_by():
            item.ended_at = time.monotonic()
            continue
        how = item.exit_text()
        if item is not recorder and code != CONFIGURATION_EXIT and \
                len(item.restarts) < respawn:
            print(f'{PROG}: {item.name} {how}; restarting it '
                  f'({len(item.restarts) + 1}/{respawn})', file=sys.stderr)
            item.restart()
            continue
        return f'{item.name} {how} before the run finished:\n{item.tail()}'
    return ''


def orphaned(chains: list[tuple[Process, list[Process]]], grace: float = ORPHAN_GRACE) -> str:
    """The failure of an estimator still running ``grace`` s after a peer it needs ended
    (``chains``: each estimator with its leader_sim and follower_sim), else ''. A simulator
    ends only once its estimators have left (ros/guard.py), so this is an estimator restarted
    after its run was over: no peer will ever send it a step."""
    now = time.monotonic()
    for estimator, peers in chains:
        for peer in peers:
            if estimator.alive() and peer.ended_at is not None and now - peer.ended_at > grace:
                return (f'{estimator.name} still ran {grace:g} s after {peer.name} ended: its '
                        'peers are gone, nothing is left to estimate')
    return ''


def global_remaps(prefix: str) -> list[str]:
    """-r rules that move the global topics (/tf, /tf_static, /clock, /diagnostics) under
    ``prefix``, so that two runs in one domain do not mix their transforms and clocks."""
    return [f'{t.name}:={prefix}{t.name}' for t in GLOBAL_TOPICS] if prefix else []


__all__ = ['CONFIGURATION_EXIT', 'RECEIVED_SIGNALS', 'Launcher', 'Process', 'exit_failure',
           'format_value', 'global_remaps', 'interrupted', 'interrupted_by', 'orphaned',
           'stop_on_signals', 'supervise', 'supervising']
