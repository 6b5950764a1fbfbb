"""Forward model of a photograph: the ground truth every estimator is tested against.

The model is the one the papers invert (Delbracio et al., IJCV 2012, sec. 2,
model (M)): v = S_1 g(u_D * h) + n, discretised by Lemma 1 as
v = S_s(u~_D * h) with u~_D = S_s LPF_s[u(D(.))] (IJCV 2012, sec. 3.1):

1. the scene u (a reflectance raster) is band-limited to the Nyquist band of
   the s-times grid and sampled there through the camera -> scene map D,
2. it is convolved on the s-times grid with the discrete kernel h, which is
   therefore *exactly* the PSF an estimator should recover,
3. the result is decimated by s, lit by a smooth illumination field, exposed
   with shot and read noise, quantised and clipped, and the four Bayer planes
   are written as a real DNG.

Units: one channel pixel (one photosite of a Bayer plane, twice the sensor
pitch) is the length unit of PSFs, as in the papers.
"""

from __future__ import annotations

import os
from typing import Callable

import cv2
import numpy as np
from scipy import fft

from psfd.estimator import raw, target

__all__ = [
    "bandlimit_scene", "diffraction_psf", "expose", "gaussian_psf", "noise_sigma", "render_plane",
    "simulate_pair", "simulate_scene", "simulate_target", "target_homography", "texture_scene"
]

Map = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]

# RGGB: (row, col) offset of each channel plane on the sensor.
RGGB_OFFSETS = {"r": (0, 0), "g1": (0, 1), "g2": (1, 0), "b": (1, 1)}
RASTER = 8  # scene raster pixels per target cell (the paper's simulation, IJCV 2012 sec. 5.1)
PUPIL_SPAN = 128  # diffraction_psf: its fine grid spans PUPIL_SPAN s-grid samples a side


# --------------------------------------------------------------------------- PSFs


def _grid(s: int, support: int) -> np.ndarray:
    if support % 2 == 0 or support < 1:
        raise ValueError("support must be a positive odd number of s-grid samples")
    return (np.arange(support) - (support - 1) / 2) / s


def gaussian_psf(
    sigma_x: float, sigma_y: float | None = None, theta: float = 0.0, s: int = 4, support: int = 17
) -> np.ndarray:
    """Anisotropic Gaussian PSF sampled on the s-times grid.

    Parameters
    ----------
    sigma_x, sigma_y : float
        Standard deviations along the kernel's own axes, in channel pixels
        (``sigma_y`` defaults to ``sigma_x``).
    theta : float
        Rotation of the x axis of the kernel, radians, counter-clockwise in (x, y-down).
    s : int
        Super-resolution factor of the grid.
    support : int
        Odd size of the kernel in s-grid samples.

    Returns
    -------
    ndarray (support, support), unit sum.
    """
    sigma_y = sigma_x if sigma_y is None else sigma_y
    c = _grid(s, support)
    y, x = np.meshgrid(c, c, indexing="ij")
    u = np.cos(theta) * x + np.sin(theta) * y
    v = -np.sin(theta) * x + np.cos(theta) * y
    h = np.exp(-0.5 * ((u / sigma_x) ** 2 + (v / sigma_y) ** 2))
    return h / h.sum()


def finest_pitch_um(fnumber: float, wavelength_um: float, s: int) -> float:
    """The finest channel pitch `diffraction_psf` renders at this f-number, wavelength and s.

    Its pupil must span at least 3 frequency steps of the fine grid (``PUPIL_SPAN`` s-grid samples a side,
    so a step of s / (PUPIL_SPAN pitch)): the coherent cut-off 1 / (2 lambda N) >= 3 s / (PUPIL_SPAN pitch).
    """
    return 6.0 * s * wavelength_um * fnumber / PUPIL_SPAN


