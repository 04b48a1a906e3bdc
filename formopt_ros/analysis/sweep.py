"""Sweeps at scale: the cells on Dask (a local cluster, or an existing one), a cache of finished
cells, the tidy table (CSV) and the heat maps."""
from __future__ import annotations

import contextlib
import csv
import functools
import hashlib
import json
import logging
import math
import os
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import CancelledError, Executor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from formopt_ros.core.strategies import STRATEGIES
from formopt_ros.core.strategies.registry import QUIET_ENV
from formopt_ros.core.study import POLL_S
from formopt_ros.core.sweep import (
    AXES, GAIN_COLUMNS, RESULT_COLUMNS, Cell, cell_key, point_label, run_cell, with_gains)

#: Columns of the table, in order.
COLUMNS = (*AXES, *RESULT_COLUMNS, *GAIN_COLUMNS)
#: Environment variable naming an existing Dask scheduler (Dask's own configuration key).
SCHEDULER_ENV = 'DASK_SCHEDULER_ADDRESS'


def package_version() -> str:
    """This package's installed version ('unknown' when it runs from a source tree)."""
    from importlib.metadata import PackageNotFoundError, version
    try:
        return version('formopt_ros')
    except PackageNotFoundError:
        return 'unknown'


@functools.cache
def core_digest() -> str:
    """A hash of the source of formopt_ros/core, where every number of a cell is computed:
    the version alone stays the same across changes of the algorithms."""
    digest = hashlib.sha256()
    core = Path(__file__).resolve().parents[1] / 'core'
    for path in sorted(core.rglob('*.py')):
        digest.update(path.relative_to(core).as_posix().encode() + b'\0' + path.read_bytes())
    return digest.hexdigest()[:16]


def versions_of(strategy: str) -> str:
    """The code versions a cell of ``strategy`` depends on: this package's (its version and
    :func:`core_digest`) and, for a plugin, its distribution's."""
    origin = STRATEGIES.origin(strategy)
    return f'formopt_ros {package_version()} core {core_digest()}' + \
        (f'; {origin}' if origin else '')


class CellCache:
    """Finished cells, one JSON file per cell key in a folder (written whole or not at all)."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)

    def path(self, key: str) -> Path:
        """The file of a cell."""
        return self.folder / f'{key}.json'

    def get(self, key: str) -> dict[str, Any] | None:
        """The cell's row, or None when it is not there (or unreadable)."""
        try:
            data = json.loads(self.path(key).read_text(encoding='utf-8'))
        except (OSError, ValueError):
            return None
        return data.get('row') if isinstance(data, dict) and data.get('key') == key else None

    def put(self, key: str, row: dict[str, Any]) -> None:
        """Store a finished cell (atomically: a reader sees the whole file or none)."""
        self.folder.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(prefix=f'.{key}.', dir=self.folder)
        with os.fdopen(handle, 'w', encoding='utf-8') as stream:
            json.dump({'key': key, 'row': row}, stream, sort_keys=True)
        os.replace(temporary, self.path(key))


@dataclass
class SweepOutcome:
    """What :func:`run_cells` did.

    Attributes:
        rows: the row of every finished cell, in the order of the cells (None: not finished).
        computed: keys of the cells computed now; reused: keys found in the cache.
        failures: key -> one line for each cell whose computation raised.
    """

    rows: list[dict[str, Any] | None]
    computed: list[str] = field(default_factory=list)
    reused: list[str] = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)


def scheduler_address(given: str | None) -> str | None:
    """The scheduler to use: ``given``, else Dask's configured one (``DASK_SCHEDULER_ADDRESS``),
    else None (a local cluster)."""
    if given:
        return given
    import dask
    configured = dask.config.get('scheduler-address', None)
    return str(configured) if configured else None


#: How long an existing scheduler may take to answer, and then to have a worker, s.
CONNECT_TIMEOUT = 30.0


