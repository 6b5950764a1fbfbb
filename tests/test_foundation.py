"""Shared building blocks: frame input, resampling, MTF figures, the PSF record, the target layout."""

from __future__ import annotations

import numpy as np
import pytest

from psfd.errors import BadInputError
from psfd.estimator import kernels, mtf, raw, resample, target


def _gaussian(sigma_px: float, s: int = 4, support: int = 33) -> np.ndarray:
    r = np.arange(support) - support // 2
    g = np.exp(-(r[None, :] ** 2 + r[:, None] ** 2) / (2 * (sigma_px * s) ** 2))
    return g / g.sum()


# --- frames -------------------------------------------------------------------------------


def test_dng_round_trip_splits_bayer_planes_and_marks_saturation(tmp_path):
    rng = np.random.default_rng(1)
    mosaic = rng.integers(600, 4000, (40, 60)).astype(np.uint16)
    mosaic[2, 2] = 4095  # an R photosite at the white level
    path = tmp_path / "x.dng"
    raw.write_dng(path, mosaic, pattern="RGGB", black=512, white=4095)
    planes = {f.channel: f for f in raw.load_frames(path)}
    assert list(planes) == ["r", "g1", "g2", "b"]
    offsets = {"r": (0, 0), "g1": (0, 1), "g2": (1, 0), "b": (1, 1)}
    for name, (dy, dx) in offsets.items():
        np.testing.assert_array_equal(planes[name].data, mosaic[dy::2, dx::2].astype(float) - 512)
        assert planes[name].offset == (dy, dx)
        assert planes[name].white == 4095 - 512
        assert planes[name].sensor_shape == (40, 60)
        assert planes[name].from_mosaic
    assert planes["r"].saturated[1, 1] and planes["r"].saturated.sum() == 1
    assert raw.load_frame(path, "b").channel == "b"


def test_other_cfa_phases_keep_their_names(tmp_path):
    mosaic = np.arange(64 * 64, dtype=np.uint16).reshape(64, 64) + 100
    path = tmp_path / "g.dng"
    raw.write_dng(path, mosaic, pattern="GBRG")
    planes = {f.channel: f.offset for f in raw.load_frames(path)}
    assert planes == {"g2": (0, 0), "b": (0, 1), "r": (1, 0), "g1": (1, 1)}  # g1 on the red rows, as LibRaw's 1


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_planes_are_handed_over_g1_first_as_they_are_built(tmp_path, pattern):
    """``built`` receives each requested plane once made, g1 (where a target is searched) first, and the
    very planes returned; the names stay in raster order and the planes are those read without it."""
    mosaic = np.random.default_rng(2).integers(600, 4000, (40, 60)).astype(np.uint16)
    path = tmp_path / "x.dng"
    raw.write_dng(path, mosaic, pattern=pattern, black=512, white=4095)
    handed: list = []
    frames = raw.load_frames(path, "all", handed.append)
    assert handed[0].channel == "g1" and sorted(f.channel for f in handed) == sorted(raw.CHANNELS)
    assert {id(f) for f in handed} == {id(f) for f in frames}
    assert [f.channel for f in frames] == list(raw.CHANNELS)
    for with_callback, plain in zip(frames, raw.load_frames(path)):
        np.testing.assert_array_equal(with_callback.data, plain.data)
        np.testing.assert_array_equal(with_callback.saturated, plain.saturated)
        assert with_callback.offset == plain.offset
    handed.clear()
    assert raw.load_frames(path, "b", handed.append) == handed and handed[0].channel == "b"
    with pytest.raises(BadInputError, match=f"has {', '.join(_raster_names(pattern))}"):
        raw.load_frames(path, "mono")


