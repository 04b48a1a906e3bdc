"""Matplotlib figures of the paper (Figs. 4-6) and NEES plots, for studies and recorded bags."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Ellipse  # noqa: E402

from formopt_ros.core.model import covariance_ellipse  # noqa: E402

#: One colour per strategy, stable across figures.
COLOURS = {'mtf': 'tab:gray', 'crm': 'tab:orange', 'mme': 'tab:purple', 'gbs': 'tab:green',
           'ram': 'tab:blue', 'rq': 'tab:red', 'periodic': 'tab:cyan'}


#: Colours of other curves (followers by id), stable per name.
_PALETTE = ('tab:cyan', 'tab:brown', 'tab:pink', 'tab:olive', 'darkblue', 'darkred')


def _colour(name: str) -> str:
    return COLOURS.get(name, _PALETTE[sum(map(ord, name)) % len(_PALETTE)])


def sensor_figure(time: np.ndarray, traces: dict[str, np.ndarray], path: Path,
                  title: str) -> Path:
    """Mean tr(W P W) over time of one follower with different sensors (label -> (steps,)
    m^2), log scale: range-only, bearing-only and range+bearing side by side."""
    fig, ax = plt.subplots(figsize=(8, 5))
    styles = {'range-only': 'tab:blue', 'bearing-only': 'tab:orange', 'range+bearing': 'k'}
    for label, values in traces.items():
        sensor, _, strategy = label.rpartition(' ')
        ax.plot(time, values, label=label, color=styles.get(sensor, None),
                linestyle='--' if strategy == 'periodic' else '-', linewidth=1.2)
    ax.set_yscale('log')
    ax.set_xlabel('time [s]')
    ax.set_ylabel('mean tr(W P W) [m$^2$]')
    ax.set_title(title, fontsize=10)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(loc='upper right')
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def trace_figure(time: np.ndarray, traces: dict[str, np.ndarray], path: Path, title: str,
                 zoom: tuple[str, ...] = ('ram', 'rq', 'gbs', 'periodic')) -> Path:
    """Mean tr(W P W) over time per strategy, log scale, with a zoomed inset of ``zoom``.

    Args:
        time: (steps,) time of each measurement, s.
        traces: strategy -> (steps,) weighted trace, m^2.
        path: PNG file to write.
    """
    fig, ax = plt.subplots(figsize=(8, 5))
    for name, values in traces.items():
        ax.plot(time, values, label=name.upper(), color=_colour(name),
                linestyle='--' if name == 'rq' else '-', linewidth=1.2)
    ax.set_yscale('log')
    ax.set_xlabel('time [s]')
    ax.set_ylabel('mean tr(W P W) [m$^2$]')
    ax.set_title(title)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(loc='upper left', ncol=3)
    shown = [n for n in zoom if n in traces]
    if len(shown) > 1 and len(time) > 10:
        start = len(time) * 2 // 3
        inset = ax.inset_axes((0.55, 0.45, 0.42, 0.35))
        for name in shown:
            inset.plot(time[start:], traces[name][start:], color=_colour(name),
                       linestyle='--' if name == 'rq' else '-', linewidth=1.0,
                       label=name.upper())
        inset.set_title('zoom: ' + ', '.join(n.upper() for n in shown), fontsize=8)
        inset.tick_params(labelsize=7)
        inset.grid(True, alpha=0.3)
    return save_figure(fig, path)


def nees_figure(time: np.ndarray, nees: dict[str, np.ndarray], band: tuple[float, float],
                path: Path, title: str) -> Path:
    """Trial-averaged NEES over time per strategy with the chi-square band (dimensionless)."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, values in nees.items():
        ax.plot(time, values, label=name.upper(), color=_colour(name), linewidth=0.8)
    ax.axhspan(band[0], band[1], color='tab:green', alpha=0.12, label='95% band')
    ax.axhline(3.0, color='black', linewidth=0.6, linestyle=':')
    ax.set_yscale('log')
    ax.set_xlabel('time [s]')
    ax.set_ylabel('NEES of [x, y, phi]')
    ax.set_title(title)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(loc='upper right', ncol=3, fontsize=8)
    return save_figure(fig, path)


