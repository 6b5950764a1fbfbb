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



def test_a_warning_whose_numbers_differ_by_window_is_logged_once_with_their_range(capsys):
    """Per-window warnings (noise floor, outer ring) differ in their numbers: a 10 x 10 grid printed one line per
    window, or "2 of 100 windows" for two that happened to round alike, without saying where."""
    from psfd.cli import logs, output

    noise = "noise floor {}% of the kernel: it may be more noise than PSF"
    ring = "the kernel reaches the edge of its support: 6% of its sum lies in the outermost ring"
    estimates = [
        _estimate("b", (0.46, 0.56), [noise.format(586)]),
        _estimate("b", (0.47, 0.56), [noise.format(148), ring]),
        _estimate("b", (0.48, 0.56), [noise.format(113)]),
        _estimate("b", (0.50, 0.56), [noise.format(148)]),
        _estimate("b", (0.50, 0.50), []),
    ]
    logs.setup()
    output.log_warnings(estimates)
    assert capsys.readouterr().err.splitlines() == [
        "psfd: warning: IMG_1.dng b, 4 of 5 windows, the largest at (0.46, 0.56): noise floor 113 to 586% of the "
        "kernel: it may be more noise than PSF",
        f"psfd: warning: IMG_1.dng b at (0.47, 0.56): {ring}",
    ]

# ---------------------------------------------------------------- a small RAW, every plane, a grid


def _old_load_raw(path) -> list:
    """The Bayer planes as `raw.load_frames` built them before: from a full copy of the mosaic, float64."""
    import rawpy

    from psfd.estimator.raw import Frame

    with rawpy.imread(str(path)) as raw:
        mosaic = raw.raw_image_visible.copy()
        top, left = raw.sizes.top_margin, raw.sizes.left_margin
        colors = np.array([[raw.raw_color(top + dy, left + dx) for dx in (0, 1)] for dy in (0, 1)])
        desc = raw.color_desc.decode("ascii")
        blacks = list(raw.black_level_per_channel)
        white = float(raw.white_level)
    planes, greens = {}, 0
    for dy in (0, 1):
        for dx in (0, 1):
            index = int(colors[dy, dx])
            letter = desc[index].lower()
            if letter == "g":
                greens += 1
            name = f"g{greens}" if letter == "g" else letter
            plane = mosaic[dy::2, dx::2]
            planes[name] = Frame(data=plane - float(blacks[index]), channel=name, white=white - float(blacks[index]),
                                 saturated=plane >= white, source=str(path), offset=(dy, dx),
                                 sensor_shape=mosaic.shape, from_mosaic=True)
    return [planes[c] for c in ("r", "g1", "g2", "b")]


def _old_estimate_frames(frames, grid, s=4, solver="nnls"):
    """`bernoulli.estimate_frames` as it ran before, serially in this process: every plane prepared, one
    band per raster factor, the windows solved plane after plane, the PSF records built here."""
    from psfd.estimator import bernoulli

    with bernoulli._one_blas_thread():  # as estimate_frames: one BLAS thread sums in one order
        return _old_path(frames, grid, s, solver)


