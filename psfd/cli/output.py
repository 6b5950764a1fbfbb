"""What the commands write and print: PSF files, figure files, JSON lines, CSV, tables.

Every output folder is checked the same way (`check_out_dir`: new or empty,
in a writable place, or replaced whole with ``--force`` when it holds only
earlier results) and written the same way (a hidden staging folder renamed at
the end, with the permissions the umask gives a new folder), so a failure
leaves nothing half-written and nothing a user made is overwritten or deleted. The pictures themselves are
drawn by `psfd.figures`.

Units, wherever a number is printed or written: MTF50 in cycles per channel
pixel (Nyquist 0.5), and in line pairs per mm and line widths per picture
height when the photosite pitch and the picture height are known (from the
RAW's EXIF, `psfd.exif.read_metadata`, or the plan's ``[rig] pitch_um``);
FWHM in channel pixels; field coordinates normalised, (0, 0) top-left.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import re
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from psfd.errors import BadInputError, NoMatchError
from psfd.estimator.kernels import PSF
from psfd.vocabulary import ALIASES, CHANNELS, METHODS, MONO
from psfd.workers import forked_map, in_worker, usable_cores



def units_line(rows: list[dict]) -> str:
    """The units of the columns `format_rows` shows for ``rows``: lp/mm and dist only where they are shown."""
    mtf = "mtf50 in cycles per channel pixel (Nyquist 0.5)"
    if _has_lp_mm(rows):
        mtf += ", lp/mm: line pairs per mm on the sensor"
    return (f"units: f/ f-number; field normalised (0,0 top-left, 1,1 bottom-right); size: kernel side in samples "
            f"of the s-times grid; {mtf}; fwhm in channel pixels" +
            ("; dist: field distance to --near, normalised" if rows and "distance" in rows[0] else ""))


def _has_lp_mm(rows: list[dict]) -> bool:
    return any(r.get("mtf50_x_lp_mm") is not None or r.get("mtf50_y_lp_mm") is not None for r in rows)

# ---------------------------------------------------------------- folders and files


# What psfd itself writes into an --out folder, so all that --force may replace: the estimates
# (`write_estimates`: NAME.npy/.tif/.png/.json, NAME.KEY.npy/.png, NAME from `base_names`, and grid.png),
# compare's compare.png and compare.json, export's PSF files (`psfd.cli.query._file_stem`) and index.json,
# and metrics.csv. Anything else in a folder is the user's, and a folder holding it is never replaced.
_METHOD = "|".join(re.escape(m) for m in (*METHODS, *ALIASES))
_CHANNEL = "|".join((*CHANNELS, MONO))
RESULT_NAME = re.compile(
    rf"metrics\.csv|index\.json|compare\.(png|json)|grid\.png"
    rf"|.+_({_METHOD})_({_CHANNEL})_w\d{{2,}}(-\d+)?(\.[A-Za-z0-9._+-]+)?\.(npy|tif|png|json)"
    rf"|psf\d{{6,}}_({_CHANNEL})_f(NA|[0-9.e+-]+)_({_METHOD})\.(npy|tif|json)"
)


def check_out_dir(out_dir: str | os.PathLike, force: bool = False,
                  inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Fail early (before any work) if ``out_dir`` cannot be created or filled.

    An existing folder must be empty, so earlier results are never overwritten
    or mixed with new ones, unless ``force`` (``--force``) asks to replace it whole:
    then it must hold only files psfd writes (`RESULT_NAME`) and none of the
    command's ``inputs``, so that no photograph, note or folder of the user's
    (the current folder given by mistake) is ever deleted with it.
    """
    out_dir = Path(out_dir).absolute()
    if out_dir.exists() and not out_dir.is_dir():
        raise BadInputError(f"{out_dir}: exists and is not a folder")
    if out_dir.exists() and any(out_dir.iterdir()):
        _check_replaceable(out_dir, inputs)
        if not force:
            raise BadInputError(f"{out_dir}: exists and is not an empty folder (add --force to replace it)")
    parent = out_dir.parent
    if not parent.is_dir():
        raise BadInputError(f"{parent}: {'not a folder' if parent.exists() else 'no such folder'}")
    if not os.access(parent, os.W_OK):
        raise BadInputError(f"{parent}: not a writable folder")
    if out_dir.is_dir() and not os.access(out_dir, os.W_OK):
        # an empty folder is replaced by the one written beside it: one the user made read-only stays so
        raise BadInputError(f"{out_dir}: not a writable folder")
    return out_dir


