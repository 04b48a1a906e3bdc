"""PERIODIC (beyond the paper): greedy while far from the periodic regime, then the best cycle.

RAM and RQ minimise the cost after the next measurement only. Over many steps a cycle of a few
boundary points does better (docs/periodic_pattern.md): in the Sec. V protocol the best cycle of
four points has a steady tr(W P W) 18 % (range) and 23 % (bearing) below the greedy optimum's
regime, but a cycle started from a large covariance can be much worse than greedy during the
transient, and it may take hundreds of steps to pay. So this strategy

1. designs, once per set of conditions (sensor, slot, r, noise levels, leader velocity, dt), the
   cycle of ``period`` boundary points with the lowest exact periodic steady state
   (:mod:`.periodic_design`, cached per process);
2. plays the exact greedy optimum (RQ) and, every ``check_every`` steps, forecasts with the
   noise-free recursion the tr(W P W) summed over a look-ahead (until the cycle settles, at
   most ``horizon`` steps) of: joining the cycle now (best phase), ``check_every`` greedy steps
   and then the cycle, and greedy throughout; it joins when now is the cheapest;
3. follows the cycle, watching the covariance: when it exceeds its forecast by more than
   ``tolerance`` (lost measurements, a disturbance) it returns to 2.

Under a speed limit or a safety distance the design is a cycle within reach when the boundary
cycle does not fit (:func:`.periodic_design.design_within_reach`: every move in the reach
disc, every point outside the safety distance); a cycle point out of reach of the estimated
pose is projected onto the step's reachable set (:func:`.region.plan_within`). A range cycle
that would come closer to the leader than 0.2 |p_o| (a wide disc) is designed within reach
too, with that clearance as its safety distance (:func:`.periodic_design.design_for`). When the
leader keeps one velocity (v, omega), straight or on an arc, the conditions are stationary in its
frame and the cycle is designed for them (it rotates with the leader). When the expected
leader velocity is not constant over the step, or the conditions changed (the slot or r, or a
noise level, the leader velocity, dt or the limits by more than ``replan_tolerance``) and have
not yet held for SETTLE_DECISIONS decisions, or the cycle does not fit the reachable set, it
plays greedy; once new conditions held, it designs again (or takes the cached design) and
starts over at 2. Behind a leader whose path repeats every N steps (an S-curve, whose velocity
never holds) it plays greedy for the first N steps and then a cycle of N points locked to the
path's phase (:mod:`.phase_locked`), when one beats greedy.
Every point is either RQ's (feasible) or a point of the cycle, in the problem's own disc.
``Solution.details`` says which mode chose the point and why, and counts re-plans, returns to
greedy, decisions made greedy while the leader's velocity changed, and switch tests.
"""
from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from formopt_ros.core.cost import Problem
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.strategies.base import (
    OptionSpec, PlanContext, Solution, Strategy, make_solution)
from formopt_ros.core.strategies.periodic_design import (
    PatternDesign, SteadyConditions, cached_design, fits_reach, greedy_target, noise_free_step)
from formopt_ros.core.strategies.phase_locked import (
    design_phase_locked, path_period, unlocked_reason)
from formopt_ros.core.strategies.rq import rq_optimum

if TYPE_CHECKING:
    from formopt_ros.core.scenario import Scenario

GREEDY = 'greedy'
#: The reason of a greedy decision while the leader's expected velocity changes.
CHANGING = "the leader's velocity changes"
#: Decisions new conditions must hold (within replan_tolerance) before a cycle is designed for
#: them (1 s at the paper's 0.1 s step).
SETTLE_DECISIONS = 10
PATTERN = 'pattern'
#: The interval between switch tests grows at most 2**6 = 64-fold.
MAX_BACKOFF_DOUBLINGS = 6


def no_cycle_reason(conditions: SteadyConditions) -> str:
    """Why no cycle was designed for ``conditions`` (PERIODIC then plays greedy)."""
    if conditions.limited:
        return 'no cycle within reach beats greedy'
    return 'no periodic steady state, or no cycle clear of the leader beats greedy'


def steady_conditions(problem: Problem, context: PlanContext) -> SteadyConditions | None:
    """The stationary conditions of this step, or None when the leader is not expected to
    keep one velocity (v, omega) over the step."""
    velocities = set(context.leader_velocities)
    if len(velocities) != 1:
        return None
    (v_l, omega_l), = velocities
    region = context.region
    return SteadyConditions(problem.measurement, (float(problem.p_o[0]), float(problem.p_o[1])),
                            float(problem.r), float(problem.sigma), float(v_l), float(omega_l),
                            context.dt, context.sigma_v, context.sigma_omega, context.kinematics,
                            float(getattr(problem, 'sigma_bearing', 0.0)),
                            region.radius if region is not None else math.inf,
                            region.safety if region is not None else 0.0)


