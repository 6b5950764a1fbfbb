"""Band-limiting and interpolation shared by the estimators.

Both methods low-pass an image by truncating its DCT and then resample it with
Keys' bicubic kernel (a = -0.5) on the s-times grid.
Delbracio et al., IJCV 2012, sec. 4.2 and Delbracio PhD thesis 2013, App. A.1;
Delbracio, Almansa, Morel, Musé, SIAM J. Imaging Sci. 2012, sec. 4 (eq. (17)).
"""

from __future__ import annotations

import cv2
import numpy as np


class _LazySciPyFFT:
    """scipy.fft, imported on first use: 0.2-0.3 s of a process's start-up (it loads scipy.special and
    scipy's array-API layer), which a caller of the Keys interpolation alone (the two-photo method) never needs."""

    def __getattr__(self, name: str):
        from scipy import fft as module

        return getattr(module, name)


fft = _LazySciPyFFT()

__all__ = [
    "band_part_cost", "dct_bases", "dct_coefficients", "dct_lowpass", "dct_sparse_part",
    "dct_synthesise", "erode", "keys_bicubic", "keys_grid", "keys_upsample", "keys_weights",
]


def dct_lowpass(
    image: np.ndarray,
    keep: tuple[int, int],
    size: tuple[int, int] | None = None,
    mask: np.ndarray | None = None,
    cross_mask: np.ndarray | None = None,
) -> np.ndarray:
    """Low-pass an image by zeroing its DCT-II coefficients from index ``keep`` on.

    The DCT avoids the ringing a periodic FFT filter would add at the image
    borders (Delbracio PhD thesis 2013, App. A.1: keep indices below
    (m s, n s) for an m x n observed window at factor s).

    Parameters
    ----------
    image : ndarray, 2-D
        float32 input is filtered in float32 (half the work; the filter's
        rounding stays far below sensor noise), anything else in float64.
    keep : (int, int)
        Number of coefficients kept along rows (axis 0) and columns (axis 1).
    size : (int, int), optional
        Resynthesise the kept band on a grid of this shape instead of the
        image's own (a band-limited zoom: sample (i + 0.5) rows / size[0] - 0.5
        of the original grid), with the amplitude preserved.
    mask : ndarray (>= keep[0], >= keep[1]), optional
        Weights (bool or float) of the kept coefficients: a band that is not
        a rectangle. Coefficient (i, j) holds the frequencies (+-i, +-j) of
        the image's half-sample-symmetric extension (the DCT-II's implicit
        periodisation, 2 rows x 2 cols); ``mask`` weighs the pair (i, j),
        (-i, -j).
    cross_mask : ndarray like ``mask``, optional
        Weights of the other pair (i, -j), (-i, j); ``mask`` by default, which
        is a plain weighting of the DCT coefficients. A different cross mask
        filters the symmetric extension with a band that is not symmetric
        under x -> -x (e.g. a rotated square), still without border ringing.

    Returns
    -------
    ndarray of shape ``size`` (default: the shape of ``image``).
    """
    image = np.asarray(image)
    if image.dtype != np.float32:
        image = image.astype(np.float64)
    rows, cols = image.shape
    out_r, out_c = (rows, cols) if size is None else (int(size[0]), int(size[1]))
    keep_r, keep_c = min(int(keep[0]), rows, out_r), min(int(keep[1]), cols, out_c)
    if mask is None and keep_r >= rows and keep_c >= cols and (out_r, out_c) == (rows, cols):
        return image.copy()
    coeffs = dct_coefficients(image, (keep_r, keep_c))
    if mask is not None:
        mask = np.asarray(mask)[:keep_r, :keep_c]
        cross_mask = None if cross_mask is None else np.asarray(cross_mask)[:keep_r, :keep_c]
    lowpassed = dct_synthesise(coeffs, (out_r, out_c), mask, cross_mask)
    if (out_r, out_c) != (rows, cols):
        # orthonormal DCTs of different lengths: sqrt(new / old) keeps the amplitude
        lowpassed *= np.sqrt(out_r * out_c / (rows * cols)).astype(lowpassed.dtype)
    return lowpassed


