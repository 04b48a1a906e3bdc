"""Plugin strategies: discovery through the entry-point group, options, the study and the
report of a broken plugin (entry points made here; test/ros/test_plugin_package.py installs a real
package)."""
from __future__ import annotations

import argparse
import importlib.metadata
import sys
from pathlib import Path

import numpy as np
import pytest

from formopt_ros.cli.common import name_list
from formopt_ros.core import solve
from formopt_ros.core.strategies import BUILTIN, STRATEGIES, Strategy, make_strategy
from formopt_ros.core.strategies.registry import GROUP, StrategyRegistry
from formopt_ros.core.study import StudyConfig, run_study, summarize

PLUGIN = '''
import math
import numpy as np
from formopt_ros.core.strategies import OptionSpec, Strategy, make_solution


class Ring(Strategy):
    name = 'ring'
    OPTIONS = {'samples': OptionSpec(16, 'points on the circle', 3, 720),
               'radius': OptionSpec(1.0, 'circle radius, fraction of r', 0.0, 1.0)}

    def plan(self, problem, context):
        n, radius = self.settings['samples'], self.settings['radius'] * problem.r
        angles = 2.0 * math.pi * np.arange(n) / n
        x_o, y_o = problem.slot
        points = np.vstack([[x_o, y_o], np.column_stack([x_o + radius * np.cos(angles),
                                                          y_o + radius * np.sin(angles)])])
        best = int(np.argmax(problem.gain(points)))
        return make_solution(problem, points[best], self.name, candidates=n + 1)


class NotAStrategy:
    name = 'notastrategy'


class BadOptions(Ring):
    name = 'badoptions'
    OPTIONS = {'samples': OptionSpec(2, 'points on the circle', 3, 720)}


class Misnamed(Ring):
    name = 'other'


class Unplanned(Strategy):
    name = 'unplanned'


class Outside(Strategy):
    name = 'outside'

    def plan(self, problem, context):
        x_o, y_o = problem.slot
        return make_solution(problem, (x_o + 3.0 * problem.r, y_o), self.name)
'''


def entry(name: str, value: str) -> importlib.metadata.EntryPoint:
    return importlib.metadata.EntryPoint(name, value, GROUP)


