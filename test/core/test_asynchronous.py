"""The asynchronous estimator: the lockstep stream in any order, real timing, real UWB noise."""
from __future__ import annotations

import math

import numpy as np
import pytest

from formopt_ros.core.asynchronous import AsyncEstimator, AsyncSettings
from formopt_ros.core.controller import Limits, twist_toward
from formopt_ros.core.estimator import EstimatorPlanner, RealNoise
from formopt_ros.core.field import Base, Camera, Radio, simulate_field
from formopt_ros.core.model import normalized_estimation_error, state_difference, wrap_angle
from formopt_ros.core.protocol import SUBSTEPS, Timebase, step_substeps
from formopt_ros.core.scenario import LeaderPath, Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.core.strategies import make_strategy
from formopt_ros.core.study import nees_band

MS = 1_000_000


def lockstep_stream(scenario: Scenario, steps: int, seed: int) -> tuple[list, object]:
    """The inputs a lockstep estimator receives in one trial of RAM: (kind, stamp, values)."""
    result = run_trial(scenario, 'ram', seed, 0, steps)
    timebase = Timebase.from_dt(scenario.dt)
    stream = []
    for k in range(steps):
        for j, n in enumerate(step_substeps(k + 1)):
            stamp = timebase.substep_end(n)
            stream.append(('follower', stamp, tuple(result.commands[k, j])))
            stream.append(('leader', stamp, tuple(result.leader[k, j])))
        stream.append(('measurement', timebase.measurement_stamp(k + 1),
                       (float(result.measurements[k]), scenario.sigma ** 2)))
    return stream, result


@pytest.mark.parametrize('kinematics', ['euler', 'exact'])
@pytest.mark.parametrize('shuffle', [False, True])
def test_fed_the_lockstep_stream_it_equals_lockstep(kinematics: str, shuffle: bool) -> None:
    """Each message of a lockstep run, in order or with the three topics interleaved at
    random (each topic's own order kept, as over DDS), gives run_trial's estimate and
    covariance after every step (1e-9; identical in order)."""
    scenario = Scenario.paper('bearing', kinematics=kinematics,
                              leader=LeaderPath('s-curve', 1.0, amplitude=0.5, period=4.0))
    steps = 80
    stream, reference = lockstep_stream(scenario, steps, seed=5)
    if shuffle:
        rng = np.random.default_rng(2)
        topics = {kind: [m for m in stream if m[0] == kind] for kind in
                  ('follower', 'leader', 'measurement')}
        stream = []
        while any(topics.values()):
            kind = rng.choice([k for k, queue in topics.items() if queue])
            stream.append(topics[kind].pop(0))
    tracker = AsyncEstimator(EstimatorPlanner(scenario, make_strategy('ram')), 0)
    applied = []
    for kind, stamp, values in stream:
        reason = tracker.add_measurement(stamp, *values) if kind == 'measurement' else \
            tracker.add_odometry(kind, stamp, *values)
        assert reason is None
        applied += tracker.advance()
    assert len(applied) == steps and tracker.counters.bridged == 0
    for k, outcome in enumerate(applied):
        np.testing.assert_allclose(outcome.x, reference.estimate[k], rtol=0, atol=1e-9)
        np.testing.assert_allclose(outcome.P, reference.covariance[k], rtol=0, atol=1e-9)
    if not shuffle:
        assert np.array_equal(applied[-1].x, reference.estimate[-1])


