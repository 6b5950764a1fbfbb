"""The PSF record every method returns, and the conventions its kernel keeps.

A PSF is a float64 array on the s-times super-resolved grid of one channel
plane, odd-sized, centred on its core, summing to 1; its field location is the
normalised position of its window's centre on the plane, (0, 0) top-left and
(1, 1) bottom-right. `normalise`, `clip_negatives`, `core_centroid`,
`split_grid` and `field_of_window` keep these conventions for every estimator.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from psfd.estimator import mtf

__all__ = ["NOISE_WARN", "PSF", "RING_WARN", "centroid", "clip_negatives", "core_centroid", "field_of_window",
           "kernel_warnings", "normalise", "split_grid", "translations"]

# Relative noise floor (`PSF.relative_noise`) above which a kernel is flagged as more noise than PSF: the
# expected error norm then exceeds the kernel's own norm (an upper bound for a non-negative kernel). Measured
# in normal use: 0.02-0.03 on the simulated rig's target (f/2.8-f/22, 3 x 3 field, 4 channels), 0.06-0.15
# on its two-photo pair at f/8; on the real photographs 0.05 (img_example.pgm, Bernoulli; 0.08-0.15 on a
# 3 x 3 grid), 0.05 (the pair, two-photo; 0.11 at s = 4), 0.41 and 0.68 (img_example.pgm by the sharp-edge
# method, blind and --target: a posterior floor, regularised). Past it: 1.63 by blind sharp edge on
# IMG_0608_v1.pgm (a wall, no edges to predict), 1.63 and 2.23 on img_example.pgm at s = 6 and 8. The
# two-photo method refuses its inter-image kernel from 0.5 on (twoscale.NOISE_MAX); a warning at 0.5 would
# flag the sharp-edge method on its own target.
NOISE_WARN = 1.0
# Share of the kernel's sum in the outermost ring of its support, beyond what noise alone can put there,
# above which the kernel is flagged as cut by its support. Noise alone: at most the ring's samples times the
# noise per sample, floor / k for a k x k kernel (a mean |error| of 0.8 of it; the whole of it clipped to
# >= 0 and kept as mass). Measured at s = 4 on renders of known PSF (tests/render.py, 0.30 pixel per cell,
# 30000 e-) and img_example.pgm, support by support: share (MTF50 change from 25 x 25, 17 x 17 for the Gaussian)
#   Gaussian 0.45 px    7: 0.28 (+8 %)   9: 0.10 (+2 %)   17: < 0
#   anisotropic         9: 0.16 (+12 %) 11: 0.07 (+5 %)   13: 0.02 (+1 %)
#   f/11 diffraction    7: 0.13 (+6 %)   9: 0.08 (-1 %)   11: 0.051 (-4 %) 13: 0.03 (-3 %)  17: 0.01
#   f/22 diffraction    9: 0.22 (+21 %) 11: 0.10 (+13 %) 13: 0.051 (+8 %) 17: 0.038 (0 %)
#   defocus             5: 0.54 (+18 %)  7: 0.19 (+4 %)   9: 0.06 (0 %)   11: 0.03 (-2 %)
#   img_example.pgm     3: 0.90 (+56 %)  5: 0.41 (+14 %)  7: 0.13 (+3 %)   9: 0.06 (-2 %)  11: 0.02 (-3 %)
# Every support that moved MTF50 by 8 % or more is flagged, none of those left by more than 3 %. The
# default supports give at most 0.038 (f/22 at 17 x 17, an r^-3 tail that no finite support holds), below
# 0.01 on the real photographs (two-photo pair 13 x 13: < 0; on 5 x 5: 0.15) and the simulated rig.
RING_WARN = 0.05


@dataclass
class PSF:
    """One local PSF estimate with its provenance.

    Attributes
    ----------
    psf : ndarray of float64
        Kernel on the s-times grid, odd size, unit sum.
    s : int
        Super-resolution factor.
    method : str
        ``bernoulli``, ``two-photo`` or ``sharp-edge``.
    channel : str
        Channel plane (``r``, ``g1``, ``g2``, ``b`` or ``mono``).
    sources : list of str
        Files the estimate came from.
    field : (float, float)
        Normalised (x, y) of the window centre, (0, 0) top-left, (1, 1) bottom-right.
    window : (int, int, int, int)
        (x0, y0, x1, y1) of the window on the channel plane, in channel pixels, end exclusive.
    noise_floor : float or None
        The error that sensor noise alone makes in the kernel, as the L2 norm
        over its samples: sqrt(E||h_e - h||^2) = sigma_n sqrt(trace((A^T A)^-1))
        for the unit-sum kernel (Delbracio et al., IJCV 2012, sec. 3.1), the
        same unit for every method; noise_floor / ||psf|| is the relative
        error, the RMS per sample noise_floor / k for a k x k kernel. It is
        the least-squares (or posterior) error: the non-negative solution
        comes closer, so it bounds the noise of the stored kernel from above.
        The two-photo method gives that of its inter-image kernel, which the
        PSF is derived from; on renders it bounds the PSF's noise as well
        (tests/test_noise_floor.py).
    residual : float or None
        RMS of the model residual on the observed samples (data units normalised to [0, 1]).
    prediction_error : float or None
        Cross-validated prediction error: RMS residual on each half of the
        observations of the kernel fitted on the other half, over the noise
        level (about 1 when the model holds; `bernoulli.cross_validated`).
    params : dict
        Estimator parameters (solver, support, grid, ...), stored with the PSF.
    warnings : list of str
        Conditions of the method that were only partly met.
    figures : dict of str to ndarray
        Extra arrays to show beside the PSF (inter-image kernel, residual image, ...).
    """

    psf: np.ndarray
    s: int
    method: str
    channel: str
    sources: list[str]
    field: tuple[float, float] = (0.5, 0.5)
    window: tuple[int, int, int, int] = (0, 0, 0, 0)
    noise_floor: float | None = None
    residual: float | None = None
    prediction_error: float | None = None
    params: dict[str, Any] = dataclasses.field(default_factory=dict)
    warnings: list[str] = dataclasses.field(default_factory=list)
    figures: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)

    @property
    def support(self) -> int:
        return int(self.psf.shape[0])

    @property
    def relative_noise(self) -> float | None:
        """The noise floor over the kernel's own L2 norm: the relative error that sensor noise alone makes."""
        return None if self.noise_floor is None else float(self.noise_floor) / float(np.linalg.norm(self.psf))

    def metrics(self) -> dict[str, float]:
        """MTF50 (cycles per channel pixel) and FWHM (channel pixels) along x and y."""
        fx, mx, my = mtf.profiles(self.psf, self.s)
        fwhm_x, fwhm_y = mtf.fwhm(self.psf, self.s)
        return {
            "mtf50_x": mtf.mtf50(fx, mx),
            "mtf50_y": mtf.mtf50(fx, my),
            "fwhm_x": fwhm_x,
            "fwhm_y": fwhm_y,
        }

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict: the fields the CLI prints and the catalogue stores."""
        return {
            "method": self.method,
            "source": self.sources[0] if len(self.sources) == 1 else list(self.sources),
            "channel": self.channel,
            "s": self.s,
            "support": self.support,
            "field_x": float(self.field[0]),
            "field_y": float(self.field[1]),
            "window": [int(v) for v in self.window],
            **self.metrics(),
            "noise_floor": self.noise_floor,
            "residual": self.residual,
            "prediction_error": self.prediction_error,
            "params": self.params,
            "warnings": list(self.warnings),
            "psf": self.psf.tolist(),
        }


# what gives an estimate more signal, said when its noise floor exceeds the kernel (`kernel_warnings`)
MORE_SIGNAL = "more light or a longer exposure, a lower -s, or a larger window (fewer --grid windows)"


def kernel_warnings(psf: np.ndarray, noise_floor: float | None, more_signal: str = MORE_SIGNAL) -> list[str]:
    """What makes a unit-sum kernel not a PSF, in the words every method uses: more noise than kernel, or
    a kernel cut by its support (`NOISE_WARN`, `RING_WARN` say why these thresholds).

    Parameters
    ----------
    psf : ndarray
        The kernel, k x k, unit sum.
    noise_floor : float or None
        `PSF.noise_floor`: the L2 norm of the error sensor noise alone makes in it.
    more_signal : str
        What gives the method more signal, said with a noise floor above the kernel.

    Returns
    -------
    list of str, empty when neither holds.
    """
    notes = []
    norm = float(np.linalg.norm(psf))
    if noise_floor is not None and noise_floor > NOISE_WARN * norm:
        notes.append(
            f"noise floor {noise_floor / norm:.0%} of the kernel: it may be more noise than PSF; give it more signal: "
            + more_signal
        )
    size = psf.shape[0]
    ring = float(np.sum(psf) - np.sum(psf[1:-1, 1:-1]))
    # noise alone puts at most its RMS per sample, noise_floor / k, into each of the ring's 4 (k - 1) samples
    noise = 4 * (size - 1) * (noise_floor or 0.0) / size
    if ring - noise > RING_WARN:
        notes.append(
            f"the kernel reaches the edge of its support: {ring:.0%} of its sum lies in the outermost ring "
            f"({noise:.0%} from noise), so it is truncated and too sharp: raise --support"
        )
    return notes


def normalise(psf: np.ndarray) -> np.ndarray:
    """Scale a kernel to unit sum (a PSF conserves energy: its MTF at 0 is 1)."""
    total = float(np.sum(psf))
    if not np.isfinite(total) or abs(total) < 1e-12:
        raise ValueError("kernel has no mass to normalise")
    return np.asarray(psf, dtype=np.float64) / total


def clip_negatives(psf: np.ndarray) -> np.ndarray:
    """Set negative values to 0 and renormalise (the papers' default projection onto h >= 0)."""
    return normalise(np.maximum(psf, 0.0))


def centroid(psf: np.ndarray) -> tuple[float, float]:
    """Centre of mass (x, y) of a kernel, in samples from its centre."""
    rows, cols = psf.shape
    total = float(np.sum(psf))
    y, x = np.mgrid[0:rows, 0:cols]
    return float(np.sum(x * psf) / total - (cols - 1) / 2), float(np.sum(y * psf) / total - (rows - 1) / 2)


def core_centroid(psf: np.ndarray, level: float = 0.05) -> tuple[float, float]:
    """Centre of mass (x, y), in samples from the centre, of the values above ``level`` x the peak.

    The estimation noise in the tails (a few per mille per sample, far from the
    centre) would move a plain centroid by a sizeable fraction of a sample; the
    core carries the position. Both estimators centre their PSFs on it.
    """
    return centroid(np.where(psf > level * psf.max(), psf, 0.0))


def translations(kernel: np.ndarray) -> Callable[[tuple[float, float]], np.ndarray]:
    """The kernel translated by -shift (x, y) samples, for any shift: a function of the shift.

    A Fourier phase ramp on the spectrum, taken once for all shifts: the
    kernels of both methods are band-limited to the s-grid band (IJCV 2012,
    sec. 3.1, Lemma 1; SIAM 2012, Lemma 1 for the inter-image kernel), so
    their samples determine them and a sub-sample translation is exact; zero
    padding to twice the support stops the shifted tails from wrapping
    around. An interpolating kernel (Keys' cubic) would instead low-pass the
    kernel by its own transfer function at the shift.
    """
    rows, cols = kernel.shape
    padded = np.zeros((2 * rows, 2 * cols))
    padded[:rows, :cols] = kernel
    spectrum = np.fft.fft2(padded)
    fy = np.fft.fftfreq(2 * rows)[:, None]
    fx = np.fft.fftfreq(2 * cols)[None, :]

    def translated(shift: tuple[float, float]) -> np.ndarray:
        ramp = np.exp(2j * np.pi * (fx * shift[0] + fy * shift[1]))
        return np.real(np.fft.ifft2(spectrum * ramp))[:rows, :cols]

    return translated


def field_of_window(window: tuple[int, int, int, int], plane_shape: tuple[int, int]) -> tuple[float, float]:
    """Normalised field location (x, y) of a window's centre on a plane."""
    x0, y0, x1, y1 = window
    rows, cols = plane_shape
    return ((x0 + x1) / 2 / cols, (y0 + y1) / 2 / rows)


def split_grid(
    bounds: tuple[int, int, int, int], grid: tuple[int, int]
) -> list[tuple[int, int, int, int]]:
    """Split a window (x0, y0, x1, y1) into ``grid`` = (nx, ny) local windows, row-major."""
    x0, y0, x1, y1 = bounds
    nx, ny = grid
    if nx < 1 or ny < 1:
        raise ValueError("grid must be at least 1x1")
    xs = np.linspace(x0, x1, nx + 1).round().astype(int)
    ys = np.linspace(y0, y1, ny + 1).round().astype(int)
    return [
        (int(xs[i]), int(ys[j]), int(xs[i + 1]), int(ys[j + 1])) for j in range(ny) for i in range(nx)
    ]
