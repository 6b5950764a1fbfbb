"""Find the Bernoulli calibration target in a photograph.

The target (psfd.estimator.target) carries 12 X-corner marks on a ring around
the noise. Detection follows the plan of Delbracio PhD thesis 2013, App. A.1:
a coarse search for the whole mark configuration, then sub-pixel refinement of
each X-corner by gradient orthogonality (Delbracio et al., IJCV 2012, sec. 4.1;
thesis App. A.1, "Sub-pixel corner refinement").

The coarse search differs from the thesis, which groups LSD line segments into
the shape of the marks: here the X-corners are found directly as saddle
points of the smoothed image, which needs no segment model of the marks and
works at any rotation and at any scale, from 0.175 px/cell (s/t = 0.7 at
s = 4, the smallest of IJCV 2012 sec. 3.3) to a target filling the frame
(a pyramid level per octave). At a smoothing of several
cells the Bernoulli noise averages out while each hourglass mark stays a
perfect saddle. A real scene has many more saddles than the target (foliage
against the sky, fences, letters), often stronger ones, so nothing is ranked
over the whole frame. Each saddle is judged by its own surroundings: against
the contrast around it (a mark is an X-corner of its own black and white),
then whether it is an X-corner at any contrast or not (`_x_shape`), and only
the best few of every small tile are kept. Two candidates become a
hypothesis when they could be neighbouring marks of a row of the ring:
similar, their dark axes across the row, and a flat black and a flat white
square between them. Every such
hypothesis (a similarity) is ranked by how many of the other ten marks it
predicts where the layout puts them, grown into a homography, and accepted
only if the 24 flat squares read as the layout says, with the orientation
fixed by corner (9, 9), the only one flanked by two black squares.
Detection and refinement are separate (`refine_target`), so that a frame's
planes can share one search.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from psfd.errors import BadInputError, MultipleTargetsError, TargetNotFoundError
from psfd.estimator import quantiles, target

# Smoothing of the saddle detector, in pixels of each pyramid level. With levels
# a factor 2 apart, level L smooths by 3 to 8 cells for targets imaged at
# 2**L / 8 to 2**L / 3 pixels per cell (the hourglass is an exact saddle out
# to 16 cells while the noise averages out); neighbouring levels overlap, and
# level 0 finds targets from 0.19 px/cell (measured; from 0.175 with its saddles centred on the image
# smoothed half as much, `_search`). Levels go on while a
# target fits (5-6 px/cell fill a 3000 x 2000 plane, level 4 or 5).
_SIGMA = 1.0
_SMALLEST = 40  # px: the smallest target a level sees, 320 cells at 1/8 px/cell
_MIN_SEED_HITS = 7  # marks a seed similarity must already explain to be grown
_STRENGTH_RATIO = 0.4  # weakest mark / strongest mark accepted in one target
_REFINE_CELLS = 8.0  # half-size of the sub-pixel refinement window, in cells
_AXIS_TOL = np.deg2rad(20.0)  # dark axis of a mark vs the pattern's y axis (perspective, noise)
# Saddle strength (see _proposals) below which a point is not a candidate, as a
# fraction of the strength of an ideal contrast-1 X-corner: low, so that a
# dim target is not lost; the shape test below does the selection.
_MIN_STRENGTH = 0.03
# The X-corner test (_x_shape): 12 samples on circles of 1.25 and 2 level
# pixels, read on the finer level: 4-10 and 6-16 cells at the level's 1/8 to
# 1/3 px/cell, inside the 16 cells where a mark is a perfect X-corner and
# clear of its blurred apex.
_RING_RADII = (1.25, 2.0)
_RING_SAMPLES = 12
# Share of the second angular harmonic: centred marks measure 0.91-0.99 on
# rendered and simulated frames (0.2-2 px/cell, blur, perspective, noise);
# about half of a cluttered scene's X-like saddles are below 0.8.
_MIN_SHAPE = 0.8
_OUTER_SHAPE = 0.6  # the same on the outer circle alone, a cheaper first pass
_LOCAL_STRENGTH = 0.3  # saddle strength / that of an ideal X-corner of the contrast around it (_proposals)
_MIN_CONTRAST = 0.02  # of the image's range: the marks' black on white is 10 times more
# Local choice: the best two candidates (contrast times shape) of every 8 x 8
# tile, under the spacing of adjacent marks (12-32 level px).
_TILE = 8
_PER_TILE = 2
# Seed pairs: the two flat squares between neighbouring marks must lie
# beyond this fraction of the marks' contrast from their mean level, one
# dark, one light (measured 0.5-1.3) ...
_SQUARE_TOL = 0.35
# ... and be flat: values within a quarter block of their centres within
# this fraction of the contrast (measured up to 0.37 at a level's smallest scale).
_FLAT_TOL = 0.5
# Spacing of adjacent ring marks (3 blocks) in level pixels: 96 cells at the
# 1/6 .. 1/3 px/cell where a level sees the marks best is 16 .. 32 px (below
# that, the finer level takes over; level 0 reaches 1/8, 12 px); the bounds
# leave room for perspective.
_SPACING = (9.0, 40.0)
# Adjacent ring marks used to seed hypotheses: the three edges of the top row.
_SEED_EDGES = ((6, 5), (5, 4), (4, 3))  # indices into target.XCORNER_BLOCKS
_RING_CORNERS = ((0, 0), (9, 0), (9, 9), (0, 9))


@dataclass
class Detection:
    """The 12 X-corners of the target in an image.

    Attributes
    ----------
    corners : ndarray (12, 2)
        Image (x, y) of the saddle points, pixel centres at integers, in the
        order of target.XCORNER_BLOCKS.
    pattern_points : ndarray (12, 2)
        The same points in pattern cells, target.xcorner_points().
    scale : float
        Approximate image pixels per pattern cell.
    """

    corners: np.ndarray
    pattern_points: np.ndarray = field(default_factory=target.xcorner_points)
    scale: float = 1.0


def find_target(image: np.ndarray, saturated: np.ndarray | None = None) -> Detection:
    """Locate the calibration target and its 12 X-corners at sub-pixel precision.

    Parameters
    ----------
    image : ndarray, 2-D
        One channel (e.g. a Bayer plane), any numeric type.
    saturated : ndarray of bool, optional
        Clipped pixels. They are set to the bright end of the range so that a
        clipped highlight reads as white; clipping keeps an X-corner
        point-symmetric, so its saddle is not displaced.

    Returns
    -------
    Detection

    Notes
    -----
    On symmetric X-corners the refinement is unbiased up to the pixel
    sampling. Measured on rendered and simulated frames (noise ~0.5-1 %):
    0.02-0.08 px at 0.3-2 px/cell; at 0.2-0.25 px/cell with a sharp PSF the
    aliased marks give a bias that follows the sub-pixel phase (up to 0.1 px,
    a common shift when all marks share the phase); with a PSF wider than
    about 3 cells (sigma; e.g. 0.8 px at 0.25 px/cell, f/32 on a small
    target) the blurred neighbouring squares reach the refinement window and
    the error grows to 0.15-0.5 px: place the target closer for such apertures
    (a Bernoulli PSF wider than 4 cells says so, `bernoulli.MARK_BLUR_CELLS`).
    Any scale from 0.175 px/cell to a target filling the frame is found
    (at 0.175-0.19 px/cell with PSFs up to a sigma of 0.6 px, 3.4 cells:
    0.17-0.23 px from the truth, as at 0.2 px/cell); in
    cluttered 3000 x 2000 planes at 0.8-6 px/cell the corners came within
    0.03-0.19 px (8-bit planes).

    Nothing is ranked over the whole frame, so a busy scene around the
    target (foliage against a clipped sky, fences, signs) does not hide it;
    the search's cost grows with the frame's area and clutter
    (bench/bench_detect.py times it).

    Raises
    ------
    TargetNotFoundError
        No target, marks that do not form the published layout, or marks too
        blurred to be located.
    MultipleTargetsError
        More than one target in the image.

    See Also
    --------
    refine_target : the corners of this detection on another plane of the frame.
    """
    norm = _normalise(image, saturated)
    found = _search(norm)
    if not found:
        raise TargetNotFoundError(f"no calibration target found in the {norm.shape[1]}x{norm.shape[0]} image")
    if len(found) > 1:
        raise MultipleTargetsError(f"{len(found)} calibration targets found in the image; frame exactly one")
    corners = _apply(found[0], target.xcorner_points())
    return refine_target(image, Detection(corners=corners, scale=_scale(corners)), saturated)


def refine_target(
    image: np.ndarray,
    detection: Detection,
    saturated: np.ndarray | None = None,
    shift: tuple[float, float] = (0.0, 0.0),
) -> Detection:
    """The X-corners of a detection refined at sub-pixel precision on ``image``.

    Detect once per frame, refine per plane: the planes of one RAW frame see
    the target at the same place, up to the half-pixel offsets of the Bayer
    mosaic (`plane_shift`) and the lens's lateral colour (about a pixel at
    most). The refinement reaches the same corners from starts up to 1.5 px
    away (measured at 0.25-0.5 px/cell). It costs about a millisecond, where
    `find_target` searches the whole plane.

    Parameters
    ----------
    image : ndarray, 2-D
        The plane to refine on, any numeric type.
    detection : Detection
        Found on this plane or on another plane of the same frame.
    saturated : ndarray of bool, optional
        Clipped pixels of ``image``, read as white (see `find_target`).
    shift : (float, float)
        (dx, dy) in pixels from the plane of ``detection`` to ``image``.

    Returns
    -------
    Detection

    Raises
    ------
    TargetNotFoundError
        A mark that cannot be located on this plane (too blurred, too dark,
        or outside the image).

    Examples
    --------
    >>> g1 = raw.load_frame(path, "g1")                                # doctest: +SKIP
    >>> found = find_target(g1.data, g1.saturated)                     # doctest: +SKIP
    >>> r = raw.load_frame(path, "r")                                  # doctest: +SKIP
    >>> refine_target(r.data, found, r.saturated, plane_shift(g1.offset, r.offset))  # doctest: +SKIP
    """
    data = np.asarray(image)
    if data.ndim != 2 or min(data.shape) < 16:
        raise BadInputError(f"expected a 2-D image of at least 16x16 pixels, got shape {data.shape}")
    corners = np.asarray(detection.corners, dtype=np.float64) + np.asarray(shift, dtype=np.float64)
    refined = _refine(data, saturated, corners, detection.scale)
    return Detection(corners=refined, pattern_points=np.array(detection.pattern_points), scale=_scale(refined))


def plane_shift(source_offset: tuple[int, int], dest_offset: tuple[int, int]) -> tuple[float, float]:
    """(dx, dy) in plane pixels from one Bayer plane to another of the same frame.

    A plane with sensor offset (row, col) (`psfd.estimator.raw.Frame.offset`)
    holds photosite (2 i + row, 2 j + col) at its pixel (i, j), so one scene
    point lies half the offset difference apart on two planes. Planes that do
    not come from a 2 x 2 mosaic have offset (0, 0): no shift.
    """
    return (0.5 * (source_offset[1] - dest_offset[1]), 0.5 * (source_offset[0] - dest_offset[0]))


def _normalise(image: np.ndarray, saturated: np.ndarray | None) -> np.ndarray:
    """float32 copy scaled to about [0, 1] between robust extremes (NaN read as black).

    The extremes are taken on a 4x reduced copy, which averages the pixel noise
    and hot pixels away, at the 0.05 and 99.95 percentiles: a target can cover
    well under 1 % of a large frame and its whites must not be clipped.
    The image is read in its own type and converted and scaled in one pass
    (a 24-megapixel plane is 100-200 MB; each pass over it counts).
    """
    data = np.asarray(image)
    if data.ndim != 2 or min(data.shape) < 16:
        raise BadInputError(f"expected a 2-D image of at least 16x16 pixels, got shape {data.shape}")
    if data.dtype not in (np.float32, np.float64, np.uint8, np.uint16) or data.strides[1] != data.itemsize:
        data = np.ascontiguousarray(data, dtype=np.float32 if data.dtype != np.float64 else np.float64)
    size = (max(1, data.shape[1] // 4), max(1, data.shape[0] // 4))
    small = cv2.resize(data, size, interpolation=cv2.INTER_AREA).astype(np.float64)
    if not np.isfinite(small).all():  # every pixel weighs in the area average: NaN and inf show here
        data = np.nan_to_num(data, nan=0.0, posinf=0.0, neginf=0.0)
        small = cv2.resize(data, size, interpolation=cv2.INTER_AREA).astype(np.float64)
    clipped = None if saturated is None else np.asarray(saturated, dtype=bool)
    if clipped is not None and clipped.any():
        top = float(data.max())
        share = cv2.resize(clipped.view(np.uint8) * np.uint8(255), size, interpolation=cv2.INTER_AREA) / 255.0
        small += (top - small) * share  # the reduced copy of the clipped pixels set to the top
    else:
        clipped = None
    lo, hi = quantiles.percentile(small, (0.05, 99.95))
    if hi - lo <= 0:
        return np.zeros(data.shape, np.float32)
    # No clipping: the saddle positions need the linear data.
    gain = 1.0 / (hi - lo)
    norm = cv2.addWeighted(data, gain, data, 0.0, -lo * gain, dtype=cv2.CV_32F)
    if clipped is not None:
        np.copyto(norm, np.float32((top - lo) * gain), where=clipped)
    return norm


def _search(norm: np.ndarray) -> list[np.ndarray]:
    """Homographies (pattern cells -> image px, correct orientation) of every target found.

    The pyramid levels are searched from the coarsest. Inside a target found
    on a coarser level nothing is searched again on the finer ones: that
    target's own marks would be found again, and its noise, which a finer
    level sees as a field of X-corners in step with its cells (a target
    close up at a few px/cell), would seed hundreds of hypotheses to grow
    and refuse (seconds on a 3000 x 2000 plane, measured).

    The first search takes only saddles about as strong as the contrast
    around them (see `_proposals`), half of a cluttered scene's. A target in
    shade beside a bright window or sky is weaker than the contrast around
    its outer marks, so when that finds nothing, the search is made again
    with the others judged too (the pyramid and the strong ones are not
    computed twice: a frame without a target costs about one search of
    every saddle).

    Each level's saddles are centred on the finer level (`_judge`), but the
    image itself has none: at 0.175-0.19 px/cell (IJCV 2012 sec. 3.3 takes
    s/t down to 0.7, 0.175 px/cell at s = 4) the squares beside a mark pull
    its centre there 0.3-0.5 px off, and a quarter of the marks fail the
    X-corner test. So when nothing is found, the image is searched again
    with its saddles centred on itself smoothed half as much, as a finer
    level would smooth (only the image: the coarser levels found nothing
    already). A frame without a target costs about 60 % more (0.16 -> 0.26
    s on a cluttered 1953 x 1301 plane).
    """
    levels: list[tuple[_Level, _Level | None, np.ndarray]] = []
    lv, finer = _Level.of(norm), None
    while min(lv.image.shape) >= _SMALLEST:
        coarser = cv2.pyrDown(lv.image)
        levels.append((lv, finer, coarser))
        finer, lv = lv, _Level.of(coarser)
    proposed: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # per level: peaks, and which are strong
    strong: dict[int, tuple[np.ndarray, ...]] = {}  # per level: the strong peaks judged

    def search(first: bool) -> list[np.ndarray]:
        found: list[np.ndarray] = []
        for level in reversed(range(len(levels))):
            lv, finer, coarser = levels[level]
            to_full = np.diag([2.0**level, 2.0**level, 1.0])  # pyrDown keeps pixel i at 2i
            taken = [np.linalg.inv(to_full) @ g for g in found]  # targets found on coarser levels
            if first:
                if level not in proposed:
                    proposed[level] = _proposals(lv, coarser)
                peaks, local = proposed[level]
                judged = strong[level] = _judge(lv, finer, _off(peaks[local], taken))
            else:  # the other peaks now, with the strong ones judged the first time
                peaks, local = proposed[level]
                more = _judge(lv, finer, _off(peaks[~local], taken))
                judged = tuple(np.concatenate(pair) for pair in zip(strong[level], more))

            def verify(h: np.ndarray, to_full=to_full) -> np.ndarray | None:
                return _orient(norm, to_full @ h)

            def known(h: np.ndarray, to_full=to_full) -> bool:
                return any(_same_target(to_full @ h, g) for g in found)

            for h in _find_at_level(_select(lv, judged, taken), verify, known):
                if not known(h, np.eye(3)):  # grown from a seed that did not look like it
                    found.append(h)
        return found

    found = search(True) or search(False)
    if found or not levels:
        return found
    image, _, coarser = levels[0]
    levels[:] = [(image, _Level.of(norm, _SIGMA / 2, zoom=1.0), coarser)]
    return search(True) or search(False)


def _off(points: np.ndarray, targets: list[np.ndarray]) -> np.ndarray:
    """The points that lie on none of the targets (homographies pattern cells -> the points' pixels)."""
    return points[~_inside(points, targets)]


def _inside(points: np.ndarray, targets: list[np.ndarray]) -> np.ndarray:
    """Whether each point lies on one of the targets (homographies pattern cells -> the points' pixels)."""
    inside = np.zeros(len(points), dtype=bool)
    for h in targets:
        cells = _apply(np.linalg.inv(h), points)
        inside |= np.all((cells >= 0) & (cells <= target.SIZE), axis=1)
    return inside


@dataclass
class _Level:
    """One pyramid level: the image, smoothed (by _SIGMA, or less where it only centres saddles), and its second
    derivatives."""

    image: np.ndarray
    smooth: np.ndarray
    ixx: np.ndarray
    iyy: np.ndarray
    ixy: np.ndarray
    zoom: float = 2.0  # its pixels per pixel of the coarser level whose saddles it centres (`_judge`)

    @classmethod
    def of(cls, image: np.ndarray, sigma: float = _SIGMA, zoom: float = 2.0) -> "_Level":
        smooth = cv2.GaussianBlur(image, (0, 0), sigma)
        return cls(image, smooth, *_hessian(smooth), zoom)


@dataclass
class _Saddles:
    """X-corner candidates of one pyramid level."""

    points: np.ndarray  # (n, 2) level pixels, sub-pixel
    strength: np.ndarray  # (n,) contrast between the light and the dark sectors
    level: np.ndarray  # (n,) mean of the surroundings, halfway between dark and light
    axis: np.ndarray  # (n,) angle of the dark axis (the bisector of the dark sectors), radians mod pi
    shape: np.ndarray  # (n,) how X-like the surroundings are, in [0, 1] (see _x_shape)
    smooth: np.ndarray  # the smoothed level image

    def __post_init__(self) -> None:
        self.tree = _Neighbours(self.points)


class _Neighbours:
    """Fixed-radius neighbour search on a few thousand points: the points binned in square cells of the radius.

    The two searches the detection asks of scipy.spatial.cKDTree (`pairs`, `nearest`), with its results;
    scipy.spatial costs 0.1-0.2 s of start-up (it loads scipy.sparse, scipy.special and scipy.constants),
    more than the searches take on a pyramid level's saddles. A point within distance r of another lies
    in its cell or one of the 8 around it, the distances of those candidates are compared exactly.
    """

    AROUND = [(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]  # a point's cell and the 8 next to it

    def __init__(self, points: np.ndarray) -> None:
        self.points = np.asarray(points, dtype=np.float64).reshape(-1, 2)

    def _cells(self, size: float, xy: np.ndarray | None = None):
        """Cell (col, row) of the points or of ``xy`` in a grid of ``size`` over the points, clipped two
        cells outside (nothing there is within one cell of a point), and the grid's width with that margin."""
        low = self.points.min(axis=0)
        top = np.floor((self.points.max(axis=0) - low) / size).astype(np.int64)
        where = self.points if xy is None else xy
        cell = np.floor((where - low) / size)
        cell = np.clip(np.nan_to_num(cell, nan=-2.0), -2, top + 2).astype(np.int64)
        width = int(top[0]) + 7
        return cell, width

    def _candidates(self, size: float, xy: np.ndarray, offsets) -> tuple[np.ndarray, np.ndarray]:
        """(query index, point index) of every point in the cells at ``offsets`` (dcol, drow) from each query's."""
        own, width = self._cells(size)
        keys = (own[:, 1] + 3) * width + own[:, 0] + 3
        order = np.argsort(keys, kind="stable")
        ordered = keys[order]
        cell, _ = self._cells(size, xy)
        base = (cell[:, 1] + 3) * width + cell[:, 0] + 3
        queries, found = [], []
        for dx, dy in offsets:
            key = base + dy * width + dx
            start, stop = np.searchsorted(ordered, key, "left"), np.searchsorted(ordered, key, "right")
            counts = stop - start
            q = np.repeat(np.arange(len(xy)), counts)
            within = np.arange(q.size) - np.repeat(np.cumsum(counts) - counts, counts)
            queries.append(q)
            found.append(order[start[q] + within])
        return np.concatenate(queries), np.concatenate(found)

    def pairs(self, r: float) -> np.ndarray:
        """(m, 2) pairs i < j of points at most ``r`` apart (cKDTree.query_pairs(r, output_type="ndarray")),
        in lexicographic order."""
        if len(self.points) < 2 or not r > 0:
            return np.empty((0, 2), dtype=np.intp)
        i, j = self._candidates(r * (1 + 1e-9), self.points, self.AROUND)
        keep = i < j
        i, j = i[keep], j[keep]
        d = self.points[i] - self.points[j]
        keep = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] <= r * r
        out = np.stack([i[keep], j[keep]], axis=1).astype(np.intp)
        return out[np.lexsort((out[:, 1], out[:, 0]))]

    def nearest(self, xy: np.ndarray, k: int, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest points closer than ``bound`` to each of ``xy`` (n, 2), nearest first:
        distances (inf where fewer) and indices (the number of points there), as
        cKDTree.query(xy, k, distance_upper_bound=bound)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        dist = np.full((len(xy), k), np.inf)
        idx = np.full((len(xy), k), len(self.points), dtype=np.intp)
        if len(self.points) == 0 or len(xy) == 0:
            return dist, idx
        q, j = self._candidates(bound * (1 + 1e-9), xy, self.AROUND)
        d = np.hypot(xy[q, 0] - self.points[j, 0], xy[q, 1] - self.points[j, 1])
        keep = d < bound
        q, j, d = q[keep], j[keep], d[keep]
        order = np.lexsort((j, d, q))  # by query, then distance (ties: lower index)
        q, j, d = q[order], j[order], d[order]
        first = np.searchsorted(q, q, "left")
        rank = np.arange(q.size) - first
        take = rank < k
        dist[q[take], rank[take]] = d[take]
        idx[q[take], rank[take]] = j[take]
        return dist, idx


def _proposals(lv: _Level, coarser: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Saddle points of one pyramid level (whole pixels) and which are strong against the contrast around them.

    Saddle points of the smoothed image: sigma^2 sqrt(-det Hess), scale
    normalised, local maxima above a floor (smooth edges and blobs do not
    score, det Hess >= 0). ``coarser`` is the next level's image.
    """
    ixx, iyy, ixy = lv.ixx, lv.iyy, lv.ixy
    # Two level-sized buffers for the whole peak search: on a 24-megapixel
    # plane each fresh array costs as much again in page faults as the
    # arithmetic that fills it.
    neg_det, spare = np.multiply(ixy, ixy), np.multiply(ixx, iyy)
    np.subtract(neg_det, spare, out=neg_det)
    border = int(np.ceil(max(3 * _SIGMA, _RING_RADII[-1] + 2)))
    neg_det[:border] = neg_det[-border:] = 0.0
    neg_det[:, :border] = neg_det[:, -border:] = 0.0
    floor = (_MIN_STRENGTH * _IDEAL / _SIGMA**2) ** 2
    peaks = cv2.compare(neg_det, cv2.dilate(neg_det, np.ones((3, 3), np.uint8), dst=spare), cv2.CMP_GE)
    peaks &= cv2.compare(neg_det, floor, cv2.CMP_GT, dst=spare.view(np.uint8)[:, : neg_det.shape[1]])
    nonzero = cv2.findNonZero(peaks)  # a few times faster than np.nonzero
    xs, ys = np.reshape(nonzero, (-1, 2)).T if nonzero is not None else (np.zeros(0, np.intp),) * 2
    at = ys * neg_det.shape[1] + xs
    xx, yy, strength = ixx.reshape(-1).take(at), iyy.reshape(-1).take(at), np.sqrt(neg_det.reshape(-1).take(at))
    # A saddle of an X-corner has opposite curvatures of similar size; an edge
    # crossing texture does not. Perspective skews the sectors, hence the slack.
    keep = np.abs(xx + yy) <= 2.0 * strength
    # A mark is an X-corner of its own black and white, so its saddle is about
    # as strong as an ideal one of the contrast around it; a texture's saddles
    # are mostly much weaker than the contrast around them. Strength over the
    # light range of the 3 x 3 tiles around (3 x 3 tiles of 8 px, which always
    # hold a mark's own black and white): marks 0.5-0.9 of the ideal (rendered
    # and cluttered frames, 0.2-2 px/cell, blur up to 3 cells), about half of a
    # cluttered scene's saddles below 0.3. `_search` judges these strong ones
    # first, and the others only if that finds nothing: a target in shade
    # beside a much brighter area is weaker than the contrast around it.
    # (Read on the next coarser level, ``coarser``, whose pyrDown smoothing
    # is about _SIGMA here: a quarter of the pixels to reduce.)
    around = _local_range(coarser, _TILE // 2)[ys // _TILE, xs // _TILE]
    local = strength >= _LOCAL_STRENGTH * _IDEAL / _SIGMA**2 * around
    return np.column_stack([xs[keep], ys[keep]]).astype(np.float32), local[keep]


def _judge(lv: _Level, finer: _Level | None, points: np.ndarray) -> tuple[np.ndarray, ...]:
    """The saddle points (whole pixels of ``lv``) that look like X-corners: (points, contrast, level, axis, shape).

    Each is centred to sub-pixel precision and then judged by its own
    surroundings (`_x_shape`, on the finer level where there is one): an
    hourglass mark is an X-corner out to half its block, two opposite dark
    sectors and two opposite light ones, point-symmetric; foliage, letters
    and edges are not.
    """
    # Centre on the saddle (gradient zero) of the finer level, where the
    # smoothing is half as wide and the neighbouring blocks do not pull it;
    # where the finer level shows no saddle at the peak, start from this
    # level's saddle instead. One Newton step, then the outer circle alone
    # (it keeps every point that passes the full test and a third of the
    # others, measured), then a second step and the full test.
    centring = lv if finer is None else finer
    zoom = 1.0 if finer is None else finer.zoom
    points, found = _newton(centring, zoom * points)
    if finer is not None:
        points[~found] = _newton(finer, zoom * _newton(lv, points[~found] / zoom)[0])[0]
    outer = _x_shape(centring.image, points, (zoom * _RING_RADII[-1],))[0]
    points = _newton(centring, points[outer >= _OUTER_SHAPE])[0]
    shape, contrast, level, axis = _x_shape(centring.image, points, zoom * np.asarray(_RING_RADII))
    keep = (shape >= _MIN_SHAPE) & (contrast >= _MIN_CONTRAST)
    return points[keep] / zoom, contrast[keep], level[keep], axis[keep], shape[keep]


def _select(lv: _Level, judged: tuple[np.ndarray, ...], taken: list[np.ndarray]) -> _Saddles:
    """X-corner candidates of one level, chosen locally, from those `_judge` passed.

    Only the best few of every small tile are kept: a busy region elsewhere
    in the frame never pushes a mark out. None is taken on the ``taken``
    targets (homographies pattern cells -> this level's pixels).
    """
    points, contrast, level, axis, shape = judged
    keep = np.flatnonzero(~_inside(points, taken))
    best = keep[_best_per_tile(points[keep], (shape * contrast)[keep], _TILE, _PER_TILE)]
    return _Saddles(points[best].astype(np.float64), contrast[best], level[best], axis[best], shape[best], lv.smooth)


def _newton(lv: _Level, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One Newton step from ``points`` toward the saddle of the smoothed image (at most a pixel).

    Returns the points and whether there was a saddle (det Hess < 0) to move to.
    """
    if np.all(points == np.rint(points)):  # on the pixel grid: no interpolation
        cols = lv.smooth.shape[1]
        at = points[:, 1].astype(np.intp) * cols + points[:, 0].astype(np.intp)  # flat: faster than (row, column)
        smooth = lv.smooth.reshape(-1)
        gx = 0.5 * (smooth.take(at + 1) - smooth.take(at - 1))
        gy = 0.5 * (smooth.take(at + cols) - smooth.take(at - cols))
        xx, yy, xy = (d.reshape(-1).take(at) for d in (lv.ixx, lv.iyy, lv.ixy))
    else:
        # Interpolated: a step from the nearest pixel instead can overshoot
        # by a third of a pixel when the point is most of a pixel from it.
        xs, ys = points[:, 0], points[:, 1]
        gx = 0.5 * (_remap(lv.smooth, xs + 1, ys) - _remap(lv.smooth, xs - 1, ys))
        gy = 0.5 * (_remap(lv.smooth, xs, ys + 1) - _remap(lv.smooth, xs, ys - 1))
        xx, yy, xy = (_remap(d, xs, ys) for d in (lv.ixx, lv.iyy, lv.ixy))
    det = xx * yy - xy * xy
    found = det < 0
    det = np.where(found, det, -np.inf)  # not a saddle there: stay
    step = np.column_stack([(xy * gy - yy * gx) / det, (xy * gx - xx * gy) / det])
    return points + np.clip(step, -1.0, 1.0).astype(np.float32), found


def _x_shape(img: np.ndarray, points: np.ndarray, radii) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """How much the surroundings of each point look like an X-corner.

    The image is read on circles of the given radii around each point. The
    angular profile of an X-corner is a square wave of period pi (light,
    dark, light, dark sectors, opposite sectors alike): 81 % of its variance
    lies in the second angular harmonic, and more once blurred (a sinusoid
    has all of it). An edge puts its variance in the first harmonic, a line
    crossing in the fourth, a T-junction or texture spreads it. Reading two
    radii at once also asks the corner to be the same at both, as a corner
    is and a curved structure is not.

    Returns
    -------
    shape : (n,) fraction of the variance in the second harmonic, in [0, 1]
    contrast : (n,) light minus dark of the square wave with that harmonic
    level : (n,) mean of the circles, halfway between dark and light
    axis : (n,) angle of the dark axis, radians mod pi
    """
    angles = 2 * np.pi * np.arange(_RING_SAMPLES) / _RING_SAMPLES
    theta = np.tile(angles, len(radii))
    radius = np.repeat(np.asarray(radii, dtype=np.float64), _RING_SAMPLES)
    dx, dy = (radius * np.cos(theta)).astype(np.float32), (radius * np.sin(theta)).astype(np.float32)
    ring = _remap(img, points[:, 0], points[:, 1], dx, dy)
    level = ring.mean(axis=1)
    ring -= level[:, None]
    re = ring @ np.cos(2 * theta).astype(np.float32)
    im = ring @ np.sin(2 * theta).astype(np.float32)
    power = re * re + im * im
    shape = 2.0 * power / (len(theta) * np.einsum("ij,ij->i", ring, ring) + 1e-30)
    # Profile ~ a cos(2 (theta - light)): a = 2 |harmonic| / n, and a square
    # wave of contrast c has a = 2 c / pi.
    contrast = np.pi / len(theta) * np.sqrt(power)
    light = 0.5 * np.arctan2(im, re)  # direction of the light sectors
    return shape, contrast, level, np.mod(light + np.pi / 2, np.pi)


def _remap(img: np.ndarray, xs: np.ndarray, ys: np.ndarray, dx: np.ndarray | None = None, dy: np.ndarray | None = None) -> np.ndarray:
    """Bilinear samples of ``img`` (edge pixels repeated outside).

    At the points (``xs``, ``ys``) of any shape or, given offsets ``dx``,
    ``dy`` of shape (k,), at each of the (n,) points plus each offset: (n, k).
    """
    xs, ys = np.asarray(xs, dtype=np.float32), np.asarray(ys, dtype=np.float32)
    shape = xs.shape if dx is None else (xs.size, len(dx))
    count = math.prod(shape)
    # cv2.remap takes maps of under 32767 rows and columns: lay them out in
    # rows of 4096 (padded), which also keeps each point's samples together.
    width = 4096
    rows = max(1, -(-count // width))
    maps = np.zeros((2, rows * width), dtype=np.float32)
    if dx is None:
        maps[0, :count], maps[1, :count] = xs.ravel(), ys.ravel()
    else:
        np.add(xs.reshape(-1, 1), dx, out=maps[0, :count].reshape(shape))
        np.add(ys.reshape(-1, 1), dy, out=maps[1, :count].reshape(shape))
    out = cv2.remap(img, maps[0].reshape(rows, width), maps[1].reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1)[:count].reshape(shape)


def _local_range(img: np.ndarray, tile: int) -> np.ndarray:
    """Max minus min of ``img`` over each ``tile`` x ``tile`` tile and its 8 neighbours, one value per tile."""
    # One rectangular max (min) filter over the 3 x 3 tiles, read at each tile's first pixel.
    window = np.ones((3 * tile, 3 * tile), np.uint8)
    corner = (tile, tile)  # the window of the tile at p starts a tile up and left of p
    top = cv2.dilate(img, window, anchor=corner)[::tile, ::tile]
    return top - cv2.erode(img, window, anchor=corner)[::tile, ::tile]


def _best_per_tile(points: np.ndarray, score: np.ndarray, tile: float, count: int) -> np.ndarray:
    """Indices of the ``count`` best-scoring points of every ``tile`` x ``tile`` square."""
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    cells = np.floor(points / tile).astype(np.int64)
    key = cells[:, 1] * (cells[:, 0].max() + 1) + cells[:, 0]
    order = np.lexsort((-score, key))
    ranked = key[order]
    first = np.concatenate([[0], np.flatnonzero(np.diff(ranked)) + 1])
    rank = np.arange(len(order)) - np.repeat(first, np.diff(np.concatenate([first, [len(order)]])))
    return np.sort(order[rank < count])


def _hessian(smooth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Second derivatives (xx, yy, xy) by 3 x 3 Sobel kernels (each has weight 4)."""
    return (
        cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3, scale=0.25),
        cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3, scale=0.25),
        cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3, scale=0.25),
    )


def _ideal_strength() -> float:
    """Saddle strength of a sharp, contrast-1 hourglass mark much larger than the smoothing."""
    side = 64
    v, u = np.mgrid[0:side, 0:side] - (side - 1) / 2.0
    mark = (np.abs(u) >= np.abs(v)).astype(np.float32)
    centre = slice(side // 2 - 1, side // 2 + 1)
    ixx, iyy, ixy = (d[centre, centre] for d in _hessian(cv2.GaussianBlur(mark, (0, 0), _SIGMA)))
    return float(_SIGMA**2 * np.sqrt(np.maximum(ixy * ixy - ixx * iyy, 0)).max())


_IDEAL = _ideal_strength()


def _angle_gap(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Difference between two axis angles, mod pi, in [0, pi/2]."""
    d = np.mod(a - b, np.pi)
    return np.minimum(d, np.pi - d)


def _find_at_level(sad: _Saddles, verify, known) -> list[np.ndarray]:
    """Homographies (pattern -> full image) of the targets found on one level.

    Every pair of candidates that could be two neighbouring marks of a row of
    the ring (a similarity) is scored by how many of the other ten marks it
    predicts where the layout puts them; hypotheses are grown and checked in
    that order, with no cap on their number. ``verify(h)`` (h: pattern ->
    level px) returns the full-image homography of a genuine target, or None;
    ``known(h)`` tells a target already found, which is not grown again.
    """
    if len(sad.points) < len(target.XCORNER_BLOCKS):
        return []
    pairs = _seed_pairs(sad)
    if len(pairs) == 0:
        return []
    pts = sad.points
    pattern = target.xcorner_points()
    zpat = pattern[:, 0] + 1j * pattern[:, 1]
    zimg = pts[:, 0] + 1j * pts[:, 1]
    weakest = np.minimum(sad.strength[pairs[:, 0]], sad.strength[pairs[:, 1]])
    scores, candidates = [], []
    for a, b in _SEED_EDGES:
        # Similarity z = alpha Z + beta taking mark a to the first point and b to the second.
        alpha = (zimg[pairs[:, 1]] - zimg[pairs[:, 0]]) / (zpat[b] - zpat[a])
        beta = zimg[pairs[:, 0]] - alpha * zpat[a]
        models = np.zeros((len(pairs), 3, 3))
        models[:, 0, 0] = models[:, 1, 1] = alpha.real
        models[:, 1, 0], models[:, 0, 1] = alpha.imag, -alpha.imag
        models[:, 0, 2], models[:, 1, 2], models[:, 2, 2] = beta.real, beta.imag, 1.0
        scores.append((_match(sad, models, pattern, weakest, 0.3) >= 0).sum(axis=1))
        candidates.append(models)
    # Keep, for each seed pair, the ring edge it explains best; grow the best first.
    scores, candidates = np.stack(scores), np.stack(candidates)
    best = np.argmax(scores, axis=0)
    hits = scores[best, np.arange(len(pairs))]
    quality = hits + sad.shape[pairs].mean(axis=1)  # ties: the more X-like seeds first
    order = [k for k in np.argsort(-quality, kind="stable") if hits[k] >= _MIN_SEED_HITS]
    results: list[np.ndarray] = []
    used: set[int] = set()
    for k in order:
        seed = tuple(pairs[k])
        model = candidates[best[k], k]
        if used.intersection(seed) or known(model):
            continue
        grown = _grow(sad, pattern, model, weakest[k])
        if grown is None:
            continue
        h, members = grown
        verified = verify(h)
        if verified is not None:
            used.update(members)
            results.append(verified)
    return results


def _seed_pairs(sad: _Saddles) -> np.ndarray:
    """(m, 2) ordered pairs of candidates that may be neighbouring marks on a row of the ring.

    Two neighbours on a row are about as strong as each other, with their
    dark axes across the row (the hourglasses stand on the rows), and
    between them lie a flat black and a flat white square, one third and two
    thirds of the way (their order depends on the row), each read at its
    centre and a quarter block to either side, along and across. Every test
    is symmetric, so each pair that passes is returned in both orders.
    """
    pairs = sad.tree.pairs(_SPACING[1])
    a, b = pairs[:, 0], pairs[:, 1]
    x, y = sad.points[:, 0].astype(np.float32), sad.points[:, 1].astype(np.float32)
    cos, sin = np.cos(sad.axis).astype(np.float32), np.sin(sad.axis).astype(np.float32)
    dx, dy = x[b] - x[a], y[b] - y[a]
    # Each axis across the step: its component along the step under sin(tol) (squared here).
    length = dx * dx + dy * dy
    limit = np.float32(np.sin(_AXIS_TOL) ** 2) * length
    keep = np.square(cos[a] * dx + sin[a] * dy) < limit
    keep &= np.square(cos[b] * dx + sin[b] * dy) < limit
    keep &= length >= np.float32(_SPACING[0] ** 2)
    keep &= np.minimum(sad.strength[a], sad.strength[b]) > _STRENGTH_RATIO * np.maximum(sad.strength[a], sad.strength[b])
    pairs = pairs[keep]
    a, b = pairs[:, 0], pairs[:, 1]
    start, step = sad.points[a], sad.points[b] - sad.points[a]
    # Sample points start + along * step + aside * (step turned a quarter).
    along = np.repeat(np.float32([1 / 3, 2 / 3]), 5) + np.tile(np.float32([0, 1, -1, 0, 0]), 2) / 12
    aside = np.tile(np.float32([0, 0, 0, 1, -1]), 2) / 12
    squares = _remap(sad.smooth, start[:, :1] + step[:, :1] * along - step[:, 1:] * aside,
                     start[:, 1:] + step[:, 1:] * along + step[:, :1] * aside).reshape(-1, 2, 5)
    mid = 0.5 * (sad.level[a] + sad.level[b])
    contrast = 0.5 * (sad.strength[a] + sad.strength[b])
    flat = np.ptp(squares, axis=2).max(axis=1) < _FLAT_TOL * contrast
    means = squares.mean(axis=2)
    keep = flat & (means.min(axis=1) < mid - _SQUARE_TOL * contrast) & (means.max(axis=1) > mid + _SQUARE_TOL * contrast)
    pairs = pairs[keep]
    return np.concatenate([pairs, pairs[:, ::-1]])  # both orders: no mirror images needed


def _match(sad: _Saddles, models: np.ndarray, pattern: np.ndarray, seed_strength, tol: float) -> np.ndarray:
    """Index of the saddle taken for each mark predicted by each model (-1: none).

    A mark is matched to the nearest saddle within ``tol`` of the mark spacing
    that is about as strong as the seeds and whose dark axis follows the
    pattern's y axis there. ``models`` is (m, 3, 3) (or one 3 x 3) and
    ``seed_strength`` (m,) or a scalar; the result is (m, 12) (or (12,)).
    """
    single = models.ndim == 2
    models = models.reshape(-1, 3, 3)
    guess = _apply_many(models, pattern)
    up = _apply_many(models, pattern + [0.0, 8.0]) - _apply_many(models, pattern - [0.0, 8.0])
    spacing = np.linalg.norm(np.roll(guess, -1, axis=1) - guess, axis=2)
    local = 0.5 * (spacing + np.roll(spacing, 1, axis=1))  # mean distance to the two ring neighbours
    bound = np.nan_to_num(tol * local, nan=0.0, posinf=0.0)
    dist, idx = sad.tree.nearest(np.nan_to_num(guess.reshape(-1, 2), nan=-1e9), 6, max(bound.max(), 1e-9))
    dist, idx = dist.reshape(*guess.shape[:2], 6), idx.reshape(*guess.shape[:2], 6)
    valid = np.isfinite(dist) & (dist < bound[..., None])
    idx = np.where(valid, idx, 0)
    strong = _STRENGTH_RATIO * np.broadcast_to(np.asarray(seed_strength, dtype=float), (len(models),))
    valid &= sad.strength[idx] > strong[:, None, None]
    valid &= _angle_gap(sad.axis[idx], np.arctan2(up[..., 1], up[..., 0])[..., None]) < _AXIS_TOL
    first = np.argmax(valid, axis=2)[..., None]
    out = np.where(np.take_along_axis(valid, first, 2), np.take_along_axis(idx, first, 2), -1)[..., 0]
    return out[0] if single else out


def _grow(sad: _Saddles, pattern: np.ndarray, model: np.ndarray, seed_strength: float):
    """Grow a seed transform into a homography by matching the marks it predicts.

    Each round keeps the marks matched within a quarter of the mark spacing
    and refits, so the fit spreads from the seed pair to the whole ring even
    under perspective. Returns (homography, indices of the 12 saddles) when
    every mark ends within a twentieth of the spacing (plus the one-pixel
    quantisation of the candidates) of the fit, else None.
    """
    previous = None
    for _ in range(8):
        matched = _match(sad, model, pattern, seed_strength, 0.25)
        ok = matched >= 0
        if ok.sum() < 5 or len(set(matched[ok])) < ok.sum():
            return None
        if previous is not None and np.array_equal(matched, previous):
            break
        previous = matched
        model = _fit(pattern[ok], sad.points[matched[ok]])
    if not ok.all():
        return None
    guess = _apply(model, pattern)
    spacing = np.linalg.norm(np.roll(guess, -1, axis=0) - guess, axis=1)
    if np.any(np.linalg.norm(sad.points[matched] - guess, axis=1) > 0.05 * spacing.min() + 1.0):
        return None
    return model, set(matched.tolist())


def _fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares transform src -> dst: similarity on one line, affine below 7 points, else homography."""
    centred = src - src.mean(axis=0)
    if np.linalg.matrix_rank(centred, tol=1e-6 * target.SIZE) < 2:
        zs, zd = centred[:, 0] + 1j * centred[:, 1], dst[:, 0] + 1j * dst[:, 1]
        alpha = np.vdot(zs, zd - zd.mean()) / np.vdot(zs, zs)
        zc = src.mean(axis=0) @ [1, 1j]
        beta = zd.mean() - alpha * zc
        return np.array([[alpha.real, -alpha.imag, beta.real], [alpha.imag, alpha.real, beta.imag], [0, 0, 1]])
    if len(src) < 7:
        design = np.column_stack([src, np.ones(len(src))])
        coef, *_ = np.linalg.lstsq(design, dst, rcond=None)
        return np.vstack([coef.T, [0.0, 0.0, 1.0]])
    h, _ = cv2.findHomography(src, dst, 0)
    return h


def _orient(norm: np.ndarray, h: np.ndarray) -> np.ndarray | None:
    """Turn ``h`` so that the marks are labelled as published, or None if this is not the target.

    The ring of X-corner positions is invariant under quarter turns, so ``h``
    is known up to one. Each hourglass has its black triangles along the
    pattern's y axis, which leaves a half turn; the flat squares settle it, as
    corner (9, 9) is the only ring corner with black squares on both sides
    (target.ORIENTATION_CORNER). A turn is accepted only if every mark and
    every flat square reads as it should, which also rejects look-alike rings
    (junctions between ring blocks, textures).
    """
    accepted = [h @ _quarter_turn(k) for k in range(4) if _looks_like_target(norm, h @ _quarter_turn(k))]
    return accepted[0] if len(accepted) == 1 else None


def _looks_like_target(norm: np.ndarray, h: np.ndarray) -> bool:
    """Check the flat squares and the hourglass sectors under the labelling ``h``."""
    flats = target.BLACK_BLOCKS + target.WHITE_BLOCKS
    level = _sample(norm, h, np.array([target.block_centre(b) for b in flats]), 8.0)
    if not np.all(np.isfinite(level)):
        return False
    # 12 dark and 12 light squares, well apart.
    ranked = np.sort(level)
    contrast = quantiles.median(ranked[12:]) - quantiles.median(ranked[:12])
    if contrast < 0.1 or ranked[12] - ranked[11] < 0.3 * contrast:
        return False
    dark = {b for b, v in zip(flats, level) if v < 0.5 * (ranked[11] + ranked[12])}
    # Orientation: the only ring corner with dark squares on both sides is (9, 9) ...
    flanked = [c for c in _RING_CORNERS if all(n in dark for n in _neighbours(c))]
    if flanked != [target.ORIENTATION_CORNER]:
        return False
    # ... and every other square must then be where the layout puts it.
    if dark != set(target.BLACK_BLOCKS):
        return False
    # Hourglass sectors, sampled 8 to 12 cells from the saddle (clear of the
    # blurred apex even at 0.2 px/cell): black above and below, white left and right.
    marks = target.xcorner_points()
    along = (8.0, 10.0, 12.0)
    sides = [[(sx * d, sy * d) for d in along] for sx, sy in ((0, -1), (0, 1), (-1, 0), (1, 0))]
    means = np.stack([np.mean([_sample(norm, h, marks + o, 0.0) for o in side], axis=0) for side in sides])
    if not np.all(np.isfinite(means)):
        return False
    return bool(np.all(means[2:].min(axis=0) - means[:2].max(axis=0) > 0.25 * contrast))


def _neighbours(corner: tuple[int, int]) -> list[tuple[int, int]]:
    """The two ring blocks next to a ring corner block."""
    cx, cy = corner
    return [(cx + (1 if cx == 0 else -1), cy), (cx, cy + (1 if cy == 0 else -1))]


def _quarter_turn(turns: int) -> np.ndarray:
    """Matrix of ``turns`` quarter turns (X, Y) -> (SIZE - Y, X) in pattern cells."""
    step = np.array([[0.0, -1.0, target.SIZE], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return np.linalg.matrix_power(step, turns)


def _sample(norm: np.ndarray, h: np.ndarray, points: np.ndarray, radius_cells: float) -> np.ndarray:
    """Mean image value in a square of +-``radius_cells`` around pattern points (NaN outside the image).

    Below one pixel the square is a single bilinear sample at the point.
    """
    centres = _apply(h, points)
    rows, cols = norm.shape
    half = int(radius_cells * _scale(_apply(h, target.xcorner_points())))
    inside = np.all(np.isfinite(centres), axis=1)
    inside &= (centres[:, 0] >= half) & (centres[:, 0] <= cols - 1 - half)
    inside &= (centres[:, 1] >= half) & (centres[:, 1] <= rows - 1 - half)
    out = np.full(len(centres), np.nan)
    if half == 0:
        xy = centres[inside].astype(np.float32).reshape(-1, 1, 2)
        if len(xy):
            out[inside] = cv2.remap(norm, xy[..., 0], xy[..., 1], cv2.INTER_LINEAR).ravel()
        return out
    for k in np.nonzero(inside)[0]:
        x, y = np.rint(centres[k]).astype(int)
        out[k] = norm[y - half : y + half + 1, x - half : x + half + 1].mean()
    return out


def _same_target(h1: np.ndarray, h2: np.ndarray) -> bool:
    """True when two homographies put the target's centre within a block of each other."""
    centre = np.array([[target.SIZE / 2, target.SIZE / 2]])
    gap = np.linalg.norm(_apply(h1, centre) - _apply(h2, centre))
    return bool(gap < _scale(_apply(h1, target.xcorner_points())) * target.BLOCK)


def _refine(data: np.ndarray, saturated: np.ndarray | None, corners: np.ndarray, scale: float) -> np.ndarray:
    """Sub-pixel saddle points by gradient orthogonality (cv2.cornerSubPix).

    Thesis App. A.1: window 7 x 7 (R = 3), tol 1e-5, 200 iterations, for a
    target at about 0.37 px/cell, i.e. a window of +-8 cells. The window is
    kept at +-8 cells at every scale, half the mark, so that it never reaches
    the neighbouring blocks whose edges would pull the estimate. Below
    0.375 px/cell that is under 3 pixels, too few for the gradient
    estimate, so the patch is first resampled (bicubic) on a u-times finer
    grid; the resampling is symmetric about every pixel, so it adds no bias.
    Only the crops around the marks are read: the solution does not depend
    on the image's gain or offset, so no normalisation is needed.
    """
    upsample = max(1, int(np.ceil(3.0 / (_REFINE_CELLS * scale))))
    radius = int(round(_REFINE_CELLS * scale * upsample))
    half = (radius + 4) // upsample + 2  # crop half-size in image pixels
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-5)
    rows, cols = data.shape
    refined = corners.copy()
    lost = np.zeros(len(corners), dtype=bool)
    for k, (x, y) in enumerate(corners):
        # An integer-aligned crop, resized by an integer factor: warpAffine would
        # quantise a fractional shift to 1/32 px and bias the result by ~0.03 px.
        cx, cy = int(round(x)), int(round(y))
        if not (half <= cx < cols - half and half <= cy < rows - half):
            lost[k] = True
            continue
        crop = _crop(data, saturated, cx, cy, half)
        if upsample > 1:
            crop = cv2.resize(crop, None, fx=upsample, fy=upsample, interpolation=cv2.INTER_CUBIC)
        # Patch pixel p sits at crop coordinate (p + 0.5) / u - 0.5.
        start = ((np.array([x - cx + half, y - cy + half]) + 0.5) * upsample - 0.5).astype(np.float32)
        point = _subpix(crop, start, radius, criteria)
        if point is None:  # already the saddle, or put back: try again from a little aside
            again = _subpix(crop, start + np.float32(0.25 * upsample), radius, criteria)
            point = again if again is not None and np.linalg.norm(again - start) < 0.05 * upsample else None
        lost[k] = point is None
        if point is not None:
            refined[k] = (point + 0.5) / upsample - 0.5 + [cx - half, cy - half]
    if np.any(lost):
        raise TargetNotFoundError(
            f"calibration target found at {scale:.2f} px/cell but its marks are too blurred to locate precisely"
        )
    return refined


def _subpix(crop: np.ndarray, start: np.ndarray, radius: int, criteria) -> np.ndarray | None:
    """cv2.cornerSubPix from ``start``, or None where it puts the point back where it started.

    It does so when the iteration leaves the window: such a mark cannot be
    located. A start that already is the saddle also stays put, which the
    caller tells apart by starting again from a little aside.
    """
    point = start.reshape(1, 1, 2).copy()
    cv2.cornerSubPix(crop, point, (radius, radius), (-1, -1), criteria)
    step = np.linalg.norm(point[0, 0] - start)
    return None if step == 0 or step >= radius else point[0, 0].astype(np.float64)


def _crop(data: np.ndarray, saturated: np.ndarray | None, cx: int, cy: int, half: int) -> np.ndarray:
    """float32 square around (cx, cy), NaN read as black and clipped pixels as the brightest there."""
    window = (slice(cy - half, cy + half + 1), slice(cx - half, cx + half + 1))
    crop = np.nan_to_num(data[window].astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    if saturated is not None:
        clipped = np.asarray(saturated[window], dtype=bool)
        if clipped.any():
            crop[clipped] = crop.max()
    return crop


def _scale(corners: np.ndarray) -> float:
    """Image pixels per cell from the mean spacing of ring-adjacent marks (3 blocks)."""
    spacing = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    return float(spacing.mean() / (3 * target.BLOCK))


def _apply_many(hs: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply (m, 3, 3) homographies to (n, 2) points: (m, n, 2)."""
    p = np.einsum("mij,nj->mni", hs, np.column_stack([points, np.ones(len(points))]))
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[..., :2] / p[..., 2:3]


def _apply(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 3 x 3 homography to (n, 2) points."""
    p = np.column_stack([points, np.ones(len(points))]) @ h.T
    return p[:, :2] / p[:, 2:3]
