"""The locator's allocator settings keep frame-sized blocks resident from one frame to the next."""
from __future__ import annotations

import subprocess
import sys

from conftest import ROOT

# Three 4K bgr8 frames' worth of blocks (a frame's sample, bytes and pixels) taken and freed each round, as the
# locator does per frame; page faults counted over the rounds after the first.
FAULTS_PER_ROUND = """
import resource, sys
import numpy as np
from vlp_ros.nodes import locator
if sys.argv[1] == 'tuned':
    locator.bound_malloc_arenas()
    locator.keep_frames_in_the_heap()
FRAME = 3840 * 2160 * 3
def one_round():
    blocks = [np.empty(FRAME, np.uint8) for _ in range(3)]
    for block in blocks:
        block.fill(1)
one_round()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    one_round()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def faults_per_round(allocator: str) -> float:
    result = subprocess.run([sys.executable, '-c', FAULTS_PER_ROUND, allocator], cwd=ROOT, capture_output=True,
                            text=True, timeout=120, check=True)
    return float(result.stdout.split()[-1])


def test_a_frames_blocks_are_taken_again_without_faulting_their_pages_in() -> None:
    # One 25 MB block faulted in afresh is ~6,100 pages of 4 KB; glibc's defaults fault in part of a frame a round.
    pages_per_frame = 3840 * 2160 * 3 / 4096
    assert faults_per_round('default') > 0.1 * pages_per_frame
    assert faults_per_round('tuned') < 0.01 * pages_per_frame
