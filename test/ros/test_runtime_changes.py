"""Run-time parameter changes: use_sim_time refused on a running node; a strategy designed off
the executor, switched when ready and recorded (summary, bag), honoured by report and replay."""
from __future__ import annotations

import threading
from typing import Any

import pytest
from harness.ros import PREFIX, set_parameters

from formopt_ros import bag as bags
from formopt_ros.analysis.offline import offline
from formopt_ros.analysis.recording import load_recording
from formopt_ros.analysis.report import load_run
from formopt_ros.cli.audit import expected_counts
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import make_strategy
from formopt_ros.core.strategies.periodic import PeriodicPattern
from formopt_ros.wire.description import StrategyChange

DEADLINE = 60.0                     # s, for every spin-until-condition loop


def test_use_sim_time_is_refused_while_running(formation) -> None:
    """A realtime node asked to follow /clock would see every input 'in the future': every
    formation node refuses the change with the reason; setting the current value passes."""
    run = formation({'measurement': 'range', 'steps': 200, 'resend_timeout': 60.0})
    assert run.spin_until(lambda: run.estimator.session.step >= 3, DEADLINE)
    for node in (run.estimator, run.leader, run.follower):
        refused = set_parameters(run, node, {'use_sim_time': True})
        assert not refused[0].successful and "'use_sim_time'" in refused[0].reason
        assert node.get_parameter('use_sim_time').value is False
        assert set_parameters(run, node, {'use_sim_time': False})[0].successful
    both = set_parameters(run, run.estimator, {'strategy': 'mtf', 'use_sim_time': True},
                          atomically=True)
    assert not both[0].successful
    assert run.estimator.pending is None and run.estimator.params['strategy'] == 'ram'


def test_a_change_the_start_would_refuse_is_refused_at_run_time(formation) -> None:
    """RAM on a range-bearing follower is refused at start (formation file, -p); set at run
    time it is refused in the callback by the same rule, and the node keeps running."""
    run = formation({'measurement': 'range-bearing', 'strategy': 'rq', 'steps': 200,
                     'resend_timeout': 60.0})
    assert run.spin_until(lambda: run.estimator.session.step >= 3, DEADLINE)
    refused = set_parameters(run, run.estimator, {'strategy': 'ram'})
    assert not refused[0].successful and 'range-bearing' in refused[0].reason, refused
    assert run.estimator.pending is None and run.estimator.params['strategy'] == 'rq'
    step = run.estimator.session.step
    assert run.spin_until(lambda: run.estimator.session.step >= step + 3, DEADLINE)


def test_a_plan_longer_than_a_step_is_warned_and_counted(formation) -> None:
    """LOOKAHEAD at its largest documented beam and horizon plans for seconds: a realtime node
    falls behind, which it counts (slow_plans) instead of stalling silently."""
    run = formation({'measurement': 'range', 'steps': 400, 'mode': 'realtime'})
    assert run.spin_until(lambda: run.estimator.session.step >= 3, DEADLINE)
    changed = set_parameters(run, run.estimator, {'strategy': 'lookahead', 'lookahead_beam': 512,
                                                  'lookahead_horizon': 50}, atomically=True)
    assert changed[0].successful, changed[0].reason
    assert run.spin_until(lambda: run.estimator.slow_plans >= 1, DEADLINE)
    assert run.estimator.summary()['slow_plans'] >= 1


