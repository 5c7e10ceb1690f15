"""The beacon decoder's entry points, one lamp in one frame (docs/beacon.md).

``light_profile`` (every pixel the lamp's light reaches) or ``row_profile`` (the disc's
interior only) turns a detected lamp into brightness per row; ``decode_packet``
and ``decode_tone`` turn that into a ``BeaconReading``; ``EvidenceTracker``
(vlp_ros.beacon.evidence) adds readings up across frames.
"""
from collections.abc import Callable

import numpy as np

from vlp_ros.beacon.packet import decode_packet
from vlp_ros.beacon.profile import RowProfile, light_profile, row_profile
from vlp_ros.beacon.reading import UNMAPPED, BeaconReading
from vlp_ros.beacon.tone import decode_tone
from vlp_ros.observation import LampObservation

__all__ = ['BeaconReading', 'RowProfile', 'UNMAPPED', 'decode_packet', 'decode_tone', 'light_profile', 'read_lamp',
           'row_profile']


def read_lamp(image: np.ndarray, observation: LampObservation, decode: Callable[[RowProfile], BeaconReading],
              glow: bool = True) -> BeaconReading:
    """One lamp's reading, as the locator takes it: ``decode`` of the disc's interior first (quick, and all a
    sharp, unclipped lamp needs). When that leaves the ID open and ``glow`` is set, every row the lamp's
    light reaches (glow, glare, clipped discs) is read too, and its reading replaces the disc's if it holds
    evidence and either spans more rows or the disc's holds none. The choice looks at the rows, never at
    which reading is surer.

    Tone mode reads the disc only (``glow=False``, docs/beacon.md): blur across rows rounds the stripes
    that the glow shows unclipped, and the square wave fitted with the given exposure then misplaces the
    frequency (on the foreign frames, mapped lamps read as off the map, once near a harmonic)."""
    disc_profile = row_profile(image, observation)
    disc = decode(disc_profile)
    if disc.lamp_id is not None or disc.unknown or not glow:
        return disc
    light_rows = light_profile(image, observation)
    if _has_evidence(disc) and _span(light_rows) <= _span(disc_profile):
        return disc
    light = decode(light_rows)
    return light if _has_evidence(light) else disc


def _has_evidence(reading: BeaconReading) -> bool:
    return bool(np.any(reading.log_likelihoods != reading.log_likelihoods[0]))


def _span(profile: RowProfile) -> int:
    """Rows from the first usable one to the last."""
    used = np.flatnonzero(profile.weights > 0)
    return int(used[-1] - used[0] + 1) if used.size else 0
