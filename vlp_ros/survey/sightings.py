"""
What each frame of a survey recording says about the lamps in view: their IDs and where the camera is relative to each.

The pipeline identifies the lamps (detection and beacon, as in the locator); each identified disc
lamp is then solved on its own in its *lamp frame*: the map turned by the lamp's marker angle and
moved to its centre, i.e. the lamp at the origin with its marker along +x. That relative pose of the
camera (one or two candidates: one lamp's rim and marker cannot always tell the tilt's mirror pose)
with its covariance is all a frame contributes to the survey.
"""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np

from vlp_ros.beacon.reading import BeaconReading, UNMAPPED
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.pipeline.frame import Pipeline
from vlp_ros.solvers.perspective import solve_lamp
from vlp_ros.solvers.pinhole_view import solver_view


@dataclass(frozen=True)
class Sighting:
    """
    One lamp in one frame: the camera's pose candidates in the lamp's frame, each with its covariance.

    ``frame`` indexes the survey's frames; ``candidates`` are cheapest first.
    """

    frame: int
    lamp_id: int
    candidates: tuple[Pose, ...]


@dataclass
class FrameSightings:
    """Every usable lamp of one frame, and what else was seen there."""

    stamp_ns: int
    sightings: list[Sighting] = field(default_factory=list)
    # Lamps the beacon read with certainty as IDs that the map does not list.
    unlisted_ids: list[int] = field(default_factory=list)
    lamps_detected: int = 0


def lamp_frame_lamp(lamp: Lamp) -> Lamp:
    """Return ``lamp`` as seen in its own frame: at the origin, its marker along +x."""
    return replace(lamp, position=np.zeros(3), marker_angle=0.0, position_sigma=None)


def relative_candidates(observation: LampObservation, lamp: Lamp, camera: CameraModel) -> tuple[Pose, ...]:
    """Return the camera's pose candidates in ``lamp``'s frame, covariance set; none without a rim and marker."""
    if lamp.is_point or not observation.rim_usable or observation.marker is None or not lamp.marker_distance > 0.0:
        return ()
    [(seen, local)], view = solver_view([(observation, lamp_frame_lamp(lamp))], camera)
    try:
        candidates = solve_lamp(seen, local, view)
    except ValueError:
        return ()
    return tuple(Pose(c.pose.rotation, c.pose.position, c.separating_covariance) for c in candidates
                 if c.pose.covariance is not None)


def frame_sightings(pipeline: Pipeline, index: int, image: np.ndarray, camera: CameraModel,
                    stamp_ns: int) -> FrameSightings:
    """Identify the lamps of one frame with ``pipeline`` and solve each identified one in its lamp frame."""
    observations, _, ids = pipeline.identify(image, stamp_ns * 1e-9)
    lamps = pipeline.settings.lamps
    result = FrameSightings(stamp_ns, lamps_detected=len(observations))
    for observation, lamp_id, evidence in zip(observations, ids, pipeline.tracker.evidence):
        if lamp_id is None:
            unlisted = _unlisted_id(evidence)
            if unlisted is not None:
                result.unlisted_ids.append(unlisted)
            continue
        candidates = relative_candidates(observation, lamps.get(lamp_id), camera)
        if candidates:
            result.sightings.append(Sighting(index, lamp_id, candidates))
    return result


def _unlisted_id(evidence: BeaconReading) -> int | None:
    """Return the ID a lamp surely carries that the map does not list (None: not certain, or a tone off the map)."""
    if not evidence.unknown:
        return None
    best = int(evidence.candidates[np.argmax(evidence.log_likelihoods + evidence.log_prior)])
    return None if best == UNMAPPED else best


def unlisted_counts(frames: list[FrameSightings]) -> Counter:
    """Return how many frames saw each unlisted ID."""
    return Counter(i for frame in frames for i in set(frame.unlisted_ids))
