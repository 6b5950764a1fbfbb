"""The forward-model simulator against closed-form optics and its own ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from psfd.estimator import mtf, raw, simulate, target


def _moments(h: np.ndarray, s: int) -> np.ndarray:
    """Covariance matrix of a kernel, in channel pixels^2."""
    c = (np.arange(h.shape[0]) - h.shape[0] // 2) / s
    y, x = np.meshgrid(c, c, indexing="ij")
    mx, my = (h * x).sum(), (h * y).sum()
    return np.array(
        [[(h * (x - mx) ** 2).sum(), (h * (x - mx) * (y - my)).sum()],
         [(h * (x - mx) * (y - my)).sum(), (h * (y - my) ** 2).sum()]]
    )


def test_gaussian_psf_has_the_requested_covariance():
    h = simulate.gaussian_psf(0.6, 0.3, theta=np.pi / 6, s=4, support=33)
    assert h.shape == (33, 33) and h.sum() == pytest.approx(1.0)
    rot = np.array([[np.cos(np.pi / 6), -np.sin(np.pi / 6)], [np.sin(np.pi / 6), np.cos(np.pi / 6)]])
    expected = rot @ np.diag([0.36, 0.09]) @ rot.T
    # Sampling a Gaussian on a grid 4x finer than sigma/0.3 changes moments by far less than 1e-3.
    np.testing.assert_allclose(_moments(h, 4), expected, atol=1e-3)


def _diffraction_mtf(f: np.ndarray, fnumber: float, wavelength_um: float, pitch_um: float) -> np.ndarray:
    """Closed-form MTF of a circular pupil times the sinc of a pitch-wide box (Goodman, eq. 6-32)."""
    nu = np.clip(f / pitch_um * wavelength_um * fnumber, 0, 1)  # f in cycles per channel pixel
    pupil = 2 / np.pi * (np.arccos(nu) - nu * np.sqrt(1 - nu * nu))
    return pupil * np.abs(np.sinc(f))


@pytest.mark.parametrize("fnumber, wavelength_um, pitch_um", [
    (5.6, 0.55, 8.0), (16.0, 0.55, 8.0),
    # the simulated rig's fast apertures on its 16 um channel pitch: the optics pass 7.5 and 12.4 cycles
    # per pixel, far beyond the s = 4 band; point samples folded that into the band (MTF 0.077 and 0.091
    # below the closed form at 1.6 cycles per pixel)
    (4.0, 0.53, 16.0), (2.8, 0.46, 16.0),
])
def test_diffraction_psf_matches_the_closed_form_mtf(fnumber, wavelength_um, pitch_um):
    h = simulate.diffraction_psf(fnumber, wavelength_um=wavelength_um, pitch_um=pitch_um, s=4, support=97)
    # band-limited to the s-grid's band, the kernel rings on the pixel box's edges: lobes of 4 % of the peak
    assert h.sum() == pytest.approx(1.0) and h.min() >= -0.05 * h.max()
    freqs, mx, my = mtf.profiles(h, 4)
    band = freqs <= 2.0  # the whole band of the s = 4 grid
    truth = _diffraction_mtf(freqs[band], fnumber, wavelength_um, pitch_um)
    # Tolerance: the Airy tails cut at the support lift the low frequencies by
    # about (tail energy), which falls as 1/support: 0.018 / 0.009 / 0.005 at
    # f/5.6 and 0.05 / 0.025 / 0.013 at f/16 for supports 33 / 65 / 97.
    np.testing.assert_allclose(mx[band], truth, atol=0.015)
    np.testing.assert_allclose(my[band], truth, atol=0.015)


def test_diffraction_grows_with_f_number_and_stays_centred_under_aberration():
    widths = [mtf.fwhm(simulate.diffraction_psf(n, support=25), 4)[0] for n in (5.6, 16, 32)]
    assert widths[0] < widths[1] < widths[2]
    h = simulate.diffraction_psf(5.6, aberration=(0.3, 0.2), support=25)
    c = _centroid(h)
    assert np.hypot(*c) < 0.05  # s-grid samples: re-centred on its centroid
    sym = simulate.diffraction_psf(5.6, support=25)
    assert np.abs(h - sym).sum() > 0.1  # the aberration does change the shape


def _centroid(h: np.ndarray) -> tuple[float, float]:
    y, x = np.mgrid[0 : h.shape[0], 0 : h.shape[1]] - h.shape[0] // 2
    return float((h * x).sum()), float((h * y).sum())


def test_render_plane_transfers_a_grating_with_the_psf_mtf():
    """Lemma 1 (IJCV 2012): the rendered plane of a grating has the kernel's MTF as contrast."""
    s, f = 4, 0.3  # cycles per channel pixel, below the channel Nyquist: no aliasing
    h = simulate.gaussian_psf(0.7, s=s, support=25)
    scale = 8.0  # scene raster pixels per channel pixel
    xs = np.arange(1200)
    scene = np.tile(0.5 + 0.4 * np.cos(2 * np.pi * f * xs / scale), (300, 1))

    def to_scene(x, y):
        return x * scale + 100.0, y * scale + 20.0

    plane = simulate.render_plane(scene, to_scene, (24, 120), h, s, background=0.5)
    row = plane[12, 10:-10]
    x = np.arange(10, 110)
    design = np.stack([np.cos(2 * np.pi * f * x), np.sin(2 * np.pi * f * x), np.ones_like(x, float)], axis=1)
    coef, *_ = np.linalg.lstsq(design, row, rcond=None)
    amplitude = np.hypot(coef[0], coef[1])
    freqs, mx, _ = mtf.profiles(h, s, size=1000)
    expected = 0.4 * np.interp(f, freqs, mx)
    # Residual error: the scene's raised-cosine band edge is far above f, the cubic
    # remap on an 8x oversampled raster attenuates f by < 0.1 %.
    assert amplitude == pytest.approx(expected, rel=0.01)
    assert coef[2] == pytest.approx(0.5, abs=1e-3)


