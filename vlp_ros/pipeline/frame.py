"""
One frame to one pose: detection, beacon decoding, solving and disambiguation (ROS-free).

This is everything the locator node does between converting an image and
publishing; the evaluation tools call it the same way.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from vlp_ros.beacon.decoding import (BeaconReading, decode_clipped_packet, decode_glow, decode_packet, decode_tone,
                                     read_lamp, RowProfile)
from vlp_ros.beacon.evidence import EvidenceTracker
from vlp_ros.beacon.packet import no_packet
from vlp_ros.beacon.steady import box_shows_no_modulation
from vlp_ros.beacon.tone import agreeing, no_tone, point_light_profile
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp, LampMap
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.detection import detect_lamps
from vlp_ros.detection.detector import SteadyTest
from vlp_ros.detection.point import measured_as_point
from vlp_ros.pipeline.config import LocatorSettings
from vlp_ros.solvers.ambiguity import choose_candidate, DisambiguationHints, UpHint
from vlp_ros.solvers.candidates import Choice, explains_the_image, PoseCandidate, Reason
from vlp_ros.solvers.continuity_ids import settled_by_continuity
from vlp_ros.solvers.fusion import solve_lamps
from vlp_ros.solvers.joint_ids import claimed_once, odd_one_out, open_lamps, settle
from vlp_ros.solvers.paper import solve_lamp_paper
from vlp_ros.solvers.pinhole_view import solver_view

NO_LAMP = 'no_lamp'
NO_ID = 'no_id'
UNKNOWN_ID = 'unknown_id'
STEADY = 'its rows show no modulation: a steady lamp'


@dataclass(frozen=True)
class SeenLamp:
    """A detected lamp and its ID in the map (None: why not, in ``detail``), for showing users."""

    observation: LampObservation
    lamp_id: int | None
    detail: str = ''


@dataclass
class FrameResult:
    """
    ``outcome`` is 'pose' when ``pose`` is set, else why there is none.

    ``seen``: the lamps detected; a pose is solved from those with an ID.
    """

    pose: Pose | None
    outcome: str
    decoded_ids: list[int] = field(default_factory=list)
    unknown_ids: int = 0
    detail: str = ''
    seen: list[SeenLamp] = field(default_factory=list)


def solvable(observation: LampObservation, lamp: Lamp) -> bool:
    """
    Whether the solvers can use ``observation`` of ``lamp``.

    An observation without a usable rim (a bare LED's light) serves only a point lamp, whose
    centre is all the solver needs.
    """
    return observation.rim_usable or lamp.is_point


class Pipeline:
    """Stateful across frames: beacon evidence per tracked lamp, and the last pose for continuity."""

    def __init__(self, settings: LocatorSettings) -> None:
        """Build a pipeline for ``settings``, with no tracked lamps and no recent pose yet."""
        self.settings = settings
        # Per-frame decoding needs these for every lamp: derive them once.
        self._known_ids = settings.lamps.ids
        self._frequencies = settings.lamps.frequencies()
        self._point_lamps = any(lamp.is_point for lamp in settings.lamps)
        self._only_point_lamps = all(lamp.is_point for lamp in settings.lamps)
        self.tracker = EvidenceTracker(known_ids=self._known_ids)
        self._recent: tuple[Pose, float] | None = None
        # Poses published against continuity (decisive evidence outside the recent pose's gate).
        self.track_restarts = 0

    def process(self, image: np.ndarray, camera: CameraModel, stamp: float,
                gravity_up: np.ndarray | None = None) -> FrameResult:
        """Pose of the camera for one bgr8/mono8 frame taken at ``stamp`` (s)."""
        observations, readings, ids = self.identify(image, stamp)
        if not observations:
            return FrameResult(None, NO_LAMP)
        ids, pairs, solved = self._identified_with_geometry(observations, ids, readings, camera, stamp, gravity_up)
        if not pairs:
            ids, pairs = self._identified_by_continuity(observations, ids, camera, stamp, gravity_up, solved)
        seen = [_seen_lamp(obs, i, reading, self.settings.lamps)
                for obs, i, reading in zip(observations, ids, readings)]
        if not pairs:
            return frame_result(None, pairs, readings, seen)
        # Detection and decoding read the raw image; the solvers see lamps through a model they take.
        choice = solved.get(_key(pairs)) or self._solve(*solver_view(pairs, camera), stamp, gravity_up)
        self._continue_track(choice, stamp)
        return frame_result(choice, pairs, readings, seen)

    def identify(self, image: np.ndarray, stamp: float
                 ) -> tuple[list[LampObservation], list[BeaconReading], list[int | None]]:
        """
        Detect the lamps of the frame at ``stamp`` and read their beacons.

        Returns the observations, this frame's readings and each lamp's ID certain so far (None if not yet),
        by the beacon alone: ``process`` then holds the IDs to the map's geometry.
        """
        # A steady lamp (no beacon) whose rim needs its clipped rows is placed at its crossings' centre; the beacon
        # reading asks the same test of every lamp, and of such a lamp with the same box and ellipse.
        steady = steady_test(image)
        observations = detect_lamps(image, steady=steady)
        readings = [self._read_beacon(image, obs, steady) for obs in observations]
        ids = self.tracker.update(observations, readings, stamp) if observations else []
        if self._point_lamps:
            # Once read, a point lamp's light is measured as a point (a map of point lamps only: every light).
            observations = [measured_as_point(image, obs) if self._only_point_lamps or not obs.rim_usable else obs
                            for obs in observations]
        return observations, readings, ids

    def _continue_track(self, choice: Choice, stamp: float) -> None:
        if choice.pose is not None:
            self._recent = (choice.pose, stamp)
            self.track_restarts += choice.restarts_track

    def _identified_with_geometry(self, observations: list[LampObservation], ids: list[int | None],
                                  readings: list[BeaconReading], camera: CameraModel, stamp: float,
                                  gravity_up: np.ndarray | None) -> tuple[list[int | None],
                                                                          list[tuple[LampObservation, Lamp]],
                                                                          dict[tuple, Choice]]:
        """
        Each lamp's ID and the (observation, lamp) pairs to solve from.

        The beacon's certain IDs, held to one pose explaining every lamp, and lamps its readings leave
        open that such a pose identifies (``solvers.joint_ids``); and the choices solved on the way, by
        ``_key`` of their pairs.
        """
        lamps = self.settings.lamps

        def pairs_of(lamp_ids: list[int | None]) -> list[tuple[LampObservation, Lamp]]:
            return identified_pairs(observations, lamp_ids, lamps)

        solved: dict[tuple, Choice] = {}
        if self.settings.solver != 'perspective' or len(observations) < 2:
            return ids, pairs_of(ids), solved

        def solve(tried: list[tuple[LampObservation, Lamp]]) -> Choice:
            key = _key(tried)
            if key not in solved:
                solved[key] = self._solve(*solver_view(tried, camera), stamp, gravity_up)
            return solved[key]

        ids = claimed_once(ids)
        certain = pairs_of(ids)
        odd = odd_one_out(certain, solve)
        if odd is not None:
            ids = [None if obs is certain[odd][0] else i for obs, i in zip(observations, ids)]
            certain = pairs_of(ids)
        settled = settle(certain, open_lamps(observations, ids, readings, lamps, solvable), solve, camera)
        by_observation = {id(obs): lamp.id for obs, lamp in settled}
        ids = [by_observation.get(id(obs), i) for obs, i in zip(observations, ids)]
        return ids, certain + settled, solved

    def _identified_by_continuity(self, observations: list[LampObservation], ids: list[int | None],
                                  camera: CameraModel, stamp: float, gravity_up: np.ndarray | None,
                                  solved: dict[tuple, Choice]
                                  ) -> tuple[list[int | None], list[tuple[LampObservation, Lamp]]]:
        """
        When no lamp is identified otherwise.

        The lamps that only one lamp of the map can be, this close to the recent pose
        (``solvers.continuity_ids``), as IDs and pairs to solve from.
        """
        hints = self._hints(stamp, gravity_up)
        if self.settings.solver != 'perspective' or not hints.continuity_counts:
            return ids, []

        def solve(tried: list[tuple[LampObservation, Lamp]]) -> Choice:
            key = _key(tried)
            if key not in solved:
                solved[key] = self._solve(*solver_view(tried, camera), stamp, gravity_up)
            return solved[key]

        settled = [settled_by_continuity(obs, evidence, self.settings.lamps, hints.recent_pose,
                                         hints.recent_gate(), solve)
                   for obs, evidence in zip(observations, self.tracker.evidence)]
        ids = [lamp.id if lamp is not None else i for lamp, i in zip(settled, ids)]
        return ids, [(obs, lamp) for obs, lamp in zip(observations, settled) if lamp is not None]

    def _read_beacon(self, image: np.ndarray, observation: LampObservation, steady: SteadyTest) -> BeaconReading:
        beacon = self.settings.beacon
        if steady(observation.bbox, observation.ellipse):
            # A steady lamp (not in the map) still counts as a lamp in view; only its reading is spared.
            if beacon.mode == 'tone':
                return no_tone(self._frequencies, STEADY)
            return no_packet(beacon.id_bits, self._known_ids, STEADY)
        if beacon.mode == 'tone':
            def decode(profile: RowProfile) -> BeaconReading:
                return decode_tone(profile, beacon.row_time, self._frequencies, beacon.frequency_tolerance,
                                   exposure=beacon.exposure, row_time_tolerance=beacon.row_time_tolerance)
            if not observation.rim_usable:
                # A bare LED's core spans a few stripe periods; its glow carries them on every row it lights.
                return decode(point_light_profile(image, observation))
            disc = read_lamp(image, observation, decode, glow=False)
            if not self._point_lamps:
                return disc
            # A bare LED's round core passes for a disc, whose few rows may read its tone wrongly (a clipped
            # 3.5 kHz core as JPEG once read 2 kHz): its glow is read too, and must agree.
            return agreeing(decode(point_light_profile(image, observation)), disc)
        # Packet decoding is benchmarked without the exposure (docs/beacon.md): it is not passed.
        return read_lamp(image, observation, lambda profile: decode_packet(
            profile, beacon.chip_rate, beacon.row_time, beacon.id_bits, self._known_ids),
            decode_glow=lambda profile: decode_glow(profile, beacon.chip_rate, beacon.row_time, beacon.id_bits,
                                                    self._known_ids),
            decode_clipped=lambda profile: decode_clipped_packet(profile, beacon.chip_rate, beacon.row_time,
                                                                 beacon.id_bits, self._known_ids))

    def _hints(self, stamp: float, gravity_up: np.ndarray | None) -> DisambiguationHints:
        return disambiguation_hints(self.settings, self._recent, stamp, gravity_up)

    def _solve(self, pairs: list[tuple[LampObservation, Lamp]], camera: CameraModel, stamp: float,
               gravity_up: np.ndarray | None) -> Choice:
        if self.settings.solver == 'paper':
            try:
                candidates = paper_candidates(pairs, camera)
            except ValueError as err:
                return Choice(None, Reason.NO_CANDIDATES, str(err))
            # Weak perspective is an approximation: a pose it cannot reconcile with the
            # image under the exact projection is decimetres off and must not be published.
            candidates = [c for c in candidates if explains_the_image(c)]
            if not candidates:
                return Choice(None, Reason.POOR_FIT, "the paper's pose does not explain the image")
            # The paper's two mirror solutions are told apart by the same hints as ours.
            return choose_candidate(candidates, self._hints(stamp, gravity_up))
        return solve_lamps(pairs, camera, self._hints(stamp, gravity_up), self.settings.floor)


def identified_pairs(observations: list[LampObservation], ids: list[int | None],
                     lamps: LampMap) -> list[tuple[LampObservation, Lamp]]:
    """Return the (observation, lamp) pairs of the lamps identified as ``ids`` that the solvers can use."""
    return [(obs, lamps.get(i)) for obs, i in zip(observations, ids)
            if i is not None and i in lamps and solvable(obs, lamps.get(i))]


def frame_result(choice: Choice | None, pairs: list[tuple[LampObservation, Lamp]], readings: list[BeaconReading],
                 seen: list[SeenLamp]) -> FrameResult:
    """Return the result of a frame whose lamps were read as ``readings``: ``choice`` solved from ``pairs``, if any."""
    unknown = sum(r.unknown for r in readings)
    decoded = [lamp.id for _, lamp in pairs]
    if choice is None:
        return FrameResult(None, UNKNOWN_ID if unknown else NO_ID, decoded, unknown, seen=seen)
    if choice.pose is None:
        return FrameResult(None, choice.reason.value, decoded, unknown, choice.detail, seen)
    return FrameResult(choice.pose, 'pose', decoded, unknown, choice.reason.value, seen)


def disambiguation_hints(settings: LocatorSettings, recent: tuple[Pose, float] | None, stamp: float,
                         gravity_up: np.ndarray | None) -> DisambiguationHints:
    """Return what tells a frame's candidate poses apart: the prior, gravity and the ``recent`` (pose, stamp)."""
    s = settings
    up = []
    if s.prior_up is not None:
        up.append(UpHint(s.prior_up, s.prior_tolerance, s.prior_sigma))
    if gravity_up is not None:
        up.append(UpHint(gravity_up, s.imu_tolerance, s.imu_sigma))
    pose, age = None, 0.0
    # A pose vouches only for later frames (stamps may arrive out of order), and never when max_age is 0.
    if recent is not None and s.continuity_max_age > 0.0 and 0.0 <= stamp - recent[1]:
        pose, age = recent[0], stamp - recent[1]
    return DisambiguationHints(up_in_camera=up, recent_pose=pose, recent_gate_m=s.continuity_gate,
                               recent_age=age, recent_max_age=s.continuity_max_age,
                               recent_max_speed=s.continuity_max_speed)


def paper_candidates(pairs: Iterable[tuple[LampObservation, Lamp]], camera: CameraModel) -> list[PoseCandidate]:
    """
    Return the paper's two poses from the largest disc lamp of ``pairs`` (as the solvers see it).

    Raises ValueError when the paper's method has none: no disc lamp, or one without a usable marker.
    """
    discs = [pair for pair in pairs if not pair[1].is_point]
    if not discs:
        raise ValueError("the paper's solver needs a disc lamp; all are point lamps")
    observation, lamp = max(discs, key=lambda pair: pair[0].ellipse[2])
    return solve_lamp_paper(observation, lamp, camera)


def steady_test(image: np.ndarray) -> SteadyTest:
    """
    Return ``detect_lamps``' test of whether a lamp of ``image`` (its box and ellipse) shows no modulation.

    Each box and ellipse is tested once: the answers are kept for the frame.
    """
    answers: dict[tuple, bool] = {}

    def test(bbox: tuple[int, int, int, int], ellipse: np.ndarray) -> bool:
        key = (tuple(bbox), np.asarray(ellipse, dtype=float).tobytes())
        if key not in answers:
            answers[key] = box_shows_no_modulation(image, bbox, ellipse)
        return answers[key]
    return test


def _key(pairs: list[tuple[LampObservation, Lamp]]) -> tuple:
    """Which lamps, seen where, a solve was given."""
    return tuple((id(observation), lamp.id) for observation, lamp in pairs)


def _seen_lamp(observation: LampObservation, lamp_id: int | None, reading: BeaconReading, lamps: LampMap) -> SeenLamp:
    if lamp_id is not None and lamp_id in lamps:
        return SeenLamp(observation, lamp_id)
    if reading.unknown:
        return SeenLamp(observation, None, 'ID not in the map')
    return SeenLamp(observation, None, reading.detail or 'ID not certain yet')
