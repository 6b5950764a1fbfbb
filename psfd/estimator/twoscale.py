"""Blind sub-pixel PSF from two photographs of a textured plane at different distances.

Delbracio, Almansa, Morel, Musé, SIAM J. Imaging Sci. 2012 (theory) and
Delbracio, Almansa, Musé, IPOL 2013 (the algorithm, sec. 4):

1. register the pair (SIFT + robust homography D: far -> near), `pair_register`;
2. low-pass the near photo v1 to the band the far photo's s-times grid can
   hold and resample it there through D: H_{lambda/s} v1 (IPOL 2013, sec. 4.2);
3. solve v2 = S_s C[H_{lambda/s} v1] k for the inter-image kernel k by plain
   least squares on the valid far pixels (SIAM 2012, eq. (9); IPOL 2013, eq. (3));
4. recover h from k by the zoom-in product h = H_{lambda^n}(k * H_{1/lambda}k *
   ... * H_{1/lambda^n}k) (SIAM 2012, eq. (11) and Alg. 1; IPOL 2013, sec. 4.4).

The method needs lambda > s (SIAM 2012, Remark 2), a scene with energy at
every frequency of the band (SIAM 2012, Lemma 1), fronto-parallel photos and
the same PSF in both (same aperture and focal length, both in focus).
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from psfd.errors import BadInputError, PairError
from psfd.vocabulary import DEFAULT_S, TWO_PHOTO, check_sizes
from psfd.estimator import fourier, pair_register, resample
from psfd.estimator.kernels import (PSF, clip_negatives, core_centroid, field_of_window, kernel_warnings, normalise,
                                    split_grid, translations)
from psfd.estimator.raw import Frame
from psfd.estimator.resample import keys_bicubic
from psfd.workers import concurrently

__all__ = [
    "band_limited", "estimate_pair", "hole_footprint", "observation_mask", "psf_from_kernel", "resample_near",
    "solve_kernel", "texture"
]

LAMBDA_ADVISED = (2.0, 8.0)  # IPOL 2013, App. 7, tip 2: shoot between 2 and 8 times the distance
LAMBDA_MAX = 50.0  # IPOL 2013, sec. 4.4: a kernel contracted 50x acts as a Dirac
N_MAX = 3  # IPOL 2013, sec. 4.4
ROTATION_WARN, ROTATION_MAX = 2.0, 10.0  # degrees about the optical axis
TILT_WARN, TILT_MAX = 0.02, 0.10  # relative change of the zoom across a window
TEXTURE_MIN = 0.1  # neighbour correlation of a photo below which it shows no texture, only noise
NOISE_MAX = 0.5  # relative noise floor of k above which the scene is too poor in the band
CHUNK = 4096  # rows of the least-squares system built at a time
OVERSAMPLE = 2.0  # grid of the near photo's band before Keys interpolation, per kept DCT coefficient
# Near pixels around a saturated one whose s-grid samples are left out, before `observation_mask` drops
# every far pixel whose footprint (p x p, then `hole_footprint`'s) reads one of them. The clipped plateau
# is wrong by the light above the white level, and the low-pass spreads that error over lobes of lambda/s
# near pixels; the footprint's erosion already keeps each kept far pixel's k-weighted samples off the plateau.
# Measured on renders of a wall with glints clipped in 0.5 % of the near photo (tests/render.py
# `wall_pair`; Gaussian 0.4 pixel x f/8 diffraction, s = 3, 30000 e-; max MTF error over the s-band,
# mean of 2-4 seeds; glint-free 0.036-0.037): at lambda = 4, 5 and 6.5, radius 1 kept 53 %, 39 % and
# 24 % of the glint-free equations, errors 0.037, 0.041 and 0.060; the former 2 + ceil(2 lambda / s)
# (5, 6, 7) with the plateau inpainted kept 28 %, 16 % and 6 %, errors 0.043, 0.056 and 0.131;
# radius 2: 0.038, 0.043, 0.068; radius 0: residual 1.3-3.0 times larger, errors 0.049, 0.064, 0.146.
# The best radius is 1 near pixel at every lambda, not a number of s-grid samples. Real wall pair
# (0.78 % saturated): 10677 -> 20538 of 52149 equations, noise floor 0.030 -> 0.021, MTF50 0.578/0.575
# -> 0.579/0.570.
SATURATED_RADIUS = 1
# Share of the first kernel's sum a q x q footprint must hold for the holes around saturated near pixels
# to be eroded by q instead of p (`hole_footprint`, then a second solve): a far pixel kept then reads the
# holes only through the taps outside it. Measured on the `wall_pair` renders above (p = 13): k's centred
# 7 x 7, 9 x 9 and 11 x 11 hold 0.92-0.94, 0.95-0.97 and 0.95-0.98 of its sum, 13 x 13 all of it (f/8's
# tails), so 0.99 changes nothing there. At 0.95 (q = 9), 15 pairs at lambda 4, 5, 6.5: 1.3-2.1 times the
# equations, max MTF error mean 0.043 -> 0.036, worst 0.075 -> 0.052, no pair worse by more than 0.002;
# glint-free pairs unchanged (no holes). A fixed q = 7 is not safe: through a Gaussian of 0.7 pixel
# (11 x 11 holds 0.94-0.95) it raised the error 0.023 -> 0.028 and 0.032 -> 0.040, where 0.95 chose
# q = 13 and 11 (0.023, 0.027); through a Gaussian of 0.3 pixel x f/5.6 it chose q = 7, errors 0.072,
# 0.090, 0.044 -> 0.039, 0.049, 0.034 (lambda 5, 5, 4). Real wall pair: q = 7, 20538 -> 35249 of 52149
# equations, noise floor 0.021 -> 0.016, MTF50 0.579/0.570 -> 0.582/0.572; `psfd estimate pair` 0.49 -> 0.53 s.
HOLE_MASS = 0.95


def estimate_pair(
    a: Frame,
    b: Frame,
    s: int = DEFAULT_S[TWO_PHOTO],
    support: int | None = None,
    clip: bool = False,
    grid: tuple[int, int] = (1, 1),
) -> list[PSF]:
    """Estimate the PSF from two photographs of one textured plane, in either order.

    Parameters
    ----------
    a, b : Frame
        The same channel plane of the two photos (a Bayer plane of two RAW
        files, or two single-channel images). Which one is near is detected.
    s : int
        Super-resolution factor; the distance ratio must exceed it.
    support : int, optional
        Odd kernel size on the s-times grid (default 4 s + 1).
    clip : bool
        Set negative PSF values to 0 (SIAM 2012, sec. 4.3) before normalising.
    grid : (int, int)
        (nx, ny) windows the common region is split into, each solved on its own.

    Returns
    -------
    list of PSF, one per window, row-major.

    Raises
    ------
    BadInputError
        Different channels, inconsistent planes, or s, support or grid out of bounds.
    PairError
        Unrelated photos, lambda not above s, a textureless scene, too large a
        rotation or tilt, too small a common region.
    """
    s, p, grid = check_sizes(s, support, grid)
    _check_inputs(a, b)
    try:
        reg = pair_register.register(a.data, b.data)  # SIFT sees each stretched to 8 bits
    except PairError:
        # a plane showing only noise has no consistent matches either: say why
        for frame in (a, b):
            _check_texture(frame)
        raise
    near, far = (a, b) if reg.near == 0 else (b, a)
    far_box, _ = pair_register.common_region(reg.to_near, far.shape, near.shape)
    return [
        _estimate_window(near, far, reg, window, s, p, clip, grid)
        for window in split_grid(far_box, grid)
    ]


# --------------------------------------------------------------------------- checks


def _check_inputs(a: Frame, b: Frame) -> None:
    for frame in (a, b):
        if frame.data.ndim != 2 or frame.saturated.shape != frame.data.shape:
            raise BadInputError(f"{frame.source}: channel plane and its saturation mask differ in size")
        if min(frame.data.shape) < 16:
            raise BadInputError(f"{frame.source}: channel plane {frame.data.shape} is too small")
    if a.channel != b.channel:
        raise BadInputError(f"the pair must use the same channel in both photos, got {a.channel} and {b.channel}")
    if a.from_mosaic and b.from_mosaic and tuple(a.sensor_shape) != tuple(b.sensor_shape):
        # RAW planes of one camera always have one size: different sizes mean
        # different cameras or crop modes, and so different PSFs
        raise BadInputError(
            f"the {a.channel} planes come from sensors of different sizes "
            f"({a.sensor_shape} and {b.sensor_shape}): use two photos of the same camera"
        )


def texture(image: np.ndarray) -> float:
    """Correlation of neighbouring pixels once the illumination is removed.

    Sensor noise is white, so it does not correlate neighbours; a scene seen
    through the PSF does. A plane showing only noise scores about 0, a textured
    scene well above TEXTURE_MIN (the real wall pair scores above 0.3).
    """
    image = np.asarray(image, dtype=np.float32)
    detail = image - cv2.GaussianBlur(image, (0, 0), 8.0)
    var = float(np.mean(detail * detail))
    if var <= 0.0:
        return 0.0
    horizontal = float(np.mean(detail[:, 1:] * detail[:, :-1]))
    vertical = float(np.mean(detail[1:, :] * detail[:-1, :]))
    return 0.5 * (horizontal + vertical) / var


def _check_texture(frame: Frame) -> None:
    score = texture(frame.data)
    if score < TEXTURE_MIN:
        raise PairError(
            f"textureless scene: {frame.source} shows no texture above the noise "
            f"(neighbour correlation {score:.2f}, needs {TEXTURE_MIN}); photograph a textured plane"
        )


def _check_geometry(
    reg: pair_register.Registration, window: tuple[int, int, int, int], s: int, warnings: list[str]
) -> tuple[float, float, float, float]:
    """Zoom, rotation and tilt of the window; PairError when the method cannot apply."""
    x0, y0, x1, y1 = window
    lam_x, lam_y, rotation = reg.geometry((x0 + x1 - 1) / 2, (y0 + y1 - 1) / 2)
    if min(lam_x, lam_y) <= s:
        raise PairError(
            f"distance ratio lambda = {min(lam_x, lam_y):.2f} does not exceed s = {s}: "
            f"take the far photo more than {s} times farther (2 to 8 times is advised), or lower s"
        )
    if max(lam_x, lam_y) > LAMBDA_ADVISED[1]:
        warnings.append(f"distance ratio {max(lam_x, lam_y):.1f} above the advised 2..8: small common region")
    if abs(rotation) > ROTATION_MAX:
        raise PairError(
            f"photos rotated by {rotation:.1f} degrees about the optical axis (at most {ROTATION_MAX}): "
            "not fronto-parallel"
        )
    if abs(rotation) > ROTATION_WARN:
        warnings.append(f"photos rotated by {rotation:.1f} degrees about the optical axis")
    zooms = [np.sqrt(abs(np.linalg.det(reg.jacobian(x, y)))) for x in (x0, x1 - 1) for y in (y0, y1 - 1)]
    tilt = float((max(zooms) - min(zooms)) / np.mean(zooms))
    if tilt > TILT_MAX:
        raise PairError(f"zoom varies by {100 * tilt:.0f}% across the window: the photos are not fronto-parallel")
    if tilt > TILT_WARN:
        warnings.append(f"zoom varies by {100 * tilt:.1f}% across the window (tilted photos)")
    return lam_x, lam_y, rotation, tilt


# --------------------------------------------------------------------------- one window


def _estimate_window(
    near: Frame,
    far: Frame,
    reg: pair_register.Registration,
    window: tuple[int, int, int, int],
    s: int,
    p: int,
    clip: bool,
    grid: tuple[int, int],
) -> PSF:
    warnings: list[str] = []
    lam_x, lam_y, rotation, tilt = _check_geometry(reg, window, s, warnings)
    upsampled, valid_fine, holes = resample_near(near, reg, window, s, (lam_x, lam_y))
    x0, y0, x1, y1 = window
    v2 = far.data[y0:y1, x0:x1] / far.white
    far_saturated = far.saturated[y0:y1, x0:x1]
    rows = observation_mask(valid_fine, holes, far_saturated, s, p)
    if far_saturated.mean() > 0.01:
        warnings.append("more than 1% of the far photo's window is saturated (left out)")
    if rows.sum() < 2 * p * p:
        raise PairError(
            f"common region too small: {int(rows.sum())} usable far pixels for {p * p} unknowns "
            f"(need {2 * p * p}); enlarge the overlap or lower the support"
        )
    # illumination: the IPOL 2013 text removes each image's mean (sec. 4.2); `solve_kernel` fits the offset
    # left between the two on the pixels it uses
    usable = valid_fine & ~holes
    upsampled = np.where(usable, upsampled - upsampled[usable].mean(), 0.0)
    v2 = v2 - v2[rows].mean()
    fit = solve_kernel(upsampled, v2, rows, s, p)
    q = hole_footprint(fit["kernel"]) if holes.any() else p
    if q < p:
        # the first kernel says how far around the holes a far pixel must stay: solve again with those rows
        rows = observation_mask(valid_fine, holes, far_saturated, s, p, q)
        fit = solve_kernel(upsampled, v2, rows, s, p)
    if fit["relative_noise"] > NOISE_MAX:
        raise PairError(
            f"textureless scene: spectral energy in the band {fit['energy']:.2e} "
            f"(weakest frequency {fit['energy_min']:.2e}) against noise {fit['sigma'] ** 2:.2e}; "
            f"the kernel would be {100 * fit['relative_noise']:.0f}% noise"
        )
    k = normalise(fit["kernel"])
    shift = core_centroid(k)
    h = psf_from_kernel(_shift(k, shift), (lam_x, lam_y))
    h = clip_negatives(h) if clip else normalise(h)
    params = {
        "lambda": [round(lam_x, 4), round(lam_y, 4)],
        "rotation_deg": round(rotation, 3),
        "tilt": round(tilt, 4),
        "matches": reg.matches,
        "inliers": reg.inliers,
        "registration_rms_px": round(reg.rms, 4),
        "spectral_energy": fit["energy"],
        "spectral_energy_min": fit["energy_min"],
        "cond": fit["cond"],
        "equations": int(rows.sum()),
        "support": p,
        "hole_footprint": q,
        "clip": clip,
        "grid": list(grid),
        "kernel_shift": [round(shift[0], 3), round(shift[1], 3)],
        "near": near.source,
        "far": far.source,
    }
    # the window and field are those of the far photo, whose grid the kernel is estimated on
    return PSF(
        psf=h,
        s=s,
        method=TWO_PHOTO,
        channel=far.channel,
        sources=[near.source, far.source],
        field=field_of_window(window, far.shape),
        window=window,
        noise_floor=fit["noise_floor"],
        residual=fit["rms"],
        params=params,
        warnings=warnings + kernel_warnings(h, fit["noise_floor"]),
        figures={"kernel": k, "residual": fit["residual"]},
    )


def resample_near(
    near: Frame,
    reg: pair_register.Registration,
    window: tuple[int, int, int, int],
    s: int,
    lam: tuple[float, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """H_{lambda/s} v1: the near photo on the s-times grid of a far window (IPOL 2013, sec. 4.2).

    Returns
    -------
    upsampled : ndarray (s (M2 - 1) + 1, s (N2 - 1) + 1)
        Samples at far coordinates (x0 + j/s, y0 + i/s), 0 where invalid or in a hole.
    valid : ndarray of bool, same shape
        Samples whose interpolation footprint lies inside the near photo.
    holes : ndarray of bool, same shape
        Samples within SATURATED_RADIUS near pixels of a saturated one.
    """
    x0, y0, x1, y1 = window
    gx = x0 + np.arange(s * (x1 - x0 - 1) + 1) / s
    gy = y0 + np.arange(s * (y1 - y0 - 1) + 1) / s
    X, Y = reg.map(gx[None, :], gy[:, None])
    nx0, ny0, nx1, ny1 = pair_register.bounding_box(X, Y, near.shape, 3)
    # saturated pixels keep their clipped value: the truth lies above it, a fill from the surroundings
    # (cv2.inpaint before) below it, further off (in the renders of SATURATED_RADIUS at lambda = 5, max
    # MTF error 0.064 against the fill's 0.076 at radius 0, 0.041 against 0.044 at radius 1); their
    # neighbourhood is left out below
    crop = near.data[ny0:ny1, nx0:nx1] / near.white
    saturated = near.saturated[ny0:ny1, nx0:nx1]
    # keep the near photo's frequencies the s-times grid can hold: below s/lambda
    # of its Nyquist band, i.e. DCT indices below (s/lambda) M1 (IPOL 2013, sec. 4.2, step 1b)
    keep = (math.ceil(crop.shape[0] * s / lam[1]), math.ceil(crop.shape[1] * s / lam[0]))
    band, zoom = band_limited(crop, keep)
    bx, by = (X - nx0 + 0.5) * zoom[1] - 0.5, (Y - ny0 + 0.5) * zoom[0] - 0.5
    # in single precision like the band (half the memory traffic), the samples then in double for the sums
    # every sample on its own: the two halves of the rows on two threads give the same values (0.3 s of the real pair)
    half = bx.shape[0] // 2
    upsampled = np.concatenate(concurrently(
        lambda: keys_bicubic(band, bx[:half], by[:half], a=-0.5, fill=np.nan),
        lambda: keys_bicubic(band, bx[half:], by[half:], a=-0.5, fill=np.nan))).astype(np.float64)
    valid = np.isfinite(upsampled)
    holes = np.zeros_like(valid)
    if saturated.any():
        bad = cv2.dilate(saturated.astype(np.uint8), np.ones((2 * SATURATED_RADIUS + 1,) * 2, np.uint8))
        iy = np.clip(np.round(Y - ny0).astype(int), 0, crop.shape[0] - 1)
        ix = np.clip(np.round(X - nx0).astype(int), 0, crop.shape[1] - 1)
        holes = valid & (bad[iy, ix] != 0)
    return np.where(valid & ~holes, upsampled, 0.0), valid, holes


def band_limited(image: np.ndarray, keep: tuple[int, int]) -> tuple[np.ndarray, tuple[float, float]]:
    """The DCT low-pass of ``image`` (IPOL 2013, sec. 4.2, step 1), resynthesised on a finer grid.

    Keys' cubic is accurate only well below the Nyquist frequency; the kept
    band reaches (s/lambda) of it, where the cubic's error (a fraction of the
    signal, folded back at other frequencies) would bias k. Resynthesising the
    kept DCT coefficients on OVERSAMPLE x ``keep`` samples puts the band at half
    the Nyquist frequency of the new grid at no loss, so the cubic then only
    has to interpolate a smooth signal.

    Returns
    -------
    band : ndarray of float32
        The band-limited image on the new grid.
    zoom : (float, float)
        New samples per original pixel along rows and cols: original
        coordinate x maps to (x + 0.5) zoom - 0.5.
    """
    rows, cols = image.shape
    keep_r, keep_c = min(int(keep[0]), rows), min(int(keep[1]), cols)
    out_r = max(keep_r, int(math.ceil(OVERSAMPLE * keep_r)))
    out_c = max(keep_c, int(math.ceil(OVERSAMPLE * keep_c)))
    # single precision (24-bit mantissa, beyond any sensor's 14 bits) halves the cost
    band = resample.dct_lowpass(np.asarray(image, dtype=np.float32), (keep_r, keep_c), size=(out_r, out_c))
    return band, (out_r / rows, out_c / cols)


def observation_mask(
    valid_fine: np.ndarray, holes: np.ndarray, far_saturated: np.ndarray, s: int, p: int, q: int | None = None
) -> np.ndarray:
    """Far pixels whose p x p footprint on the s-times grid is valid (IPOL 2013, sec. 4.3) and whose
    central q x q part (default p) misses the holes.

    The papers erode the subsampled mask by (p - 1) / (2 s); eroding the fine
    mask by (p - 1) / 2 and then subsampling is the same for convex regions and
    also exact around holes left by saturated near pixels.
    """
    q = p if q is None else q
    inside = cv2.erode(valid_fine.astype(np.uint8), np.ones((p, p), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    # beyond the window there are no holes, only the border above
    clear = cv2.erode((~holes).astype(np.uint8), np.ones((q, q), np.uint8),
                      borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return (inside[::s, ::s] > 0) & (clear[::s, ::s] > 0) & ~far_saturated


def hole_footprint(kernel: np.ndarray, mass: float = HOLE_MASS) -> int:
    """Side of the smallest centred odd square holding ``mass`` of the kernel's sum.

    The kernel's noise averages out in the sum, not in its absolute values: on
    the renders of HOLE_MASS, 99 % of the first kernel's absolute mass took
    123-165 of its 169 taps.

    Parameters
    ----------
    kernel : ndarray (p, p), p odd
    mass : float
        Share of the sum the square must hold.

    Returns
    -------
    int
        The side q, odd, p when no smaller square holds it (or the sum is not positive).
    """
    p = kernel.shape[0]
    total = float(kernel.sum())
    c = (p - 1) // 2
    for q in range(1, p, 2):
        h = (q - 1) // 2
        if total > 0 and float(kernel[c - h:c + h + 1, c - h:c + h + 1].sum()) >= mass * total:
            return q
    return p


def solve_kernel(upsampled: np.ndarray, v2: np.ndarray, rows: np.ndarray, s: int, p: int) -> dict:
    """Least-squares inter-image kernel k_e = (S_s C[H_{lambda/s} v1])^+ v2 (SIAM 2012, eq. (9)).

    Only the masked rows of S_s C are built, CHUNK at a time, and folded into
    the p^2 x p^2 normal equations, with a free offset beside k (the
    illumination level, see below); the pseudo-inverse drops eigenvalues below
    1e-12 of the largest (singular values below 1e-6, the IPOL code's DGELSD rcond).

    Returns
    -------
    dict with ``kernel`` (p x p), ``residual`` (far window, 0 outside the mask),
    ``rms``, ``sigma``, ``noise_floor`` (sigma sqrt(trace((A^T A)^-1)), for the
    unit-sum kernel), ``relative_noise`` (noise floor / ||k||), ``cond``,
    ``energy`` and ``energy_min`` (mean and smallest eigenvalue of A^T A / n:
    the resampled scene's power in the band, on average and at its weakest).
    """
    half = (p - 1) // 2
    # window (i, j) of the view starts at fine sample (i, j): row (ii, jj) of
    # S_s C reads the window starting at (s ii - half, s jj - half), flipped
    windows = sliding_window_view(upsampled, (p, p))
    ii, jj = np.nonzero(rows)
    n = ii.size
    ata = np.zeros((p * p, p * p))
    atb = np.zeros(p * p)
    col = np.zeros(p * p)
    b = v2[ii, jj]
    for start in range(0, n, CHUNK):
        sl = slice(start, start + CHUNK)
        a = windows[s * ii[sl] - half, s * jj[sl] - half].reshape(-1, p * p)
        ata += a.T @ a
        atb += a.T @ b[sl]
        col += a.sum(axis=0)
    # a free offset c beside k (v2 = S_s C[H v1] k + c): the least squares of k with every column of S_s C
    # and v2 centred on the rows used. The IPOL 2013 text (sec. 4.2) removes each image's mean for the
    # illumination; taken over different regions (the whole resampled near window, the far pixels kept
    # after erosion) the two means leave a constant in v2 that no kernel explains, which biased k
    # (tests/test_twoscale.py: the offset dominated the residual of noise-free renders)
    mean_a, mean_b = col / n, float(b.mean())
    ata -= n * np.outer(mean_a, mean_a)
    atb -= n * mean_a * mean_b
    evals, evecs = np.linalg.eigh(ata)
    keep = evals > evals[-1] * 1e-12
    inv_evals = np.where(keep, 1.0 / np.where(keep, evals, 1.0), 0.0)
    flipped = (evecs @ (inv_evals * (evecs.T @ atb))).reshape(p, p)
    kernel = flipped[::-1, ::-1]
    # prediction S_s(C * k) on the far grid, all at once: filter2D correlates, with the flipped kernel
    pred = cv2.filter2D(upsampled, -1, flipped, borderType=cv2.BORDER_CONSTANT)[::s, ::s]
    pred += mean_b - float(mean_a @ flipped.ravel())  # the offset
    residual = np.where(rows, v2 - pred, 0.0)
    rss = float(np.sum(residual[rows] ** 2))
    sigma = math.sqrt(rss / max(n - p * p - 1, 1))
    total = float(kernel.sum())
    scale = 1.0 / abs(total) if abs(total) > 1e-12 else float("inf")
    noise_floor = sigma * math.sqrt(float(np.sum(inv_evals))) * scale
    norm_k = float(np.linalg.norm(kernel)) * scale
    return {
        "kernel": kernel,
        "residual": residual,
        "rms": math.sqrt(rss / n),
        "sigma": sigma,
        "noise_floor": noise_floor,
        "relative_noise": noise_floor / norm_k if norm_k > 0 else float("inf"),
        "cond": float(math.sqrt(evals[-1] / max(evals[0], evals[-1] * 1e-300))),
        "energy": float(evals.mean() / n),
        "energy_min": float(max(evals[0], 0.0) / n),
    }


# --------------------------------------------------------------------------- k -> h


def _sample(kernel: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Keys bicubic (a = -0.5) samples of a kernel at (x, y), 0 outside its support.

    The kernel is padded with two rings of zeros so that the 4 x 4 footprint
    near its edge reads k = 0 instead of being cut off.
    """
    x, y = np.broadcast_arrays(x, y)
    return keys_bicubic(np.pad(kernel, 2), x + 2, y + 2, a=-0.5, fill=0.0)


def _shift(kernel: np.ndarray, shift: tuple[float, float]) -> np.ndarray:
    """The kernel moved by -shift, so that a kernel whose core is centred at ``shift`` becomes centred.

    A blind pair fixes h only up to the sub-pixel translation left by the
    registration (SIAM 2012, sec. 5.1: the PSFs "differ only by a subpixel
    translation"); the convention is a centred PSF, so that translation is removed.
    k is band-limited to the s-grid band (SIAM 2012, Lemma 1), so the move is a
    Fourier phase ramp (`kernels.translations`), exact, as for the Bernoulli
    method's kernels; Keys' cubic at a shift of 0.2 (0.5) sample lowered the MTF
    of a Gaussian of 0.3 pixel by up to 0.013 (0.037).
    """
    return translations(kernel)(shift)


def psf_from_kernel(
    kernel: np.ndarray, lam: tuple[float, float], n_max: int = N_MAX, lam_max: float = LAMBDA_MAX
) -> np.ndarray:
    """The PSF h from the inter-image kernel k by the zoom-in product (SIAM 2012, Alg. 1; IPOL 2013, sec. 4.4).

    h = H_{lambda^n}(k * H_{1/lambda}k * ... * H_{1/lambda^n}k): the dilated
    copies H_{1/lambda^m}k are Keys bicubic samples of k on a grid of step
    lambda^-m centred on the kernel centre, convolved on the finest grid, and
    the product is finally sampled back with step lambda^n. Factors are added
    while lambda^m <= lam_max and m <= n_max, so the remaining error
    1/h^(zeta/lambda^(n+1)) lies beyond a 50x contraction (IPOL 2013: negligible).

    Parameters
    ----------
    kernel : ndarray (p, q), odd sizes
    lam : (lambda_x, lambda_y)

    Returns
    -------
    ndarray (p, q), not normalised.
    """
    p, q = kernel.shape
    lam_x, lam_y = lam
    product = kernel
    n = 0
    while n < n_max and max(lam_x, lam_y) ** (n + 1) <= lam_max:
        n += 1
        sx, sy = lam_x**n, lam_y**n
        # odd sizes keep the centre on a sample
        qn = 2 * math.ceil((q * sx - 1) / 2) + 1
        pn = 2 * math.ceil((p * sy - 1) / 2) + 1
        x = np.arange(qn) / sx + (q - 1) / 2 - (qn - 1) / (2 * sx)
        y = np.arange(pn) / sy + (p - 1) / 2 - (pn - 1) / (2 * sy)
        dilated = _sample(kernel, x[None, :], y[:, None])
        dilated /= dilated.sum()
        # central part of the convolution, the size of the dilated factor (IPOL 2013, step 3)
        product = fourier.convolve_same(dilated, product)
    if n == 0:
        return kernel.copy()
    rows, cols = product.shape
    x = (np.arange(q) - (q - 1) / 2) * lam_x**n + (cols - 1) / 2
    y = (np.arange(p) - (p - 1) / 2) * lam_y**n + (rows - 1) / 2
    return _sample(product, x[None, :], y[:, None])
