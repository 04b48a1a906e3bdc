"""The session that feeds an :class:`~formopt_ros.core.estimator.EstimatorPlanner` timestamped
inputs step after step (the estimator node and offline replay both use it): plausibility
refusals counted, range-bearing parts joined, NEES against a truth where one is known."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from formopt_ros.core.consistency import ConsistencyWatch
from formopt_ros.core.estimator import (
    INNOVATION_GATE, EstimatorPlanner, InputBounds, StepPlan, UpdateResult)
from formopt_ros.core.model import BEARING, RANGE, RANGE_BEARING, normalized_estimation_error
from formopt_ros.core.protocol import Timebase, held_leader_motion, step_substeps
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.stepper import ReadyStep, StepAssembler
from formopt_ros.core.strategies import Strategy


@dataclass(frozen=True)
class StepOutcome:
    """What one processed step produced: the posterior and the next decision."""

    step: int
    stamp_ns: int
    x: np.ndarray                  # (3,) posterior
    P: np.ndarray                  # (3, 3) posterior covariance
    weighted_trace: float          # tr(W P W), m^2
    update: UpdateResult           # the measurement's effect (gated or used)
    plan: StepPlan | None          # the decision for step + 1 (None once the run is done)
    skipped: int = 0


@dataclass
class Counters:
    """Inputs accepted and refused by a session."""

    accepted_measurements: int = 0
    rejected_measurements: int = 0
    rejected_odometry: int = 0
    skipped_steps: int = 0
    gated_measurements: int = 0          # refused by the innovation gate
    covariance_inflations: int = 0       # re-openings after GATE_PATIENCE gated in a row
    foreign_messages: int = 0            # messages of another run (another run_id)
    filled_substeps: int = 0             # hold sub-steps for odometry lost while down

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
        watch: the consistency watch, fed every measurement's NIS (gated or used) and every
            step's NEES where the truth is known (:mod:`formopt_ros.core.consistency`).
    """

    estimator: EstimatorPlanner
    assembler: StepAssembler
    steps: int = 0
    counters: Counters = field(default_factory=Counters)
    nees_sum: float = 0.0
    nees_count: int = 0
    last_reason: str = ''
    last_stamp_ns: int | None = None
    final_truth: np.ndarray | None = None
    watch: ConsistencyWatch = field(default_factory=ConsistencyWatch)
    _truth: dict[int, np.ndarray] = field(default_factory=dict, repr=False)
    _posteriors: dict[int, tuple[np.ndarray, np.ndarray]] = field(
        default_factory=dict, repr=False)
    _bounds: InputBounds | None = field(default=None, repr=False)
    # range-bearing: the parts of a step's measurement received so far, {step: {kind: (stamp
    # ns, value, variance)}}
    _parts: dict[int, dict[str, tuple[int, float, float]]] = field(default_factory=dict,
                                                                   repr=False)
    _plan: StepPlan | None = field(default=None, repr=False)      # the last plan_next()
    # lockstep: the finite refused inputs seen (kind, stamp, values), whose repeat stands in
    _refused: set[tuple[object, ...]] = field(default_factory=set, repr=False)
    # the last accepted twist of each robot (lockstep: carried over a refused one)
    _twists: dict[str, tuple[float, float]] = field(
        default_factory=lambda: {'follower': (0.0, 0.0), 'leader': (0.0, 0.0)}, repr=False)

    @property
    def bounds(self) -> InputBounds:
        """The plausibility bounds of the scenario."""
        if self._bounds is None:
            self._bounds = InputBounds.from_scenario(self.estimator.scenario)
        return self._bounds

    @classmethod
    def create(cls, scenario: Scenario, strategy: Strategy, rng: np.random.Generator | None,
               lockstep: bool, steps: int = 0) -> 'EstimatorSession':
        """A session at step 0 for ``scenario``."""
        assembler = StepAssembler(lockstep, Timebase.from_dt(scenario.dt),
                                  scenario.leader.velocity(0, scenario.dt))
        session = cls(EstimatorPlanner(scenario, strategy, rng), assembler, steps)
        session._twists['leader'] = scenario.leader.velocity(0, scenario.dt)
        return session

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
        self._plan = self.estimator.plan(self.step + 1,
                                         held_leader_motion(self.assembler.latest_leader))
        return self._plan

    def _repeated(self, refused: tuple[object, ...]) -> bool:
        """Lockstep: whether this finite refused input (kind, stamp and values) came before:
        a source that repeats it will not send another (an injected message that a good one
        follows is refused once and harms nothing)."""
        values = [v for v in refused if isinstance(v, float)]
        if not self.assembler.lockstep or not all(math.isfinite(v) for v in values):
            return False
        seen = refused in self._refused
        self._refused.add(refused)
        return seen

    def _stand_in(self, robot: str, stamp_ns: int) -> tuple[float, float]:
        """The twist a refused lockstep odometry message of ``robot`` is replaced with."""
        substep = self.assembler.timebase.substep_ending_at(stamp_ns)
        plan = self._plan
        if robot == 'follower' and plan is not None and substep is not None and \
                substep in step_substeps(plan.step):
            j = substep - step_substeps(plan.step)[0]
            return float(plan.command.linear[j]), float(plan.command.angular[j])
        return self._twists[robot]

    def add_odometry(self, robot: str, stamp_ns: int, v: float, omega: float,
                     now_ns: int | None = None) -> str | None:
        """Odometry of one sub-step of robot 'follower' or 'leader'; the refusal reason, or
        None. Lockstep: an implausible finite twist is refused (counted); when its source
        sends it again (a simulator with absurd noise repeats its step on a resent
        waypoint), its sub-step carries another instead, so that the step is not waited
        for in vain: the follower's commanded twist of that sub-step (the leader's, or one
        off the planned step: the robot's last accepted twist)."""
        problem = self.bounds.odometry_problem(v, omega)
        if problem is not None:
            refusal = self.reject('rejected_odometry', f'{robot} odometry {problem}')
            if self._repeated(('odometry', robot, stamp_ns, v, omega)):
                self.assembler.add_odometry(robot, stamp_ns, *self._stand_in(robot, stamp_ns),
                                            now_ns)
            return refusal
        reason = self._count(self.assembler.add_odometry(robot, stamp_ns, v, omega, now_ns),
                             'rejected_odometry')
        if reason is None:
            self._twists[robot] = (v, omega)
        return reason

    def add_measurement(self, step: int, stamp_ns: int, value: float, variance: float,
                        now_ns: int | None = None, kind: str | None = None) -> str | None:
        """The measurement of ``step`` (``kind``: the scenario's, or for a range-bearing
        follower 'range' or 'bearing', one part of the step's measurement); the refusal
        reason, or None.

        A range-bearing step goes to the assembler once its parts are in (the range, and the
        bearing on the steps that have one, ``Scenario.bearing_at``), as z = [d, beta] with
        both stamps equal; in realtime a part of a later step sends an earlier incomplete step
        on with what it has (NaN for the missing part). Lockstep: a finite value outside the
        plausibility bounds (a simulator with absurd noise: a negative range) is refused
        (counted); sent again by its source (a simulator repeats its step on a resent
        waypoint), its step goes on without it (no update), instead of waiting for good."""
        scenario = self.estimator.scenario
        kind = scenario.measurement if kind is None else kind
        stacked = scenario.measurement == RANGE_BEARING
        if kind != scenario.measurement and not (stacked and kind in (RANGE, BEARING)):
            return self.reject('rejected_measurements', f'measurement of kind {kind} for a '
                               f'{scenario.measurement} follower')
        if stacked and kind == BEARING and not scenario.bearing_at(step):
            return self.reject('rejected_measurements', f'a bearing at step {step}: this '
                               f'follower has one every {scenario.bearing_every} steps')
        problem = self.bounds.measurement_problem(kind, value, variance)
        if problem is not None:
            refusal = self.reject('rejected_measurements', f'measurement {problem}')
            if self._repeated(('measurement', kind, step, stamp_ns, value, variance)):
                # its step goes on without it (NaN: no update)
                if stacked:
                    self._add_part(step, stamp_ns, kind, math.nan, variance, now_ns)
                else:
                    self.assembler.add_measurement(step, stamp_ns, math.nan, variance, now_ns)
            return refusal
        if stacked:
            reason = self._add_part(step, stamp_ns, kind, value, variance, now_ns)
        else:
            reason = self._count(self.assembler.add_measurement(step, stamp_ns, value, variance,
                                                                now_ns), 'rejected_measurements')
        if reason is None:
            self.counters.accepted_measurements += 1
        return reason

    def _add_part(self, step: int, stamp_ns: int, kind: str, value: float, variance: float,
                  now_ns: int | None) -> str | None:
        """One part of a range-bearing step (see :meth:`add_measurement`)."""
        parts = self._parts.setdefault(step, {})
        if kind in parts:
            return self.reject('rejected_measurements', f'a {kind} of step {step} is already '
                               'waiting')
        if parts and next(iter(parts.values()))[0] != stamp_ns:
            return self.reject('rejected_measurements', f'the {kind} of step {step} is stamped '
                               f'{stamp_ns} ns, its other part {next(iter(parts.values()))[0]}')
        parts[kind] = (stamp_ns, value, variance)
        reason = None
        if not self.assembler.lockstep:
            for older in sorted(k for k in self._parts if k < step):
                reason = self._send_parts(older, now_ns) or reason
        if len(parts) == (2 if self.estimator.scenario.bearing_at(step) else 1):
            reason = self._send_parts(step, now_ns) or reason
        return reason

    def _send_parts(self, step: int, now_ns: int | None) -> str | None:
        """The parts of ``step`` to the assembler as one measurement [d, beta] (NaN where a part
        is missing)."""
        parts = self._parts.pop(step)
        stamp = next(iter(parts.values()))[0]
        nan = (stamp, math.nan, math.nan)
        (_, d, var_d), (_, beta, var_beta) = parts.get(RANGE, nan), parts.get(BEARING, nan)
        return self._count(self.assembler.add_measurement(
            step, stamp, np.array([d, beta]), (var_d, var_beta), now_ns), 'rejected_measurements')

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
            nees = normalized_estimation_error(truth, x, P)
            self.nees_sum += nees
            self.nees_count += 1
            self.watch.add_nees(nees, self.step)
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
        update = estimator.update(ready.step, ready.value, ready.variance)
        for part in update.nis_parts() if update.measured else ():
            self.watch.add_nis(part, not update.used, ready.step)
        if not update.measured:
            pass                            # refused before it came (counted there)
        elif not update.used:
            self.reject('gated_measurements', f'measurement of step {ready.step} gated: '
                        f'normalised innovation {update.nis:.4g} > {INNOVATION_GATE:g}')
        elif update.inflation > 1.0:
            self.counters.covariance_inflations += 1
        self.counters.skipped_steps += ready.skipped
        self.counters.filled_substeps += ready.filled
        self.last_stamp_ns, self.final_truth = ready.stamp_ns, None
        self._posteriors[ready.stamp_ns] = (estimator.x, estimator.P)
        for old in [t for t in self._posteriors if t < ready.stamp_ns]:
            del self._posteriors[old]       # a truth that never came: no NEES for that step
        for old in [t for t in self._truth if t < ready.stamp_ns]:
            del self._truth[old]
        self._evaluate(ready.stamp_ns)
        plan = None if self.finished else self.plan_next()
        return StepOutcome(ready.step, ready.stamp_ns, estimator.x, estimator.P,
                           estimator.weighted_trace(), update, plan, ready.skipped)

    def mean_nees(self) -> float | None:
        """Mean NEES over the steps with known truth (None without any)."""
        return self.nees_sum / self.nees_count if self.nees_count else None
