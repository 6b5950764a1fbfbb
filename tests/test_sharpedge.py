"""Sharp-edge prediction baseline (Joshi, Szeliski, Kriegman, CVPR 2008) and the gamma of its target.

Ground truth: frames rendered by psfd.estimator.simulate from a known PSF,
and the closed forms of Delbracio et al., IJCV 2012, sec. 2.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import signal

from psfd.errors import BadInputError, EstimationError, TargetNotFoundError
from psfd.estimator import gamma, mtf, sharpedge, simulate
from psfd.estimator.kernels import centroid, split_grid
from psfd.estimator.raw import Frame

from conftest import DATA

S = 4
SUPPORT = 17
WHITE = 16383.0


def edge_frame(psf, *, px_per_square=20.0, angle=8.0, shape=(220, 220), seed=0, distortion=0.0):
    """A channel plane of the printed edge target (8 x 8 squares, white border) rendered with ``psf``."""
    pps = 32  # raster pixels per square
    scene = sharpedge.edge_target(px_per_square=pps)
    a, k = np.deg2rad(angle), pps / px_per_square
    cy, cx = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    norm = np.hypot(cx, cy)

    def to_scene(x, y):
        x, y = np.asarray(x) - cx, np.asarray(y) - cy
        f = 1.0 + distortion * (x * x + y * y) / norm**2  # barrel/pincushion about the plane centre
        x, y = x * f, y * f
        return (k * (np.cos(a) * x - np.sin(a) * y) + scene.shape[1] / 2 - 0.5,
                k * (np.sin(a) * x + np.cos(a) * y) + scene.shape[0] / 2 - 0.5)

    ideal = simulate.render_plane(scene, to_scene, shape, psf, S, background=1.0)
    data = simulate.expose(ideal, black=0, white=int(WHITE), rng=np.random.default_rng(seed))
    return Frame(data=data, channel="g1", white=WHITE, saturated=data >= WHITE, source="edges.sim")


def mtf_rms(psf, truth, band):
    f, mx, my = mtf.profiles(psf, S)
    _, tx, ty = mtf.profiles(truth, S)
    sel = (f >= band[0]) & (f <= band[1])
    d = np.concatenate([(mx - tx)[sel], (my - ty)[sel]])
    return float(np.sqrt(np.mean(d * d)))


# ---------------------------------------------------------------- gamma


def test_view_matrix_is_the_decimated_convolution():
    rng = np.random.default_rng(0)
    u = rng.random((S * 9 + SUPPORT, S * 9 + SUPPORT))
    h = rng.random((SUPPORT, SUPPORT))
    a = gamma.view_matrix(u, S, SUPPORT)
    direct = signal.convolve2d(u, h, mode="valid")[::S, ::S]  # S_s (u * h), IJCV 2012 problem (P)
    assert a.shape == (direct.size, SUPPORT * SUPPORT)
    np.testing.assert_allclose(a @ h.ravel(), direct.ravel(), rtol=1e-12)


def test_gamma_of_iid_bernoulli_matches_the_closed_form():
    # gamma(E[U^T U]) = (4/M)(1/(N+1) + N - 1) for i.i.d. {0,1} (IJCV 2012, sec. 2) is the large-M limit;
    # a finite window inflates it by the inverse-Wishart mean factor M / (M - N - 1) (8 % at M = 3600,
    # N = 289). The realisation scatters by O(1/sqrt(M - N)) around that: 3 %.
    rng = np.random.default_rng(1)
    m, n = 60 * 60, SUPPORT**2
    u = rng.integers(0, 2, (S * 59 + SUPPORT, S * 59 + SUPPORT)).astype(float)
    value = gamma.gamma(gamma.view_matrix(u, S, SUPPORT))
    limit = gamma.bernoulli_formula(m, n)
    assert value == pytest.approx(limit * m / (m - n - 1), rel=0.03)
    assert value > gamma.bound(m, n)


def test_gamma_bernoulli_target_versus_edge_target():
    """17x17 support, s = 4, 80x80 window (IJCV 2012 Table 2 / thesis Table 2.2: 0.69 vs 1133.05, bound 0.35)."""
    bern = gamma.pattern_gamma("bernoulli", SUPPORT)
    edges = gamma.pattern_gamma("edges", SUPPORT)
    print(f"\ngamma 17x17: bernoulli {bern:.3f} (thesis 0.69, bound 0.35), edges {edges:.1f} (thesis 1133.05), "
          f"ratio {edges / bern:.0f}")
    # Our view differs from the thesis's in raster and low-pass details (not given in the text): 30 %.
    assert bern == pytest.approx(0.69, rel=0.3)
    assert bern > 0.35
    # The edge pattern's straight edges carry one phase each: its gamma is far above the noise's.
    assert edges > 30 * bern


def test_aligned_edge_target_is_degenerate():
    """A print aligned with the pixel grid sees every straight edge at one sub-pixel phase."""
    aligned = gamma.pattern_gamma("edges", SUPPORT, tiles=2, angle=0.0)
    assert aligned > 100 * gamma.pattern_gamma("edges", SUPPORT, tiles=2)


# ---------------------------------------------------------------- estimator pieces


def test_edges_are_located_to_a_fraction_of_a_pixel():
    # a blurred straight step at x = 40.3 (a symmetric PSF does not move its DoG zero crossing)
    x = np.arange(100) - 40.3
    profile = 0.2 + 0.6 * 0.5 * (1 + np.tanh(x / 1.2))
    image = np.tile(profile, (60, 1)) + np.random.default_rng(2).normal(0, 0.005, (60, 100))
    edges = sharpedge.detect_edges(image)
    assert len(edges) > 40
    assert np.median(edges.x) == pytest.approx(40.3, abs=0.05)
    assert np.all(edges.nx > 0.99)  # normal points to the bright side
    levelled = sharpedge.edge_levels(image, edges, length=8)
    # the paper's max/min rule averages near the plateau: within 2 % of the contrast
    assert np.median(levelled.hi) == pytest.approx(0.8, abs=0.012)
    assert np.median(levelled.lo) == pytest.approx(0.2, abs=0.012)


def test_noise_sigma_ignores_edges():
    rng = np.random.default_rng(3)
    image = np.where(np.arange(200)[None, :] > 90, 0.8, 0.2) * np.ones((200, 1)) + rng.normal(0, 0.01, (200, 200))
    assert sharpedge.noise_sigma(image) == pytest.approx(0.01, rel=0.1)


@pytest.mark.parametrize("surround", ["white", "black"])
def test_clipped_pixels_are_no_evidence_of_a_noise_free_frame(surround):
    """The real example photo framed by a blown-out surround (saturated white, 80 pixels wide: two thirds
    of the frame), or by blacks crushed to 0 (a dark room), has the photo's noise: clipped blocks show none,
    and the median over a frame more than half clipped read 0 before (sigma 1e-6, a noise floor of 1.2e-5
    for the photo's 0.089)."""
    from psfd.estimator import raw

    photo = raw.load_frame(DATA / "img_example.pgm")
    data = np.pad(photo.data, 80, constant_values=photo.white if surround == "white" else 0)
    framed = Frame(data=data, channel=photo.channel, white=photo.white, saturated=data >= photo.white,
                   source="framed")
    [a] = sharpedge.estimate_edges(photo, s=S)
    [b] = sharpedge.estimate_edges(framed, s=S)
    assert b.params["sigma"] == pytest.approx(a.params["sigma"], rel=0.02)
    assert b.noise_floor == pytest.approx(a.noise_floor, rel=0.05)


def test_solver_recovers_a_kernel_from_a_known_sharp_image():
    rng = np.random.default_rng(4)
    truth = simulate.gaussian_psf(0.6, 0.4, theta=0.3, s=S, support=SUPPORT)
    sharp = rng.random((S * 49 + 1, S * 49 + 1))
    observed = signal.fftconvolve(sharp, truth, mode="same")[::S, ::S]
    valid = np.zeros(observed.shape, bool)
    valid[3:-3, 3:-3] = True
    ata, atb, _ = sharpedge._normal_equations(sharp, observed, valid, S, SUPPORT)
    k, _ = sharpedge.solve_kernel(ata, atb, 1e-3, SUPPORT, weight=0.0)
    np.testing.assert_allclose(k, truth, atol=1e-6)


# ---------------------------------------------------------------- whole estimates


@pytest.fixture(scope="module")
def smooth_truth():
    return simulate.gaussian_psf(0.8, 0.5, theta=0.5, s=S, support=SUPPORT)


@pytest.fixture(scope="module")
def smooth_frame(smooth_truth):
    return edge_frame(smooth_truth, distortion=0.02)


@pytest.mark.parametrize("target", [False, True])
def test_estimate_recovers_a_smooth_psf(smooth_frame, smooth_truth, target):
    """Blind and target forms at the paper's lambda = 2 on a well-sampled PSF.

    The paper reports no error figures; the noise-target method claims 2-5 %
    MTF error (IJCV 2012, sec. 5.6). The edge levels are averages of samples
    within 10 % of the plateau (sec. 4.1), which biases the contrast by a few
    per cent: we allow an RMS MTF error of 0.05 below Nyquist.
    """
    [est] = sharpedge.estimate_edges(smooth_frame, s=S, target_form=target)
    low = mtf_rms(est.psf, smooth_truth, (0, 0.5))
    print(f"\ntarget={target}: RMS MTF error below Nyquist {low:.4f}, params {est.params}")
    assert est.method == "sharp-edge" and est.psf.shape == (SUPPORT, SUPPORT)
    assert est.psf.sum() == pytest.approx(1.0) and est.psf.min() >= 0
    assert low < 0.05
    # edge locations fix the kernel's position: centred to half an s-grid sample (1/8 pixel)
    assert np.hypot(*centroid(est.psf)) < 0.5
    assert est.params["weight"] == 2.0 and est.params["gamma"] == SUPPORT**2
    # the residual cannot beat the sensor noise; prediction errors near corners and junctions add to it
    assert est.residual >= 0.8 * est.params["sigma"]


def test_target_form_on_the_bernoulli_marks(tmp_path):
    """The Bernoulli target's flat squares and hourglasses, registered by its X-corners, as known step edges.

    Fewer edge pixels and only three edge directions (0, 90, +-63 degrees):
    the orientation test is reported. At the target's design scale a mark is
    only 8 pixels wide, so the marches and the prediction band of a wide PSF
    cross the next mark (0.12 RMS MTF error for sigma = 0.8 pixel); for the
    in-focus PSF the thesis compares with, the tolerance above holds.
    """
    from psfd.estimator import raw

    truth = simulate.gaussian_psf(0.4, 0.3, theta=0.5, s=S, support=SUPPORT)
    simulate.simulate_target(tmp_path / "bern.dng", psf=truth, s=S, pixels_per_cell=0.25, rotation_deg=5, seed=3)
    [est] = sharpedge.estimate_edges(raw.load_frame(tmp_path / "bern.dng", "g1"), s=S, target_form=True)
    low = mtf_rms(est.psf, truth, (0, 0.5))
    print(f"\nBernoulli marks: RMS MTF error below Nyquist {low:.4f}, {est.params['valid_pixels']} pixels")
    assert est.params["pattern"] == "Bernoulli target marks"
    assert low < 0.05
    assert any("orientations uneven" in w for w in est.warnings)


@pytest.mark.parametrize("form", ["edge target", "Bernoulli marks"])
def test_the_target_form_does_not_depend_on_the_order_of_its_edge_points(smooth_frame, form, monkeypatch):
    """The edge points and the samples lie on the same s-grid, and one sample in five is as near to two or more
    edge points. When a sample took the levels of the first of them in a k-d tree's order, their order decided
    the PSF: reversed, the example photo's moved by 0.050 (a third of its noise floor, 0.15), the edge target's
    here by 0.0018 (floor 0.022). With the mean of the tied points' levels, reversing them leaves the PSF as it
    was (measured: bit for bit; allowed: 1e-3 of the floor per sample, the sums of three or more levels in
    another order)."""
    from psfd.estimator import raw

    frame = smooth_frame if form == "edge target" else raw.load_frame(DATA / "img_example.pgm", "mono")
    pattern = sharpedge.locate_pattern(frame)
    [forward] = sharpedge.estimate_edges(frame, s=S, pattern=pattern)
    edges = sharpedge._target_edges
    monkeypatch.setattr(sharpedge, "_target_edges",
                        lambda *args, **kwargs: (lambda e: e.subset(np.arange(len(e))[::-1]))(edges(*args, **kwargs)))
    [backward] = sharpedge.estimate_edges(frame, s=S, pattern=pattern)
    assert np.abs(backward.psf - forward.psf).max() <= 1e-3 * forward.noise_floor / forward.support


def test_the_tied_points_are_all_the_nearest():
    """`_TiedPoints` against a search of every point: each sample's nearest points within the bound, all of
    them where several are as near, on s-grid points as dense as the target form's, ties of up to 8 points
    included (the candidates asked first are then too few, and asked again)."""
    rng = np.random.default_rng(4)
    i, j = rng.integers(0, 60, 400), rng.integers(0, 60, 400)
    # eight points 5 samples from (100, 100)
    i, j = np.r_[i, 103, 103, 97, 97, 104, 104, 96, 96], np.r_[j, 104, 96, 104, 96, 103, 97, 103, 97]
    points = sharpedge._TiedPoints(i, j)
    qi, qj = np.mgrid[-5:110, -5:110]
    qi, qj = qi.ravel(), qj.ravel()
    found, sample, point = points.query(qi, qj, 5.5)
    d2 = (qi[:, None] - i[None, :]) ** 2 + (qj[:, None] - j[None, :]) ** 2
    nearest = d2.min(axis=1)
    np.testing.assert_array_equal(found, nearest < 5.5**2)
    expected = np.nonzero((d2 == nearest[:, None]) & found[:, None])
    got = np.lexsort((point, sample))
    np.testing.assert_array_equal(sample[got], expected[0])
    np.testing.assert_array_equal(point[got], expected[1])
    assert np.bincount(sample).max() == 8  # the sample at (100, 100)


@pytest.fixture(scope="module")
def defocused_edge_target():
    """The edge target through a defocus disc of 0.6 pixel with diffraction at f/5.6 (tests/render.py), and
    its true sharp levels: the print's black and white under the light, as the estimator reads the plane."""
    import render

    kernel = render.KINDS["defocus"]
    frame = render.render_edge_target(kernel, rotation_deg=15.0, seed=1)
    return frame, kernel, _true_levels(frame, render.Light().field(frame.shape), render.Print(), render.Exposure())


@pytest.fixture(scope="module")
def defocused_bernoulli_marks():
    """The Bernoulli target through the same defocus disc, 0.45 pixel per cell, turned by 20 degrees, tilted."""
    import render

    kernel = render.KINDS["defocus"]
    shot = render.render(kernel, render.View(0.45, rotation_deg=20.0, tilt=(0.04, -0.03)), seed=1)
    return shot.frame, kernel, _true_levels(shot.frame, shot.light, shot.paper, shot.exposure)


def _true_levels(frame, light, paper, exposure):
    """(x, y) -> (black, white): the print's levels under the light, over the frame's white level."""
    scale = exposure.electrons * exposure.dn_per_electron / frame.white

    def levels(x, y):
        lit = scale * light(x, y)
        return paper.black * lit, paper.white * lit

    return levels


@pytest.mark.parametrize("form", ["edge target", "Bernoulli marks"])
def test_the_target_forms_levels_are_the_prints(request, form):
    """Every edge level the target form shades with is the print's, to 0.1 of the edge contrast, on renders.

    The levels are the plateaus of marches along the normal (Joshi et al., CVPR 2008, sec. 4.1). Where a
    march met another edge of the pattern (checkerboard crossings, the hourglasses' tips) or left the known
    region (into the Bernoulli target's noise), its levels were off by up to 0.81 of the contrast on the edge
    target (648 of 18,583 points beyond 0.1) and 0.85 on the marks (1,349 of 4,249); such points now take the
    levels of their nearest clear points (`sharpedge._clear_marches`). Measured on 6 renders (this defocus
    disc, a Gaussian, diffraction at f/11; both targets): at most 0.088 of the contrast, here 0.077 and 0.066
    (the levels' own bias: the plateau's 10 % rule and the PSF's tails, about 0.03 on average).
    """
    frame, _, truth = request.getfixturevalue("defocused_edge_target" if form == "edge target"
                                              else "defocused_bernoulli_marks")
    known = sharpedge.locate_pattern(frame)
    assert known.name == ("edge target" if form == "edge target" else "Bernoulli target marks")
    image = np.asarray(frame.data, dtype=np.float64) / frame.white
    rows, cols = image.shape
    kernel_radius = (SUPPORT // 2) / S
    band, length = 2 * kernel_radius, int(np.ceil(2 * kernel_radius)) + 2  # estimate_edges's defaults
    *_, edges, (cx0, cy0) = sharpedge._window_equations(image, frame.saturated, (0, 0, cols, rows), S, SUPPORT,
                                                        band, length, sharpedge.noise_sigma(image), known)
    black, white = truth(edges.x + cx0, edges.y + cy0)
    error = np.maximum(np.abs(edges.lo - black), np.abs(edges.hi - white)) / (white - black)
    print(f"\n{form}: {len(edges)} edge points, level error max {error.max():.3f}, "
          f"99th percentile {np.percentile(error, 99):.3f}")
    assert len(edges) > 4000
    assert error.max() < 0.1


def target_form_errors(frame, kernel, pattern: str):
    """The target form's PSF of ``frame`` against ``kernel``: `render.compare`'s errors and the L2 error over
    the support (against `render.support_truth`, the band-limited samples), the pattern checked."""
    import render

    [est] = sharpedge.estimate_edges(frame, s=S, support=SUPPORT, target_form=True)
    errors = render.compare(est.psf, kernel, S)
    l2 = float(np.sqrt(np.sum((est.psf - render.support_truth(kernel, S, SUPPORT)) ** 2)))
    print(f"\n{pattern} through {kernel.name}: {errors}  L2 {l2:.4f}  floor {est.noise_floor:.4f}")
    assert est.params["pattern"] == pattern
    return errors, l2


def test_the_target_form_against_the_true_psf(defocused_edge_target):
    """The target form on a photograph of the edge target from the independent renderer, against its PSF
    (`render.support_truth`: the band-limited samples on the support).

    Measured on 12 renders of this kind (a Gaussian of 0.45 pixel, this defocus disc, diffraction at f/11;
    20 pixels per square, turned by 15 and 40 degrees, 2 noise seeds each): L2 error 0.019-0.036, here
    0.023; max MTF error 0.042-0.093, here 0.063, of which the mean signed error, +0.015 to +0.042, is the
    edge levels' bias (the plateau's 10 % rule, sec. 4.1: the estimate is too narrow, RMS width 0.81 of the
    truth's for this disc). Against the marches that met another edge keeping their levels (before
    `sharpedge._clear_marches`), paired over the 12: L2 error -0.0025 +- 0.0002 (lower on all 12), max MTF
    error -0.0073 +- 0.0012, the mean signed error -0.0052 +- 0.0002, RMS width +0.012 (0.79 -> 0.81 here).
    Allowed: 0.03 in L2 (0.026 before; the two noise seeds of this view give 0.023 and 0.026), 0.08 in max
    MTF, a signed error in (0, 0.035).
    """
    frame, kernel, _ = defocused_edge_target
    errors, l2 = target_form_errors(frame, kernel, "edge target")
    assert l2 < 0.03
    assert errors.max_mtf < 0.08
    assert 0 < errors.mean_signed < 0.035


def test_the_marks_target_form_against_the_true_psf(defocused_bernoulli_marks):
    """The target form on the Bernoulli target's marks from the independent renderer, against its PSF.

    Measured on 6 renders of this kind (this defocus disc, 0.45 pixel per cell, turned by 20 and 65
    degrees, 3 noise seeds each): L2 error 0.035-0.043, here 0.036; max MTF error 0.061-0.114, here 0.061;
    mean signed error +0.023 to +0.028; RMS width 0.81-0.82 of the truth's. Before the marches that cross
    another mark or run into the noise gave up their levels (`sharpedge._clear_marches`): L2 error
    0.047-0.067 (0.047 here), RMS width 0.78; paired over 16 renders of the marks (this disc and a Gaussian
    of 0.45 pixel, 0.3 and 0.45 pixel per cell): L2 error -0.017 +- 0.0025 (lower on all 16), max MTF error
    -0.020 +- 0.010. Allowed: 0.045 in L2, 0.13 in max MTF, a signed error in (0, 0.035).
    """
    frame, kernel, _ = defocused_bernoulli_marks
    errors, l2 = target_form_errors(frame, kernel, "Bernoulli target marks")
    assert l2 < 0.045
    assert errors.max_mtf < 0.13
    assert 0 < errors.mean_signed < 0.035


def test_the_target_form_is_measured_on_the_target_wherever_it_lies():
    """The target form's PSF comes from the print alone: the same photograph of the edge target framed in a
    larger one, off-centre in a dark room (read noise only, 8 DN of 16383), gives the same kernel, the same
    noise floor and a window and field that follow the print.

    Before, the window was the whole frame (field (0.5, 0.5) wherever the target lay, and the empty windows
    of a grid refused the run) and the noise was read on the whole frame: the room's 6.3e-4 instead of the
    print's 0.011, a noise floor 17 times too small (0.0024 for 0.042, with a kernel 0.053 from the truth).
    Measured: the windows move by the offset exactly, the noise is the same, the floor within 0.3 % and the
    kernel within 0.09 of its floor (the print is located anew in the larger frame, through another
    stretch of its grey levels: its registration moves by a few thousandths of a pixel).
    """
    truth = simulate.gaussian_psf(0.8, 0.5, theta=0.5, s=S, support=SUPPORT)
    alone = edge_frame(truth, px_per_square=16.0)  # the whole print, white border included, inside the frame
    rows, cols = alone.shape
    top, left = 40, 260
    room = np.round(300.0 + 8.0 * np.random.default_rng(2).standard_normal((400, 600)))
    room[top : top + rows, left : left + cols] = alone.data
    clipped = np.zeros(room.shape, dtype=bool)
    clipped[top : top + rows, left : left + cols] = alone.saturated
    framed = Frame(data=room, channel="g1", white=WHITE, saturated=clipped, source="room.sim")

    [a] = sharpedge.estimate_edges(alone, s=S, target_form=True)
    [b] = sharpedge.estimate_edges(framed, s=S, target_form=True)
    x0, y0, x1, y1 = a.window
    assert b.window == (x0 + left, y0 + top, x1 + left, y1 + top)
    assert x1 - x0 < cols and y1 - y0 < rows  # the print's box, not the frame
    centre = ((cols - 1) / 2 + left, (rows - 1) / 2 + top)  # the board's centre (`edge_frame`)
    assert b.field == pytest.approx((centre[0] / 600, centre[1] / 400), abs=0.01)
    assert b.params["sigma"] == pytest.approx(a.params["sigma"], rel=0.01)
    assert b.noise_floor == pytest.approx(a.noise_floor, rel=0.02)
    assert np.linalg.norm(b.psf - a.psf) < 0.25 * a.noise_floor
    # a grid splits the print, not the frame: every window holds part of it
    windows = [e.window for e in sharpedge.estimate_edges(framed, s=S, target_form=True, grid=(2, 2))]
    assert windows == split_grid(b.window, (2, 2))


def test_grid_gives_one_psf_per_window(smooth_frame):
    ests = sharpedge.estimate_edges(smooth_frame, s=2, grid=(2, 1))
    assert [e.window for e in ests] == [(0, 0, 110, 220), (110, 0, 220, 220)]
    assert ests[0].field == pytest.approx((0.25, 0.5))
    # half a target per window: some orientations are rare, which the paper's test (b) reports
    assert all(e.psf.shape == (9, 9) for e in ests)


def test_bad_inputs(smooth_frame):
    with pytest.raises(BadInputError):
        sharpedge.estimate_edges(smooth_frame, support=16)
    with pytest.raises(BadInputError):
        sharpedge.estimate_edges(smooth_frame, weight=-1)
    with pytest.raises(BadInputError):
        sharpedge.estimate_edges(smooth_frame, radius=0)
    flat = Frame(data=np.full((120, 120), 8000.0) + np.random.default_rng(5).normal(0, 5, (120, 120)),
                 channel="g1", white=WHITE, saturated=np.zeros((120, 120), bool), source="flat")
    with pytest.raises(EstimationError, match="usable pixels near edges"):
        sharpedge.estimate_edges(flat)
    with pytest.raises(TargetNotFoundError):
        sharpedge.estimate_edges(flat, target_form=True)


# ---------------------------------------------------------------- psfd target --kind edges


def test_target_cli_writes_the_edge_target(tmp_path, capsys):
    import shutil
    import subprocess

    import cv2

    from psfd.cli import main

    assert main(["target", "--kind", "edges", "--out", str(tmp_path / "edges.png"), "--px-per-cell", "2"]) == 0
    png = cv2.imread(str(tmp_path / "edges.png"), cv2.IMREAD_GRAYSCALE)
    expected = sharpedge.edge_target(px_per_square=32)
    np.testing.assert_array_equal(png, (expected * 255).astype(np.uint8))
    assert main(["target", "--kind", "edges", "--out", str(tmp_path / "edges.pdf"), "--size-mm", "200"]) == 0
    if shutil.which("pdftoppm"):  # the vector PDF, rasterised by poppler, draws the same target
        subprocess.run(["pdftoppm", "-r", "32", "-png", str(tmp_path / "edges.pdf"), str(tmp_path / "r")], check=True)
        page = cv2.imread(str(next(tmp_path.glob("r*.png"))), cv2.IMREAD_GRAYSCALE).astype(float)
        square = page.shape[1] / (sharpedge.SQUARES[0] + 2 * sharpedge.BORDER)
        ref = sharpedge.edge_target(px_per_square=square)[: page.shape[0], : page.shape[1]] * 255
        body = slice(0, int(page.shape[0] - square))  # the caption sits in the bottom border
        assert np.mean(np.abs(page[body] - ref[body])) < 8  # anti-aliased edge pixels only
    assert main(["target", "--kind", "lines", "--out", str(tmp_path / "x.png")]) == 2
    assert main(["target", "--kind", "edges", "--seed", "3", "--out", str(tmp_path / "x.png")]) == 2
    assert not (tmp_path / "x.png").exists()
    capsys.readouterr()


def _equations_both_ways(frame, window, known):
    """A window's normal equations by the tiled path and by the dense one (tests/sharpedge_dense.py)."""
    import sharpedge_dense

    image = np.asarray(frame.data, dtype=np.float64) / float(frame.white)
    sigma = sharpedge.noise_sigma(image)
    kernel_radius = (SUPPORT // 2) / S
    band, length = 2 * kernel_radius, int(np.ceil(2 * kernel_radius)) + 2  # estimate_edges's defaults
    args = (image, frame.saturated, window, S, SUPPORT, band, length, sigma, known)
    tiled = sharpedge._window_equations(*args)
    return tiled[:5], sharpedge_dense.window_equations(*args)


@pytest.mark.parametrize("form", ["blind", "edge target", "Bernoulli marks"])
def test_tiled_prediction_gives_the_dense_normal_equations(smooth_frame, form):
    """Evaluating the s-grid only on qualifying footprints, tile by tile, leaves eq. (5) as the whole grid gives it.

    Blind: the same pixels and bit-for-bit the same sums up to their order. Target forms: the coverage is
    taken from the nearest pixel centre away from the pattern's changes, so a sample may differ from the
    dense rendering where a change falls between pixel centres; the sums agree to 1e-6 of their size.
    """
    from psfd.estimator import raw

    frame = smooth_frame if form != "Bernoulli marks" else raw.load_frame(DATA / "img_example.pgm", "mono")
    known = None if form == "blind" else sharpedge.locate_pattern(frame)
    rows, cols = frame.data.shape
    window = (cols // 5, rows // 6, cols - cols // 4, rows - rows // 7)  # margins cut on all four sides
    (ata, atb, btb, used, edges), (d_ata, d_atb, d_btb, d_used, d_edges) = _equations_both_ways(frame, window, known)
    assert used == d_used > SUPPORT * SUPPORT
    assert len(edges) == len(d_edges)
    np.testing.assert_allclose(np.column_stack([edges.x, edges.y, edges.lo, edges.hi]),
                               np.column_stack([d_edges.x, d_edges.y, d_edges.lo, d_edges.hi]), rtol=0, atol=1e-9)
    tol = 1e-12 if form == "blind" else 1e-6
    np.testing.assert_allclose(ata, d_ata, rtol=0, atol=tol * np.abs(d_ata).max())
    np.testing.assert_allclose(atb, d_atb, rtol=0, atol=tol * np.abs(d_atb).max())
    assert btb == pytest.approx(d_btb, rel=tol)


@pytest.mark.parametrize("form", ["blind", "edge target", "Bernoulli marks"])
def test_tiles_predicted_on_two_threads_give_the_one_thread_equations(smooth_frame, form, monkeypatch):
    """The tiles' predictions on two threads, taken into the equations in the tiles' order: the sums of one
    thread, bit for bit (few tiles ahead, so that the threads finish tiles out of order many times)."""
    from psfd import workers
    from psfd.estimator import raw

    frame = smooth_frame if form != "Bernoulli marks" else raw.load_frame(DATA / "img_example.pgm", "mono")
    image = np.asarray(frame.data, dtype=np.float64) / float(frame.white)
    known = None if form == "blind" else sharpedge.locate_pattern(frame)
    rows, cols = frame.data.shape
    kernel_radius = (SUPPORT // 2) / S
    args = (image, frame.saturated, (0, 0, cols, rows), S, SUPPORT, 2 * kernel_radius,
            int(np.ceil(2 * kernel_radius)) + 2, sharpedge.noise_sigma(image), known)
    tiles = sharpedge._tiles
    monkeypatch.setattr(sharpedge, "_tiles", lambda rows, cols, size=24: tiles(rows, cols, size))  # many tiles
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    two = sharpedge._window_equations(*args)
    monkeypatch.setattr(workers, "usable_cores", lambda: 1)
    one = sharpedge._window_equations(*args)
    assert one[3] == two[3] > SUPPORT * SUPPORT
    for a, b in zip(one[:3], two[:3]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("seed", range(6))
def test_the_threshold_percentile_is_numpys_without_holding_every_value(seed):
    """detect_edges' 99.5th percentile of the gradient magnitude, from the tiles' values keeping only
    the largest (memory bounded on a 24-megapixel frame), equals np.percentile bit for bit."""
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400_000))
    values = rng.standard_normal(n) if seed % 2 else rng.integers(0, 40, n).astype(np.float64)  # ties too
    parts = np.array_split(values, int(rng.integers(1, 60)))
    assert sharpedge._percentile(iter(parts), n, 99.5) == float(np.percentile(values, 99.5))


def test_a_large_frame_is_searched_shrunk_then_in_the_boards_box():
    """Above BOARD_SEARCH_PIXELS the board is found on a shrunk copy and its corners measured again at full
    resolution in its box: the corners of a search of the whole frame, to a small fraction of a pixel;
    a frame without a board (the real wall photo) is refused without the full-resolution search."""
    from psfd.estimator import raw

    frame = edge_frame(simulate.gaussian_psf(0.6, 0.5, theta=0.4, s=S, support=SUPPORT), px_per_square=70,
                       shape=(740, 740), distortion=0.02)
    assert frame.data.size > sharpedge.BOARD_SEARCH_PIXELS
    image = frame.data / frame.white
    lo, hi = np.percentile(image, [1, 99])
    grey = np.clip((image - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    whole = sharpedge._find_board(grey, (7, 7), cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY, 3)
    boxed = sharpedge._board_corners(grey, (7, 7), sharpedge.SQUARES)
    assert whole is not None and boxed is not None
    assert np.abs(boxed - whole).max() < 0.05  # pixels; the corners' own noise is larger
    wall = raw.load_frame(DATA / "IMG_0608_v1.pgm", "mono")
    with pytest.raises(TargetNotFoundError):
        sharpedge.locate_target(wall.data / wall.white)


# ---------------------------------------------------------------- memory: the plane read where needed


def _levels_whole_plane(image, edges, length):
    """`sharpedge.edge_levels` as it was: both marches sampled over the whole plane at once (the reference)."""
    from scipy import ndimage

    steps = np.arange(1, length + 1, dtype=np.float64)[None, :]
    x, y = edges.x[:, None], edges.y[:, None]
    nx, ny = edges.nx[:, None], edges.ny[:, None]
    bright = ndimage.map_coordinates(image, [y + steps * ny, x + steps * nx], order=1, mode="nearest")
    dark = ndimage.map_coordinates(image, [y - steps * ny, x - steps * nx], order=1, mode="nearest")
    hi = sharpedge._plateau_max(bright)
    lo = sharpedge._plateau_min(dark, hi - dark[:, 0])
    return sharpedge.Edgels(edges.x, edges.y, edges.nx, edges.ny, edges.strength, lo, hi).subset(hi > lo)


def _noise_whole_plane(image):
    """`sharpedge.noise_sigma` as it was: the Haar sub-band of the whole plane at once (the reference)."""
    rows, cols = (image.shape[0] // 2) * 2, (image.shape[1] // 2) * 2
    a = image[:rows, :cols]
    hh = (a[0::2, 0::2] - a[0::2, 1::2] - a[1::2, 0::2] + a[1::2, 1::2]) / 2.0
    return float(np.median(np.abs(hh)) / 0.6745)


@pytest.mark.parametrize("integer", [False, True])
def test_the_plane_read_in_strips_gives_what_a_float64_copy_gives(monkeypatch, integer):
    """The plane divided where it is read (`_Scaled`, float64 or integer samples), its noise and the edge levels
    measured strip by strip: the edge points, levels and normal equations of a float64 copy of the whole plane,
    bit for bit, on a part of the real wall photo (many strips: none aligned with the edges' rows)."""
    from psfd.estimator import raw

    wall = raw.load_frame(DATA / "IMG_0608_v1.pgm", "mono")
    rows, cols = slice(300, 811), slice(400, 1101)  # odd sizes: the last strip and the Haar blocks are partial
    data = wall.data[rows, cols].astype(np.uint16) if integer else wall.data[rows, cols]
    saturated = wall.saturated[rows, cols]
    copy = np.asarray(data, dtype=np.float64) / float(wall.white)
    scaled = sharpedge._Scaled(data, wall.white)
    monkeypatch.setattr(sharpedge, "LEVEL_CHUNK", 397)
    monkeypatch.setattr(sharpedge, "STRIP", 62)
    sigma = sharpedge.noise_sigma(scaled)
    assert sigma == _noise_whole_plane(copy) == sharpedge.noise_sigma(copy)
    length = 6
    found = sharpedge.detect_edges(scaled, noise=sigma)
    reference = sharpedge.detect_edges(copy, noise=sigma)
    assert len(found) > 10 * sharpedge.LEVEL_CHUNK  # many chunks
    for name in ("x", "y", "nx", "ny", "strength"):
        np.testing.assert_array_equal(getattr(found, name), getattr(reference, name))
    levelled, whole = sharpedge.edge_levels(scaled, found, length), _levels_whole_plane(copy, reference, length)
    for name in ("x", "y", "lo", "hi"):
        np.testing.assert_array_equal(getattr(levelled, name), getattr(whole, name))
    support, s = 9, 2
    window = (40, 30, copy.shape[1] - 50, copy.shape[0] - 20)
    args = (saturated, window, s, support, 4.0, length, sigma, None)  # band: estimate_edges's default
    ata, atb, btb, used, _, _ = sharpedge._window_equations(scaled, *args)
    r_ata, r_atb, r_btb, r_used, _, _ = sharpedge._window_equations(copy, *args)
    print(f"\n{len(found)} edge points, {used} pixels used")
    assert used == r_used > support * support and btb == r_btb
    np.testing.assert_array_equal(ata, r_ata)
    np.testing.assert_array_equal(atb, r_atb)


def test_the_heap_is_returned_only_where_glibc_has_malloc_trim():
    import os

    sharpedge._trim_heap()  # looks malloc_trim up once; harmless where there is none
    trim = sharpedge._MALLOC_TRIM[0]
    libc = os.confstr("CS_GNU_LIBC_VERSION") if hasattr(os, "confstr") else None
    assert (trim is not None) == bool(libc and "glibc" in libc)


@pytest.mark.slow
@pytest.mark.timeout(1500)  # the command has its own 1200 s below
def test_edges_of_a_24_megapixel_raw_stay_under_500_mb(tmp_path):
    """`psfd estimate edges` on a 6000 x 4000 RGGB DNG whose planes are the real wall photo (issue 11: <= 500 MB).

    The peak is read by a small Python process that starts psfd: a child forked from the test process
    would count the test process's pages too.
    """
    import subprocess
    import sys

    import scenes

    scenes.wall_raw24(tmp_path / "wall.dng")
    probe = ("import resource, subprocess, sys\n"
             "done = subprocess.run([sys.executable, '-m', 'psfd', 'estimate', 'edges', sys.argv[1], '-q', '--json'],"
             " capture_output=True, text=True)\n"
             "peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss\n"
             "print(done.returncode, peak, done.stdout.count('\\n'))\n")
    out = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "wall.dng")], capture_output=True, text=True,
                         timeout=1200, check=True).stdout.split()
    code, peak_kib, estimates = int(out[0]), int(out[1]), int(out[2])
    print(f"\npeak {peak_kib / 1024:.0f} MiB for {estimates} estimates")
    assert code == 0 and estimates == 4
    assert peak_kib / 1024 <= 500
