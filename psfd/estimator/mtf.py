"""Modulation transfer function and scalar sharpness figures of a PSF.

Frequencies are in cycles per channel pixel: 0.5 is the channel's Nyquist
frequency and a kernel on the s-times grid reaches s/2 (the thesis's MTF
profiles, Delbracio PhD thesis 2013, sec. 2.5).
"""

from __future__ import annotations

import numpy as np

PAD = 256  # FFT size for profiles: fine enough to read MTF50 by interpolation


def mtf2d(psf: np.ndarray, s: int, size: int = PAD) -> tuple[np.ndarray, np.ndarray]:
    """2-D MTF of a kernel sampled on the s-times grid.

    Parameters
    ----------
    psf : ndarray, 2-D
    s : int
        Super-resolution factor of the grid the kernel is sampled on.
    size : int
        FFT size (zero padding).

    Returns
    -------
    freqs : ndarray
        Centred frequencies in cycles per channel pixel, from -s/2 to below s/2.
    mtf : ndarray, (size, size)
        |OTF| normalised so that MTF(0) = 1, centred (fftshift).
    """
    otf = np.fft.fft2(psf, s=(size, size))
    dc = otf[0, 0]
    mag = np.abs(otf) / (abs(dc) if abs(dc) > 0 else 1.0)
    freqs = np.fft.fftshift(np.fft.fftfreq(size, d=1.0 / s))
    return freqs, np.fft.fftshift(mag)


def profiles(psf: np.ndarray, s: int, size: int = PAD) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Horizontal and vertical MTF profiles through the origin, non-negative frequencies.

    Returns
    -------
    freqs, mtf_x, mtf_y : ndarray
        ``mtf_x`` varies along the x frequency axis (fy = 0), ``mtf_y`` along y.
    """
    otf = np.fft.fft2(psf, s=(size, size))
    mag = np.abs(otf) / max(abs(otf[0, 0]), 1e-300)
    half = size // 2 + 1
    freqs = np.arange(half) * s / size
    return freqs, mag[0, :half].copy(), mag[:half, 0].copy()


def mtf50(freqs: np.ndarray, mtf: np.ndarray) -> float:
    """First frequency where a profile falls to 0.5, linearly interpolated (nan if it never does)."""
    below = np.flatnonzero(mtf < 0.5)
    if below.size == 0:
        return float("nan")
    i = int(below[0])
    if i == 0:
        return 0.0
    f0, f1, m0, m1 = freqs[i - 1], freqs[i], mtf[i - 1], mtf[i]
    return float(f0 + (m0 - 0.5) * (f1 - f0) / (m0 - m1))


def fwhm(psf: np.ndarray, s: int) -> tuple[float, float]:
    """Full width at half maximum along x and y through the peak, in channel pixels."""
    row, col = np.unravel_index(int(np.argmax(psf)), psf.shape)
    return _width(psf[row, :]) / s, _width(psf[:, col]) / s


def _width(line: np.ndarray) -> float:
    peak = int(np.argmax(line))
    half = line[peak] / 2
    left = peak
    while left > 0 and line[left - 1] > half:
        left -= 1
    right = peak
    while right < line.size - 1 and line[right + 1] > half:
        right += 1
    # interpolate the half-maximum crossing on each side
    lx = left - (line[left] - half) / (line[left] - line[left - 1]) if left > 0 else float(left)
    rx = right + (line[right] - half) / (line[right] - line[right + 1]) if right < line.size - 1 else float(right)
    return float(rx - lx)
