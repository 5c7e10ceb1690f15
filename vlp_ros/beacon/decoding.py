"""
The beacon decoder's entry points, one lamp in one frame (docs/beacon.md).

``light_profile`` (every pixel the lamp's light reaches) or ``row_profile`` (the disc's
interior only) turns a detected lamp into brightness per row; ``decode_packet``
and ``decode_tone`` turn that into a ``BeaconReading``; ``EvidenceTracker``
(vlp_ros.beacon.evidence) adds readings up across frames.
"""
from collections.abc import Callable, Iterable

import numpy as np

from vlp_ros.beacon.packet import BLUR_MIXES, decode_clipped_packet, decode_packet
from vlp_ros.beacon.profile import light_profile, row_profile, RowProfile
from vlp_ros.beacon.reading import BeaconReading, has_evidence, no_evidence, UNMAPPED, UNMAPPED_WEIGHT
from vlp_ros.beacon.tone import decode_tone
from vlp_ros.core.observation import LampObservation

__all__ = ['BLUR_MIXES', 'BeaconReading', 'RowProfile', 'UNMAPPED', 'decode_clipped_packet', 'decode_glow',
           'decode_packet', 'decode_tone', 'light_profile', 'has_evidence', 'read_lamp', 'row_profile']


def read_lamp(image: np.ndarray, observation: LampObservation, decode: Callable[[RowProfile], BeaconReading],
              glow: bool = True, decode_glow: Callable[[RowProfile], BeaconReading] | None = None,
              decode_clipped: Callable[[RowProfile], BeaconReading] | None = None) -> BeaconReading:
    """
    One lamp's reading, as the locator takes it.

    ``decode`` of the disc's interior first (quick, and all a sharp, unclipped lamp needs). When the disc holds no
    evidence at all (its chips fit no packet, as a clipped, blurred disc's do) and ``glow`` is set, every row the lamp's
    light reaches (glow, glare, the clipped disc's dark rows) is read instead. A disc with evidence is kept even if
    uncertain: summed over frames by the tracker, light-profile readings of half packets gave wrong IDs (2 in 3013
    benchmark tracks and frames). ``decode_glow`` (packet mode: ``decode_glow`` below, sharp chips first, blur weighed
    in when they leave the ID open), when given, reads the light profile instead of ``decode``, and its reading is taken
    only if it is certain: a disc without evidence is one that blur and clipping spoilt. Its uncertain readings are not
    passed on, because summed over frames they left the tracker less certain than the sharp ones (the simulator's
    realistic drive: 2 poses instead of 7 of 62). Nor are the light profile's uncertain sharp readings: where the disc
    clips, its bright rows are seen on the glow alone, and summed over frames such readings leaned to wrong IDs (the
    accuracy benchmark's realistic robot row).

    A disc that is uncertain (a lamp showing less than a packet) and does not clip is read again to its edge
    (``row_profile`` with no margin: its top and bottom rows, which the margin drops, hold the end chips), and
    takes that reading where it is certain and names the disc's own most probable ID. Otherwise it takes the
    light profile's reading only where that is certain and names the disc's most probable ID
    (``confirmed_by_light``).

    Tone mode reads the disc only (``glow=False``, docs/beacon.md): blur across rows rounds the stripes
    that the glow shows unclipped, and the square wave fitted with the given exposure then misplaces the
    frequency (on the foreign frames, mapped lamps read as off the map, once near a harmonic).

    ``decode_clipped`` (packet mode: ``decode_clipped_packet``) reads a disc that ``decode`` leaves without an ID
    again with its clipped chips censored; a certain reading of it is taken at once. An uncertain one with evidence
    stands for a disc whose Gaussian reading has none, unless the light is certain: it is what the tracker sums for
    a clipped disc below a packet (the simulator's realistic drive: the right ID at 0.97-0.999 frame after frame).
    """
    disc_profile = row_profile(image, observation)
    disc = decode(disc_profile)
    if disc.lamp_id is not None or disc.unknown:
        return disc
    if has_evidence(disc) and not np.any(disc_profile.saturated):
        whole = confirmed_by_light(disc, decode(row_profile(image, observation, edge_margin=0)))
        if whole.lamp_id is not None:
            return whole
    censored = disc
    if decode_clipped is not None:
        clipped = decode_clipped(disc_profile)
        if clipped.lamp_id is not None or clipped.unknown:
            return clipped
        if not has_evidence(disc) and has_evidence(clipped):
            censored = clipped
    if not glow:
        return censored
    if has_evidence(disc):
        return confirmed_by_light(disc, decode(light_profile(image, observation)))
    profile = light_profile(image, observation)
    light = (decode if decode_glow is None else decode_glow)(profile)
    return light if light.lamp_id is not None or light.unknown else censored


def confirmed_by_light(disc: BeaconReading, light: BeaconReading) -> BeaconReading:
    """
    Return ``light`` where it is certain and names ``disc``'s most probable candidate; otherwise ``disc``.

    ``light`` is the reading over every row the lamp's light reaches. A glare halo carries the stripes on
    rows above and below the disc, so a lamp that shows less than a packet on its disc can show all of it
    in its light (the simulator's hand-held glare stills: 0.7 of a packet on the disc, read at 0.97;
    certain on the light). Both must agree: a certain light reading alone is not enough where the disc's
    own rows favour another ID.
    """
    if light.lamp_id is None:
        return disc
    return light if _most_probable_candidate(disc) == light.lamp_id else disc


def decode_glow(profile: RowProfile, chip_rate: float, row_time: float, id_bits: int = 8,
                known_ids: Iterable[int] | None = None, *, timing_tolerance: float = 0.05,
                unmapped_weight: float = UNMAPPED_WEIGHT) -> BeaconReading:
    """
    Packet mode's reading of a lamp's light profile (``read_lamp``'s ``decode_glow``).

    ``decode_packet`` with blur weighed in (sharp chips first), certain only if the chip period does not
    decide the ID.

    The reading's certainty is that of the IDs on the one chip grid the search found. Where the disc clips
    and blur spreads it, its bright rows are seen on the faint glow alone and its dark rows on the disc, and
    grids several percent apart fit such a profile about as well: on the simulator's realistic hand-held
    stills, grids found 4-6 % short read lamp 11 as 107 at 0.99999 (sharp and blurred chips alike), the
    nominal period as 11 at 1.0. So a
    certain reading is checked on each third of the period's range (each searched on its own), and stands
    only if no third's reading that has evidence names another ID.
    """
    def read(scale: float, tolerance: float) -> BeaconReading:
        return decode_packet(profile, chip_rate * scale, row_time, id_bits, known_ids,
                             timing_tolerance=tolerance, unmapped_weight=unmapped_weight, blur_mixes=BLUR_MIXES)
    whole = read(1.0, timing_tolerance)
    if whole.lamp_id is None and not whole.unknown:
        return whole
    best = _most_probable_candidate(whole)
    third = timing_tolerance / 3.0
    for scale in (1.0 - 2.0 * third, 1.0, 1.0 + 2.0 * third):
        part = read(scale, third)
        if has_evidence(part) and _most_probable_candidate(part) != best:
            return no_evidence(whole.candidates, whole.mapped, whole.log_prior,
                               f'the glow reads ID {best} on one chip period and ID '
                               f'{_most_probable_candidate(part)} on another')
    return whole


def _most_probable_candidate(reading: BeaconReading) -> int:
    return int(reading.candidates[np.argmax(reading.log_likelihoods + reading.log_prior)])
