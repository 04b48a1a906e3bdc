"""Fault injection into running formations: another run on the same topics, mismatched
scenarios, foreign and poisoned messages, node restarts in both modes. Each case asserts its
outcome: refused and counted, stopped with the documented exit code and one line, or resumed
with the same numbers."""
from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import numpy as np
import pytest
from formopt_interfaces.msg import Measurement, Waypoint
from harness.ros import namespace, node_scenario, topic

from formopt_ros.core.model import normalized_estimation_error
from formopt_ros.core.protocol import SUBSTEPS, seconds_to_ns
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.ros import conversions, qos
from formopt_ros.ros.guard import INTRUDER_GRACE, MISMATCH_EXIT, MISMATCH_LINGER

TOL = 1e-9                 # lockstep: the same arithmetic as the pure simulation
SEED = 5


# --- scenario handshake -------------------------------------------------------------------------
@pytest.mark.parametrize('name,value,shown', [
    ('dt', 0.02, ('0.02', '0.05')),
    ('formation_slot', [-1.0, -2.5], ('[-1.0, -2.5]', '[-1.0, -2.0]')),
    ('range_sigma', 0.2, ('0.2', '0.1')),
    ('seed', 3, ('3', '5'))])
def test_mismatched_scenario_stops_the_run_at_start(formation, name: str, value: object,
                                                    shown: tuple[str, str]) -> None:
    """An estimator configured differently from its follower_sim stops before waypoint 1 with
    exit code 2 and one line naming the parameter and both values; so does follower_sim (and
    the leader when dt differs, its own parameter)."""
    run = formation({'measurement': 'range', 'seed': SEED, 'steps': 20},
                    per_node={'estimator_planner': {name: value}})
    nodes = [run.estimator, run.follower] + ([run.leader] if name == 'dt' else [])
    assert run.spin_until(lambda: all(n.finished for n in nodes), 20.0), \
        [(n.get_name(), n.error) for n in nodes]
    for node in nodes:
        assert node.exit_code == 2 and f'parameter {name!r} is ' in node.error, node.error
        assert all(text in node.error for text in shown) and '\n' not in node.error
    assert run.estimator.published['waypoint'] == 0 and run.follower.executed == 0
    assert run.estimator.summary()['ok'] is False


def test_mismatch_in_separate_processes_is_one_line(node_process) -> None:
    """The three nodes started as a user does, the estimator with another dt: every node exits
    2, the estimator's stderr ends with one 'error:' line naming dt and both values, no
    traceback anywhere."""
    params = {'measurement': 'bearing', 'steps': 10, 'recorders': 0}
    leader = node_process('leader_sim', params)
    sim = node_process('follower_sim', params)
    estimator = node_process('estimator_planner', dict(params, dt=0.02))
    codes = [p.wait(timeout=60.0) for p in (estimator, sim, leader)]
    assert codes == [2, 2, 2], [p.stderr for p in (estimator, sim, leader)]
    errors = [line for line in estimator.stderr.splitlines()
              if line.startswith('estimator_planner: error:')]
    assert len(errors) == 1 and "parameter 'dt' is 0.02 in" in errors[0], estimator.stderr
    assert f'{namespace("follower")}/follower_sim' in errors[0] or \
        f'{namespace("leader")}/leader_sim' in errors[0]
    assert not any('Traceback' in p.stderr for p in (estimator, sim, leader))


def test_a_peer_matched_late_still_reads_the_mismatch(formation) -> None:
    """An estimator that disagrees with its leader while its follower_sim is not up yet does
    not leave at once (its latched description would leave with it and the follower_sim would
    wait forever): it stops once the late follower_sim is matched, which then stops with exit
    code 2 too; without a late peer it stops after MISMATCH_LINGER s."""
    params = {'measurement': 'range', 'steps': 20}
    run = formation(params, follower=False, per_node={'estimator_planner': {'dt': 0.02}})
    assert run.spin_until(lambda: run.estimator.guard.failure is not None, 20.0)
    assert not run.estimator.finished and run.estimator.guard.failure.code == MISMATCH_EXIT
    sim = run._make('follower_sim', 'follower', params)
    run.nodes.append(sim)
    assert run.spin_until(lambda: run.estimator.finished and sim.finished, 20.0), sim.error
    for node in (run.estimator, sim):
        assert node.exit_code == MISMATCH_EXIT and "parameter 'dt' is " in node.error


