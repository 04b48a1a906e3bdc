"""Tests of PERIODIC: the symplectic steady state, the design, the gain and the fallbacks."""
from __future__ import annotations

import math
import os
import subprocess
import sys
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pytest

from formopt_ros.core import solve
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.estimator import EstimatorPlanner
from formopt_ros.core.protocol import held_leader_motion, step_substeps
from formopt_ros.core.reach import CLEARANCE_FRACTION, reach_centre
from formopt_ros.core.scenario import LeaderPath, Scenario, Segment
from formopt_ros.core.simulation import FollowerTruth, run_trial, trial_streams
from formopt_ros.core.strategies import PlanContext, Solution, make_strategy
from formopt_ros.core.strategies.periodic_design import (
    SteadyConditions, arrival_poses, cached_design, clear_cache, cycle_maps,
    design_within_reach, greedy_loop, greedy_target, lft, loop_length, move_map, noise_free_step,
    pair_grid, reach_map, solve_rows)
from formopt_ros.core.strategies.rq import rq_optimum
from formopt_ros.core.strategies.periodic import CHANGING, SETTLE_DECISIONS, describe_design
from formopt_ros.core.strategies.phase_locked import (
    MIN_GAIN, design_phase_locked, path_period, phase_conditions)
from formopt_ros.core.study import StudyConfig, run_study, summarize

SEED = 20251201
#: Allowed relative violation of |p - p_o| <= r.
FEASIBILITY_RTOL = 1e-9


def conditions(kind: str, **overrides: object) -> SteadyConditions:
    """The straight-leader conditions of the paper's scenario with overrides."""
    result = SteadyConditions.from_scenario(Scenario.paper(kind, **overrides))
    assert result is not None
    return result


@pytest.fixture(scope='module', params=['range', 'bearing'])
def paper_design(request: pytest.FixtureRequest):
    """The default (period 4) design of the paper's scenario, from the cache."""
    design, _ = cached_design(conditions(request.param), 4)
    assert design is not None
    return design


# --- the symplectic form of the noise-free recursion ---------------------------------------------
@pytest.mark.parametrize('kind', ['range', 'bearing'])
@pytest.mark.parametrize('omega_l', [0.0, 0.3])
def test_move_map_is_one_ekf_step(kind: str, omega_l: float) -> None:
    """(A P + B)(C P + D)^-1 of a move's 6 x 6 map equals propagate + update (1e-9 relative)."""
    rng = np.random.default_rng(SEED)
    c = replace(conditions(kind), omega_l=omega_l)
    for _ in range(50):
        x = np.array([*(c.slot + 0.3 * rng.normal(size=2)), rng.uniform(-3, 3)])
        target = c.slot + 0.2 * rng.normal(size=2)
        A = rng.normal(size=(3, 3))
        P = 0.01 * (A @ A.T + 0.1 * np.eye(3))
        M, pose = move_map(x, target, c)
        x_next, P_next = noise_free_step(x, P, target, c)
        # 1e-12 m: the same Euler steps.
        np.testing.assert_allclose(pose, x_next, rtol=0, atol=1e-12)
        # 1e-9 relative: a 3x3 solve against the Joseph form of the update.
        np.testing.assert_allclose(lft(M[None], P[None])[0], P_next, rtol=0,
                                   atol=1e-9 * np.abs(P_next).max())


def test_maps_of_a_locked_cycle_equal_each_move_alone() -> None:
    """Along an S-curve each move of a cycle has its own leader velocity; the cycle's maps,
    computed in one batch with a velocity per move, equal each move's map computed alone with
    its own conditions (1e-14 relative: the same operations, element by element)."""
    s_curve = Scenario.paper('range', max_speed=2.0,
                             leader=LeaderPath('s-curve', 1.0, amplitude=0.5, period=2.0))
    phases = phase_conditions(s_curve, 10)
    rng = np.random.default_rng(SEED)
    points = phases[0].slot + 0.1 * rng.normal(size=(10, 2))
    maps = cycle_maps(points, phases)
    for k in range(10):
        start = arrival_poses(points[k - 2][None], points[k - 1][None], phases[k - 1])[0]
        alone = move_map(start, points[k], phases[k])[0]
        np.testing.assert_allclose(maps[k], alone, rtol=0, atol=1e-14 * np.abs(alone).max())


