"""Non-blind sub-pixel PSF estimation from one photograph of the Bernoulli target.

Delbracio, Musé, Almansa, Morel, IJCV 2012 (seed 001) and the detailed
algorithm of Delbracio PhD thesis 2013, App. A.1. With the model
(IJCV 2012, model (M) of sec. 2 and Lemma 1 of sec. 3.1)

    v = S_s(u~_D * h) + n,   u~_D = S_s LPF_s[u(D(.))],

the s-times PSF h is the least-squares solution of S_s U h = v (problem (P)),
well conditioned because the target u is Bernoulli(0.5) white noise
(IJCV 2012, sec. 3.2). Steps (IJCV 2012, sec. 4, Fig. 7):

1. detection, the map D (homography plus radial distortion, or the thesis's
   thin-plate spline), illumination and response curve (detect.py, geometry.py, radiometry.py),
2. u~_D: the target rasterised, DCT low-passed with the s-grid band pulled
   back through the local linear part of D (`s_band`, `u_tilde`), warped by D
   onto the s-times grid with Keys' bicubic kernel (`u_tilde_d`),
3. mask of the noise region, eroded by (k-1)/(2s) (`noise_mask`),
4. normal equations of S_s U h = v (`normal_equations`) and a solver (`solve`).
"""

from __future__ import annotations

import contextlib
import functools
from typing import Callable

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from psfd.errors import BadInputError, EstimationError, SaturatedError, TargetNotFoundError
from psfd.estimator import detect, geometry, kernels, mtf, quantiles, radiometry, resample, target
from psfd.estimator.kernels import PSF
from psfd.estimator.nnls import _cholesky_solve, nnls_normal
from psfd.estimator.raw import Frame
from psfd.vocabulary import (BERNOULLI, DEFAULT_S, DEFAULT_SOLVER, SOLVERS, TARGET_MIN_PX_PER_CELL, check_sizes,
                             check_solver, default_support)
from psfd.workers import concurrently, forked_map, usable_cores

__all__ = [
    "PatternBand", "WindowBand", "band_reach", "cross_validated", "estimate_frames", "estimate_plane",
    "estimate_target", "estimate_window", "jacobian_of", "nnls_normal", "noise_mask", "normal_equations",
    "raster_factor", "recentre", "s_band", "solve", "u_tilde",
    "u_tilde_d",
]

Map = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
SCALE_RANGE = (0.7, 2.0)  # s/t range of near-optimal conditioning, IJCV 2012 sec. 3.3, Fig. 4b
# Half the target is white (noise cells, white squares, margin): a frame more than half clipped has
# lost them, whether or not the marks can still be found, and detection on it fails for that reason.
OVEREXPOSED = 0.5
# Width of the PSF (the sigma of the Gaussian of the same MTF50), in target cells, above which it blurs the
# squares beside each mark into the mark's refinement window (`detect.refine_target`, +-8 cells): the corners
# are pulled off, and the map with them, and the PSF comes out too wide. Measured on renders through
# Gaussians at 0.175-0.3 px/cell (tests/render.py), the MTF50 through the whole pipeline against the same
# estimate with the true map and light: up to 3.8 cells (the estimate's width) within 1.8 % of it; 4.2-4.3
# cells 2.5-4.3 % lower (corners up to 0.5 px off); 5.1 cells 6-9 % lower (0.7-0.9 px).
MARK_BLUR_CELLS = 4.0


# --------------------------------------------------------------------------- u~_D


def raster_factor(s: int, pixels_per_cell: float) -> int:
    """Raster pixels per target cell: at least 4 (IJCV 2012 sec. 4, "Pattern Rasterization") and 2x the s-grid rate.

    ``pixels_per_cell`` is 1/t for an upright target; for a rotated or
    sheared one pass `band_reach`, the rate along the pattern axis the
    pulled-back band reaches furthest (sqrt(2)/t at 45 degrees).
    """
    return int(min(16, max(4, np.ceil(2 * s * pixels_per_cell))))


def jacobian_of(to_pattern: Map, at: tuple[float, float]) -> np.ndarray:
    """Local linear part of D at channel point ``at``: [[dX/dx, dX/dy], [dY/dx, dY/dy]], cells per pixel."""
    x0, y0 = at
    X, Y = to_pattern(np.array([x0, x0 + 1.0, x0]), np.array([y0, y0, y0 + 1.0]))
    return np.array([[X[1] - X[0], X[2] - X[0]], [Y[1] - Y[0], Y[2] - Y[0]]], dtype=np.float64)


def band_reach(jacobian: np.ndarray) -> float:
    """Channel pixels per cell seen by the pulled-back s-band along its furthest pattern axis.

    A camera frequency xi (cycles per pixel) is the pattern frequency
    J^-T xi with J = ``jacobian``; over the square |xi_x|, |xi_y| <= s/2 its
    pattern X and Y components reach s/2 times the column sums of |J^-1|.
    """
    return float(np.abs(np.linalg.inv(jacobian)).sum(axis=0).max())


