"""One follower's brain: the EKF and its motion strategy (paper Secs. III-B to III-D), with its
input gate (:mod:`formopt_ros.core.session` feeds it timestamped inputs).

The input gate (documented thresholds; every refusal is counted and says why):

* plausibility (:class:`InputBounds`, relative to the scenario): a speed above
  ``TRAVEL_BOUND`` |p_o| per sub-step, a yaw rate above ``TURN_BOUND`` half-turns per
  sub-step, a range above ``RANGE_BOUND`` |p_o|, a bearing outside [-pi, pi], a measurement
  variance outside [sigma^2 / VARIANCE_BOUND, sigma^2 * VARIANCE_BOUND] are refused;
* innovation (chi-square, 1 dof): a measurement whose normalised innovation squared
  nu^2 / S exceeds ``INNOVATION_GATE`` = 100 (10 standard deviations) is not used. In the
  Sec. V study (2 sensors x 7 strategies x 50 trials x 600 steps = 420 000 updates) the largest
  value is 78 (bearing, step 3, while the heading is still uncertain), so the gate changes
  no study number. After ``GATE_PATIENCE`` refusals in a row the filter is taken to be lost:
  the next measurement is used after scaling P so that its innovation is at 3 standard
  deviations (counted as a covariance inflation).
* range and bearing of one step ('range-bearing'): one joint gate on the stacked normalised
  innovation squared nu' S^-1 nu (chi-square, 2 dof) at the same tail probability as the
  scalar gate: ``INNOVATION_GATE_2`` = -2 ln P(chi2_1 > 100) = 105.1, re-opening at
  ``REOPEN_NIS_2`` = -2 ln P(chi2_1 > 9) = 11.8 (P scaled so that the stacked innovation sits
  there). A step with one of the two (rates: :attr:`Scenario.bearing_every`) is a scalar
  update behind the scalar gate.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from formopt_ros.core.checks import InvalidInput, as_integer, as_real
from formopt_ros.core.cost import Problem
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.model import (
    BEARING, RANGE, RANGE_BEARING, ekf_update, ekf_update_stacked, propagate, stacked_nis,
    transition_matrices)
from formopt_ros.core.protocol import MotionCommand, motion_commands, predict_move
from formopt_ros.core.reach import reach_region
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.stacked import StackedProblem
from formopt_ros.core.solver import timed_plan
from formopt_ros.core.strategies import (
    EstimatorView, PlanContext, Solution, StepRecord, Strategy)

#: Processed steps a strategy can look back on through ``EstimatorView.history`` (kept short:
#: the history is part of every checkpoint the estimator node writes after each step).
HISTORY_LENGTH = 8
#: Normalised innovation squared above which a measurement is not used (chi-square, 1 dof).
INNOVATION_GATE = 100.0
#: The stacked (2 dof) gate and re-opening level: the scalar ones' tail probabilities.
INNOVATION_GATE_2 = -2.0 * math.log(math.erfc(math.sqrt(INNOVATION_GATE / 2.0)))
#: Re-opening level of the stacked gate, 2 dof (the tail of 3 standard deviations).
REOPEN_NIS_2 = -2.0 * math.log(math.erfc(math.sqrt(9.0 / 2.0)))
#: Gated measurements in a row after which the filter re-opens with an inflated covariance.
GATE_PATIENCE = 3
#: Normalised innovation squared a re-opening measurement is scaled to (3 standard deviations).
REOPEN_NIS = 9.0
#: Plausibility: at most this many |p_o| of travel per sub-step (speed <= bound |p_o| / dt).
TRAVEL_BOUND = 20.0
#: Plausibility: at most this many half-turns per sub-step (|omega| <= bound pi / dt).
TURN_BOUND = 10.0
#: Plausibility: a range of at most this many |p_o|.
RANGE_BOUND = 100.0
#: Plausibility: a measurement variance within this factor of sigma^2, either way.
VARIANCE_BOUND = 100.0


@dataclass(frozen=True)
class InputBounds:
    """Plausibility bounds of the inputs of one scenario (see the module docstring).

    Attributes:
        speed: largest |v| of an odometry sub-step, m/s.
        yaw_rate: largest |omega|, rad/s.
        range: largest range, m.
        variance: (smallest, largest) measurement variance, m^2 or rad^2.
        bearing_variance: the same for the bearing of a range-bearing follower, rad^2 (None:
            ``variance`` holds for every kind).
    """

    speed: float
    yaw_rate: float
    range: float
    variance: tuple[float, float]
    bearing_variance: tuple[float, float] | None = None

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> 'InputBounds':
        """The bounds of ``scenario``."""
        def around(sigma: float) -> tuple[float, float]:
            return sigma ** 2 / VARIANCE_BOUND, sigma ** 2 * VARIANCE_BOUND
        return cls(TRAVEL_BOUND * scenario.d_o / scenario.dt,
                   TURN_BOUND * np.pi / scenario.dt, RANGE_BOUND * scenario.d_o,
                   around(scenario.sigma),
                   around(scenario.sigma_bearing) if scenario.measurement == RANGE_BEARING
                   else None)

    def odometry_problem(self, v: float, omega: float) -> str | None:
        """Why a velocity pair (m/s, rad/s) is implausible, or None."""
        if not abs(v) <= self.speed:
            return f'speed {v:.6g} m/s exceeds the plausible {self.speed:.6g} m/s'
        if not abs(omega) <= self.yaw_rate:
            return f'yaw rate {omega:.6g} rad/s exceeds the plausible {self.yaw_rate:.6g} rad/s'
        return None

    def measurement_problem(self, kind: str, value: float, variance: float) -> str | None:
        """Why a range (m) or bearing (rad) with its variance is implausible, or None."""
        if kind == 'range' and not 0.0 <= value <= self.range:
            return f'range {value:.6g} m is outside [0, {self.range:.6g}] m'
        if kind == 'bearing' and not abs(value) <= np.pi:
            return f'bearing {value:.6g} rad is outside [-pi, pi]'
        low, high = self.bearing_variance if kind == BEARING and self.bearing_variance \
            else self.variance
        if not low <= variance <= high:
            return (f'variance {variance:.6g} is outside [{low:.6g}, {high:.6g}] (a factor '
                    f'{VARIANCE_BOUND:g} around sigma^2)')
        return None


def innovation_gate(innovation: Any, S: Any, variance: float, gated_in_a_row: Any,
                    gate: float = INNOVATION_GATE,
                    patience: int = GATE_PATIENCE) -> tuple[Any, Any, Any]:
    """The gate's decision (module docstring) for one measurement or a batch (arrays (T,)).

    Args:
        innovation: z - h(x), m or rad; S: its variance H P H' + R.
        variance: the measurement noise variance R.
        gated_in_a_row: measurements gated in a row before this one.
        gate: the normalised innovation squared above which it is refused.
        patience: gated measurements in a row after which the filter re-opens.

    Returns:
        (nis, use, inflation): the normalised innovation squared; whether the measurement is
        used; the factor to scale P by before using it (1 unless the filter re-opens).
    """
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        nis = innovation * innovation / S
        projected = S - variance
        reopen = (np.asarray(gated_in_a_row) >= patience) & np.isfinite(nis) & \
            (projected > 0.0)
        passes = nis <= gate
        inflation = np.where(reopen & ~passes, np.maximum(
            (innovation * innovation / REOPEN_NIS - variance) / projected, 1.0), 1.0)
    use = passes | reopen
    if np.ndim(use) == 0:
        return float(nis), bool(use), float(inflation)
    return nis, use, inflation


def stacked_innovation_gate(innovation: np.ndarray, S: np.ndarray,
                            variances: tuple[float, float], gated_in_a_row: Any,
                            gate: float = INNOVATION_GATE_2) -> tuple[Any, Any, Any]:
    """:func:`innovation_gate` for a stacked range-bearing update (module docstring).

    Args:
        innovation: z - h(x), (2,) or (T, 2) (m, rad); S: H P H' + R, (2, 2) or (T, 2, 2).
        variances: (sigma_d^2, sigma_beta^2), the diagonal of R.
        gated_in_a_row: measurements gated in a row before this one.
        gate: the stacked normalised innovation squared above which it is refused.

    Returns:
        (nis, use, inflation): nis = nu' S^-1 nu; the factor a re-opening update scales P by is
        the larger root alpha of nu' (alpha A + R)^-1 nu = REOPEN_NIS_2, A = S - R (a
        quadratic: nu' adj(B) nu is affine and det B quadratic in alpha), at least 1.
    """
    r0, r1 = variances
    with np.errstate(divide='ignore', invalid='ignore', over='ignore'):
        nis = stacked_nis(innovation, S)
        n0, n1 = innovation[..., 0], innovation[..., 1]
        a00, a01, a11 = S[..., 0, 0] - r0, S[..., 0, 1], S[..., 1, 1] - r1
        q1 = a11 * n0 * n0 - 2.0 * a01 * n0 * n1 + a00 * n1 * n1
        q0 = r1 * n0 * n0 + r0 * n1 * n1
        c = REOPEN_NIS_2
        qa, qb, qc = c * (a00 * a11 - a01 * a01), c * (a00 * r1 + a11 * r0) - q1, c * r0 * r1 - q0
        root = (-qb + np.sqrt(np.maximum(qb * qb - 4.0 * qa * qc, 0.0))) / (2.0 * qa)
        reopen = (np.asarray(gated_in_a_row) >= GATE_PATIENCE) & np.isfinite(nis) & (qa > 0.0)
        passes = nis <= gate
        inflation = np.where(reopen & ~passes, np.maximum(root, 1.0), 1.0)
    use = passes | reopen
    if np.ndim(use) == 0:
        return float(nis), bool(use), float(inflation)
    return nis, use, inflation


@dataclass(frozen=True)
class RealNoise:
    """Measurement-noise handling for real sensors (all off by default: the paper's filter).

    Attributes:
        bias_sigma: range only: standard deviation of a range-bias state b (m) at the start
            (z = |p| + b + noise); 0: no bias state. Use it for UWB radios, whose ranges carry
            biases of about 0.1 m that change slowly with geometry.
        bias_walk: random walk of the bias, m / sqrt(s) (how fast it may drift).
        huber: Huber threshold k in innovation standard deviations (0: off). A measurement
            whose normalised innovation e exceeds k is used with its variance scaled by |e| / k,
            so it pulls the estimate as much as a k-sigma one (one-sided non-line-of-sight
            tails, outliers the gate lets through). Typical: 2 to 3.
        gate: the innovation gate in standard deviations (0: the paper filter's 10). Outliers
            of a radio are often within 10 sigma of an uncertain prior (a +1 m range when
            sqrt(S) is 0.2 m is 5 sigma): 5 keeps them out.
        reopen_after: gated measurements in a row after which the filter takes itself to be
            lost and re-opens on the next one with an inflated covariance (0: GATE_PATIENCE,
            the paper filter's 3). Non-line-of-sight ranges come in bursts (someone between
            the robots): a burst longer than this is fused as if it were the truth.
    """

    bias_sigma: float = 0.0
    bias_walk: float = 0.0
    huber: float = 0.0
    gate: float = 0.0
    reopen_after: int = 0

    def __post_init__(self) -> None:
        for name in ('bias_sigma', 'bias_walk', 'huber', 'gate'):
            object.__setattr__(self, name, as_real(name, getattr(self, name), 0.0))
        for name in ('huber', 'gate'):
            if getattr(self, name) and getattr(self, name) < 1.0:
                raise InvalidInput(name, f'must be 0 (off) or >= 1 standard deviation, got '
                                         f'{getattr(self, name)!r}')
        object.__setattr__(self, 'reopen_after',
                           as_integer('reopen_after', self.reopen_after, 0, 10**6))

    @property
    def patience(self) -> int:
        """Gated measurements in a row before the filter re-opens."""
        return self.reopen_after or GATE_PATIENCE

    @property
    def gate_nis(self) -> float:
        """The gate as a normalised innovation squared."""
        return self.gate ** 2 if self.gate else INNOVATION_GATE


@dataclass(frozen=True)
class UpdateResult:
    """What one measurement did to the filter.

    Attributes:
        innovation: z - h(x), m or rad (wrapped for bearing); [d, beta] residuals (2,) of a
            stacked range-bearing update.
        nis: normalised innovation squared nu^2 / S (before any inflation).
        used: False when the innovation gate refused the measurement.
        inflation: factor applied to P before a re-opening update (1: none).
        weight: Huber's weight of the measurement (1: full; below 1: down-weighted).
        parts: the NIS as independent chi-square(1) terms for the consistency watch: (nis,)
            for a scalar update; for a stacked one the squared components of the whitened
            innovation L^-1 nu (S = L L', range first: its own NIS, then the bearing's given
            the range), which sum to nis.
        measured: False when the step had no measurement (NaN: refused before it came):
            nothing was updated or gated, innovation and nis are NaN.
    """

    innovation: float | np.ndarray
    nis: float
    used: bool
    inflation: float = 1.0
    weight: float = 1.0
    parts: tuple[float, ...] = ()
    measured: bool = True

    def nis_parts(self) -> tuple[float, ...]:
        """:attr:`parts`, or (nis,) when none were set."""
        return self.parts or (self.nis,)


def whitened_squares(innovation: np.ndarray, S: np.ndarray) -> tuple[float, float]:
    """The squared components of L^-1 nu for S = L L' (Cholesky, 2x2): chi-square(1) each
    and independent for a consistent filter; they sum to nu' S^-1 nu."""
    l00 = math.sqrt(S[0, 0])
    l10 = S[0, 1] / l00
    l11 = math.sqrt(max(S[1, 1] - l10 * l10, 0.0))
    e0 = innovation[0] / l00
    e1 = (innovation[1] - l10 * e0) / l11
    return float(e0 * e0), float(e1 * e1)


@dataclass(frozen=True)
class StepPlan:
    """The decision for one measurement step: where to go and how to drive there."""

    step: int
    solution: Solution
    command: MotionCommand


def driven_prior(scenario: Scenario, x: np.ndarray, P: np.ndarray, target: np.ndarray,
                 leader: tuple[tuple[float, float], ...]) -> np.ndarray:
    """Covariance after driving from (x, P) to ``target`` with the protocol's commands under the
    leader velocities ``leader``, before the update: :func:`predict_move` with the scenario's
    dt and odometry noise; one pose or a batch (shapes as there), returns the shape of P."""
    return predict_move(x, P, target, leader, scenario.dt, scenario.sigma_v,
                        scenario.sigma_omega, scenario.kinematics)[1]


def planning_problem(scenario: Scenario, step: int, prior: np.ndarray,
                     sigma: float | None = None) -> Problem:
    """The planner's problem of measurement step ``step`` with prior covariance ``prior``
    (3, 3) (not validated: the scenario is): a :class:`~formopt_ros.core.cost.Problem` of the
    scenario's kind, for 'range-bearing' a :class:`~formopt_ros.core.stacked.StackedProblem`,
    or a range Problem at a step without a bearing. ``sigma``: the (range) noise the planner
    assumes (default the scenario's). (Typed as Problem: a StackedProblem has the attributes and
    methods of one that the strategies use.)"""
    s = scenario
    sigma = s.sigma if sigma is None else sigma
    if s.measurement != RANGE_BEARING:
        return Problem(prior, s.slot, s.r, sigma, s.measurement, False)
    if not s.bearing_at(step):
        return Problem(prior, s.slot, s.r, sigma, RANGE, False)
    return cast(Problem, StackedProblem(prior, s.slot, s.r, sigma, s.sigma_bearing, False))


class EstimatorPlanner:
    """The follower's EKF and motion strategy.

    Args:
        scenario: the run's settings.
        strategy: a strategy object (``make_strategy(name, **options)``); it may keep state.
        rng: random stream of randomised strategies (CRM).
        noise: range bias state and robust update (:class:`RealNoise`; default: off).
        sensor_offset: where the range or bearing sensor sits on the follower, [m_x, m_y] (m,
            body frame; None: at its origin, as in the paper). The filter models it exactly
            (:func:`~formopt_ros.core.model.sensor_pose`); the planner's problem does not.

    The filter's state is the pose [x, y, phi] in {L}, followed by the range bias b (m) when
    ``noise.bias_sigma`` > 0 (range only): ``state`` (n,) and ``covariance`` (n, n); ``x`` and
    ``P`` are the pose and its covariance (3,) and (3, 3).
    """

    def __init__(self, scenario: Scenario, strategy: Strategy,
                 rng: np.random.Generator | None = None, noise: RealNoise = RealNoise(),
                 sensor_offset: tuple[float, float] | None = None) -> None:
        self.scenario = scenario
        self.sensor_offset = sensor_offset
        self.strategy = strategy
        self.rng = rng
        self.noise = noise
        self.state, self.covariance = scenario.initial_estimate()
        if scenario.measurement == RANGE_BEARING and (sensor_offset is not None
                                                      or noise != RealNoise()):
            raise ValueError('a range-bearing follower has no sensor offset, bias state or '
                             'robust update yet')
        if noise.bias_sigma > 0.0:
            if scenario.measurement != 'range':
                raise ValueError('a bias state needs range measurements, got '
                                 f'{scenario.measurement!r}')
            self.state = np.append(self.state, 0.0)
            self.covariance = np.pad(self.covariance, (0, 1))
            self.covariance[3, 3] = noise.bias_sigma ** 2
        self.history: deque[StepRecord] = deque(maxlen=HISTORY_LENGTH)
        self.gated_in_a_row = 0
        self._target = scenario.slot
        self._slot = scenario.slot

    @property
    def x(self) -> np.ndarray:
        """The pose estimate [x, y, phi] in {L}, (3,)."""
        return self.state[:3]

    @property
    def P(self) -> np.ndarray:
        """Its covariance (3, 3)."""
        return self.covariance[:3, :3]

    @property
    def planning_sigma(self) -> float:
        """The measurement noise the planner assumes: with a bias state, the bias's variance
        is added to the noise's (the planner's problem has the pose only)."""
        s = self.scenario
        if self.state.size == 3:
            return s.sigma
        return float(np.sqrt(s.sigma ** 2 + self.covariance[3, 3]))

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
        problem = planning_problem(s, step, prior, self.planning_sigma)
        view = EstimatorView(self.x, self.P, self.history,
                             lambda target: self.prior_for(target, leader))
        region = reach_region(s.p_o, s.r, self.x, leader, s.dt, s.kinematics, s.max_speed,
                              s.safety_distance)
        context = PlanContext(step, leader, self.rng, view, s.dt, s.sigma_v, s.sigma_omega,
                              s.kinematics, region, s)
        solution = timed_plan(self.strategy, problem, context)
        self._target = solution.p
        command = motion_commands(self.x, solution.p, s.dt, leader[0][0], leader[0][1],
                                  s.kinematics)
        return StepPlan(step, solution, command)

    def propagate(self, v_f: float, omega_f: float, v_l: float, omega_l: float,
                  dt: float | None = None,
                  noise: tuple[float, float, float, float] | None = None) -> None:
        """EKF propagation over one interval (default: the scenario's sub-step dt, s) with
        follower odometry (v_f m/s, omega_f rad/s) and leader velocity held over it.

        ``noise``: the velocity noise standard deviations of this interval (follower v, omega,
        leader v, omega; m/s and rad/s); default the scenario's.
        """
        s = self.scenario
        dt = s.dt if dt is None else dt
        if noise is None:
            noise = (s.sigma_v, s.sigma_omega, s.sigma_v_leader, s.sigma_omega_leader)
        if self.state.size == 3:
            self.state, self.covariance = propagate(self.state, self.covariance, v_f, omega_f,
                                                    dt, v_l, omega_l, *noise, s.kinematics)
            return
        Phi = transition_matrices(self.x, v_f, omega_f, dt, v_l, omega_l, *noise,
                                  kinematics=s.kinematics)[0]
        pose, pose_covariance = propagate(self.x, self.P, v_f, omega_f, dt, v_l, omega_l,
                                          *noise, s.kinematics)
        covariance = self.covariance.copy()
        covariance[:3, :3] = pose_covariance
        covariance[:3, 3] = covariance[3, :3] = Phi @ self.covariance[:3, 3]
        covariance[3, 3] += self.noise.bias_walk ** 2 * dt
        self.state, self.covariance = np.append(pose, self.state[3]), covariance

    def update(self, step: int, z: Any, variance: Any = None,
               kind: str | None = None) -> UpdateResult:
        """EKF update with a range (m) or bearing (rad) measurement of step ``step``, behind the
        innovation gate (module docstring): a refused measurement leaves x and P as they are.

        'range-bearing' scenarios: z = [d, beta] (2,), NaN where a sensor gave nothing this
        step, and ``variance`` None or (sigma_d^2, sigma_beta^2); both present: one stacked
        update (:func:`~formopt_ros.core.model.ekf_update_stacked`, 2-dof gate), one present: a
        scalar update of that kind. ``kind``: the scalar kind of z when it is not the
        scenario's (used for a single sensor of a range-bearing follower).
        """
        s = self.scenario
        if s.measurement == RANGE_BEARING and kind is None:
            return self._update_stacked(step, z, variance)
        kind = s.measurement if kind is None else kind
        variance = s.sigma ** 2 if variance is None else variance
        if math.isnan(z):
            return UpdateResult(math.nan, math.nan, False, measured=False)
        x, P, innovation, S = ekf_update(self.state, self.covariance, z, kind,
                                         variance, self.sensor_offset)
        nis, use, inflation = innovation_gate(innovation, S, variance, self.gated_in_a_row,
                                              self.noise.gate_nis, self.noise.patience)
        if not use:
            self.gated_in_a_row += 1
            return UpdateResult(innovation, nis, False)
        weight = 1.0
        if self.noise.huber and nis > self.noise.huber ** 2 and inflation == 1.0:
            weight = self.noise.huber / float(np.sqrt(nis))
        if inflation > 1.0 or weight < 1.0:
            x, P, innovation, S = ekf_update(self.state, inflation * self.covariance, z,
                                             kind, variance / weight, self.sensor_offset)
        self.gated_in_a_row = 0
        self.state, self.covariance = x, P
        self.history.append(StepRecord(step, self.x, self.P, self._target))
        return UpdateResult(innovation, nis, True, float(inflation), weight)

    def _update_stacked(self, step: int, z: Any, variance: Any) -> UpdateResult:
        """:meth:`update` of a range-bearing follower: z (2,), NaN for a missing component."""
        s = self.scenario
        d, beta = (float(v) for v in np.asarray(z, dtype=float).reshape(2))
        variances = (s.sigma ** 2, s.sigma_bearing ** 2) if variance is None else \
            (float(variance[0]), float(variance[1]))
        if math.isnan(d) or math.isnan(beta):
            if math.isnan(d) and math.isnan(beta):
                return UpdateResult(np.array([math.nan, math.nan]), math.nan, False,
                                    measured=False)
            if math.isnan(beta):
                return self.update(step, d, variances[0], kind=RANGE)
            return self.update(step, beta, variances[1], kind=BEARING)
        z_pair = np.array([d, beta])
        x, P, innovation, S = ekf_update_stacked(self.state, self.covariance, z_pair, variances)
        nis, use, inflation = stacked_innovation_gate(innovation, S, variances,
                                                      self.gated_in_a_row)
        parts = whitened_squares(innovation, S)
        if not use:
            self.gated_in_a_row += 1
            return UpdateResult(innovation, nis, False, parts=parts)
        if inflation > 1.0:
            x, P, innovation, S = ekf_update_stacked(self.state, inflation * self.covariance,
                                                     z_pair, variances)
        self.gated_in_a_row = 0
        self.state, self.covariance = x, P
        self.history.append(StepRecord(step, self.x, self.P, self._target))
        return UpdateResult(innovation, nis, True, float(inflation), parts=parts)

    def weighted_trace(self) -> float:
        """tr(W P W) of the current covariance, m^2."""
        return weighted_trace(self.P, self._slot)