def _old_path(frames, grid, s, solver):
    from psfd.estimator import bernoulli, geometry, kernels, target
    from psfd.estimator.kernels import PSF

    support = 4 * s + 1
    noise = target.default_noise()
    planes = []
    for frame, detection in bernoulli._detections(frames):
        image = np.asarray(frame.data, dtype=np.float64)
        to_image, to_pattern = geometry.target_maps(detection, "auto")
        box = bernoulli._target_box(to_image, image.shape, margin=(support - 1) // (2 * s) + 2)
        v, alpha, tail = bernoulli._corrected(frame, image, box, to_image, to_pattern, noise, (support - 1) / (2 * s))
        x0, y0 = box[0], box[1]

        def local_to_pattern(x, y, to_pattern=to_pattern, x0=x0, y0=y0):
            return to_pattern(np.asarray(x) + x0, np.asarray(y) + y0)

        plane = bernoulli._Plane(v, local_to_pattern, s, support, grid)
        planes.append((plane, frame, (x0, y0), alpha, tail, s * float(detection.scale)))
    bands = {}
    for factor in sorted({p.factor for p, *_ in planes}):
        same = [p for p, *_ in planes if p.factor == factor]
        bands[factor] = bernoulli.PatternBand(noise, factor, s, [j for p in same for j in p.jacobians],
                                              same[0].reference)
    out = []
    for plane, frame, (x0, y0), alpha, tail, scale in planes:
        for k in range(len(plane.windows)):
            r = bernoulli._window_result(plane, k, bands[plane.factor], solver, keep_normal=True)
            kernel, shift = bernoulli._recentred(r["psf"], solver, r["normal"], r["noise_floor"])
            wx0, wy0, wx1, wy1 = r["window"]
            window = (wx0 + x0, wy0 + y0, wx1 + x0, wy1 + y0)
            params = {"solver": solver, "support": support, "grid": [int(grid[0]), int(grid[1])], "crf_alpha": alpha,
                      "light_tail": tail, "scale": scale, "geometry": "homography+radial", "mass": r["mass"],
                      "samples": r["count"], "kernel_shift": [round(shift[0], 4), round(shift[1], 4)]}
            out.append(PSF(psf=kernel, s=s, method="bernoulli", channel=frame.channel, sources=[frame.source],
                           field=kernels.field_of_window(window, frame.shape), window=window,
                           noise_floor=r["noise_floor"], residual=r["residual"],
                           prediction_error=r["prediction_error"], params=params,
                           warnings=bernoulli._warnings(scale, alpha, r["mass"], s)))
    return out


@pytest.fixture(scope="module")
def small_raw(tmp_path_factory):
    from psfd.estimator import simulate

    path = tmp_path_factory.mktemp("frames") / "small.dng"
    simulate.simulate_target(path, psf=simulate.diffraction_psf(5.6, s=4, support=17), s=4, pixels_per_cell=0.3,
                             rotation_deg=3.0, sensor=(560, 720), seed=1, tilt=(0.02, -0.01), distortion=0.01)
    return path


@pytest.mark.parametrize("channel", ["all", "r", "g1", "g2", "b"])
def test_raw_planes_as_the_old_decode(small_raw, channel):
    from psfd.estimator import raw

    old = [f for f in _old_load_raw(small_raw) if channel in ("all", f.channel)]
    new = raw.load_frames(small_raw, channel)
    assert [f.channel for f in new] == [f.channel for f in old]
    for a, b in zip(new, old):
        assert a.data.dtype == b.data.dtype == np.float64 and np.array_equal(a.data, b.data)
        assert np.array_equal(a.saturated, b.saturated)
        assert (a.white, a.source, a.offset, a.sensor_shape, a.from_mosaic) == (
            b.white, b.source, b.offset, b.sensor_shape, b.from_mosaic)
        assert a.data.base is None or a.data.base.size == a.data.size  # its own memory, not LibRaw's buffer


@pytest.fixture(scope="module")
def old_estimates(small_raw):
    return _old_estimate_frames(_old_load_raw(small_raw), (3, 2))


def _same(new, old) -> None:
    assert len(new) == len(old)
    for a, b in zip(new, old):
        assert (a.channel, a.sources, a.window, a.field) == (b.channel, b.sources, b.window, b.field)
        assert np.array_equal(a.psf, b.psf)  # bit-identical
        assert (a.noise_floor, a.residual, a.prediction_error) == (b.noise_floor, b.residual, b.prediction_error)
        assert a.params == b.params and a.warnings == b.warnings


@pytest.mark.parametrize("workers", [1, 2])
def test_every_plane_and_window_as_the_old_path(small_raw, old_estimates, workers):
    from psfd.estimator import bernoulli, raw

    _same(bernoulli.estimate_frames(raw.load_frames(small_raw, "all"), grid=(3, 2), workers=workers), old_estimates)


def test_one_plane_as_the_old_path(small_raw):
    from psfd.estimator import bernoulli, raw

    b = bernoulli.estimate_frames(raw.load_frames(small_raw, "b"), grid=(3, 2), workers=2)
    _same(b, _old_estimate_frames([f for f in _old_load_raw(small_raw) if f.channel == "b"], (3, 2)))


@pytest.mark.parametrize("channels", [["g1"], ["r", "b"]])
def test_a_run_step_decodes_only_its_plane_with_the_same_psfs(small_raw, channels):
    """A run's step (`work.estimate_step`) decodes only the plane a plan asks for when there is one (a
    quarter of the memory of all four): its PSFs are those it made from all four planes decoded."""
    from psfd.daemon import work
    from psfd.estimator import bernoulli, raw

    step = work.estimate_step("bernoulli", [str(small_raw)], channels, {"grid": (2, 1)})
    planes = {f.channel: f for f in raw.load_frames(small_raw, "all")}
    _same(step, bernoulli.estimate_frames([planes[c] for c in channels], grid=(2, 1), workers=1))


@pytest.mark.parametrize("supersample", [1, 3])
def test_cells_in_float32_are_the_float64_raster(supersample):
    from psfd.estimator import target

    noise = target.seeded_noise(2)
    wide = target.cells(noise, supersample)
    narrow = target.cells(noise, supersample, dtype=np.float32)
    assert wide.dtype == np.float64 and narrow.dtype == np.float32
    assert np.array_equal(narrow, wide.astype(np.float32))


def test_the_same_bits_for_any_number_of_workers(small_raw):
    """A window's band is read from the part kept for the same window of the previous plane, in the same
    process; the groups (`bernoulli._groups`) fix which, so the workers' scheduling never shows in the PSFs
    (a single window: two groups of two planes, on both cores)."""
    from psfd.estimator import bernoulli, raw

    frames = raw.load_frames(small_raw, "all")
    assert bernoulli._groups([1, 1, 1, 1]) == [[(0, 0), (1, 0)], [(2, 0), (3, 0)]]
    assert bernoulli._groups([2, 2, 1]) == [[(0, 0), (1, 0), (2, 0)], [(0, 1), (1, 1)]]
    for grid in ((1, 1), (3, 2)):
        one = bernoulli.estimate_frames(frames, grid=grid, workers=1)
        for _ in range(2):
            _same(bernoulli.estimate_frames(frames, grid=grid, workers=2), one)
