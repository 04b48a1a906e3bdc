"""The leader/follower world and the Sec. V protocol of the paper, seeded and strategy-agnostic.

One measurement step (DESIGN.md, "The Sec. V protocol"):

1. the estimator predicts the covariance it would have after driving to the slot p_o and asks
   the strategy for the next position p (the optimiser's prior, paper Sec. III-D);
2. the follower executes two sub-steps of ``dt``: rotate in place until its heading points at
   the displacement still needed, then translate (omega = 0) so that the *estimate* lands on p;
   the leader keeps moving during both; true velocities are the commands plus fresh Gaussian
   noise, while the EKF propagates with the commands (the odometry);
3. one range or bearing measurement of the true pose, one EKF update.

The pieces (:class:`LeaderMotion`, :class:`FollowerTruth`, :class:`EstimatorPlanner`) are
separate so that the ROS nodes run exactly the same arithmetic in separate processes.
Random numbers: per trial, :func:`trial_streams` gives a *noise* stream (initial truth, velocity
and measurement noise, always drawn in the same order) and a *planner* stream (CRM): every
strategy sees the same noise in a trial (common random numbers).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from formopt_ros.core.cost import Problem, weighted_trace
from formopt_ros.core.model import (
    BEARING, RANGE, ekf_update, normalized_estimation_error, predict_measurement, propagate,
    propagate_state, wrap_angle)
from formopt_ros.core.solver import Solution, solve_problem

#: Sub-steps per measurement step: rotate, then translate.
SUBSTEPS = 2


@dataclass(frozen=True)
class Scenario:
    """Everything that defines a run except the strategy and the seed (defaults: paper Sec. V).

    Attributes:
        measurement: 'range' or 'bearing'.
        p_o: formation slot in the leader frame, m.
        r: allowed deviation from the slot, m.
        sigma: measurement noise standard deviation, m or rad.
        v_leader, omega_leader: leader velocities, m/s and rad/s.
        dt: sub-step length, s.
        sigma_v, sigma_omega: follower velocity noise standard deviations, m/s and rad/s.
        initial_covariance: diagonal of P_1|1 (m^2, m^2, rad^2); the estimate starts at
            [p_o, 0] and the truth is drawn from N(estimate, P_1|1).
    """

    measurement: str
    p_o: tuple[float, float]
    r: float
    sigma: float
    v_leader: float = 1.0
    omega_leader: float = 0.0
    dt: float = 0.05
    sigma_v: float = 0.2
    sigma_omega: float = 0.1
    initial_covariance: tuple[float, float, float] = (0.1, 0.1, 4e-4)

    @classmethod
    def paper(cls, measurement: str, **overrides: float) -> 'Scenario':
        """The paper's Sec. V settings for 'range' (p_o = [-1, -2], sigma_d = 0.1 m) or
        'bearing' (p_o = [-1, 2], sigma_beta = 0.02 rad); r = 0.1 |p_o|."""
        if measurement not in (RANGE, BEARING):
            raise ValueError(f"measurement must be 'range' or 'bearing', got {measurement!r}")
        p_o = (-1.0, -2.0) if measurement == RANGE else (-1.0, 2.0)
        values = dict(measurement=measurement, p_o=p_o, r=0.1 * math.hypot(*p_o),
                      sigma=0.1 if measurement == RANGE else 0.02)
        values.update(overrides)
        return cls(**values)

    @property
    def slot(self) -> np.ndarray:
        """p_o as an array, shape (2,), m."""
        return np.array(self.p_o, dtype=float)

    def initial_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """(x_1|1 = [p_o, 0], P_1|1)."""
        return np.array([self.p_o[0], self.p_o[1], 0.0]), np.diag(self.initial_covariance)


def trial_streams(seed: int, trial: int) -> tuple[np.random.Generator, np.random.Generator]:
    """(noise, planner) random generators of one trial; independent of the strategy."""
    noise, planner = np.random.SeedSequence([seed, trial]).spawn(2)
    return np.random.default_rng(noise), np.random.default_rng(planner)


class LeaderMotion:
    """Leader velocities per sub-step; straight at v_L by default. Subclass for other paths."""

    def __init__(self, v_leader: float, omega_leader: float = 0.0) -> None:
        self.v_leader = v_leader
        self.omega_leader = omega_leader

    def velocity(self, substep: int) -> tuple[float, float]:
        """(v_L m/s, omega_L rad/s) during global sub-step index ``substep`` (0-based)."""
        return self.v_leader, self.omega_leader

    def straight(self, substep: int) -> bool:
        """True when the leader drives straight (the unobservable case for MTF)."""
        return self.velocity(substep)[1] == 0.0


def motion_commands(x: np.ndarray, target: np.ndarray, dt: float, v_l: float,
                    omega_l: float) -> tuple[tuple[float, float], tuple[float, float]]:
    """Commands ((v1, v2), (omega1, omega2)) that move the pose x to position target in {L}.

    Sub-step 1 rotates in place (v = 0) to the heading of the remaining displacement; sub-step
    2 translates (omega = omega_L, i.e. no turn relative to the leader) so that the
    Euler-propagated pose (eq. 10) lands exactly on target while the leader moves.
    """
    x1 = propagate_state(x, 0.0, omega_l, dt, v_l, omega_l)      # position after rotating
    dx = target[0] - x1[0] - omega_l * x1[1] * dt + v_l * dt
    dy = target[1] - x1[1] + omega_l * x1[0] * dt
    heading = math.atan2(dy, dx)
    turn = float(wrap_angle(heading - x[2]))
    return (0.0, math.hypot(dx, dy) / dt), (turn / dt + omega_l, omega_l)


class FollowerTruth:
    """The real follower: true pose in {L}, noisy execution of commands, noisy measurements."""

    def __init__(self, scenario: Scenario, noise: np.random.Generator) -> None:
        self.scenario = scenario
        self.noise = noise
        x0, P0 = scenario.initial_estimate()
        self.x = x0 + np.linalg.cholesky(P0) @ noise.normal(size=3)
        self.x[2] = wrap_angle(self.x[2])

    def execute(self, v_cmd: float, omega_cmd: float, v_l: float, omega_l: float) -> None:
        """One sub-step of eq. (9) with true velocities = commands + N(0, sigma^2) noise."""
        s = self.scenario
        w = self.noise.normal(size=2)
        self.x = propagate_state(self.x, v_cmd + s.sigma_v * w[0],
                                 omega_cmd + s.sigma_omega * w[1], s.dt, v_l, omega_l)

    def measure(self) -> float:
        """Range (m) or bearing (rad, wrapped) of the true pose plus N(0, sigma^2) noise."""
        s = self.scenario
        z = predict_measurement(s.measurement, self.x) + s.sigma * self.noise.normal()
        return float(wrap_angle(z)) if s.measurement == BEARING else z


@dataclass
class PlanResult:
    """The planner's decision for one step."""

    solution: Solution
    v_commands: tuple[float, float]
    omega_commands: tuple[float, float]