def test_a_mismatch_without_readers_stops_after_the_linger(formation) -> None:
    """With no follower_sim ever matched the estimator still stops: MISMATCH_LINGER s after it
    read the leader's disagreeing description (2 s of slack for the 0.05 s timer and load)."""
    run = formation({'measurement': 'range', 'steps': 20}, follower=False,
                    per_node={'estimator_planner': {'dt': 0.02}})
    assert run.spin_until(lambda: run.estimator.guard.failure is not None, 20.0)
    started = time.monotonic()
    assert run.spin_until(lambda: run.estimator.finished, MISMATCH_LINGER + 10.0)
    assert MISMATCH_LINGER - 0.1 <= time.monotonic() - started <= MISMATCH_LINGER + 2.0
    assert run.estimator.exit_code == MISMATCH_EXIT


# --- another run, strays ------------------------------------------------------------------------
def test_a_second_publisher_stops_the_run(formation) -> None:
    """A stray publisher on the measurement topic (a second run with the same names, or a
    forgotten `ros2 topic pub`) stops the estimator with exit code 1 after the grace period,
    naming the topic and the publishing nodes; the summary is not ok."""
    run = formation({'measurement': 'range', 'steps': 10**6})
    stray = run.probe.create_publisher(Measurement, topic('follower', 'measurement'),
                                       qos.STREAM)
    started = time.monotonic()
    assert run.spin_until(lambda: run.estimator.finished, INTRUDER_GRACE + 20.0)
    waited = time.monotonic() - started
    assert run.estimator.exit_code == 1 and waited >= INTRUDER_GRACE - 0.5
    error = run.estimator.error
    assert f"2 publishers on {topic('follower', 'measurement')}" in error
    assert '/test_probe' in error and 'follower_sim' in error
    summary = run.estimator.summary()
    assert summary['ok'] is False and summary['error'] == error
    run.probe.destroy_publisher(stray)


def test_messages_of_another_run_are_refused_and_counted(formation) -> None:
    """run_id 'run_a': a measurement and a waypoint of 'run_b' (otherwise valid: the right
    step, stamp and follower) are refused and counted by every node that reads them, and the
    run equals the clean simulation."""
    steps = 30
    run = formation({'measurement': 'range', 'strategy': 'ram', 'seed': SEED, 'steps': steps,
                     'run_id': 'run_a'})
    meas_pub = run.probe.create_publisher(Measurement, topic('follower', 'measurement'),
                                          qos.STREAM)
    way_pub = run.probe.create_publisher(Waypoint, topic('follower', 'waypoint'), qos.STREAM)
    dt = Scenario.paper('range').dt
    sent: list[int] = []

    def inject() -> None:
        step = run.estimator.session.step
        if not sent and step >= 5:
            k = step + 1
            stamp = conversions.stamp(seconds_to_ns(SUBSTEPS * k * dt))
            meas_pub.publish(conversions.measurement(stamp, 'follower', 'follower', k, 'range',
                                                     2.0, 0.01, 'run_b'))
            waypoint = copy.deepcopy(run.estimator.last_waypoint)
            waypoint.run_id, waypoint.step = 'run_b', k + 1
            way_pub.publish(waypoint)
            sent.append(k)

    assert run.run(timeout=30.0, step=inject) and sent
    assert run.estimator.session.counters.foreign_messages == 1
    assert run.follower.counters['foreign_waypoints'] == 1
    assert run.leader.foreign_waypoints == 1
    assert run.probe.statuses[-1].foreign_messages == 1
    ref = run_trial(node_scenario('range'), 'ram', SEED, 0, steps)
    x, P = run.probe.estimates[-1]
    np.testing.assert_allclose(x, ref.estimate[-1], rtol=0, atol=TOL)


