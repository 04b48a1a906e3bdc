"""Batched Monte Carlo engine: all trials of a strategy advanced together as stacked arrays.

:func:`run_trials` is :func:`~formopt_ros.core.simulation.run_trial` (the per-trial reference,
which the ROS nodes equal) for many trials at once, and :func:`run_lanes` the same for several
strategies in one stack (every (strategy, trial) a lane, so numpy's per-call cost is shared):

* the random numbers are drawn per trial from ``trial_streams(seed, trial)`` in the order
  run_trial draws them (3 for the start, then per step (v, omega) per sub-step and z; numpy's
  Generator gives the same numbers in one call as in many);
* every step runs the same model functions (:mod:`~formopt_ros.core.model`,
  :func:`~formopt_ros.core.estimator.driven_prior`) on arrays of shape (T, ...): element-wise
  numpy arithmetic, libm calls element by element and stacked matrix products give every trial
  the bits it gets alone;
* the strategy is asked once per step for all trials through ``Strategy.plan_batch`` when its
  class provides one (MTF, CRM, MME, GBS, RAM, RQ), else trial by trial through
  ``Strategy.plan``, with one strategy object, estimator view (posterior, history, exact
  move-dependent prior) and random stream per trial, which is how a stateful strategy runs;
  under a speed limit or a safety distance every strategy runs trial by trial, each planning
  inside its own reachable set (:mod:`~formopt_ros.core.reach`).
  A range-bearing scenario plans every strategy trial by trial (its problems are
  :class:`~formopt_ros.core.stacked.StackedProblem`, which have no batch form).

A test checks agreement with run_trial to 1e-9 for every strategy, both sensors and a turning
leader; in practice the numbers are identical.
"""
from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from formopt_ros.core.cost import Problem, ProblemBatch
from formopt_ros.core.estimator import (
    HISTORY_LENGTH, driven_prior, innovation_gate, planning_problem, stacked_innovation_gate)
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.model import (
    RANGE, RANGE_BEARING, ekf_update, ekf_update_stacked, normalized_estimation_error, propagate)
from formopt_ros.core.protocol import SUBSTEPS, command_velocities, held_leader_motion, \
    step_substeps
from formopt_ros.core.reach import reach_region
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import (
    TrialResult, draws_per_step, initial_truth, trial_streams, true_measurement, true_motion)
from formopt_ros.core.solver import outside_the_disc, timed_plan
from formopt_ros.core.strategies import (
    BatchContext, EstimatorView, PlanContext, StepRecord, Strategy, make_strategy)


@dataclass
class TrialsResult:
    """Per-step records of T trials: :class:`TrialResult` arrays with a leading trial axis."""

    weighted_trace: np.ndarray     # (T, steps) tr(W P_k|k W), m^2
    nees: np.ndarray               # (T, steps) NEES of [x, y, phi]
    estimate: np.ndarray           # (T, steps, 3) x_k|k in {L}
    truth: np.ndarray              # (T, steps, 3) true pose in {L}
    covariance: np.ndarray         # (T, steps, 3, 3) P_k|k
    waypoints: np.ndarray          # (T, steps, 2) chosen positions, m
    decision_time: np.ndarray      # (T, steps) strategy wall time per trial, s
    innovation_nis: np.ndarray     # (T, steps) normalised innovation squared of each update
    gated: np.ndarray              # (T, steps) True where the innovation gate refused it
    fallback: np.ndarray           # (T, steps) the strategy fell back (RAM to RQ)

    def trial(self, index: int) -> TrialResult:
        """The records of trial ``index`` (position in the ``trials`` given to run_trials)."""
        return TrialResult(self.weighted_trace[index], self.nees[index], self.estimate[index],
                           self.truth[index], self.covariance[index], self.waypoints[index],
                           self.decision_time[index], self.innovation_nis[index],
                           self.gated[index], self.fallback[index])


class _PerTrialPlanner:
    """The per-trial route for strategies without ``plan_batch``: one strategy object, history
    and view per trial, exactly as :class:`~formopt_ros.core.estimator.EstimatorPlanner`."""

    def __init__(self, strategies: list[Strategy], scenario: Scenario,
                 rngs: Sequence[np.random.Generator]) -> None:
        self.strategies = strategies
        self.scenario = scenario
        self.rngs = rngs
        self.histories: list[deque[StepRecord]] = [deque(maxlen=HISTORY_LENGTH)
                                                   for _ in strategies]

    def plan(self, step: int, leader: tuple[tuple[float, float], ...], x: np.ndarray,
             P: np.ndarray, problems: 'ProblemBatch | _PlanningProblems', p: np.ndarray,
             times: np.ndarray,
             fallback: np.ndarray) -> None:
        s = self.scenario
        for t, strategy in enumerate(self.strategies):
            x_t, P_t = x[t].copy(), P[t].copy()

            def prior_for(target: np.ndarray, x_t: np.ndarray = x_t,
                          P_t: np.ndarray = P_t) -> np.ndarray:
                return driven_prior(s, x_t, P_t, target, leader)

            view = EstimatorView(x_t, P_t, self.histories[t], prior_for)
            region = reach_region(s.p_o, s.r, x_t, leader, s.dt, s.kinematics, s.max_speed,
                                  s.safety_distance)
            context = PlanContext(step, leader, self.rngs[t], view, s.dt, s.sigma_v,
                                  s.sigma_omega, s.kinematics, region, s)
            solution = timed_plan(strategy, problems.problem(t), context)
            p[t], times[t], fallback[t] = solution.p, solution.solve_time_s, \
                solution.fallback is not None

    def record(self, step: int, x: np.ndarray, P: np.ndarray, targets: np.ndarray) -> None:
        for t, history in enumerate(self.histories):
            history.append(StepRecord(step, x[t], P[t], targets[t]))