def test_late_duplicate_and_missing_inputs_are_counted() -> None:
    """A measurement or odometry stamped before the estimate's time is dropped, a repeated
    stamp too, and a measurement whose odometry never comes is applied after the reorder lag
    with the last twist carried on (bridged), each counted."""
    scenario = Scenario('range', (-1.0, -2.0), 0.2, 0.1)
    tracker = AsyncEstimator(EstimatorPlanner(scenario, make_strategy('mtf')), 0,
                             AsyncSettings(reorder_lag_ns=100 * MS))
    for stamp in range(20 * MS, 220 * MS, 20 * MS):
        assert tracker.add_odometry('follower', stamp, 1.0, 0.0) is None
        assert tracker.add_odometry('leader', stamp, 1.0, 0.0) is None
    assert tracker.add_odometry('leader', 200 * MS, 1.0, 0.0) is not None     # duplicate
    assert tracker.add_measurement(190 * MS, 2.236, 0.01) is None
    assert len(tracker.advance()) == 1 and tracker.time_ns == 190 * MS
    assert tracker.add_measurement(150 * MS, 2.236, 0.01) is not None         # late
    assert tracker.add_odometry('follower', 180 * MS, 1.0, 0.0) is not None   # late
    assert tracker.add_measurement(400 * MS, 2.236, 0.01) is None
    assert tracker.advance(now_ns=450 * MS) == []          # waits: 400 + lag is not reached
    applied = tracker.advance(now_ns=500 * MS)
    assert len(applied) == 1 and applied[0].bridged
    c = tracker.counters
    assert (c.duplicates, c.late_measurements, c.late_odometry, c.bridged) == (1, 1, 1, 1)
    assert c.measurements == 2 and c.odometry == 20
    assert tracker.add_measurement(600 * MS, 2.2, 0.01) is None
    assert 'duplicate' in tracker.add_measurement(600 * MS, 2.2, 0.01)
    assert tracker.counters.duplicates == 2
    # a late leader message still tells its current twist, on which the leader is carried on
    tracker.add_odometry('leader', 450 * MS, 0.7, 0.1)
    assert tracker.timelines['leader'].last == (0.7, 0.1)


def test_odometry_may_carry_its_own_noise() -> None:
    """A message's own noise equal to the scenario's changes nothing (bit for bit); a larger
    one, on either robot, gives a larger covariance; a split interval's pieces add up to the
    whole message's noise (1e-6 relative: the pieces' linearisation points differ)."""
    scenario = Scenario('range', (-1.0, -2.0), 0.2, 0.1, sigma_v_leader=0.05,
                        sigma_omega_leader=0.02)

    def run(follower_noise: tuple | None, leader_noise: tuple | None,
            stamps: tuple[int, ...] = (50 * MS,)) -> np.ndarray:
        tracker = AsyncEstimator(EstimatorPlanner(scenario, make_strategy('mtf')), 0)
        tracker.add_odometry('follower', 100 * MS, 1.0, 0.0, follower_noise)
        tracker.add_odometry('leader', 100 * MS, 1.0, 0.0, leader_noise)
        for stamp in stamps:
            tracker.propagate_to(stamp)
        tracker.propagate_to(100 * MS)
        return tracker.estimator.P

    plain = run(None, None)
    assert np.array_equal(run((0.2, 0.1), (0.05, 0.02)), plain)
    assert np.trace(run((0.4, 0.1), None)) > np.trace(plain)
    assert np.trace(run(None, (0.5, 0.2))) > np.trace(plain)
    np.testing.assert_allclose(run(None, None, (10 * MS, 30 * MS, 70 * MS)), run(None, None, ()),
                               rtol=1e-6)


def test_estimate_at_leaves_the_state_alone() -> None:
    """The estimate propagated to a later stamp equals what propagation would give, and the
    state stays at its time."""
    scenario = Scenario('bearing', (-1.0, 2.0), 0.2, 0.02)
    tracker = AsyncEstimator(EstimatorPlanner(scenario, make_strategy('mtf')), 0)
    for stamp in range(10 * MS, 110 * MS, 10 * MS):
        tracker.add_odometry('follower', stamp, 1.2, 0.3)
        tracker.add_odometry('leader', stamp, 1.0, 0.1)
    x, P = tracker.estimate_at(100 * MS)
    assert tracker.time_ns == 0 and tracker.pending()['follower_odometry'] == 10
    tracker.propagate_to(100 * MS)
    np.testing.assert_array_equal(x, tracker.estimator.x)
    np.testing.assert_array_equal(P, tracker.estimator.P)


def zigzag(slot: np.ndarray, side: np.ndarray, period: float):
    """A target that alternates between slot +- side every period/2 s."""
    def target(t: float) -> np.ndarray:
        return slot + side * (1.0 if math.floor(2.0 * t / period) % 2 == 0 else -1.0)
    return target


