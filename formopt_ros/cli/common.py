"""One convention for every command: one line 'prog: error: ...' naming the option and value,
exit code 2, never a traceback; argument types that check ranges and refuse to overwrite."""
from __future__ import annotations

import argparse
import contextlib
import functools
import math
import os
import signal
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn, TypeVar

from formopt_ros.core.checks import InvalidInput, as_integer, as_real
from formopt_ros.wire.outputs import broken_link_on

#: Exit codes of :func:`command`: an interrupted command and one whose reader closed the pipe
#: (128 + SIGINT or SIGPIPE, as a shell reports a process those signals end), and a failure
#: of the system (a file that cannot be written).
INTERRUPTED_EXIT, CLOSED_PIPE_EXIT, SYSTEM_EXIT = 130, 141, 1

Main = TypeVar('Main', bound=Callable[..., Any])


def command(prog: str) -> Callable[[Main], Main]:
    """Decorate a command's ``main``: Ctrl-C prints '<prog>: interrupted' and returns 130; an
    OSError (an output that cannot be written) prints one 'error:' line and returns 1; a closed
    stdout (``| head``) ends quietly with 141. Never a traceback."""
    def wrap(main: Main) -> Main:
        @functools.wraps(main)
        def run(*args: Any, **kwargs: Any) -> Any:
            try:
                return main(*args, **kwargs)
            except KeyboardInterrupt:
                print(f'{prog}: interrupted', file=sys.stderr)
                return INTERRUPTED_EXIT
            except BrokenPipeError:
                # the reader left: stop writing (Python would complain at exit otherwise)
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
                return CLOSED_PIPE_EXIT
            except OSError as error:
                where = f': {error.filename}' if error.filename else ''
                print(f'{prog}: error: {error.strerror or error}{where}', file=sys.stderr)
                return SYSTEM_EXIT
        return run  # type: ignore[return-value]
    return wrap


