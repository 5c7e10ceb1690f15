"""
Whether the camera's settings let the decoders read the map's lamps (docs/beacon.md, "Camera settings").

Inside these limits the beacon benchmark reads over 99 % of single frames (packet: 1.3 packets in
view; tone: 3 stripe periods). Outside them frames are still decoded, never with a wrong ID, but
less often: the locator says so once at start-up, naming the setting to change.
"""
from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from vlp_ros.beacon.encoding import complement_closed
from vlp_ros.beacon.tone import ROW_TIME_TOLERANCE

# Packet mode: rows per chip (the benchmark's fewest, all read), and the longest exposure (in chips)
# that leaves chips apart.
MIN_ROWS_PER_CHIP = 2.5
MAX_EXPOSURE_CHIPS = 1.0
# Tone mode: rows per stripe period (a stripe of two rows or more), and the least share of the
# stripes' contrast that the exposure's average over time lets through (|sinc(exposure x frequency)|).
MIN_ROWS_PER_PERIOD = 4.0
MIN_TRANSMISSION = 0.3


def packet_setting_advice(chip_rate: float, row_time: float, exposure: float | None,
                          id_bits: int = 8) -> list[str]:
    """Return what to change so that packet-mode frames are read reliably (empty: nothing)."""
    advice = []
    if complement_closed(id_bits):
        advice.append(f'beacon.id_bits {id_bits} is odd: the complement of every ID passes parity too, so a lamp is '
                      f"told from the lamp of its complement ID only by the stripes' polarity, which clipped, "
                      f'blurred stripes can hide (such lamps then stay unidentified); an even beacon.id_bits avoids it')
    rows_per_chip = 1.0 / (chip_rate * row_time)
    if rows_per_chip < MIN_ROWS_PER_CHIP:
        advice.append(f'beacon.chip_rate {chip_rate:g} Hz gives {rows_per_chip:.1f} rows per chip at beacon.row_time '
                      f'{row_time * 1e6:g} us (reliable from {MIN_ROWS_PER_CHIP:g}): lamps need more frames to be '
                      f'identified, or are not identified at all')
    if exposure is not None and exposure * chip_rate > MAX_EXPOSURE_CHIPS:
        advice.append(f'beacon.exposure {exposure * 1e6:g} us spans {exposure * chip_rate:.1f} chips (reliable up to '
                      f'{MAX_EXPOSURE_CHIPS:g}): neighbouring chips blur together; shorten the exposure')
    return advice


def tone_setting_advice(frequencies: Mapping[str, float], row_time: float, exposure: float | None,
                        frequency_tolerance: float = 60.0,
                        row_time_tolerance: float = ROW_TIME_TOLERANCE) -> list[str]:
    """
    Return what to change so that tone-mode frames are read reliably and never wrongly (empty: nothing).

    ``frequencies`` by lamp name, the tolerances as ``decode_tone``'s.
    """
    advice = []
    if exposure is None:
        advice.append('beacon.exposure is 0 (unknown): tone lamps are then identified only from about ten stripe '
                      "periods in view; set it to the camera's exposure time")
    elif exposure < row_time:
        advice.append(f'beacon.exposure {exposure * 1e6:g} us is shorter than beacon.row_time {row_time * 1e6:g} us: '
                      f"stripe edges between the rows' exposures cannot be placed, and lamps are identified less "
                      f'often; an exposure of at least a row time reads them best')
    few_rows = {name: 1.0 / (f * row_time) for name, f in frequencies.items()
                if f * row_time * MIN_ROWS_PER_PERIOD > 1.0}
    if few_rows:
        advice.append(f'fewer than {MIN_ROWS_PER_PERIOD:g} rows per stripe period at beacon.row_time '
                      f'{row_time * 1e6:g} us for {_listed(few_rows, "rows")}: these lamps need more stripe periods '
                      f'in view (a larger image of the lamp) to be identified')
    crowded = _crowded_pairs(frequencies, frequency_tolerance, row_time_tolerance)
    if crowded:
        pairs = ', '.join(crowded[:6]) + (' and more' if len(crowded) > 6 else '')
        advice.append(f'beacon.row_time_tolerance {row_time_tolerance:g}: tone lamps {pairs} lie less than 2 x '
                      f'(beacon.frequency_tolerance + beacon.row_time_tolerance x frequency) apart, so their bands '
                      f'meet: near the middle neither is identified, and a lamp between them that is not in the map '
                      f'reads as one of them when it is alone in view (with other lamps in view the row time is '
                      f'measured and it is not); spread their frequencies, or measure the row time and lower '
                      f'beacon.row_time_tolerance')
    if exposure is not None:
        contrast = {name: abs(float(np.sinc(exposure * f))) for name, f in frequencies.items()}
        washed = {name: left for name, left in contrast.items() if left < MIN_TRANSMISSION}
        if washed:
            lamps = _listed(washed, 'of the contrast left', percent=True)
            advice.append(f'beacon.exposure {exposure * 1e6:g} us spans about whole stripe periods of {lamps}: '
                          f'their stripes are washed out; choose an exposure away from multiples of their periods')
    return advice


def _crowded_pairs(frequencies: Mapping[str, float], frequency_tolerance: float,
                   row_time_tolerance: float) -> list[str]:
    """Neighbouring lamps whose bands (decode_tone's) reach the midpoint between them."""
    ordered = sorted(frequencies.items(), key=lambda item: item[1])
    return [f'{low!r} and {high!r}' for (low, f_low), (high, f_high) in zip(ordered, ordered[1:])
            if frequency_tolerance + row_time_tolerance * f_high >= 0.5 * (f_high - f_low)]


def _listed(values: Mapping[str, float], unit: str, percent: bool = False) -> str:
    shown = [f'{name!r} ({100.0 * v:.0f} % {unit})' if percent else f'{name!r} ({v:.1f} {unit})'
             for name, v in sorted(values.items())]
    return ', '.join(shown[:6]) + (f' and {len(shown) - 6} more' if len(shown) > 6 else '')
