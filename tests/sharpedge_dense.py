"""The sharp-edge estimator's dense path, as psfd 0.1 computed it: the reference of the tiled one.

`psfd.estimator.sharpedge` evaluates the predicted sharp image only on the
footprints of pixels that may qualify, tile by tile. This module keeps the
straightforward form it replaced, which builds the whole s-times grid of a
window's crop (the coverage, the prediction, the mask), so that a test can show
the two give the same normal equations (Joshi et al., CVPR 2008, eq. (5)).
Only what the tiling changed is here; the rest is the package's own.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from psfd.estimator.sharpedge import (
    ANTI_ALIAS, DOG_RATIO, LATERAL, Edgels, KnownPattern, _clear_marches, _normal_equations, edge_levels, noise_sigma
)


def detect_edges(image: np.ndarray, sigma: float = 1.0, noise: float | None = None) -> Edgels:
    """Sub-pixel DoG zero crossings (sec. 4.1), the maps computed over the whole image at once."""
    g1 = ndimage.gaussian_filter(image, sigma)
    dog = g1 - ndimage.gaussian_filter(image, DOG_RATIO * sigma)
    gy, gx = np.gradient(g1)
    mag = np.hypot(gx, gy)
    noise = noise_sigma(image) if noise is None else noise
    threshold = max(10.0 * noise / np.sqrt(8 * np.pi) / sigma**2, 0.25 * float(np.percentile(mag, 99.5)))
    border = int(np.ceil(3 * DOG_RATIO * sigma)) + 1
    cand = mag >= threshold
    cand[:border] = cand[-border:] = False
    cand[:, :border] = cand[:, -border:] = False
    cand &= dog < 0
    py, px = np.nonzero(cand)
    nx, ny = gx[py, px] / mag[py, px], gy[py, px] / mag[py, px]
    d0 = dog[py, px]
    d1 = ndimage.map_coordinates(dog, [py + ny, px + nx], order=1)
    hit = d1 >= 0
    t = d0[hit] / (d0[hit] - d1[hit])
    x, y = px[hit] + t * nx[hit], py[hit] + t * ny[hit]
    strength = ndimage.map_coordinates(mag, [y, x], order=1)
    keep = strength >= threshold
    nan = np.full(int(keep.sum()), np.nan)
    return Edgels(x[keep], y[keep], nx[hit][keep], ny[hit][keep], strength[keep], nan, nan.copy())


def predict_sharp(edges: Edgels, shape: tuple[int, int], s: int, band: float) -> tuple[np.ndarray, np.ndarray]:
    """The blind prediction on the whole s-grid: levels of the nearest edge point, a one-sample ramp."""
    sharp, known = np.zeros(shape), np.zeros(shape, dtype=bool)
    if len(edges) == 0:
        return sharp, known
    tree = cKDTree(np.column_stack([edges.x, edges.y]))
    iy, ix = np.mgrid[0 : shape[0], 0 : shape[1]]
    px, py = ix.ravel() / s, iy.ravel() / s
    dist, idx = tree.query(np.column_stack([px, py]), distance_upper_bound=band * np.sqrt(2) + 1.0)
    found = np.isfinite(dist)
    i = idx[found]
    dx, dy = px[found] - edges.x[i], py[found] - edges.y[i]
    d = dx * edges.nx[i] + dy * edges.ny[i]
    along = np.abs(dx * edges.ny[i] - dy * edges.nx[i])
    ok = (np.abs(d) <= band) & (along <= 1.0)
    flat = np.flatnonzero(found)[ok]
    sharp.ravel()[flat] = edges.lo[i[ok]] + (edges.hi[i[ok]] - edges.lo[i[ok]]) * np.clip(0.5 + d[ok] * s, 0, 1)
    known.ravel()[flat] = True
    return sharp, known


def render_target(known: KnownPattern, shape: tuple[int, int], s: int, origin: tuple[float, float]
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Anti-aliased coverage of a located pattern and where it is known, on the whole s-grid (sec. 5.1)."""
    iy, ix = np.mgrid[0 : shape[0], 0 : shape[1]]
    px, py = known.to_pattern(origin[0] + ix / s, origin[1] + iy / s)
    dxdj, dxdi = np.gradient(px)[::-1]
    dydj, dydi = np.gradient(py)[::-1]
    alpha = np.zeros(shape)
    sub = (np.arange(ANTI_ALIAS) + 0.5) / ANTI_ALIAS - 0.5
    for oy in sub:
        for ox in sub:
            alpha += known.reflectance(px + dxdj * ox + dxdi * oy, py + dydj * ox + dydi * oy)
    return alpha / ANTI_ALIAS**2, known.region(px, py)