@pytest.fixture(scope='module')
def changed_run(tmp_path_factory) -> dict[str, Any]:
    """A recorded lockstep run (range, MTF, seed 5, 300 steps) switched to PERIODIC (period 3)
    mid-run; PERIODIC's preparation is held until the test saw 10 more steps with MTF."""
    import rclpy
    from harness.ros import Formation, spin_until

    from formopt_ros.ros.nodes.recorder import Recorder
    make_strategy('periodic', period=3).prepare(Scenario.paper('range'))   # the design, cached
    release = threading.Event()
    original = PeriodicPattern.prepare

    def held(self: PeriodicPattern, scenario: Scenario) -> None:
        assert release.wait(DEADLINE), 'the test never released the preparation'
        original(self, scenario)

    path = tmp_path_factory.mktemp('changed') / 'run.mcap'
    patch = pytest.MonkeyPatch()
    patch.setattr(PeriodicPattern, 'prepare', held)
    rclpy.init()
    try:
        run = Formation({'measurement': 'range', 'seed': 5, 'strategy': 'mtf', 'steps': 300,
                         'recorders': 2, 'resend_timeout': 60.0})
        recorder = Recorder(['--ros-args', '-r', f'__ns:={PREFIX}', '-p',
                             f'output_path:={path}', '-p', 'flush_period:=0.1'])
        run.executor.add_node(recorder)
        estimator = run.estimator
        assert run.spin_until(lambda: estimator.session.step >= 5, DEADLINE)
        result = set_parameters(run, estimator, {'strategy': 'periodic', 'periodic_period': 3})
        requested = estimator.pending[2]
        assert result[0].successful and estimator.session.step < 300
        assert run.spin_until(lambda: estimator.session.step >= requested + 10, DEADLINE)
        assert estimator.session.estimator.strategy.name == 'mtf'    # the old one goes on
        release.set()
        assert run.spin_until(lambda: estimator.finished, DEADLINE)
        total = run.total()
        assert spin_until(run.executor, lambda: sum(recorder.counts.values()) >= total,
                          DEADLINE)
        recorder.close()
        out = {'path': path, 'summary': estimator.summary(), 'requested': requested,
               'statuses': run.probe.step_statuses(), 'counts': dict(recorder.counts)}
        run.executor.remove_node(recorder)
        recorder.destroy_node()
        run.destroy()
    finally:
        release.set()
        patch.undo()
        rclpy.try_shutdown()
    return out


def test_strategy_change_is_designed_off_the_executor_and_recorded(
        changed_run: dict[str, Any]) -> None:
    """The set call returned while the design was held; MTF planned meanwhile; the change
    (step, old, new) is in the summary, the statuses and the bag's description."""
    summary = changed_run['summary']
    assert summary['ok'] and summary['steps'] == 300
    (change,) = summary['strategy_changes']
    step = change['step']
    assert (change['from'], change['to'], change['options']['period']) == ('mtf', 'periodic', 3)
    assert step >= changed_run['requested'] + 10 and change['requested_at_step'] == \
        changed_run['requested']
    assert summary['strategies'] == ['mtf', 'periodic'] and summary['strategy'] == 'periodic'
    statuses = changed_run['statuses']
    assert {s.strategy for s in statuses if s.step <= step} == {'mtf'}
    assert {s.strategy for s in statuses if s.step > step} == {'periodic'}
    recording = load_recording(bags.read_bag(changed_run['path']))
    description = recording.follower().description
    assert description.strategy == 'mtf'
    assert description.strategy_changes == (StrategyChange(step, 'periodic', change['options']),)
    topic = f'{PREFIX}/follower/description'
    assert changed_run['counts'][topic] == 2 == expected_counts(
        PREFIX, None, {'follower': (None, summary)})[topic]


def test_report_and_offline_replay_honour_the_change(changed_run: dict[str, Any]) -> None:
    """formopt-report labels the run 'mtf+periodic'; replay --offline of its own bag
    re-estimates with the strategy in force at each step (1e-9); MTF throughout differs."""
    recording = load_recording(bags.read_bag(changed_run['path']))
    follower = recording.follower()
    assert load_run(recording, follower).strategy == 'mtf+periodic'
    result = offline(recording)
    assert result.strategy == 'mtf+periodic'
    assert (result.steps, result.recorded_steps) == (300, 300) and result.max_diff <= 1e-9
    forced = offline(recording, strategy='mtf')
    assert forced.strategy == 'mtf' and forced.max_waypoint_diff > 1e-3
