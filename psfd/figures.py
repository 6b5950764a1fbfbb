"""Every picture psfd draws: the PSF figure, array images, the method comparison and the field report.

The commands only decide what to draw and where; the drawing lives here, so
that a figure looks the same whichever command writes it. Figures are drawn
with matplotlib's object interface on the Agg canvas (no pyplot, no GUI, no
global state) and written by their file suffix: PNG for viewing, PDF or SVG
when a vector file is wanted. matplotlib is imported inside the drawing
functions, so that commands which draw nothing never load it.

Units, the same on every figure: spatial frequency in cycles per channel pixel
(the channel plane of one Bayer colour; its Nyquist frequency is 0.5), and in
line pairs per mm on a second axis when the photosite pitch is known
(`psfd.estimator.mtf.lp_per_mm`); PSF values are the fraction of the kernel's
energy in one sample of the s-times grid (a kernel sums to 1); positions on a
kernel in channel pixels from its centre; positions on the sensor in
photosites from its top-left corner, and in mm when the pitch is known.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from psfd.estimator import mtf
from psfd.estimator.kernels import PSF

if TYPE_CHECKING:  # pragma: no cover - types only
    from matplotlib.figure import Figure

__all__ = ["FORMATS", "Sensor", "array_figure", "can_write", "comparison_figure", "grid_figure", "pixel_borders",
           "psf_figure", "report_figure", "PSFFigures", "save", "save_array", "save_comparison", "save_grid",
           "save_psf", "save_report", "write_png"]

# Suffixes matplotlib writes without extra libraries: raster for viewing, vector for papers and print.
FORMATS = ("png", "pdf", "svg", "eps", "jpg", "jpeg", "tif", "tiff", "webp")
DPI = 110
NEGATIVE = "#7fc8e8"  # light blue: not in inferno, so a negative sample can never pass for a small one
LOG_DECADES = 4  # the log views show four decades below the largest value
CHANNEL_ORDER = ("r", "g1", "g2", "b", "mono")
FREQ_UNIT = "cycles per channel pixel"  # a channel pixel: one pixel of a Bayer channel's plane, 2 photosites across
FREQ_LABEL = f"spatial frequency ({FREQ_UNIT})"
VALUE_LABEL = "PSF value (fraction of energy per sample)"


@dataclass(frozen=True)
class Sensor:
    """The sensor a field report is drawn on: its size in photosites and, when known, the photosite pitch."""

    width: int
    height: int
    pitch_um: float | None = None

    @property
    def aspect(self) -> float:
        return self.width / self.height


# ---------------------------------------------------------------- files


def can_write(path: str | Path) -> bool:
    """Whether `save` can write a figure of this file name (by its suffix, `FORMATS`)."""
    return Path(path).suffix.lower().lstrip(".") in FORMATS


def _figure(width: float, height: float, layout: str | None = None) -> Figure:
    """A new figure on the Agg canvas (no pyplot: nothing global, nothing that opens a window).

    ``layout``: None places the axes by the callers' fixed margins (`Figure.subplots_adjust`), which
    draws several times faster than the constrained layout engine measuring every label.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=DPI, layout=layout)
    FigureCanvasAgg(fig)
    return fig


def save(fig: Figure, path: str | Path) -> None:
    """Write a figure; the format follows the suffix (`FORMATS`). OSError when it cannot be written."""
    path = Path(path)
    if not can_write(path):
        raise OSError(f"cannot write a figure named {path.name} (use {', '.join(FORMATS[:3])})")
    fmt = path.suffix.lower().lstrip(".")
    metadata = {"Creator": "psfd"} if fmt in ("png", "pdf", "svg") else None
    # the format is given, not guessed: the staging names of atomic writes end in .partial.png
    fig.savefig(path, format={"jpg": "jpeg", "tif": "tiff"}.get(fmt, fmt), dpi=DPI, metadata=metadata)


def save_psf(est: PSF, path: str | Path, pitch_um: float | None = None) -> None:
    """`psf_figure` of one estimate, written to ``path``."""
    save(psf_figure(est, pitch_um), path)


def save_array(array: np.ndarray, path: str | Path, name: str = "", est: PSF | None = None) -> None:
    """`array_figure` of a 2-D array that came with an estimate, written to ``path``."""
    save(array_figure(array, name, est), path)


def save_comparison(curves: list[tuple[str, np.ndarray, int]], path: str | Path, against_truth: bool = False) -> None:
    """`comparison_figure` of labelled kernels ``(label, psf, s)``, written to ``path``."""
    save(comparison_figure(curves, against_truth), path)


def save_grid(estimates: Sequence[PSF], path: str | Path) -> None:
    """`grid_figure` of the estimates of grids of windows, written to ``path``."""
    save(grid_figure(estimates), path)


def save_report(rows: list[dict], arrays: Mapping[int, np.ndarray], channel: str, path: str | Path,
                sensors: Mapping[int, Sensor | None] | None = None, note: str | None = None) -> None:
    """`report_figure` of catalogue rows, written to ``path``."""
    save(report_figure(rows, arrays, channel, sensors, note), path)


# ---------------------------------------------------------------- kernels


def kernel_extent(shape: tuple[int, int], s: int) -> list[float]:
    """imshow extent (left, right, bottom, top) of a kernel in channel pixels from its centre sample."""
    rows, cols = shape
    cx, cy = cols // 2, rows // 2
    return [(-cx - 0.5) / s, (cols - 1 - cx + 0.5) / s, (rows - 1 - cy + 0.5) / s, (-cy - 0.5) / s]


def pixel_borders(size: int, s: int) -> list[float]:
    """Channel-pixel borders inside a kernel of ``size`` samples, in channel pixels from its centre.

    The centre sample is the centre of a channel pixel, so the borders lie at
    odd multiples of half a pixel from it.
    """
    half = (size / 2) / s
    return [m + 0.5 for m in range(-math.ceil(half) - 1, math.ceil(half) + 1) if abs(m + 0.5) < half - 1e-9]


def _draw_pixel_grid(ax: Any, shape: tuple[int, int], s: int) -> list:
    lines = [ax.axvline(x, color="0.75", lw=0.6, alpha=0.7) for x in pixel_borders(shape[1], s)]
    return lines + [ax.axhline(y, color="0.75", lw=0.6, alpha=0.7) for y in pixel_borders(shape[0], s)]


def _kernel_axes(ax: Any, title: str) -> None:
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("x (channel pixels)")
    ax.set_ylabel("y (channel pixels)")


def _cmap(name: str, under: str | None = None, bad: str | None = None) -> Any:
    import matplotlib

    extremes = {key: colour for key, colour in (("under", under), ("bad", bad)) if colour}
    return matplotlib.colormaps[name].with_extremes(**extremes)


