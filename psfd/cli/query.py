"""`psfd query`, `psfd export`, `psfd report`: read PSFs back out of the catalogue."""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import tifffile

from psfd.catalogue import Catalogue, QueryResult, default_path, parse_fnumber
from psfd.cli.output import staging_dir
from psfd.errors import BadInputError, CatalogueError
from psfd.estimator.raw import CHANNELS

EXPORT_FORMATS = ("npy", "tiff", "json")
# The `PSF.method` names the estimators store.
METHODS = ("bernoulli", "two-photo", "sharp-edge")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``query``, ``export`` and ``report`` commands."""
    filters = argparse.ArgumentParser(add_help=False)
    filters.add_argument(
        "--catalogue", metavar="PATH", help="catalogue file (default: $XDG_DATA_HOME/psfd/catalogue.sqlite or ~/.local/share/...)"
    )
    filters.add_argument("--camera", help="camera model (case-insensitive substring) or serial number")
    filters.add_argument("--lens", help="lens name (case-insensitive substring)")
    filters.add_argument("--aperture", metavar="F", help="f-number, e.g. 5.6; the nearest measured one if not measured")
    filters.add_argument("--channel", help=f"Bayer channel ({', '.join(CHANNELS)}, mono)")
    filters.add_argument("--method", help=", ".join(METHODS[:-1]) + " or " + METHODS[-1])
    near = argparse.ArgumentParser(add_help=False)
    near.add_argument("--near", metavar="X,Y", help="normalised field location: the nearest PSF per aperture")
    near.add_argument("--limit", metavar="N", help="at most this many PSFs")

    about = "list catalogued PSFs (a table, or JSON lines with the arrays)"
    query = subparsers.add_parser("query", parents=[filters, near], help=about, description=about)
    query.add_argument("--json", action="store_true", help="one JSON object per line, with the PSF array")
    query.set_defaults(func=run_query)

    about = "write catalogued PSFs to a new folder, one file each plus index.json"
    export = subparsers.add_parser("export", parents=[filters, near], help=about, description=about)
    export.add_argument("--format", default="npy", metavar="FORMAT", help=f"{' | '.join(EXPORT_FORMATS)} (default npy)")
    export.add_argument("--out", required=True, help="folder to create (must not exist or be empty)")
    export.set_defaults(func=run_export)

    about = "draw a figure: per aperture, the PSFs over the field and an MTF50 field map"
    report = subparsers.add_parser("report", parents=[filters], help=about, description=about)
    report.add_argument("--out", default="report.png", help="image file (default report.png)")
    report.set_defaults(func=run_report)


# -- arguments -------------------------------------------------------------------


def parse_near(text: str | None) -> tuple[float, float] | None:
    """``"0.8,0.1"`` -> (0.8, 0.1); a normalised field location, both in [0, 1]."""
    if text is None:
        return None
    parts = text.split(",")
    try:
        x, y = (float(p) for p in parts)
    except ValueError:
        raise BadInputError(f"--near wants X,Y (two numbers in [0, 1]), got {text!r}") from None
    if not (0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
        raise BadInputError(f"--near {text}: field coordinates are normalised to [0, 1]")
    return x, y


def _positive_int(text: str | None, name: str) -> int | None:
    if text is None:
        return None
    if not text.isdigit() or int(text) < 1:
        raise BadInputError(f"{name} wants a positive whole number, got {text!r}")
    return int(text)


def open_catalogue(args: argparse.Namespace) -> Catalogue:
    """The catalogue named by ``--catalogue`` (default: the user's), which must exist."""
    return Catalogue(args.catalogue or default_path(), create=False)


def query_options(args: argparse.Namespace) -> dict[str, Any]:
    """Validated keyword arguments of Catalogue.query from the filter options (before any file is opened)."""
    if args.channel is not None and args.channel not in (*CHANNELS, "mono"):
        raise BadInputError(f"unknown channel {args.channel!r} (one of {', '.join(CHANNELS)}, mono)")
    if args.method is not None and args.method not in METHODS:
        raise BadInputError(f"unknown method {args.method!r} (one of {', '.join(METHODS)})")
    return {
        "camera": args.camera,
        "lens": args.lens,
        "aperture": parse_fnumber(args.aperture),
        "channel": args.channel,
        "method": args.method,
        "near": parse_near(getattr(args, "near", None)),
        "limit": _positive_int(getattr(args, "limit", None), "--limit"),
    }


def run_filters(cat: Catalogue, options: dict[str, Any]) -> QueryResult:
    """Run a query; its note (nearest aperture used) goes to stderr, apart from the results."""
    result = cat.query(**options)
    if result.note:
        print(f"psfd: note: {result.note}", file=sys.stderr)
    return result


# -- query -------------------------------------------------------------------------


def _fmt(value: Any, spec: str = ".3f") -> str:
    return "-" if value is None else format(value, spec)


TABLE = (
    ("id", lambda r: str(r["id"])),
    ("camera", lambda r: r["camera"] or "-"),
    ("lens", lambda r: r["lens"] or "-"),
    ("f/", lambda r: _fmt(r["aperture"], "g")),
    ("ch", lambda r: r["channel"]),
    ("method", lambda r: r["method"]),
    ("field", lambda r: f"{r['field_x']:.3f},{r['field_y']:.3f}"),
    ("s", lambda r: str(r["s"])),
    ("size", lambda r: str(r["support"])),
    ("mtf50 x/y", lambda r: f"{_fmt(r['mtf50_x'])}/{_fmt(r['mtf50_y'])}"),
    ("fwhm x/y", lambda r: f"{_fmt(r['fwhm_x'], '.2f')}/{_fmt(r['fwhm_y'], '.2f')}"),
)


def format_table(rows: list[dict]) -> str:
    """Aligned text table of PSF rows (MTF50 in cycles per channel pixel, FWHM in channel pixels)."""
    columns = list(TABLE)
    if rows and "distance" in rows[0]:
        columns.append(("dist", lambda r: f"{r['distance']:.3f}"))
    cells = [[name for name, _ in columns]] + [[cell(r) for _, cell in columns] for r in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(columns))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in cells)