def test_steady_state_is_the_limit_of_the_recursion(paper_design) -> None:
    """Driving the cycle with the EKF's own recursion from P_1|1 for 2000 steps reaches the
    design's steady posteriors (1e-6 relative; the slowest mode decays below 1e-6 by then)."""
    design = paper_design
    c, m = design.conditions, design.period
    x, P = Scenario.paper(c.measurement).initial_estimate()
    for k in range(2000):
        x, P = noise_free_step(x, P, design.points[k % m], c)
    phase = (2000 - 1) % m
    np.testing.assert_allclose(P, design.posteriors[phase], rtol=0,
                               atol=1e-6 * np.abs(P).max())
    assert design.steady_cost == pytest.approx(float(np.mean(design.costs)), rel=1e-12)


def test_future_costs_match_the_recursion(paper_design) -> None:
    """The eigen-decomposition forecast equals stepping the EKF recursion (300 steps, 1e-8)."""
    design = paper_design
    c, m = design.conditions, design.period
    x, P = Scenario.paper(c.measurement).initial_estimate()
    for phase in range(m):
        forecast = design.rollout_costs(x, P, phase, 300)
        xs, Ps, direct = x, P, []
        for k in range(300):
            xs, Ps = noise_free_step(xs, Ps, design.points[(phase + k) % m], c)
            direct.append(weighted_trace(Ps, c.slot))
        # 1e-8 relative: eigenvector solves of a matrix product over up to 75 periods.
        np.testing.assert_allclose(forecast, direct, rtol=1e-8)


def test_design_beats_every_pair_and_greedy(paper_design) -> None:
    """The designed cycle is no worse than any two-point cycle of the 10 degree grid, and its
    steady value is at least 15 % below the greedy optimum's noise-free regime."""
    design = paper_design
    c = design.conditions
    _, pair_costs = pair_grid(c)
    assert design.steady_cost <= pair_costs.min()
    x, P = Scenario.paper(c.measurement).initial_estimate()
    greedy = []
    for _ in range(600):
        x, P = noise_free_step(x, P, greedy_target(x, P, c), c)
        greedy.append(weighted_trace(P, c.slot))
    assert design.steady_cost < 0.85 * np.mean(greedy[-200:])
    assert np.allclose(np.hypot(*(design.points - c.slot).T), c.r, rtol=1e-12)


# --- the gain in a study -------------------------------------------------------------------------
@pytest.mark.parametrize('kind', ['range', 'bearing'])
def test_gain_on_a_seeded_short_study(kind: str) -> None:
    """6 trials x 400 steps, seed 3 (common random numbers): steady value (last 133 steps) at
    least 10 % below RQ (measured: -13.2 % range, -22.6 % bearing), the mean over all steps no
    higher than RQ's (measured -4.8 %, -17.6 %), trial-mean NEES in the 95 % band on >= 80 % of
    the steps (measured 97 %, 97 %)."""
    summary = summarize(run_study(StudyConfig(kind, trials=6, steps=400, seed=3,
                                              strategies=('rq', 'periodic')), jobs=1))
    rq, periodic = summary['strategies']['rq'], summary['strategies']['periodic']
    assert periodic['steady_trace'] <= 0.90 * rq['steady_trace']
    assert periodic['mean_trace'] <= rq['mean_trace']
    assert periodic['nees_in_band'] >= 0.8


def test_a_wide_range_disc_keeps_the_cycle_clear_of_the_leader() -> None:
    """Range, r = 0.9 and 0.95 |p_o|: the four-point boundary cycle would come 0.26 and 0.11 m
    from the leader, where the filter of a follower playing it turns inconsistent (flagged:
    trial-mean NEES 14 and 5.9 over 50 trials x 600 steps). Each design keeps
    CLEARANCE_FRACTION |p_o| (0.45 m) from the leader; at 0.9, 20 trials x 300 steps, seed 0
    (the old cycle's trial 17 diverged by step 40): nothing flagged, steady tr(W P W) at least
    20 % below RQ's (measured -30 % over 600 steps)."""
    for fraction in (0.9, 0.95):
        scenario = Scenario.paper('range', r=fraction * math.sqrt(5.0))
        design = cached_design(SteadyConditions.from_scenario(scenario), 4)[0]
        assert design is not None
        assert np.min(np.hypot(*design.points.T)) >= CLEARANCE_FRACTION * math.sqrt(5.0)
        assert '0.447 m clear of the leader' in describe_design(scenario, {})
    summary = summarize(run_study(StudyConfig('range', trials=20, steps=300, seed=0,
                                              strategies=('rq', 'periodic'),
                                              scenario={'r': 0.9 * math.sqrt(5.0)}), jobs=1))
    assert summary['consistency']['flagged'] == {}
    rq, periodic = summary['strategies']['rq'], summary['strategies']['periodic']
    assert periodic['steady_trace'] <= 0.8 * rq['steady_trace']