def dct_coefficients(image: np.ndarray, keep: tuple[int, int]) -> np.ndarray:
    """The orthonormal DCT-II coefficients of ``image`` below index ``keep`` (rows, cols).

    Axis by axis, dropping the unwanted coefficients at once, so the second
    pass works on fewer lines. float32 input stays float32.
    """
    coeffs = fft.dct(image, type=2, norm="ortho", axis=1, workers=-1)[:, : int(keep[1])]
    return fft.dct(coeffs, type=2, norm="ortho", axis=0, workers=-1)[: int(keep[0])]


def dct_synthesise(
    coeffs: np.ndarray, size: tuple[int, int], mask: np.ndarray | None = None, cross_mask: np.ndarray | None = None
) -> np.ndarray:
    """The image of `dct_coefficients` ``coeffs`` weighted by the band ``mask`` / ``cross_mask`` (see `dct_lowpass`).

    The coefficients the array does not hold are zero; ``size`` is the
    (rows, cols) of the grid to synthesise on (the transform's length).
    """
    out_r, out_c = int(size[0]), int(size[1])
    anti = None
    if mask is not None:
        same = np.asarray(mask, dtype=coeffs.dtype)
        cross = same if cross_mask is None else np.asarray(cross_mask, dtype=coeffs.dtype)
        if same.shape != coeffs.shape or cross.shape != coeffs.shape:
            raise ValueError(f"mask and cross_mask need at least {coeffs.shape} coefficients")
        # With theta = pi i (row + 1/2) / rows, phi = pi j (col + 1/2) / cols,
        # a = mask and b = cross_mask, the pairs of coefficient (i, j) resynthesise
        # (a cos(theta + phi) + b cos(theta - phi)) / 2
        #     = (a + b) / 2 cos(theta) cos(phi) + (b - a) / 2 sin(theta) sin(phi):
        # the cosine part is an inverse DCT-II, the sine part an inverse DST-II
        # (whose index k is frequency k + 1, with the same orthonormal factor).
        if cross is not same and np.any(cross != same):
            anti = (coeffs * (cross - same) / 2)[1:, 1:]
        coeffs = coeffs * (same + cross) / 2
    lowpassed = fft.idct(coeffs, type=2, norm="ortho", axis=0, n=out_r, workers=-1)
    lowpassed = fft.idct(lowpassed, type=2, norm="ortho", axis=1, n=out_c, workers=-1)
    if anti is not None and anti.size:
        sine = fft.idst(anti, type=2, norm="ortho", axis=0, n=out_r, workers=-1)
        lowpassed += fft.idst(sine, type=2, norm="ortho", axis=1, n=out_c, workers=-1)
    return lowpassed


