"""The strategy registry: the built-in strategies, then the installed plugin strategies.

A plugin is a :class:`~formopt_ros.core.strategies.base.Strategy` subclass that another
installed distribution declares in the entry-point group :data:`GROUP` under the strategy's
name (docs/plugins.md). The registry looks for plugins once, on the first use that needs
every name (iteration, ``len``, an unknown name); looking up a built-in strategy never does.
A plugin that cannot be used (it does not import, is not a Strategy, has a bad name or bad
``OPTIONS``) is left out and reported in one line on stderr naming it, once per process; it
never hides the built-in strategies or the other plugins.
"""
from __future__ import annotations

import inspect
import os
import re
import sys
from collections.abc import Iterable, Iterator, MutableMapping
from dataclasses import dataclass
from typing import Any

from formopt_ros.core.strategies.base import OptionSpec, Strategy

#: Entry-point group of plugin strategies: ``name = module:StrategyClass``.
GROUP = 'formopt_ros.strategies'
#: A strategy or option name: it becomes the ROS parameter '<strategy>_<option>'.
NAME = re.compile(r'^[a-z][a-z0-9_]*$')
#: Set to 0 to silence the report of unusable plugins (e.g. in worker processes).
QUIET_ENV = 'FORMOPT_PLUGIN_WARNINGS'


@dataclass(frozen=True)
class PluginProblem:
    """An unusable plugin: the entry point's name, its ``module:attr`` and distribution, and
    why it was left out (one line)."""

    name: str
    value: str
    distribution: str
    reason: str

    def __str__(self) -> str:
        return (f'formopt_ros: warning: strategy plugin {self.name!r} ({self.value} from '
                f'{self.distribution}) ignored: {self.reason}')


def _one_line(error: BaseException) -> str:
    text = ' '.join(str(error).split())
    return f'{type(error).__name__}: {text}' if text else type(error).__name__


def check_plugin(name: str, obj: object, taken: Iterable[str],
                 parameters: Iterable[str] = ()) -> str:
    """Why ``obj`` cannot be the strategy ``name`` ('' when it can).

    Args:
        name: the entry point's name; the class's ``name`` must equal it.
        obj: what the entry point loaded.
        taken: names already in the registry (a plugin never replaces one).
        parameters: '<strategy>_<option>' names already used by the registry's strategies.
    """
    if not NAME.match(name):
        return ('the name must be lower-case letters, digits and underscores, starting with a '
                'letter (it prefixes ROS parameters)')
    if name in taken:
        return f'the name {name!r} is taken (a plugin never replaces a registered strategy)'
    if not (inspect.isclass(obj) and issubclass(obj, Strategy)):
        return f'{obj!r} is not a subclass of formopt_ros.core.strategies.Strategy'
    if obj.name != name:
        return (f'its class {obj.__name__} has name {obj.name!r}; the entry point must be '
                'named as the strategy')
    if obj.plan is Strategy.plan:
        return f'its class {obj.__name__} does not implement plan()'
    options = obj.OPTIONS
    if not isinstance(options, dict):
        return f'OPTIONS must be a dict of name -> OptionSpec, got {type(options).__name__}'
    used = set(parameters)
    for option, spec in options.items():
        if not isinstance(option, str) or not NAME.match(option):
            return (f'option name {option!r} must be lower-case letters, digits and '
                    'underscores, starting with a letter')
        if not isinstance(spec, OptionSpec):
            return f'option {option!r} must be an OptionSpec, got {spec!r}'
        if not isinstance(spec.default, (bool, int, float)):
            return f'option {option!r}: the default must be a bool, int or float'
        if not isinstance(spec.default, bool) and not spec.low <= spec.high:
            return f'option {option!r}: low {spec.low!r} exceeds high {spec.high!r}'
        try:
            spec.check(name, option, spec.default)
        except ValueError as error:
            return f'option {option!r}: its default is refused: {error}'
        if f'{name}_{option}' in used:
            return f'its parameter {name}_{option} is already a parameter of another strategy'
    return ''


def parameter_names(strategies: dict[str, type[Strategy]]) -> set[str]:
    """Every '<strategy>_<option>' parameter of these strategies."""
    return {f'{name}_{option}' for name, cls in strategies.items() for option in cls.OPTIONS}