# --- feasibility and fallbacks -------------------------------------------------------------------
def drive(scenario_at: Callable[[int], Scenario], steps: int, options: dict[str, object],
          skip_updates: range = range(0)) -> list[tuple[Solution, Scenario, np.ndarray]]:
    """Run the Sec. V loop with PERIODIC; ``scenario_at(k)`` may change the scenario the
    estimator plans with at step k (its noise, slot...), ``skip_updates`` drops measurements.

    Returns per step (solution, scenario of the step, planning prior of the paper's problem).
    """
    scenario = scenario_at(1)
    noise, planner_rng = trial_streams(SEED, 0)
    truth = FollowerTruth(scenario, noise)
    strategy = make_strategy('periodic', **options)
    estimator = EstimatorPlanner(scenario, strategy, planner_rng)
    latest = scenario.leader.velocity(0, scenario.dt)
    out = []
    for k in range(1, steps + 1):
        scenario = scenario_at(k)
        estimator.scenario = truth.scenario = scenario
        leader = held_leader_motion(latest)
        prior = estimator.prior_for(scenario.slot, leader)
        plan = estimator.plan(k, leader)
        out.append((plan.solution, scenario, prior))
        for j, substep in enumerate(step_substeps(k)):
            latest = v_l, omega_l = scenario.leader.velocity(substep, scenario.dt)
            v, omega = plan.command.linear[j], plan.command.angular[j]
            truth.execute(v, omega, v_l, omega_l)
            estimator.propagate(v, omega, v_l, omega_l)
        z = truth.measure()
        if k not in skip_updates:
            estimator.update(k, z)
    return out


def assert_feasible(records: list[tuple[Solution, Scenario, np.ndarray]]) -> None:
    """Every chosen point lies in its step's disc (relative tolerance FEASIBILITY_RTOL)."""
    for solution, scenario, _ in records:
        distance = math.hypot(*(solution.p - scenario.slot))
        assert distance <= scenario.r * (1 + FEASIBILITY_RTOL), (solution, scenario)


TURN = LeaderPath(kind='segments', segments=(Segment(20.0, 1.0), Segment(6.0, 1.0, 0.4),
                                             Segment(1000.0, 1.0)))


@pytest.mark.parametrize('kind', ['range', pytest.param('bearing', marks=pytest.mark.slow)])
@pytest.mark.parametrize('overrides', [
    {'r': 1e-3 * math.sqrt(5)}, {'r': 0.95 * math.sqrt(5)}, {'r': 0.3 * math.sqrt(5)},
    {'leader': TURN}, {'leader': LeaderPath('s-curve', 1.0, amplitude=0.5, period=2.0)},
    {'leader': LeaderPath.constant(0.0)}, {'sigma_v': 0.0, 'sigma_omega': 0.0}],
    ids=['tiny-r', 'r-near-slot-distance', 'r-30%', 'turn', 's-curve', 'leader-stopped',
         'no-odometry-noise'])
def test_never_leaves_the_disc(kind: str, overrides: dict[str, object]) -> None:
    """200 steps (period 2, testing every 5 steps so the cycle is joined early where it pays):
    every point in the disc, whatever the geometry or the leader motion."""
    scenario = Scenario.paper(kind, **overrides)
    trial = run_trial(scenario, 'periodic', SEED, 0, 200, {'period': 2, 'check_every': 5})
    distance = np.hypot(*(trial.waypoints - scenario.slot).T)
    assert np.all(distance <= scenario.r * (1 + FEASIBILITY_RTOL))
    assert np.all(np.isfinite(trial.weighted_trace))


@pytest.mark.parametrize('kind', ['range', 'bearing'])
def test_noise_change_mid_run_replans_and_stays_feasible(kind: str) -> None:
    """The sensor noise triples at step 250: greedy at once (the conditions changed), one
    re-plan once they held SETTLE_DECISIONS decisions, another cycle joined later, and every
    point inside the disc. (Scaling every noise by the same
    factor would scale the whole Riccati recursion and keep the same cycle.)"""
    base = Scenario.paper(kind)
    noisy = replace(base, sigma=3 * base.sigma)
    records = drive(lambda k: base if k < 250 else noisy, 450, {'period': 2})
    assert_feasible(records)
    modes = [solution.details['mode'] for solution, _, _ in records]
    assert 'pattern' in modes[:249]
    held = 249 + SETTLE_DECISIONS - 1
    assert {s.details['reason'] for s, _, _ in records[249:held]} == {CHANGING}
    assert records[held - 1][0].details['replans'] == 0
    assert records[held][0].details['replans'] == 1 and modes[held] == 'greedy'
    assert 'pattern' in modes[250:]
    before = {tuple(np.round(s.p, 9)) for s, _, _ in records[200:249] if s.details['mode']
              == 'pattern'}
    after = {tuple(np.round(s.p, 9)) for s, _, _ in records[-40:] if s.details['mode']
             == 'pattern'}
    assert before and after and before != after


