"""A third-party strategy package (docs/plugins.md's worked example, written here and
pip-installed into a folder on this process's path) runs in the study, a sweep,
formopt-bench and a lockstep ROS run with no file of formopt_ros changed; a broken plugin is
reported and hides nothing."""
from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from harness.ros import REPO, node_scenario

from formopt_ros.core.simulation import run_trial
from formopt_ros.core.strategies import BUILTIN, STRATEGIES
from formopt_ros.core.study import StudyConfig, run_study, summarize

DOCS = REPO / 'docs' / 'plugins.md'
SCRIPT = REPO / 'scripts' / 'run_formation.sh'
BIN = Path(sys.executable).parent
TOL = 1e-9
BROKEN_MODULE = '''
class NotAStrategy:
    name = 'notastrategy'
'''
BROKEN_PYPROJECT = '''
[build-system]
requires = ["setuptools>=61"]
build-backend = "setuptools.build_meta"

[project]
name = "formopt-broken-plugins"
version = "0.0.1"

[project.entry-points."formopt_ros.strategies"]
missing = "formopt_broken_nowhere:Thing"
notastrategy = "formopt_broken_plugins:NotAStrategy"
badoptions = "formopt_ring_bad:BadOptions"

[tool.setuptools]
py-modules = ["formopt_broken_plugins", "formopt_ring_bad"]
'''
BAD_OPTIONS = '''
from formopt_ring import Ring
from formopt_ros.core.strategies import OptionSpec


class BadOptions(Ring):
    name = 'badoptions'
    OPTIONS = {'samples': OptionSpec(1, 'points on the circle', 3, 720)}
'''


def documented_files() -> dict[str, str]:
    """The files of docs/plugins.md's example: name -> content."""
    text = DOCS.read_text()
    return dict(re.findall(r'<!-- file: (\S+) -->\n```\w*\n(.*?)```', text, re.S))


def pip(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, '-m', 'pip', *args, '--quiet',
                           '--disable-pip-version-check'], capture_output=True, text=True,
                          timeout=600)


def install(folder: Path, target: Path | None = None) -> None:
    """pip install the folder (into ``target`` when given, a folder only the processes that put
    it on their path see), or skip the test when pip cannot (offline, no build backend)."""
    into = ('--target', str(target)) if target else ()
    result = pip('install', '--no-deps', '--no-build-isolation', *into, str(folder))
    if result.returncode != 0:                       # no local build backend: fetch one
        result = pip('install', '--no-deps', *into, str(folder))
    if result.returncode != 0:
        pytest.skip(f'pip cannot install {folder.name} here: '
                    f'{result.stderr.strip().splitlines()[-1:]}')
    importlib.invalidate_caches()
    STRATEGIES.rediscover()


def path_with(folder: Path) -> str:
    """This process's PYTHONPATH with ``folder`` in front."""
    return os.pathsep.join([str(folder), *filter(None, [os.environ.get('PYTHONPATH')])])


@pytest.fixture(scope='module')
def ring(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """The worked example installed for this module into a folder of its own, on this
    process's path and its children's PYTHONPATH (removed afterwards): the environment the
    other tests share never sees it."""
    folder = tmp_path_factory.mktemp('plugin') / 'formopt-ring'
    folder.mkdir()
    site = tmp_path_factory.mktemp('plugin-site')
    files = documented_files()
    assert set(files) == {'pyproject.toml', 'formopt_ring.py'}, files.keys()
    for name, content in files.items():
        (folder / name).write_text(content)
    before = os.environ.get('PYTHONPATH')
    sys.path.insert(0, str(site))
    os.environ['PYTHONPATH'] = path_with(site)
    try:
        install(folder, site)
        yield 'ring'
    finally:
        sys.path.remove(str(site))
        if before is None:
            os.environ.pop('PYTHONPATH', None)
        else:
            os.environ['PYTHONPATH'] = before
        importlib.invalidate_caches()
        STRATEGIES.rediscover()
        sys.modules.pop('formopt_ring', None)


def command(*args: str, timeout: float = 600,
            env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN / args[0]), *args[1:]], capture_output=True, text=True,
                          timeout=timeout, env=env)


def test_discovery_and_options(ring: str) -> None:
    code = ('from formopt_ros.core.strategies import STRATEGIES, make_strategy\n'
            'print(list(STRATEGIES), STRATEGIES.origin("ring"))\n'
            'print(make_strategy("ring", samples=64).settings)\n'
            'make_strategy("ring", samples=1)\n')
    result = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                            timeout=120)
    lines = result.stdout.splitlines()
    assert lines[0] == f"{[*BUILTIN, 'ring']} formopt-ring 0.1.0"
    assert lines[1] == "{'samples': 64, 'radius': 1.0}"
    assert 'ring option samples must be an integer in [3, 720]' in result.stderr and \
        'got 1' in result.stderr
    help_text = command('formopt-montecarlo', '--help').stdout
    listed = help_text.replace('\n', '').replace(' ', '')
    assert 'mtf,crm,mme,gbs,ram,rq,periodic,lookahead,ring' in listed


