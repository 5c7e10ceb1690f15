"""
The seed paper's own tie-break between its two mirror poses (its Appendix B), for evaluation only.

With R the map-to-camera rotation, R . [0, 0, 1] is where map up points in the
camera frame. The paper keeps the solution whose third row is positive (the
camera faces up) and whose second row is positive (the user looks at the
screen). That rule knows nothing of the scene: it is right only when the phone
is held the way it assumes, which is why the locator uses gravity, the prior
and continuity instead (``vlp_ros.solvers.ambiguity``).
"""
from __future__ import annotations

import argparse

from vlp_ros.core.pose import Pose
from vlp_ros.evaluation.metrics import FrameOutcome
from vlp_ros.solvers.candidates import Choice, distinct, PoseCandidate, Reason

PAPER_TIEBREAKS = ('hints', 'appendix-b')


def add_paper_tiebreak_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument('--paper-tiebreak', choices=PAPER_TIEBREAKS, default='hints',
                        help="how the paper's solver picks between its mirror poses: the locator's hints "
                             '(gravity, prior, continuity) or its own Appendix B rule (camera faces up, '
                             'user looks at the screen)')


def faces_up_toward_user(pose: Pose) -> bool:
    """Appendix B's condition: map up in the camera frame has positive z (third) and y (second) components."""
    up = pose.up_in_camera()
    return bool(up[2] > 0.0 and up[1] > 0.0)


def appendix_b_choice(candidates: list[PoseCandidate]) -> Choice:
    """Return the one candidate that meets Appendix B's condition, or no pose when none or several do."""
    kept = distinct(candidates)
    if len(kept) == 1:
        return Choice(kept[0].pose, Reason.UNIQUE)
    agreeing = [c for c in kept if faces_up_toward_user(c.pose)]
    if not agreeing:
        return Choice(None, Reason.NO_CANDIDATE_AGREES, 'no candidate faces up toward the user (Appendix B)')
    if len(agreeing) > 1:
        return Choice(None, Reason.AMBIGUOUS, 'several candidates face up toward the user (Appendix B)')
    return Choice(agreeing[0].pose, Reason.UP_DIRECTION, 'Appendix B')


def picks_mirror(candidates: list[Pose], truth: Pose) -> bool | None:
    """
    Whether Appendix B picks the mirror pose: not the candidate whose orientation is nearer the truth.

    None when there are not two distinct candidates or it picks neither.
    """
    if len(candidates) != 2:
        return None
    agreeing = [faces_up_toward_user(pose) for pose in candidates]
    if sum(agreeing) != 1:
        return None
    picked, other = candidates if agreeing[0] else candidates[::-1]
    return picked.rotation_error(truth) > other.rotation_error(truth)


def mirror_picks(outcomes: list[FrameOutcome]) -> tuple[int, int]:
    """(frames where Appendix B picks the mirror pose, frames where it picks one of two)."""
    verdicts = [picks_mirror(o.candidates, o.truth) for o in outcomes]
    decided = [v for v in verdicts if v is not None]
    return sum(decided), len(decided)


def mirror_summary(label: str, outcomes: list[FrameOutcome]) -> str:
    """One line: per group, how often Appendix B picks the mirror pose."""
    parts = []
    for group in sorted({o.group for o in outcomes}):
        mirrors, decided = mirror_picks([o for o in outcomes if o.group == group])
        share = f' ({100 * mirrors / decided:.0f} %)' if decided else ''
        parts.append(f'{group} {mirrors} of {decided}{share}'.strip())
    return (f"{label}: Appendix B's tie-break (camera faces up, user looks at the screen) picks the paper's "
            f'mirror pose in {", ".join(parts)} frames with two candidates')
