"""
IDs settled jointly with the geometry.

A lamp whose beacon reading is uncertain on its own (a tone between two bands, a frequency a row
time off by 2 % leaves open) gets an ID only when one pose explains every lamp with it.

The lamps identified with certainty give a pose first. Each open lamp is then tried as every
candidate its reading leaves plausible: a candidate counts only if the joint pose with it still
explains the image and coincides with the certain lamps' pose within their covariance, and the
lamp is identified only if the candidates that do leave all but 1e-4 of their readings' posterior
to one (two lamps cannot stand at one place of the ceiling, so a second candidate that fits is a
map or geometry that cannot tell them apart; then only the reading can). When the certain lamps
give no pose (too few of them), the assignments of the open lamps' candidates are solved (residuals
to spare: at least two more than the pose needs, since three point lamps alone explain any
assignment exactly; with more than 27 assignments, those of the most certain lamps, the others
then settled against their pose), and one is taken only if it holds all but 1e-4 of the posterior (the product
of its lamps' readings: they are independent) of the assignments that explain the image (solved most
probable first, until those left hold too little posterior to change the outcome), and only
when the candidates tried hold all but 1e-4 of each open lamp's posterior: the pose is then the
assignment's own, and on a symmetric map a wrong assignment is explained by a pose turned about the
lamps as well as the right one is (a disc without its marker leaves the yaw free), or moved by one
spacing of a regular grid (each lamp read as its neighbour), so the right one must be among those
tried, and the readings must tell it from the others that fit.

Against the certain lamps' pose, a candidate is solved only if that pose, moved anywhere within the
same Mahalanobis distance, can see it within a few of its radii of the detected lamp: a joint pose
that coincides with the certain one sees any other candidate (another lamp of the map, typically a
metre or more away) where no lamp is, and cannot explain the image, so its solve is spared. Open lamps
that each leave one candidate so are first solved together: a pose near the certain one that explains every
lamp with those IDs settles them all at once (the rule itself, one solve instead of one per lamp), and only
when none does is each solved in turn.

Certain IDs are held to the same rule. Two lamps that claim one ID (a lamp not in the map whose
tone, 2 % off, lies in a mapped lamp's band) are both reopened, and so is the one lamp without
which the others are explained when no pose explains them all, so that the geometry decides which
of them, if any, is that lamp.
"""
from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
import itertools
from typing import TypeVar

import numpy as np
# scipy.special, not scipy.stats: the same chi-square tail without scipy.stats' import time at start.
from scipy.special import chdtri

from vlp_ros.beacon.reading import BeaconReading
from vlp_ros.core.camera import CameraModel
from vlp_ros.core.lamp_map import Lamp, LampMap
from vlp_ros.core.observation import LampObservation
from vlp_ros.core.pose import Pose
from vlp_ros.solvers.candidates import Choice, Reason

# A candidate whose posterior (the reading alone) is below this is not tried, unless needed to cover _COVERED.
PLAUSIBLE = 1e-3
# At most this many candidates per open lamp, and assignments tried when no certain pose exists.
_MAX_CANDIDATES = 3
_MAX_ASSIGNMENTS = 27
# The joint pose with a settled lamp must lie within this squared Mahalanobis distance (under the
# certain lamps' covariance) of their pose: chi-square(6) at 1 - 1e-4.
_SAME_POSE = float(chdtri(6, 1e-4))
# Without a pose from the certain lamps, the candidates tried must hold this much of each open lamp's posterior;
# the candidate (or assignment) taken must hold this much of the posterior of those the geometry explains.
_COVERED = 1.0 - 1e-4
# A candidate seen farther than this many of its radii from the detected lamp's centre (beyond where the pose
# may move) leaves its rim unexplained.
_REACH_RADII = 3.0
# Residuals beyond the six a pose takes, so that a wrong assignment can fail to be explained.
_SPARE_RESIDUALS = 2

Pair = tuple[LampObservation, Lamp]
Solver = Callable[[list[Pair]], Choice]
Option = TypeVar('Option')


@dataclass(frozen=True)
class OpenLamp:
    """
    A detected lamp without a certain ID, with the map's lamps its reading leaves plausible.

    It holds those lamps of the map and their posterior probabilities (the reading alone).
    """

    observation: LampObservation
    candidates: tuple[Lamp, ...]
    posterior: tuple[float, ...]

    @property
    def coverage(self) -> float:
        """Return the share of the reading's posterior that the candidates hold."""
        return float(sum(self.posterior))


def claimed_once(ids: list[int | None]) -> list[int | None]:
    """``ids`` with every ID that two lamps claim taken from both."""
    counts = Counter(i for i in ids if i is not None)
    return [i if i is not None and counts[i] == 1 else None for i in ids]