def test_a_study_through_formopt_montecarlo(ring: str, tmp_path: Path) -> None:
    out = tmp_path / 'mc'
    result = command('formopt-montecarlo', '--measurement', 'range', '--trials', '3',
                     '--steps', '40', '--seed', '4', '--strategies', 'ram,ring', '--option',
                     'ring.samples=64', '--jobs', '2', '--no-figures', '--out', str(out))
    assert result.returncode == 0, result.stderr
    assert '| RING |' in result.stdout
    summary = json.loads((out / 'range' / 'summary.json').read_text())
    assert summary['options']['ring'] == {'samples': 64, 'radius': 1.0}
    here = summarize(run_study(StudyConfig('range', 3, 40, 4, ('ram', 'ring'),
                                           {'ring': {'samples': 64}}), jobs=1))
    for name in ('ram', 'ring'):
        assert summary['strategies'][name]['steady_trace'] == \
            here['strategies'][name]['steady_trace']
    # 64 samples of the boundary: within 0.5 % of RAM's optimum
    assert summary['strategies']['ring']['steady_trace'] == pytest.approx(
        summary['strategies']['ram']['steady_trace'], rel=5e-3)


def test_a_sweep_and_formopt_bench(ring: str, tmp_path: Path) -> None:
    out = tmp_path / 'sweep'
    result = command('formopt-sweep', '--strategies', 'ram,ring', '--option', 'ring.samples=64',
                     '--r-fraction', '0.05,0.2', '--trials', '2', '--steps', '30',
                     '--workers', '2', '--no-figures', '--out', str(out))
    assert result.returncode == 0, result.stderr
    rows = list(csv_rows(out / 'sweep.csv'))
    assert [r['strategy'] for r in rows] == ['ram', 'ring'] * 2
    assert all(json.loads(r['options']) == {'samples': 64, 'radius': 1.0}
               for r in rows if r['strategy'] == 'ring')
    assert all(abs(float(r['gain_over_ram_pct'])) < 1.0 for r in rows)
    assert 'warning' not in result.stderr
    bench = command('formopt-bench', '--methods', 'rq,ring', '--problems', '5', '--repeats',
                    '1', '--measurement', 'range')
    assert bench.returncode == 0, bench.stderr
    assert re.search(r'^range\s+ring\s', bench.stdout, re.M), bench.stdout


def csv_rows(path: Path) -> Iterator[dict[str, str]]:
    import csv
    with open(path, newline='') as handle:
        yield from csv.DictReader(handle)


def test_a_lockstep_ros_run(ring: str, tmp_path: Path, ros_domain: int) -> None:
    assert 'ring' in subprocess.run([str(SCRIPT), '--help'], capture_output=True, text=True,
                                    timeout=60).stdout
    out = tmp_path / 'run'
    result = subprocess.run([str(SCRIPT), '--measurement', 'range', '--strategy', 'ring', '-p',
                             'ring_samples:=64', '--steps', '30', '--seed', '3', '--out',
                             str(out), '--domain-id', str(ros_domain), '--no-record',
                             '--timeout', '120'], capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stdout + result.stderr
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['ok'] and summary['steps'] == 30
    assert summary['formation']['followers'][0]['strategy'] == 'ring'
    assert summary['formation']['followers'][0]['options'] == {'samples': 64}
    ref = run_trial(node_scenario('range'), 'ring', 3, 0, 30, options={'samples': 64})
    np.testing.assert_allclose(summary['final_estimate'], ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(summary['final_covariance'], ref.covariance[-1], rtol=0,
                               atol=TOL)


def test_a_broken_plugin_is_named_and_hides_nothing(ring: str, tmp_path: Path) -> None:
    """The broken package goes into a folder of its own, seen by this process and the study it
    starts only: installed into the environment, the warnings reached every test running
    beside it (a run_formation test that wants one line of stderr failed)."""
    folder, site = tmp_path / 'formopt-broken-plugins', tmp_path / 'site'
    folder.mkdir()
    (folder / 'pyproject.toml').write_text(BROKEN_PYPROJECT)
    (folder / 'formopt_broken_plugins.py').write_text(BROKEN_MODULE)
    (folder / 'formopt_ring_bad.py').write_text(BAD_OPTIONS)
    site.mkdir()
    sys.path.insert(0, str(site))
    try:
        install(folder, site)
        out = tmp_path / 'mc'
        result = command('formopt-montecarlo', '--measurement', 'range', '--trials', '2',
                         '--steps', '10', '--strategies', 'ram,ring', '--jobs', '1',
                         '--no-figures', '--out', str(out),
                         env={**os.environ, 'PYTHONPATH': path_with(site)})
        assert result.returncode == 0, result.stderr
        warnings = [line for line in result.stderr.splitlines() if 'warning: strategy' in line]
        source = 'from formopt-broken-plugins 0.0.1) ignored: '
        assert warnings == [
            "formopt_ros: warning: strategy plugin 'badoptions' (formopt_ring_bad:BadOptions "
            f"{source}option 'samples': its default is refused: badoptions option samples must "
            'be an integer in [3, 720], got 1',
            "formopt_ros: warning: strategy plugin 'missing' (formopt_broken_nowhere:Thing "
            f"{source}cannot be imported: ModuleNotFoundError: No module named "
            "'formopt_broken_nowhere'",
            "formopt_ros: warning: strategy plugin 'notastrategy' (formopt_broken_plugins:"
            f"NotAStrategy {source}<class 'formopt_broken_plugins.NotAStrategy'> is not a "
            'subclass of formopt_ros.core.strategies.Strategy']
        assert set(json.loads((out / 'range' / 'summary.json').read_text())['strategies']) \
            == {'ram', 'ring'}
        assert list(STRATEGIES) == [*BUILTIN, 'ring']
        assert [p.name for p in STRATEGIES.problems] == ['badoptions', 'missing',
                                                         'notastrategy']
    finally:
        sys.path.remove(str(site))
        importlib.invalidate_caches()
        STRATEGIES.rediscover()
        for module in ('formopt_broken_plugins', 'formopt_ring_bad'):
            sys.modules.pop(module, None)
