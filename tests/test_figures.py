"""The figures as an imaging engineer reads them: what each axis says, which scale is shared, what is drawn where.

The figures are checked through matplotlib's own objects (axes, labels, norms, artists' data), so the
checks name what a reader sees without comparing pixels.
"""

from __future__ import annotations

import math
import re

import cv2
import numpy as np
import pytest
from matplotlib.collections import PathCollection, TriMesh
from matplotlib.colors import LogNorm
from PIL import Image

from psfd import figures
from psfd.estimator import mtf
from psfd.estimator.kernels import PSF


def gaussian(sigma_x: float, sigma_y: float, s: int = 4, support: int = 17, angle: float = 0.0) -> np.ndarray:
    """A unit-sum Gaussian on the s-times grid, sigmas in channel pixels along the axes rotated by ``angle``."""
    r = (np.arange(support) - support // 2) / s
    x, y = np.meshgrid(r, r)
    u = x * math.cos(angle) + y * math.sin(angle)
    v = -x * math.sin(angle) + y * math.cos(angle)
    k = np.exp(-0.5 * (u / sigma_x) ** 2 - 0.5 * (v / sigma_y) ** 2)
    return k / k.sum()


def estimate(psf: np.ndarray, noise_floor: float | None = 1e-3, **extra) -> PSF:
    return PSF(psf, 4, "bernoulli", "g1", ["/data/IMG_0001.dng"], (0.3, 0.6), (100, 50, 200, 150),
               noise_floor=noise_floor, **extra)


def texts(fig) -> str:
    return " | ".join(t.get_text() for ax in fig.axes for t in (ax.title, ax.xaxis.label, ax.yaxis.label)) + \
        " | " + (fig._suptitle.get_text() if fig._suptitle else "")


def test_pixel_borders_surround_the_centre_sample():
    # 17 samples at s = 4 span 4.25 channel pixels: borders half a pixel either side of the centre pixel
    assert figures.pixel_borders(17, 4) == [-1.5, -0.5, 0.5, 1.5]
    assert figures.pixel_borders(13, 3) == [-1.5, -0.5, 0.5, 1.5]
    assert figures.pixel_borders(9, 1) == [-3.5, -2.5, -1.5, -0.5, 0.5, 1.5, 2.5, 3.5]
    assert figures.kernel_extent((17, 17), 4) == [-2.125, 2.125, 2.125, -2.125]


def test_psf_figure_linear_log_and_mtf_with_noise_band():
    psf = gaussian(0.6, 0.9)
    psf[0, 0] = -2e-4  # a negative sample, as unregularised least squares leaves
    psf /= psf.sum()
    fig = figures.psf_figure(estimate(psf), pitch_um=4.0)
    images = [a for ax in fig.axes for a in ax.get_images()]
    assert len(images) == 2  # linear and log views
    linear, log = images
    assert linear.norm.vmin == 0 and linear.norm.vmax == pytest.approx(psf.max())
    assert isinstance(log.norm, LogNorm) and log.norm.vmin == pytest.approx(psf.max() * 1e-4)
    assert np.ma.masked_invalid(log.get_array()).mask[0, 0]  # the negative sample is drawn as "bad" (blue), never as a small value
    # both views on the s-grid in channel pixels, with the channel-pixel borders drawn
    for image in images:
        assert image.get_extent() == pytest.approx([-2.125, 2.125, 2.125, -2.125])
        ax = image.axes
        assert ax.get_xlabel() == "x (channel pixels)" and ax.get_ylabel() == "y (channel pixels)"
        verticals = sorted(line.get_xdata()[0] for line in ax.get_lines() if line.get_xdata()[0] == line.get_xdata()[1])
        assert verticals == [-1.5, -0.5, 0.5, 1.5]
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(bars) == 2 and all("fraction of energy per sample" in ax.get_ylabel() for ax in bars)
    # the log view's white line: the floor per sample, the norm of the kernel's error over its 17 x 17 samples / 17
    (white,) = [line for line in bars[1].get_lines() if line.get_color() == "white"]
    assert white.get_ydata()[0] == pytest.approx(1e-3 / 17)
    assert "noise floor per sample" in bars[1].get_ylabel()
    relative = 1e-3 / np.linalg.norm(psf)
    assert f"noise floor {relative:.1%} of the kernel's L2 norm ({1e-3 / 17:.1e} per sample)" in fig._suptitle.get_text()
    assert all(len(ax.get_yticks()) >= 3 for ax in bars)  # colour bars with ticks
    mtf_ax = next(ax for ax in fig.axes if ax.get_ylabel() == "MTF")
    assert mtf_ax.get_xlabel() == figures.FREQ_LABEL
    freqs, mx, my = mtf.profiles(psf, 4)
    assert mtf_ax.get_ylim()[1] >= max(mx.max(), my.max())
    assert mtf_ax.get_xlim() == pytest.approx((0, 2.0))  # up to s/2
    band = figures.mtf_noise_band(estimate(psf))
    assert band == pytest.approx(1e-3)  # the floor: the norm of the kernel's error, each OTF value's (Parseval)
    spans = [p for p in mtf_ax.patches if p.get_label().startswith("noise floor")]
    assert len(spans) == 1 and spans[0].get_path().get_extents().transformed(spans[0].get_transform()).height > 0
    legend = [t.get_text() for t in mtf_ax.get_legend().get_texts()]
    assert any(t.startswith("x (horizontal frequency): MTF50 0.") for t in legend)
    # lp/mm on a second axis: 1 cycle per channel pixel = 1 / (2 x 4 um) = 125 lp/mm
    top = [child for child in mtf_ax.child_axes if child.get_xlabel() == "line pairs per mm"]
    assert len(top) == 1
    assert "channel g1" in fig._suptitle.get_text() and "s = 4" in fig._suptitle.get_text()
    assert figures.mtf_noise_band(estimate(psf, noise_floor=None)) is None


def test_psf_figures_drawn_in_turn_match_each_figure_drawn_whole(tmp_path):
    """`PSFFigures` draws an estimate's own artists over the axes its layout shares: every pixel as the whole
    figure (`save_psf`), whatever the estimates before it left on the canvas. Each kernel changes what the
    one before showed: the colour bars' range, the noise band and white line (none without a floor), the
    MTF50 marks (none where the MTF stays above 0.5 up to s/2), the legend and the title."""
    sharpened = 1.6 * gaussian(0.5, 0.5) - 0.6 * gaussian(1.2, 1.2)  # MTF above 1: a taller MTF axis
    kernels = [estimate(gaussian(0.6, 0.9)), estimate(gaussian(1.1, 0.5), noise_floor=None),
               estimate(gaussian(0.05, 0.05)), estimate(gaussian(0.3, 0.3), noise_floor=2e-2),
               estimate(sharpened / sharpened.sum()), estimate(gaussian(0.6, 0.9))]
    assert not math.isfinite(kernels[2].metrics()["mtf50_x"])  # MTF 0.82 at s/2: no MTF50 to mark
    drawer = figures.PSFFigures()
    for n, est in enumerate(kernels):
        drawer.save(est, tmp_path / f"turn{n}.png", pitch_um=4.0)
        figures.save_psf(est, tmp_path / f"whole{n}.png", pitch_um=4.0)
        turn, whole = (cv2.imread(str(tmp_path / f"{k}{n}.png")) for k in ("turn", "whole"))
        assert turn.shape == whole.shape and np.array_equal(turn, whole), n
    assert len(drawer._layouts) == 2  # the Gaussians shared one: all but the first were drawn over it
    turn, whole = (Image.open(tmp_path / f"{k}0.png") for k in ("turn", "whole"))
    assert turn.info["Creator"] == whole.info["Creator"] == "psfd"
    assert turn.info["dpi"] == pytest.approx(whole.info["dpi"], abs=0.01)


def test_log_colour_bar_label_sits_where_matplotlib_places_it_for_every_kernel():
    """The log colour bar's label is at one place for every kernel (`PSFFigures` draws it once per layout): the
    label pad right of the tick labels, as matplotlib places it by them, from a near-delta's peak to a wide one's."""
    for psf in (gaussian(0.05, 0.05), gaussian(0.6, 0.9), gaussian(2.0, 2.0, support=33)):
        fig = figures.psf_figure(estimate(psf))
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        bar = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"][1]
        right = max(t.get_window_extent(renderer).x1 for t in bar.get_yticklabels() if t.get_text())
        gap = bar.yaxis.label.get_window_extent(renderer).x0 - right
        assert gap == pytest.approx(bar.yaxis.labelpad * fig.dpi / 72, abs=0.5), psf.max()


def test_png_writer_is_read_back_by_an_independent_decoder(tmp_path):
    """`write_png`'s file as libpng (OpenCV) and Pillow decode it: the same pixels, the dpi and the creator."""
    rgb = np.random.default_rng(1).integers(0, 256, size=(37, 53, 3), dtype=np.uint8)
    rgb[10:20] = 255  # a flat band, as a figure's background
    figures.write_png(rgb, tmp_path / "f.png")
    assert np.array_equal(cv2.imread(str(tmp_path / "f.png"))[..., ::-1], rgb)
    image = Image.open(tmp_path / "f.png")
    assert image.mode == "RGB" and np.array_equal(np.asarray(image), rgb)
    assert image.info["Creator"] == "psfd" and image.info["dpi"] == pytest.approx((figures.DPI, figures.DPI), abs=0.01)


def test_comparison_figure_does_not_clip_and_its_legend_matches_the_lines():
    truth = gaussian(0.5, 0.5, support=33)
    sharpened = 1.6 * truth - 0.6 * gaussian(1.2, 1.2, support=33)  # negative lobes: MTF up to 1.12
    fig = figures.comparison_figure([("truth", truth, 4), ("sharpened", sharpened, 4)], against_truth=True)
    (ax,) = fig.axes
    _, mx, my = mtf.profiles(sharpened, 4)
    assert max(mx.max(), my.max()) > 1.05
    assert ax.get_ylim()[1] >= max(mx.max(), my.max())  # nothing clipped
    assert ax.get_ylabel() == "MTF" and ax.get_xlabel() == figures.FREQ_LABEL
    assert "true PSF" in ax.get_title()
    styles = {line.get_linestyle() for line in ax.get_lines() if len(line.get_xdata()) > 2}
    assert styles == {"-", "--"}
    legend = {t.get_text(): h.get_linestyle() for t, h in zip(ax.get_legend().get_texts(), ax.get_legend().legend_handles)}
    assert legend["solid: x (horizontal frequency)"] == "-" and legend["dashed: y (vertical frequency)"] == "--"
    assert "truth" in legend and "sharpened" in legend


def test_array_figures_have_axes_units_and_a_zero_centred_scale():
    est = estimate(gaussian(0.6, 0.6))
    signed = np.random.default_rng(0).normal(size=(30, 40))
    fig = figures.array_figure(signed, "residual", est)
    image = fig.axes[0].get_images()[0]
    assert image.norm.vmin == -image.norm.vmax  # 0 is the middle colour
    assert image.get_extent() == [99.5, 139.5, 79.5, 49.5]  # channel pixels of the window on the plane
    assert fig.axes[0].get_xlabel() == "x (channel pixels)" and "residual" in fig.axes[0].get_title()
    assert any(ax.get_label() == "<colorbar>" and ax.get_ylabel() for ax in fig.axes)
    kernel = figures.array_figure(gaussian(1.0, 1.0), "kernel", est).axes[0].get_images()[0]
    assert kernel.norm.vmin == 0 and kernel.get_extent() == pytest.approx([-2.125, 2.125, 2.125, -2.125])


def test_vector_and_raster_files(tmp_path):
    est = estimate(gaussian(0.6, 0.9))
    for name, magic in (("f.png", b"\x89PNG"), ("f.pdf", b"%PDF"), ("f.svg", b"<?xml")):
        figures.save_psf(est, tmp_path / name)
        assert (tmp_path / name).read_bytes().startswith(magic)
    assert figures.can_write("a.svg") and figures.can_write("a.PDF") and not figures.can_write("a.xyz")
    with pytest.raises(OSError, match="cannot write a figure"):
        figures.save_psf(est, tmp_path / "f.xyz")


def test_sagittal_and_meridional_against_an_elongated_gaussian():
    """A Gaussian of sigma_r along the radius and sigma_t across it: MTF exp(-2 pi^2 sigma^2 f^2), so
    MTF50 = sqrt(ln 2 / 2) / (pi sigma). Meridional (frequencies along the radius) sees sigma_r."""
    sigma_r, sigma_t = 0.9, 0.45
    field, aspect = (0.9, 0.85), 1.5
    angle = math.atan2(field[1] - 0.5, (field[0] - 0.5) * aspect)
    psf = gaussian(sigma_r, sigma_t, s=4, support=33, angle=angle)
    sagittal, meridional = figures.sagittal_meridional(psf, 4, field, aspect)
    expected = lambda sigma: math.sqrt(math.log(2) / 2) / (math.pi * sigma)  # noqa: E731
    # the sampled Gaussian is truncated at 4 sigma and sampled at 1/4 pixel: 1 % covers both
    assert meridional == pytest.approx(expected(sigma_r), rel=0.01)
    assert sagittal == pytest.approx(expected(sigma_t), rel=0.01)
    # along x the directional profile is the FFT profile
    freqs, mx, _ = mtf.profiles(psf, 4)
    np.testing.assert_allclose(mtf.directional_profile(psf, 4, 0.0, freqs), mx, atol=1e-9)


def rows_for(apertures, points, channels=("r", "g1", "g2", "b")):
    rows, arrays, n = [], {}, 0
    for aperture in apertures:
        for fx, fy in points:
            for channel in channels:
                n += 1
                r2 = (fx - 0.5) ** 2 + (fy - 0.5) ** 2
                arrays[n] = gaussian(0.3 * aperture / 4 * (1 + 3 * r2), 0.3 * aperture / 4)
                rows.append({"id": n, "camera": "cam", "lens": "lens", "method": "bernoulli", "aperture": aperture,
                             "channel": channel, "field_x": fx, "field_y": fy, "s": 4, "support": 17,
                             "window": [0, 0, 10, 10]})
    return rows, arrays


def test_report_shows_every_channel_on_the_true_sensor_with_shared_scales():
    grid = [(x, y) for y in (0.2, 0.5, 0.8) for x in (0.15, 0.5, 0.85)]
    rows, arrays = rows_for((4.0, 11.0), grid)
    sensor = figures.Sensor(6000, 4000, 3.9)
    fig = figures.report_figure(rows, arrays, "g1", {r["id"]: sensor for r in rows})
    psf_axes = [ax for ax in fig.axes if ax.get_title().endswith(": PSFs")]
    assert sorted(ax.get_title() for ax in psf_axes) == sorted(
        f"f/{a}  channel {c}: PSFs" for a in (4, 11) for c in ("r", "g1", "g2", "b"))
    for ax in psf_axes:  # the sensor's own 3:2 in photosites, and as many tiles as PSFs, all one size
        assert ax.get_xlim() == (0, 6000) and ax.get_ylim() == (4000, 0) and ax.get_aspect() == 1.0
        tiles = ax.get_images()
        assert len(tiles) == 9
        assert {round(t.get_extent()[1] - t.get_extent()[0], 6) for t in tiles} == {600.0}  # TILE of the width
        assert {id(t.norm) for t in tiles} == {id(psf_axes[0].get_images()[0].norm)}  # one log scale for all
    maps = [ax for ax in fig.axes if "MTF50" in ax.get_title() and ax.get_title().startswith("f/")]
    assert sorted(ax.get_title() for ax in maps) == sorted(
        f"f/{a}  g1: MTF50 {k}" for a in (4, 11) for k in ("sagittal", "meridional"))
    markers = [c for ax in maps for c in ax.collections if isinstance(c, PathCollection)]
    assert len(markers) == 4 and len({(c.norm.vmin, c.norm.vmax) for c in markers}) == 1  # one MTF50 scale
    for ax in maps:  # interpolation only between measured points: the mesh's vertices are the points
        (mesh,) = [c for c in ax.collections if isinstance(c, TriMesh)]
        (points,) = [c for c in ax.collections if isinstance(c, PathCollection)]
        vertices = {tuple(np.round(v, 6)) for v in zip(mesh._triangulation.x, mesh._triangulation.y)}
        assert vertices == {tuple(np.round(p, 6)) for p in points.get_offsets()}
        assert {tuple(np.round(p, 6)) for p in points.get_offsets()} == {(fx * 6000, fy * 4000) for fx, fy in grid}
    stated = [ax for ax in fig.axes if ax.get_label() == "<colorbar>" and "for all apertures" in ax.get_xlabel()]
    assert len(stated) == 1
    # mm on the sensor when the pitch is known: 6000 photosites of 3.9 um = 23.4 mm
    mm_axes = [child for ax in maps for child in ax.child_axes if child.get_xlabel() == "x (mm)"]
    forward, _ = mm_axes[0]._functions
    assert forward(6000.0) == pytest.approx(23.4)
    chart = next(ax for ax in fig.axes if ax.get_xlabel().startswith("image height"))
    assert chart.get_ylabel() == "MTF50 of g1\n(cycles per channel pixel)"
    (lp_mm,) = [child for child in chart.child_axes if child.get_ylabel() == "line pairs per mm"]
    forward, _ = lp_mm._functions  # Nyquist of a Bayer plane of 3.9 um photosites: 1 / (2 x 7.8 um) = 64.1 lp/mm
    assert forward(0.5) == pytest.approx(0.5 / (2 * 3.9e-3))


def test_report_of_one_point_and_no_pitch():
    """One measured point: a marker, no interpolated area; no pitch: photosites only; sensor from the window."""
    rows, arrays = rows_for((5.6,), [(0.5, 0.5)], channels=("g1",))
    rows[0]["window"] = [300, 200, 340, 240]  # centre (320, 220) of a 640 x 440 plane at (0.5, 0.5)
    fig = figures.report_figure(rows, arrays, "g1")
    maps = [ax for ax in fig.axes if "MTF50" in ax.get_title() and ax.get_title().startswith("f/")]
    assert all(not any(isinstance(c, TriMesh) for c in ax.collections) for ax in maps)
    psf_ax = next(ax for ax in fig.axes if ax.get_title().endswith(": PSFs"))
    assert psf_ax.get_xlim() == (0, 1280) and psf_ax.get_ylim() == (880, 0)  # Bayer plane x 2 photosites
    assert not any(child.get_xlabel() == "x (mm)" for ax in fig.axes for child in ax.child_axes)


@pytest.mark.parametrize("key, rigs", [
    ("serial", ["cam #A1, lens", "cam #B2, lens"]),
    ("lens_serial", ["cam, lens #A1", "cam, lens #B2"]),
])
def test_two_bodies_or_lens_copies_of_one_model_are_two_rows_not_one_map(key, rigs):
    """Two bodies (serials) of one camera model, or two copies of one lens model (the serials their frames
    record), at one aperture: each its own row of tiles and of MTF50 maps, never tiles drawn over each other
    nor values interpolated between them."""
    grid = [(x, y) for y in (0.2, 0.5, 0.8) for x in (0.15, 0.5, 0.85)]
    rows, arrays = rows_for((5.6,), grid, channels=("g1",))
    other, other_arrays = rows_for((5.6,), grid, channels=("g1",))
    for row in rows:
        row[key] = "A1"
    for row in other:
        arrays[row["id"] + 100] = other_arrays[row["id"]]
        row.update({"id": row["id"] + 100, key: "B2"})
    fig = figures.report_figure(rows + other, arrays, "g1")
    psf_axes = [ax for ax in fig.axes if ax.get_title().endswith(": PSFs")]
    assert [len(ax.get_images()) for ax in psf_axes] == [9, 9]
    assert [t.get_text() for t in fig.texts if t is not fig._suptitle] == rigs  # each row under its rig's name
    chart = next(ax for ax in fig.axes if ax.get_xlabel().startswith("image height"))
    assert {t.get_text() for t in chart.get_legend().get_texts()} >= {f"f/5.6 bernoulli, {rig}" for rig in rigs}


def inside_figure(fig) -> list[str]:
    """Texts and legends that fall (partly) outside the figure once drawn: a reader would see them cut."""
    fig.canvas.draw()
    renderer, box = fig.canvas.get_renderer(), fig.bbox
    artists = [a for ax in fig.axes for a in (ax.title, ax.xaxis.label, ax.yaxis.label, ax.get_legend()) if a]
    artists += [fig._suptitle] if fig._suptitle else []
    out = []
    for artist in artists:
        if getattr(artist, "get_text", lambda: "x")() == "":
            continue
        extent = artist.get_window_extent(renderer)
        if extent.x0 < box.x0 - 1 or extent.x1 > box.x1 + 1 or extent.y0 < box.y0 - 1 or extent.y1 > box.y1 + 1:
            out.append(getattr(artist, "get_text", lambda: "legend")())
    return out


def test_nothing_is_cut_off_at_the_figure_edges():
    label = "sharp-edge target w=2 IMG_0001_with_a_long_name.CR2"  # as `psfd compare` labels its curves
    truth = gaussian(0.5, 0.5, support=33)
    assert inside_figure(figures.comparison_figure([("truth", truth, 4), (label, gaussian(0.7, 0.6, support=33), 4)],
                                                   against_truth=True)) == []
    fig = figures.psf_figure(estimate(gaussian(0.6, 0.9)), pitch_um=4.0)
    assert inside_figure(fig) == []
    # the title's two lines (of a frame with a long name) clear every panel's title and the lp/mm axis
    renderer = fig.canvas.get_renderer()
    fig._suptitle.set_text(fig._suptitle.get_text().replace("IMG_0001.dng", "IMG_0001_with_a_long_name.CR2"))
    title = fig._suptitle.get_window_extent(renderer)
    below = [ax.title.get_window_extent(renderer) for ax in fig.axes if ax.get_title()]
    below += [child.get_tightbbox(renderer) for ax in fig.axes for child in ax.child_axes]
    assert len(below) == 4 and not any(box.overlaps(title) for box in below)
    rows, arrays = rows_for((4.0, 11.0), [(x, y) for y in (0.2, 0.5, 0.8) for x in (0.15, 0.5, 0.85)])
    assert inside_figure(figures.report_figure(rows, arrays, "g1")) == []


def test_report_marks_the_image_centre_above_a_tile_measured_there():
    rows, arrays = rows_for((5.6,), [(0.5, 0.5)], channels=("g1",))
    fig = figures.report_figure(rows, arrays, "g1", {rows[0]["id"]: figures.Sensor(640, 480, None)})
    for ax in (ax for ax in fig.axes if ax.get_title().startswith("f/")):
        (centre,) = [line for line in ax.get_lines() if line.get_marker() == "+"]
        assert tuple(centre.get_xydata()[0]) == (320, 240)
        assert centre.get_zorder() > max(a.get_zorder() for a in ax.get_images() + ax.collections)


def grid_estimates(nx: int, ny: int, channels=("g1", "r"), size=(40, 30), origin=(100, 50)) -> list[PSF]:
    """A grid of windows per channel, the PSF wider to the right (a field dependence to see)."""
    out = []
    for channel in channels:
        for j in range(ny):
            for i in range(nx):
                a, b = origin[0] + i * size[0], origin[1] + j * size[1]
                out.append(PSF(gaussian(0.4 + 0.1 * i, 0.5), 4, "bernoulli", channel, ["/data/IMG_0001.dng"],
                               ((i + 0.5) / nx, (j + 0.5) / ny), (a, b, a + size[0], b + size[1]),
                               params={"grid": [nx, ny]}))
    return out


def test_grid_figure_draws_each_kernel_over_its_window_on_shared_scales():
    estimates = grid_estimates(3, 2)
    fig = figures.grid_figure(estimates)
    titled = {ax.get_title(): ax for ax in fig.axes if ax.get_title()}
    assert sorted(titled) == sorted(f"channel {c}: {w}" for c in ("r", "g1") for w in ("PSFs", "MTF50 x", "MTF50 y"))
    columns = sorted(((ax.get_position().x0, ax.get_title().split(":")[0]) for ax in titled.values()))
    assert [c for _, c in columns][::3] == ["channel r", "channel g1"]  # the Bayer order, left to right
    for ax in titled.values():  # the channel plane in channel pixels, the windows' box at its true aspect
        assert ax.get_xlim() == (99.5, 219.5) and ax.get_ylim() == (109.5, 49.5) and ax.get_aspect() == 1.0
    peak = max(e.psf.max() for e in estimates)
    for channel in ("r", "g1"):
        (image,) = titled[f"channel {channel}: PSFs"].get_images()
        assert image.get_extent() == [99.5, 219.5, 109.5, 49.5]
        assert isinstance(image.norm, LogNorm) and image.norm.vmax == pytest.approx(peak)  # one scale for all
        assert image.norm.vmin == pytest.approx(peak * 1e-4)
        mosaic = image.get_array()
        sy, sx = mosaic.shape[0] / 60, mosaic.shape[1] / 120  # raster pixels per channel pixel
        for est in (e for e in estimates if e.channel == channel):  # every kernel sample inside its own window
            a, b, c, d = est.window
            k = est.psf.shape[0]
            at = (np.arange(k) + 0.5) / k  # the samples' centres, as fractions of the window
            rows = ((b + at * (d - b) - 50) * sy).astype(int)
            cols = ((a + at * (c - a) - 100) * sx).astype(int)
            np.testing.assert_array_equal(mosaic[np.ix_(rows, cols)], est.psf.astype(np.float32))
        for axis, name in enumerate(("x", "y")):
            ax = titled[f"channel {channel}: MTF50 {name}"]
            (cells,) = ax.collections
            mine = [e for e in estimates if e.channel == channel]
            expected = [e.metrics()[f"mtf50_{name}"] for e in mine]
            np.testing.assert_allclose(cells.get_array(), expected)
            assert [t.get_text() for t in ax.texts] == [f"{v:.3f}" for v in expected]  # six windows: written
            assert cells.norm.vmin == pytest.approx(min(e.metrics()[k] for e in estimates for k in ("mtf50_x", "mtf50_y")))
    x_mtf = [e.metrics()["mtf50_x"] for e in estimates if e.channel == "g1"]
    assert x_mtf[0] > x_mtf[1] > x_mtf[2]  # the wider PSFs to the right: the field dependence is what is drawn
    bars = [ax for ax in fig.axes if ax.get_label() == "<colorbar>"]
    assert len(bars) == 2 and "log scale" in bars[0].get_ylabel() and "MTF50" in bars[1].get_ylabel()
    assert "3x2 grid of windows" in fig._suptitle.get_text()
    assert inside_figure(fig) == []
    assert inside_figure(figures.grid_figure(grid_estimates(3, 2, channels=("mono",)))) == []  # one narrow column


def test_grid_figure_of_a_large_grid_writes_no_values_and_keeps_empty_channels_empty():
    estimates = grid_estimates(10, 10, channels=("b",)) + grid_estimates(2, 1, channels=("g2",), size=(500, 300))
    estimates[-1].sources = estimates[-2].sources = ["/data/IMG_0002.dng"]
    fig = figures.grid_figure(estimates)
    rows = {ax.get_ylabel().split(",")[0] for ax in fig.axes if ax.get_ylabel() and ax.get_label() != "<colorbar>"}
    assert rows == {"IMG_0001.dng", "IMG_0002.dng"}  # a row of panels per photograph
    empty = [ax for ax in fig.axes if ax.get_title() and not ax.get_images() and not ax.collections]
    assert len(empty) == 6  # each photograph's panels of the other's channel
    crowded = [ax for ax in fig.axes if ax.get_title().startswith("channel b: MTF50") and ax.collections]
    assert len(crowded) == 2 and all(not ax.texts for ax in crowded)  # 100 windows: colours only
    (tiles,) = [image for ax in fig.axes for image in ax.get_images() if ax.get_title() == "channel b: PSFs"]
    assert tiles.get_extent() == [99.5, 1099.5, 349.5, 49.5]  # both photographs' windows, on every panel
    alpha = tiles.get_alpha()  # the 400 x 300 pixels of b's windows drawn, nothing beyond them
    width = alpha.shape[1] * 400 // 1000
    assert alpha[:, :width].min() == 1 and alpha[:, width:].max() == 0
    assert max(alpha.shape) <= 1536  # the raster of 1000 x 300 pixels of windows at 6 per kernel sample, bounded


def test_the_colour_bars_clear_the_height_chart_with_one_aperture_or_many():
    """A report of one aperture (`psfd report --aperture 5.6`, one capture) drew the colour bars' two-line labels
    over the height chart's title and mm axis: the bars took their room from a single row of panels."""
    grid = [(x, y) for y in (0.2, 0.5, 0.8) for x in (0.15, 0.5, 0.85)]
    for apertures in ((5.6,), (4.0, 11.0), (4.0, 5.6, 8.0, 11.0)):
        rows, arrays = rows_for(apertures, grid)
        fig = figures.report_figure(rows, arrays, "g1", {r["id"]: figures.Sensor(640, 480, 8.0) for r in rows})
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        bars = [ax.get_tightbbox(renderer) for ax in fig.axes if ax.get_label() == "<colorbar>"]
        chart = next(ax for ax in fig.axes if ax.get_xlabel().startswith("image height"))
        above = [chart.title.get_window_extent(renderer)] + [child.get_tightbbox(renderer) for child in chart.child_axes]
        assert len(bars) == 2 and not any(bar.overlaps(box) for bar in bars for box in above), apertures
        assert inside_figure(fig) == []


def drawn_texts(fig) -> list:
    """Every text a reader sees once the figure is drawn: titles, axis and tick labels (of the ticks drawn),
    the labels of secondary axes and colour bars, legends' entries, figure texts; not empty, not hidden."""
    from matplotlib.text import Text

    fig.canvas.draw()
    texts = [t for t in fig.texts if isinstance(t, Text)]  # the suptitle among them
    for ax in [*fig.axes, *(child for ax in fig.axes for child in ax.child_axes)]:
        texts += [ax.title, ax._left_title, ax._right_title, *ax.texts]
        for axis in (ax.xaxis, ax.yaxis):
            texts.append(axis.label)
            texts += [label for tick in axis._update_ticks() for label in (tick.label1, tick.label2)]
        if ax.get_legend():
            texts += ax.get_legend().get_texts()
    return [t for t in texts if t.get_visible() and t.get_text().strip()]


def overlapping_texts(fig) -> list[tuple[str, str]]:
    """Pairs of drawn texts whose boxes overlap (by more than half a pixel): neither can be read."""
    renderer = fig.canvas.get_renderer()
    boxes = [(t.get_text(), t.get_window_extent(renderer).expanded(1.0, 1.0)) for t in drawn_texts(fig)]
    clash = []
    for i, (a, box_a) in enumerate(boxes):
        for b, box_b in boxes[i + 1:]:
            width = min(box_a.x1, box_b.x1) - max(box_a.x0, box_b.x0)
            height = min(box_a.y1, box_b.y1) - max(box_a.y0, box_b.y0)
            if width > 0.5 and height > 0.5:
                clash.append((a, b))
    return clash


def rig_rows(rigs: list[tuple[str, str, str, str, tuple[float, ...]]], channels=("r", "g1")) -> tuple[list, dict]:
    """Rows of several rigs: (camera, body serial, lens, lens serial, apertures) each, a 3x3 field grid."""
    grid = [(x, y) for y in (0.2, 0.5, 0.8) for x in (0.15, 0.5, 0.85)]
    rows, arrays = [], {}
    for camera, serial, lens, lens_serial, apertures in rigs:
        mine, mine_arrays = rows_for(apertures, grid, channels=channels)
        for row in mine:
            arrays[len(rows) + 1] = mine_arrays[row["id"]]
            rows.append({**row, "id": len(rows) + 1, "camera": camera, "serial": serial, "lens": lens,
                         "lens_serial": lens_serial})
    return rows, arrays


FOUR_RIGS = [("Canon EOS 5D Mark IV", "0123456789", "EF 50mm f/1.8 STM", "A1", (4.0, 8.0)),
             ("Canon EOS 5D Mark IV", "9876543210", "EF 50mm f/1.8 STM", "B2", (5.6, 11.0)),
             ("NIKON D850", "3001234", "AF-S NIKKOR 35mm f/1.8G ED", "", (4.0, 11.0)),
             ("NIKON D850", "3001234", "AF-S NIKKOR 85mm f/1.8G", "", (8.0, 16.0))]


def test_report_of_several_rigs_draws_every_label_clear_of_every_other():
    """Four rigs (two bodies of one model with two copies of one lens, one body with two lenses), two apertures
    each: the rows' labels named the rig in one vertical line longer than the row, drawn over the next rows',
    and each row's tick labels ran over the next row's titles. Every text stands clear of the others and of the
    figure's edges, and each rig is named once, above its rows."""
    rows, arrays = rig_rows(FOUR_RIGS)
    sensors = {r["id"]: figures.Sensor(6000, 4000, 3.9) if r["camera"].startswith("Canon")
               else figures.Sensor(8256, 5504, 4.35) for r in rows}
    fig = figures.report_figure(rows, arrays, "g1", sensors)
    assert overlapping_texts(fig) == []
    assert inside_figure(fig) == []
    headings = [t.get_text() for t in fig.texts if t is not fig._suptitle]
    assert headings == [f"{camera} #{serial}, {lens}" + (f" #{copy}" if copy else "")
                        for camera, serial, lens, copy, _ in sorted(FOUR_RIGS)]


def unnamed_pixels(fig) -> list[str]:
    """Texts that speak of a pixel without saying which: a channel pixel (of one Bayer channel's plane, 2
    photosites across) or a photosite. MTF50 in cycles per channel pixel read as cycles per photosite gives
    lp/mm twice too high."""
    texts = [" ".join(t.get_text().split()) for t in drawn_texts(fig)]  # a line may break after "channel"
    return [text for text in texts if re.search(r"(?<!channel )\b(pixels?|px)\b", text)]


def test_every_unit_of_every_figure_says_which_pixel_it_means():
    """The report's colour bar and height chart said "cycles/pixel" beside axes drawn in photosites; every
    figure names the pixel it counts in, as `psfd query`'s units line does."""
    rows, arrays = rig_rows(FOUR_RIGS[:1])
    report = figures.report_figure(rows, arrays, "g1", {r["id"]: figures.Sensor(6000, 4000, 3.9) for r in rows})
    assert unnamed_pixels(report) == []
    bar = next(ax for ax in report.axes if ax.get_label() == "<colorbar>" and "MTF50" in ax.get_xlabel())
    assert bar.get_xlabel().startswith("MTF50 (cycles per channel pixel)")
    assert "2 photosites across; Nyquist 0.5" in " ".join(report._suptitle.get_text().split())
    est = estimate(gaussian(0.6, 0.9))
    kernel = gaussian(0.5, 0.5)
    for fig in (figures.psf_figure(est, pitch_um=4.0), figures.grid_figure(grid_estimates(2, 2)),
                figures.comparison_figure([("truth", kernel, 4), ("bernoulli", kernel, 4)], against_truth=True),
                figures.array_figure(kernel, "kernel", est), figures.array_figure(kernel, "residual", est)):
        assert unnamed_pixels(fig) == []
