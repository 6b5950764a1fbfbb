"""Geometric registration of the target: homography, radial distortion, thin-plate splines.

The thesis models the whole distortion between the pattern and the image
(perspective and lens) by one smoothing thin-plate spline fitted on the 12
X-corners (Delbracio et al., IJCV 2012, sec. 4.1; Delbracio PhD thesis 2013,
App. A.2, after Sprengel et al. 1996). `target_maps` by default fits a
homography, plus radial distortion when the corners call for it (as Joshi et
al., CVPR 2008, model their target), which follows rotated, tilted and
distorted views without copying the corners' noise inside (see its
docstring); homography + spline and the spline alone are kept as options.
Both directions are returned: pattern -> image to find the flat squares and
the noise region, image -> pattern to render the pattern on the camera grid.
"""

from __future__ import annotations

import functools
import math
from typing import Callable

import cv2
import numpy as np

from psfd.estimator.detect import Detection

__all__ = ["RadialHomography", "ThinPlateSpline", "image_box", "target_maps"]

# Thesis App. A.2: lambda = 10 for the 12 corners (the distortion over the
# target is almost affine).
SMOOTHING = 10.0


class ThinPlateSpline:
    """Approximating thin-plate spline R^2 -> R^2.

    It minimises (Delbracio PhD thesis 2013, App. A.2, after Sprengel et al. 1996)

        E(f) = sum_i |f(P_i) - p_i|^2 + lambda * J(f),

    over f(x) = d0 + d1 x + d2 y + sum_j c_j phi(|x - P_j|), phi(r) = r^2 log r.
    With the QR decomposition X = [Q1 Q2][R; 0] of the n x 3 affine design
    matrix X = [1 x y] the minimiser is (thesis App. A.2)

        c = Q2 (Q2^T Phi Q2 + lambda I)^-1 Q2^T Y,   d = R^-1 Q1^T (Y - Phi c).

    It solves (Phi + lambda I) c + X d = Y, X^T c = 0, the very system that
    scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline", degree=1,
    smoothing=lambda) solves, so the conventions agree (tests check the two
    against each other). The closed form is written here anyway because the
    spline is evaluated on millions of points of the s-times grid and scipy's
    general evaluator is several times slower than the 12-centre sum below.
    J is the bending energy measured with the kernel r^2 log r (no 1/(8 pi)),
    as in the thesis's closed form, so lambda is in squared source units.
    """

    def __init__(self, centres: np.ndarray, c: np.ndarray, d: np.ndarray) -> None:
        self.centres = centres  # (n, 2) source points P_j
        self.c = c  # (n, 2) non-affine coefficients
        self.d = d  # (3, 2) affine coefficients for [1, x, y]

    @classmethod
    def fit(cls, src: np.ndarray, dst: np.ndarray, smoothing: float = SMOOTHING) -> "ThinPlateSpline":
        """Fit the spline taking ``src`` (n, 2) to ``dst`` (n, 2); n >= 3 points not on a line."""
        src = np.asarray(src, dtype=np.float64)
        dst = np.asarray(dst, dtype=np.float64)
        if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 2 or len(src) < 3:
            raise ValueError(f"need matching (n, 2) point arrays with n >= 3, got {src.shape} and {dst.shape}")
        n = len(src)
        design = np.column_stack([np.ones(n), src])
        q, r = np.linalg.qr(design, mode="complete")
        q1, q2, r = q[:, :3], q[:, 3:], r[:3]
        if abs(np.linalg.det(r)) < 1e-12 * max(1.0, np.abs(src).max()) ** 2:
            raise ValueError("thin-plate spline needs points that are not all on one line")
        phi = _kernel(np.sum((src[:, None, :] - src[None, :, :]) ** 2, axis=2))
        gamma = np.linalg.solve(q2.T @ phi @ q2 + smoothing * np.eye(n - 3), q2.T @ dst)
        c = q2 @ gamma
        d = np.linalg.solve(r, q1.T @ (dst - phi @ c))
        return cls(src, c, d)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        """Map (m, 2) points; returns (m, 2)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        x, y = self.map(points[:, 0], points[:, 1])
        return np.column_stack([x, y])

    def map(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Map coordinate arrays of any (equal) shape; returns (X, Y) of that shape."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        shape = x.shape
        x, y = x.ravel(), y.ravel()
        out_x = self.d[0, 0] + self.d[1, 0] * x + self.d[2, 0] * y
        out_y = self.d[0, 1] + self.d[1, 1] * x + self.d[2, 1] * y
        r2 = np.empty(min(_CHUNK, x.size))
        tmp = np.empty_like(r2)
        for start in range(0, x.size, _CHUNK):  # chunks keep the temporaries in cache
            cx, cy = x[start : start + _CHUNK], y[start : start + _CHUNK]
            acc_x, acc_y = out_x[start : start + _CHUNK], out_y[start : start + _CHUNK]
            r2_, tmp_ = r2[: cx.size], tmp[: cx.size]
            for (px, py), (cx_j, cy_j) in zip(self.centres, self.c):
                np.subtract(cx, px, out=r2_)
                np.multiply(r2_, r2_, out=r2_)
                np.subtract(cy, py, out=tmp_)
                np.multiply(tmp_, tmp_, out=tmp_)
                np.add(r2_, tmp_, out=r2_)
                # phi = r^2 log r = 0.5 r2 log r2; the tiny offset makes phi(0) = 0.
                np.add(r2_, 1e-300, out=tmp_)
                np.log(tmp_, out=tmp_)
                np.multiply(tmp_, r2_, out=tmp_)
                acc_x += (0.5 * cx_j) * tmp_
                acc_y += (0.5 * cy_j) * tmp_
        return out_x.reshape(shape), out_y.reshape(shape)


_CHUNK = 1 << 16


def _kernel(r2: np.ndarray) -> np.ndarray:
    """phi(r) = r^2 log r, from r^2 (phi(0) = 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 0.5 * r2 * np.log(r2)
    return np.where(r2 > 0, out, 0.0)


Mapping = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

# Significance of the radial terms (F-test, 3 and 2 n - 11 degrees of
# freedom). Measured on simulated views at 0-60 degrees, 0.25 and 0.33
# pixels per cell: the X-corners' errors are not white (at 14 degrees they
# leave a homography residual ten times that at 0 or 45 degrees), so a lax
# choice (comparing GCV scores, about a 13 % test) keeps radial terms fitted
# to that error (0.05 px RMS in the noise region instead of 0.006-0.011 for
# two of twelve undistorted views); at 1 % only one of twelve took
# them, while all off-centre views with k1 = 0.1 and three of four with k1 =
# 0.05 did (0.03-0.04 px instead of 0.1-0.2 with the homography alone).
RADIAL_SIGNIFICANCE = 0.01


def _incomplete_beta(x: float, a: float, b: float) -> float:
    """The regularised incomplete beta function I_x(a, b) (Abramowitz & Stegun 26.5.8).

    Its continued fraction, evaluated by the modified Lentz method (Thompson & Barnett,
    J. Comput. Phys. 64, 1986), converges fast for x < (a + 1) / (a + b + 2); above,
    I_x(a, b) = 1 - I_{1-x}(b, a) (A&S 26.5.2).
    """
    if x <= 0.0:
        return 0.0
    if x >= 1.0:
        return 1.0
    if x > (a + 1.0) / (a + b + 2.0):
        return 1.0 - _incomplete_beta(1.0 - x, b, a)
    log_beta = math.lgamma(a) + math.lgamma(b) - math.lgamma(a + b)
    log_front = a * math.log(x) + b * math.log1p(-x) - math.log(a) - log_beta  # x^a (1-x)^b / (a B(a, b))
    tiny = 1e-300
    f, c, d = tiny, tiny, 0.0
    for i in range(400):  # 1 / (1 + d_1 / (1 + d_2 / (1 + ...)))
        m = i // 2
        if i == 0:
            term = 1.0
        elif i % 2:  # d_{2m+1}
            term = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))
        else:  # d_{2m}
            term = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m))
        d = 1.0 + term * d
        d = 1.0 / (d if abs(d) > tiny else tiny)
        c = 1.0 + term / c
        c = c if abs(c) > tiny else tiny
        f *= c * d
        if abs(c * d - 1.0) < 1e-16:
            break
    return math.exp(log_front) * f


