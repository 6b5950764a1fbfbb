"""`psfd estimate target|pair|edges`: PSFs from photographs already on disk.

Thin: check the arguments, load the channel planes, call the estimator, write
or print. The estimators are imported inside the handlers, after the arguments
and files are checked, so that `psfd` starts quickly and a bad input is
reported before any numerical work.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from psfd.cli import output
from psfd.errors import BadInputError
from psfd.estimator import raw, target
from psfd.estimator.psf import PSF

SOLVERS = ("ls", "ls-threshold", "nnls")  # bernoulli.estimate_target's; checked here for a one-line error


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("estimate", help="estimate PSFs from photographs on disk")
    methods = parser.add_subparsers(dest="method", metavar="METHOD")
    methods.required = True

    p = methods.add_parser(
        "target",
        help="non-blind: photographs of the Bernoulli noise target",
        description="Sub-pixel PSF from one photograph of the Bernoulli target (Delbracio et al., IJCV 2012).",
    )
    p.add_argument("frames", nargs="+", metavar="FRAME", help="RAW file or single-channel PGM/PNG/TIFF")
    _common(p, s=4)
    p.add_argument("--pattern", metavar="PGM", help="noise of the printed target (default: the published one)")
    p.add_argument("--solver",
                   help="nnls (non-negative least squares, the default), ls (least squares) or "
                        "ls-threshold (least squares, negatives clipped: biased towards too wide a PSF)")
    p.add_argument("--tps", metavar="LAMBDA",
                   help="map the target with a thin-plate spline of this smoothing (the thesis uses 10) "
                        "instead of the default homography plus radial distortion")
    p.set_defaults(func=run_target)

    p = methods.add_parser(
        "pair",
        help="blind: two photographs of a textured plane at different distances",
        description=(
            "Sub-pixel PSF from a near/far pair (Delbracio et al., SIAM J. Imaging Sciences 2012; "
            "IPOL 2013). Which is near is detected."
        ),
    )
    p.add_argument("photo_a", metavar="PHOTO_A")
    p.add_argument("photo_b", metavar="PHOTO_B")
    _common(p, s=3)
    p.add_argument("--clip", action="store_true", help="set negative PSF values to 0 before normalising")
    p.set_defaults(func=run_pair)

    p = methods.add_parser(
        "edges",
        help="baseline: sharp-edge prediction (Joshi et al., CVPR 2008)",
        description="PSF from the sharp edges of a photograph (Joshi, Szeliski, Kriegman, CVPR 2008).",
    )
    p.add_argument("frames", nargs="+", metavar="FRAME")
    _common(p, s=4)
    p.add_argument("--weight", help="lambda, the kernel smoothness weight of eq. (5) (default 2, the paper's)")
    p.add_argument("--radius", help="use pixels within this many channel pixels of an edge (default: kernel radius)")
    p.add_argument("--target", action="store_true",
                   help="the frame shows the printed edge target: predict the sharp image from its geometry")
    p.set_defaults(func=run_edges)


def _common(p: argparse.ArgumentParser, s: int) -> None:
    # Checked by raw.load_frames (one-line error) rather than argparse choices (usage dump).
    p.add_argument("--channel", default="all",
                   help="r, g1, g2, b or all: Bayer plane of a RAW file (default all; "
                        "a single-channel image is its own plane)")
    p.add_argument("-s", default=str(s), help=f"super-resolution factor (default {s})")
    p.add_argument("--support", help="odd kernel side on the s-times grid, >= 3 (default 4s+1)")
    p.add_argument("--grid", default="1x1", help="NxM local windows, N across and M down (default 1x1)")
    p.add_argument("--out", metavar="DIR", help="write .npy, .tif and .png figures here")
    p.add_argument("--json", action="store_true", help="print one JSON object per estimate per line")


def _settings(args: argparse.Namespace) -> dict:
    """The options every method shares, checked; the output folder checked before any work."""
    if args.out is not None:
        output.check_out_dir(args.out)
    return {
        "s": output.parse_int(args.s, "-s", minimum=1),
        "support": output.parse_support(args.support),
        "grid": output.parse_grid(args.grid),
    }


def _optional_float(text: str | None, name: str) -> float | None:
    return None if text is None else output.parse_float(text, name)


def _load_all(paths: list[str], channel: str) -> list[raw.Frame]:
    """Every requested plane of every file; all files are read before any estimation starts."""
    return [frame for path in paths for frame in raw.load_frames(path, channel)]


def _report(args: argparse.Namespace, estimates: list[PSF]) -> int:
    if args.out is not None:
        files = output.write_estimates(estimates, args.out)
    if args.json:
        output.print_json(estimates)
    else:
        output.print_table(estimates)
        if args.out is not None:
            print(f"wrote {len(files)} files to {args.out}")
    return 0


def run_target(args: argparse.Namespace) -> int:
    settings = _settings(args)
    if args.solver is not None and args.solver not in SOLVERS:
        raise BadInputError(f"--solver: use one of {', '.join(SOLVERS)}, got {args.solver!r}")
    tps = None if args.tps is None else output.parse_float(args.tps, "--tps")
    if tps is not None and tps < 0:
        raise BadInputError(f"--tps: the smoothing must be 0 or more, got {args.tps}")
    noise = target.load_noise(args.pattern) if args.pattern else None
    frames = _load_all(args.frames, args.channel)
    from psfd.estimator import bernoulli

    if args.solver is not None:  # otherwise the estimator's default
        settings["solver"] = args.solver
    estimates = [
        psf
        for frame in frames
        for psf in bernoulli.estimate_target(frame, noise=noise, tps=tps, **settings)
    ]
    return _report(args, estimates)


def pair_planes(a: list[raw.Frame], b: list[raw.Frame]) -> list[tuple[raw.Frame, raw.Frame]]:
    """Match the planes of two photographs by channel (a lone plane on each side pairs as is)."""
    if len(a) == 1 and len(b) == 1:
        return [(a[0], b[0])]
    by_channel = {f.channel: f for f in b}
    missing = [f.channel for f in a if f.channel not in by_channel]
    if missing or len(a) != len(b):
        raise BadInputError(
            f"{Path(a[0].source).name} and {Path(b[0].source).name} do not have the same channels; "
            "give two RAW files or two single-channel images"
        )
    return [(f, by_channel[f.channel]) for f in a]


def run_pair(args: argparse.Namespace) -> int:
    settings = _settings(args)
    pairs = pair_planes(raw.load_frames(args.photo_a, args.channel), raw.load_frames(args.photo_b, args.channel))
    from psfd.estimator import twoscale

    estimates = [psf for a, b in pairs for psf in twoscale.estimate_pair(a, b, clip=args.clip, **settings)]
    return _report(args, estimates)


def run_edges(args: argparse.Namespace) -> int:
    settings = _settings(args)
    weight = _optional_float(args.weight, "--weight")
    radius = _optional_float(args.radius, "--radius")
    frames = _load_all(args.frames, args.channel)
    from psfd.estimator import sharpedge

    estimates = [
        psf
        for frame in frames
        for psf in sharpedge.estimate_edges(frame, weight=weight, radius=radius, target=args.target, **settings)
    ]
    return _report(args, estimates)