def open_lamps(observations: list[LampObservation], ids: list[int | None], readings: list[BeaconReading],
               lamps: LampMap, usable: Callable[[LampObservation, Lamp], bool]) -> list[OpenLamp]:
    """
    Return the lamps without an ID whose reading weighs mapped candidates (a surely unmapped one has none).

    Each comes with its plausible candidates not taken by a certain lamp, most probable first.
    """
    taken = {i for i in ids if i is not None}
    found = []
    for observation, lamp_id, reading in zip(observations, ids, readings):
        if lamp_id is not None or reading.unknown:
            continue
        log_post = np.asarray(reading.log_likelihoods, float) + np.asarray(reading.log_prior, float)
        if not np.isfinite(log_post.max()) or np.all(log_post == log_post[0]):
            continue
        posterior = np.exp(log_post - log_post.max())
        posterior /= posterior.sum()
        order = [k for k in np.argsort(-posterior)
                 if reading.mapped[k] and int(reading.candidates[k]) not in taken
                 and int(reading.candidates[k]) in lamps and usable(observation, lamps.get(int(reading.candidates[k])))]
        order = _plausible(order, posterior)
        if order:
            found.append(OpenLamp(observation, tuple(lamps.get(int(reading.candidates[k])) for k in order),
                                  tuple(float(posterior[k]) for k in order)))
    return found


def _plausible(order: list[int], posterior: np.ndarray) -> list[int]:
    """
    Return the plausible candidates, most probable first.

    They are those at ``PLAUSIBLE`` or above, and below it as many as the assignments need to cover
    ``_COVERED`` of the posterior (at most ``_MAX_CANDIDATES`` in all): a lamp read at 0.9989 with its
    two neighbours at 6e-4 and 5e-4 is otherwise never covered.
    """
    kept, covered = [], 0.0
    for k in order[:_MAX_CANDIDATES]:
        if posterior[k] < PLAUSIBLE and covered >= _COVERED:
            break
        kept.append(k)
        covered += float(posterior[k])
    return kept


def odd_one_out(certain: list[Pair], solve: Solver) -> int | None:
    """
    Return the one certain lamp (index) without which a pose explains the others with residuals to spare.

    That is when no pose explains them all; None when they are explained, or when no single lamp (or
    more than one) is the odd one.
    """
    if len(certain) < 2 or _residuals(certain) < 6 + _SPARE_RESIDUALS + 2 or solve(certain).reason \
            is not Reason.INCONSISTENT_LAMPS:
        return None
    explained = [k for k in range(len(certain)) if solve(certain[:k] + certain[k + 1:]).pose is not None]
    return explained[0] if len(explained) == 1 else None


def settle(certain: list[Pair], lamps: list[OpenLamp], solve: Solver, camera: CameraModel | None = None) -> list[Pair]:
    """
    Return the open lamps that one pose explains with exactly one of their candidates, as pairs.

    ``camera`` (that of the observations' pixels), when given, spares the solves of candidates that a pose
    coinciding with the certain lamps' one cannot see where the lamp is.
    """
    if not lamps:
        return []
    anchor = solve(certain) if certain else None
    if _anchors(anchor):
        return _settled_by_pose(certain, lamps, solve, anchor, camera)
    first, rest = _within_budget(lamps)
    settled = _settled_by_assignment(certain, first, solve)
    if not settled or not rest:
        return settled
    anchor = solve([*certain, *settled])
    return settled + _settled_by_pose([*certain, *settled], rest, solve, anchor, camera) if _anchors(anchor) \
        else settled


def _anchors(choice: Choice | None) -> bool:
    return choice is not None and choice.pose is not None and choice.pose.covariance is not None


def _within_budget(lamps: list[OpenLamp]) -> tuple[list[OpenLamp], list[OpenLamp]]:
    """
    Return the most certain open lamps whose assignments number at most ``_MAX_ASSIGNMENTS``, and the others.

    The others are settled against the first ones' pose: five open tone lamps of three candidates each
    are 243 assignments.
    """
    ranked = sorted(lamps, key=lambda o: -max(o.posterior))
    count = 1
    for k, open_lamp in enumerate(ranked):
        count *= len(open_lamp.candidates)
        if count > _MAX_ASSIGNMENTS:
            return ranked[:k], ranked[k:]
    return ranked, []


