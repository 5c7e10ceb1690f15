"""The locator's start objects stay out of Python's garbage collections, and later cycles are still freed."""
from __future__ import annotations

import subprocess
import sys

from conftest import ROOT

# In a process of its own: freezing the objects of pytest's process would keep them for every later test.
AFTER_THE_KERNELS = """
import gc
import weakref
from vlp_ros.pipeline.warm_up import warm_up
from vlp_ros.nodes.locator import keep_start_objects_out_of_collections

warm_up()
tracked = len(gc.get_objects())
keep_start_objects_out_of_collections()
print(f'frozen={gc.get_freeze_count()}')
print(f'tracked={tracked}')
print(f'walked={len(gc.get_objects())}')


class Cycle:
    pass


made = Cycle()
made.itself = made
gone = weakref.ref(made)
del made
gc.collect()
print(f'later_cycle_freed={gone() is None}')
"""


def test_the_kernels_objects_are_frozen_and_later_cycles_still_collected() -> None:
    result = subprocess.run([sys.executable, '-c', AFTER_THE_KERNELS], cwd=ROOT, capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr
    printed = dict(line.split('=') for line in result.stdout.strip().splitlines() if '=' in line)
    frozen, tracked, walked = (int(printed[key]) for key in ('frozen', 'tracked', 'walked'))
    # numba's and LLVM's objects number in the hundred thousands: each full collection walked them all.
    assert frozen >= 0.9 * tracked > 50_000
    assert walked < 0.01 * frozen
    assert printed['later_cycle_freed'] == 'True'
