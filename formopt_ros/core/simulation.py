"""The leader/follower world and the Sec. V protocol of the paper, seeded and strategy-agnostic.

One measurement step (DESIGN.md, "The Sec. V protocol"):

1. the estimator predicts the covariance it would have after driving to the slot p_o and asks
   the strategy for the next position p (the optimiser's prior, paper Sec. III-D);
2. the follower executes two sub-steps of ``dt``: rotate in place until its heading points at
   the displacement still needed, then translate (omega = 0) so that the *estimate* lands on p;
   the leader keeps moving during both; true velocities are the commands plus fresh Gaussian
   noise, while the EKF propagates with the commands (the odometry);
3. one range or bearing measurement of the true pose, one EKF update ('range-bearing': range
   and bearing of the true pose, one stacked update; at steps without a bearing (rates,
   ``Scenario.bearing_every``) a range update).

The pieces (the leader path of :class:`~formopt_ros.core.scenario.Scenario`,
:class:`FollowerTruth`, :class:`~formopt_ros.core.estimator.EstimatorPlanner`) are separate so
that the ROS nodes run exactly the same arithmetic in separate processes.
Random numbers: per trial, :func:`trial_streams` gives a *noise* stream (initial truth, velocity
and measurement noise, always drawn in the same order) and a *planner* stream (CRM): every
strategy sees the same noise in a trial (common random numbers).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from formopt_ros.core.estimator import EstimatorPlanner
from formopt_ros.core.model import (
    BEARING, RANGE, RANGE_BEARING, integrate_unicycle, normalized_estimation_error,
    predict_measurement, propagate_state, wrap_angle)
from formopt_ros.core.protocol import SUBSTEPS, held_leader_motion, step_substeps
from formopt_ros.core.formation import Formation
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import make_strategy


def trial_streams(seed: int, trial: int) -> tuple[np.random.Generator, np.random.Generator]:
    """(noise, planner) random generators of one trial; independent of the strategy."""
    noise, planner = np.random.SeedSequence([seed, trial]).spawn(2)
    return np.random.default_rng(noise), np.random.default_rng(planner)


#: Normal draws of the noise stream per measurement step: (v, omega) per sub-step, then z.
DRAWS_PER_STEP = 2 * SUBSTEPS + 1


def draws_per_step(scenario: Scenario) -> int:
    """Normal draws per measurement step: DRAWS_PER_STEP, and one more (the bearing's, drawn
    at every step whether or not it arrives) for 'range-bearing'."""
    return DRAWS_PER_STEP + (scenario.measurement == RANGE_BEARING)


def initial_truth(scenario: Scenario, draw: np.ndarray) -> np.ndarray:
    """True start pose (3,) from three standard normal draws: x_1|1 + chol(P_1|1) draw."""
    x0, P0 = scenario.initial_estimate()
    x = x0 + np.linalg.cholesky(P0) @ draw
    x[2] = wrap_angle(x[2])
    return x


def true_motion(scenario: Scenario, x: np.ndarray, v_cmd: Any, omega_cmd: Any, w: np.ndarray,
                v_l: float, omega_l: float) -> np.ndarray:
    """One sub-step (the scenario's kinematics) with true velocities = commands + sigma * w
    (standard normal w, shape (2,), or (T, 2) for poses x of shape (T, 3))."""
    s = scenario
    return propagate_state(x, v_cmd + s.sigma_v * w[..., 0], omega_cmd + s.sigma_omega * w[..., 1],
                           s.dt, v_l, omega_l, s.kinematics)


def true_measurement(scenario: Scenario, x: np.ndarray, w: Any) -> Any:
    """Range (m) or bearing (rad, wrapped) of the true pose(s) plus sigma * w (standard normal);
    'range-bearing': [d, beta] (2,) or (T, 2) from w (2,) or (T, 2), both noises."""
    s = scenario
    if s.measurement == RANGE_BEARING:
        w = np.asarray(w, dtype=float)
        z = predict_measurement(RANGE_BEARING, x) + np.array([s.sigma, s.sigma_bearing]) * w
        z[..., 1] = wrap_angle(z[..., 1])
        return z
    z = predict_measurement(s.measurement, x) + s.sigma * w
    if s.measurement != BEARING:
        return z
    return float(wrap_angle(z)) if np.ndim(z) == 0 else wrap_angle(z)


class FollowerTruth:
    """The real follower: true pose in {L}, noisy execution of commands, noisy measurements."""

    def __init__(self, scenario: Scenario, noise: np.random.Generator) -> None:
        self.scenario = scenario
        self.noise = noise
        self.x = initial_truth(scenario, noise.normal(size=3))

    def execute(self, v_cmd: float, omega_cmd: float, v_l: float, omega_l: float) -> None:
        """One sub-step with true velocities = commands + N(0, sigma^2) noise."""
        self.x = true_motion(self.scenario, self.x, v_cmd, omega_cmd, self.noise.normal(size=2),
                             v_l, omega_l)

    def park(self, v_l: float, omega_l: float) -> None:
        """One sub-step standing still (the driver is down: no command, no noise) while the
        leader moves at (v_l m/s, omega_l rad/s)."""
        self.x = propagate_state(self.x, 0.0, 0.0, self.scenario.dt, v_l, omega_l,
                                 self.scenario.kinematics)

    def measure(self) -> Any:
        """Range (m) or bearing (rad, wrapped) of the true pose plus N(0, sigma^2) noise;
        'range-bearing': [d, beta] (2,) (both drawn at every step)."""
        if self.scenario.measurement == RANGE_BEARING:
            return true_measurement(self.scenario, self.x, self.noise.normal(size=2))
        return float(true_measurement(self.scenario, self.x, self.noise.normal()))


def received(scenario: Scenario, step: int, z: Any) -> Any:
    """What the estimator receives at measurement step ``step`` (1-based): z itself, or for a
    range-bearing follower without a bearing that step (``bearing_every``) [d, NaN]."""
    if scenario.measurement != RANGE_BEARING or scenario.bearing_at(step):
        return z
    z = np.array(z, dtype=float)
    z[..., 1] = np.nan
    return z


def measurement_parts(scenario: Scenario, step: int, z: Any) -> list[tuple[str, float, float]]:
    """The scalar measurements a follower sends at measurement step ``step`` (1-based) for its
    measurement z: [(kind, value m or rad, variance m^2 or rad^2)]; a range-bearing follower
    sends its range and, on the steps that have one, its bearing."""
    if scenario.measurement != RANGE_BEARING:
        return [(scenario.measurement, float(z), scenario.sigma ** 2)]
    parts = [(RANGE, float(z[0]), scenario.sigma ** 2)]
    if scenario.bearing_at(step):
        parts.append((BEARING, float(z[1]), scenario.sigma_bearing ** 2))
    return parts


def leader_poses(scenario: Scenario, steps: int) -> np.ndarray:
    """The leader's pose (x m, y m, yaw rad) in the fixed frame at the end of each measurement
    step, starting at the origin heading along +x, shape (steps, 3) (dead reckoning, as
    leader_sim)."""
    pose = (0.0, 0.0, 0.0)
    out = np.empty((steps, 3))
    for k in range(steps):
        for substep in step_substeps(k + 1):
            v, omega = scenario.leader.velocity(substep, scenario.dt)
            pose = integrate_unicycle(pose, v, omega, scenario.dt)
        out[k] = pose
    return out


@dataclass
class TrialResult:
    """Per-step records of one trial; arrays have the step count as first dimension."""

    weighted_trace: np.ndarray     # (steps,) tr(W P_k|k W), m^2
    nees: np.ndarray               # (steps,) NEES of [x, y, phi]
    estimate: np.ndarray           # (steps, 3) x_k|k in {L}
    truth: np.ndarray              # (steps, 3) true pose in {L}
    covariance: np.ndarray         # (steps, 3, 3) P_k|k
    waypoints: np.ndarray          # (steps, 2) chosen positions, m
    decision_time: np.ndarray      # (steps,) strategy wall time, s
    innovation_nis: np.ndarray     # (steps,) normalised innovation squared of each update
    gated: np.ndarray              # (steps,) True where the innovation gate refused it
    fallback: np.ndarray | None = None      # (steps,) the strategy fell back (RAM to RQ)
    # run_trial only (the inputs a node would receive):
    commands: np.ndarray | None = None      # (steps, SUBSTEPS, 2) odometry (v m/s, omega rad/s)
    leader: np.ndarray | None = None        # (steps, SUBSTEPS, 2) leader (v m/s, omega rad/s)
    measurements: np.ndarray | None = None  # (steps,) range (m) or bearing (rad); (steps, 2)
    #                                         [d, beta] for range-bearing (NaN: no bearing)


def run_trial(scenario: Scenario, strategy: str, seed: int, trial: int, steps: int,
              options: dict[str, object] | None = None) -> TrialResult:
    """Simulate ``steps`` measurement steps of one trial with one strategy (Sec. V protocol).

    The planner knows the leader only through its odometry as it comes: it expects the
    velocity of the last sub-step to persist (``held_leader_motion``), as the node does.
    """
    noise, planner_rng = trial_streams(seed, trial)
    truth = FollowerTruth(scenario, noise)
    estimator = EstimatorPlanner(scenario, make_strategy(strategy, **(options or {})),
                                 planner_rng)
    latest = scenario.leader.velocity(0, scenario.dt)
    fallback = np.zeros(steps, dtype=bool)
    commands, leader = np.empty((steps, SUBSTEPS, 2)), np.empty((steps, SUBSTEPS, 2))
    measurements = np.empty((steps, 2) if scenario.measurement == RANGE_BEARING else steps)
    out = TrialResult(np.empty(steps), np.empty(steps), np.empty((steps, 3)),
                      np.empty((steps, 3)), np.empty((steps, 3, 3)), np.empty((steps, 2)),
                      np.empty(steps), np.empty(steps), np.zeros(steps, dtype=bool), fallback,
                      commands, leader, measurements)
    for k in range(steps):
        plan = estimator.plan(k + 1, held_leader_motion(latest))
        for j, substep in enumerate(step_substeps(k + 1)):
            latest = v_l, omega_l = scenario.leader.velocity(substep, scenario.dt)
            v, omega = plan.command.linear[j], plan.command.angular[j]
            truth.execute(v, omega, v_l, omega_l)
            estimator.propagate(v, omega, v_l, omega_l)
            commands[k, j], leader[k, j] = (v, omega), latest
        measurements[k] = received(scenario, k + 1, truth.measure())
        update = estimator.update(k + 1, measurements[k])
        out.innovation_nis[k], out.gated[k] = update.nis, not update.used
        out.weighted_trace[k] = estimator.weighted_trace()
        out.nees[k] = normalized_estimation_error(truth.x, estimator.x, estimator.P)
        out.estimate[k], out.truth[k], out.covariance[k] = estimator.x, truth.x, estimator.P
        out.waypoints[k] = plan.solution.p
        out.decision_time[k] = plan.solution.solve_time_s
        fallback[k] = plan.solution.fallback is not None
    return out


def run_formation(formation: Formation, steps: int) -> dict[str, TrialResult]:
    """Every follower of a formation for ``steps`` steps: followers do not interact, so each
    is one :func:`run_trial` with its scenario (the shared leader path), strategy and seed."""
    return {f.id: run_trial(f.scenario, f.strategy, f.seed, formation.trial, steps, f.options)
            for f in formation.followers}


__all__ = ['DRAWS_PER_STEP', 'SUBSTEPS', 'FollowerTruth', 'Scenario', 'TrialResult',
           'draws_per_step', 'initial_truth', 'leader_poses', 'received', 'run_formation',
           'run_trial', 'trial_streams', 'true_measurement', 'true_motion']
