"""The code style of every Python file in the package, as ament_python packages check it (ament_flake8)."""
import configparser
from pathlib import Path

from ament_flake8.main import main_with_errors
import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ('vlp_ros', 'test', 'launch', 'setup.py')


def line_length() -> int:
    """Return the line length setup.cfg sets for flake8."""
    config = configparser.ConfigParser()
    config.read(ROOT / 'setup.cfg')
    return config.getint('flake8', 'max-line-length')


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8() -> None:
    rc, errors = main_with_errors(argv=['--linelength', str(line_length()), *(str(ROOT / p) for p in CHECKED)])
    assert rc == 0, f'Found {len(errors)} code style errors / warnings:\n' + '\n'.join(errors)
