"""What the commands write and print: PSF files, figures, JSON lines, tables.

Also the parsing of the numbers users type, so every command rejects them
with the same one-line `BadInputError` instead of argparse's usage dump.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path
from collections.abc import Callable
from typing import Any, TextIO

import cv2
import numpy as np

from psfd.errors import BadInputError
from psfd.estimator import mtf
from psfd.estimator.psf import PSF

# ---------------------------------------------------------------- argument values


def parse_int(text: str | int, name: str, minimum: int | None = None) -> int:
    """An integer option value, or a one-line BadInputError."""
    try:
        value = int(str(text).strip())
    except ValueError:
        raise BadInputError(f"{name}: expected an integer, got {text!r}") from None
    if minimum is not None and value < minimum:
        raise BadInputError(f"{name}: must be at least {minimum}, got {value}")
    return value


def parse_float(text: str | float, name: str) -> float:
    """A finite number option value, or a one-line BadInputError."""
    try:
        value = float(str(text).strip())
    except ValueError:
        raise BadInputError(f"{name}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise BadInputError(f"{name}: expected a finite number, got {text!r}")
    return value


def parse_support(text: str | int | None) -> int | None:
    """``--support``: an odd kernel side of at least 3 samples (None: the estimator's 4s+1)."""
    if text is None:
        return None
    value = parse_int(text, "--support", minimum=3)
    if value % 2 == 0:
        raise BadInputError(f"--support: must be odd so the kernel has a centre sample, got {value}")
    return value


def parse_grid(text: str) -> tuple[int, int]:
    """``--grid NxM``: N windows across and M down, each at least 1."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not match or int(match[1]) < 1 or int(match[2]) < 1:
        raise BadInputError(f"--grid: expected NxM with N, M >= 1 (e.g. 3x2), got {text!r}")
    return int(match[1]), int(match[2])


# ---------------------------------------------------------------- file names


def base_names(estimates: list[PSF]) -> list[str]:
    """One file-name stem per estimate: ``<source stem>_<method>_<channel>_w<window index>``.

    The window index counts the estimates of one source, method and channel in
    order (the estimators return grid windows row-major).
    """
    counts: dict[tuple, int] = {}
    names: list[str] = []
    for est in estimates:
        stem = "+".join(Path(s).stem for s in est.sources) or "psf"
        key = (tuple(est.sources), est.method, est.channel)
        index = counts.get(key, 0)
        counts[key] = index + 1
        name = re.sub(r"[^A-Za-z0-9._+-]", "_", f"{stem}_{est.method}_{est.channel}_w{index:02d}")
        unique, n = name, 2
        while unique in names:  # same stem from two folders
            unique, n = f"{name}-{n}", n + 1
        names.append(unique)
    return names


# ---------------------------------------------------------------- figures

PANEL = 360  # target side of the enlarged PSF panel, pixels
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
    return max(1, PANEL // size)


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


# ---------------------------------------------------------------- writing


def check_out_dir(out_dir: str | os.PathLike) -> Path:
    """Fail early (before any estimation) if ``out_dir`` cannot be created or filled.

    Like ``psfd export``, an existing folder must be empty, so earlier results are
    never overwritten or mixed with new ones.
    """
    out_dir = Path(out_dir).absolute()
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise BadInputError(f"{out_dir}: exists and is not an empty folder")
    parent = out_dir.parent
    if not parent.is_dir():
        raise BadInputError(f"{parent}: {'not a folder' if parent.exists() else 'no such folder'}")
    if not os.access(parent, os.W_OK):
        raise BadInputError(f"{parent}: not a writable folder")
    return out_dir


def staging_dir(out: Path) -> Path:
    """A new hidden temporary folder beside ``out``; an unwritable place is a one-line BadInputError."""
    try:
        return Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    except OSError as exc:
        raise BadInputError(f"cannot write in {out.parent}: {exc.strerror or exc}") from None


def _imwrite(path: Path, img: np.ndarray) -> None:
    if not cv2.imwrite(str(path), img):
        raise OSError(f"cannot encode {path.name}")


def _write_one(folder: Path, name: str, est: PSF) -> list[str]:
    import tifffile  # only the writers need it

    files = [f"{name}.npy", f"{name}.tif", f"{name}.png", f"{name}.json"]
    np.save(folder / files[0], est.psf)
    meta = {"method": est.method, "channel": est.channel, "s": est.s, "field": [float(v) for v in est.field]}
    tifffile.imwrite(folder / files[1], est.psf.astype(np.float32), metadata=meta)
    _imwrite(folder / files[2], psf_figure(est))
    # the provenance and metrics beside the arrays, so a folder of results describes itself
    (folder / files[3]).write_text(json.dumps(_plain(est.to_json()), allow_nan=False) + "\n")
    for key, array in est.figures.items():
        label = re.sub(r"[^A-Za-z0-9._+-]", "_", key)
        array = np.asarray(array)
        np.save(folder / f"{name}.{label}.npy", array)
        files.append(f"{name}.{label}.npy")
        if array.ndim == 2 and array.size:
            _imwrite(folder / f"{name}.{label}.png", array_image(array))
            files.append(f"{name}.{label}.png")
    return files


def write_estimates(
    estimates: list[PSF],
    out_dir: str | os.PathLike,
    extra: dict[str, Callable[[Path], None]] | None = None,
) -> list[Path]:
    """Write every estimate as .npy, 32-bit float .tif and a .png figure, plus its extra figures.

    Per estimate ``NAME`` (see `base_names`): ``NAME.npy`` (float64 kernel),
    ``NAME.tif`` (float32), ``NAME.png`` (`psf_figure`), ``NAME.json`` (the
    `print_json` record), and for each entry
    ``key`` of ``PSF.figures``: ``NAME.key.npy`` and, when 2-D, ``NAME.key.png``.

    ``extra`` maps further file names to functions that write them at the path
    given (e.g. a comparison figure), so they join the same atomic folder.

    ``out_dir`` must not exist or be empty (`check_out_dir`). Everything is written
    into a temporary folder beside it and renamed to ``out_dir`` at the end, so a
    failure leaves nothing half-written.

    Returns
    -------
    list of Path
        The files written, in ``out_dir``.
    """
    out_dir = check_out_dir(out_dir)
    tmp = staging_dir(out_dir)
    try:
        files = [f for name, est in zip(base_names(estimates), estimates) for f in _write_one(tmp, name, est)]
        for name, write in (extra or {}).items():
            write(tmp / name)
            files.append(name)
        if out_dir.exists():  # the empty folder check_out_dir accepted
            out_dir.rmdir()
        os.rename(tmp, out_dir)  # one atomic step: the folder appears complete
    except OSError as exc:
        raise BadInputError(f"{out_dir}: cannot write results ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [out_dir / f for f in files]


# ---------------------------------------------------------------- printing


def _plain(value: Any) -> Any:
    """JSON-ready copy: numpy types to Python, NaN/inf to null (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def print_json(estimates: list[PSF], stream: TextIO | None = None) -> None:
    """One JSON object per estimate per line (`PSF.to_json`)."""
    stream = sys.stdout if stream is None else stream
    for est in estimates:
        stream.write(json.dumps(_plain(est.to_json()), allow_nan=False) + "\n")
    stream.flush()


def _fmt(value: float | None, spec: str = ".3f") -> str:
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def print_table(estimates: list[PSF], stream: TextIO | None = None) -> None:
    """A short human-readable table: one line per estimate, warnings below it."""
    stream = sys.stdout if stream is None else stream
    print(
        f"{'source':<28} {'chan':<5} {'field x,y':<11} {'MTF50 x':>8} {'MTF50 y':>8} "
        f"{'FWHM x':>7} {'FWHM y':>7} {'noise':>9}",
        file=stream,
    )
    for est in estimates:
        m = est.metrics()
        source = "+".join(Path(s).stem for s in est.sources)
        source = source if len(source) <= 28 else source[:27] + "~"
        print(
            f"{source:<28} {est.channel:<5} {est.field[0]:.2f},{est.field[1]:.2f}  "
            f"{_fmt(m['mtf50_x']):>8} {_fmt(m['mtf50_y']):>8} {_fmt(m['fwhm_x'], '.2f'):>7} "
            f"{_fmt(m['fwhm_y'], '.2f'):>7} {_fmt(est.noise_floor, '.2e'):>9}",
            file=stream,
        )
        for warning in est.warnings:
            print(f"  warning: {warning}", file=stream)
    print("MTF50 in cycles per channel pixel (Nyquist 0.5); FWHM in channel pixels.", file=stream)
