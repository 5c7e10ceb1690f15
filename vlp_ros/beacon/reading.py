"""What decoding one lamp yields: evidence over candidate IDs, and a decision that prefers None to a guess."""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np


# Candidate standing for "a frequency that no lamp of the map has" (tone mode).
UNMAPPED = -1
# Prior weight of one ID that is not in the map relative to one that is: the map
# is trusted, but a lamp it does not list must still be possible.
UNMAPPED_WEIGHT = 0.01
MIN_CONFIDENCE = 0.9999


@dataclass(frozen=True)
class BeaconReading:
    """
    One lamp in one frame.

    ``candidates`` are the IDs the data were weighed against (``UNMAPPED`` for "none
    of the map's lamps"), ``log_likelihoods`` the evidence for each (any additive
    constant), ``log_prior`` their prior (any additive constant) and ``mapped``
    which of them the map holds. Evidence from independent frames of one lamp adds.
    ``lamp_id`` is set only when a mapped candidate reaches the decoder's confidence;
    ``unknown`` when the lamp surely carries an ID that is not in the map.
    ``detail`` says why there is no ID.
    """

    lamp_id: int | None
    confidence: float
    candidates: np.ndarray
    log_likelihoods: np.ndarray
    log_prior: np.ndarray
    mapped: np.ndarray
    unknown: bool = False
    detail: str = ''

    def __post_init__(self) -> None:
        n = len(self.candidates)
        if not len(self.log_likelihoods) == len(self.log_prior) == len(self.mapped) == n:
            raise ValueError('candidates, log_likelihoods, log_prior and mapped must have the same length')


@dataclass(frozen=True)
class Decision:
    lamp_id: int | None
    confidence: float
    unknown: bool
    detail: str


def log_prior(mapped: np.ndarray, unmapped_weight: float) -> np.ndarray:
    """Equal prior over mapped candidates, ``unmapped_weight`` times less for each other one."""
    if not unmapped_weight >= 0.0:
        raise ValueError(f'unmapped_weight must not be negative, got {unmapped_weight}')
    with np.errstate(divide='ignore'):
        return np.where(mapped, 0.0, np.log(unmapped_weight))


def decide(candidates: np.ndarray, mapped: np.ndarray, log_likelihoods: np.ndarray,
           log_prior: np.ndarray, min_confidence: float) -> Decision:
    """Return the most probable candidate if it is mapped and its posterior reaches ``min_confidence``."""
    if not 0.0 < min_confidence < 1.0:
        raise ValueError(f'min_confidence must lie in (0, 1), got {min_confidence}')
    best, confidence = _most_probable(np.asarray(log_likelihoods, dtype=float), np.asarray(log_prior, dtype=float))
    if best < 0:
        return Decision(None, 0.0, False, 'no candidate is possible')
    if confidence < min_confidence:
        return Decision(None, confidence, False, f'not certain (best candidate {candidates[best]} at {confidence:.4g})')
    if not mapped[best]:
        what = 'a frequency' if candidates[best] == UNMAPPED else f'ID {candidates[best]}'
        return Decision(None, confidence, True, f'lamp carries {what} that is not in the map')
    return Decision(int(candidates[best]), confidence, False, '')


def reading(candidates: np.ndarray, mapped: np.ndarray, log_likelihoods: np.ndarray,
            log_prior: np.ndarray, min_confidence: float) -> BeaconReading:
    """Return a reading with its decision made."""
    d = decide(candidates, mapped, log_likelihoods, log_prior, min_confidence)
    return BeaconReading(d.lamp_id, d.confidence, candidates, log_likelihoods, log_prior, mapped,
                         d.unknown, d.detail)


def has_evidence(reading: BeaconReading) -> bool:
    """Whether ``reading`` weighs its candidates at all (a reading without evidence adds nothing)."""
    return bool(np.any(reading.log_likelihoods != reading.log_likelihoods[0]))


def no_evidence(candidates: np.ndarray, mapped: np.ndarray, log_prior: np.ndarray, detail: str) -> BeaconReading:
    """Return a reading that adds nothing (flat likelihood), with why."""
    return BeaconReading(None, 0.0, candidates, np.zeros(len(candidates)), log_prior, mapped, False, detail)


def _most_probable(log_likelihoods: np.ndarray, log_prior: np.ndarray) -> tuple[int, float]:
    """Return the most probable candidate and its posterior probability; -1 if none has a finite posterior."""
    log_post = log_likelihoods + log_prior
    if log_post.size == 0:
        return -1, 0.0
    best = int(np.argmax(log_post))
    if np.isnan(log_post).any() or not math.isfinite(log_post[best]):
        return -1, 0.0
    return best, 1.0 / float(np.exp(log_post - log_post[best]).sum())
