"""Radiometric corrections: illumination (black and white fields) and camera response.

Delbracio et al., IJCV 2012, sec. 4.1 (non-uniform illumination and the
response curve g), Delbracio PhD thesis 2013, App. A.3-A.4.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import numpy as np

from psfd.errors import EstimationError
from psfd.estimator import fourier, quantiles, target

Field = Callable[[np.ndarray, np.ndarray], np.ndarray]

# The far tail of the PSF, beyond the estimated support. Diffraction by a
# circular pupil falls off as h(r) ~ (lambda N) / (pi^3 r^3) on average over its
# rings (the asymptote of [2 J1(v) / v]^2, Born & Wolf 8.5.2), so its
# edge-spread tail decays only as 1 / r: at f/22 on a 2 x 4.3 um plane (lambda N
# = 1.4 px) the centre of a flat square 6.4 px from its edges reads 0.029 of the
# black-to-white span above black (a black square) or 0.022 below white (a
# white one). Taking those centres as pure black and white shrinks W - B by 5 %,
# stretches the normalised noise and makes the kernel too sharp: +0.013 mean
# signed MTF error through the whole pipeline against -0.001 with the true light
# (tests/render.py, airy f/22, support 25, 0.40 px/cell). The tail is modelled
# as a r^-3 beyond the support, its light from the known layout (`_tail_raster`),
# and a is fitted with the fields from how the flat squares' values change with
# the distance to their edges. On that render the value predicted by the layout
# follows the measured flare with correlation 0.99-1.00 and the r^-3 slope that
# fits it is 0.94-1.02 times the diffraction asymptote's; a is fitted at 0.043
# (asymptote 0.045), the fields land within 0.1-0.3 % of the span of the true
# levels, and the whole pipeline's mean signed MTF error is -0.0015 to +0.0017 at
# f/11 and f/22, within 0.0015 of the true light's (bench/bench_accuracy.py).
# Rejected after measurement or by their structure:
# - extrapolating the estimated kernel's tail and re-estimating: the kernel ends
#   at the support (2-3 px) where its samples are noisiest, and the light that
#   matters comes from 3-16 px, which the flat squares sample directly;
# - a free offset in the solver with the kernel's sum fixed: a constant offset
#   is what the mass beyond the support already adds to the data (a uniform
#   pedestal, IJCV 2012 sec. 3.2), and the offset column correlates with the
#   kernel's summed columns at about 0.996 (the ~130 Bernoulli cells under a
#   17 x 17 support at 0.37 px/cell vary by 1/sqrt(130) of their mean), so the
#   two are told apart only through the noise;
# - nothing around the target (margin 0): the border squares then lack the
#   light of the paper beyond them and a comes out at 0.013 instead of 0.042
#   (f/22, 0.30 px/cell), +0.014 mean signed error; 24, 64 or 192 cells of
#   white paper agree within 0.002, 64 is kept;
# - without the light leaving beyond the radius (2 pi / radius per unit a) the
#   white field is 0.8 % low and the mean signed error +0.003 at f/22.
_TAIL_MARGIN = 64  # cells of white paper modelled around the target (the renders' board: 24, then grey)
_TAIL_RADIUS = 192  # cells: light from further away varies too slowly to tell from the quadratic fields
_TAIL_INNER = 2.0  # cells: the tail kernel starts here; every sample is further than this from another colour
# Samples keep this far (pixels) beyond the support's reach from the edge of their square: the PSF's core
# stays inside the support, and the X-corners place the edges to ~0.1 px ...
_EDGE_CLEARANCE = 0.5
# ... but no further than this (pixels): a 25-sample support at s = 4 reaches 3 px, and at 0.33 px/cell
# starting at 3.5 px leaves 1.8 px to the square's centre (350 pixels in all) and a to +-0.014 at the
# published photograph's noise (a defocus disc through f/5.6, a = 0.012; one seed in two fitted 0.042
# and widened the kernel by -0.017 mean signed MTF). From 2.5 px: +-0.005, and the anisotropic Gaussian
# (sigma 0.7 px) still shows no tail (a = 0.0001 +- 0.0012; 0.0011 from 2.0 px), f/22 the same a (0.043).
_SAMPLE_START = 2.5
_MAX_SAMPLES = 4000  # per square, taken evenly: the fit's 13 unknowns need far fewer
# The tail is fitted only where the flat squares show it, above this many standard errors. The squares'
# pixels measure a to 0.0017 at 0.33 px per cell and support 25 (760 pixels from 2.5 px; 0.005 at the
# published photograph's noise), where diffraction has 0.012 at f/5.6, 0.045 at f/22. Kept at any
# positive value, the noise of a tail-less PSF would leave a = 0.4 standard errors on average and widen
# the kernel (-0.0013 mean signed MTF on the anisotropic Gaussian when a was measured to 0.005); a
# negative a is no PSF.
_SIGNIFICANT = 2.0


class Light(NamedTuple):
    """The fitted light model: black and white fields, and the amplitude of the PSF's far tail.

    ``tail``: a in h(r) = a r^-3 (r in pixels) beyond the support; lambda N / pi^3 for diffraction.
    """

    black: Field
    white: Field
    tail: float


def illumination(image: np.ndarray, to_image: Callable, to_pattern: Callable, reach: float,
                 noise: np.ndarray | None = None) -> Light:
    """Black and white fields B(x, y), W(x, y) from the flat squares of the target.

    Each field is a quadratic surface a + b x + c y + d x^2 + e x y + f y^2
    (IJCV 2012, sec. 4.1: "a second order polynomial"; the six-term form with
    the cross term), with coordinates centred and scaled on the squares. A
    pixel of a flat square reads its level plus the light the PSF's far tail
    brings from the rest of the print (module notes above `_TAIL_MARGIN`)::

        v(x) = L(x) + (W(x) - B(x)) t F(x),

    L = B in the 12 black squares and W in the 12 white ones, F the layout's
    r^-3 response (`_tail_response`: positive in black squares, negative in
    white ones), t the tail amplitude. The two fields and t are fitted by least
    squares to every pixel of the flat squares further than ``reach`` + 0.5 px
    (at most 2.5 px) from their edges (outliers - dust, a hot pixel - removed
    per square), with W - B in the tail term from the previous pass (three
    passes). A t below two standard errors (`_SIGNIFICANT`) is not shown by
    the squares, and a negative one is no PSF: the fit is then repeated with t = 0.

    Parameters
    ----------
    image : ndarray, 2-D
        The photograph (one channel).
    to_image, to_pattern : callable (X, Y) -> (x, y)
        Pattern cells -> image pixels and back (geometry.target_maps).
    reach : float
        Half the PSF support in pixels ((k - 1) / (2 s)): within it the PSF is
        estimated, beyond it only its far tail is modelled.
    noise : ndarray (256, 256), optional
        The printed noise cells; the published pattern by default.

    Returns
    -------
    Light: (black, white) callables f(x, y) -> ndarray, image coordinates of any
    shape, and the tail amplitude.
    """
    image = np.asarray(image, dtype=np.float64)
    noise = target.default_noise() if noise is None else np.asarray(noise, dtype=np.float64)
    raster = _tail_raster(np.packbits(noise > 0.5).tobytes())
    blacks = _squares(image, to_image, to_pattern, target.BLACK_BLOCKS, reach, raster)
    whites = _squares(image, to_image, to_pattern, target.WHITE_BLOCKS, reach, raster)
    level = [float(quantiles.median([quantiles.median(sq.values) for sq in group])) for group in (blacks, whites)]
    span = level[1] - level[0]
    squares = [sq.without_outliers(span) for sq in blacks + whites]
    xy = np.array([sq.centre for sq in squares])
    centre, spread = xy.mean(axis=0), float(xy.std()) or 1.0
    x, y, values, response = (np.concatenate([getattr(sq, name) for sq in squares])
                              for name in ("x", "y", "values", "response"))
    white = np.repeat(np.arange(len(squares)) >= len(blacks), [sq.values.size for sq in squares])
    design = _design((x - centre[0]) / spread, (y - centre[1]) / spread)
    levels = np.concatenate([design * ~white[:, None], design * white[:, None]], axis=1)
    coef, *_ = np.linalg.lstsq(levels, values, rcond=None)  # no tail: the first W - B
    tail = 0.0
    for _ in range(3):  # W - B in the tail term from the previous pass: the fields move 2e-4, 1e-5, 1e-6 of it
        both = np.column_stack([levels, (design @ (coef[6:] - coef[:6])) * response])
        solution, *_ = np.linalg.lstsq(both, values, rcond=None)
        if solution[12] <= _SIGNIFICANT * _standard_error(both, values, solution):
            coef, *_ = np.linalg.lstsq(levels, values, rcond=None)
            tail = 0.0
            break
        coef, tail = solution[:12], float(solution[12])
    return Light(_field(coef[:6], centre, spread), _field(coef[6:], centre, spread), tail)


def _standard_error(design: np.ndarray, values: np.ndarray, solution: np.ndarray) -> float:
    """Standard error of the last unknown of a least-squares fit, from its residual."""
    residual = values - design @ solution
    variance = float(residual @ residual) / max(1, values.size - design.shape[1])
    return float(np.sqrt(variance * np.linalg.inv(design.T @ design)[-1, -1]))


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


class _Square(NamedTuple):
    """The pixels of a flat square read by the light model, and the layout's tail response F there."""

    centre: tuple[float, float]
    x: np.ndarray
    y: np.ndarray
    values: np.ndarray
    response: np.ndarray

    def without_outliers(self, span: float) -> "_Square":
        """Without values further than max(6 MADs, 10 % of the black-to-white ``span``) from the median.

        Dust and hot pixels are further; the span term keeps a noise-free
        square's own tail gradient (up to 5 % of the span at f/22) in.
        """
        median = quantiles.median(self.values)
        mad = quantiles.median(np.abs(self.values - median))
        keep = np.abs(self.values - median) <= max(6 * 1.4826 * mad, 0.1 * span)
        return _Square(self.centre, *(a[keep] for a in (self.x, self.y, self.values, self.response)))