def field_trial(seed: int, leader: LeaderPath, noise: RealNoise, duration: float = 60.0,
                sensor: Radio | Camera = Radio(),
                offset: tuple[float, float] | None = None,
                outage: tuple[float, float] | None = None,
                poses: bool = False,
                settings: AsyncSettings = AsyncSettings()) -> tuple[np.ndarray, float, dict]:
    """One simulated real run (odometry 50 Hz each; by default ranges 30 Hz, bias 0.1 m, 2 %
    outliers of +1-3 m, 1 % dropouts, +-5 ms jitter); the follower zigzags around its slot
    under speed and acceleration limits, steered on its true pose. With a camera the filter
    takes its bearings turned by the mount's yaw, at ``offset``. ``outage`` (start, end s):
    no leader odometry then; ``poses``: the odometry carries the robots' poses. Returns the
    NEES per applied measurement, the RMS position error (m) after the first 100, and the
    counters (with 'stamps' and 'errors': each NEES's stamp, ns, and position error, m, and
    'watch_failed': whether the consistency watch raised its ERROR)."""
    rng = np.random.default_rng(seed)
    slot = np.array([-1.0, -2.0])
    kind = 'range' if isinstance(sensor, Radio) else 'bearing'
    scenario = Scenario(kind, tuple(slot), 0.5, sensor.sigma, leader=leader, sigma_v=0.1,
                        sigma_omega=0.05, initial_covariance=(0.05, 0.05, 0.01))
    target = zigzag(slot, 0.4 * np.array([2.0, -1.0]) / math.sqrt(5.0), 2.0)
    limits, previous = Limits(speed=2.5, yaw_rate=4.0, acceleration=4.0), [0.0, 0.0]

    def command(t: float, pose: np.ndarray) -> tuple[float, float]:
        previous[:] = twist_toward(pose, target(t), leader.velocity(int(t / 0.02), 0.02), 0.5,
                                   limits, tuple(previous), 0.02)
        return previous[0], previous[1]

    x0, P0 = scenario.initial_estimate()
    start = x0 + np.linalg.cholesky(P0) @ rng.normal(size=3)
    run = simulate_field(duration, start,
                         lambda t: leader.velocity(int(round(t / 0.02)), 0.02), command, rng,
                         Base(50.0, 0.0, scenario.sigma_v, scenario.sigma_omega),
                         Base(50.0, 0.007), sensor)
    tracker = AsyncEstimator(EstimatorPlanner(scenario, make_strategy('mtf'), noise=noise,
                                              sensor_offset=offset), 0, settings)
    turn = sensor.mount[2] if isinstance(sensor, Camera) else 0.0
    lost = outage or (0.0, 0.0)
    inputs = [(s, 0, 'follower', (v, w)) for s, v, w in run.follower_odometry] + \
        [(s, 0, 'leader', (v, w)) for s, v, w in run.leader_odometry
         if not lost[0] <= s / 1e9 < lost[1]] + \
        [(s + 2 * MS, 1, 'z', (z,)) for s, z in run.ranges]      # measurements arrive 2 ms late
    nees, errors, stamps = [], [], []
    for arrival, _, kind, values in sorted(inputs):
        if kind == 'z':
            tracker.add_measurement(arrival - 2 * MS, float(wrap_angle(values[0] + turn))
                                    if turn else values[0], sensor.sigma ** 2)
        else:
            tracker.add_odometry(kind, arrival, *values,
                                 pose=run.poses[kind][arrival] if poses else None)
        for outcome in tracker.advance(now_ns=arrival):
            truth = run.truth[outcome.stamp_ns]
            nees.append(normalized_estimation_error(truth, outcome.x, outcome.P))
            errors.append(np.hypot(*state_difference(truth, outcome.x)[:2]))
            stamps.append(outcome.stamp_ns)
    counters = tracker.counters.as_dict() | {'outliers': run.outliers, 'ranges': len(run.ranges),
                                             'stamps': stamps, 'errors': np.array(errors),
                                             'watch_failed': tracker.watch.failed}
    return np.array(nees), float(np.sqrt(np.mean(np.square(errors[100:])))), counters


