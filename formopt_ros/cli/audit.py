"""The audit of a recording: the messages every node says it published, against what the
recorder wrote (OUT/recorder_counts.json)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from formopt_ros.core.protocol import SUBSTEPS
from formopt_ros.wire.topics import BY_KEY, resolve

#: Messages per topic a killed node may have published without the recorder receiving them:
#: its last step's (its checkpoint counts them, the process died before they were sent; the
#: peers get that step again from the repeat that a restart triggers). SUBSTEPS odometry and
#: /tf messages, one of the rest.
IN_FLIGHT_PER_RESTART = SUBSTEPS


def expected_counts(prefix: str, leader: dict[str, Any] | None,
                    followers: dict[str, tuple[dict[str, Any] | None, dict[str, Any] | None]],
                    remapped: bool = True) -> dict[str, int]:
    """Messages per topic the nodes say they published (their summaries); the global topics
    under ``prefix`` when ``remapped`` (:func:`global_remaps`, as run_formation starts them)."""
    tf, tf_static, clock, diagnostics = (f'{prefix if remapped else ""}{name}' for name in (
        '/tf', '/tf_static', '/clock', '/diagnostics'))
    out: dict[str, int] = {tf: 0, diagnostics: 0}
    leader_ns = f"{prefix}/{leader['leader_id']}" if leader else ''
    if leader:
        out[resolve(leader_ns, BY_KEY['leader_odom'])] = leader['published']['odometry']
        out[resolve(leader_ns, BY_KEY['leader_description'])] = 1
        out[clock] = leader['published']['clock']
        out[tf] += leader['published']['tf']
    for follower_id, (sim, estimator) in followers.items():
        ns = f'{prefix}/{follower_id}'
        if sim:
            for key, name in (('follower_odom', 'odometry'), ('measurement', 'measurement'),
                              ('truth', 'truth')):
                out[resolve(ns, BY_KEY[key])] = sim['published'][name]
            out[tf] += sim['published']['tf']
            out[tf_static] = out.get(tf_static, 0) + 1
            out[resolve(ns, BY_KEY['sim_description'])] = 1
        if estimator:
            published = estimator['message_counts']['published']
            for key in ('estimate', 'waypoint', 'status', 'markers'):
                out[resolve(ns, BY_KEY[key])] = published[key]
            out[resolve(ns, BY_KEY['description'])] = published.get('description', 1)
            out[tf] += published['tf']
            out[diagnostics] += published['diagnostics']
    if out.get(clock) == 0:
        del out[clock]
    return {k: v for k, v in out.items() if v or k == tf}


def audit_recording(out: Path, prefix: str, leader: dict[str, Any] | None,
                    followers: dict[str, tuple[dict[str, Any] | None, dict[str, Any] | None]],
                    restarts: int) -> tuple[dict[str, Any], str]:
    """The recording's entry of summary.json and the failure it shows ('' if none): the
    recorder's write error (naming the file), messages a node published and the recorder
    misses (after ``restarts`` restarts of killed nodes, up to IN_FLIGHT_PER_RESTART per topic
    and restart are reported as ``lost_in_flight``, not a failure), or messages no node of
    this run published (another run in the domain; not judged after a restart, which
    publishes again what it sent after its last checkpoint)."""
    counts_file = out / 'recorder_counts.json'
    written = json.loads(counts_file.read_text()) if counts_file.exists() else {}
    recorded = written.get('counts', {})
    expected = expected_counts(prefix, leader, followers)
    missing = {topic: n - recorded.get(topic, 0) for topic, n in expected.items()
               if recorded.get(topic, 0) < n}
    extra = {topic: n - expected.get(topic, 0) for topic, n in recorded.items()
             if n > expected.get(topic, 0)}
    complete = bool(recorded) and not missing
    in_flight = bool(recorded) and bool(missing) and \
        max(missing.values()) <= IN_FLIGHT_PER_RESTART * restarts
    recording = {'path': str(out / 'run.mcap'), 'counts': recorded, 'expected': expected,
                 'complete': complete, 'missing': missing, 'extra': extra,
                 'lost_in_flight': in_flight, 'error': written.get('error')}
    failure = ''
    if written.get('error'):              # e.g. a full disk: the recorder names the file
        failure = f"the recorder failed: {written['error']}"
    elif not complete and not in_flight:
        failure = f'the recording misses messages: {missing or "no counts"}'
    elif extra and not restarts:
        failure = (f'the recording holds messages that no node of this run published: '
                   f'{extra} (another run publishes on these topics in this ROS domain; '
                   'use --domain-id or --prefix)')
    return recording, failure


__all__ = ['audit_recording', 'expected_counts']