def test_expose_noise_and_clipping():
    rng = np.random.default_rng(3)
    ideal = np.full((200, 200), 0.5)
    raw_values = simulate.expose(ideal, rng=rng)
    norm = (raw_values - 512) / (0.75 * (16383 - 512))
    assert norm.mean() == pytest.approx(0.5, abs=1e-3)
    # std of 40000 samples is known to 0.4 %: allow 3 %.
    assert norm.std() == pytest.approx(simulate.noise_sigma(0.5), rel=0.03)
    bright = simulate.expose(np.ones((10, 10)), exposure=2.0, rng=rng)
    assert bright.max() == 16383


def test_simulate_target_writes_a_dng_with_its_ground_truth(tmp_path):
    path = tmp_path / "target.dng"
    h = {c: simulate.gaussian_psf(0.5 + 0.1 * i) for i, c in enumerate(raw.CHANNELS)}
    truth = simulate.simulate_target(path, psf=h, rotation_deg=12, distortion=0.04, tilt=(0.05, -0.03), seed=4)
    frames = raw.load_frames(path)
    assert [f.channel for f in frames] == list(raw.CHANNELS)
    for frame in frames:
        assert frame.shape == (240, 320)
        assert frame.offset == simulate.RGGB_OFFSETS[frame.channel]
        assert not frame.saturated.any()
        np.testing.assert_array_equal(truth["psf"][frame.channel], h[frame.channel])
    g1 = frames[1]
    to_pattern, to_image = truth["to_pattern"]["g1"], truth["to_image"]["g1"]
    # the two maps are inverse to each other (distortion inverted by iteration)
    X, Y = to_pattern(*to_image(np.array([40.0, 150.0, 280.0]), np.array([40.0, 200.0, 100.0])))
    np.testing.assert_allclose(X, [40.0, 150.0, 280.0], atol=1e-6)
    np.testing.assert_allclose(Y, [40.0, 200.0, 100.0], atol=1e-6)
    # flat squares read black and white (centre pixel of each block, well inside)
    scale = 0.75 * (truth["white"] - truth["black"])
    for blocks, level in ((target.BLACK_BLOCKS, 0.0), (target.WHITE_BLOCKS, 1.0)):
        pts = np.array([target.block_centre(b) for b in blocks])
        x, y = to_image(pts[:, 0], pts[:, 1])
        values = g1.data[np.round(y).astype(int), np.round(x).astype(int)] / scale
        # the light field falls by at most 15 % from the centre
        assert np.all(np.abs(values - level) < 0.2)
    # the noise region averages to half the white level (Bernoulli(0.5))
    yy, xx = np.mgrid[0:240, 0:320].astype(float)
    X, Y = to_pattern(xx, yy)
    inside = (X > 40) & (X < 280) & (Y > 40) & (Y < 280)
    assert g1.data[inside].mean() / scale == pytest.approx(0.5, abs=0.08)


def test_simulate_target_saturates_when_overexposed(tmp_path):
    simulate.simulate_target(tmp_path / "hot.dng", psf=simulate.gaussian_psf(0.5), exposure=1.6)
    frame = raw.load_frame(tmp_path / "hot.dng", "g1")
    assert frame.saturated.any()
