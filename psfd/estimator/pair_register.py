"""Registration of a near/far pair: SIFT matches and a robust homography.

The two-photo method needs the map D from the far photograph to the near one
with sub-pixel accuracy (Delbracio, Almansa, Musé, IPOL 2013, sec. 4.1: SIFT
keypoints and an a-contrario robust homography). OpenCV provides SIFT and a
robust estimator (MAGSAC++, in the same a-contrario spirit as ORSA), so both
are used as they are. Which photo is near is read from the homography (the far
photo is the contraction), never from the order the photos were given in, and
the registration is then made far -> near whatever that order.

Coordinates are (x, y) with pixel centres at integers, as everywhere in psfd.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import lgamma, log

import cv2
import numpy as np

from psfd.errors import PairError
from psfd.estimator import quantiles
from psfd.workers import concurrently

__all__ = ["Registration", "bounding_box", "common_region", "features", "log10_nfa", "match",
           "register", "to_uint8"]

RATIO = 0.8  # Lowe's ratio test (IJCV 2004, sec. 7.1)
PRECISION = 1.5  # inlier threshold in pixels, the IPOL 2013 ORSA precision
MIN_INLIERS = 5  # IPOL 2013 code: fewer matches cannot define a homography robustly
MAX_PIXELS = 400_000  # SIFT works on at most this many pixels per photo (see `_factor`)


@dataclass
class Registration:
    """The far -> near homography of a pair and the evidence for it.

    Attributes
    ----------
    near : int
        Index (0 or 1) of the near photo among the two given to `register`.
    to_near : ndarray (3, 3)
        D: far-plane (x, y) -> near-plane (x, y), normalised so that D[2, 2] = 1.
    far_points, near_points : ndarray (n, 2)
        The inlier matches.
    matches : int
        Matches that passed the ratio test, before the robust fit.
    rms : float
        RMS reprojection error of the inliers, in far pixels.
    """

    near: int
    to_near: np.ndarray
    far_points: np.ndarray
    near_points: np.ndarray
    matches: int
    rms: float

    @property
    def inliers(self) -> int:
        return int(len(self.far_points))

    def map(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map far-plane coordinates (arrays of any shape) to the near plane."""
        return _apply(self.to_near, x, y)

    def jacobian(self, x: float, y: float) -> np.ndarray:
        """2x2 derivative of D at the far-plane point (x, y): columns d/dx, d/dy."""
        return _jacobian(self.to_near, x, y)

    def geometry(self, x: float, y: float) -> tuple[float, float, float]:
        """Local zoom (lambda_x, lambda_y) and rotation (degrees) of D at a far-plane point.

        The papers take lambda = (D00, D11) for a pure zoom (IPOL 2013, sec. 4.4);
        the norms of the Jacobian's columns are the same for a pure zoom and stay
        right when a small rotation mixes the axes.
        """
        jac = self.jacobian(x, y)
        lam_x, lam_y = np.hypot(jac[0, 0], jac[1, 0]), np.hypot(jac[0, 1], jac[1, 1])
        rotation = np.degrees(np.arctan2(jac[1, 0] - jac[0, 1], jac[0, 0] + jac[1, 1]))
        return float(lam_x), float(lam_y), float(rotation)


