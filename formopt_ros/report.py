"""formopt-report: figures and a summary of one recorded formation run (an .mcap bag)."""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from formopt_ros import bag as bags
from formopt_ros import conversions
from formopt_ros.core.model import MEASUREMENT_KINDS, normalized_estimation_error
from formopt_ros.core.montecarlo import nees_band, steady_window
from formopt_ros.core.simulation import SUBSTEPS, Scenario
from formopt_ros.figures import nees_figure, trace_figure, trajectory_figure

REQUIRED = ['follower/estimate', 'follower/status']
OPTIONAL = ['follower/truth', 'follower/waypoint', 'leader/odom', 'follower/measurement']


@dataclass
class Run:
    """Per-step arrays of a recorded run (step k at row k - 1)."""

    steps: np.ndarray            # (n,) measurement step index
    time: np.ndarray             # (n,) simulated time of the step, s
    estimate: np.ndarray         # (n, 3) x_k|k in {L}
    covariance: np.ndarray       # (n, 3, 3)
    weighted_trace: np.ndarray   # (n,) tr(W P W) from the status, m^2
    truth: np.ndarray            # (n, 3) true pose in {L}, NaN where not recorded
    leader: np.ndarray           # (n, 2) leader position in the fixed frame, m
    waypoints: np.ndarray        # (n, 2) chosen position for step k in {L}, NaN if missing
    nees: np.ndarray             # (n,) NaN where no truth
    strategy: str
    measurement: str
    p_o: np.ndarray
    r: float
    dt: float
    last_status: object


def _latest_before(stamps: np.ndarray, values: np.ndarray, stamp: int) -> np.ndarray | None:
    """The value with the largest stamp <= stamp (+1 us), or None."""
    index = int(np.searchsorted(stamps, stamp + 1000, side='right')) - 1
    return values[index] if index >= 0 else None


def load_run(bag: bags.Bag) -> Run:
    """Decode and align a bag's estimates, statuses, truth, waypoints and leader odometry."""
    data = bag.formation(REQUIRED, OPTIONAL, 'for the report')
    estimates = data['follower/estimate']
    statuses = [m for _, m in data['follower/status']]
    if not estimates or not statuses:
        raise bags.BagError(f'{bag.path}: no estimate or status messages (empty run)')
    last = statuses[-1]
    kind = last.measurement_kind if last.measurement_kind in MEASUREMENT_KINDS else 'range'
    base = Scenario.paper(kind)
    waypoints = [m for _, m in data['follower/waypoint']]
    dt = waypoints[0].substep_duration if waypoints else base.dt
    p_o = (np.array([waypoints[0].formation_slot.x, waypoints[0].formation_slot.y])
           if waypoints else base.slot)
    r = waypoints[0].radius if waypoints else base.r
    step_of = {conversions.nanoseconds(s.header.stamp): s for s in statuses}
    rows = []
    for index, (_, msg) in enumerate(estimates):
        status = step_of.get(conversions.nanoseconds(msg.header.stamp))
        x, P = conversions.estimate_values(msg)
        rows.append((status.step if status else index + 1, x, P,
                     status.weighted_trace if status else math.nan))
    n = len(rows)
    steps = np.array([row[0] for row in rows])
    stamp_of_step = {m.step: conversions.nanoseconds(m.header.stamp)
                     for _, m in data['follower/measurement']}
    truth_by_stamp = {conversions.nanoseconds(m.header.stamp): conversions.pose_of(m.pose)
                      for _, m in data['follower/truth']}
    truth = np.full((n, 3), np.nan)
    leader = np.zeros((n, 2))
    odom = data['leader/odom']
    odom_stamps = np.array([conversions.nanoseconds(m.header.stamp) for _, m in odom])
    odom_xy = np.array([[m.pose.pose.position.x, m.pose.pose.position.y] for _, m in odom])
    for i, k in enumerate(steps):
        stamp = stamp_of_step.get(int(k), round(SUBSTEPS * int(k) * dt * 1e9))
        if stamp in truth_by_stamp:
            truth[i] = truth_by_stamp[stamp]
        if len(odom):
            position = _latest_before(odom_stamps, odom_xy, stamp)
            if position is not None:
                leader[i] = position
    chosen = {w.step: (w.position.x, w.position.y) for w in waypoints}
    way = np.array([chosen.get(int(k), (math.nan, math.nan)) for k in steps])
    estimate = np.array([row[1] for row in rows])
    covariance = np.array([row[2] for row in rows])
    nees = np.array([normalized_estimation_error(truth[i], estimate[i], covariance[i])
                     if np.all(np.isfinite(truth[i])) else math.nan for i in range(n)])
    return Run(steps, SUBSTEPS * steps * dt, estimate, covariance,
               np.array([row[3] for row in rows]), truth, leader, way, nees, last.strategy,
               kind, p_o, r, dt, last)