@functools.lru_cache(maxsize=None)
def f_quantile(q: float, d1: int, d2: int) -> float:
    """The upper ``q`` quantile of Snedecor's F(d1, d2) distribution: P(F > f) = q.

    scipy.special.fdtri(d1, d2, 1 - q) to 1e-10 (tests/test_geometry.py), without scipy.special and
    scipy.stats: their imports cost 0.2-0.5 s of start-up for this one number. With x = d1 f / (d1 f + d2),
    P(F <= f) = I_x(d1 / 2, d2 / 2) and P(F > f) = I_{1-x}(d2 / 2, d1 / 2) (Abramowitz & Stegun 26.6.2,
    26.5.2): the smaller of x and 1 - x is found by bisection to its last bit, so that the other, and f,
    keep their precision in either tail.
    """
    if not 0.0 < q < 1.0:
        raise ValueError(f"the tail probability must be in (0, 1), got {q}")
    upper = q < 0.5  # f is large: 1 - x is small
    a, b, target = (d2 / 2.0, d1 / 2.0, q) if upper else (d1 / 2.0, d2 / 2.0, 1.0 - q)
    lo, hi = 0.0, 1.0
    for _ in range(2000):  # halves the bracket, down to the subnormals for a tiny root
        mid = 0.5 * (lo + hi)
        if mid in (lo, hi):
            break
        if _incomplete_beta(mid, a, b) < target:
            lo = mid
        else:
            hi = mid
    y = 0.5 * (lo + hi)
    return d2 * (1.0 - y) / (d1 * y) if upper else d2 * y / (d1 * (1.0 - y))


