"""The independent renderer (tests/render.py) against analytic cases, before anything is tested with it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import render
from scipy import integrate, signal, special

S = 4


def _phi(z):
    return 0.5 * (1.0 + special.erf(z / math.sqrt(2.0)))


def test_sampled_gaussian_is_the_closed_form():
    """Gaussian optics times a box of side a: h(x, y) = g(x) g(y), g(x) = [Phi((x + a/2)/sigma) - Phi((x - a/2)/sigma)] / a."""
    sigma, a = 0.45, 0.5
    h = render.gaussian(sigma, aperture=a).sampled(S, 33)
    x = (np.arange(33) - 16) / S
    g = (_phi((x + a / 2) / sigma) - _phi((x - a / 2) / sigma)) / a
    np.testing.assert_allclose(h, np.outer(g, g) / S**2, atol=1e-12 * h.max())
    assert h.sum() == pytest.approx(1.0, abs=1e-9)  # the whole kernel is inside 33 samples: energy kept


def test_sampled_airy_is_the_integrated_airy_pattern():
    """Diffraction: (2 J1(v) / v)^2 with v = pi r / (lambda N), integrated over the photosite box by quadrature."""
    fnumber, wavelength, pitch, a = 5.6, 0.55, 8.6, 0.5
    scale = wavelength * fnumber / pitch  # lambda N in channel pixels
    kernel = render.airy(fnumber, wavelength, pitch, aperture=a)
    h = kernel.sampled(S, 17)

    def airy(y, x):
        v = math.pi * math.hypot(x, y) / scale
        return 1.0 if v < 1e-12 else (2.0 * special.j1(v) / v) ** 2

    area = 4.0 * scale**2 / math.pi  # integral of the pattern over the plane
    for k in (0, 1, 3, 6):  # samples along the x axis and one off it
        x, y = k / S, 1 / S
        value, _ = integrate.dblquad(airy, x - a / 2, x + a / 2, y - a / 2, y + a / 2, epsabs=1e-10)
        assert h[8 + 1, 8 + k] == pytest.approx(value / (area * a * a) / S**2, rel=1e-4)


@pytest.mark.parametrize("kernel", [render.gaussian(0.7, 0.35, theta_deg=30.0), render.airy(11.0),
                                    render.defocus(0.6)], ids=lambda k: k.name)
def test_mtf_of_the_samples_is_the_analytic_mtf(kernel):
    """The DFT of the point samples is ĥ periodised (Poisson summation); on the s-band it is |ĥ| up to the aliasing."""
    h = kernel.sampled(S, 255)
    fx, fy = render.band(S, 16)
    dft = render.kernel_mtf(h, S, fx, fy) * h.sum()
    beyond = kernel.outside(S, 255)  # what the 255-sample window leaves out changes the DFT by at most that much
    np.testing.assert_allclose(dft, np.abs(kernel.periodised_otf(fx, fy, S)), atol=beyond + 1e-9)
    assert np.abs(dft - kernel.mtf(fx, fy)).max() <= kernel.aliasing(S) + beyond + 1e-9
    assert kernel.otf(np.zeros(1), np.zeros(1))[0] == pytest.approx(1.0)


def _edge_spread(distance: np.ndarray, sigma: float, a: float, angle: float) -> np.ndarray:
    """Edge spread of Gaussian optics times an a x a box across an edge whose normal makes ``angle`` with x.

    The line spread is the Gaussian convolved with the box's projections on the
    normal, boxes of a |cos| and a |sin|, computed on a 1e-4 pixel grid.
    """
    d = np.arange(-80000, 80001) * 1e-4
    line = np.exp(-0.5 * (d / sigma) ** 2)
    for width in (a * abs(math.cos(angle)), a * abs(math.sin(angle))):
        if width > 1e-6:
            line = signal.fftconvolve(line, (np.abs(d) <= width / 2).astype(float), mode="same")
    spread = np.cumsum(line)
    return np.interp(distance, d, spread / spread[-1])


@pytest.mark.parametrize("degrees", [0.0, 10.0, 45.0])
def test_edge_is_the_analytic_edge_spread(degrees):
    """A straight edge, averaged exactly over each 1/32-pixel square, through the Fourier path: the edge
    spread to 1e-4 of the step at 0, 10 and 45 degrees (point samples would leave 0.0139 at 0 degrees:
    every edge moved to the next 1/32 of a pixel)."""
    sigma, a, lo, hi = 0.45, 0.5, 0.2, 0.9
    angle = math.radians(degrees)
    n = np.array([math.cos(angle), math.sin(angle)])

    def scene(x, y, pixel):
        d = (x - 40.3) * n[0] + (y - 30.1) * n[1]
        dark = render._below(-d, abs(n[0]) * pixel / 2, abs(n[1]) * pixel / 2)  # share of the square at d < 0
        return lo * dark + hi * (1 - dark)

    image = render.blur(scene, (64, 80), render.gaussian(sigma, aperture=a))
    yy, xx = np.mgrid[0:64, 0:80]
    expected = lo + (hi - lo) * _edge_spread((xx - 40.3) * n[0] + (yy - 30.1) * n[1], sigma, a, angle)
    inner = (xx > 20) & (xx < 60) & (yy > 10) & (yy < 54)  # clear of the periodic wrap of the other edges
    assert np.abs(image - expected)[inner].max() < 1e-4 * (hi - lo)


def test_constant_scene_and_energy_are_kept():
    # sigma = 1: |ĥ| < 1e-8 beyond 1 cycle per pixel, so the pixel samples sum to the integral (Poisson)
    kernel = render.gaussian(1.0)
    flat = render.blur(lambda x, y, pixel: np.full(np.broadcast(x, y).shape, 0.37), (40, 50), kernel)
    np.testing.assert_allclose(flat, 0.37, rtol=1e-6)  # the scene is transformed in float32
    # a bright 5.3 x 4.1 pixel rectangle: the blurred plane holds exactly its energy
    def box(x, y, pixel):
        inside_x = np.clip((np.minimum(x + pixel / 2, 27.0) - np.maximum(x - pixel / 2, 21.7)) / pixel, 0, 1)
        inside_y = np.clip((np.minimum(y + pixel / 2, 22.2) - np.maximum(y - pixel / 2, 18.1)) / pixel, 0, 1)
        return inside_x * inside_y

    image = render.blur(box, (40, 50), kernel)
    assert image.sum() == pytest.approx(5.3 * 4.1, rel=1e-6)


def test_target_follows_the_published_layout():
    """DESIGN.md: noise in blocks 1..8, hourglass X-corners, black squares, white paper around."""
    noise = render.published_noise()
    assert noise.shape == (256, 256) and noise.mean() == pytest.approx(0.502, abs=0.001)
    paper = render.Print()
    black, white = paper.black, paper.white

    def at(x, y):
        return pytest.approx(float(render.reflectance(np.array([x]), np.array([y]), noise, paper)[0]))

    i, j = 100, 37
    assert at(32 + i + 0.5, 32 + j + 0.5) == black + (white - black) * noise[j, i]
    cx, cy = 9 * 32 + 16, 9 * 32 + 16  # corner (9, 9): the orientation mark
    assert at(cx, cy - 10) == black and at(cx, cy + 10) == black  # triangles on the top and bottom edges
    assert at(cx - 10, cy) == white and at(cx + 10, cy) == white
    assert at(9 * 32 + 16, 8 * 32 + 16) == black and at(8 * 32 + 16, 9 * 32 + 16) == black  # flanked by blacks
    assert at(7 * 32 + 16, 0 * 32 + 16) == white  # a white square
    assert at(-10.0, 100.0) == white and at(-paper.board - 1.0, 100.0) == paper.background


def test_footprint_averages_the_cells():
    """The mean over a small square straddling a cell corner is the area-weighted mean of the four cells."""
    noise = render.published_noise()
    paper = render.Print()
    X, Y, side = 32 + 10.0, 32 + 20.0, 0.3  # a corner of four noise cells
    footprint = np.eye(2) * side
    offset = np.array([0.06, -0.04])
    mean = render.reflectance(np.array([X + offset[0]]), np.array([Y + offset[1]]), noise, paper,
                              footprint=footprint)[0]
    wx = np.array([0.15 - 0.06, 0.15 + 0.06]) / side  # shares left and right of X = 42
    wy = np.array([0.15 + 0.04, 0.15 - 0.04]) / side  # above and below Y = 52
    cells = paper.black + (paper.white - paper.black) * noise[19:21, 9:11]
    assert mean == pytest.approx(float(wy @ cells @ wx), abs=1e-6)


@pytest.mark.parametrize("width", [0.3, 1.0, 1.7])
def test_raster_mean_is_the_area_weighted_mean_of_the_cells(width):
    """`raster_mean` against the mean of 600 x 600 points spread over each square: the points miss at most half
    a point's share at each cell edge crossed, four at most, so 2/600 of the cells' range (allowed: 4e-3)."""
    rng = np.random.default_rng(0)
    raster = rng.random((6, 7)).astype(np.float32)
    u, v = rng.uniform(1.5, 5.0, 5), rng.uniform(1.5, 4.0, 5)
    mean = render.raster_mean(raster, u, v, width)
    t = ((np.arange(600) + 0.5) / 600 - 0.5) * width
    for k in range(5):
        rows, cols = np.floor(v[k] + t).astype(int), np.floor(u[k] + t).astype(int)
        assert mean[k] == pytest.approx(float(raster[rows[:, None], cols[None, :]].mean()), abs=4e-3)


def test_sensor_noise_is_shot_read_and_quantisation():
    shot = render.render(render.gaussian(0.5), render.View(0.3), seed=4)
    e = shot.exposure
    gain = e.dn_per_electron
    expected = shot.ideal * e.electrons * gain
    variance = gain**2 * (shot.ideal * e.electrons + e.read_noise**2) + 1 / 12
    z = (shot.frame.data - expected) / np.sqrt(variance)
    assert abs(z.mean()) < 0.02 and z.std() == pytest.approx(1.0, abs=0.02)
    assert shot.frame.white == e.white_level - e.black_level and not shot.frame.saturated.any()
    # the estimator's normalised plane: black ink 0, white paper 1, noise as Render.sigma says
    v = shot.normalised()
    rows, cols = v.shape
    assert shot.sigma(0.5) == pytest.approx(np.sqrt(0.42 * 5000 + 16 + 1 / 12 / gain**2) / (0.76 * 5000), rel=1e-6)
    x, y = shot.to_image(np.array([7 * 32 + 16.0]), np.array([16.0]))  # centre of a white square
    assert v[int(round(y[0])), int(round(x[0]))] == pytest.approx(1.0, abs=5 * shot.sigma(1.0))


@pytest.mark.slow
def test_target_render_converges_with_the_sampling():
    """32 and 64 samples per pixel agree far below the sensor noise of the accuracy tests.

    Upright, where every cell edge lines up with the samples. The lowest noise
    used (tests/test_accuracy.py) is 0.0049 of the black-to-white range at
    mid-grey: the difference is below a tenth of it in RMS and half of it
    anywhere (aliasing of the 1/32-pixel averages, about 1e-3 of the step).
    """
    kernel = render.airy(5.6)
    view = render.View(0.3, rotation_deg=0.0, tilt=(0.04, -0.03))
    planes = [render.render(kernel, view, samples=n, exposure=render.Exposure(electrons=math.inf)) for n in (32, 64)]
    paper = render.Print()
    difference = (planes[0].ideal - planes[1].ideal) / (paper.white - paper.black)
    assert np.sqrt(np.mean(difference**2)) < 0.1 * 0.0049
    assert np.abs(difference).max() < 0.5 * 0.0049
