"""The two-photo (two-scale) blind PSF estimator: simulated pairs of known PSF and the real wall pair."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import cv2
import numpy as np
import pytest

from psfd.errors import BadInputError, PairError
from psfd import workers
from psfd.estimator import kernels, mtf, pair_register, raw, simulate, twoscale

from conftest import DATA

S = 3
SUPPORT = 4 * S + 1
# aliased on the channel grid (MTF at Nyquist ~0.25), anisotropic so that x and y are told apart
TRUE_PSF = simulate.gaussian_psf(0.45, 0.55, s=S, support=SUPPORT)

# MTF tolerance. The kernel's L2 error from sensor noise (PSF.noise_floor,
# sigma sqrt(trace((A^T A)^-1)), IJCV 2012 sec. 2) is 0.013-0.024 on these
# pairs, and by Parseval that is the RMS error of one MTF sample; 0.05 allows
# about 3 sigma over the profile. Without noise the bias (registration, the
# near photo's aliasing, SIAM 2012 eq. (8)) measures 0.010-0.016.
MTF_TOL = 0.05


def _mtf_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Largest |MTF| difference along x and y, up to s times the channel Nyquist (s/2 cycles/pixel)."""
    _, ex, ey = mtf.profiles(estimate, S)
    _, tx, ty = mtf.profiles(truth, S)
    return float(max(np.abs(ex - tx).max(), np.abs(ey - ty).max()))


# f/11 diffraction through an 8 um square photosite: an Airy pattern, not a Gaussian. Its MTF is
# below 0.01 beyond 0.8 x the s-grid Nyquist, where the simulator starts tapering the scene; sharper
# kernels (f/8: 0.04, f/4: 0.2) leave the band-limited model (SIAM 2012, sec. 2) and that taper
# shows up in their estimate.
DIFFRACTION_PSF = simulate.diffraction_psf(11.0, s=S, support=SUPPORT)


@pytest.fixture(
    scope="module",
    params=[(TRUE_PSF, 4.0), (TRUE_PSF, 6.0), (DIFFRACTION_PSF, 5.0)],
    ids=["gaussian-lambda4", "gaussian-lambda6", "diffraction-lambda5"],
)
def simulated(request):
    psf, lam = request.param
    pair = simulate.simulate_pair(psf=psf, s=S, lam=lam, offset=(1.3, -0.7), seed=1)
    # far first: the order must not matter
    [estimate] = twoscale.estimate_pair(pair["far"], pair["near"], s=S)
    return pair, estimate


def test_recovers_the_mtf_of_a_simulated_pair(simulated):
    pair, est = simulated
    assert _mtf_error(est.psf, pair["psf"]) < MTF_TOL
    assert est.method == "two-photo" and est.s == S and est.psf.shape == (SUPPORT, SUPPORT)
    assert est.psf.sum() == pytest.approx(1.0)
    assert est.sources == ["simulated-near", "simulated-far"]
    # SIFT + homography: the zoom within 0.5 % (far-pixel registration error ~0.1 px over ~100 px)
    assert est.params["lambda"] == pytest.approx([pair["lam"]] * 2, rel=5e-3)
    assert est.params["inliers"] >= pair_register.MIN_INLIERS
    assert est.params["spectral_energy"] > 0
    assert est.noise_floor is not None and est.noise_floor < 0.03
    assert set(est.figures) == {"kernel", "residual"}
    assert est.figures["kernel"].shape == (SUPPORT, SUPPORT)
    x0, y0, x1, y1 = est.window
    assert est.figures["residual"].shape == (y1 - y0, x1 - x0)
    # the residual is at the noise level: sensor noise is ~0.3 % of the range at mid grey
    assert est.residual < 0.006


def test_clip_projects_on_non_negative_kernels(simulated):
    pair, est = simulated
    [clipped] = twoscale.estimate_pair(pair["near"], pair["far"], s=S, clip=True)
    assert clipped.psf.min() >= 0.0 and clipped.psf.sum() == pytest.approx(1.0)
    assert clipped.params["clip"] is True
    # clipping the negative mass m and renormalising moves the kernel by at most 2 m in L1,
    # hence its MTF by at most 2 m (SIAM 2012, sec. 4.3 projects on h >= 0)
    negative = float(-est.psf[est.psf < 0].sum())
    assert _mtf_error(clipped.psf, est.psf) <= 2 * negative + 1e-9


