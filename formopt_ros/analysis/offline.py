"""Offline re-estimation: re-run one follower's estimator over its recorded inputs and compare.

The bag's odometry, measurements and truth are fed, in recorded (log-time) order, through the
same functions the estimator node calls (:mod:`formopt_ros.wire.inputs`) into the same
:class:`~formopt_ros.core.session.EstimatorSession`, so a lockstep bag is reproduced exactly
(the inputs are matched by their stamps) and a realtime bag as the recorder saw the arrivals
(the estimator may have seen another order). A strategy changed mid-run (the description's
``strategy_changes``) takes over at the step it took over in the node.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from formopt_ros.analysis.recording import FollowerRecording, Recording, with_overrides
from formopt_ros.bag import BagError
from formopt_ros.core.session import EstimatorSession, StepOutcome
from formopt_ros.core.model import state_difference
from formopt_ros.core.simulation import trial_streams
from formopt_ros.core.strategies import make_strategy
from formopt_ros.wire import inputs
from formopt_ros.wire.description import RunDescription, StrategyChange
from formopt_ros.wire.messages import estimate_values, header_ns


@dataclass
class OfflineResult:
    """Offline estimator run over a bag's inputs versus its recorded estimates."""

    follower_id: str
    steps: int
    recorded_steps: int
    strategy: str                   # every strategy used, '+'-joined in order
    measurement: str
    mode: str
    legacy: bool
    max_state_diff: float
    max_covariance_diff: float
    max_waypoint_diff: float | None
    max_stamp_diff_ns: int
    estimates: list[np.ndarray] = field(default_factory=list, repr=False)
    covariances: list[np.ndarray] = field(default_factory=list, repr=False)
    #: the re-estimate's consistency watch (:meth:`ConsistencyWatch.summary`), the verdict the
    #: estimator node reaches on the same inputs
    consistency: dict[str, Any] = field(default_factory=dict)
    #: steps re-estimated whose recorded estimate is missing, and recorded steps not
    #: re-estimated (their inputs are missing); the differences cover the steps both have
    not_recorded: list[int] = field(default_factory=list)
    not_reestimated: list[int] = field(default_factory=list)
    #: the last step either has, and the steps before it that neither has
    last_step: int = 0
    absent: list[int] = field(default_factory=list)

    @property
    def consistent(self) -> bool:
        """False when the re-estimate saw sustained inconsistency or gating."""
        return self.consistency.get('worst', {}).get('level') != 'error'

    @property
    def max_diff(self) -> float:
        """Largest difference over states, covariances, waypoints (m) and, in lockstep, stamps
        (s); inf when a step is missing from either. The verdict of the replay: a planner that
        sends other waypoints than the recorded ones fails it even when the estimates agree."""
        if self.not_recorded or self.not_reestimated or self.absent:
            return math.inf
        return self.compared_diff

    @property
    def compared_diff(self) -> float:
        """The largest difference over the steps both the re-estimate and the recording have
        (paired by step number)."""
        return max(self.max_state_diff, self.max_covariance_diff,
                   self.max_waypoint_diff or 0.0, self.max_stamp_diff_ns * 1e-9)

    def as_dict(self) -> dict[str, Any]:
        """JSON-friendly summary (no arrays)."""
        return {'follower_id': self.follower_id, 'steps': self.steps,
                'recorded_steps': self.recorded_steps, 'strategy': self.strategy,
                'measurement': self.measurement, 'mode': self.mode, 'legacy': self.legacy,
                'max_state_diff': self.max_state_diff,
                'max_covariance_diff': self.max_covariance_diff,
                'max_waypoint_diff': self.max_waypoint_diff,
                'max_stamp_diff_ns': self.max_stamp_diff_ns, 'max_diff': self.max_diff,
                'consistency': self.consistency, 'missing_from_recording': self.absent,
                'not_reestimated': self.not_reestimated, 'not_recorded': self.not_recorded}


def _inputs(recording: Recording, follower: FollowerRecording) -> list[tuple[int, str, Any]]:
    """(log time, kind, message) of every estimator input, in recorded order."""
    events = []
    for kind, topic in (('follower_odom', follower.topics.get('follower_odom')),
                        ('leader_odom', recording.leader_topic),
                        ('truth', follower.topics.get('truth')),
                        ('measurement', follower.topics.get('measurement'))):
        events += [(record.log_time, kind, msg) for record, msg in recording.messages(topic)]
    order = {'truth': 0, 'follower_odom': 1, 'leader_odom': 1, 'measurement': 2}
    events.sort(key=lambda e: (e[0], order[e[1]]))
    return events