def dct_sparse_part(
    coeffs: np.ndarray, i: np.ndarray, j: np.ndarray, cos_w: np.ndarray, sin_w: np.ndarray,
    size: tuple[int, int], rows: slice, cols: slice, bases: dict | None = None,
) -> np.ndarray:
    """The image of a few DCT coefficients on ``rows`` x ``cols`` of the grid: `dct_synthesise` of a sparse band.

    Coefficient (``i[n]``, ``j[n]``) of ``coeffs`` enters with weight ``cos_w[n]``
    on its cosine part and ``sin_w[n]`` on its sine part (a band (a, b) of
    `dct_synthesise` has cos_w = (a + b) / 2, sin_w = (b - a) / 2); repeated
    coordinates add up. It is synthesised from the orthonormal DCT-III and
    DST-III basis functions (sqrt(2 / N) cos(pi k (n + 1/2) / N), sqrt(1 / N)
    for k = 0; sqrt(2 / N) sin(pi k (n + 1/2) / N)) tabulated on the rows and
    columns asked for, at the frequencies present only: B_rows D B_cols^T
    with D sparse, multiplied in the cheaper order (`band_part_cost`). float64.
    ``bases`` (`dct_bases` of the grid) saves tabulating them on every call.
    """
    from scipy import sparse  # already loaded with scipy.linalg

    out_r, out_c = int(size[0]), int(size[1])
    n_r = np.arange(out_r)[rows] + 0.5
    n_c = np.arange(out_c)[cols] + 0.5
    out = np.zeros((n_r.size, n_c.size))
    if i.size == 0:
        return out
    value = coeffs[i, j].astype(np.float64)
    used_r, at_r = _used(i, coeffs.shape[0])
    used_c, at_c = _used(j, coeffs.shape[1])
    by_rows = _part_costs(i.size, used_r.size, used_c.size, n_r.size, n_c.size)
    by_rows = by_rows[0] <= by_rows[1]
    # sin(0) = 0 on the first row and column
    for weights, wave in ((value * cos_w, np.cos), (np.where((i == 0) | (j == 0), 0.0, value * sin_w), np.sin)):
        if not np.any(weights):
            continue
        if bases is None:
            table_r = _basis(wave, out_r, n_r, used_r)
            table_c = _basis(wave, out_c, n_c, used_c)
        else:
            table_r = bases[wave.__name__, 0][rows][:, used_r]
            table_c = bases[wave.__name__, 1][cols][:, used_c]
        d = sparse.csr_matrix((weights, (at_r, at_c)), shape=(used_r.size, used_c.size))
        if by_rows:
            out += table_r @ (d @ table_c.T)
        else:
            out += (d.T @ table_r.T).T @ table_c.T
    return out


def dct_bases(size: tuple[int, int], keep: tuple[int, int]) -> dict:
    """The basis functions `dct_sparse_part` reads, on every row and column of a ``size`` grid, for the
    frequencies below ``keep``: {("cos" or "sin", axis): ndarray (size[axis], keep[axis])}."""
    out = {}
    for wave in (np.cos, np.sin):
        for axis in (0, 1):
            n, k = int(size[axis]), int(keep[axis])
            if axis == 1 and (n, k) == (int(size[0]), int(keep[0])):  # a square grid: one table for both
                out[wave.__name__, 1] = out[wave.__name__, 0]
            else:
                out[wave.__name__, axis] = _basis(wave, n, np.arange(n) + 0.5, np.arange(k))
    return out


def _basis(wave, length: int, at: np.ndarray, frequencies: np.ndarray) -> np.ndarray:
    """Orthonormal DCT-III (``np.cos``) or DST-III (``np.sin``) basis functions ``frequencies`` at points ``at``."""
    table = wave(np.pi / length * np.outer(at, frequencies)) * np.sqrt(2.0 / length)
    if wave is np.cos:
        table[:, frequencies == 0] *= np.sqrt(0.5)
    return table


def band_part_cost(i: np.ndarray, j: np.ndarray, rows: int, cols: int) -> float:
    """Multiply-adds of `dct_sparse_part` of coefficients (``i``, ``j``) on ``rows`` x ``cols`` (both parts)."""
    if i.size == 0:
        return 0.0
    used_r = int(np.count_nonzero(np.bincount(i)))
    used_c = int(np.count_nonzero(np.bincount(j)))
    return 2.0 * min(_part_costs(i.size, used_r, used_c, rows, cols))


