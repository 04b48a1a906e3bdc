"""One follower's brain: the EKF and its motion strategy (paper Secs. III-B to III-D), and the
session that feeds it timestamped inputs (the estimator node and offline replay both use it).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import numpy as np

from formopt_ros.core.cost import Problem, weighted_trace
from formopt_ros.core.model import ekf_update, normalized_estimation_error, propagate
from formopt_ros.core.protocol import (
    SUBSTEPS, MotionCommand, Timebase, command_velocities, held_leader_motion, motion_commands)
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.solver import timed_plan
from formopt_ros.core.stepper import ReadyStep, StepAssembler
from formopt_ros.core.strategies import (
    EstimatorView, PlanContext, Solution, StepRecord, Strategy)

#: Processed steps a strategy can look back on through ``EstimatorView.history``.
HISTORY_LENGTH = 256


@dataclass(frozen=True)
class StepPlan:
    """The decision for one measurement step: where to go and how to drive there."""

    step: int
    solution: Solution
    command: MotionCommand


def driven_prior(scenario: Scenario, x: np.ndarray, P: np.ndarray, target: np.ndarray,
                 leader: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Covariance after driving from (x, P) to ``target`` with the protocol's commands under the
    leader velocities ``leader`` (one (v, omega) per sub-step), before the update.

    Args:
        scenario: dt and the odometry noise.
        x, P: posterior pose (3,) and covariance (3, 3), or batches (T, 3) and (T, 3, 3).
        target: position (2,) m, or one per pose (T, 2).
        leader: expected (v_L m/s, omega_L rad/s) per sub-step.

    Returns:
        The prior covariance, shape of P.
    """
    s = scenario
    speed, turn_rate = command_velocities(x, target, s.dt, leader[0][0], leader[0][1])
    for j, (v, omega) in enumerate(((0.0, turn_rate), (speed, leader[0][1]))[:SUBSTEPS]):
        x, P = propagate(x, P, v, omega, s.dt, leader[j][0], leader[j][1], s.sigma_v,
                         s.sigma_omega)
    return P


class EstimatorPlanner:
    """The follower's EKF and motion strategy.

    Args:
        scenario: the run's settings.
        strategy: a strategy object (``make_strategy(name, **options)``); it may keep state.
        rng: random stream of randomised strategies (CRM).
    """

    def __init__(self, scenario: Scenario, strategy: Strategy,
                 rng: np.random.Generator | None = None) -> None:
        self.scenario = scenario
        self.strategy = strategy
        self.rng = rng
        self.x, self.P = scenario.initial_estimate()
        self.history: deque[StepRecord] = deque(maxlen=HISTORY_LENGTH)
        self._target = scenario.slot
        self._slot = scenario.slot

    def prior_for(self, target: np.ndarray,
                  leader: tuple[tuple[float, float], ...]) -> np.ndarray:
        """Covariance (3, 3) after driving to ``target`` (2,) with the protocol's commands under
        the leader velocities ``leader`` (one (v, omega) per sub-step), before the update."""
        return driven_prior(self.scenario, self.x, self.P, target, leader)

    def plan(self, step: int, leader: tuple[tuple[float, float], ...]) -> StepPlan:
        """Choose the position for measurement step ``step`` (1-based) and its commands.

        Args:
            step: the measurement step the motion leads to.
            leader: expected (v_L m/s, omega_L rad/s) per sub-step of the motion.
        """
        s = self.scenario
        prior = self.prior_for(self._slot, leader)     # the paper's planning prior (Sec. III-D)
        problem = Problem(prior, self._slot, s.r, s.sigma, s.measurement, False)
        view = EstimatorView(self.x, self.P, self.history,
                             lambda target: self.prior_for(target, leader))
        context = PlanContext(step, leader, self.rng, view, s.dt, s.sigma_v, s.sigma_omega)
        solution = timed_plan(self.strategy, problem, context)
        self._target = solution.p
        command = motion_commands(self.x, solution.p, s.dt, leader[0][0], leader[0][1])
        return StepPlan(step, solution, command)

    def propagate(self, v_f: float, omega_f: float, v_l: float, omega_l: float) -> None:
        """EKF propagation over one sub-step with odometry (v_f, omega_f) and leader velocity."""
        s = self.scenario
        self.x, self.P = propagate(self.x, self.P, v_f, omega_f, s.dt, v_l, omega_l, s.sigma_v,
                                   s.sigma_omega)

    def update(self, step: int, z: float, variance: float | None = None) -> tuple[float, float]:
        """EKF update with a range (m) or bearing (rad) measurement of step ``step``.

        Returns:
            (innovation, innovation variance S).
        """
        s = self.scenario
        variance = s.sigma ** 2 if variance is None else variance
        self.x, self.P, innovation, S = ekf_update(self.x, self.P, z, s.measurement, variance)
        self.history.append(StepRecord(step, self.x, self.P, self._target))
        return innovation, S

    def weighted_trace(self) -> float:
        """tr(W P W) of the current covariance, m^2."""
        return weighted_trace(self.P, self._slot)


@dataclass(frozen=True)
class StepOutcome:
    """What one processed step produced: the posterior and the next decision."""

    step: int
    stamp_ns: int
    x: np.ndarray                  # (3,) posterior
    P: np.ndarray                  # (3, 3) posterior covariance
    weighted_trace: float          # tr(W P W), m^2
    innovation: float
    plan: StepPlan | None          # the decision for step + 1 (None once the run is done)
    skipped: int = 0