def connect(address: str) -> Any:
    """A Dask client of the existing scheduler at ``address`` with at least one worker; a
    ConnectionError (an OSError) in one sentence when the address is malformed, nothing
    answers as a Dask scheduler within :data:`CONNECT_TIMEOUT` s (a connection to another
    kind of service can hang, so the attempt runs in a daemon thread left behind), or no
    worker joins within that time."""
    from urllib.parse import urlsplit

    from dask.distributed import Client
    try:
        urlsplit(address if '://' in address else f'tcp://{address}').port
    except ValueError as malformed:                 # e.g. a port above 65535
        raise ConnectionError(f'{address} is not a scheduler address: {malformed}') from None
    outcome: dict[str, Any] = {}

    def attempt() -> None:
        try:
            outcome['client'] = Client(address, timeout=f'{CONNECT_TIMEOUT:g}s')
        except Exception as error:                  # noqa: BLE001 (reported below)
            outcome['error'] = error

    thread = threading.Thread(target=attempt, daemon=True)
    thread.start()
    thread.join(CONNECT_TIMEOUT + 5.0)
    if thread.is_alive():
        raise ConnectionError(f'{address} did not answer as a Dask scheduler within '
                              f'{CONNECT_TIMEOUT:g} s')
    if 'error' in outcome:
        error = outcome['error']
        raise ConnectionError(f'no Dask scheduler at {address}: '
                              f'{str(error) or type(error).__name__}') from error
    client = outcome['client']
    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT)
    except Exception:                               # noqa: BLE001 (a timeout, of some kind)
        client.close()
        raise ConnectionError(f'the Dask scheduler at {address} has no worker after '
                              f'{CONNECT_TIMEOUT:g} s (start one: dask worker {address})'
                              ) from None
    return client


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A Dask client of the scheduler at ``scheduler`` (or Dask's configured one,
    :func:`connect`), else of a new local cluster of ``workers`` single-threaded processes
    (default: one per core), closed on exit."""
    from dask.distributed import Client, LocalCluster
    address = scheduler_address(scheduler)
    if address:
        # a lost scheduler is reported by the caller in one line: not by the client's own
        # reconnection tracebacks as well
        loggers = [logging.getLogger(name) for name in ('distributed', 'distributed.client')]
        levels = [logger.level for logger in loggers]
        for logger in loggers:
            logger.setLevel(logging.CRITICAL)
        try:
            with connect(address) as client:
                yield client
        finally:
            for logger, level in zip(loggers, levels):
                logger.setLevel(level)
        return
    # a random dashboard port (no clash with another cluster); the parent has reported any
    # broken plugin already: the workers stay quiet; they are born ignoring SIGINT, so that
    # Ctrl-C (sent to the whole process group) reaches only this process, which cancels the
    # cells and closes the cluster, and no worker prints a traceback
    with _ignoring_interrupts():
        cluster = LocalCluster(n_workers=workers or os.cpu_count() or 1, threads_per_worker=1,
                               processes=True, host='127.0.0.1', dashboard_address=':0',
                               silence_logs=logging.CRITICAL, env={QUIET_ENV: '0'})
    with cluster, Client(cluster) as client:
        yield client


@contextlib.contextmanager
def dask_executor(workers: int | None = None,
                  scheduler: str | None = None) -> Iterator[tuple[Executor, int]]:
    """(A :class:`concurrent.futures.Executor` on the Dask client of :func:`dask_client`, the
    number of worker threads it has), closed on exit; tasks are never deduplicated."""
    with dask_client(workers, scheduler) as client:
        threads = sum(int(worker['nthreads'])
                      for worker in client.scheduler_info()['workers'].values())
        yield client.get_executor(pure=False), max(1, threads)


@contextlib.contextmanager
def _ignoring_interrupts() -> Iterator[None]:
    """SIGINT ignored meanwhile (processes started then inherit it); in the main thread."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def run_cells(cells: Sequence[Cell], cache: CellCache, workers: int | None = None,
              scheduler: str | None = None,
              progress: Callable[[int], None] | None = None,
              finished: Callable[[str, dict[str, Any]], None] | None = None,
              stop: Callable[[], bool] | None = None) -> SweepOutcome:
    """Run every cell not in ``cache`` on Dask and store each in the cache as it finishes.

    Args:
        cells: the sweep's cells.
        cache: finished cells; a cell found there is not computed again.
        workers: processes of the local cluster (ignored with a scheduler).
        scheduler: address of an existing Dask scheduler (default: ``DASK_SCHEDULER_ADDRESS``,
            else a local cluster).
        progress: called with the number of cells newly available (reused ones first).
        finished: called with (key, row) after each computed cell is stored.
        stop: polled every POLL_S s while the cells run; True raises KeyboardInterrupt there
            (a Ctrl-C the caller recorded: :func:`~formopt_ros.cli.common.ctrl_c_deferred`).

    A KeyboardInterrupt (Ctrl-C) cancels the remaining cells and propagates; every cell
    finished before it is in the cache. A cell whose computation raises is reported in
    ``failures`` and the others go on. A cluster that drops the cells (its scheduler or every
    worker stopped) raises ConnectionError; the cells finished before are in the cache.
    """
    keys = [cell_key(cell, versions_of(cell.strategy)) for cell in cells]
    found: dict[str, dict[str, Any]] = {}
    for key in dict.fromkeys(keys):
        row = cache.get(key)
        if row is not None:
            found[key] = row
    outcome = SweepOutcome([], reused=list(found))
    if progress and found:
        progress(sum(1 for key in keys if key in found))
    todo = {key: cell for key, cell in zip(keys, cells) if key not in found}
    if todo:
        from dask.distributed import as_completed
        with dask_client(workers, scheduler) as client:
            futures = client.map(run_cell, list(todo.values()), key=list(todo), pure=False)
            try:
                completed = as_completed(futures)
                while not completed.is_empty():
                    if stop is not None and stop():
                        raise KeyboardInterrupt
                    if stop is not None and not completed.has_ready():
                        time.sleep(POLL_S)
                        continue
                    for future in completed.next_batch(block=True):
                        key = str(future.key)
                        try:
                            row = future.result()
                        except CancelledError as error:
                            raise ConnectionError('the Dask cluster dropped the sweep (its '
                                                  'scheduler or every worker stopped)'
                                                  ) from error
                        except Exception as error:      # the cell's strategy failed
                            outcome.failures[key] = ' '.join(
                                f'{type(error).__name__}: {error}'.split())
                            continue
                        cache.put(key, row)
                        found[key] = row
                        outcome.computed.append(key)
                        if finished:
                            finished(key, row)
                        if progress:
                            progress(sum(1 for k in keys if k == key))
            except BaseException:
                client.cancel(futures)
                raise
    outcome.rows = [found.get(key) for key in keys]
    return outcome