@dataclass
class EstimatorPlanner:
    """The follower's EKF and motion strategy (paper Secs. III-B to III-D).

    Attributes:
        scenario: the run's settings.
        strategy: one of the solver's METHODS.
        planner_rng: random stream of randomised strategies (CRM).
        options: extra strategy options (e.g. ``{'cell': 0.01}`` for GBS).
    """

    scenario: Scenario
    strategy: str
    planner_rng: np.random.Generator
    options: dict = field(default_factory=dict)
    x: np.ndarray = field(init=False)
    P: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.x, self.P = self.scenario.initial_estimate()

    def predicted_covariance(self, target: np.ndarray, v_l: tuple[float, float],
                             omega_l: tuple[float, float]) -> np.ndarray:
        """Covariance after driving to ``target`` with the protocol's commands (no update)."""
        s = self.scenario
        v, omega = motion_commands(self.x, target, s.dt, v_l[0], omega_l[0])
        x, P = self.x, self.P
        for k in range(SUBSTEPS):
            x, P = propagate(x, P, v[k], omega[k], s.dt, v_l[k], omega_l[k], s.sigma_v,
                             s.sigma_omega)
        return P

    def plan(self, step: int, leader_velocities: list[tuple[float, float]],
             leader_straight: bool = True) -> PlanResult:
        """Choose the next position for measurement step ``step`` (1-based) and its commands.

        Args:
            step: the measurement step the motion leads to.
            leader_velocities: expected (v_L m/s, omega_L rad/s) of the leader during each
                sub-step of the motion (the simulator knows the leader's plan; a robot holds
                the last odometry).
            leader_straight: whether the leader drives straight (MME's switch).
        """
        s = self.scenario
        v_l = tuple(v for v, _ in leader_velocities)
        omega_l = tuple(w for _, w in leader_velocities)
        prior = self.predicted_covariance(s.slot, v_l, omega_l)
        options = dict(self.options)
        if self.strategy == 'mme':
            options.update(step=step, leader_straight=leader_straight)
        solution = solve_problem(Problem(prior, s.slot, s.r, s.sigma, s.measurement, False),
                                 self.strategy, self.planner_rng, **options)
        v, omega = motion_commands(self.x, solution.p, s.dt, v_l[0], omega_l[0])
        return PlanResult(solution, v, omega)

    def propagate(self, v_f: float, omega_f: float, v_l: float, omega_l: float) -> None:
        """EKF propagation over one sub-step with odometry (v_f, omega_f) and leader velocity."""
        s = self.scenario
        self.x, self.P = propagate(self.x, self.P, v_f, omega_f, s.dt, v_l, omega_l, s.sigma_v,
                                   s.sigma_omega)

    def update(self, z: float, variance: float | None = None) -> None:
        """EKF update with a range (m) or bearing (rad) measurement."""
        s = self.scenario
        variance = s.sigma ** 2 if variance is None else variance
        self.x, self.P, _, _ = ekf_update(self.x, self.P, z, s.measurement, variance)

    def weighted_trace(self) -> float:
        """tr(W P W) of the current covariance, m^2."""
        return weighted_trace(self.P, self.scenario.slot)


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


