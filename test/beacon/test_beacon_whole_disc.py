"""An unclipped disc showing less than a packet is read again to its edge: its top and bottom rows hold chips."""
from beacon_scenes import lamp_image
import cv2
import numpy as np

from vlp_ros.beacon.decoding import decode_packet, read_lamp, row_profile
from vlp_ros.beacon.encoding import packet_length, packet_waveform

ROW_TIME = 20e-6
ROWS_PER_CHIP = 5.0
CHIP_RATE = 1.0 / (ROWS_PER_CHIP * ROW_TIME)
ID_BITS = 8
MAP_IDS = list(range(3, 256, 7))


def test_discs_of_most_of_a_packet_gain_ids_from_their_edge_rows_and_never_a_wrong_one():
    rng = np.random.default_rng(14)
    packet_rows = packet_length(ID_BITS) * ROWS_PER_CHIP

    def decode(profile):
        return decode_packet(profile, CHIP_RATE, ROW_TIME, ID_BITS, MAP_IDS)

    eroded, whole = 0, 0
    for _ in range(150):
        # One lamp in ten carries an ID off the map: reading it as a mapped one would be wrong.
        lamp_id = int(rng.choice(MAP_IDS)) if rng.uniform() > 0.1 else int(rng.choice(
            sorted(set(range(2 ** ID_BITS)) - set(MAP_IDS))))
        waveform = packet_waveform(lamp_id, CHIP_RATE, rng.uniform(0.5, 1.0), ID_BITS,
                                   offset=rng.uniform(0.0, packet_rows * ROW_TIME))
        half_height = 0.5 * rng.uniform(0.65, 0.95) * packet_rows
        image, observation = lamp_image(waveform, ROW_TIME, 0.3 / CHIP_RATE, (1.3 * half_height, half_height),
                                        peak=rng.uniform(120.0, 220.0), rng=rng)
        blur = rng.uniform(0.0, 1.5)
        if blur > 0.3:
            image = cv2.GaussianBlur(image, (0, 0), blur)
        reading = read_lamp(image, observation, decode, glow=False)
        disc = decode(row_profile(image, observation))
        assert reading.lamp_id in (None, lamp_id), (lamp_id, reading.lamp_id, reading.confidence)
        eroded += disc.lamp_id == lamp_id
        whole += reading.lamp_id == lamp_id
    # Read to their edges, discs of 0.65-0.95 packet give IDs where their eroded interior leaves bits unseen.
    assert whole >= eroded + 5, (whole, eroded)
