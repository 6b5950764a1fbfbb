"""Thin-plate spline registration (Delbracio PhD thesis 2013, App. A.2)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from psfd.estimator import geometry, target
from psfd.estimator.detect import Detection
from psfd.estimator.geometry import RadialHomography, ThinPlateSpline, target_maps

PATTERN = target.xcorner_points()


def affine(points: np.ndarray) -> np.ndarray:
    a = np.array([[0.34, -0.09], [0.11, 0.36]])
    return points @ a.T + [57.0, 31.0]


def distorted(points: np.ndarray) -> np.ndarray:
    """A perspective view (5 % scale change) plus barrel distortion of about 0.5 px at the target's corners."""
    x, y = points[:, 0] - 160.0, points[:, 1] - 160.0
    w = 1.0 + 2e-4 * x + 1e-4 * y
    u, v = 0.37 * x / w, 0.37 * y / w
    r2 = (u * u + v * v) / 60.0**2
    return np.column_stack([150.0 + u * (1 - 0.003 * r2), 120.0 + v * (1 - 0.003 * r2)])


@pytest.mark.parametrize("smoothing", [0.0, 10.0, 1e6])
def test_affine_map_is_reproduced_exactly(smoothing):
    # An affine map has no bending energy, so the approximating spline fits it
    # exactly whatever lambda (thesis App. A.2: lambda -> inf gives the affine fit).
    tps = ThinPlateSpline.fit(PATTERN, affine(PATTERN), smoothing)
    grid = np.random.default_rng(0).uniform(0, 320, (500, 2))
    np.testing.assert_allclose(tps(grid), affine(grid), atol=1e-8)


def test_same_solution_as_scipy():
    # The thesis's closed form solves the same system as scipy's smoothing
    # thin-plate RBF with degree 1 and smoothing = lambda.
    rng = np.random.default_rng(1)
    dst = distorted(PATTERN) + rng.normal(0, 0.2, PATTERN.shape)
    points = rng.uniform(0, 320, (300, 2))
    for smoothing in (0.0, 10.0, 1e4):
        ours = ThinPlateSpline.fit(PATTERN, dst, smoothing)(points)
        ref = RBFInterpolator(PATTERN, dst, kernel="thin_plate_spline", smoothing=smoothing, degree=1)(points)
        np.testing.assert_allclose(ours, ref, atol=1e-8)


def test_interpolates_with_no_smoothing_and_approximates_with_more():
    rng = np.random.default_rng(2)
    dst = distorted(PATTERN) + rng.normal(0, 0.3, PATTERN.shape)
    exact = ThinPlateSpline.fit(PATTERN, dst, 0.0)
    np.testing.assert_allclose(exact(PATTERN), dst, atol=1e-8)
    stiff = ThinPlateSpline.fit(PATTERN, dst, 1e9)
    design = np.column_stack([np.ones(12), PATTERN])
    coef, *_ = np.linalg.lstsq(design, dst, rcond=None)
    np.testing.assert_allclose(stiff(PATTERN), design @ coef, atol=1e-3)


INNER = np.stack(np.meshgrid(np.linspace(32, 288, 17), np.linspace(32, 288, 17)), axis=-1).reshape(-1, 2)


def test_perspective_is_exact_with_the_homography():
    # 10 % scale change across the target: the spline alone (the thesis's
    # model) misses the noise region's interior by a quarter pixel, the
    # homography + spline of target_maps not at all.
    def perspective(points):
        x, y = points[:, 0] - 160.0, points[:, 1] - 160.0
        w = 1.0 + 3e-4 * x - 1e-4 * y
        return np.column_stack([150.0 + 0.37 * x / w, 120.0 + 0.37 * y / w])

    detection = Detection(corners=perspective(PATTERN), pattern_points=PATTERN, scale=0.37)
    for projective, worst in ((True, 1e-6), (False, 0.2)):
        to_image, _ = target_maps(detection, projective=projective)
        x, y = to_image(INNER[:, 0], INNER[:, 1])
        error = np.hypot(x - perspective(INNER)[:, 0], y - perspective(INNER)[:, 1]).max()
        assert (error < worst) if projective else (error > worst), (projective, error)