def _raster_names(pattern: str) -> list[str]:
    """The plane names of a 2 x 2 pattern in raster order (the greens named by the rows they share)."""
    red_row = pattern.index("R") // 2
    return [c.lower() if c != "G" else ("g1" if i // 2 == red_row else "g2") for i, c in enumerate(pattern)]


@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
def test_a_green_keeps_its_name_in_every_phase_of_the_mosaic(tmp_path, pattern):
    """g1 is the green on the rows of red and g2 the one on the rows of blue, as LibRaw numbers them (colour
    1 and 3): the same photosites are named alike in a mosaic cropped by a row or a column, where the names
    were given in raster order (a one-row crop of an RGGB frame swapped them)."""
    mosaic = np.random.default_rng(1).integers(600, 4000, (66, 66)).astype(np.uint16)
    raw.write_dng(tmp_path / "whole.dng", mosaic, pattern=pattern)
    whole = {f.channel: f for f in raw.load_frames(tmp_path / "whole.dng")}
    red_rows = whole["r"].offset[0]
    assert whole["g1"].offset[0] == red_rows and whole["g2"].offset[0] != red_rows
    cropped_pattern = {"RGGB": "GBRG", "BGGR": "GRBG", "GRBG": "BGGR", "GBRG": "RGGB"}[pattern]
    raw.write_dng(tmp_path / "crop.dng", mosaic[1:-1], pattern=cropped_pattern)  # one row off each end
    for frame in raw.load_frames(tmp_path / "crop.dng"):
        dy, dx = whole[frame.channel].offset
        # the plane of the crop starts one row of photosites lower: its rows are the whole plane's from where
        # that row falls
        first = (frame.offset[0] + 1 - dy) // 2
        assert frame.offset[1] == dx and (frame.offset[0] + 1 - dy) % 2 == 0, frame.channel
        np.testing.assert_array_equal(frame.data, whole[frame.channel].data[first: first + frame.data.shape[0]])


def test_an_x_trans_raw_is_refused_not_split_into_mixed_planes(tmp_path):
    """A 6 x 6 X-Trans sensor (Fujifilm's layout): every 2 x 2 sub-grid of it mixes red, green and blue
    photosites (the one from (0, 0) holds 5 green, 2 red and 2 blue in each 6 x 6 tile). It was read as a
    Bayer mosaic whose top-left 2 x 2 was all green: a "g1" and a "g2" plane, each four ninths not green."""
    xtrans = "GGRGGB" "GGBGGR" "BRGRBG" "GGBGGR" "GGRGGB" "RBGBRG"
    path = tmp_path / "xtrans.dng"
    raw.write_dng(path, np.random.default_rng(0).integers(600, 4000, (96, 144)).astype(np.uint16),
                  pattern=xtrans, black=512, white=16383)
    for channel in ("all", "g1"):
        with pytest.raises(BadInputError, match="6x6 colour filter pattern, not a 2 x 2 Bayer mosaic"):
            raw.load_frames(path, channel)


def test_pgm_is_one_plane_named_mono(data_dir):
    frame = raw.load_frame(data_dir / "img_example.pgm")
    assert frame.channel == "mono" and frame.shape == (292, 328) and frame.white == 255
    assert not frame.from_mosaic
    assert raw.load_frames(data_dir / "img_example.pgm")[0].channel == "mono"
    with pytest.raises(BadInputError, match=r"img_example.pgm: has no g1 channel \(a single-channel image"):
        raw.load_frame(data_dir / "img_example.pgm", "g1")


def test_sixteen_bit_pgm_white_level_comes_from_its_header(tmp_path):
    path = tmp_path / "w.pgm"
    body = np.full((16, 20), 4095, dtype=">u2")  # the smallest plane psfd reads (raw.MIN_SIDE)
    path.write_bytes(b"P5\n20 16\n4095\n" + body.tobytes())
    frame = raw.load_frame(path, "mono")
    assert frame.white == 4095 and frame.saturated.all()


def test_eight_bit_pgm_white_level_comes_from_its_header(tmp_path):
    # Netpbm allows any maxval up to 255 in one byte per sample: 200 is its white, and what reaches it is clipped
    path = tmp_path / "w.pgm"
    body = np.tile(np.array([0, 100, 199, 200], np.uint8), (16, 5))
    path.write_bytes(b"P5\n20 16\n200\n" + body.tobytes())
    frame = raw.load_frame(path, "mono")
    assert frame.white == 200
    np.testing.assert_array_equal(frame.saturated, body == 200)


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("notes.pgm", b"this is not an image", "not a readable image"),
        ("notes.dng", b"II*\x00garbage", "not a readable RAW file"),
    ],
)
def test_unreadable_files_are_bad_input(tmp_path, name, content, message):
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(BadInputError, match=message):
        raw.load_frames(path)