@pytest.mark.parametrize('kind', ['range', 'bearing'])
def test_leader_speed_change_replans(kind: str) -> None:
    """The leader slows from 1 to 0.6 m/s at 20 s: the first decision that expects the new
    speed plays greedy (the velocity changed), the SETTLE_DECISIONS-th re-plans (it held), and
    every point stays inside the disc."""
    scenario = Scenario.paper(kind, leader=LeaderPath(
        kind='segments', segments=(Segment(20.0, 1.0), Segment(1000.0, 0.6))))
    records = drive(lambda k: scenario, 300, {'period': 2})
    assert_feasible(records)
    replans = [s.details['replans'] for s, _, _ in records]
    first = replans.index(1) + 1
    change = first - SETTLE_DECISIONS + 1               # the first step expecting 0.6 m/s
    assert velocity(scenario, change)[0] == 0.6 and velocity(scenario, change - 1)[0] == 1.0
    assert {s.details['reason'] for s, _, _ in records[change - 1:first - 1]} == {CHANGING}
    assert records[first - 1][0].details['reason'] != CHANGING and replans[-1] == 1


@pytest.mark.parametrize('kind', ['range', 'bearing'])
def test_greedy_while_the_leader_velocity_changes_then_a_cycle_for_the_turn(kind: str) -> None:
    """The leader turns from 20 s to 26 s (steps 201-260): the decisions that expect a new
    velocity (the turn, its end) are RQ's exact optimum (same point to 1e-12 m), flagged as
    changing, until it held SETTLE_DECISIONS decisions; then a design for it (a cycle in the
    leader's frame for the arc, the straight cycle again after it), and a cycle is played
    before, during and after the turn."""
    scenario = Scenario.paper(kind, leader=TURN)
    records = drive(lambda k: scenario, 450, {'period': 2})
    assert_feasible(records)
    changing = [k for k, (s, _, _) in enumerate(records, 1) if s.details['reason'] == CHANGING]
    # the planner holds the leader velocity of the last sub-step of the previous step
    expected = [velocity(scenario, k) for k in range(1, 451)]
    starts = [k for k in range(2, 451) if expected[k - 1] != expected[k - 2]]
    assert len(starts) == 2
    assert changing == [k for start in starts for k in range(start, start + SETTLE_DECISIONS - 1)]
    for k in changing:
        solution, _, prior = records[k - 1]
        assert solution.details['mode'] == 'greedy'
        np.testing.assert_allclose(solution.p, rq_optimum(replace_problem(scenario, prior)).p,
                                   rtol=0, atol=1e-12)
    last = records[-1][0].details
    assert last['changing_fallbacks'] == len(changing) and last['replans'] == 2
    modes = [s.details['mode'] for s, _, _ in records]
    assert 'pattern' in modes[:200] and 'pattern' in modes[starts[0] + SETTLE_DECISIONS:260]
    assert 'pattern' in modes[starts[1] + SETTLE_DECISIONS:]


@pytest.mark.parametrize('kind', ['range', 'bearing'])
def test_a_cycle_in_the_leader_frame_beats_greedy_on_an_arc(kind: str) -> None:
    """Leader on an arc at 0.3 rad/s, no speed limit: PERIODIC's cycle (designed in the
    leader's frame) ends at least 15 % below RQ (mean tr(W P W) over steps 301-400, one seeded
    trial; measured -22 % for bearing and -45 % for range over ten trials, docs/lookahead.md),
    and its filter stays consistent (mean NEES below 5 over those steps)."""
    scenario = Scenario.paper(kind, leader=LeaderPath('arc', 1.0, 0.3))
    greedy, cycle = (run_trial(scenario, name, SEED, 0, 400) for name in ('rq', 'periodic'))
    assert cycle.weighted_trace[300:].mean() < 0.85 * greedy.weighted_trace[300:].mean()
    assert cycle.nees[300:].mean() < 5.0