def nearest_levels(measured: Edgels, others: Edgels) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of ``others``: the mean levels of the nearest of the ``measured`` points (all on the s-grid)."""
    tree = cKDTree(np.column_stack([measured.x, measured.y]))
    k = min(8, len(measured))
    dist, idx = tree.query(np.column_stack([others.x, others.y]), k=k)
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    tied = dist <= dist[:, :1] * (1 + 1e-12)
    count = tied.sum(axis=1)
    return (np.where(tied, measured.lo[idx], 0.0).sum(axis=1) / count,
            np.where(tied, measured.hi[idx], 0.0).sum(axis=1) / count)


def shade_target(image: np.ndarray, alpha: np.ndarray, inside: np.ndarray, s: int, band: float, length: int,
                 known_pattern: KnownPattern, origin: tuple[float, float], kernel_radius: float
                 ) -> tuple[np.ndarray, np.ndarray, Edgels]:
    """Edge points of the rendered target, their levels, and the shaded coverage (sec. 4.2).

    An edge point whose marches meet another edge of the pattern or leave its known region
    (`sharpedge._clear_marches`) takes the mean levels of its nearest clear points (sec. 4.1).
    """
    smooth = ndimage.gaussian_filter(alpha, 1.0)
    gy, gx = np.gradient(smooth)
    mag = np.hypot(gx, gy)
    iy, ix = np.nonzero((alpha > 0.05) & (alpha < 0.95) & inside & (mag > 0))
    nan = np.full(iy.size, np.nan)
    points = Edgels(ix / s, iy / s, gx[iy, ix] / mag[iy, ix], gy[iy, ix] / mag[iy, ix], mag[iy, ix], nan, nan.copy())
    clear = _clear_marches(known_pattern, origin, points, 2 * kernel_radius, s, LATERAL * kernel_radius)
    edges = edge_levels(image, points.subset(clear), length)
    if len(edges) and not clear.all():
        others = points.subset(~clear)
        others.lo, others.hi = nearest_levels(edges, others)
        edges = Edgels(*(np.concatenate([a, b]) for a, b in zip(vars(edges).values(), vars(others).values())))
    elif not len(edges):
        edges = edge_levels(image, points, length)
    known, sharp = np.zeros(alpha.shape, dtype=bool), np.zeros(alpha.shape)
    if len(edges) == 0:
        return sharp, known, edges
    # the levels of the nearest edge point, their mean where several are as near (all lie on the s-grid)
    tree = cKDTree(np.column_stack([edges.x, edges.y]))
    iy, ix = np.mgrid[0 : alpha.shape[0], 0 : alpha.shape[1]]
    k = min(8, len(edges))  # ties of more than 4 points: none measured on the example photo
    dist, idx = tree.query(np.column_stack([ix.ravel() / s, iy.ravel() / s]), k=k, distance_upper_bound=band)
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    found = np.isfinite(dist[:, 0]) & inside.ravel()
    dist, idx = dist[found], idx[found]
    tied = dist <= dist[:, :1] * (1 + 1e-12)
    lo = np.where(tied, np.append(edges.lo, 0.0)[idx], 0.0).sum(axis=1) / tied.sum(axis=1)
    hi = np.where(tied, np.append(edges.hi, 0.0)[idx], 0.0).sum(axis=1) / tied.sum(axis=1)
    sharp.ravel()[found] = lo + (hi - lo) * alpha.ravel()[found]
    known.ravel()[found] = True
    return sharp, known, edges


def window_equations(image, saturated, window, s, support, band, length, sigma, known):
    """(ata, atb, btb, pixels used, edge points) of one window, as `sharpedge._window_equations` returns them."""
    x0, y0, x1, y1 = window
    rows, cols = image.shape
    margin = int(np.ceil(band + length)) + 6
    cx0, cy0 = max(0, x0 - margin), max(0, y0 - margin)
    crop = image[cy0 : min(rows, y1 + margin), cx0 : min(cols, x1 + margin)]
    shape = (s * (crop.shape[0] - 1) + 1, s * (crop.shape[1] - 1) + 1)
    if known is None:
        edges = edge_levels(crop, detect_edges(crop, noise=sigma), length)
        sharp, predicted = predict_sharp(edges, shape, s, band)
    else:
        alpha, inside = render_target(known, shape, s, (cx0, cy0))
        sharp, predicted, edges = shade_target(crop, alpha, inside, s, band, length, known, (cx0, cy0),
                                               (support // 2) / s)
    valid = ndimage.binary_erosion(predicted, np.ones((support, support), bool), border_value=0)[::s, ::s].copy()
    valid &= ~ndimage.binary_dilation(saturated[cy0 : cy0 + crop.shape[0], cx0 : cx0 + crop.shape[1]],
                                      iterations=int(np.ceil(band)) + 1)
    inwin = np.zeros_like(valid)
    inwin[y0 - cy0 : y1 - cy0, x0 - cx0 : x1 - cx0] = True
    valid &= inwin
    ata, atb, btb = _normal_equations(sharp, crop, valid, s, support)
    return ata, atb, btb, int(valid.sum()), edges