def test_saturated_pixels_are_left_out():
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, seed=10)
    [plain] = twoscale.estimate_pair(pair["near"], pair["far"], s=S)
    near, far = pair["near"], pair["far"]
    # clip a bright patch in each photo, as an over-exposed spot would
    near_data, near_sat = near.data.copy(), near.saturated.copy()
    near_data[150:200, 150:200], near_sat[150:200, 150:200] = near.white, True
    # the far patch apart from the near one's image (far pixels 53-66 in both directions)
    far_data, far_sat = far.data.copy(), far.saturated.copy()
    far_data[90:100, 30:50], far_sat[90:100, 30:50] = far.white, True
    near = dataclasses.replace(near, data=near_data, saturated=near_sat)
    far = dataclasses.replace(far, data=far_data, saturated=far_sat)
    [est] = twoscale.estimate_pair(near, far, s=S)
    # the far patch drops 10 x 20 far pixels; the near one (50 + 2 SATURATED_RADIUS) / 4 far pixels across,
    # (q - 1) / s more with the footprint q the holes are eroded by (`hole_footprint`: 7 here, 15 x 15 dropped)
    q = est.params["hole_footprint"]
    assert est.params["equations"] < plain.params["equations"] - 200 - int(50 / 4 + (q - 1) / S) ** 2
    assert _mtf_error(est.psf, TRUE_PSF) < MTF_TOL


def test_a_scene_brighter_at_the_edge_of_the_common_region():
    """The illumination level of the pair is removed over the far pixels the kernel is fitted on.

    The scene is darker inside the near photo's field than in a frame along its edge, which the resampled
    near window holds and the eroded far pixels mostly do not. Each image's mean taken over its own region
    (IPOL 2013, sec. 4.2) then left a constant in the far photo that no kernel explains: max MTF error 0.49
    and noise floor 0.14 here (RMS residual 0.016 against 0.003 of noise); with the offset fitted on the pixels
    used, 0.018 and 0.018, within MTF_TOL as the plain pairs. On renders of the Bernoulli print at two
    distances by tests/render.py (a Gaussian of 0.45 pixel, s = 3, lambda 4 and 8, no noise) the same
    offset made the max MTF error 0.05-0.20 and the RMS width 0.76-0.78 of the truth's; fitted: 0.014-0.018, 0.99.
    """
    lam, rp = 4.0, 2.0  # simulate_pair's default raster pixels per near pixel
    side = int(np.ceil(rp * lam * 128)) + 32  # its default scene size for a 128-pixel far photo
    tex = simulate.texture_scene((side, side), seed=1)
    y, x = np.mgrid[0:side, 0:side]
    centre = (side - 1) / 2
    edge = np.maximum(np.abs(x - centre), np.abs(y - centre)) > rp * 384 / 2 - 1.5 * lam * rp  # near field: 384 px
    scene = np.where(edge, np.minimum(1.8 * tex, 0.98), 0.6 * tex)
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=lam, scene=scene, offset=(1.3, -0.7), seed=1)
    [est] = twoscale.estimate_pair(pair["far"], pair["near"], s=S)
    assert _mtf_error(est.psf, TRUE_PSF) < MTF_TOL
    assert est.noise_floor < 0.03


def test_matches_are_one_to_one():
    """A keypoint of the far photo nearest to several of the near one keeps only its closest match."""
    rng = np.random.default_rng(0)
    far = rng.normal(size=(5, 128)).astype(np.float32) * 50
    near = np.vstack([far[0] + rng.normal(size=(10, 128)).astype(np.float32),
                      rng.normal(size=(5, 128)).astype(np.float32) * 50])
    closest = int(np.argmin(np.linalg.norm(near[:10] - far[0], axis=1)))
    near_points = rng.uniform(0, 100, (15, 2))
    pa, pb = pair_register.match(near_points, near, np.arange(10.0).reshape(5, 2), far)
    assert len(pb) == len(np.unique(pb, axis=0)) == 1
    assert np.array_equal(pa[0], near_points[closest]) and np.array_equal(pb[0], [0.0, 1.0])