def test_arc_under_a_speed_limit_the_forecast_holds() -> None:
    """Range follower, leader on an arc at 0.3 rad/s, 1.75 m/s limit: the cycle within reach
    (its moves checked against the reach disc carried round by the leader's turn) is played
    and its forecast holds: the mean tr(W P W) over steps 301-400 (one seeded trial) within
    5 % of the design's steady value (+1.4 % over ten trials; +24 % when the reach disc was
    only shifted, as behind a straight leader) and below RQ's (-7.7 % over ten trials,
    docs/lookahead.md)."""
    scenario = Scenario.paper('range', leader=LeaderPath('arc', 1.0, 0.3), max_speed=1.75)
    conditions = SteadyConditions.from_scenario(scenario)
    assert conditions is not None and conditions.limited
    design = cached_design(conditions, 4)[0]
    assert design is not None
    greedy, cycle = (run_trial(scenario, name, SEED, 0, 400) for name in ('rq', 'periodic'))
    played = cycle.weighted_trace[300:].mean()
    assert abs(played / design.steady_cost - 1.0) < 0.05
    assert played < greedy.weighted_trace[300:].mean()


@pytest.mark.parametrize('kinematics', ['exact', 'euler'])
def test_reach_map_is_the_reach_centre(kinematics: str) -> None:
    """The affine reach map of a design equals reach_centre at 50 random poses (any heading)
    behind a leader on an arc, to 1e-12 m."""
    scenario = replace(Scenario.paper('range', leader=LeaderPath('arc', 1.0, 0.3)),
                       kinematics=kinematics)
    conditions = SteadyConditions.from_scenario(scenario)
    assert conditions is not None
    offset, linear = reach_map(conditions)
    rng = np.random.default_rng(3)
    poses = rng.uniform([-5.0, -5.0, -math.pi], [5.0, 5.0, math.pi], (50, 3))
    for pose in poses:
        expected = reach_centre(pose, conditions.leader, conditions.dt, kinematics)
        np.testing.assert_allclose(offset + linear @ pose[:2], expected, rtol=0, atol=1e-12)


def test_a_singular_subspace_is_no_steady_state() -> None:
    """solve_rows gives NaN for a singular row and the solution of the others (the range
    design with exact kinematics at 1.75 m/s met one and raised LinAlgError)."""
    A = np.stack([2.0 * np.eye(3), np.zeros((3, 3))])
    B = np.ones((2, 3, 3))
    out = solve_rows(A, B)
    np.testing.assert_allclose(out[0], 0.5 * np.ones((3, 3)), rtol=0, atol=1e-15)
    assert np.all(np.isnan(out[1]))


@pytest.mark.slow
def test_design_within_reach_with_exact_kinematics_at_1_75() -> None:
    """The configuration that raised: a range follower, exact kinematics, 1.75 m/s, behind a
    straight leader; the design is made and beats greedy's loop."""
    scenario = replace(Scenario.paper('range', max_speed=1.75), kinematics='exact')
    conditions = SteadyConditions.from_scenario(scenario)
    assert conditions is not None
    design = design_within_reach(conditions)
    assert design is not None and design.steady_cost < greedy_loop(conditions)[0]


@pytest.mark.parametrize('max_speed, yaw_rate', [(1.55, 0.0), (1.5, -0.1)])
def test_greedy_holding_a_point_is_not_a_loop_of_one(max_speed: float, yaw_rate: float) -> None:
    """Range under a speed limit: greedy holds a point for up to 8 steps before it jumps back;
    its loop is 22 (19) steps, not 1, and the design from it beats greedy by more than 5 %
    (the two-target test called the hold a loop of one, and PERIODIC played greedy)."""
    leader = LeaderPath('arc', 1.0, yaw_rate) if yaw_rate else LeaderPath()
    conditions = SteadyConditions.from_scenario(
        Scenario.paper('range', max_speed=max_speed, leader=leader))
    assert conditions is not None
    greedy, targets = greedy_loop(conditions)
    assert loop_length(targets, 40, conditions) == (22 if yaw_rate == 0.0 else 19)
    design = design_within_reach(conditions)
    assert design is not None and design.steady_cost < 0.95 * greedy


@pytest.mark.slow
def test_a_design_within_reach_does_not_depend_on_the_blas_threads() -> None:
    """Bearing behind an arc of 0.3 rad/s under 2 m/s, greedy without a loop: one BLAS thread
    (a Dask worker's) and two end SLSQP at different digits; both processes design a cycle
    about 24 % below greedy (with one thread SLSQP stopped outside the reach and PERIODIC
    played greedy, so a study's numbers hung on --jobs)."""
    code = ("from formopt_ros.core.scenario import LeaderPath, Scenario\n"
            "from formopt_ros.core.strategies import periodic_design as pd\n"
            "c = pd.SteadyConditions.from_scenario(Scenario.paper('bearing', max_speed=2.0, "
            "leader=LeaderPath('arc', 1.0, 0.3)))\n"
            "design = pd.design_within_reach(c)\n"
            "print(design.steady_cost / pd.greedy_loop(c)[0] if design else 'none')\n")
    for threads in ('1', '2'):
        env = {**os.environ, 'OMP_NUM_THREADS': threads, 'OPENBLAS_NUM_THREADS': threads}
        done = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                              env=env, timeout=300)
        assert done.returncode == 0, done.stderr
        assert 0.7 < float(done.stdout) < 0.8, (threads, done.stdout)


