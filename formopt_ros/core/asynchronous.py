"""The estimator of a follower on real robots: odometry of both robots at any rates, each
interval integrated exactly, each measurement applied at its own stamp through a reorder buffer.

Odometry: a message stamped t carries the twist (v m/s, omega rad/s) the robot held over the
interval since its previous message, (t_prev, t] (what a base that differentiates its encoders
reports; the simulators stamp each sub-step's odometry at its end). The first message of a robot
covers the time since the estimator started. The estimator's state lives at one time; to reach a
measurement stamp it splits the interval at every odometry stamp of either robot, so over each
piece both twists are constant and the exact propagation of :mod:`formopt_ros.core.model`
applies.

Messages of one topic arrive in stamp order (as over one DDS topic); topics interleave in any
order. Measurements wait in a reorder buffer and are applied in stamp order. One is applied
as soon as both robots' odometry reaches its stamp, or once the caller's clock is
``reorder_lag`` past it: then a robot whose odometry has not arrived is carried on its last
twist (``bridged``). A measurement or odometry stamped at or before the time the state has
reached is late: dropped and counted. An odometry interval longer than ``max_gap`` (messages
lost) is integrated with the twist of the message that ends it and counted as a gap. A
message's velocity noise (its twist covariance when given, else the scenario's sigmas) is held
over its whole interval, so a piece of duration tau of a message's interval T carries the share
tau / T of its displacement variance: the noise standard deviation is scaled by sqrt(T / tau),
and the pieces of one message add up to the whole message's noise. Fed the lockstep stream
(odometry on the sub-step grid, a measurement after its step's odometry) it performs
lockstep's arithmetic.
"""
from __future__ import annotations

import bisect
import copy
import heapq
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from formopt_ros.core.consistency import ConsistencyWatch, WatchSettings
from formopt_ros.core.estimator import EstimatorPlanner, StepPlan, UpdateResult
from formopt_ros.core.field import dead_reckoned_estimate, odometry_pose_at, relative_pose
from formopt_ros.core.protocol import NS_PER_S, held_leader_motion

#: How long the odometry poses of each robot are kept, ns (the longest outage bridged by
#: dead reckoning).
POSE_MEMORY_NS = 60 * NS_PER_S
#: A robot whose twists say it travelled more than this (m) while its pose stayed put
#: publishes no odometry pose.
POSE_CHECK_M = 0.05

#: The two odometry streams.
ROBOTS = ('follower', 'leader')


@dataclass(frozen=True)
class AsyncSettings:
    """Timing rules of the asynchronous estimator (module docstring).

    Attributes:
        reorder_lag_ns: how long a measurement waits for odometry and earlier measurements,
            ns (the largest delay between a stamp and its arrival the estimator accepts).
        max_gap_ns: odometry intervals longer than this are counted as gaps, ns.
        max_gated_share: share of the consistency window's measurements the gate may refuse
            before the watch calls it sustained gating (an ERROR). Real ranges carry
            non-line-of-sight outliers that the gate refuses rightly (10 % of them gated 5 of
            20 with the filter consistent, NEES 1.9); a diverged filter gates most. The
            simulated filter, without outliers, keeps the watch's 10 %. The NIS of a gated
            measurement is judged by this share alone (WatchSettings.judge_gated_nis).
    """

    reorder_lag_ns: int = 100_000_000
    max_gap_ns: int = 500_000_000
    max_gated_share: float = 0.5

    def __post_init__(self) -> None:
        if self.reorder_lag_ns < 0 or self.max_gap_ns <= 0:
            raise ValueError(f'reorder_lag_ns must be >= 0 and max_gap_ns > 0, got '
                             f'{self.reorder_lag_ns} and {self.max_gap_ns}')


@dataclass
class AsyncCounters:
    """What the asynchronous estimator did with its inputs."""

    odometry: int = 0                  # odometry messages accepted (both robots)
    measurements: int = 0              # measurements applied (used or gated)
    late_odometry: int = 0             # stamped at or before the state's time: dropped
    late_measurements: int = 0         # stamped at or before the state's time: dropped
    duplicates: int = 0                # a second message with the same stamp: dropped
    bridged: int = 0                   # propagations past a robot's last odometry
    gaps: int = 0                      # odometry intervals longer than max_gap
    gated_measurements: int = 0        # refused by the innovation gate
    downweighted_measurements: int = 0  # used with Huber weight < 1
    covariance_inflations: int = 0     # the filter re-opened after gated measurements
    outage_resets: int = 0             # the state made again by dead reckoning after an outage

    def as_dict(self) -> dict[str, int]:
        """Plain dict (for JSON and status messages)."""
        return dict(self.__dict__)