def test_a_homography_collapsing_the_plane_is_no_registration():
    """45 near points matched to one far point fit a homography of rank 1 with 45 inliers; counted as the
    distinct places they are, they are one, and the pair is not registered (it was, and the refit on those
    inliers then failed with a TypeError)."""
    rng = np.random.default_rng(0)
    near = rng.uniform(0, 500, (60, 2))
    far = np.vstack([np.tile([[85.98, 84.59]], (45, 1)), rng.uniform(0, 150, (15, 2))])
    with pytest.raises(PairError, match="unrelated photos: 1 of 60"):
        pair_register._robust_fit(near, far, pair_register.PRECISION, 150.0 * 150.0)


def _tapered(sigma: float, cutoff: float):
    """A Gaussian of ``sigma`` pixels whose transfer function falls to 0 at ``cutoff`` cycles per pixel (raised
    cosine from half of it): the near photo of a pair at lambda = 8, s = 3 then holds no aliasing in the band
    the kernel is read from (below s / (2 lambda), aliases from 1 - s / (2 lambda) on; SIAM 2012, eq. (8))."""
    import render

    g = render.gaussian(sigma)

    def optics(fx, fy):
        t = np.clip((np.hypot(fx, fy) / cutoff - 0.5) / 0.5, 0.0, 1.0)
        return g.optics(fx, fy) * (0.5 + 0.5 * np.cos(np.pi * t))

    return render.Kernel(f"gaussian {sigma:g} tapered to {cutoff:g}", optics, cutoff)


@pytest.mark.slow
@pytest.mark.parametrize("case", ["gaussian-lambda4", "tapered-lambda8"])
def test_the_print_at_two_distances_from_the_independent_renderer(case):
    """The Bernoulli print photographed at two distances by tests/render.py (its own optics, sampling and
    sensor; nothing shared with the estimator or psfd.estimator.simulate), against the truth
    (`render.support_truth`, the band-limited samples of the continuous kernel).

    Measured: a Gaussian of 0.45 pixel at lambda = 4 (30000 e-), max MTF error over the band 0.024, L2 0.007,
    noise floor 0.015 (each image's mean removed on its own region: 0.126, 0.023, 0.036); the tapered
    Gaussian at lambda = 8 without noise: 0.015, 0.004, 0.003 (85 matches to 21 far keypoints: the robust fit
    took 49 near points all matched to one far point as the inliers of a collapsing homography, and the refit
    failed with a TypeError; with one-to-one matches, the former offset gave 0.155).
    Allowed: MTF_TOL.
    """
    import render

    if case == "gaussian-lambda4":
        kernel, near_ppc, lam, size, exposure = render.gaussian(0.45), 1.2, 4.0, 420, render.Exposure(30000.0)
    else:
        kernel, near_ppc, lam, size, exposure = _tapered(0.35, 0.8), 1.6, 8.0, 560, render.Exposure(float("inf"))
    flat = render.Light((0.0,) * 5)
    near = render.render(kernel, render.View(near_ppc), shape=(size, size), seed=0, light=flat, exposure=exposure,
                         name="near")
    far = render.render(kernel, render.View(near_ppc / lam), shape=(150, 150), seed=7, light=flat, exposure=exposure,
                        name="far")
    [est] = twoscale.estimate_pair(near.frame, far.frame, s=S)
    assert est.params["lambda"] == pytest.approx([lam, lam], rel=2e-3)
    errors = render.compare(est.psf, kernel, S)
    assert errors.max_mtf_2d < MTF_TOL, errors


@pytest.mark.parametrize("shift", [(0.2, -0.2), (0.5, 0.5)])
def test_the_kernel_is_recentred_without_losing_its_high_frequencies(shift):
    """The sub-sample move that centres k keeps its MTF: k is band-limited to the s-grid band (SIAM 2012,
    Lemma 1), so the move is exact but for round-off and the truncation at the support. A sharp kernel
    (Gaussian of 0.3 pixel with the photosite box, s = 3, through tests/render.py) moved by ``shift`` and
    back: Keys' cubic lowered its MTF by up to 0.026 (0.2 sample) and 0.066 (0.5 sample), the phase ramp moves
    it by 0.001 and 0.004 (the kernel's tails cut at the support); allowed 0.005."""
    import render

    kernel = render.gaussian(0.3).sampled(S, 25, bandlimited=True)
    moved = twoscale._shift(twoscale._shift(kernel, shift), (-shift[0], -shift[1]))
    assert _mtf_error(moved, kernel) < 0.005