class PeriodicPattern(Strategy):
    """PERIODIC: greedy transient, then the cycle of boundary points with the best steady state.

    See the module docstring. One object per follower: it keeps the design, the mode and the
    phase of the cycle.
    """

    name = 'periodic'
    stateless = False
    OPTIONS = {
        'period': OptionSpec(4, 'points in the cycle of boundary points', 2, 6),
        'check_every': OptionSpec(10, 'steps between tests whether joining the cycle pays',
                                  1, 1000),
        'horizon': OptionSpec(500, 'longest look-ahead of that test, steps', 10, 100000),
        'tolerance': OptionSpec(0.25, 'relative excess of tr(W P W) over its prediction that '
                                'sends the follower back to greedy', 0.01, 100.0),
        'replan_tolerance': OptionSpec(1e-3, 'relative change of a noise level, the leader '
                                       'speed or dt that makes a new design (any change of '
                                       'the slot or r does)', 0.0, 1.0),
    }

    def __init__(self, **options: object) -> None:
        super().__init__(**options)
        self.conditions: SteadyConditions | None = None     # those of the design adopted
        #: the conditions that held over the last decisions without a change, and how many
        self.streak: tuple[SteadyConditions | None, int] = (None, 0)
        self.design: PatternDesign | None = None
        #: the scenario whose locked cycle (designed once per process) was last played
        self.locked_for: Scenario | None = None
        self.mode = GREEDY
        self.phase = 0                     # phase of the cycle reached by the last target
        self.next_check = 1                # step of the next switch test
        self.backoff = 0                   # doublings of the interval between tests
        self.predicted: np.ndarray = np.empty(0)   # tr(W P W) predicted after each step
        self.joined_at = 0                 # step whose target was the first of the cycle
        self.approaching = False           # within the first period after joining
        self.counts = {'replans': 0, 'returns_to_greedy': 0, 'changing_fallbacks': 0,
                       'switch_tests': 0, 'unpaid_tests': 0}

    # --- the decision ------------------------------------------------------------------------
    def prepare(self, scenario: Scenario) -> None:
        """Design (and cache) the cycle for the conditions ``scenario`` starts in, or the
        cycle locked to its leader path when the path repeats, so that no plan spends the
        design time (about 1 s; 10-40 s for a locked cycle, which inside a lockstep step
        outlasted the peers' stall timeout)."""
        if path_period(scenario.leader, scenario.dt) is not None:
            design_phase_locked(scenario)
            return
        conditions = SteadyConditions.from_scenario(scenario)
        if conditions is not None:
            cached_design(conditions, int(self.settings['period']))

    def plan(self, problem: Problem, context: PlanContext) -> Solution:
        """The next position: RQ's, or the cycle's next point (see the module docstring)."""
        if context.estimator is None:
            return self._greedy(problem, 'no estimator: one-off problem')
        locked = self._phase_locked(problem, context)
        if locked is not None:
            return locked
        conditions = steady_conditions(problem, context)
        settled = self._settled(conditions)
        if conditions is None or not settled:
            self.mode = GREEDY
            self.counts['changing_fallbacks'] += 1
            return self._greedy(problem, CHANGING)
        designed = self._adopt(conditions, context.step)
        if self.design is None:
            return self._greedy(problem, no_cycle_reason(conditions), designed)
        if not fits_reach(self.design.points, conditions):
            self.mode = GREEDY
            return self._greedy(problem, 'the cycle does not fit the reachable set', designed)
        x, P = context.estimator.x, context.estimator.P
        if self.mode == PATTERN and conditions.limited and self.approaching:
            # under a speed limit the first points of the cycle may be out of reach (projected):
            # the forecast holds from where the follower is one period after joining
            if context.step - self.joined_at >= self.design.period:
                self.approaching = False
                self.joined_at = context.step
                self.predicted = self.design.future_costs(self.phase, P, self._horizon())
        elif self.mode == PATTERN and not self._on_track(P, context.step):
            self.mode = GREEDY
            self.counts['returns_to_greedy'] += 1
            self.backoff = min(self.backoff + 1, MAX_BACKOFF_DOUBLINGS)
            self.next_check = context.step + int(self.settings['check_every']) * 2 ** self.backoff
        if self.mode == GREEDY and context.step >= self.next_check:
            self._switch_test(x, P, context.step)
        if self.mode == GREEDY:
            return self._greedy(problem, 'transient', designed)
        self.phase = (self.phase + 1) % self.design.period
        point = self.design.points[self.phase].copy()
        if not problem.feasible(point):     # the design's disc is the problem's: never seen
            self.mode = GREEDY
            return self._greedy(problem, 'cycle point outside the disc', designed)
        return make_solution(problem, point, self.name, True,
                             details=self._details(PATTERN, 'cycle', designed))

    def _phase_locked(self, problem: Problem, context: PlanContext) -> Solution | None:
        """Behind a leader whose path repeats every N steps (an S-curve): greedy over its
        first period, then the point of this step's phase of the cycle locked to the path
        (:mod:`.phase_locked`, designed at step N + 1), or greedy when none beats greedy.
        None when the path does not repeat."""
        scenario = context.scenario
        period = None if scenario is None else path_period(scenario.leader, scenario.dt)
        if scenario is None or period is None:
            return None
        self.mode = GREEDY
        if context.step <= period:
            return self._greedy(problem, "transient: the leader path's first period")
        # the first time, or the scenario changed (a node's parameters): report the design
        designed, self.locked_for = self.locked_for != scenario, scenario
        found = design_phase_locked(scenario)
        time_s = found.design_time_s if designed and found else None
        if found is None:
            return self._greedy(problem, 'no cycle locked to the leader path beats greedy',
                                time_s)
        self.phase = (context.step - 1) % period
        point = found.points[self.phase].copy()
        if context.region is None and not problem.feasible(point):   # not seen: designed in it
            return self._greedy(problem, 'cycle point outside the disc', time_s)
        self.mode = PATTERN
        return make_solution(problem, point, self.name, True, details=self._details(
            PATTERN, 'cycle locked to the leader path', time_s))

    def _greedy(self, problem: Problem, reason: str,
                design_time_s: float | None = None) -> Solution:
        solution = rq_optimum(problem, self.name)
        solution.details.update(self._details(GREEDY, reason, design_time_s))
        return solution

    def _details(self, mode: str, reason: str, design_time_s: float | None) -> dict[str, Any]:
        details: dict[str, Any] = {'mode': mode, 'reason': reason, 'phase': self.phase,
                                   **self.counts}
        if design_time_s is not None:
            details['design_time_s'] = design_time_s
        return details

    # --- conditions and design ---------------------------------------------------------------
    def _settled(self, conditions: SteadyConditions | None) -> bool:
        """True when ``conditions`` may be designed for: they are the first ones, or those of
        the design adopted, or they held (within ``replan_tolerance``) for SETTLE_DECISIONS
        decisions (None, a velocity not constant over the step, never). A leader whose
        velocity keeps changing (an S-curve, even near its peaks) gets no design that holds for
        only a few steps."""
        if conditions is None:
            self.streak = (None, 0)
            return False
        tolerance = float(self.settings['replan_tolerance'])
        first, count = self.streak
        same = first is not None and first.close_to(conditions, tolerance)
        self.streak = (first, count + 1) if same else (conditions, 1)
        return self.conditions is None or self.conditions.close_to(conditions, tolerance) or \
            self.streak[1] >= SETTLE_DECISIONS

    def _adopt(self, conditions: SteadyConditions, step: int) -> float | None:
        """Design (or fetch) the cycle when the conditions changed; its design time when it was
        computed now, else None."""
        tolerance = float(self.settings['replan_tolerance'])
        if self.conditions is not None and self.conditions.close_to(conditions, tolerance):
            return None
        if self.conditions is not None:
            self.counts['replans'] += 1
        self.conditions = conditions
        start = time.perf_counter()
        self.design, computed = cached_design(conditions, int(self.settings['period']))
        self.mode, self.next_check, self.backoff = GREEDY, step, 0
        return time.perf_counter() - start if computed else None

    # --- switching ---------------------------------------------------------------------------
    def _horizon(self) -> int:
        assert self.design is not None
        return max(2 * int(self.settings['check_every']),
                   min(self.design.horizon, int(self.settings['horizon'])))

    def _best_entry(self, x: np.ndarray, P: np.ndarray, steps: int) -> tuple[float, int,
                                                                             np.ndarray]:
        """(summed cost, phase, predicted costs) of the best phase to join the cycle at."""
        assert self.design is not None
        best: tuple[float, int, np.ndarray] | None = None
        for phase in range(self.design.period):
            costs = self.design.rollout_costs(x, P, phase, steps)
            total = float(costs.sum())
            if np.isfinite(total) and (best is None or total < best[0]):
                best = (total, phase, costs)
        if best is None:
            return np.inf, 0, np.empty(0)
        return best

    def _switch_test(self, x: np.ndarray, P: np.ndarray, step: int) -> None:
        """Join the cycle now when, predicted noise-free and summed over the look-ahead, that
        beats both ``check_every`` greedy steps followed by the cycle (so the greedy transient
        is not cut short) and greedy throughout (so the cycle pays within the look-ahead);
        greedy throughout is extrapolated from the mean of the last two greedy steps (the
        greedy optimum settles into a zigzag). Else test again: ``check_every`` steps later,
        doubled for every return to greedy and every test in which the cycle did not pay within
        the look-ahead (at most MAX_BACKOFF_DOUBLINGS times)."""
        assert self.design is not None and self.conditions is not None
        self.counts['switch_tests'] += 1
        delay = int(self.settings['check_every'])
        steps = self._horizon()
        try:
            now, phase, costs = self._best_entry(x, P, steps)
            greedy_costs = []
            for _ in range(delay):
                x, P = noise_free_step(x, P, greedy_target(x, P, self.conditions),
                                       self.conditions)
                greedy_costs.append(weighted_trace(P, self.conditions.slot))
            spent = float(np.sum(greedy_costs))
            later = spent + self._best_entry(x, P, steps - delay)[0]
            greedy_throughout = spent + (steps - delay) * float(np.mean(greedy_costs[-2:]))
        except np.linalg.LinAlgError:
            now, later, greedy_throughout = np.inf, 0.0, 0.0
        if np.isfinite(now) and now <= min(later, greedy_throughout):
            self.mode, self.joined_at, self.predicted = PATTERN, step, costs
            self.approaching = True
            self.phase = (phase - 1) % self.design.period     # plan() advances to `phase`
            return
        if not now <= greedy_throughout:
            self.counts['unpaid_tests'] += 1
            self.backoff = min(self.backoff + 1, MAX_BACKOFF_DOUBLINGS)
        self.next_check = step + delay * 2 ** self.backoff

    def _on_track(self, P: np.ndarray, step: int) -> bool:
        """False when tr(W P W) of the posterior of step - 1 exceeds its prediction by more
        than ``tolerance`` (relative); beyond the prediction, the cycle's steady value."""
        assert self.design is not None
        index = step - 1 - self.joined_at
        if index < 0:
            return True
        expected = (self.predicted[index] if index < len(self.predicted)
                    else self.design.costs[self.phase])
        actual = weighted_trace(P, self.design.conditions.slot)
        return actual <= (1.0 + float(self.settings['tolerance'])) * expected