@dataclass
class TwistTimeline:
    """The odometry of one robot not yet integrated: (stamp ns, v m/s, omega rad/s), sorted.

    Attributes:
        last: the twist of the newest message integrated or received, used to carry the robot
            past its last message.
    """

    samples: list[tuple[int, float, float]] = field(default_factory=list)
    last: tuple[float, float] | None = None
    #: stamp -> the message's own (sigma_v m/s, sigma_omega rad/s), where it gave them
    noise: dict[int, tuple[float, float]] = field(default_factory=dict)

    def add(self, stamp_ns: int, v: float, omega: float,
            noise: tuple[float, float] | None = None) -> bool:
        """Insert one message (with its own velocity noise, if known); False when its stamp is
        already there."""
        index = bisect.bisect_left(self.samples, (stamp_ns,))
        if index < len(self.samples) and self.samples[index][0] == stamp_ns:
            return False
        self.samples.insert(index, (stamp_ns, v, omega))
        if noise is not None:
            self.noise[stamp_ns] = noise
        if index == len(self.samples) - 1:
            self.last = (v, omega)
        return True

    @property
    def newest_ns(self) -> int | None:
        """Stamp of the newest message not yet integrated (None: none waits)."""
        return self.samples[-1][0] if self.samples else None

    def twist_until(self, end_ns: int) -> tuple[float, float, int | None]:
        """The twist held just before ``end_ns``: that of the first message stamped at or after
        it (its stamp), else the last known one (stamp None: carried)."""
        index = bisect.bisect_left(self.samples, (end_ns,))
        if index < len(self.samples):
            _, v, omega = self.samples[index]
            return v, omega, self.samples[index][0]
        v, omega = self.last if self.last is not None else (0.0, 0.0)
        return v, omega, None

    def drop_through(self, stamp_ns: int) -> None:
        """Forget the messages stamped at or before ``stamp_ns`` (integrated)."""
        index = bisect.bisect_right(self.samples, (stamp_ns, np.inf, np.inf))
        if index:
            self.last = self.samples[index - 1][1:]
            for stamp, _, _ in self.samples[:index]:
                self.noise.pop(stamp, None)
            del self.samples[:index]


@dataclass(frozen=True)
class AppliedMeasurement:
    """One measurement applied at its stamp: the posterior and what the update did."""

    stamp_ns: int
    x: np.ndarray          # (3,) pose in {L}
    P: np.ndarray          # (3, 3)
    update: UpdateResult
    bridged: bool          # a robot's odometry was carried past its last message


