"""An independent physical renderer of photographs of the Bernoulli target, for tests only.

It shares nothing with the estimator's model of image formation: no call into
psfd's resampling, DCT, Keys interpolation, simulator or registration. The
target is drawn from its vector description (DESIGN.md, "The published target
layout"; the noise values are read from the published PGM by this module's own
parser), the blur is a continuous kernel applied by its analytic transfer
function, and the camera adds illumination, shot and read noise and an ADC.
`wall_pair` photographs a painted wall with glints from two distances through
the same blur and sensor, for the two-photo method.

Image formation (Delbracio et al., IJCV 2012, sec. 2, model (M'), with a linear
sensor g)::

    v(m) = ADC( Poisson(E * [(L . r o D) * h](m)) + read noise ),

- r: printed reflectance in pattern cells (black ink, white paper, the board
  around the target, a grey background), piecewise constant with straight
  edges;
- D: camera -> pattern map, the inverse of a homography H (pattern -> camera)
  made of a scale of ``pixels_per_cell``, a rotation (any angle) and a small
  perspective (`View`);
- L: illumination, a quadratic surface in plane coordinates, multiplying the
  reflectance before the blur, as light falls on the print;
- h = h_optics * 1_C: the continuous PSF in channel pixels, the optics
  (Gaussian, rotated anisotropic Gaussian, circular-pupil diffraction, a
  defocus disc with diffraction) convolved with the photosite aperture C, a
  box of ``aperture`` channel pixels (0.5 by default: one sensor pitch with
  full fill factor, a Bayer plane's pitch being two sensor pitches);
- m: pixel centres of the channel plane at integer coordinates (x = column,
  y = row); S_1 point-samples the blurred irradiance there (the pixel
  integration is inside h, IJCV 2012 sec. 2: h_sensor = 1_C).

Rendering (`blur`): the scene L . r o D is sampled at ``samples`` >= 32
samples per channel pixel along both axes, each sample the exact mean of the
scene over its 1/32-pixel square (`reflectance`: the share of each cell
from the square's footprint; every cell edge is resolved, not moved to the
next sample, which upright would shift every edge by up to 1/64 pixel in a
periodic pattern), Fourier transformed strip by strip keeping only the
frequencies the kernel passes, divided by the square's transfer function,
multiplied by the kernel's analytic transfer function ĥ (no sampled kernel
is ever convolved), and evaluated at the pixel centres by folding the
spectrum onto the plane's own frequency grid. Memory stays at a few tens of
MB for any plane: the fine raster exists one strip at a time.

The truth
---------
``Kernel.sampled(s, size)`` is the continuous kernel point-sampled on the
s-times grid, h(k / s) / s^2 for integer offsets k from the kernel's centre
(sample k at k / s channel pixels), the s^2 being the Riemann weight of one
s-grid cell (IJCV 2012 sec. 3.1, Lemma 1: the discrete kernel is S_s h). It
is computed exactly from ĥ (the samples' DFT is ĥ periodised with period s,
`Kernel.periodised_otf`) and sums to 1 over the whole grid (Poisson summation;
ĥ(s n) = 0 for n != 0 for every kernel here).

The estimator describes the same object, pixel box included: its u~_D is the
point-sampled pattern (bernoulli.u_tilde_d samples D at i / s, no box) and
S_1 a point sampling (IJCV 2012, sec. 2), and its kernel is centred on the
pixel centre, as here. Two differences are inherent in the model, and the
comparison (`support_truth`, `compare`) follows them:

- u~_D = S_s LPF_s u_D is band-limited to |f| < s/2 cycles per pixel, so least
  squares estimates the samples of the band-limited kernel LPF_s h, whose DFT
  is ĥ itself on the band, not its periodised copy: the data's components
  beyond the band are uncorrelated with the band-limited regressors and act
  as noise. The two differ by the aliasing of ĥ across s/2, `Kernel.aliasing`:
  0.011 for diffraction at f/5.6 through a half-pixel photosite (ĥ reaches
  2.8 cycles per pixel), below 0.001 for the other kinds.
- An estimate has a finite support of k x k samples. The part of the kernel
  beyond it adds to the data its mean (its mass times the pattern's mean)
  and a zero-mean part uncorrelated with the regressors; on the Bernoulli
  pattern, whose Gram matrix is M (sigma^2 I + m^2 1 1^T) (IJCV 2012 sec.
  3.2), least squares explains the mean by a uniform pedestal of
  `Kernel.outside` / k^2 per sample, so the estimate keeps unit mass.

So an estimate is compared with the band-limited samples on its support plus
that pedestal, normalised to unit sum as estimates are; noise-free renders
with the true map match it to 0.001-0.003 in MTF when the mass beyond the
support is below 1 %, and to about a quarter of that mass otherwise
(diffraction: 0.008 at f/5.6, 0.016 at f/22), the pedestal being only its mean. `compare` also reports the
error against |ĥ| over the band (``max_continuous``), which adds what the
support cannot hold: up to 0.02-0.06 at the lowest frequencies for
diffraction, whose mass beyond a 17 x 17 or 25 x 25 support is 3-8 %.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import fft, special

from psfd.estimator.raw import Frame

# --------------------------------------------------------------------------- kernels

OTF = Callable[[np.ndarray, np.ndarray], np.ndarray]
TINY = 1e-12  # |OTF| below this counts as zero when choosing the band to render


@dataclass(frozen=True)
class Kernel:
    """A continuous PSF in channel pixels: optics convolved with the photosite box.

    Attributes
    ----------
    name : str
    optics : callable (fx, fy) -> ndarray
        Transfer function of the optics alone, frequencies in cycles per channel pixel.
    cutoff : float
        |optics| < TINY for |f| beyond this (cycles per channel pixel).
    aperture : float
        Side of the photosite box in channel pixels.
    """

    name: str
    optics: OTF
    cutoff: float
    aperture: float = 0.5

    def otf(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """ĥ(fx, fy) = optics(f) sinc(a fx) sinc(a fy), with ĥ(0) = 1."""
        return self.optics(fx, fy) * np.sinc(self.aperture * fx) * np.sinc(self.aperture * fy)

    def mtf(self, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
        """|ĥ|, the continuous MTF (``max_continuous`` of `compare`)."""
        return np.abs(self.otf(fx, fy))

    def periodised_otf(self, fx: np.ndarray, fy: np.ndarray, s: int) -> np.ndarray:
        """sum_n ĥ(f + s n): the transfer function of the point samples on the s-grid."""
        reach = int(math.ceil(self.cutoff / s))
        out = np.zeros(np.broadcast(fx, fy).shape, dtype=np.complex128)
        for a in range(-reach, reach + 1):
            for b in range(-reach, reach + 1):
                out += self.otf(fx + a * s, fy + b * s)
        return out

    def sampled(self, s: int, size: int, period: int = 128, bandlimited: bool = False) -> np.ndarray:
        """The truth: h(k / s) / s^2 on a ``size`` x ``size`` grid centred on k = 0.

        Exact up to the wrap-around of tails beyond ``period`` channel pixels:
        the inverse DFT of the periodised ĥ on a grid of step 1 / period.
        ``bandlimited``: the samples of LPF_s h instead, whose DFT is ĥ itself
        on |f| < s/2 (what least squares estimates, see the module docstring).
        """
        if size % 2 == 0 or size > period * s:
            raise ValueError("size must be odd and smaller than the period")
        n = period * s
        f = np.fft.fftfreq(n, d=1.0 / s)  # cycles per channel pixel, step 1 / period
        if bandlimited:
            spectrum = self.otf(f[None, :], f[:, None]).astype(np.complex128)
        else:
            spectrum = self.periodised_otf(f[None, :], f[:, None], s)
        h = np.fft.fftshift(np.real(np.fft.ifft2(spectrum)))
        c, half = n // 2, size // 2
        return h[c - half : c + half + 1, c - half : c + half + 1]

    def outside(self, s: int, support: int) -> float:
        """Mass of the kernel beyond a ``support`` x ``support`` window of the s-grid."""
        return float(1.0 - self.sampled(s, support).sum())

    def aliasing(self, s: int, n: int = 65) -> float:
        """max | |periodised ĥ| - |ĥ| | over the s-band: how far the point samples' MTF is from |ĥ|."""
        f = np.linspace(-s / 2, s / 2, n)
        fx, fy = np.meshgrid(f, f)
        return float(np.abs(np.abs(self.periodised_otf(fx, fy, s)) - self.mtf(fx, fy)).max())


