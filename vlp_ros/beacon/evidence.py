"""
Beacon evidence across frames: a lamp too small to read in one frame is read over several.

Each lamp is tracked by its image position: a moving camera carries lamps through
the image by tens of pixels a frame, so each track predicts where its lamp is now
(its last centre moved on at its last velocity) and takes the nearest lamp of a
similar size within a gate that grows with the time since it was seen. The
log-likelihoods of its frames add, since the noise and the packet phase are
independent from frame to frame. A track that is not seen for ``max_gap`` seconds
is dropped. A frame that is itself certain of another
candidate than its track starts the track afresh: two lamps were confused. A frame
stamped as the track's last one (the same frame delivered twice) adds nothing.
"""
from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from vlp_ros.beacon.reading import BeaconReading, decide, Decision, MIN_CONFIDENCE
from vlp_ros.core.observation import LampObservation


# Largest ratio between the sizes of a lamp in consecutive frames of one track.
_MAX_SIZE_RATIO = 1.5


@dataclass
class _Track:
    center: np.ndarray
    size: float
    last_seen: float
    velocity: np.ndarray | None = None
    candidates: np.ndarray | None = None
    log_likelihoods: np.ndarray | None = None
    log_prior: np.ndarray | None = None
    mapped: np.ndarray | None = None
    frames: int = 0

    def predicted(self, elapsed: float) -> np.ndarray:
        """Where the lamp should be ``elapsed`` s after it was last seen."""
        return self.center if self.velocity is None else self.center + self.velocity * elapsed

    def follow(self, observation: LampObservation, stamp: float) -> None:
        """Move the track to ``observation``, seen at ``stamp``."""
        elapsed = stamp - self.last_seen
        if elapsed > 0.0:
            self.velocity = (observation.center - self.center) / elapsed
        self.center, self.size, self.last_seen = observation.center, float(observation.ellipse[2]), stamp

    def restart(self, reading: BeaconReading) -> None:
        """Forget the evidence so far and start from ``reading``."""
        self.candidates, self.log_prior, self.mapped = reading.candidates, reading.log_prior, reading.mapped
        self.log_likelihoods = np.array(reading.log_likelihoods, dtype=float)
        self.frames = 1