def mtf_noise_band(est: PSF) -> float | None:
    """One standard deviation of the MTF error that the kernel's noise floor implies, or None.

    The floor is the L2 norm of the kernel's noise error (`PSF.noise_floor`);
    for errors independent from sample to sample each OTF value is off by that
    norm (Parseval), so MTF values below this band cannot be told from noise
    (Delbracio et al., IJCV 2012, sec. 3.1, on the noise of the estimate).
    """
    if est.noise_floor is None or not math.isfinite(est.noise_floor):
        return None
    return float(est.noise_floor)


def psf_figure(est: PSF, pitch_um: float | None = None) -> Figure:
    """The figure of one estimate: the kernel in a linear and a log view on the s-times grid with the
    channel-pixel grid drawn, and its horizontal and vertical MTF with the noise floor as a band.

    ``pitch_um``: the photosite pitch, for a second frequency axis in line pairs per mm.
    """
    panels = _PSFPanels(*_psf_layout(est, pitch_um))
    panels.show(est)
    return panels.fig


def _psf_layout(est: PSF, pitch_um: float | None) -> tuple:
    """What a PSF figure's axes, ticks and labels depend on: estimates that agree on it share all but their
    data (`PSFFigures`). The MTF axis grows above 1 only for a kernel with negative lobes."""
    _, mx, my = mtf.profiles(est.psf, est.s)
    # an MTF above 1 (negative lobes) is shown, not clipped; the axis grows in tenths, which most such kernels share
    top = max(1.0, math.ceil(max(float(mx.max()), float(my.max())) * 10.0 - 1e-9) / 10.0)
    lp_mm = mtf.lp_per_mm(1.0, pitch_um, est.channel) if pitch_um else None
    return est.psf.shape, est.s, lp_mm, top, bool((est.psf < 0).any())


class _PSFPanels:
    """One `psf_figure` laid out for a `_psf_layout`, and the artists that show an estimate on it.

    `show` puts an estimate's data into the artists it returns, in the order they are drawn; everything
    else (axes, ticks, labels, the pixel grid's place, the Nyquist line) is the same for every estimate of
    the layout. The z-orders put the artists an estimate changes above the ones it does not, so that
    drawing them over the rest (`PSFFigures`) gives the figure drawn whole.
    """

    def __init__(self, shape: tuple[int, int], s: int, lp_mm: float | None, top: float, negative: bool):
        from matplotlib.colors import LogNorm, Normalize
        from matplotlib.patches import Rectangle

        self.fig = fig = _figure(16.5, 5.6)
        # room at the top for the two lines of the title above the MTF axes' title and lp/mm axis
        fig.subplots_adjust(left=0.05, right=0.985, bottom=0.1, top=0.79, wspace=0.42)
        self.ax_lin, self.ax_log, self.ax_mtf = fig.subplots(1, 3, width_ratios=[1, 1, 1.3])
        extent = kernel_extent(shape, s)
        blank = np.ones(shape)
        self.linear = self.ax_lin.imshow(blank, cmap=_cmap("inferno", under="black"), norm=Normalize(0.0, 1.0),
                                         extent=extent, interpolation="nearest")
        _kernel_axes(self.ax_lin, "linear scale" + (" (negative values drawn as 0)" if negative else ""))
        self.bar_lin = fig.colorbar(self.linear, ax=self.ax_lin, shrink=0.85, extend="min" if negative else "neither")
        self.bar_lin.set_label(VALUE_LABEL)
        self.log = self.ax_log.imshow(blank, cmap=_cmap("inferno", under="black", bad=NEGATIVE),
                                      norm=LogNorm(10.0 ** -LOG_DECADES, 1.0), extent=extent, interpolation="nearest")
        _kernel_axes(self.ax_log, f"log scale, {LOG_DECADES} decades\n(black: below, blue: negative or 0)")
        self.bar_log = fig.colorbar(self.log, ax=self.ax_log, shrink=0.85, extend="min")
        self.bar_log.set_label(VALUE_LABEL + "\nwhite line: noise floor per sample")
        _fix_label(self.bar_log, WIDEST_LOG)
        self.white = self.bar_log.ax.axhline(1.0, color="white", lw=2)
        self.grid = [*_draw_pixel_grid(self.ax_lin, shape, s), *_draw_pixel_grid(self.ax_log, shape, s)]
        # the noise floor band across the whole axes (as axhspan draws it, whose patch type changed in matplotlib 3.9)
        self.band = self.ax_mtf.add_patch(Rectangle((0.0, 0.0), 1.0, 1.0, transform=self.ax_mtf.get_yaxis_transform(),
                                                    color="0.6", alpha=0.35, lw=0, zorder=1.6))
        self.curves = [self.ax_mtf.plot([], [], style, lw=1.8)[0] for style in ("-", "--")]
        self.marks = [self.ax_mtf.plot([], [], "o", color=line.get_color(), ms=5)[0] for line in self.curves]
        self.nyquist = _mtf_axes(self.ax_mtf, s, top, lp_mm)
        self.title = fig.suptitle(" ", fontsize=10)

    def show(self, est: PSF) -> list:
        """Show ``est`` (of this layout) on the figure; the artists that changed, in drawing order."""
        psf, s = est.psf, est.s
        peak = float(psf.max())
        self.linear.set_data(psf)
        self.linear.norm.vmax = peak
        floor = peak * 10.0 ** -LOG_DECADES
        self.log.set_data(np.where(psf > 0, psf, np.nan))
        with self.log.norm.callbacks.blocked():  # its colour bar redrawn once (by vmax), not once per limit
            self.log.norm.vmin = floor
        self.log.norm.vmax = peak
        per_sample = _per_sample(est)
        self.white.set_ydata([per_sample or floor] * 2)
        self.white.set_visible(bool(per_sample and floor < per_sample < peak))
        band = mtf_noise_band(est)
        self.band.set_visible(band is not None)
        self.band.set_height(band or 0.0)
        self.band.set_label(f"noise floor (1 sigma = {band:.3f})" if band is not None else "_band")
        freqs, mx, my = mtf.profiles(psf, s)
        for values, line, mark, name in zip((mx, my), self.curves, self.marks,
                                            ("x (horizontal frequency)", "y (vertical frequency)")):
            value = mtf.mtf50(freqs, values)
            line.set_data(freqs, values)
            line.set_label(f"{name}: MTF50 {_num(value, '.3f')}")
            mark.set_data([value], [0.5])
            mark.set_visible(math.isfinite(value))
        legend = self.ax_mtf.legend(handles=[self.band, *self.curves, self.nyquist][0 if band is not None else 1:],
                                    fontsize=8, loc="upper right")
        m = est.metrics()
        self.title.set_text(
            f"{est.method} PSF, channel {est.channel}, field ({est.field[0]:.2f}, {est.field[1]:.2f}) of "
            f"{', '.join(Path(p).name for p in est.sources) or 'an image'}\n"
            f"s = {s} (grid lines: channel pixels), support {psf.shape[0]} samples = {psf.shape[0] / s:.2f} channel px;  "
            f"FWHM x {_num(m['fwhm_x'], '.2f')} y {_num(m['fwhm_y'], '.2f')} channel px;  "
            f"noise floor {_num(est.relative_noise, '.1%')} of the kernel's L2 norm ({_num(per_sample, '.1e')} per sample)"
        )
        spines = [*self.ax_lin.spines.values(), *self.ax_log.spines.values(), *self.ax_mtf.spines.values()]
        return [self.linear, self.log, *self.grid, self.band, *self.curves, *self.marks, *spines,
                self.bar_lin.ax, self.bar_log.ax, legend, self.title]