def test_scattered_saturated_highlights_leave_fewer_equations_not_a_bias():
    """The near photo's brightest 0.2 % flagged as saturated, their values left as they are: only the holes in
    the mask change, and so only the number of equations (4438 of 5184 here with the holes eroded by the
    first kernel's 7 x 7 `hole_footprint`; 3373 by the whole 13 x 13 footprint, 2374 with a radius of 6 near
    pixels around each hole instead of 1). Before, the means removed from
    the two photos (IPOL 2013, sec. 4.2) were taken over sets the holes made different, and the offset left
    between them biased k: residual 2.7 times the sensor noise, PSF error 0.056 for the unmasked pair's 0.011
    (the real 8-bit wall pair, 0.8 % of its near photo saturated: MTF50 0.655/0.642, against 0.590/0.577 for
    the same photos unflagged in 16 bits). With the constant fitted, the residual is the noise and the error
    grows as the equations fall, by about sqrt(5184 / 3373) = 1.24 (measured 0.013; 0.017 with 2374; 0.0126
    with 4438, 1.05 times the unmasked pair's).
    """
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=5.0, seed=1)
    near, far = pair["near"], pair["far"]
    [plain] = twoscale.estimate_pair(near, far, s=S)
    flagged = dataclasses.replace(near, saturated=near.data >= np.quantile(near.data, 0.998))
    [est] = twoscale.estimate_pair(flagged, far, s=S)
    assert est.params["equations"] < 0.9 * plain.params["equations"]
    assert est.residual < 1.1 * plain.residual
    error, plain_error = (float(np.linalg.norm(e.psf - TRUE_PSF)) for e in (est, plain))
    assert error < 2.0 * plain_error


def test_glints_clipped_in_the_near_photo_leave_out_only_their_surroundings():
    """A wall with glints (tests/render.py `wall_pair`: its own raster, optics and sensor), 0.45 % of the near
    photo and 0.3 % of the far one clipped, through a Gaussian of 0.4 pixel and f/8 diffraction (Airy tails
    beyond the support), lambda = 4: the estimate against the known PSF, and the far pixels it keeps.

    Measured over seeds 0-3: the glint-free photos keep 88 % of the window's far pixels as equations; a
    near-pixel radius 2 + ceil(2 lambda / s) around each clipped pixel and the fill by cv2.inpaint kept 23-30 %
    (max MTF error 0.039-0.070), radius 1 and the clipped values 45-51 % (0.039-0.048) with the holes eroded
    by the whole 13 x 13 footprint, 54-66 % (0.038-0.045; seed 0: 66 %, 0.040) by the first kernel's
    `hole_footprint` (q = 9 or 11), the glint-free error being 0.036-0.038 (the tails and the near photo's
    aliasing). Allowed: MTF_TOL, and 60 % of the window.
    """
    import render

    optics, airy = render.gaussian(0.4), render.airy(8.0)
    kernel = render.Kernel("gaussian 0.4 at f/8", lambda fx, fy: optics.optics(fx, fy) * airy.optics(fx, fy),
                           airy.cutoff)
    near, far = render.wall_pair(kernel, 4.0, (420, 420), (110, 110), seed=0, glints=2.5)
    assert 0.003 < near.saturated.mean() < 0.01 and far.saturated.any()
    [est] = twoscale.estimate_pair(near, far, s=S)
    x0, y0, x1, y1 = est.window
    assert est.params["equations"] > 0.6 * (x1 - x0) * (y1 - y0)
    assert render.compare(est.psf, kernel, S).max_mtf_2d < MTF_TOL


