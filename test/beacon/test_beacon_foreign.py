"""
The independent renderer's hand-held 4K frames (foreign_frames/README.md).

A clipped, blurred, glaring lamp whose disc alone fits no packet is read on its light, with blur weighed
in, and never to a wrong ID.
"""
from conftest import SHARED_DATA
import pytest

from vlp_ros.evaluation.recording import recorded_frames, RecordingTopics
from vlp_ros.pipeline.config import settings_from_params_file
from vlp_ros.pipeline.frame import Pipeline, STEADY

HANDHELD = SHARED_DATA / 'foreign_frames' / 'handheld_4k_realistic'


@pytest.mark.skipif(not HANDHELD.exists(), reason='the shared foreign frames are not here')
def test_the_hand_held_realistic_lamp_is_identified_in_seven_frames_of_eight_and_never_wrongly():
    settings = settings_from_params_file(HANDHELD / 'params.yaml')
    pipeline = Pipeline(settings)
    frames = list(recorded_frames(HANDHELD / 'bag', RecordingTopics(image='/image_raw/compressed'), None))
    decoded = [pipeline.process(f.image, f.camera, f.stamp_ns * 1e-9, f.up).decoded_ids for f in frames]
    # One mapped lamp (ID 90) beside unmodulated lamps: any other ID would be wrong. Its light is read with
    # blur weighed in, the chip grid searched on the whole window (the first 24 chips lie in the glow's faint
    # rows) and the grids around it weighed in too, and a clipped disc's chips censored: each of the 8 stills
    # reads 90 at 0.99999 or more, and the target is 90 % of them.
    assert all(ids in ([], [90]) for ids in decoded), decoded
    assert sum(ids == [90] for ids in decoded) >= 7, decoded


@pytest.mark.skipif(not HANDHELD.exists(), reason='the shared foreign frames are not here')
def test_the_hand_held_realistic_stills_unmodulated_lamps_are_all_left_unread():
    # Beside lamp 90 the stills show a dozen unmodulated lamps, clipped over most of their rows: each is found steady,
    # and none is read (a reading of a clipped disc and its glow costs several times a beacon's).
    settings = settings_from_params_file(HANDHELD / 'params.yaml')
    pipeline = Pipeline(settings)
    frames = list(recorded_frames(HANDHELD / 'bag', RecordingTopics(image='/image_raw/compressed'), None))
    seen = [lamp for f in frames for lamp in pipeline.process(f.image, f.camera, f.stamp_ns * 1e-9, f.up).seen]
    others = [lamp for lamp in seen if lamp.lamp_id != 90]
    assert len(others) >= 10
    assert all(lamp.detail == STEADY for lamp in others), [lamp.detail for lamp in others]
