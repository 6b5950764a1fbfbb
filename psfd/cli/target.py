"""`psfd target`: render a calibration target for print (Bernoulli noise, or sharp edges)."""

from __future__ import annotations

import argparse
from pathlib import Path

from psfd.cli import summary
from psfd.cli.options import parse_float, parse_int
from psfd.errors import BadInputError
from psfd.vocabulary import BERNOULLI, SHARP_EDGE


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "target",
        help=summary("target"),
        description=(
            "Render the Bernoulli noise target (published layout). The noise is saved beside the output "
            "as NAME.ORIGIN.noise.pgm (ORIGIN: seedN, published, or the --noise file's name); give it to "
            "`psfd estimate bernoulli --pattern` when photographing a print of it. Files that exist with other "
            "content are not replaced unless --force."
        ),
    )
    parser.add_argument("--out", required=True, help="output file, .pdf (vector, for print) or .png (raster)")
    parser.add_argument("--seed", help="draw a new noise realisation from this seed (default: the published noise)")
    parser.add_argument("--noise", metavar="PGM", help="use this 256x256 noise pattern instead of a seed")
    parser.add_argument("--size-mm", default="700", help="side of the printed target in mm (PDF; default 700)")
    parser.add_argument("--px-per-cell", default="8", help="pixels per noise cell (PNG; default 8)")
    parser.add_argument("--force", action="store_true", help="replace an existing target or noise file")
    parser.add_argument("--kind", default=BERNOULLI,
                        help=f"{BERNOULLI} (default) or {SHARP_EDGE} (once edges): the edge target of Joshi et al., "
                             "CVPR 2008 "
                             "(8x8 squares with disks; --size-mm is the board side, a square is 16 cells in PNG)")
    parser.set_defaults(func=run)


def parse_size(text: str) -> float:
    """``--size-mm``: checked for every format, as it sets the cell size printed in the caption and message."""
    size_mm = parse_float(text, "--size-mm")
    if size_mm <= 0:
        raise BadInputError(f"--size-mm: must be a positive number of millimetres, got {text!r}")
    return size_mm


def run(args: argparse.Namespace) -> int:
    kind = SHARP_EDGE if args.kind == "edges" else args.kind  # the word of psfd 0.1
    if kind not in (BERNOULLI, SHARP_EDGE):
        raise BadInputError(f"--kind: use {BERNOULLI} or {SHARP_EDGE}, got {args.kind!r}")
    if kind == SHARP_EDGE:
        return run_edges(args)
    size_mm = parse_size(args.size_mm)
    px_per_cell = parse_int(args.px_per_cell, "--px-per-cell", minimum=1)
    if args.noise is not None and args.seed is not None:
        raise BadInputError("give --seed or --noise, not both")
    from psfd import printing
    from psfd.estimator import target

    if args.noise is not None:
        noise = target.load_noise(args.noise)
        origin, name = f"noise {args.noise}", Path(args.noise).stem
    elif args.seed is not None:
        seed = parse_int(args.seed, "--seed", minimum=0)
        noise = target.seeded_noise(seed)
        origin, name = f"seed {seed}", f"seed{seed}"
    else:
        noise = target.default_noise()
        origin, name = "published noise", "published"
    cell_mm = size_mm / target.SIZE
    caption = (
        f"psfd Bernoulli target {size_mm:.5g} mm - {origin} - cell {cell_mm:.5g} mm - print at 100 % (no scaling)"
    )
    out, pgm = printing.write_target(args.out, noise, origin=name, size_mm=size_mm, caption=caption,
                                     px_per_cell=px_per_cell, force=args.force)
    print(f"wrote {out} ({origin}, cell {cell_mm:.5g} mm) and its noise {pgm}")
    return 0


def run_edges(args: argparse.Namespace) -> int:
    """Write the sharp-edge target (psfd.estimator.sharpedge.edge_target) as a vector PDF or a PNG."""
    if args.seed is not None or args.noise is not None:
        raise BadInputError("--seed and --noise apply to the Bernoulli target only")
    size_mm = parse_size(args.size_mm)
    px_per_cell = parse_int(args.px_per_cell, "--px-per-cell", minimum=1)
    from psfd import printing
    from psfd.estimator import sharpedge

    square_mm = size_mm / sharpedge.SQUARES[0]
    caption = f"psfd sharp-edge target - square {square_mm:.4g} mm - print at 100 % (no scaling)"
    out = printing.write_edge_target(args.out, size_mm=size_mm, caption=caption, px_per_cell=px_per_cell,
                                     force=args.force)
    print(f"wrote {out} (sharp-edge target, square {square_mm:.4g} mm)")
    return 0
