"""Frame-sized pixel arrays reused from one frame to the next."""
from __future__ import annotations

import sys

import numpy as np

# sys.getrefcount(self._arrays[index]) when nothing else refers to the array: the list and getrefcount's argument.
_OWN_REFERENCES = 2


class FrameBuffers:
    """
    A few frame-sized arrays, each handed out again once nothing refers to it or to a view of it.

    A fresh frame-sized array is either a fresh mapping, its pages faulted in and zeroed as the decoder first
    writes them (at 4K 25 MB: ~3 ms a frame, and in the locator bursts of 60-80 ms decodes), or a block of glibc's
    heap, which keeps freed frames as resident fragments (~20 MB more peak RSS in the locator under a 4K JPEG
    stream). A numpy view keeps its base array referenced, so a frame that anything still holds is never written
    over.
    """

    def __init__(self, count: int) -> None:
        self._arrays: list[np.ndarray] = []
        self._count = count

    def array(self, shape: tuple[int, ...]) -> np.ndarray:
        """Return a writable C-contiguous uint8 array of ``shape`` that no one else holds (contents undefined)."""
        for index in range(len(self._arrays)):
            if self._arrays[index].shape == shape and self._unused(index):
                return self._arrays[index]
        # Unused arrays of another size (the camera changed) give way.
        self._arrays = [self._arrays[index] for index in range(len(self._arrays))
                        if self._arrays[index].shape == shape or not self._unused(index)]
        fresh = np.empty(shape, np.uint8)
        if len(self._arrays) < self._count:
            self._arrays.append(fresh)
        return fresh

    def _unused(self, index: int) -> bool:
        # Indexed, not bound to a name, so that no variable of this class adds a reference.
        return sys.getrefcount(self._arrays[index]) == _OWN_REFERENCES
