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

    ``frame`` indexes the survey's frames; ``candidates`` are cheapest first, their covariance the fit's
    own (the measurement noise); ``model_errors`` what each candidate's covariance grows by when the rim's
    smooth model-error patterns are allowed for (``solvers.covariance.allow_for_model_error``), positive
    semi-definite, zero where the fit allowed none.
    """

    frame: int
    lamp_id: int
    candidates: tuple[Pose, ...]
    model_errors: tuple[np.ndarray, ...] = ()

    def measured(self, k: int, model_share: float) -> Pose:
        """Return candidate ``k`` with its fit's covariance plus ``model_share`` of its model error."""
        candidate = self.candidates[k]
        if not self.model_errors or model_share == 0.0:
            return candidate
        return Pose(candidate.rotation, candidate.position, candidate.covariance + model_share * self.model_errors[k])


@dataclass
class FrameSightings:
    """Every usable lamp of one frame, and what else was seen there."""

    stamp_ns: int
    sightings: list[Sighting] = field(default_factory=list)
    # Lamps the beacon read with certainty as IDs that the map does not list.
    unlisted_ids: list[int] = field(default_factory=list)


def lamp_frame_lamp(lamp: Lamp) -> Lamp:
    """Return ``lamp`` as seen in its own frame: at the origin, its marker along +x."""
    return replace(lamp, position=np.zeros(3), marker_angle=0.0, position_sigma=None)


def sighting(frame: int, observation: LampObservation, lamp: Lamp, camera: CameraModel) -> Sighting | None:
    """Return the sighting of ``lamp`` in ``frame``, solved in the lamp's frame; None without a rim and a marker."""
    if lamp.is_point or not observation.rim_usable or observation.marker is None or not lamp.marker_distance > 0.0:
        return None
    [(seen, local)], view = solver_view([(observation, lamp_frame_lamp(lamp))], camera)
    try:
        candidates = [c for c in solve_lamp(seen, local, view) if c.pose.covariance is not None]
    except ValueError:
        return None
    if not candidates:
        return None
    poses = tuple(Pose(c.pose.rotation, c.pose.position, c.separating_covariance) for c in candidates)
    return Sighting(frame, lamp.id, poses, tuple(_semi_definite(c.pose.covariance - c.separating_covariance)
                                                 for c in candidates))


def _semi_definite(matrix: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(0.5 * (matrix + matrix.T))
    return (vectors * np.maximum(values, 0.0)) @ vectors.T


def frame_sightings(pipeline: Pipeline, index: int, image: np.ndarray, camera: CameraModel,
                    stamp_ns: int) -> FrameSightings:
    """Identify the lamps of one frame with ``pipeline`` and solve each identified one in its lamp frame."""
    observations, _, ids = pipeline.identify(image, stamp_ns * 1e-9)
    lamps = pipeline.settings.lamps
    result = FrameSightings(stamp_ns)
    for observation, lamp_id, evidence in zip(observations, ids, pipeline.tracker.evidence):
        if lamp_id is None:
            unlisted = _unlisted_id(evidence)
            if unlisted is not None:
                result.unlisted_ids.append(unlisted)
            continue
        seen = sighting(index, observation, lamps.get(lamp_id), camera)
        if seen is not None:
            result.sightings.append(seen)
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