# --- poisoned values and stamps ------------------------------------------------------------------
@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_poisoned_messages_do_not_stall_or_corrupt(formation, mode: str) -> None:
    """A measurement stamped 1e6 s ahead for step k + 100000, one with a range of 1e300 m and
    one with a wrong frame id are refused and counted; one 5 m off at the right step and stamp
    is gated (lockstep: it arrives before the real one, which is then refused). The run
    goes on to its last step with a finite, consistent estimate."""
    steps = 40 if mode == 'lockstep' else 30
    run = formation({'measurement': 'range', 'strategy': 'ram', 'seed': SEED, 'steps': steps,
                     'mode': mode, 'resend_timeout': 0.5})
    pub = run.probe.create_publisher(Measurement, topic('follower', 'measurement'), qos.STREAM)
    dt = Scenario.paper('range').dt
    sent: list[int] = []

    def inject() -> None:
        step = run.estimator.session.step
        if sent or step < 5:
            return
        k = step + 2               # its real measurement cannot have been published yet
        now = run.probe.get_clock().now().nanoseconds
        stamp_ns = seconds_to_ns(SUBSTEPS * k * dt) if mode == 'lockstep' else now + 10**6
        make = conversions.measurement
        stamp = conversions.stamp(stamp_ns)
        pub.publish(make(conversions.stamp(10**15), 'follower', 'follower', k + 100_000,
                         'range', 2.2, 0.01))
        pub.publish(make(stamp, 'follower', 'follower', k, 'range', 1e300, 0.01))
        pub.publish(make(stamp, 'follower/odom', 'follower', k, 'range', 2.2, 0.01))
        if mode == 'lockstep':
            truth = run.follower.truth.x
            pub.publish(make(stamp, 'follower', 'follower', k, 'range',
                             float(np.hypot(*truth[:2])) + 5.0, 0.01))
        sent.append(k)

    assert run.run(timeout=60.0, step=inject), f'stalled at {run.estimator.session.step}'
    counters = run.estimator.session.counters
    assert counters.rejected_measurements >= 3
    if mode == 'lockstep':
        assert counters.gated_measurements == 1
    x, P = run.estimator.session.estimator.x, run.estimator.session.estimator.P
    truth = run.follower.truth.x
    assert np.all(np.isfinite(x)) and normalized_estimation_error(truth, x, P) < 30.0


# --- restarts -----------------------------------------------------------------------------------
def test_lockstep_restarts_resume_exactly(formation, tmp_path: Path) -> None:
    """Each node is killed (no shutdown) and restarted from its checkpoint in turn, the
    estimator, the follower and the leader: every estimate equals the uninterrupted pure
    simulation (1e-9) and the summaries say where each resumed."""
    steps = 45
    run = formation({'measurement': 'bearing', 'strategy': 'crm', 'seed': SEED,
                     'steps': steps, 'resend_timeout': 0.3},
                    per_node={kind: {'checkpoint_path': str(tmp_path / f'{kind}.pkl')}
                              for kind in ('leader_sim', 'follower_sim', 'estimator_planner')})
    for kind, at in (('estimator_planner', 10), ('follower_sim', 20), ('leader_sim', 30)):
        assert run.spin_until(lambda: run.estimator.session.step >= at, 30.0)
        run.restart(kind, 'leader' if kind == 'leader_sim' else 'follower', down=0.2)
    assert run.run(timeout=60.0), f'stalled at {run.estimator.session.step}'
    ref = run_trial(node_scenario('bearing'), 'crm', SEED, 0, steps)
    x, P = run.probe.estimates[-1]
    np.testing.assert_allclose(x, ref.estimate[-1], rtol=0, atol=TOL)
    np.testing.assert_allclose(P, ref.covariance[-1], rtol=0, atol=TOL)
    assert run.estimator.session.step == steps
    assert run.estimator.summary()['resumed']['from_step'] >= 10
    assert run.follower.summary()['resumed']['from_step'] >= 20
    assert run.leader.summary()['resumed']['from_step'] >= 30


