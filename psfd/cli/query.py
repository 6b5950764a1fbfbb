"""`psfd query`, `psfd export`, `psfd report`, `psfd metadata`: read PSFs back out of the catalogue.

What other tools read: ``query --json`` (one object per PSF, docs/formats.md), ``query --csv`` and
``export``'s ``metrics.csv`` (one row per PSF, units in the header), and ``metadata``: the Datasette
metadata describing the catalogue's tables and columns with their units.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from psfd.cli import options, summary
from psfd.errors import BadInputError, NoMatchError
from psfd.vocabulary import CHANNELS, METHODS, MONO

EXPORT_FORMATS = ("npy", "tiff", "json")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``query``, ``export`` and ``report`` commands."""
    filters = argparse.ArgumentParser(add_help=False)
    options.add_catalogue_option(filters)
    filters.add_argument("--camera", help="camera model (case-insensitive substring) or serial number")
    filters.add_argument("--lens", help="lens name (case-insensitive substring) or the serial number its frames "
                                        "record")
    filters.add_argument("--aperture", metavar="F",
                         help="f-number, e.g. 5.6; a camera body and lens copy not measured at it gives its nearest "
                              "measured one, shown in the f/ column and named in a note on stderr")
    filters.add_argument("--channel", help=f"Bayer channel ({', '.join(CHANNELS)}, {MONO}; any case)")
    filters.add_argument("--method", help=", ".join(METHODS[:-1]) + " or " + METHODS[-1])
    near = argparse.ArgumentParser(add_help=False)
    near.add_argument("--near", metavar="X,Y", help="normalised field location: the nearest PSF per aperture")
    near.add_argument("--limit", metavar="N", help="at most this many PSFs (default: all)")

    about = summary("query")
    query = subparsers.add_parser("query", parents=[filters, near], help=about, description=about)
    how = query.add_mutually_exclusive_group()
    how.add_argument("--json", action="store_true", help="one JSON object per line, with the PSF array")
    how.add_argument("--csv", action="store_true", help="CSV, one row per PSF, units in the header (no arrays)")
    query.set_defaults(func=run_query)

    about = summary("export")
    export = subparsers.add_parser("export", parents=[filters, near], help=about, description=about)
    export.add_argument("--format", default="npy", metavar="FORMAT", help=f"{' | '.join(EXPORT_FORMATS)} (default npy)")
    export.add_argument("--out", required=True, help="folder to create (must not exist or be empty)")
    export.add_argument("--force", action="store_true", help="replace --out if it holds an earlier export")
    export.set_defaults(func=run_export)

    about = summary("report")
    report = subparsers.add_parser("report", parents=[filters], help=about, description=about)
    report.add_argument("--out", default="report.png",
                        help="figure file: .png, or .pdf / .svg for vector output (default report.png)")
    report.set_defaults(func=run_report)

    about = summary("metadata")
    meta = subparsers.add_parser("metadata", help=about, description=about + " (datasette CATALOGUE -m FILE)")
    options.add_catalogue_option(meta)
    meta.add_argument("--out", metavar="FILE", help="write here instead of printing (e.g. metadata.json)")
    meta.set_defaults(func=run_metadata)


# -- arguments -------------------------------------------------------------------


def open_catalogue(args: argparse.Namespace):
    """The catalogue named by ``--catalogue`` (default: the user's), which must exist."""
    from psfd.catalogue import Catalogue, default_path

    return Catalogue(args.catalogue or default_path(), readonly=True)


def query_options(args: argparse.Namespace) -> dict[str, Any]:
    """Validated keyword arguments of Catalogue.query from the filter options (before any file is opened)."""
    near, limit = getattr(args, "near", None), getattr(args, "limit", None)
    return {
        "camera": args.camera,
        "lens": args.lens,
        "aperture": None if args.aperture is None else options.parse_fnumber(args.aperture),
        "channel": None if args.channel is None else options.parse_channel(args.channel, allowed=(*CHANNELS, MONO)),
        "method": None if args.method is None else options.parse_method(args.method),
        "near": None if near is None else options.parse_near(near),
        "limit": None if limit is None else options.parse_int(limit, "--limit", minimum=1),
    }