def _check_replaceable(out_dir: Path, inputs: Iterable[str | os.PathLike]) -> None:
    """Refuse a folder holding anything but earlier results (`RESULT_NAME`), or an input of the command,
    with or without ``--force``: the one-line error names it and says what to do instead."""
    for entry in sorted(out_dir.iterdir()):
        if entry.is_dir() or not RESULT_NAME.fullmatch(entry.name):
            kind = "folder" if entry.is_dir() else "file"
            raise BadInputError(f"{out_dir}: exists and is not an empty folder of psfd results (it holds the {kind} "
                                f"{entry.name}); choose a new or empty folder for --out")
    here = out_dir.resolve()
    for path in map(Path, inputs):
        # the link's folder and the file's own: an input reached through a symbolic link is kept too
        if here in (path.absolute().parent.resolve(), path.resolve().parent):
            raise BadInputError(f"{out_dir}: exists and holds {path.name}, an input of this command, which --force "
                                "would delete; choose a new or empty folder for --out")


def umask() -> int:
    """The process's file-creation mask (read by setting it and putting it back)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def publish(staging: Path, out: Path) -> None:
    """Rename a complete staging folder to ``out``, with the permissions a new folder gets (the umask's,
    not `tempfile.mkdtemp`'s private 0700). An existing ``out`` (``--force``, checked by `check_out_dir`)
    is moved aside first and removed only once the new folder is in place."""
    os.chmod(staging, 0o777 & ~umask())
    old = None
    if out.exists():
        if any(out.iterdir()):
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".old", dir=out.parent))
            os.rename(out, old / "replaced")
        else:
            out.rmdir()  # the empty folder check_out_dir accepted
    os.rename(staging, out)  # one atomic step: the folder appears complete
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def staging_dir(out: Path) -> Path:
    """A new hidden temporary folder beside ``out``; an unwritable place is a one-line BadInputError."""
    try:
        return Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".part", dir=out.parent))
    except OSError as exc:
        raise BadInputError(f"cannot write in {out.parent}: {exc.strerror or exc}") from None


def check_out_file(out: str | os.PathLike) -> Path:
    """Fail early (before any work) if the file ``out`` cannot be made: its folder must exist.

    As for an output folder (`check_out_dir`), the name given is made and no missing folder above it:
    a mistyped path, or media not mounted, is a one-line error naming the folder, not a new tree of
    folders on the wrong disk. Returns the folder.
    """
    out = Path(out).absolute()
    if out.is_dir():
        raise BadInputError(f"{out}: is a folder; name a file")
    parent = out.parent
    if not parent.is_dir():
        raise BadInputError(f"{parent}: {'not a folder' if parent.exists() else 'no such folder'}")
    return parent


def write_folder(out_dir: str | os.PathLike, write: Callable[[Path], list[str]], force: bool = False,
                 inputs: Iterable[str | os.PathLike] = ()) -> list[Path]:
    """Fill a new folder atomically: ``write(staging)`` fills a hidden folder beside ``out_dir``
    and returns the names it wrote; the folder is renamed to ``out_dir`` only when complete.

    ``out_dir`` must not exist or be empty, or with ``force`` is replaced whole if it holds only earlier
    results and none of the command's ``inputs`` (`check_out_dir`, `publish`): checked again here, as the
    folder may have changed during the work.
    """
    out_dir = check_out_dir(out_dir, force, inputs)
    tmp = staging_dir(out_dir)
    try:
        files = write(tmp)
        publish(tmp, out_dir)
    except OSError as exc:
        raise BadInputError(f"{out_dir}: cannot write results ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return [out_dir / f for f in files]


def write_file(out: Path, write: Callable[[Path], None]) -> None:
    """Write one file atomically: ``write(path)`` writes a hidden sibling with the same suffix,
    renamed to ``out`` when complete, in a folder that exists (`check_out_file`)."""
    staging = check_out_file(out) / f".{out.stem}.{os.getpid()}.partial{out.suffix}"
    try:
        write(staging)
        os.replace(staging, out)
    except OSError as exc:
        reason = f": {exc.strerror}" if exc.strerror else ""
        raise BadInputError(f"could not write {out}{reason}") from None
    finally:
        with contextlib.suppress(OSError):  # on a read-only disk even a missing file's unlink fails (EROFS)
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


def tiff_resolution(pitch_um: float | None, s: int | None, channel: str) -> dict:
    """tifffile's resolution arguments for a kernel: samples per cm on the sensor, or none when the pitch is
    unknown. The kernel is sampled at the channel pixel pitch / s: a Bayer plane's pixel is two photosites, a
    mono plane's one (`psfd.estimator.mtf.channel_pitch_mm`)."""
    from psfd.estimator import mtf

    if not pitch_um or not s:
        return {}
    density = 10.0 * s / mtf.channel_pitch_mm(pitch_um, channel)
    return {"resolution": (density, density), "resolutionunit": "CENTIMETER"}


def _write_one(folder: Path, name: str, est: PSF, sensor: Any, drawn: bool) -> list[str]:
    """The files of one estimate but its PSF figure (`_write_figures`); its other figures when ``drawn``."""
    import tifffile  # only the writers need these

    from psfd import figures

    files = [f"{name}.npy", f"{name}.tif", f"{name}.json"]
    np.save(folder / files[0], est.psf)
    meta = {"method": est.method, "channel": est.channel, "s": est.s, "field": [float(v) for v in est.field]}
    tifffile.imwrite(folder / files[1], est.psf.astype(np.float32), metadata=meta,
                     **tiff_resolution(sensor.pitch_um if sensor else None, est.s, est.channel))
    # the provenance and metrics beside the arrays, so a folder of results describes itself
    (folder / files[2]).write_text(json.dumps(estimate_json(est, sensor), allow_nan=False) + "\n")
    for key, array in est.figures.items():
        label = re.sub(r"[^A-Za-z0-9._+-]", "_", key)
        array = np.asarray(array)
        np.save(folder / f"{name}.{label}.npy", array)
        files.append(f"{name}.{label}.npy")
        if drawn and array.ndim == 2 and array.size:
            figures.save_array(array, folder / f"{name}.{label}.png", key, est)
            files.append(f"{name}.{label}.png")
    return files


def _write_figures(jobs: list[tuple[PSF, Path, float | None]]) -> None:
    """The PSF figures (estimate, path, pitch), on every usable core when there are several to share.

    Each core draws one run of them with a `psfd.figures.PSFFigures`, whose first figure of a layout costs
    three times the next ones: four figures are the fewest worth a fork.
    """
    from matplotlib.backends import backend_agg  # noqa: F401 - imported once here (0.7 s), not in every worker

    from psfd import figures

    workers = 1 if in_worker() or len(jobs) < 4 else min(usable_cores(), len(jobs) // 2)
    runs = np.array_split(np.arange(len(jobs)), workers)

    def draw(n: int) -> None:
        drawer = figures.PSFFigures()
        for i in runs[n]:
            drawer.save(*jobs[i])

    forked_map(draw, len(runs), workers)


GRID_FIGURE = "grid.png"  # `psfd.figures.grid_figure`, beside the estimates of grids of windows


def _gridded(estimates: list[PSF]) -> bool:
    """Whether some photograph, method and channel has estimates of more than one window: a grid to draw."""
    windows: dict[tuple, set] = {}
    for est in estimates:
        windows.setdefault((tuple(est.sources), est.method, est.channel), set()).add(tuple(est.window))
    return any(len(w) > 1 for w in windows.values())


def write_estimates(
    estimates: list[PSF],
    out_dir: str | os.PathLike,
    extra: dict[str, Callable[[Path], None]] | None = None,
    force: bool = False,
    inputs: Iterable[str | os.PathLike] = (),
    drawn: bool = True,
) -> list[Path]:
    """Write every estimate as .npy, 32-bit float .tif and a .png figure, plus its extra figures.

    Per estimate ``NAME`` (see `base_names`): ``NAME.npy`` (float64 kernel),
    ``NAME.tif`` (float32), ``NAME.png`` (`psfd.figures.psf_figure`), ``NAME.json``
    (the `print_json` record), and for each entry
    ``key`` of ``PSF.figures``: ``NAME.key.npy`` and, when 2-D, ``NAME.key.png``;
    ``metrics.csv``, one row per estimate (`write_csv`); and for grids of windows
    (`_gridded`) ``grid.png``, all of them where they were measured (`psfd.figures.grid_figure`).

    ``extra`` maps further file names to functions that write them at the path
    given (e.g. a comparison figure), so they join the same atomic folder
    (`write_folder`: nothing is left half-written). ``force`` and ``inputs``: as for `check_out_dir`.
    ``drawn=False`` leaves out the estimates' figures (the PNG files), the slowest part of a large grid.

    Returns
    -------
    list of Path
        The files written, in ``out_dir``.
    """

    sensors = estimate_sensors(estimates)

    def write(folder: Path) -> list[str]:
        files = []
        records = []
        jobs = []
        for name, est in zip(base_names(estimates), estimates):
            sensor = sensors.get(est.sources[0]) if est.sources else None
            files += _write_one(folder, name, est, sensor, drawn)
            records.append({**estimate_record(est, sensor), "file": f"{name}.npy"})
            if drawn:
                jobs.append((est, folder / f"{name}.png", sensor.pitch_um if sensor else None))
                files.append(f"{name}.png")
        if jobs:
            _write_figures(jobs)
        if drawn and _gridded(estimates):
            from psfd import figures

            figures.save_grid(estimates, folder / GRID_FIGURE)
            files.append(GRID_FIGURE)
        with open(folder / "metrics.csv", "w", newline="", encoding="utf-8") as stream:
            write_csv(records, stream)
        files.append("metrics.csv")
        for name, write_extra in (extra or {}).items():
            write_extra(folder / name)
            files.append(name)
        return files

    return write_folder(out_dir, write, force, inputs)


def write_report(catalogue: Any, rows: list[dict], channel: str, out: Path, note: str | None = None) -> None:
    """The field report (`psfd.figures.report_figure`) of the catalogue rows, every channel's PSFs and the
    MTF50 of ``channel``, written to ``out`` (PNG, PDF, SVG... by its suffix), with the query's ``note``."""
    from psfd import figures

    if not any(r["channel"] == channel for r in rows):
        raise NoMatchError(f"no PSF of channel {channel} to report")
    arrays = {row["id"]: catalogue.psf(row["id"])[0] for row in rows}
    sensors = catalogue_sensors(catalogue, rows)
    write_file(out, lambda path: figures.save_report(rows, arrays, channel, path, sensors, note))


# ---------------------------------------------------------------- sensors and units


def estimate_sensors(estimates: list[PSF]) -> dict[str, Any]:
    """The `source_sensor` of each estimate's first source, its EXIF read once per file (not per window)."""
    return {path: source_sensor(path) for path in {est.sources[0] for est in estimates if est.sources}}


def _frame_metadata(path: str) -> Any:
    """The `psfd.exif.FrameMetadata` of a RAW file, read once per version of the file (its sensor and settings
    go with each of its PSFs); empty for an image without EXIF."""
    try:
        stat = os.stat(path)
    except OSError:
        return _read_metadata(path, None)
    return _read_metadata(path, (stat.st_mtime_ns, stat.st_size))


@functools.lru_cache(maxsize=64)
def _read_metadata(path: str, version: tuple[int, int] | None) -> Any:
    """`_frame_metadata` of one ``version`` (modification time, size) of a file; None: no such file."""
    from psfd import exif
    from psfd.estimator.raw import RAW_SUFFIXES

    if version is not None and Path(path).suffix.lower() in RAW_SUFFIXES:  # a PGM or PNG plane carries no EXIF
        try:
            return exif.read_metadata(path)
        except (BadInputError, OSError):
            pass
    return exif.FrameMetadata()


# the settings of a frame its PSFs carry (record key: `psfd.exif.FrameMetadata` field), as catalogue rows do
SETTINGS = {"aperture": "f_number", "focal_length_mm": "focal_length_mm", "focus_distance_m": "focus_distance_m"}


def source_settings(path: str | os.PathLike) -> dict:
    """f-number, focal length and focus distance (`SETTINGS`) a frame file's EXIF records, None where it does not."""
    meta = _frame_metadata(str(path))
    return {key: getattr(meta, field) for key, field in SETTINGS.items()}


def source_sensor(path: str | os.PathLike, pitch_um: float | None = None) -> Any:
    """The `psfd.figures.Sensor` of a frame file from its EXIF (size, pitch), or None when it says neither.

    ``pitch_um`` (e.g. a plan's ``[rig] pitch_um``) stands in when the file gives no pitch.
    """
    from psfd import figures

    meta = _frame_metadata(str(path))
    pitch = meta.pixel_pitch_um or pitch_um
    if not (meta.width and meta.height):
        return figures.Sensor(0, 0, pitch) if pitch else None
    return figures.Sensor(int(meta.width), int(meta.height), pitch)


def _plan_pitch(plan_text: str | None) -> float | None:
    """A plan's ``[rig] pitch_um``, if it has one."""
    import tomllib

    try:
        value = tomllib.loads(plan_text or "").get("rig", {}).get("pitch_um")
    except tomllib.TOMLDecodeError:
        return None
    return float(value) if isinstance(value, (int, float)) and value > 0 else None


def catalogue_sensors(catalogue: Any, rows: list[dict]) -> dict[int, Any]:
    """The `psfd.figures.Sensor` of each catalogue row: its first frame's EXIF, the pitch of its run's plan
    when the EXIF has none (None when neither tells anything). Files and plans are read once each."""
    by_path: dict[str, Any] = {}
    pitches: dict[Any, float | None] = {}
    out: dict[int, Any] = {}
    for row in rows:
        run_id = row.get("run_id")
        if run_id not in pitches:
            pitches[run_id] = _plan_pitch(catalogue.run(run_id)["plan_text"]) if run_id is not None else None
        frames = catalogue.psf_frames(row["id"])
        if not frames:
            out[row["id"]] = None
            continue
        path = str(frames[0]["path"])
        key = f"{path}\0{pitches[run_id]}"
        if key not in by_path:
            by_path[key] = source_sensor(path, pitches[run_id])
        out[row["id"]] = by_path[key]
    return out


def units(record: dict, sensor: Any) -> dict:
    """``record`` with the pitch, picture height and MTF50 in lp/mm and LW/PH where the sensor tells them."""
    from psfd.estimator import mtf

    pitch = sensor.pitch_um if sensor else None
    height = sensor.height if sensor and sensor.height else None
    out = {**record, "pixel_pitch_um": pitch, "image_height_px": height}
    for axis in ("x", "y"):
        value = record.get(f"mtf50_{axis}")
        known = value is not None and math.isfinite(value)
        out[f"mtf50_{axis}_lp_mm"] = mtf.lp_per_mm(value, pitch, record["channel"]) if known and pitch else None
        out[f"mtf50_{axis}_lw_ph"] = mtf.lw_per_ph(value, height, record["channel"]) if known and height else None
    return out


def estimate_record(est: PSF, sensor: Any = None) -> dict:
    """The CSV / JSON record of one estimate: `PSF.to_json` without the array, with its first frame's
    settings (`source_settings`) and `units`; its photographs by absolute path (results outlive the
    folder a relative one was typed in)."""
    record = {k: v for k, v in est.to_json().items() if k != "psf"}
    source = record["source"]
    record["source"] = os.path.abspath(source) if isinstance(source, str) else [os.path.abspath(s) for s in source]
    settings = source_settings(est.sources[0]) if est.sources else dict.fromkeys(SETTINGS)
    return units(plain({**record, **settings}), sensor)


# ---------------------------------------------------------------- CSV

# (record key, CSV header with its unit): one row per PSF, for spreadsheets and pandas. A header, bracket
# included, is the column's name that programs read (two columns share `mtf50_x`): it never changes
# (docs/formats.md, which says which pixel each `px` counts: a channel pixel in `[cycles/px]`, a photosite
# in `image_height [px]`).
CSV_COLUMNS = (
    ("id", "id"), ("file", "file"), ("camera", "camera"), ("serial", "serial"), ("lens", "lens"),
    ("lens_serial", "lens_serial"),
    ("method", "method"), ("channel", "channel"), ("aperture", "aperture [f-number]"),
    ("focal_length_mm", "focal_length [mm]"), ("focus_distance_m", "focus_distance [m]"),
    ("field_x", "field_x [0-1 of width]"), ("field_y", "field_y [0-1 of height]"),
    ("window", "window x0 y0 x1 y1 [channel px]"), ("s", "s [samples per channel px]"),
    ("support", "support [samples]"),
    ("mtf50_x", "mtf50_x [cycles/px]"), ("mtf50_y", "mtf50_y [cycles/px]"),
    ("mtf50_x_lp_mm", "mtf50_x [lp/mm]"), ("mtf50_y_lp_mm", "mtf50_y [lp/mm]"),
    ("mtf50_x_lw_ph", "mtf50_x [LW/PH]"), ("mtf50_y_lw_ph", "mtf50_y [LW/PH]"),
    ("fwhm_x", "fwhm_x [channel px]"), ("fwhm_y", "fwhm_y [channel px]"),
    ("noise_floor", "noise_floor [L2 norm of the unit-sum kernel's error]"),
    ("residual", "residual [normalised data units, RMS]"),
    ("prediction_error", "prediction_error [cross-validated residual / noise level]"),
    ("pixel_pitch_um", "pixel_pitch [um]"), ("image_height_px", "image_height [px]"),
    ("run_id", "run_id"), ("step", "step"), ("source", "source"), ("created", "created [UTC]"),
)


def write_csv(records: list[dict], stream: TextIO) -> None:
    """One CSV row per PSF record (`estimate_record` or a catalogue row with `units`), units in the header.

    Columns a record does not have stay empty; lists are written space-separated.
    """
    import csv

    writer = csv.writer(stream, lineterminator="\n")
    writer.writerow([header for _, header in CSV_COLUMNS])
    for record in records:
        record = {**record, "source": record.get("source") or record.get("sources")}
        writer.writerow([_csv_cell(record.get(key)) for key, _ in CSV_COLUMNS])


def _csv_cell(value: Any) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, (list, tuple)):
        return " ".join(_csv_cell(v) for v in value)
    if isinstance(value, float):
        return format(value, ".6g")
    return str(value)


# ---------------------------------------------------------------- printing


def plain(value: Any) -> Any:
    """JSON-ready copy: numpy arrays and numbers to Python, NaN/inf to null (JSON has no NaN)."""
    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        # numbers with nothing to replace convert in one call (400 kernels of 17 x 17: 0.013 s, 0.11 s item by item)
        if value.dtype.kind in "biu" or (value.dtype.kind == "f" and np.isfinite(value).all()):
            return value.tolist()
        return plain(value.tolist())
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def fmt(value: float | None, spec: str = ".3f") -> str:
    """A number for a table, ``-`` when absent or not finite."""
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def estimate_json(est: PSF, sensor: Any = None) -> dict:
    """The JSON object of one estimate (docs/formats.md): `estimate_record` and the kernel as ``psf``."""
    return {**estimate_record(est, sensor), "psf": plain(est.psf)}


def print_json(estimates: list[PSF], stream: TextIO | None = None) -> None:
    """One JSON object per estimate per line (`estimate_json`)."""
    stream = sys.stdout if stream is None else stream
    sensors = estimate_sensors(estimates)
    for est in estimates:
        sensor = sensors.get(est.sources[0]) if est.sources else None
        stream.write(json.dumps(estimate_json(est, sensor), allow_nan=False) + "\n")
    stream.flush()


@contextlib.contextmanager
def progress_bar(label: str, quiet: int = 0, stream: TextIO | None = None
                 ) -> Iterator[Callable[[float], None] | None]:
    """A progress callback (fraction done, 0 to 1) drawing a tqdm bar on ``stream`` (stderr), or None.

    As `psfd run` shows its steps: a bar only on a terminal, and none with -q or when the
    output goes to a file or a pipe (a log has no use for a redrawn line). The bar is
    removed when the work ends, so the table printed next stands alone.
    """
    stream = sys.stderr if stream is None else stream
    if quiet or not (hasattr(stream, "isatty") and stream.isatty()):
        yield None
        return
    from tqdm import tqdm  # only a terminal needs it

    bar = tqdm(total=100, desc=label, file=stream, dynamic_ncols=True, leave=False,
               bar_format="{desc}: {percentage:3.0f}%|{bar}| {elapsed}<{remaining}")

    def update(fraction: float) -> None:
        bar.update(round(100.0 * min(max(fraction, 0.0), 1.0), 1) - bar.n)
        if fraction >= 1.0:
            bar.refresh()  # the end is shown even when it comes sooner than tqdm redraws

    try:
        yield update
    finally:
        bar.close()


def log_warnings(estimates: list[PSF]) -> None:
    """Each estimate's warnings on the log (stderr), named by source, channel and field: never inside a table.

    A warning that several windows of one plane share (the imaging scale of a
    whole frame, for each of its 100 windows) is logged once for the plane,
    with how many of its windows carry it: ``SOURCE CH, N of M windows: ...``.
    The same warning with other numbers (each window's noise floor) is the
    same warning: its numbers are given as ranges, with the window of the
    largest first number.
    """
    import logging

    log = logging.getLogger("psfd.estimate")
    planes: dict[tuple[str, str], list[PSF]] = {}  # in the order of the estimates
    for est in estimates:
        planes.setdefault(("+".join(Path(s).name for s in est.sources) or "estimate", est.channel), []).append(est)
    for (source, channel), group in planes.items():
        # warning with its numbers left out -> (the window, its warning) of each carrier, in order of first appearance
        carriers: dict[str, list[tuple[PSF, str]]] = {}
        for est in group:
            for warning in est.warnings:
                carriers.setdefault(_NUMBER.sub("#", warning), []).append((est, warning))
        for carried in carriers.values():
            est, warning = carried[0]
            if len(carried) == 1:
                log.warning("%s %s at (%.2f, %.2f): %s", source, channel, est.field[0], est.field[1], warning)
                continue
            where = f"{len(carried)} of {len(group)} windows"
            warning, largest = _ranged([text for _, text in carried])
            if largest is not None:
                field = carried[largest][0].field
                where += f", the largest at ({field[0]:.2f}, {field[1]:.2f})"
            log.warning("%s %s, %s: %s", source, channel, where, warning)


_NUMBER = re.compile(r"\d+(?:\.\d+)?")


def _ranged(texts: list[str]) -> tuple[str, int | None]:
    """Texts alike but for their numbers as one, each number that differs as 'LOW to HIGH'; and the index of the
    text with the largest first differing number (None when none differs)."""
    columns = list(zip(*(_NUMBER.findall(text) for text in texts)))
    spans = [(min(col, key=float), max(col, key=float)) for col in columns]
    differ = [k for k, (lo, hi) in enumerate(spans) if float(lo) != float(hi)]
    if not differ:
        return texts[0], None
    pieces = iter(f"{lo} to {hi}" if float(lo) != float(hi) else lo for lo, hi in spans)
    largest = max(range(len(texts)), key=lambda i: float(columns[differ[0]][i]))
    return _NUMBER.sub(lambda _: next(pieces), texts[0]), largest


def print_table(estimates: list[PSF], stream: TextIO | None = None) -> None:
    """A short human-readable table, one line per estimate, with its units line (warnings: `log_warnings`)."""
    stream = sys.stdout if stream is None else stream
    print(
        f"{'source':<28} {'chan':<5} {'field x,y':<11} {'MTF50 x':>8} {'MTF50 y':>8} "
        f"{'FWHM x':>7} {'FWHM y':>7} {'noise':>9} {'pred.':>5}",
        file=stream,
    )
    for est in estimates:
        m = est.metrics()
        source = "+".join(Path(s).stem for s in est.sources)
        source = source if len(source) <= 28 else source[:27] + "~"
        print(
            f"{source:<28} {est.channel:<5} {est.field[0]:.2f},{est.field[1]:.2f}  "
            f"{fmt(m['mtf50_x']):>8} {fmt(m['mtf50_y']):>8} {fmt(m['fwhm_x'], '.2f'):>7} "
            f"{fmt(m['fwhm_y'], '.2f'):>7} {fmt(est.relative_noise, '.1%'):>9} {fmt(est.prediction_error, '.2f'):>5}",
            file=stream,
        )
    print("MTF50 in cycles per channel pixel (Nyquist 0.5); FWHM in channel pixels; noise: the noise floor over the "
          "kernel's L2 norm (its relative error from sensor noise); pred.: cross-validated prediction error over the "
          "noise level (about 1 when the model holds).", file=stream)


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
    """Aligned text table of catalogue PSF rows (MTF50 in cycles per channel pixel, FWHM in channel pixels;
    MTF50 in lp/mm too when the rows carry it, `units`). Their units line is `units_line`."""
    columns = list(ROW_COLUMNS)
    # two bodies of one model, or two copies of one lens model (`--near` keeps the nearest PSF of each): the
    # serial (the lens's as its frames' EXIF records it) tells their rows apart
    for name, serial, header in (("camera", "serial", "serial"), ("lens", "lens_serial", "lens #")):
        if len({(r[name], r.get(serial)) for r in rows}) > len({r[name] for r in rows}):
            at = [column for column, _ in columns].index(name) + 1
            columns.insert(at, (header, lambda r, serial=serial: r.get(serial) or "-"))
    if _has_lp_mm(rows):
        columns.insert(-1, ("lp/mm x/y", lambda r: f"{fmt(r.get('mtf50_x_lp_mm'), '.1f')}/"
                                                  f"{fmt(r.get('mtf50_y_lp_mm'), '.1f')}"))
    if rows and "distance" in rows[0]:
        columns.append(("dist", lambda r: f"{r['distance']:.3f}"))
    cells = [[name for name, _ in columns]] + [[cell(r) for _, cell in columns] for r in rows]
    widths = [max(len(line[i]) for line in cells) for i in range(len(columns))]
    return "\n".join("  ".join(c.ljust(w) for c, w in zip(line, widths)).rstrip() for line in cells)
