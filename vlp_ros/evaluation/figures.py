"""
Figures in the style of the seed paper's Figs. 4-6, and the error against the off-axis angle.

Figs. 4-6: per-point error, error CDF, X-Y view; then the 3D error against the lamp's angle
off the optical axis.
"""
from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use('Agg')  # files only; no display on robots or CI
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vlp_ros.evaluation.metrics import FrameOutcome, position_errors  # noqa: E402


def _groups(outcomes: list[FrameOutcome]) -> dict[str, list[FrameOutcome]]:
    groups: dict[str, list[FrameOutcome]] = {}
    for o in outcomes:
        groups.setdefault(o.group, []).append(o)
    return groups


def per_point_error(outcomes: list[FrameOutcome], path: Path, title: str) -> Path:
    """Mean 3D error at each grid point, as a coloured map per group (cf. the paper's Fig. 4)."""
    groups = _groups(outcomes)
    fig, axes = plt.subplots(1, len(groups), figsize=(5.2 * len(groups), 4.4), squeeze=False)
    for ax, (label, items) in zip(axes[0], sorted(groups.items())):
        points: dict[tuple[float, float], list[float]] = {}
        for o in items:
            if o.estimate is not None and o.point is not None:
                points.setdefault(o.point, []).append(o.estimate.position_error(o.truth))
        if points:
            xy = np.array(list(points))
            mean_cm = np.array([100 * np.mean(v) for v in points.values()])
            sc = ax.scatter(xy[:, 0], xy[:, 1], c=mean_cm, s=220, cmap='viridis', marker='s')
            fig.colorbar(sc, ax=ax, label='mean 3D error (cm)')
        ax.set_title(f'{title} {label}'.strip())
        ax.set_xlabel('x (m)')
        ax.set_ylabel('y (m)')
        ax.set_aspect('equal')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def error_cdf(series: dict[str, list[FrameOutcome]], path: Path, title: str) -> Path:
    """Cumulative distribution of the 3D error, one curve per series (cf. the paper's Fig. 5)."""
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for label, items in series.items():
        errors = np.sort(position_errors(items)) * 100
        if errors.size:
            ax.plot(errors, np.arange(1, errors.size + 1) / errors.size, label=label)
    ax.set_xscale('log')
    ax.set_xlabel('3D position error (cm)')
    ax.set_ylabel('fraction of poses')
    ax.set_title(title)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def xy_view(outcomes: list[FrameOutcome], path: Path, title: str) -> Path:
    """Estimated against true camera positions seen from above (cf. the paper's Fig. 6)."""
    fig, ax = plt.subplots(figsize=(5.6, 5.4))
    truth = np.array([o.truth.position for o in outcomes])
    estimates = np.array([o.estimate.position for o in outcomes if o.estimate is not None])
    ax.scatter(truth[:, 0], truth[:, 1], s=60, facecolors='none', edgecolors='k', label='truth')
    if estimates.size:
        ax.scatter(estimates[:, 0], estimates[:, 1], s=8, c='tab:red', label='estimate')
    ax.set_xlabel('x (m)')
    ax.set_ylabel('y (m)')
    ax.set_aspect('equal')
    ax.set_title(title)
    ax.legend(loc='upper right')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def error_vs_off_axis(series: dict[str, tuple[np.ndarray, np.ndarray]], path: Path, title: str,
                      reference_distance_m: float | None = None) -> Path:
    """
    Plot the 3D error against the lamp's angle off the optical axis, one marker set per series.

    ``series``: label -> (angles in deg, errors in m); with ``reference_distance_m``, the
    weak-perspective rule of thumb error = distance x tan(angle) as a dashed line.
    """
    fig, ax = plt.subplots(figsize=(7.2, 4.8))
    largest = 1.0
    for label, (angles, errors) in series.items():
        if len(angles):
            ax.scatter(angles, 100 * np.asarray(errors), s=10, alpha=0.6, label=label)
            largest = max(largest, float(np.max(angles)))
    if reference_distance_m is not None:
        angle = np.linspace(0.5, largest, 100)
        ax.plot(angle, 100 * reference_distance_m * np.tan(np.radians(angle)), 'k--', lw=1,
                label=f'{reference_distance_m:g} m x tan(angle)')
    ax.set_yscale('log')
    ax.set_xlabel("lamp's angle off the optical axis (deg)")
    ax.set_ylabel('3D position error (cm)')
    ax.set_title(title)
    ax.grid(True, which='both', alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
