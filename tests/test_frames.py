"""The serial work around the Bernoulli windows of a RAW frame: the same results as the unoptimised path.

The previous implementations are kept here as references (the MTF profiles
through the 2-D transform, the RAW planes from a full copy of the mosaic, the
PSF records built in the parent process) and compared with what psfd runs now.
"""

from __future__ import annotations

import numpy as np
import pytest

from psfd.estimator import mtf


def _profiles_2d(psf: np.ndarray, s: int, size: int = mtf.PAD):
    """MTF profiles as psfd computed them before: rows and columns of the size x size 2-D transform."""
    otf = np.fft.fft2(psf, s=(size, size))
    mag = np.abs(otf) / max(abs(otf[0, 0]), 1e-300)
    half = size // 2 + 1
    return np.arange(half) * s / size, mag[0, :half], mag[:half, 0]


@pytest.mark.parametrize("shape", [(17, 17), (9, 13), (300, 280)])
def test_profiles_from_projections_equal_the_2d_transform(shape):
    # the projections' 1-D transforms are the 2-D transform's axes (Fourier slice theorem);
    # only the summation order differs: equal to a few units of the last place of values <= 1
    kernel = np.random.default_rng(1).random(shape)
    for new, old in zip(mtf.profiles(kernel, 4), _profiles_2d(kernel, 4)):
        assert new.shape == old.shape
        np.testing.assert_allclose(new, old, rtol=0, atol=1e-14)


def _estimate(channel: str, field: tuple[float, float], warnings: list[str], source: str = "/data/IMG_1.dng"):
    from psfd.estimator.kernels import PSF

    delta = np.zeros((5, 5))
    delta[2, 2] = 1.0
    return PSF(psf=delta, s=1, method="bernoulli", channel=channel, sources=[source], field=field,
               warnings=warnings)


def test_a_warning_shared_by_windows_is_logged_once_per_plane(capsys):
    from psfd.cli import logs, output

    scale = "imaging scale s/t = 4.20 is outside [1.0, 1.6]"
    mass = "kernel mass 1.30 before normalisation (expected 1)"
    estimates = [
        _estimate("g1", (0.25, 0.25), [scale]),
        _estimate("g1", (0.75, 0.25), [scale, mass]),
        _estimate("g1", (0.25, 0.75), [scale]),
        _estimate("r", (0.50, 0.50), [scale]),
        _estimate("g1", (0.50, 0.50), [mass], source="/data/IMG_2.dng"),
        _estimate("g1", (0.50, 0.60), [mass], source="/data/IMG_2.dng"),
    ]
    logs.setup()
    output.log_warnings(estimates)
    assert capsys.readouterr().err.splitlines() == [
        f"psfd: warning: IMG_1.dng g1, 3 of 3 windows: {scale}",
        f"psfd: warning: IMG_1.dng g1 at (0.75, 0.25): {mass}",  # one window: named by its field
        f"psfd: warning: IMG_1.dng r at (0.50, 0.50): {scale}",
        f"psfd: warning: IMG_2.dng g1, 2 of 2 windows: {mass}",
    ]
