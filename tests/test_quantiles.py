"""quantiles.median and quantiles.percentile equal numpy's bit for bit, which they replace on the estimate paths."""

from __future__ import annotations

import numpy as np
import pytest

from psfd.estimator import quantiles

ARRAYS = {
    "odd float": np.random.default_rng(0).standard_normal(101),
    "even float": np.random.default_rng(1).standard_normal(100),
    "float32 plane": np.random.default_rng(2).random((37, 52), dtype=np.float32),
    "ints": np.random.default_rng(3).integers(0, 300, 1001),
    "even ints": np.random.default_rng(4).integers(-5, 5, 64),
    "one": np.array([2.5]),
    "two": np.array([3.0, -1.0]),
    "ties": np.array([1.0, 1.0, 2.0, 2.0, 2.0, 7.0]),
    "list": [0.1, 0.7, 0.3, 0.2],
    "with NaN": np.array([1.0, np.nan, 3.0, 0.5]),
}


@pytest.mark.parametrize("name", ARRAYS)
def test_the_median_is_numpy_one(name):
    a = ARRAYS[name]
    expected, ours = np.median(a), quantiles.median(a)
    assert type(ours) is type(expected)
    np.testing.assert_array_equal(ours, expected)  # bit for bit (NaN equals NaN)


@pytest.mark.parametrize("name", ARRAYS)
@pytest.mark.parametrize("q", [(0.05, 99.95), (0.1, 99.9), [1, 99], (0, 50, 100), 50.0, 3, 99.999, (33.3,)])
def test_the_percentiles_are_numpy_ones(name, q):
    a = ARRAYS[name]
    expected, ours = np.percentile(a, q), quantiles.percentile(a, q)
    assert np.shape(ours) == np.shape(expected) and np.result_type(ours) == np.result_type(expected)
    np.testing.assert_array_equal(ours, expected)


def test_a_percentile_out_of_range_is_refused():
    with pytest.raises(ValueError, match="range"):
        quantiles.percentile(np.arange(5.0), (-1, 50))


@pytest.mark.parametrize("seed", range(4))
def test_the_percentiles_of_random_samples_are_numpy_ones(seed):
    """Random samples (ties, tiny and strided, as pair_register.to_uint8 takes): np.percentile bit for bit."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        n = int(rng.integers(1, 3000))
        values = rng.integers(0, 40, n).astype(np.float64) if seed % 2 else rng.standard_normal(n) * 1e3
        qs = (0.1, 99.9) if rng.random() < 0.5 else tuple(rng.uniform(0, 100, 2))
        assert list(quantiles.percentile(values, qs)) == [float(v) for v in np.percentile(values, qs)]
    plane = rng.random((301, 257))
    assert list(quantiles.percentile(plane[::3, ::2], (0.1, 99.9))) == list(np.percentile(plane[::3, ::2], (0.1, 99.9)))