def run_filters(cat, options: dict[str, Any], nothing: str = ""):
    """Run a query (`psfd.catalogue.QueryResult`); its note (the lenses answered at their nearest aperture)
    goes to stderr.

    Raises NoMatchError (exit 1, as for every reader) when no PSF matches; ``nothing`` ends its message.
    """
    result = cat.query(**options)
    notes = [result.note] if result.note else []
    notes += partial_runs(cat, result.rows)
    result.note = "; ".join(notes) or None
    if result.note:
        print(f"psfd: note: {result.note}", file=sys.stderr)
    if not result.rows:
        filters = {key: options.get(key) for key in ("camera", "lens", "aperture", "channel", "method")}
        why = cat.why_empty(**filters)  # the first filter that leaves no PSF, and what there is
        raise NoMatchError(f"no PSF matches: {why}{nothing}" if why else f"no PSF matches the query{nothing}")
    return result


def partial_runs(cat, rows: list[dict]) -> list[str]:
    """A note per run of ``rows`` with steps not done: its PSFs are a part of the plan's (a run under way,
    stopped, killed, cancelled or failed). A run journalled ``running`` whose frame store nobody holds was
    killed: ``interrupted``, as `psfd status` says (`psfd.daemon.store.shown_state`), not ``running``."""
    from psfd.daemon.store import frames_dir_for, shown_state

    notes = []
    for run_id in sorted({row["run_id"] for row in rows if row.get("run_id") is not None}):
        summary = cat.run_summary(run_id)
        if summary["done"] < summary["total"]:
            state = shown_state(summary["state"], frames_dir_for(cat.path), cat.path)
            notes.append(f"run {run_id} is not done ({state}, {summary['done']} of {summary['total']} "
                         "steps): the PSFs of its other steps are missing")
    return notes


# -- query -------------------------------------------------------------------------


def with_units(cat, rows: list[dict]) -> list[dict]:
    """Catalogue rows with pitch, picture height and MTF50 in lp/mm and LW/PH (`psfd.cli.output.units`)."""
    from psfd.cli import output

    sensors = output.catalogue_sensors(cat, rows)
    return [output.units(row, sensors.get(row["id"])) for row in rows]


def run_query(args: argparse.Namespace) -> int:
    from psfd.cli import output

    filters = query_options(args)
    with open_catalogue(args) as cat:
        try:
            result = run_filters(cat, filters)  # none: exit 1, as grep; --json output stays empty (zero lines)
        except NoMatchError:
            if args.csv:
                output.write_csv([], sys.stdout)  # the header alone
            raise
        rows = with_units(cat, result.rows)
        if args.csv:
            output.write_csv(rows, sys.stdout)
        elif args.json:
            for row in rows:
                array, _ = cat.psf(row["id"])
                print(json.dumps(output.plain({**row, "psf": array})))
        else:
            print(output.format_rows(rows))
            print(output.units_line(rows))
    return 0


# -- export ----------------------------------------------------------------------


def _file_stem(row: dict) -> str:
    aperture = "NA" if row["aperture"] is None else format(row["aperture"], "g")
    return f"psf{row['id']:06d}_{row['channel']}_f{aperture}_{row['method']}"


def _write_psf(folder: Path, stem: str, array, meta: dict, fmt: str) -> str:
    import numpy as np

    if fmt == "npy":
        name = f"{stem}.npy"
        np.save(folder / name, array, allow_pickle=False)
    elif fmt == "tiff":
        import tifffile

        from psfd.cli import output

        name = f"{stem}.tif"
        # 32-bit float keeps ~7 significant digits, far below any PSF's noise floor.
        tifffile.imwrite(folder / name, array.astype(np.float32), description=json.dumps(meta), metadata=None,
                         **output.tiff_resolution(meta.get("pixel_pitch_um"), meta.get("s"), meta["channel"]))
    else:
        name = f"{stem}.json"
        (folder / name).write_text(json.dumps({**meta, "psf": array.tolist()}))
    return name