def run_trial(scenario: Scenario, strategy: str, seed: int, trial: int, steps: int,
              options: dict | None = None, leader: LeaderMotion | None = None) -> TrialResult:
    """Simulate ``steps`` measurement steps of one trial with one strategy (Sec. V protocol)."""
    noise, planner_rng = trial_streams(seed, trial)
    leader = leader or LeaderMotion(scenario.v_leader, scenario.omega_leader)
    truth = FollowerTruth(scenario, noise)
    estimator = EstimatorPlanner(scenario, strategy, planner_rng, dict(options or {}))
    out = TrialResult(np.empty(steps), np.empty(steps), np.empty((steps, 3)),
                      np.empty((steps, 3)), np.empty((steps, 3, 3)), np.empty((steps, 2)),
                      np.empty(steps))
    for k in range(steps):
        first = k * SUBSTEPS
        plan = estimator.plan(k + 1, [leader.velocity(first + j) for j in range(SUBSTEPS)],
                              leader.straight(first))
        for j in range(SUBSTEPS):
            v_l, omega_l = leader.velocity(k * SUBSTEPS + j)
            truth.execute(plan.v_commands[j], plan.omega_commands[j], v_l, omega_l)
            estimator.propagate(plan.v_commands[j], plan.omega_commands[j], v_l, omega_l)
        estimator.update(truth.measure())
        out.weighted_trace[k] = estimator.weighted_trace()
        out.nees[k] = normalized_estimation_error(truth.x, estimator.x, estimator.P)
        out.estimate[k], out.truth[k], out.covariance[k] = estimator.x, truth.x, estimator.P
        out.waypoints[k] = plan.solution.p
        out.decision_time[k] = plan.solution.solve_time_s
    return out