def _used(index: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
    """The distinct values of ``index`` (sorted) and the position of each entry among them."""
    present = np.bincount(index, minlength=length) > 0
    position = np.cumsum(present) - 1
    return np.flatnonzero(present), position[index]


def _part_costs(nonzero: int, used_r: int, used_c: int, rows: int, cols: int) -> tuple[float, float]:
    # B_r (D B_c^T): D B_c^T then a dense product; (B_r D) B_c^T: the same the other way round
    return (float(nonzero) * cols + float(rows) * used_r * cols, float(nonzero) * rows + float(rows) * used_c * cols)


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
    u = 1 - t
    # eq. (15) at the distances 1 + t and 2 - t (outer taps) and t, 1 - t (inner), expanded
    out = np.empty(t.shape + (4,), dtype=t.dtype if t.dtype.kind == "f" else np.float64)
    out[..., 0] = a * t * u * u
    out[..., 1] = ((a + 2) * t - (a + 3)) * t * t + 1
    out[..., 2] = ((a + 2) * u - (a + 3)) * u * u + 1
    out[..., 3] = a * u * t * t
    return out


def keys_upsample(values: np.ndarray, s: int, start: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """A smooth function sampled on integers, interpolated (Keys, a = -0.5) on the grid of step 1 / s.

    ``values[r, c]`` is the function at (r - 1 + start[0] // s, c - 1 + start[1] // s);
    the result holds it at (i / s, j / s) for i from ``start[0]``, j from
    ``start[1]``, over ``shape``. ``values`` needs (shape + start % s) / s + 3
    samples along each axis (`keys_grid` gives the integer range). Keys' a = -0.5 kernel
    reproduces quadratics exactly (Keys, IEEE Trans. ASSP 1981, sec. III), so
    a map whose third derivatives are small over one sample (a homography,
    lens distortion) is reproduced to far below its own precision.
    """
    out = np.asarray(values, dtype=np.float64)
    for axis in (0, 1):
        n = out.shape[axis] - 3
        w = keys_weights(np.arange(s) / s)  # (phase, tap)
        taps = [np.take(out, np.arange(k, k + n), axis=axis) for k in range(4)]
        if axis == 0:
            up = sum(taps[k][:, None, :] * w[None, :, k, None] for k in range(4)).reshape(n * s, -1)
            first = start[0] % s
            out = up[first : first + shape[0]]
        else:
            up = sum(taps[k][:, :, None] * w[None, None, :, k] for k in range(4)).reshape(-1, n * s)
            first = start[1] % s
            out = up[:, first : first + shape[1]]
    return out


def keys_grid(start: int, count: int, s: int) -> np.ndarray:
    """The integers `keys_upsample` needs to cover samples ``start / s`` .. ``(start + count - 1) / s``."""
    return np.arange(start // s - 1, (start + count - 1) // s + 3)


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
        float32 input is interpolated in float32, anything else in float64.
    x, y : ndarray
        Column and row coordinates (pixel centres at integers), same shape.
    a : float
        Keys' parameter.
    fill : float
        Value where the 4 x 4 neighbourhood leaves the image.

    Returns
    -------
    ndarray with the shape of ``x`` and the working precision of ``image``.
    """
    image = np.asarray(image)
    dtype = np.float32 if image.dtype == np.float32 else np.float64
    flat = np.ascontiguousarray(image, dtype=dtype).ravel()
    x = np.asarray(x)
    y = np.asarray(y)
    rows, cols = image.shape
    x0 = np.floor(x)
    y0 = np.floor(y)
    inside = (x0 >= 1) & (x0 <= cols - 3) & (y0 >= 1) & (y0 <= rows - 3)
    out = np.full(x.shape, fill, dtype=dtype)
    if not inside.any():
        return out
    xi = x0[inside].astype(np.intp)
    yi = y0[inside].astype(np.intp)
    wx = keys_weights((x[inside] - xi).astype(dtype), a)
    wy = keys_weights((y[inside] - yi).astype(dtype), a)
    # Flat indices into the raveled image: np.take on 1-D is much faster than 2-D fancy indexing.
    base = yi * cols + xi
    acc = np.zeros(xi.shape, dtype=dtype)
    for j in range(4):
        row = base + (j - 1) * cols
        line = wx[:, 0] * np.take(flat, row - 1)
        for i in range(1, 4):
            line += wx[:, i] * np.take(flat, row + (i - 1))
        acc += wy[:, j] * line
    out[inside] = acc
    return out


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Erode a validity mask by a square of half-size ``radius`` pixels.

    The papers erode the observation mask by (k - 1) / (2 s) pixels so that
    every kept sample sees a full kernel footprint of valid data
    (Delbracio PhD thesis 2013, App. A.1).
    """
    mask = np.ascontiguousarray(mask, dtype=bool)
    if radius <= 0:
        return mask.copy()
    # OpenCV's erosion (outside the image counts as invalid): scipy.ndimage would add 0.1 s of imports
    structure = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
    eroded = cv2.erode(mask.view(np.uint8), structure, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return eroded.view(bool)