def _jacobian(h: np.ndarray, x: float, y: float) -> np.ndarray:
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    X = (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w
    Y = (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
    return np.array(
        [
            [(h[0, 0] - X * h[2, 0]) / w, (h[0, 1] - X * h[2, 1]) / w],
            [(h[1, 0] - Y * h[2, 0]) / w, (h[1, 1] - Y * h[2, 1]) / w],
        ]
    )


def _apply(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w


def to_uint8(image: np.ndarray) -> np.ndarray:
    """Stretch a linear plane to 8 bits for SIFT (0.1 and 99.9 percentiles to 0 and 255).

    SIFT's contrast threshold is absolute, so a dim RAW plane would lose most
    keypoints without a stretch; a robust one keeps a few hot pixels from
    compressing the rest.
    """
    image = np.asarray(image, dtype=np.float64)
    # a strided sample gives the same percentiles at a fraction of the cost on large planes
    step = max(1, int(np.sqrt(image.size / 250_000)))
    lo, hi = quantiles.percentile(image[::step, ::step], (0.1, 99.9))  # np.percentile's, without numpy.ma
    if hi <= lo:
        return np.zeros(image.shape, dtype=np.uint8)
    return np.clip((image - lo) * (255.0 / (hi - lo)) + 0.5, 0, 255).astype(np.uint8)


def _factor(shape: tuple[int, int]) -> float:
    """Down-scaling applied before SIFT so that a photo has at most MAX_PIXELS pixels.

    Only the near photo's coarse keypoints can match the far photo (its fine
    ones image below the far photo's resolution), so shrinking a large near
    photo loses no match and costs little precision once expressed in far
    pixels; `register` checks that afterwards and redoes the far photo at full
    resolution if it was the one shrunk.
    """
    return max(1.0, float(np.sqrt(shape[0] * shape[1] / MAX_PIXELS)))


def features(image8: np.ndarray, factor: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """SIFT keypoints and descriptors of an 8-bit image, optionally computed on a shrunk copy.

    Returns
    -------
    points : ndarray (n, 2)
        Keypoint (x, y) in the coordinates of ``image8``.
    descriptors : ndarray (n, 128) of float32
    """
    rows, cols = image8.shape
    small = image8
    if factor > 1.0:
        size = (max(8, round(cols / factor)), max(8, round(rows / factor)))
        small = cv2.resize(image8, size, interpolation=cv2.INTER_AREA)
    # precise upscale keeps the doubled first octave aligned with the input grid
    # (the default bilinear doubling shifts keypoints by a quarter pixel)
    sift = cv2.SIFT_create(enable_precise_upscale=True)
    keypoints, desc = sift.detectAndCompute(small, None)
    if not keypoints:
        return np.zeros((0, 2)), np.zeros((0, 128), dtype=np.float32)
    pts = np.array([kp.pt for kp in keypoints], dtype=np.float64)
    if small is not image8:
        # pixel centres: x_full = (x_small + 0.5) * scale - 0.5
        pts = (pts + 0.5) * np.array([cols / small.shape[1], rows / small.shape[0]]) - 0.5
    return pts, desc


def match(
    points_a: np.ndarray, desc_a: np.ndarray, points_b: np.ndarray, desc_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Ratio-test matches between two keypoint sets, duplicates removed.

    Returns
    -------
    (pa, pb) : ndarray (m, 2) each, matched positions in a and in b.
    """
    if len(desc_a) < 2 or len(desc_b) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    # a k-d forest: exhaustive matching of tens of thousands of descriptors costs seconds
    flann = cv2.FlannBasedMatcher({"algorithm": 1, "trees": 4}, {"checks": 64})
    pairs = flann.knnMatch(desc_a, desc_b, k=2)
    good = [(m.queryIdx, m.trainIdx, m.distance) for m, n in (p for p in pairs if len(p) == 2)
            if m.distance < RATIO * n.distance]
    if not good:
        return np.zeros((0, 2)), np.zeros((0, 2))
    # one-to-one: a keypoint of b that is the nearest of several of a keeps only its closest match. Many
    # to one are no correspondences, and they let the robust fit accept a homography that collapses
    # the plane onto that one point (a far photo of a print of repeated cells: 85 matches, 21 far points)
    good.sort(key=lambda g: g[2])  # stable: ties keep the order of a
    _, first = np.unique([g[1] for g in good], return_index=True)
    idx = np.array([good[i][:2] for i in sorted(first, key=lambda i: (good[i][0], good[i][1]))])
    pa, pb = points_a[idx[:, 0]], points_b[idx[:, 1]]
    # several keypoints (orientations) at one place give the same match twice
    _, keep = np.unique(np.round(np.hstack([pa, pb]), 2), axis=0, return_index=True)
    keep.sort()
    return pa[keep], pb[keep]


def _robust_fit(
    src: np.ndarray, dst: np.ndarray, precision: float, dst_area: float
) -> tuple[np.ndarray, np.ndarray]:
    """MAGSAC++ homography src -> dst and its inlier mask; PairError when the photos do not match.

    Four matches always fit a homography, so a few agreeing matches prove
    nothing: the fit is kept only if its inliers are not what chance would give,
    by the a-contrario number of false alarms of Moisan, Moulon, Monasse
    (IPOL 2012, the ORSA homography the IPOL 2013 code uses).
    """
    found, n = 0, len(src)
    if n >= 4:
        h, mask = cv2.findHomography(
            src.astype(np.float32), dst.astype(np.float32), cv2.USAC_MAGSAC, precision,
            maxIters=10000, confidence=0.9999,
        )
        if h is not None and abs(h[2, 2]) > 1e-12:
            h = h / h[2, 2]
            inliers = mask.ravel().astype(bool)
            # inliers count as distinct places in both photos: keypoints at one place (several scales or
            # orientations) support a homography no more than one does
            found = min(len(set(map(tuple, np.round(pts[inliers], 2).tolist()))) for pts in (src, dst))
            if found >= MIN_INLIERS and np.linalg.det(h[:2, :2]) > 0:
                px, py = _apply(h, src[inliers, 0], src[inliers, 1])
                eps = max(float(np.max(np.hypot(px - dst[inliers, 0], py - dst[inliers, 1]))), 0.5)
                if log10_nfa(n, found, np.pi * eps**2 / dst_area) < 0.0:
                    return h, inliers
    raise PairError(
        f"unrelated photos: {found} of {n} SIFT matches agree on one homography, no more than chance "
        f"(need {MIN_INLIERS} or more that chance cannot explain); "
        "photograph the same textured plane from two distances"
    )


def log10_nfa(n: int, k: int, alpha: float) -> float:
    """log10 of (n - 4) C(n, k) C(k, 4) alpha^(k - 4): expected number of chance homographies
    with k of n matches within the precision of probability alpha (Moisan et al., IPOL 2012)."""
    def log_comb(a: int, b: int) -> float:
        return lgamma(a + 1) - lgamma(b + 1) - lgamma(a - b + 1)

    alpha = min(max(alpha, 1e-300), 1.0)
    value = log(max(n - 4, 1)) + log_comb(n, k) + log_comb(k, 4) + (k - 4) * log(alpha)
    return value / log(10.0)


def register(a: np.ndarray, b: np.ndarray) -> Registration:
    """Find the far -> near homography of two photographs of one plane, in either order.

    Parameters
    ----------
    a, b : ndarray, 2-D
        Linear channel planes (any scale; each is stretched to 8 bits for SIFT).

    Returns
    -------
    Registration

    Raises
    ------
    PairError
        Fewer than MIN_INLIERS consistent matches, or no more than chance
        would give ("unrelated photos").
    """
    factors = [_factor(np.shape(a)), _factor(np.shape(b))]

    def keypoints(plane: np.ndarray, factor: float) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]:
        image8 = to_uint8(plane)
        return image8, features(image8, factor)

    # the two photos' keypoints are independent: one thread each (0.8 of the real pair's 2.2 s in one)
    (image_a, feats_a), (image_b, feats_b) = concurrently(lambda: keypoints(a, factors[0]),
                                                          lambda: keypoints(b, factors[1]))
    images, feats, areas = (image_a, image_b), (feats_a, feats_b), (float(np.size(a)), float(np.size(b)))
    first = _fit(feats[0], feats[1], factors[1], areas[1])
    near = _near_index(first[0], first[2][first[1]])
    far = 1 - near
    # the photos play the roles near and far, not first and second (IPOL 2013, sec. 4.1: which is which is read
    # from the homography): the fit is the far -> near one, made again when a is near, so that the order the
    # photos come in changes nothing (matched a -> b, the real pair's MTF50 moved by 0.001: 320 or 302 inliers)
    d, inliers, pf, pn = first if near == 1 else _fit(feats[far], feats[near], factors[near], areas[near])
    lam = _zoom(d, pf[inliers])
    if factors[far] > 1.0 or factors[near] > max(1.0, lam / 2):
        # the far photo (or a near photo shrunk by more than lambda/2) lost
        # precision: redo SIFT at the needed resolution on the common region only
        return _refine(images, near, d, lam, len(pf))
    return _finish(near, pf[inliers], pn[inliers], len(pf))


def _fit(src: tuple[np.ndarray, np.ndarray], dst: tuple[np.ndarray, np.ndarray], dst_factor: float,
         dst_area: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Matches of keypoints ``src`` in ``dst`` and the robust homography src -> dst (`_robust_fit`).

    Returns the homography, its inlier mask and the matched points in src and in dst.
    """
    # FLANN's randomised k-d trees (`match`) draw from OpenCV's per-thread generator: restart it from the
    # state a fresh thread starts with (seed 0 stands for it), or the matches, and so the PSF, would
    # depend on what OpenCV drew before (psfd compare's checkerboard search, an earlier pair in the daemon)
    cv2.setRNGSeed(0)
    ps, pd = match(*src, *dst)
    h, inliers = _robust_fit(ps, pd, PRECISION * dst_factor, dst_area)
    return h, inliers, ps, pd


def _zoom(h: np.ndarray, points: np.ndarray) -> float:
    """Mean linear magnification of h at the centre of the points."""
    cx, cy = points.mean(axis=0)
    return float(np.sqrt(abs(np.linalg.det(_jacobian(h, cx, cy)))))


def _near_index(h_ab: np.ndarray, points_a: np.ndarray) -> int:
    """0 if a is the near photo: the far photo is the contraction of the near one."""
    return 0 if _zoom(h_ab, points_a) < 1.0 else 1


def _finish(near: int, far_pts: np.ndarray, near_pts: np.ndarray, matches: int) -> Registration:
    """Least-squares refit of D (far -> near) on all inliers, as the IPOL 2013 code refines its ORSA model."""
    d, _ = cv2.findHomography(far_pts.astype(np.float32), near_pts.astype(np.float32), 0)
    if d is None or abs(d[2, 2]) < 1e-12:  # degenerate inliers (collinear): no plane-to-plane map
        raise PairError("the matches of the two photos do not determine a homography: "
                        "photograph the same textured plane from two distances")
    d = d / d[2, 2]
    reg = Registration(near, d, far_pts, near_pts, matches, 0.0)
    # reprojection error measured in far pixels: map the near points back
    bx, by = _apply(np.linalg.inv(d), near_pts[:, 0], near_pts[:, 1])
    reg.rms = float(np.sqrt(np.mean((bx - far_pts[:, 0]) ** 2 + (by - far_pts[:, 1]) ** 2)))
    return reg


def _refine(images: tuple[np.ndarray, np.ndarray], near: int, d: np.ndarray, lam: float, matches: int) -> Registration:
    """Second pass on the common region: far photo at full resolution, near shrunk by at most lambda/2."""
    far = 1 - near
    far_box, near_box = common_region(d, images[far].shape, images[near].shape, margin=8)
    crops = []
    for im, (x0, y0, x1, y1) in ((images[far], far_box), (images[near], near_box)):
        crops.append((im[y0:y1, x0:x1], np.array([x0, y0], dtype=np.float64)))
    f_near = min(max(1.0, lam / 2), _factor(crops[1][0].shape))
    (pf, df), (pn, dn) = concurrently(lambda: features(crops[0][0], 1.0), lambda: features(crops[1][0], f_near))
    pf, pn = match(pf + crops[0][1], df, pn + crops[1][1], dn)
    _, inliers = _robust_fit(pf, pn, PRECISION * f_near, float(crops[1][0].size))
    return _finish(near, pf[inliers], pn[inliers], max(matches, len(pf)))


def common_region(
    to_near: np.ndarray, far_shape: tuple[int, int], near_shape: tuple[int, int], margin: int = 0
) -> tuple[tuple[int, int, int, int], tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1), end exclusive, of the part of the scene both photos see.

    The far box is the far photo's part that maps inside the near photo; the
    near box is the image of the far box, grown by ``margin`` near pixels so
    that interpolation near its edge has neighbours.
    """
    rows, cols = near_shape
    inv = np.linalg.inv(to_near)
    cx = np.array([0.0, cols - 1, cols - 1, 0.0])
    cy = np.array([0.0, 0.0, rows - 1, rows - 1])
    fx, fy = _apply(inv, cx, cy)
    far_box = bounding_box(fx, fy, far_shape, 0)
    x0, y0, x1, y1 = far_box
    nx, ny = _apply(to_near, np.array([x0, x1 - 1, x1 - 1, x0], float), np.array([y0, y0, y1 - 1, y1 - 1], float))
    return far_box, bounding_box(nx, ny, near_shape, margin)


def bounding_box(x: np.ndarray, y: np.ndarray, shape: tuple[int, int], margin: int) -> tuple[int, int, int, int]:
    """Box (x0, y0, x1, y1), end exclusive, of the pixels around points (x, y), grown by margin, inside shape."""
    rows, cols = shape
    x0 = int(np.clip(np.floor(x.min()) - margin, 0, cols))
    x1 = int(np.clip(np.ceil(x.max()) + 1 + margin, 0, cols))
    y0 = int(np.clip(np.floor(y.min()) - margin, 0, rows))
    y1 = int(np.clip(np.ceil(y.max()) + 1 + margin, 0, rows))
    if x1 - x0 < 1 or y1 - y0 < 1:
        raise PairError("the two photos share no common region")
    return x0, y0, x1, y1
