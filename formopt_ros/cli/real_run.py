"""A formation run on the real-robot interfaces: per follower a field_sim (its simulated base,
driven by cmd_vel, and its range radio or camera; the first also publishes the leader's
odometry) and a follower_estimator, in real time; the recorder takes the standard topics, and
the summary holds each estimator's verdict, its error and NEES against the recorded truth and
an audit of the recording. run_formation runs it for followers with ``interfaces: real``."""
from __future__ import annotations

import sys
import time
from pathlib import Path
from collections.abc import Callable
from typing import Any

from formopt_ros.cli.supervisor import (
    CONFIGURATION_EXIT, exit_failure, interrupted_by, supervising)
from formopt_ros.core.formation import Formation, FollowerSpec
from formopt_ros.wire.topics import real_frames

#: Parameters run_formation sets for the real nodes ('real' settings may not).
MANAGED = {'sensor', 'formation_slot', 'leader_odom_topic', 'publish_leader', 'start_time',
           'duration', 'summary_path', 'base_frame', 'leader_frame', 'strategy', 'sensor_frame',
           'range_sigma', 'bearing_sigma', 'deviation_fraction', 'dt', 'initial_covariance',
           'use_sim_time'}
REAL_NODES = ('field_sim', 'follower_estimator')
#: Time between the start of the processes and the simulated world's start: s, plus per
#: follower (two processes each start on a loaded machine).
STARTUP_S, STARTUP_PER_FOLLOWER_S = 3.0, 1.5


def node_parameters(formation: Formation, index: int, leader_topic: str, start_time: float,
                    duration: float, names: dict[str, set[str]]) -> dict[str, dict[str, Any]]:
    """The parameters of follower ``index``'s field_sim and follower_estimator: its scenario
    (sensor, slot, noise, strategy and options), shared frames and start time, then its
    ``real`` settings; ``names`` are each node's parameter names."""
    from formopt_ros.ros.run_config import follower_values
    follower: FollowerSpec = formation.followers[index]
    values = follower_values(follower, formation.trial, formation.leader_id)
    values['sensor'] = values.pop('measurement')
    if values['max_speed']:                # the file's limit: the base's, and planned within
        values['plan_within_reach'] = True
    else:                                  # no limit in the file: the bases keep their own
        del values['max_speed']
    frames = real_frames(follower.id, values['sensor'])
    values.update({'base_frame': frames['base'], 'leader_frame': formation.leader_id,
                   'sensor_frame': frames['sensor']})
    out = {node: {k: v for k, v in values.items() if k in names[node]} for node in REAL_NODES}
    out['field_sim'].update({'leader_odom_topic': leader_topic, 'publish_leader': index == 0,
                             'start_time': start_time, 'duration': duration})
    for key, value in follower.real.items():
        for node in REAL_NODES:
            if key in names[node]:
                out[node][key] = value
    return out


def check_real(formation: Formation, names: dict[str, set[str]],
               check: Callable[[str, str, Any], str | None]) -> str | None:
    """Why the formation's 'real' settings would fail a node (None: fine): unknown keys, keys
    run_formation sets, values the nodes' specs refuse (``check(node, name, value)``)."""
    for follower in formation.followers:
        for key, value in follower.real.items():
            if key in MANAGED:
                return f"follower {follower.id!r}: real: {key} is set from the follower's " \
                       'own keys (sensor, slot, deviation, noise, ...) or by run_formation'
            if key in ('max_speed', 'safety_distance') and \
                    getattr(follower.scenario, key) not in (None, 0.0):
                return f"follower {follower.id!r}: {key} is given twice, as the follower's " \
                       'key and in real: give it once'
            nodes = [node for node in REAL_NODES if key in names[node]]
            if not nodes:
                return f'follower {follower.id!r}: real: {key}: no such parameter of ' \
                       'field_sim or follower_estimator (docs/nodes.md lists them)'
            for node in nodes:
                problem = check(node, key, value)
                if problem:
                    return f'follower {follower.id!r}: real: {problem}'
        problem = real_limits_problem(follower)
        if problem:
            return f'follower {follower.id!r}: real: {problem}'
    return None


def real_limits_problem(follower: FollowerSpec) -> str | None:
    """Why the follower's scenario with the limits its ``real`` settings give the estimator
    (safety_distance; max_speed where it plans within reach) is refused, or None: the same
    rule the nodes apply, checked before anything starts."""
    import dataclasses
    real, scenario = follower.real, follower.scenario
    within = real.get('plan_within_reach', bool(scenario.max_speed))
    try:
        dataclasses.replace(
            scenario, safety_distance=real.get('safety_distance', scenario.safety_distance),
            max_speed=real.get('max_speed', scenario.max_speed) if within else None)
    except ValueError as error:
        return str(error)
    return None