def velocity(scenario: Scenario, step: int) -> tuple[float, float]:
    """The leader velocity the planner expects for ``step``: that of the last sub-step of the
    step before."""
    return scenario.leader.velocity(step_substeps(step - 1)[-1], scenario.dt)


def replace_problem(scenario: Scenario, prior: np.ndarray):
    """The paper's one-step problem of ``scenario`` with planning prior ``prior``."""
    from formopt_ros.core.cost import Problem
    return Problem(prior, scenario.slot, scenario.r, scenario.sigma, scenario.measurement)


def test_returns_to_greedy_when_measurements_are_lost() -> None:
    """30 lost range measurements while on the cycle: tr(W P W) leaves its forecast by more than
    the tolerance, the strategy returns to greedy, then joins the cycle again."""
    scenario = Scenario.paper('range')
    records = drive(lambda k: scenario, 500, {'period': 2}, skip_updates=range(200, 230))
    modes = [s.details['mode'] for s, _, _ in records]
    assert modes[190] == 'pattern'
    assert records[-1][0].details['returns_to_greedy'] >= 1
    assert 'greedy' in modes[200:240] and modes[-1] == 'pattern'


def test_one_off_solve_is_the_greedy_optimum() -> None:
    """Without an estimator (``solve``) the strategy is RQ."""
    P = np.diag([0.02, 0.03, 1e-3])
    for kind, p_o, sigma in (('range', np.array([-1.0, -2.0]), 0.1),
                             ('bearing', np.array([-1.0, 2.0]), 0.02)):
        ours = solve(P, p_o, 0.2, sigma, measurement=kind, method='periodic')
        rq = solve(P, p_o, 0.2, sigma, measurement=kind, method='rq')
        np.testing.assert_array_equal(ours.p, rq.p)
        assert ours.details['mode'] == 'greedy' and ours.method == 'periodic'


def test_no_cycle_without_odometry_noise() -> None:
    """Without process noise no cycle has a steady state: greedy, flagged."""
    assert cached_design(conditions('range', sigma_v=0.0, sigma_omega=0.0), 2)[0] is None
    scenario = Scenario.paper('range', sigma_v=0.0, sigma_omega=0.0)
    records = drive(lambda k: scenario, 5, {'period': 2})
    assert all(s.details['reason'].startswith('no periodic steady state')
               for s, _, _ in records)


@pytest.mark.parametrize('options', [{'period': 1}, {'period': 7}, {'check_every': 0},
                                     {'tolerance': -1.0}, {'horizon': 2.5}])
def test_options_are_validated(options: dict[str, object]) -> None:
    """Out-of-range options raise ValueError naming the strategy."""
    with pytest.raises(ValueError, match='periodic'):
        make_strategy('periodic', **options)


def test_plan_context_default_is_greedy() -> None:
    """A PlanContext without estimator (as solve builds it) never joins a cycle."""
    strategy = make_strategy('periodic')
    P = np.diag([0.02, 0.03, 1e-3])
    problem = replace_problem(Scenario.paper('bearing'), P)
    for step in range(1, 30):
        assert strategy.plan(problem, PlanContext(step=step)).details['mode'] == 'greedy'


def test_command_prints_cycle_and_timings(tmp_path, capsys: pytest.CaptureFixture) -> None:
    """formopt-periodic prints the cycle, the design time and the decision times."""
    from formopt_ros.cli.periodic import main
    assert main(['--measurement', 'range', '--period', '2', '--repeats', '1', '--trials', '1',
                 '--steps', '30']) == 0
    out = capsys.readouterr().out
    assert 'offline design: median' in out and 'cycle at [' in out
    assert 'online decision over 1 x 30 steps' in out


@pytest.mark.slow
def test_docs_figure(tmp_path) -> None:
    """The docs figure (short runs, cycles of 2) is written and not empty."""
    pytest.importorskip('matplotlib')
    from formopt_ros.analysis.periodic import periodic_figure
    path = periodic_figure([Scenario.paper('range'), Scenario.paper('bearing')],
                           tmp_path / 'figure.png', steps=80, period=2)
    assert path.stat().st_size > 10_000


