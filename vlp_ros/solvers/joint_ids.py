"""IDs settled jointly with the geometry: a lamp whose beacon reading is uncertain on its own (a tone
between two bands, a frequency a row time off by 2 % leaves open) gets an ID only when one pose
explains every lamp with it.

The lamps identified with certainty give a pose first. Each open lamp is then tried as every
candidate its reading leaves plausible: a candidate counts only if the joint pose with it still
explains the image and coincides with the certain lamps' pose within their covariance, and the
lamp is identified only if exactly one candidate does (two lamps cannot stand at one place of the
ceiling, so a second candidate that fits is a map or geometry that cannot tell them apart). When
the certain lamps give no pose (too few of them), every assignment of the open lamps' candidates is
solved, and one is taken only if it is the only one that explains the image with residuals to
spare (at least two more than the pose needs: three point lamps alone explain any assignment
exactly), and only when the candidates tried hold all but 1e-4 of each open lamp's posterior:
the pose is then the assignment's own, and on a symmetric map a wrong assignment is explained
by a pose turned about the lamps as well as the right one is (a disc without its marker leaves
the yaw free), so the right one must be among those tried for the count to mean anything.

Certain IDs are held to the same rule. Two lamps that claim one ID (a lamp not in the map whose
tone, 2 % off, lies in a mapped lamp's band) are both reopened, and so is the one lamp without
which the others are explained when no pose explains them all, so that the geometry decides which
of them, if any, is that lamp.
"""
from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2

from vlp_ros.beacon.reading import BeaconReading
from vlp_ros.lamp_map import Lamp, LampMap
from vlp_ros.observation import LampObservation
from vlp_ros.solvers.candidates import Choice, Reason

# A candidate whose posterior (the reading alone) is below this is not tried.
PLAUSIBLE = 1e-3
# At most this many candidates per open lamp, and assignments tried when no certain pose exists.
_MAX_CANDIDATES = 3
_MAX_ASSIGNMENTS = 27
# The joint pose with a settled lamp must lie within this squared Mahalanobis distance (under the
# certain lamps' covariance) of their pose: chi-square(6) at 1 - 1e-4.
_SAME_POSE = float(chi2.ppf(1.0 - 1e-4, 6))
# Without a pose from the certain lamps, the candidates tried must hold this much of each open lamp's posterior.
_COVERED = 1.0 - 1e-4
# Residuals beyond the six a pose takes, so that a wrong assignment can fail to be explained.
_SPARE_RESIDUALS = 2

Pair = tuple[LampObservation, Lamp]
Solver = Callable[[list[Pair]], Choice]


@dataclass(frozen=True)
class OpenLamp:
    """A detected lamp without a certain ID and the lamps of the map its reading leaves plausible."""

    observation: LampObservation
    candidates: tuple[Lamp, ...]
    coverage: float


def claimed_once(ids: list[int | None]) -> list[int | None]:
    """``ids`` with every ID that two lamps claim taken from both."""
    counts = Counter(i for i in ids if i is not None)
    return [i if i is not None and counts[i] == 1 else None for i in ids]


def open_lamps(observations: list[LampObservation], ids: list[int | None], readings: list[BeaconReading],
               lamps: LampMap, usable: Callable[[LampObservation, Lamp], bool]) -> list[OpenLamp]:
    """The lamps without an ID whose reading weighs mapped candidates (a surely unmapped one has
    none), each with its plausible candidates not taken by a certain lamp, most probable first."""
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
                 if reading.mapped[k] and posterior[k] >= PLAUSIBLE and int(reading.candidates[k]) not in taken
                 and int(reading.candidates[k]) in lamps
                 and usable(observation, lamps.get(int(reading.candidates[k])))][:_MAX_CANDIDATES]
        if order:
            found.append(OpenLamp(observation, tuple(lamps.get(int(reading.candidates[k])) for k in order),
                                  float(posterior[order].sum())))
    return found


def odd_one_out(certain: list[Pair], solve: Solver) -> int | None:
    """The one certain lamp (index) without which a pose explains the others with residuals to spare,
    when no pose explains them all; None when they are explained, or when no single lamp (or more than
    one) is the odd one."""
    if len(certain) < 2 or _residuals(certain) < 6 + _SPARE_RESIDUALS + 2 or solve(certain).reason \
            is not Reason.INCONSISTENT_LAMPS:
        return None
    explained = [k for k in range(len(certain)) if solve(certain[:k] + certain[k + 1:]).pose is not None]
    return explained[0] if len(explained) == 1 else None


def settle(certain: list[Pair], lamps: list[OpenLamp], solve: Solver) -> list[Pair]:
    """The open lamps that one pose explains with exactly one of their candidates, as pairs."""
    if not lamps:
        return []
    anchor = solve(certain) if certain else None
    if anchor is not None and anchor.pose is not None and anchor.pose.covariance is not None:
        return _settled_by_pose(certain, lamps, solve, anchor)
    return _settled_by_assignment(certain, lamps, solve)


def _settled_by_pose(certain: list[Pair], lamps: list[OpenLamp], solve: Solver, anchor: Choice) -> list[Pair]:
    settled: list[Pair] = []
    for open_lamp in lamps:
        used = {lamp.id for _, lamp in settled}
        fitting = [lamp for lamp in open_lamp.candidates if lamp.id not in used
                   and _explained_near(solve([*certain, *settled, (open_lamp.observation, lamp)]), anchor)]
        if len(fitting) == 1:
            settled.append((open_lamp.observation, fitting[0]))
    return settled


def _explained_near(choice: Choice, anchor: Choice) -> bool:
    if choice.pose is None:
        return False
    error = choice.pose.error_vector(anchor.pose)
    return float(error @ np.linalg.solve(anchor.pose.covariance, error)) <= _SAME_POSE


def _settled_by_assignment(certain: list[Pair], lamps: list[OpenLamp], solve: Solver) -> list[Pair]:
    options = [[(o.observation, lamp) for lamp in o.candidates] for o in lamps]
    if np.prod([len(o) for o in options]) > _MAX_ASSIGNMENTS or min(o.coverage for o in lamps) < _COVERED:
        return []
    explaining = []
    for assignment in itertools.product(*options):
        pairs = [*certain, *assignment]
        if len({lamp.id for _, lamp in pairs}) < len(pairs) or _residuals(pairs) < 6 + _SPARE_RESIDUALS:
            continue
        if solve(pairs).pose is not None:
            explaining.append(list(assignment))
            if len(explaining) > 1:
                return []
    return explaining[0] if explaining else []


def _residuals(pairs: list[Pair]) -> int:
    """Residuals the lamps give at the least (a point two; a disc its rim, counted as five)."""
    return sum(2 if lamp.is_point else 5 for _, lamp in pairs)