class RadialHomography:
    """Homography followed by radial lens distortion about an unknown centre.

    The pattern is flat, so perspective is a homography H; what the lens adds
    is radial distortion (Joshi, Szeliski, Kriegman, CVPR 2008, sec. 3, fit
    their target the same way; here in least squares on the 12 X-corners).
    Over the target a radial field k (q - c) |q - c|^2 about a centre c far
    from it is, in q relative to the target centre and with w = k (t - c),
    an affine part (taken up by H) plus

        delta(q) = 2 q (w . q) + w |q|^2 + k q |q|^2,

    exactly (the distortion is cubic in q), so three parameters (w, k) model
    it without knowing the optical centre.
    """

    def __init__(self, h: np.ndarray, centre: np.ndarray, params: np.ndarray) -> None:
        self.h = h  # pattern cells -> undistorted image pixels
        self.h_inv = np.linalg.inv(h)
        self.centre = centre  # target centre t in the image
        self.params = params  # (w_x, w_y, k)

    @classmethod
    def fit(cls, pattern: np.ndarray, corners: np.ndarray, radial: bool = True) -> "RadialHomography":
        """Least-squares fit on (n, 2) point pairs (Gauss-Newton from the DLT homography)."""
        h, _ = cv2.findHomography(pattern, corners, 0)
        centre = corners.mean(axis=0)
        params = np.zeros(3)
        if not radial:
            return cls(h, centre, params)
        for _ in range(5):  # the start is within the distortion of the optimum: a few steps converge
            model = cls(h, centre, params)
            predicted = model.image_points(pattern)
            columns = []
            for j in range(8):  # H[2, 2] stays fixed (scale)
                step = 1e-7 * max(1.0, abs(h.flat[j]))
                moved = h.copy()
                moved.flat[j] += step
                columns.append((cls(moved, centre, params).image_points(pattern) - predicted).ravel() / step)
            q = _project(h, pattern) - centre
            columns += [_radial(q, unit).ravel() for unit in np.eye(3)]  # delta is linear in (w, k)
            jac = np.column_stack(columns)
            norm = np.linalg.norm(jac, axis=0)  # columns differ by orders of magnitude
            update = np.linalg.lstsq(jac / norm, (corners - predicted).ravel(), rcond=None)[0] / norm
            h = h + np.append(update[:8], 0.0).reshape(3, 3)
            params = params + update[8:]
        return cls(h, centre, params)

    @classmethod
    def select(cls, pattern: np.ndarray, corners: np.ndarray,
               significance: float = RADIAL_SIGNIFICANCE) -> "RadialHomography":
        """The homography alone, or with the radial terms when an F-test finds them significant.

        Three more parameters always lower the residual; with 12 noisy
        corners they also copy the detection error into the interior, so they
        are kept only when they explain more than that error would.
        """
        plain, radial = cls.fit(pattern, corners, radial=False), cls.fit(pattern, corners)
        rss_plain, rss_radial = plain.residual(pattern, corners), radial.residual(pattern, corners)
        dof = 2 * len(pattern) - 11
        if rss_radial <= 0.0:
            return radial if rss_plain > 0.0 else plain
        f = (rss_plain - rss_radial) / 3 / (rss_radial / dof)
        return radial if f > f_quantile(significance, 3, dof) else plain

    def residual(self, pattern: np.ndarray, corners: np.ndarray) -> float:
        """Sum of squared distances between the mapped pattern points and the corners."""
        return float(np.sum((self.image_points(pattern) - corners) ** 2))

    def image_points(self, pattern: np.ndarray) -> np.ndarray:
        """Map (n, 2) pattern points to the image."""
        q = _project(self.h, pattern)
        return q + _radial(q - self.centre, self.params)

    def to_image(self, X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pattern cells -> image pixels, coordinate arrays of any (equal) shape."""
        x, y = _apply(self.h, X, Y)
        dx, dy = _radial_xy(x - self.centre[0], y - self.centre[1], self.params)
        return x + dx, y + dy

    def to_pattern(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Image pixels -> pattern cells: fixed point of u = x - delta(u), then H^-1."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        ux, uy = x, y
        if np.any(self.params):
            # A contraction: delta's gradient over the target is ~0.06 for
            # k1 = 0.1 far off-centre, so each step gains a digit; stop at
            # 1e-6 px, far below the corners' precision (5-6 steps there).
            for _ in range(30):
                dx, dy = _radial_xy(ux - self.centre[0], uy - self.centre[1], self.params)
                change = np.abs(x - dx - ux).max(initial=0.0)
                ux, uy = x - dx, y - dy
                if change < 1e-6:
                    break
        return _apply(self.h_inv, ux, uy)


def _radial_xy(qx: np.ndarray, qy: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """delta(q) = 2 q (w . q) + w |q|^2 + k q |q|^2 (see RadialHomography)."""
    wx, wy, k = params
    r2 = qx * qx + qy * qy
    a = 2 * (wx * qx + wy * qy) + k * r2
    return a * qx + wx * r2, a * qy + wy * r2


def _radial(q: np.ndarray, params: np.ndarray) -> np.ndarray:
    return np.column_stack(_radial_xy(q[:, 0], q[:, 1], params))


def _apply(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A homography on coordinate arrays of any (equal) shape."""
    x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w


def image_box(to_image: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]],
              extent: tuple[float, float, float, float], shape: tuple[int, int], margin: int,
              points: int) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1), end exclusive, of the pixels of a plane of ``shape`` that hold the image of the
    pattern rectangle ``extent`` (X0, Y0, X1, Y1) through ``to_image``, grown by ``margin``, inside the plane
    (empty when the image lies outside it).

    The rectangle's edge is traced with ``points`` points a side: a homography with radial distortion maps
    the rectangle's edge onto the edge of its image.
    """
    X0, Y0, X1, Y1 = extent
    along_x, along_y = np.linspace(X0, X1, points), np.linspace(Y0, Y1, points)
    X = np.concatenate([along_x, along_x, np.full_like(along_y, X0), np.full_like(along_y, X1)])
    Y = np.concatenate([np.full_like(along_x, Y0), np.full_like(along_x, Y1), along_y, along_y])
    x, y = to_image(X, Y)
    rows, cols = shape
    x0 = max(0, int(np.floor(np.min(x))) - margin)
    y0 = max(0, int(np.floor(np.min(y))) - margin)
    x1 = min(cols, int(np.ceil(np.max(x))) + margin + 1)
    y1 = min(rows, int(np.ceil(np.max(y))) + margin + 1)
    return x0, y0, x1, y1


def target_maps(
    detection: Detection, smoothing: float | str = "auto", projective: bool = True
) -> tuple[Mapping, Mapping]:
    """The two registration maps of a detected target.

    By default (``smoothing="auto"``) the maps are a homography, plus radial
    distortion when the 12 corners show it (`RadialHomography.select`). With
    a number ``smoothing`` = lambda (cells^2) each map is the least-squares
    homography plus a smoothing thin-plate spline of what it leaves; with
    ``projective=False`` as well, the spline alone, as in the thesis (App.
    A.2; lambda = SMOOTHING for ``"auto"``).

    Why not the spline by default: lambda = 10 cells^2 (the thesis's value,
    but its bending energy depends on the unit, so not necessarily its
    smoothing) copies the X-corners' noise (~0.05 px) into 0.1-0.2 px bulges
    inside the target; a fixed large lambda misses off-centre lens
    distortion (0.2-0.4 px for k1 = 0.1); lambda chosen per photograph by
    generalised cross-validation (Craven & Wahba 1979) on 12 corners was
    erratic (0.006-0.11 px). Over simulated views at 0-60 degrees, with tilt
    and k1 up to 0.1 off-centre, the chosen model left 0.004-0.05 px RMS
    (translation removed) in the noise region, lambda = 10 0.006-0.074. The thesis
    argues the distortion over a ~100 px target is almost affine, but a target
    seen at an angle is not: with the 12 corners all on the ring, a spline
    alone misses the interior of a perspective view by about 15 % of its
    non-affine part (0.28 px in the noise region for a 5 % scale change across
    the target), while the homography is exact for it and leaves the spline
    only the lens distortion, which it handles as in the thesis.

    Returns
    -------
    to_image : callable (X, Y) -> (x, y)
        Pattern cells -> image pixels.
    to_pattern : callable (x, y) -> (X, Y)
        Image pixels -> pattern cells.
    """
    pattern, corners = detection.pattern_points, detection.corners
    if isinstance(smoothing, str):
        if smoothing != "auto":
            raise ValueError(f"smoothing must be a number or 'auto', got {smoothing!r}")
        if projective:
            model = RadialHomography.select(pattern, corners)
            return model.to_image, model.to_pattern
        smoothing = SMOOTHING
    # The inverse spline's smoothing acts in image pixels: lambda scales with
    # the squared length unit (phi(a r) = a^2 phi(r) + a^2 r^2 log a, and the
    # second term is affine on the fitted coefficients), so rescale it by the
    # squared image scale for both directions to bend alike.
    inverse_smoothing = smoothing * detection.scale**2
    if not projective:
        forward = ThinPlateSpline.fit(pattern, corners, smoothing)
        backward = ThinPlateSpline.fit(corners, pattern, inverse_smoothing)
        return forward.map, backward.map
    h, _ = cv2.findHomography(pattern, corners, 0)
    h_inv = np.linalg.inv(h)
    forward = ThinPlateSpline.fit(pattern, corners - _project(h, pattern), smoothing)
    backward = ThinPlateSpline.fit(corners, pattern - _project(h_inv, corners), inverse_smoothing)

    def to_image(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _compose(h, forward, X, Y)

    def to_pattern(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return _compose(h_inv, backward, x, y)

    return to_image, to_pattern


def _project(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a homography to (n, 2) points."""
    p = np.column_stack([points, np.ones(len(points))]) @ h.T
    return p[:, :2] / p[:, 2:3]


def _compose(h: np.ndarray, residual: ThinPlateSpline, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Homography ``h`` plus the spline ``residual`` at coordinate arrays of any shape."""
    hx, hy = _apply(h, x, y)
    dx, dy = residual.map(x, y)
    return hx + dx, hy + dy
