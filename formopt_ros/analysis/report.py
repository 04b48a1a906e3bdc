"""Figures and a summary of one recorded formation run (an .mcap bag), without ROS."""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from formopt_ros.analysis.figures import nees_figure, trace_figure, trajectory_figure
from formopt_ros.analysis.recording import FollowerRecording, Recording
from formopt_ros.bag import BagError
from formopt_ros.core.consistency import ConsistencyWatch
from formopt_ros.core.model import normalized_estimation_error
from formopt_ros.core.protocol import SUBSTEPS, Timebase
from formopt_ros.core.study import nees_band, steady_window
from formopt_ros.wire.description import RunDescription
from formopt_ros.wire.messages import estimate_values, header_ns, pose_values
from formopt_ros.wire.jsonfile import write_json


@dataclass
class Run:
    """Per-step arrays of a recorded run (step k at row k - 1)."""

    steps: np.ndarray            # (n,) measurement step index
    time: np.ndarray             # (n,) simulated time of the step, s
    estimate: np.ndarray         # (n, 3) x_k|k in {L}
    covariance: np.ndarray       # (n, 3, 3)
    weighted_trace: np.ndarray   # (n,) tr(W P W) from the status, m^2
    truth: np.ndarray            # (n, 3) true pose in {L}, NaN where not recorded
    leader: np.ndarray           # (n, 3) leader pose (x m, y m, yaw rad) in the fixed frame
    waypoints: np.ndarray        # (n, 2) chosen position for step k in {L}, NaN if missing
    nees: np.ndarray             # (n,) NaN where no truth
    strategy: str
    measurement: str
    p_o: np.ndarray
    r: float
    dt: float
    last_status: Any


def _latest_before(stamps: np.ndarray, values: np.ndarray, stamp: int) -> np.ndarray | None:
    """The value with the largest stamp <= stamp (+1 us), or None."""
    index = int(np.searchsorted(stamps, stamp + 1000, side='right')) - 1
    return values[index] if index >= 0 else None


def load_run(recording: Recording, follower: FollowerRecording) -> Run:
    """Decode and align a follower's estimates, statuses, truth, waypoints and leader odometry."""
    estimates = recording.follower_estimates(follower)
    statuses = recording.follower_messages(follower, 'status')
    if not estimates or not statuses:
        raise BagError(f'{recording.bag.path}: no estimate or status messages of '
                       f'{follower.namespace} (empty run)')
    description = follower.description
    scenario = description.scenario
    timebase = Timebase.from_dt(scenario.dt)
    rows = [(step, *estimate_values(msg), status.weighted_trace if status else math.nan)
            for step, msg, status in estimates]
    n = len(rows)
    steps = np.array([row[0] for row in rows])
    stamp_of_step = {int(m.step): header_ns(m)
                     for m in recording.follower_messages(follower, 'measurement')}
    truth_by_stamp = {header_ns(m): pose_values(m.pose)
                      for m in recording.follower_messages(follower, 'truth')}
    truth = np.full((n, 3), np.nan)
    leader = np.zeros((n, 3))
    odom = [m for _, m in recording.messages(recording.leader_topic)]
    odom_stamps = np.array([header_ns(m) for m in odom])
    odom_xy = np.array([pose_values(m.pose.pose) for m in odom])
    for i, k in enumerate(steps):
        stamp = stamp_of_step.get(int(k), timebase.measurement_stamp(int(k)))
        if stamp in truth_by_stamp:
            truth[i] = truth_by_stamp[stamp]
        if len(odom):
            position = _latest_before(odom_stamps, odom_xy, stamp)
            if position is not None:
                leader[i] = position
    chosen = {int(w.step): (w.position.x, w.position.y)
              for w in recording.follower_messages(follower, 'waypoint')}
    way = np.array([chosen.get(int(k), (math.nan, math.nan)) for k in steps])
    estimate = np.array([row[1] for row in rows])
    covariance = np.array([row[2] for row in rows])
    nees = np.array([normalized_estimation_error(truth[i], estimate[i], covariance[i])
                     if np.all(np.isfinite(truth[i])) else math.nan for i in range(n)])
    return Run(steps, SUBSTEPS * steps * scenario.dt, estimate, covariance,
               np.array([row[3] for row in rows]), truth, leader, way, nees,
               strategies_used(description, statuses), scenario.measurement, scenario.slot,
               scenario.r,
               scenario.dt, statuses[-1])


