"""Matplotlib figures of the paper (Figs. 4-6) and NEES plots, for studies and recorded bags."""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle, Ellipse  # noqa: E402

#: One colour per strategy, stable across figures.
COLOURS = {'mtf': 'tab:gray', 'crm': 'tab:orange', 'mme': 'tab:purple', 'gbs': 'tab:green',
           'ram': 'tab:blue', 'rq': 'tab:red'}


def _colour(name: str) -> str:
    return COLOURS.get(name, 'black')


def trace_figure(time: np.ndarray, traces: dict[str, np.ndarray], path: Path, title: str,
                 zoom: tuple[str, ...] = ('ram', 'rq', 'gbs')) -> Path:
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
        inset = ax.inset_axes([0.55, 0.45, 0.42, 0.35])
        for name in shown:
            inset.plot(time[start:], traces[name][start:], color=_colour(name),
                       linestyle='--' if name == 'rq' else '-', linewidth=1.0,
                       label=name.upper())
        inset.set_title('zoom: ' + ', '.join(n.upper() for n in shown), fontsize=8)
        inset.tick_params(labelsize=7)
        inset.grid(True, alpha=0.3)
    return _save(fig, path)


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
    return _save(fig, path)


def covariance_ellipse(centre: np.ndarray, covariance: np.ndarray, sigmas: float = 3.0,
                       **style: object) -> Ellipse:
    """The ``sigmas``-sigma ellipse of a 2x2 position covariance (m^2) around centre (m)."""
    values, vectors = np.linalg.eigh(covariance)
    angle = np.degrees(np.arctan2(vectors[1, 1], vectors[0, 1]))
    width, height = 2 * sigmas * np.sqrt(np.maximum(values[::-1], 0.0))
    return Ellipse(centre, width, height, angle=angle, fill=False, **style)


def trajectory_figure(panels: dict[str, dict[str, np.ndarray]], p_o: np.ndarray, r: float,
                      path: Path, title: str, every: int = 3) -> Path:
    """Paper Fig. 4: estimated follower and leader paths in a fixed frame, 3-sigma ellipses.

    Args:
        panels: name -> {'leader': (n, 2) leader positions in the fixed frame (m),
            'estimate': (n, 3) follower estimate in {L}, 'covariance': (n, 3, 3),
            optional 'truth': (n, 3) true pose in {L}, optional 'waypoints': (n, 2) in {L}}.
            The leader's heading is taken as 0 (straight along the fixed x-axis).
        p_o, r: formation slot (m, leader frame) and allowed deviation (m).
        every: draw an ellipse and a disc every ``every`` steps.
    """
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.6 * len(panels)), squeeze=False)
    for ax, (name, panel) in zip(axes[:, 0], panels.items()):
        leader = panel['leader']
        follower = leader + panel['estimate'][:, :2]
        ax.plot(leader[:, 0], leader[:, 1], 'k.-', markersize=3, linewidth=0.8, label='leader')
        ax.plot(follower[:, 0], follower[:, 1], '.-', color=_colour(name), markersize=3,
                linewidth=0.9, label=f'follower estimate ({name.upper()})')
        if panel.get('truth') is not None:
            truth = leader + panel['truth'][:, :2]
            ax.plot(truth[:, 0], truth[:, 1], ':', color='black', linewidth=0.8,
                    label='follower truth')
        if panel.get('waypoints') is not None:
            way = leader + panel['waypoints']
            ax.plot(way[:, 0], way[:, 1], 'x', color=_colour(name), markersize=3,
                    label='chosen waypoints')
        for k in range(0, len(leader), every):
            ax.add_patch(Circle(leader[k] + p_o, r, fill=False, color='0.6', linewidth=0.5))
            ax.add_patch(covariance_ellipse(follower[k], panel['covariance'][k][:2, :2],
                                            color=_colour(name), linewidth=0.6))
        ax.set_aspect('equal')
        ax.set_ylabel('y [m]')
        ax.set_title(f'{title}: {name.upper()}', fontsize=9)
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper right', fontsize=7, ncol=2)
    axes[-1, 0].set_xlabel('x [m] (fixed frame; leader drives along +x)')
    return _save(fig, path)


def _save(fig: plt.Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
