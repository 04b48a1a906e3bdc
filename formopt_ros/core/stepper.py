"""Which odometry and which measurement make measurement step k: one implementation for the
estimator node and for the offline re-estimation of a bag.

Inputs are keyed by integer nanosecond stamps. Two modes:

* lockstep: step k is ready when its measurement and the follower's and the leader's odometry
  of its sub-steps, stamped exactly on the :class:`~formopt_ros.core.protocol.Timebase` grid,
  are all in, whatever order they came in (a replayed bag delivers each topic's queue at its
  own pace). Inputs off the grid, of steps already processed, duplicates, and inputs more than
  ``LOCKSTEP_LOOKAHEAD_STEPS`` steps ahead are refused; a refused input changes nothing, so a
  stamp from far in the future cannot block the real ones.
* realtime: a step is ready when a measurement of a step not yet processed is in, and the
  follower odometry stamped like it (the follower stamps its last sub-step and the measurement
  alike; the measurement may overtake it on its own topic), or ``REALTIME_PATIENCE`` follower
  odometry messages came after the measurement without it (it was lost). The step takes the
  follower odometry stamped up to the measurement, each paired with the latest leader
  odometry stamped at or before it. Stamps more than ``future_tolerance_ns`` after the
  caller's clock are refused, so one bad stamp cannot block the later real messages; so are
  inputs stamped at or before the last processed measurement (already accounted for) and
  duplicate stamps. Inputs may come in any order otherwise (a follower that repeats its last
  step's messages after a restart of the estimator is heard). A lost measurement is skipped
  (the next one carries the odometry since) and counted. After a resume
  (:meth:`StepAssembler.open_gap`) the follower odometry lost while the estimator was down is
  replaced by the protocol's hold sub-steps (v = 0, omega = omega_L: what a follower without a
  waypoint does), one per missing dt, and counted.

Every refusal returns a reason (a short text) to count.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from formopt_ros.core.protocol import Timebase, hold_command, step_substeps

#: Realtime: how far (ns) a stamp may lie in the future of the receiving clock.
DEFAULT_FUTURE_TOLERANCE_NS = 500_000_000
#: Lockstep: inputs may belong to at most this many steps after the next one (the skew a replay
#: of a bag can produce between topics is bounded by the subscription queue depth).
LOCKSTEP_LOOKAHEAD_STEPS = 2000
#: Realtime: follower odometry messages a measurement waits for the odometry of its stamp.
REALTIME_PATIENCE = 10


@dataclass(frozen=True)
class Motion:
    """One propagation sub-step: follower odometry and the leader velocity paired with it."""

    v_f: float            # m/s
    omega_f: float        # rad/s
    v_l: float            # m/s
    omega_l: float        # rad/s


@dataclass(frozen=True)
class ReadyStep:
    """Everything one EKF step needs: the motions to propagate, then the measurement."""

    step: int
    stamp_ns: int
    motions: tuple[Motion, ...]
    value: Any            # m or rad; range-bearing: [d m, beta rad] (2,), NaN where missing
    variance: Any         # m^2 or rad^2; range-bearing: (d, beta) variances
    skipped: int = 0      # realtime: steps whose measurement never came
    filled: int = 0       # realtime: hold sub-steps put in for odometry lost in a resume gap


@dataclass
class StepAssembler:
    """Collects timestamped inputs and hands out ready steps in order (see module docstring).

    Attributes:
        lockstep: lockstep (True) or realtime (False) rules.
        timebase: the lockstep grid (also used for nothing else in realtime).
        latest_leader: the last leader (v m/s, omega rad/s) used; the planner expects it to
            persist. Starts at the scenario's first leader velocity.
        next_step: the step the assembler waits for.
    """

    lockstep: bool
    timebase: Timebase
    latest_leader: tuple[float, float]
    future_tolerance_ns: int = DEFAULT_FUTURE_TOLERANCE_NS
    next_step: int = 1
    _follower: dict[int, tuple[float, float]] = field(default_factory=dict, repr=False)
    _leader: dict[int, tuple[float, float]] = field(default_factory=dict, repr=False)
    _measurements: dict[int, tuple[int, Any, Any]] = field(
        default_factory=dict, repr=False)
    _accounted_ns: int = -1           # realtime: stamp of the last processed measurement
    _last_follower_ns: int | None = None   # realtime: last follower odometry used
    _leader_used_ns: int = -1               # realtime: last leader odometry used
    #: realtime: step -> follower odometry messages received since its measurement
    _waited: dict[int, int] = field(default_factory=dict, repr=False)
    _gap: tuple[int, int] | None = None     # realtime: (since, resumed at) stamps, ns

    def open_gap(self, resumed_ns: int, since_ns: int | None = None) -> None:
        """Realtime, after a resume at ``resumed_ns``: follower odometry missing between
        ``since_ns`` (default: the last one used) and the first one after the resume is
        filled with hold sub-steps."""
        if since_ns is None:
            since_ns = self._last_follower_ns if self._last_follower_ns is not None \
                else self._accounted_ns
        self._gap = (since_ns, resumed_ns)

    def rejoin(self, next_step: int, stamp_ns: int,
               leader: tuple[float, float] | None = None) -> None:
        """Continue at ``next_step`` after a restart without history: everything stamped at or
        before ``stamp_ns`` (the measurement of step next_step - 1, where the estimate is
        re-initialised) counts as processed and is dropped; ``leader``, when given, becomes
        the leader velocity held until its odometry comes."""
        self.next_step = next_step
        self._accounted_ns = self._leader_used_ns = stamp_ns
        if not self.lockstep:
            self._last_follower_ns = stamp_ns
        for store in (self._follower, self._leader):
            for stamp in [t for t in store if t <= stamp_ns]:
                del store[stamp]
        for step in [k for k in self._measurements if k < next_step]:
            del self._measurements[step]
            self._waited.pop(step, None)
        if leader is not None:
            self.latest_leader = leader

    # --- inputs ------------------------------------------------------------------------------
    def add_odometry(self, robot: str, stamp_ns: int, v: float, omega: float,
                     now_ns: int | None = None) -> str | None:
        """Store one odometry sub-step of robot 'follower' or 'leader' (v m/s, omega rad/s);
        the reason when refused, else None."""
        store = {'follower': self._follower, 'leader': self._leader}[robot]
        reason = self._check_stamp(f'{robot} odometry', stamp_ns, now_ns, store)
        if reason is None:
            store[stamp_ns] = (v, omega)
            if robot == 'follower':
                for step in self._waited:
                    self._waited[step] += 1
        return reason

    def add_measurement(self, step: int, stamp_ns: int, value: Any, variance: Any,
                        now_ns: int | None = None) -> str | None:
        """Store the measurement of ``step`` (a ReadyStep's value and variance); the reason
        when refused, else None."""
        if step < self.next_step:
            return f'step {step} already processed'
        if self.lockstep and self.timebase.measurement_stamp(step) != stamp_ns:
            return (f'stamp {stamp_ns} ns is not the lockstep stamp of step {step} '
                    f'({self.timebase.measurement_stamp(step)} ns)')
        if step in self._measurements:
            return f'a measurement of step {step} is already waiting'
        reason = self._check_stamp('measurement', stamp_ns, now_ns, {})
        if reason is None:
            self._measurements[step] = (stamp_ns, value, variance)
            if not self.lockstep:
                self._waited[step] = 0
        return reason

    def _check_stamp(self, stream: str, stamp_ns: int, now_ns: int | None,
                     pending: dict[int, tuple[float, float]]) -> str | None:
        if self.lockstep:
            substep = self.timebase.substep_ending_at(stamp_ns)
            if substep is None:
                return f'stamp {stamp_ns} ns is off the lockstep grid of {self.timebase.dt_ns} ns'
            if substep < step_substeps(self.next_step)[0]:
                return f'stamp {stamp_ns} ns belongs to a step already processed'
            last_step = self.next_step + LOCKSTEP_LOOKAHEAD_STEPS
            if substep > step_substeps(last_step)[-1]:
                return (f'stamp {stamp_ns} ns belongs to a step after {last_step} (waiting for '
                        f'step {self.next_step})')
            if stamp_ns in pending:
                return f'duplicate {stream} stamped {stamp_ns} ns'
            return None
        if now_ns is not None and stamp_ns > now_ns + self.future_tolerance_ns:
            return f'stamp {stamp_ns} ns is {(stamp_ns - now_ns) * 1e-9:.3f} s in the future'
        leader = stream == 'leader odometry'
        accounted = self._leader_used_ns if leader else self._accounted_ns
        if stamp_ns <= accounted:
            what = 'leader odometry used' if leader else 'processed measurement'
            return f'stamp {stamp_ns} ns is not after the last {what} ({accounted} ns)'

        if stamp_ns in pending:
            return f'duplicate {stream} stamped {stamp_ns} ns'
        return None

    # --- output ------------------------------------------------------------------------------
    def pop_ready(self) -> ReadyStep | None:
        """The next ready step (its inputs removed), or None when it is not complete yet."""
        return self._pop_lockstep() if self.lockstep else self._pop_realtime()

    def _pop_lockstep(self) -> ReadyStep | None:
        k = self.next_step
        if k not in self._measurements:
            return None
        stamps = [self.timebase.substep_end(n) for n in step_substeps(k)]
        if any(t not in self._follower or t not in self._leader for t in stamps):
            return None
        motions = []
        for t in stamps:
            v_l, omega_l = self._leader.pop(t)
            v_f, omega_f = self._follower.pop(t)
            motions.append(Motion(v_f, omega_f, v_l, omega_l))
            self.latest_leader = (v_l, omega_l)
        stamp, value, variance = self._measurements.pop(k)
        self.next_step = k + 1
        return ReadyStep(k, stamp, tuple(motions), value, variance)

    def _pop_realtime(self) -> ReadyStep | None:
        if not self._measurements:
            return None
        k = min(self._measurements)
        if self._measurements[k][0] not in self._follower and \
                self._waited[k] < REALTIME_PATIENCE:
            return None                      # its last odometry is still on the way
        stamp, value, variance = self._measurements.pop(k)
        del self._waited[k]
        motions: list[Motion] = []
        filled = 0
        for t in sorted(t for t in self._follower if t <= stamp):
            earlier = [u for u in self._leader if u <= t]
            if earlier:
                self._leader_used_ns = max(earlier)
                self.latest_leader = self._leader[self._leader_used_ns]
                for u in earlier:
                    del self._leader[u]
            filled += self._fill_gap(t, motions)
            v_f, omega_f = self._follower.pop(t)
            motions.append(Motion(v_f, omega_f, *self.latest_leader))
            self._last_follower_ns = t
        skipped = k - self.next_step
        self.next_step = k + 1
        self._accounted_ns = stamp
        return ReadyStep(k, stamp, tuple(motions), value, variance, skipped, filled)

    def _fill_gap(self, t: int, motions: list[Motion]) -> int:
        """Hold sub-steps for the follower odometry missing before ``t`` inside the resume gap;
        their number."""
        if self._gap is None:
            return 0
        since, resumed = self._gap
        if t <= since:
            return 0
        previous = self._last_follower_ns if self._last_follower_ns is not None and \
            self._last_follower_ns >= since else since
        missing = 0
        if previous < resumed and previous >= 0:
            missing = max(round((t - previous) / self.timebase.dt_ns) - 1, 0)
        v_l, omega_l = self.latest_leader
        motions.extend(Motion(*hold_command(omega_l), v_l, omega_l) for _ in range(missing))
        if t >= resumed:
            self._gap = None
        return missing

    def pending(self) -> dict[str, int]:
        """How many inputs wait, per stream (for status and diagnostics)."""
        return {'follower_odometry': len(self._follower), 'leader_odometry': len(self._leader),
                'measurements': len(self._measurements)}
