"""Domain rules a scenario must meet before a run starts, each with its stated reason.

* :func:`check_input_domain`: the inputs the run itself produces must pass the estimator's
  plausibility gate (:class:`~formopt_ros.core.estimator.InputBounds`, relative to |p_o|):
  otherwise every leader odometry message of a tiny slot (e.g. 2 mm at 1 m/s) is refused as
  implausible and the run hangs until its timeout.
* :func:`check_deviation_domain`: a follower that measures bearings (alone or with ranges)
  whose disc comes too close to the leader diverges (docs/faults.md, "Why large discs diverge
  for bearing"): the EKF's bearing model is linearised with a Jacobian of size 1/|p| and a
  curvature of 1/|p|^2, so a position error that is a fair fraction of the distance to the
  leader makes the update wrong by more than the measurement noise. Measured boundary (50
  trials x 600 steps, RAM, the paper's bearing noise): consistent when the disc keeps
  ``CLEARANCE_SIGMAS`` initial position standard deviations and ``BEARING_CLEARANCE_FRACTION``
  |p_o| from the leader, divergent trials just beyond; range-bearing diverges from 0.7 |p_o|
  on and is held to the same rule.

Both raise ValueError naming the field to change; neither is needed for the paper's settings.
"""
from __future__ import annotations

import math
from dataclasses import replace

from formopt_ros.core.checks import InvalidInput
from formopt_ros.core.cost import MIN_DEVIATION
from formopt_ros.core.estimator import TRAVEL_BOUND, TURN_BOUND
from formopt_ros.core.model import BEARING, RANGE_BEARING
from formopt_ros.core.reach import CLEARANCE_SIGMAS
from formopt_ros.core.scenario import LeaderPath, Scenario

#: The steady-state clearance of a bearing follower's disc, a fraction of |p_o|: with a small
#: initial covariance (1e-4 m^2) RAM's filter is flagged at a disc of 0.8 |p_o| (trial-mean
#: NEES in its band on 74 % of the steps), consistent at 0.78 (79 %) and 0.75 (87 %).
BEARING_CLEARANCE_FRACTION = 0.22
#: Initial position standard deviations the estimate may move by when it settles (the
#: follower's commands cover that correction in one sub-step).
SETTLING_SIGMAS = 3.0


def leader_extremes(path: LeaderPath) -> tuple[float, float]:
    """The largest |speed| (m/s) and |yaw rate| (rad/s) the leader path ever commands."""
    motions = path.extreme_motions()
    return max(abs(v) for v, _ in motions), max(abs(w) for _, w in motions)


def check_input_domain(scenario: Scenario, field: str = 'p_o') -> None:
    """Refuse a scenario whose own odometry the estimator would refuse as implausible.

    The gate allows TRAVEL_BOUND |p_o| of travel and TURN_BOUND half-turns per sub-step dt.
    The leader travels up to max |v_L| dt per sub-step; the follower, which rotates in place on
    one sub-step and translates on the other, covers twice that plus a move across the disc
    (up to 2 r) plus the estimate's settling (SETTLING_SIGMAS initial position standard
    deviations: a correction of the estimate is driven in one sub-step). All of it must fit in
    TRAVEL_BOUND |p_o|.

    Args:
        scenario: the follower's settings.
        field: the name the message gives the slot (the caller's spelling, e.g. 'slot').

    Raises:
        ValueError: naming ``field``, the need and the bound, with the smallest slot allowed.
    """
    s = scenario
    speed, turn = leader_extremes(s.leader)
    if turn > TURN_BOUND * math.pi / s.dt:
        raise ValueError(f'leader yaw rate {turn:g} rad/s exceeds what the estimator accepts '
                         f'as plausible ({TURN_BOUND:g} half-turns per dt = '
                         f'{TURN_BOUND * math.pi / s.dt:.6g} rad/s)')
    sigma0 = math.sqrt(max(s.initial_covariance[0], s.initial_covariance[1]))
    need = 2.0 * speed * s.dt + 2.0 * s.r + SETTLING_SIGMAS * sigma0
    allowed = TRAVEL_BOUND * s.d_o
    if need > allowed:
        smallest = need / TRAVEL_BOUND
        raise ValueError(
            f'{field} [{s.p_o[0]:.6g}, {s.p_o[1]:.6g}] (|p_o| = {s.d_o:.6g} m) is too small '
            f'for this run: the estimator refuses as implausible any odometry of more than '
            f'{TRAVEL_BOUND:g} |p_o| = {allowed:.6g} m per sub-step, and the follower may '
            f'need {need:.6g} m '
            f"(twice the leader's {speed:g} m/s x dt {s.dt:g} s, the disc 2 r = "
            f'{2 * s.r:.6g} m, the settling {SETTLING_SIGMAS:g} initial standard deviations '
            f'= {SETTLING_SIGMAS * sigma0:.6g} m): its odometry would be refused. Use a slot at '
            f'least {smallest:.6g} m from the leader')