def table_rows(rows: Sequence[dict[str, Any] | None]) -> list[dict[str, Any]]:
    """The finished rows with the gains over RAM (:func:`~formopt_ros.core.sweep.with_gains`)."""
    return with_gains([row for row in rows if row is not None])


def _cell_text(value: Any) -> str:
    if value is None:
        return ''
    if isinstance(value, float):
        return repr(value)
    return str(value)


def write_table(rows: Sequence[dict[str, Any]], path: Path) -> None:
    """The tidy table: one line per (scenario, strategy), :data:`COLUMNS`; floats written
    exactly (``repr``), so equal results give equal files."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, 'w', newline='', encoding='utf-8') as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for row in rows:
            writer.writerow([_cell_text(row.get(column)) for column in COLUMNS])


def read_table(path: Path) -> list[dict[str, str]]:
    """The table of :func:`write_table` as text values per column."""
    with open(path, newline='', encoding='utf-8') as handle:
        return list(csv.DictReader(handle))


def swept_axes(rows: Sequence[dict[str, Any]]) -> list[str]:
    """The axes that take more than one value in these rows, in :data:`AXES` order."""
    return [axis for axis in AXES if len({row[axis] for row in rows}) > 1]


def _levels(rows: Sequence[dict[str, Any]], axis: str) -> list[Any]:
    values = list(dict.fromkeys(row[axis] for row in rows))
    return sorted(values) if all(isinstance(v, float) for v in values) else values


def gain_grid(rows: Sequence[dict[str, Any]], strategy: str, x_axis: str,
              y_axis: str) -> tuple[list[Any], list[Any], np.ndarray]:
    """(x values, y values, mean gain over RAM %, shape (len y, len x)) of one strategy: the
    mean over the other axes; nan where no row (or no RAM) is."""
    xs, ys = _levels(rows, x_axis), _levels(rows, y_axis)
    sums, counts = np.zeros((len(ys), len(xs))), np.zeros((len(ys), len(xs)))
    for row in rows:
        if row['strategy'] == strategy and row.get('gain_over_ram_pct') is not None:
            j, i = ys.index(row[y_axis]), xs.index(row[x_axis])
            sums[j, i] += row['gain_over_ram_pct']
            counts[j, i] += 1
    with np.errstate(invalid='ignore'):
        return xs, ys, np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def winners(rows: Sequence[dict[str, Any]], x_axis: str, y_axis: str
            ) -> tuple[list[Any], list[Any], list[list[str]]]:
    """(x values, y values, winner per (y, x)): the strategy that is best at the most points
    of that (x, y) over the other axes (``best_at_point``; a tie at a point counts for none,
    a tie of tallies goes to the first strategy in row order; where every point is a tie, the
    commonest tie, e.g. 'ram=rq'; '' when no strategy is consistent there)."""
    xs, ys = _levels(rows, x_axis), _levels(rows, y_axis)
    order = list(dict.fromkeys(row['strategy'] for row in rows))
    tallies: dict[tuple[int, int], dict[str, int]] = {}
    seen: set[tuple[str, int, int]] = set()
    for row in rows:
        j, i = ys.index(row[y_axis]), xs.index(row[x_axis])
        label = point_label(row)
        if (label, j, i) in seen:
            continue
        seen.add((label, j, i))
        if row['best_at_point']:
            tally = tallies.setdefault((j, i), {})
            tally[row['best_at_point']] = tally.get(row['best_at_point'], 0) + 1
    grid = [['' for _ in xs] for _ in ys]
    for (j, i), tally in tallies.items():
        outright = {name: count for name, count in tally.items() if name in order}
        grid[j][i] = max(order, key=lambda name: (outright.get(name, 0), -order.index(name))) \
            if outright else max(tally, key=lambda label: tally[label])     # ties only
    return xs, ys, grid


def sweep_figures(rows: Sequence[dict[str, Any]], x_axis: str, y_axis: str,
                  folder: Path) -> list[Path]:
    """Heat maps of each strategy's steady gain over RAM across (x_axis, y_axis) and a map of
    where each strategy wins, one pair per sensor when the sensor is not an axis of the maps;
    returns the files written."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap, TwoSlopeNorm
    folder.mkdir(parents=True, exist_ok=True)
    written = []
    facets = [None] if 'measurement' in (x_axis, y_axis) else \
        list(dict.fromkeys(row['measurement'] for row in rows))
    for facet in facets:
        part = [row for row in rows if facet is None or row['measurement'] == facet]
        suffix = f'_{facet}' if facet else ''
        others = [axis for axis in swept_axes(part) if axis not in (x_axis, y_axis)]
        note = f' (mean over {", ".join(others)})' if others else ''
        names = [n for n in dict.fromkeys(r['strategy'] for r in part) if n != 'ram']
        if any(r['strategy'] == 'ram' for r in part) and names:
            grids = [gain_grid(part, name, x_axis, y_axis) for name in names]
            limit = max([float(np.nanmax(np.abs(g[2]))) for g in grids
                         if np.isfinite(g[2]).any()] + [1.0])
            figure, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names) + 0.8, 3.8),
                                        squeeze=False, layout='constrained')
            for axis, name, (xs, ys, values) in zip(axes[0], names, grids):
                image = axis.imshow(values, origin='lower', cmap='RdBu', aspect='auto',
                                    norm=TwoSlopeNorm(0.0, -limit, limit))
                _ticks(axis, xs, ys, x_axis, y_axis)
                for (j, i), value in np.ndenumerate(values):
                    if math.isfinite(value):
                        axis.text(i, j, f'{value:+.1f}', ha='center', va='center', fontsize=8)
                axis.set_title(f'{name.upper()} vs RAM')
            figure.colorbar(image, ax=axes[0].tolist(), label='steady tr(W P W) gain over '
                            'RAM, % (> 0: lower)')
            figure.suptitle(f'{facet or "both sensors"}: gain over RAM{note}', fontsize=10)
            path = folder / f'gain_over_ram{suffix}.png'
            figure.savefig(path, dpi=110)
            plt.close(figure)
            written.append(path)
        xs, ys, grid = winners(part, x_axis, y_axis)
        order = list(dict.fromkeys(r['strategy'] for r in part))
        palette = plt.get_cmap('tab10')
        codes = np.array([[order.index(name) if name in order else -1 for name in line]
                          for line in grid], dtype=float)       # a tie: no colour
        codes[codes < 0] = np.nan
        figure, axis = plt.subplots(figsize=(5.2, 4.0), layout='constrained')
        axis.imshow(codes, origin='lower', aspect='auto', vmin=-0.5, vmax=9.5,
                    cmap=ListedColormap([palette(k) for k in range(10)]))
        _ticks(axis, xs, ys, x_axis, y_axis)
        for j, line in enumerate(grid):
            for i, name in enumerate(line):
                axis.text(i, j, name.upper() or '-', ha='center', va='center', fontsize=8)
        axis.set_title(f'{facet or "both sensors"}: lowest steady tr(W P W){note}',
                       fontsize=9)
        path = folder / f'winners{suffix}.png'
        figure.savefig(path, dpi=110)
        plt.close(figure)
        written.append(path)
    return written


def _ticks(axis: Any, xs: list[Any], ys: list[Any], x_axis: str, y_axis: str) -> None:
    axis.set_xticks(range(len(xs)), [f'{x:g}' if isinstance(x, float) else str(x) for x in xs])
    axis.set_yticks(range(len(ys)), [f'{y:g}' if isinstance(y, float) else str(y) for y in ys])
    axis.set_xlabel(x_axis)
    axis.set_ylabel(y_axis)


__all__ = ['COLUMNS', 'CellCache', 'SweepOutcome', 'connect', 'dask_client', 'dask_executor',
           'read_table', 'run_cells', 'sweep_figures', 'table_rows', 'write_table']
