"""The strategy interface: ``Strategy(**options).plan(problem, context) -> Solution``.

A strategy is an object, created once per follower with its options (declared in ``OPTIONS``
with default, unit and admissible range, so nodes and commands expose them without special
cases), and asked once per measurement step for the next position. What changes from step to
step comes in a :class:`PlanContext`: the step index, the leader motion expected during the
step, the random stream and a read-only view of the estimator (its posterior, history and the
exact move-dependent prior), so a stateful, multi-step strategy needs no change in the
simulator or the nodes.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from formopt_ros.core.checks import InvalidInput, as_bool, as_integer, as_real
from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.model import EXACT
from formopt_ros.core.reach import Region
from formopt_ros.core.strategies.verify import exact_cost

if TYPE_CHECKING:
    from formopt_ros.core.scenario import Scenario


@dataclass(frozen=True)
class Solution:
    """The chosen next position, what it costs, how it was found and what was proved about it.

    Attributes:
        p: chosen position in the leader frame, shape (2,), m.
        cost: tr(W P_post W) after a measurement at p, m^2.
        cost_at_slot: the same cost at the formation slot p_o, m^2.
        method: strategy name.
        measurement: 'range' or 'bearing'.
        on_boundary: True when |p - p_o| = r (constraint active).
        candidates: number of critical or grid points examined.
        solve_time_s: wall time of the strategy, s (set by the solver).
        fallback: method used when the primary route could not certify its answer, else None.
        certificate: what was proved about p (RAM and RQ; 'none' for the other strategies):
            'interior-eigenvector' or 'boundary-bound' for a proof (checked in floating point
            with its rounding bounded, or in exact arithmetic when
            ``details['certificate_arithmetic'] == 'exact'``) that no feasible point is cheaper
            by more than ``details['certificate_gap']`` times ``cost`` (at most 2e-10),
            'all-critical-points' when every stationary point was enumerated by a polynomial
            root finder and p is the best of them (bearing: nor is a boundary sample or the
            slot), and an exact local search from p found no better point,
            'none' when nothing was proved (RQ and RAM then say why in ``details['reason']``;
            see :mod:`formopt_ros.core.strategies.certificate`).
        details: method-specific diagnostics (the certificate's gap, multiplier and residual).
    """

    p: np.ndarray
    cost: float
    cost_at_slot: float
    method: str
    measurement: str
    on_boundary: bool = False
    candidates: int = 1
    solve_time_s: float = 0.0
    fallback: str | None = None
    certificate: str = 'none'
    details: dict[str, Any] = field(default_factory=dict)

    def with_solve_time(self, seconds: float) -> 'Solution':
        """A copy with ``solve_time_s`` set (``dataclasses.replace`` costs microseconds)."""
        copy = object.__new__(Solution)
        values = self.__dict__.copy()
        values['solve_time_s'] = seconds
        object.__setattr__(copy, '__dict__', values)
        return copy


def make_solution(problem: Problem, p: np.ndarray | Sequence[float], method: str,
                  on_boundary: bool = False, candidates: int = 1, fallback: str | None = None,
                  details: dict[str, Any] | None = None, certificate: str = 'none',
                  gain: float | None = None) -> Solution:
    """A :class:`Solution` for point p (2,) with its cost and the cost at the slot.

    ``gain`` is the gain at p when the caller has it already (it must come from
    ``problem.gain_at``, so that ``cost`` equals ``problem.cost(p)``). A certificate that had
    to compute the exact cost (``details['exact_cost']``, where the formula's rounding
    is large) gives that value instead, and the cost at the slot is then exact too.
    """
    x, y = float(p[0]), float(p[1])
    base = problem.base_cost
    if details is not None and 'exact_cost' in details:
        cost, cost_at_slot = details['exact_cost'], exact_cost(problem, *problem.slot)
    else:
        cost = base - (problem.gain_at(x, y) if gain is None else gain)
        cost_at_slot = base - problem.gain_at(*problem.slot)
    # every field given: fill the frozen record directly (its __init__ costs 1.5 us)
    solution = object.__new__(Solution)
    object.__setattr__(solution, '__dict__', {
        'p': np.array((x, y)), 'cost': cost, 'cost_at_slot': cost_at_slot, 'method': method,
        'measurement': problem.measurement, 'on_boundary': on_boundary,
        'candidates': candidates, 'solve_time_s': 0.0, 'fallback': fallback,
        'certificate': certificate, 'details': {} if details is None else details})
    return solution


@dataclass(frozen=True)
class StepRecord:
    """One processed step of the estimator: its posterior and the position it had chosen."""

    step: int
    x: np.ndarray          # (3,) posterior [x, y, phi] in the leader frame
    P: np.ndarray          # (3, 3) posterior covariance
    target: np.ndarray     # (2,) position the step's motion aimed at, m


@dataclass(frozen=True)
class EstimatorView:
    """What a strategy may read of the estimator before choosing the next position.

    Attributes:
        x, P: current posterior (before the coming motion), shapes (3,) and (3, 3).
        history: the most recent processed steps, oldest first (bounded length).
        prior_for: target (2,) -> the exact prior covariance (3, 3) after driving to target
            with the protocol's commands under the expected leader motion.
    """

    x: np.ndarray
    P: np.ndarray
    history: Sequence[StepRecord]
    prior_for: Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class PlanContext:
    """Per-step information for a strategy.

    Attributes:
        step: the measurement step (1-based) the motion leads to.
        leader_velocities: expected (v_L m/s, omega_L rad/s) of the leader per sub-step.
        rng: random stream of randomised strategies (CRM).
        estimator: the estimator's state, or None for a one-off problem.
        dt: sub-step length, s.
        sigma_v, sigma_omega: odometry noise standard deviations, m/s and rad/s.
        kinematics: the motion model, 'exact' or 'euler' (core/model.py).
        region: the reachable set of the step (speed limit, safety distance), or None for the
            whole disc (the paper's protocol); see :mod:`formopt_ros.core.reach`.
        scenario: the run's scenario (its ``leader`` is the path the simulated leader drives),
            or None for a one-off problem.
    """

    step: int = 1
    leader_velocities: tuple[tuple[float, float], ...] = ((1.0, 0.0), (1.0, 0.0))
    rng: np.random.Generator | None = None
    estimator: EstimatorView | None = None
    dt: float = 0.05
    sigma_v: float = 0.2
    sigma_omega: float = 0.1
    kinematics: str = EXACT
    region: Region | None = None
    scenario: Scenario | None = None

    @property
    def leader_straight(self) -> bool:
        """True when the leader is expected to drive straight (the unobservable case)."""
        return all(omega == 0.0 for _, omega in self.leader_velocities)


@dataclass(frozen=True)
class BatchContext:
    """Per-step information for :meth:`Strategy.plan_batch`: a :class:`PlanContext` for T trials
    advanced together (same step and leader motion; one random stream per trial).

    Attributes:
        step: the measurement step (1-based) the motion leads to.
        leader_velocities: expected (v_L m/s, omega_L rad/s) of the leader per sub-step.
        rngs: the random stream of each trial (CRM draws from them as :meth:`Strategy.plan`
            would, trial by trial).
        dt: sub-step length, s.
        sigma_v, sigma_omega: odometry noise standard deviations, m/s and rad/s.
        kinematics: the motion model, 'exact' or 'euler' (core/model.py).
    """

    step: int
    leader_velocities: tuple[tuple[float, float], ...]
    rngs: Sequence[np.random.Generator]
    dt: float = 0.05
    sigma_v: float = 0.2
    sigma_omega: float = 0.1
    kinematics: str = EXACT

    def trial(self, t: int, estimator: 'EstimatorView | None' = None) -> PlanContext:
        """The :class:`PlanContext` of trial t."""
        return PlanContext(self.step, self.leader_velocities, self.rngs[t], estimator,
                           self.dt, self.sigma_v, self.sigma_omega, self.kinematics)


@dataclass(frozen=True)
class BatchPlan:
    """The decisions of :meth:`Strategy.plan_batch` for T trials.

    Attributes:
        p: chosen positions, shape (T, 2), m.
        fallback: per trial, True when the primary route could not certify its answer (RAM),
            shape (T,); None when the strategy has no fallback.
    """

    p: np.ndarray
    fallback: np.ndarray | None = None


@dataclass(frozen=True)
class OptionSpec:
    """One strategy option: default, meaning with unit, admissible closed range [low, high]."""

    default: float | int | bool
    description: str
    low: float = 0.0
    high: float = 1.0

    def check(self, strategy: str, name: str, value: object) -> float | int | bool:
        """The value as the option's type, or InvalidInput naming strategy and option."""
        field = f'{strategy} option {name}'
        if isinstance(self.default, bool):
            return as_bool(field, value)
        if isinstance(self.default, int):
            return as_integer(field, value, int(self.low), int(self.high))
        return as_real(field, value, self.low, self.high)


class Strategy:
    """Base class: options validated at construction, :meth:`plan` once per step."""

    #: Name used in configuration (``solve(method=...)``, the ``strategy`` parameter).
    name: ClassVar[str] = ''
    #: Options accepted by the constructor.
    OPTIONS: ClassVar[dict[str, OptionSpec]] = {}
    #: True when :meth:`plan` keeps no state between calls, so one object may serve every
    #: caller (``solve`` reuses one per method).
    stateless: ClassVar[bool] = True

    def __init__(self, **options: object) -> None:
        self.settings: dict[str, float | int | bool] = {}
        if not options and not self.OPTIONS:
            return
        unknown = sorted(set(options) - set(self.OPTIONS))
        if unknown:
            raise InvalidInput(f'method {self.name!r}', f'accepts options '
                               f'{sorted(self.OPTIONS)}, got unknown {unknown}')
        self.settings = {
            key: spec.check(self.name, key, options.get(key, spec.default))
            for key, spec in self.OPTIONS.items()}

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The next position for ``problem``: a :class:`Solution` with solve_time_s unset (the
        solver stamps it; a record returned again is copied first)."""
        raise NotImplementedError

    def plan_batch(self, problems: ProblemBatch, context: BatchContext) -> BatchPlan:
        """The next positions of T trials advanced together (the batched Monte Carlo engine).

        Optional. A strategy that overrides it promises that one object may serve all trials
        and that ``plan_batch(...).p[t]`` equals ``plan(problems.problem(t),
        context.trial(t)).p`` bit for bit (the engines' agreement test checks it). Strategies
        that do not override it (e.g. stateful ones that read ``context.estimator``) are run by
        the engine with one object per trial through :meth:`plan`.
        """
        raise NotImplementedError

    def prepare(self, scenario: Scenario) -> None:
        """Do once, before a run of ``scenario``, the work the first plan would otherwise pay
        for (a realtime node calls it before its first waypoint). Default: nothing."""

    @classmethod
    def vectorised(cls) -> bool:
        """True when the class overrides :meth:`plan_batch`."""
        return cls.plan_batch is not Strategy.plan_batch

    def __repr__(self) -> str:
        settings = ', '.join(f'{k}={v!r}' for k, v in self.settings.items())
        return f'{type(self).__name__}({settings})'
