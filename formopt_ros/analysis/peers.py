"""General-purpose optimisers a user might pick for problem Pi_1: SciPy SLSQP and CasADi + IPOPT.

They see the problem as a user would pose it: minimise tr(W P_post W) (the formula of
:mod:`formopt_ros.core.cost`, reused symbolically for CasADi) over the disc
|p - p_o|^2 <= r^2, from p_o or from several starts, with default or tightened tolerances.
Being local methods, they may stop at a boundary or interior point that is not the global
optimum; ``formopt-bench`` counts how often against the certified optimum.

CasADi is optional (``pip install .[peers]``); :func:`casadi_available` says whether it is.
"""
from __future__ import annotations

import importlib.util
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.optimize import minimize

from formopt_ros.core.cost import Problem
from formopt_ros.core.formulas import quotient_gain

#: Starts of the multi-start variants: p_o and points at STARTS_RADIUS r around it.
MULTI_STARTS = 8
STARTS_RADIUS = 0.7
#: IPOPT options of the 'tuned' variants (the defaults stop at tol = 1e-8, absolute).
IPOPT_TUNED = {'tol': 1e-14, 'acceptable_tol': 1e-14, 'max_iter': 500}


def starts(problem: Problem, count: int) -> np.ndarray:
    """p_o and count - 1 points at STARTS_RADIUS r around it, shape (count, 2), m."""
    angle = 2.0 * math.pi * np.arange(count - 1) / max(count - 1, 1)
    ring = problem.p_o + STARTS_RADIUS * problem.r * np.stack([np.cos(angle), np.sin(angle)], 1)
    return np.vstack([problem.p_o, ring])


def _best(problem: Problem, points: list[np.ndarray]) -> np.ndarray:
    """The cheapest feasible point (projected onto the disc if a solver overstepped it)."""
    projected = []
    for p in points:
        offset = np.asarray(p, dtype=float) - problem.p_o
        distance = math.hypot(*offset)
        projected.append(problem.p_o + offset * min(1.0, problem.r / distance)
                         if distance > 0 else problem.p_o.copy())
    costs = problem.cost(np.array(projected))
    return projected[int(np.argmin(costs))]


def slsqp(problem: Problem, count: int = 1) -> np.ndarray:
    """SciPy SLSQP (default options, finite-difference gradients) from ``count`` starts."""
    r2 = problem.r * problem.r

    def objective(z: np.ndarray) -> float:
        return float(problem.cost(z))

    def inside(z: np.ndarray) -> float:
        return float(r2 - (z[0] - problem.p_o[0]) ** 2 - (z[1] - problem.p_o[1]) ** 2)

    results = [minimize(objective, start, method='SLSQP',
                        constraints=[{'type': 'ineq', 'fun': inside}]).x
               for start in starts(problem, count)]
    return _best(problem, results)


def casadi_available() -> bool:
    """True when ``import casadi`` would work."""
    return importlib.util.find_spec('casadi') is not None


@dataclass
class Ipopt:
    """CasADi + IPOPT on a parametric NLP built once per measurement kind (parameters: the
    gain's coefficients, tr(W P W), p_o and r), so a solve pays no symbolic set-up.

    Attributes:
        measurement: 'range' or 'bearing'.
        options: IPOPT options on top of print_level 0 (empty: IPOPT's defaults).
    """

    measurement: str
    options: dict[str, Any] = field(default_factory=dict)
    _solver: Any = field(default=None, init=False, repr=False)
    _terms: int = field(default=0, init=False, repr=False)

    def __post_init__(self) -> None:
        import casadi
        z = casadi.SX.sym('z', 2)
        k = 4 if self.measurement == 'range' else 6
        num, den = casadi.SX.sym('num', k), casadi.SX.sym('den', k)
        base, slot, r = casadi.SX.sym('base'), casadi.SX.sym('slot', 2), casadi.SX.sym('r')
        gain = quotient_gain(self.measurement, (tuple(num[i] for i in range(k)),
                                                tuple(den[i] for i in range(k))), z[0], z[1])
        offset = z - slot
        nlp = {'x': z, 'p': casadi.vertcat(num, den, base, slot, r), 'f': base - gain,
               'g': casadi.dot(offset, offset) - r * r}
        self._solver = casadi.nlpsol('pi1', 'ipopt', nlp, {
            'ipopt': {'print_level': 0, 'sb': 'yes', **self.options}, 'print_time': False})
        self._terms = k

    def solve(self, problem: Problem, count: int = 1) -> np.ndarray:
        """The best of IPOPT's answers from ``count`` starts."""
        num, den = problem.coefficients
        parameters = np.concatenate([num, den, [problem.base_cost], problem.p_o, [problem.r]])
        results = [np.asarray(self._solver(x0=start, p=parameters, lbg=-np.inf, ubg=0.0)['x'],
                              dtype=float).ravel() for start in starts(problem, count)]
        return _best(problem, results)


def peer_methods(measurement: str) -> dict[str, Callable[[Problem], np.ndarray]]:
    """name -> solver for the peers available here: 'slsqp' (from p_o), 'slsqp-8', and with
    CasADi 'ipopt' (from p_o, IPOPT defaults), 'ipopt-tuned' (tightened tolerances) and
    'ipopt-8' (tuned, 8 starts)."""
    methods: dict[str, Callable[[Problem], np.ndarray]] = {
        'slsqp': slsqp, f'slsqp-{MULTI_STARTS}': lambda p: slsqp(p, MULTI_STARTS)}
    if casadi_available():
        default, tuned = Ipopt(measurement), Ipopt(measurement, dict(IPOPT_TUNED))
        methods.update({'ipopt': default.solve, 'ipopt-tuned': tuned.solve,
                        f'ipopt-{MULTI_STARTS}': lambda p: tuned.solve(p, MULTI_STARTS)})
    return methods


__all__ = ['IPOPT_TUNED', 'Ipopt', 'MULTI_STARTS', 'casadi_available', 'peer_methods', 'slsqp',
           'starts']