def test_smooth_distortion_within_tolerance():
    # Perspective plus ~0.5 px of barrel distortion, 12 corners, lambda = 10:
    # in the noise region the maps follow it to half the 0.1 px tolerance of
    # the corner detection (the residual is the interior bulge of the radial
    # term, which no point on the ring constrains).
    detection = Detection(corners=distorted(PATTERN), pattern_points=PATTERN, scale=0.37)
    to_image, to_pattern = target_maps(detection)
    x, y = to_image(INNER[:, 0], INNER[:, 1])
    truth = distorted(INNER)
    assert np.hypot(x - truth[:, 0], y - truth[:, 1]).max() < 0.05
    X, Y = to_pattern(truth[:, 0], truth[:, 1])
    assert np.hypot(X - INNER[:, 0], Y - INNER[:, 1]).max() < 0.05 / 0.37  # the same in cells


def test_map_keeps_shapes():
    tps = ThinPlateSpline.fit(PATTERN, affine(PATTERN))
    x, y = np.meshgrid(np.arange(5.0), np.arange(3.0))
    X, Y = tps.map(x, y)
    assert X.shape == Y.shape == (3, 5)
    np.testing.assert_allclose(np.stack([X.ravel(), Y.ravel()], 1), affine(np.stack([x.ravel(), y.ravel()], 1)))


def test_degenerate_points_are_refused():
    with pytest.raises(ValueError):
        ThinPlateSpline.fit(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]), np.zeros((4, 2)))
    with pytest.raises(ValueError):
        ThinPlateSpline.fit(PATTERN[:2], PATTERN[:2])


def test_target_maps_are_inverse_of_each_other():
    detection = Detection(corners=distorted(PATTERN), pattern_points=PATTERN, scale=0.37)
    to_image, to_pattern = target_maps(detection)
    X, Y = np.meshgrid(np.linspace(32, 288, 9), np.linspace(32, 288, 9))
    x, y = to_image(X, Y)
    back_x, back_y = to_pattern(x, y)
    # Two separately fitted splines: consistent to a small fraction of a cell
    # (0.05 cell = 0.02 px at this scale).
    assert np.abs(back_x - X).max() < 0.05 and np.abs(back_y - Y).max() < 0.05
    # and each follows the true distortion.
    truth = distorted(np.stack([X.ravel(), Y.ravel()], 1))
    assert np.abs(np.stack([x.ravel(), y.ravel()], 1) - truth).max() < 0.05


# --------------------------------------------------------------------------- model choice
def _view(points: np.ndarray, rotation_deg: float, k1: float = 0.0) -> np.ndarray:
    """Pattern cells -> image pixels: 0.33 px per cell, rotated, slight perspective, then
    radial distortion as in simulate.simulate_target (k1 on the 400 px half-diagonal of a
    (480, 640) sensor, the target centred at (150, 120) px, well off the optical centre)."""
    a = np.deg2rad(rotation_deg)
    x, y = points[:, 0] - 160.0, points[:, 1] - 160.0
    w = 1.0 + 1.5e-4 * x - 1e-4 * y
    u = 0.33 * (np.cos(a) * x - np.sin(a) * y) / w + 150.0 - 319.5
    v = 0.33 * (np.sin(a) * x + np.cos(a) * y) / w + 120.0 - 239.5
    f = 1.0 - k1 * (u * u + v * v) / 400.0**2  # distorted ~ undistorted (1 - k1 r^2)
    return np.column_stack([319.5 + u * f, 239.5 + v * f])


def _map_error(to_image, truth) -> float:
    x, y = to_image(INNER[:, 0], INNER[:, 1])
    return float(np.sqrt(np.mean((x - truth[:, 0]) ** 2 + (y - truth[:, 1]) ** 2)))


SIGMA = 0.05  # X-corner error beyond the common bias, pixels (detect.find_target: 0.03-0.1 with the bias)


