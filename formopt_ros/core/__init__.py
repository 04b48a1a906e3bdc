"""Pure core of formopt_ros (numpy, scipy): model, cost, strategies, protocol, simulation."""
from formopt_ros.core.cost import Problem
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.scenario import LeaderPath, Scenario
from formopt_ros.core.solver import METHODS, solve
from formopt_ros.core.strategies import STRATEGIES, PlanContext, Solution, make_strategy

__all__ = ['LeaderPath', 'METHODS', 'PlanContext', 'Problem', 'STRATEGIES', 'Scenario',
           'Solution', 'make_strategy', 'solve', 'weighted_trace']