def test_a_rendered_pair_gives_one_psf_in_either_order():
    """tests/render.py `wall_pair` (its own wall, optics and sensor), lambda = 4: the near and the far photo given
    in either order are one registration and one PSF. Before, the matching ran from the first photo to the
    second: 109 or 102 inliers, PSFs 0.0041 apart in L2, noise floors 0.0167 and 0.0150."""
    import render

    kernel = render.gaussian(0.4)
    near, far = render.wall_pair(kernel, 4.0, (420, 420), (110, 110), seed=0)
    [near_first] = twoscale.estimate_pair(near, far, s=S)
    [far_first] = twoscale.estimate_pair(far, near, s=S)
    np.testing.assert_array_equal(near_first.psf, far_first.psf)
    assert near_first.params == far_first.params and near_first.sources == far_first.sources == [near.source, far.source]
    assert render.compare(near_first.psf, kernel, S).max_mtf_2d < MTF_TOL


def test_psf_from_kernel_inverts_the_inter_image_relation():
    # For a Gaussian h of variance v, k^ = h^(z)/h^(z/lambda) is Gaussian of variance v (1 - 1/lambda^2)
    # (SIAM 2012, eq. (5)), so the zoom-in product must give h back (up to Keys' interpolation).
    for lam in (3.5, 4.0, 6.0):
        sx, sy = 0.5, 0.7
        shrink = np.sqrt(1 - 1 / lam**2)
        k = simulate.gaussian_psf(sx * shrink, sy * shrink, s=S, support=SUPPORT)
        h = twoscale.psf_from_kernel(k, (lam, lam))
        h /= h.sum()
        truth = simulate.gaussian_psf(sx, sy, s=S, support=SUPPORT)
        assert np.abs(h - truth).max() < 0.01 * truth.max()


def test_real_pair_in_either_order(data_dir):
    near_path, far_path = data_dir / "IMG_0608_v1.pgm", data_dir / "IMG_0602_v1_CUT.pgm"
    a = raw.load_frame(data_dir / "IMG_0602_v1_CUT.pgm", "mono")
    b = raw.load_frame(data_dir / "IMG_0608_v1.pgm", "mono")
    [ab] = twoscale.estimate_pair(a, b, s=S, support=13)
    [ba] = twoscale.estimate_pair(b, a, s=S, support=13)
    for est in (ab, ba):
        # the homography says the full frame is the near photo and the cut is the far one
        assert est.sources == [str(near_path), str(far_path)]
        assert 4.5 < est.params["lambda"][0] < 6.0
        assert est.psf.sum() == pytest.approx(1.0)
        # centred: the core's centre of mass within a quarter of an s-grid sample (1/12 pixel)
        cx, cy = kernels.core_centroid(est.psf)
        assert abs(cx) < 0.25 and abs(cy) < 0.25
        assert np.unravel_index(np.argmax(est.psf), est.psf.shape) == (6, 6)
        m = est.metrics()
        # an in-focus green channel: FWHM between a diffraction-limited spot and a few pixels
        assert 0.4 < m["fwhm_x"] < 2.0 and 0.4 < m["fwhm_y"] < 2.0
        assert 0.2 < m["mtf50_x"] < S / 2
        assert est.psf.min() > -0.05 * est.psf.max()
    # the photos play the roles near and far, which the scale between them tells, not their order (IPOL 2013,
    # sec. 4.1): one registration far -> near, one PSF. Before, the matching ran from the first photo given to
    # the second: 320 or 302 inliers, MTF50 y 0.5721 or 0.5732, the PSFs 0.0053 apart in L2 (noise floor 0.0157)
    np.testing.assert_array_equal(ab.psf, ba.psf)
    assert ab.params == ba.params and ab.noise_floor == ba.noise_floor


def test_grid_splits_the_common_region():
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, near_shape=(448, 448), seed=2)
    ests = twoscale.estimate_pair(pair["near"], pair["far"], s=S, grid=(2, 1))
    assert len(ests) == 2
    (_, t0, r0, b0), (l1, t1, _, b1) = ests[0].window, ests[1].window
    assert r0 == l1 and (t0, b0) == (t1, b1)
    assert ests[0].field[0] < 0.5 < ests[1].field[0]
    for est in ests:
        # half the equations: the noise floor grows by sqrt(2), hence 1.5x the tolerance
        assert _mtf_error(est.psf, TRUE_PSF) < 1.5 * MTF_TOL