def gaussian(sigma: float, sigma_y: float | None = None, theta_deg: float = 0.0, aperture: float = 0.5,
             name: str | None = None) -> Kernel:
    """Gaussian optics of standard deviations ``sigma`` (along its axis turned by ``theta_deg``) and ``sigma_y``."""
    sy = sigma if sigma_y is None else sigma_y
    t = math.radians(theta_deg)

    def optics(fx, fy):
        fu = math.cos(t) * fx + math.sin(t) * fy
        fv = -math.sin(t) * fx + math.cos(t) * fy
        return np.exp(-2.0 * math.pi**2 * ((sigma * fu) ** 2 + (sy * fv) ** 2))

    cutoff = math.sqrt(math.log(1 / TINY) / (2 * math.pi**2)) / min(sigma, sy)
    return Kernel(name or f"gaussian {sigma:g}x{sy:g}@{theta_deg:g}", optics, cutoff, aperture)


def two_lobes(sigma: float = 0.3, weight: float = 0.4, offset: tuple[float, float] = (1.2, 0.5),
              aperture: float = 0.5) -> Kernel:
    """A Gaussian lobe with a second one, of ``weight`` of the light, ``offset`` (x, y) channel pixels away.

    Not symmetric under a half turn, a transposition or a mirror, as every other kernel here is: only such a
    kernel shows whether an estimate is the PSF or its flipped copy (a correlation kernel, a convolution turned
    round). The second lobe's shift is the phase ramp exp(-2 pi i f . offset) of its transfer function.
    """
    lobe = gaussian(sigma, aperture=aperture)
    dx, dy = offset

    def optics(fx, fy):
        return lobe.optics(fx, fy) * ((1.0 - weight) + weight * np.exp(-2j * math.pi * (fx * dx + fy * dy)))

    return Kernel(f"two lobes {sigma:g}, {weight:g} at ({dx:g}, {dy:g})", optics, lobe.cutoff, aperture)


def _pupil_otf(fc: float) -> OTF:
    """Incoherent circular-pupil transfer function, cut-off ``fc`` cycles per pixel (Goodman, Fourier Optics, 6.3)."""

    def optics(fx, fy):
        nu = np.minimum(np.hypot(fx, fy) / fc, 1.0)
        return (2.0 / math.pi) * (np.arccos(nu) - nu * np.sqrt(1.0 - nu * nu))

    return optics


def airy(fnumber: float, wavelength_um: float = 0.55, pitch_um: float = 8.6, aperture: float = 0.5) -> Kernel:
    """Diffraction-limited circular pupil at ``fnumber``; ``pitch_um`` is the channel plane's pitch.

    The cut-off is 1 / (lambda N) cycles per um, pitch / (lambda N) cycles per channel pixel
    (2.79 at f/5.6 for 0.55 um and 2 x 4.3 um).
    """
    fc = pitch_um / (wavelength_um * fnumber)
    return Kernel(f"airy f/{fnumber:g}", _pupil_otf(fc), fc, aperture)


def defocus(radius: float, fnumber: float = 5.6, wavelength_um: float = 0.55, pitch_um: float = 8.6,
            aperture: float = 0.5) -> Kernel:
    """A geometric defocus disc of ``radius`` channel pixels through a diffraction-limited pupil.

    The disc's transfer function is 2 J1(2 pi R f) / (2 pi R f); the pupil's band limit keeps the product finite.
    """
    fc = pitch_um / (wavelength_um * fnumber)
    pupil = _pupil_otf(fc)

    def optics(fx, fy):
        x = 2.0 * math.pi * radius * np.hypot(fx, fy)
        disc = np.where(x > 1e-9, 2.0 * special.j1(x) / np.where(x > 1e-9, x, 1.0), 1.0)
        return disc * pupil(fx, fy)

    return Kernel(f"defocus r{radius:g} f/{fnumber:g}", optics, fc, aperture)


