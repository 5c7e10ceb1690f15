"""The small-array median, percentile and ranked value equal numpy's."""
import numpy as np
import pytest

from vlp_ros.compiled.small_arrays import median, percentile, ranked


@pytest.mark.parametrize('size', [1, 2, 3, 10, 61, 300])
@pytest.mark.parametrize('dtype', [float, np.uint8])
def test_median_and_percentiles_equal_numpys(size: int, dtype: type) -> None:
    rng = np.random.default_rng(size)
    for _ in range(20):
        values = (rng.uniform(0.0, 255.0, size)).astype(dtype)
        assert median(values) == pytest.approx(float(np.median(values)))
        for q in (0.0, 5.0, 50.0, 90.0, 100.0):
            assert percentile(values, q) == pytest.approx(float(np.percentile(values, q)))


def test_inputs_are_left_unchanged() -> None:
    values = np.array([5.0, 1.0, 4.0, 2.0, 3.0])
    median(values)
    percentile(values, 90.0)
    assert values.tolist() == [5.0, 1.0, 4.0, 2.0, 3.0]


def test_ranked_is_the_sorted_values_entry() -> None:
    rng = np.random.default_rng(7)
    for count in (1, 2, 9, 25):
        # Few levels (many ties) and many.
        for high in (3, 255):
            values = rng.integers(0, high, 30).astype(float)
            expected = np.sort(values[:count])
            for rank in range(count):
                assert ranked(values.copy(), count, rank) == expected[rank]