# The widest tick label of a log colour bar of a kernel: 10^-k, k from 1 to 9 (a peak below 1e-6 would take a
# unit-sum kernel of a million samples); 10^0 and 10^1 are narrower.
WIDEST_LOG = r"$\mathdefault{10^{-5}}$"


def _fix_label(bar: Any, widest: str) -> None:
    """Put a colour bar's label where matplotlib puts it right of the tick label ``widest``, whatever its labels.

    matplotlib places the label by the tick labels a bar has; at one place it is the same for every estimate,
    and `PSFFigures` draws it once per layout instead of once per estimate.
    """
    from matplotlib.transforms import offset_copy

    axis, fig = bar.ax.yaxis, bar.ax.figure
    tick = axis.get_major_ticks()[0]
    pixels, _, _ = fig.canvas.get_renderer().get_text_width_height_descent(
        widest, tick.label2.get_fontproperties(), ismath=widest.startswith("$"))
    offset = tick.get_tick_padding() + tick.get_pad() + pixels * 72.0 / fig.dpi + axis.labelpad  # points
    axis.set_label_coords(1.0, 0.5, transform=offset_copy(bar.ax.transAxes, bar.ax.figure, x=offset, units="points"))


def _per_sample(est: PSF) -> float | None:
    """The noise floor as the RMS error of one sample: the norm over the k x k samples, over k."""
    return None if est.noise_floor is None else float(est.noise_floor) / math.sqrt(est.psf.size)


def _num(value: float | None, spec: str) -> str:
    return "n/a" if value is None or not math.isfinite(value) else format(value, spec)


def _mtf_axes(ax: Any, s: int, top: float, lp_mm: float | None) -> Any:
    """The MTF axes up to s/2 and ``top``, the 0.5 level and the lp/mm axis (``lp_mm``: lp/mm per cycle per
    pixel); the Nyquist line, returned for the legend."""
    # below the band and the curves (z-order 1.6 and 2), above the grid (1.5): see `_PSFPanels`
    ax.axhline(0.5, color="0.5", lw=0.6, ls=":", zorder=1.55)
    nyquist = ax.axvline(0.5, color="0.3", lw=0.8, ls="-.", label="Nyquist (0.5)", zorder=1.55)
    ax.set_xlim(0, s / 2.0)
    ax.set_ylim(0, 1.05 * top)
    ax.set_xlabel(FREQ_LABEL)
    ax.set_ylabel("MTF")
    ax.set_title("MTF profiles", fontsize=10)
    ax.grid(alpha=0.25)
    if lp_mm:
        top_axis = ax.secondary_xaxis("top", functions=(lambda f: f * lp_mm, lambda f: f / lp_mm))
        top_axis.set_xlabel("line pairs per mm", fontsize=9)
    return nyquist


class PSFFigures:
    """Writes `psf_figure`s of many estimates, drawing for each only what is its own.

    Estimates of one `_psf_layout` (kernel shape, s, pitch, MTF range) share a figure: its axes, ticks
    and labels are drawn once, and each estimate draws its data over a copy of them (Agg blitting, as
    matplotlib's animation does). A whole figure costs 0.3 s of a core, an estimate's part of it 0.09 s
    (bench/bench_figures.py): the ticks of its colour bars, its legend and title (matplotlib renders
    every glyph anew), its images, and 9 ms of PNG (`write_png`). PNG files only; other formats are
    drawn whole (`save_psf`).
    """

    def __init__(self) -> None:
        self._layouts: dict[tuple, tuple[_PSFPanels, Any]] = {}

    def save(self, est: PSF, path: str | Path, pitch_um: float | None = None) -> None:
        """Write the figure of ``est`` to ``path``, as `save_psf` does."""
        path = Path(path)
        if path.suffix.lower() != ".png":
            save_psf(est, path, pitch_um)
            return
        layout = _psf_layout(est, pitch_um)
        if layout not in self._layouts:
            panels = _PSFPanels(*layout)
            for artist in panels.show(est):
                artist.set_animated(True)
            panels.fig.canvas.draw()
            # the log colour bar's label is the same for every estimate (`_fix_label`): into the background
            label = panels.bar_log.ax.yaxis.label
            panels.fig.draw_artist(label)
            label.set_visible(False)
            self._layouts[layout] = panels, panels.fig.canvas.copy_from_bbox(panels.fig.bbox)
        panels, background = self._layouts[layout]
        canvas = panels.fig.canvas
        canvas.restore_region(background)
        for artist in panels.show(est):
            artist.set_animated(True)  # a new legend
            panels.fig.draw_artist(artist)
        write_png(np.asarray(canvas.buffer_rgba())[..., :3], path)


def write_png(rgb: np.ndarray, path: str | Path, level: int = 3) -> None:
    """Write an RGB image (rows x columns x 3, uint8) as a PNG file with the metadata `save` writes.

    The rows are stored unfiltered (PNG filter type 0) and deflated at ``level``: a figure's flat areas
    and antialiased text compress as well so as after the filter that Pillow and libpng choose row by row
    (a PSF figure: 131 kB either way), and that choice was two thirds of their 25 ms; this takes 9 ms.
    """

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    height, width, _ = rgb.shape
    rows = np.concatenate([np.zeros((height, 1), np.uint8), rgb.reshape(height, -1)], axis=1)  # filter byte 0
    per_metre = round(DPI / 0.0254)
    with open(path, "wb") as stream:
        stream.write(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
                     + chunk(b"pHYs", struct.pack(">IIB", per_metre, per_metre, 1))
                     + chunk(b"tEXt", b"Creator\0psfd") + chunk(b"IDAT", zlib.compress(rows.tobytes(), level))
                     + chunk(b"IEND", b""))


# ---------------------------------------------------------------- arrays beside an estimate

# name -> (title, colour bar label, axes on the kernel's s-grid (True) or the channel plane (False))
ARRAYS = {
    "kernel": ("inter-image kernel k (near to far), s-times grid", "value (fraction of energy per sample)", True),
    "residual": ("model residual on the far photograph (0 outside the mask)",
                 "far minus predicted (normalised data units)", False),
}