def run_query(args: argparse.Namespace) -> int:
    options = query_options(args)
    with open_catalogue(args) as cat:
        result = run_filters(cat, options)
        if not result.rows:
            # on stderr, so that --json output stays empty (zero JSON lines) and parseable
            print("psfd: no PSF matches the query", file=sys.stderr)
        elif args.json:
            for row in result:
                array, _ = cat.psf(row["id"])
                print(json.dumps({**row, "psf": array.tolist()}))
        else:
            print(format_table(result.rows))
    return 0


# -- export ----------------------------------------------------------------------


def _parent_folder(out: Path) -> Path:
    """The folder ``out`` goes in, created if needed; an unwritable place is a bad input."""
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInputError(f"cannot create {out.parent}: {exc.strerror}") from None
    return out.parent


def _file_stem(row: dict) -> str:
    aperture = "NA" if row["aperture"] is None else format(row["aperture"], "g")
    return f"psf{row['id']:06d}_{row['channel']}_f{aperture}_{row['method']}"


def _write_psf(folder: Path, stem: str, array: np.ndarray, meta: dict, fmt: str) -> str:
    if fmt == "npy":
        name = f"{stem}.npy"
        np.save(folder / name, array, allow_pickle=False)
    elif fmt == "tiff":
        name = f"{stem}.tif"
        # 32-bit float keeps ~7 significant digits, far below any PSF's noise floor.
        tifffile.imwrite(folder / name, array.astype(np.float32), description=json.dumps(meta), metadata=None)
    else:
        name = f"{stem}.json"
        (folder / name).write_text(json.dumps({**meta, "psf": array.tolist()}))
    return name


