"""The Bernoulli-target estimator against photographs of the independent renderer (tests/render.py).

Each render is estimated twice: through the whole pipeline a user runs
(`estimate_target`: detection, geometry, illumination, response curve,
solver), and through `estimate_plane` with the true map and the true light
field, which leaves the solver and the model of u~_D alone. The estimate is
compared with the truth over the s-band as `render.compare` defines it: the
MTF error along the fx and fy axes up to s/2 cycles per pixel (s x Nyquist),
and the mean signed MTF error over the 2-D band where the true MTF exceeds
0.05. On a k x k support the truth is the sampled kernel plus the mass beyond
the support as a pedestal, which is what least squares returns for it (render
module docstring).

Tolerances, from the reported noise floor F = sigma_n sqrt(trace((A^T A)^-1))
(IJCV 2012 sec. 3.1: E||h_ls - h||^2 = F^2):

- MAX_MTF = 0.02. The least-squares error e has E|DFT(e)(f)|^2 = F^2 at each
  frequency for a near-white error (the Bernoulli Gram matrix is near a
  multiple of the identity, IJCV 2012 sec. 3.2), so the MTF error at one
  frequency has a standard deviation of about F / sqrt(2), and its maximum
  over the ~k independent frequencies of the two profiles stays below
  3 F / sqrt(2) with 99 % probability. The non-negative solution is the
  projection of h_ls onto h >= 0 in the metric of A^T A, a convex set that
  holds the truth, so it can only come closer. For F <= MAX_FLOOR = 0.0075
  the noise takes at most 0.016, which leaves 0.004 for the model (above it
  the tolerance is 3 F / sqrt(2) + 0.004, up to F = 0.016: the whole
  pipeline's floor counts the misregistration of the detected map in
  sigma_n, 0.0086 on a render whose floor with the true map is 0.0033).
  Noise-free renders with the true light field measure 0.001-0.003 for the
  kernels with no mass beyond the support. Diffraction
  has 3-8 % there, and the pedestal describes only its mean: noise-free,
  0.008 at f/5.6 (3 %) and 0.016 at f/22 (8 %), about a quarter of that
  mass; half of it is added to the tolerance.
- MAX_BIAS = 0.01. The mean signed error averages the noise over the >= 100
  independent frequencies where the MTF exceeds 0.05: its standard deviation
  is below F / sqrt(2 x 100) = 0.0011 even at F = 0.016, the noise floor of
  the published photograph and of the photo-like renders here, and the
  noise-free model bias is below 0.003. The old default (negative values
  clipped, the rest renormalised) misses it by -0.027 at that noise: its
  clipped tail noise becomes mass.
- The whole pipeline is held to the same tolerances (before, the flare below
  was added to all three, the floor's bound included). Its light model once
  added a bias: it took the centres of the flat squares as pure black and
  white, but a diffraction PSF's far tail (intensity ~ r^-3, edge spread
  ~ 1/r) brings light into them, c_b above black and c_w below white
  (`Render.flare`, from the truth: 0.045 together for f/22 at 0.4 pixel per
  cell), the normalised plane was stretched by 1 / (1 - c_b - c_w) and the
  kernel with it: +0.014 to +0.019 mean signed MTF error at f/22, +0.009 at
  f/11. radiometry.illumination now fits that tail with the fields.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import render

from psfd.estimator import bernoulli, detect, geometry, radiometry

S = 4
MAX_MTF = 0.02
MAX_BIAS = 0.01
MAX_FLOOR = 0.0075  # the noise floor that justifies MAX_MTF (module docstring)
MODEL = MAX_MTF - 3 * MAX_FLOOR / math.sqrt(2)  # what MAX_MTF leaves for the model: 0.004
PHOTO_FLOOR = 0.016  # the floor up to which MAX_BIAS holds (module docstring)
LAB = render.Exposure(electrons=30000.0)  # a base-ISO RAW: mid-grey noise 0.5 % of the black-to-white range
PHOTO = render.Exposure(electrons=5000.0)  # the noise of the published photograph: 1.2 %


def _render(kind: str, support: int, pixels_per_cell: float, rotation: float, seed: int = 1):
    kernel = render.KINDS[kind]
    view = render.View(pixels_per_cell, rotation_deg=rotation, tilt=(0.04, -0.03))
    return render.render(kernel, view, seed=seed, exposure=LAB, name=f"{kind}-{support}"), support


def _true_light(shot, support, **kwargs) -> dict:
    (result,) = bernoulli.estimate_plane(shot.normalised(), shot.to_pattern, s=S, support=support, **kwargs)
    return result


def _check(errors: render.Errors, floor: float, kernel: render.Kernel, support: int) -> None:
    assert floor <= PHOTO_FLOOR, f"noise floor {floor:.4f}: the bias tolerance is not justified"
    noise = MAX_MTF if floor <= MAX_FLOOR else 3 * floor / math.sqrt(2) + MODEL  # module docstring
    tail = kernel.outside(S, support) / 2  # what the pedestal leaves out of the mass beyond the support
    assert errors.max_mtf <= noise + tail, errors
    assert abs(errors.mean_signed) <= MAX_BIAS, errors


# --------------------------------------------------------------------------- default suite: two small renders

FAST = {"gaussian-17": ("gaussian", 17, 0.30, 0.0), "defocus-25": ("defocus", 25, 0.33, 180.0)}


@pytest.fixture(scope="module", params=list(FAST))
def fast(request):
    """A render, its estimate with the true map and light, and through the whole pipeline (default solver)."""
    shot, support = _render(*FAST[request.param])
    (est,) = bernoulli.estimate_target(shot.frame, support=support)
    return shot, support, _true_light(shot, support), est


def test_solver_is_accurate_and_unbiased(fast):
    """The default solver with the true map and light: MTF within 0.02, no bias (module docstring)."""
    shot, support, result, _ = fast
    _check(render.compare(result["psf"], shot.kernel, S), result["noise_floor"], shot.kernel, support)


def test_whole_pipeline_is_accurate_and_unbiased(fast):
    shot, support, _, est = fast
    _check(render.compare(est.psf, shot.kernel, S), est.noise_floor, shot.kernel, support)
    assert est.warnings == []


def test_lower_end_of_the_papers_scale_range():
    """s/t = 0.7, the smallest imaging scale of IJCV 2012 sec. 3.3 (0.175 px/cell at s = 4), through the
    whole pipeline: the target is found (its marks centred on the image smoothed half as much) and the PSF
    is as accurate as at the advised scale, within its larger noise floor (0.009: the noise covers 45 x 45
    pixels)."""
    shot, support = _render("gaussian", 17, 0.175, 20.0)
    (est,) = bernoulli.estimate_target(shot.frame, support=support)
    _check(render.compare(est.psf, shot.kernel, S), est.noise_floor, shot.kernel, support)


def test_a_psf_too_wide_for_the_marks_is_said_to_be():
    """A Gaussian of 1.2 px at 0.25 px/cell (the PSF's sigma 5.1 cells) blurs the squares beside each mark
    into its refinement window: the corners are pulled 0.6-0.9 px off, and the PSF through the whole pipeline
    has its MTF50 6-7 % low while the estimate with the true map is within 1 %. The PSF says so and says how
    close to bring the target; at 0.4 px/cell the same lens is measured without the warning, within tolerance."""
    kernel = render.gaussian(1.2)
    far = render.render(kernel, render.View(0.25, rotation_deg=20.0, tilt=(0.04, -0.03)), seed=1, exposure=LAB)
    (est,) = bernoulli.estimate_target(far.frame, support=25)
    (warning,) = [w for w in est.warnings if "marks" in w]
    assert "bring the target closer, a cell to 0.43 pixel or more" in warning, warning
    near = render.render(kernel, render.View(0.4, rotation_deg=20.0, tilt=(0.04, -0.03)), seed=1, exposure=LAB)
    (est,) = bernoulli.estimate_target(near.frame, support=25)
    assert not [w for w in est.warnings if "marks" in w], est.warnings
    _check(render.compare(est.psf, kernel, S), est.noise_floor, kernel, 25)


def test_no_bias_at_the_noise_of_the_published_photograph(fast):
    """At 1.2 % noise (floor 0.008-0.016 here, img_example.pgm: 0.0098) the default stays unbiased where
    clipping the negative values makes the PSF too wide (-0.02 to -0.05 on a 25 x 25 support,
    bench/bench_accuracy.py; -0.009 at 17 x 17, inside the tolerance, so the contrast is shown at 25)."""
    shot, support, _, _ = fast
    noisy = shot.exposed(PHOTO, seed=2)
    (est,) = bernoulli.estimate_target(noisy.frame, support=support)
    assert est.noise_floor <= 0.016
    errors = render.compare(est.psf, shot.kernel, S)
    assert abs(errors.mean_signed) <= MAX_BIAS, errors
    if support < 25:
        return
    (clipped,) = bernoulli.estimate_target(noisy.frame, support=support, solver="ls-threshold")
    too_wide = render.compare(clipped.psf, shot.kernel, S)
    assert too_wide.mean_signed < errors.mean_signed - 0.01 and too_wide.width_ratio > 1.2, too_wide


def test_prediction_error_is_near_one_and_flags_a_kernel_that_does_not_hold(fast):
    """Cross-validated prediction error (bernoulli.cross_validated): about sqrt(1 + k^2 / (M / 2)) with
    the model right (1.02-1.06 here); a 0.2 % scale error of the map (misregistration up to 0.1 pixel at
    the edges of the noise region, in opposite directions on opposite halves) raises it above 1.3."""
    shot, support, right, _ = fast
    expected = math.sqrt(1 + support**2 / (right["count"] / 2))
    assert 0.97 < right["prediction_error"] < expected + 0.05
    if support > 17:
        return  # the misregistered fit is shown once, on the small support
    cx, cy = (shot.frame.shape[1] - 1) / 2, (shot.frame.shape[0] - 1) / 2

    def misregistered(x, y):
        return shot.to_pattern(cx + (np.asarray(x) - cx) * 1.002, cy + (np.asarray(y) - cy) * 1.002)

    (wrong,) = bernoulli.estimate_plane(shot.normalised(), misregistered, s=S, support=support)
    assert wrong["prediction_error"] > 1.3 > right["prediction_error"]


# --------------------------------------------------------------------------- default suite: a diffraction tail


@pytest.fixture(scope="module")
def diffraction():
    """f/22 on a 2 x 4.3 um plane (lambda N = 1.41 px) at 0.30 pixel per cell: the far tail brings 0.06 of the
    span into the centres of the flat squares (`Render.flare`), which the old light model read as black and white."""
    shot, support = _render("airy-f22", 17, 0.30, 30.0)
    assert sum(shot.flare()) > 0.05
    return shot, support


def test_whole_pipeline_is_unbiased_under_a_diffraction_tail(diffraction):
    """Through the whole pipeline, f/22 is as accurate as with the true light (the old light model:
    max 0.045, signed +0.019, width 0.94; now 0.016, +0.002, 1.00; true light 0.017, +0.000, 1.01)."""
    shot, support = diffraction
    (est,) = bernoulli.estimate_target(shot.frame, support=support)
    errors = render.compare(est.psf, shot.kernel, S)
    _check(errors, est.noise_floor, shot.kernel, support)
    # _check allows half the mass beyond the support (6 % here) on top of MAX_MTF for the support's own
    # model error; on this render that error and the noise leave 0.017 with the true light, so the
    # light model must not add to it: MAX_MTF itself holds
    assert errors.max_mtf <= MAX_MTF, errors
    assert est.warnings == []
    assert est.params["light_tail"] > 0.03  # recorded with the PSF (docs/formats.md)


def test_light_fields_are_the_levels_without_the_tail(diffraction):
    """The fitted fields are the true black and white levels, not the flat squares' centres, and the
    fitted tail amplitude is the diffraction asymptote's, lambda N / pi^3 (radiometry.illumination)."""
    shot, support = diffraction
    to_image, to_pattern = geometry.target_maps(detect.find_target(shot.frame.data))
    black, white, tail = radiometry.illumination(shot.frame.data, to_image, to_pattern, (support - 1) / (2 * S))
    fnumber, wavelength, pitch = 22.0, 0.55, 8.6  # render.KINDS["airy-f22"]
    assert tail == pytest.approx(wavelength * fnumber / pitch / math.pi**3, rel=0.15)
    # the true fields over the noise region, in units of the true span (the old model read the squares'
    # centres: black +0.035, white -0.027, `Render.flare`)
    X, Y = np.meshgrid(np.linspace(40, 280, 9), np.linspace(40, 280, 9))
    x, y = shot.to_image(X, Y)
    level = shot.exposure.electrons * shot.exposure.dn_per_electron * shot.light(x, y)
    true_black, true_white = level * shot.paper.black, level * shot.paper.white
    span = true_white - true_black
    assert np.abs((black(x, y) - true_black) / span).max() < 0.005
    assert np.abs((white(x, y) - true_white) / span).max() < 0.005


# --------------------------------------------------------------------------- default suite: low light

LOW_LIGHT = render.Exposure(electrons=150.0)  # at reflectance 1: a floor of 36 % of the kernel's L2 norm here
# MTF50 of the kept (not recentred) estimate over the truth's, minus 1, at LOW_LIGHT: mean and standard
# deviation over both axes and the noise seeds 1-10 of `Render.exposed` (-10.3 to +0.7 %): the non-negative
# solution keeps the positive half of the tail noise (bench/bench_conditions.py)
KEPT_BIAS, KEPT_SPREAD = -0.051, 0.028


def test_recentring_adds_no_bias_in_low_light():
    """At 150 e- the recentred kernel keeps the MTF50 of the kept one: the recentring re-solves the
    non-negative kernel on the shifted grid (bernoulli._shifted_nnls) where it used to clip the Fourier
    shift's ringing, whose positive half became mass in the tails.

    Over noise seeds 1-4 and both axes: the recentred MTF50 over the kept one differs by 0.45 % (standard
    deviation of one axis and seed, 10 seeds; the constraint h >= 0 holds on other samples), so their mean
    over these 8 stays within 1 % (6 standard deviations; -0.02 % here); the clip made it -4.9 % (-1.1 to
    -7.4 % on 10 seeds). Against the truth the mean is the kept path's bias, KEPT_BIAS, within 3 standard
    errors of an 8-value mean (KEPT_SPREAD / sqrt(8)): -6.2 % here, the clip -10.8 %.
    """
    shot, support = _render("gaussian", 17, 0.30, 20.0)
    truth = render.mtf50(render.support_truth(shot.kernel, S, support), S)
    to_kept, to_truth = [], []
    for seed in (1, 2, 3, 4):
        dark = shot.exposed(LOW_LIGHT, seed=seed)
        (est,) = bernoulli.estimate_target(dark.frame, support=support)
        (kept,) = bernoulli.estimate_target(dark.frame, support=support, recentre=False)
        assert est.noise_floor > 0.3 * np.linalg.norm(est.psf)  # the low light this is about
        assert np.hypot(*est.params["kernel_shift"]) > 0.05  # a sub-sample shift was removed
        mtf50 = render.mtf50(est.psf, S)
        to_kept += list(mtf50 / render.mtf50(kept.psf, S) - 1)
        to_truth += list(mtf50 / truth - 1)
    assert abs(np.mean(to_kept)) < 0.01, to_kept
    assert abs(np.mean(to_truth) - KEPT_BIAS) < 3 * KEPT_SPREAD / math.sqrt(8), to_truth


# --------------------------------------------------------------------------- slow: every kind

SLOW = {
    "gaussian-25": ("gaussian", 25, 0.35, 60.0),
    "anisotropic-17": ("anisotropic", 17, 0.50, 35.0),
    "airy-f5.6-17": ("airy-f5.6", 17, 0.37, 100.0),
    "airy-f11-17": ("airy-f11", 17, 0.33, 45.0),
    "airy-f11-25": ("airy-f11", 25, 0.35, 160.0),
    "airy-f22-17": ("airy-f22", 17, 0.35, 120.0),
    "airy-f22-25": ("airy-f22", 25, 0.40, 75.0),
    "defocus-25-upright": ("defocus", 25, 0.45, 180.0),
}


@pytest.mark.slow
@pytest.mark.parametrize("case", list(SLOW))
def test_every_kind(case):
    shot, support = _render(*SLOW[case], seed=3)
    result = _true_light(shot, support)
    _check(render.compare(result["psf"], shot.kernel, S), result["noise_floor"], shot.kernel, support)
    (est,) = bernoulli.estimate_target(shot.frame, support=support)
    _check(render.compare(est.psf, shot.kernel, S), est.noise_floor, shot.kernel, support)
