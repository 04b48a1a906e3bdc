"""formopt-sweep: cells equal the study, Dask with 1 or 2 workers (or a separate cluster) gives
the same numbers, an interrupted sweep resumes without recomputing a finished cell."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytest.importorskip('dask.distributed')

from formopt_ros.analysis.sweep import (  # noqa: E402
    CellCache, dask_executor, read_table, run_cells, table_rows, winners, write_table)
from formopt_ros.cli import sweep as cli  # noqa: E402
from formopt_ros.core.scenario import LeaderPath  # noqa: E402
from formopt_ros.core.study import (  # noqa: E402
    StudyConfig, run_studies, run_study, summarize)
from formopt_ros.core.sweep import (  # noqa: E402
    TIMING_COLUMNS, Cell, expand, run_cell, with_gains)

STRATEGIES = ('ram', 'crm', 'mtf')
GRID = {'r_fraction': [0.05, 0.2], 'sigma_scale': [0.5, 1.0]}


def tiny_cells(trials: int = 3, steps: int = 40) -> list[Cell]:
    return [Cell.make(point, name, {}, trials, steps, 7) for point in expand(GRID)
            for name in STRATEGIES]


def results(rows: list[dict[str, Any] | None]) -> list[dict[str, Any]]:
    """The rows without their wall-clock columns."""
    assert all(row is not None for row in rows)
    return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS} for row in rows]


def test_a_cell_is_the_study_of_its_scenario() -> None:
    """A cell's figures are those of formopt-montecarlo's study with every strategy together,
    a speed limit and a safety distance included."""
    point = {'measurement': 'bearing', 'r_fraction': 0.15, 'sigma_scale': 2.0,
             'odometry_scale': 0.5, 'leader_path': 'arc', 'leader_speed': 0.8, 'dt': 0.04,
             'max_speed': 2.5, 'safety_distance': 2.0}
    cells = [Cell.make(point, name, {}, 4, 50, 3) for name in ('ram', 'crm')]
    scenario = {'r': 0.15 * 5 ** 0.5, 'sigma': 0.04, 'sigma_v': 0.1, 'sigma_omega': 0.05,
                'leader': LeaderPath('arc', 0.8, 0.5), 'dt': 0.04, 'max_speed': 2.5,
                'safety_distance': 2.0}
    together = summarize(run_study(StudyConfig('bearing', 4, 50, 3, ('ram', 'crm'),
                                               scenario=scenario), jobs=1))
    assert together['scenario'] == cells[0].config().make_scenario().to_dict()
    for cell in cells:
        row = run_cell(cell)
        study = together['strategies'][cell.strategy]
        for column in ('steady_trace', 'mean_trace', 'nees_mean', 'nees_in_band',
                       'steady_trace_std', 'gated_updates'):
            assert row[column] == study[column], column
        assert row['consistent'] == (cell.strategy not in together['consistency']['flagged'])
        assert (row['nees_band_low'], row['nees_band_high']) == tuple(together['nees_band'])


@pytest.mark.slow
def test_the_study_on_dask_equals_the_study_in_one_process() -> None:
    """formopt-montecarlo's engine: both kinds' tasks on a two-worker local Dask cluster give
    the numbers of one process, bit for bit, and each kind's result is handed to ``finish`` in
    this process."""
    configs = [StudyConfig(kind, 3, 30, 9, ('ram', 'rq', 'periodic'))
               for kind in ('range', 'bearing')]
    alone = run_studies(configs, jobs=1)
    finished: list[str] = []
    with dask_executor(workers=2) as (executor, workers):
        assert workers == 2
        spread = run_studies(configs, workers, finish=lambda r: finished.append(
            r.config.measurement), executor=executor)
    assert sorted(finished) == ['bearing', 'range']
    for one, two in zip(alone, spread):
        for name, record in one.records.items():
            for column in ('weighted_trace', 'nees', 'max_nis', 'gated', 'speed'):
                np.testing.assert_array_equal(getattr(record, column),
                                              getattr(two.records[name], column), column)


def test_gains_and_winners_follow_the_rows() -> None:
    base = {'measurement': 'range', 'r_fraction': 0.1, 'sigma_scale': 1.0,
            'odometry_scale': 1.0, 'leader_path': 'straight', 'leader_speed': 1.0,
            'leader_yaw_rate': 0.5, 'leader_period': 10.0, 'dt': 0.05, 'kinematics': 'euler',
            'max_speed': 0.0, 'safety_distance': 0.0}
    rows = [{**base, 'strategy': 'ram', 'steady_trace': 2.0, 'mean_trace': 4.0,
             'consistent': True},
            {**base, 'strategy': 'crm', 'steady_trace': 1.5, 'mean_trace': 5.0,
             'consistent': True},
            {**base, 'strategy': 'mtf', 'steady_trace': 1.0, 'mean_trace': 1.0,
             'consistent': False}]
    out = with_gains(rows)
    assert [r['gain_over_ram_pct'] for r in out] == [0.0, 25.0, 50.0]
    assert [r['mean_gain_over_ram_pct'] for r in out] == [0.0, -25.0, 75.0]
    assert {r['best_at_point'] for r in out} == {'crm'}      # MTF is flagged
    rq = {**base, 'strategy': 'rq', 'steady_trace': 1.5 * (1 + 2e-9), 'mean_trace': 5.0,
          'consistent': True}                                # RQ ties CRM: a win for none
    tied = with_gains(rows + [rq])
    assert {r['best_at_point'] for r in tied} == {'crm=rq'}
    assert winners(tied, 'r_fraction', 'measurement')[2] == [['crm=rq']]
    rq['steady_trace'] = 1.5 * (1 - 1e-5)
    assert {r['best_at_point'] for r in with_gains(rows + [rq])} == {'rq'}
    rq['steady'] = False                                     # its trace grows: not a winner
    assert {r['best_at_point'] for r in with_gains(rows + [rq])} == {'crm'}


@pytest.mark.slow
def test_one_and_two_workers_give_the_same_table(tmp_path: Path) -> None:
    cells = tiny_cells()
    one = run_cells(cells, CellCache(tmp_path / 'one'), workers=1)
    two = run_cells(cells, CellCache(tmp_path / 'two'), workers=2)
    assert len(one.computed) == len(two.computed) == len(cells) == 12
    assert results(one.rows) == results(two.rows)
    rows = table_rows(one.rows)
    write_table(rows, tmp_path / 'one.csv')
    table = read_table(tmp_path / 'one.csv')
    assert len(table) == 12 and table[0]['strategy'] == 'ram'
    assert float(table[1]['steady_trace']) == rows[1]['steady_trace']     # exact in the CSV
    ram = [r for r in rows if r['strategy'] == 'ram']
    assert all(r['gain_over_ram_pct'] == 0.0 for r in ram)
    # at every point, staying in the slot (MTF) is worse than RAM's optimum for range
    assert all(r['gain_over_ram_pct'] < -10.0 for r in rows if r['strategy'] == 'mtf')


@pytest.mark.slow
def test_an_interrupted_sweep_resumes_without_recomputing(tmp_path: Path) -> None:
    cells = tiny_cells()
    whole = run_cells(cells, CellCache(tmp_path / 'whole'), workers=2)
    cache = CellCache(tmp_path / 'cells')
    done: list[str] = []

    def interrupt_after_five(key: str, row: dict[str, Any]) -> None:
        done.append(key)
        if len(done) == 5:
            raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        run_cells(cells, cache, workers=2, finished=interrupt_after_five)
    assert sorted(p.stem for p in cache.folder.glob('*.json')) == sorted(done)
    resumed = run_cells(cells, cache, workers=1)
    assert sorted(resumed.reused) == sorted(done)
    assert len(resumed.computed) == len(cells) - 5 and not set(resumed.computed) & set(done)
    assert results(resumed.rows) == results(whole.rows)


def test_the_command_writes_table_figures_and_resumes(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / 'sweep.yaml'
    config.write_text('grid:\n  r_fraction: [0.05, 0.2]\n  leader_path: [straight, arc]\n'
                      'scenarios:\n  - {measurement: bearing, sigma_scale: 2}\n'
                      'strategies: [ram, crm]\noptions: {crm: {}}\ntrials: 3\nsteps: 30\n'
                      'seed: 1\nheatmap: [r_fraction, leader_path]\n')
    out = tmp_path / 'out'
    args = ['--config', str(config), '--workers', '2', '--out', str(out)]
    assert cli.main(args) == 0
    table = read_table(out / 'sweep.csv')
    assert len(table) == 10                             # (4 grid + 1 listed) x 2
    assert [r['leader_path'] for r in table[:4:2]] == ['straight', 'arc']
    assert table[-1]['measurement'] == 'bearing' and table[-1]['sigma_scale'] == '2.0'
    assert {p.name for p in (out / 'figures').iterdir()} == {
        'gain_over_ram_range.png', 'winners_range.png', 'gain_over_ram_bearing.png',
        'winners_bearing.png'}
    assert json.loads((out / 'sweep.json').read_text())['cells'] == 10
    first = (out / 'sweep.csv').read_text()
    assert cli.main(args + ['--no-figures']) == 0              # every cell from the cache
    assert (out / 'sweep.csv').read_text() == first
    with pytest.raises(SystemExit) as stop:             # another sweep: it would overwrite
        cli.main(['--measurement', 'range', '--r-fraction', '0.1', '--strategies', 'mtf',
                  '--trials', '2', '--steps', '20', '--out', str(out)])
    assert stop.value.code == 2 and (out / 'sweep.csv').read_text() == first
    assert 'holds another sweep' in capsys.readouterr().err


@pytest.mark.parametrize('args, message', [
    (['--strategies', 'ram,nope'], "unknown 'nope'"),
    (['--r-fraction', '0.1,x'], 'must be a comma list of numbers'),
    (['--leader-path', 'circle'], 'circle: the values are straight, arc, s-curve'),
    (['--leader-path', 'straight', '--leader-yaw-rate', '0.3,0.5'],
     "leader_yaw_rate is not used by leader_path 'straight'"),
    (['--r-fraction', '1.5'], 'r must lie in [1e-06, 0.999] |p_o|'),
    (['--sigma-scale', '-1'], 'sigma_scale -1 is out of range'),
    (['--option', 'crm.speed=1'], "method 'crm' accepts options"),
    (['--heatmap', 'r_fraction,colour'], 'heatmap must name two axes'),
    (['--measurement', 'bearing', '--r-fraction', '0.6'], '--allow-inconsistent runs it'),
    (['--scheduler', 'tcp://127.0.0.1:99999'], 'is not a scheduler address'),
])
def test_bad_sweeps_stop_with_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    result = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.sweep', *args, '--out',
                             str(tmp_path / 'o')], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith('formopt-sweep: error: ') and message in result.stderr, \
        result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_a_separate_dask_cluster_gives_the_same_numbers(tmp_path: Path) -> None:
    """`dask scheduler` + `dask worker` (2 processes) started here; --scheduler ADDRESS."""
    dask_cli = Path(sys.executable).parent / 'dask'
    if not dask_cli.exists() or shutil.which(str(dask_cli)) is None:
        pytest.skip('the dask command is not installed')
    from dask.distributed import Client
    address_file = tmp_path / 'scheduler.json'
    scheduler = subprocess.Popen([str(dask_cli), 'scheduler', '--host', '127.0.0.1', '--port',
                                  '0', '--no-dashboard', '--scheduler-file', str(address_file)],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    worker = subprocess.Popen([str(dask_cli), 'worker', '--scheduler-file', str(address_file),
                               '--nworkers', '2', '--nthreads', '1', '--no-dashboard'],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        try:
            with Client(scheduler_file=str(address_file), timeout='60s') as client:
                client.wait_for_workers(2, timeout=120)
                address = client.scheduler.address
        except (OSError, TimeoutError) as error:
            pytest.skip(f'the Dask cluster did not start: {error}')
        common = ['--r-fraction', '0.05,0.2', '--sigma-scale', '0.5,1', '--strategies',
                  'ram,crm,mtf', '--trials', '3', '--steps', '40', '--seed', '7']
        remote = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.sweep', *common,
                                 '--scheduler', address, '--out', str(tmp_path / 'remote'),
                                 '--no-figures'], capture_output=True, text=True, timeout=300)
        assert remote.returncode == 0, remote.stderr
        assert f'on {address}' in remote.stdout
        local = subprocess.run([sys.executable, '-m', 'formopt_ros.cli.sweep', *common,
                                '--workers', '1', '--out', str(tmp_path / 'local'),
                                '--no-figures'], capture_output=True, text=True, timeout=300)
        assert local.returncode == 0, local.stderr

        def numbers(folder: str) -> list[dict[str, str]]:
            return [{k: v for k, v in row.items() if k not in TIMING_COLUMNS}
                    for row in read_table(tmp_path / folder / 'sweep.csv')]
        assert numbers('remote') == numbers('local') and len(numbers('local')) == 12
        expected = results(run_cells(tiny_cells(), CellCache(tmp_path / 'api'),
                                     workers=1).rows)
        assert [float(r['steady_trace']) for r in numbers('remote')] == [
            r['steady_trace'] for r in expected]
    finally:
        for process in (worker, scheduler):
            process.terminate()
        for process in (worker, scheduler):
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()


@pytest.mark.slow
def test_ctrl_c_keeps_the_finished_cells_and_the_rerun_computes_the_rest(
        tmp_path: Path) -> None:
    """SIGINT to the command's process group (as Ctrl-C) once a cell is finished in the
    cache: exit 130 with one line saying what is kept, no worker traceback; the same command
    again computes only the other cells."""
    import os
    import signal
    import time
    args = [sys.executable, '-m', 'formopt_ros.cli.sweep', '--r-fraction', '0.05,0.2',
            '--sigma-scale', '0.5,1', '--strategies', 'ram,crm,mtf', '--trials', '4',
            '--steps', '1000', '--workers', '2', '--no-figures', '--out', str(tmp_path / 'o')]
    process = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               start_new_session=True)
    cells, deadline = tmp_path / 'o' / 'cells', time.monotonic() + 120
    while not any(cells.glob('*.json')):         # until one cell is finished and stored
        assert process.poll() is None and time.monotonic() < deadline, process.poll()
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGINT)
    _, err = process.communicate(timeout=120)
    text = err.decode()
    assert process.returncode == 130, text
    assert 'Traceback' not in text, text
    kept = len(list((tmp_path / 'o' / 'cells').glob('*.json')))
    assert 1 <= kept < 12
    assert f'formopt-sweep: interrupted; {kept} of 12 cells are finished and kept' in text
    again = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert f'12 cells ({12 - kept} computed, {kept} reused' in again.stdout
    assert len(read_table(tmp_path / 'o' / 'sweep.csv')) == 12


def test_the_documented_sweep_file_is_accepted(tmp_path: Path) -> None:
    """The sweep file of docs/sweeps.md, as written, gives its 13 scenarios x 4 strategies."""
    docs = (Path(__file__).resolve().parents[2] / 'docs' / 'sweeps.md').read_text()
    text = docs.split('## A sweep file', 1)[1].split('```yaml\n', 1)[1].split('```', 1)[0]
    (tmp_path / 'sweep.yaml').write_text(text)
    args = cli.build_parser().parse_args(['--config', str(tmp_path / 'sweep.yaml'), '--out',
                                          str(tmp_path / 'o')])
    cells = cli.make_cells(cli.sweep_spec(args), allow_inconsistent=False)
    assert len(cells) == 13 * 4 and {cell.strategy for cell in cells} == {
        'ram', 'rq', 'gbs', 'periodic'}
