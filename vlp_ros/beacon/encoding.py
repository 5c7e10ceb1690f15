"""
The beacon contract (docs/beacon.md): what a lamp transmits, as chips and as light over time.

Packet mode: preamble ``1 1 1 0 0 0``, then ``id_bits`` data bits MSB first, then one
even-parity bit; every bit Manchester coded (1 -> ``1 0``, 0 -> ``0 1``); packets
repeat back to back. Tone mode: a 50 % duty square wave, i.e. chips ``1 0`` at twice
the tone frequency. A 1 chip is full brightness, a 0 chip ``1 - depth`` of it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PREAMBLE = (1, 1, 1, 0, 0, 0)
MANCHESTER = {1: (1, 0), 0: (0, 1)}


def packet_length(id_bits: int) -> int:
    """Chips in one packet (24 for 8-bit IDs)."""
    return len(PREAMBLE) + 2 * (id_bits + 1)


def packet_bits(lamp_id: int, id_bits: int = 8) -> list[int]:
    """Return data bits (MSB first) followed by the even-parity bit."""
    if not 0 <= lamp_id < 2 ** id_bits:
        raise ValueError(f'lamp id {lamp_id} does not fit in {id_bits} bits')
    data = [(lamp_id >> (id_bits - 1 - k)) & 1 for k in range(id_bits)]
    return data + [sum(data) % 2]


def complement_closed(id_bits: int) -> bool:
    """
    Whether every packet's complement (each data and parity bit inverted) passes parity too.

    With odd ``id_bits`` the word has an even number of bits. Its chips, all inverted, are then the
    complement ID's packet with the preamble inverted, so only the stripes' polarity tells the two apart.
    """
    return id_bits % 2 == 1


def packet_chips(lamp_id: int, id_bits: int = 8) -> np.ndarray:
    """One packet as chips (uint8 0/1): preamble, then the Manchester-coded bits."""
    chips = list(PREAMBLE)
    for bit in packet_bits(lamp_id, id_bits):
        chips.extend(MANCHESTER[bit])
    return np.array(chips, dtype=np.uint8)


@dataclass(frozen=True)
class Waveform:
    """
    A periodic chip sequence as light: level 1 for a 1 chip, ``1 - depth`` for a 0 chip.

    ``offset`` (s) is the time at which chip 0 of the sequence starts.
    """

    chips: np.ndarray
    chip_rate: float
    depth: float
    offset: float = 0.0

    @property
    def period(self) -> float:
        return len(self.chips) / self.chip_rate

    def levels(self) -> np.ndarray:
        return 1.0 - self.depth * (1.0 - np.asarray(self.chips, dtype=float))

    def mean_brightness(self, start: np.ndarray, exposure: float) -> np.ndarray:
        """Brightness averaged over each window [start, start + exposure] (exact integral)."""
        start = np.asarray(start, dtype=float)
        if exposure <= 0.0:
            return self.level_at(start)
        return (self._integral(start + exposure) - self._integral(start)) / exposure

    def level_at(self, t: np.ndarray) -> np.ndarray:
        """Instantaneous brightness at times ``t``."""
        rel = np.asarray(t, dtype=float) - self.offset
        k = np.floor(rel * self.chip_rate).astype(int) % len(self.chips)
        return self.levels()[k]

    def _integral(self, t: np.ndarray) -> np.ndarray:
        """Integral of the light from ``offset`` to ``t``."""
        levels = self.levels()
        chip_time = 1.0 / self.chip_rate
        cumulative = np.concatenate([[0.0], np.cumsum(levels) * chip_time])
        rel = np.asarray(t, dtype=float) - self.offset
        periods = np.floor(rel / self.period)
        within = rel - periods * self.period
        k = np.minimum((within / chip_time).astype(int), len(levels) - 1)
        return periods * cumulative[-1] + cumulative[k] + levels[k] * (within - k * chip_time)


def packet_waveform(lamp_id: int, chip_rate: float, depth: float,
                    id_bits: int = 8, offset: float = 0.0) -> Waveform:
    return Waveform(packet_chips(lamp_id, id_bits), chip_rate, depth, offset)


def tone_waveform(frequency: float, depth: float, offset: float = 0.0) -> Waveform:
    return Waveform(np.array([1, 0], dtype=np.uint8), 2.0 * frequency, depth, offset)
