"""A one-line progress bar on stderr for the command-line tools."""
from __future__ import annotations

import sys


def progress_bar(done: int, total: int, label: str = 'frames', width: int = 40) -> None:
    filled = width * done // max(total, 1)
    sys.stderr.write(f'\r[{"#" * filled}{"." * (width - filled)}] {done}/{total} {label}')
    if done >= total:
        sys.stderr.write('\n')
    sys.stderr.flush()