def test_an_estimator_restarted_without_checkpoint_rejoins(formation) -> None:
    """Lockstep, no checkpoint: the estimator killed after step 15 comes back at step 0 and
    sends the waypoint of step 1; follower_sim and leader_sim count and name it stale, the
    follower repeats its last step and the estimator rejoins after it, its estimate re-made
    from both robots' odometry poses (consistent with the truth of that moment: the follower
    waits), finishes the run (no hang) and says so in its summary and diagnostics."""
    from formopt_ros.ros.nodes.estimator_planner import REJOIN_INFLATION
    steps = 60
    # resends are not needed here; one on a loaded machine repeats a step whose copies are
    # then refused as duplicates (rejected_odometry 2 in one CI run)
    run = formation({'measurement': 'range', 'strategy': 'ram', 'seed': SEED, 'steps': steps,
                     'resend_timeout': 2.0})
    assert run.spin_until(lambda: run.estimator.session.step >= 15, 30.0)
    run.restart('estimator_planner', down=0.2)
    assert run.spin_until(lambda: run.estimator.rejoined is not None and
                          run.estimator.rejoined['prior_covariance_diagonal'] is not None, 30.0)
    session = run.estimator.session
    prior = normalized_estimation_error(run.follower.truth.x, session.estimator.x,
                                        session.estimator.P)
    assert prior < 7.81, prior                      # the 95 % point of chi-square, 3 dof
    assert run.run(timeout=60.0), f'stalled at {run.estimator.session.step}'
    summary = run.estimator.summary()
    rejoined = summary['rejoined']
    assert summary['ok'] and summary['steps'] == steps and summary['resumed'] is None
    assert 16 <= rejoined['at_step'] < steps and rejoined['heard_from'] == 'follower odometry'
    assert rejoined['dropped_inputs'] >= SUBSTEPS + 1         # the repeated step's inputs
    scenario = node_scenario('range')
    assert all(np.array(rejoined['prior_covariance_diagonal'])
               >= REJOIN_INFLATION * np.array(scenario.initial_covariance))
    assert run.follower.summary()['counters']['stale_waypoints'] >= 1
    assert run.leader.summary()['stale_waypoints'] >= 1
    statuses = run.probe.step_statuses()
    assert (statuses[-1].step, statuses[-1].rejected_odometry) == (steps, 0), \
        run.estimator.session.last_reason
    diagnostic = run.estimator.diagnostic()
    assert f"rejoined at step {rejoined['at_step']}" in diagnostic.message
    nees = normalized_estimation_error(run.follower.truth.x, session.estimator.x,
                                       session.estimator.P)
    assert math.isfinite(nees) and nees < 20.0, nees


def test_realtime_restarts_recover(formation, tmp_path: Path) -> None:
    """Realtime: the estimator is down 0.6 s (the odometry it missed becomes hold sub-steps),
    later the follower is down 0.6 s (it resumes its true pose, parked meanwhile); the run
    reaches its last step with a consistent estimate (NEES < 20) and both report the gap."""
    steps = 70
    run = formation({'measurement': 'range', 'strategy': 'ram', 'seed': SEED, 'steps': steps,
                     'mode': 'realtime', 'resend_timeout': 0.2},
                    per_node={kind: {'checkpoint_path': str(tmp_path / f'{kind}.pkl')}
                              for kind in ('follower_sim', 'estimator_planner')})
    assert run.spin_until(lambda: run.estimator.session.step >= 20, 30.0)
    run.restart('estimator_planner', down=0.6)
    assert run.spin_until(lambda: run.estimator.session.step >= 40, 30.0)
    run.restart('follower_sim', down=0.6)
    assert run.run(timeout=60.0), f'stalled at {run.estimator.session.step}'
    estimator, follower = run.estimator.summary(), run.follower.summary()
    assert estimator['ok'] and estimator['steps'] == steps
    assert estimator['resumed']['from_step'] >= 20 and estimator['resumed']['down_s'] >= 0.5
    assert estimator['counters']['filled_substeps'] >= 5
    assert follower['resumed']['parked_substeps'] >= 5
    session = run.estimator.session
    nees = normalized_estimation_error(run.follower.truth.x, session.estimator.x,
                                       session.estimator.P)
    assert math.isfinite(nees) and nees < 20.0, nees


