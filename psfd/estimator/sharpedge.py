"""Sharp-edge prediction PSF estimate (Joshi, Szeliski, Kriegman, CVPR 2008): the baseline.

The method predicts a sharp image near strong edges and solves the masked,
regularised, non-negative least squares (Joshi et al., CVPR 2008, eq. (5))

    L(K) = ||M(B) - M(D(I_H * K))||^2 / sigma^2 + lambda gamma ||grad K||^2,   K >= 0,

with gamma = (2R + 1)^2 and lambda = 2, on the s-times grid (sec. 5.1).

Blind form (sec. 4.1): sub-pixel difference-of-Gaussians edges, the local
maximum and minimum found by marching along each edge normal with the 90 %
hysteresis rule, propagated to both sides up to the sub-pixel edge location.
Target form (sec. 4.2): the printed edge target (`edge_target`) located by
its checkerboard corners, rendered at s times through the fitted
homography and radial distortion, and shaded from the photograph; a frame
of the Bernoulli target instead offers the step edges of its marks. An edge
point whose marches would meet another edge of the pattern takes the levels
of its nearest edge points whose marches do not.

Only the observed pixels whose whole kernel footprint is predicted enter the
normal equations, a small share of a photograph: the work is cut into tiles
of TILE_PX pixels and the s-grid is evaluated only on the footprints of
pixels that may qualify, coarse to fine, never whole. Memory stays bounded
and the time follows the edges, not the area, with the same estimate as
predicting every sample of the s-grid.
"""

from __future__ import annotations

import copy
import os
from dataclasses import dataclass, fields
from typing import Callable

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from psfd.errors import BadInputError, EstimationError, TargetNotFoundError
from psfd.vocabulary import DEFAULT_S, SHARP_EDGE, check_sizes
from psfd.estimator import target
from psfd.estimator.kernels import MORE_SIGNAL, PSF, field_of_window, kernel_warnings, split_grid
from psfd.estimator.nnls import nnls_normal
from psfd.estimator.raw import Frame

__all__ = [
    "SQUARES", "Edgels", "KnownPattern", "TargetView", "bernoulli_marks", "bernoulli_pattern", "detect_edges",
    "edge_levels", "edge_pattern", "edge_target", "edge_target_in", "estimate_edges", "locate_pattern",
    "locate_target", "noise_sigma", "solve_kernel"
]

TILE = 2  # squares per tile side of the edge target
DISK = 0.3  # disk radius of the edge target, in squares
SQUARES = (8, 8)  # squares of the printed edge target (inner corners: 7 x 7)
BORDER = 1.0  # white margin of the print, in squares


def edge_pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Reflectance of the edge target at pattern coordinates (unit = one square).

    Our rendition of the paper's target (CVPR 2008, sec. 4.2, Fig. 3; the
    figure itself is not in the text): a checkerboard, whose balanced corners
    register the print without blur-induced shift, and in every square a disk
    of the opposite colour made of four 90-degree arcs, so that step edges
    cover all orientations equally.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    ix, iy = np.floor(x), np.floor(y)
    black = (ix + iy) % 2 == 0
    inside = (x - ix - 0.5) ** 2 + (y - iy - 0.5) ** 2 < DISK**2
    return np.where(black ^ inside, 0.0, 1.0)


def edge_target(
    squares: tuple[int, int] = SQUARES, px_per_square: float = 64.0, border: float = BORDER
) -> np.ndarray:
    """Raster of the edge target: ``squares`` = (nx, ny) squares, white ``border`` (in squares) around.

    Parameters
    ----------
    squares : (int, int)
        Squares across and down (even: whole tiles).
    px_per_square : float
        Raster pixels per square side.
    border : float
        White margin, in squares, on each side.

    Returns
    -------
    ndarray of float64, 0 black and 1 white; raster pixel centre (i, j) is the
    pattern point ((j + 0.5) / px_per_square - border, (i + 0.5) / px_per_square - border).
    """
    nx, ny = squares
    cols = int(round((nx + 2 * border) * px_per_square))
    rows = int(round((ny + 2 * border) * px_per_square))
    x = (np.arange(cols) + 0.5) / px_per_square - border
    y = (np.arange(rows) + 0.5) / px_per_square - border
    out = edge_pattern(x[None, :], y[:, None])
    outside = (x[None, :] < 0) | (x[None, :] >= nx) | (y[:, None] < 0) | (y[:, None] >= ny)
    out[outside] = 1.0
    return out


# --------------------------------------------------------------------------- blind prediction (sec. 4.1)

ORIENTATION_BINS = 18  # 10-degree bins over [0, 180): an edge and its flipped twin constrain the same slice
MIN_PER_BIN = 100  # edges per orientation bin (sec. 5.2, test (b))
# the blind method's signal is the photograph's own edges: more light or a longer exposure gives it few more
_MORE_EDGES = ("a photograph with long straight edges in every direction (or of a printed target, with --target), "
               "a lower -s, or a larger window (fewer --grid windows)")
LAMBDA = 2.0  # smoothness weight found "to work well" (sec. 5)
DOG_RATIO = 1.6  # sigma2 / sigma1 of the difference of Gaussians