def array_figure(array: np.ndarray, name: str = "", est: PSF | None = None) -> Figure:
    """A 2-D array with axes and a colour bar: signed arrays on a diverging map centred on 0.

    ``name`` picks the title and units (`ARRAYS`); ``est`` gives the s-grid (kernels) or the window
    origin on the channel plane (images), so the axes are in channel pixels.
    """
    from matplotlib.colors import Normalize

    a = np.asarray(array, dtype=np.float64)
    title, label, on_grid = ARRAYS.get(name, (name or "array", "value", False))
    fig = _figure(6.6, 5.6 * min(2.0, max(0.5, a.shape[0] / a.shape[1])))
    ax = fig.subplots()
    finite = a[np.isfinite(a)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if lo < 0 < hi:
        span = max(-lo, hi)
        cmap, norm = "RdBu_r", Normalize(-span, span)
    else:
        lo = min(lo, 0.0)  # a non-negative array is drawn from 0, so its colours are proportions
        cmap, norm = "inferno", Normalize(lo, hi if hi > lo else lo + 1.0)
    if on_grid and est is not None:
        extent = kernel_extent(a.shape, est.s)
        xlabel, ylabel = "x (channel pixels from the centre)", "y (channel pixels from the centre)"
    else:
        x0, y0 = (est.window[0], est.window[1]) if est is not None else (0, 0)
        extent = [x0 - 0.5, x0 + a.shape[1] - 0.5, y0 + a.shape[0] - 0.5, y0 - 0.5]
        xlabel, ylabel = "x (channel pixels)", "y (channel pixels)"
    image = ax.imshow(a, cmap=cmap, norm=norm, extent=extent, interpolation="nearest")
    if on_grid and est is not None:
        _draw_pixel_grid(ax, a.shape, est.s)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    source = f"\n{', '.join(Path(p).name for p in est.sources)}, channel {est.channel}" if est is not None else ""
    ax.set_title(f"{title}{source}", fontsize=10)
    fig.colorbar(image, ax=ax, shrink=0.85).set_label(label)
    return fig


# ---------------------------------------------------------------- method comparison


def comparison_figure(curves: list[tuple[str, np.ndarray, int]], against_truth: bool = False) -> Figure:
    """Overlaid MTF profiles of labelled kernels ``(label, psf, s)``: x solid, y dashed, one colour per kernel.

    A kernel labelled ``truth`` is drawn in black. The vertical axis reaches the largest value drawn,
    so an MTF above 1 (negative kernel lobes) is never clipped.
    """
    from matplotlib.lines import Line2D

    fig = _figure(11.5, 5.6)
    ax = fig.subplots()
    handles, top, fmax = [], 1.0, 0.5
    colours = iter(f"C{i}" for i in range(1000))
    for label, psf, s in curves:
        colour = "black" if label == "truth" else next(colours)
        freqs, mx, my = mtf.profiles(psf, s)
        ax.plot(freqs, mx, "-", color=colour, lw=1.8 if label == "truth" else 1.4)
        ax.plot(freqs, my, "--", color=colour, lw=1.8 if label == "truth" else 1.4)
        handles.append(Line2D([], [], color=colour, lw=2.5, label=label if len(label) <= 48 else label[:47] + "~"))
        top = max(top, float(mx.max()), float(my.max()))
        fmax = max(fmax, float(freqs[-1]))
    ax.axvline(0.5, color="0.3", lw=0.8, ls="-.")
    ax.axhline(0.5, color="0.5", lw=0.6, ls=":")
    ax.text(0.5, 1.0, " Nyquist", transform=ax.get_xaxis_transform(), va="top", fontsize=8, color="0.3")
    ax.set_xlim(0, fmax)
    ax.set_ylim(0, 1.05 * top)
    if top > 1.0:
        ax.axhline(1.0, color="0.5", lw=0.6)
        ax.text(0.5, 1.0, " MTF above 1: negative kernel lobes", ha="left", va="bottom", fontsize=8, color="0.3")
    ax.set_xlabel(FREQ_LABEL)
    ax.set_ylabel("MTF")
    ax.grid(alpha=0.25)
    ax.set_title("MTF of each estimate" + (" and of the true PSF" if against_truth else ""), fontsize=11)
    styles = [Line2D([], [], color="0.2", ls="-", label="solid: x (horizontal frequency)"),
              Line2D([], [], color="0.2", ls="--", label="dashed: y (vertical frequency)")]
    # inside, top right: every MTF has fallen there, and nothing of the legend falls off the figure
    ax.legend(handles=handles + styles, loc="upper right", fontsize=8, framealpha=0.9)
    return fig


# ---------------------------------------------------------------- grid of windows

ANNOTATED = 36  # windows per panel up to which each window's MTF50 is written in it


def _mosaic(estimates: Sequence[PSF], box: tuple[int, int, int, int], samples: int = 6,
            largest: int = 1536) -> np.ndarray:
    """The kernels of ``estimates`` each enlarged to fill its window (nearest sample), on one float32 raster of
    the channel plane's ``box`` (x0, y0, x1, y1): about ``samples`` raster pixels per kernel sample, at most
    ``largest`` per side (several times a panel's pixels: the memory of a 32 x 32 grid on a whole frame
    stays a few MB); NaN outside every window."""
    x0, y0, x1, y1 = box
    scale = max(samples * e.psf.shape[1] / (e.window[2] - e.window[0]) for e in estimates)
    scale = min(scale, largest / max(x1 - x0, y1 - y0))  # raster pixels per channel pixel
    out = np.full((max(1, round((y1 - y0) * scale)), max(1, round((x1 - x0) * scale))), np.nan, dtype=np.float32)
    sy, sx = out.shape[0] / (y1 - y0), out.shape[1] / (x1 - x0)
    for est in estimates:
        a, b, c, d = est.window
        # the raster pixels whose centres fall in the window, and the kernel sample under each centre
        r = np.arange(math.ceil((b - y0) * sy - 0.5), math.ceil((d - y0) * sy - 0.5))
        q = np.arange(math.ceil((a - x0) * sx - 0.5), math.ceil((c - x0) * sx - 0.5))
        if r.size and q.size:
            rows, cols = est.psf.shape
            i = np.minimum(((r + 0.5) / sy + y0 - b) / (d - b) * rows, rows - 1).astype(int)
            j = np.minimum(((q + 0.5) / sx + x0 - a) / (c - a) * cols, cols - 1).astype(int)
            out[r[0]:r[-1] + 1, q[0]:q[-1] + 1] = est.psf[np.ix_(i, j)]
    return out


def grid_figure(estimates: Sequence[PSF]) -> Figure:
    """The PSFs of grids of windows where they were measured, and their MTF50 along x and y.

    One column per channel and, per photograph (or pair) and method, three rows of panels on the channel
    plane, in channel pixels: each kernel drawn over its own window (enlarged to fill it; one log colour
    scale for every tile), then the MTF50 of each window along x and along y (one colour scale for both
    rows and every channel; the value written in each window when a panel has `ANNOTATED` or fewer).
    The field dependence of the PSF at a glance, which a figure per window hides.
    """
    from matplotlib.colors import LogNorm, Normalize

    groups: dict[tuple, list[PSF]] = {}
    for est in estimates:
        groups.setdefault((tuple(est.sources), est.method), []).append(est)
    channels = [c for c in CHANNEL_ORDER if any(e.channel == c for e in estimates)]
    mtf50 = {id(e): (m["mtf50_x"], m["mtf50_y"]) for e in estimates for m in [e.metrics()]}
    values = [v for pair in mtf50.values() for v in pair if math.isfinite(v)]
    vmin, vmax = (min(values), max(values)) if values else (0.0, 0.5)
    if vmax - vmin < 1e-3:
        vmin, vmax = vmin - 0.01, vmax + 0.01
    mtf_norm = Normalize(vmin, vmax)
    peak = max(float(e.psf.max()) for e in estimates)
    psf_norm = LogNorm(peak * 10.0 ** -LOG_DECADES, peak)
    box = (min(e.window[0] for e in estimates), min(e.window[1] for e in estimates),
           max(e.window[2] for e in estimates), max(e.window[3] for e in estimates))
    fig, axes = _grid_panels(3 * len(groups), len(channels), box)
    for g, ((sources, method), group) in enumerate(groups.items()):
        name = ", ".join(Path(p).name for p in sources) or "an image"
        for j, channel in enumerate(channels):
            for k, what in enumerate(("PSFs", "MTF50 x", "MTF50 y")):
                axes[3 * g + k, j].set_title(f"channel {channel}: {what}", fontsize=9)
            mine = [e for e in group if e.channel == channel]
            if mine:  # a channel measured on another photograph only: its panels stay empty here
                tiles = _psf_tiles(axes[3 * g, j], mine, box, psf_norm)
                cells = _mtf_cells(axes[3 * g + 1, j], mine, [mtf50[id(e)][0] for e in mine], mtf_norm)
                _mtf_cells(axes[3 * g + 2, j], mine, [mtf50[id(e)][1] for e in mine], mtf_norm)
        for k in range(3):
            axes[3 * g + k, 0].set_ylabel(f"{name}, {method}\ny (channel pixels)", fontsize=8)
    # the colour bars beside the first photograph's rows: the PSF tiles', and the MTF50 cells' across both rows
    bar = fig.colorbar(tiles, cax=_beside(fig, axes[0, -1], axes[0, -1]), extend="min")
    bar.set_label("PSF value (fraction of energy\nper sample), log scale", fontsize=7)
    bar = fig.colorbar(cells, cax=_beside(fig, axes[1, -1], axes[2, -1]))
    bar.set_label("MTF50 (cycles per channel pixel):\none scale for x, y and every channel", fontsize=7)
    import textwrap

    grids = sorted({"x".join(str(n) for n in e.params["grid"]) for e in estimates if e.params.get("grid")})
    title = (f"PSFs and MTF50 over {' and '.join(grids) or 'a'} grid{'s' if len(grids) > 1 else ''} of windows, "
             "each kernel drawn over its window (enlarged to fill it)")
    fig.suptitle("\n".join(textwrap.wrap(title, int(fig.get_figwidth() * 12))), fontsize=10)  # 10-point characters
    return fig


def _grid_panels(rows: int, cols: int, box: tuple[int, int, int, int]) -> tuple[Figure, np.ndarray]:
    """A figure of rows x cols axes on the channel plane's ``box`` (x0, y0, x1, y1), true aspect ratio, with
    fixed margins in inches (a layout engine measures every tick label: several times the drawing)."""
    x0, y0, x1, y1 = (v - 0.5 for v in box)  # pixel edges
    panel_w = 3.0
    panel_h = panel_w * min(4.0, max(0.25, (y1 - y0) / (x1 - x0)))
    gap_w, gap_h, left, right, top, bottom = 0.55, 0.75, 0.85, 1.6, 1.0, 0.55  # inches; top: a title of two lines
    width = left + cols * panel_w + (cols - 1) * gap_w + right
    height = top + rows * panel_h + (rows - 1) * gap_h + bottom
    fig = _figure(width, height)
    grid = fig.add_gridspec(rows, cols, left=left / width, right=1 - right / width, top=1 - top / height,
                            bottom=bottom / height, wspace=gap_w / panel_w, hspace=gap_h / panel_h)
    axes = np.array([[fig.add_subplot(grid[i, j]) for j in range(cols)] for i in range(rows)])
    for ax in axes.flat:
        ax.set_xlim(x0, x1)
        ax.set_ylim(y1, y0)
        ax.set_aspect("equal")
        ax.set_facecolor("0.93")
        ax.tick_params(labelsize=7)
        ax.set_xlabel("x (channel pixels)", fontsize=8)
    return fig, axes


def _beside(fig: Figure, upper: Any, lower: Any) -> Any:
    """Axes for a colour bar right of ``upper`` .. ``lower`` (axes of one column), as tall as they span."""
    top, bottom = upper.get_position(), lower.get_position()
    inch = 1.0 / fig.get_figwidth()
    return fig.add_axes((top.x1 + 0.25 * inch, bottom.y0, 0.15 * inch, top.y1 - bottom.y0), label="<colorbar>")


def _windows(estimates: Sequence[PSF], **style: Any) -> Any:
    """The windows of ``estimates`` as one collection of rectangles (pixel edges)."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    boxes = [Rectangle((a - 0.5, b - 0.5), c - a, d - b) for a, b, c, d in (e.window for e in estimates)]
    return PatchCollection(boxes, edgecolor="0.45", lw=0.5, **style)


def _psf_tiles(ax: Any, estimates: Sequence[PSF], box: tuple[int, int, int, int], norm: Any) -> Any:
    """Each kernel over its window on ``ax``, as one image (hundreds of images draw 100x slower)."""
    x0, y0, x1, y1 = box
    mosaic = _mosaic(estimates, box)
    # samples <= 0 in the bad colour (as on the PSF figure's log view); outside the windows, nothing
    image = ax.imshow(np.where(mosaic > 0, mosaic, np.nan), cmap=_cmap("inferno", under="black", bad=NEGATIVE),
                      norm=norm, extent=[x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5], alpha=np.isfinite(mosaic) * 1.0,
                      zorder=2)
    ax.add_collection(_windows(estimates, facecolor="none", zorder=2.5))
    return image


def _mtf_cells(ax: Any, estimates: Sequence[PSF], values: list[float], norm: Any) -> Any:
    """Each window on ``ax`` coloured by its value, written in it when there are `ANNOTATED` or fewer."""
    cells = _windows(estimates, cmap=_cmap("viridis", bad="0.8"), norm=norm, zorder=2)
    cells.set_array(np.array(values, dtype=float))
    ax.add_collection(cells)
    if len(estimates) <= ANNOTATED:
        for est, value in zip(estimates, values):
            a, b, c, d = est.window
            dark = math.isfinite(value) and norm(value) < 0.5
            ax.text((a + c) / 2 - 0.5, (b + d) / 2 - 0.5, _num(value, ".3f"), ha="center", va="center",
                    fontsize=6.5, zorder=3, color="white" if dark else "black")
    return cells


# ---------------------------------------------------------------- field report

TILE = 0.1  # side of one PSF tile, as a fraction of the sensor width: the same for every tile and figure


def sagittal_meridional(psf: np.ndarray, s: int, field: tuple[float, float], aspect: float) -> tuple[float, float]:
    """MTF50 (cycles per channel pixel) across and along the radius through a field point.

    Meridional: frequencies along the radius from the image centre (the MTF of lines tangent to a
    circle around the centre); sagittal: frequencies across it (lines along the radius). At the
    centre, where there is no radius, x is taken as the radius.
    """
    dx, dy = (field[0] - 0.5) * aspect, field[1] - 0.5
    angle = math.atan2(dy, dx) if math.hypot(dx, dy) > 1e-6 else 0.0
    freqs = np.linspace(0.0, s / 2.0, 257)
    meridional = mtf.mtf50(freqs, mtf.directional_profile(psf, s, angle, freqs))
    sagittal = mtf.mtf50(freqs, mtf.directional_profile(psf, s, angle + math.pi / 2, freqs))
    return sagittal, meridional


def _group_rows(rows: list[dict]) -> dict[tuple, list[dict]]:
    """Rows by (camera, lens, method, aperture). The camera names its body's serial and the lens its copy's: two
    bodies, or two copies of one lens, are two rows of the report, never tiles drawn over each other or MTF50
    interpolated between them."""
    def named(row: dict, name: str, serial: str) -> str:
        text = row.get(name) or ""
        return f"{text} #{row[serial]}" if row.get(serial) else text

    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        key = (named(row, "camera", "serial"), named(row, "lens", "lens_serial"), row["method"],
               row.get("aperture") or 0.0)
        groups.setdefault(key, []).append(row)
    return dict(sorted(groups.items()))


def _sensor_of(rows: list[dict], sensors: Mapping[int, Sensor | None]) -> Sensor:
    """The sensor of a group of rows: the first known one, else inferred from the windows (channel planes)."""
    known = [sensors[r["id"]] for r in rows if sensors.get(r["id"]) is not None]
    pitch = next((k.pitch_um for k in known if k.pitch_um), None)
    sized = [k for k in known if k.width > 0 and k.height > 0]
    if sized:
        return Sensor(sized[0].width, sized[0].height, sized[0].pitch_um or pitch)
    widths, heights = [], []
    for row in rows:  # the window centre is at field x plane size: plane size = centre / field
        x0, y0, x1, y1 = row["window"]
        factor = 1 if row["channel"] == "mono" else 2  # a Bayer plane has half the photosites
        if row["field_x"] > 0.1:
            widths.append(factor * (x0 + x1) / 2 / row["field_x"])
        if row["field_y"] > 0.1:
            heights.append(factor * (y0 + y1) / 2 / row["field_y"])
    if widths and heights:
        return Sensor(int(round(float(np.median(widths)))), int(round(float(np.median(heights)))), pitch)
    return Sensor(3000, 2000, pitch)  # nothing to go by: a 3:2 frame


def _field_points(rows: list[dict], arrays: Mapping[int, np.ndarray], sensor: Sensor) -> list[dict]:
    """One point per measured field location (repeats averaged): photosite position, radius, S and M MTF50."""
    points: dict[tuple, list] = {}
    for row in rows:
        key = (round(row["field_x"], 4), round(row["field_y"], 4))
        sag, mer = sagittal_meridional(arrays[row["id"]], row["s"], (row["field_x"], row["field_y"]), sensor.aspect)
        points.setdefault(key, []).append((sag, mer))
    out = []
    for (fx, fy), values in points.items():
        sag = np.nanmean([v[0] for v in values]) if any(math.isfinite(v[0]) for v in values) else math.nan
        mer = np.nanmean([v[1] for v in values]) if any(math.isfinite(v[1]) for v in values) else math.nan
        x, y = fx * sensor.width, fy * sensor.height
        radius = math.hypot(x - sensor.width / 2, y - sensor.height / 2)
        out.append({"x": x, "y": y, "radius": radius, "sagittal": float(sag), "meridional": float(mer)})
    return out


def _sensor_axes(ax: Any, sensor: Sensor, title: str, *, show_x: bool, show_y: bool, mm_x: bool = False,
                 mm_y: bool = False) -> None:
    """Axes on the whole sensor, true aspect ratio, photosites from the top-left (labelled where ``show_x``,
    ``show_y``); a mm scale on top (``mm_x``) or at the right (``mm_y``) when the pitch is known."""
    ax.set_xlim(0, sensor.width)
    ax.set_ylim(sensor.height, 0)
    ax.set_aspect("equal")
    ax.set_facecolor("0.93")
    ax.set_title(title, fontsize=9)
    ax.plot([sensor.width / 2], [sensor.height / 2], "+", color="0.4", ms=8, mew=0.8, zorder=5)  # the image centre, above tiles
    ax.tick_params(labelsize=7)
    if show_x:
        ax.set_xlabel("x (photosites)", fontsize=8)
    if show_y:
        ax.set_ylabel("y (photosites)", fontsize=8)
    if sensor.pitch_um:
        mm = sensor.pitch_um / 1000.0
        if mm_x:
            top = ax.secondary_xaxis("top", functions=(lambda v: v * mm, lambda v: v / mm))
            top.set_xlabel("x (mm)", fontsize=7)
            top.tick_params(labelsize=6)
        if mm_y:
            side = ax.secondary_yaxis("right", functions=(lambda v: v * mm, lambda v: v / mm))
            side.set_ylabel("y (mm)", fontsize=7)
            side.tick_params(labelsize=6)


# The field report's fixed layout, in inches (a layout engine would measure every label: several times the
# drawing). Above a row of panels: its titles, the mm axis on a rig's first row, and the rig's name when the
# report holds several; below it: its tick labels, and the x label on a rig's last row.
PANEL = 2.5  # width of a sensor panel; its height follows the sensor's aspect ratio
COLUMN_GAP = 0.6  # the next panel's y tick labels
LEFT, RIGHT = 0.95, 0.75  # a row's two-line y label; the mm and lp/mm axes at the right
ROOM = {"heading": 0.3, "mm": 0.4, "title": 0.3, "ticks": 0.27, "xlabel": 0.2, "between": 0.08,
        "bars": 0.3, "bar": 0.15, "bar_labels": 0.75, "chart": 2.8, "chart_labels": 0.55, "legend_line": 0.19}


def _rig_name(camera: str, lens: str) -> str:
    """How the report names a rig: the camera body and the lens copy (their serials when known)."""
    return ", ".join(part for part in (camera, lens) if part) or "unknown camera and lens"


def _common_pitch(bands: list) -> float | None:
    """The photosite pitch of every row of the report, or None when it is unknown or differs between rigs
    (then no mm or lp/mm axis fits every row of a chart drawn over all of them)."""
    pitches = {sensor.pitch_um for _, _, sensor, _ in bands}
    return pitches.pop() if len(pitches) == 1 else None


def report_figure(rows: list[dict], arrays: Mapping[int, np.ndarray], channel: str,
                  sensors: Mapping[int, Sensor | None] | None = None, note: str | None = None) -> Figure:
    """The field report: one row of panels per (camera, lens, method, aperture), and MTF50 against image height.

    Each row shows the PSFs of every channel at their measured field positions on the whole sensor
    (true aspect ratio, photosites and mm), one tile per PSF, all tiles the same size and on one log
    colour scale; then the sagittal and meridional MTF50 of ``channel`` at each measured field point:
    markers, coloured on one scale for every aperture, with linear interpolation drawn only inside
    the measured points' hull (no extrapolation). The rows of one rig (camera body and lens copy) follow
    each other under its name. The last panel plots MTF50 against image height.

    Parameters
    ----------
    rows : list of dict
        Catalogue rows (`psfd.catalogue.Catalogue.query`), any channels.
    arrays : mapping
        PSF arrays by row id.
    channel : str
        The channel whose MTF50 is mapped and charted.
    sensors : mapping, optional
        `Sensor` of each row id (None or absent: inferred from the windows, no pitch).
    note : str, optional
        What the reader must know of the rows (a run not done, an aperture replaced), under the title.
    """
    from matplotlib import patheffects, tri
    from matplotlib.colors import LogNorm, Normalize
    from matplotlib.ticker import MaxNLocator

    sensors = sensors or {}
    groups = _group_rows(rows)
    channels = [c for c in CHANNEL_ORDER if any(r["channel"] == c for r in rows)]
    if channel not in channels:
        channel = channels[0]
    bands = []
    for key, group in groups.items():
        sensor = _sensor_of(group, sensors)
        points = _field_points([r for r in group if r["channel"] == channel], arrays, sensor)
        bands.append((key, group, sensor, points))
    values = [p[k] for *_, points in bands for p in points for k in ("sagittal", "meridional") if math.isfinite(p[k])]
    vmin, vmax = (min(values), max(values)) if values else (0.0, 0.5)
    if vmax - vmin < 1e-3:
        vmin, vmax = vmin - 0.01, vmax + 0.01
    mtf_norm = Normalize(vmin, vmax)
    peak = max(float(arrays[r["id"]].max()) for r in rows)
    psf_norm = LogNorm(peak * 10.0 ** -LOG_DECADES, peak)
    psf_cmap = _cmap("inferno", under="black", bad=NEGATIVE)
    halo = patheffects.withStroke(linewidth=2, foreground="white")  # values stay readable on dark colours

    rigs = sorted({(camera, lens) for camera, lens, *_ in groups})
    layout = _ReportLayout(bands, len(channels) + 2, _report_title(rows, channels, channel, rigs, note))
    fig = layout.fig
    psf_image, mtf_markers = None, None
    for i, ((camera, lens, method, aperture), group, sensor, points) in enumerate(bands):
        place = layout.rows[i]
        name = f"f/{aperture:g}" if aperture else "f/?"
        if place["heading"]:
            fig.text(layout.left, place["heading_y"], _rig_name(camera, lens), fontsize=10, fontweight="bold",
                     ha="left", va="top")
        tile = TILE * sensor.width
        for j, ch in enumerate(channels):
            ax = layout.panel(i, j)
            _sensor_axes(ax, sensor, f"{name}  channel {ch}: PSFs", show_x=place["xlabel"], show_y=j == 0,
                         mm_x=place["mm"])
            if j == 0:
                ax.set_ylabel(f"{name} {method}\ny (photosites)", fontsize=8)
            for row in (r for r in group if r["channel"] == ch):
                x, y = row["field_x"] * sensor.width, row["field_y"] * sensor.height
                array = arrays[row["id"]]
                extent = [x - tile / 2, x + tile / 2, y + tile / 2, y - tile / 2]
                psf_image = ax.imshow(np.where(array > 0, array, np.nan), cmap=psf_cmap, norm=psf_norm,
                                      extent=extent, interpolation="nearest", zorder=2)
                ax.add_patch(_rectangle(extent))
            ax.set_xlim(0, sensor.width)
            ax.set_ylim(sensor.height, 0)
        for j, kind in enumerate(("sagittal", "meridional")):
            ax = layout.panel(i, len(channels) + j)
            _sensor_axes(ax, sensor, f"{name}  {channel}: MTF50 {kind}", show_x=place["xlabel"], show_y=False,
                         mm_x=place["mm"], mm_y=j == 1)
            good = [p for p in points if math.isfinite(p[kind])]
            xs, ys, vs = (np.array([p[k] for p in good]) for k in ("x", "y", kind))
            if len(good) >= 3:
                try:  # Delaunay triangles span the hull of the measured points only: nothing is extrapolated
                    mesh = tri.Triangulation(xs, ys)
                    ax.tripcolor(mesh, vs, cmap="viridis", norm=mtf_norm, shading="gouraud", zorder=1)
                except (ValueError, RuntimeError):
                    pass  # collinear points: no area to interpolate over, the markers say it all
            mtf_markers = ax.scatter(xs, ys, c=vs, cmap="viridis", norm=mtf_norm, s=70, edgecolors="black",
                                     linewidths=0.6, zorder=3)
            for p in good:
                ax.annotate(f"{p[kind]:.3f}", (p["x"], p["y"]), textcoords="offset points", xytext=(0, 7),
                            ha="center", fontsize=6.5, zorder=4, path_effects=[halo])

    if psf_image is not None:
        many = len(channels) > 2
        bar = fig.colorbar(psf_image, cax=layout.bar(0, len(channels), 0.6 if many else 0.95), orientation="horizontal",
                           extend="min")
        bar.set_label(f"PSF value (fraction of energy per sample),\nlog scale, {LOG_DECADES} decades, the same for "
                      "every tile", fontsize=8)
    if mtf_markers is not None:
        bar = fig.colorbar(mtf_markers, cax=layout.bar(len(channels), len(channels) + 2, 0.9), orientation="horizontal")
        bar.locator = MaxNLocator(6)
        bar.update_ticks()
        bar.set_label(f"MTF50 ({FREQ_UNIT}): one scale,\n{vmin:.3f} to {vmax:.3f}, for all apertures", fontsize=8)
    handles = _height_chart(layout.chart, bands, channel)
    layout.chart.legend(handles=handles, fontsize=7, ncols=2, loc="upper center", bbox_to_anchor=layout.legend_at,
                        bbox_transform=fig.transFigure)
    return fig


def _report_title(rows: list[dict], channels: list[str], channel: str, rigs: list[tuple[str, str]],
                  note: str | None) -> str:
    """The report's title, what each panel shows and in which unit, and the note; unwrapped."""
    tile_px = {r["support"] / r["s"] for r in rows}
    pixel = ("a channel pixel, of one Bayer channel's plane, is 2 photosites across" if
             set(channels) - {"mono"} else "a channel pixel of the mono plane is one photosite")
    about = (f"Each tile shows a whole kernel ({', '.join(f'{t:g}' for t in sorted(tile_px))} channel pixels) "
             f"enlarged to {TILE:.0%} of the sensor width at its measured position; + marks the image centre; "
             "meridional: frequencies along the radius, sagittal: across it. "
             f"MTF50 in {FREQ_UNIT} ({pixel}; Nyquist 0.5); positions on the sensor in photosites.")
    if len(rigs) == 1:
        about = f"{_rig_name(*rigs[0])}. {about}"
    head = f"Field report: PSFs of {', '.join(channels)} and MTF50 of {channel} over the sensor, per aperture"
    return "\n".join([head, about] + ([f"Note: {note}."] if note else []))


class _ReportLayout:
    """The field report's figure and where each of its parts goes (fixed margins in inches, `ROOM`)."""

    def __init__(self, bands: list, ncols: int, title: str):
        import textwrap

        self.ncols = ncols
        width = LEFT + ncols * PANEL + (ncols - 1) * COLUMN_GAP + RIGHT
        chars = int(width * 13)  # characters of 9-point text across the figure
        lines = [line for part in title.split("\n") for line in textwrap.wrap(part, chars)]
        several = len({key[:2] for key, *_ in bands}) > 1
        y = 0.15 + 0.16 * len(lines) + 0.1  # inches from the top
        self.rows = []
        for i, (key, _, sensor, _) in enumerate(bands):
            first = i == 0 or bands[i - 1][0][:2] != key[:2]
            last = i == len(bands) - 1 or bands[i + 1][0][:2] != key[:2]
            place = {"heading": several and first, "mm": first and bool(sensor.pitch_um), "xlabel": last,
                     "heading_y": y}
            y += ROOM["heading"] * place["heading"] + ROOM["mm"] * place["mm"] + ROOM["title"]
            place["top"], place["height"] = y, PANEL / sensor.aspect
            y += place["height"] + ROOM["ticks"] + ROOM["xlabel"] * last + ROOM["between"]
            self.rows.append(place)
        self.bar_top = y + ROOM["bars"]
        y = self.bar_top + ROOM["bar"] + ROOM["bar_labels"] + ROOM["title"] + ROOM["mm"] * bool(_common_pitch(bands))
        chart_top = y
        y += ROOM["chart"] + ROOM["chart_labels"]
        legend_top = y
        y += ROOM["legend_line"] * math.ceil((len(bands) + 2) / 2) + 0.25
        self.width, self.height = width, y
        for place in self.rows:  # the rig's name: its top at the top of the room left for it
            place["heading_y"] = 1 - place["heading_y"] / y
        self.fig = _figure(width, y)
        self.fig.suptitle("\n".join(lines), fontsize=9, y=1 - 0.15 / y, va="top")
        self.left = LEFT / width
        span = ncols * PANEL + (ncols - 1) * COLUMN_GAP
        self.chart = self.fig.add_axes(self._rect(LEFT, chart_top, span, ROOM["chart"]))
        self.legend_at = ((LEFT + span / 2) / width, 1 - legend_top / y)

    def _rect(self, left: float, top: float, width: float, height: float) -> tuple[float, float, float, float]:
        """Figure coordinates of a box given in inches from the figure's top-left corner."""
        return (left / self.width, 1 - (top + height) / self.height, width / self.width, height / self.height)

    def _column(self, j: int) -> float:
        return LEFT + j * (PANEL + COLUMN_GAP)

    def panel(self, i: int, j: int) -> Any:
        """New axes for the panel of row ``i``, column ``j``, as wide as `PANEL` and as tall as its sensor's aspect."""
        place = self.rows[i]
        return self.fig.add_axes(self._rect(self._column(j), place["top"], PANEL, place["height"]))

    def bar(self, first: int, end: int, share: float) -> Any:
        """Axes for a horizontal colour bar under columns ``first`` to ``end`` (excluded), ``share`` of their
        span wide, centred."""
        span = self._column(end - 1) + PANEL - self._column(first)
        left = self._column(first) + span * (1 - share) / 2
        return self.fig.add_axes(self._rect(left, self.bar_top, span * share, ROOM["bar"]), label="<colorbar>")


def _rectangle(extent: Sequence[float]) -> Any:
    from matplotlib.patches import Rectangle

    left, right, bottom, top = extent
    return Rectangle((left, top), right - left, bottom - top, fill=False, edgecolor="0.45", lw=0.5, zorder=2.5)


def _height_chart(ax: Any, bands: list, channel: str) -> list:
    """MTF50 against image height (distance from the centre), one colour per row of the report,
    sagittal solid with circles, meridional dashed with squares, a line through the mean at each height;
    its legend's handles. mm and lp/mm axes only when every row has the same known pitch."""
    from matplotlib.lines import Line2D

    pitch = _common_pitch(bands)
    several = len({band[0][:2] for band in bands}) > 1
    handles = []
    for i, ((camera, lens, method, aperture), _, sensor, points) in enumerate(bands):
        colour = f"C{i % 10}"
        for kind, style, marker in (("sagittal", "-", "o"), ("meridional", "--", "s")):
            good = sorted((p["radius"], p[kind]) for p in points if math.isfinite(p[kind]))
            if not good:
                continue
            radius, value = np.array(good).T
            ax.plot(radius, value, marker, color=colour, ms=4, alpha=0.7, mfc="none" if kind == "meridional" else colour)
            # heights within 2 % of the half diagonal are one height (a 4:3 grid's edge midpoints differ a little)
            step = 0.02 * math.hypot(sensor.width, sensor.height) / 2
            bins = np.round(radius / step)
            heights = [radius[bins == b].mean() for b in np.unique(bins)]
            means = [value[bins == b].mean() for b in np.unique(bins)]
            ax.plot(heights, means, style, color=colour, lw=1.3)
        label = f"f/{aperture:g}" if aperture else "f/?"
        rig = f", {_rig_name(camera, lens)}" if several else ""
        handles.append(Line2D([], [], color=colour, lw=2, label=f"{label} {method}{rig}"))
    handles += [Line2D([], [], color="0.2", ls="-", marker="o", label="sagittal"),
                Line2D([], [], color="0.2", ls="--", marker="s", mfc="none", label="meridional")]
    ax.set_xlabel("image height: distance from the image centre (photosites)")
    corner = max(math.hypot(sensor.width, sensor.height) / 2 for _, _, sensor, _ in bands)
    ax.set_xlim(-0.02 * corner, 1.02 * corner)  # from the centre to the corner
    ax.set_ylabel(f"MTF50 of {channel}\n({FREQ_UNIT})", fontsize=8)
    ax.grid(alpha=0.25)
    ax.set_title(f"MTF50 of {channel} against image height (lines through the mean at each measured height)",
                 fontsize=9)
    if pitch:
        mm = pitch / 1000.0
        ax.secondary_xaxis("top", functions=(lambda v: v * mm, lambda v: v / mm)).set_xlabel("mm", fontsize=8)
        scale = mtf.lp_per_mm(1.0, pitch, channel)
        ax.secondary_yaxis("right", functions=(lambda v: v * scale, lambda v: v / scale)).set_ylabel(
            "line pairs per mm", fontsize=8)
    return handles
