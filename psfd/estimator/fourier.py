"""The orthonormal cosine and sine transforms and the FFT convolution the estimators use, on OpenCV's DFT.

scipy.fft has all of them, but importing it costs 0.3-0.5 s of a process's
start-up (it loads scipy's array-API layer and scipy.special), more than a
whole estimate of a target photo spends in the transforms; OpenCV is loaded
anyway (reading frames, Keys interpolation). The DCT-II and its inverse are
one real DFT of the samples reordered (Makhoul, "A fast cosine transform in
one and two dimensions", IEEE Trans. ASSP 28(1), 1980); the DST-II is the
DCT-II of the sign-alternated samples, reversed. float32 stays float32 (half
the work, rounding far below sensor noise); anything else is float64. The
results equal scipy.fft.dct / idct / idst(type=2, norm="ortho") and
scipy.signal.fftconvolve(mode="same") to float rounding (tests/test_fourier.py).

On large arrays the lines are transformed in two halves on two threads (see
`_by_lines`): OpenCV's DFT and numpy's array operations release the GIL, and
scipy.fft's own ``workers=2`` would otherwise be twice as fast.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from psfd.workers import concurrently, in_worker, usable_cores

__all__ = ["convolve_same", "dct", "idct", "idst"]


def _real(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x)
    return x if x.dtype == np.float32 else x.astype(np.float64)


# Lines x samples from which two threads pay: a thread costs ~0.1 ms, a line of 1000 samples ~10 us
_THREADED_SIZE = 1 << 18


def _lines(x: np.ndarray, axis: int) -> np.ndarray:
    """``x`` with ``axis`` moved last, as a 2-D array of lines (OpenCV transforms rows): a view for 2-D ``x``."""
    moved = np.moveaxis(x, axis, -1)
    return moved.reshape(int(np.prod(moved.shape[:-1])), moved.shape[-1])


def _across(lines: np.ndarray) -> bool:
    """Whether the rows of the 2-D ``lines`` run across memory (the columns of a C-ordered array, as `_lines`
    gives for axis 0): numpy gathers those an element per cache line, cv2.transpose ~10 times faster."""
    return lines.strides[0] == lines.itemsize and lines.shape[0] > 1 and lines.shape[1] > 1


def _threads(size: int) -> int:
    """2 for a transform of ``size`` samples that two threads speed up, else 1. Never in a worker process
    (the estimators' pools already run one per core)."""
    return 2 if size >= _THREADED_SIZE and not in_worker() and usable_cores() >= 2 else 1


def _by_lines(transform: Callable[[np.ndarray, np.ndarray], None], x: np.ndarray, axis: int, width: int) -> np.ndarray:
    """The C-contiguous array of ``transform(lines, out)`` (which writes the transforms, ``width`` long, of the
    rows of ``lines`` into those of ``out``) along ``axis`` of ``x``.

    With two threads (when `_threads` says so), each half of the lines is transposed (axis 0), transformed
    and written to its place on its own thread: every row is transformed alone (DFT_ROWS), so the result
    is that of one thread bit for bit.
    """
    lines = _lines(x, axis)
    shape = list(x.shape)
    shape[axis] = width
    result = np.empty(shape, dtype=x.dtype)
    target = _lines(result, axis)  # a view of result for 2-D arrays (transposed for axis 0), else a copy
    direct = target.flags.c_contiguous and np.may_share_memory(target, result)

    def part(rows: slice) -> None:
        source = cv2.transpose(lines[rows].T) if _across(lines[rows]) else lines[rows]
        if direct:
            transform(source, target[rows])
            return
        out = np.empty((len(source), width), dtype=x.dtype)
        transform(source, out)
        if _across(target[rows]):
            target[rows].T[...] = cv2.transpose(out)
        else:
            target[rows] = out

    if _threads(lines.size) < 2 or len(lines) < 2:
        part(slice(None))
    else:
        half = len(lines) // 2
        concurrently(lambda: part(slice(0, half)), lambda: part(slice(half, None)))
    if not np.may_share_memory(target, result):
        result[...] = np.moveaxis(target.reshape(tuple(np.delete(shape, axis)) + (width,)), -1, axis)
    return result


def dct(x: np.ndarray, keep: int | None = None, axis: int = -1) -> np.ndarray:
    """The first ``keep`` (all by default) orthonormal DCT-II coefficients of ``x`` along ``axis``.

    scipy.fft.dct(x, type=2, norm="ortho", axis=axis)[..., :keep] (on ``axis``).
    One real DFT of the even samples followed by the odd ones reversed, v (Makhoul 1980):
    X_k = Re(exp(-i pi k / 2N) V_k), scaled by sqrt(1/N) for k = 0 and sqrt(2/N) otherwise.
    """
    x = _real(x)
    n = x.shape[axis]
    return _by_lines(_dct_lines, x, axis, n if keep is None else max(0, min(int(keep), n)))


def _dct_lines(lines: np.ndarray, out: np.ndarray) -> None:
    """`dct` of the rows of ``lines``, its first out.shape[1] coefficients written into ``out``."""
    n, keep = lines.shape[1], out.shape[1]
    v = np.empty(lines.shape, dtype=lines.dtype)
    half = (n + 1) // 2
    v[:, :half] = lines[:, ::2]
    v[:, half:] = lines[:, 1::2][:, ::-1]
    # OpenCV's packed spectrum of a real row: Re V_0, Re V_1, Im V_1, Re V_2, ... (Re V_N/2 last for even N)
    packed = cv2.dft(v, flags=cv2.DFT_ROWS)
    k = np.arange(keep)
    folded = np.minimum(k, n - k)  # V_k = conj(V_{N-k})
    re_at = np.maximum(2 * folded - 1, 0)
    im_at = np.where((folded == 0) | (2 * folded == n), -1, 2 * folded)  # -1: no imaginary part
    scale = np.where(k == 0, np.sqrt(1.0 / n), np.sqrt(2.0 / n))
    cos = (np.cos(0.5 * np.pi * k / n) * scale).astype(lines.dtype)
    sin = (np.sin(0.5 * np.pi * k / n) * scale * np.where(k > n - k, -1.0, 1.0) * (im_at >= 0)).astype(lines.dtype)
    if keep > 1 and keep <= n // 2 + (n % 2):  # the usual band: strided views, no gathers
        out[:, 0] = packed[:, 0] * cos[0]
        out[:, 1:] = packed[:, 1 : 2 * keep - 2 : 2] * cos[1:]
        out[:, 1:] += packed[:, 2 : 2 * keep - 1 : 2] * sin[1:]
    else:
        out[...] = packed[:, re_at] * cos + packed[:, np.maximum(im_at, 0)] * sin


def _idct_lines(c: np.ndarray, out: np.ndarray, start: int = 0) -> None:
    """The inverse orthonormal DCT-II of length n = out.shape[1] of the rows of ``c``, written into ``out``;
    column j of ``c`` holds coefficient start + j (the others zero): `dct` undone,
    V_m = exp(i pi m / 2N) (X_m - i X_{N-m}) / 2 for m = 0 .. N/2, then one inverse real DFT. Only the
    nonzero parts of the half spectrum are computed, straight into OpenCV's packed layout (Re V_0, Re V_1,
    Im V_1, ..., Re V_N/2 for even N)."""
    rows, n = out.shape
    kept = min(c.shape[1], n - start)
    h = n // 2 + 1
    m = np.arange(h)
    w = np.where(m == 0, np.sqrt(n), np.sqrt(n / 2.0))  # orthonormal scale and the /2
    wcos = (w * np.cos(0.5 * np.pi * m / n)).astype(c.dtype)
    wsin = (w * np.sin(0.5 * np.pi * m / n)).astype(c.dtype)
    packed = np.zeros((rows, n), dtype=c.dtype)
    lo, hi = start, min(start + kept, h)  # X_m for m < N/2 + 1
    if hi > lo:
        _add_half_spectrum(packed, lo, c[:, : hi - lo], wcos[lo:hi], wsin[lo:hi], fresh=True)
    first = (lo, hi)
    lo, hi = max(1, n - start - kept + 1), min(h - 1, n - start)  # X_{N-m} for m in [lo, hi]
    if hi >= lo:
        b = c[:, n - hi - start : n - lo - start + 1][:, ::-1]
        fresh = first[1] <= first[0] or hi < first[0] or lo >= first[1]  # the usual band: one of the two only
        _add_half_spectrum(packed, lo, b, wsin[lo : hi + 1], -wcos[lo : hi + 1], fresh)
    v = cv2.idft(packed, flags=cv2.DFT_ROWS | cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)
    half = (n + 1) // 2
    out[:, ::2] = v[:, :half]
    out[:, 1::2] = v[:, half:][:, ::-1]


def _add_half_spectrum(packed: np.ndarray, lo: int, x: np.ndarray, re: np.ndarray, im: np.ndarray,
                       fresh: bool = False) -> None:
    """Add x (re + i im) to V_m, m = lo, lo + 1, ..., in OpenCV's packed rows (Re V_0 in column 0, Re V_m
    and Im V_m in 2m - 1 and 2m, Re V_N/2 last for even N), through strided views. ``fresh``: those V_m are
    still zero, and the products are written in place (0 + p = p: the same values, without a temporary
    and a second pass over the rows)."""
    n = packed.shape[1]

    def add(at, factor, weight):
        if fresh:
            np.multiply(factor, weight, out=packed[:, at])
        else:
            packed[:, at] += factor * weight

    if lo == 0:
        add(0, x[:, 0], re[0])
        x, re, im, lo = x[:, 1:], re[1:], im[1:], 1
    count = x.shape[1]
    if count and n % 2 == 0 and lo + count - 1 == n // 2:  # V_N/2 is real
        add(n - 1, x[:, -1], re[-1])
        x, re, im, count = x[:, :-1], re[:-1], im[:-1], count - 1
    if count:
        add(slice(2 * lo - 1, 2 * (lo + count) - 1, 2), x, re)
        add(slice(2 * lo, 2 * (lo + count), 2), x, im)


def idct(c: np.ndarray, n: int | None = None, axis: int = -1) -> np.ndarray:
    """The inverse orthonormal DCT-II (a DCT-III) of length ``n`` along ``axis``, the coefficients ``c`` does
    not hold zero: scipy.fft.idct(c, type=2, norm="ortho", n=n, axis=axis)."""
    c = _real(c)
    return _by_lines(_idct_lines, c, axis, c.shape[axis] if n is None else int(n))


def idst(c: np.ndarray, n: int | None = None, axis: int = -1) -> np.ndarray:
    """The inverse orthonormal DST-II of length ``n`` along ``axis``, missing coefficients zero:
    scipy.fft.idst(c, type=2, norm="ortho", n=n, axis=axis).

    DST-II_k(x) = DCT-II_{N-1-k}((-1)^j x_j), both orthonormal (sin(pi (N - k') (2j + 1) / 2N)
    = (-1)^j cos(pi k' (2j + 1) / 2N)), so the inverse is the inverse DCT-II of the
    coefficients reversed (coefficient k at N-1-k), with the signs of the odd samples changed.
    """
    c = _real(c)

    def lines_idst(lines: np.ndarray, out: np.ndarray) -> None:
        n = out.shape[1]
        kept = min(lines.shape[1], n)
        _idct_lines(lines[:, :kept][:, ::-1], out, start=n - kept)
        out[:, 1::2] *= -1

    return _by_lines(lines_idst, c, axis, c.shape[axis] if n is None else int(n))


def convolve_same(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Central part of the full 2-D convolution a * b, the size of ``a`` (scipy.signal.fftconvolve's "same").

    Both zero-padded past the full size to a length OpenCV's DFT is fast at; float32 when both are.
    """
    dtype = np.float32 if np.asarray(a).dtype == np.float32 and np.asarray(b).dtype == np.float32 else np.float64
    a, b = np.asarray(a, dtype=dtype), np.asarray(b, dtype=dtype)
    full = (a.shape[0] + b.shape[0] - 1, a.shape[1] + b.shape[1] - 1)
    size = (cv2.getOptimalDFTSize(full[0]), cv2.getOptimalDFTSize(full[1]))
    spectra = []
    for x in (a, b):
        padded = np.zeros(size, dtype=dtype)
        padded[: x.shape[0], : x.shape[1]] = x
        spectra.append(cv2.dft(padded, nonzeroRows=x.shape[0]))
    product = cv2.idft(cv2.mulSpectrums(*spectra, 0), flags=cv2.DFT_REAL_OUTPUT | cv2.DFT_SCALE)
    r0, c0 = (full[0] - a.shape[0]) // 2, (full[1] - a.shape[1]) // 2
    return product[r0 : r0 + a.shape[0], c0 : c0 + a.shape[1]]