def test_raw_pair_per_bayer_channel(tmp_path):
    scene = simulate.texture_scene((1100, 1100), seed=4)
    c = (np.array(scene.shape) - 1) / 2
    truth = {}
    for name, lam, (cy, cx) in (("near", 1.0, (255.5, 319.5)), ("far", 4.0, (127.5, 127.5))):
        # 1.25 raster pixels per sensor photosite on the near shot, 4 times more on the far one

        def to_scene(x, y, lam=lam, cx=cx, cy=cy):
            return c[1] + 1.25 * lam * (np.asarray(x) - cx), c[0] + 1.25 * lam * (np.asarray(y) - cy)

        truth[name] = simulate.simulate_scene(
            tmp_path / f"{name}.dng", scene=scene, sensor_to_scene=to_scene, psf=TRUE_PSF, s=S,
            sensor=(512, 640) if name == "near" else (256, 256), seed=7,
        )
    near = raw.load_frame(tmp_path / "near.dng", "g1")
    far = raw.load_frame(tmp_path / "far.dng", "g1")
    # the two DNGs come from "sensors" of different sizes: refused for RAW planes
    with pytest.raises(BadInputError, match="different sizes"):
        twoscale.estimate_pair(near, far, s=S)
    # same camera: pretend the sensor shape agrees (the planes keep their own sizes)
    far = dataclasses.replace(far, sensor_shape=near.sensor_shape)
    [est] = twoscale.estimate_pair(far, near, s=S)
    assert est.channel == "g1"
    assert _mtf_error(est.psf, TRUE_PSF) < MTF_TOL


def test_large_far_photo_is_registered_again_at_full_resolution(monkeypatch):
    # photos above MAX_PIXELS are shrunk for a first SIFT pass; a shrunk far photo
    # loses precision, so the common region is matched again at full resolution
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, near_shape=(512, 512), far_shape=(256, 256), seed=9)
    monkeypatch.setattr(pair_register, "MAX_PIXELS", 30_000)
    calls = []
    refine = pair_register._refine
    monkeypatch.setattr(pair_register, "_refine", lambda *a, **k: calls.append(1) or refine(*a, **k))
    [est] = twoscale.estimate_pair(pair["near"], pair["far"], s=S)
    assert calls == [1]
    assert est.params["lambda"] == pytest.approx([4.0, 4.0], rel=5e-3)
    assert _mtf_error(est.psf, TRUE_PSF) < MTF_TOL


# --------------------------------------------------------------------------- bad input


def test_unrelated_photos():
    one = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, seed=11)
    other = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, seed=12)
    with pytest.raises(PairError, match="unrelated photos"):
        twoscale.estimate_pair(one["near"], other["far"], s=S)


def test_pair_too_close_in_distance():
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=2.5, seed=3)
    with pytest.raises(PairError, match="does not exceed s = 3"):
        twoscale.estimate_pair(pair["near"], pair["far"], s=S)


def test_flat_scene_is_textureless():
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, scene=np.full((700, 700), 0.5), seed=5)
    with pytest.raises(PairError, match="textureless scene"):
        twoscale.estimate_pair(pair["near"], pair["far"], s=S)


def test_scene_without_fine_detail_is_textureless():
    # large blobs register well but leave the band the kernel lives in empty (SIAM 2012, Lemma 1)
    tex = cv2.GaussianBlur(simulate.texture_scene((800, 800), seed=3), (0, 0), 12)
    blobs = 0.5 + 0.18 * (tex - tex.mean()) / tex.std()
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.0, scene=blobs, seed=6)
    with pytest.raises(PairError, match="textureless scene: spectral energy in the band"):
        twoscale.estimate_pair(pair["near"], pair["far"], s=S)


def test_rotation_too_large():
    pair = simulate.simulate_pair(psf=TRUE_PSF, s=S, lam=4.5, rotation_deg=15.0, seed=8)
    with pytest.raises(PairError, match="rotated by 15"):
        twoscale.estimate_pair(pair["near"], pair["far"], s=S)


def _frame(shape, channel="g1", sensor=(100, 100), mask_shape=None):
    data = np.zeros(shape)
    return raw.Frame(
        data=data, channel=channel, white=1.0, saturated=np.zeros(mask_shape or shape, bool),
        source=f"{channel}.dng", sensor_shape=sensor, from_mosaic=True,
    )


