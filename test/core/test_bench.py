"""formopt-bench and the general-purpose peers (SciPy SLSQP, CasADi + IPOPT when installed)."""
from __future__ import annotations

import csv

import numpy as np
import pytest

from formopt_ros.analysis import peers
from formopt_ros.cli import bench
from formopt_ros.core.model import BEARING, RANGE
from formopt_ros.core.strategies.rq import rq_optimum
from harness.problems import hard_problem


@pytest.mark.parametrize('kind', [RANGE, BEARING])
def test_peers_never_beat_the_certified_optimum(kind: str) -> None:
    """On 15 hard problems per kind every peer returns a feasible point whose cost is not below
    the certified RQ optimum (1e-12 relative): an outside check of the certificates."""
    rng = np.random.default_rng(31)
    methods = peers.peer_methods(kind)
    for _ in range(15):
        problem = hard_problem(rng, kind)
        optimum = rq_optimum(problem).cost
        for name, method in methods.items():
            p = method(problem)
            assert np.hypot(*(p - problem.p_o)) <= problem.r * (1 + 1e-9), name
            assert problem.cost(p) >= optimum * (1 - 1e-12), name


def test_bench_prints_the_table_and_writes_csv(tmp_path, capsys: pytest.CaptureFixture) -> None:
    """A small run prints one row per kind and method with the miss columns; the CSV has one
    row per (kind, problem, method) and refuses to overwrite an existing file."""
    path = tmp_path / 'bench.csv'
    methods = 'ram,rq,rq-loop,rq-batch,gbs,gbs-cached,slsqp'
    assert bench.main(['--problems', '3', '--repeats', '1', '--methods', methods,
                       '--csv', str(path)]) == 0
    out = capsys.readouterr().out
    assert 'proved: range 3/3, bearing 3/3' in out
    lines = out.splitlines()
    assert 'below bound' in lines[1]
    for kind in ('range', 'bearing'):
        for method in methods.split(','):
            row = next(line.split() for line in lines if line.split()[:2] == [kind, method])
            assert row[-2] == '0', row          # no cost below a proved bound
    with open(path, newline='') as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == 2 * 3 * 7
    assert {row['miss'] for row in rows
            if row['method'] in ('ram', 'rq', 'rq-loop', 'rq-batch')} == {'0'}
    # rq-batch in calls of 2 problems: the third problem's call is another call
    assert bench.main(['--problems', '3', '--repeats', '1', '--methods', 'rq-batch',
                       '--batch-size', '2', '--measurement', 'range',
                       '--csv', str(tmp_path / 'batch.csv')]) == 0
    assert 'rq-batch: 2 problems per call' in capsys.readouterr().out
    with open(tmp_path / 'batch.csv', newline='') as handle:
        times = [row['time_us'] for row in csv.DictReader(handle)]
    assert times[0] == times[1] != times[2]
    with pytest.raises(SystemExit) as stop:
        bench.main(['--problems', '1', '--csv', str(path)])
    assert stop.value.code == 2
    assert 'refusing to overwrite' in capsys.readouterr().err


def test_a_cost_below_the_proved_bound_is_counted() -> None:
    """summarise counts a cost below optimum (1 - gap) by more than 1e-9 as 'below bound' (a
    contradicted certificate is shown, not clipped away), and one below an unproved reference's
    cost (gap nan); a cost within the gap is not counted."""
    optimum, gap = np.array([1.0, 1.0, 1.0]), np.array([1e-10, 1e-10, np.nan])
    results = {'rq': {'time': np.ones(3), 'cost': optimum, 'fallback': np.zeros(3, bool)},
               'other': {'time': np.ones(3), 'cost': np.array([1.0 - 1e-6, 1.0 - 5e-10, 0.5]),
                         'fallback': np.zeros(3, bool)}}
    rows = {row[1]: row for row in bench.summarise('range', results, optimum, gap)}
    assert rows['rq'][-2] == '0' and rows['other'][-2] == '2'


def test_bench_skips_ipopt_without_casadi(monkeypatch: pytest.MonkeyPatch,
                                          capsys: pytest.CaptureFixture) -> None:
    """Without CasADi the ipopt rows are skipped with a one-line note."""
    monkeypatch.setattr(peers, 'casadi_available', lambda: False)
    monkeypatch.setattr(bench, 'casadi_available', lambda: False)
    assert bench.main(['--problems', '1', '--repeats', '1', '--measurement', 'range',
                       '--methods', 'rq,ipopt,ipopt-8']) == 0
    out = capsys.readouterr().out
    assert 'casadi is not installed' in out
    assert not any(line.startswith('range    ipopt') for line in out.splitlines())


def test_bench_rejects_unknown_methods(capsys: pytest.CaptureFixture) -> None:
    """An unknown method stops with exit code 2 and names the accepted ones."""
    with pytest.raises(SystemExit) as stop:
        bench.main(['--methods', 'rq,simplex'])
    assert stop.value.code == 2
    assert 'ipopt-tuned' in capsys.readouterr().err


def test_bench_range_bearing_rows(capsys: pytest.CaptureFixture) -> None:
    """--measurement range-bearing: RQ (the branch and bound) proves every reference; its rows
    and the baselines' are printed; RAM and rq-batch (no form for it) are left out."""
    assert bench.main(['--problems', '3', '--repeats', '1', '--measurement', 'range-bearing',
                       '--methods', 'ram,rq,rq-loop,rq-batch,gbs-cached,mtf']) == 0
    out = capsys.readouterr().out
    assert 'proved: range-bearing 3/3' in out
    rows = [line.split() for line in out.splitlines() if line.startswith('range-bearing')]
    assert [row[1] for row in rows] == ['rq', 'rq-loop', 'gbs-cached', 'mtf']
    assert all(row[-2] == '0' for row in rows)          # nothing below a proved bound
    assert rows[0][6] == '0' and rows[1][6] == '0'      # RQ misses nothing