# The render kinds of the accuracy tests (a 2 x 4.3 um Bayer plane at 0.55 um for diffraction).
KINDS: dict[str, Kernel] = {
    "gaussian": gaussian(0.45),
    "anisotropic": gaussian(0.7, 0.35, theta_deg=30.0),
    "airy-f5.6": airy(5.6),
    "airy-f11": airy(11.0),
    "airy-f22": airy(22.0),
    "defocus": defocus(0.6),
}


# --------------------------------------------------------------------------- the printed target

# DESIGN.md, "The published target layout": a 10 x 10 grid of 32-cell blocks, the
# noise in blocks 1..8, and the marks of the border ring (x right, y down).
BLOCK = 32
TARGET = 10 * BLOCK
NOISE_START, NOISE_STOP = BLOCK, 9 * BLOCK
XCORNERS = ((9, 9), (9, 6), (9, 3), (9, 0), (6, 0), (3, 0), (0, 0), (0, 3), (0, 6), (0, 9), (3, 9), (6, 9))
BLACKS = ((9, 8), (9, 5), (9, 2), (8, 0), (5, 0), (2, 0), (0, 2), (0, 5), (0, 8), (2, 9), (5, 9), (8, 9))
WHITES = ((9, 7), (9, 4), (9, 1), (7, 0), (4, 0), (1, 0), (0, 1), (0, 4), (0, 7), (1, 9), (4, 9), (7, 9))
PATTERN = Path(__file__).resolve().parents[1] / "psfd" / "data" / "pattern_noise.pgm"


def read_pgm(path: str | Path) -> np.ndarray:
    """An 8- or 16-bit binary PGM (P5) as an integer array, by the format's definition (netpbm pgm(5))."""
    data = Path(path).read_bytes()
    fields, pos = [], 0
    while len(fields) < 4:  # magic, width, height, maxval, separated by whitespace and comments
        while data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.index(b"\n", pos) + 1
            continue
        end = pos
        while not data[end : end + 1].isspace():
            end += 1
        fields.append(data[pos:end])
        pos = end
    if fields[0] != b"P5":
        raise ValueError(f"{path}: not a binary PGM")
    width, height, maxval = (int(v) for v in fields[1:])
    dtype = np.dtype(">u2") if maxval > 255 else np.dtype("u1")
    pixels = np.frombuffer(data, dtype=dtype, count=width * height, offset=pos + 1)
    return pixels.reshape(height, width).astype(np.int64)


def published_noise() -> np.ndarray:
    """The published 256 x 256 noise cells, 1 white and 0 black."""
    return (read_pgm(PATTERN) > 127).astype(np.float64)


@dataclass(frozen=True)
class Print:
    """Reflectances of the print and its surroundings; the board is white paper around the target."""

    black: float = 0.04
    white: float = 0.80
    board: int = 24  # cells of white paper beyond the target on each side
    background: float = 0.25


def reflectance(X: np.ndarray, Y: np.ndarray, noise: np.ndarray, paper: Print = Print(),
                table: np.ndarray | None = None, footprint: np.ndarray | None = None) -> np.ndarray:
    """Reflectance at pattern coordinates (X, Y) in cells (cell (i, j) covers [i, i+1) x [j, j+1)).

    With ``footprint`` J (2 x 2, cells per unit of (p, q)), the mean over the
    parallelogram (X, Y) + J (p, q), |p|, |q| <= 1/2, instead of the value at
    the point: the share of each cell is the product of the shares along X and
    along Y (`_below`), exact for an upright J and for a footprint crossing one
    cell edge; across the diagonal edges of the X-corner marks, the share on
    each side of the diagonal.
    ``table``: `_cell_table` of ``noise`` and ``paper``, to build it once per render.
    """
    table = _cell_table(noise, paper) if table is None else table
    X, Y = np.broadcast_arrays(X, Y)
    i0, j0 = np.floor(X).astype(np.int32), np.floor(Y).astype(np.int32)
    value = _cell(table, paper, i0, j0, X, Y, footprint)
    if footprint is None:
        return value
    footprint = np.asarray(footprint, dtype=np.float64)
    (jxx, jxy), (jyx, jyy) = np.abs(footprint) / 2
    reach_x, reach_y = jxx + jxy, jyx + jyy
    if reach_x >= 0.5 or reach_y >= 0.5:
        raise ValueError("the footprint must be smaller than half a cell")
    fx, fy = X - i0, Y - j0  # position inside the cell, [0, 1)
    near = np.flatnonzero((fx < reach_x) | (fx > 1 - reach_x) | (fy < reach_y) | (fy > 1 - reach_y))
    i, j, x, y, fx, fy = (a.ravel()[near] for a in (i0, j0, X, Y, fx, fy))
    # shares of the neighbouring column (left or right) and row (above or below)
    left, right = _below(-fx, jxx, jxy), 1.0 - _below(1.0 - fx, jxx, jxy)
    up, down = _below(-fy, jyx, jyy), 1.0 - _below(1.0 - fy, jyx, jyy)
    u, v = left + right, up + down
    sx, sy = np.where(right > 0, 1, -1).astype(np.int32), np.where(down > 0, 1, -1).astype(np.int32)
    out = value.ravel()  # a copy: broadcast inputs may share memory
    out[near] = ((1 - u) * (1 - v) * out[near] + u * (1 - v) * _cell(table, paper, i + sx, j, x, y, footprint)
                 + (1 - u) * v * _cell(table, paper, i, j + sy, x, y, footprint)
                 + u * v * _cell(table, paper, i + sx, j + sy, x, y, footprint))
    return out.reshape(value.shape)


def _below(d: np.ndarray, a, b) -> np.ndarray:
    """P(a u + b v < d) for u, v uniform on [-1, 1]: the share of a footprint of half-extents
    a and b (along one pattern axis) below an edge at distance d from its centre (a trapezoid CDF)."""
    big, small = np.maximum(np.maximum(a, b), 1e-12), np.minimum(a, b)
    reach, flat = big + small, big - small
    d = np.asarray(d, dtype=np.float32)
    out = np.minimum(np.maximum(0.5 + d / (2 * big), 0.0), 1.0)
    # the quadratic ends of the trapezoid (none when one extent is 0)
    corner = 8 * big * np.maximum(small, 1e-30)
    out = np.where(d < -flat, np.maximum(d + reach, 0.0) ** 2 / corner, out)
    out = np.where(d > flat, 1.0 - np.maximum(reach - d, 0.0) ** 2 / corner, out)
    return out.astype(np.float32)