def run_export(args: argparse.Namespace) -> int:
    if args.format not in EXPORT_FORMATS:
        raise BadInputError(f"unknown export format {args.format!r} (one of {', '.join(EXPORT_FORMATS)})")
    options = query_options(args)
    out = Path(args.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BadInputError(f"{out} already exists and is not an empty folder")
    with open_catalogue(args) as cat:
        result = run_filters(cat, options)
        if not result.rows:
            raise CatalogueError("no PSF matches the query; nothing exported")
        # Everything is written into a hidden sibling folder and renamed at the end, so an
        # error leaves no half-exported folder behind.
        _parent_folder(out)
        staging = staging_dir(out)
        try:
            index = []
            for row in result:
                array, meta = cat.psf(row["id"])
                meta = {**meta, **({"distance": row["distance"]} if "distance" in row else {})}
                index.append({"file": _write_psf(staging, _file_stem(row), array, meta, args.format), **meta})
            (staging / "index.json").write_text(json.dumps({"note": result.note, "psfs": index}, indent=1))
            os.rename(staging, out)
        except BaseException:
            shutil.rmtree(staging, ignore_errors=True)
            raise
    print(f"exported {len(index)} PSFs to {out}")
    return 0


# -- report ----------------------------------------------------------------------

PANEL = (480, 320)  # width, height of one field panel: a 3:2 sensor
MARGIN, HEADER = 16, 28
FONT = cv2.FONT_HERSHEY_SIMPLEX
WHITE = (255, 255, 255)


def _pick_channel(rows: list[dict], asked: str | None) -> str:
    if asked:
        return asked
    channels = {r["channel"] for r in rows}
    return "g1" if "g1" in channels else sorted(channels)[0]


def _sharpness(row: dict) -> float | None:
    values = [v for v in (row["mtf50_x"], row["mtf50_y"]) if v is not None]
    return float(np.mean(values)) if values else None


def _psf_panel(cat: Catalogue, rows: list[dict]) -> np.ndarray:
    """Each PSF drawn at its field position, scaled to its own peak, square-root shaded to show the tails."""
    width, height = PANEL
    panel = np.zeros((height, width, 3), np.uint8)
    n_side = math.ceil(math.sqrt(len(rows)))
    size = int(np.clip(min(width, height) / (n_side + 1), 24, 96))
    for row in rows:
        array, _ = cat.psf(row["id"])
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


def _mtf_panel(rows: list[dict], vmin: float, vmax: float) -> np.ndarray:
    """MTF50 over the field, inverse-distance-weighted between the measured locations.

    Inverse distance weighting (a few lines of numpy) is used rather than scipy's
    griddata because it needs no triangulation, so it also works with one or two
    collinear measurements and leaves no holes outside their convex hull.
    """
    width, height = PANEL
    points = [(r["field_x"], r["field_y"], _sharpness(r)) for r in rows if _sharpness(r) is not None]
    panel = np.zeros((height, width, 3), np.uint8)
    if not points:
        cv2.putText(panel, "no MTF50", (10, height // 2), FONT, 0.6, WHITE, 1, cv2.LINE_AA)
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
        cv2.putText(panel, f"{v:.2f}", (centre[0] + 5, centre[1] - 5), FONT, 0.4, WHITE, 1, cv2.LINE_AA)
    return panel


def _colour_bar(image: np.ndarray, origin: tuple[int, int], size: tuple[int, int]) -> None:
    """The MTF50 colour scale, low to high from left to right."""
    (x, y), (width, height) = origin, size
    ramp = np.tile(np.linspace(0, 255, width).astype(np.uint8), (height, 1))
    image[y : y + height, x : x + width] = cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS)


def draw_report(cat: Catalogue, rows: list[dict], channel: str) -> np.ndarray:
    """One band per (camera, lens, method, aperture): the PSFs over the field, and the MTF50 field map.

    MTF50 is the mean of the x and y values in cycles per channel pixel; one colour scale
    (printed in the title) is shared by all bands so that apertures can be compared.
    """
    rows = [r for r in rows if r["channel"] == channel]
    if not rows:
        raise CatalogueError(f"no PSF of channel {channel} to report")
    values = [v for v in map(_sharpness, rows) if v is not None]
    vmin, vmax = (min(values), max(values)) if values else (0.0, 0.5)
    groups: dict[tuple, list[dict]] = {}
    for row in rows:
        key = (row["camera"] or "", row["lens"] or "", row["method"], row["aperture"] or 0.0)
        groups.setdefault(key, []).append(row)
    width, height = PANEL
    band = height + HEADER + MARGIN
    image = np.full((HEADER + MARGIN + band * len(groups), 2 * width + 3 * MARGIN, 3), 32, np.uint8)
    title = f"channel {channel}   MTF50 (cycles/pixel) colour scale {vmin:.3f} .. {vmax:.3f}"
    cv2.putText(image, title, (MARGIN, HEADER - 8), FONT, 0.55, WHITE, 1, cv2.LINE_AA)
    _colour_bar(image, (image.shape[1] - MARGIN - 160, 8), (160, 12))
    for i, ((camera, lens, method, aperture), group) in enumerate(sorted(groups.items())):
        top = HEADER + MARGIN + i * band
        name = f"f/{aperture:g}" if aperture else "f/?"
        label = f"{name}  {method}  {camera} {lens}  {len(group)} PSFs"
        cv2.putText(image, label, (MARGIN, top + 18), FONT, 0.5, WHITE, 1, cv2.LINE_AA)
        cv2.putText(image, f"{name}: MTF50 map", (2 * MARGIN + width, top + 18), FONT, 0.5, WHITE, 1, cv2.LINE_AA)
        y = top + HEADER
        image[y : y + height, MARGIN : MARGIN + width] = _psf_panel(cat, group)
        image[y : y + height, 2 * MARGIN + width : 2 * MARGIN + 2 * width] = _mtf_panel(group, vmin, vmax)
    return image


def run_report(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if not cv2.haveImageWriter(str(out)):
        raise BadInputError(f"cannot write an image named {out} (use .png, .jpg or .tif)")
    options = query_options(args)
    with open_catalogue(args) as cat:
        result = run_filters(cat, options)
        if not result.rows:
            raise CatalogueError("no PSF matches the query; nothing to report")
        image = draw_report(cat, result.rows, _pick_channel(result.rows, args.channel))
    # cv2 picks the codec by the suffix, so the temporary name keeps it.
    staging = _parent_folder(out) / f".{out.stem}.{os.getpid()}.partial{out.suffix}"
    try:
        if not cv2.imwrite(str(staging), image):
            raise BadInputError(f"could not write {out}")
        os.replace(staging, out)
    except OSError as exc:
        raise BadInputError(f"could not write {out}: {exc.strerror or exc}") from None
    finally:
        if staging.exists():  # imwrite may fail before creating it (read-only folder)
            staging.unlink()
    print(f"report written to {out}")
    return 0
