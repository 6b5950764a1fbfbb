"""The transforms on OpenCV's DFT against scipy.fft and scipy.signal, which they replace on the estimate paths."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.fft
import scipy.signal

from psfd.estimator import fourier

# float32: a few units of float32 rounding (2^-23 ~ 1.2e-7) of sums of up to 251 unit-variance terms;
# float64: the same in float64
TOLERANCE = {np.float32: 2e-5, np.float64: 1e-12}


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("n", [1, 2, 7, 8, 31, 250, 251])
@pytest.mark.parametrize("axis", [0, 1, -1])
def test_the_dct_and_its_inverses_are_scipy_ones(dtype, n, axis):
    x = np.random.default_rng(n).standard_normal((3, n) if axis else (n, 3)).astype(dtype)
    full = scipy.fft.dct(x, type=2, norm="ortho", axis=axis)
    tol = TOLERANCE[dtype]
    for keep in sorted({1, n // 2, n // 2 + 1, n}):
        kept = full.take(np.arange(keep), axis=axis)
        ours = fourier.dct(x, keep, axis=axis)
        assert ours.dtype == full.dtype and ours.flags.c_contiguous
        np.testing.assert_allclose(ours, kept, rtol=0, atol=tol)
        for m in (n, n + 3, 2 * n + 1):
            for theirs, back in ((scipy.fft.idct, fourier.idct), (scipy.fft.idst, fourier.idst)):
                expected = theirs(kept, type=2, norm="ortho", axis=axis, n=m)
                got = back(kept, m, axis=axis)
                assert got.dtype == expected.dtype and got.shape == expected.shape
                np.testing.assert_allclose(got, expected, rtol=0, atol=tol)


def test_a_whole_dct_comes_back():
    x = np.random.default_rng(3).standard_normal((17, 24))
    np.testing.assert_allclose(fourier.idct(fourier.dct(x)), x, rtol=0, atol=1e-13)
    np.testing.assert_allclose(fourier.dct(x, axis=0), scipy.fft.dct(x, type=2, norm="ortho", axis=0), rtol=0,
                               atol=1e-13)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("shapes", [((7, 9), (13, 5)), ((31, 31), (17, 17)), ((5, 5), (21, 21)), ((8, 6), (3, 4)),
                                    ((300, 287), (41, 41))])
def test_the_convolution_is_fftconvolve_same(dtype, shapes):
    rng = np.random.default_rng(0)
    a, b = rng.random(shapes[0]).astype(dtype), rng.random(shapes[1]).astype(dtype)
    ours = fourier.convolve_same(a, b)
    expected = scipy.signal.fftconvolve(a, b, mode="same")
    assert ours.dtype == dtype
    # float32: rounding of sums of up to 41^2 products in [0, 1) (values up to ~420)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-12 if dtype == np.float64 else 5e-4)


@pytest.mark.parametrize("dtype, shape", [(np.float32, (1100, 1300)), (np.float64, (257, 331)),
                                          (np.float32, (3, 2, 5))])
def test_two_threads_give_the_one_thread_result_bit_for_bit(dtype, shape, monkeypatch):
    # each half of the lines on its own thread (fourier._by_lines), against all of them on this one
    x = np.random.default_rng(5).standard_normal(shape).astype(dtype)

    def transforms():
        out = []
        for axis in range(x.ndim):
            n = x.shape[axis]
            for keep in (n // 2 + 1, n):
                c = fourier.dct(x, keep, axis=axis)
                out += [c, fourier.idct(c, n, axis=axis), fourier.idst(c, n + 2, axis=axis)]
        return out

    monkeypatch.setattr(fourier, "_threads", lambda size: 1)
    one = transforms()
    monkeypatch.setattr(fourier, "_threads", lambda size: 2)
    two = transforms()
    for a, b in zip(one, two):
        assert a.dtype == b.dtype and a.flags.c_contiguous and b.flags.c_contiguous
        np.testing.assert_array_equal(a, b, strict=True)
    # and the threaded ones are scipy's (float32 sums of up to 1300 terms: a few units of 2^-23 times sqrt(1300))
    tol = 1e-4 if dtype == np.float32 else 1e-12
    for axis in range(x.ndim):
        expected = scipy.fft.dct(x, type=2, norm="ortho", axis=axis)
        np.testing.assert_allclose(two[6 * axis + 3], expected, rtol=0, atol=tol)
        np.testing.assert_allclose(two[6 * axis + 4], x, rtol=0, atol=tol)


def test_threads_only_on_large_arrays_and_never_in_a_worker_process():
    import multiprocessing

    assert fourier._threads(100) == 1
    big = fourier._THREADED_SIZE
    assert fourier._threads(big) == (2 if fourier.usable_cores() >= 2 else 1)
    if "fork" in multiprocessing.get_all_start_methods():
        with multiprocessing.get_context("fork").Pool(1) as pool:
            assert pool.apply(fourier._threads, (big,)) == 1