def run_export(args: argparse.Namespace) -> int:
    from psfd.catalogue import default_path
    from psfd.cli import output

    fmt = "tiff" if args.format.lower() in ("tif", "tiff") else args.format.lower()  # as the files are named
    if fmt not in EXPORT_FORMATS:
        raise BadInputError(f"unknown export format {args.format!r} (one of {', '.join(EXPORT_FORMATS)})")
    filters = query_options(args)
    out = Path(args.out)
    inputs = [args.catalogue or default_path()]  # never deleted by --force
    output.check_out_dir(out, args.force, inputs)
    with open_catalogue(args) as cat:
        result = run_filters(cat, filters, "; nothing exported")
        rows = with_units(cat, result.rows)

        def write(folder: Path) -> list[str]:
            index = []
            for row in rows:
                array, meta = cat.psf(row["id"])
                meta = output.plain({**row, **meta})
                index.append({"file": _write_psf(folder, _file_stem(row), array, meta, fmt), **meta})
            (folder / "index.json").write_text(json.dumps({"note": result.note, "psfs": index}, indent=1))
            with open(folder / "metrics.csv", "w", newline="", encoding="utf-8") as stream:
                output.write_csv(index, stream)
            return [entry["file"] for entry in index] + ["index.json", "metrics.csv"]

        output.write_folder(out, write, args.force, inputs)
    print(f"exported {len(result.rows)} PSF{'' if len(result.rows) == 1 else 's'} to {out}")
    return 0


# -- report ----------------------------------------------------------------------


def pick_channel(rows: list[dict], asked: str | None) -> str:
    """The channel to draw: the one asked, else g1 when present, else the first there is."""
    if asked:
        return asked
    channels = {r["channel"] for r in rows}
    return "g1" if "g1" in channels else sorted(channels)[0]


def run_report(args: argparse.Namespace) -> int:
    from psfd import figures
    from psfd.cli import output

    out = Path(args.out)
    if not figures.can_write(out):
        raise BadInputError(f"cannot write a figure named {out} (use .png, or .pdf or .svg for vector output)")
    output.check_out_file(out)  # before any work, as export and estimate check their folders
    filters = query_options(args)
    channel = filters.pop("channel")  # the report draws every channel's PSFs; --channel picks the MTF50 one
    with open_catalogue(args) as cat:
        result = run_filters(cat, filters, "; nothing to report")
        if channel and not any(r["channel"] == channel for r in result.rows):
            with_channel = {key: filters[key] for key in ("camera", "lens", "aperture", "method")}
            why = cat.why_empty(**with_channel, channel=channel) or f"no PSF of channel {channel}"
            raise NoMatchError(f"no PSF matches: {why}; nothing to report")
        output.write_report(cat, result.rows, pick_channel(result.rows, channel), out, result.note)
    print(f"report written to {out}")
    return 0


def run_metadata(args: argparse.Namespace) -> int:
    from psfd.catalogue import Catalogue, datasette_metadata, default_path

    path = Path(args.catalogue) if args.catalogue else default_path()
    if args.out is not None:
        from psfd.cli import output

        output.check_out_file(Path(args.out))
        _check_not_catalogue(Path(args.out), path)
    # only a catalogue this psfd reads is described: a mistyped path or a newer schema is an error, not metadata
    Catalogue(path, readonly=True).close()
    text = json.dumps(datasette_metadata(path.stem), indent=2) + "\n"
    if args.out is None:
        sys.stdout.write(text)
        return 0
    output.write_file(Path(args.out), lambda staging: staging.write_text(text, encoding="utf-8"))
    print(f"wrote {args.out}: datasette {path} -m {args.out}")
    return 0


def _check_not_catalogue(out: Path, catalogue: Path) -> None:
    """Refuse an ``--out`` that is the catalogue or one of SQLite's files beside it: writing the metadata
    there would replace every measurement with a page of JSON (a link to it counts: the same file)."""
    for suffix in ("", "-wal", "-shm", "-journal"):
        target = catalogue.with_name(catalogue.name + suffix)
        same = out.exists() and target.exists() and os.path.samefile(out, target)
        if same or out.absolute() == target.absolute():
            raise BadInputError(f"--out {out} would replace {target.name}, the catalogue's own file; "
                                "name another file for the metadata")
