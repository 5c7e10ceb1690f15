"""IDs settled by continuity: a lamp whose beacon is not yet certain, seen where only one lamp of the map
can be.

A lamp that comes into view after a gap (or as the last one leaves) holds less than a packet in
its first frames, so the beacon alone needs several of them. The recent pose of the camera and the
distance it may have moved since (``DisambiguationHints.recent_gate``) bound where the camera is:
each lamp of the map that could be the one seen gives a pose, and a lamp whose pose lies outside
that gate cannot be it. When exactly one lamp of the map is left, and the beacon's evidence so far
(the tracker's, over the frames of this lamp) gives it at least ``BEACON_SHARE`` of what the geometry
leaves possible (that lamp, or an ID not in the map), that lamp is the one seen. The share keeps a
lamp without beacon evidence (an unmodulated one: ``1 / (1 + 0.01 x the IDs not in the map)`` = 0.29
for 8-bit IDs) from being taken for the mapped lamp it stands near.

Only disc lamps are tried: the ring test below needs the distance a rim gives.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from vlp_ros.beacon.reading import BeaconReading
from vlp_ros.lamp_map import Lamp, LampMap
from vlp_ros.observation import LampObservation
from vlp_ros.pose import Pose
from vlp_ros.solvers.candidates import Choice, Reason

# The settled lamp's share of the beacon posterior left once the geometry has excluded the other
# mapped lamps: the beacon must clearly lean to it (one frame of 0.8 packet gives it ~0.97).
BEACON_SHARE = 0.9
# Slack (relative) of the camera's distance from a lamp, scaled from one lamp to another by their radii.
_DISTANCE_SLACK = 0.05

Pair = tuple[LampObservation, Lamp]
Solver = Callable[[list[Pair]], Choice]


def settled_by_continuity(observation: LampObservation, evidence: BeaconReading, lamps: LampMap,
                          recent: Pose, gate: float, solve: Solver) -> Lamp | None:
    """The one lamp of ``lamps`` that ``observation`` can be within ``gate`` (m) of the ``recent``
    pose, if the beacon's ``evidence`` leans to it; None otherwise. ``solve`` should remember its
    answers: the most probable lamp's pose is asked for twice."""
    if evidence.unknown or not observation.rim_usable:
        return None
    posterior = _posterior(evidence)
    if posterior is None:
        return None
    by_id = {int(c): p for c, p, m in zip(evidence.candidates, posterior, evidence.mapped) if m}
    discs = [lamp for lamp in lamps if not lamp.is_point]
    likely = max(discs, key=lambda lamp: by_id.get(lamp.id, 0.0), default=None)
    if likely is None:
        return None
    reference = solve([(observation, likely)])
    if reference.pose is None:
        return None
    distance = float(np.linalg.norm(reference.pose.position - likely.position))
    fitting, excluded = [], 0.0
    for lamp in discs:
        if _fits(observation, lamp, distance * lamp.radius / likely.radius, recent, gate, solve):
            fitting.append(lamp)
        else:
            excluded += by_id.get(lamp.id, 0.0)
    if len(fitting) != 1:
        return None
    lamp = fitting[0]
    left = 1.0 - excluded
    return lamp if left > 0.0 and by_id.get(lamp.id, 0.0) >= BEACON_SHARE * left else None


def _fits(observation: LampObservation, lamp: Lamp, distance: float, recent: Pose, gate: float,
          solve: Solver) -> bool:
    """Whether ``lamp`` seen as ``observation`` can put the camera within ``gate`` of ``recent``. Ruled
    out at once when the camera's ``distance`` from the lamp cannot reach (the triangle inequality)."""
    if abs(float(np.linalg.norm(lamp.position - recent.position)) - distance) > gate + _DISTANCE_SLACK * distance:
        return False
    choice = solve([(observation, lamp)])
    if choice.reason is Reason.AMBIGUOUS:
        return True  # two poses within the gate: the lamp explains the frame, though its pose is not decided
    return choice.pose is not None and choice.pose.position_error(recent) <= gate


def _posterior(evidence: BeaconReading) -> np.ndarray | None:
    log_post = np.asarray(evidence.log_likelihoods, float) + np.asarray(evidence.log_prior, float)
    if not np.isfinite(log_post.max()):
        return None
    posterior = np.exp(log_post - log_post.max())
    return posterior / posterior.sum()
