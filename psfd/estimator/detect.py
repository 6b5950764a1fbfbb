"""Find the Bernoulli calibration target in a photograph.

The target (psfd.estimator.target) carries 12 X-corner marks on a ring around
the noise. Detection follows the plan of Delbracio PhD thesis 2013, App. A.1:
a coarse search for the whole mark configuration, then sub-pixel refinement of
each X-corner by gradient orthogonality (Delbracio et al., IJCV 2012, sec. 4.1;
thesis App. A.1, "Sub-pixel corner refinement").

The coarse search differs from the thesis, which groups LSD line segments:
LSD is not part of OpenCV's free modules in every build, and the X-corners are
found more directly as saddle points of the smoothed image. At a smoothing of
several cells the Bernoulli noise averages out while each hourglass mark stays
a perfect saddle, so the 12 marks are among the strongest saddles of the image
at the octave of the target's scale. Candidates are grouped by hypothesising
that two of them are adjacent marks of the ring (a similarity), collecting the
other ten, and refitting a homography; the flat black and white squares then
fix the orientation (only corner (9, 9) is flanked by two black squares) and
reject anything that is not the target.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.spatial import cKDTree

from psfd.errors import BadInputError, MultipleTargetsError, TargetNotFoundError
from psfd.estimator import target

# Smoothing of the saddle detector, in pixels of each pyramid level. With levels
# a factor 2 apart, a level sees the X-corners at 3 to 8 cells of smoothing for
# targets imaged at 0.19 * 2**L to 0.5 * 2**L pixels per cell: the hourglass is
# an exact saddle out to 16 cells while the noise is averaged down.
_SIGMA = 1.5
_MAX_LEVEL = 3
_MAX_CANDIDATES = 250
_MAX_SEEDS = 120  # strongest candidates tried as seed pairs
_MAX_HYPOTHESES = 300  # seed hypotheses grown, most promising first
_STRENGTH_RATIO = 0.4  # weakest mark / strongest mark accepted in one target
# Saddle strength (see _saddles) below which a point is not a candidate, as a
# fraction of the strength of an ideal contrast-1 X-corner.
_MIN_STRENGTH = 0.12
# Spacing of adjacent ring marks (3 blocks) in level pixels: 96 cells at
# 0.19 .. 0.5 px/cell is 18 .. 48 px; the bounds leave room for perspective.
_SPACING = (10.0, 90.0)
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

    Raises
    ------
    TargetNotFoundError
        No target, or marks that do not form the published layout.
    MultipleTargetsError
        More than one target in the image.
    """
    norm = _normalise(image, saturated)
    found = _search(norm)
    if not found:
        raise TargetNotFoundError(f"no calibration target found in the {norm.shape[1]}x{norm.shape[0]} image")
    if len(found) > 1:
        raise MultipleTargetsError(f"{len(found)} calibration targets found in the image; frame exactly one")
    homography = found[0]
    corners = _apply(homography, target.xcorner_points())
    scale = _scale(corners)
    corners = _refine(norm, corners, scale)
    return Detection(corners=corners, pattern_points=target.xcorner_points(), scale=scale)