@pytest.fixture
def plugin_module(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> str:
    """A module of plugin classes on sys.path (removed afterwards)."""
    (tmp_path / 'fake_formopt_plugins.py').write_text(PLUGIN)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield 'fake_formopt_plugins'
    sys.modules.pop('fake_formopt_plugins', None)


def installed(monkeypatch: pytest.MonkeyPatch, points: list[importlib.metadata.EntryPoint]
              ) -> list[int]:
    """Make importlib.metadata report ``points`` as the installed ones; returns a call log."""
    calls: list[int] = []

    def fake(**selection: str) -> list[importlib.metadata.EntryPoint]:
        calls.append(1)
        assert selection == {'group': GROUP}
        return list(points)
    monkeypatch.setattr(importlib.metadata, 'entry_points', fake)
    return calls


def test_a_plugin_joins_the_registry_after_the_built_in_strategies(
        plugin_module: str, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    calls = installed(monkeypatch, [entry('ring', f'{plugin_module}:Ring')])
    registry = StrategyRegistry({name: STRATEGIES[name] for name in BUILTIN})
    assert registry['ram'] is STRATEGIES['ram'] and 'rq' in registry
    assert calls == []                      # a built-in name never looks for plugins
    assert list(registry) == [*BUILTIN, 'ring'] and registry.plugins() == ('ring',)
    assert len(registry) == len(BUILTIN) + 1 and calls == [1]
    list(registry)
    assert calls == [1] and registry.problems == []
    assert capsys.readouterr().err == ''


def test_a_plugin_runs_in_solve_and_the_study(plugin_module: str,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    installed(monkeypatch, [entry('ring', f'{plugin_module}:Ring')])
    monkeypatch.setattr(STRATEGIES, '_table', None)
    monkeypatch.setattr(STRATEGIES, 'problems', [])
    ring = make_strategy('ring', samples=8)
    assert ring.settings == {'samples': 8, 'radius': 1.0}
    with pytest.raises(ValueError, match=r'ring option samples must be an integer in \[3, 720\]'):
        make_strategy('ring', samples=2)
    P = np.diag([0.02, 0.01, 1e-3])
    p_o = np.array([-1.0, -2.0])
    r = 0.1 * np.hypot(*p_o)
    sol = solve(P, p_o, r, 0.1, measurement='range', method='ring', samples=720)
    best = solve(P, p_o, r, 0.1, measurement='range', method='rq')
    assert sol.method == 'ring' and sol.candidates == 721
    assert best.cost <= sol.cost <= best.cost * (1 + 1e-4)    # 0.5 deg from the optimum
    config = StudyConfig('range', trials=3, steps=40, seed=2, strategies=('ram', 'ring'),
                         options={'ring': {'samples': 720}})
    summary = summarize(run_study(config, jobs=1))
    assert summary['options']['ring'] == {'samples': 720, 'radius': 1.0}
    ring_row, ram_row = summary['strategies']['ring'], summary['strategies']['ram']
    # RAM is the exact optimum per step: a fine boundary search comes within 0.1 %
    assert ram_row['steady_trace'] == pytest.approx(ring_row['steady_trace'], rel=1e-3)
    alone = summarize(run_study(StudyConfig('range', trials=3, steps=40, seed=2,
                                            strategies=('ring',),
                                            options={'ring': {'samples': 720}}), jobs=1))
    timing = ('decision_time_s', 'decision_time_median_s')        # wall time, not a result
    assert {k: v for k, v in alone['strategies']['ring'].items() if k not in timing} == {
        k: v for k, v in ring_row.items() if k not in timing}
    per_trial = summarize(run_study(config, jobs=1, engine='per-trial'))
    assert per_trial['strategies']['ring']['steady_trace'] == pytest.approx(
        ring_row['steady_trace'], rel=1e-9)


@pytest.mark.parametrize('engine', ['batched', 'per-trial'])
def test_a_plugin_that_leaves_the_disc_stops_the_study(plugin_module: str, engine: str,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """A plugin's point 3 r from the slot is never scored: the study stops with an error
    naming the strategy, as a node refuses such a waypoint."""
    installed(monkeypatch, [entry('outside', f'{plugin_module}:Outside')])
    monkeypatch.setattr(STRATEGIES, '_table', None)
    monkeypatch.setattr(STRATEGIES, 'problems', [])
    config = StudyConfig('range', trials=2, steps=5, seed=0, strategies=('ram', 'outside'))
    with pytest.raises(ValueError, match=r"strategy 'outside' planned a point 0\.67082 m from "
                                         r'the slot, outside its disc \(r = 0\.223607 m\)'):
        run_study(config, jobs=1, engine=engine)


BROKEN = [('missing', 'no_such_formopt_module:Thing', "cannot be imported: ModuleNotFoundError: "
           "No module named 'no_such_formopt_module'"),
          ('notastrategy', '{m}:NotAStrategy', 'is not a subclass of formopt_ros.core.'
           'strategies.Strategy'),
          ('badoptions', '{m}:BadOptions', "option 'samples': its default is refused: badoptions "
           'option samples must be an integer in [3, 720]'),
          ('misnamed', '{m}:Misnamed', "has name 'other'; the entry point must be named as the "
           'strategy'),
          ('unplanned', '{m}:Unplanned', 'does not implement plan()'),
          ('ram', '{m}:Ring', "the name 'ram' is taken"),
          ('Bad-Name', '{m}:Ring', 'the name must be lower-case letters')]


def test_broken_plugins_are_reported_once_and_hide_nothing(
        plugin_module: str, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    points = [entry(name, value.format(m=plugin_module)) for name, value, _ in BROKEN]
    installed(monkeypatch, [*points, entry('ring', f'{plugin_module}:Ring')])
    registry = StrategyRegistry({name: STRATEGIES[name] for name in BUILTIN})
    assert list(registry) == [*BUILTIN, 'ring']
    assert registry['ram'] is STRATEGIES['ram']
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == len(BROKEN)
    for (name, _, reason), line in zip(sorted(BROKEN), lines):
        assert line.startswith(f"formopt_ros: warning: strategy plugin '{name}' ("), line
        assert reason in line, line
    list(registry)
    assert capsys.readouterr().err == ''                     # once per process
    assert [p.name for p in registry.problems] == sorted(n for n, _, _ in BROKEN)
    parse = name_list(tuple(registry), registry.left_out())     # what --strategies says
    with pytest.raises(argparse.ArgumentTypeError,
                       match="'missing' is a plugin left out: cannot be imported"):
        parse('ram,missing')


def test_two_plugins_of_one_name_are_both_refused(plugin_module: str,
                                                  monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    installed(monkeypatch, [entry('ring', f'{plugin_module}:Ring'),
                            entry('ring', f'{plugin_module}:BadOptions')])
    monkeypatch.setenv('FORMOPT_PLUGIN_WARNINGS', '0')
    registry = StrategyRegistry({name: STRATEGIES[name] for name in BUILTIN})
    assert list(registry) == list(BUILTIN)
    assert capsys.readouterr().err == ''                     # silenced
    assert [p.reason for p in registry.problems] == [
        "2 installed plugins are named 'ring'; none of them is used"] * 2


def test_the_registry_is_the_packages_own() -> None:
    """Without plugins installed the registry holds the built-in strategies in their order."""
    assert tuple(STRATEGIES)[:len(BUILTIN)] == BUILTIN
    assert all(issubclass(STRATEGIES[name], Strategy) for name in STRATEGIES)