@pytest.mark.slow
@pytest.mark.parametrize('leader', [LeaderPath(), LeaderPath('s-curve', 1.0, amplitude=0.6,
                                                             period=8.0)],
                         ids=['straight', 's-curve'])
def test_real_uwb_noise_needs_the_bias_state_and_huber(leader: LeaderPath) -> None:
    """12 seeded 60 s runs: with the range-bias state and Huber weighting the trial-mean NEES
    (after a 5 s start) lies in the 95 % band of 12 trials on >= 90 % of the ranges and its
    mean within [2.2, 3.6] (one trial alone wanders from 1.2 to 5.6: its heading error drifts
    slowly); the plain filter on 4 of the runs is overconfident (mean above 20). Every range
    is applied and counted; at least 90 % of the outliers are down-weighted or gated."""
    trials = 12
    robust = [field_trial(seed, leader, RealNoise(bias_sigma=0.3, bias_walk=0.002, huber=2.5))
              for seed in range(trials)]
    plain = [field_trial(seed, leader, RealNoise()) for seed in range(4)]
    length = min(len(n) for n, _, _ in robust + plain)
    start = 150                                       # 5 s of ranges at 30 Hz
    mean = np.mean([n[start:length] for n, _, _ in robust], axis=0)
    low, high = nees_band(trials)
    inside = float(np.mean((mean >= low) & (mean <= high)))
    plain_mean = float(np.mean([n[start:length] for n, _, _ in plain]))
    assert 2.2 <= float(np.mean(mean)) <= 3.6 and inside >= 0.9, (np.mean(mean), inside)
    assert plain_mean > 20.0, plain_mean
    for _, _, counters in robust:
        assert counters['measurements'] == counters['ranges']
        assert counters['downweighted_measurements'] + counters['gated_measurements'] >= \
            0.9 * counters['outliers']
        assert counters['late_measurements'] == counters['bridged'] == 0


def test_gated_non_line_of_sight_ranges_are_no_inconsistency() -> None:
    """10 % of the ranges non-line-of-sight (+1-3 m), the node's robust filter (bias state,
    Huber, 5-sigma gate), four seeded 20 s runs: the gate refuses the outliers, the filter
    stays consistent (mean NEES below 4) and the watch raises no ERROR; with the simulated
    filter's rule (10 % gated share) it called runs inconsistent and stopped the base."""
    noise = RealNoise(bias_sigma=0.3, bias_walk=0.002, huber=2.5, gate=5.0)
    radio = Radio(outlier_rate=0.1)
    runs = [field_trial(seed, LeaderPath(), noise, 20.0, radio) for seed in range(4)]
    for _, _, counters in runs:
        assert counters['gated_measurements'] >= 0.5 * counters['outliers'], counters
        assert not counters['watch_failed'], counters
    assert float(np.mean([np.mean(nees[150:]) for nees, _, _ in runs])) < 4.0
    strict = [field_trial(seed, LeaderPath(), noise, 20.0, radio,
                          settings=AsyncSettings(max_gated_share=0.1))[2]['watch_failed']
              for seed in range(4)]
    assert sum(strict) >= 2, strict


def test_after_a_link_outage_the_odometry_poses_bridge_it() -> None:
    """No leader odometry from 4 s to 9 s of an S-curve, three seeds: the filter carries the
    leader on its last twist meanwhile, and its updates are made with motion that did not
    happen. With the poses the odometry messages carry, the first leader message after the
    outage makes the state again from the state before it, moved by both robots' odometry
    (once per run): from 11 s on every run is consistent (mean NEES below 6, RMS error below
    0.15 m). On twists alone they are not (mean NEES 14-5900; one is 3 m off)."""
    leader = LeaderPath('s-curve', 1.0, amplitude=0.6, period=8.0)
    noise = RealNoise(bias_sigma=0.3, bias_walk=0.002, huber=2.5)

    def after(seed: int, poses: bool) -> tuple[float, float, int]:
        nees, _, counters = field_trial(seed, leader, noise, 20.0, outage=(4.0, 9.0),
                                        poses=poses)
        late = np.array(counters['stamps']) > 11e9
        return (float(np.mean(nees[late])),
                float(np.sqrt(np.mean(np.square(counters['errors'][late])))),
                counters['outage_resets'])

    for seed in (1, 2, 4):
        nees, rms, resets = after(seed, True)
        assert nees < 6.0 and rms < 0.15 and resets == 1, (seed, nees, rms, resets)
    blind = [after(seed, False)[0] for seed in (1, 2, 4)]
    assert min(blind) > 10.0, blind