@dataclass
class Edgels:
    """Sub-pixel edge points of one image.

    Attributes
    ----------
    x, y : ndarray
        Position in pixels (pixel centres at integers).
    nx, ny : ndarray
        Unit normal pointing from the dark to the bright side.
    strength : ndarray
        Smoothed gradient magnitude at the point.
    lo, hi : ndarray
        Predicted sharp values on the dark and the bright side (nan until `edge_levels`).
    """

    x: np.ndarray
    y: np.ndarray
    nx: np.ndarray
    ny: np.ndarray
    strength: np.ndarray
    lo: np.ndarray
    hi: np.ndarray

    def __len__(self) -> int:
        return int(self.x.size)

    def subset(self, keep: np.ndarray) -> "Edgels":
        return Edgels(*(getattr(self, f.name)[keep] for f in fields(self)))

    def orientation_histogram(self) -> np.ndarray:
        """Edge counts in 10-degree bins of the normal's direction over [0, 180) (sec. 5.2)."""
        angle = np.degrees(np.arctan2(self.ny, self.nx)) % 180.0
        return np.bincount((angle // (180.0 / ORIENTATION_BINS)).astype(int) % ORIENTATION_BINS,
                           minlength=ORIENTATION_BINS)


class _Scaled:
    """A channel plane over its white level, divided where it is read.

    A float64 copy of a 24-megapixel frame's plane is 48 MB, and the edge
    search reads the plane strip by strip and the accumulation pixel by pixel:
    each read divides only what it takes, element by element the same values
    as dividing the whole plane at once.
    """

    def __init__(self, data: np.ndarray, white: float) -> None:
        self.data, self.white = data, float(white)

    @property
    def shape(self) -> tuple[int, ...]:
        return self.data.shape

    def __getitem__(self, key) -> np.ndarray:
        return np.true_divide(self.data[key], self.white, dtype=np.float64)

    def crop(self, y0: int, y1: int, x0: int, x1: int) -> "_Scaled":
        return _Scaled(self.data[y0:y1, x0:x1], self.white)


def _plane(image) -> "_Scaled | np.ndarray":
    """A `_Scaled` plane as it is, anything else as a float64 array."""
    return image if isinstance(image, _Scaled) else np.asarray(image, dtype=np.float64)


STRIP = 512  # rows of a plane read at once where a whole-plane statistic is computed (even: whole 2 x 2 blocks)


def noise_sigma(image: "np.ndarray | _Scaled", blocks: np.ndarray | None = None) -> float:
    """Noise standard deviation from the finest diagonal Haar sub-band, median(|HH|) / 0.6745.

    Stands in for the Liu et al. estimator the paper uses (sec. 5): the
    diagonal detail of 2 x 2 blocks is almost free of image content away from
    edges, and the median ignores the edges. ``blocks`` (rows // 2, cols // 2),
    optional: the 2 x 2 blocks to take, all by default.
    """
    a = _plane(image)
    rows, cols = (a.shape[0] // 2) * 2, (a.shape[1] // 2) * 2
    parts = []
    for y0 in range(0, rows, STRIP):  # strips of whole 2 x 2 blocks: only |HH| is held, a quarter of the plane
        b = a[y0 : min(y0 + STRIP, rows), :cols]
        hh = (b[0::2, 0::2] - b[0::2, 1::2] - b[1::2, 0::2] + b[1::2, 1::2]) / 2.0
        hh = np.abs(hh, out=hh)
        parts.append(hh.ravel() if blocks is None else hh[blocks[y0 // 2 : y0 // 2 + hh.shape[0]]])
    return float(np.median(np.concatenate(parts) if parts else np.zeros(0)) / 0.6745)


TILE_PX = 128  # channel pixels per side of the tiles the work is cut into: memory stays bounded on any frame


TRIM_EVERY = 256  # tiles between two returns of the freed heap to the system (`_trim_heap`)
_MALLOC_TRIM: list = []  # glibc's malloc_trim, or None elsewhere: looked up once


def _trim_heap() -> None:
    """Hand the heap's freed pages back to the system (glibc's ``malloc_trim(0)``); nothing on other C libraries.

    The tile-sized temporaries of the edge search and the accumulation leave
    glibc's heap fragmented: the process would keep its largest footprint of
    every step, and each plane of a 24-megapixel frame would add to it. glibc
    offers no option for this through Python, hence ctypes.
    """
    if not _MALLOC_TRIM:
        trim = None
        if hasattr(os, "confstr") and "glibc" in (_confstr("CS_GNU_LIBC_VERSION") or ""):
            import ctypes

            trim = getattr(ctypes.CDLL(None), "malloc_trim", None)
        _MALLOC_TRIM.append(trim)
    if _MALLOC_TRIM[0] is not None:
        _MALLOC_TRIM[0](0)


def _confstr(name: str) -> str | None:
    try:
        return os.confstr(name)
    except (ValueError, OSError):
        return None


def _tiles(rows: tuple[int, int], cols: tuple[int, int], size: int = TILE_PX):
    """Row-major tiles (y0, y1, x0, x1) covering ``rows[0]:rows[1]`` x ``cols[0]:cols[1]``."""
    for y0 in range(rows[0], rows[1], size):
        for x0 in range(cols[0], cols[1], size):
            yield y0, min(y0 + size, rows[1]), x0, min(x0 + size, cols[1])


# --------------------------------------------------------------------------- filters without scipy
# scipy.ndimage and scipy.spatial cost 0.5-0.65 s of imports, a fifth of `psfd estimate edges` on a
# 2.5-megapixel frame: the few of their functions this module needs are written here with numpy and
# OpenCV, and give the same bits (tests/test_scipy_reference.py).


def _gauss_radius(sd: float) -> int:
    """Half-width of the Gaussian kernel of `_gaussian_filter` (scipy.ndimage.gaussian_filter's: truncated at 4 sd)."""
    return int(4.0 * sd + 0.5)


def _gaussian_filter(image: np.ndarray, sd: float) -> np.ndarray:
    """scipy.ndimage.gaussian_filter(image, sd) (mode "reflect"), bit for bit: the same normalised kernel, and the
    same arithmetic, axis by axis in float64, each pass stored in the image's type: the centre tap, then each pair
    of taps at +-j summed first, from the outermost in."""
    radius = _gauss_radius(sd)
    x = np.arange(-radius, radius + 1)
    weights = np.exp(-0.5 / (sd * sd) * x**2)
    weights /= weights.sum()
    image = np.asarray(image)
    out = image
    for axis in range(image.ndim):
        line = out.astype(np.float64)
        n = line.shape[axis]
        padded = _reflected(line, radius, axis)

        def taps(k: int) -> np.ndarray:  # the samples k - radius away from each output sample
            return padded[(slice(None),) * axis + (slice(k, k + n),)]

        summed = taps(radius) * weights[radius]
        pair = np.empty_like(summed)
        for j in range(radius, 0, -1):
            np.add(taps(radius - j), taps(radius + j), out=pair)
            pair *= weights[radius - j]
            summed += pair
        out = summed.astype(image.dtype, copy=False)
    return out


def _reflected(line: np.ndarray, radius: int, axis: int) -> np.ndarray:
    """``line`` extended by ``radius`` samples at both ends of ``axis`` as "reflect" extends it (d c b a | a b c d)."""
    n = line.shape[axis]
    if radius > n:  # reflected more than once: numpy's "symmetric" padding repeats it
        return np.pad(line, [(radius, radius) if a == axis else (0, 0) for a in range(line.ndim)], mode="symmetric")
    index = np.concatenate([np.arange(radius - 1, -1, -1), np.arange(n), np.arange(n - 1, n - 1 - radius, -1)])
    return np.take(line, index, axis=axis)


def _bilinear(image: np.ndarray, y: np.ndarray, x: np.ndarray, nearest: bool = False) -> np.ndarray:
    """scipy.ndimage.map_coordinates(image, [y, x], order=1) of a float64 image, bit for bit: mode "constant"
    (0 outside the rows 0 .. rows - 1 and columns 0 .. cols - 1), or "nearest" (the edge samples repeated).
    Each of the four neighbours times its row weight, then its column weight, summed in row-major order."""
    rows, cols = image.shape
    y0, x0 = np.floor(y), np.floor(x)
    ty, tx = y - y0, x - x0
    row_weights, col_weights = (1.0 - ty, ty), (1.0 - tx, tx)
    y0, x0 = y0.astype(np.intp), x0.astype(np.intp)
    # out of the image a neighbour reads its edge sample: the value for "nearest", zero weight or dropped below
    starts = (np.clip(y0, 0, rows - 1) * cols, np.clip(y0 + 1, 0, rows - 1) * cols)
    xs = (np.clip(x0, 0, cols - 1), np.clip(x0 + 1, 0, cols - 1))
    flat = np.ascontiguousarray(image).ravel()
    out = np.zeros(np.shape(y))
    for a in (0, 1):
        for b in (0, 1):
            term = flat.take(starts[a] + xs[b])
            term *= row_weights[a]
            term *= col_weights[b]
            out += term
    if nearest:
        return out
    return np.where((y >= 0) & (y <= rows - 1) & (x >= 0) & (x <= cols - 1), out, 0.0)


def _dilate(mask: np.ndarray, iterations: int) -> np.ndarray:
    """scipy.ndimage.binary_dilation(mask, iterations=iterations): that many dilations by the 4-neighbour cross
    are one by the diamond of that radius, nothing entering from outside the image."""
    r = int(iterations)
    y, x = np.mgrid[-r : r + 1, -r : r + 1]
    diamond = (np.abs(y) + np.abs(x) <= r).astype(np.uint8)
    return cv2.dilate(mask.astype(np.uint8), diamond, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


class _NearestPoints:
    """The nearest of a set of points (x, y) within a distance, as scipy.spatial.cKDTree.query with
    ``distance_upper_bound`` finds it.

    OpenCV's exact single k-d tree (FLANN, no approximation) works in float32: the two nearest it finds
    are ranked again by their float64 distances, which agreed with cKDTree on all of 9 million queries
    around the edge points of a real photograph (the first alone missed 25 near ties). Exact ties may be
    broken otherwise than by cKDTree: blind edge points lie where the photograph puts them, and ties
    are rare (the real photograph's PSF moved by 1e-14), unlike the target form's (`_TiedPoints`). It
    releases the GIL as the k-d tree did, for `_accumulate`'s second thread.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray) -> None:
        self.x, self.y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        points = np.column_stack([self.x, self.y]).astype(np.float32)
        self.index = cv2.flann_Index(points, {"algorithm": 4, "leaf_max_size": 10})  # FLANN_INDEX_KDTREE_SINGLE

    def query(self, x: np.ndarray, y: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """(found, index): whether a point lies closer than ``bound`` to each (x, y), and the nearest's index
        (meaningful where found)."""
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        k = min(2, self.x.size)
        candidates, _ = self.index.knnSearch(np.column_stack([x, y]).astype(np.float32), k, params={"eps": 0.0})
        dx = x[:, None] - self.x[candidates]
        dy = y[:, None] - self.y[candidates]
        d2 = dx * dx + dy * dy
        best = np.argmin(d2, axis=1)
        at = np.arange(x.size)
        return d2[at, best] < bound * bound, candidates[at, best]


class _TiedPoints:
    """The nearest of a set of points on the s-grid within a distance, all of them where several are as near,
    for the target form (`_TargetPrediction`).

    There the edge points and the samples lie on the same s-grid (`_target_edges`), and one query in five
    is an exact tie between two or more edge points. Taking one of them, as a k-d tree's layout happened
    to rank them, made the PSF depend on that rank: on the example photo, the other tied point moved it
    by 0.035 and the points in reverse order by 0.050 (a third of its noise floor, 0.15), for the levels of
    neighbouring edge points differ, most near the pattern's corners. So every tied point is returned and
    the prediction averages their levels, whatever the points' order. Points and samples are given in
    samples, integers: squared distances are exact integers, and so are the ties. OpenCV's exact single
    k-d tree (FLANN) proposes the candidates; its float32 holds integers below 2^24 exactly.
    """

    FIRST = 4  # candidates asked first: ties of 4 or 5 points are rare (168 of 48,600 queries of the example photo)

    def __init__(self, i: np.ndarray, j: np.ndarray) -> None:
        self.i, self.j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
        points = np.column_stack([self.j, self.i]).astype(np.float32)
        self.index = cv2.flann_Index(points, {"algorithm": 4, "leaf_max_size": 10})  # FLANN_INDEX_KDTREE_SINGLE

    def query(self, i: np.ndarray, j: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(found, sample, point): whether a point lies closer than ``bound`` samples to each sample (i, j), and
        the pairs (sample, point) of every found sample with each of its nearest points, grouped by sample."""
        i, j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
        found = np.zeros(i.size, dtype=bool)
        samples, points = [np.zeros(0, np.intp)], [np.zeros(0, np.intp)]
        rows, k = np.arange(i.size), min(self.FIRST, self.i.size)
        while rows.size:
            query = np.column_stack([j[rows], i[rows]]).astype(np.float32)
            index, _ = self.index.knnSearch(query, k, params={"eps": 0.0})
            d2 = (i[rows, None] - self.i[index]) ** 2 + (j[rows, None] - self.j[index]) ** 2
            tied = d2 == d2.min(axis=1, keepdims=True)
            more = tied.all(axis=1) & (k < self.i.size)  # all candidates tied: more points may be as near
            hit = ~more & (d2.min(axis=1) < bound * bound)
            found[rows[hit]] = True
            r, c = np.nonzero(tied & hit[:, None])
            samples.append(rows[r])
            points.append(index[r, c].astype(np.intp))
            rows, k = rows[more], min(2 * k, self.i.size)
        return found, np.concatenate(samples), np.concatenate(points)


def _edge_maps(image: np.ndarray, tile: tuple[int, int, int, int], sigma: float, halo: int, dog: bool = True):
    """DoG, smoothed gradient and its magnitude on a tile and ``halo`` pixels around it (within the image).

    Returns the region's first (row, col) and the four maps; inside the tile they are the
    whole image's values, as the filters reach less than ``halo`` pixels. Without ``dog``
    the DoG map is None (its wider Gaussian is not computed).
    """
    y0, y1, x0, x1 = tile
    oy, ox = max(0, y0 - halo), max(0, x0 - halo)
    region = image[oy : min(image.shape[0], y1 + halo), ox : min(image.shape[1], x1 + halo)]
    g1 = _gaussian_filter(region, sigma)
    difference = g1 - _gaussian_filter(region, DOG_RATIO * sigma) if dog else None
    gy, gx = np.gradient(g1)
    return (oy, ox), difference, gx, gy, np.hypot(gx, gy)


def _percentile(parts, total: int, q: float) -> float:
    """``np.percentile`` (linear) of ``total`` values given in parts, keeping only the largest.

    The share above the percentile (here 0.5 %) is all that is kept, so the
    magnitudes of a whole frame are never held at once; the two order
    statistics and their interpolation are numpy's (`numpy.percentile`,
    method "linear": index q (n - 1), weight on the upper neighbour).
    """
    virtual = (total - 1) * np.true_divide(q, 100)  # numpy's virtual index of the method "linear"
    lower = int(np.floor(virtual))
    gamma = virtual - lower
    keep = total - lower  # ranks lower .. total - 1, ascending
    top = np.empty(0)
    for values in parts:
        top = np.concatenate([top, np.ravel(values)])
        if top.size > 4 * keep + 65536:
            top = np.partition(top, top.size - keep)[top.size - keep :]
    top = np.sort(np.partition(top, top.size - keep)[top.size - keep :] if top.size > keep else top)
    a, b = top[0], top[min(1, top.size - 1)]
    difference = b - a
    # numpy's _lerp: from the nearer neighbour
    return float(b - difference * (1 - gamma) if gamma >= 0.5 else a + difference * gamma)


def detect_edges(image: np.ndarray, sigma: float = 1.0, threshold: float | None = None,
                 noise: float | None = None) -> Edgels:
    """Sub-pixel difference-of-Gaussians edges (sec. 4.1).

    An edge point is a zero crossing of DoG = G_sigma * I - G_1.6sigma * I,
    followed from a pixel one step along the smoothed gradient, where DoG
    passes from negative (dark side) to positive (bright side); its position
    is the linear interpolation of the crossing.

    The maps are computed tile by tile with a margin wider than the filters,
    so that memory stays bounded on any frame and every value is the one the
    whole image would give; edge points come out in raster order of their pixel.

    Parameters
    ----------
    image : ndarray, 2-D
    sigma : float
        Scale of the inner Gaussian, pixels.
    threshold : float, optional
        Minimum smoothed gradient magnitude; default: 10 times its noise level
        and a quarter of the 99.5th percentile of the magnitude.
    noise : float, optional
        Noise standard deviation of ``image`` (estimated when not given).

    Returns
    -------
    Edgels
    """
    image = _plane(image)
    rows, cols = image.shape
    # both Gaussians, the gradient, and the interpolations up to one pixel along the normal
    halo = _gauss_radius(DOG_RATIO * sigma) + 3
    tiles = list(_tiles((0, rows), (0, cols)))
    if threshold is None:
        noise = noise_sigma(image) if noise is None else noise

        def magnitudes():
            for y0, y1, x0, x1 in tiles:
                (oy, ox), _, _, _, m = _edge_maps(image, (y0, y1, x0, x1), sigma, halo, dog=False)
                yield m[y0 - oy : y1 - oy, x0 - ox : x1 - ox]

        # std of a derivative of Gaussian-smoothed white noise: sigma_n / sqrt(8 pi) / sigma^2
        threshold = max(10.0 * noise / np.sqrt(8 * np.pi) / sigma**2,
                        0.25 * _percentile(magnitudes(), rows * cols, 99.5))
    border = int(np.ceil(3 * DOG_RATIO * sigma)) + 1
    parts = []
    for y0, y1, x0, x1 in tiles:
        ty0, ty1, tx0, tx1 = max(y0, border), min(y1, rows - border), max(x0, border), min(x1, cols - border)
        if ty0 >= ty1 or tx0 >= tx1:
            continue
        (oy, ox), dog, gx, gy, mag = _edge_maps(image, (y0, y1, x0, x1), sigma, halo)
        cand = mag[ty0 - oy : ty1 - oy, tx0 - ox : tx1 - ox] >= threshold
        cand &= dog[ty0 - oy : ty1 - oy, tx0 - ox : tx1 - ox] < 0
        ly, lx = np.nonzero(cand)
        ly, lx = ly + (ty0 - oy), lx + (tx0 - ox)
        py, px = ly + oy, lx + ox
        m = mag[ly, lx]
        nx, ny = gx[ly, lx] / m, gy[ly, lx] / m
        d0 = dog[ly, lx]
        # image coordinates moved by whole pixels into the region: exactly, so the interpolation weights are the same
        d1 = _bilinear(dog, (py + ny) - oy, (px + nx) - ox)
        hit = d1 >= 0
        t = d0[hit] / (d0[hit] - d1[hit])
        x = px[hit] + t * nx[hit]
        y = py[hit] + t * ny[hit]
        strength = _bilinear(mag, y - oy, x - ox)
        keep = strength >= threshold
        parts.append((py[hit][keep] * cols + px[hit][keep], x[keep], y[keep], nx[hit][keep], ny[hit][keep],
                      strength[keep]))
    return _sorted_edgels(parts)


def _sorted_edgels(parts: list[tuple[np.ndarray, ...]]) -> Edgels:
    """Edgels from per-tile (key, x, y, nx, ny, strength) arrays, in raster order of ``key``, levels unknown."""
    if not parts:
        empty = np.zeros(0)
        return Edgels(empty, empty.copy(), empty.copy(), empty.copy(), empty.copy(), empty.copy(), empty.copy())
    key, x, y, nx, ny, strength = (np.concatenate(column) for column in zip(*parts))
    order = np.argsort(key, kind="stable")
    nan = np.full(key.size, np.nan)
    return Edgels(x[order], y[order], nx[order], ny[order], strength[order], nan, nan.copy())


def _plateau_max(profile: np.ndarray) -> np.ndarray:
    """The paper's robust maximum of profiles marching away from the edge (sec. 4.1).

    The march stops at the first sample below 90 % of the previous one; the
    maximum is the mean of the samples before it within 10 % of their peak.
    """
    drop = profile[:, 1:] < 0.9 * profile[:, :-1]
    stop = np.where(drop.any(axis=1), np.argmax(drop, axis=1) + 1, profile.shape[1])
    valid = np.arange(profile.shape[1])[None, :] < stop[:, None]
    peak = np.where(valid, profile, -np.inf).max(axis=1)
    near = valid & (profile >= 0.9 * peak[:, None])
    return np.sum(np.where(near, profile, 0.0), axis=1) / np.maximum(near.sum(axis=1), 1)


def _plateau_min(profile: np.ndarray, contrast: np.ndarray) -> np.ndarray:
    """The minimum, the analogous rule (sec. 4.1) measured in units of the edge contrast.

    A literal mirror of the 90 % rule (stop when a sample exceeds the previous
    one by 1/0.9) is meaningless near black, so the march stops when the
    profile rises again by 10 % of the contrast, and the minimum is the mean
    of the samples within 10 % of the contrast from the lowest.
    """
    tol = 0.1 * contrast[:, None]
    rise = profile[:, 1:] > profile[:, :-1] + tol
    stop = np.where(rise.any(axis=1), np.argmax(rise, axis=1) + 1, profile.shape[1])
    valid = np.arange(profile.shape[1])[None, :] < stop[:, None]
    low = np.where(valid, profile, np.inf).min(axis=1)
    near = valid & (profile <= low[:, None] + tol)
    return np.sum(np.where(near, profile, 0.0), axis=1) / np.maximum(near.sum(axis=1), 1)


def edge_levels(image: np.ndarray, edges: Edgels, length: int) -> Edgels:
    """Measure each edge's bright and dark levels by marching ``length`` pixels along its normal (sec. 4.1).

    Edges whose dark level is not below their bright level are dropped.
    """
    image = _plane(image)
    steps = np.arange(1, length + 1, dtype=np.float64)[None, :]
    lo, hi = np.empty(len(edges)), np.empty(len(edges))
    # edges come in raster order: a chunk of them spans a strip of rows, read alone (`_strip_levels`)
    for start in range(0, len(edges), LEVEL_CHUNK):
        chunk = slice(start, start + LEVEL_CHUNK)
        lo[chunk], hi[chunk] = _strip_levels(image, edges.x[chunk, None], edges.y[chunk, None],
                                             edges.nx[chunk, None], edges.ny[chunk, None], steps)
    out = Edgels(edges.x, edges.y, edges.nx, edges.ny, edges.strength, lo, hi)
    return out.subset(hi > lo)


LEVEL_CHUNK = 32768  # edge points whose levels are measured at once (`edge_levels`)


def _strip_levels(image, x, y, nx, ny, steps) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of edge points by the marches of `edge_levels`, sampling only the rows they reach.

    The strip's first row is an integer subtracted from positive coordinates:
    exact, so the bilinear weights are those of the whole plane; its rows reach
    two beyond the farthest sample, and where it stops short of the plane's
    border no sample is clamped ("nearest" only acts at the plane's own border,
    which the strip then shares).
    """
    by, bx = y + steps * ny, x + steps * nx
    dy, dx = y - steps * ny, x - steps * nx
    rows = image.shape[0]
    reach = np.concatenate([by.ravel(), dy.ravel()]) if by.size else np.zeros(1)
    y0 = int(min(max(np.floor(reach.min()) - 1, 0), rows))
    y1 = int(min(max(np.floor(reach.max()) + 3, y0 + 1), rows))
    strip = image[y0:y1]
    if y0:
        by -= y0
        dy -= y0
    bright = _bilinear(strip, by, bx, nearest=True)
    dark = _bilinear(strip, dy, dx, nearest=True)
    hi = _plateau_max(bright)
    return _plateau_min(dark, hi - dark[:, 0]), hi


# --------------------------------------------------------------------------- predicted image, normal equations (sec. 5.1)


class _BlindPrediction:
    """The blind prediction of the sharp image (secs. 4.1, 5.1), sample by sample of a crop's s-grid.

    Each s-grid sample takes the levels of its nearest edge point: the bright
    level on the bright side, the dark level on the other, and in between
    along the normal a linear ramp one s-grid sample wide centred on the
    sub-pixel edge, the paper's "simple form of anti-aliasing". Samples more
    than ``band`` pixels from the edge along its normal, or beyond the end of
    an edge, are not predicted.
    """

    def __init__(self, edges: Edgels, s: int, band: float) -> None:
        self.edges, self.s, self.band = edges, s, band
        # a predicted sample lies within band along the normal and 1 pixel along the edge of an edge point
        self.reach = float(np.hypot(band, 1.0))
        self.tree = _NearestPoints(edges.x, edges.y) if len(edges) else None

    def focus(self, box: tuple[int, int, int, int]) -> "_BlindPrediction":
        """The prediction over this block of samples: itself, it prepares nothing per block (see `_accumulate`)."""
        return self

    def predict(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(predicted, sharp) at samples (i, j), i.e. at pixel (j / s, i / s)."""
        known = np.zeros(i.shape, dtype=bool)
        sharp = np.zeros(i.shape)
        if self.tree is None or i.size == 0:
            return known, sharp
        e, s, band = self.edges, self.s, self.band
        px, py = j / s, i / s
        found, idx = self.tree.query(px, py, band * np.sqrt(2) + 1.0)
        k = idx[found]
        dx, dy = px[found] - e.x[k], py[found] - e.y[k]
        d = dx * e.nx[k] + dy * e.ny[k]  # signed distance along the normal, bright side > 0
        along = np.abs(dx * e.ny[k] - dy * e.nx[k])
        # along the edge the nearest point is at most half the spacing of edge points (~1 pixel) away;
        # more means the sample lies beyond the end of an edge
        ok = (np.abs(d) <= band) & (along <= 1.0)
        alpha = np.clip(0.5 + d[ok] * s, 0.0, 1.0)
        flat = np.flatnonzero(found)[ok]
        sharp[flat] = e.lo[k[ok]] + (e.hi[k[ok]] - e.lo[k[ok]]) * alpha
        known[flat] = True
        return known, sharp


def _levels(s: int) -> list[int]:
    """Sample strides at which footprints are checked, coarse to fine: 2s, s, s/2, ..., 1."""
    levels = [2 * s, s]
    while levels[-1] > 1:
        levels.append(levels[-1] // 2 if levels[-1] % 2 == 0 else 1)
    return levels


def _box_any(mask: np.ndarray, size: int, forward: bool) -> np.ndarray:
    """Whether any of ``size`` x ``size`` samples starting (``forward``) or ending at each position is set."""
    anchor = (0, 0) if forward else (size - 1, size - 1)
    return cv2.dilate(mask.view(np.uint8), np.ones((size, size), np.uint8), anchor=anchor) > 0


def _near_edges(edges: Edgels, shape: tuple[int, int], radius: float) -> np.ndarray:
    """Pixels whose centre is within ``radius`` of an edge point (a superset: measured from the point's pixel)."""
    marks = np.zeros(shape, np.uint8)
    if len(edges):
        iy = np.clip(np.rint(edges.y).astype(np.intp), 0, shape[0] - 1)
        ix = np.clip(np.rint(edges.x).astype(np.intp), 0, shape[1] - 1)
        marks[iy, ix] = 1
    # the point is within half a pixel diagonal of its pixel's centre
    r = radius + np.sqrt(0.5) + 1e-9
    k = int(np.floor(r))
    yy, xx = np.mgrid[-k : k + 1, -k : k + 1]
    return cv2.dilate(marks, (yy * yy + xx * xx <= r * r).astype(np.uint8)) > 0


def _gram(patches: np.ndarray, rows: np.ndarray, cols: np.ndarray, b: np.ndarray, support: int,
          ata: np.ndarray, atb: np.ndarray, chunk: int = 4096) -> float:
    """Add the rows of A (flipped patches at (rows, cols)) to A^T A and A^T b; returns b^T b."""
    n = support * support
    btb = 0.0
    for start in range(0, rows.size, chunk):
        r, c = rows[start : start + chunk], cols[start : start + chunk]
        a = patches[r, c][:, ::-1, ::-1].reshape(-1, n)
        bb = b[start : start + chunk]
        ata += a.T @ a
        atb += a.T @ bb
        btb += float(bb @ bb)
    return btb


def _normal_equations(sharp: np.ndarray, observed: np.ndarray, valid: np.ndarray, s: int, support: int,
                      chunk: int = 4096) -> tuple[np.ndarray, np.ndarray, float]:
    """A^T A, A^T b and b^T b of the masked data term ||M(B) - M(D(I_H * K))||^2 (eqs. (4), (5), sec. 5.1).

    Observed pixel (m, n) is the s-grid sample (s m, s n) of the blurred
    sharp image (point sampling D, eq. (1)). Rows are gathered in chunks so
    memory stays small whatever the window.
    """
    half = support // 2
    padded = np.pad(sharp, half)  # padded sample (s m + half) is sample s m
    patches = sliding_window_view(padded, (support, support))[::s, ::s]
    rows, cols = np.nonzero(valid)
    ata = np.zeros((support * support,) * 2)
    atb = np.zeros(support * support)
    btb = _gram(patches, rows, cols, observed[rows, cols], support, ata, atb, chunk)
    return ata, atb, btb


def _accumulate(crop: np.ndarray, candidates: np.ndarray, prediction, s: int, support: int,
                tiles: list[tuple[int, int, int, int]], progress: Callable[[], None] | None = None
                ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Normal equations of the observed pixels whose whole footprint is predicted (eq. (4)'s mask M).

    Tile by tile, the prediction is evaluated only on the footprints of
    ``candidates`` (pixels that may qualify, their footprints inside the
    s-grid), from a coarse lattice of samples to every sample: a candidate is
    dropped as soon as one sample of its footprint is not predicted, so the
    s-grid is never built whole. The tiles' predictions are independent: with
    two cores the next tiles are predicted on a second thread (the k-d tree's
    search and OpenCV release the GIL) while the equations take in the tiles
    in their order, the same sums in the same order as on one thread.

    Returns
    -------
    ata, atb, btb, and the number of pixels used.
    """
    n = support * support
    ata, atb, btb, used = np.zeros((n, n)), np.zeros(n), 0.0, 0
    done = 0
    for footprints in _tile_predictions(crop, candidates, prediction, s, support, tiles):
        if footprints is not None:
            sharp, ci, cj, observed = footprints
            btb += _gram(sliding_window_view(sharp, (support, support)), ci, cj, observed, support, ata, atb)
            used += ci.size
        if progress is not None:
            progress()
        done += 1
        if done % TRIM_EVERY == 0:
            _trim_heap()
    return ata, atb, btb, used


TILES_AHEAD = 4  # tiles handed to the two threads ahead of the equations: their temporaries stay few


def _tile_predictions(crop, candidates, prediction, s, support, tiles):
    """Each tile's `_tile_footprints`, in the tiles' order; two tiles at a time on two threads where there are two cores."""
    from psfd.workers import usable_cores

    call = lambda tile: _tile_footprints(crop, candidates, prediction, s, support, tile)  # noqa: E731
    if usable_cores() < 2 or len(tiles) < 2:
        yield from map(call, tiles)
        return
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(2) as pool:
        pending = deque(pool.submit(call, tile) for tile in tiles[:TILES_AHEAD])
        for tile in tiles[TILES_AHEAD:]:
            done = pending.popleft().result()
            pending.append(pool.submit(call, tile))
            yield done
        while pending:
            yield pending.popleft().result()


def _tile_footprints(crop, candidates, prediction, s, support, tile):
    """The predicted block of one tile and its candidates whose whole footprint is predicted, or None.

    Returns
    -------
    (sharp, ci, cj, observed): the block of s-grid samples, each kept candidate's footprint corner in it,
    and its observed value.
    """
    y0, y1, x0, x1 = tile
    cy, cx = np.nonzero(candidates[y0:y1, x0:x1])
    if not cy.size:
        return None
    half = support // 2
    grid = (s * (crop.shape[0] - 1) + 1, s * (crop.shape[1] - 1) + 1)
    cy, cx = cy + y0, cx + x0
    # the block of samples the tile's footprints cover, and each candidate's footprint corner in it
    bi0, bj0 = max(0, s * y0 - half), max(0, s * x0 - half)
    bi1, bj1 = min(grid[0], s * (y1 - 1) + half + 1), min(grid[1], s * (x1 - 1) + half + 1)
    ci, cj = s * cy - half - bi0, s * cx - half - bj0
    block = prediction.focus((bi0, bi1, bj0, bj1))
    queried = np.zeros((bi1 - bi0, bj1 - bj0), bool)
    known = np.zeros_like(queried)
    sharp = np.zeros(queried.shape)
    alive = np.ones(cy.size, bool)
    for step in _levels(s):
        if not alive.any():
            break
        corners = np.zeros_like(queried)
        corners[ci[alive], cj[alive]] = True
        # the samples of this level's lattice (multiples of step) in the footprints, not yet asked:
        # looked for on the lattice alone, in the same raster order
        i0, j0 = -bi0 % step, -bj0 % step
        lattice = (slice(i0, None, step), slice(j0, None, step))
        need = _box_any(corners, support, forward=False)[lattice]
        need &= ~queried[lattice]
        li, lj = np.nonzero(need)
        ii, jj = li * step + i0, lj * step + j0
        known[ii, jj], sharp[ii, jj] = block.predict(ii + bi0, jj + bj0)
        queried[ii, jj] = True
        alive &= ~_box_any(queried & ~known, support, forward=True)[ci, cj]
    if not alive.any():
        return None
    return sharp, ci[alive], cj[alive], crop[cy[alive], cx[alive]]


# --------------------------------------------------------------------------- PSF (sec. 5)


def _smoothness_matrix(support: int) -> np.ndarray:
    """grad^T grad of eq. (5), grad the forward differences along x and y inside the kernel, written directly:
    the Laplacian of the 4-neighbour grid of the kernel's samples (the number of neighbours on the diagonal,
    -1 for each pair of neighbours). Small integers: exactly the product, without the operator (2 support^4
    values, a quarter of a gigabyte at 65 x 65) or its support^6 multiply-adds."""
    n = support * support
    i = np.arange(n)
    row, col = np.divmod(i, support)
    lap = np.zeros((n, n))
    lap[i, i] = 4 - (row == 0) - (row == support - 1) - (col == 0) - (col == support - 1)
    for a, b in ((i[col < support - 1], 1), (i[row < support - 1], support)):  # right and lower neighbours
        lap[a, a + b] = lap[a + b, a] = -1.0
    return lap


def solve_kernel(ata: np.ndarray, atb: np.ndarray, sigma: float, support: int, weight: float = LAMBDA
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Minimise ||A k - b||^2 / sigma^2 + lambda gamma ||grad k||^2 subject to k >= 0 (eq. (5)).

    gamma = (2R + 1)^2 with R the kernel radius on the grid the kernel lives
    on, i.e. the number of kernel samples. The paper uses a projected-gradient
    Newton method; the problem is the same strictly convex quadratic
    k^T Q k / 2 - c^T k, solved here exactly on its normal equations by block
    principal pivoting (`psfd.estimator.nnls.nnls_normal`): the minimiser the
    former Lawson-Hanson solve on Q's Cholesky factor (scipy.optimize.nnls) gave,
    to 1e-9 (tests/test_scipy_reference.py), and no scipy module loaded (the
    former solve's were 143, 0.11-0.15 s of an ``estimate edges`` run).

    Returns
    -------
    kernel : ndarray (support, support), not normalised.
    hessian : ndarray, Q (its inverse is the posterior covariance of k).
    """
    q = _smoothness_matrix(support)
    q *= weight * support**2
    q += ata / sigma**2  # the sum in either order: Q bit for bit as ata / sigma^2 + weight gamma grad^T grad
    c = atb / sigma**2
    # a whisper of ridge keeps Q positive definite when the weight is 0 and the data rank-deficient
    q[np.diag_indices_from(q)] += 1e-12 * np.trace(q) / q.shape[0]
    # started with every sample bound: on the windows of the real wall photo (17 x 17 and 9 x 9, weights 0, 2
    # and 2e6) as few Cholesky solves as from the LS kernel's positive samples (1-12), without the LS solve
    k = nnls_normal(q, c)
    return k.reshape(support, support), q


# --------------------------------------------------------------------------- target form (sec. 4.2)

@dataclass
class TargetView:
    """Where the edge target lies in a channel plane (sec. 3, "Geometric Transformations").

    ``homography`` maps pattern coordinates (squares) to undistorted pixel
    coordinates; the radial model p_d = c + (p_u - c)(1 + a1 r^2 + a2 r^4),
    r = |p_u - c| / ``norm``, maps those to the photograph.
    """

    homography: np.ndarray
    radial: tuple[float, float]
    centre: tuple[float, float]
    norm: float
    squares: tuple[int, int] = SQUARES

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cx, cy = self.centre
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / self.norm**2
        f = 1.0 + self.radial[0] * r2 + self.radial[1] * r2 * r2
        return cx + (x - cx) * f, cy + (y - cy) * f

    def undistort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ux, uy = np.array(x, dtype=np.float64), np.array(y, dtype=np.float64)
        for _ in range(20):  # fixed point: the distortion is a small perturbation of the identity
            dx, dy = self.distort(ux, uy)
            ux, uy = ux + (x - dx), uy + (y - dy)
            if max(np.max(np.abs(x - dx)), np.max(np.abs(y - dy))) < 1e-6:
                break
        return ux, uy

    def to_pattern(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        ux, uy = self.undistort(x, y)
        return _apply_h(np.linalg.inv(self.homography), ux, uy)

    def to_image(self, px: np.ndarray, py: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.distort(*_apply_h(self.homography, px, py))


def _apply_h(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w


def locate_target(image: np.ndarray, squares: tuple[int, int] = SQUARES) -> TargetView:
    """Find the edge target's checkerboard corners and fit homography + radial distortion (secs. 3, 4.2).

    Balanced checkerboard crossings are not displaced by a single-peaked blur
    (sec. 4.2); OpenCV's sector-based detector finds them on blurred prints.
    The bilinear fit of F^d = R(H(F^k)) alternates between the homography
    (radial terms fixed) and the two radial terms (homography fixed), which
    are then linear (sec. 3); a0 is held at 1, it duplicates the homography's scale.

    Raises
    ------
    TargetNotFoundError
    """
    lo, hi = np.percentile(image[:: _stride(image.shape), :: _stride(image.shape)], [1, 99])
    grey = np.clip((image - lo) / max(hi - lo, 1e-12) * 255, 0, 255).astype(np.uint8)
    inner = (squares[0] - 1, squares[1] - 1)
    det = _board_corners(grey, inner, squares)
    if det is None:
        raise TargetNotFoundError("no edge target found (its checkerboard corners were not detected)")
    gy, gx = np.mgrid[1 : inner[1] + 1, 1 : inner[0] + 1]
    pattern = np.column_stack([gx.ravel(), gy.ravel()]).astype(np.float64)
    rows, cols = image.shape
    view = TargetView(np.eye(3), (0.0, 0.0), ((cols - 1) / 2, (rows - 1) / 2), float(np.hypot(cols, rows)) / 2, squares)
    for _ in range(8):
        ux, uy = view.undistort(det[:, 0], det[:, 1])
        h, _ = cv2.findHomography(pattern, np.column_stack([ux, uy]), 0)
        view.homography = h
        px, py = _apply_h(h, pattern[:, 0], pattern[:, 1])
        cx, cy = view.centre
        r2 = ((px - cx) ** 2 + (py - cy) ** 2) / view.norm**2
        lhs = np.concatenate([np.column_stack([(px - cx) * r2, (px - cx) * r2**2]),
                              np.column_stack([(py - cy) * r2, (py - cy) * r2**2])])
        rhs = np.concatenate([det[:, 0] - px, det[:, 1] - py])
        view.radial = tuple(np.linalg.lstsq(lhs, rhs, rcond=None)[0])
    # the corner grid is symmetric: fix the colour parity from square (1, 1) (black) against (2, 1) (white)
    probe = np.array([[1.15, 1.15], [1.85, 1.85], [2.15, 1.15], [2.85, 1.85]])
    ix, iy = view.to_image(probe[:, 0], probe[:, 1])
    values = _bilinear(image, iy, ix)
    if values[:2].mean() > values[2:].mean():
        view.homography = view.homography @ np.array([[-1.0, 0, squares[0]], [0, 1, 0], [0, 0, 1]])
    return view


BOARD_SEARCH_PIXELS = 500_000  # larger frames are searched shrunk first (`_board_corners`)


def _stride(shape: tuple[int, ...]) -> int:
    """Subsampling step that leaves about a million pixels: percentiles of a large plane at a fraction of the cost."""
    return max(1, int(np.sqrt(shape[0] * shape[1] / 1_000_000)))


def _find_board(grey: np.ndarray, inner: tuple[int, int], flags: int, tries: int) -> np.ndarray | None:
    # the sector-based detector is not deterministic (it missed a clean board about once in 25 runs): retry
    for _ in range(tries):
        found, corners = cv2.findChessboardCornersSB(grey, inner, flags=flags)
        if found:
            return corners.reshape(-1, 2).astype(np.float64)
    return None


def _board_corners(grey: np.ndarray, inner: tuple[int, int], squares: tuple[int, int]) -> np.ndarray | None:
    """The inner corners (x, y) of the checkerboard in an 8-bit image, or None.

    OpenCV's exhaustive sector-based search costs seconds on a frame of a few
    megapixels, most of it spent where there is no board (3 tries took 8 s on
    the 2.5-megapixel wall photo, which has none). A frame above
    BOARD_SEARCH_PIXELS is first searched shrunk to that size (the board's
    squares must stay some 10 pixels wide there), and the board found is then
    searched again at full resolution in its box only, with the same flags as
    a small frame gets: same corners, at the cost of the board's area.
    """
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
    rows, cols = grey.shape
    factor = float(np.sqrt(rows * cols / BOARD_SEARCH_PIXELS))
    if factor <= 1.0:
        return _find_board(grey, inner, flags, 3)
    small = cv2.resize(grey, (max(8, round(cols / factor)), max(8, round(rows / factor))), interpolation=cv2.INTER_AREA)
    # the sub-pixel refinement (CALIB_CB_ACCURACY) is left to the full-resolution pass; a second,
    # plain search covers a miss of the exhaustive one
    coarse = _find_board(small, inner, cv2.CALIB_CB_EXHAUSTIVE, 1)
    if coarse is None:
        coarse = _find_board(small, inner, 0, 1)
    if coarse is None:
        return None
    coarse = (coarse + 0.5) * np.array([cols / small.shape[1], rows / small.shape[0]]) - 0.5
    # the outer squares and the white border around the inner corners, plus a square of slack
    step = float(np.max(np.hypot(*np.diff(coarse.reshape(inner[1], inner[0], 2), axis=1).reshape(-1, 2).T)))
    margin = (BORDER + 2.0) * step
    x0, y0 = np.maximum(np.floor(coarse.min(axis=0) - margin).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(coarse.max(axis=0) + margin).astype(int) + 1, (cols, rows))
    fine = _find_board(np.ascontiguousarray(grey[y0:y1, x0:x1]), inner, flags, 3)
    if fine is None:
        return _find_board(grey, inner, flags, 1)  # as for a small frame, on the whole of it
    return fine + np.array([x0, y0], dtype=np.float64)


@dataclass
class KnownPattern:
    """A printed pattern located in a photograph: where it is, what it looks like, where it is known.

    Attributes
    ----------
    to_pattern : callable
        (x, y) channel pixels -> (X, Y) pattern coordinates.
    reflectance : callable
        (X, Y) -> reflectance in [0, 1].
    region : callable
        (X, Y) -> bool, where the reflectance is known and made of step edges.
    name : str
    to_image : callable
        (X, Y) pattern coordinates -> (x, y) channel pixels, the inverse of ``to_pattern``.
    extent : (float, float, float, float)
        (X0, Y0, X1, Y1), a rectangle of pattern coordinates that holds the whole ``region``.
    """

    to_pattern: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    reflectance: Callable[[np.ndarray, np.ndarray], np.ndarray]
    region: Callable[[np.ndarray, np.ndarray], np.ndarray]
    name: str
    to_image: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    extent: tuple[float, float, float, float]

    def box(self, shape: tuple[int, int]) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1), end exclusive: the pixels of a plane of ``shape`` whose centres may lie in the
        region, the part of the frame the pattern's PSF is measured on (its window and field).

        `extent` traced through `to_image` (`psfd.estimator.geometry.image_box`), a pixel added on each side
        for the tracing's chords.
        """
        from psfd.estimator import geometry  # as `bernoulli_pattern`: the registration steps load on demand

        x0, y0, x1, y1 = geometry.image_box(self.to_image, self.extent, shape, 1, 257)
        if x1 <= x0 or y1 <= y0:
            raise TargetNotFoundError("the located pattern lies outside the frame")
        return x0, y0, x1, y1


def _edge_print(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The printed edge target: `edge_pattern` on the board, white on its border."""
    nx, ny = SQUARES
    board = (x >= 0) & (x < nx) & (y >= 0) & (y < ny)
    return np.where(board, edge_pattern(x, y), 1.0)


def _on_print(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    nx, ny = SQUARES
    return (x > -BORDER) & (x < nx + BORDER) & (y > -BORDER) & (y < ny + BORDER)


def bernoulli_marks(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Reflectance of the Bernoulli target's ring of marks (target.cells without the noise), cell coordinates."""
    bx, by = np.floor(x / target.BLOCK), np.floor(y / target.BLOCK)
    u, v = x - target.BLOCK * bx - target.BLOCK / 2, y - target.BLOCK * by - target.BLOCK / 2
    out = np.ones(np.broadcast(x, y).shape)
    for cx, cy in target.BLACK_BLOCKS:
        out[(bx == cx) & (by == cy)] = 0.0
    hourglass = np.abs(u) < np.abs(v)  # black triangles on the top and bottom edges, apexes at the centre
    for cx, cy in target.XCORNER_BLOCKS:
        out[(bx == cx) & (by == cy) & hourglass] = 0.0
    return out


def _on_ring(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The ring of marks: inside the target, outside the noise (whose cells are no step edges at this scale)."""
    lo, hi = target.NOISE_START, target.NOISE_STOP
    on_target = (x >= 0) & (x < target.SIZE) & (y >= 0) & (y < target.SIZE)
    return on_target & ~((x >= lo) & (x < hi) & (y >= lo) & (y < hi))


def locate_pattern(frame: Frame) -> KnownPattern:
    """The printed pattern of the target form in a frame: the edge target, or else the marks of the Bernoulli target.

    The Bernoulli target's black and white squares and X-corner hourglasses
    are step edges of known geometry too, registered by the detection's
    map (`geometry.target_maps`); their edges only run at 0, 90 and about +-63 degrees,
    which the orientation test (sec. 5.2) reports. The Bernoulli target is
    searched on the plane as `psfd.estimator.bernoulli` searches it, so that
    both methods see a frame through the same registration (a search of the
    plane over its white level can end some 0.002 cells away: the search's
    sub-pixel refinement stops at its tolerance).

    Raises
    ------
    TargetNotFoundError
    """
    try:
        return edge_target_in(frame)
    except TargetNotFoundError:
        pass
    from psfd.estimator import detect  # the Bernoulli pipeline's registration steps

    try:
        detection = detect.find_target(frame.data, frame.saturated)
    except TargetNotFoundError:
        raise TargetNotFoundError("no edge target and no Bernoulli target found in the frame") from None
    return bernoulli_pattern(detection)


def edge_target_in(frame: Frame) -> KnownPattern:
    """The edge target located in a frame (`locate_target` on the plane over its white level) as a located pattern.

    Raises
    ------
    TargetNotFoundError
    """
    view = locate_target(_Scaled(frame.data, frame.white)[:, :])
    nx, ny = view.squares
    return KnownPattern(view.to_pattern, _edge_print, _on_print, "edge target", view.to_image,
                        (-BORDER, -BORDER, nx + BORDER, ny + BORDER))


def bernoulli_pattern(detection) -> KnownPattern:
    """The marks of a detected Bernoulli target (`psfd.estimator.detect.find_target`) as a located pattern."""
    from psfd.estimator import geometry

    to_image, to_pattern = geometry.target_maps(detection)
    return KnownPattern(to_pattern, bernoulli_marks, _on_ring, "Bernoulli target marks", to_image,
                        (0.0, 0.0, float(target.SIZE), float(target.SIZE)))


LATERAL = 1.0  # kernel radii beside a march that must be clear of other edges too (`_clear_marches`)
ANTI_ALIAS = 4  # coverage sub-samples per s-grid sample side
EXACT_MARGIN = 2  # pixels around a change of the pattern between pixel centres where coverage is computed


def _changes(values: np.ndarray, margin: int) -> np.ndarray:
    """Pixels within ``margin`` of a pixel whose value differs from one of its 8 neighbours."""
    v = np.ascontiguousarray(values, dtype=np.float32)
    ring = np.ones((3, 3), np.uint8)
    differs = (cv2.dilate(v, ring) != cv2.erode(v, ring)).astype(np.uint8)
    return cv2.dilate(differs, np.ones((2 * margin + 1,) * 2, np.uint8)) > 0


class _PatternBlock:
    """A located pattern over one block of a crop's s-grid, evaluated where asked (secs. 4.2, 5.1).

    Sample (i, j) sits at pixel (origin_x + j / s, origin_y + i / s). Its
    coverage ``alpha`` is the mean reflectance over ANTI_ALIAS^2 points of its
    1/s-pixel footprint (placed by the map's local Jacobian, the map's central
    differences over the crop's s-grid as numpy.gradient takes them) and
    ``inside`` tells whether the pattern is known there. Away from the
    pattern's edges and from the border of its known region both equal their
    value at the nearest pixel centre, which takes one look-up per pixel; only
    samples within EXACT_MARGIN pixels of a change between pixel centres are
    computed point by point, so the work follows the edges, not the area.
    """

    def __init__(self, known: "KnownPattern", origin: tuple[int, int], s: int, grid: tuple[int, int],
                 box: tuple[int, int, int, int]) -> None:
        self.known, self.origin, self.s, self.grid = known, origin, s, grid
        i0, i1, j0, j1 = box
        pixels = ((grid[0] - 1) // s + 1, (grid[1] - 1) // s + 1)
        reach = EXACT_MARGIN + 1
        self.p0, self.q0 = max(0, i0 // s - reach), max(0, j0 // s - reach)
        p1, q1 = min(pixels[0], (i1 - 1) // s + reach + 2), min(pixels[1], (j1 - 1) // s + reach + 2)
        yy, xx = np.mgrid[self.p0 : p1, self.q0 : q1]
        X, Y = known.to_pattern(origin[0] + xx, origin[1] + yy)
        self.value = known.reflectance(X, Y)
        self.region = np.asarray(known.region(X, Y), dtype=bool)
        self.exact_value = _changes(self.value, EXACT_MARGIN)
        self.exact_region = _changes(self.region, EXACT_MARGIN)
        # pattern coordinates of the samples, computed once when first needed (one sample around for the Jacobian)
        self.c0 = (max(0, i0 - 1), max(0, j0 - 1))
        shape = (min(grid[0], i1 + 1) - self.c0[0], min(grid[1], j1 + 1) - self.c0[1])
        self.px, self.py = np.full(shape, np.nan), np.full(shape, np.nan)

    def any_edge(self) -> bool:
        """Whether the block may hold partly covered samples inside the known region."""
        return bool(self.exact_value.any() and (self.region.any() or self.exact_region.any()))

    def _nearest(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return (np.floor(i / self.s + 0.5).astype(np.intp) - self.p0,
                np.floor(j / self.s + 0.5).astype(np.intp) - self.q0)

    def _coords(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        li, lj = i - self.c0[0], j - self.c0[1]
        todo = np.isnan(self.px[li, lj])
        if todo.any():
            ti, tj = i[todo], j[todo]
            x, y = self.known.to_pattern(self.origin[0] + tj / self.s, self.origin[1] + ti / self.s)
            self.px[li[todo], lj[todo]], self.py[li[todo], lj[todo]] = x, y
        return self.px[li, lj], self.py[li, lj]

    def _derivative(self, i: np.ndarray, j: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
        """d(px, py) / d(i or j) as numpy.gradient takes it over the whole s-grid (one-sided at its border)."""
        size = self.grid[axis]
        k = i if axis == 0 else j
        lo, hi = np.maximum(k - 1, 0), np.minimum(k + 1, size - 1)
        a = (lo, j) if axis == 0 else (i, lo)
        b = (hi, j) if axis == 0 else (i, hi)
        xa, ya = self._coords(*a)
        xb, yb = self._coords(*b)
        step = np.where((k > 0) & (k < size - 1), 2.0, 1.0)
        return (xb - xa) / step, (yb - ya) / step

    def alpha(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Coverage of samples (i, j) in [0, 1]."""
        pi, pj = self._nearest(i, j)
        out = self.value[pi, pj].astype(np.float64)
        exact = self.exact_value[pi, pj]
        if exact.any():
            ei, ej = i[exact], j[exact]
            px, py = self._coords(ei, ej)
            dxdi, dydi = self._derivative(ei, ej, 0)
            dxdj, dydj = self._derivative(ei, ej, 1)
            cover = np.zeros(ei.size)
            sub = (np.arange(ANTI_ALIAS) + 0.5) / ANTI_ALIAS - 0.5
            for oy in sub:
                for ox in sub:
                    cover += self.known.reflectance(px + dxdj * ox + dxdi * oy, py + dydj * ox + dydi * oy)
            out[exact] = cover / ANTI_ALIAS**2
        return out

    def inside(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Whether the pattern is known at samples (i, j)."""
        pi, pj = self._nearest(i, j)
        out = self.region[pi, pj].copy()
        exact = self.exact_region[pi, pj]
        if exact.any():
            out[exact] = self.known.region(*self._coords(i[exact], j[exact]))
        return out


def _target_edges(known: "KnownPattern", origin: tuple[int, int], s: int, grid: tuple[int, int],
                  progress: Callable[[], None] | None = None) -> Edgels:
    """Edge points of the located pattern on a crop's s-grid (sec. 4.2): every partly covered sample.

    Normals come from the gradient of the coverage smoothed over one sample.
    All of them, about s per pixel of edge length: any subset is a choice the
    levels, and so the PSF, depend on beyond the noise. The one taken before
    (the samples on the pixels' rows and columns, of every other pixel, about
    one per pixel of edge length) moved the example photo's PSF by 0.070 when
    the other half was taken (half its noise floor, 0.15), and was less accurate
    on renders of known PSF: L2 error against the truth higher by 0.006 on the
    edge target and by 0.05 (about twice) on the Bernoulli target's marks. Edge
    points come out in raster order.
    """
    halo = _gauss_radius(1.0) + 1  # the smoothing and the gradient
    parts = []
    for i0, i1, j0, j1 in _tiles((0, grid[0]), (0, grid[1]), s * TILE_PX):
        block = _PatternBlock(known, origin, s, grid, (max(0, i0 - halo), min(grid[0], i1 + halo),
                                                       max(0, j0 - halo), min(grid[1], j1 + halo)))
        if block.any_edge():
            bi0, bj0 = max(0, i0 - halo), max(0, j0 - halo)
            ii, jj = np.mgrid[bi0 : min(grid[0], i1 + halo), bj0 : min(grid[1], j1 + halo)]
            alpha = block.alpha(ii.ravel(), jj.ravel()).reshape(ii.shape)
            smooth = _gaussian_filter(alpha, 1.0)
            gy, gx = np.gradient(smooth)
            mag = np.hypot(gx, gy)
            own = (slice(i0 - bi0, i1 - bi0), slice(j0 - bj0, j1 - bj0))
            edge = (alpha[own] > 0.05) & (alpha[own] < 0.95) & (mag[own] > 0)
            li, lj = np.nonzero(edge)
            iy, ix = li + i0, lj + j0
            keep = block.inside(iy, ix)
            iy, ix = iy[keep], ix[keep]
            li, lj = iy - bi0, ix - bj0
            m = mag[li, lj]
            parts.append((iy * grid[1] + ix, ix / s, iy / s, gx[li, lj] / m, gy[li, lj] / m, m))
        if progress is not None:
            progress()
    parts = [p for p in parts if p[0].size]
    return _sorted_edgels(parts)


def _clear_marches(known: "KnownPattern", origin: tuple[int, int], edges: Edgels, reach: float, s: int,
                   lateral: float) -> np.ndarray:
    """Whether each edge point's marches see its own edge alone: along its normal, from one s-grid step out to
    ``reach`` pixels, the pattern is white on the bright side and black on the dark side, and known; and so it
    is ``lateral`` pixels to either side along the edge, from the marches' first sample (1 pixel) on.

    The levels of an edge are the plateaus its marches reach (Joshi et al., CVPR 2008, sec. 4.1). A march
    that meets another edge of the pattern (a checkerboard crossing, the tip of an hourglass), runs beside
    one, or leaves the region where the pattern is known (into the Bernoulli target's noise, off the target)
    measures something else; in the target form the pattern tells which points those are (sec. 4.2). A
    plateau sample lies a kernel radius from its own edge and from any other, hence ``reach`` = 2 and
    ``lateral`` = LATERAL kernel radii (`_window_equations`). On renders of known PSF the levels of such
    points were off by up to 0.85 of the edge contrast; with their nearest clear points' levels instead
    (`_target_levels`), every level is within 0.09 of the truth. The strips are mapped to the pattern by
    their ends, linearly between them: over a few pixels the map is affine to far below a sample, and the
    points kept were the same as with every sample mapped on the example photo and on renders.
    """
    ok = np.ones(len(edges), dtype=bool)
    steps = int(round(reach * s))
    if not len(edges) or steps < 1:
        return ok
    x, y = edges.x + origin[0], edges.y + origin[1]
    lines = [(0.0, np.arange(1, steps + 1) / steps)]  # (offset along the edge, fractions of the strip)
    if lateral > 0:
        first = np.arange(min(s, steps), steps + 1) / steps
        lines += [(-lateral, first), (lateral, first)]
    for offset, t in lines:
        for sign, colour in ((1.0, 1.0), (-1.0, 0.0)):
            k = np.flatnonzero(ok)  # the points still clear: a point fails on its first blocked strip
            nx, ny = edges.nx[k], edges.ny[k]
            lx, ly = x[k] - offset * ny, y[k] + offset * nx
            x0, y0 = known.to_pattern(lx, ly)
            x1, y1 = known.to_pattern(lx + sign * reach * nx, ly + sign * reach * ny)
            px = x0[:, None] + t[None, :] * (x1 - x0)[:, None]
            py = y0[:, None] + t[None, :] * (y1 - y0)[:, None]
            ok[k] = (known.reflectance(px, py) == colour).all(axis=1) & np.asarray(known.region(px, py), bool).all(axis=1)
    return ok


def _target_levels(image, points: Edgels, clear: np.ndarray, s: int, length: int) -> Edgels:
    """The levels of the target form's edge points: measured by the marches where they are ``clear``
    (`edge_levels`), and elsewhere the mean levels of the nearest such points (`_TiedPoints`).

    Only the levels change, not the edge points, so the samples predicted are those before (Joshi et al.,
    CVPR 2008, secs. 4.1, 4.2). The measured points come first, in the order given, then the others.
    Without a clear point every point keeps the levels of its own marches.
    """
    if clear.all() or not clear.any():
        return edge_levels(image, points, length)
    measured = edge_levels(image, points.subset(clear), length)
    others = points.subset(~clear)
    if not len(measured):
        return edge_levels(image, points, length)
    _, sample, point = _TiedPoints(*_on_grid(measured, s)).query(*_on_grid(others, s), np.inf)
    others.lo, others.hi = _mean_levels(measured, sample, point, len(others))
    return Edgels(*(np.concatenate([getattr(measured, f.name), getattr(others, f.name)]) for f in fields(Edgels)))


def _on_grid(edges: Edgels, s: int) -> tuple[np.ndarray, np.ndarray]:
    """(i, j): the s-grid samples the target form's edge points are (`_target_edges`: x = j / s, y = i / s)."""
    return np.rint(edges.y * s), np.rint(edges.x * s)


def _mean_levels(edges: Edgels, sample: np.ndarray, point: np.ndarray, n: int,
                 at: "np.ndarray | slice" = slice(None)) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of samples 0 .. n - 1, taken ``at`` (each needs a point there): the mean levels of each sample's
    nearest edge points, the (sample, point) pairs of `_TiedPoints.query`."""
    count = np.bincount(sample, minlength=n)[at]
    return (np.bincount(sample, edges.lo[point], n)[at] / count, np.bincount(sample, edges.hi[point], n)[at] / count)


class _TargetPrediction:
    """The target form's sharp image (Joshi et al., CVPR 2008, sec. 4.2): the pattern's coverage, shaded with the
    levels of the nearest edge point.

    The levels come from the photograph by the same marches as in the blind
    case, at edge locations known from the pattern; each s-grid sample of the
    known region within ``band`` pixels of an edge point is predicted. Where
    several edge points are equally near (the edge points lie on the s-grid
    too, `_TiedPoints`), the sample takes the mean of their levels, so that
    no arbitrary pick among them decides it.
    """

    def __init__(self, known: "KnownPattern", origin: tuple[int, int], s: int, grid: tuple[int, int],
                 edges: Edgels, band: float) -> None:
        self.known, self.origin, self.s, self.grid, self.edges, self.band = known, origin, s, grid, edges, band
        self.reach = band
        self.points = _TiedPoints(*_on_grid(edges, s)) if len(edges) else None
        self.block: _PatternBlock | None = None

    def focus(self, box: tuple[int, int, int, int]) -> "_TargetPrediction":
        """The prediction over this block of samples (see `_accumulate`): a copy that evaluates the pattern there.

        A copy, not this one changed: two tiles may be predicted at once.
        """
        focused = copy.copy(self)
        focused.block = _PatternBlock(self.known, self.origin, self.s, self.grid, box)
        return focused

    def predict(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(predicted, sharp) at samples (i, j) of the focused block."""
        known = np.zeros(i.shape, dtype=bool)
        sharp = np.zeros(i.shape)
        if self.points is None or i.size == 0:
            return known, sharp
        found, sample, point = self.points.query(i, j, self.band * self.s)
        found[found] = self.block.inside(i[found], j[found])
        keep = found[sample]
        sample, point = sample[keep], point[keep]
        e = self.edges
        lo, hi = _mean_levels(e, sample, point, i.size, found)
        sharp[found] = lo + (hi - lo) * self.block.alpha(i[found], j[found])
        return found, sharp


# --------------------------------------------------------------------------- estimate


def estimate_edges(
    frame: Frame,
    s: int = DEFAULT_S[SHARP_EDGE],
    support: int | None = None,
    weight: float | None = None,
    radius: float | None = None,
    grid: tuple[int, int] = (1, 1),
    target_form: bool = False,
    pattern: KnownPattern | None = None,
    progress: Callable[[float], None] | None = None,
) -> list[PSF]:
    """Sharp-edge prediction PSFs of one channel plane, one per grid window, row-major.

    Parameters
    ----------
    frame : Frame
        A photograph with strong step edges at all orientations (blind), or of
        a printed target (``target_form=True``).
    s : int
        Super-resolution factor of the kernel grid.
    support : int, optional
        Odd kernel side on the s-grid (default 4 s + 1).
    weight : float, optional
        lambda of eq. (5) (default 2, the paper's).
    radius : float, optional
        R, channel pixels: observed pixels within R of an edge are used, and the
        sharp image is predicted within R plus the kernel radius (default: the kernel radius).
    grid : (int, int)
        (nx, ny) local windows.
    target_form : bool
        Predict the sharp image from a printed pattern of known geometry: the
        edge target (`edge_target`), or else the marks of the Bernoulli target
        (`locate_pattern`).
    pattern : KnownPattern, optional
        The pattern already located in this frame (`locate_pattern`,
        `bernoulli_pattern`): the target form without locating it again.
    progress : callable, optional
        Called with the fraction of the work done, 0 to 1, as it proceeds.

    Returns
    -------
    list of PSF with method ``sharp-edge``.

    Raises
    ------
    BadInputError
        Invalid parameters.
    TargetNotFoundError
        ``target_form`` and neither target in the frame.
    EstimationError
        A window has fewer usable pixels near edges than kernel unknowns (sec. 5.2, test (a)).
    """
    s, support, grid = check_sizes(s, support, grid)
    weight, radius = _check(weight, radius)
    image = _Scaled(frame.data, frame.white)
    kernel_radius = (support // 2) / s
    radius = max(kernel_radius, 1.0) if radius is None else radius
    band = radius + kernel_radius
    length = int(np.ceil(2 * kernel_radius)) + 2  # march far enough to leave the blurred ramp
    # the board search reads the whole plane over its white level at once: divided for it alone (`edge_target_in`)
    known = pattern if pattern is not None else locate_pattern(frame) if target_form else None
    rows, cols = image.shape
    if known is None:
        bounds = (0, 0, cols, rows)
        sigma = max(noise_sigma(image, _unclipped_blocks(_clipped(frame))), 1e-6)
    else:
        # the pattern's edges are all the form uses: its windows, field and noise are those of the pattern,
        # not of the rest of the frame (read on the whole frame, a dark room around the edge target gave a
        # noise of 6e-4 for the print's 0.011 and a floor 17 times too small, and a target off-centre was
        # reported at the frame's centre; tests/test_sharpedge.py)
        bounds = known.box((rows, cols))
        sigma = max(_pattern_noise(image, _clipped(frame), known, bounds), 1e-6)
    windows = split_grid(bounds, grid)
    out = []
    for w, window in enumerate(windows):
        step = None if progress is None else (lambda f, w=w: progress((w + f) / len(windows)))
        kernel, info, warnings = _estimate_window(image, frame.saturated, window, s, support, weight, band, length,
                                                  sigma, known, step)
        floor = info.pop("noise_floor")
        out.append(PSF(
            psf=kernel, s=s, method=SHARP_EDGE, channel=frame.channel, sources=[frame.source],
            field=field_of_window(window, (rows, cols)), window=window,
            noise_floor=floor, residual=info.pop("residual"),
            params={"support": support, "weight": weight, "gamma": support**2, "radius": radius, "grid": list(grid),
                    "pattern": known.name if known else "blind", **info},
            warnings=warnings + kernel_warnings(kernel, floor, MORE_SIGNAL if known else _MORE_EDGES),
        ))
        _trim_heap()
    return out


def _clipped(frame: Frame) -> np.ndarray:
    """The frame's clipped pixels: its saturated ones and, in a single-channel image (black level 0, as a PGM
    or TIFF holds it), those at 0, where the blacks were crushed. A plane of a RAW mosaic has its black level
    subtracted, and its values at or below 0 are the sensor's noise around black, not clipped."""
    if frame.from_mosaic:
        return frame.saturated
    return frame.saturated | (np.asarray(frame.data) <= 0)


def _unclipped_blocks(saturated: np.ndarray) -> np.ndarray | None:
    """The plane's 2 x 2 blocks (from its even rows and columns) that hold no clipped pixel, for `noise_sigma`;
    None when none is clipped. A clipped block reads no noise at all: a frame more than half clipped (a blown
    sky, the white board around a target) read as noise-free, sigma 1e-6 and a noise floor 1e-5."""
    rows, cols = (saturated.shape[0] // 2) * 2, (saturated.shape[1] // 2) * 2
    if not saturated[:rows, :cols].any():
        return None
    clipped = saturated[:rows, :cols]
    blocks = ~(clipped[0::2, 0::2] | clipped[0::2, 1::2] | clipped[1::2, 0::2] | clipped[1::2, 1::2])
    return blocks if blocks.any() else None


def _pattern_noise(image: _Scaled, saturated: np.ndarray, known: KnownPattern, box: tuple[int, int, int, int]
                   ) -> float:
    """`noise_sigma` of the plane on the located pattern alone: the 2 x 2 blocks of ``box`` (the plane's own,
    from its even rows and columns) whose centre lies in the pattern's region and that hold no clipped pixel
    (a clipped block reads no noise at all).

    The same statistic as on a whole frame, the one eq. (5)'s weight was measured with; read on the whole
    frame it was the room's around the target instead (a dark room: 17 times less noise than the print).
    """
    x0, y0, x1, y1 = box
    x0, y0 = x0 - x0 % 2, y0 - y0 % 2  # the median of other blocks differs by its sampling error, a few per cent
    rows, cols = (y1 - y0) // 2, (x1 - x0) // 2
    by, bx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    blocks = np.asarray(known.region(*known.to_pattern(x0 + 2 * bx + 0.5, y0 + 2 * by + 0.5)), dtype=bool)
    unclipped = _unclipped_blocks(saturated[y0 : y0 + 2 * rows, x0 : x0 + 2 * cols])
    if unclipped is not None:
        blocks &= unclipped
    crop = image.crop(y0, y1, x0, x1)
    return noise_sigma(crop, blocks) if blocks.any() else noise_sigma(crop)


def _check(weight, radius) -> tuple[float, float | None]:
    weight = LAMBDA if weight is None else float(weight)
    if not np.isfinite(weight) or weight < 0:
        raise BadInputError(f"weight must be a number >= 0, got {weight}")
    if radius is not None and (not np.isfinite(radius) or radius <= 0):
        raise BadInputError(f"radius must be a positive number of pixels, got {radius}")
    return weight, radius


def _counter(progress: Callable[[float], None] | None, start: float, span: float, total: int):
    """A callback that maps ``total`` calls onto progress(start) .. progress(start + span), or None."""
    if progress is None:
        return None
    done = [0]

    def tick() -> None:
        done[0] += 1
        progress(start + span * min(done[0], total) / max(total, 1))

    return tick


def _window_equations(image, saturated, window, s, support, band, length, sigma, known, progress=None):
    """One window's normal equations of eq. (5) and the edge points of its crop.

    Returns
    -------
    ata, atb, btb, the number of pixels used, the crop's edge points, and the crop's first (col, row).
    """
    x0, y0, x1, y1 = window
    rows, cols = image.shape
    margin = int(np.ceil(band + length)) + 6
    cx0, cy0 = max(0, x0 - margin), max(0, y0 - margin)
    cx1, cy1 = min(cols, x1 + margin), min(rows, y1 + margin)
    crop = image.crop(cy0, cy1, cx0, cx1) if isinstance(image, _Scaled) else image[cy0:cy1, cx0:cx1]
    grid = (s * (crop.shape[0] - 1) + 1, s * (crop.shape[1] - 1) + 1)
    half = support // 2
    if known is None:
        edges = edge_levels(crop, detect_edges(crop, noise=sigma), length)
        prediction = _BlindPrediction(edges, s, band)
        start = 0.2  # of the window's work, roughly what finding the edges takes
    else:
        tiles = len(list(_tiles((0, grid[0]), (0, grid[1]), s * TILE_PX)))
        points = _target_edges(known, (cx0, cy0), s, grid, _counter(progress, 0.0, 0.5, tiles))
        kernel_radius = half / s
        clear = _clear_marches(known, (cx0, cy0), points, 2 * kernel_radius, s, LATERAL * kernel_radius)
        edges = _target_levels(crop, points, clear, s, length)
        prediction = _TargetPrediction(known, (cx0, cy0), s, grid, edges, band)
        start = 0.5
    _trim_heap()  # the edge search's temporaries, before the accumulation's
    # observed pixels that may use their whole kernel footprint (eq. (4)'s mask M): the footprint inside the
    # s-grid and the window, away from clipped pixels, and every pixel centre in it near an edge point
    r = half // s
    candidates = cv2.erode(_near_edges(edges, crop.shape, prediction.reach).view(np.uint8),
                           np.ones((2 * r + 1, 2 * r + 1), np.uint8),
                           borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    candidates &= ~_dilate(saturated[cy0:cy1, cx0:cx1], int(np.ceil(band)) + 1)
    edge_px = -(-half // s)  # footprints reach ceil(half / s) pixels
    inside = np.zeros_like(candidates)
    inside[max(y0 - cy0, edge_px) : min(y1 - cy0, crop.shape[0] - edge_px),
           max(x0 - cx0, edge_px) : min(x1 - cx0, crop.shape[1] - edge_px)] = True
    candidates &= inside
    tiles = list(_tiles((y0 - cy0, y1 - cy0), (x0 - cx0, x1 - cx0)))
    ata, atb, btb, n_valid = _accumulate(crop, candidates, prediction, s, support, tiles,
                                         _counter(progress, start, 1.0 - start, len(tiles)))
    return ata, atb, btb, n_valid, edges, (cx0, cy0)


def _estimate_window(image, saturated, window, s, support, weight, band, length, sigma, known, progress=None):
    """One window: predict the sharp image around it, mask, solve eq. (5); (kernel, diagnostics, warnings)."""
    ata, atb, btb, n_valid, edges, (cx0, cy0) = _window_equations(image, saturated, window, s, support, band,
                                                                   length, sigma, known, progress)
    x0, y0, x1, y1 = window
    in_window = (edges.x >= x0 - cx0) & (edges.x < x1 - cx0) & (edges.y >= y0 - cy0) & (edges.y < y1 - cy0)
    hist = edges.subset(in_window).orientation_histogram()
    if known is not None:  # about s edge points per pixel of edge length (`_target_edges`): counted per pixel
        hist //= s
    unknowns = support * support
    if n_valid <= unknowns:  # sec. 5.2, test (a)
        raise EstimationError(
            f"window {window}: {n_valid} usable pixels near edges for {unknowns} kernel unknowns "
            "(use fewer grid windows, a smaller support or a photograph with more edges)"
        )
    warnings = []
    if hist.min() < MIN_PER_BIN:  # sec. 5.2, test (b): the paper skips such windows; we keep and flag them
        warnings.append(
            f"edge orientations uneven: fewest {int(hist.min())} edge points in a 10-degree bin "
            f"(the paper asks {MIN_PER_BIN}); the kernel is under-constrained across those directions"
        )
    k, q = solve_kernel(ata, atb, sigma, support, weight)
    total = float(k.sum())
    if not np.isfinite(total) or total <= 0:
        raise EstimationError(f"window {window}: the kernel came out empty")
    kv = k.ravel()
    rss = max(btb - 2 * kv @ atb + kv @ ata @ kv, 0.0)
    info = {
        "sigma": sigma,
        "valid_pixels": n_valid,
        "edges": int(in_window.sum()),
        "orientation_min": int(hist.min()),
        "mass": total,
        # the norm of the posterior error of the normalised kernel, sqrt(trace(Q^-1)) / total: the unit of
        # every method's floor (`kernels.PSF.noise_floor`)
        "noise_floor": float(np.sqrt(np.trace(np.linalg.inv(q))) / total),
        "residual": float(np.sqrt(rss / n_valid)),
    }
    return k / total, info, warnings
