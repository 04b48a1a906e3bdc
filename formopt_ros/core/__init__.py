"""Pure core of formopt_ros (numpy and scipy only): model, cost, strategies, simulation."""
from formopt_ros.core.cost import Problem, weighted_trace
from formopt_ros.core.solver import METHODS, Solution, solve

__all__ = ['METHODS', 'Problem', 'Solution', 'solve', 'weighted_trace']
