"""Bad inputs published into a running lockstep formation are rejected, counted, harmless."""
from __future__ import annotations

import math

import numpy as np
from formopt_interfaces.msg import Measurement
from harness.ros import node_scenario, topic
from nav_msgs.msg import Odometry

from formopt_ros.core.protocol import SUBSTEPS, seconds_to_ns
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.simulation import run_trial
from formopt_ros.ros import conversions, qos

STEPS = 30
INJECT_AFTER = 10          # inject once the estimator processed this many steps
SEED = 7
DT = Scenario.paper('range').dt
TOL = 1e-9                 # the estimate must equal the clean run's (same arithmetic)


def bad_measurements(step: int) -> list[Measurement]:
    """Each is rejected for one reason; step is the next one the estimator waits for."""
    future = conversions.stamp(seconds_to_ns((step + 5) * SUBSTEPS * DT))

    def meas(value=1.0, variance=0.01, follower='follower', kind=Measurement.RANGE,
             stamp=future, k=step) -> Measurement:
        return Measurement(header=conversions.header(stamp, follower), follower_id=follower,
                           step=k, kind=kind, value=value, variance=variance)
    return [
        meas(value=math.nan),
        meas(value=math.inf),
        meas(variance=0.0),
        meas(variance=-0.01),
        meas(variance=math.nan),
        meas(follower='intruder'),
        meas(kind=Measurement.BEARING),
        # valid values, step never processed, but stamped before the last accepted one
        meas(stamp=conversions.stamp(seconds_to_ns(0.5 * DT)), k=10 ** 6),
    ]


def bad_odometry(step: int) -> list[tuple[str, Odometry]]:
    """(topic, message) pairs, each rejected for one reason."""
    future = conversions.stamp(seconds_to_ns((step + 5) * SUBSTEPS * DT))
    odom = conversions.odometry
    follower_odom, leader_odom = topic('follower', 'odom'), topic('leader', 'odom')
    return [
        (follower_odom, odom(future, 'follower/odom', 'follower', (0, 0, 0), math.nan, 0.0)),
        (follower_odom, odom(future, 'follower/odom', 'follower', (0, 0, 0), 0.5, math.inf)),
        (follower_odom, odom(future, 'follower/odom', 'follower', (0, 0, 0), 0.5, 0.0,
                             (-1.0, 0.01))),
        (follower_odom, odom(future, 'follower/odom', 'intruder', (0, 0, 0), 0.5, 0.0)),
        # valid values, of a step already processed
        (follower_odom, odom(conversions.stamp(seconds_to_ns(DT)), 'follower/odom', 'follower',
                             (0, 0, 0), 0.5, 0.0)),
        (leader_odom, odom(future, 'odom', 'leader', (0, 0, 0), 1.0, math.nan)),
        (leader_odom, odom(future, 'odom', 'intruder', (0, 0, 0), 1.0, 0.0)),
    ]


def test_bad_inputs_are_rejected_and_counted(formation) -> None:
    run = formation({'measurement': 'range', 'strategy': 'crm', 'seed': SEED, 'steps': STEPS,
                     'resend_timeout': 60.0})
    injector = run.probe       # publishes from the same process, in the same executor
    meas_pub = injector.create_publisher(Measurement, topic('follower', 'measurement'),
                                         qos.STREAM)
    odom_pubs = {name: injector.create_publisher(Odometry, name, qos.STREAM)
                 for name in (topic('follower', 'odom'), topic('leader', 'odom'))}
    measurements, odometry = bad_measurements(INJECT_AFTER + 1), bad_odometry(INJECT_AFTER + 1)
    injected = []

    def inject() -> None:
        if not injected and run.estimator.session.step >= INJECT_AFTER:
            for msg in measurements:
                meas_pub.publish(msg)
            for name, msg in odometry:
                odom_pubs[name].publish(msg)
            injected.append(run.estimator.session.step)

    assert run.run(timeout=30.0, step=inject), f'estimator at step {run.estimator.session.step}'
    assert injected and injected[0] < STEPS, 'the bad inputs were published too late'
    status = run.probe.statuses[-1]
    assert status.step == STEPS
    assert status.rejected_measurements == len(measurements)
    assert status.rejected_odometry == len(odometry)
    assert status.accepted_measurements == STEPS
    # leader_sim and follower_sim reject the bad leader odometry too; nothing else is rejected
    assert run.follower.counters['rejected_odometry'] == 2
    assert run.follower.counters['rejected_waypoints'] == 0
    # never corrupted: every published estimate equals the clean pure simulation
    ref = run_trial(node_scenario('range'), 'crm', SEED, 0, STEPS)
    assert len(run.probe.estimates) == STEPS
    for k, (x, P) in enumerate(run.probe.estimates):
        np.testing.assert_allclose(x, ref.estimate[k], rtol=0, atol=TOL, err_msg=f'step {k + 1}')
        np.testing.assert_allclose(P, ref.covariance[k], rtol=0, atol=TOL,
                                   err_msg=f'step {k + 1}')


def test_a_simulator_with_absurd_noise_does_not_stall_the_run(formation) -> None:
    """range_sigma 1 m at 2.2 m (allowed): follower_sim sends a negative range at step 3
    (seed 4), which the estimator refuses as implausible; lockstep goes on to the last step
    without that update instead of waiting for good."""
    steps = 8
    run = formation({'measurement': 'range', 'strategy': 'mtf', 'seed': 4, 'steps': steps,
                     'range_sigma': 1.0})
    assert run.run(timeout=30.0), f'estimator at step {run.estimator.session.step}'
    status = run.probe.statuses[-1]
    assert status.step == steps and status.rejected_measurements >= 1
    assert status.accepted_measurements == steps - 1
