"""What every pose solver hands back: candidate poses, and the decision among them."""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import numpy as np
# scipy.special, not scipy.stats: the same chi-square tail without scipy.stats' import time at start.
from scipy.special import chdtrc

from vlp_ros.core.pose import Pose
from vlp_ros.solvers.fit_kernels import inverse_form


@dataclass
class PoseCandidate:
    """
    One pose that explains an observation.

    ``cost`` is the chi-square of the fit: the sum of squared residuals, each
    divided by its measurement sigma (so ~ ``residual_count`` - 6 for the right
    pose under the stated noise). Lower explains the image better.
    """

    pose: Pose
    cost: float
    residual_count: int = 0
    # The covariance the measurements give without the rims' model-error prior (None: the pose's):
    # what tells candidates apart, which a covariance widened alike for all of them cannot.
    fit_covariance: np.ndarray | None = None

    @property
    def separating_covariance(self) -> np.ndarray | None:
        """Return the covariance by which this candidate is told apart from others."""
        return self.pose.covariance if self.fit_covariance is None else self.fit_covariance


class Reason(str, Enum):
    """
    Why a pose was, or was not, chosen.

    ``str`` so it logs and serialises as its value.
    """

    UNIQUE = 'unique'                          # a single candidate (or both coincide)
    UP_DIRECTION = 'up_direction'              # decided by a known up direction (prior or IMU)
    CONTINUITY = 'continuity'                  # decided by a recent pose of this camera
    MULTI_LAMP = 'multi_lamp'                  # decided by other lamps in the same frame
    COST = 'cost'                              # one candidate's fit is overwhelmingly better
    AMBIGUOUS = 'ambiguous'                    # nothing tells the candidates apart
    CONFLICTING_HINTS = 'conflicting_hints'    # hints point to different candidates
    NO_CANDIDATE_AGREES = 'no_candidate_agrees'  # every candidate contradicts a hint
    NO_CANDIDATES = 'no_candidates'            # the solver found no pose at all
    INCONSISTENT_LAMPS = 'inconsistent_lamps'  # the lamps of one frame admit no common pose
    POOR_FIT = 'poor_fit'                      # no candidate explains the image within its noise
    OFF_THE_FLOOR = 'off_the_floor'            # every candidate plainly contradicts the floor (planar.*)


@dataclass
class Choice:
    """
    The outcome of disambiguation: ``pose`` is None exactly when no pose may be published.

    ``restarts_track``: the pose was singled out by evidence that outweighs continuity while
    lying outside the recent pose's gate, so it starts a new track.
    """

    pose: Pose | None
    reason: Reason
    detail: str = ''
    restarts_track: bool = False

    @property
    def ok(self) -> bool:
        return self.pose is not None


# Candidates closer than this (squared Mahalanobis distance under the better
# one's covariance, i.e. within one sigma) are the same pose for any purpose:
# picking either costs less than the noise already does.
COINCIDENT_MAHALANOBIS2 = 1.0


def coincide(better: PoseCandidate, other: PoseCandidate) -> bool:
    """
    Tell whether two candidates are the same pose within ``better``'s uncertainty.

    They must be exactly equal when either has no covariance.
    """
    error = other.pose.error_vector(better.pose)
    if better.pose.covariance is None or other.pose.covariance is None:
        return bool(np.all(np.abs(error) < 1e-12))
    return inverse_form(better.separating_covariance, error) <= COINCIDENT_MAHALANOBIS2


def distinct(candidates: list[PoseCandidate]) -> list[PoseCandidate]:
    """Candidates by increasing cost, each kept only if it differs from every cheaper one kept."""
    kept: list[PoseCandidate] = []
    for candidate in sorted(candidates, key=lambda c: c.cost):
        if not any(coincide(k, candidate) for k in kept):
            kept.append(candidate)
    return kept


# A fit is inconsistent with the image when its chi-square is both improbable under the
# stated noise (tail below 1e-6) and over 4x its degrees of freedom, so sigmas that are
# off by up to 2x are tolerated while a misplaced lamp or a wrong model (thousands) is not.
INCONSISTENT_TAIL = 1e-6
INCONSISTENT_REDUCED_CHI2 = 4.0


def explains_the_image(candidate: PoseCandidate) -> bool:
    """Whether the candidate's residuals are what the stated measurement noise allows."""
    dof = candidate.residual_count - 6
    if dof <= 0:
        return True
    return not (candidate.cost > INCONSISTENT_REDUCED_CHI2 * dof and chdtrc(dof, candidate.cost) < INCONSISTENT_TAIL)