def check_deviation_domain(scenario: Scenario, field: str = 'deviation') -> None:
    """Refuse a bearing or range-bearing scenario whose disc reaches too close to the leader
    (module docstring).

    The clearance, the larger of |p_o| - r and the safety distance (no point is planned
    closer), must be at least CLEARANCE_SIGMAS initial position standard deviations (the
    first updates) and BEARING_CLEARANCE_FRACTION |p_o| (the steady state). The rule was
    measured at the paper's bearing noise; a much finer bearing can diverge inside it
    (docs/faults.md).
    Range followers are not limited: RAM, RQ and PERIODIC stay consistent up to a deviation of
    0.999 |p_o| (behind a straight or turning leader PERIODIC keeps its cycle
    0.2 |p_o| from the leader, :data:`~formopt_ros.core.reach.CLEARANCE_FRACTION`).

    Args:
        scenario: the follower's settings.
        field: the name the message gives the deviation (e.g. 'deviation',
            'deviation_fraction', '--r-fraction').

    Raises:
        ValueError: naming ``field``, the clearance, the rule and the largest fraction allowed.
    """
    s = scenario
    if s.measurement not in (BEARING, RANGE_BEARING):
        return
    sigma0 = math.sqrt(max(s.initial_covariance[0], s.initial_covariance[1]))
    clearance = max(s.d_o - s.r, s.safety_distance)     # no point is planned inside either
    need = max(CLEARANCE_SIGMAS * sigma0, BEARING_CLEARANCE_FRACTION * s.d_o)
    if clearance < need * (1.0 - 1e-9):     # the limit itself passes (0.78 of 0.22 |p_o| ...)
        # the remedies named are rounded so that they pass (1e-10: 0.78 stays 0.78)
        largest = math.floor((1.0 - need / s.d_o) * 1e4 + 1e-6) / 1e4
        safety = math.ceil(need * 1e4 - 1e-6) / 1e4       # m, on a 0.1 mm grid
        remedies = [f'a deviation of at most {largest:g}'] if largest >= MIN_DEVIATION else []
        try:                                     # Scenario's own rule: it leaves a point
            replace(s, safety_distance=safety)
            remedies.append(f'a safety distance of at least {safety:g} m')
        except InvalidInput:
            pass
        if not remedies:
            remedies.append('a slot farther from the leader or a smaller initial covariance')
        raise ValueError(
            f'{field} {s.r / s.d_o:.6g}: a follower that measures bearings must keep its disc '
            f'{need:.6g} m from the leader (the larger of {CLEARANCE_SIGMAS:g} initial '
            f'position standard deviations = {CLEARANCE_SIGMAS * sigma0:.6g} m and '
            f'{BEARING_CLEARANCE_FRACTION:g} |p_o| = {BEARING_CLEARANCE_FRACTION * s.d_o:.6g} '
            f'm), this one comes to {clearance:.6g} m: closer, the linearised bearing model is '
            'wrong by more than the noise and the filter diverges (docs/faults.md). Use '
            + ', or '.join(remedies))


def check_domain(scenario: Scenario, slot_field: str = 'p_o',
                 deviation_field: str = 'deviation') -> None:
    """:func:`check_input_domain` then :func:`check_deviation_domain`."""
    check_input_domain(scenario, slot_field)
    check_deviation_domain(scenario, deviation_field)


__all__ = ['BEARING_CLEARANCE_FRACTION', 'CLEARANCE_SIGMAS', 'SETTLING_SIGMAS',
           'check_deviation_domain', 'check_domain', 'check_input_domain', 'leader_extremes']