@pytest.mark.parametrize(
    "a, b, kwargs, message",
    [
        (_frame((50, 50), "g1"), _frame((50, 50), "r"), {}, "same channel"),
        (_frame((50, 50)), _frame((60, 60), sensor=(120, 120)), {}, "different sizes"),
        (_frame((50, 50)), _frame((50, 50), mask_shape=(40, 40)), {}, "saturation mask differ"),
        (_frame((50, 50)), _frame((50, 50)), {"support": 12}, "odd"),
        (_frame((50, 50)), _frame((50, 50)), {"s": 0}, "positive integer"),
    ],
)
def test_bad_input(a, b, kwargs, message):
    with pytest.raises(BadInputError, match=message):
        twoscale.estimate_pair(a, b, **kwargs)


def test_band_limiting_is_the_shared_dct_low_pass():
    """`band_limited` gives resample.dct_lowpass's band within float32 rounding (1e-6 of the signal)."""
    from psfd.estimator import resample

    image = np.random.default_rng(1).random((221, 251)) * 1000.0
    for keep in ((50, 60), (100, 251), (221, 251)):
        band, zoom = twoscale.band_limited(image, keep)
        size = (int(np.ceil(twoscale.OVERSAMPLE * keep[0])), int(np.ceil(twoscale.OVERSAMPLE * keep[1])))
        shared = resample.dct_lowpass(image.astype(np.float32), keep, size=size)
        assert band.shape == shared.shape and zoom == (size[0] / 221, size[1] / 251)
        assert np.abs(band - shared).max() < 1e-6 * np.abs(shared).max()


def test_registration_does_not_depend_on_what_opencv_drew_before(data_dir):
    """FLANN's randomised trees draw from OpenCV's generator: psfd compare searches a checkerboard
    (which draws too) before the pair, the daemon registers pair after pair; the homography must not change."""
    a = raw.load_frame(data_dir / "IMG_0602_v1_CUT.pgm", "mono")
    b = raw.load_frame(data_dir / "IMG_0608_v1.pgm", "mono")
    first = pair_register.register(a.data, b.data)
    cv2.randu(np.zeros((64, 64)), 0.0, 1.0)  # draws from the same generator
    again = pair_register.register(a.data, b.data)
    np.testing.assert_array_equal(first.to_near, again.to_near)
    assert first.inliers == again.inliers


def test_the_real_pair_on_threads_is_the_pair_on_one(data_dir, monkeypatch):
    """SIFT of the two photos and the near photo's Keys sampling on two threads: the registration and the
    PSF of the same work done on one thread, bit for bit."""
    a = raw.load_frame(data_dir / "IMG_0602_v1_CUT.pgm", "mono")
    b = raw.load_frame(data_dir / "IMG_0608_v1.pgm", "mono")
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    threaded_reg = pair_register.register(a.data, b.data)
    [threaded] = twoscale.estimate_pair(a, b, s=3)
    monkeypatch.setattr(workers, "usable_cores", lambda: 1)
    alone_reg = pair_register.register(a.data, b.data)
    [alone] = twoscale.estimate_pair(a, b, s=3)
    np.testing.assert_array_equal(threaded_reg.to_near, alone_reg.to_near)
    np.testing.assert_array_equal(threaded_reg.far_points, alone_reg.far_points)
    np.testing.assert_array_equal(threaded.psf, alone.psf)
    assert threaded.params == alone.params and threaded.noise_floor == alone.noise_floor


def test_the_real_pair_loads_neither_scipy_nor_numpy_ma():
    """`psfd estimate pair` imports no scipy (0.2-0.3 s of start-up the method does not need) and no numpy.ma,
    which np.percentile's NaN check imports (0.06 s): the pair's stretch does without it."""
    code = ("import sys; from psfd.cli import main; "
            f"main(['estimate', 'pair', {str(DATA / 'IMG_0602_v1_CUT.pgm')!r}, {str(DATA / 'IMG_0608_v1.pgm')!r}, "
            "'-s', '3', '-q']); print(sorted(m for m in sys.modules if m.split('.')[0] == 'scipy' or m == 'numpy.ma'))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip().splitlines()[-1] == "[]"
