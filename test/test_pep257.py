"""The docstrings of every Python file in the package, as ament_python packages check them (ament_pep257)."""
from pathlib import Path

from ament_pep257.main import main
import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ('vlp_ros', 'test', 'launch', 'setup.py')


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257() -> None:
    rc = main(argv=[str(ROOT / p) for p in CHECKED])
    assert rc == 0, 'Found code style errors / warnings'