def test_any_change_of_the_disc_replans() -> None:
    """r grows by one part in 10^5 (far below replan_tolerance) while on the cycle: the
    strategy plays greedy at once and re-plans once the new disc held SETTLE_DECISIONS decisions
    rather than keep points of the old disc, and stays feasible."""
    base = Scenario.paper('bearing')
    wider = replace(base, r=base.r * (1 + 1e-5))
    records = drive(lambda k: base if k < 150 else wider, 200, {'period': 2})
    assert_feasible(records)
    assert records[148][0].details['mode'] == 'pattern'
    assert records[149][0].details['reason'] == CHANGING
    assert records[149 + SETTLE_DECISIONS - 1][0].details['replans'] == 1


def test_prepare_designs_before_the_first_plan() -> None:
    """prepare(scenario) designs and caches the cycle (a realtime node calls it at start), so
    the first plan finds it cached; other strategies' prepare does nothing."""
    scenario = Scenario.paper('range')
    clear_cache()
    make_strategy('periodic').prepare(scenario)
    conditions = SteadyConditions.from_scenario(scenario)
    assert conditions is not None
    design, computed = cached_design(conditions, 4)
    assert design is not None and not computed
    make_strategy('rq').prepare(scenario)


def fast_s_curve(kind: str, **overrides: object) -> Scenario:
    """The paper's scenario behind an S-curve of period 2 s (20 steps), at 2 m/s unless told."""
    return Scenario.paper(kind, leader=LeaderPath('s-curve', 1.0, amplitude=0.5, period=2.0),
                          **{'max_speed': 2.0, **overrides})


def test_only_a_whole_number_of_steps_repeats() -> None:
    """The S-curve of period 10 s repeats every 100 steps (dt 0.05 s, two sub-steps); a period
    of 10.03 s, one of 0.5 s (5 steps: the velocity changes too much within a step for the
    design), a straight leader and an arc do not count as repeating."""
    dt = 0.05
    assert path_period(LeaderPath('s-curve', 1.0, amplitude=0.5, period=10.0), dt) == 100
    assert path_period(LeaderPath('s-curve', 1.0, amplitude=0.5, period=1.0), dt) == 10
    assert path_period(LeaderPath('s-curve', 1.0, amplitude=0.5, period=10.03), dt) is None
    assert path_period(LeaderPath('s-curve', 1.0, amplitude=0.5, period=0.5), dt) is None
    assert path_period(LeaderPath('straight', 1.0), dt) is None
    assert path_period(LeaderPath('arc', 1.0, yaw_rate=0.1), dt) is None


@pytest.mark.parametrize('kind', ['range', pytest.param('bearing', marks=pytest.mark.slow)])
def test_the_phase_locked_cycle_costs_what_it_says(kind: str) -> None:
    """Played on the noise-free recursion from the paper's initial covariance for 30 periods,
    with each step's own leader velocity, the locked cycle's last period has the design's steady
    cost (1e-9 relative), at least MIN_GAIN below greedy's (measured: 8.8 % range, 23.5 %
    bearing); every move lies in its reach disc and every point in the slot's disc, except
    where greedy could not reach the disc, and then no farther from the slot than greedy."""
    scenario = fast_s_curve(kind)
    design = design_phase_locked(scenario)
    assert design is not None and design.period == 20
    assert design.steady_cost <= (1.0 - MIN_GAIN) * design.greedy_cost
    phases = phase_conditions(scenario, design.period)
    x, P = np.array([*scenario.p_o, 0.0]), np.diag([0.1, 0.1, 4e-4])
    costs, greedy = [], []
    for _ in range(30):
        for k, phase in enumerate(phases):
            x, P = noise_free_step(x, P, design.points[k], phase)
            costs.append(weighted_trace(P, phase.slot))
    assert np.mean(costs[-20:]) == pytest.approx(design.steady_cost, rel=1e-9)
    x, P = np.array([*scenario.p_o, 0.0]), np.diag([0.1, 0.1, 4e-4])
    for _ in range(20):
        for k, phase in enumerate(phases):
            target = greedy_target(x, P, phase)
            greedy.append(np.hypot(*(target - phase.slot)))
            x, P = noise_free_step(x, P, target, phase)
    allowed = np.maximum(scenario.r, greedy[-20:]) * (1.0 + 1e-9)
    assert np.all(np.hypot(*(design.points - phases[0].slot).T) <= allowed)
    moves = [design.points[k] - (linear @ design.points[k - 1] + offset)
             for k, (offset, linear) in enumerate(map(reach_map, phases))]
    assert np.max(np.hypot(*np.array(moves).T)) <= phases[0].reach * (1.0 + 1e-9)


