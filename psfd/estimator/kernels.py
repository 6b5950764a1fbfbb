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

__all__ = ["PSF", "centroid", "clip_negatives", "core_centroid", "field_of_window", "normalise", "split_grid",
           "translations"]


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