def _cell(table: np.ndarray, paper: Print, i: np.ndarray, j: np.ndarray, X: np.ndarray, Y: np.ndarray,
          footprint: np.ndarray | None = None) -> np.ndarray:
    """Reflectance of cell (i, j); in an X-corner block, of the hourglass at (X, Y) brought into that cell,
    averaged over ``footprint`` (see `reflectance`) across the diagonal edge."""
    size = table.shape[0] - 1  # the last row and column hold the background (`_cell_table`)
    ti, tj = i + paper.board, j + paper.board
    outside = (ti < 0) | (ti >= size) | (tj < 0) | (tj >= size)
    value = table[np.where(outside, size, tj), np.where(outside, size, ti)]
    mark = np.isnan(value)
    if mark.any():
        # X-corner: an hourglass, black where |dy| > |dx| from the block centre (triangles on the top and
        # bottom edges); across its diagonal edges the footprint's share on the black side, as in `reflectance`
        im, jm = i[mark], j[mark]
        dx = np.minimum(np.maximum(X[mark], im), im + 0.999) - (BLOCK * np.floor(im / BLOCK) + BLOCK / 2)
        dy = np.minimum(np.maximum(Y[mark], jm), jm + 0.999) - (BLOCK * np.floor(jm / BLOCK) + BLOCK / 2)
        above = np.abs(dy) - np.abs(dx)  # > 0 on the black side
        if footprint is None:
            black = (above > 0).astype(np.float32)
        else:
            (jxx, jxy), (jyx, jyy) = footprint
            sx, sy = np.sign(dx), np.sign(dy)  # gradient of |dy| - |dx| is (-sx, sy)
            black = 1.0 - _below(-above, np.abs(sy * jyx - sx * jxx) / 2, np.abs(sy * jyy - sx * jxy) / 2)
        value[mark] = paper.white + (paper.black - paper.white) * black
    return value


def _cell_table(noise: np.ndarray, paper: Print) -> np.ndarray:
    """Reflectance of every cell of the board (the target and ``paper.board`` cells around it), NaN in
    X-corner blocks, and one more row and column for the background."""
    table = np.full((TARGET + 2 * paper.board + 1,) * 2, paper.white, dtype=np.float32)
    table[-1, :] = table[:, -1] = paper.background  # what lies beyond the board
    target = table[paper.board : paper.board + TARGET, paper.board : paper.board + TARGET]
    target[NOISE_START:NOISE_STOP, NOISE_START:NOISE_STOP] = paper.black + (paper.white - paper.black) * noise
    for blocks, value in ((BLACKS, paper.black), (XCORNERS, np.nan)):
        for bx, by in blocks:
            target[BLOCK * by : BLOCK * (by + 1), BLOCK * bx : BLOCK * (bx + 1)] = value
    return table


# --------------------------------------------------------------------------- geometry and light


@dataclass(frozen=True)
class View:
    """Pattern -> camera homography: scale, rotation, perspective, position.

    ``tilt`` (tx, ty): the local scale falls by the fraction tx (ty) from the
    target's centre to its right (bottom) edge, as a plane turned away from the
    camera; ``centre``: plane coordinates of the target centre (None: the plane's centre).
    """

    pixels_per_cell: float = 0.37
    rotation_deg: float = 0.0
    tilt: tuple[float, float] = (0.0, 0.0)
    centre: tuple[float, float] | None = None

    def homography(self, shape: tuple[int, int]) -> np.ndarray:
        rows, cols = shape
        cx, cy = ((cols - 1) / 2, (rows - 1) / 2) if self.centre is None else self.centre
        a = math.radians(self.rotation_deg)
        p = self.pixels_per_cell
        half = TARGET / 2
        to_centre = np.array([[1.0, 0.0, -half], [0.0, 1.0, -half], [0.0, 0.0, 1.0]])
        perspective = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [self.tilt[0] / half, self.tilt[1] / half, 1.0]])
        similarity = np.array([[p * math.cos(a), -p * math.sin(a), cx], [p * math.sin(a), p * math.cos(a), cy],
                               [0.0, 0.0, 1.0]])
        return similarity @ perspective @ to_centre