def test_no_locked_cycle_where_greedy_never_settles() -> None:
    """A leader turning on the spot (speed 0) leaves greedy's noise-free covariance growing:
    no design (at once, not after SLSQP's iterations), and PERIODIC plays greedy."""
    scenario = Scenario.paper('bearing', leader=LeaderPath('s-curve', 0.0, amplitude=0.5,
                                                           period=2.0))
    assert design_phase_locked(scenario) is None
    np.testing.assert_array_equal(run_trial(scenario, 'periodic', SEED, 0, 40).waypoints,
                                  run_trial(scenario, 'rq', SEED, 0, 40).waypoints)


@pytest.mark.parametrize('kind', ['range', pytest.param('bearing', marks=pytest.mark.slow)])
def test_behind_a_repeating_path_greedy_then_the_locked_cycle(kind: str) -> None:
    """One seeded trial of 200 steps behind the 2 s S-curve at 2 m/s: the first period (20
    steps) is RQ's, bit for bit, then the locked cycle (projected onto the reachable set where
    it is out of reach) leaves it; over steps 101-200 the mean tr(W P W) is at least 5 % below
    RQ's."""
    scenario = fast_s_curve(kind)
    periodic, greedy = run_trial(scenario, 'periodic', SEED, 0, 200), \
        run_trial(scenario, 'rq', SEED, 0, 200)
    np.testing.assert_array_equal(periodic.waypoints[:20], greedy.waypoints[:20])
    assert not np.allclose(periodic.waypoints[20:40], greedy.waypoints[20:40])
    assert np.mean(periodic.weighted_trace[100:]) <= 0.95 * np.mean(greedy.weighted_trace[100:])


@pytest.mark.slow
def test_an_arc_design_within_reach_with_exact_kinematics_runs() -> None:
    """Range behind an arc (0.1 rad/s) under 1.5 m/s with exact kinematics, the defaults of
    formation files and nodes: some candidate cycles of the design have no steady state (their
    period map overflows); they are left out, the design is made and the run goes on (it ended
    in LinAlgError before step 1)."""
    scenario = Scenario.paper('range', leader=LeaderPath('arc', 1.0, yaw_rate=0.1),
                              max_speed=1.5, kinematics='exact')
    with np.errstate(all='raise'):
        run = run_trial(scenario, 'periodic', 0, 0, 3)
    assert np.all(np.isfinite(run.weighted_trace))
    assert describe_design(scenario, {}).startswith('cycle of ')


def test_a_cycle_that_repeats_itself_is_named_by_its_points() -> None:
    """Range behind an arc at 0.1 rad/s without a limit: the best four-step cycle is two points
    played twice ([a, b, a, b], 0.55 of greedy noise-free); the study's note names two points
    and their two angles, not four."""
    scenario = Scenario.paper('range', leader=LeaderPath('arc', 1.0, yaw_rate=0.1))
    note = describe_design(scenario, {})
    assert note.startswith('cycle of 2 boundary points at [')
    angles = note.split('[')[1].split(']')[0].split(', ')
    assert len(angles) == 2 and abs(float(angles[0]) - float(angles[1])) > 90.0


@pytest.mark.parametrize('period, reason', [
    (7.25, 'not a whole number of steps of 0.1 s'), (0.5, 'outside the 10-400 steps')])
def test_an_s_curve_without_a_locked_cycle_says_why(period: float, reason: str) -> None:
    """An S-curve whose period is no whole number of steps, or too short, gets no locked cycle,
    and the study's line says which (it said only that the velocity changes)."""
    scenario = Scenario.paper('bearing', leader=LeaderPath('s-curve', 1.0, amplitude=0.5,
                                                           period=period))
    assert reason in describe_design(scenario, {})


def test_prepare_designs_the_cycle_locked_to_a_repeating_path() -> None:
    """A node prepares its strategy before step 1: PERIODIC designs the cycle locked to an
    S-curve then (cached), so that no lockstep step spends the 10-40 s of a design."""
    scenario = Scenario.paper('bearing', leader=LeaderPath('s-curve', 1.0, amplitude=0.5,
                                                           period=2.0), max_speed=2.0)
    design_phase_locked.cache_clear()
    make_strategy('periodic').prepare(scenario)
    assert design_phase_locked.cache_info().currsize == 1
    design_phase_locked(scenario)
    assert design_phase_locked.cache_info().hits == 1
