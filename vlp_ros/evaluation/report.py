"""The evaluation's outputs: a terminal table, and a folder with a Markdown summary and figures."""
from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from vlp_ros.evaluation import figures
from vlp_ros.evaluation.metrics import FrameOutcome, format_table, summarize, summary_row

# The seed paper's published mean 3D errors (Zhang et al. 2017), by lamp height above the camera.
PAPER_PUBLISHED_MEAN_M = {'1.5 m': 0.1279, '2 m': 0.1752}


@dataclass
class Evaluation:
    """Outcomes per solver, each a list of frames tagged with its group (e.g. lamp height)."""

    title: str
    series: dict[str, list[FrameOutcome]]
    notes: list[str] = field(default_factory=list)

    def rows(self) -> list[list[str]]:
        rows = []
        for solver, outcomes in self.series.items():
            groups = sorted({o.group for o in outcomes})
            for group in groups:
                label = f'{solver} {group}'.strip()
                rows.append(summary_row(label, summarize([o for o in outcomes if o.group == group])))
        return rows

    def published_rows(self) -> list[str]:
        groups = {o.group for outcomes in self.series.values() for o in outcomes}
        return [f'paper (published) {g}: mean 3D error {100 * m:.2f} cm'
                for g, m in PAPER_PUBLISHED_MEAN_M.items() if g in groups]

    def table(self, markdown: bool = False) -> str:
        return format_table(self.rows(), markdown=markdown)


def write_report(evaluation: Evaluation, folder: Path) -> Path:
    """summary.md and PNG figures in ``folder``; returns the summary's path."""
    folder.mkdir(parents=True, exist_ok=True)
    made = []
    for solver, outcomes in evaluation.series.items():
        slug = re.sub(r'[^a-z0-9]+', '_', solver.lower()).strip('_')
        made.append(figures.per_point_error(outcomes, folder / f'per_point_error_{slug}.png', solver))
        made.append(figures.xy_view(outcomes, folder / f'xy_view_{slug}.png', f'{solver}: estimates vs truth'))
    made.append(figures.error_cdf(_cdf_series(evaluation.series), folder / 'error_cdf.png', '3D error CDF'))
    lines = [f'# {evaluation.title}', '', evaluation.table(markdown=True), '']
    lines += [f'- {row}' for row in evaluation.published_rows()]
    lines += [f'- {note}' for note in evaluation.notes]
    lines += ['', '## Figures', ''] + [f'![{p.stem}]({p.name})' for p in made]
    summary = folder / 'summary.md'
    summary.write_text('\n'.join(lines) + '\n')
    return summary


def _cdf_series(series: dict[str, list[FrameOutcome]]) -> dict[str, list[FrameOutcome]]:
    curves = {}
    for solver, outcomes in series.items():
        for group in sorted({o.group for o in outcomes}):
            curves[f'{solver} {group}'.strip()] = [o for o in outcomes if o.group == group]
    return curves