def test_truncated_dng_is_bad_input(tmp_path):
    path = tmp_path / "full.dng"
    raw.write_dng(path, np.full((64, 64), 1000, dtype=np.uint16))
    cut = tmp_path / "cut.dng"
    cut.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(BadInputError, match="cut.dng"):
        raw.load_frames(cut)


def test_folders_and_foreign_files_are_named_as_such(tmp_path):
    with pytest.raises(BadInputError, match="is a folder"):
        raw.load_frames(tmp_path)
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(BadInputError, match="not an image psfd reads"):
        raw.load_frames(tmp_path / "notes.txt")


def test_missing_file_and_unknown_channel(tmp_path, data_dir):
    with pytest.raises(BadInputError, match="no such file"):
        raw.load_frames(tmp_path / "nope.dng")
    with pytest.raises(BadInputError, match="unknown channel"):
        raw.load_frames(data_dir / "img_example.pgm", "green")


def test_colour_image_is_refused(tmp_path):
    import cv2

    path = tmp_path / "rgb.png"
    cv2.imwrite(str(path), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(BadInputError, match="colour channels"):
        raw.load_frames(path)


def test_write_dng_leaves_no_partial_file_on_failure(tmp_path):
    with pytest.raises(Exception):
        raw.write_dng(tmp_path / "x.dng", np.zeros((4, 4, 4), dtype=np.uint16), pattern="RGXB")
    assert list(tmp_path.iterdir()) == []


# --- resampling -----------------------------------------------------------------------------


def test_keys_bicubic_interpolates_samples_and_reproduces_quadratics():
    rng = np.random.default_rng(0)
    image = rng.random((20, 30))
    yy, xx = np.mgrid[0:20, 0:30].astype(float)
    at_samples = resample.keys_bicubic(image, xx, yy)
    valid = ~np.isnan(at_samples)
    np.testing.assert_allclose(at_samples[valid], image[valid], atol=1e-12)
    # Keys (1981): with a = -0.5 the kernel reproduces polynomials up to degree 2 exactly.
    quad = 0.01 * xx**2 - 0.02 * xx * yy + 0.3 * yy
    x, y = xx[3:-4, 3:-4] + 0.37, yy[3:-4, 3:-4] + 0.61
    np.testing.assert_allclose(
        resample.keys_bicubic(quad, x, y), 0.01 * x**2 - 0.02 * x * y + 0.3 * y, atol=1e-10
    )
    assert np.isnan(resample.keys_bicubic(image, np.array([0.5]), np.array([5.0]))[0])


def test_keys_weights_sum_to_one():
    t = np.linspace(0, 0.999, 50)
    np.testing.assert_allclose(resample.keys_weights(t).sum(axis=-1), 1.0, atol=1e-12)



@pytest.mark.parametrize("s", [2, 4, 5])
def test_keys_upsample_reproduces_quadratics_on_the_fine_grid(s):
    # Keys (1981), a = -0.5: a quadratic sampled on the integers is interpolated exactly at every i / s, j / s
    start, shape = (2 * s + 1, 3 * s - 1), (4 * s + 3, 5 * s + 2)
    gy = resample.keys_grid(start[0], shape[0], s).astype(float)
    gx = resample.keys_grid(start[1], shape[1], s).astype(float)
    quad = lambda x, y: 0.02 * x**2 - 0.03 * x * y + 0.01 * y**2 + 0.4 * x - 0.2 * y + 1.5  # noqa: E731
    values = quad(*np.meshgrid(gx, gy))
    y, x = np.mgrid[start[0]: start[0] + shape[0], start[1]: start[1] + shape[1]] / s
    np.testing.assert_allclose(resample.keys_upsample(values, s, start, shape), quad(x, y), rtol=0, atol=1e-12)
    # several functions on one grid (the map's X and Y, `bernoulli._pattern_grid`): each as when alone
    both = resample.keys_upsample(np.stack([values, quad(*np.meshgrid(gx, gy)[::-1])]), s, start, shape)
    np.testing.assert_allclose(both, [quad(x, y), quad(y, x)], rtol=0, atol=1e-12)

def test_dct_lowpass_keeps_low_and_removes_high_frequencies():
    n = 64
    x = np.arange(n)
    low = np.cos(np.pi * 3 * (x + 0.5) / n)  # DCT-II basis function 3
    high = np.cos(np.pi * 40 * (x + 0.5) / n)
    image = np.add.outer(low + high, np.zeros(n))
    out = resample.dct_lowpass(image, (20, 20))
    np.testing.assert_allclose(out, np.add.outer(low, np.zeros(n)), atol=1e-10)


def test_erode_shrinks_a_mask_by_radius():
    mask = np.zeros((20, 20), bool)
    mask[5:15, 5:15] = True
    eroded = resample.erode(mask, 2)
    assert eroded.sum() == 6 * 6 and eroded[7:13, 7:13].all()


# --- MTF and the PSF record -------------------------------------------------------------------


def test_gaussian_mtf50_and_fwhm_match_closed_forms():
    sigma = 0.6  # channel pixels
    kernel = _gaussian(sigma)
    freqs, mx, my = mtf.profiles(kernel, 4)
    # MTF of a Gaussian: exp(-2 pi^2 sigma^2 f^2) = 0.5 at f = sqrt(ln 2 / 2) / (pi sigma)
    assert mtf.mtf50(freqs, mx) == pytest.approx(np.sqrt(np.log(2) / 2) / (np.pi * sigma), rel=2e-3)
    assert mtf.mtf50(freqs, my) == pytest.approx(mtf.mtf50(freqs, mx))
    fx, fy = mtf.fwhm(kernel, 4)
    assert fx == pytest.approx(2 * np.sqrt(2 * np.log(2)) * sigma, rel=0.01)


def test_psf_record_to_json_has_the_documented_fields():
    record = kernels.PSF(_gaussian(0.5, support=17), 4, "bernoulli", "g1", ["a.dng"], field=(0.25, 0.75))
    out = record.to_json()
    for key in ("method", "source", "channel", "s", "support", "field_x", "field_y", "psf", "mtf50_x", "mtf50_y"):
        assert key in out
    assert out["support"] == 17 and out["source"] == "a.dng" and len(out["psf"]) == 17


def test_psf_helpers():
    k = np.zeros((5, 5))
    k[2, 3] = 2.0
    k[2, 1] = -1.0
    clipped = kernels.clip_negatives(k)
    assert clipped.sum() == pytest.approx(1.0) and clipped.min() == 0
    assert kernels.centroid(clipped) == pytest.approx((1.0, 0.0))
    with pytest.raises(ValueError):
        kernels.normalise(np.zeros((3, 3)))
    # the core centroid ignores faint tails that would drag a plain centroid
    tailed = clipped.copy()
    tailed[0, 0] = 0.01
    assert kernels.centroid(tailed)[0] < 0.98 and kernels.core_centroid(tailed) == pytest.approx((1.0, 0.0))
    windows = kernels.split_grid((0, 0, 100, 60), (2, 3))
    assert windows[0] == (0, 0, 50, 20) and windows[-1] == (50, 40, 100, 60) and len(windows) == 6
    assert kernels.field_of_window((50, 40, 100, 60), (60, 100)) == pytest.approx((0.75, 50 / 60))


# --- target layout ------------------------------------------------------------------------------


def test_target_layout_matches_the_published_pattern():
    noise = target.default_noise()
    assert noise.shape == (256, 256) and set(np.unique(noise)) == {0.0, 1.0}
    assert abs(noise.mean() - 0.5) < 0.01
    raster = target.cells(noise, supersample=4)
    assert raster.shape == (1280, 1280)
    np.testing.assert_array_equal(raster[32 * 4 : 288 * 4 : 4, 32 * 4 : 288 * 4 : 4], noise)
    for bx, by in target.BLACK_BLOCKS:
        assert raster[(32 * by + 16) * 4, (32 * bx + 16) * 4] == 0
    for bx, by in target.WHITE_BLOCKS:
        assert raster[(32 * by + 16) * 4, (32 * bx + 16) * 4] == 1
    for bx, by in target.XCORNER_BLOCKS:
        cy, cx = (32 * by + 16) * 4, (32 * bx + 16) * 4
        # hourglass: black above and below the saddle, white left and right
        assert raster[cy - 40, cx] == 0 and raster[cy + 40, cx] == 0
        assert raster[cy, cx - 40] == 1 and raster[cy, cx + 40] == 1
    # (9, 9) is the only X-corner with two black neighbours in the ring
    black = set(target.BLACK_BLOCKS)

    def black_neighbours(block):
        bx, by = block
        return len({(bx - 1, by), (bx + 1, by), (bx, by - 1), (bx, by + 1)} & black)

    flanked = [b for b in target.XCORNER_BLOCKS if black_neighbours(b) == 2]
    assert flanked == [target.ORIENTATION_CORNER]


def test_seeded_noise_is_reproducible_and_round_trips(tmp_path):
    a = target.seeded_noise(7)
    np.testing.assert_array_equal(a, target.seeded_noise(7))
    assert not np.array_equal(a, target.seeded_noise(8))
    target.save_noise(a, tmp_path / "n.pgm")
    np.testing.assert_array_equal(target.load_noise(tmp_path / "n.pgm"), a)
    target.save_noise(np.zeros((10, 10)), tmp_path / "small.pgm")
    with pytest.raises(BadInputError, match="256x256"):
        target.load_noise(tmp_path / "small.pgm")


def test_dct_lowpass_resynthesises_a_band_on_a_finer_grid():
    n, m = 40, 100
    x = np.arange(n)
    image = np.add.outer(np.cos(np.pi * 3 * (x + 0.5) / n), np.zeros(n))
    fine = resample.dct_lowpass(image, (10, 10), size=(m, m))
    xf = (np.arange(m) + 0.5) * n / m - 0.5  # fine sample i sits at this original coordinate
    np.testing.assert_allclose(fine, np.add.outer(np.cos(np.pi * 3 * (xf + 0.5) / n), np.zeros(m)), atol=1e-10)
    assert resample.dct_lowpass(image.astype(np.float32), (10, 10)).dtype == np.float32


def test_dct_lowpass_with_masks_filters_the_symmetric_extension():
    """mask / cross_mask filter the DCT's half-sample-symmetric extension with any centrally symmetric band.

    Reference: the 2-D FFT of the explicit 2R x 2C extension, multiplied by a
    rotated square band (not symmetric under a mirror), first quadrant kept.
    """
    rng = np.random.default_rng(0)
    rows, cols = 40, 52
    image = rng.random((rows, cols))
    extended = np.block([[image, image[:, ::-1]], [image[::-1], image[::-1, ::-1]]])
    ky, kx = np.meshgrid(np.fft.fftfreq(2 * rows) * 2 * rows, np.fft.fftfreq(2 * cols) * 2 * cols, indexing="ij")

    def band(kx, ky):  # a square of half-width 1/2 (in units of the size) turned by 0.4 rad
        u = np.cos(0.4) * kx / cols + np.sin(0.4) * ky / rows
        v = -np.sin(0.4) * kx / cols + np.cos(0.4) * ky / rows
        return (np.abs(u) < 0.5) & (np.abs(v) < 0.5)

    expected = np.real(np.fft.ifft2(np.fft.fft2(extended) * band(kx, ky)))[:rows, :cols]
    i, j = np.mgrid[0:rows, 0:cols]
    same, cross = band(j, i), band(j, -i)
    out = resample.dct_lowpass(image, (rows, cols), mask=same, cross_mask=cross)
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # cropping ``keep`` drops the coefficients beyond it, as zeroing them in the masks does
    cut = np.zeros_like(same)
    cut[:30, :40] = True
    np.testing.assert_allclose(
        resample.dct_lowpass(image, (30, 40), mask=same, cross_mask=cross),
        resample.dct_lowpass(image, (rows, cols), mask=same & cut, cross_mask=cross & cut),
        atol=1e-12,
    )
    # a mask alone weights the DCT coefficients: a rectangle is the plain truncation
    np.testing.assert_allclose(
        resample.dct_lowpass(image, (rows, cols), mask=cut), resample.dct_lowpass(image, (30, 40)), atol=1e-12
    )
    with pytest.raises(ValueError, match="coefficients"):
        resample.dct_lowpass(image, (30, 40), mask=np.ones((10, 10)))


def test_cli_turns_an_unforeseen_file_system_refusal_into_one_line(tmp_path, capfd):
    from psfd.cli import main

    blocker = tmp_path / "file.txt"
    blocker.write_text("a file where a folder should be")
    code = main(["target", "--out", str(blocker / "sub" / "t.png")])
    err = capfd.readouterr().err
    assert code != 0 and err.startswith("psfd: error:") and err.count("\n") == 1, err
