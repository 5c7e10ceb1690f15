"""The evaluation's outputs: a terminal table, and a folder with a Markdown summary and figures."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
import re

from vlp_ros.evaluation import figures
from vlp_ros.evaluation.metrics import format_table, FrameOutcome, point_summary_row, POINT_TABLE_HEADER, summarize

# The seed paper's published mean 3D errors (Zhang et al. 2017), by lamp height above the camera,
# and the spread it gives with each.
PAPER_PUBLISHED_MEAN_M = {'1.5 m': 0.1279, '2 m': 0.1752}
PAPER_PUBLISHED_SPREAD = {'1.5 m': '5.05-27.25 cm', '2 m': '8.94-25.12 cm, sd 3.7'}


@dataclass
class Evaluation:
    """
    Outcomes per solver, each a list of frames tagged with its group (e.g. lamp height).

    ``published``: the paper's published figures go in a last column, beside the rows of
    their lamp height (for experiments that reproduce the paper's). ``name`` prefixes the
    figure files when several evaluations share a report folder.
    """

    title: str
    series: dict[str, list[FrameOutcome]]
    notes: list[str] = field(default_factory=list)
    published: bool = False
    name: str = ''

    def groups(self) -> list[str]:
        return sorted({o.group for outcomes in self.series.values() for o in outcomes})

    def rows(self) -> list[list[str]]:
        rows = []
        for solver, outcomes in self.series.items():
            for group in sorted({o.group for o in outcomes}):
                label = f'{solver} {group}'.strip()
                row = point_summary_row(label, summarize([o for o in outcomes if o.group == group]))
                if self.published:
                    row.append(published_figures(group))
                rows.append(row)
        return rows

    def published_rows(self) -> list[str]:
        return [f'paper (published) {g}: mean 3D error {100 * m:.2f} cm ({PAPER_PUBLISHED_SPREAD[g]})'
                for g, m in PAPER_PUBLISHED_MEAN_M.items() if g in self.groups()]

    def table(self, markdown: bool = False) -> str:
        header = POINT_TABLE_HEADER + (('published cm',) if self.published else ())
        return format_table(self.rows(), header, markdown=markdown)


def published_figures(group: str) -> str:
    """Return the paper's mean 3D error and spread at this lamp height, '-' for heights it did not publish."""
    if group not in PAPER_PUBLISHED_MEAN_M:
        return '-'
    return f'{100 * PAPER_PUBLISHED_MEAN_M[group]:.2f} ({PAPER_PUBLISHED_SPREAD[group]})'


def _slug(text: str) -> str:
    return re.sub(r'[^a-z0-9]+', '_', text.lower()).strip('_')


def _evaluation_figures(evaluation: Evaluation, folder: Path) -> list[Path]:
    prefix = f'{_slug(evaluation.name)}_' if evaluation.name else ''
    made = []
    for solver, outcomes in evaluation.series.items():
        slug = prefix + _slug(solver)
        made.append(figures.per_point_error(outcomes, folder / f'per_point_error_{slug}.png', solver))
        made.append(figures.xy_view(outcomes, folder / f'xy_view_{slug}.png', f'{solver}: estimates vs truth'))
    made.append(figures.error_cdf(_cdf_series(evaluation.series), folder / f'{prefix}error_cdf.png',
                                  f'{evaluation.name} 3D error CDF'.strip()))
    return made


def write_report(evaluations: Evaluation | Sequence[Evaluation], folder: Path,
                 extra_figures: Sequence[Path] = ()) -> Path:
    """
    Write summary.md and PNG figures into ``folder``; return the summary's path.

    One section (with its figures) per evaluation, then ``extra_figures``, already drawn there.
    """
    folder.mkdir(parents=True, exist_ok=True)
    lines = []
    for evaluation in [evaluations] if isinstance(evaluations, Evaluation) else evaluations:
        made = _evaluation_figures(evaluation, folder)
        lines += [f'# {evaluation.title}', '', evaluation.table(markdown=True), '']
        lines += [f'- {row}' for row in evaluation.published_rows()]
        lines += [f'- {note}' for note in evaluation.notes]
        lines += ['', '## Figures', ''] + [f'![{p.stem}]({p.name})' for p in made] + ['']
    lines += [f'![{p.stem}]({p.name})' for p in extra_figures]
    summary = folder / 'summary.md'
    summary.write_text('\n'.join(lines).rstrip('\n') + '\n')
    return summary


def _cdf_series(series: dict[str, list[FrameOutcome]]) -> dict[str, list[FrameOutcome]]:
    curves = {}
    for solver, outcomes in series.items():
        for group in sorted({o.group for o in outcomes}):
            curves[f'{solver} {group}'.strip()] = [o for o in outcomes if o.group == group]
    return curves