@pytest.mark.slow
def test_a_mounted_camera_needs_its_lever_arm() -> None:
    """Bearings from a camera 0.25 m ahead and 0.1 m left of the base, turned 0.4 rad: with
    the mount in the model the trial-mean NEES of 6 seeded 30 s runs (after 5 s) lies in the
    95 % band on >= 85 % of the bearings; taken at the base's origin, the filter is
    overconfident (mean NEES above 10)."""
    camera = Camera(mount=(0.25, 0.1, 0.4), sigma=0.01)
    trials, start = 6, 75
    for offset, consistent in (((0.25, 0.1), True), (None, False)):
        runs = [field_trial(seed, LeaderPath(), RealNoise(), 30.0, camera, offset)[0]
                for seed in range(trials)]
        length = min(len(n) for n in runs)
        mean = np.mean([n[start:length] for n in runs], axis=0)
        if consistent:
            low, high = nees_band(trials)
            inside = float(np.mean((mean >= low) & (mean <= high)))
            assert inside >= 0.85 and 2.0 <= float(np.mean(mean)) <= 4.0, (inside, mean.mean())
        else:
            assert float(np.mean(mean)) > 10.0, mean.mean()


def test_twist_toward_respects_the_limits() -> None:
    """Random poses and targets: the command stays within speed, yaw rate and the steps the
    accelerations allow, never reverses, and turns toward the needed direction."""
    rng = np.random.default_rng(4)
    limits = Limits(speed=1.5, yaw_rate=2.0, acceleration=1.0, yaw_acceleration=5.0)
    previous = (0.0, 0.0)
    for _ in range(2000):
        x = np.array([*rng.uniform(-3, 3, size=2), rng.uniform(-math.pi, math.pi)])
        v, omega = twist_toward(x, rng.uniform(-3, 3, size=2), (rng.uniform(0, 2), 0.0), 0.5,
                                limits, previous, 0.02)
        assert 0.0 <= v <= limits.speed and abs(omega) <= limits.yaw_rate
        assert abs(v - previous[0]) <= 0.02 * limits.acceleration + 1e-12
        assert abs(omega - previous[1]) <= 0.02 * limits.yaw_acceleration + 1e-12
        previous = (v, omega)
    with pytest.raises(ValueError, match='speed'):
        Limits(speed=0.0)
    assert SUBSTEPS == 2


def test_an_unknown_range_bias_costs_more_than_a_quarter_on_a_straight_leader() -> None:
    """The posterior Cramer-Rao bound (the noise-free covariance at the truth) of the UWB
    follower of config/formation_real_interfaces.yaml on a straight leader: with an unknown
    bias (prior 0.1 m) its position bound is above 1.25x the bias-free one for the planner and
    for the widest tangential swing the disc allows, and the bias stays at 90 % of its prior or
    more: the disc's directions to the leader do not reveal it (docs/real_robots.md)."""
    import importlib.util
    from pathlib import Path
    path = Path(__file__).resolve().parents[2] / 'scripts' / 'measure_bias_bound.py'
    spec = importlib.util.spec_from_file_location('measure_bias_bound', path)
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    scenario = script.uwb_scenario({'kind': 'straight', 'speed': 1.0})
    ideal, _ = script.bound(scenario, 'rq', 0.0, 300, 1)
    for policy in ('rq', 'swing'):
        with_bias, bias = script.bound(scenario, policy, 0.1, 300, 1)
        assert with_bias > 1.7 * ideal and bias > 0.09, (policy, with_bias / ideal, bias)
