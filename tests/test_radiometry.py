"""Illumination fields and the camera response (IJCV 2012, sec. 4.1; thesis App. A.3-A.4)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from psfd.errors import EstimationError
from psfd.estimator import detect, geometry, radiometry, target

SHAPE = (200, 240)


def pattern_to_image(scale: float = 0.5, angle: float = 20.0) -> np.ndarray:
    a = np.deg2rad(angle)
    rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) * scale
    h = np.eye(3)
    h[:2, :2] = rot
    h[:2, 2] = np.array([SHAPE[1] / 2, SHAPE[0] / 2]) - rot @ [160.0, 160.0]
    return h


def to_image_of(h: np.ndarray):
    def to_image(X, Y):
        X, Y = np.asarray(X, float), np.asarray(Y, float)
        w = h[2, 0] * X + h[2, 1] * Y + h[2, 2]
        return (h[0, 0] * X + h[0, 1] * Y + h[0, 2]) / w, (h[1, 0] * X + h[1, 1] * Y + h[1, 2]) / w

    return to_image


def maps(h: np.ndarray):
    """(to_image, to_pattern) of a pattern -> image homography."""
    return to_image_of(h), to_image_of(np.linalg.inv(h))


REACH = 2.0  # pixels: the default 17 x 17 support at s = 4


def reflectance(h: np.ndarray) -> np.ndarray:
    """The target's reflectance on the image grid (sharp, 4 raster pixels per cell)."""
    n = 4
    from_raster = np.array([[1 / n, 0, 0.5 / n], [0, 1 / n, 0.5 / n], [0, 0, 1]])
    return cv2.warpPerspective(target.cells(None, n).astype(np.float32), h @ from_raster, SHAPE[::-1], flags=cv2.INTER_LINEAR).astype(float)


def black_field(x, y):
    # Dark level with a slope and a curvature (black offset left over, flare).
    return 40.0 + 0.05 * (x - 120) - 2e-4 * (y - 100) ** 2 + 1e-4 * (x - 120) * (y - 100)


def white_field(x, y):
    # Vignetting: 15 % fall-off towards the corners plus a left-right gradient.
    r2 = ((x - 110) ** 2 + (y - 95) ** 2) / 160.0**2
    return 3000.0 * (1 - 0.15 * r2) + 1.5 * (x - 120)


def test_illumination_recovers_known_quadratic_fields():
    h = pattern_to_image()
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    b, w = black_field(xx, yy), white_field(xx, yy)
    image = b + (w - b) * reflectance(h)
    black, white, tail = radiometry.illumination(image, *maps(h), REACH)
    # Both fields are quadratics and the edges are sharp (no tail), so the fit is exact up to
    # the raster's interpolation.
    assert tail < 1e-4
    X, Y = np.meshgrid(np.linspace(32, 288, 20), np.linspace(32, 288, 20))
    x, y = to_image_of(h)(X, Y)
    contrast = (white_field(x, y) - black_field(x, y)).min()
    assert np.abs(black(x, y) - black_field(x, y)).max() < 1e-3 * contrast
    assert np.abs(white(x, y) - white_field(x, y)).max() < 1e-3 * contrast
    # Normalised, every pixel (reflectance 0 to 1) reads 0 to 1.
    v = radiometry.normalise(image, black, white, xx, yy)
    assert v.min() > -0.01 and v.max() < 1.01


def test_illumination_is_robust_to_a_hot_pixel():
    h = pattern_to_image()
    yy, xx = np.mgrid[0 : SHAPE[0], 0 : SHAPE[1]].astype(float)
    image = 40.0 + 3000.0 * reflectance(h)
    to_image, to_pattern = maps(h)
    x, y = to_image(*target.block_centre(target.BLACK_BLOCKS[0]))
    image[int(round(float(y))), int(round(float(x)))] = 16383.0
    black, _, tail = radiometry.illumination(image, to_image, to_pattern, REACH)
    assert abs(float(black(x, y)) - 40.0) < 1.0
    assert tail < 1e-4


def test_illumination_is_robust_to_dust_on_a_white_square():
    """A dark speck of 3 x 3 pixels at 40 % on a white square moves neither field nor the tail."""
    h = pattern_to_image()
    image = 40.0 + 3000.0 * reflectance(h)
    to_image, to_pattern = maps(h)
    x, y = to_image(*target.block_centre(target.WHITE_BLOCKS[3]))
    col, row = int(round(float(x))), int(round(float(y)))
    image[row - 1 : row + 2, col + 1 : col + 4] *= 0.4
    black, white, tail = radiometry.illumination(image, to_image, to_pattern, REACH)
    assert abs(float(white(x, y)) - 3040.0) < 1.0 and abs(float(black(x, y)) - 40.0) < 1.0
    assert tail < 1e-4


def test_a_target_too_small_to_clear_the_support_still_reads_the_squares():
    """At 0.175 pixel per cell (the smallest the target is found at) a square is 5.6 px wide: no pixel is 3.5 px
    from its edges, so its inner third is read; with sharp edges the fields stay exact."""
    h = pattern_to_image(scale=0.175)
    image = 40.0 + 3000.0 * reflectance(h)
    black, white, _ = radiometry.illumination(image, *maps(h), 3.0)
    x, y = to_image_of(h)(160.0, 160.0)
    assert float(black(x, y)) == pytest.approx(40.0, abs=3.0) and float(white(x, y)) == pytest.approx(3040.0, abs=3.0)