def ellipse_patch(centre: np.ndarray, covariance: np.ndarray, sigmas: float = 3.0,
                  **style: Any) -> Ellipse:
    """The ``sigmas``-sigma ellipse of a 2x2 position covariance (m^2) around centre (m)."""
    major, minor, angle = covariance_ellipse(covariance, sigmas)
    return Ellipse((float(centre[0]), float(centre[1])), 2 * major, 2 * minor,
                   angle=float(np.degrees(angle)), fill=False, **style)


def to_fixed_frame(leader: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Points given in the leader frame (n, 2) -> the fixed frame, with leader poses (n, 3)."""
    c, s = np.cos(leader[:, 2]), np.sin(leader[:, 2])
    x, y = points[:, 0], points[:, 1]
    return leader[:, :2] + np.stack([c * x - s * y, s * x + c * y], axis=1)


def _rotated(covariance: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -s], [s, c]])
    return R @ covariance @ R.T


def trajectory_figure(panels: dict[str, dict[str, Any]], path: Path, title: str,
                      every: int = 3) -> Path:
    """Paper Fig. 4: leader and estimated follower paths in the fixed frame, 3-sigma ellipses.

    Args:
        panels: panel title -> {'leader': (n, 3) leader poses (x m, y m, yaw rad) in the fixed
            frame, 'followers': list of {'label': str, 'strategy': str, 'estimate': (n, 3) in
            the leader frame, 'covariance': (n, 3, 3), 'p_o': (2,) m, 'r': m, optional
            'truth': (n, 3) and 'waypoints': (n, 2) in the leader frame}}.
        path: PNG file to write.
        every: draw an ellipse and a disc every ``every`` steps.
    """
    fig, axes = plt.subplots(len(panels), 1, figsize=(10, 3.6 * len(panels)), squeeze=False)
    for ax, (name, panel) in zip(axes[:, 0], panels.items()):
        leader = np.asarray(panel['leader'], dtype=float)
        ax.plot(leader[:, 0], leader[:, 1], 'k.-', markersize=3, linewidth=0.8, label='leader')
        for follower in panel['followers']:
            colour = _colour(follower['strategy'])
            estimate = to_fixed_frame(leader, follower['estimate'][:, :2])
            ax.plot(estimate[:, 0], estimate[:, 1], '.-', color=colour, markersize=3,
                    linewidth=0.9, label=f"{follower['label']} estimate")
            if follower.get('truth') is not None:
                truth = to_fixed_frame(leader, follower['truth'][:, :2])
                ax.plot(truth[:, 0], truth[:, 1], ':', color='black', linewidth=0.8,
                        label=f"{follower['label']} truth")
            if follower.get('waypoints') is not None:
                way = to_fixed_frame(leader, follower['waypoints'])
                ax.plot(way[:, 0], way[:, 1], 'x', color=colour, markersize=3,
                        label=f"{follower['label']} waypoints")
            slot = to_fixed_frame(leader, np.tile(follower['p_o'], (len(leader), 1)))
            for k in range(0, len(leader), every):
                ax.add_patch(Circle(slot[k], follower['r'], fill=False, color='0.6',
                                    linewidth=0.5))
                ax.add_patch(ellipse_patch(
                    estimate[k], _rotated(follower['covariance'][k][:2, :2], leader[k, 2]),
                    color=colour, linewidth=0.6))
        ax.set_aspect('equal')
        ax.set_ylabel('y [m]')
        ax.set_title(f'{title}: {name}', fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0)
    axes[-1, 0].set_xlabel('x [m] (fixed frame)')
    return save_figure(fig, path)


def save_figure(fig: plt.Figure, path: Path) -> Path:
    """Lay out ``fig``, write it to the PNG ``path`` (folders created), close it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches='tight')      # no margins around equal axes
    plt.close(fig)
    return path
