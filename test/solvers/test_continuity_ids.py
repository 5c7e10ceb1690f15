"""
A lamp whose beacon is not yet certain, identified by where the recent pose says it can be.

Only when exactly one lamp of the map can be there and the beacon leans to it
(``solvers.continuity_ids``): a robot that loses the lamps for half a second gets a pose again
within a few frames.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from solver_scenes import observe

from vlp_ros.beacon.reading import BeaconReading
from vlp_ros.core.lamp_map import Lamp, LampMap
from vlp_ros.core.pose import Pose
from vlp_ros.sim.scenarios import robot_1080p_camera, ROBOT_CAMERA_MOUNT
from vlp_ros.solvers.ambiguity import DisambiguationHints, UpHint
from vlp_ros.solvers.continuity_ids import settled_by_continuity
from vlp_ros.solvers.fusion import solve_lamps

CAMERA = robot_1080p_camera()
# The drive's ceiling: two rows of four 15 cm lamps 2.4 m apart, 2.15 m above the camera, markers every way.
LAMPS = LampMap([Lamp(f'lamp_{k}', 10 + k, np.array([2.4 * (k // 2 - 1), 2.4 * (k % 2 - 0.5), 2.6]), 0.075,
                      marker_angle=1.3 * k - 2.0) for k in range(8)])
SEEN = LAMPS.get(12)
# The camera under lamp 12, the lamp well inside the image; a moment ago it was 0.2 m back.
TRUTH = Pose(Rotation.from_euler('z', 0.4).as_matrix() @ ROBOT_CAMERA_MOUNT, [0.5, -0.9, 0.45])
RECENT = Pose(TRUTH.rotation, TRUTH.position - [0.2, 0.0, 0.0])
# IDs 0-9 are not in the map (each 0.01 of a mapped ID's prior, as the packet decoder weighs them).
CANDIDATES = np.array([*range(10), *LAMPS.ids])
MAPPED = CANDIDATES >= 10


def evidence(leaning: dict[int, float]) -> BeaconReading:
    """Return a beacon reading that is not certain: likelihood ``leaning[id]`` for the IDs given, 0.003 the rest."""
    likelihood = np.array([leaning.get(int(c), 0.003) for c in CANDIDATES])
    return BeaconReading(None, 0.0, CANDIDATES, np.log(likelihood), np.where(MAPPED, 0.0, np.log(0.01)), MAPPED)


def settled(reading: BeaconReading, gate: float = 0.5, recent: Pose = RECENT) -> Lamp | None:
    hints = DisambiguationHints([UpHint(TRUTH.up_in_camera(), 0.1, np.radians(0.7))], recent_pose=recent,
                                recent_gate_m=gate)
    observation = observe(SEEN, TRUTH, CAMERA, rng=np.random.default_rng(1))
    return settled_by_continuity(observation, reading, LAMPS, recent, hints.recent_gate(),
                                 lambda pairs: solve_lamps(pairs, CAMERA, hints))


def test_a_lamp_seen_where_only_one_lamp_of_the_map_can_be_is_that_lamp() -> None:
    # One frame of 0.8 packet: the right ID most likely, three IDs off the map a bit behind (~0.97 its share).
    reading = evidence({12: 1.0, 3: 1.0, 4: 1.0, 5: 1.0})
    assert settled(reading) is SEEN
    # Another mapped lamp the beacon reads as a close second is ruled out by where the camera was.
    assert settled(evidence({12: 1.0, 15: 0.5, 3: 1.0})) is SEEN


def test_a_lamp_without_beacon_evidence_is_not_taken_for_the_mapped_lamp_it_stands_near() -> None:
    # An unmodulated lamp reads alike for every ID (the map's prior alone would give lamp 12 1 / 1.1 here).
    assert settled(evidence({})) is None
    # Evidence that hardly narrows the ID down: lamp 12 and the ten IDs off the map nearly alike.
    assert settled(evidence({12: 0.0035})) is None


def test_a_lamp_whose_beacon_names_another_lamp_is_not_settled_by_where_it_is() -> None:
    assert settled(evidence({15: 1.0, 12: 0.01})) is None


def test_after_a_long_gap_two_lamps_can_be_there_and_neither_is_chosen() -> None:
    # 2.5 m of motion: the camera may as well be under a neighbouring lamp.
    assert settled(evidence({12: 1.0, 3: 1.0}), gate=2.5) is None


def test_a_camera_far_from_every_lamp_that_could_be_seen_gets_no_id() -> None:
    far = Pose(RECENT.rotation, RECENT.position + [1.2, 1.2, 0.0])
    assert settled(evidence({12: 1.0, 3: 1.0}), recent=far) is None