@pytest.mark.parametrize("rotation_deg", [0.0, 14.0, 30.0, 45.0])
def test_noisy_corners_are_not_copied_into_the_interior(rotation_deg):
    # A least-squares homography (8 parameters, 24 coordinates) predicts the
    # interior with an RMS error of about SIGMA sqrt(8 / 24) = 0.029 px
    # (measured 0.024-0.036 over 12 draws); allow 0.04. lambda = 10 cells^2
    # copies the corner noise into the interior instead (0.054-0.067).
    rng = np.random.default_rng(int(rotation_deg))
    truth = _view(INNER, rotation_deg)
    detection = Detection(corners=_view(PATTERN, rotation_deg) + rng.normal(0, SIGMA, PATTERN.shape),
                          pattern_points=PATTERN, scale=0.33)
    error = _map_error(target_maps(detection)[0], truth)
    assert error < 0.04
    assert _map_error(target_maps(detection, smoothing=10.0)[0], truth) > error


@pytest.mark.parametrize("k1", [0.05, 0.1])
def test_off_centre_lens_distortion_is_followed(k1):
    # k1 = 0.05-0.1 leaves 0.12-0.27 px beyond the best homography in the
    # noise region; the radial terms take it up. With 11 parameters the
    # prediction error is about SIGMA sqrt(11 / 24) = 0.034 px at the corners
    # and more inside, where the cubic term is extrapolated from the ring
    # (measured 0.041-0.065 over 8 draws); allow 0.075.
    rng = np.random.default_rng(3)
    truth = _view(INNER, 14.0, k1)
    detection = Detection(corners=_view(PATTERN, 14.0, k1) + rng.normal(0, SIGMA, PATTERN.shape),
                          pattern_points=PATTERN, scale=0.33)
    to_image, to_pattern = target_maps(detection)
    assert _map_error(to_image, truth) < 0.075
    homography = RadialHomography.fit(PATTERN, detection.corners, radial=False)
    assert _map_error(homography.to_image, truth) > 0.1
    X, Y = to_pattern(truth[:, 0], truth[:, 1])  # the inverse agrees (in cells)
    assert np.sqrt(np.mean((X - INNER[:, 0]) ** 2 + (Y - INNER[:, 1]) ** 2)) < 0.075 / 0.33


def test_radial_map_inverts_itself():
    model = RadialHomography.fit(PATTERN, _view(PATTERN, 30.0, 0.1))
    assert np.any(model.params)
    x, y = model.to_image(INNER[:, 0], INNER[:, 1])
    X, Y = model.to_pattern(x, y)
    np.testing.assert_allclose(np.column_stack([X, Y]), INNER, atol=1e-6)


def test_thesis_spline_is_still_available():
    # An explicit lambda gives the homography + thin-plate spline of App. A.2 unchanged.
    rng = np.random.default_rng(5)
    corners = _view(PATTERN, 14.0) + rng.normal(0, SIGMA, PATTERN.shape)
    to_image, _ = target_maps(Detection(corners=corners, pattern_points=PATTERN, scale=0.33), smoothing=10.0)
    h, _ = cv2.findHomography(PATTERN, corners, 0)
    tps = ThinPlateSpline.fit(PATTERN, corners - cv2.perspectiveTransform(PATTERN[None], h)[0], 10.0)
    expected = cv2.perspectiveTransform(INNER[None], h)[0] + tps(INNER)
    np.testing.assert_allclose(np.column_stack(to_image(INNER[:, 0], INNER[:, 1])), expected, atol=1e-9)
    with pytest.raises(ValueError):
        target_maps(Detection(corners=corners, pattern_points=PATTERN, scale=0.33), smoothing="gcv")


@pytest.mark.parametrize("q", [0.001, 0.01, 0.05, 0.5])
@pytest.mark.parametrize("d1", [1, 3, 5])
@pytest.mark.parametrize("d2", [1, 2, 13, 37, 1000])
def test_the_f_quantile_is_scipys(q, d1, d2):
    """geometry.f_quantile (which spares scipy.special's start-up) against scipy.special.fdtri and
    scipy.stats: to 1e-10 relative (the continued fraction to ~1e-12 absolute, the bisection to the last bit
    of the smaller of x and 1 - x; measured at most 5e-13 here)."""
    import scipy.stats
    from scipy import special

    ours = geometry.f_quantile(q, d1, d2)
    assert ours == pytest.approx(special.fdtri(d1, d2, 1.0 - q), rel=1e-10)
    assert ours == pytest.approx(scipy.stats.f.isf(q, d1, d2), rel=1e-10)
