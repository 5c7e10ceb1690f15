"""
IDs settled jointly with the geometry.

With several lamps in view, a lamp whose tone lies where two lamps' bands meet (a row time known to
2 % leaves it open) is identified when one pose explains every lamp with it, and a lamp that is not
in the map is never given an ID that way.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from vlp_ros.beacon.encoding import tone_waveform
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.detection import detect_lamps
from vlp_ros.pipeline.config import settings_from_tree
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.sim.imu import specific_force
from vlp_ros.sim.point_lamps import bare_led_scenario, PointLampLook, PointSimLamp, render_point_lamps
from vlp_ros.solvers.candidates import Choice, Reason
from vlp_ros.solvers.joint_ids import OpenLamp, settle

# 3500 and 3650 Hz: each band reaches 60 Hz + 2 % (70-73 Hz) out, so they meet between 3517 and 3633 Hz.
FREQUENCIES = (2000.0, 2500.0, 3000.0, 3500.0, 3650.0)
PHOTOS = 4


@pytest.fixture(scope='module')
def photos():
    """
    Return photos of the rig with its tones as FREQUENCIES and the row time 2 % off, and a sixth LED.

    The sixth LED is not in the map, at 3575 Hz (between the two close bands), beside the centre.
    """
    scenario = bare_led_scenario('4k', photos=PHOTOS, seed=21, look=PointLampLook(), row_time_error=0.02)
    rng = np.random.default_rng(3)
    lamps = [PointSimLamp(replace(sim.lamp, frequency=f), tone_waveform(f, 0.75, float(rng.uniform(0.0, 1.0 / f))))
             for sim, f in zip(scenario.lamps, FREQUENCIES)]
    scenario = replace(scenario, lamps=lamps)
    stranger = PointSimLamp(Lamp('stranger', 6, np.array([0.0, 0.22, 2.46]), 0.0, frequency=3575.0),
                            tone_waveform(3575.0, 0.75, 1e-4))
    frames = []
    for index, pose in enumerate(scenario.poses):
        alone = scenario.render(index, rng)
        force = specific_force(pose, None, scenario.imu_noise, rng)
        with_stranger = render_point_lamps(scenario.camera, pose, [*lamps, stranger], scenario.sensor,
                                           alone.start_time, rng, scenario.look, scenario.scale)
        frames.append((alone, with_stranger, force / np.linalg.norm(force)))
    return scenario, frames


def located(scenario, photos) -> list[tuple[int, int, float | None]]:
    """
    Per (frame, up) photo.

    Lamps identified right and wrong (against the LED nearest to each), and the pose's position
    error (m; None without a pose).
    """
    pipeline = Pipeline(settings_from_tree(scenario.locator_parameters(imu=True)))
    found = []
    for frame, up in photos:
        result = pipeline.process(frame.image, frame.camera, frame.start_time, up)
        truths = [min(frame.lamps, key=lambda t: np.linalg.norm(seen.observation.center - t.center_pixel)).lamp_id
                  for seen in result.seen if seen.lamp_id is not None]
        ids = [seen.lamp_id for seen in result.seen if seen.lamp_id is not None]
        right = sum(t == i for t, i in zip(truths, ids))
        error = None if result.pose is None else float(np.linalg.norm(result.pose.position - frame.pose.position))
        found.append((right, len(ids) - right, error))
    return found


@pytest.mark.simulation
def test_lamps_between_two_bands_are_identified_by_the_pose_that_explains_every_lamp(photos) -> None:
    scenario, frames = photos
    outcomes = located(scenario, [(frame, up) for frame, _, up in frames])
    assert all(wrong == 0 and error is not None and error < 0.05 for _, wrong, error in outcomes), outcomes
    # The tones alone left the lamp between the bands open on every photo (16 of 20 identified).
    assert sum(right for right, _, _ in outcomes) >= 5 * PHOTOS - 1


@pytest.mark.simulation
def test_a_lamp_not_in_the_map_whose_tone_takes_a_mapped_id_is_told_apart_by_the_geometry(photos) -> None:
    scenario, frames = photos
    assert all(any(t.lamp_id == 6 and t.fully_inside for t in frame.lamps) for _, frame, _ in frames)
    outcomes = located(scenario, [(frame, up) for _, frame, up in frames])
    # The stranger's tone, 2 % off, lies in lamp 5's band alone, so its reading claims ID 5 as the real
    # lamp 5 does: both are reopened, and only the real one fits the pose.
    posed = [(wrong, error) for _, wrong, error in outcomes if error is not None]
    assert all(wrong == 0 and error < 0.05 for wrong, error in posed), outcomes
    # Where three lamps and the stranger are certain (one photo here) nothing tells which is the
    # stranger: no pose.
    assert len(posed) >= PHOTOS - 1


def _lamp(lamp_id: int) -> Lamp:
    return Lamp(f'l{lamp_id}', lamp_id, np.array([0.5 * lamp_id, 0.0, 2.5]), 0.0, frequency=1000.0 * lamp_id)


def _observation() -> LampObservation:
    frame = bare_led_scenario('1080p', photos=1, seed=1).render(0, None)
    return detect_lamps(frame.image)[0]


def test_a_lamp_two_of_whose_candidates_fit_the_pose_stays_open() -> None:
    # A pose that explains anything: geometry that cannot tell the candidates apart settles nothing.
    anywhere = Choice(Pose(np.eye(3), np.zeros(3), np.eye(6) * 1e-4), Reason.MULTI_LAMP)
    observation = _observation()
    certain = [(observation, _lamp(1)), (observation, _lamp(2))]
    lamp = OpenLamp(observation, (_lamp(3), _lamp(4)), (0.5, 0.5))
    assert settle(certain, [lamp], lambda pairs: anywhere) == []
    assert [lamp.id for _, lamp in settle(certain, [OpenLamp(observation, (_lamp(3),), (1.0,))],
                                          lambda pairs: anywhere)] == [3]


def test_without_a_certain_pose_an_assignment_counts_only_if_the_right_one_was_tried() -> None:
    observation = _observation()

    def fits_three(pairs) -> Choice:
        # The certain lamps alone give no pose; with lamp 3 in the open lamp's place, one.
        if any(lamp.id == 3 for _, lamp in pairs):
            return Choice(Pose(np.eye(3), np.zeros(3)), Reason.MULTI_LAMP)
        return Choice(None, Reason.AMBIGUOUS)

    certain = [(observation, _lamp(1)), (observation, _lamp(2)), (observation, _lamp(5))]
    covered = OpenLamp(observation, (_lamp(3), _lamp(4)), (0.5, 0.5))
    assert [lamp.id for _, lamp in settle(certain, [covered], fits_three)] == [3]
    # A reading that leaves 1 % to candidates not tried: the right one may be among those.
    assert settle(certain, [replace(covered, posterior=(0.5, 0.49))], fits_three) == []


def test_where_the_grid_explains_every_lamp_read_as_its_neighbour_the_readings_decide() -> None:
    # A regular grid whose IDs run along it: moved by one spacing, a pose explains the lamps read each as
    # its neighbour as well as the right assignment (tone stills: 3 lamps at 0.996-0.999 each, their
    # neighbours holding the rest).
    observation = _observation()
    right, shifted = (3, 5, 7, 9), (2, 4, 6, 8)

    def fits_right_or_shifted(pairs) -> Choice:
        explained = tuple(lamp.id for _, lamp in pairs) in (right, shifted)
        return Choice(Pose(np.eye(3), np.zeros(3)) if explained else None, Reason.MULTI_LAMP)

    def read(p_right: float) -> list[OpenLamp]:
        return [OpenLamp(observation, (_lamp(r), _lamp(s)), (p_right, 1.0 - p_right)) for r, s in zip(right, shifted)]

    assert [lamp.id for _, lamp in settle([], read(0.999), fits_right_or_shifted)] == list(right)
    # Readings that lean less (0.7 each: the shifted assignment holds 3 % of the two) leave every lamp open.
    assert settle([], read(0.7), fits_right_or_shifted) == []


def test_more_open_lamps_than_assignments_can_be_tried_are_settled_by_the_most_certain_ones_pose() -> None:
    # Five open tone lamps of three candidates each: 243 assignments. The three most certain are settled
    # by assignment, the other two against their pose.
    observation = _observation()
    right = (3, 5, 7, 9, 11)
    anchor_pose = Pose(np.eye(3), np.zeros(3), np.eye(6) * 1e-4)

    def fits_right(pairs) -> Choice:
        explained = all(lamp.id == r for (_, lamp), r in zip(pairs, right))
        return Choice(anchor_pose if explained else None, Reason.MULTI_LAMP)

    def disc(lamp_id: int) -> Lamp:
        # Discs: three point lamps alone would explain any assignment.
        return replace(_lamp(lamp_id), radius=0.075)

    lamps = [OpenLamp(observation, (disc(r), disc(r - 1), disc(r + 1)), (p, 0.6 * (1.0 - p), 0.4 * (1.0 - p)))
             for r, p in zip(right, (0.999, 0.9985, 0.998, 0.9975, 0.997))]
    assert [lamp.id for _, lamp in settle([], lamps, fits_right)] == list(right)


def test_against_the_certain_pose_only_candidates_it_can_see_where_the_lamp_is_are_solved() -> None:
    # The certain lamps' pose sees lamp 3 where the open lamp is; lamp 4, half a metre on, 2.5 m up, lies
    # over a hundred pixels off a lamp a few pixels wide: no joint pose near the certain one explains it.
    camera = bare_led_scenario('1080p', photos=1, seed=1).camera
    anchor_pose = Pose(np.eye(3), np.zeros(3), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))
    seen_at = camera.project(anchor_pose.map_to_camera(_lamp(3).position))[0]
    observation = _observation()
    observation = replace(observation, ellipse=np.array([*seen_at, *observation.ellipse[2:]]))
    asked = []

    def anywhere(pairs) -> Choice:
        asked.extend(lamp.id for _, lamp in pairs[2:])
        return Choice(anchor_pose, Reason.MULTI_LAMP)

    certain = [(observation, _lamp(1)), (observation, _lamp(2))]
    lamp = OpenLamp(observation, (_lamp(3), _lamp(4)), (0.5, 0.5))
    assert [lamp.id for _, lamp in settle(certain, [lamp], anywhere, camera)] == [3]
    assert asked == [3]
    # Without the camera both are solved, and a pose that explains anything leaves the lamp open.
    assert settle(certain, [lamp], anywhere) == []


def test_open_lamps_each_with_one_candidate_in_reach_are_settled_by_one_solve_of_them_all() -> None:
    # The certain lamps' pose sees lamp 3 where one open lamp is and lamp 4 where the other is; each
    # lamp's other candidate lies over a hundred pixels off. One pose near the certain one that explains
    # both settles both; where none does, each is tried on its own.
    camera = bare_led_scenario('1080p', photos=1, seed=1).camera
    anchor_pose = Pose(np.eye(3), np.zeros(3), np.diag([1e-6, 1e-6, 1e-6, 1e-8, 1e-8, 1e-8]))
    observation = _observation()

    def seen_as(lamp_id: int) -> LampObservation:
        seen_at = camera.project(anchor_pose.map_to_camera(_lamp(lamp_id).position))[0]
        return replace(observation, ellipse=np.array([*seen_at, *observation.ellipse[2:]]))

    certain = [(observation, _lamp(1)), (observation, _lamp(2))]
    lamps = [OpenLamp(seen_as(3), (_lamp(3), _lamp(4)), (0.9, 0.1)),
             OpenLamp(seen_as(4), (_lamp(4), _lamp(3)), (0.8, 0.2))]
    asked = []

    def anywhere(pairs) -> Choice:
        asked.append([lamp.id for _, lamp in pairs[2:]])
        return Choice(anchor_pose, Reason.MULTI_LAMP)

    assert [lamp.id for _, lamp in settle(certain, lamps, anywhere, camera)] == [3, 4]
    # The first solve is the certain lamps' own.
    assert asked == [[], [3, 4]]
    asked.clear()

    def without_four(pairs) -> Choice:
        asked.append([lamp.id for _, lamp in pairs[2:]])
        return Choice(None if any(lamp.id == 4 for _, lamp in pairs) else anchor_pose, Reason.MULTI_LAMP)

    assert [lamp.id for _, lamp in settle(certain, lamps, without_four, camera)] == [3]
    assert asked == [[], [3, 4], [3], [3, 4]]


def test_without_a_certain_pose_assignments_too_improbable_to_change_the_outcome_are_not_solved() -> None:
    observation = _observation()
    right = (3, 5, 7)
    asked = []

    def fits_right(pairs) -> Choice:
        asked.append(tuple(lamp.id for _, lamp in pairs))
        return Choice(Pose(np.eye(3), np.zeros(3)) if asked[-1] == right else None, Reason.MULTI_LAMP)

    def read(p_right: float) -> list[OpenLamp]:
        # Discs: three point lamps alone would explain any assignment.
        return [OpenLamp(observation, (replace(_lamp(r), radius=0.075), replace(_lamp(r + 1), radius=0.075)),
                         (p_right, 1.0 - p_right)) for r in right]

    # The right assignment holds all but 3e-6 of the posterior: no other can outweigh it.
    assert [lamp.id for _, lamp in settle([], read(1.0 - 1e-6), fits_right)] == list(right)
    assert asked == [right]
    asked.clear()
    # Read at 0.99 each, the others hold 3 %: all are solved but the least probable (1e-6 of the posterior).
    assert [lamp.id for _, lamp in settle([], read(0.99), fits_right)] == list(right)
    assert len(asked) == 2 ** len(right) - 1 and (4, 6, 8) not in asked
