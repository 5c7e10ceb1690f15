"""Reading back the aligned tables that the benchmarks print (vlp_ros.evaluation.metrics.format_table)."""
from __future__ import annotations

import re

CELL_GAP = re.compile(r'\s{2,}')


def printed_tables(text: str) -> list[dict[str, dict[str, str]]]:
    """
    Return every table in ``text``: each row's cells by column name, the rows by their first cell.

    A table is a header line, a line of dashes and rows up to a blank line; cells are separated by two
    spaces or more.
    """
    lines = text.splitlines()
    tables = []
    for index in range(1, len(lines) - 1):
        if not (lines[index] and set(lines[index]) == {'-'}):
            continue
        header = CELL_GAP.split(lines[index - 1].strip())
        rows = {}
        for line in lines[index + 1:]:
            if not line.strip():
                break
            cells = CELL_GAP.split(line.strip())
            names = header[1:] if len(header) == len(cells) else header  # a blank first heading is stripped
            rows[cells[0]] = dict(zip(names, cells[1:]))
        tables.append(rows)
    return tables