class AsyncEstimator:
    """An :class:`EstimatorPlanner` fed timestamped inputs of any rate (module docstring).

    Args:
        estimator: the EKF and strategy (its scenario's dt is the planner's sub-step).
        start_ns: the time of the initial estimate, ns.
        settings: the timing rules.
    """

    def __init__(self, estimator: EstimatorPlanner, start_ns: int,
                 settings: AsyncSettings = AsyncSettings()) -> None:
        self.estimator = estimator
        self.time_ns = start_ns
        self.settings = settings
        self.counters = AsyncCounters()
        self.timelines = {robot: TwistTimeline() for robot in ROBOTS}
        self._previous = {robot: start_ns for robot in ROBOTS}   # end of the last interval
        self._waiting: list[tuple[int, float, float]] = []      # heap of measurements
        self.applied = 0
        # odometry poses (stamp ns, pose, v, omega) of each robot over the last POSE_MEMORY_NS,
        # and, per robot carried past its last message, the state when that began
        self._poses: dict[str, deque[tuple[int, tuple[float, float, float], float, float]]] = {
            robot: deque() for robot in ROBOTS}
        self._carried_from: dict[str, tuple[int, np.ndarray, np.ndarray]] = {}
        # every update's NIS and whether it was gated
        self.watch = ConsistencyWatch(WatchSettings(max_gated_share=settings.max_gated_share,
                                                    judge_gated_nis=False))

    # --- inputs ------------------------------------------------------------------------------
    def add_odometry(self, robot: str, stamp_ns: int, v: float, omega: float,
                     noise: tuple[float, float] | None = None,
                     pose: tuple[float, float, float] | None = None) -> str | None:
        """The twist ``robot`` ('follower' or 'leader') held up to ``stamp_ns``, with its own
        noise standard deviations (m/s, rad/s; None: the scenario's) and, when the message
        carries one, the robot's odometry pose at ``stamp_ns`` (x m, y m, yaw rad in its own
        odometry frame: with both robots' poses an outage is bridged by dead reckoning,
        :meth:`_reset_after_outage`); the reason when refused (late, duplicate), else None."""
        if stamp_ns <= self.time_ns:
            self.counters.late_odometry += 1
            timeline = self.timelines[robot]
            if not timeline.samples:          # the freshest twist known, to carry the robot on
                timeline.last = (v, omega)
            return f'{robot} odometry stamped {stamp_ns} ns is not after the estimate ' \
                   f'({self.time_ns} ns)'
        if not self.timelines[robot].add(stamp_ns, v, omega, noise):
            self.counters.duplicates += 1
            return f'duplicate {robot} odometry stamped {stamp_ns} ns'
        self.counters.odometry += 1
        carried = self._carried_from.pop(robot, None)
        if pose is not None:
            log = self._poses[robot]
            log.append((stamp_ns, pose, v, omega))
            while log and log[0][0] < stamp_ns - POSE_MEMORY_NS:
                log.popleft()
            if carried is not None and self.time_ns - carried[0] > self.settings.max_gap_ns:
                self._reset_after_outage(carried)
        return None

    def _reset_after_outage(self, carried: tuple[int, np.ndarray, np.ndarray]) -> None:
        """A robot was carried on its last twist for longer than max_gap (its messages lost)
        and is heard again: the updates meanwhile were made with motion that did not happen,
        so the state is made again from the state when the carrying began, moved by both
        robots' odometry poses since (:func:`~formopt_ros.core.field.dead_reckoned_estimate`:
        the prior plus the odometry's drift). Skipped unless both robots' poses cover the span
        and move with their twists (a base that publishes no pose reports a constant one)."""
        then, x0, P0 = carried
        moves = []
        for robot in ROBOTS:
            log = self._poses[robot]
            start = odometry_pose_at(log, then, None, True)
            end = odometry_pose_at(log, self.time_ns, None, True)
            if start is None or end is None or not log or log[0][0] > then:
                return
            moves.append(relative_pose(start, end))
            span = (log[-1][0] - log[0][0]) / NS_PER_S
            travelled = max(abs(v) for _, _, v, _ in log) * span
            if travelled > POSE_CHECK_M and np.hypot(*(np.subtract(log[-1][1][:2],
                                                                   log[0][1][:2]))) < 1e-6:
                return                      # a pose that never moves: not an odometry pose
        follower_move, leader_move = moves
        s = self.estimator.scenario
        x, P = dead_reckoned_estimate(
            x0[:3], P0[:3, :3], tuple(leader_move), tuple(follower_move),
            max(1, round((self.time_ns - then) / NS_PER_S / s.dt)), s.dt,
            (s.sigma_v, s.sigma_omega, s.sigma_v_leader, s.sigma_omega_leader))
        state = x0.copy()
        state[:3] = x
        covariance = np.diag(np.diag(P0)).astype(float)
        covariance[:3, :3] = P
        self.estimator.state, self.estimator.covariance = state, covariance
        self.counters.outage_resets += 1

    def add_measurement(self, stamp_ns: int, value: float, variance: float) -> str | None:
        """A range (m) or bearing (rad) with its variance, taken at ``stamp_ns``; the reason
        when refused (late), else None. It is applied by :meth:`advance`."""
        if any(t == stamp_ns for t, _, _ in self._waiting):
            self.counters.duplicates += 1
            return f'duplicate measurement stamped {stamp_ns} ns'
        if stamp_ns <= self.time_ns:
            self.counters.late_measurements += 1
            return f'measurement stamped {stamp_ns} ns is not after the estimate ' \
                   f'({self.time_ns} ns)'
        heapq.heappush(self._waiting, (stamp_ns, value, variance))
        return None

    # --- processing --------------------------------------------------------------------------
    def _covered(self, stamp_ns: int) -> bool:
        return all(t.newest_ns is not None and t.newest_ns >= stamp_ns
                   for t in self.timelines.values())

    def advance(self, now_ns: int | None = None) -> list[AppliedMeasurement]:
        """Apply every measurement whose odometry is in, and (with the clock ``now_ns``) every
        one older than the reorder lag; in stamp order."""
        out = []
        while self._waiting:
            stamp = self._waiting[0][0]
            due = now_ns is not None and stamp <= now_ns - self.settings.reorder_lag_ns
            if not (self._covered(stamp) or due):
                break
            stamp, value, variance = heapq.heappop(self._waiting)
            bridged = self.propagate_to(stamp)
            update = self.estimator.update(self.applied + 1, value, variance)
            self.applied += 1
            self._count(update)
            for part in update.nis_parts():
                self.watch.add_nis(part, not update.used, self.applied)
            out.append(AppliedMeasurement(stamp, self.estimator.x.copy(),
                                          self.estimator.P.copy(), update, bridged))
        return out

    def _count(self, update: UpdateResult) -> None:
        c = self.counters
        c.measurements += 1
        c.gated_measurements += not update.used
        c.downweighted_measurements += update.used and update.weight < 1.0
        c.covariance_inflations += update.used and update.inflation > 1.0

    def propagate_to(self, stamp_ns: int) -> bool:
        """Integrate both robots' odometry from the state's time to ``stamp_ns``; True when a
        robot was carried past its last message (counted as bridged)."""
        bridged = False
        while self.time_ns < stamp_ns:
            pieces = {robot: t.twist_until(self.time_ns + 1)
                      for robot, t in self.timelines.items()}
            for robot, (_, _, message_end) in pieces.items():
                if message_end is None and robot not in self._carried_from:
                    self._carried_from[robot] = (self.time_ns, self.estimator.state.copy(),
                                                 self.estimator.covariance.copy())
            ends = [s for _, _, s in pieces.values() if s is not None and s < stamp_ns]
            end = min(ends, default=stamp_ns)
            (v_f, omega_f, _), (v_l, omega_l, _) = pieces['follower'], pieces['leader']
            self.estimator.propagate(v_f, omega_f, v_l, omega_l,
                                     (end - self.time_ns) / NS_PER_S, self._noise(pieces, end))
            self.time_ns = end
            for robot, timeline in self.timelines.items():
                ends_here = pieces[robot][2]
                bridged = bridged or ends_here is None
                if ends_here == end:
                    self.counters.gaps += end - self._previous[robot] > \
                        self.settings.max_gap_ns
                    self._previous[robot] = end
                timeline.drop_through(end)
        self.counters.bridged += bridged
        return bridged

    def _noise(self, pieces: dict[str, tuple[float, float, int | None]],
               end: int) -> tuple[float, float, float, float] | None:
        """The noise standard deviations of the piece (time_ns, end]: each robot's message's
        own or the scenario's, scaled by sqrt(T / tau) (module docstring); None when the piece
        is a whole message of each robot with the scenario's noise (the lockstep case)."""
        s = self.estimator.scenario
        defaults = {'follower': (s.sigma_v, s.sigma_omega),
                    'leader': (s.sigma_v_leader, s.sigma_omega_leader)}
        out: list[float] = []
        plain = True
        for robot, (_, _, ends) in pieces.items():
            sigmas = defaults[robot] if ends is None else \
                self.timelines[robot].noise.get(ends, defaults[robot])
            span = 1.0 if ends is None else (ends - self._previous[robot]) / (end - self.time_ns)
            plain = plain and span == 1.0 and sigmas == defaults[robot]
            out += [sigmas[0] * float(np.sqrt(span)), sigmas[1] * float(np.sqrt(span))]
        return None if plain else (out[0], out[1], out[2], out[3])

    # --- outputs -----------------------------------------------------------------------------
    def estimate_at(self, stamp_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """The pose (3,) and covariance (3, 3) propagated to ``stamp_ns`` on the odometry in
        (the state itself stays where it is)."""
        if stamp_ns <= self.time_ns:
            return self.estimator.x.copy(), self.estimator.P.copy()
        probe = copy.copy(self)
        probe.estimator = copy.copy(self.estimator)
        probe.counters = AsyncCounters()
        probe.timelines = {r: copy.deepcopy(t) for r, t in self.timelines.items()}
        probe._previous = dict(self._previous)
        probe.propagate_to(stamp_ns)
        return probe.estimator.x.copy(), probe.estimator.P.copy()

    def plan(self, step: int) -> StepPlan:
        """The strategy's next decision from the current estimate, the leader expected to hold
        its last reported twist."""
        last = self.timelines['leader'].last
        return self.estimator.plan(step, held_leader_motion(last if last else (0.0, 0.0)))

    def pending(self) -> dict[str, int]:
        """Inputs waiting, per stream."""
        return {'follower_odometry': len(self.timelines['follower'].samples),
                'leader_odometry': len(self.timelines['leader'].samples),
                'measurements': len(self._waiting)}

    def waiting_measurements(self) -> list[tuple[int, float]]:
        """The measurements buffered and not yet applied: (stamp ns, value m or rad), in stamp
        order."""
        return [(stamp, value) for stamp, value, _ in sorted(self._waiting)]


__all__ = ['AppliedMeasurement', 'AsyncCounters', 'AsyncEstimator', 'AsyncSettings',
           'ROBOTS', 'TwistTimeline']
