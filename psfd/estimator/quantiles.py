"""Median and percentiles of a whole array, equal bit for bit to numpy's.

numpy.median and numpy.percentile import numpy.ma on their first call (to
check for masked arrays among their results): 35-55 ms of a process's
start-up for a handful of medians of small arrays. These take the same
partition, the same mean of the middle values and the same linear
interpolation between order statistics ("linear", method 7 of Hyndman &
Fan, Am. Stat. 50(4), 1996), over the flattened array, without it
(tests/test_quantiles.py compares them with numpy's).
"""

from __future__ import annotations

import numpy as np

__all__ = ["median", "percentile"]


def median(a) -> np.floating:
    """numpy.median(a) of the flattened array: the middle value, or the mean of the two middle ones; NaN
    when the array holds one."""
    a = np.asarray(a).ravel()
    n = a.size
    if n == 0:
        return np.median(a)  # numpy's warning and NaN
    kth = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    inexact = np.issubdtype(a.dtype, np.inexact)
    if inexact:
        kth.append(-1)  # a NaN sorts last
    part = np.partition(a, kth)
    middle = part[n // 2 : n // 2 + 1] if n % 2 else part[n // 2 - 1 : n // 2 + 1]
    result = np.mean(middle)  # as numpy: the mean of one or two values, in its result type
    if inexact and np.isnan(part[-1]):
        return type(result)(np.nan)
    return result


def percentile(a, q) -> np.ndarray | np.floating:
    """numpy.percentile(a, q) (method "linear") of the flattened array, ``q`` in per cent, one or several."""
    arr = np.asarray(a).ravel()
    scalar = type(q) in (int, float)
    quantiles = np.true_divide(q, 100)
    if not ((quantiles >= 0) & (quantiles <= 1)).all():
        raise ValueError("Percentiles must be in the range [0, 100]")
    n = arr.size
    virtual = np.asanyarray((n - 1) * quantiles)
    previous = np.array(np.floor(virtual))  # arrays, also for one q (numpy's in-place `out=...`)
    following = np.array(previous + 1)
    above, below = virtual >= n - 1, virtual < 0
    previous[above], following[above] = -1, -1
    previous[below], following[below] = 0, 0
    previous, following = previous.astype(np.intp), following.astype(np.intp)
    # numpy takes np.unique of these, which imports numpy.ma too: the same sorted distinct indices
    kth = sorted({0, -1, *previous.ravel().tolist(), *following.ravel().tolist()})
    part = np.partition(arr, kth)
    lo, hi = part[previous], part[following]
    gamma = np.asanyarray(virtual - previous, dtype=virtual.dtype)
    if scalar:
        gamma = float(gamma)
    # numpy's _lerp: from the lower value below t = 0.5, from the upper one above (monotone in t)
    diff = hi - lo
    result = np.array(np.add(lo, diff * gamma))
    np.subtract(hi, diff * (1 - gamma), out=result, where=np.asarray(gamma) >= 0.5, casting="unsafe")
    if np.issubdtype(arr.dtype, np.inexact) and np.isnan(part[-1]):
        result[...] = np.nan
    return result[()] if result.ndim == 0 else result
