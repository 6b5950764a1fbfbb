"""Noise amplification of a pattern view: gamma = sum of sigma_i^-2 of S_s U.

For the linear model v = S_s U h + n the least-squares kernel has
E||h_e - h||^2 = sigma_n^2 * sum_i sigma_i^-2, with sigma_i the singular values
of S_s U (Delbracio et al., IJCV 2012, sec. 2, "quality factor of a view").
gamma compares calibration patterns independently of the estimator: the
Bernoulli target is near the lower bound of Lemma 3, a step-edge target is
orders of magnitude above it (IJCV 2012, Table 2; Delbracio PhD thesis 2013,
Table 2.2).

A view is the band-limited pattern u~_D sampled on the s-times grid
(IJCV 2012, eq. (3)); here the pattern is seen frontally at t = s, i.e. one
pattern cell per s-grid sample, the scale the paper recommends (sec. 3.1).
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from psfd.estimator import resample, target

__all__ = [
    "band_limited_view", "bernoulli_formula", "bernoulli_view", "bound", "edge_view", "gamma", "pattern_gamma",
    "view_matrix", "window_view"
]

RASTER = 5  # raster pixels per s-grid sample; odd so that a sample centre is a raster pixel
# The thesis's Table 2.2 (s = 4, ~80 x 80 window): support -> gamma
THESIS_TABLE = {
    "supports": (9, 17, 25, 33),
    "edges": (99.44, 1133.05, 6445.87, 58419.08),
    "bernoulli": (0.19, 0.69, 1.54, 2.98),
    "bound": (0.10, 0.35, 0.70, 1.15),
}


def view_matrix(sharp: np.ndarray, s: int, support: int) -> np.ndarray:
    """The matrix S_s U of a view: one row per observed pixel, one column per kernel sample.

    Observed pixel (i, j) sees the s-grid samples centred on
    (s i + R, s j + R), R = (support - 1) / 2, through the convolution
    (u * h)(x) = sum_a u(x - a) h(a) (IJCV 2012, problem (P)).

    Parameters
    ----------
    sharp : ndarray, 2-D
        u~_D on the s-times grid; its shape is (s (rows - 1) + support, s (cols - 1) + support)
        for a window of rows x cols observed pixels (extra samples are ignored).
    s : int
    support : int
        Odd kernel side in s-grid samples.

    Returns
    -------
    ndarray (rows * cols, support ** 2), rows in raster order of the observed window.
    """
    patches = sliding_window_view(np.asarray(sharp, dtype=np.float64), (support, support))[::s, ::s]
    # flip: row entry a holds u(x - a) for the kernel sample a
    return patches[..., ::-1, ::-1].reshape(-1, support * support)


def gamma(matrix: np.ndarray) -> float:
    """sum_i sigma_i^-2 of a view matrix (inf when it is rank deficient).

    The SVD of the matrix itself, not the eigenvalues of its Gram matrix: an
    edge pattern's condition number is large enough that squaring it would
    lose the smallest singular values to round-off.
    """
    sv = np.linalg.svd(np.asarray(matrix, dtype=np.float64), compute_uv=False)
    if sv.size < matrix.shape[1] or sv[-1] <= sv[0] * 1e-15:
        return float("inf")
    return float(np.sum(sv**-2.0))


def bound(observations: int, unknowns: int, a: float = 0.0, b: float = 1.0) -> float:
    """Lower bound of gamma over all patterns with values in [a, b] (IJCV 2012, Lemma 3 / Prop. 1)."""
    return (1.0 / b**2 + 4.0 * (unknowns - 1) ** 2 / (b - a) ** 2) / (observations * unknowns)


def bernoulli_formula(observations: int, unknowns: int, a: float = 0.0, b: float = 1.0) -> float:
    """gamma of the expected Gram matrix of an i.i.d. Bernoulli(0.5) view (IJCV 2012, sec. 2).

    (4/M)[1/(N(a+b)^2 + (b-a)^2) + (N-1)/(b-a)^2]: the large-window limit.
    """
    m, n = observations, unknowns
    return 4.0 / m * (1.0 / (n * (a + b) ** 2 + (b - a) ** 2) + (n - 1) / (b - a) ** 2)


def band_limited_view(raster: np.ndarray, q: int = RASTER) -> np.ndarray:
    """u~ = S_s LPF_s u: a raster of q pixels per s-grid sample, low-passed to the s-grid Nyquist and sampled.

    The low-pass truncates the DCT, as the thesis's implementation does
    (Delbracio PhD thesis 2013, App. A.1), so the border does not ring.
    """
    rows, cols = raster.shape
    low = resample.dct_lowpass(raster, keep=(rows // q, cols // q))
    return low[q // 2 :: q, q // 2 :: q]


def window_view(view: np.ndarray, pixels: int, s: int, support: int) -> np.ndarray:
    """The samples a centred window of ``pixels`` x ``pixels`` observed pixels sees."""
    size = s * (pixels - 1) + support
    r0 = (view.shape[0] - size) // 2
    c0 = (view.shape[1] - size) // 2
    if r0 < 0 or c0 < 0:
        raise ValueError("window larger than the rendered view")
    return view[r0 : r0 + size, c0 : c0 + size]


def bernoulli_view(s: int = 4, noise: np.ndarray | None = None, margin: int = 24) -> np.ndarray:
    """The whole published target (target.cells) at t = s on white paper, as u~ on the s-grid.

    320 cells at one cell per s-grid sample image to 320 / s pixels: 80 x 80 at
    s = 4, the thesis's window (its Table 2.2 counts this window, flat border included).
    """
    cells = target.cells(noise, supersample=RASTER)
    pad = margin * RASTER
    raster = np.pad(cells, pad, constant_values=1.0)
    return band_limited_view(raster)


def edge_view(s: int = 4, pixels: int = 80, tiles: float = 1.0, angle: float = 10.0, margin: int = 24) -> np.ndarray:
    """The sharp-edge target (sharpedge.edge_pattern) framed so that ``tiles`` tiles span ``pixels`` pixels.

    The paper solved one PSF per 220-pixel window, the size of one tile of its
    target (Joshi et al., CVPR 2008, sec. 7), so the default frames one tile.
    The target is turned by ``angle`` degrees: a print is never aligned with
    the pixel grid to a fraction of a sample, and an aligned view would see
    every straight edge at the same sub-pixel phase, a degenerate case that
    makes gamma explode for reasons unrelated to the pattern.
    """
    from psfd.estimator import sharpedge  # here: sharpedge imports this module

    samples = s * pixels + 2 * margin  # s-grid samples rendered
    square = s * pixels / (tiles * sharpedge.TILE) * RASTER  # raster pixels per square
    c = (np.arange(samples * RASTER) + 0.5 - samples * RASTER / 2) / square
    x, y = c[None, :], c[:, None]
    a = np.deg2rad(angle)
    raster = sharpedge.edge_pattern(np.cos(a) * x - np.sin(a) * y, np.sin(a) * x + np.cos(a) * y)
    return band_limited_view(raster)


def pattern_gamma(kind: str, support: int, s: int = 4, pixels: int = 80, **view_args) -> float:
    """gamma of the Bernoulli target (``kind="bernoulli"``) or the edge target (``"edges"``) over a pixels^2 window."""
    if kind == "bernoulli":
        view = bernoulli_view(s, **view_args)
    elif kind == "edges":
        view = edge_view(s, pixels, **view_args)
    else:
        raise ValueError(f"unknown pattern {kind!r}")
    return gamma(view_matrix(window_view(view, pixels, s, support), s, support))