def test_flats_outside_the_image():
    h = pattern_to_image()
    h[0, 2] -= 100.0  # push the target half out of the frame
    with pytest.raises(EstimationError):
        radiometry.illumination(np.ones(SHAPE), *maps(h), REACH)


def test_normalise_has_no_value_where_white_is_below_black():
    x = np.array([0.0, 1.0, 2.0])
    v = radiometry.normalise(np.array([5.0, 5.0, 5.0]), lambda x, y: 0 * x, lambda x, y: 10.0 - 5 * x, x, x)
    np.testing.assert_allclose(v[:2], [0.5, 1.0])
    assert np.isnan(v[2])


def blurred_noise(rng) -> np.ndarray:
    """Values of a blurred Bernoulli(0.5) image in [0, 1], mean about 1/2."""
    u = cv2.GaussianBlur(rng.integers(0, 2, (128, 128)).astype(float), (0, 0), 0.8)
    return np.clip(u - u.mean() + 0.5, 0, 1)


@pytest.mark.parametrize("alpha", [-0.6, -0.1, 0.0, 0.25, 0.9])
def test_crf_alpha_recovers_a_known_parabola(alpha):
    u = blurred_noise(np.random.default_rng(3))
    u -= u.mean() - 0.5  # exact mean 1/2 after clipping
    # The camera applies the inverse of g(v) = alpha v^2 + (1 - alpha) v.
    if alpha == 0:
        v = u
    else:
        v = (-(1 - alpha) + np.sqrt((1 - alpha) ** 2 + 4 * alpha * u)) / (2 * alpha)
    found = radiometry.crf_alpha(v)
    # The mean condition is linear in alpha, so the recovery is exact.
    assert found == pytest.approx(alpha, abs=1e-9)
    np.testing.assert_allclose(radiometry.apply_crf(v, found), u, atol=1e-9)
    assert radiometry.apply_crf(np.array([0.0, 1.0]), found) == pytest.approx([0.0, 1.0])


def test_crf_targets_the_printed_pattern_mean():
    """The published noise averages 0.502, not 1/2: a linear camera must get alpha = 0 for it, and
    forcing 1/2 would bend the response (alpha = -0.01 here, 0.25 % of the range at mid-grey)."""
    u = blurred_noise(np.random.default_rng(5))
    u -= u.mean() - target.default_noise().mean()  # a linear camera: the image averages the cells' mean
    assert target.default_noise().mean() == pytest.approx(0.502, abs=5e-4)
    assert radiometry.crf_alpha(u, target.default_noise().mean()) == pytest.approx(0.0, abs=1e-12)
    assert abs(radiometry.crf_alpha(u)) > 0.005


def test_crf_non_monotone_is_an_error():
    u = blurred_noise(np.random.default_rng(4))
    with pytest.raises(EstimationError, match="not monotone"):
        radiometry.crf_alpha(0.2 * u)  # averages 0.1: a badly exposed or wrongly normalised target


def test_crf_binary_values():
    assert radiometry.crf_alpha(np.array([0.0, 1.0, 1.0, 0.0])) == 0.0
    with pytest.raises(EstimationError):
        radiometry.crf_alpha(np.array([0.0, 1.0, 1.0, 1.0]))
    with pytest.raises(EstimationError):
        radiometry.crf_alpha(np.array([np.nan]))


def test_real_photograph(data_dir):
    """Detection, maps and both corrections on the published example photo."""
    image = cv2.imread(str(data_dir / "img_example.pgm"), cv2.IMREAD_UNCHANGED).astype(float)
    to_image, to_pattern = geometry.target_maps(detect.find_target(image))
    black, white, tail = radiometry.illumination(image, to_image, to_pattern, REACH)
    # f/5.6 on a 400D-class green plane: diffraction alone gives lambda N / pi^3 = 0.009 px; the lens and
    # the print's paper scatter more (0.022 fitted)
    assert 0.0 < tail < 0.05
    yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]].astype(float)
    X, Y = to_pattern(xx, yy)
    v = radiometry.normalise(image, black, white, xx, yy)

    def block_mean(block):
        inside = (np.abs(X - target.block_centre(block)[0]) < 8) & (np.abs(Y - target.block_centre(block)[1]) < 8)
        return v[inside].mean()

    # The flats read black and white after normalisation (8-bit data: +-0.05).
    assert all(abs(block_mean(b)) < 0.05 for b in target.BLACK_BLOCKS)
    assert all(abs(block_mean(b) - 1) < 0.05 for b in target.WHITE_BLOCKS)
    core = (X > target.NOISE_START + 16) & (X < target.NOISE_STOP - 16) & (Y > target.NOISE_START + 16) & (Y < target.NOISE_STOP - 16)
    alpha = radiometry.crf_alpha(v[core])
    # A camera response close to linear (IJCV 2012, Fig. 13), monotone.
    assert abs(alpha) < 0.5
    assert radiometry.apply_crf(v[core], alpha).mean() == pytest.approx(0.5, abs=1e-9)
