"""Every motion strategy behind one interface (see :mod:`.base`), registered by name.

The names below are the stable Strategy API a plugin strategy builds on (docs/plugins.md);
:data:`STRATEGIES` holds the built-in strategies, then the plugins of the entry-point group
``formopt_ros.strategies`` (:mod:`.registry`).
"""
from __future__ import annotations

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.strategies.base import (
    BatchContext, BatchPlan, EstimatorView, OptionSpec, PlanContext, Solution, StepRecord,
    Strategy, make_solution)
from formopt_ros.core.strategies.baselines import (
    ActiveSideSteps, ConstrainedRandomMotion, GridSearch, MaintainFormation)
from formopt_ros.core.strategies.lookahead import RecedingHorizon
from formopt_ros.core.strategies.periodic import PeriodicPattern
from formopt_ros.core.strategies.ram import RelaxedAlgebraicMethod
from formopt_ros.core.strategies.registry import GROUP, StrategyRegistry
from formopt_ros.core.strategies.rq import RayleighQuotient

#: Version of the Strategy API of docs/plugins.md: raised only when a change could break a
#: plugin written against it.
STRATEGY_API = 1
_BUILTIN_CLASSES = (MaintainFormation, ConstrainedRandomMotion, ActiveSideSteps, GridSearch,
                    RelaxedAlgebraicMethod, RayleighQuotient, PeriodicPattern, RecedingHorizon)
#: Names of the built-in strategies, in the order of the paper's comparison, then ours.
BUILTIN = tuple(cls.name for cls in _BUILTIN_CLASSES)
#: name -> strategy class: the built-in strategies, then the plugins sorted by name.
STRATEGIES = StrategyRegistry({cls.name: cls for cls in _BUILTIN_CLASSES})


def make_strategy(name: str, **options: object) -> Strategy:
    """A new strategy object; InvalidInput for an unknown name or option, or a bad value."""
    if not isinstance(name, str) or name not in STRATEGIES:
        raise InvalidInput('method', f'must be one of {tuple(STRATEGIES)}, got {name!r}')
    return STRATEGIES[name](**options)


__all__ = ['BUILTIN', 'BatchContext', 'BatchPlan', 'EstimatorView', 'GROUP', 'OptionSpec',
           'PlanContext', 'Problem', 'ProblemBatch', 'STRATEGIES', 'STRATEGY_API', 'Solution',
           'StepRecord', 'Strategy', 'make_solution', 'make_strategy']
