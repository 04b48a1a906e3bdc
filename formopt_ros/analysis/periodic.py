"""Noise-free runs of PERIODIC, RAM's greedy optimum and the bare cycle, and the docs figure."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from formopt_ros.analysis.figures import COLOURS, plt, save_figure
from formopt_ros.core.estimator import EstimatorPlanner
from formopt_ros.core.formulas import weighted_trace
from formopt_ros.core.model import predict_measurement
from formopt_ros.core.protocol import held_leader_motion
from formopt_ros.core.scenario import Scenario
from formopt_ros.core.strategies import make_strategy
from formopt_ros.core.strategies.periodic_design import (
    PatternDesign, SteadyConditions, cached_design, noise_free_step)


@dataclass(frozen=True)
class NoiseFreeRun:
    """One noise-free run: per step tr(W P W) (steps,), m^2, and the target (steps, 2), m."""

    weighted_trace: np.ndarray
    waypoints: np.ndarray
    modes: tuple[str, ...]


def noise_free_run(scenario: Scenario, strategy: str, steps: int,
                   options: dict[str, object] | None = None) -> NoiseFreeRun:
    """The estimator and ``strategy`` over ``steps`` steps when every measurement equals its
    prediction (zero innovations): the estimate lands on each target, the covariance follows
    the recursion the planners forecast."""
    estimator = EstimatorPlanner(scenario, make_strategy(strategy, **(options or {})))
    leader = held_leader_motion(scenario.leader.velocity(0, scenario.dt))
    costs, waypoints, modes = np.empty(steps), np.empty((steps, 2)), []
    for k in range(steps):
        plan = estimator.plan(k + 1, leader)
        for v, omega, (v_l, omega_l) in zip(plan.command.linear, plan.command.angular, leader):
            estimator.propagate(v, omega, v_l, omega_l)
        estimator.update(k + 1, predict_measurement(scenario.measurement, estimator.x))
        costs[k], waypoints[k] = estimator.weighted_trace(), plan.solution.p
        modes.append(str(plan.solution.details.get('mode', strategy)))
    return NoiseFreeRun(costs, waypoints, tuple(modes))


def cycle_run(design: PatternDesign, scenario: Scenario, steps: int) -> np.ndarray:
    """tr(W P W) (steps,) of the bare cycle played from the scenario's initial estimate."""
    x, P = scenario.initial_estimate()
    out = np.empty(steps)
    for k in range(steps):
        x, P = noise_free_step(x, P, design.points[k % design.period], design.conditions)
        out[k] = weighted_trace(P, design.conditions.slot)
    return out


def design_for(scenario: Scenario, period: int) -> PatternDesign:
    """PERIODIC's cycle for the scenario (cached); ValueError when it has none."""
    conditions = SteadyConditions.from_scenario(scenario)
    design = None if conditions is None else cached_design(conditions, period)[0]
    if design is None:
        raise ValueError(f'no periodic cycle for {scenario}')
    return design


def periodic_figure(scenarios: list[Scenario], path: Path, steps: int = 600,
                    period: int = 4, shown: int = 12) -> Path:
    """The docs figure: per scenario (column) the cycle's points against RAM's noise-free
    steady trajectory and MME's two points in the leader frame (top), and tr(W P W) over the
    steps of RAM, the bare cycle and PERIODIC (bottom, noise-free).

    Args:
        scenarios: one column each (the paper's range and bearing scenarios in the docs).
        path: PNG file to write.
        steps: steps of the noise-free runs.
        period: points of the cycle.
        shown: RAM's last waypoints drawn.
    """
    fig, axes = plt.subplots(2, len(scenarios), figsize=(5.5 * len(scenarios), 9.5),
                             squeeze=False)
    for column, scenario in enumerate(scenarios):
        design = design_for(scenario, period)
        greedy = noise_free_run(scenario, 'ram', steps)
        ours = noise_free_run(scenario, 'periodic', steps, {'period': period})
        mme = noise_free_run(scenario, 'mme', 2)
        bare = cycle_run(design, scenario, steps)
        ax = axes[0, column]
        slot, r = scenario.slot, scenario.r
        angle = np.linspace(0.0, 2.0 * np.pi, 200)
        ax.plot(slot[0] + r * np.cos(angle), slot[1] + r * np.sin(angle), color='0.6', lw=0.8)
        ax.plot(*slot, '+', color='black', ms=10, label='slot $p_o$')
        tail = greedy.waypoints[-shown:]
        ax.plot(tail[:, 0], tail[:, 1], 'o-', color=COLOURS['ram'], ms=5, lw=0.8,
                label=f'RAM (greedy), last {shown} steps')
        loop = np.vstack([design.points, design.points[:1]])
        ax.plot(loop[:, 0], loop[:, 1], '-', color=COLOURS['periodic'], lw=1.5)
        for k, point in enumerate(design.points):
            ax.annotate(str(k + 1), point, textcoords='offset points', xytext=(6, 6),
                        color=COLOURS['periodic'], fontsize=10, weight='bold')
        ax.plot(design.points[:, 0], design.points[:, 1], 's', color=COLOURS['periodic'], ms=7,
                label=f'PERIODIC cycle ({period} points, in order)')
        ax.plot(mme.waypoints[:, 0], mme.waypoints[:, 1], 'x', color=COLOURS['mme'], ms=9,
                mew=2, label='MME')
        ax.arrow(slot[0] - 1.3 * r, slot[1] - 1.25 * r, 0.5 * r, 0.0, width=0.01 * r,
                 color='black')
        ax.text(slot[0] - 1.3 * r, slot[1] - 1.4 * r, 'leader travel (+x)', fontsize=8)
        ax.set_xlim(slot[0] - 1.45 * r, slot[0] + 1.45 * r)
        ax.set_ylim(slot[1] - 1.5 * r, slot[1] + 1.3 * r)
        ax.set_aspect('equal')
        ax.set_xlabel('x [m] (leader frame)')
        ax.set_ylabel('y [m]')
        ax.set_title(f'{scenario.measurement}-only: where the follower measures', fontsize=10)
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper center', bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8)
        ax = axes[1, column]
        numbers = np.arange(1, steps + 1)
        ax.plot(numbers, greedy.weighted_trace, color=COLOURS['ram'], label='RAM (greedy)')
        ax.plot(numbers, bare, color='tab:orange', lw=0.9, label='cycle from step 1')
        ax.plot(numbers, ours.weighted_trace, color=COLOURS['periodic'], lw=1.5,
                label='PERIODIC')
        joined = ours.modes.index('pattern') + 1 if 'pattern' in ours.modes else None
        if joined:
            ax.axvline(joined, color=COLOURS['periodic'], ls=':', lw=0.8)
            ax.text(joined, ax.get_ylim()[1], f' joins at step {joined}', va='top', fontsize=8)
        ax.axhline(design.steady_cost, color=COLOURS['periodic'], ls='--', lw=0.8,
                   label='cycle steady value')
        ax.set_yscale('log')
        ax.set_xlabel('step')
        ax.set_ylabel('tr(W P W) [m$^2$], noise-free')
        ax.grid(True, which='both', alpha=0.3)
        ax.legend(loc='upper right', fontsize=8)
    return save_figure(fig, path)