@dataclass
class Counters:
    """Inputs accepted and refused by a session."""

    accepted_measurements: int = 0
    rejected_measurements: int = 0
    rejected_odometry: int = 0
    skipped_steps: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain dict (for JSON and the status message)."""
        return dict(self.__dict__)


@dataclass
class EstimatorSession:
    """Feeds timestamped inputs to an :class:`EstimatorPlanner` through a
    :class:`~formopt_ros.core.stepper.StepAssembler`, step after step.

    Attributes:
        estimator: the EKF and strategy.
        assembler: which inputs make which step.
        steps: stop planning after this many steps (0: never).
    """

    estimator: EstimatorPlanner
    assembler: StepAssembler
    steps: int = 0
    counters: Counters = field(default_factory=Counters)
    nees: dict[int, float] = field(default_factory=dict)
    last_reason: str = ''
    last_stamp_ns: int | None = None
    final_truth: np.ndarray | None = None
    _truth: dict[int, np.ndarray] = field(default_factory=dict, repr=False)
    _posteriors: dict[int, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, repr=False)

    @classmethod
    def create(cls, scenario: Scenario, strategy: Strategy, rng: np.random.Generator | None,
               lockstep: bool, steps: int = 0) -> 'EstimatorSession':
        """A session at step 0 for ``scenario``."""
        assembler = StepAssembler(lockstep, Timebase.from_dt(scenario.dt),
                                  scenario.leader.velocity(0, scenario.dt))
        return cls(EstimatorPlanner(scenario, strategy, rng), assembler, steps)

    @property
    def step(self) -> int:
        """The last processed step (0 before the first)."""
        return self.assembler.next_step - 1

    @property
    def finished(self) -> bool:
        """True once ``steps`` steps are processed (never when steps is 0)."""
        return bool(self.steps) and self.step >= self.steps

    def plan_next(self) -> StepPlan:
        """The decision for the step after the last processed one."""
        return self.estimator.plan(self.step + 1, held_leader_motion(self.assembler.latest_leader))

    def add_follower_odometry(self, stamp_ns: int, v: float, omega: float,
                              now_ns: int | None = None) -> str | None:
        """Follower odometry of one sub-step; the refusal reason, or None."""
        return self._count(self.assembler.add_follower_odometry(stamp_ns, v, omega, now_ns),
                           'rejected_odometry')

    def add_leader_odometry(self, stamp_ns: int, v: float, omega: float,
                            now_ns: int | None = None) -> str | None:
        """Leader odometry of one sub-step; the refusal reason, or None."""
        return self._count(self.assembler.add_leader_odometry(stamp_ns, v, omega, now_ns),
                           'rejected_odometry')

    def add_measurement(self, step: int, stamp_ns: int, value: float, variance: float,
                        now_ns: int | None = None) -> str | None:
        """The measurement of ``step``; the refusal reason, or None."""
        reason = self._count(self.assembler.add_measurement(step, stamp_ns, value, variance,
                                                            now_ns), 'rejected_measurements')
        if reason is None:
            self.counters.accepted_measurements += 1
        return reason

    def reject(self, counter: str, reason: str) -> str:
        """Count an input refused before it reached the session (e.g. malformed)."""
        return self._count(reason, counter) or reason

    def _count(self, reason: str | None, counter: str) -> str | None:
        if reason is not None:
            setattr(self.counters, counter, getattr(self.counters, counter) + 1)
            self.last_reason = reason
        return reason

    def add_truth(self, stamp_ns: int, pose: np.ndarray) -> None:
        """Ground truth (evaluation only): NEES of the posterior with the same stamp."""
        self._truth[stamp_ns] = np.asarray(pose, dtype=float)
        self._evaluate(stamp_ns)

    def _evaluate(self, stamp_ns: int) -> None:
        if stamp_ns in self._truth and stamp_ns in self._posteriors:
            x, P = self._posteriors.pop(stamp_ns)
            truth = self._truth.pop(stamp_ns)
            self.nees[stamp_ns] = normalized_estimation_error(truth, x, P)
            if stamp_ns == self.last_stamp_ns:
                self.final_truth = truth

    def advance(self) -> list[StepOutcome]:
        """Process every ready step: propagate, update, plan the next one (until finished)."""
        out = []
        while not self.finished:
            ready = self.assembler.pop_ready()
            if ready is None:
                break
            out.append(self._process(ready))
        return out

    def _process(self, ready: ReadyStep) -> StepOutcome:
        estimator = self.estimator
        for m in ready.motions:
            estimator.propagate(m.v_f, m.omega_f, m.v_l, m.omega_l)
        innovation, _ = estimator.update(ready.step, ready.value, ready.variance)
        self.counters.skipped_steps += ready.skipped
        self.last_stamp_ns, self.final_truth = ready.stamp_ns, None
        self._posteriors[ready.stamp_ns] = (estimator.x, estimator.P)
        for old in [t for t in self._posteriors if t < ready.stamp_ns]:
            del self._posteriors[old]       # a truth that never came: no NEES for that step
        for old in [t for t in self._truth if t < ready.stamp_ns]:
            del self._truth[old]
        self._evaluate(ready.stamp_ns)
        plan = None if self.finished else self.plan_next()
        return StepOutcome(ready.step, ready.stamp_ns, estimator.x, estimator.P,
                           estimator.weighted_trace(), innovation, plan, ready.skipped)

    def mean_nees(self) -> float | None:
        """Mean NEES over the steps with known truth (None without any)."""
        return float(np.mean(list(self.nees.values()))) if self.nees else None
