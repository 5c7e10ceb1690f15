"""
IDs settled by continuity: a lamp whose beacon is not yet certain, seen where only one lamp of the map can be.

A lamp that comes into view after a gap (or as the last one leaves) holds less than a packet in
its first frames, so the beacon alone needs several of them. The recent pose of the camera and the
distance it may have moved since (``DisambiguationHints.recent_gate``) bound where the camera is:
each lamp of the map that could be the one seen gives a pose, and a lamp whose pose lies outside
that gate cannot be it. When exactly one lamp of the map is left, that lamp is the one seen if the
beacon's evidence so far (the tracker's, over the frames of this lamp) leans to it: it is the most
probable ID of all, it holds at least ``BEACON_SHARE`` of the posterior the geometry leaves (that
lamp, or an ID not in the map), and the data alone (every ID equally likely a priori) give it at
least ``DATA_SHARE`` of what is left, so that it is the beacon, not the map's prior, that narrows
the lamp down to a few IDs. A lamp without beacon evidence (an unmodulated one) is never taken for
the mapped lamp it stands near, nor is one whose beacon names another lamp of the map.

Only disc lamps are tried: the ring test below needs the distance a rim gives.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from vlp_ros.beacon.reading import BeaconReading, has_evidence
from vlp_ros.core.lamp_map import Lamp, LampMap
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import Choice, Reason

# The settled lamp's share of the beacon posterior left once the geometry has excluded the other
# mapped lamps: the beacon must clearly lean to it (one frame of 0.8 packet gives it ~0.97).
BEACON_SHARE = 0.9
# Its share of the likelihood left, all IDs equal a priori: the data leave it and at most ~7 IDs off the map
# (one frame of 0.8 packet: it and 3, 0.25; no evidence with 8-bit IDs: 1/249).
DATA_SHARE = 1.0 / 8.0
# Slack (relative) of the camera's distance from a lamp, scaled from one lamp to another by their radii.
_DISTANCE_SLACK = 0.05

Pair = tuple[LampObservation, Lamp]
Solver = Callable[[list[Pair]], Choice]


def settled_by_continuity(observation: LampObservation, evidence: BeaconReading, lamps: LampMap,
                          recent: Pose, gate: float, solve: Solver) -> Lamp | None:
    """
    Return the one lamp of ``lamps`` that ``observation`` can be within ``gate`` (m) of the ``recent`` pose.

    Only if the beacon's ``evidence`` leans to it; None otherwise. ``solve`` should remember its
    answers: the most probable lamp's pose is asked for twice.
    """
    if evidence.unknown or not observation.rim_usable or not has_evidence(evidence):
        return None
    log_likelihoods = np.asarray(evidence.log_likelihoods, float)
    posterior = _normalized(log_likelihoods + np.asarray(evidence.log_prior, float))
    if posterior is None:
        return None
    likely = _beacon_choice(evidence, posterior, lamps)
    if likely is None:
        return None
    reference = solve([(observation, likely)])
    if reference.pose is None:
        return None
    distance = float(np.linalg.norm(reference.pose.position - likely.position))
    excluded = np.zeros(len(posterior), bool)
    for k, (candidate, mapped) in enumerate(zip(evidence.candidates, evidence.mapped)):
        lamp = lamps.get(int(candidate)) if mapped else None
        if lamp is not None and not lamp.is_point and lamp is not likely:
            if _fits(observation, lamp, distance * lamp.radius / likely.radius, recent, gate, solve):
                return None  # a second lamp of the map could be there
            excluded[k] = True
    if not _fits(observation, likely, distance, recent, gate, solve):
        return None
    chosen = int(np.flatnonzero(evidence.candidates == likely.id)[0])
    left = ~excluded
    data = _normalized(np.where(left, log_likelihoods, -np.inf))
    return likely if (posterior[chosen] >= BEACON_SHARE * posterior[left].sum()
                      and data is not None and data[chosen] >= DATA_SHARE) else None


def _beacon_choice(evidence: BeaconReading, posterior: np.ndarray, lamps: LampMap) -> Lamp | None:
    """Return the disc lamp of the map that is the beacon's most probable ID (None if that ID is off the map)."""
    best = int(np.argmax(posterior))
    if not evidence.mapped[best]:
        return None
    lamp = lamps.get(int(evidence.candidates[best]))
    return None if lamp is None or lamp.is_point else lamp


def _fits(observation: LampObservation, lamp: Lamp, distance: float, recent: Pose, gate: float,
          solve: Solver) -> bool:
    """
    Whether ``lamp`` seen as ``observation`` can put the camera within ``gate`` of ``recent``.

    Ruled out at once when the camera's ``distance`` from the lamp cannot reach (the triangle
    inequality).
    """
    if abs(float(np.linalg.norm(lamp.position - recent.position)) - distance) > gate + _DISTANCE_SLACK * distance:
        return False
    choice = solve([(observation, lamp)])
    if choice.reason is Reason.AMBIGUOUS:
        return True  # two poses within the gate: the lamp explains the frame, though its pose is not decided
    return choice.pose is not None and choice.pose.position_error(recent) <= gate


def _normalized(log_weights: np.ndarray) -> np.ndarray | None:
    if not np.isfinite(log_weights.max()):
        return None
    weights = np.exp(log_weights - log_weights.max())
    return weights / weights.sum()