def s_band(shape: tuple[int, int], factor: int, s: int, jacobian: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The s-grid band of the camera pulled back to the DCT coefficients of the pattern raster.

    LPF_s keeps the camera frequencies |xi_x|, |xi_y| < s/2 cycles per
    channel pixel, the band of the s-times grid (IJCV 2012 sec. 3.1, Lemma 1).
    The paper filters the pattern before warping because D is locally close
    to a similarity (IJCV 2012 sec. 4); a similarity includes a rotation, so
    the band in pattern coordinates is the camera square seen through the
    local linear part J of D: u(J x) has at camera frequency xi the pattern
    frequency f with xi = J^T f. Truncating the pattern's DCT at a square
    instead (right for an upright target only) both aliases the rotated
    square's corners on the s-grid and leaves the corners of the camera band
    empty, which makes S_s U singular there (the noise floor of a 30 degree
    rotation grows 70x).

    DCT coefficient (i, j) of an R x C raster at ``factor`` pixels per cell
    holds the frequencies (+-j factor / 2C, +-i factor / 2R) cycles per cell;
    a rotated square is symmetric under f -> -f but not under a mirror, so
    the pairs with equal signs and with opposite signs get their own masks
    (see `resample.dct_lowpass`).

    Returns
    -------
    same, cross : ndarray of bool (rows, cols)
        Masks of the frequencies (j, i) and (j, -i), cropped to the
        smallest box holding both.
    """
    rows, cols = shape
    (lo_same, hi_same), (lo_cross, hi_cross) = _s_band_rows(shape, factor, s, jacobian)
    keep_r, keep_c = _band_box(hi_same - lo_same, hi_cross - lo_cross, hi_same, hi_cross)
    j = np.arange(keep_c)[None, :]
    same = (j >= lo_same[:keep_r, None]) & (j < hi_same[:keep_r, None])
    cross = (j >= lo_cross[:keep_r, None]) & (j < hi_cross[:keep_r, None])
    return same, cross


def _band_box(width_same, width_cross, hi_same, hi_cross) -> tuple[int, int]:
    """(rows, cols) of the smallest box from index 0 holding every row interval of both masks."""
    used = (width_same > 0) | (width_cross > 0)
    if not used.any():
        return 1, 1
    keep_r = int(np.nonzero(used)[0].max()) + 1
    keep_c = int(max(hi_same[width_same > 0].max(initial=0), hi_cross[width_cross > 0].max(initial=0)))
    return keep_r, max(keep_c, 1)


def _s_band_rows(shape, factor, s, jacobian):
    """For each row i of the DCT coefficients the box can reach, the columns [lo, hi) inside `s_band`'s masks.

    For a fixed row, both inequalities of `s_band` are |alpha f_x + beta| < s / 2
    with f_x increasing along the row: the kept columns are one interval.
    Its ends are found by a binary search, checked against the very floating-point
    expression `s_band` states (the rounded sum is monotone in f_x too), so the masks
    are exactly those of evaluating it on the whole box, at a few
    operations per row instead of per coefficient.
    """
    rows, cols = shape
    box_r, box_c = _reach_box(shape, factor, s, jacobian)
    f_y = np.arange(box_r) * (factor / (2.0 * rows))
    f_x = np.arange(box_c) * (factor / (2.0 * cols))
    (a, b), (c, d) = jacobian
    half = s / 2
    # xi = J^T f; strict inequality as the rectangular truncation keeps indices below s/2: for each sign and
    # each of the two inequalities, the first column inside (lower end) and the first past it (upper end),
    # all eight searches corrected together (`_first`)
    xs, betas, guesses = [], [], []
    for sign in (1.0, -1.0):
        for alpha, beta in ((a, c * sign * f_y), (b, d * sign * f_y)):
            if alpha < 0:  # |x + beta| = |-x - beta| exactly in floating point: make the sum increasing
                alpha, beta = -alpha, -beta
            x = alpha * f_x
            xs += [x, x]
            betas += [beta, beta]
            guesses += [np.searchsorted(x, -half - beta, "right"), np.searchsorted(x, half - beta, "left")]
    lower = np.array([True, False] * 4)[:, None]  # the tests v > -half (lower ends) and v >= half (upper ends)
    ends = _first(np.array(xs), np.array(betas), lambda v: np.where(lower, v > -half, v >= half), np.array(guesses))
    out = []
    for k in (0, 4):  # sign +1, then -1: the two inequalities' lower ends at k, k + 2, upper ends at k + 1, k + 3
        lo = np.maximum(ends[k], ends[k + 2])
        hi = np.minimum(ends[k + 1], ends[k + 3])
        out.append((lo, np.maximum(hi, lo)))
    return out[0], out[1]


def _reach_box(shape: tuple[int, int], factor: int, s: int, jacobian: np.ndarray) -> tuple[int, int]:
    """(rows, cols) of DCT coefficients from index 0 that hold `s_band` of ``jacobian`` (`band_reach`), a
    bound on its masks' shape."""
    rows, cols = shape
    reach = np.abs(np.linalg.inv(jacobian)).sum(axis=0) * (s / 2)
    return min(rows, int(reach[1] * 2 * rows / factor) + 2), min(cols, int(reach[0] * 2 * cols / factor) + 2)


def _first(x: np.ndarray, beta: np.ndarray, test: Callable[[np.ndarray], np.ndarray],
           guess: np.ndarray) -> np.ndarray:
    """Per row, the first index j with ``test(x[j] + beta[row])`` (false, then true, along j); len(x) if none.

    ``guess`` is that index in exact arithmetic (a binary search of x): the
    rounded sum can move the answer by a step, so it is corrected against
    ``test`` itself until the test is false before it and true at it. Several
    searches at once: ``x`` (searches, len), ``beta`` and ``guess`` (searches,
    rows), ``test`` elementwise on (searches, rows).
    """
    j = np.asarray(guess, dtype=np.intp).copy()
    n = x.shape[-1]
    # x[search, j] read as x.ravel()[search n + j]: np.take_along_axis builds an index array per axis, 3x the cost
    flat, line = np.ascontiguousarray(x).ravel(), np.arange(x.shape[0])[:, None] * n
    while True:
        back = (j > 0) & test(flat[line + np.maximum(j - 1, 0)] + beta)
        ahead = ~back & (j < n) & ~test(flat[line + np.minimum(j, n - 1)] + beta)
        if not (back.any() or ahead.any()):
            return j
        j += ahead.astype(np.intp) - back.astype(np.intp)


def u_tilde(
    noise: np.ndarray, s: int, jacobian: np.ndarray, factor: int, raster: np.ndarray | None = None
) -> np.ndarray:
    """The target raster band-limited to the s-grid band, before warping (u~ of IJCV 2012 sec. 3.1).

    The whole target (noise, marks and flat squares) is rasterised at
    ``factor`` pixels per cell and its DCT (no border ringing, Delbracio PhD
    thesis 2013, App. A.1) restricted to `s_band`: for an upright target this
    is the thesis' truncation at index s x (size of the target in channel
    pixels), the cut-off (m s, n s); for a rotated one the same band turned
    with the target.

    Parameters
    ----------
    noise : ndarray (256, 256)
    s : int
    jacobian : ndarray (2, 2)
        Local linear part of D (`jacobian_of`); diag(t, t) for an upright target.
    factor : int
        Raster pixels per cell.
    raster : ndarray, optional
        ``target.cells(noise, factor)`` as float32, to share it between windows.

    Returns
    -------
    ndarray (320 factor, 320 factor); raster pixel (i, j) is centred on cell
    coordinates ((j + 0.5) / factor, (i + 0.5) / factor).
    """
    # float32: 4x faster on the 1280 x 1280 raster, rounding far below sensor noise
    raster = target.cells(noise, factor).astype(np.float32) if raster is None else raster
    same, cross = s_band(raster.shape, factor, s, jacobian)
    return resample.dct_lowpass(raster, same.shape, mask=same, cross_mask=cross)


def u_tilde_d(
    raster: np.ndarray, factor: int, to_pattern: Map, box: tuple[int, int, int, int], s: int, half: int
) -> np.ndarray:
    """u~_D on the s-times grid over a window, with ``half`` extra samples on each side.

    s-grid sample i lies at channel coordinate i / s (the S_s of IJCV 2012
    sec. 3.1); each is mapped to the pattern by D (`geometry.target_maps`) and
    read from the band-limited raster by Keys' bicubic interpolation, a = -0.5
    (Delbracio PhD thesis 2013, App. A.1).

    Parameters
    ----------
    raster : ndarray or WindowBand
        Output of `u_tilde`, or the window's band of a `PatternBand` (the
        same u~, read only where the window needs it).
    factor : int
        Raster pixels per cell.
    to_pattern : callable
        Channel-plane (x, y) -> pattern cell (X, Y).
    box : (x0, y0, x1, y1)
        Window in channel pixels, end exclusive.
    s, half : int
        Grid factor and (support - 1) / 2.

    Returns
    -------
    ndarray (s (y1 - y0 - 1) + 2 half + 1, s (x1 - x0 - 1) + 2 half + 1); array
    index (0, 0) is s-grid sample (s y0 - half, s x0 - half).
    """
    x0, y0, x1, y1 = box
    if isinstance(raster, WindowBand):
        return raster.sample(*_pattern_grid(to_pattern, box, s, half))
    iy = np.arange(s * y0 - half, s * (y1 - 1) + half + 1) / s
    ix = np.arange(s * x0 - half, s * (x1 - 1) + half + 1) / s
    gy, gx = np.meshgrid(iy, ix, indexing="ij")
    X, Y = to_pattern(gx, gy)
    return resample.keys_bicubic(raster, np.asarray(X) * factor - 0.5, np.asarray(Y) * factor - 0.5, a=-0.5)


def _pattern_grid(to_pattern: Map, box: tuple[int, int, int, int], s: int, half: int) -> tuple[np.ndarray, np.ndarray]:
    """D on the s-grid of a window (as `u_tilde_d` samples it), from D on the channel pixels.

    D (a homography and lens distortion, or a smooth spline) is evaluated on
    the s^2 times fewer channel pixels and interpolated by Keys' kernel,
    which reproduces quadratics: what is left is D's third derivative over a
    pixel, below 1e-6 cells on a target (the precision D is inverted to).
    """
    x0, y0, x1, y1 = box
    start = (s * y0 - half, s * x0 - half)
    shape = (s * (y1 - 1 - y0) + 2 * half + 1, s * (x1 - 1 - x0) + 2 * half + 1)
    gy = resample.keys_grid(start[0], shape[0], s).astype(np.float64)
    gx = resample.keys_grid(start[1], shape[1], s).astype(np.float64)
    X, Y = to_pattern(*np.meshgrid(gx, gy))
    X, Y = resample.keys_upsample(np.stack([np.asarray(X), np.asarray(Y)]), s, start, shape)  # both on one grid
    return X, Y


class PatternBand:
    """u~ of `u_tilde` for many windows at once: the raster's DCT taken once, each window's band by difference.

    Every window has its own band (`s_band` of its local Jacobian), so
    `u_tilde` would low-pass the whole raster once per window; the bands of
    one target differ in a few hundred to a few hundred thousand of millions
    of coefficients (perspective and lens distortion change the Jacobian by a
    few per cent across a target). The synthesis is linear in the band, so a
    window's u~ is the u~ of one reference band (synthesised once) plus the
    image of the coefficients where its band differs from the reference
    (`_band_difference`, from the bands' row intervals; `resample.dct_runs_part`),
    evaluated only on the part of the raster that the window reads (`read`),
    or its own band synthesised whole when that costs less. The result equals
    `u_tilde`'s up to float rounding. Sharing one band between windows whose
    Jacobians differ by 0.3 % already moves their PSFs by 13 % of the noise
    floor (measured on a 24-megapixel frame), so no window skips its own band.

    The same window on the other Bayer planes of a photograph reads nearly the
    same part of the raster through a band a few hundred coefficients away
    (the planes see the target half a pixel apart), against tens of thousands
    from the reference: the parts already read are kept (a bounded number, per
    process, until `forget`) and a window starts from the kept part whose band
    is closest. `estimate_frames` solves a window's planes as one group and
    forgets between groups (`_groups`), so a PSF never depends on what else
    the same process solved.

    Parameters
    ----------
    noise : ndarray (256, 256)
    factor : int
        Raster pixels per cell (`raster_factor`).
    s : int
    jacobians : sequence of ndarray (2, 2)
        The local linear parts of D of every window that will be read.
    reference : ndarray (2, 2)
        The Jacobian whose band is synthesised whole (e.g. at the target's centre).
    """

    # bytes of parts kept for later windows, per process (100 windows of a 24-megapixel frame's plane)
    KEPT_BYTES = 48 << 20

    def __init__(self, noise: np.ndarray, factor: int, s: int, jacobians, reference: np.ndarray) -> None:
        # float32 from the start: 4x faster on the raster, rounding far below sensor noise (as in `u_tilde`),
        # and no float64 copy of the raster (80 MB at 10 pixels per cell) at the peak
        cells = target.cells(noise, factor, dtype=np.float32)
        self.factor, self.s, self.shape = factor, s, cells.shape
        # a bound on every window's band (the masks of 400 windows would hold gigabytes, and even their
        # exact sizes cost milliseconds each); the coefficients past a band are zero in its masks
        shapes = [_reach_box(cells.shape, factor, s, j) for j in [reference, *jacobians]]
        self.keep = (max(r for r, _ in shapes), max(c for _, c in shapes))
        self.coeffs = resample.dct_coefficients(cells, self.keep)
        del cells
        ref = s_band(self.shape, factor, s, reference)
        self.base = resample.dct_synthesise(self.coeffs[: ref[0].shape[0], : ref[0].shape[1]], self.shape, *ref)
        self.reference = self.rows(reference)
        # the basis functions the differences are synthesised from (tens of MB): tabulated once, before
        # the workers fork, when many windows will read them; computed per window for a few
        self.bases = resample.dct_bases(self.shape, self.keep) if len(jacobians) > 4 else None
        # a part read for a window is kept with margins that hold the same window on the other Bayer planes:
        # their windows move by up to a channel pixel (the planes' offsets, the mask's bounds), which is
        # up to factor x |J| row sums raster pixels
        self.margin = int(np.ceil(factor * max(np.abs(j).sum(axis=1).max() for j in [reference, *jacobians]))) + 2
        self._kept: list[tuple[tuple[int, int, int, int], tuple[np.ndarray, ...], np.ndarray]] = []
        self._kept_bytes = 0

    def rows(self, jacobian: np.ndarray) -> tuple[np.ndarray, ...]:
        """`s_band` of ``jacobian`` as row intervals over the kept rows: lo, hi of ``same``, then of ``cross``."""
        (lo_same, hi_same), (lo_cross, hi_cross) = _s_band_rows(self.shape, self.factor, self.s, jacobian)
        out = []
        for end in (lo_same, hi_same, lo_cross, hi_cross):
            full = np.zeros(self.keep[0], dtype=np.intp)  # rows past the band: empty intervals
            n = min(end.size, self.keep[0])  # rows past `keep` are empty in every band
            full[:n] = end[:n]
            out.append(full)
        return tuple(out)

    def window(self, jacobian: np.ndarray) -> "WindowBand":
        """The band of the window whose local linear part of D is ``jacobian``."""
        return WindowBand(self, jacobian)

    def read(self, jacobian: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
        """u~ of the band of ``jacobian`` on raster rows r0 .. r1 - 1 and columns c0 .. c1 - 1 (``box``), float32.

        Read from the reference band or from the closest part kept from an
        earlier window that holds ``box``, corrected by the coefficients where
        the two bands differ.
        """
        r0, r1, c0, c1 = box
        own = self.rows(jacobian)
        # start from the band with the fewest differing coefficients
        source, source_rows, at = self.base, self.reference, (0, 0)
        fewest = _band_gap(own, self.reference)
        for (k0, k1, l0, l1), kept_rows, part in self._kept:
            if k0 <= r0 and r1 <= k1 and l0 <= c0 and c1 <= l1:
                gap = _band_gap(own, kept_rows)
                if gap < fewest:
                    source, source_rows, at, fewest = part, kept_rows, (k0, l0), gap
        fresh = source is self.base and fewest > 0  # the reference band itself is read as it is
        if fresh:  # read with margins, kept for the same window on the other planes
            rows, cols = self.shape
            m = self.margin
            r0, r1, c0, c1 = max(r0 - m, 0), min(r1 + m, rows), max(c0 - m, 0), min(c1 + m, cols)
        crop = source[r0 - at[0]: r1 - at[0], c0 - at[1]: c1 - at[1]]
        if fewest:
            crop = self._corrected(crop, jacobian, _band_difference(own, source_rows), (r0, r1, c0, c1))
        if fresh:
            self._keep((r0, r1, c0, c1), own, crop)
        return crop[box[0] - r0: box[1] - r0, box[2] - c0: box[3] - c0]

    def _corrected(self, crop: np.ndarray, jacobian: np.ndarray, runs: tuple[np.ndarray, ...],
                   box: tuple[int, int, int, int]) -> np.ndarray:
        """``crop`` plus the image of ``runs`` on ``box``, or the band of ``jacobian`` synthesised whole and
        cropped when that costs less."""
        r0, r1, c0, c1 = box
        rows, cols = self.shape
        cover, cost = resample.band_part_cover(runs, r1 - r0, c1 - c0, self.coeffs.shape)
        if not cost:
            return crop
        # the difference costs `band_part_cover`'s multiply-adds on the crop, the window's own band
        # a synthesis of the whole raster by FFTs, measured ~4x slower per rows x cols x log2(rows x cols)
        if cost < 4 * rows * cols * np.log2(rows * cols):
            part = resample.dct_runs_part(self.coeffs, runs, self.shape, slice(r0, r1), slice(c0, c1), self.bases,
                                          cover)
            part += crop  # both float32, the part a fresh array
            return part
        same, cross = s_band(self.shape, self.factor, self.s, jacobian)
        coeffs = self.coeffs[: same.shape[0], : same.shape[1]]
        return np.ascontiguousarray(resample.dct_synthesise(coeffs, self.shape, same, cross)[r0:r1, c0:c1])

    def forget(self) -> None:
        """Drop the kept parts: what is read next starts from the reference band."""
        self._kept.clear()
        self._kept_bytes = 0

    def _keep(self, box: tuple[int, int, int, int], rows: tuple[np.ndarray, ...], part: np.ndarray) -> None:
        """Keep a part read for later windows, the oldest dropped past `KEPT_BYTES`."""
        self._kept.append((box, rows, part))
        self._kept_bytes += part.nbytes
        while self._kept_bytes > self.KEPT_BYTES and len(self._kept) > 1:
            self._kept_bytes -= self._kept.pop(0)[2].nbytes


def _band_gap(own: tuple[np.ndarray, ...], other: tuple[np.ndarray, ...]) -> int:
    """Number of coefficients where two bands (`PatternBand.rows`) differ: the sizes of the symmetric
    differences of their row intervals, of both masks."""
    gap = 0
    for k in (0, 2):
        lo, hi, lo_o, hi_o = own[k], own[k + 1], other[k], other[k + 1]
        common = np.maximum(np.minimum(hi, hi_o) - np.maximum(lo, lo_o), 0)
        gap += int((hi - lo).sum() + (hi_o - lo_o).sum() - 2 * common.sum())
    return gap


def _band_difference(own: tuple[np.ndarray, ...], other: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """The coefficients where the band ``own`` differs from ``other`` (both `PatternBand.rows`), as runs
    (row, start, stop, cosine weight, sine weight) for `resample.dct_runs_part`: built from the row
    intervals, never from masks of the whole band."""
    rows = np.arange(own[0].size)
    parts = []
    # (a, b) = (same, cross) enter as cos (a + b) / 2 and sin (b - a) / 2 (`resample.dct_synthesise`)
    for k, (cos_w, sin_w) in ((0, (0.5, -0.5)), (2, (0.5, 0.5))):
        lo, hi, lo_ref, hi_ref = own[k], own[k + 1], other[k], other[k + 1]
        for sign, (a, b, c, d) in ((1.0, (lo, hi, lo_ref, hi_ref)), (-1.0, (lo_ref, hi_ref, lo, hi))):
            # [a, b) minus [c, d): [a, min(b, c)) and [max(a, d), b)
            for start, stop in ((a, np.minimum(b, c)), (np.maximum(a, d), b)):
                run = stop > start
                n = int(np.count_nonzero(run))
                weights = (np.full(n, sign * cos_w), np.full(n, sign * sin_w))
                parts.append((rows[run], start[run], stop[run], *weights))
    return tuple(np.concatenate(column) for column in zip(*parts))


class WindowBand:
    """One window's u~ (`PatternBand.window`), read by `u_tilde_d` where the window needs it."""

    def __init__(self, band: PatternBand, jacobian: np.ndarray) -> None:
        self.band, self.jacobian = band, jacobian

    def sample(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Keys' bicubic interpolation (a = -0.5) of u~ at pattern cells (X, Y), as `u_tilde_d`."""
        band = self.band
        factor = band.factor
        x, y = X * factor - 0.5, Y * factor - 0.5
        rows, cols = band.shape
        finite = np.isfinite(x) & np.isfinite(y)
        if not finite.any():
            return np.full(x.shape, np.nan, dtype=np.float32)
        # the crop holds every 4 x 4 neighbourhood that lies in the raster (`keys_bicubic` reads
        # taps -1 .. 2 and leaves NaN where they leave its image, which is the raster at its edges)
        at_x, at_y = (x, y) if finite.all() else (x[finite], y[finite])  # no copies in the usual case
        r0 = int(np.clip(np.floor(at_y.min()) - 1, 0, rows))
        r1 = int(np.clip(np.floor(at_y.max()) + 3, r0, rows))
        c0 = int(np.clip(np.floor(at_x.min()) - 1, 0, cols))
        c1 = int(np.clip(np.floor(at_x.max()) + 3, c0, cols))
        crop = band.read(self.jacobian, (r0, r1, c0, c1))
        x -= c0  # x and y are this call's own arrays
        y -= r0
        return resample.keys_bicubic(crop, x, y, a=-0.5)


def noise_mask(shape: tuple[int, int], to_pattern: Map, s: int, support: int) -> np.ndarray:
    """Channel pixels inside the noise region, eroded by (k - 1) / (2 s) pixels.

    The erosion keeps only pixels whose whole kernel footprint lies on the
    noise (Delbracio PhD thesis 2013, App. A.1).
    """
    rows, cols = shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    X, Y = to_pattern(x, y)
    lo, hi = target.NOISE_START, target.NOISE_STOP
    inside = (X >= lo) & (X < hi) & (Y >= lo) & (Y < hi)
    return resample.erode(inside, int(np.ceil((support - 1) / (2 * s))))


# --------------------------------------------------------------------------- S_s U h = v


def normal_equations(
    u: np.ndarray, v: np.ndarray, labels: np.ndarray, s: int, support: int, parts: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Normal equations of the masked system S_s U h = v (IJCV 2012, problem (P)), one per part of the observations.

    Row m of S_s U is the k x k patch of u~_D that the kernel meets at camera
    pixel m: u~_D(s m - k) for kernel offsets k (IJCV 2012, sec. 3.1). The
    patches are strided views of ``u`` (sliding_window_view, decimated by s);
    only the used rows are gathered, and each part's A^T A is one
    symmetric rank update (`_gram`; the parts cost one update of the whole
    between them; the whole system is their sum).

    The product is taken in float32 on u~_D minus its mean c, and the mean is
    added back exactly: with A = A' + c 1 1^T,
    A^T A = A'^T A' + c (a 1^T + 1 a^T) + c^2 M 1 1^T, a = A'^T 1.
    Removing the mean removes the dominant eigenvalue of A^T A (IJCV 2012,
    sec. 3.2: M(N m_u^2 + sigma_u^2)), so float32 rounding no longer limits
    the solution (relative error ~1e-5, far below the noise) at 5x the speed.

    Parameters
    ----------
    u : ndarray
        u~_D from `u_tilde_d` for the window of ``v``.
    v : ndarray (rows, cols)
        Normalised observations of the window.
    labels : ndarray of int (rows, cols)
        Part 0 .. parts - 1 of each observation, -1 for those not to use.
    s, support, parts : int

    Returns
    -------
    ata : ndarray (parts, k^2, k^2)
    atv : ndarray (parts, k^2)
    vtv : ndarray (parts,)
    count : ndarray (parts,)
        Number of equations of each part.

    Raises
    ------
    EstimationError
        Fewer observations in all than unknowns.

    Notes
    -----
    The unknowns are the kernel flipped (a correlation); `estimate_window`
    flips the solution back to convolution order.
    """
    finite = np.isfinite(u)
    whole = bool(finite.all())  # the usual case: no patch to test row by row
    c = float(u.mean() if whole else u[finite].mean()) if finite.any() else 0.0
    centred = (u - c if whole else np.where(finite, u - c, np.nan)).astype(np.float32)
    windows = sliding_window_view(centred, (support, support))[::s, ::s]
    n = support * support
    ata = np.empty((parts, n, n))
    atv = np.empty((parts, n))
    vtv = np.empty(parts)
    count = np.empty(parts, dtype=np.int64)
    for p in range(parts):
        mine = labels == p
        a = windows[mine].reshape(-1, n)
        b = v[mine]
        keep = np.isfinite(b) if whole else np.all(np.isfinite(a), axis=1) & np.isfinite(b)
        if not keep.all():
            a, b = a[keep], b[keep]
        _add_mean(ata[p], _gram(a), a.sum(axis=0, dtype=np.float64), c, len(b))
        atv[p] = b @ a.astype(np.float64) + c * float(b.sum())
        vtv[p] = float(b @ b)
        count[p] = len(b)
    if count.sum() <= n:
        raise EstimationError(f"noise region too small for a {support}x{support} kernel: {count.sum()} samples")
    return ata, atv, vtv, count


def _add_mean(out: np.ndarray, gram: np.ndarray, col: np.ndarray, c: float, rows: int) -> None:
    """A^T A = A'^T A' + c (a 1^T + 1 a^T) + c^2 M 1 1^T into ``out`` (`normal_equations`), a = A'^T 1 = ``col``.

    Written in place, pass after pass, with no k^2 x k^2 temporary: a_i + a_j as a's rows plus its column
    (numpy's outer sum is slower than the two passes), then the same products and sums in the same order as
    the former np.add.outer(a, a) * c + c^2 M added to the widened product, so the same bits (the sums
    commute exactly).
    """
    out[:] = col
    out += col[:, None]
    out *= c
    out += c * c * rows
    out += gram  # the float32 product widened as it is added


def _gram(a: np.ndarray) -> np.ndarray:
    """A^T A of a float32 matrix as one symmetric rank update: numpy's matmul of an array's transpose with
    itself calls BLAS syrk (half the multiply-adds of a general product) and fills in the other triangle."""
    return a.T @ a


def solve(
    ata: np.ndarray, atv: np.ndarray, solver: str = DEFAULT_SOLVER
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Solve the normal equations (IJCV 2012, sec. 4, "Numerical Methods for PSF Estimation").

    ``ls``: h = (A^T A)^-1 A^T v, the unbiased estimator h_e = (S_s U)^+ v of
    IJCV 2012 sec. 3.1, with the sensor noise left in the kernel's tails as
    values of both signs; ``ls-threshold``: the same with negative values set
    to 0 (the former default, kept for comparison);
    ``nnls``: non-negative least squares min ||A h - v|| s.t. h >= 0
    (problem (P) of IJCV 2012, sec. 4), by `nnls_normal`.

    Why ``nnls`` is the default (tests/render.py, bench/bench_accuracy.py):
    clipping the negative values of the LS kernel keeps the positive half of
    the zero-mean noise in the tails, and the normalisation to unit sum turns
    it into a pedestal, so ``ls-threshold`` makes every PSF too wide. On
    renders of the target through continuous kernels (Gaussian, rotated
    anisotropic Gaussian, diffraction at f/5.6, f/11 and f/22, defocus; supports
    17 and 25; 0.30-0.50 pixel per cell) with the noise of the published
    photograph (noise floor 0.008-0.028), with the true map and light (means
    of two seeds), the mean signed MTF error (where the true MTF exceeds
    0.05) is -0.001 to -0.013 at 17 x 17 and -0.028 to -0.045 at 25 x 25 for ``ls-threshold``,
    its RMS width 2-12 % and 22-79 % too large, its worst MTF error up to s x
    Nyquist 0.017-0.050 and 0.10-0.17; ``ls``: -0.003 to +0.000, worst
    0.008-0.081; ``nnls``: -0.003 to +0.000, worst 0.006-0.036 (RMS width
    1-8 % above the truth's: a moment dominated by the outermost samples,
    where it keeps the positive half of the noise, without the pedestal).
    On img_example.pgm the clipped kernel gains 2.4 % of mass at 17 x 17 and
    9.7 % at 25 x 25 over the LS one, ``nnls`` none. ``nnls`` is the
    projection of the LS solution onto h >= 0 in the metric of A^T A, which
    holds the true kernel, so it can only come closer to it in that metric;
    it is a physical, non-negative PSF and costs about as much as ``ls``
    (`nnls_normal`).

    Returns
    -------
    h : ndarray (k^2,)
        Solution in the order of the normal equations, not normalised.
    h_ls : ndarray (k^2,)
        Unconstrained solution (for the residual and noise floor).
    inverse_factor : ndarray (k^2, k^2)
        L^-1, with L the Cholesky factor of A^T A = L L^T (lower triangular).
    """
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}: use one of {', '.join(SOLVERS)}")
    try:
        lower = np.linalg.cholesky(ata)  # LAPACK potrf
    except np.linalg.LinAlgError:
        raise EstimationError("the system S_s U h = v is singular: is the target in view?") from None
    # L^-1 is needed for the noise floor (trace((A^T A)^-1) = ||L^-1||_F^2): the LS solution is two products
    # with it, h = L^-T (L^-1 A^T v), instead of a second factorisation of A^T A
    inverse_factor = _triangular_inverse(lower)
    h_ls = inverse_factor.T @ (inverse_factor @ atv)
    if not np.isfinite(h_ls).all():
        raise EstimationError("the system S_s U h = v is singular: is the target in view?")
    return _project(ata, atv, h_ls, solver, h_ls > 0), h_ls, inverse_factor


def _project(ata: np.ndarray, atv: np.ndarray, h_ls: np.ndarray, solver: str, positive: np.ndarray) -> np.ndarray:
    """The solver's kernel from the LS one; ``positive`` starts the non-negative solver."""
    if solver == "ls":
        return h_ls
    if solver == "ls-threshold":
        return np.maximum(h_ls, 0.0)
    return nnls_normal(ata, atv, positive)


def _triangular_inverse(lower: np.ndarray) -> np.ndarray:
    """L^-1 of a lower triangular L, by halves: [[A, 0], [B, C]]^-1 = [[A^-1, 0], [-C^-1 B A^-1, C^-1]].

    LAPACK's trtri is not in numpy; the recursion costs n^3 / 3 multiply-adds as trtri does, most of
    them in two matrix products per level, where a general inverse would cost 2 n^3. The halves are
    written in place into one output, and the diagonal blocks of 32 or fewer rows where the halving
    stops are inverted by one stacked call per size (16 inversions of 18 x 18 for 289 unknowns: each
    the same LAPACK call as alone, a sixteenth of numpy's overhead).
    """
    n = lower.shape[0]
    out = np.zeros_like(lower)
    leaves: dict[int, list[int]] = {}
    merges: list[tuple[int, int, int]] = []  # children before their parent

    def halve(lo: int, hi: int) -> None:
        if hi - lo <= 32:
            leaves.setdefault(hi - lo, []).append(lo)
            return
        mid = lo + (hi - lo) // 2
        halve(lo, mid)
        halve(mid, hi)
        merges.append((lo, mid, hi))

    halve(0, n)
    for size, starts in leaves.items():
        inverses = np.linalg.inv(np.stack([lower[lo:lo + size, lo:lo + size] for lo in starts]))
        for lo, inverse in zip(starts, inverses):
            out[lo:lo + size, lo:lo + size] = inverse
    for lo, mid, hi in merges:
        block = out[mid:hi, lo:mid]
        np.matmul(out[mid:hi, mid:hi] @ lower[mid:hi, lo:mid], out[lo:mid, lo:mid], out=block)
        np.negative(block, out=block)  # -(C^-1 B) A^-1: the sign is exact either side of the product
    return out


def estimate_window(
    v: np.ndarray,
    mask: np.ndarray,
    box: tuple[int, int, int, int],
    raster: np.ndarray,
    factor: int,
    to_pattern: Map,
    s: int,
    support: int,
    solver: str,
    keep_normal: bool = False,
) -> dict:
    """Solve S_s U h = v on one window of a normalised plane.

    Parameters
    ----------
    v : ndarray
        Whole normalised plane (radiometry applied).
    mask : ndarray of bool
        Usable observations on the whole plane.
    box : (x0, y0, x1, y1)
        Window in channel pixels.
    keep_normal : bool
        Also return the normal equations, for the recentring's re-solve (`_recentred`); k^4 values, so
        only where the record is made at once.

    Returns
    -------
    dict with ``psf`` (unit sum, convolution order), ``mass`` (sum before
    normalisation), ``noise_floor`` sigma_n sqrt(trace((A^T A)^-1)) / mass (IJCV 2012,
    sec. 3.1: E||h_e - h||^2 = sigma_n^2 ||(S_s U)^+||_F^2, for the unit-sum kernel), ``sigma`` (sigma_n
    from the LS residual), ``residual`` (RMS residual of the returned kernel),
    ``prediction_error`` (`cross_validated`), ``count``; with ``keep_normal``, ``normal`` = (A^T A, A^T v)
    in the order of the unknowns (the kernel flipped, `normal_equations`).
    """
    x0, y0, x1, y1 = box
    half = (support - 1) // 2
    u = u_tilde_d(raster, factor, to_pattern, box, s, half)
    usable = mask[y0:y1, x0:x1]
    parts = normal_equations(u, v[y0:y1, x0:x1], _quadrants(usable), s, support, 4)
    ata, atv, vtv, count = (x.sum(axis=0) for x in parts)
    h, h_ls, inverse_factor = solve(ata, atv, solver)

    def rss(x: np.ndarray) -> float:  # ||A x - v||^2 from the normal equations
        return max(vtv - 2.0 * float(x @ atv) + float(x @ ata @ x), 0.0)

    sigma = np.sqrt(rss(h_ls) / (count - h_ls.size))
    observed = v[y0:y1, x0:x1][usable]
    _check_pattern_fits(sigma**2, float(np.var(observed)), support, s,
                        lambda: _explained_on_default_support(v, mask, box, raster, factor, to_pattern, s, support))
    mass = float(h.sum())
    if not np.isfinite(mass) or mass <= 0:
        raise EstimationError("the estimated kernel has no positive mass: check the target and exposure")
    kernel = h.reshape(support, support)[::-1, ::-1] / mass
    return {
        **({"normal": (ata, atv)} if keep_normal else {}),
        "psf": np.ascontiguousarray(kernel),
        "mass": mass,
        # trace((A^T A)^-1) = ||L^-1||_F^2; the error of h / mass is that of h over the mass
        "noise_floor": float(sigma * np.linalg.norm(inverse_factor) / mass),
        "sigma": float(sigma),
        "residual": float(np.sqrt(rss(h) / count)),
        "prediction_error": cross_validated(parts, solver, h > 0, float(sigma)),
        "count": int(count),
    }


def _quadrants(usable: np.ndarray) -> np.ndarray:
    """Quadrant 0..3 (x half + 2 y half) of each usable pixel, split at the medians of their x and y; -1 elsewhere."""
    rows, cols = np.nonzero(usable)
    labels = np.full(usable.shape, -1, dtype=np.int64)
    if rows.size:
        labels[rows, cols] = (cols >= quantiles.median(cols)) + 2 * (rows >= quantiles.median(rows))
    return labels


# Halves of the noise region as pairs of quadrants (x half + 2 y half): left | right, top | bottom.
_HALVES = (((0, 2), (1, 3)), ((0, 1), (2, 3)))


def cross_validated(
    parts: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], solver: str, positive: np.ndarray, sigma: float
) -> float | None:
    """Cross-validated prediction error of the kernel, in units of the noise level sigma_n.

    The kernel is fitted (same solver) on one half of the noise region and
    predicts the other half, for the four halves (left, right, top, bottom);
    the RMS of those residuals is divided by sigma_n, the noise level of the
    LS fit of the whole region. With the model right, only the noise of the
    half-size fit adds to sigma_n: about sqrt(1 + k^2 / (M / 2)) for M
    observations, 1.02-1.08 on renders of a whole target. More means the kernel fitted on one part of the
    window does not explain the other: a PSF varying across the window,
    misregistration, a light model or a noise pattern that does not fit; it
    says how far to trust the estimate where the noise floor alone cannot. None
    when a half has fewer observations than unknowns.

    Cost: the four halves come from the quadrant normal equations
    (`normal_equations`, no extra pass over the data) and four solves of
    the k^2 system, started from the whole fit's signs for ``nnls`` (4-6
    Cholesky solves of the free block each on the example photo, 6-10 on a 24 MP
    frame's 10 x 10 grid): 6 % of an estimate at 17 x 17,
    13-20 % at 25 x 25 and 33 x 33 (img_example.pgm).

    Parameters
    ----------
    parts : ata, atv, vtv, count per quadrant (`normal_equations`)
    solver : str
    positive : ndarray of bool
        Positive samples of the whole fit (start of the non-negative solver).
    sigma : float
    """
    ata, atv, vtv, count = parts
    n = ata.shape[1]
    # every half is counted before any is solved: one too small makes the error None, and its fits would be lost
    if sigma <= 0 or any(count[a] + count[b] <= n for pair in _HALVES for a, b in pair):
        return None
    rss = observations = 0.0
    for pair in _HALVES:
        # each half's sums once (a pair of quadrants: one addition each): the half fitted on is the other's test
        halves = [(ata[a] + ata[b], atv[a] + atv[b], vtv[a] + vtv[b], int(count[a] + count[b])) for a, b in pair]
        for (q, c, _, _), (q_test, c_test, b_test, m_test) in (halves, halves[::-1]):
            try:
                if solver == "nnls":  # started from the whole fit's signs, no LS solve needed
                    h = nnls_normal(q, c, positive)
                else:
                    h = _project(q, c, _cholesky_solve(q, c), solver, positive)
            except np.linalg.LinAlgError:
                return None
            rss += max(float(b_test - 2.0 * h @ c_test + h @ q_test @ h), 0.0)
            observations += float(m_test)
    return float(np.sqrt(rss / observations) / sigma)


def _check_pattern_fits(residual_variance: float, signal_variance: float, support: int, s: int,
                        on_default_support: Callable[[], float | None]) -> None:
    """Refuse an estimate whose model explains little of the photographed noise, naming the cause.

    With the right pattern the LS residual is sensor noise, orders of magnitude
    below the variance of the blurred noise image even at f/32; with the wrong
    noise realisation the kernel's few hundred unknowns explain only a few per
    cent of it, and the "PSF" would be noise. A support much narrower than the
    PSF explains as little with the right pattern (img_example.pgm at s = 8 on
    3 x 3 samples, 3/8 pixel: 0 %; 99 % on the default 33 x 33), so a support
    below the default is tried at the default (``on_default_support``, the
    share explained there or None) before the pattern is blamed: another noise
    realisation explains nothing on either (img_example.pgm: 0 %).
    """
    explained = 1.0 - residual_variance / max(signal_variance, 1e-30)
    if explained >= 0.5:
        return
    wider = on_default_support()
    if wider is not None and wider >= 0.5:
        default = default_support(s)
        raise EstimationError(
            f"the kernel reaches beyond its {support}x{support} support ({support / s:.2f} pixel at s = {s}): "
            f"the model explains {max(explained, 0.0):.0%} of the photographed noise with it, {wider:.0%} "
            f"with the default {default}x{default}: raise --support"
        )
    raise EstimationError(
        f"the photographed noise does not follow the target's pattern (the model explains "
        f"{max(explained, 0.0):.0%} of it): give the printed target's noise with --pattern"
    )


def _explained_on_default_support(v: np.ndarray, mask: np.ndarray, box: tuple[int, int, int, int],
                                  raster: np.ndarray, factor: int, to_pattern: Map, s: int,
                                  support: int) -> float | None:
    """Share of the window's photographed noise the least-squares kernel explains on the default support
    (`default_support`); None when ``support`` is not below it or the window is too small for it.

    ``mask`` is eroded for ``support`` (`noise_mask`); it is eroded further, within the window, so that
    every kept pixel's default footprint lies on the noise.
    """
    wide = default_support(s)
    if support >= wide:
        return None
    x0, y0, x1, y1 = box
    extra = int(np.ceil((wide - 1) / (2 * s))) - int(np.ceil((support - 1) / (2 * s)))
    usable = resample.erode(mask[y0:y1, x0:x1], extra)
    try:
        u = u_tilde_d(raster, factor, to_pattern, box, s, (wide - 1) // 2)
        ata, atv, vtv, count = (x[0] for x in normal_equations(u, v[y0:y1, x0:x1], np.where(usable, 0, -1), s, wide))
        h = _cholesky_solve(ata, atv)
    except (EstimationError, np.linalg.LinAlgError):
        return None
    residual_variance = max(vtv - 2.0 * float(h @ atv) + float(h @ ata @ h), 0.0) / (count - h.size)
    return 1.0 - residual_variance / max(float(np.var(v[y0:y1, x0:x1][usable])), 1e-30)


def estimate_plane(
    v: np.ndarray,
    to_pattern: Map,
    *,
    noise: np.ndarray | None = None,
    s: int = DEFAULT_S[BERNOULLI],
    support: int | None = None,
    solver: str = DEFAULT_SOLVER,
    grid: tuple[int, int] = (1, 1),
) -> list[dict]:
    """PSFs from a normalised plane whose camera -> pattern map is known.

    Parameters
    ----------
    v : ndarray
        Plane with illumination and response corrected (black 0, white 1).
    to_pattern : callable
        Channel (x, y) -> pattern cells (X, Y): the map D.
    noise : ndarray (256, 256), optional
        Noise cells (published pattern by default).
    s, support, solver, grid
        See `estimate_target`.

    Returns
    -------
    list of dict, one per grid window (row-major): `estimate_window` output
    plus ``window`` (x0, y0, x1, y1).
    """
    support = 4 * s + 1 if support is None else int(support)
    if support % 2 == 0 or support < 3:
        raise ValueError("support must be an odd number >= 3")
    noise = target.default_noise() if noise is None else np.asarray(noise, dtype=np.float64)
    plane = _Plane(np.asarray(v, dtype=np.float64), to_pattern, s, support, grid)
    band = PatternBand(noise, plane.factor, s, plane.jacobians, plane.reference)
    return [_window_result(plane, k, band, solver) for k in range(len(plane.windows))]


class _Plane:
    """A normalised plane split into windows, each with the local linear part of D at its centre."""

    def __init__(self, v: np.ndarray, to_pattern: Map, s: int, support: int, grid: tuple[int, int]) -> None:
        self.v, self.to_pattern, self.s, self.support = v, to_pattern, s, support
        self.mask = noise_mask(v.shape, to_pattern, s, support)
        if not self.mask.any():
            raise EstimationError("no usable pixel in the noise region of the target")
        rows, cols = np.nonzero(self.mask)
        bounds = (int(cols.min()), int(rows.min()), int(cols.max()) + 1, int(rows.max()) + 1)
        self.windows = kernels.split_grid(bounds, grid)
        # The band follows D's linear part at each window's centre (the centroid
        # of its usable pixels): with perspective and lens distortion it changes
        # across the target (`PatternBand` filters once for all windows).
        self.jacobians = [jacobian_of(to_pattern, _mask_centre(self.mask, w)) for w in self.windows]
        self.reference = jacobian_of(to_pattern, _mask_centre(self.mask, bounds))
        self.factor = raster_factor(s, max(band_reach(j) for j in self.jacobians))


def _window_result(plane: _Plane, k: int, band: PatternBand, solver: str, keep_normal: bool = False) -> dict:
    """`estimate_window` on window ``k`` of a plane, with its box."""
    window = plane.windows[k]
    result = estimate_window(plane.v, plane.mask, window, band.window(plane.jacobians[k]), plane.factor,
                             plane.to_pattern, plane.s, plane.support, solver, keep_normal)
    result["window"] = window
    return result


def _mask_centre(mask: np.ndarray, window: tuple[int, int, int, int]) -> tuple[float, float]:
    """(x, y) centroid of the usable pixels of a window (its centre when it has none)."""
    x0, y0, x1, y1 = window
    rows, cols = np.nonzero(mask[y0:y1, x0:x1])
    if rows.size == 0:
        return ((x0 + x1 - 1) / 2, (y0 + y1 - 1) / 2)
    return (x0 + float(cols.mean()), y0 + float(rows.mean()))


# --------------------------------------------------------------------------- whole pipeline


def estimate_target(
    frame: Frame,
    noise: np.ndarray | None = None,
    s: int = DEFAULT_S[BERNOULLI],
    support: int | None = None,
    solver: str = DEFAULT_SOLVER,
    grid: tuple[int, int] = (1, 1),
    recentre: bool = True,
    tps: float | None = None,
    detection: detect.Detection | None = None,
) -> list[PSF]:
    """Sub-pixel PSFs from one photograph of the Bernoulli target (IJCV 2012, sec. 4, Fig. 7).

    Parameters
    ----------
    frame : Frame
        One channel plane holding the whole target.
    noise : ndarray (256, 256), optional
        The printed noise cells; the published pattern by default.
    s : int
        Super-resolution factor.
    support : int, optional
        Odd kernel size on the s-grid; 4 s + 1 by default (the reference
        choice: 17 x 17 and larger agree, 9 x 9 is too small, IJCV 2012 sec. 5.2, Fig. 18).
    solver : str
        ``ls``, ``ls-threshold`` or ``nnls`` (`DEFAULT_SOLVER`); see `solve`.
    grid : (int, int)
        Split the noise region into nx x ny local windows, one PSF each.
    recentre : bool
        Move each PSF by a sub-sample shift so that its core is centred (see
        `recentre`); the shift removed is kept in ``params["kernel_shift"]``.
        A non-negative kernel is solved again on the shifted grid where the
        shift's ringing would otherwise be clipped into a wider PSF (`_recentred`).
        The X-corners place the kernel only to within their bias (up to
        ~0.1 pixel, 0.4 s-grid samples at s = 4; detect.find_target), so the
        raw position is not a measurement at that level.
    tps : float, optional
        Map the target with the thesis's thin-plate spline of this smoothing
        (10 in Delbracio PhD thesis 2013, App. A.2) on top of a homography,
        instead of the default homography plus radial distortion
        (`geometry.target_maps` says why the default differs).
    detection : detect.Detection, optional
        The target already found in this frame (`detect.find_target`): not searched again.

    Returns
    -------
    list of PSF, one per window, row-major.

    Raises
    ------
    BadInputError
        Bad solver, support, grid or noise pattern.
    TargetNotFoundError, MultipleTargetsError
        From the detection.
    SaturatedError
        Clipped photosites on the target.
    EstimationError
        The system cannot be solved (target too small, no positive mass).
    """
    return estimate_frames([frame], noise, s, support, solver, grid, recentre, tps,
                           detections=None if detection is None else [detection])


def estimate_frames(
    frames: list[Frame],
    noise: np.ndarray | None = None,
    s: int = DEFAULT_S[BERNOULLI],
    support: int | None = None,
    solver: str = DEFAULT_SOLVER,
    grid: tuple[int, int] = (1, 1),
    recentre: bool = True,
    tps: float | None = None,
    workers: int | None = None,
    detections: list[detect.Detection | EstimationError | None] | None = None,
) -> list[PSF]:
    """`estimate_target` on several planes: the target detected once per photograph, the windows shared by workers.

    The planes of one RAW file (same ``source``) see the target at the same
    place up to the Bayer offsets: it is searched on one plane (g1 when
    there) and refined on the others (`detect.refine_target`). All planes'
    windows share one band-limited pattern per raster factor (`PatternBand`)
    and, when there is more than one window and enough work, are solved by
    forked worker processes that inherit the prepared planes and receive
    only window indices.

    Parameters
    ----------
    frames : list of Frame
        In the order of the result.
    workers : int, optional
        Processes solving the windows; by default the cores this process may
        use, and none for a single window or little work.
    detections : list, optional
        Per frame, the target already found in it (`detect.find_target`) or None; a frame with one is not
        searched again. Or the error of a search that found none: raised where the frame would be searched
        again, as that search's own.
    noise, s, support, solver, grid, recentre, tps
        See `estimate_target`.

    Returns
    -------
    list of PSF: every window of the first plane (row-major), then of the next.
    """
    support = _check_arguments(s, support, solver, grid)
    noise = _check_noise(noise)
    with _one_blas_thread():
        return _estimate_frames(frames, noise, s, support, solver, grid, recentre, tps, workers, detections)


def _one_blas_thread():
    """BLAS on one thread while estimating (inherited by forked workers).

    The products are small (289 unknowns): on a shared 2-core machine a
    second BLAS thread that loses its core stalls a 289 x 289 Cholesky or a
    4096 x 289 product 5-100x, and the windows already share the cores between
    processes (a single window in-process on a loaded machine: median 0.81 s
    with one thread, 1.5 s with two). OpenBLAS, the BLAS of numpy's and
    OpenCV's wheels, is set through its own public openblas_set_num_threads:
    threadpoolctl does the same but its import and its scan of every loaded
    library cost 20-45 ms a process, 5-10 % of a target photo's estimate;
    it remains the way for any other BLAS. Without either the BLAS keeps its
    own setting.
    """
    libraries = _openblas_libraries()
    if libraries:
        return _openblas_threads(libraries, 1)
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return contextlib.nullcontext()
    return threadpool_limits(1, user_api="blas")


# OpenBLAS's thread setting, in the builds of numpy's wheels (scipy_openblas, 64-bit integers) and others
_OPENBLAS_SETTERS = ("openblas_set_num_threads", "scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                     "openblas_set_num_threads64_", "openblas_set_num_threads_64")


def _openblas_libraries() -> list[tuple[Callable[[], int], Callable[[int], None]]]:
    """(get, set) of the number of threads of every OpenBLAS this process has loaded (Linux: /proc/self/maps)."""
    import ctypes
    import os

    if not hasattr(os, "RTLD_NOLOAD"):
        return []

    try:
        with open("/proc/self/maps") as maps:
            paths = sorted({line.split(None, 5)[5].strip() for line in maps
                            if "openblas" in line.lower() and len(line.split(None, 5)) == 6})
    except OSError:
        return []
    found = []
    for path in paths:
        try:  # already loaded: RTLD_NOLOAD only returns its handle, its symbols stay local
            library = ctypes.CDLL(path, mode=os.RTLD_NOLOAD)
        except OSError:
            continue
        for name in _OPENBLAS_SETTERS:
            setter = getattr(library, name, None)
            getter = getattr(library, name.replace("_set_", "_get_"), None)
            if setter is not None and getter is not None:
                found.append((getter, setter))
                break
    return found


@contextlib.contextmanager
def _openblas_threads(libraries, threads: int):
    before = [get() for get, _ in libraries]
    for _, set_threads in libraries:
        set_threads(threads)
    try:
        yield
    finally:
        for (_, set_threads), n in zip(libraries, before):
            set_threads(n)


def _estimate_frames(frames, noise, s, support, solver, grid, recentre, tps, workers, known=None) -> list[PSF]:
    planes = [_locate(frame, detection, s, support, grid, tps) for frame, detection in _detections(frames, known)]
    # The light and response-curve correction of the planes (numpy, most of it without the GIL) runs beside
    # the band-limiting of the pattern (DCTs): the band needs only the windows' Jacobians, which the located
    # planes already have. A correction's error is raised first: it names the plane.

    def pattern_bands() -> dict[int, PatternBand]:
        bands = {}
        for factor in sorted({p.factor for p in planes}):
            same = [p for p in planes if p.factor == factor]
            bands[factor] = PatternBand(noise, factor, s, [j for p in same for j in p.jacobians], same[0].reference)
        return bands

    _, bands = concurrently(lambda: [_correct(plane, noise, s, support) for plane in planes], pattern_bands)
    counts = [len(p.windows) for p in planes]
    groups = _groups(counts)

    def record(plane: _TargetPlane, r: dict) -> PSF:
        return _psf(plane, r, s, support, solver, grid, recentre, tps)

    solved = _run_windows(planes, bands, groups, solver, workers, record)
    results = {job: psf for group, psfs in zip(groups, solved) for job, psf in zip(group, psfs)}
    return [results[i, k] for i in range(len(planes)) for k in range(counts[i])]  # plane after plane


def _groups(counts: list[int]) -> list[list[tuple[int, int]]]:
    """The (plane, window) jobs in groups that one process solves in turn: the same window of every plane.

    The planes lie half a pixel apart, so those windows' bands nearly agree and
    each is read from the part kept for the previous one (`PatternBand.read`).
    A group starts with nothing kept, so every PSF depends on its group only,
    never on what a worker happened to solve before: the same bits for any
    number of workers. A single window's planes make two groups (both cores).
    """
    groups = [[(i, k) for i in range(len(counts)) if k < counts[i]] for k in range(max(counts))]
    if len(groups) == 1 and len(groups[0]) > 1:
        half = (len(groups[0]) + 1) // 2
        groups = [groups[0][:half], groups[0][half:]]
    return groups


def _detections(frames: list[Frame], known: list[detect.Detection | EstimationError | None] | None = None):
    """(frame, detection) for every frame: one search per photograph, refined on its other planes; a frame's
    ``known`` detection (if not None) is taken as it is, and a ``known`` error is raised as `_search` raises its
    own."""
    found: dict[str, tuple[Frame, detect.Detection]] = {}
    order = sorted(range(len(frames)), key=lambda i: frames[i].channel != "g1")  # search on g1 when there
    detections = {i: d for i, d in enumerate(known or []) if d is not None}
    for i in order:
        frame = frames[i]
        clipped = float(np.mean(frame.saturated)) if frame.saturated.size else 0.0
        if clipped > OVEREXPOSED:  # the cause, named before the detection it defeats fails
            raise SaturatedError(f"{frame.source} ({frame.channel}): {clipped:.0%} of the frame is saturated; "
                                 "lower the exposure")
        if not isinstance(detections.get(i), detect.Detection):
            detections[i] = _search(frame, found, detections.get(i))
        if frame.from_mosaic:
            found.setdefault(frame.source, (frame, detections[i]))
    return [(frames[i], detections[i]) for i in range(len(frames))]


def _search(frame: Frame, found: dict[str, tuple[Frame, detect.Detection]],
            failed: EstimationError | None = None) -> detect.Detection:
    """The target in one plane: refined from another plane of the same photograph when one was searched
    (``found``, by source), else searched; ``failed``, the error of a search already made on it, is raised
    where it would be searched again."""
    image = np.asarray(frame.data)
    try:
        if frame.from_mosaic and frame.source in found:
            first, detection = found[frame.source]
            try:
                return detect.refine_target(image, detection, frame.saturated,
                                            detect.plane_shift(first.offset, frame.offset))
            except EstimationError:  # a mark lost on this plane: search it on its own
                pass
        if failed is not None:
            raise failed
        return detect.find_target(image, frame.saturated)
    except EstimationError as exc:  # say which of several frames and planes could not be used
        if isinstance(exc, TargetNotFoundError) and _seen_mirrored(image, frame.saturated):
            exc = TargetNotFoundError("the target is seen mirrored (in a mirror, or a transparency from behind); "
                                      "psfd reads it as printed: photograph its printed side directly")
        raise type(exc)(f"{frame.source} ({frame.channel}): {exc}") from None


def _seen_mirrored(image: np.ndarray, saturated: np.ndarray | None) -> bool:
    """Whether the target is in the left-right mirror image of a plane where it was not found.

    No quarter turn of the published layout matches its mirror image (the hourglasses would lie across
    their rows), so the detector rightly finds no target there; asked only once the search has failed, so
    that the one line says what is wrong rather than that nothing is there. A vertical flip is a half
    turn of a horizontal one: this one search covers both.
    """
    flipped = None if saturated is None else np.ascontiguousarray(saturated[:, ::-1])
    try:
        detect.find_target(np.ascontiguousarray(image[:, ::-1]), flipped)
    except EstimationError:
        return False
    return True


class _TargetPlane(_Plane):
    """A plane of a photograph cropped to the target, corrected, with what its PSFs record.

    Built in two steps: `_locate` (the maps, the crop ``box`` and the windows:
    all the band-limiting needs) and `_correct` (the normalised values ``v``,
    ``alpha`` and ``tail``).
    """

    frame: Frame
    box: tuple[int, int, int, int]
    maps: tuple[Map, Map]  # (to_image, to_pattern) of the whole plane
    offset: tuple[int, int]
    alpha: float
    tail: float
    scale: float
    geometry: str


def _prepare(
    frame: Frame, detection: detect.Detection, noise: np.ndarray, s: int, support: int, grid: tuple[int, int],
    tps: float | None,
) -> _TargetPlane:
    """The map D of a detection, the target's crop of the plane normalised, and its windows."""
    return _correct(_locate(frame, detection, s, support, grid, tps), noise, s, support)


def _locate(frame: Frame, detection: detect.Detection, s: int, support: int, grid: tuple[int, int],
            tps: float | None) -> _TargetPlane:
    """The map D of a detection, the target's crop box and its windows; ``v`` not yet computed."""
    try:
        # the map D (IJCV 2012 sec. 4; Delbracio PhD thesis 2013, App. A.1; geometry.target_maps)
        to_image, to_pattern = geometry.target_maps(detection, "auto" if tps is None else float(tps))
        box = _target_box(to_image, frame.shape, margin=(support - 1) // (2 * s) + 2)
        x0, y0, x1, y1 = box

        def local_to_pattern(x, y):
            return to_pattern(np.asarray(x) + x0, np.asarray(y) + y0)

        # the windows need only the crop's shape: a read-only zero of that shape stands for v until `_correct`
        plane = _TargetPlane(np.broadcast_to(0.0, (y1 - y0, x1 - x0)), local_to_pattern, s, support, grid)
    except EstimationError as exc:
        raise type(exc)(f"{frame.source} ({frame.channel}): {exc}") from None
    plane.frame, plane.box, plane.maps, plane.offset = frame, box, (to_image, to_pattern), (x0, y0)
    plane.scale = s * float(detection.scale)  # s / t, with 1/t = image pixels per cell
    plane.geometry = "homography+radial" if tps is None else f"homography+tps({float(tps):g})"
    return plane


def _correct(plane: _TargetPlane, noise: np.ndarray, s: int, support: int) -> _TargetPlane:
    """``plane`` with its crop's illumination and response curve corrected (`_corrected`)."""
    frame = plane.frame
    image = np.asarray(frame.data, dtype=np.float64)
    try:
        plane.v, plane.alpha, plane.tail = _corrected(frame, image, plane.box, *plane.maps, noise,
                                                      (support - 1) / (2 * s))
    except EstimationError as exc:
        raise type(exc)(f"{frame.source} ({frame.channel}): {exc}") from None
    return plane


# s-grid samples of all windows together below which forking workers costs more than it gains
_MIN_PARALLEL_SAMPLES = 200_000


def _run_windows(planes: list[_TargetPlane], bands: dict, groups: list[list[tuple[int, int]]], solver: str,
                 workers: int | None, record: Callable[[_TargetPlane, dict], object] | None = None) -> list[list]:
    """`estimate_window` of every (plane, window) job of every group (`_groups`), in order, in forked
    workers when worth it; a list of results per group.

    ``record(plane, result)``, when given, turns each window's result into
    what is returned (a `PSF`) where the window was solved: in a worker, in
    parallel, and only the records cross back to the parent, a group at a time.
    """
    if workers is None:
        samples = sum(_area(planes[i].windows[k]) * planes[i].s ** 2 for group in groups for i, k in group)
        workers = min(usable_cores(), len(groups)) if samples >= _MIN_PARALLEL_SAMPLES else 1
    return forked_map(functools.partial(_solve_group, planes, bands, groups, solver, record), len(groups), workers)


def _solve_group(planes: list[_TargetPlane], bands: dict, groups: list[list[tuple[int, int]]], solver: str,
                 record: Callable[[_TargetPlane, dict], object] | None, n: int) -> list:
    for band in bands.values():
        band.forget()
    out = []
    for i, k in groups[n]:
        plane = planes[i]
        try:
            # the normal equations stay in this process: only the record (without them) is sent back
            result = _window_result(plane, k, bands[plane.factor], solver, keep_normal=record is not None)
        except EstimationError as exc:
            frame = plane.frame
            raise type(exc)(f"{frame.source} ({frame.channel}): {exc}") from None
        out.append(result if record is None else record(plane, result))
    return out


def _area(window: tuple[int, int, int, int]) -> int:
    return (window[2] - window[0]) * (window[3] - window[1])


def _psf(plane: _TargetPlane, r: dict, s: int, support: int, solver: str, grid: tuple[int, int], recentre: bool,
         tps: float | None) -> PSF:
    """The PSF record of one window's result."""
    frame = plane.frame
    x0, y0 = plane.offset
    params = {"solver": solver, "support": support, "grid": [int(grid[0]), int(grid[1])], "crf_alpha": plane.alpha,
              "light_tail": plane.tail,
              "scale": plane.scale, "geometry": plane.geometry}
    kernel, shift = (_recentred(r["psf"], solver, r.get("normal"), r["noise_floor"]) if recentre
                     else (r["psf"], (0.0, 0.0)))
    wx0, wy0, wx1, wy1 = r["window"]
    window = (wx0 + x0, wy0 + y0, wx1 + x0, wy1 + y0)
    return PSF(
        psf=kernel,
        s=s,
        method=BERNOULLI,
        channel=frame.channel,
        sources=[frame.source],
        field=kernels.field_of_window(window, frame.shape),
        window=window,
        noise_floor=r["noise_floor"],
        residual=r["residual"],
        prediction_error=r["prediction_error"],
        params={**params, "mass": r["mass"], "samples": r["count"],
                "kernel_shift": [round(shift[0], 4), round(shift[1], 4)]},
        warnings=(_warnings(plane.scale, plane.alpha, r["mass"], s) + _mark_blur(kernel, plane.scale, s)
                  + kernels.kernel_warnings(kernel, r["noise_floor"])),
    )


def _mark_blur(kernel: np.ndarray, scale: float, s: int) -> list[str]:
    """The warning of a PSF too wide for the marks to be located at the imaging scale ``scale`` = s/t
    (`MARK_BLUR_CELLS`), or none."""
    freqs, mtf_x, mtf_y = mtf.profiles(kernel, s)
    f50 = np.nanmean([mtf.mtf50(freqs, mtf_x), mtf.mtf50(freqs, mtf_y)])
    if not f50 > 0:
        return []
    sigma = np.sqrt(np.log(2) / 2) / (np.pi * f50)  # channel pixels: a Gaussian's MTF is 1/2 there
    cells = sigma * s / scale  # a cell images to s/t / s pixel
    if cells <= MARK_BLUR_CELLS:
        return []
    closer = sigma / 3  # pixels per cell that leave a margin under MARK_BLUR_CELLS
    lower_s = (f", with -s {max(1, int(SCALE_RANGE[1] / closer))} or less (s/t up to {SCALE_RANGE[1]:g})"
               if s * closer > SCALE_RANGE[1] else "")
    return [f"the PSF (sigma about {sigma:.2f} pixel, {cells:.1f} cells) blurs the target's marks beyond where "
            f"they can be located, so its map and this PSF are off (too wide): bring the target closer, a cell "
            f"to {closer:.2f} pixel or more{lower_s}"]


def recentre(kernel: np.ndarray, shift: tuple[float, float]) -> np.ndarray:
    """The kernel translated by -``shift`` (x, y) s-grid samples, by a Fourier phase ramp (`kernels.translations`).

    h is band-limited to the s-grid band (IJCV 2012 sec. 3.1, Lemma 1), so
    its samples determine it and a sub-sample translation is exact in the
    Fourier domain.
    """
    return kernels.translations(kernel)(shift)


def _recentred(kernel: np.ndarray, solver: str, normal: tuple[np.ndarray, np.ndarray] | None = None,
               noise_floor: float = 0.0) -> tuple[np.ndarray, tuple[float, float]]:
    """The kernel with its core centred, and the shift removed (x, y samples).

    The interpolated kernel rings below 0 where the non-negative kernel has
    exact zeros; clipping that ringing keeps its positive half as mass in
    the tails, a wider PSF. When the clip would remove a mass that matters
    (`_clip_biases`) and the window's normal equations ``normal`` are given,
    the kernel is instead the non-negative least-squares solution on the
    shifted grid (`_shifted_nnls`).
    """
    total = np.zeros(2)
    out = kernel
    translated = kernels.translations(kernel)
    for _ in range(3):  # the core moves with the shift: a few passes converge
        total += kernels.core_centroid(out)
        out = translated((float(total[0]), float(total[1])))
    shift = (float(total[0]), float(total[1]))
    # ls: nothing is clipped, the ringing of a kernel of both signs adds no mass (at 150 e- on the render of
    # tests/test_accuracy.py, seeds 1-3, MTF50 recentred over not recentred: -0.2 to +0.9 %, no common sign)
    if solver == "ls":
        return kernels.normalise(out), shift
    if solver == "nnls" and normal is not None and _clip_biases(out, noise_floor):
        return _shifted_nnls(kernel, normal, shift), shift
    # the interpolation rings slightly below 0: project back as the solver did
    return kernels.clip_negatives(out), shift


# Negative mass of the translated kernel, over the window's noise floor F, above which `_recentred` re-solves
# rather than clips (`_clip_biases`): 2 / sqrt(200), twice the noise of the band-mean MTF error.
CLIP_RESOLVE = 2 / 200**0.5


def _clip_biases(translated: np.ndarray, noise_floor: float) -> bool:
    """Whether clipping the translated kernel's negative values would add a mass the window's MTF can show.

    The clip adds the negative mass m to the kernel's sum: renormalised, the
    MTF loses m / (1 + m) of its value wherever the clipped ringing's own
    transfer is small, a bias of at most m over the band. The noise alone
    makes an MTF error of std F / sqrt(2) at each frequency and F / sqrt(200)
    on its mean over the >= 100 frequencies of the band (IJCV 2012 sec. 3.1;
    tests/test_accuracy.py): below twice that (`CLIP_RESOLVE`) no statistic
    of the window tells the clip's bias from noise, and the clip is kept. m / F
    measured (bench/bench_conditions.py, seeds 1 and 2): 0.02-0.06 at 30000 e-,
    0.10-0.29 at 500 e-, 0.44-0.73 at 150 e- (where the clip cost 3-7 % of
    MTF50); 0.00-0.18, median 0.05, on the 400 windows of a simulated 24 MP
    frame's 10 x 10 grid (bench/bench_frames.py, "large"), 5 of which pay
    the re-solve (2-3 ms, a tenth of a window's solve; the clip had cost them
    1-2 % of MTF50); on img_example.pgm 0.10 whole, 0.09-0.40 on a 3 x 3 grid
    (floor 13-15 % of the kernel), 8 of 9 windows re-solved, where the clip
    cost 0.4-0.9 % of MTF50.
    """
    return float(-np.minimum(translated, 0.0).sum()) > CLIP_RESOLVE * noise_floor


def _shifted_nnls(kernel: np.ndarray, normal: tuple[np.ndarray, np.ndarray], shift: tuple[float, float]) -> np.ndarray:
    """The non-negative least-squares kernel of ``normal`` on the grid translated by -``shift``, unit sum.

    With T the translation as a linear map of the samples, the translated
    kernel g = T h of the solution h of min ||A h - v||^2, h >= 0 is, for
    an orthogonal T, the solution of min ||A T^T g - v||^2 subject to g >= 0
    instead of h >= 0: the non-negative solve of the normal equations
    (T Q T^T, T c) (IJCV 2012, problem (P), on the shifted grid), started
    from the positive samples of T h. A circular Fourier translation of an
    odd number of samples is real and orthogonal (`_circular_shift`); a
    separable one is T_y kron T_x, applied along each axis (`_separable`).
    Its wrap-around moves the few samples that leave one edge to the other,
    where the kernel's tail is down to the noise; its LS solution is exactly
    T h_ls, so nothing but the constraint's grid changes. The zero-padded
    translation of `kernels.translations` is instead a k x k block of an
    orthogonal map of 2k x 2k samples: what leaves the support is lost, it is
    neither orthogonal nor exactly invertible on the kernel's samples.
    """
    q, c = normal
    k = kernel.shape[0]
    ty, tx = _circular_shift(k, shift[1]), _circular_shift(k, shift[0])
    # the unknowns are the kernel flipped (`normal_equations`): reversed, they are in the order of ``kernel``
    q, c = q[::-1, ::-1], c[::-1]
    tq = _separable(ty, tx, _separable(ty, tx, q).T)  # T (Q T^T), Q symmetric
    tc = _separable(ty, tx, c)[:, 0]
    start = _separable(ty, tx, kernel.ravel())[:, 0] > 0
    return kernels.normalise(nnls_normal(tq, tc, start).reshape(k, k))


def _circular_shift(size: int, shift: float) -> np.ndarray:
    """The matrix of the circular translation by -``shift`` samples of an odd number of samples.

    A Fourier phase ramp as `kernels.translations`, without its padding: with
    an odd size there is no Nyquist frequency, the ramp is Hermitian, so the
    matrix is real, and a phase ramp between a unitary DFT and its inverse
    is unitary, so the real matrix is orthogonal.
    """
    ramp = np.exp(2j * np.pi * np.fft.fftfreq(size) * shift)
    return np.real(np.fft.ifft(ramp[:, None] * np.fft.fft(np.eye(size), axis=0), axis=0))


def _separable(ty: np.ndarray, tx: np.ndarray, m: np.ndarray) -> np.ndarray:
    """(T_y kron T_x) m for m with k^2 rows (k x k samples, row-major), one axis at a time: 2 k^3 multiply-adds
    per column instead of k^4."""
    k = tx.shape[0]
    rows = np.tensordot(ty, m.reshape(k, k, -1), axes=1)  # along y
    return np.matmul(tx, rows).reshape(k * k, -1)  # along x


def _corrected(
    frame: Frame, image: np.ndarray, box: tuple[int, int, int, int], to_image: Map, to_pattern: Map,
    noise: np.ndarray, reach: float,
) -> tuple[np.ndarray, float, float]:
    """The target crop with illumination and response curve corrected, the curve's alpha and the light
    model's tail amplitude (`radiometry.Light`).

    ``reach``: half the PSF support in pixels; the light model fits the PSF's tail beyond it.

    Raises SaturatedError when a clipped photosite falls on the target: the
    linear model (M) does not hold there (IJCV 2012 sec. 2).
    """
    x0, y0, x1, y1 = box
    yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float64)
    X, Y = to_pattern(xx, yy)
    on_target = (X >= 0) & (X < target.SIZE) & (Y >= 0) & (Y < target.SIZE)
    clipped = int(np.count_nonzero(frame.saturated[y0:y1, x0:x1] & on_target))
    if clipped:
        # estimate_target's message names the frame and the channel
        raise SaturatedError(f"{clipped} saturated pixels on the target; lower the exposure")
    # illumination: v' = (v - B) / (W - B), quadratic B and W from the flat squares (IJCV 2012 sec. 4),
    # with the light the PSF's far tail brings into them (radiometry.illumination)
    black, white, tail = radiometry.illumination(image, to_image, to_pattern, reach, noise)
    v = radiometry.normalise(image[y0:y1, x0:x1], black, white, xx, yy)
    # response curve: phi(v') = alpha v'^2 + (1 - alpha) v' with the noise region averaging what its
    # printed cells average (IJCV 2012 sec. 4 takes 1/2; the published pattern averages 0.502)
    lo, hi = target.NOISE_START, target.NOISE_STOP
    core = (X >= lo) & (X < hi) & (Y >= lo) & (Y < hi)
    alpha = float(radiometry.crf_alpha(v[core], _visible_mean(noise, to_image, box)))
    return radiometry.apply_crf(v, alpha), alpha, tail


def _visible_mean(noise: np.ndarray, to_image: Map, box: tuple[int, int, int, int]) -> float:
    """Mean of the noise cells whose centres fall inside ``box`` (the whole pattern's mean when it is all in view).

    Each cell counts once: the blur spreads every pixel over several cells, so
    the pixels average the cells by area. Reading the cell under each pixel
    centre instead would sample one cell in ten at 0.3 pixel per cell, an error
    of +-0.006 on the mean and +-0.03 on alpha.
    """
    centres = np.arange(target.NOISE) + target.NOISE_START + 0.5
    X, Y = np.meshgrid(centres, centres)
    x, y = to_image(X, Y)
    x0, y0, x1, y1 = box
    inside = (x >= x0) & (x <= x1 - 1) & (y >= y0) & (y <= y1 - 1)
    return float(noise[inside].mean()) if inside.any() else float(noise.mean())


def _check_arguments(s: int, support: int | None, solver: str, grid: tuple[int, int]) -> int:
    _, support, _ = check_sizes(s, support, grid)
    check_solver(solver)
    return support


def _check_noise(noise: np.ndarray | None) -> np.ndarray:
    if noise is None:
        return target.default_noise()
    noise = np.asarray(noise, dtype=np.float64)
    if noise.shape != (target.NOISE, target.NOISE):
        raise BadInputError(f"noise pattern must be {target.NOISE}x{target.NOISE} cells, got {noise.shape}")
    return noise


def _target_box(to_image: Map, shape: tuple[int, int], margin: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) of the plane rectangle holding the whole target, plus ``margin``."""
    x0, y0, x1, y1 = geometry.image_box(to_image, (0.0, 0.0, target.SIZE, target.SIZE), shape, margin, 33)
    if x1 - x0 < 8 or y1 - y0 < 8:
        raise EstimationError("the detected target lies outside the image")
    return x0, y0, x1, y1


def _warnings(scale: float, alpha: float, mass: float, s: int) -> list[str]:
    notes = []
    if not SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]:
        # s/t = 1 (a cell at 1/s pixel), unless the target would then be too small to be found (s >= 6)
        smallest = 1.0 / s < TARGET_MIN_PX_PER_CELL
        cell = f"{TARGET_MIN_PX_PER_CELL:g}" if smallest else f"{1.0 / s:.2g}"
        found = (f" (the target is found from {TARGET_MIN_PX_PER_CELL:g} pixel per cell: s/t = "
                 f"{s * TARGET_MIN_PX_PER_CELL:.2g} at s = {s})" if smallest else "")
        notes.append(
            f"imaging scale s/t = {scale:.2f} is outside [{SCALE_RANGE[0]}, {SCALE_RANGE[1]}] "
            f"(IJCV 2012 sec. 3.3): move the target so a cell images to about {cell} pixel{found}"
        )
    if abs(alpha) > 1:
        notes.append(f"response-curve coefficient {alpha:.2f} makes the correction non-monotone")
    if abs(mass - 1.0) > 0.1:
        # unit area is expected, not imposed (IJCV 2012 sec. 4): a large gap means a bad light model
        notes.append(f"kernel mass {mass:.2f} before normalisation (expected 1): check the illumination fit")
    return notes