def diffraction_psf(
    fnumber: float,
    wavelength_um: float = 0.55,
    pitch_um: float = 8.0,
    s: int = 4,
    support: int = 17,
    defocus_waves: float = 0.0,
    aberration: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Circular-pupil diffraction convolved with the pixel aperture, on the s-times grid.

    The intensity PSF is |F(pupil)|^2 with the pupil phase
    W = defocus rho^2 + astigmatism + coma (in waves); it is convolved with a
    square aperture one channel pitch wide, which is the photosite (one sensor
    pitch, full fill factor) convolved with a 4-spot birefringent low-pass
    filter of one sensor pitch displacement, as in a Bayer DSLR; the optics of
    the thesis' example camera (Delbracio PhD thesis 2013, sec. 2.2.1).
    The kernel is the s-grid samples of LPF_s h, the PSF band-limited to
    |fx|, |fy| < s/2 cycles per channel pixel: its transfer function is the
    optics' own over that band. Lemma 1 (IJCV 2012: u * h = I_s(u~ * S_s h))
    needs h band-limited there, and a fast lens is not (f/4 at 0.53 um on a
    16 um channel pitch passes 7.5 cycles per pixel, s = 4 holds 2): the
    point samples S_s h would fold that content into the band, lowering or
    raising the MTF by up to 0.09 depending on the sub-sample position of
    the kernel, and an aberrated corner could then out-resolve the
    aberration-free centre. As the renderer band-limits the scene to the same
    band, u~ * S_s LPF_s h is the image of the scene through h (up to the
    light beyond the support).
    The band-limited kernel rings where the pixel box has sharp edges: its
    negative lobes reach 4 % of the peak (f/2.8, 0.46 um, 16 um pitch, s = 4)
    and are kept, as clipping them would change its MTF. It is re-centred on
    its centroid so that a coma tilt does not move it.

    Parameters
    ----------
    fnumber : float
    wavelength_um : float
    pitch_um : float
        Pitch of the channel plane (twice the sensor pitch for a Bayer plane).
    s, support : int
        Grid factor and odd size of the kernel in s-grid samples.
    defocus_waves : float
        Peak defocus W20 at the pupil edge, in waves.
    aberration : (float, float)
        Field aberration vector (ax, ay) in waves: astigmatism and coma of
        magnitude |a| oriented along a (aberrations grow towards the corners
        along the radial direction).

    Returns
    -------
    ndarray (support, support), unit sum.
    """
    # Fine samples per s-grid sample: enough that the optics' transfer function (it ends at
    # pitch / (wavelength N) cycles per channel pixel) does not wrap round the fine grid
    # (period s q) into the band |f| < s/2; n keeps the grid PUPIL_SPAN s-grid samples a side.
    q = max(4, int((pitch_um / (wavelength_um * fnumber) + s / 2) / s) + 1)
    n = PUPIL_SPAN * q
    dx = pitch_um / (s * q)  # fine spatial step, um
    f = fft.fftfreq(n, dx)
    fy, fx = np.meshgrid(f, f, indexing="ij")
    radius = 1.0 / (2.0 * wavelength_um * fnumber)  # coherent cut-off of the pupil, cycles/um
    if pitch_um < finest_pitch_um(fnumber, wavelength_um, s):
        raise ValueError("f-number too large for the simulation grid")
    u, v = fx / radius, fy / radius
    rho2 = u * u + v * v
    pupil = (rho2 <= 1.0).astype(np.complex128)
    ax, ay = aberration
    mag = float(np.hypot(ax, ay))
    w = defocus_waves * rho2
    if mag > 0:
        p = (ax * u + ay * v) / mag  # pupil coordinate along the aberration direction
        w = w + mag * (p * p - 0.5 * rho2)  # astigmatism (Zernike Z2,2 rotated)
        w = w + mag * (3 * rho2 - 2) * p  # coma (Zernike Z3,1 rotated)
    pupil *= np.exp(2j * np.pi * w)
    intensity = np.abs(fft.ifft2(pupil)) ** 2
    otf = fft.fft2(intensity)
    otf /= otf[0, 0]
    # pixel aperture: a box of one channel pitch
    otf *= np.sinc(fx * pitch_um) * np.sinc(fy * pitch_um)
    otf *= _band(fx * pitch_um, s) * _band(fy * pitch_um, s)  # LPF_s
    # Re-centre on the centroid of the part inside the support with a Fourier
    # phase ramp (exact sub-sample shift); a few passes because the window
    # moves with the shift.
    half = (support - 1) // 2
    if support % 2 == 0 or q * half >= n // 2:
        raise ValueError(f"support must be odd and below {n // q} samples")
    idx = n // 2 + q * np.arange(-half, half + 1)
    near = np.arange(n // 2 - q * half, n // 2 + q * half + 1)
    offsets = near - n // 2
    for _ in range(3):
        fine = fft.fftshift(np.real(fft.ifft2(otf)))
        part = fine[np.ix_(near, near)]
        cx = float((part * offsets[None, :]).sum() / part.sum())
        cy = float((part * offsets[:, None]).sum() / part.sum())
        otf = otf * np.exp(2j * np.pi * (fx * cx + fy * cy) * dx)
    fine = fft.fftshift(np.real(fft.ifft2(otf)))
    h = fine[np.ix_(idx, idx)]
    return h / h.sum()


def _band(f: np.ndarray, s: int) -> np.ndarray:
    """Ideal low-pass to |f| < s/2 cycles per channel pixel; half weight on the band edge, whose
    two frequencies +-s/2 are one on the s-grid."""
    edge = np.isclose(np.abs(f), s / 2, rtol=0, atol=1e-9)
    return np.where(edge, 0.5, (np.abs(f) < s / 2).astype(np.float64))


# --------------------------------------------------------------------------- rendering


def _jacobian_scale(to_scene: Map, shape: tuple[int, int]) -> float:
    """Largest scene-raster displacement per channel pixel near the plane centre."""
    y0, x0 = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    xs = np.array([x0, x0 + 1.0, x0])
    ys = np.array([y0, y0, y0 + 1.0])
    X, Y = to_scene(xs, ys)
    jac = np.array([[X[1] - X[0], X[2] - X[0]], [Y[1] - Y[0], Y[2] - Y[0]]], dtype=np.float64)
    return float(np.linalg.svd(jac, compute_uv=False)[0])


def bandlimit_scene(scene: np.ndarray, cutoff: float, background: float) -> tuple[np.ndarray, int]:
    """Low-pass a scene raster to ``cutoff`` cycles per raster pixel (LPF_s of IJCV 2012, sec. 3.1).

    The filter is flat to 80 % of the cut-off and falls with a raised cosine
    to zero at the cut-off, which keeps Gibbs ringing small while leaving the
    band the PSF lives in untouched. The raster is padded with ``background``
    so the periodic FFT does not wrap the target onto itself.

    Returns
    -------
    filtered : ndarray of float32
        The raster padded with ``background`` by ``pad`` pixels on each side.
    pad : int
    """
    pad = int(np.ceil(4.0 / max(cutoff, 1e-6)))
    rows, cols = scene.shape
    shape = (fft.next_fast_len(rows + 2 * pad, real=True), fft.next_fast_len(cols + 2 * pad, real=True))
    padded = np.full(shape, background, dtype=np.float32)
    padded[pad : pad + rows, pad : pad + cols] = scene
    spec = fft.rfft2(padded - background, workers=-1)
    fy = np.abs(fft.fftfreq(shape[0]))[:, None]
    fx = fft.rfftfreq(shape[1])[None, :]

    def taper(f: np.ndarray) -> np.ndarray:
        t = np.clip((f / cutoff - 0.8) / 0.2, 0.0, 1.0)
        return (0.5 + 0.5 * np.cos(np.pi * t)).astype(np.float32)

    spec *= taper(fy) * taper(fx)
    out = fft.irfft2(spec, s=shape, workers=-1).astype(np.float32) + np.float32(background)
    return out, pad


def render_plane(
    scene: np.ndarray,
    to_scene: Map,
    shape: tuple[int, int],
    psf: np.ndarray,
    s: int,
    background: float | None = None,
    _bandlimited: tuple[np.ndarray, int] | None = None,
) -> np.ndarray:
    """Ideal linear channel plane v = S_s(u~_D * h) (IJCV 2012, sec. 3.1, eq. (1)), values in [0, 1].

    Parameters
    ----------
    scene : ndarray, 2-D
        Reflectance raster in [0, 1].
    to_scene : callable
        ``to_scene(x, y) -> (X, Y)`` from channel-plane coordinates (pixel
        centres at integers) to scene-raster coordinates (pixel centres at integers).
    shape : (int, int)
        (rows, cols) of the plane.
    psf : ndarray
        Odd-sized kernel on the s-times grid (unit sum).
    s : int
        Super-resolution factor of ``psf``.
    background : float, optional
        Reflectance outside the raster (default: mean of the raster's border).
    _bandlimited : (ndarray, int), optional
        Output of `bandlimit_scene`, to share one filtering between planes.

    Returns
    -------
    ndarray of float64 (rows, cols).
    """
    scene = np.asarray(scene, dtype=np.float32)
    psf = np.asarray(psf, dtype=np.float64)
    if psf.ndim != 2 or psf.shape[0] % 2 == 0 or psf.shape[1] % 2 == 0:
        raise ValueError("psf must be a 2-D kernel of odd size")
    background = _border_mean(scene) if background is None else float(background)
    out = np.full(shape, background * float(psf.sum()), dtype=np.float64)
    box = _scene_box(scene.shape, to_scene, shape, psf.shape[0] // (2 * s) + 2)
    if box is None:
        return out
    r0, r1, c0, c1 = box
    if _bandlimited is None:
        # Nyquist of the s-grid is s/2 cycles per channel pixel; in raster units
        # it is divided by the raster pixels per channel pixel.
        cutoff = min(0.5, s / 2.0 / _jacobian_scale(to_scene, shape))
        _bandlimited = bandlimit_scene(scene, cutoff, background)
    filtered, pad = _bandlimited
    hy, hx = psf.shape[0] // 2, psf.shape[1] // 2
    # s-grid sample i sits at channel coordinate i / s (Lemma 1: S_s samples at n/s)
    iy = np.arange(s * r0 - hy, s * (r1 - 1) + hy + 1)
    ix = np.arange(s * c0 - hx, s * (c1 - 1) + hx + 1)
    gy, gx = np.meshgrid(iy / s, ix / s, indexing="ij")
    X, Y = to_scene(gx, gy)
    u = cv2.remap(
        filtered,
        (np.asarray(X) + pad).astype(np.float32),
        (np.asarray(Y) + pad).astype(np.float32),
        interpolation=cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=float(background),
    )
    from scipy import signal  # here: its import alone takes a second, and `psfd rail ... --simulate` never renders

    conv = signal.fftconvolve(u.astype(np.float64), psf, mode="valid")  # index j <-> s-grid s*r0 + j
    out[r0:r1, c0:c1] = conv[::s, ::s]
    return out


def _scene_box(
    scene_shape: tuple[int, int], to_scene: Map, shape: tuple[int, int], margin: int
) -> tuple[int, int, int, int] | None:
    """Rows/cols of the plane whose footprint meets the scene raster (end exclusive)."""
    rows, cols = shape
    step = 4
    ys = np.arange(0, rows + step, step).clip(max=rows - 1)
    xs = np.arange(0, cols + step, step).clip(max=cols - 1)
    gy, gx = np.meshgrid(ys, xs, indexing="ij")
    X, Y = to_scene(gx.astype(np.float64), gy.astype(np.float64))
    inside = (X >= -1) & (X <= scene_shape[1]) & (Y >= -1) & (Y <= scene_shape[0])
    if not inside.any():
        return None
    r, c = np.nonzero(inside)
    m = margin + step
    return (
        max(0, int(ys[r.min()]) - m),
        min(rows, int(ys[r.max()]) + m + 1),
        max(0, int(xs[c.min()]) - m),
        min(cols, int(xs[c.max()]) + m + 1),
    )


def expose(
    ideal: np.ndarray,
    *,
    black: int = 512,
    white: int = 16383,
    exposure: float = 0.75,
    illumination: np.ndarray | None = None,
    read_noise: float = 2.0,
    gain: float = 2.5,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Raw values of one plane: illumination, exposure, shot + read noise, quantisation, clipping.

    Parameters
    ----------
    ideal : ndarray
        Linear plane in [0, 1] (reflectance seen through the optics).
    black, white : int
        Black level and saturation level of the raw values.
    exposure : float
        Fraction of the range (white - black) that reflectance 1 reaches.
    illumination : ndarray, optional
        Multiplicative light field (same shape), 1 = nominal.
    read_noise : float
        Read noise, DN RMS.
    gain : float
        Electrons per DN (shot noise is Poisson in electrons).
    rng : numpy Generator

    Returns
    -------
    ndarray of float64: integer raw values in [0, white].
    """
    rng = np.random.default_rng(0) if rng is None else rng
    signal_dn = np.asarray(ideal, dtype=np.float64) * exposure * (white - black)
    if illumination is not None:
        signal_dn = signal_dn * illumination
    electrons = rng.poisson(np.maximum(signal_dn, 0.0) * gain)
    values = black + electrons / gain + rng.normal(0.0, read_noise, signal_dn.shape)
    return np.clip(np.round(values), 0, white)


def noise_sigma(level: float, *, black: int = 512, white: int = 16383, exposure: float = 0.75,
                read_noise: float = 2.0, gain: float = 2.5) -> float:
    """Standard deviation of `expose` noise at reflectance ``level``, in units of reflectance.

    Shot variance level*E/gain plus read variance (and 1/12 quantisation), divided by E^2,
    with E = exposure * (white - black).
    """
    scale = exposure * (white - black)
    var = level * scale / gain + read_noise**2 + 1.0 / 12.0
    return float(np.sqrt(var) / scale)


# --------------------------------------------------------------------------- frames


def simulate_scene(
    path: str | os.PathLike,
    *,
    scene: np.ndarray,
    sensor_to_scene: Map,
    psf: np.ndarray | dict[str, np.ndarray],
    s: int = 4,
    sensor: tuple[int, int] = (480, 640),
    seed: int = 0,
    exposure: float = 0.75,
    illumination: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    background: float | None = None,
    read_noise: float = 2.0,
    gain: float = 2.5,
    black: int = 512,
    white: int = 16383,
    exif: dict | None = None,
) -> dict:
    """Render a planar scene on the four planes of an RGGB sensor and write a DNG.

    Parameters
    ----------
    path : path-like
        DNG to write (written to a temporary name and renamed).
    scene : ndarray
        Reflectance raster in [0, 1].
    sensor_to_scene : callable
        ``f(x, y) -> (X, Y)`` from full-sensor coordinates (photosite centres at
        integers) to scene-raster coordinates.
    psf : ndarray or dict
        One kernel on the s-grid of the channel planes, or one per channel name.
    s : int
    sensor : (int, int)
        Sensor (rows, cols), even.
    seed : int
        Seed of the noise.
    exposure : float
        Fraction of the raw range reached by reflectance 1 under nominal light.
    illumination : callable, optional
        ``f(x, y)`` light field at normalised sensor coordinates in [0, 1].
    background : float, optional
        Reflectance outside the raster.
    exif : dict, optional
        Exposure metadata for the DNG (see `raw.write_dng`).

    Returns
    -------
    dict with ``path``, ``psf`` (per channel), ``s``, ``sensor``, ``to_scene``
    (per channel: channel plane -> scene raster), ``black``, ``white``,
    ``exposure``, ``sigma`` (noise std at reflectance 0.5, reflectance units).
    """
    rows, cols = sensor
    if rows % 2 or cols % 2:
        raise ValueError("sensor dimensions must be even")
    psfs = psf if isinstance(psf, dict) else {c: psf for c in RGGB_OFFSETS}
    rng = np.random.default_rng(seed)
    mosaic = np.zeros(sensor, dtype=np.uint16)
    plane_shape = (rows // 2, cols // 2)
    background = _border_mean(scene) if background is None else float(background)
    maps: dict[str, Map] = {}
    prefiltered = None  # the band-limited scene is shared by the four planes
    for name, (dy, dx) in RGGB_OFFSETS.items():
        def to_scene(x, y, dx=dx, dy=dy):
            return sensor_to_scene(2 * np.asarray(x) + dx, 2 * np.asarray(y) + dy)

        maps[name] = to_scene
        if prefiltered is None:
            cutoff = min(0.5, s / 2.0 / _jacobian_scale(to_scene, plane_shape))
            prefiltered = bandlimit_scene(np.asarray(scene, np.float32), cutoff, background)
        h = np.asarray(psfs[name], dtype=np.float64)
        ideal = render_plane(scene, to_scene, plane_shape, h, s, background, _bandlimited=prefiltered)
        light = None
        if illumination is not None:
            yy, xx = np.mgrid[0 : plane_shape[0], 0 : plane_shape[1]]
            light = illumination((2 * xx + dx) / (cols - 1), (2 * yy + dy) / (rows - 1))
        mosaic[dy::2, dx::2] = expose(
            ideal, black=black, white=white, exposure=exposure, illumination=light,
            read_noise=read_noise, gain=gain, rng=rng,
        ).astype(np.uint16)
    raw.write_dng(path, mosaic, pattern="RGGB", black=black, white=white, exif=exif)
    return {
        "path": str(path),
        "psf": {c: np.asarray(psfs[c], dtype=np.float64) for c in RGGB_OFFSETS},
        "s": s,
        "sensor": tuple(sensor),
        "to_scene": maps,
        "black": black,
        "white": white,
        "exposure": exposure,
        "sigma": noise_sigma(0.5, black=black, white=white, exposure=exposure, read_noise=read_noise, gain=gain),
    }


def _border_mean(scene: np.ndarray) -> float:
    return float(np.concatenate([scene[0], scene[-1], scene[:, 0], scene[:, -1]]).mean())


def target_homography(
    *,
    pixels_per_cell: float,
    rotation_deg: float,
    centre: tuple[float, float],
    sensor: tuple[int, int],
    tilt: tuple[float, float] = (0.0, 0.0),
) -> np.ndarray:
    """Homography from target cell coordinates to (undistorted) full-sensor coordinates.

    ``pixels_per_cell`` is in channel pixels (two sensor photosites); ``tilt``
    = (px, py) adds perspective: the scale changes by a factor (1 + p) from the
    target centre to its right (px) or bottom (py) edge.
    """
    half = target.SIZE / 2
    to_centre = np.array([[1, 0, -half], [0, 1, -half], [0, 0, 1]], dtype=np.float64)
    px, py = tilt
    # (x, y, 1) -> (x, y, 1 - (px x + py y)/half): points at +half are magnified by ~(1 + p)
    persp = np.array([[1, 0, 0], [0, 1, 0], [-px / half / (1 + px) if px else 0.0,
                                                -py / half / (1 + py) if py else 0.0, 1]])
    a = np.deg2rad(rotation_deg)
    k = 2.0 * pixels_per_cell  # sensor photosites per cell
    rot = np.array([[k * np.cos(a), -k * np.sin(a), 0], [k * np.sin(a), k * np.cos(a), 0], [0, 0, 1]])
    cx, cy = centre[0] * (sensor[1] - 1), centre[1] * (sensor[0] - 1)
    shift = np.array([[1, 0, cx], [0, 1, cy], [0, 0, 1]], dtype=np.float64)
    return shift @ rot @ persp @ to_centre


def simulate_target(
    path: str | os.PathLike,
    *,
    psf: np.ndarray | dict[str, np.ndarray],
    s: int = 4,
    pixels_per_cell: float = 0.25,
    rotation_deg: float = 0.0,
    centre: tuple[float, float] = (0.5, 0.5),
    sensor: tuple[int, int] = (480, 640),
    distortion: float = 0.0,
    seed: int = 0,
    exposure: float = 0.75,
    noise: np.ndarray | None = None,
    tilt: tuple[float, float] = (0.0, 0.0),
    illumination: float = 0.15,
    read_noise: float = 2.0,
    gain: float = 2.5,
    exif: dict | None = None,
) -> dict:
    """Photograph of the published Bernoulli target (target.cells) written as an RGGB DNG.

    Geometry: cells -> sensor by a homography (scale, rotation, perspective
    ``tilt``) followed by radial distortion; the camera -> pattern map D of
    IJCV 2012 sec. 2 is its inverse. Light: a smooth field falling by
    ``illumination`` (relative) from the centre to the corners, plus a
    left-right gradient of half that.

    Parameters
    ----------
    path : path-like
        DNG to write.
    psf : ndarray or dict
        Kernel(s) on the s-grid of the channel planes (one or per channel).
    s : int
    pixels_per_cell : float
        Channel pixels per target cell (1/t in IJCV 2012 sec. 3.3; s/t = s * pixels_per_cell).
    rotation_deg : float
    centre : (float, float)
        Normalised sensor (x, y) of the target centre.
    sensor : (int, int)
        Sensor (rows, cols).
    distortion : float
        Radial coefficient k1: r_undistorted = r_distorted (1 + k1 r^2), r
        normalised by the sensor half-diagonal.
    seed : int
        Noise seed.
    exposure : float
        Fraction of the raw range reached by white (> 1 saturates it).
    noise : ndarray (256, 256), optional
        Noise cells; the published pattern by default.
    tilt : (float, float)
        Perspective, see `target_homography`.
    illumination : float
        Relative fall-off of the light field.
    exif : dict, optional
        Exposure metadata for the DNG (see `raw.write_dng`).

    Returns
    -------
    dict: everything `simulate_scene` returns plus ``noise``, ``homography``
    (cells -> undistorted sensor), ``distortion``, ``to_pattern`` and
    ``to_image`` (per channel: channel plane <-> cell coordinates),
    ``corners`` (per channel: (12, 2) X-corners in channel coordinates, in
    target.XCORNER_BLOCKS order), ``pixels_per_cell`` and ``light`` (the
    light field ``f(x, y)`` at normalised sensor coordinates).
    """
    noise = target.default_noise() if noise is None else np.asarray(noise, dtype=np.float64)
    rows, cols = sensor
    hom = target_homography(
        pixels_per_cell=pixels_per_cell, rotation_deg=rotation_deg, centre=centre, sensor=sensor, tilt=tilt
    )
    inv = np.linalg.inv(hom)
    c0 = np.array([(cols - 1) / 2, (rows - 1) / 2])
    norm = float(np.hypot(*c0))

    def undistort(x, y):
        r2 = ((x - c0[0]) ** 2 + (y - c0[1]) ** 2) / norm**2
        f = 1.0 + distortion * r2
        return c0[0] + (x - c0[0]) * f, c0[1] + (y - c0[1]) * f

    def sensor_to_cells(x, y):
        xu, yu = undistort(np.asarray(x, np.float64), np.asarray(y, np.float64))
        w = inv[2, 0] * xu + inv[2, 1] * yu + inv[2, 2]
        return (inv[0, 0] * xu + inv[0, 1] * yu + inv[0, 2]) / w, (inv[1, 0] * xu + inv[1, 1] * yu + inv[1, 2]) / w

    def cells_to_sensor(X, Y):
        X, Y = np.asarray(X, np.float64), np.asarray(Y, np.float64)
        w = hom[2, 0] * X + hom[2, 1] * Y + hom[2, 2]
        xu = (hom[0, 0] * X + hom[0, 1] * Y + hom[0, 2]) / w
        yu = (hom[1, 0] * X + hom[1, 1] * Y + hom[1, 2]) / w
        x, y = xu.copy(), yu.copy()
        for _ in range(30):  # invert the radial model by fixed-point iteration
            ux, uy = undistort(x, y)
            x, y = x + (xu - ux), y + (yu - uy)
        return x, y

    # Scene raster: pixel centre (i, j) is cell coordinate ((j + 0.5) / R, (i + 0.5) / R)
    scene = target.cells(noise, RASTER).astype(np.float32)

    def sensor_to_scene(x, y):
        X, Y = sensor_to_cells(x, y)
        return X * RASTER - 0.5, Y * RASTER - 0.5

    def light(xn, yn):
        r2 = ((xn - 0.5) ** 2 + (yn - 0.5) ** 2) / 0.5
        return 1.0 - illumination * r2 - 0.5 * illumination * (xn - 0.5)

    truth = simulate_scene(
        path, scene=scene, sensor_to_scene=sensor_to_scene, psf=psf, s=s, sensor=sensor, seed=seed,
        exposure=exposure, illumination=light if illumination else None, background=1.0,
        read_noise=read_noise, gain=gain, exif=exif,
    )
    to_pattern, to_image, corners = {}, {}, {}
    for name, (dy, dx) in RGGB_OFFSETS.items():
        def tp(x, y, dx=dx, dy=dy):
            return sensor_to_cells(2 * np.asarray(x, np.float64) + dx, 2 * np.asarray(y, np.float64) + dy)

        def ti(X, Y, dx=dx, dy=dy):
            x, y = cells_to_sensor(X, Y)
            return (x - dx) / 2, (y - dy) / 2

        to_pattern[name], to_image[name] = tp, ti
        pts = target.xcorner_points()
        corners[name] = np.stack(ti(pts[:, 0], pts[:, 1]), axis=1)
    truth.update(
        noise=noise, homography=hom, distortion=distortion, to_pattern=to_pattern, to_image=to_image,
        corners=corners, pixels_per_cell=pixels_per_cell, light=light,
    )
    return truth


# --------------------------------------------------------------------------- near/far pairs


def texture_scene(shape: tuple[int, int], seed: int = 0, slope: float = 0.75, contrast: float = 0.18) -> np.ndarray:
    """A multi-scale noise texture: white noise shaped to a 1/f**slope amplitude spectrum.

    The two-photo papers advise textures with elements of many sizes: SIFT
    matches the coarse ones, the fine ones condition the kernel estimate
    (SIAM J. Imaging Sci. 2012, sec. 5.6). Reflectance mean 0.5, RMS ``contrast``,
    clipped to [0.02, 0.98].
    """
    rng = np.random.default_rng(seed)
    spec = fft.rfft2(rng.standard_normal(shape))
    fy = fft.fftfreq(shape[0])[:, None]
    fx = fft.rfftfreq(shape[1])[None, :]
    f = np.maximum(np.hypot(fx, fy), 1.0 / max(shape))
    tex = fft.irfft2(spec / f**slope, s=shape)
    tex = (tex - tex.mean()) / tex.std()
    return np.clip(0.5 + contrast * tex, 0.02, 0.98)


def simulate_pair(
    *,
    psf: np.ndarray,
    s: int,
    lam: float,
    near_shape: tuple[int, int] = (384, 384),
    far_shape: tuple[int, int] = (128, 128),
    raster_per_pixel: float = 2.0,
    rotation_deg: float = 0.0,
    offset: tuple[float, float] = (0.0, 0.0),
    scene: np.ndarray | None = None,
    seed: int = 0,
    exposure: float = 0.75,
    noise: bool = True,
) -> dict:
    """Two channel planes of one textured plane seen from distances in ratio ``lam`` through ``psf``.

    The near plane sees the scene at ``raster_per_pixel`` raster pixels per
    channel pixel, the far plane ``lam`` times coarser, rotated by
    ``rotation_deg`` and displaced by ``offset`` near pixels; both are rendered
    by `render_plane` with the same kernel, the model of the two-photo papers
    (SIAM J. Imaging Sci. 2012, sec. 3.1: v_i = S_1(H_{lambda_i} u * h) + n_i).

    Returns
    -------
    dict with ``near`` and ``far`` (raw.Frame, black-subtracted), ``psf``, ``s``,
    ``lam`` and ``to_near`` (3 x 3 homography, far plane -> near plane).
    """
    rp = float(raster_per_pixel)
    theta = np.radians(rotation_deg)
    if scene is None:
        side = int(np.ceil(rp * lam * max(far_shape))) + 32  # the far view; beyond it, background
        scene = texture_scene((side, side), seed=seed)
    scy, scx = (scene.shape[0] - 1) / 2, (scene.shape[1] - 1) / 2
    ncy, ncx = (near_shape[0] - 1) / 2, (near_shape[1] - 1) / 2
    fcy, fcx = (far_shape[0] - 1) / 2, (far_shape[1] - 1) / 2
    c, si = np.cos(theta), np.sin(theta)
    # far plane -> near plane: zoom by lam, rotation, offset (a similarity, exactly a homography)
    to_near = np.array(
        [
            [lam * c, -lam * si, ncx + offset[0] - lam * (c * fcx - si * fcy)],
            [lam * si, lam * c, ncy + offset[1] - lam * (si * fcx + c * fcy)],
            [0.0, 0.0, 1.0],
        ]
    )

    def near_to_scene(x, y):
        return scx + rp * (np.asarray(x) - ncx), scy + rp * (np.asarray(y) - ncy)

    def far_to_scene(x, y):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        return near_to_scene(to_near[0, 0] * x + to_near[0, 1] * y + to_near[0, 2],
                             to_near[1, 0] * x + to_near[1, 1] * y + to_near[1, 2])

    rng = np.random.default_rng(seed + 1)
    black, white = 512, 16383
    frames = {}
    for name, to_scene, shape in (("near", near_to_scene, near_shape), ("far", far_to_scene, far_shape)):
        ideal = render_plane(scene, to_scene, shape, psf, s)
        if noise:
            values = expose(ideal, black=black, white=white, exposure=exposure, rng=rng)
        else:
            values = black + ideal * exposure * (white - black)
        frames[name] = raw.Frame(
            data=values - black,
            channel=raw.MONO,
            white=float(white - black),
            saturated=values >= white,
            source=f"simulated-{name}",
            offset=(0, 0),
            sensor_shape=tuple(shape),
        )
    return {"near": frames["near"], "far": frames["far"], "psf": np.asarray(psf, np.float64), "s": s,
            "lam": lam, "to_near": to_near}