class EvidenceTracker:
    """
    Accumulates per-candidate evidence for every lamp in view until its ID is certain.

    ``known_ids`` (None: any) limits the IDs it returns. A lamp continues a track when
    its centre lies within ``gate`` + ``reach`` x (time since the track was seen, s)
    semi-major axes of where the track predicts it: ``gate`` is what the prediction
    may miss by, ``reach`` how fast (semi-major axes per second) a lamp's image may
    change its speed. The gate must stay below half the distance between lamps in the
    image (in semi-major axes, the lamps' spacing over their radius: 32 for 15 cm
    lamps 2.4 m apart).
    """

    def __init__(self, known_ids: Iterable[int] | None = None, min_confidence: float = MIN_CONFIDENCE,
                 gate: float = 0.5, max_gap: float = 0.5, reach: float = 30.0) -> None:
        if not 0.0 < min_confidence < 1.0:
            raise ValueError(f'min_confidence must lie in (0, 1), got {min_confidence}')
        if not (gate > 0.0 and max_gap > 0.0 and reach >= 0.0):
            raise ValueError(f'gate and max_gap must be positive and reach not negative, got {gate}, {max_gap} '
                             f'and {reach}')
        self.known_ids = None if known_ids is None else {int(i) for i in known_ids}
        self.min_confidence = min_confidence
        self.gate = gate
        self.max_gap = max_gap
        self.reach = reach
        self.tracks: list[_Track] = []
        self.decisions: list[Decision] = []
        # Per observation of the latest update: its track's evidence so far, as one reading.
        self.evidence: list[BeaconReading] = []
        self._stamp: float | None = None

    def update(self, observations: Sequence[LampObservation], readings: Sequence[BeaconReading],
               stamp: float) -> list[int | None]:
        """Return the certain ID of each observation (None if not yet), after adding this frame's readings."""
        if len(observations) != len(readings):
            raise ValueError(f'{len(observations)} observations but {len(readings)} readings')
        if self._stamp is not None and stamp < self._stamp:
            self.tracks = []
        self._stamp = stamp
        self.tracks = [t for t in self.tracks if stamp - t.last_seen <= self.max_gap]
        matches = self._associate(observations, stamp)
        followed = []
        for k, (observation, reading) in enumerate(zip(observations, readings)):
            track = matches.get(k)
            if track is None:
                track = _Track(observation.center, float(observation.ellipse[2]), stamp)
                track.restart(reading)
                self.tracks.append(track)
            elif stamp == track.last_seen:
                pass  # the same frame again (delivered twice): its packet phase and noise are not new evidence
            elif self._continues(track, reading):
                track.log_likelihoods = track.log_likelihoods + reading.log_likelihoods
                track.frames += 1
            else:
                track.restart(reading)
            track.follow(observation, stamp)
            followed.append(track)
        for k in self._inheriting_another_lamps_id(followed, readings):
            followed[k].restart(readings[k])
        self.decisions, self.evidence = [], []
        for track in followed:
            decision = self._decide(track)
            self.decisions.append(decision)
            self.evidence.append(BeaconReading(decision.lamp_id, decision.confidence, track.candidates,
                                               track.log_likelihoods, track.log_prior, track.mapped,
                                               decision.unknown, decision.detail))
        return [d.lamp_id for d in self.decisions]

    def _inheriting_another_lamps_id(self, followed: list[_Track], readings: Sequence[BeaconReading]) -> list[int]:
        """
        Return the observations whose track is certain of an ID that another lamp of this frame reads with certainty.

        The other lamp reads it on its own: one lamp cannot be in two places, and the frame's own reading says
        where it is now. The other track was continued by a lamp that came near the old place of a lamp now
        elsewhere (a hand-held camera moved between stills, an unmodulated lamp beside the track's lamp).
        """
        read_now = {r.lamp_id for r in readings if r.lamp_id is not None}
        return [k for k, (track, reading) in enumerate(zip(followed, readings))
                if reading.lamp_id is None and self._decide(track).lamp_id in read_now]

    def _associate(self, observations: Sequence[LampObservation], stamp: float) -> dict[int, _Track]:
        """Observation index -> track, nearest to the tracks' predictions first, each track used once."""
        pairs = []
        for track in self.tracks:
            elapsed = stamp - track.last_seen
            predicted = track.predicted(elapsed)
            for k, observation in enumerate(observations):
                size = float(observation.ellipse[2])
                if not 1.0 / _MAX_SIZE_RATIO <= size / track.size <= _MAX_SIZE_RATIO:
                    continue
                distance = float(np.linalg.norm(observation.center - predicted))
                if distance <= (self.gate + self.reach * elapsed) * max(size, track.size):
                    pairs.append((distance, k, id(track), track))
        matches: dict[int, _Track] = {}
        taken: set[int] = set()
        for _, k, key, track in sorted(pairs, key=lambda p: p[:3]):
            if k not in matches and key not in taken:
                matches[k] = track
                taken.add(key)
        return matches

    def _continues(self, track: _Track, reading: BeaconReading) -> bool:
        """Whether ``reading`` can add to ``track``: same candidates, and not certain of another one."""
        if not np.array_equal(track.candidates, reading.candidates):
            return False
        if reading.lamp_id is None and not reading.unknown:
            return True
        frame_best = np.argmax(reading.log_likelihoods + reading.log_prior)
        track_best = np.argmax(track.log_likelihoods + track.log_prior)
        return frame_best == track_best or self._decide(track).confidence < self.min_confidence

    def _decide(self, track: _Track) -> Decision:
        decision = decide(track.candidates, track.mapped, track.log_likelihoods, track.log_prior,
                          self.min_confidence)
        if decision.lamp_id is not None and self.known_ids is not None and decision.lamp_id not in self.known_ids:
            return Decision(None, decision.confidence, True, f'ID {decision.lamp_id} is not in the map')
        return decision