def _apply(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The homography ``h`` at (x, y), in the inputs' precision (float32 for the fine raster)."""
    x, y = np.asarray(x), np.asarray(y)
    (a, b, c), (d, e, f), (g, k, m) = h.tolist()
    w = g * x + k * y + m
    return (a * x + b * y + c) / w, (d * x + e * y + f) / w


@dataclass(frozen=True)
class Light:
    """Illumination 1 + c . (u, v, u^2, u v, v^2), u and v the plane coordinates scaled to [-1, 1]."""

    coefficients: tuple[float, ...] = (0.06, -0.04, -0.10, 0.03, -0.06)

    def field(self, shape: tuple[int, int]) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        rows, cols = shape
        c = self.coefficients

        def light(x, y):
            u, v = (2 * x - (cols - 1)) / cols, (2 * y - (rows - 1)) / rows
            return 1.0 + c[0] * u + c[1] * v + c[2] * u * u + c[3] * u * v + c[4] * v * v

        return light


@dataclass(frozen=True)
class Exposure:
    """Sensor: photoelectrons at reflectance 1 under light 1, read noise, ADC gain and levels (14-bit).

    5000 e- puts the noise of the normalised mid-grey at about 1.2 % of the
    black-to-white range, the level of the published photograph (the LS
    residual of img_example.pgm is 1.6 %, model errors included).
    """

    electrons: float = 5000.0
    read_noise: float = 4.0  # e- RMS
    gain: float | None = None  # DN per e-; None: reflectance 1 at 60 % of the ADC range
    black_level: int = 512
    white_level: int = 16383

    @property
    def dn_per_electron(self) -> float:
        if self.gain is not None:
            return self.gain
        return 0.6 * (self.white_level - self.black_level) / self.electrons


# --------------------------------------------------------------------------- rendering


def blur(scene: Callable[[np.ndarray, np.ndarray, float], np.ndarray], shape: tuple[int, int], kernel: Kernel,
         samples: int = 32, margin: int = 16, strip_samples: int = 1 << 21) -> np.ndarray:
    """(scene * h) at the pixel centres (x = column, y = row) of a ``shape`` plane.

    Parameters
    ----------
    scene : callable (x, y, pixel) -> ndarray
        Mean irradiance over the square of side ``pixel`` centred on plane
        coordinates (x, y); called on broadcastable row (1, n) and column (m, 1) arrays.
    shape : (rows, cols)
    kernel : Kernel
    samples : int
        Samples of the scene per pixel along each axis (>= 32).
    margin : int
        Pixels rendered beyond each side and dropped: the Fourier evaluation is
        periodic, and the margin keeps the wrap-around of the kernel's tails off the plane.
    strip_samples : int
        Fine samples per strip (memory).

    Notes
    -----
    With R = ``samples`` and fine samples at x_j = (j + 1/2) / R - 1/2 - margin,
    the Fourier coefficients on the period P (plane plus margins) of the scene
    averaged over squares of side 1/R are
    G(k) = R^-2 sum_j scene(x_j) e^(-2 pi i k x_j / P); dividing by the
    square's transfer function sinc(k / (R P)) per axis leaves the scene's own.
    The blurred plane at the pixel centres is the inverse DFT of
    sum_n G(k + n P) ĥ((k + n P) / P) (folding onto the plane's frequency grid
    is the sampling at integers). Only |k| / P <= the kernel's cut-off is
    kept, so the x transform of each strip is truncated at once.
    """
    if samples < 32:
        raise ValueError("at least 32 samples per pixel")
    rows, cols = shape
    R = int(samples)
    py, px = rows + 2 * margin, cols + 2 * margin  # periods, pixels
    ny, nx = py * R, px * R
    cutoff = min(kernel.cutoff, R / 2 - 1)
    kx, ky = int(math.ceil(cutoff * px)), int(math.ceil(cutoff * py))
    # float32 places a sample to 1e-5 pixel, far inside the 1/R raster
    xs = ((np.arange(nx) + 0.5) / R - 0.5 - margin).astype(np.float32)
    ys = ((np.arange(ny) + 0.5) / R - 0.5 - margin).astype(np.float32)
    partial = np.empty((ny, kx + 1), dtype=np.complex128)
    step = max(1, strip_samples // nx)
    for i in range(0, ny, step):
        values = np.asarray(scene(xs[None, :], ys[i : i + step, None], 1.0 / R), dtype=np.float32)
        partial[i : i + step] = fft.rfft(values, axis=1)[:, : kx + 1]
    spectrum = fft.fft(partial, axis=0)
    spectrum = np.concatenate([spectrum[ny - ky :], spectrum[: ky + 1]])  # rows k_y = -ky .. ky
    kxs, kys = np.arange(kx + 1), np.arange(-ky, ky + 1)
    offset = 0.5 / R - 0.5 - margin  # x_0 = y_0
    # phase of the sample positions, Riemann weight 1 / R and the averaging square, per axis
    spectrum *= (np.exp(-2j * np.pi * kxs * offset / px) / (R * np.sinc(kxs / (R * px))))[None, :]
    spectrum *= (np.exp(-2j * np.pi * kys * offset / py) / (R * np.sinc(kys / (R * py))))[:, None]
    full = np.zeros((2 * ky + 1, 2 * kx + 1), dtype=np.complex128)  # k_x = -kx .. kx by Hermitian symmetry
    full[:, kx:] = spectrum
    full[:, :kx] = np.conj(spectrum[::-1, :0:-1])
    fx = np.arange(-kx, kx + 1) / px
    fy = np.arange(-ky, ky + 1) / py
    full *= kernel.otf(fx[None, :], fy[:, None])
    plane = np.fft.ifft2(_fold(_fold(full, -ky, py, axis=0), -kx, px, axis=1)).real
    return plane[:rows, :cols]


def _fold(a: np.ndarray, first: int, period: int, axis: int) -> np.ndarray:
    """Sum the entries of frequency index ``first + i`` into bin ``(first + i) mod period`` along ``axis``."""
    a = np.moveaxis(a, axis, 0)
    out = np.zeros((period,) + a.shape[1:], dtype=a.dtype)
    index = (first + np.arange(a.shape[0])) % period
    for start in range(0, a.shape[0], period):  # each chunk maps to distinct bins
        chunk = slice(start, min(start + period, a.shape[0]))
        out[index[chunk]] += a[chunk]
    return np.moveaxis(out, 0, axis)


@dataclass
class Render:
    """A rendered photograph and its truth.

    Attributes
    ----------
    frame : Frame
        The channel plane as the estimator reads it (black level subtracted, DN).
    ideal : ndarray
        Noise-free blurred irradiance (reflectance x light, before the sensor).
    kernel : Kernel
        The continuous PSF (the truth, see the module docstring).
    view : View
    to_pattern, to_image : callable
        Plane (x, y) -> pattern cells (X, Y) and back.
    light : callable
        Illumination at plane coordinates.
    paper : Print
    exposure : Exposure
    """

    frame: Frame
    ideal: np.ndarray
    kernel: Kernel
    view: View
    to_pattern: Callable
    to_image: Callable
    light: Callable
    paper: Print
    exposure: Exposure
    noise: np.ndarray = field(repr=False, default=None)

    def normalised(self) -> np.ndarray:
        """The plane with the true light field divided out: black ink 0, white paper 1 (the estimator's v)."""
        rows, cols = self.frame.shape
        yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
        e = self.exposure
        scale = e.electrons * e.dn_per_electron * self.light(xx, yy)
        return (self.frame.data / scale - self.paper.black) / (self.paper.white - self.paper.black)

    def exposed(self, exposure: Exposure, seed: int = 0) -> Render:
        """The same scene and optics through another exposure (no new rendering)."""
        frame, exposure = expose(self.ideal, exposure, seed, self.frame.source)
        return dataclasses.replace(self, frame=frame, exposure=exposure)

    def flare(self) -> tuple[float, float]:
        """Light of the kernel's tails at the centres of the flat squares: (black level above 0,
        white level below 1), normalised: what a light model that takes these centres as pure black and white
        is off by (radiometry.illumination fits it)."""
        levels = []
        for blocks in (BLACKS, WHITES):
            centres = np.array([(BLOCK * bx + BLOCK / 2, BLOCK * by + BLOCK / 2) for bx, by in blocks])
            x, y = self.to_image(centres[:, 0], centres[:, 1])
            col, row = np.round(x).astype(int), np.round(y).astype(int)
            value = self.ideal[row, col] / self.light(col.astype(float), row.astype(float))
            levels.append((value - self.paper.black) / (self.paper.white - self.paper.black))
        return float(np.mean(levels[0])), float(1.0 - np.mean(levels[1]))

    def sigma(self, level: float = 0.5) -> float:
        """Standard deviation of the sensor noise at a normalised ``level``, at light 1, in normalised units."""
        e, p = self.exposure, self.paper
        electrons = e.electrons * (p.black + level * (p.white - p.black))
        variance = electrons + e.read_noise**2 + 1.0 / (12 * e.dn_per_electron**2)  # shot, read, quantisation
        return float(np.sqrt(variance) / (e.electrons * (p.white - p.black)))


def render(kernel: Kernel, view: View = View(), *, shape: tuple[int, int] | None = None, seed: int = 0,
           noise: np.ndarray | None = None, light: Light = Light(), paper: Print = Print(),
           exposure: Exposure = Exposure(), samples: int = 32, name: str = "render") -> Render:
    """A photograph of the printed target through ``kernel``, seen as ``view``.

    Parameters
    ----------
    shape : (rows, cols), optional
        Plane size; by default the turned board, 10 % and 8 pixels more.
    seed : int
        Seed of the shot and read noise.
    noise : ndarray (256, 256), optional
        Printed noise cells (the published ones by default).
    exposure : Exposure
        ``electrons=inf`` renders without noise (the ideal plane, quantised).
    """
    noise = published_noise() if noise is None else np.asarray(noise, dtype=np.float64)
    if shape is None:  # the board turned by the rotation, with room for the perspective
        a = math.radians(view.rotation_deg)
        turned = abs(math.cos(a)) + abs(math.sin(a))
        side = int(math.ceil(view.pixels_per_cell * (TARGET + 2 * paper.board) * turned * 1.1)) + 8
        shape = (side, side)
    h = view.homography(shape)
    inverse = np.linalg.inv(h)
    field_of = light.field(shape)
    table = _cell_table(noise, paper)
    # D's linear part at the target's centre: a 1/R-pixel square there covers J / R cells. Across
    # the target the footprint changes with the perspective by a few per cent of 1/R pixel.
    x0, y0 = _apply(h, np.array([TARGET / 2]), np.array([TARGET / 2]))
    X, Y = _apply(inverse, x0 + np.array([0.0, 1e-3, 0.0]), y0 + np.array([0.0, 0.0, 1e-3]))
    jacobian = np.array([[X[1] - X[0], X[2] - X[0]], [Y[1] - Y[0], Y[2] - Y[0]]]) / 1e-3

    def scene(x, y, pixel):
        X, Y = _apply(inverse, x, y)
        return reflectance(X, Y, noise, paper, table, jacobian * pixel) * field_of(x, y)

    ideal = blur(scene, shape, kernel, samples)
    frame, exposure = expose(ideal, exposure, seed, name)
    return Render(
        frame=frame, ideal=ideal, kernel=kernel, view=view,
        to_pattern=lambda x, y: _apply(inverse, x, y), to_image=lambda X, Y: _apply(h, X, Y),
        light=field_of, paper=paper, exposure=exposure, noise=noise,
    )


def edge_print(X: np.ndarray, Y: np.ndarray, squares: int = 8) -> np.ndarray:
    """Reflectance of the sharp-edge target (Joshi et al., CVPR 2008, sec. 4.2, as psfd prints it) in squares:
    a ``squares`` x ``squares`` checkerboard, square (0, 0) black, in each square a disc of radius 0.3 square
    of the other colour; white beyond the board. 0 black, 1 white."""
    ix, iy = np.floor(X), np.floor(Y)
    disc = (X - ix - 0.5) ** 2 + (Y - iy - 0.5) ** 2 < 0.3**2
    black = (((ix + iy) % 2 == 0) ^ disc) & (X >= 0) & (X < squares) & (Y >= 0) & (Y < squares)
    return np.where(black, 0.0, 1.0)


def render_edge_target(kernel: Kernel, px_per_square: float = 20.0, rotation_deg: float = 8.0, *,
                       tilt: tuple[float, float] = (0.04, -0.03), shape: tuple[int, int] = (230, 230), seed: int = 0,
                       light: Light = Light(), paper: Print = Print(), exposure: Exposure = Exposure(),
                       samples: int = 32) -> Frame:
    """A photograph of the sharp-edge target (8 x 8 squares and a white border of one square) through ``kernel``:
    `edge_target_light` through the sensor (`expose`)."""
    ideal = edge_target_light(kernel, px_per_square, rotation_deg, tilt=tilt, shape=shape, light=light, paper=paper,
                              samples=samples)
    return expose(ideal, exposure, seed, "edge target")[0]


def edge_target_light(kernel: Kernel, px_per_square: float = 20.0, rotation_deg: float = 8.0, *,
                      tilt: tuple[float, float] = (0.04, -0.03), shape: tuple[int, int] = (230, 230),
                      light: Light = Light(), paper: Print = Print(), samples: int = 32) -> np.ndarray:
    """The light the sensor of `render_edge_target` receives, before its noise (what `expose` takes).

    The same optics, light and sensor as `render`; the print is turned by
    ``rotation_deg`` about the plane's centre, with the perspective of
    `View.tilt`. The scene is the reflectance at the centre of each
    1/``samples``-pixel square rather than its mean there: an edge moves by
    up to 1/(2 ``samples``) pixel, in a direction that changes along the
    turned edges, a blur some ten times narrower than the kernels here.
    """
    rows, cols = shape
    a, p, half = math.radians(rotation_deg), px_per_square, 4.0  # the board's centre, in squares
    perspective = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [tilt[0] / half, tilt[1] / half, 1.0]])
    similarity = np.array([[p * math.cos(a), -p * math.sin(a), (cols - 1) / 2],
                           [p * math.sin(a), p * math.cos(a), (rows - 1) / 2], [0.0, 0.0, 1.0]])
    inverse = np.linalg.inv(similarity @ perspective @ np.array([[1.0, 0.0, -half], [0.0, 1.0, -half], [0, 0, 1]]))
    field_of = light.field(shape)

    def scene(x, y, pixel):
        X, Y = _apply(inverse, x.astype(np.float64), y.astype(np.float64))
        on_print = (X > -1) & (X < 9) & (Y > -1) & (Y < 9)
        r = np.where(on_print, paper.black + (paper.white - paper.black) * edge_print(X, Y), paper.background)
        return (r * field_of(x, y)).astype(np.float32)

    return blur(scene, shape, kernel, samples)


