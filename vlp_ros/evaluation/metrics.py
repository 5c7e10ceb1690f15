"""Error statistics of estimated poses against ground truth."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vlp_ros.core.pose import Pose
from vlp_ros.solvers.covariance import nees

WRONG_FIX_M = 0.5  # a published pose further than this from the truth is a wrong fix


@dataclass
class FrameOutcome:
    """
    One frame: the true pose, the estimate (None = no pose published) and where it was taken.

    ``candidates``: the solver's distinct poses, when the evaluation recorded them.
    """

    truth: Pose
    estimate: Pose | None
    group: str = ''
    point: tuple[float, float] | None = None
    reason: str = ''
    candidates: list[Pose] = field(default_factory=list)


@dataclass
class ErrorSummary:
    """
    Per-photo statistics, and (``point_*``) the paper's.

    At each grid point the error of the average of that point's estimates, over the
    ``points`` points with any.
    """

    frames: int
    poses: int
    mean_m: float
    std_m: float
    min_m: float
    p95_m: float
    max_m: float
    orientation_mean_deg: float
    orientation_p95_deg: float
    wrong_fixes: int
    mean_nees: float
    points: int
    point_mean_m: float
    point_std_m: float
    point_min_m: float
    point_max_m: float

    @property
    def no_pose(self) -> int:
        return self.frames - self.poses


def position_errors(outcomes: list[FrameOutcome]) -> np.ndarray:
    return np.array([o.estimate.position_error(o.truth) for o in outcomes if o.estimate is not None])


def point_average_errors(outcomes: list[FrameOutcome]) -> np.ndarray:
    """
    Return the paper's metric.

    Per grid point, the distance from the true position to the mean of the estimated
    positions taken there (points without an estimate are left out).
    """
    by_point: dict[tuple[float, float] | None, list[FrameOutcome]] = {}
    for o in outcomes:
        if o.estimate is not None:
            by_point.setdefault(o.point, []).append(o)
    return np.array([np.linalg.norm(np.mean([o.estimate.position - o.truth.position for o in items], axis=0))
                     for items in by_point.values()])


def off_axis_deg(truth: Pose, point: np.ndarray) -> float:
    """Angle (deg) between the camera's optical axis and the direction to ``point`` (map frame)."""
    in_camera = truth.map_to_camera(point)[0]
    return float(np.degrees(np.arccos(np.clip(in_camera[2] / np.linalg.norm(in_camera), -1.0, 1.0))))


def nees_or_nan(estimate: Pose, truth: Pose) -> float:
    """NEES of a pose, NaN for a pose without a covariance (the paper's solver gives none)."""
    return float('nan') if estimate.covariance is None else nees(estimate, truth)


def summarize(outcomes: list[FrameOutcome]) -> ErrorSummary:
    estimated = [o for o in outcomes if o.estimate is not None]
    errors = position_errors(outcomes)
    point_errors = point_average_errors(outcomes)
    angles = np.degrees([o.estimate.rotation_error(o.truth) for o in estimated])
    nees_values = np.array([nees_or_nan(o.estimate, o.truth) for o in estimated])

    def stat(values: np.ndarray, fn) -> float:
        return float(fn(values)) if values.size else float('nan')

    finite_nees = nees_values[np.isfinite(nees_values)] if nees_values.size else nees_values
    return ErrorSummary(
        frames=len(outcomes), poses=len(estimated),
        mean_m=stat(errors, np.mean), std_m=stat(errors, np.std), min_m=stat(errors, np.min),
        p95_m=stat(errors, lambda v: np.percentile(v, 95)), max_m=stat(errors, np.max),
        orientation_mean_deg=stat(angles, np.mean),
        orientation_p95_deg=stat(angles, lambda v: np.percentile(v, 95)),
        wrong_fixes=int(np.sum(errors > WRONG_FIX_M)),
        mean_nees=stat(finite_nees, np.mean),
        points=int(point_errors.size), point_mean_m=stat(point_errors, np.mean),
        point_std_m=stat(point_errors, np.std), point_min_m=stat(point_errors, np.min),
        point_max_m=stat(point_errors, np.max))


TABLE_HEADER = ('', 'frames', 'poses', 'mean cm', 'std cm', 'p95 cm', 'max cm',
                'orient. mean deg', 'orient. p95 deg', 'wrong fixes', 'no pose', 'mean NEES')
# With the per-photo minimum and the paper's metric (the error of each point's average estimate).
POINT_TABLE_HEADER = TABLE_HEADER + ('min cm', 'points', 'point avg: mean cm', 'std cm', 'min-max cm')


def _cm(value: float) -> str:
    return '-' if np.isnan(value) else f'{100 * value:.2f}'


def summary_row(label: str, s: ErrorSummary) -> list[str]:
    def num(value: float, digits: int = 3) -> str:
        return '-' if np.isnan(value) else f'{value:.{digits}f}'

    return [label, str(s.frames), str(s.poses), _cm(s.mean_m), _cm(s.std_m), _cm(s.p95_m), _cm(s.max_m),
            num(s.orientation_mean_deg), num(s.orientation_p95_deg), str(s.wrong_fixes), str(s.no_pose),
            num(s.mean_nees, 2)]


def point_summary_row(label: str, s: ErrorSummary) -> list[str]:
    """``summary_row`` with the columns of ``POINT_TABLE_HEADER``."""
    span = '-' if np.isnan(s.point_min_m) else f'{_cm(s.point_min_m)}-{_cm(s.point_max_m)}'
    return summary_row(label, s) + [_cm(s.min_m), str(s.points), _cm(s.point_mean_m), _cm(s.point_std_m), span]


def format_table(rows: list[list[str]], header: tuple[str, ...] = TABLE_HEADER, markdown: bool = False) -> str:
    """Rows of strings as an aligned text table, or as a Markdown table."""
    table = [list(header), *rows]
    if markdown:
        lines = ['| ' + ' | '.join(r) + ' |' for r in table]
        lines.insert(1, '|' + '---|' * len(header))
        return '\n'.join(lines)
    widths = [max(len(r[i]) for r in table) for i in range(len(header))]
    lines = ['  '.join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in table]
    lines.insert(1, '-' * len(lines[0]))
    return '\n'.join(lines)