def test_an_estimator_started_after_its_run_finished_says_so(formation) -> None:
    """An estimator (re)started without a checkpoint after its peers' last step has nothing to
    rejoin: it stops with exit code 1 and an error naming the step, never an ok summary."""
    steps = 8
    run = formation({'measurement': 'range', 'strategy': 'ram', 'seed': SEED, 'steps': steps,
                     'resend_timeout': 0.3})
    assert run.spin_until(lambda: run.estimator.finished, 30.0)
    late = run.restart('estimator_planner')
    assert run.spin_until(lambda: late.finished, 30.0)
    summary = late.summary()
    assert late.exit_code == 1 and summary['ok'] is False
    assert f'last step, {steps}' in summary['error']


def test_a_realtime_estimator_restarted_without_checkpoint_rejoins(formation) -> None:
    """Realtime, no checkpoint: the estimator killed after step 20 and back 0.6 s later sends
    waypoint 1; follower_sim re-sends its last measurement, the estimator rejoins after it
    from both robots' odometry poses (the time the follower held meanwhile filled in, the steps
    it missed not counted as lost), finishes the run with a consistent estimate and says so in
    its summary and diagnostics."""
    from formopt_ros.ros.nodes.estimator_planner import REJOIN_INFLATION
    steps = 70
    run = formation({'measurement': 'range', 'strategy': 'ram', 'seed': SEED, 'steps': steps,
                     'mode': 'realtime', 'resend_timeout': 0.2})
    assert run.spin_until(lambda: run.estimator.session.step >= 20, 30.0)
    run.restart('estimator_planner', down=0.6)
    assert run.run(timeout=60.0), f'stalled at {run.estimator.session.step}'
    summary = run.estimator.summary()
    rejoined = summary['rejoined']
    assert summary['steps'] == steps and summary['resumed'] is None
    assert 21 <= rejoined['at_step'] < steps and rejoined['heard_from'] == 'measurement'
    scenario = node_scenario('range')
    assert all(np.array(rejoined['prior_covariance_diagonal'])
               >= REJOIN_INFLATION * np.array(scenario.initial_covariance))
    assert summary['counters']['skipped_steps'] <= 2          # lost in flight, not the gap
    assert summary['counters']['filled_substeps'] >= 5        # held while it was down
    assert f"rejoined at step {rejoined['at_step']}" in run.estimator.diagnostic().message
    session = run.estimator.session
    nees = normalized_estimation_error(run.follower.truth.x, session.estimator.x,
                                       session.estimator.P)
    assert math.isfinite(nees) and nees < 20.0, nees


def test_restart_refuses_a_checkpoint_of_another_run(formation, tmp_path: Path) -> None:
    """A checkpoint is bound to its run: an estimator with another seed (same file) exits 2
    naming checkpoint_path; a finished run's checkpoint is refused too."""
    from formopt_ros.ros.nodes.estimator_planner import EstimatorPlannerNode
    from formopt_ros.ros.params import ParameterError
    from harness.ros import node_args
    checkpoint = tmp_path / 'estimator.pkl'
    run = formation({'measurement': 'range', 'seed': SEED, 'steps': 5,
                     'checkpoint_path': str(checkpoint)})
    assert run.run(timeout=30.0) and checkpoint.exists()
    for params, text in (({'seed': SEED + 1}, 'another run'), ({'seed': SEED}, 'finished')):
        with pytest.raises(ParameterError, match=f"checkpoint_path.*{text}"):
            EstimatorPlannerNode(node_args('estimator_planner', 'follower', {
                'measurement': 'range', 'steps': 5, 'checkpoint_path': str(checkpoint),
                **params}))


