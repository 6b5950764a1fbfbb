"""Band-limiting and interpolation shared by the estimators.

Both methods low-pass an image by truncating its DCT and then resample it with
Keys' bicubic kernel (a = -0.5) on the s-times grid.
Delbracio et al., IJCV 2012, sec. 4.2 and Delbracio PhD thesis 2013, App. A.1;
Delbracio, Almansa, Morel, Musé, SIAM J. Imaging Sci. 2012, sec. 4 (eq. (17)).
"""

from __future__ import annotations

import numpy as np
from scipy import fft, ndimage


def dct_lowpass(image: np.ndarray, keep: tuple[int, int]) -> np.ndarray:
    """Low-pass an image by zeroing its DCT-II coefficients from index ``keep`` on.

    The DCT avoids the ringing a periodic FFT filter would add at the image
    borders (Delbracio PhD thesis 2013, App. A.1: keep indices below
    (m s, n s) for an m x n observed window at factor s).

    Parameters
    ----------
    image : ndarray, 2-D
    keep : (int, int)
        Number of coefficients kept along rows (axis 0) and columns (axis 1).

    Returns
    -------
    ndarray of float64, same shape as ``image``.
    """
    rows, cols = image.shape
    keep_r, keep_c = min(int(keep[0]), rows), min(int(keep[1]), cols)
    if keep_r >= rows and keep_c >= cols:
        return np.asarray(image, dtype=np.float64).copy()
    coeffs = fft.dctn(np.asarray(image, dtype=np.float64), type=2, norm="ortho", workers=-1)
    coeffs[keep_r:, :] = 0.0
    coeffs[:, keep_c:] = 0.0
    return fft.idctn(coeffs, type=2, norm="ortho", workers=-1)


def keys_weights(t: np.ndarray, a: float = -0.5) -> np.ndarray:
    """Keys' cubic convolution weights for the four taps around fractional offset ``t``.

    Keys, IEEE Trans. ASSP 1981, eq. (15); a = -0.5 makes the interpolant
    third-order accurate (the value the reference code was corrected to).

    Parameters
    ----------
    t : ndarray
        Fractional offsets in [0, 1).
    a : float

    Returns
    -------
    ndarray with a trailing axis of 4: weights of taps at offsets -1, 0, 1, 2.
    """
    t = np.asarray(t)
    d = np.stack([1 + t, t, 1 - t, 2 - t], axis=-1)
    near = ((a + 2) * d - (a + 3)) * d * d + 1  # |d| <= 1
    far = ((a * d - 5 * a) * d + 8 * a) * d - 4 * a  # 1 < |d| < 2
    return np.where(d <= 1, near, far)


def keys_bicubic(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    a: float = -0.5,
    fill: float = np.nan,
) -> np.ndarray:
    """Sample ``image`` at real positions with Keys' bicubic interpolation.

    OpenCV's ``remap`` has a fixed a = -0.75, so the a = -0.5 kernel the
    papers specify is evaluated here directly.

    Parameters
    ----------
    image : ndarray, 2-D
    x, y : ndarray
        Column and row coordinates (pixel centres at integers), same shape.
    a : float
        Keys' parameter.
    fill : float
        Value where the 4 x 4 neighbourhood leaves the image.

    Returns
    -------
    ndarray of float64 with the shape of ``x``.
    """
    image = np.asarray(image, dtype=np.float64)
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    rows, cols = image.shape
    x0 = np.floor(x)
    y0 = np.floor(y)
    inside = (x0 >= 1) & (x0 <= cols - 3) & (y0 >= 1) & (y0 <= rows - 3)
    out = np.full(x.shape, fill, dtype=np.float64)
    if not inside.any():
        return out
    xi = x0[inside].astype(np.intp)
    yi = y0[inside].astype(np.intp)
    wx = keys_weights(x[inside] - xi, a)
    wy = keys_weights(y[inside] - yi, a)
    acc = np.zeros(xi.shape, dtype=np.float64)
    for j in range(4):
        line = np.zeros(xi.shape, dtype=np.float64)
        for i in range(4):
            line += wx[:, i] * image[yi + (j - 1), xi + (i - 1)]
        acc += wy[:, j] * line
    out[inside] = acc
    return out


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Erode a validity mask by a square of half-size ``radius`` pixels.

    The papers erode the observation mask by (k - 1) / (2 s) pixels so that
    every kept sample sees a full kernel footprint of valid data
    (Delbracio PhD thesis 2013, App. A.1).
    """
    mask = np.asarray(mask, dtype=bool)
    if radius <= 0:
        return mask.copy()
    structure = np.ones((2 * radius + 1, 2 * radius + 1), dtype=bool)
    return ndimage.binary_erosion(mask, structure=structure, border_value=0)
