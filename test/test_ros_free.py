"""Everything below vlp_ros/ but the nodes imports without ROS: the core and the tools run on plain Python."""
from pathlib import Path
import subprocess
import sys

ROOT = Path(__file__).resolve().parents[1]
# Benchmarks of the nodes themselves: the cost of the locator's visualization messages (it builds
# them), the locator's start-up time (it watches for the locator's subscription over DDS) and the
# camera rate it keeps up with (it streams frames into the locator over DDS).
NEEDS_ROS = {'vlp_ros.benchmarks.visualization_cost', 'vlp_ros.benchmarks.startup', 'vlp_ros.benchmarks.camera_rate'}


def ros_free_modules() -> list[str]:
    """Return every module of the package outside vlp_ros/nodes/ that may not need ROS."""
    names = ('.'.join(path.relative_to(ROOT).with_suffix('').parts) for path in (ROOT / 'vlp_ros').rglob('*.py'))
    return sorted(name.removesuffix('.__init__') for name in names
                  if not name.startswith('vlp_ros.nodes') and name.removesuffix('.__init__') not in NEEDS_ROS)


def test_no_module_outside_the_nodes_imports_rclpy() -> None:
    modules = ros_free_modules()
    script = ('import importlib, sys\n'
              f'for name in {modules!r}:\n'
              '    importlib.import_module(name)\n'
              '    assert "rclpy" not in sys.modules, name\n')
    result = subprocess.run([sys.executable, '-c', script], cwd=ROOT, capture_output=True, text=True, timeout=240)
    assert result.returncode == 0, result.stderr