def _squares(image: np.ndarray, to_image: Callable, to_pattern: Callable, blocks, reach: float,
             raster: np.ndarray) -> list[_Square]:
    """The pixels of each flat square further than ``reach`` + `_EDGE_CLEARANCE` pixels from its edges
    (at most `_SAMPLE_START`).

    On a target too small for that, the inner third of the square. At most
    `_MAX_SAMPLES` per square, taken evenly. All squares go through the maps at once.
    """
    centres = np.array([target.block_centre(b) for b in blocks])
    half = target.BLOCK / 2
    # each square's centre, one cell to its right (the local scale) and its four corners
    offsets = np.array([[0.0, 0.0], [1.0, 0.0], [-half, -half], [half, -half], [half, half], [-half, half]])
    points = centres[:, None, :] + offsets[None, :, :]
    px, py = (np.reshape(c, points.shape[:2]) for c in to_image(points[..., 0].ravel(), points[..., 1].ravel()))
    scale = np.hypot(px[:, 1] - px[:, 0], py[:, 1] - py[:, 0])  # pixels per cell
    x0, x1 = np.floor(px[:, 2:].min(axis=1)).astype(int), np.ceil(px[:, 2:].max(axis=1)).astype(int)
    y0, y1 = np.floor(py[:, 2:].min(axis=1)).astype(int), np.ceil(py[:, 2:].max(axis=1)).astype(int)
    rows, cols = image.shape
    if (x0 < 0).any() or (y0 < 0).any() or (x1 >= cols).any() or (y1 >= rows).any():
        raise EstimationError("a flat square of the target falls outside the image")
    grids = [np.mgrid[y0[k] : y1[k] + 1, x0[k] : x1[k] + 1].reshape(2, -1) for k in range(len(blocks))]
    owner = np.repeat(np.arange(len(blocks)), [g.shape[1] for g in grids])
    y, x = np.concatenate(grids, axis=1)
    X, Y = to_pattern(x.astype(np.float64), y.astype(np.float64))
    depth = half - np.maximum(np.abs(X - centres[owner, 0]), np.abs(Y - centres[owner, 1]))  # cells to an edge
    start = min(reach + _EDGE_CLEARANCE, _SAMPLE_START)
    keep = depth >= np.minimum(start / scale, half * 2 / 3)[owner]
    x, y, X, Y, owner = x[keep], y[keep], X[keep], Y[keep], owner[keep]
    response = _tail_response(raster, X, Y) / scale[owner]
    values = image[y, x]
    squares = []
    for k in range(len(blocks)):
        mine = np.flatnonzero(owner == k)
        if mine.size == 0:
            raise EstimationError("a flat square of the target is too small in the image to read its level")
        mine = mine[:: max(1, mine.size // _MAX_SAMPLES)]
        squares.append(_Square((float(px[k, 0]), float(py[k, 0])), x[mine].astype(np.float64),
                               y[mine].astype(np.float64), values[mine], response[mine]))
    return squares


@functools.lru_cache(maxsize=4)
def _tail_raster(packed_noise: bytes) -> np.ndarray:
    """G(X) = sum over cells Y of (T(Y) - T(X)) |X - Y|^-3, on the cells of the print (target and margin).

    T is the printed reflectance (0 black, 1 white; `target.cells`) with
    `_TAIL_MARGIN` cells of white paper around it; the sum runs over
    `_TAIL_INNER` <= |X - Y| <= `_TAIL_RADIUS` cells, and the light the tail
    takes beyond that radius (2 pi / radius) leaves every cell too: what comes
    back from that far is a level common to black and white, varying too
    slowly over the target to tell from the fields. At a point further than
    `_TAIL_INNER` from any other colour the light of a tail h(r) = a r^-3
    (pixels) is (a / p) G, p the pixels per cell: the kernel's lengths are p
    pixels per cell and its area element p^2. Cells are a fine enough raster:
    each is one colour (up to the X-corners' diagonals), and r^-3 changes by
    under 2 % across a cell 5 or more cells away. Single precision (G to 1e-6
    of its range) halves the 0.1 s of the transforms; computed once per noise pattern.
    """
    noise = np.unpackbits(np.frombuffer(packed_noise, dtype=np.uint8))[: target.NOISE**2]
    layout = np.pad(target.cells(noise.reshape(target.NOISE, target.NOISE).astype(np.float64), 1), _TAIL_MARGIN,
                    constant_values=1.0).astype(np.float32)
    r = np.arange(-_TAIL_RADIUS, _TAIL_RADIUS + 1, dtype=np.float64)
    distance = np.hypot(r[None, :], r[:, None])
    kernel = np.zeros_like(distance)
    ring = (distance >= _TAIL_INNER) & (distance <= _TAIL_RADIUS)
    kernel[ring] = distance[ring] ** -3.0
    around = fourier.convolve_same(layout, kernel.astype(np.float32))  # the kernel's centre on each cell
    lost = kernel.sum() + 2 * np.pi / _TAIL_RADIUS  # beyond the radius: int r^-3 2 pi r dr
    return around.astype(np.float64) - layout * lost


def _tail_response(raster: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """`_tail_raster` at pattern points (X, Y), bilinear between cell centres."""
    rows = np.clip(np.asarray(Y, dtype=np.float64) + _TAIL_MARGIN - 0.5, 0, raster.shape[0] - 1.001)
    cols = np.clip(np.asarray(X, dtype=np.float64) + _TAIL_MARGIN - 0.5, 0, raster.shape[1] - 1.001)
    r0, c0 = rows.astype(int), cols.astype(int)
    fr, fc = rows - r0, cols - c0
    top = raster[r0, c0] * (1 - fc) + raster[r0, c0 + 1] * fc
    bottom = raster[r0 + 1, c0] * (1 - fc) + raster[r0 + 1, c0 + 1] * fc
    return top * (1 - fr) + bottom * fr


def _field(coef: np.ndarray, centre: np.ndarray, spread: float) -> Field:
    """The surface a + b x + c y + d x^2 + e x y + f y^2 in centred, scaled coordinates."""

    def field(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        x, y = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        u, v = (x - centre[0]) / spread, (y - centre[1]) / spread
        return coef[0] + coef[1] * u + coef[2] * v + coef[3] * u * u + coef[4] * u * v + coef[5] * v * v

    return field


def _design(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.column_stack([np.ones_like(u), u, v, u * u, u * v, v * v])