def strategies_used(description: RunDescription, statuses: list[Any]) -> str:
    """Every strategy of the run, '+'-joined in order of first use: the description's (with
    its mid-run changes) and those the statuses name (bags recorded before the changes were
    described)."""
    names = description.strategies() + [str(s.strategy) for s in statuses if s.strategy]
    return '+'.join(dict.fromkeys(names))


def make_report(recording: Recording, out: Path, trajectory_steps: int = 40,
                follower_id: str | None = None) -> dict[str, Any]:
    """Write trajectory.png (the paper's Fig. 4 for a formation: the leader and every follower,
    3-sigma ellipses and feasible discs), weighted_trace.png, nees.png, summary.json and
    summary.md (one row per follower)."""
    bag = recording.bag
    followers = [recording.follower(follower_id)] if follower_id else \
        sorted(recording.followers.values(), key=_vertical_order)
    runs = {f.follower_id: load_run(recording, f) for f in followers}
    out.mkdir(parents=True, exist_ok=True)
    n = min(len(run.steps) for run in runs.values())
    shown = slice(0, min(n, trajectory_steps))
    first = next(iter(runs.values()))
    panel: dict[str, Any] = {'leader': first.leader[shown], 'followers': []}
    for follower_id_, run in runs.items():
        has_truth = bool(np.any(np.isfinite(run.truth[:, 0])))
        has_way = bool(np.any(np.isfinite(run.waypoints[:, 0])))
        panel['followers'].append({
            'label': f'{follower_id_} ({run.measurement}, {run.strategy})',
            'strategy': run.strategy if len(runs) == 1 else follower_id_,
            'estimate': run.estimate[shown], 'covariance': run.covariance[shown],
            'truth': run.truth[shown] if has_truth else None,
            'waypoints': run.waypoints[shown] if has_way else None, 'p_o': run.p_o,
            'r': run.r})
    title = f'{bag.path.name}: first {len(first.steps[shown])} steps'
    figures = [trajectory_figure({'formation' if len(runs) > 1 else first.strategy.upper():
                                  panel}, out / 'trajectory.png', title,
                                 every=max(3, len(first.steps[shown]) // 30))]
    figures.append(trace_figure(first.time[:n], {f: r.weighted_trace[:n]
                                                 for f, r in runs.items()},
                                out / 'weighted_trace.png', f'{bag.path.name}: weighted trace',
                                zoom=()))
    valid = {f: np.isfinite(r.nees) for f, r in runs.items()}
    if any(np.any(v) for v in valid.values()):
        figures.append(nees_figure(first.time[:n], {f: np.where(valid[f], r.nees, np.nan)[:n]
                                                    for f, r in runs.items()},
                                   nees_band(1), out / 'nees.png',
                                   f'{bag.path.name}: NEES (one run)'))
    times = [r.log_time for r in bag.messages]
    rows = {f: _follower_summary(recording, runs[f], next(x for x in followers
                                                          if x.follower_id == f))
            for f in runs}
    summary: dict[str, Any] = {
        'bag': str(bag.path),
        'duration_s': (max(times) - min(times)) * 1e-9 if times else 0.0,
        'run_time_s': max(float(r.time[-1]) for r in runs.values()),
        'nees_band_95': list(nees_band(1)),
        'followers': rows,
        'message_counts': bag.counts(),
        'figures': [p.name for p in figures],
    }
    if len(rows) == 1:                     # the single follower's row at the top level too
        summary.update(next(iter(rows.values())))
    write_json(out / 'summary.json', summary)
    (out / 'summary.md').write_text(_markdown(summary))
    return summary


def _vertical_order(follower: FollowerRecording) -> float:
    """Followers top to bottom as Fig. 4 shows them: by decreasing slot y."""
    return -float(follower.description.scenario.p_o[1])


def _follower_summary(recording: Recording, run: Run,
                      follower: FollowerRecording) -> dict[str, Any]:
    n = len(run.steps)
    window = steady_window(n)
    valid = np.isfinite(run.nees)
    status = run.last_status
    steps = max(int(status.step), follower.description.steps)   # a cut end is missing too
    missing = sorted(set(range(1, steps + 1)) - {int(k) for k in run.steps})
    watch = ConsistencyWatch()           # the estimator's own rule, on the recorded NEES
    for step, nees in zip(run.steps, run.nees):
        if math.isfinite(nees):
            watch.add_nees(float(nees), int(step))
    return {
        'follower_id': follower.follower_id,
        'description': 'reconstructed from the messages' if follower.legacy else 'recorded',
        'steps': steps,
        'estimates': n,
        'missing_steps': len(missing),
        'missing_ranges': step_ranges(missing),
        'strategy': run.strategy,
        'strategy_changes': [c.to_dict() for c in follower.description.strategy_changes],
        'measurement': run.measurement,
        'slot_m': [float(v) for v in run.p_o],
        'r_m': run.r,
        'dt_s': run.dt,
        'steady_weighted_trace': float(np.nanmean(run.weighted_trace[-window:])),
        'steady_window_steps': window,
        'final_weighted_trace': float(run.weighted_trace[-1]),
        'mean_nees': float(np.mean(run.nees[valid])) if np.any(valid) else None,
        'consistent': not watch.failed,
        'inconsistency': None if not watch.failed else
        f'at step {watch.worst.step}: {watch.worst.reason}',
        'nees_steps': int(np.sum(valid)),
        'rejected_measurements': int(status.rejected_measurements),
        'rejected_odometry': int(status.rejected_odometry),
        'accepted_measurements': int(status.accepted_measurements),
    }


def step_ranges(steps: list[int]) -> str:
    """Sorted step numbers as ranges: [1, 2, 3, 7] -> '1-3, 7' ('' for none)."""
    ranges: list[list[int]] = []
    for step in steps:
        if ranges and step == ranges[-1][1] + 1:
            ranges[-1][1] = step
        else:
            ranges.append([step, step])
    return ', '.join(f'{a}-{b}' if b > a else f'{a}' for a, b in ranges)


def steps_text(row: dict[str, Any]) -> str:
    """'300' for a complete run; '223 of 300 (missing 1-77)' when the bag lacks steps."""
    if not row['missing_steps']:
        return f"{row['steps']}"
    return f"{row['estimates']} of {row['steps']} (missing {row['missing_ranges']})"


def _markdown(s: dict[str, Any]) -> str:
    lo, hi = s['nees_band_95']
    lines = [f"# Formation run: {Path(s['bag']).name}", '',
             f"Recorded over {s['duration_s']:.3f} s of the recorder's clock; the run's last "
             f"step is at {s['run_time_s']:.3f} s of the scenario's time. Steady value: mean "
             f'tr(W P W) over the last steps (column); NEES of one run, 95 % band {lo:.3f} to '
             f'{hi:.3f}.', '',
             '| follower | sensor | strategy | slot [m] | r [m] | steps | steady tr(W P W) '
             '[m^2] | final tr(W P W) [m^2] | mean NEES | refused meas. / odom. |',
             '|---|---|---|---|---|---|---|---|---|---|']
    for f, row in s['followers'].items():
        nees = 'n/a' if row['mean_nees'] is None else f"{row['mean_nees']:.3f}"
        nees += '' if row['consistent'] else ' (inconsistent)'
        lines.append(
            f"| {f} | {row['measurement']} | {row['strategy']} | "
            f"[{row['slot_m'][0]:g}, {row['slot_m'][1]:g}] | {row['r_m']:.4g} | "
            f"{steps_text(row)} | {row['steady_weighted_trace']:.6g} (last "
            f"{row['steady_window_steps']}) | {row['final_weighted_trace']:.6g} | {nees} | "
            f"{row['rejected_measurements']} / {row['rejected_odometry']} |")
    lines += ['', '## Messages per topic', '', '| topic | messages |', '|---|---|']
    lines += [f'| {topic} | {count} |' for topic, count in sorted(s['message_counts'].items())]
    lines += ['', '## Figures', ''] + [f'![{name}]({name})' for name in s['figures']]
    return '\n'.join(lines) + '\n'