def offline(recording: Recording, follower_id: str | None = None, **overrides: Any
            ) -> OfflineResult:
    """Re-run one follower's estimator over the bag and compare with what it published.

    Args:
        recording: the loaded bag.
        follower_id: which follower (default: the only one).
        **overrides: RunDescription fields to replace (strategy, options, seed, trial, mode,
            scenario); None values are ignored.
    """
    follower = recording.follower(follower_id)
    if follower.topics.get('measurement') is None or follower.topics.get('estimate') is None:
        raise BagError(f'{recording.bag.path}: {follower.namespace} has no measurement or no '
                       'estimate topic (needed for the offline replay)')
    description = with_overrides(follower.description, **overrides)
    try:
        strategy = make_strategy(description.strategy, **description.options)
    except ValueError as error:
        raise BagError(f'{recording.bag.path}: {error}') from None
    _, planner_rng = trial_streams(description.seed, description.trial)
    session = EstimatorSession.create(description.scenario, strategy, planner_rng,
                                      description.mode == 'lockstep', description.steps)
    plans = {1: session.plan_next().solution.p}
    outcomes: list[StepOutcome] = []
    changes = list(description.strategy_changes)
    lockstep = description.mode == 'lockstep'
    for log_time, kind, msg in _inputs(recording, follower):
        now = None if lockstep else log_time
        if kind == 'follower_odom':
            inputs.feed_odometry(session, 'follower', msg, description.follower_id, now)
        elif kind == 'leader_odom':
            inputs.feed_odometry(session, 'leader', msg, description.leader_id, now)
        elif kind == 'truth':
            inputs.feed_truth(session, msg)
        else:
            inputs.feed_measurement(session, msg, description.follower_id, now,
                                    description.run_id)
        while changes and changes[0].step <= session.step:
            session.estimator.strategy = _prepared(recording, description, changes.pop(0))
        for outcome in session.advance():
            outcomes.append(outcome)
            if outcome.plan is not None:
                plans[outcome.plan.step] = outcome.plan.solution.p
    # compared step by step, not by position: a bag with a damaged stretch lacks some steps
    recorded = {step: (header_ns(msg), *estimate_values(msg))
                for step, msg, _ in recording.follower_estimates(follower)}
    pairs = [(o, recorded[o.step]) for o in outcomes if o.step in recorded]
    state = max((float(np.max(np.abs(state_difference(o.x, r[1])))) for o, r in pairs),
                default=0.0)
    covariance = max((float(np.max(np.abs(o.P - r[2]))) for o, r in pairs), default=0.0)
    stamps = max((abs(o.stamp_ns - r[0]) for o, r in pairs), default=0)
    estimated = {o.step for o in outcomes}
    last = max(estimated | set(recorded), default=0)
    chosen = {int(w.step): np.array([w.position.x, w.position.y])
              for w in recording.follower_messages(follower, 'waypoint')}
    common = [step for step in plans if step in chosen]
    waypoint = max((float(np.max(np.abs(plans[s] - chosen[s]))) for s in common),
                   default=None)
    return OfflineResult(description.follower_id, len(outcomes), len(recorded),
                         '+'.join(description.strategies()), description.scenario.measurement,
                         description.mode, follower.legacy, state, covariance, waypoint,
                         stamps if lockstep else 0, [o.x for o in outcomes],
                         [o.P for o in outcomes], session.watch.summary(),
                         sorted(estimated - set(recorded)), sorted(set(recorded) - estimated),
                         last, sorted(set(range(1, last + 1)) - estimated - set(recorded)))


def _prepared(recording: Recording, description: RunDescription, change: StrategyChange) -> Any:
    """The strategy of a mid-run change, prepared for the run's scenario."""
    try:
        strategy = make_strategy(change.strategy, **change.options)
    except ValueError as error:
        raise BagError(f'{recording.bag.path}: strategy change at step {change.step}: '
                       f'{error}') from None
    strategy.prepare(description.scenario)
    return strategy