def expose(ideal: np.ndarray, exposure: Exposure, seed: int, name: str) -> tuple[Frame, Exposure]:
    """The sensor: shot noise (Poisson), read noise (Gaussian), gain, black level, 14-bit ADC and clipping.

    The same ``ideal`` exposed with other seeds gives photographs of one scene that differ only in their noise.
    """
    e = exposure
    if math.isinf(e.electrons):  # noise-free: a fixed scale, no quantisation
        e = Exposure(10000.0, 0.0, None, e.black_level, e.white_level)
        data = ideal * e.electrons * e.dn_per_electron
        saturated = np.zeros(ideal.shape, dtype=bool)
    else:
        rng = np.random.default_rng(seed)
        electrons = rng.poisson(np.maximum(ideal, 0.0) * e.electrons) + rng.normal(0.0, e.read_noise, ideal.shape)
        raw = np.clip(np.round(electrons * e.dn_per_electron) + e.black_level, 0, e.white_level)
        saturated = raw >= e.white_level
        data = raw - e.black_level
    return Frame(data.astype(np.float64), "g1", float(e.white_level - e.black_level), saturated, name), e


# --------------------------------------------------------------------------- comparing an estimate with the truth


def band(s: int, n: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Frequencies (fx, fy) of an n x n grid covering |f| <= s/2 cycles per channel pixel (s x Nyquist)."""
    f = (np.arange(n) - n // 2) * (s / n)  # includes -s/2, excludes +s/2 (the same frequency for a DFT)
    return np.meshgrid(f, f)


def kernel_mtf(psf: np.ndarray, s: int, fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """|sum_k h_k e^(-2 pi i f . k / s)| / |sum_k h_k| for a kernel centred on its middle sample."""
    rows, cols = psf.shape
    kx = np.arange(cols) - cols // 2
    ky = np.arange(rows) - rows // 2
    ex = np.exp(-2j * np.pi * fx.ravel()[:, None] * kx[None, :] / s)  # (F, cols)
    ey = np.exp(-2j * np.pi * fy.ravel()[:, None] * ky[None, :] / s)  # (F, rows)
    otf = np.einsum("fr,rc,fc->f", ey, psf, ex)
    return (np.abs(otf) / abs(psf.sum())).reshape(fx.shape)


def mtf50(psf: np.ndarray, s: int) -> np.ndarray:
    """MTF50 (cycles per channel pixel) along fx and fy (`kernel_mtf`), linear between the samples around 0.5."""
    f = np.linspace(0, s / 2, 801)
    out = []
    for fx, fy in ((f, 0 * f), (0 * f, f)):
        m = kernel_mtf(psf, s, fx, fy)
        i = int(np.argmax(m < 0.5))
        out.append(f[i - 1] + (0.5 - m[i - 1]) * (f[i] - f[i - 1]) / (m[i] - m[i - 1]) if i else np.nan)
    return np.array(out)


def rms_width(psf: np.ndarray, s: int) -> float:
    """sqrt of the second central moment of a kernel, in channel pixels."""
    rows, cols = psf.shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    total = psf.sum()
    cx, cy = (psf * x).sum() / total, (psf * y).sum() / total
    return float(np.sqrt((psf * ((x - cx) ** 2 + (y - cy) ** 2)).sum() / total) / s)


def core_width(psf: np.ndarray, s: int) -> float:
    """RMS width of a kernel within a disc of half its half-support about the centre sample, in channel pixels.

    The full second moment weighs each sample by its squared distance, up to
    2 ((k - 1) / 2)^2 in the corners: there a few thousandths of mass, the
    positive half of the tail noise a non-negative solution keeps, change it
    by several per cent. The core's moment does not see them.
    """
    rows, cols = psf.shape
    y, x = np.mgrid[0:rows, 0:cols].astype(np.float64)
    r2 = (x - cols // 2) ** 2 + (y - rows // 2) ** 2
    core = r2 <= ((min(rows, cols) - 1) / 4) ** 2
    return float(np.sqrt((psf * r2)[core].sum() / psf[core].sum()) / s)


def support_truth(kernel: Kernel, s: int, support: int) -> np.ndarray:
    """What an estimate on a ``support`` x ``support`` grid describes: the band-limited samples
    there plus the mass beyond the support as a uniform pedestal (see the module docstring)."""
    sampled = kernel.sampled(s, support, bandlimited=True)
    return sampled + (1.0 - sampled.sum()) / sampled.size


@dataclass
class Errors:
    """How an estimate compares with the truth over the s-band |fx|, |fy| <= s/2 (s x Nyquist).

    ``max_mtf``: max |MTF error| along the fx and fy axes (the papers' MTF
    profiles); ``max_mtf_2d``: over the whole band; ``mean_signed``: mean
    MTF error where the true MTF exceeds 0.05 (negative: too wide); all three
    against `support_truth`. ``width_ratio``: RMS width over that of
    `support_truth`. ``max_continuous``: max |MTF error| over the band
    against |ĥ| itself (adds what the support cannot hold, see `Kernel.outside`).
    ``core_width_ratio``: `core_width` over the truth's (the core's width, blind to the outermost samples).
    """

    max_mtf: float
    max_mtf_2d: float
    mean_signed: float
    width_ratio: float
    max_continuous: float
    core_width_ratio: float = float("nan")

    def __str__(self) -> str:
        return (f"max {self.max_mtf:.4f} (2-D {self.max_mtf_2d:.4f})  signed {self.mean_signed:+.4f}  "
                f"width {self.width_ratio:.3f} (core {self.core_width_ratio:.3f})  "
                f"continuous {self.max_continuous:.4f}")


def compare(psf: np.ndarray, kernel: Kernel, s: int) -> Errors:
    """Errors of an estimated kernel (on the s-grid, centred on its middle sample) against the truth."""
    best = support_truth(kernel, s, psf.shape[0])
    axis = np.linspace(0.0, s / 2, 129)
    zero = np.zeros_like(axis)
    profiles = [kernel_mtf(psf, s, fx, fy) - kernel_mtf(best, s, fx, fy) for fx, fy in ((axis, zero), (zero, axis))]
    fx, fy = band(s)
    estimate, truth = kernel_mtf(psf, s, fx, fy), kernel_mtf(best, s, fx, fy)
    error = estimate - truth
    return Errors(
        max_mtf=float(max(np.abs(p).max() for p in profiles)),
        max_mtf_2d=float(np.abs(error).max()),
        mean_signed=float(error[truth > 0.05].mean()),
        width_ratio=rms_width(psf, s) / rms_width(best, s),
        max_continuous=float(np.abs(estimate - kernel.mtf(fx, fy)).max()),
        core_width_ratio=core_width(psf, s) / core_width(best, s),
    )


# --------------------------------------------------------------------------- a painted wall at two distances


def wall(side: float, seed: int, glints: float = 0.0, density: int = 6) -> np.ndarray:
    """Radiance (1 = white paint in unit light) of a square wall ``side`` near pixels wide, as a raster of
    ``density`` cells per near pixel, each cell of constant radiance.

    Dead leaves: occluding discs of grey 0.05-0.6 with radii of density r^-3 from 0.5 to 60 near pixels
    (a scale-invariant texture, as of natural surfaces), a 10 % grain per cell, and ``glints`` glints per
    1000 near pixels^2: discs of 0.15-0.8 near pixel radius, 3 to 60 times white (both log-uniform), most
    of them clipped in a near photo and the largest in a far one too. A glint is a bright speck of the
    surface (mica, a drop of varnish), seen in both photos where it lies, unlike a mirror reflection,
    which moves with the viewpoint.
    """
    rng = np.random.default_rng(seed)
    n = int(math.ceil(side * density))
    canvas = np.full((n, n), 0.3, dtype=np.float32)
    # discs drawn at 1/16 cell (cv2's fixed-point shift of 4 bits)
    lo, hi = 0.5 * density, 60.0 * density
    count = int(2.0 * n * n / (2.0 * math.pi * lo**2 * math.log(hi / lo)))  # covered twice on average
    radii = lo / np.sqrt(1.0 - rng.random(count) * (1.0 - (lo / hi) ** 2))  # inverse CDF of r^-3 on [lo, hi]
    for x, y, r, v in zip(rng.uniform(0, n, count), rng.uniform(0, n, count), radii, rng.uniform(0.05, 0.6, count)):
        cv2.circle(canvas, (int(16 * x), int(16 * y)), int(16 * r), float(v), -1, cv2.LINE_8, 4)
    canvas *= (1.0 + 0.1 * rng.standard_normal(canvas.shape)).astype(np.float32)
    k = rng.poisson(glints * side * side / 1000.0)
    xs, ys = rng.uniform(0, n, k), rng.uniform(0, n, k)
    radii = np.exp(rng.uniform(math.log(0.15), math.log(0.8), k)) * density
    for x, y, r, v in zip(xs, ys, radii, np.exp(rng.uniform(math.log(3.0), math.log(60.0), k))):
        cv2.circle(canvas, (int(16 * x), int(16 * y)), max(int(16 * r), 8), float(v), -1, cv2.LINE_8, 4)
    return canvas


def raster_mean(raster: np.ndarray, u: np.ndarray, v: np.ndarray, width: float) -> np.ndarray:
    """Exact mean of a raster of constant cells (cell (i, j) covers [j, j+1) x [i, i+1)) over the squares of
    side ``width`` <= 2 cells centred at (u, v): each square meets three cells at most along each axis."""
    if width > 2.0:
        raise ValueError("squares of at most 2 cells")
    rows, cols = raster.shape

    def shares(start, size):
        """The cells floor(start) + 0, 1, 2 (clamped to the raster) and the length of [start, start + width) in each."""
        first = np.floor(start)
        return [(np.clip(first + d, 0, size - 1).astype(np.int64),
                 np.maximum(np.minimum(first + d + 1, start + width) - np.maximum(first + d, start), 0.0))
                for d in range(3)]

    total = 0.0
    for cy, wy in shares(v - width / 2, rows):
        for cx, wx in shares(u - width / 2, cols):
            total = total + raster[cy, cx] * (wy * wx)
    return (total / (width * width)).astype(np.float32)


def wall_pair(kernel: Kernel, lam: float, near_shape: tuple[int, int], far_shape: tuple[int, int], seed: int,
              glints: float = 0.0, exposure: Exposure = Exposure(30000.0),
              offset: tuple[float, float] = (1.3, -0.7), density: int = 6) -> tuple[Frame, Frame]:
    """A near and a far photograph of one `wall`, fronto-parallel, the far one ``lam`` times farther.

    Both see the same radiance through ``kernel`` (`blur`: the exact mean of the raster over each
    1/32-pixel square, `raster_mean`, then the analytic transfer function), under flat light, and
    go through the same sensor (`expose`: shot and read noise, 14-bit ADC, clipping at the white
    level, which is reflectance 1 / 0.6). A near pixel covers one world unit, a far pixel ``lam``; the
    far photo's centre lies ``offset`` near pixels from the near one's, and the far photo may see
    beyond the near one (the common region is then the near photo's field).
    """
    samples = 32
    if lam * density / samples > 2.0:
        raise ValueError("a far pixel's 1/32 square spans more than 2 raster cells: lower the density")
    side = max(near_shape[0], near_shape[1], lam * (max(far_shape) + 40)) + 40
    raster = wall(side, seed, glints, density)
    centre = side / 2

    def view(scale: float, shape: tuple[int, int], at: tuple[float, float]):
        cx, cy = (shape[1] - 1) / 2, (shape[0] - 1) / 2

        def scene(x, y, pixel):
            u = (at[0] + scale * (np.asarray(x, dtype=np.float64) - cx)) * density
            v = (at[1] + scale * (np.asarray(y, dtype=np.float64) - cy)) * density
            return raster_mean(raster, u, v, scale * pixel * density)

        return scene

    near = blur(view(1.0, near_shape, (centre, centre)), near_shape, kernel, samples)
    far = blur(view(lam, far_shape, (centre + offset[0], centre + offset[1])), far_shape, kernel, samples)
    return (expose(near, exposure, seed + 100, "near")[0], expose(far, exposure, seed + 200, "far")[0])
