"""What the commands write and print: PSF files, figure files, JSON lines, tables.

Every output folder is checked the same way (`check_out_dir`: new or empty,
in a writable place) and written the same way (a hidden staging folder
renamed at the end), so a failure leaves nothing half-written. The pictures
themselves are drawn by `psfd.figures`.
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from psfd.errors import BadInputError, NoMatchError, path_reason
from psfd.estimator.kernels import PSF

# ---------------------------------------------------------------- folders and files


def check_out_dir(out_dir: str | os.PathLike) -> Path:
    """Fail early (before any work) if ``out_dir`` cannot be created or filled.

    An existing folder must be empty, so earlier results are never overwritten
    or mixed with new ones.
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


def parent_folder(out: Path) -> Path:
    """The folder ``out`` goes in, created if needed; an unwritable place is a bad input."""
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInputError(f"cannot create {out.parent}: {path_reason(out.parent, exc)}") from None
    return out.parent


def write_folder(out_dir: str | os.PathLike, write: Callable[[Path], list[str]]) -> list[Path]:
    """Fill a new folder atomically: ``write(staging)`` fills a hidden folder beside ``out_dir``
    and returns the names it wrote; the folder is renamed to ``out_dir`` only when complete.

    ``out_dir`` must not exist or be empty (`check_out_dir`).
    """
    out_dir = check_out_dir(out_dir)
    tmp = staging_dir(out_dir)
    try:
        files = write(tmp)
        if out_dir.exists():  # the empty folder check_out_dir accepted
            out_dir.rmdir()
        os.rename(tmp, out_dir)  # one atomic step: the folder appears complete
    except OSError as exc:
        raise BadInputError(f"{out_dir}: cannot write results ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [out_dir / f for f in files]


def write_file(out: Path, write: Callable[[Path], None]) -> None:
    """Write one file atomically: ``write(path)`` writes a hidden sibling with the same suffix,
    renamed to ``out`` when complete."""
    staging = parent_folder(out) / f".{out.stem}.{os.getpid()}.partial{out.suffix}"
    try:
        write(staging)
        os.replace(staging, out)
    except OSError as exc:
        reason = f": {exc.strerror}" if exc.strerror else ""
        raise BadInputError(f"could not write {out}{reason}") from None
    finally:
        staging.unlink(missing_ok=True)


# ---------------------------------------------------------------- PSF estimates


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


def _write_one(folder: Path, name: str, est: PSF) -> list[str]:
    import tifffile  # only the writers need these

    from psfd import figures

    files = [f"{name}.npy", f"{name}.tif", f"{name}.png", f"{name}.json"]
    np.save(folder / files[0], est.psf)
    meta = {"method": est.method, "channel": est.channel, "s": est.s, "field": [float(v) for v in est.field]}
    tifffile.imwrite(folder / files[1], est.psf.astype(np.float32), metadata=meta)
    figures.save_psf(est, folder / files[2])
    # the provenance and metrics beside the arrays, so a folder of results describes itself
    (folder / files[3]).write_text(json.dumps(plain(est.to_json()), allow_nan=False) + "\n")
    for key, array in est.figures.items():
        label = re.sub(r"[^A-Za-z0-9._+-]", "_", key)
        array = np.asarray(array)
        np.save(folder / f"{name}.{label}.npy", array)
        files.append(f"{name}.{label}.npy")
        if array.ndim == 2 and array.size:
            figures.save_array(array, folder / f"{name}.{label}.png")
            files.append(f"{name}.{label}.png")
    return files


def write_estimates(
    estimates: list[PSF],
    out_dir: str | os.PathLike,
    extra: dict[str, Callable[[Path], None]] | None = None,
) -> list[Path]:
    """Write every estimate as .npy, 32-bit float .tif and a .png figure, plus its extra figures.

    Per estimate ``NAME`` (see `base_names`): ``NAME.npy`` (float64 kernel),
    ``NAME.tif`` (float32), ``NAME.png`` (`psfd.figures.psf_figure`), ``NAME.json``
    (the `print_json` record), and for each entry
    ``key`` of ``PSF.figures``: ``NAME.key.npy`` and, when 2-D, ``NAME.key.png``.

    ``extra`` maps further file names to functions that write them at the path
    given (e.g. a comparison figure), so they join the same atomic folder
    (`write_folder`: nothing is left half-written).

    Returns
    -------
    list of Path
        The files written, in ``out_dir``.
    """

    def write(folder: Path) -> list[str]:
        files = [f for name, est in zip(base_names(estimates), estimates) for f in _write_one(folder, name, est)]
        for name, write_extra in (extra or {}).items():
            write_extra(folder / name)
            files.append(name)
        return files

    return write_folder(out_dir, write)


def write_report(catalogue: Any, rows: list[dict], channel: str, out: Path) -> None:
    """The field report (`psfd.figures.report_figure`) of the catalogue rows of ``channel``, written to ``out``."""
    from psfd import figures

    rows = [r for r in rows if r["channel"] == channel]
    if not rows:
        raise NoMatchError(f"no PSF of channel {channel} to report")
    arrays = {row["id"]: catalogue.psf(row["id"])[0] for row in rows}
    write_file(out, lambda path: figures.save_report(rows, arrays, channel, path))


# ---------------------------------------------------------------- printing


def plain(value: Any) -> Any:
    """JSON-ready copy: numpy arrays and numbers to Python, NaN/inf to null (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def fmt(value: float | None, spec: str = ".3f") -> str:
    """A number for a table, ``-`` when absent or not finite."""
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def print_json(estimates: list[PSF], stream: TextIO | None = None) -> None:
    """One JSON object per estimate per line (`PSF.to_json`)."""
    stream = sys.stdout if stream is None else stream
    for est in estimates:
        stream.write(json.dumps(plain(est.to_json()), allow_nan=False) + "\n")
    stream.flush()


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
            f"{fmt(m['mtf50_x']):>8} {fmt(m['mtf50_y']):>8} {fmt(m['fwhm_x'], '.2f'):>7} "
            f"{fmt(m['fwhm_y'], '.2f'):>7} {fmt(est.noise_floor, '.2e'):>9}",
            file=stream,
        )
        for warning in est.warnings:
            print(f"  warning: {warning}", file=stream)
    print("MTF50 in cycles per channel pixel (Nyquist 0.5); FWHM in channel pixels.", file=stream)


ROW_COLUMNS = (
    ("id", lambda r: str(r["id"])),
    ("camera", lambda r: r["camera"] or "-"),
    ("lens", lambda r: r["lens"] or "-"),
    ("f/", lambda r: fmt(r["aperture"], "g")),
    ("ch", lambda r: r["channel"]),
    ("method", lambda r: r["method"]),
    ("field", lambda r: f"{r['field_x']:.3f},{r['field_y']:.3f}"),
    ("s", lambda r: str(r["s"])),
    ("size", lambda r: str(r["support"])),
    ("mtf50 x/y", lambda r: f"{fmt(r['mtf50_x'])}/{fmt(r['mtf50_y'])}"),
    ("fwhm x/y", lambda r: f"{fmt(r['fwhm_x'], '.2f')}/{fmt(r['fwhm_y'], '.2f')}"),
)


def format_rows(rows: list[dict]) -> str:
    """Aligned text table of catalogue PSF rows (MTF50 in cycles per channel pixel, FWHM in channel pixels)."""
    columns = list(ROW_COLUMNS)
    if rows and "distance" in rows[0]:
        columns.append(("dist", lambda r: f"{r['distance']:.3f}"))
    cells = [[name for name, _ in columns]] + [[cell(r) for _, cell in columns] for r in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(columns))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in cells)
