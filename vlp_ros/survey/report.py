"""
The survey's report for the deployer: a plan view, a table of the lamps and the residuals.

``plan.png``: the lamps from above with their 3-sigma position ellipses (drawn enlarged, by the
factor in the legend, since they are millimetres across in a room of metres), marker directions,
the anchors and the camera's trajectory. ``lamps.md`` and ``lamps.csv``: each lamp's position,
sigma, marker angle, frames seen and residuals. ``residuals.csv``: every sighting's residual.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use('Agg')  # files only; no display on robots or CI
from matplotlib.patches import Ellipse  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from vlp_ros.survey.estimation import per_lamp_residuals, SurveyEstimate  # noqa: E402
from vlp_ros.survey.partial_map import PartialMap  # noqa: E402

# The enlarged ellipses' largest 3-sigma semi-axis is this share of the smallest lamp spacing.
ELLIPSE_SHARE = 0.25
SIGMA_SCALE = 3.0


@dataclass(frozen=True)
class LampRow:
    name: str
    lamp_id: int
    role: str
    position: np.ndarray
    sigma: np.ndarray
    marker_angle: float
    marker_sigma: float
    frames: int
    residual_rms: float
    mean_chi_square: float


def lamp_rows(partial: PartialMap, estimate: SurveyEstimate) -> list[LampRow]:
    """One row per listed lamp: anchors as given, surveyed lamps as estimated, undetermined ones empty."""
    residuals = per_lamp_residuals(estimate)
    rows = []
    for lamp in partial.lamps:
        rms, chi = residuals.get(lamp.id, (np.nan, np.nan))
        frames = estimate.frames_seen[lamp.id]
        surveyed = estimate.lamps.get(lamp.id)
        if lamp.name in partial.anchors:
            anchor = partial.anchors[lamp.name]
            angle = anchor.marker_angle if anchor.marker_angle is not None else (
                surveyed.marker_angle if surveyed else np.nan)
            angle_sigma = 0.0 if anchor.marker_angle is not None else (surveyed.marker_angle_sigma if surveyed
                                                                       else np.nan)
            rows.append(LampRow(lamp.name, lamp.id, 'anchor', anchor.position, np.zeros(3), angle, angle_sigma,
                                frames, rms, chi))
        elif surveyed is not None:
            rows.append(LampRow(lamp.name, lamp.id, 'surveyed', surveyed.position, surveyed.position_sigma,
                                surveyed.marker_angle, surveyed.marker_angle_sigma, frames, rms, chi))
        else:
            rows.append(LampRow(lamp.name, lamp.id, 'undetermined', np.full(3, np.nan), np.full(3, np.nan), np.nan,
                                np.nan, frames, rms, chi))
    return rows


def write_report(partial: PartialMap, estimate: SurveyEstimate, folder: Path | str) -> Path:
    """Write plan.png, lamps.md, lamps.csv and residuals.csv into ``folder``; return it."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rows = lamp_rows(partial, estimate)
    _plan(rows, estimate, folder / 'plan.png')
    (folder / 'lamps.md').write_text(lamps_markdown(rows, estimate))
    _lamps_csv(rows, folder / 'lamps.csv')
    with open(folder / 'residuals.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['frame', 'lamp_id', 'chi_square_6dof', 'position_residual_mm'])
        for r in estimate.residuals:
            writer.writerow([r.frame, r.lamp_id, f'{r.chi_square:.3f}', f'{1e3 * r.position_error:.3f}'])
    return folder


def lamps_markdown(rows: list[LampRow], estimate: SurveyEstimate) -> str:
    """Return the lamp table as markdown, with how the residuals and sigmas are to be read."""
    lines = ['| lamp | ID | role | x (m) | y (m) | z (m) | sigma x, y, z (mm) | marker (deg) | marker sigma (deg) '
             '| frames | residual RMS (mm) | mean chi-square (6 dof) |',
             '| --- | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: |']
    for r in rows:
        sigma = ', '.join(f'{1e3 * s:.2f}' for s in r.sigma)
        lines.append(f'| {r.name} | {r.lamp_id} | {r.role} | {r.position[0]:.4f} | {r.position[1]:.4f} | '
                     f'{r.position[2]:.4f} | {sigma} | {np.degrees(r.marker_angle):.3f} | '
                     f'{np.degrees(r.marker_sigma):.3f} | {r.frames} | {1e3 * r.residual_rms:.2f} | '
                     f'{r.mean_chi_square:.2f} |')
    lines += ['', f'Residuals: each sighting (one lamp in one frame) against the estimate, the camera position in '
                  f"the lamp's frame (mm) and the chi-square of the whole 6-DoF pose under its stated noise. "
                  f'Sigmas include a variance factor of {estimate.variance_factor:.2f} from the residuals '
                  '(never below 1).']
    if estimate.undetermined:
        why = sorted(estimate.undetermined.items())
        lines += ['', 'Undetermined: ' + '; '.join(f'ID {i}: {reason}' for i, reason in why)]
    return '\n'.join(lines) + '\n'


def _lamps_csv(rows: list[LampRow], path: Path) -> None:
    with open(path, 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['name', 'id', 'role', 'x_m', 'y_m', 'z_m', 'sigma_x_m', 'sigma_y_m', 'sigma_z_m',
                         'marker_angle_rad', 'marker_sigma_rad', 'frames', 'residual_rms_m', 'mean_chi_square'])
        for r in rows:
            writer.writerow([r.name, r.lamp_id, r.role, *(f'{v:.5f}' for v in r.position),
                             *(f'{v:.6f}' for v in r.sigma), f'{r.marker_angle:.6f}', f'{r.marker_sigma:.6f}',
                             r.frames, f'{r.residual_rms:.6f}', f'{r.mean_chi_square:.3f}'])


def _plan(rows: list[LampRow], estimate: SurveyEstimate, path: Path) -> None:
    placed = [r for r in rows if np.all(np.isfinite(r.position))]
    figure, axes = plt.subplots(figsize=(8, 7))
    if estimate.cameras:
        trajectory = np.array([estimate.cameras[f].position for f in sorted(estimate.cameras)])
        axes.plot(trajectory[:, 0], trajectory[:, 1], '-', color='0.6', lw=1, label='camera trajectory')
    scale = _ellipse_scale(placed)
    for r in placed:
        anchor = r.role == 'anchor'
        axes.plot(*r.position[:2], '^' if anchor else 'o', color='tab:red' if anchor else 'tab:blue', ms=8)
        if np.isfinite(r.marker_angle):
            axes.annotate('', xy=r.position[:2] + 0.15 * np.array([np.cos(r.marker_angle), np.sin(r.marker_angle)]),
                          xytext=r.position[:2], arrowprops={'arrowstyle': '->', 'color': 'tab:red'})
        axes.annotate(f'{r.name} ({r.lamp_id})', r.position[:2], textcoords='offset points', xytext=(6, 6),
                      fontsize=8)
        surveyed = estimate.lamps.get(r.lamp_id)
        if surveyed is not None and not anchor:
            _draw_ellipse(axes, r.position[:2], surveyed.position_covariance[:2, :2], scale)
    axes.plot([], [], '^', color='tab:red', label='anchor')
    axes.plot([], [], 'o', color='tab:blue', label=f'surveyed ({SIGMA_SCALE:.0f}-sigma ellipse x {scale:.0f})')
    axes.set_aspect('equal')
    axes.set_xlabel('map x (m)')
    axes.set_ylabel('map y (m)')
    axes.set_title('Surveyed lamps, plan view')
    axes.legend(loc='upper center', bbox_to_anchor=(0.5, -0.1), ncol=3, fontsize=8)
    axes.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


def _ellipse_scale(rows: list[LampRow]) -> float:
    """How much the 3-sigma ellipses are enlarged to be seen: a round factor, at least 1."""
    if len(rows) < 2:
        return 1.0
    points = np.array([r.position[:2] for r in rows])
    gaps = np.linalg.norm(points[:, None] - points[None], axis=2)
    spacing = np.min(gaps[gaps > 0]) if np.any(gaps > 0) else 1.0
    largest = max((SIGMA_SCALE * np.max(r.sigma[:2]) for r in rows if r.role == 'surveyed'), default=0.0)
    if not largest > 0.0:
        return 1.0
    wanted = ELLIPSE_SHARE * spacing / largest
    return float(max(1.0, 10.0 ** np.floor(np.log10(wanted))))


def _draw_ellipse(axes, centre: np.ndarray, covariance: np.ndarray, scale: float) -> None:
    values, vectors = np.linalg.eigh(covariance)
    width, height = 2.0 * SIGMA_SCALE * scale * np.sqrt(np.maximum(values, 0.0))
    angle = np.degrees(np.arctan2(vectors[1, 0], vectors[0, 0]))
    axes.add_patch(Ellipse(centre, width, height, angle=angle, fill=False, color='tab:blue', lw=1.2))