@contextlib.contextmanager
def ctrl_c_deferred() -> Iterator[Callable[[], bool]]:
    """Ctrl-C (SIGINT) inside the block only records itself: the block polls the callable it
    gets and raises KeyboardInterrupt at that safe point, and the block's end raises it if
    nothing did. Raised wherever the main thread happens to be, a KeyboardInterrupt can land
    inside a library's locking (a Dask client's, a Popen's) and hang the shutdown that
    follows. Outside the main thread nothing changes."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: False
        return
    received: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield lambda: bool(received)
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt


class ArgumentParser(argparse.ArgumentParser):
    """argparse with a one-line error message (no usage dump) and exit code 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``prog: error: message`` and exit 2."""
        self.exit(2, f'{self.prog}: error: {message} (see --help)\n')


def fail(prog: str, message: str) -> NoReturn:
    """Stop a command with one error line and exit code 2."""
    print(f'{prog}: error: {message}', file=sys.stderr)
    sys.exit(2)


def integer(low: int, high: int | None = None) -> Callable[[str], int]:
    """argparse type: an integer in [low, high] (:func:`~formopt_ros.core.checks.as_integer`)."""
    def parse(text: str) -> int:
        try:
            return as_integer('value', text, low, high)
        except InvalidInput as error:
            raise argparse.ArgumentTypeError(error.reason) from None
    return parse


def number(low: float, high: float = math.inf, low_open: bool = False) -> Callable[[str], float]:
    """argparse type: a finite number in [low, high] (or (low, high] with low_open)
    (:func:`~formopt_ros.core.checks.as_real`)."""
    def parse(text: str) -> float:
        try:
            return as_real('value', text, low, None if math.isinf(high) else high,
                           low_open=low_open)
        except InvalidInput as error:
            raise argparse.ArgumentTypeError(error.reason) from None
    return parse


def name_list(choices: Sequence[str], left_out: Mapping[str, str] | None = None
              ) -> Callable[[str], list[str]]:
    """argparse type: a comma list of names among ``choices``, each once, none empty (in the
    order given); ``left_out``: name -> why it is not among them (a broken plugin)."""
    def parse(text: str) -> list[str]:
        names = [name.strip() for name in text.split(',')]
        if not all(names):
            raise argparse.ArgumentTypeError(
                f'must be a comma list of names among {",".join(choices)}, got {text!r} (an '
                'empty name)')
        unknown = [name for name in names if name not in choices]
        broken = [name for name in unknown if name in (left_out or {})]
        if broken:
            raise argparse.ArgumentTypeError('; '.join(
                f'{name!r} is a plugin left out: {(left_out or {})[name]}' for name in broken))
        if unknown:
            raise argparse.ArgumentTypeError(
                f'unknown {", ".join(map(repr, unknown))}: the names are {",".join(choices)}')
        repeated = [name for index, name in enumerate(names) if name in names[:index]]
        if repeated:
            raise argparse.ArgumentTypeError(f'{", ".join(map(repr, repeated))} given twice in '
                                             f'{text!r}')
        return names
    return parse


def _refuse_empty(text: str) -> None:
    """An empty path names the current folder: refused."""
    if not text.strip():
        raise argparse.ArgumentTypeError('an empty path; name the output')


def new_file(text: str) -> Path:
    """argparse type: a file path that does not exist yet (not even as a dangling symbolic
    link, which writing would follow) and whose folder can be made."""
    _refuse_empty(text)
    path = Path(text)
    _refuse_dangling(path, text)
    if os.path.lexists(path):
        raise argparse.ArgumentTypeError(f'{text} exists; refusing to overwrite it')
    _check_parent(path, text)
    return path


def new_folder(text: str) -> Path:
    """argparse type: an output folder that does not exist yet, or exists and is empty."""
    _refuse_empty(text)
    path = Path(text)
    _refuse_dangling(path, text)
    if os.path.lexists(path) and (not path.is_dir() or any(path.iterdir())):
        raise argparse.ArgumentTypeError(f'{text} exists and is not an empty folder; refusing '
                                         'to overwrite what is in it (choose a new folder)')
    _check_parent(path, text)
    return path


def _refuse_dangling(path: Path, text: str) -> None:
    """Refuse a path that is, or lies below, a symbolic link to nothing or a loop of links."""
    problem = broken_link_on(path)
    if problem:
        raise argparse.ArgumentTypeError(f'cannot create {text}: {problem}')


def _check_parent(path: Path, text: str) -> None:
    """Refuse a path that cannot be created (or an empty folder that cannot be written): the
    nearest existing folder must let a new entry be made there (tried with a temporary folder,
    removed at once), so a long run never ends on an output it cannot write."""
    parent = path.resolve() if path.is_dir() else path.resolve().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise argparse.ArgumentTypeError(f'cannot create {text}: {parent} is not a folder')
    try:
        os.rmdir(tempfile.mkdtemp(prefix='.formopt-probe-', dir=parent))
    except OSError as error:
        raise argparse.ArgumentTypeError(
            f'cannot create {text}: nothing can be created in {parent} '
            f'({error.strerror})') from None


def bag_file(text: str) -> Path:
    """argparse type: an .mcap file, or the folder ``ros2 bag record`` writes (its one .mcap
    file, or the folder itself for a split recording, read as one bag)."""
    from formopt_ros.bag import BagError
    from formopt_ros.bag.reader import bag_files
    path = Path(text)
    if not path.is_dir():
        return existing_file(text)
    try:
        files = bag_files(path)
    except BagError as error:
        raise argparse.ArgumentTypeError(str(error)) from None
    return files[0] if len(files) == 1 else path


def existing_file(text: str) -> Path:
    """argparse type: a file that exists."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f'{text}: is a directory; expected a file')
    if not path.is_file():
        raise argparse.ArgumentTypeError(f'{text}: no such file')
    return path