class _PlanningProblems:
    """The per-trial problems of one step of a range-bearing scenario (``problem(t)``, as
    :meth:`~formopt_ros.core.cost.ProblemBatch.problem`)."""

    def __init__(self, scenario: Scenario, step: int, prior: np.ndarray) -> None:
        self.scenario, self.step, self.prior = scenario, step, prior

    def problem(self, t: int) -> Problem:
        return planning_problem(self.scenario, self.step, self.prior[t])


def run_trials(scenario: Scenario, strategy: str, seed: int, trials: Sequence[int], steps: int,
               options: dict[str, object] | None = None) -> TrialsResult:
    """Simulate ``steps`` measurement steps of the given trials with one strategy, together.

    Args:
        scenario: the run's settings (any leader path).
        strategy: strategy name; options: its options.
        seed: the study seed; trial i uses ``trial_streams(seed, i)``.
        trials: trial indices.
        steps: measurement steps.

    Returns:
        The records of every trial (equal to ``run_trial(scenario, strategy, seed, i, steps,
        options)`` for each i).
    """
    return run_lanes(scenario, [strategy], seed, trials, steps,
                     {strategy: options or {}})[strategy]


def run_lanes(scenario: Scenario, strategies: Sequence[str], seed: int, trials: Sequence[int],
              steps: int, options: dict[str, dict[str, object]] | None = None
              ) -> dict[str, TrialsResult]:
    """:func:`run_trials` for several strategies at once: every (strategy, trial) is a lane of
    one stacked state, so numpy's per-call cost is shared by all of them; each strategy plans
    its own lanes. Returns strategy name -> records."""
    s = scenario
    T, S = len(trials), len(strategies)
    options = options or {}
    per_step = draws_per_step(s)
    stacked = s.measurement == RANGE_BEARING
    draws = np.array([trial_streams(seed, trial)[0].normal(size=3 + per_step * steps)
                      for trial in trials])
    truth = np.tile(np.array([initial_truth(s, d[:3]) for d in draws]), (S, 1))
    motion = np.tile(draws[:, 3:].reshape(T, steps, per_step), (S, 1, 1))
    x0, P0 = s.initial_estimate()
    x, P = np.tile(x0, (S * T, 1)), np.tile(P0, (S * T, 1, 1))
    slot = s.slot
    lanes = [slice(i * T, (i + 1) * T) for i in range(S)]
    planners: list[Strategy | _PerTrialPlanner] = []
    rngs = []
    for name in strategies:
        rngs.append([trial_streams(seed, trial)[1] for trial in trials])
        first = make_strategy(name, **options.get(name, {}))
        limited = s.max_speed is not None or s.safety_distance > 0.0
        batched = first.vectorised() and not (limited or stacked)
        planners.append(first if batched else _PerTrialPlanner(
            [first] + [make_strategy(name, **options.get(name, {})) for _ in range(T - 1)],
            s, rngs[-1]))
    waypoints = np.empty((S * T, steps, 2))
    decision_time, fallback = np.empty((S * T, steps)), np.zeros((S * T, steps), dtype=bool)
    out = TrialsResult(np.empty((S * T, steps)), np.empty((S * T, steps)),
                       np.empty((S * T, steps, 3)), np.empty((S * T, steps, 3)),
                       np.empty((S * T, steps, 3, 3)), waypoints, decision_time,
                       np.empty((S * T, steps)), np.zeros((S * T, steps), dtype=bool), fallback)
    gated_in_a_row = np.zeros(S * T, dtype=int)
    latest = s.leader.velocity(0, s.dt)
    for k in range(steps):
        leader = held_leader_motion(latest)
        prior = driven_prior(s, x, P, slot, leader)
        p = np.empty((S * T, 2))
        for planner, lane, lane_rngs in zip(planners, lanes, rngs):
            problems = None if stacked else ProblemBatch.shared(
                prior[lane], slot, s.r, s.sigma, s.measurement, validate=False)
            if isinstance(planner, _PerTrialPlanner):
                planner.plan(k + 1, leader, x[lane], P[lane],
                             problems or _PlanningProblems(s, k + 1, prior[lane]), p[lane],
                             decision_time[lane, k], fallback[lane, k])
                continue
            assert problems is not None             # range-bearing plans trial by trial
            start = time.perf_counter()
            plan = planner.plan_batch(problems, BatchContext(k + 1, leader, lane_rngs, s.dt,
                                                             s.sigma_v, s.sigma_omega,
                                                             s.kinematics))
            decision_time[lane, k] = (time.perf_counter() - start) / T
            p[lane] = plan.p
            distances = np.hypot(p[lane, 0] - slot[0], p[lane, 1] - slot[1])
            if np.max(distances) > s.r * (1.0 + 1e-9):      # (a batch is never limited)
                worst = int(np.argmax(distances))
                raise outside_the_disc(planner.name, p[lane][worst], slot, s.r)
            if plan.fallback is not None:
                fallback[lane, k] = plan.fallback
        speed, turn_rate = command_velocities(x, p, s.dt, leader[0][0], leader[0][1],
                                              s.kinematics)
        for j, substep in enumerate(step_substeps(k + 1)):
            latest = v_l, omega_l = s.leader.velocity(substep, s.dt)
            v, omega = ((0.0, turn_rate), (speed, leader[0][1]))[j]
            truth = true_motion(s, truth, v, omega, motion[:, k, 2 * j:2 * j + 2], v_l, omega_l)
            x, P = propagate(x, P, v, omega, s.dt, v_l, omega_l, s.sigma_v, s.sigma_omega,
                             s.sigma_v_leader, s.sigma_omega_leader, s.kinematics)
        if stacked:
            z = true_measurement(s, truth, motion[:, k, 2 * SUBSTEPS:2 * SUBSTEPS + 2])
            update = _gated_update_stacked if s.bearing_at(k + 1) else _gated_update
        else:
            z, update = true_measurement(s, truth, motion[:, k, 2 * SUBSTEPS]), _gated_update
        x, P, gated_in_a_row, out.innovation_nis[:, k], out.gated[:, k] = update(
            s, x, P, z, gated_in_a_row)
        for planner, lane in zip(planners, lanes):
            if isinstance(planner, _PerTrialPlanner):
                planner.record(k + 1, x[lane], P[lane], p[lane])
        out.weighted_trace[:, k] = weighted_trace(P, slot)
        out.nees[:, k] = normalized_estimation_error(truth, x, P)
        out.estimate[:, k], out.truth[:, k], out.covariance[:, k] = x, truth, P
        waypoints[:, k] = p
    return {name: TrialsResult(*(getattr(out, f.name)[lane] for f in fields(TrialsResult)))
            for name, lane in zip(strategies, lanes)}