def _normalise(image: np.ndarray, saturated: np.ndarray | None) -> np.ndarray:
    """float32 copy stretched to [0, 1] between robust extremes (NaN read as black)."""
    data = np.asarray(image)
    if data.ndim != 2 or min(data.shape) < 16:
        raise BadInputError(f"expected a 2-D image of at least 16x16 pixels, got shape {data.shape}")
    data = np.nan_to_num(data.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    sample = data[:: max(1, data.shape[0] // 512), :: max(1, data.shape[1] // 512)]
    lo, hi = np.percentile(sample, (0.5, 99.5))
    if saturated is not None:
        data[np.asarray(saturated, dtype=bool)] = hi
    if hi - lo <= 0:
        return np.zeros_like(data)
    return np.clip((data - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


def _search(norm: np.ndarray) -> list[np.ndarray]:
    """Homographies (pattern cells -> image px, correct orientation) of every target found."""
    found: list[np.ndarray] = []
    level_img = norm
    for level in range(_MAX_LEVEL + 1):
        if min(level_img.shape) < 24:
            break
        to_full = np.diag([2.0**level, 2.0**level, 1.0])  # pyrDown keeps pixel i at 2i
        for h in _find_at_level(level_img):
            h_full = _orient(norm, to_full @ h)
            if h_full is not None and not any(_same_target(h_full, g) for g in found):
                found.append(h_full)
        level_img = cv2.pyrDown(level_img)
    return found


def _saddles(img: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Saddle points of the smoothed image: positions (n, 2) and strengths (n,), strongest first.

    The strength sigma^2 sqrt(-det Hess) is scale-normalised and proportional
    to contrast; an ideal X-corner of contrast 1 scores about 0.3 (see
    _MIN_STRENGTH), a smooth edge or blob does not score (det Hess >= 0).
    """
    smooth = cv2.GaussianBlur(img, (0, 0), _SIGMA)
    ixx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3) / 4.0
    iyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3) / 4.0
    ixy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3) / 4.0
    neg_det = ixy * ixy - ixx * iyy
    strength = _SIGMA**2 * np.sqrt(np.maximum(neg_det, 0.0))
    # A saddle of an X-corner has opposite curvatures of similar size; an edge
    # crossing texture does not. Perspective skews the sectors, hence the slack.
    strength[np.abs(ixx + iyy) * _SIGMA**2 > strength] = 0.0
    border = int(3 * _SIGMA)
    strength[:border] = strength[-border:] = 0.0
    strength[:, :border] = strength[:, -border:] = 0.0
    peaks = (strength >= cv2.dilate(strength, np.ones((5, 5), np.uint8))) & (strength > _MIN_STRENGTH * _IDEAL)
    ys, xs = np.nonzero(peaks)
    values = strength[ys, xs]
    order = np.argsort(values)[::-1][:_MAX_CANDIDATES]
    return np.column_stack([xs[order], ys[order]]).astype(np.float64), values[order]


def _ideal_strength() -> float:
    """Saddle strength of a sharp, contrast-1 hourglass mark much larger than the smoothing."""
    side = 64
    v, u = np.mgrid[0:side, 0:side] - (side - 1) / 2.0
    mark = (np.abs(u) >= np.abs(v)).astype(np.float32)
    smooth = cv2.GaussianBlur(mark, (0, 0), _SIGMA)
    c = side // 2
    ixx = cv2.Sobel(smooth, cv2.CV_32F, 2, 0, ksize=3)[c - 1 : c + 1, c - 1 : c + 1] / 4.0
    iyy = cv2.Sobel(smooth, cv2.CV_32F, 0, 2, ksize=3)[c - 1 : c + 1, c - 1 : c + 1] / 4.0
    ixy = cv2.Sobel(smooth, cv2.CV_32F, 1, 1, ksize=3)[c - 1 : c + 1, c - 1 : c + 1] / 4.0
    return float(_SIGMA**2 * np.sqrt(np.maximum(ixy * ixy - ixx * iyy, 0)).max())


_IDEAL = _ideal_strength()


def _find_at_level(img: np.ndarray) -> list[np.ndarray]:
    """Homographies (pattern -> level px, orientation up to a quarter turn) of ring-shaped saddle sets."""
    points, strength = _saddles(img)
    if len(points) < len(target.XCORNER_BLOCKS):
        return []
    tree = cKDTree(points)
    seeds = cKDTree(points[:_MAX_SEEDS])
    pairs = np.array(sorted(seeds.query_pairs(_SPACING[1])), dtype=np.int64).reshape(-1, 2)
    gaps = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    ratio = strength[pairs[:, 1]] / strength[pairs[:, 0]]  # <= 1: points are sorted by strength
    pairs = pairs[(gaps >= _SPACING[0]) & (ratio > _STRENGTH_RATIO)]
    pairs = np.concatenate([pairs, pairs[:, ::-1]])  # both orders: no mirror images needed
    if len(pairs) == 0:
        return []
    weakest = np.minimum(strength[pairs[:, 0]], strength[pairs[:, 1]])
    pattern = target.xcorner_points()
    zpat = pattern[:, 0] + 1j * pattern[:, 1]
    zimg = points[:, 0] + 1j * points[:, 1]
    hypotheses = []
    for a, b in _SEED_EDGES:
        # Similarity z = alpha Z + beta taking mark a to the first point and b to the second.
        alpha = (zimg[pairs[:, 1]] - zimg[pairs[:, 0]]) / (zpat[b] - zpat[a])
        beta = zimg[pairs[:, 0]] - alpha * zpat[a]
        pred = alpha[:, None] * zpat[None, :] + beta[:, None]
        dist, idx = tree.query(np.column_stack([pred.real.ravel(), pred.imag.ravel()]))
        dist, idx = dist.reshape(pred.shape), idx.reshape(pred.shape)
        # A hit is a saddle near the predicted mark and about as strong as the seeds
        # (the 12 marks share contrast and blur; the noise's saddles are weaker).
        tol = 0.3 * np.abs(alpha) * 3 * target.BLOCK
        hit = (dist < tol[:, None]) & (strength[idx] > _STRENGTH_RATIO * weakest[:, None])
        hits = hit.sum(axis=1)
        good = np.nonzero(hits >= 7)[0]
        hypotheses.extend((hits[i], pred[i], (pairs[i, 0], pairs[i, 1])) for i in good)
    hypotheses.sort(key=lambda item: -item[0])
    results: list[np.ndarray] = []
    used: set[int] = set()
    for _, pred, seed in hypotheses[:_MAX_HYPOTHESES]:
        if used.intersection(seed):
            continue
        grown = _grow(points, tree, pattern, pred)
        if grown is not None:
            h, members = grown
            used.update(members)
            results.append(h)
    return results


def _grow(points: np.ndarray, tree: cKDTree, pattern: np.ndarray, pred: np.ndarray):
    """Refit a homography to the saddles nearest the predicted marks.

    Returns (homography, indices of the 12 saddles) when every mark has a
    saddle within a twentieth of the mark spacing (plus the one-pixel
    quantisation of the candidates) of the fitted homography, else None.
    """
    guess = np.column_stack([pred.real, pred.imag])
    for tol in (0.3, 0.15, 0.05):
        spacing = np.linalg.norm(np.roll(guess, -1, axis=0) - guess, axis=1)
        local = 0.5 * (spacing + np.roll(spacing, 1))  # mean distance to the two ring neighbours
        dist, idx = tree.query(guess)
        ok = dist < tol * local + (1.0 if tol < 0.1 else 0.0)
        if ok.sum() < 8 or len(set(idx[ok])) < ok.sum():
            return None
        h, _ = cv2.findHomography(pattern[ok], points[idx[ok]], 0)
        if h is None:
            return None
        guess = _apply(h, pattern)
    return (h, set(idx.tolist())) if ok.all() else None


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
    """Check the hourglass sectors and the flat squares under the labelling ``h``."""
    black = _sample(norm, h, np.array([target.block_centre(b) for b in target.BLACK_BLOCKS]), 8.0)
    white = _sample(norm, h, np.array([target.block_centre(b) for b in target.WHITE_BLOCKS]), 8.0)
    if not (np.all(np.isfinite(black)) and np.all(np.isfinite(white))):
        return False
    contrast = np.median(white) - np.median(black)
    if contrast < 0.1 or white.min() - black.max() < 0.3 * contrast:
        return False
    dark_corners = [c for c in _RING_CORNERS if all(_is_black(n) for n in _neighbours(c))]
    if dark_corners != [target.ORIENTATION_CORNER]:
        return False
    # Hourglass sectors, sampled 6 and 10 cells from the saddle: black above and
    # below, white left and right.
    marks = target.xcorner_points()
    offsets = {"dark": ((0, -6), (0, -10), (0, 6), (0, 10)), "light": ((-6, 0), (-10, 0), (6, 0), (10, 0))}
    dark = np.stack([_sample(norm, h, marks + o, 2.0) for o in offsets["dark"]])
    light = np.stack([_sample(norm, h, marks + o, 2.0) for o in offsets["light"]])
    if not (np.all(np.isfinite(dark)) and np.all(np.isfinite(light))):
        return False
    return bool(np.all(light.min(axis=0) - dark.max(axis=0) > 0.3 * contrast))


def _is_black(block: tuple[int, int]) -> bool:
    return block in target.BLACK_BLOCKS


def _neighbours(corner: tuple[int, int]) -> list[tuple[int, int]]:
    """The two ring blocks next to a ring corner block."""
    cx, cy = corner
    return [(cx + (1 if cx == 0 else -1), cy), (cx, cy + (1 if cy == 0 else -1))]


def _quarter_turn(turns: int) -> np.ndarray:
    """Matrix of ``turns`` quarter turns (X, Y) -> (SIZE - Y, X) in pattern cells."""
    step = np.array([[0.0, -1.0, target.SIZE], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    return np.linalg.matrix_power(step, turns)


def _sample(norm: np.ndarray, h: np.ndarray, points: np.ndarray, radius_cells: float) -> np.ndarray:
    """Mean image value in a square of +-``radius_cells`` around pattern points (NaN outside the image)."""
    centres = _apply(h, points)
    scale = _scale(_apply(h, target.xcorner_points()))
    half = int(radius_cells * scale)
    rows, cols = norm.shape
    out = np.full(len(centres), np.nan)
    for k, (x, y) in enumerate(np.rint(centres).astype(int)):
        if half <= x < cols - half and half <= y < rows - half:
            out[k] = norm[y - half : y + half + 1, x - half : x + half + 1].mean()
    return out


def _same_target(h1: np.ndarray, h2: np.ndarray) -> bool:
    """True when two homographies put the target's centre within a block of each other."""
    centre = np.array([[target.SIZE / 2, target.SIZE / 2]])
    gap = np.linalg.norm(_apply(h1, centre) - _apply(h2, centre))
    return bool(gap < _scale(_apply(h1, target.xcorner_points())) * target.BLOCK)


def _refine(norm: np.ndarray, corners: np.ndarray, scale: float) -> np.ndarray:
    """Sub-pixel saddle points by gradient orthogonality (cv2.cornerSubPix).

    Thesis App. A.1: window 7 x 7 (R = 3), tol 1e-5, 200 iterations, for a
    target at about 0.37 px/cell; the window is scaled with the target so that
    it always spans +-8 cells, half the mark, and never reaches the next block.
    """
    radius = max(2, int(round(8 * scale)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 200, 1e-5)
    pts = corners.astype(np.float32).reshape(-1, 1, 2).copy()
    cv2.cornerSubPix(norm, pts, (radius, radius), (-1, -1), criteria)
    refined = pts.reshape(-1, 2).astype(np.float64)
    if np.any(np.linalg.norm(refined - corners, axis=1) > radius):
        raise TargetNotFoundError("calibration target marks could not be located to sub-pixel precision")
    return refined


def _scale(corners: np.ndarray) -> float:
    """Image pixels per cell from the mean spacing of ring-adjacent marks (3 blocks)."""
    spacing = np.linalg.norm(np.roll(corners, -1, axis=0) - corners, axis=1)
    return float(spacing.mean() / (3 * target.BLOCK))


def _apply(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 3 x 3 homography to (n, 2) points."""
    p = np.column_stack([points, np.ones(len(points))]) @ h.T
    return p[:, :2] / p[:, 2:3]
