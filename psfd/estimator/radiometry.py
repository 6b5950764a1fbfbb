"""Radiometric corrections: illumination (black and white fields) and camera response.

Delbracio et al., IJCV 2012, sec. 4.1 (non-uniform illumination and the
response curve g), Delbracio PhD thesis 2013, App. A.3-A.4.
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from psfd.errors import EstimationError
from psfd.estimator import target

Field = Callable[[np.ndarray, np.ndarray], np.ndarray]

# Half-size of the averaging window of a flat square, in cells: 5 x 5 pixels at
# the published example's 0.37 px/cell (thesis App. A.3) is +-2 px = +-5.4 cells.
_WINDOW_CELLS = 5.4
# Keep the window this many cells inside its 32-cell square, clear of the blur
# of the square's edges.
_MARGIN_CELLS = 6.0


def illumination(image: np.ndarray, to_image: Callable) -> tuple[Field, Field]:
    """Black and white fields B(x, y), W(x, y) from the flat squares of the target.

    Each field is a quadratic surface a + b x + c y + d x^2 + e x y + f y^2
    (IJCV 2012, sec. 4.1: "a second order polynomial"; the six-term form with
    the cross term) fitted by least squares to robust means of the 12 black
    (resp. white) squares, with coordinates centred and scaled on the squares.

    Parameters
    ----------
    image : ndarray, 2-D
        The photograph (one channel).
    to_image : callable (X, Y) -> (x, y)
        Pattern cells -> image pixels (geometry.target_maps).

    Returns
    -------
    (black, white) : callables f(x, y) -> ndarray, image coordinates of any shape.
    """
    image = np.asarray(image, dtype=np.float64)
    black_xy, black_v = _flat_samples(image, to_image, target.BLACK_BLOCKS)
    white_xy, white_v = _flat_samples(image, to_image, target.WHITE_BLOCKS)
    centre = np.concatenate([black_xy, white_xy]).mean(axis=0)
    spread = float(np.concatenate([black_xy, white_xy]).std()) or 1.0
    black = _quadratic(black_xy, black_v, centre, spread)
    white = _quadratic(white_xy, white_v, centre, spread)
    return black, white


def normalise(image: np.ndarray, black: Field, white: Field, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(v - B) / (W - B) at image coordinates (x, y) of the values ``image`` (IJCV 2012, sec. 4.1).

    NaN where the fitted white field does not exceed the black one: far from
    the target the two extrapolated quadratics may cross, and those pixels
    carry no usable value.
    """
    b = black(x, y)
    span = white(x, y) - b
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(span > 0, (np.asarray(image, dtype=np.float64) - b) / span, np.nan)


def crf_alpha(values: np.ndarray, mean: float = 0.5) -> float:
    """Parameter of the response parabola g(u) = alpha u^2 + (1 - alpha) u.

    The PSF has unit mass, so the corrected noise region must average what the
    printed noise averages under it: 1/2 for an ideal Bernoulli(0.5) pattern
    (IJCV 2012, sec. 4.1; thesis App. A.4), 0.502 for the published one (pass
    the pattern's own mean, ``mean``):
    alpha = (mean - mean(u)) / (mean(u^2) - mean(u)).

    g is monotone on [0, 1] only for |alpha| <= 1 (g'(0) = 1 - alpha,
    g'(1) = 1 + alpha). A larger alpha means the normalised noise is far from
    averaging ``mean`` - saturation, a wrong illumination fit or not the
    published noise - and correcting it would fold the data over, so it is an
    EstimationError rather than a warning: no PSF estimate would be meaningful.

    Parameters
    ----------
    values : ndarray
        Illumination-normalised values of the noise region (``normalise``).
    mean : float
        Mean of the printed noise cells (0 black, 1 white) under those values.
    """
    u = np.asarray(values, dtype=np.float64).ravel()
    u = u[np.isfinite(u)]
    if u.size == 0:
        raise EstimationError("no noise-region values to estimate the camera response from")
    observed, observed_sq = u.mean(), np.mean(u * u)
    denominator = observed_sq - observed
    if abs(denominator) < 1e-9:  # binary data: any alpha fits; take the identity
        if abs(mean - observed) > 1e-6:
            raise EstimationError(
                f"noise region is binary with mean {observed:.3f}, not {mean:.3f}: camera response undefined"
            )
        return 0.0
    alpha = float((mean - observed) / denominator)
    if abs(alpha) > 1.0:
        raise EstimationError(
            f"camera response correction alpha = {alpha:.2f} is not monotone (|alpha| > 1): "
            f"the noise region averages {observed:.3f} instead of {mean:.3f} (saturated or badly lit target?)"
        )
    return alpha


def apply_crf(values: np.ndarray, alpha: float) -> np.ndarray:
    """g(u) = alpha u^2 + (1 - alpha) u (IJCV 2012, sec. 4.1); fixes 0 and 1."""
    u = np.asarray(values, dtype=np.float64)
    return alpha * u * u + (1.0 - alpha) * u


def _flat_samples(image: np.ndarray, to_image: Callable, blocks) -> tuple[np.ndarray, np.ndarray]:
    """Image position and robust mean value of each flat square.

    The window is the thesis's 5 x 5 pixels scaled with the target, shrunk to
    stay inside the square; the mean is the interquartile mean, robust to a
    speck of dust or a hot pixel.
    """
    centres = np.array([target.block_centre(b) for b in blocks])
    cx, cy = to_image(centres[:, 0], centres[:, 1])
    # Local scale (px per cell) of each square from the map itself.
    ex, ey = to_image(centres[:, 0] + 1.0, centres[:, 1])
    scale = np.hypot(ex - cx, ey - cy)
    rows, cols = image.shape
    values = np.empty(len(centres))
    for k in range(len(centres)):
        inside = (target.BLOCK / 2 - _MARGIN_CELLS) * scale[k] / np.sqrt(2)  # the window's corner stays inside
        half = int(max(0, min(round(_WINDOW_CELLS * scale[k]), np.floor(inside))))
        x, y = int(round(cx[k])), int(round(cy[k]))
        if not (half <= x < cols - half and half <= y < rows - half):
            raise EstimationError("a flat square of the target falls outside the image")
        window = np.sort(image[y - half : y + half + 1, x - half : x + half + 1].ravel())
        n = window.size
        values[k] = window[n // 4 : n - n // 4].mean() if n >= 4 else window.mean()
    return np.column_stack([cx, cy]), values


def _quadratic(xy: np.ndarray, values: np.ndarray, centre: np.ndarray, spread: float) -> Field:
    """Least-squares surface a + b x + c y + d x^2 + e x y + f y^2 in centred, scaled coordinates."""
    u, v = (xy[:, 0] - centre[0]) / spread, (xy[:, 1] - centre[1]) / spread
    coef, *_ = np.linalg.lstsq(_design(u, v), values, rcond=None)

    def field(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        u, v = (x - centre[0]) / spread, (y - centre[1]) / spread
        return coef[0] + coef[1] * u + coef[2] * v + coef[3] * u * u + coef[4] * u * v + coef[5] * v * v

    return field


def _design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