def _gated_update(s: Scenario, x: np.ndarray, P: np.ndarray, z: np.ndarray,
                  gated_in_a_row: np.ndarray) -> tuple[np.ndarray, ...]:
    """The EKF update of every lane behind the innovation gate, as
    :meth:`~formopt_ros.core.estimator.EstimatorPlanner.update` does it for one: (x, P, gated in
    a row, nis, gated) after the update."""
    variance = s.sigma ** 2
    kind = s.measurement
    if kind == RANGE_BEARING:               # a step without a bearing: the range alone
        kind, z = RANGE, z[:, 0]
    x_new, P_new, innovation, S = ekf_update(x, P, z, kind, variance)
    nis, use, inflation = innovation_gate(innovation, S, variance, gated_in_a_row)
    reopen = np.flatnonzero(use & (inflation > 1.0))
    if reopen.size:
        x_new[reopen], P_new[reopen], _, _ = ekf_update(
            x[reopen], inflation[reopen, None, None] * P[reopen], z[reopen], kind, variance)
    x_new[~use], P_new[~use] = x[~use], P[~use]
    return x_new, P_new, np.where(use, 0, gated_in_a_row + 1), nis, ~use


def _gated_update_stacked(s: Scenario, x: np.ndarray, P: np.ndarray, z: np.ndarray,
                          gated_in_a_row: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`_gated_update` for range and bearing together (z (T, 2)), as
    :meth:`~formopt_ros.core.estimator.EstimatorPlanner.update` does it for one."""
    variances = (s.sigma ** 2, s.sigma_bearing ** 2)
    x_new, P_new, innovation, S = ekf_update_stacked(x, P, z, variances)
    nis, use, inflation = stacked_innovation_gate(innovation, S, variances, gated_in_a_row)
    reopen = np.flatnonzero(use & (inflation > 1.0))
    if reopen.size:
        x_new[reopen], P_new[reopen], _, _ = ekf_update_stacked(
            x[reopen], inflation[reopen, None, None] * P[reopen], z[reopen], variances)
    x_new[~use], P_new[~use] = x[~use], P[~use]
    return x_new, P_new, np.where(use, 0, gated_in_a_row + 1), nis, ~use


__all__ = ['TrialsResult', 'run_lanes', 'run_trials']
