"""Every motion strategy behind one interface (see :mod:`.base`), registered by name."""
from __future__ import annotations

from formopt_ros.core.strategies.base import (
    BatchContext, BatchPlan, EstimatorView, OptionSpec, PlanContext, Solution, StepRecord,
    Strategy, make_solution)
from formopt_ros.core.strategies.baselines import (
    ActiveSideSteps, ConstrainedRandomMotion, GridSearch, MaintainFormation)
from formopt_ros.core.strategies.periodic import PeriodicPattern
from formopt_ros.core.strategies.ram import RelaxedAlgebraicMethod
from formopt_ros.core.strategies.rq import RayleighQuotient

#: name -> strategy class, in the order of the paper's comparison, then ours beyond it.
STRATEGIES: dict[str, type[Strategy]] = {
    cls.name: cls for cls in (MaintainFormation, ConstrainedRandomMotion, ActiveSideSteps,
                              GridSearch, RelaxedAlgebraicMethod, RayleighQuotient,
                              PeriodicPattern)}


def make_strategy(name: str, **options: object) -> Strategy:
    """A new strategy object; ValueError for an unknown name or option, or a bad value."""
    if not isinstance(name, str) or name not in STRATEGIES:
        raise ValueError(f'method must be one of {tuple(STRATEGIES)}, got {name!r}')
    return STRATEGIES[name](**options)


__all__ = ['BatchContext', 'BatchPlan', 'EstimatorView', 'OptionSpec', 'PlanContext',
           'STRATEGIES', 'Solution', 'StepRecord', 'Strategy', 'make_solution', 'make_strategy']