def run_real(formation: Formation, launcher: Any, out: Path, prefix: str, steps: int,
             record: bool, names: dict[str, set[str]]) -> dict[str, Any]:
    """Start, supervise and stop the real-interface nodes; the summary's content (without
    writing it). The run lasts ``steps`` measurement steps of the formation (2 dt each); a
    node that ends before is a failure."""
    duration = steps * 2.0 * formation.dt
    leader_topic = f'{prefix}/{formation.leader_id}/odom'
    topics = ['/diagnostics', '/tf_static', leader_topic]
    for follower in formation.followers:
        sensor = follower.scenario.measurement
        topics += [f'{prefix}/{follower.id}/{name}' for name in
                   ('odom', sensor, 'cmd_vel', 'estimate', 'target', 'truth')]
    recorder = None
    if record:
        recorder = launcher.start('recorder', 'recorder', prefix, {
            'output_path': str(out / 'run.mcap'), 'counts_path': str(out / 'recorder_counts.json'),
            'topics': topics}, summary=False)
    start_time = time.time() + STARTUP_S + STARTUP_PER_FOLLOWER_S * len(formation.followers)
    pairs = {}
    for index, follower in enumerate(formation.followers):
        params = node_parameters(formation, index, leader_topic, start_time, duration, names)
        ns = f'{prefix}/{follower.id}'
        estimator = launcher.start(f'{follower.id}.follower_estimator', 'follower_estimator',
                                   ns, params['follower_estimator'],
                                   remaps=[f'leader_odom:={leader_topic}'])
        sim = launcher.start(f'{follower.id}.field_sim', 'field_sim', ns, params['field_sim'])
        pairs[follower.id] = (sim, estimator)
    print(f'run_formation.sh: started {len(launcher.processes)} processes (real interfaces, '
          f'{len(formation.followers)} follower(s), {duration:g} s from '
          f'{time.strftime("%H:%M:%S", time.localtime(start_time))}); logs in {out}')
    everything = [p for pair in pairs.values() for p in pair] + ([recorder] if recorder else [])
    failure = ''
    with supervising():
        while not failure and time.time() < start_time + duration:
            dead = [p for p in everything if not p.alive()]
            if dead:
                failure = f'{dead[0].name} {dead[0].exit_text()} before the run finished:\n' \
                          f'{dead[0].tail()}'
            failure = interrupted_by() or failure
            time.sleep(0.05)
        # the estimators first (their summaries judge fresh streams), then the sims, the
        # recorder
        launcher.stop([e for _, e in pairs.values()])
        launcher.stop([s for s, _ in pairs.values()])
        if recorder is not None:
            launcher.stop([recorder])
    failure = failure or interrupted_by()
    return summarise(formation, pairs, out if record else None, prefix, failure)


#: A real-interface run whose estimates, against field_sim's truth, have a mean NEES above
#: this (three times the 3 of a consistent 3-dof estimate) is not ok. The estimates come at the
#: radio's rate and are strongly correlated, so the chi-square band of independent samples
#: does not apply; a factor of three tells a filter misled (a leader clock 80 ms behind: 14-18)
#: from one merely tight (clean runs: 1.6-6).
TRACKING_NEES_LIMIT = 9.0


def summarise(formation: Formation, pairs: dict[str, tuple[Any, Any]], recording: Path | None,
              prefix: str, failure: str) -> dict[str, Any]:
    """Each follower's estimator and simulator summaries, its tracking against the recorded
    truth, and the verdict: ok only when every node ended cleanly, every estimator says ok,
    its estimates are consistent with the truth (mean NEES at most TRACKING_NEES_LIMIT) and
    the recording holds every estimate, measurement and odometry message the nodes sent."""
    from formopt_ros.analysis.foreign import tracking_errors
    from formopt_ros.bag.reader import read_bag
    bag = read_bag(recording / 'run.mcap') if recording is not None else None
    followers: dict[str, Any] = {}
    refused = [p for pair in pairs.values() for p in pair if p.code == CONFIGURATION_EXIT]
    if refused and not failure:             # a node refused its parameters: its own words
        failure = f'{refused[0].name} refused its configuration:\n{refused[0].tail()}'
    for follower_id, (sim, estimator) in pairs.items():
        result, world = estimator.summary(), sim.summary()
        if result is None or world is None:
            failure = failure or f'{follower_id}: a node wrote no summary:\n{estimator.tail()}'
            continue
        if not result['ok']:
            failure = failure or f"{follower_id}: follower_estimator: {result['errors']}"
        result['field_sim'] = world
        if bag is not None:
            ns = f'{prefix}/{follower_id}'
            counts = bag.counts()
            result['tracking'] = tracking = tracking_errors(
                bag, f'{ns}/estimate', f'{ns}/truth') \
                if counts.get(f'{ns}/estimate') and counts.get(f'{ns}/truth') else None
            if tracking:
                tracking['consistent'] = (tracking['mean_nees'] or 0.0) <= TRACKING_NEES_LIMIT
            if tracking and not tracking['consistent']:
                failure = failure or (
                    f"{follower_id}: the estimate is inconsistent with the simulated truth: "
                    f"mean NEES {tracking['mean_nees']:.3g} > {TRACKING_NEES_LIMIT:g} "
                    f"(RMS error {tracking['rms_position_error_m']:.3g} m); unsynchronised "
                    'clocks or a lost filter')
            sensor = formation.follower(follower_id).scenario.measurement
            expected = {f'{ns}/odom': world['sent']['odom'],
                        f'{ns}/{sensor}': world['sent'][sensor],
                        f'{ns}/estimate': result['counters'].get('measurements', 0)}
            missing = {t: n - counts.get(t, 0) for t, n in expected.items()
                       if counts.get(t, 0) < n}
            if missing:
                failure = failure or f'{follower_id}: the recording misses messages: {missing}'
        followers[follower_id] = result
    processes = [p for pair in pairs.values() for p in pair]
    codes = {p.name: p.code for p in processes}
    exited, late = exit_failure(processes)
    failure = failure or exited
    if failure:
        print(f'run_formation.sh: error: {failure}', file=sys.stderr)
    return {'ok': not failure, 'failure': failure or None, 'interfaces': 'real',
            'followers': followers, 'exit_codes': codes, 'killed_after_its_part': late,
            'recording': str(recording / 'run.mcap') if recording is not None else None}


__all__ = ['check_real', 'node_parameters', 'run_real']