def _settled_by_pose(certain: list[Pair], lamps: list[OpenLamp], solve: Solver, anchor: Choice,
                     camera: CameraModel | None) -> list[Pair]:
    """
    Return the open lamps settled one after the other against ``anchor``, each with the lamps settled before it.

    When each of several open lamps leaves one candidate within reach, and one pose near the anchor explains
    them all with those candidates, they are settled by that one solve.
    """
    reachable = [[(lamp, p) for lamp, p in zip(open_lamp.candidates, open_lamp.posterior)
                  if camera is None or _within_reach(open_lamp.observation, lamp, anchor.pose, camera)]
                 for open_lamp in lamps]
    alone = [(open_lamp.observation, options[0][0]) for open_lamp, options in zip(lamps, reachable)
             if len(options) == 1]
    if len(alone) == len(lamps) > 1 and len({lamp.id for _, lamp in alone}) == len(alone) \
            and _explained_near(solve([*certain, *alone]), anchor):
        return alone
    settled: list[Pair] = []
    for open_lamp, options in zip(lamps, reachable):
        used = {lamp.id for _, lamp in settled}
        fitting = [(lamp, p) for lamp, p in options if lamp.id not in used
                   and _explained_near(solve([*certain, *settled, (open_lamp.observation, lamp)]), anchor)]
        decided = _decisive(fitting)
        if decided is not None:
            settled.append((open_lamp.observation, decided))
    return settled


def _within_reach(observation: LampObservation, lamp: Lamp, pose: Pose, camera: CameraModel) -> bool:
    """
    Return whether ``pose``, moved within ``_SAME_POSE`` of its covariance, can see ``lamp`` near ``observation``.

    Near: within ``_REACH_RADII`` of the lamp's angular radius (or the detected one's, if larger) of the
    detected centre. A pose within that Mahalanobis distance turns by at most sqrt(_SAME_POSE) times the
    largest rotation sigma and moves by at most as many of the largest position sigma, which turn the
    lamp's ray by that distance over the lamp's.
    """
    point = pose.map_to_camera(lamp.position)[0]
    distance = float(np.linalg.norm(point))
    seen = np.append(camera.normalize(observation.center.reshape(1, 2))[0], 1.0)
    angle = float(np.arccos(np.clip(point @ seen / (distance * np.linalg.norm(seen)), -1.0, 1.0)))
    covariance = pose.covariance
    spread = np.sqrt(np.linalg.eigvalsh(covariance[3:, 3:])[-1]) \
        + np.sqrt(np.linalg.eigvalsh(covariance[:3, :3])[-1]) / distance
    if lamp.position_sigma is not None:
        spread += float(np.max(lamp.position_sigma)) / distance
    size = max(lamp.radius / distance, float(observation.ellipse[2]) / camera.focal)
    return angle <= np.sqrt(_SAME_POSE) * spread + _REACH_RADII * size


def _explained_near(choice: Choice, anchor: Choice) -> bool:
    if choice.pose is None:
        return False
    error = choice.pose.error_vector(anchor.pose)
    return float(error @ np.linalg.solve(anchor.pose.covariance, error)) <= _SAME_POSE


def _settled_by_assignment(certain: list[Pair], lamps: list[OpenLamp], solve: Solver) -> list[Pair]:
    options = [[((o.observation, lamp), p) for lamp, p in zip(o.candidates, o.posterior)] for o in lamps]
    if not options or min(o.coverage for o in lamps) < _COVERED:
        return []
    tried = []
    for assignment in itertools.product(*options):
        pairs = [*certain, *(pair for pair, _ in assignment)]
        if len({lamp.id for _, lamp in pairs}) < len(pairs) or _residuals(pairs) < 6 + _SPARE_RESIDUALS:
            continue
        tried.append((pairs, float(np.prod([p for _, p in assignment]))))
    # Most probable first: the first that explains the image is the one that may be taken, and it is (or is
    # not) once the posterior of those not solved yet cannot change that.
    tried.sort(key=lambda item: -item[1])
    unsolved = np.cumsum([p for _, p in tried][::-1])[::-1]
    taken, explained = None, 0.0
    for (pairs, p), left in zip(tried, unsolved):
        if taken is not None and not _COVERED * explained <= taken[1] < _COVERED * (explained + left):
            break
        if solve(pairs).pose is not None:
            explained += p
            taken = taken or (pairs[len(certain):], p)
    return taken[0] if taken is not None and taken[1] >= _COVERED * explained else []


def _decisive(fitting: list[tuple[Option, float]]) -> Option | None:
    """Return the option (with its posterior) that holds all but 1e-4 of the posterior of ``fitting``, or None."""
    total = sum(p for _, p in fitting)
    best = max(fitting, key=lambda option: option[1], default=None)
    return best[0] if best is not None and best[1] >= _COVERED * total else None


def _residuals(pairs: list[Pair]) -> int:
    """Residuals the lamps give at the least (a point two; a disc its rim, counted as five)."""
    return sum(2 if lamp.is_point else 5 for _, lamp in pairs)