def discover(builtin: dict[str, type[Strategy]], entry_points: Iterable[Any] | None = None
             ) -> tuple[dict[str, type[Strategy]], list[PluginProblem], dict[str, str]]:
    """The usable plugin strategies (sorted by name), the problems of the others and the
    distribution ('name version') of each usable one.

    Args:
        builtin: the registered strategies (a plugin may not take their names).
        entry_points: the entry points to examine (default: the installed ones of
            :data:`GROUP`); each has ``name``, ``value``, ``load()`` and ``dist``.
    """
    if entry_points is None:
        from importlib.metadata import entry_points as installed
        entry_points = installed(group=GROUP)
    points = sorted(entry_points, key=lambda ep: (ep.name, _distribution(ep), ep.value))
    counts: dict[str, int] = {}
    for point in points:
        counts[point.name] = counts.get(point.name, 0) + 1
    found: dict[str, type[Strategy]] = {}
    origins: dict[str, str] = {}
    problems = []
    for point in points:
        if counts[point.name] > 1:
            reason = (f'{counts[point.name]} installed plugins are named {point.name!r}; none '
                      'of them is used')
        else:
            try:
                obj = point.load()
            except Exception as error:          # a broken plugin must not break the package
                reason = f'cannot be imported: {_one_line(error)}'
            else:
                reason = check_plugin(point.name, obj, {*builtin, *found},
                                      parameter_names({**builtin, **found}))
                if not reason:
                    found[point.name] = obj
                    origins[point.name] = _distribution(point)
                    continue
        problems.append(PluginProblem(point.name, point.value, _distribution(point), reason))
    return found, problems, origins


def _distribution(point: Any) -> str:
    dist = getattr(point, 'dist', None)
    return f'{dist.name} {dist.version}' if dist is not None else 'an unknown distribution'


class StrategyRegistry(MutableMapping[str, type[Strategy]]):
    """name -> strategy class: the built-in strategies in their order, then the plugins sorted
    by name (found on first need; :attr:`problems` lists the plugins left out)."""

    def __init__(self, builtin: dict[str, type[Strategy]]) -> None:
        self._builtin = dict(builtin)
        self._table: dict[str, type[Strategy]] | None = None
        self.problems: list[PluginProblem] = []
        self._origins: dict[str, str] = {}

    @property
    def builtin(self) -> tuple[str, ...]:
        """Names of the built-in strategies."""
        return tuple(self._builtin)

    def _all(self) -> dict[str, type[Strategy]]:
        if self._table is None:
            plugins, self.problems, self._origins = discover(self._builtin)
            self._table = {**self._builtin, **plugins}
            if os.environ.get(QUIET_ENV, '1') != '0':
                for problem in self.problems:
                    print(problem, file=sys.stderr)
        return self._table

    def plugins(self) -> tuple[str, ...]:
        """Names of the usable plugin strategies, sorted."""
        return tuple(name for name in self._all() if name not in self._builtin)

    def left_out(self) -> dict[str, str]:
        """name -> why, of the plugins left out (each problem's reason)."""
        self._all()
        return {problem.name: problem.reason for problem in self.problems}

    def origin(self, name: str) -> str:
        """The distribution ('name version') a plugin strategy comes from; '' for the
        built-in ones (and for names not registered)."""
        self._all()
        return self._origins.get(name, '')

    def rediscover(self) -> None:
        """Forget the plugins found so far; the next need looks again (after an install)."""
        self._table = None
        self.problems = []
        self._origins = {}

    def __getitem__(self, name: str) -> type[Strategy]:
        if self._table is None and name in self._builtin:
            return self._builtin[name]
        return self._all()[name]

    def __contains__(self, name: object) -> bool:
        if self._table is None and name in self._builtin:
            return True
        return name in self._all()

    def __iter__(self) -> Iterator[str]:
        return iter(tuple(self._all()))

    def __len__(self) -> int:
        return len(self._all())

    def __setitem__(self, name: str, cls: type[Strategy]) -> None:
        self._all()[name] = cls

    def __delitem__(self, name: str) -> None:
        del self._all()[name]

    def __repr__(self) -> str:
        return f'StrategyRegistry({list(self)})'


__all__ = ['GROUP', 'PluginProblem', 'StrategyRegistry', 'check_plugin', 'discover']
