"""A decision over candidate IDs prefers None to a guess, also when there is nothing to choose from."""
import numpy as np

from vlp_ros.beacon.reading import decide


def test_no_candidates_give_no_decision() -> None:
    empty = np.zeros(0)
    decision = decide(np.zeros(0, dtype=int), np.zeros(0, dtype=bool), empty, empty, 0.99)
    assert decision.lamp_id is None and decision.confidence == 0.0


def test_a_clear_mapped_candidate_is_chosen_and_a_nan_gives_none() -> None:
    candidates, mapped = np.array([3, 7, 9]), np.ones(3, dtype=bool)
    log_prior = np.full(3, -np.log(3.0))
    assert decide(candidates, mapped, np.array([0.0, 30.0, 0.0]), log_prior, 0.99).lamp_id == 7
    assert decide(candidates, mapped, np.array([0.0, np.nan, 0.0]), log_prior, 0.99).lamp_id is None