def repeat_length(points: np.ndarray, scale: float) -> int:
    """The least d dividing the number of points (m, 2) with point k + d equal to point k
    (within 1e-9 ``scale``, m) for every k: m when the cycle does not repeat itself."""
    m = len(points)
    return next(d for d in range(1, m + 1) if m % d == 0 and np.allclose(
        points, np.roll(points, -d, axis=0), rtol=0.0, atol=1e-9 * scale))


def describe_design(scenario: Scenario, options: dict[str, object]) -> str:
    """One line on the cycle PERIODIC plays in ``scenario`` and the time its design took (from
    this process's cache: free after a run, designed now otherwise)."""
    if path_period(scenario.leader, scenario.dt) is not None:
        locked = design_phase_locked(scenario)
        if locked is None:
            return 'no cycle locked to the repeating leader path beats greedy (greedy throughout)'
        return (f'cycle of {locked.period} points locked to the leader path, played after its '
                f'first period: steady tr(W P W) {locked.steady_cost:.6g} m^2 against greedy\'s '
                f'{locked.greedy_cost:.6g} m^2 (noise-free), designed in '
                f'{locked.design_time_s:.1f} s (once per scenario and worker process)')
    conditions = SteadyConditions.from_scenario(scenario)
    if conditions is None:
        reason = unlocked_reason(scenario.leader, scenario.dt)
        because = f', and {reason}' if reason else ''
        return f"the leader's velocity changes from the start{because}: no cycle (greedy while " \
            'it does)'
    period = int(PeriodicPattern(**options).settings['period'])
    design = cached_design(conditions, period)[0]
    if design is None:
        return f'{no_cycle_reason(conditions)} (greedy throughout)'
    shortest = repeat_length(design.points, conditions.r)    # [a, b, a, b] is a, b twice
    angles = ', '.join(f'{a:.1f}' for a in np.degrees(design.angles[:shortest]))
    radii = np.hypot(*(design.points - conditions.slot).T)
    if not np.allclose(radii, conditions.r, rtol=1e-9):       # designed within reach
        held = 'within reach'
        if design.conditions.safety > conditions.safety:      # a range cycle held off
            held = f'{design.conditions.safety:.3g} m clear of the leader' + \
                (' and within reach' if conditions.limited else '')
        return (f'cycle of {shortest} points {held} (angles [{angles}] deg around '
                f'p_o), steady tr(W P W) {design.steady_cost:.6g} m^2, designed offline in '
                f'{design.design_time_s:.2f} s (once per scenario and worker process)')
    return (f'cycle of {shortest} boundary points at [{angles}] deg around p_o, steady '
            f'tr(W P W) {design.steady_cost:.6g} m^2, settles in {design.horizon} steps; '
            f'designed offline in {design.design_time_s:.2f} s ({design.evaluations} cycles '
            'evaluated; once per scenario and worker process)')
