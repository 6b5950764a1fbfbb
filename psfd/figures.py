"""Every picture psfd draws: the PSF figure, array images, the method comparison and the field report.

The commands only decide what to draw and where; the drawing lives here, so
that a figure looks the same whichever command writes it. Pictures are BGR
uint8 arrays drawn with OpenCV and written by `save` (PNG, JPEG or TIFF by the
file's suffix). MTF profiles come from `psfd.estimator.mtf`, in cycles per
channel pixel (Nyquist 0.5).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np

from psfd.estimator import mtf
from psfd.estimator.kernels import PSF

__all__ = ["array_image", "can_write", "comparison_figure", "psf_figure", "report_figure", "save", "save_array",
           "save_comparison", "save_psf", "save_report"]


def can_write(path: str | Path) -> bool:
    """Whether `save` can write an image of this file name (by its suffix)."""
    return bool(cv2.haveImageWriter(str(path)))


def save(image: np.ndarray, path: str | Path) -> None:
    """Write a picture; the format follows the suffix. OSError when it cannot be encoded or written."""
    if not cv2.imwrite(str(path), image):
        raise OSError(f"cannot write {Path(path).name}")


def save_psf(est: PSF, path: str | Path) -> None:
    """`psf_figure` of one estimate, written to ``path``."""
    save(psf_figure(est), path)


def save_array(array: np.ndarray, path: str | Path) -> None:
    """`array_image` of a 2-D array, written to ``path``."""
    save(array_image(array), path)


def save_comparison(curves: list[tuple[str, np.ndarray, int]], path: str | Path) -> None:
    """`comparison_figure` of labelled kernels ``(label, psf, s)``, written to ``path``."""
    save(comparison_figure(curves), path)


def save_report(rows: list[dict], arrays: Mapping[int, np.ndarray], channel: str, path: str | Path) -> None:
    """`report_figure` of catalogue rows, written to ``path``."""
    save(report_figure(rows, arrays, channel), path)


# ---------------------------------------------------------------- one estimate

PSF_PANEL = 360  # target side of the enlarged PSF panel, pixels
PAD = 12
TITLE = 34  # height of the title band
PLOT_W, PLOT_H = 520, 360
AXES = (56, 16, 24, 44)  # left, top, right, bottom margins of the MTF axes inside the plot
GRID_COLOUR = (0, 200, 0)  # BGR; not in the inferno colour map, so the grid is always visible
X_COLOUR = (200, 90, 0)
Y_COLOUR = (0, 0, 210)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def zoom(size: int) -> int:
    """Nearest-neighbour enlargement of a kernel of ``size`` samples for the PSF panel."""
    return max(1, PSF_PANEL // size)


def grid_lines(size: int, s: int, factor: int) -> list[int]:
    """Panel pixel positions of the channel-pixel borders drawn over a kernel.

    The centre sample (size // 2) is the centre of a channel pixel, whose
    borders lie s/2 samples either side; the others follow every s samples.
    """
    centre = size // 2 + 0.5  # sample-edge coordinates
    first = centre - s / 2
    first -= math.floor(first / s) * s
    return [int(round(e * factor)) for e in np.arange(first, size + 1e-9, s) if 0 < e < size]


def _text(img: np.ndarray, text: str, org: tuple[int, int], colour=(0, 0, 0), scale: float = 0.45) -> None:
    cv2.putText(img, text, org, FONT, scale, colour, 1, cv2.LINE_AA)


def psf_panel(psf: np.ndarray, s: int) -> np.ndarray:
    """The kernel enlarged with nearest neighbour (inferno map, negatives black) and the channel-pixel grid."""
    peak = float(np.max(psf))
    grey = np.clip(psf / peak if peak > 0 else psf * 0, 0, 1)
    img = cv2.applyColorMap(np.round(grey * 255).astype(np.uint8), cv2.COLORMAP_INFERNO)
    f = zoom(psf.shape[0])
    img = cv2.resize(img, None, fx=f, fy=f, interpolation=cv2.INTER_NEAREST)
    for pos in grid_lines(psf.shape[1], s, f):
        img[:, pos] = GRID_COLOUR
    for pos in grid_lines(psf.shape[0], s, f):
        img[pos, :] = GRID_COLOUR
    return img


def mtf_plot(psf: np.ndarray, s: int) -> np.ndarray:
    """Horizontal (x) and vertical (y) MTF profiles up to s/2 cycles per channel pixel.

    Nyquist (0.5 cycle per channel pixel) is the dashed line; the MTF50 of
    each profile is printed in its colour.
    """
    img = np.full((PLOT_H, PLOT_W, 3), 255, dtype=np.uint8)
    left, top, right, bottom = AXES
    x0, y0, x1, y1 = left, top, PLOT_W - right, PLOT_H - bottom
    freqs, mx, my = mtf.profiles(psf, s)
    fmax = float(freqs[-1])
    # An MTF above 1 (negative kernel lobes) is shown up to 2, not hidden.
    top_value = min(2.0, 1.05 * max(1.0, float(mx.max()), float(my.max())))

    def px(f: np.ndarray | float, m: np.ndarray | float) -> tuple:
        return x0 + np.asarray(f) / fmax * (x1 - x0), y1 - np.clip(m, 0, top_value) / top_value * (y1 - y0)

    for level in (0.5, 1.0):  # guide lines
        _, yy = px(0, level)
        cv2.line(img, (x0, int(yy)), (x1, int(yy)), (215, 215, 215), 1)
    nx, _ = px(0.5, 0)
    for y in range(y0, y1, 8):  # dashed Nyquist line
        cv2.line(img, (int(nx), y), (int(nx), min(y + 4, y1)), (120, 120, 120), 1)
    _text(img, "Nyquist", (int(nx) + 4, y0 + 14), (90, 90, 90), 0.4)
    for values, colour in ((mx, X_COLOUR), (my, Y_COLOUR)):
        xs, ys = px(freqs, values)
        points = np.round(np.stack([xs, ys], axis=1)).astype(np.int32)
        cv2.polylines(img, [points], False, colour, 2, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x1, y1), (0, 0, 0), 1)
    step = 0.5 if fmax <= 4 else 1.0
    for f in np.arange(0, fmax + 1e-9, step):
        xx, _ = px(f, 0)
        cv2.line(img, (int(xx), y1), (int(xx), y1 + 4), (0, 0, 0), 1)
        _text(img, f"{f:g}", (int(xx) - 8, y1 + 18), scale=0.4)
    for m in np.arange(0, top_value, 0.5):
        _, yy = px(0, m)
        cv2.line(img, (x0 - 4, int(yy)), (x0, int(yy)), (0, 0, 0), 1)
        _text(img, f"{m:.1f}", (x0 - 34, int(yy) + 5), scale=0.4)
    _text(img, "cycles / channel pixel", (x0 + (x1 - x0) // 2 - 80, PLOT_H - 6), scale=0.45)
    _, label_y = px(0, 0.75)
    _text(img, "MTF", (8, int(label_y) + 5), scale=0.45)
    for row, (name, values, colour) in enumerate((("x", mx, X_COLOUR), ("y", my, Y_COLOUR))):
        value = mtf.mtf50(freqs, values)
        label = f"MTF {name}: MTF50 {value:.3f}" if math.isfinite(value) else f"MTF {name}: MTF50 n/a"
        _text(img, label, (x1 - 200, y0 + 40 + 20 * row), colour)
    return img


def psf_figure(est: PSF) -> np.ndarray:
    """The figure of one estimate (BGR uint8): title, PSF panel with pixel grid, MTF profiles."""
    panel = psf_panel(est.psf, est.s)
    plot = mtf_plot(est.psf, est.s)
    height = TITLE + max(panel.shape[0], PLOT_H) + PAD
    width = 3 * PAD + panel.shape[1] + PLOT_W
    img = np.full((height, width, 3), 255, dtype=np.uint8)
    img[TITLE : TITLE + panel.shape[0], PAD : PAD + panel.shape[1]] = panel
    img[TITLE : TITLE + PLOT_H, 2 * PAD + panel.shape[1] : 2 * PAD + panel.shape[1] + PLOT_W] = plot
    title = (
        f"{est.method} {est.channel}  field ({est.field[0]:.2f}, {est.field[1]:.2f})  "
        f"s={est.s}  support={est.support}  grid lines = channel pixels"
    )
    _text(img, title, (PAD, 22), scale=0.5)
    return img


def array_image(array: np.ndarray, min_side: int = 256) -> np.ndarray:
    """A 2-D array as 8-bit grey for viewing: signed arrays centred on mid-grey, small ones enlarged."""
    a = np.nan_to_num(np.asarray(array, dtype=np.float64))
    lo, hi = float(a.min()), float(a.max())
    if lo < 0:
        span = max(-lo, hi) or 1.0
        grey = 127.5 + 127.5 * a / span
    else:
        grey = 255 * a / (hi or 1.0)
    img = np.round(np.clip(grey, 0, 255)).astype(np.uint8)
    factor = max(1, min_side // max(img.shape))
    return cv2.resize(img, None, fx=factor, fy=factor, interpolation=cv2.INTER_NEAREST) if factor > 1 else img


# ---------------------------------------------------------------- method comparison

COLOURS = ((200, 90, 0), (0, 0, 210), (0, 150, 0), (160, 0, 160), (0, 140, 220), (120, 80, 40), (90, 90, 90))
W, H = 760, 460
LEFT, TOP, RIGHT, BOTTOM = 56, 16, 250, 44


def comparison_figure(curves: list[tuple[str, np.ndarray, int]]) -> np.ndarray:
    """Overlaid MTF profiles (x solid, y dotted), one colour per curve, legend on the right (BGR uint8)."""
    img = np.full((H, W, 3), 255, np.uint8)
    x0, y0, x1, y1 = LEFT, TOP, W - RIGHT, H - BOTTOM
    fmax = max(s for _, _, s in curves) / 2.0

    def px(f, m):
        return x0 + np.asarray(f) / fmax * (x1 - x0), y1 - np.clip(m, 0, 1.05) / 1.05 * (y1 - y0)

    nx, _ = px(0.5, 0)
    cv2.line(img, (int(nx), y0), (int(nx), y1), (170, 170, 170), 1)
    _text(img, "Nyquist", (int(nx) + 4, y0 + 14), (90, 90, 90), 0.4)
    for i, (label, psf, s) in enumerate(curves):
        colour = (0, 0, 0) if label == "truth" else COLOURS[i % len(COLOURS)]
        f, mx, my = mtf.profiles(psf, s)
        for values, dotted in ((mx, False), (my, True)):
            xs, ys = px(f, values)
            pts = np.round(np.stack([xs, ys], 1)).astype(np.int32)
            if dotted:  # OpenCV draws no dashed lines: every other short piece of the polyline
                for j in range(0, len(pts) - 1, 4):
                    end = pts[min(j + 2, len(pts) - 1)]
                    cv2.line(img, tuple(map(int, pts[j])), tuple(map(int, end)), colour, 1, cv2.LINE_AA)
            else:
                cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)
        ly = y0 + 14 + 18 * i
        cv2.line(img, (x1 + 12, ly - 4), (x1 + 32, ly - 4), colour, 2)
        _text(img, label[:40], (x1 + 38, ly), (0, 0, 0), 0.33)
    cv2.rectangle(img, (x0, y0), (x1, y1), (0, 0, 0), 1)
    for f in np.arange(0, fmax + 1e-9, 0.5):
        xx, _ = px(f, 0)
        _text(img, f"{f:g}", (int(xx) - 8, y1 + 18), (0, 0, 0), 0.4)
    for m in (0.0, 0.5, 1.0):
        _, yy = px(0, m)
        _text(img, f"{m:.1f}", (x0 - 34, int(yy) + 5), (0, 0, 0), 0.4)
    _text(img, "cycles / channel pixel   (x solid, y dotted)", (x0 + 60, H - 8), (0, 0, 0), 0.45)
    return img


# ---------------------------------------------------------------- field report

REPORT_PANEL = (480, 320)  # width, height of one field panel: a 3:2 sensor
REPORT_MARGIN, REPORT_HEADER = 16, 28
WHITE = (255, 255, 255)


def _sharpness(row: dict) -> float | None:
    values = [v for v in (row["mtf50_x"], row["mtf50_y"]) if v is not None]
    return float(np.mean(values)) if values else None


def _psf_field(rows: list[dict], arrays: Mapping[int, np.ndarray]) -> np.ndarray:
    """Each PSF drawn at its field position, scaled to its own peak, square-root shaded to show the tails."""
    width, height = REPORT_PANEL
    panel = np.zeros((height, width, 3), np.uint8)
    n_side = math.ceil(math.sqrt(len(rows)))
    size = int(np.clip(min(width, height) / (n_side + 1), 24, 96))
    for row in rows:
        array = arrays[row["id"]]
        shade = np.sqrt(np.clip(array / max(array.max(), 1e-300), 0, 1))
        thumb = cv2.applyColorMap(
            cv2.resize((255 * shade).astype(np.uint8), (size, size), interpolation=cv2.INTER_NEAREST),
            cv2.COLORMAP_INFERNO,
        )
        cx = int(np.clip(row["field_x"] * width - size / 2, 0, width - size))
        cy = int(np.clip(row["field_y"] * height - size / 2, 0, height - size))
        panel[cy : cy + size, cx : cx + size] = thumb
        cv2.rectangle(panel, (cx, cy), (cx + size - 1, cy + size - 1), (90, 90, 90), 1)
    return panel


def _mtf50_field(rows: list[dict], vmin: float, vmax: float) -> np.ndarray:
    """MTF50 over the field, inverse-distance-weighted between the measured locations.

    Inverse distance weighting (a few lines of numpy) is used rather than scipy's
    griddata because it needs no triangulation, so it also works with one or two
    collinear measurements and leaves no holes outside their convex hull.
    """
    width, height = REPORT_PANEL
    points = [(r["field_x"], r["field_y"], _sharpness(r)) for r in rows if _sharpness(r) is not None]
    panel = np.zeros((height, width, 3), np.uint8)
    if not points:
        _text(panel, "no MTF50", (10, height // 2), WHITE, 0.6)
        return panel
    fx, fy, value = (np.array(v, float) for v in zip(*points))
    gy, gx = np.mgrid[0:height:4, 0:width:4]
    d2 = (gx[..., None] / width - fx) ** 2 + (gy[..., None] / height - fy) ** 2
    weight = 1.0 / np.maximum(d2, 1e-9)
    field = (weight * value).sum(-1) / weight.sum(-1)
    level = np.clip((field - vmin) / max(vmax - vmin, 1e-12), 0, 1)
    small = cv2.applyColorMap((255 * level).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    panel[:] = cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR)
    for x, y, v in points:
        centre = (int(x * (width - 1)), int(y * (height - 1)))
        cv2.circle(panel, centre, 3, WHITE, -1, cv2.LINE_AA)
        _text(panel, f"{v:.2f}", (centre[0] + 5, centre[1] - 5), WHITE, 0.4)
    return panel


def _colour_bar(image: np.ndarray, origin: tuple[int, int], size: tuple[int, int]) -> None:
    """The MTF50 colour scale, low to high from left to right."""
    (x, y), (width, height) = origin, size
    ramp = np.tile(np.linspace(0, 255, width).astype(np.uint8), (height, 1))
    image[y : y + height, x : x + width] = cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS)


def report_figure(rows: list[dict], arrays: Mapping[int, np.ndarray], channel: str) -> np.ndarray:
    """One band per (camera, lens, method, aperture): the PSFs over the field, and the MTF50 field map.

    ``rows`` are catalogue rows (`psfd.catalogue.Catalogue.query`) of ``channel``, at least one;
    ``arrays`` maps their ids to the PSF arrays. MTF50 is the mean of the x and y values in
    cycles per channel pixel; one colour scale (printed in the title) is shared by all bands
    so that apertures can be compared.
    """
    values = [v for v in map(_sharpness, rows) if v is not None]
    vmin, vmax = (min(values), max(values)) if values else (0.0, 0.5)
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        key = (row["camera"] or "", row["lens"] or "", row["method"], row["aperture"] or 0.0)
        groups.setdefault(key, []).append(row)
    (width, height), margin, header = REPORT_PANEL, REPORT_MARGIN, REPORT_HEADER
    band = height + header + margin
    image = np.full((header + margin + band * len(groups), 2 * width + 3 * margin, 3), 32, np.uint8)
    title = f"channel {channel}   MTF50 (cycles/pixel) colour scale {vmin:.3f} .. {vmax:.3f}"
    _text(image, title, (margin, header - 8), WHITE, 0.55)
    _colour_bar(image, (image.shape[1] - margin - 160, 8), (160, 12))
    for i, ((camera, lens, method, aperture), group) in enumerate(sorted(groups.items())):
        top = header + margin + i * band
        name = f"f/{aperture:g}" if aperture else "f/?"
        _text(image, f"{name}  {method}  {camera} {lens}  {len(group)} PSFs", (margin, top + 18), WHITE, 0.5)
        _text(image, f"{name}: MTF50 map", (2 * margin + width, top + 18), WHITE, 0.5)
        y = top + header
        image[y : y + height, margin : margin + width] = _psf_field(group, arrays)
        image[y : y + height, 2 * margin + width : 2 * margin + 2 * width] = _mtf50_field(group, vmin, vmax)
    return image