def test_a_plan_outside_the_disc_stops_the_node_in_one_line() -> None:
    """A node method that plans, when a strategy (a plugin) plans outside its disc: the node
    stops with exit code 1 and the reason (no callback traceback), as run_formation reports."""
    from types import SimpleNamespace

    from formopt_ros.core.solver import outside_the_disc
    from formopt_ros.ros.runtime import stops_on_a_plan_outside_the_disc
    logged: list[str] = []
    node = SimpleNamespace(get_logger=lambda: SimpleNamespace(error=logged.append))

    @stops_on_a_plan_outside_the_disc
    def plan(node: SimpleNamespace) -> None:
        raise outside_the_disc('cheater', (3.0, 0.0), (0.0, 0.0), 1.0)

    plan(node)
    assert node.exit_code == 1 and node.finished and logged == [node.error]
    assert node.error == ("strategy 'cheater' planned a point 3 m from the slot, outside its "
                          'disc (r = 1 m); the waypoint is not sent')


@pytest.mark.parametrize('mode', ['lockstep', 'realtime'])
def test_a_frozen_peer_ends_the_run_after_the_stall_timeout(formation, mode: str) -> None:
    """leader_sim stops answering mid-run (a frozen process: taken off the executor): the
    estimator ends the run with exit code 1 after stall_timeout, naming the input it no longer
    hears, instead of resending its waypoint until the run's --timeout (lockstep) or going on
    with the leader's last odometry (realtime)."""
    run = formation({'measurement': 'range', 'steps': 400, 'stall_timeout': 1.5,
                     'resend_timeout': 0.2, 'mode': mode})
    assert run.spin_until(lambda: run.estimator.session.step >= 5, 30.0)
    run.executor.remove_node(run.leader)
    try:
        assert run.spin_until(lambda: run.estimator.finished, 30.0)
    finally:
        run.executor.add_node(run.leader)
    assert run.estimator.exit_code == 1 and run.estimator.session.step < 400
    assert '(stall_timeout)' in run.estimator.error, run.estimator.error
    assert 'leader odometry (leader_sim)' in run.estimator.error, run.estimator.error


def test_an_estimator_whose_peers_never_come_ends_after_the_start_timeout(node_process) -> None:
    """An estimator alone (its simulators frozen or never started) with start_timeout 2 s
    (run_formation.sh sets 60) exits 1 with one line naming what it waits for."""
    estimator = node_process('estimator_planner', {'measurement': 'range', 'steps': 10,
                                                   'recorders': 0, 'start_timeout': 2.0})
    assert estimator.wait(timeout=60.0) == 1, estimator.stderr
    errors = [line for line in estimator.stderr.splitlines()
              if line.startswith('estimator_planner: error:')]
    assert len(errors) == 1 and 'did not start within 2 s (start_timeout): waiting for ' \
        'subscribers on' in errors[0], estimator.stderr


def test_a_restarted_publisher_gets_its_lease_not_the_intruder_grace(monkeypatch) -> None:
    """Two publishers of one name (a driver restarted while its predecessor's discovery lease,
    20 s with Fast DDS's default, has not ended): no failure before RESTART_GRACE, then one
    that says so; two names fail after INTRUDER_GRACE as before."""
    from types import SimpleNamespace
    from formopt_ros.ros import guard
    clock = [0.0]
    monkeypatch.setattr(guard, 'time', SimpleNamespace(monotonic=lambda: clock[0]))

    def checked(names: list[str], times: list[float]) -> list[guard.Failure]:
        infos = [SimpleNamespace(node_namespace='/', node_name=name) for name in names]
        failures: list[guard.Failure] = []
        run_guard = guard.RunGuard(SimpleNamespace(get_publishers_info_by_topic=lambda _: infos),
                                   False, failures.append)
        run_guard.watch('/leader/odom')
        for clock[0] in times:
            run_guard.check()
        return failures

    assert not checked(['driver', 'driver'], [0.0, 10.0, guard.RESTART_GRACE - 0.1])
    late, = checked(['driver', 'driver'], [0.0, guard.RESTART_GRACE])
    assert 'two nodes named /driver' in late.message and late.code == guard.INTRUDER_EXIT
    assert checked(['driver', 'stray'], [0.0, guard.INTRUDER_GRACE])
