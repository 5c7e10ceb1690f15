"""Evidence across frames: a lamp too small to read at once becomes certain, and only its own frames count."""
import dataclasses

from beacon_scenes import flat_profile
import numpy as np
import pytest

from vlp_ros.beacon.decoding import decode_packet
from vlp_ros.beacon.encoding import packet_waveform
from vlp_ros.beacon.evidence import EvidenceTracker
from vlp_ros.beacon.reading import BeaconReading, no_evidence
from vlp_ros.core.observation import LampObservation

ROW_TIME = 2e-5
CHIP_RATE = 1.0 / (5 * ROW_TIME)
MAP = [3, 17, 77, 130, 201, 254]


def observation_at(x, y, a=40.0):
    return LampObservation(np.array([x, y, a, 0.8 * a, 0.0]), np.zeros((0, 2)), 0.1, None, 0.1,
                           (0, 0, 1, 1), np.ones((1, 1), dtype=bool))


def half_packet(lamp_id, frame):
    """Half a packet of ``lamp_id`` seen from a different place in the packet every frame."""
    wave = packet_waveform(lamp_id, CHIP_RATE, 0.7, offset=frame * 7.3e-4)
    profile = flat_profile(wave, 60, ROW_TIME, 3e-5, noise=0.5, rng=np.random.default_rng(frame))
    return decode_packet(profile, CHIP_RATE, ROW_TIME, 8, MAP)


def test_half_packets_add_up_to_a_certain_id():
    tracker = EvidenceTracker(MAP)
    ids = []
    for frame in range(8):
        reading = half_packet(201, frame)
        assert reading.lamp_id is None
        ids.append(tracker.update([observation_at(100.0 + frame, 50.0)], [reading], 0.033 * frame)[0])
    assert ids[0] is None
    assert set(ids) <= {None, 201} and ids[-1] == 201


def test_lamps_far_apart_are_tracked_apart():
    tracker = EvidenceTracker(MAP)
    for frame in range(8):
        readings = [half_packet(201, frame), half_packet(17, frame + 100)]
        ids = tracker.update([observation_at(100.0, 50.0), observation_at(300.0, 50.0)], readings, 0.033 * frame)
    assert ids == [201, 17]
    assert len(tracker.tracks) == 2


def test_a_track_not_seen_for_long_starts_over():
    tracker = EvidenceTracker(MAP, max_gap=0.2)
    for frame in range(8):
        tracker.update([observation_at(100.0, 50.0)], [half_packet(201, frame)], 0.033 * frame)
    assert tracker.update([observation_at(100.0, 50.0)], [half_packet(201, 50)], 10.0) == [None]


def test_a_certain_frame_of_another_id_starts_the_track_over():
    tracker = EvidenceTracker(MAP)
    for frame in range(8):
        tracker.update([observation_at(100.0, 50.0)], [half_packet(201, frame)], 0.033 * frame)
    full = decode_packet(flat_profile(packet_waveform(17, CHIP_RATE, 0.7), 200, ROW_TIME, 3e-5), CHIP_RATE,
                         ROW_TIME, 8, MAP)
    assert full.lamp_id == 17
    assert tracker.update([observation_at(101.0, 50.0)], [full], 0.3) == [17]
    assert len(tracker.tracks) == 1 and tracker.tracks[0].frames == 1


def test_unknown_id_is_never_returned():
    tracker = EvidenceTracker(MAP)
    reading = decode_packet(flat_profile(packet_waveform(100, CHIP_RATE, 0.7), 200, ROW_TIME, 3e-5), CHIP_RATE,
                            ROW_TIME, 8, MAP)
    for frame in range(4):
        assert tracker.update([observation_at(100.0, 50.0)], [reading], 0.033 * frame) == [None]
    assert tracker.decisions[0].unknown


def test_bad_inputs_are_rejected():
    tracker = EvidenceTracker(MAP)
    with pytest.raises(ValueError, match='readings'):
        tracker.update([observation_at(1.0, 1.0)], [], 0.0)
    with pytest.raises(ValueError, match='min_confidence'):
        EvidenceTracker(MAP, min_confidence=1.0)
    reading = half_packet(201, 0)
    with pytest.raises(ValueError, match='same length'):
        dataclasses.replace(reading, log_prior=reading.log_prior[:3])


def test_a_lamp_moving_through_the_image_becomes_certain_within_a_few_frames():
    # A robot at 0.8 m/s turning at 0.3 rad/s, 10 frames/s: a 38 px lamp moves 40-100 px a frame on a curve.
    tracker = EvidenceTracker(MAP)
    ids = []
    for frame in range(5):
        angle = 0.3 * frame
        x, y = 900.0 + 250.0 * np.cos(angle), 500.0 + 250.0 * np.sin(angle)
        ids.append(tracker.update([observation_at(x, y, a=38.0)], [half_packet(201, frame)], 0.1 * frame)[0])
    assert set(ids) <= {None, 201} and ids[-1] == 201
    assert len(tracker.tracks) == 1


def test_moving_lamps_keep_their_own_tracks():
    tracker = EvidenceTracker(MAP)
    for frame in range(6):
        shift = 70.0 * frame
        readings = [half_packet(201, frame), half_packet(17, frame + 100)]
        observations = [observation_at(100.0 + shift, 50.0, a=38.0), observation_at(1300.0 + shift, 80.0, a=38.0)]
        ids = tracker.update(observations, readings, 0.1 * frame)
    assert ids == [201, 17]
    assert len(tracker.tracks) == 2


def test_a_frame_delivered_twice_adds_no_evidence():
    # The same frame again has the same packet phase and noise: summed ten times, a reading that leans
    # to lamp 3 at ~0.77 would pass for certain.
    candidates = np.array(MAP)
    reading = BeaconReading(None, 0.0, candidates, np.array([0.0, -3.0, -3.0, -3.0, -1.5, -3.0]),
                            np.zeros(len(MAP)), np.ones(len(MAP), bool))
    once, twice = EvidenceTracker(MAP), EvidenceTracker(MAP)
    once.update([observation_at(100.0, 50.0)], [reading], 0.0)
    for _ in range(10):
        twice.update([observation_at(100.0, 50.0)], [reading], 0.0)
    assert once.decisions[0].confidence < 0.9
    assert twice.decisions[0].lamp_id is None
    assert twice.decisions[0].confidence == pytest.approx(once.decisions[0].confidence, abs=1e-6)
    assert twice.tracks[0].frames == 1


def test_a_lamp_near_where_a_certain_lamp_was_does_not_inherit_its_id():
    """
    A hand-held camera moved between stills.

    Lamp 201 is read now elsewhere, and an unmodulated lamp stands where the track left it. One lamp cannot
    be in two places: only the one read now keeps the ID.
    """
    tracker = EvidenceTracker(MAP)
    for frame in range(8):
        tracker.update([observation_at(100.0, 50.0)], [half_packet(201, frame)], 0.033 * frame)
    assert tracker.decisions[0].lamp_id == 201
    full = decode_packet(flat_profile(packet_waveform(201, CHIP_RATE, 0.7), 200, ROW_TIME, 3e-5), CHIP_RATE,
                         ROW_TIME, 8, MAP)
    steady = no_evidence(full.candidates, full.mapped, full.log_prior, 'steady')
    ids = tracker.update([observation_at(102.0, 50.0), observation_at(900.0, 50.0)], [steady, full], 0.3)
    assert ids == [None, 201]
    assert tracker.update([observation_at(103.0, 50.0)], [steady], 0.333) == [None]
