"""Thin-plate spline registration (Delbracio PhD thesis 2013, App. A.2)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import RBFInterpolator

from psfd.estimator import target
from psfd.estimator.detect import Detection
from psfd.estimator.register import ThinPlateSpline, target_maps

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
