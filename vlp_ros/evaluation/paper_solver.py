"""
The seed paper's solver as published, for measuring it: the demo's and the accuracy benchmark's paper rows.

It sees what the locator sees (the same detection, beacon reading and IDs, through
``Pipeline.identify``) and solves as the locator's ``solver: paper`` does, except that
it publishes every pose the paper's method finds, also those that do not explain the
image (the locator's fit gate is the locator's, not the paper's), and tells its mirror
poses apart by ``tiebreak``: the locator's hints or its own Appendix B rule.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from vlp_ros.core.camera import CameraModel
from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.tiebreak import appendix_b_choice, PAPER_TIEBREAKS
from vlp_ros.pipeline.config import LocatorSettings
from vlp_ros.pipeline.frame import (disambiguation_hints, frame_result, FrameResult, identified_pairs, NO_LAMP,
                                    paper_candidates, Pipeline)
from vlp_ros.solvers.ambiguity import choose_candidate
from vlp_ros.solvers.candidates import Choice, distinct, PoseCandidate, Reason
from vlp_ros.solvers.pinhole_view import solver_view


class PublishedPaperSolver:
    """
    Stateful across frames as the locator: beacon evidence per tracked lamp, and the last pose for continuity.

    ``candidates``: the distinct poses of the frame just processed (none when the solver was not reached).
    """

    def __init__(self, settings: LocatorSettings, tiebreak: str = 'hints') -> None:
        if tiebreak not in PAPER_TIEBREAKS:
            raise ValueError(f'paper tie-break must be one of {", ".join(PAPER_TIEBREAKS)}, got {tiebreak!r}')
        self.settings = replace(settings, solver='paper')
        self.tiebreak = tiebreak
        self.candidates: list[Pose] = []
        self._identifying = Pipeline(self.settings)
        self._recent: tuple[Pose, float] | None = None

    def process(self, image: np.ndarray, camera: CameraModel, stamp: float,
                gravity_up: np.ndarray | None = None) -> FrameResult:
        """Pose of the camera for one frame taken at ``stamp`` (s), as ``Pipeline.process``."""
        self.candidates = []
        observations, readings, ids = self._identifying.identify(image, stamp)
        if not observations:
            return FrameResult(None, NO_LAMP)
        pairs = identified_pairs(observations, ids, self.settings.lamps)
        if not pairs:
            return frame_result(None, pairs, readings, [])
        try:
            candidates = paper_candidates(*solver_view(pairs, camera))
        except ValueError as err:
            return frame_result(Choice(None, Reason.NO_CANDIDATES, str(err)), pairs, readings, [])
        self.candidates = [c.pose for c in distinct(candidates)]
        choice = self._choose(candidates, stamp, gravity_up)
        if choice.pose is not None:
            self._recent = (choice.pose, stamp)
        return frame_result(choice, pairs, readings, [])

    def _choose(self, candidates: list[PoseCandidate], stamp: float, gravity_up: np.ndarray | None) -> Choice:
        if self.tiebreak == 'appendix-b':
            return appendix_b_choice(candidates)
        return choose_candidate(candidates, disambiguation_hints(self.settings, self._recent, stamp, gravity_up))
