"""The integer-nanosecond lockstep timebase and the sub-step structure of a measurement step."""
from __future__ import annotations

import pytest

from formopt_ros.core.protocol import (
    SUBSTEPS, Timebase, held_leader_motion, seconds_to_ns, step_substeps)


def test_timebase_stamps_are_exact_integers() -> None:
    """Sub-step n ends at (n + 1) dt; step k's measurement at SUBSTEPS k dt; its waypoint at
    SUBSTEPS (k - 1) dt; the inverses find them back exactly and refuse stamps off the grid."""
    timebase = Timebase.from_dt(0.05)
    assert timebase.dt_ns == 50_000_000
    assert [timebase.substep_end(n) for n in step_substeps(3)] == [250_000_000, 300_000_000]
    assert timebase.measurement_stamp(3) == 300_000_000
    assert timebase.waypoint_stamp(3) == 200_000_000
    for n in range(10_000):
        assert timebase.substep_ending_at(timebase.substep_end(n)) == n
    for k in range(1, 5_000):
        assert timebase.step_of_measurement(timebase.measurement_stamp(k)) == k
    assert timebase.substep_ending_at(0) is None                  # nothing ends at t = 0
    assert timebase.substep_ending_at(50_000_001) is None
    assert timebase.step_of_measurement(50_000_000) is None       # a sub-step, not a step


def test_timebase_matches_float_seconds_for_long_runs() -> None:
    """For dt = 0.05 s the integer stamps equal the rounded float seconds of the old protocol
    over a million sub-steps (no drift)."""
    timebase = Timebase.from_dt(0.05)
    for n in (0, 1, 999, 123_456, 999_999):
        assert timebase.substep_end(n) == seconds_to_ns((n + 1) * 0.05)


@pytest.mark.parametrize('dt', [0.0, -0.01, 1e-10])
def test_timebase_refuses_a_step_shorter_than_a_nanosecond(dt: float) -> None:
    with pytest.raises(ValueError, match='dt'):
        Timebase.from_dt(dt)


def test_step_substeps_and_held_leader_motion() -> None:
    assert list(step_substeps(1)) == list(range(SUBSTEPS))
    assert list(step_substeps(4)) == [6, 7]
    assert held_leader_motion((1.0, 0.2)) == ((1.0, 0.2),) * SUBSTEPS