def make_report(bag: bags.Bag, out: Path, trajectory_steps: int = 100) -> dict:
    """Write trajectory.png, weighted_trace.png, nees.png, summary.json and summary.md."""
    run = load_run(bag)
    out.mkdir(parents=True, exist_ok=True)
    n = len(run.steps)
    shown = slice(0, min(n, trajectory_steps))
    has_truth = bool(np.any(np.isfinite(run.truth[:, 0])))
    has_way = bool(np.any(np.isfinite(run.waypoints[:, 0])))
    panel = {'leader': run.leader[shown], 'estimate': run.estimate[shown],
             'covariance': run.covariance[shown],
             'truth': run.truth[shown] if has_truth else None,
             'waypoints': run.waypoints[shown] if has_way else None}
    figures = [trajectory_figure(
        {run.strategy: panel}, run.p_o, run.r, out / 'trajectory.png',
        f'{bag.path.name}: {run.measurement}, first {len(run.steps[shown])} steps',
        every=max(3, len(run.steps[shown]) // 30))]
    figures.append(trace_figure(run.time, {run.strategy: run.weighted_trace},
                                out / 'weighted_trace.png',
                                f'{bag.path.name}: weighted trace ({run.measurement})'))
    valid = np.isfinite(run.nees)
    if np.any(valid):
        figures.append(nees_figure(run.time[valid], {run.strategy: run.nees[valid]},
                                   nees_band(1), out / 'nees.png',
                                   f'{bag.path.name}: NEES (one run)'))
    window = steady_window(n)
    status = run.last_status
    counts = bag.counts()
    times = [r.log_time for r in bag.messages]
    summary = {
        'bag': str(bag.path),
        'steps': int(status.step),
        'estimates': n,
        'strategy': run.strategy,
        'measurement': run.measurement,
        'dt_s': run.dt,
        'duration_s': (max(times) - min(times)) * 1e-9 if times else 0.0,
        'steady_weighted_trace': float(np.nanmean(run.weighted_trace[-window:])),
        'steady_window_steps': window,
        'final_weighted_trace': float(run.weighted_trace[-1]),
        'mean_nees': float(np.mean(run.nees[valid])) if np.any(valid) else None,
        'nees_steps': int(np.sum(valid)),
        'nees_band_95': list(nees_band(1)),
        'rejected_measurements': int(status.rejected_measurements),
        'rejected_odometry': int(status.rejected_odometry),
        'accepted_measurements': int(status.accepted_measurements),
        'message_counts': counts,
        'figures': [p.name for p in figures],
    }
    (out / 'summary.json').write_text(json.dumps(summary, indent=2) + '\n')
    (out / 'summary.md').write_text(_markdown(summary))
    return summary


def _markdown(s: dict) -> str:
    nees = 'n/a (no truth recorded)' if s['mean_nees'] is None else (
        f"{s['mean_nees']:.3f} over {s['nees_steps']} steps (95% band for one run "
        f"{s['nees_band_95'][0]:.3f} to {s['nees_band_95'][1]:.3f})")
    lines = [
        f"# Formation run: {Path(s['bag']).name}", '',
        '| quantity | value |', '|---|---|',
        f"| steps | {s['steps']} |",
        f"| strategy | {s['strategy']} |",
        f"| measurement | {s['measurement']} |",
        f"| sub-step dt | {s['dt_s']} s |",
        f"| recorded duration | {s['duration_s']:.3f} s |",
        f"| steady tr(W P W) (last {s['steady_window_steps']} steps) | "
        f"{s['steady_weighted_trace']:.6g} m^2 |",
        f"| final tr(W P W) | {s['final_weighted_trace']:.6g} m^2 |",
        f'| mean NEES | {nees} |',
        f"| rejected measurements / odometry (last status) | {s['rejected_measurements']} / "
        f"{s['rejected_odometry']} |",
        f"| accepted measurements | {s['accepted_measurements']} |", '',
        '## Messages per topic', '', '| topic | messages |', '|---|---|']
    lines += [f'| {topic} | {count} |' for topic, count in sorted(s['message_counts'].items())]
    lines += ['', '## Figures', ''] + [f'![{name}]({name})' for name in s['figures']]
    return '\n'.join(lines) + '\n'


def main(argv: list[str] | None = None) -> None:
    """Console entry point: ``formopt-report BAG --out DIR``; exit 2 on a bad bag."""
    parser = argparse.ArgumentParser(prog='formopt-report', description=__doc__)
    parser.add_argument('bag', type=Path, help='the recorded .mcap file')
    parser.add_argument('--out', type=Path, required=True, help='output folder')
    parser.add_argument('--trajectory-steps', type=int, default=100,
                        help='steps drawn in the trajectory figure (default: first 100)')
    args = parser.parse_args(argv)
    try:
        summary = make_report(bags.read_bag(args.bag), args.out, args.trajectory_steps)
    except bags.BagError as error:
        print(f'error: {error}', file=sys.stderr)
        sys.exit(2)
    nees = 'n/a' if summary['mean_nees'] is None else f"{summary['mean_nees']:.3f}"
    print(f"{args.bag}: {summary['steps']} steps, {summary['strategy']}, "
          f"{summary['measurement']}; steady tr(W P W) {summary['steady_weighted_trace']:.6g} "
          f"m^2; mean NEES {nees}; wrote {', '.join(summary['figures'])}, summary.json, "
          f'summary.md to {args.out}')
    sys.exit(0)


if __name__ == '__main__':
    main()
