"""`psfd estimate bernoulli|two-photo|sharp-edge`: PSFs from photographs already on disk.

Thin: check the arguments, load the channel planes, call the estimator, write
or print. Every argument and the output folder are checked before any file is
read; the estimators are imported inside the handlers. The command words of
psfd 0.1 (``target``, ``pair``, ``edges``) stay as aliases.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import threading
from pathlib import Path

from psfd.cli import options, summary
from psfd.errors import BadInputError, EstimationError
from psfd.vocabulary import (ALIASES, BERNOULLI, CHANNELS, DEFAULT_SOLVER, MONO, SHARP_EDGE, SOLVERS, TWO_PHOTO,
                             check_solver)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("estimate", help=summary("estimate"))
    commands = parser.add_subparsers(dest="method", metavar="METHOD")
    commands.required = True
    aliases = {method: [word for word, name in ALIASES.items() if name == method] for method in ALIASES.values()}

    p = commands.add_parser(
        BERNOULLI, aliases=aliases[BERNOULLI],
        help="non-blind: photographs of the Bernoulli noise target",
        description="Sub-pixel PSF from one photograph of the Bernoulli target (Delbracio et al., IJCV 2012).",
    )
    p.add_argument("frames", nargs="+", metavar="FRAME", help="RAW file or single-channel PGM/PNG/TIFF")
    _common(p, BERNOULLI)
    p.add_argument("--pattern", metavar="PGM", help="noise of the printed target (default: the published one)")
    p.add_argument("--solver", default=DEFAULT_SOLVER,
                   help=f"{', '.join(SOLVERS)}: least squares; least squares with negatives clipped "
                        f"(biased: too wide a PSF); non-negative least squares (default {DEFAULT_SOLVER})")
    p.add_argument("--tps", metavar="LAMBDA",
                   help="map the target with a thin-plate spline of this smoothing (the thesis uses 10) "
                        "instead of the default homography plus radial distortion")
    p.set_defaults(func=run_bernoulli)

    p = commands.add_parser(
        TWO_PHOTO, aliases=aliases[TWO_PHOTO],
        help="blind: two photographs of a textured plane at different distances",
        description=(
            "Sub-pixel PSF from a near/far pair (Delbracio et al., SIAM J. Imaging Sciences 2012; "
            "IPOL 2013). Which is near is detected from the scale between them: the photos may come in "
            "either order, for one PSF, and the output names the near one first."
        ),
    )
    p.add_argument("photo_a", metavar="PHOTO_A", help="one photo of the pair, near or far")
    p.add_argument("photo_b", metavar="PHOTO_B", help="the other photo")
    _common(p, TWO_PHOTO)
    p.add_argument("--clip", action="store_true", help="set negative PSF values to 0 before normalising")
    p.set_defaults(func=run_two_photo)

    p = commands.add_parser(
        SHARP_EDGE, aliases=aliases[SHARP_EDGE],
        help="baseline: sharp-edge prediction (Joshi et al., CVPR 2008)",
        description="PSF from the sharp edges of a photograph (Joshi, Szeliski, Kriegman, CVPR 2008).",
    )
    p.add_argument("frames", nargs="+", metavar="FRAME")
    _common(p, SHARP_EDGE)
    p.add_argument("--weight", help="lambda, the kernel smoothness weight of eq. (5) (default 2, the paper's)")
    p.add_argument("--radius", help="use pixels within this many channel pixels of an edge (default: kernel radius)")
    p.add_argument("--target", action="store_true",
                   help="the frame shows the printed edge target: predict the sharp image from its geometry")
    p.set_defaults(func=run_sharp_edge)


def _common(p: argparse.ArgumentParser, method: str) -> None:
    # Checked by raw.load_frames (one-line error) rather than argparse choices (usage dump).
    p.add_argument("--channel", default="all",
                   help="r, g1, g2, b or all: Bayer plane of a RAW file (default all; "
                        "a single-channel image is its own plane)")
    options.add_size_options(p, method)
    p.add_argument("--out", metavar="DIR", help="write .npy, .tif, .json, .png figures and metrics.csv here")
    p.add_argument("--force", action="store_true", help="replace --out if it holds earlier results")
    p.add_argument("--no-figures", action="store_true",
                   help="write the PSF files and metrics.csv in --out without the .png figures, which take most "
                        "of the time of a large --grid")
    p.add_argument("--json", action="store_true", help="print one JSON object per estimate per line")


def _settings(args: argparse.Namespace, method: str) -> dict:
    """The options every method shares, checked; the output folder checked before any work."""
    settings = options.sizes(args, method)
    if args.channel != "all":  # G1 is g1, as for every command (`options.parse_channel`)
        args.channel = options.parse_channel(args.channel, allowed=(*CHANNELS, MONO, "all"))
    if args.no_figures and args.out is None:
        raise BadInputError("--no-figures leaves figures out of --out: give --out DIR too")
    if args.out is not None:
        from psfd.cli import output

        output.check_out_dir(args.out, args.force, _inputs(args))
    return settings


def _inputs(args: argparse.Namespace) -> list[str]:
    """The files the command reads, which ``--force`` must never delete with the folder it replaces."""
    named = [getattr(args, name, None) for name in ("photo_a", "photo_b", "pattern")]
    return [*getattr(args, "frames", []), *(path for path in named if path is not None)]


def _load_all(paths: list[str], channel: str) -> list:
    """Every requested plane of every file; all files are read before any estimation starts."""
    from psfd.estimator import raw

    return [frame for path in paths for frame in raw.load_frames(path, channel)]


def _load_searched(paths: list[str], channel: str) -> tuple[list, list | None]:
    """`_load_all`, and per plane the target found on it aside, the error of that search, or None: the
    ``detections`` of `bernoulli.estimate_frames`.

    `estimate_frames` searches the target once per photograph, on the first plane `raw.load_frames` builds
    (g1 when there), and refines it on the others. That search (0.2-0.5 s on a 24-megapixel RAW, much of it
    page faults of fresh buffers) needs that plane only, so here it runs on a second thread while the
    file's other planes, and the next files, are decoded. It is the call `estimate_frames` would make on
    the same plane, so the PSFs are the same. A search that finds no target passes its error on, which
    `estimate_frames` raises, naming the plane, without searching again (a search of a plane without a
    target costs as much as one that finds it, or more).
    """
    from concurrent.futures import Future, ThreadPoolExecutor

    from psfd.workers import usable_cores

    if usable_cores() < 2:  # nothing to overlap with: `estimate_frames` searches as it always does
        return _load_all(paths, channel), None
    searches: dict[int, Future] = {}  # id of a file's first plane -> the search on it
    sources: set[str] = set()  # a file named twice is searched once, as `estimate_frames` does

    def built(frame) -> None:
        if frame.source not in sources:
            sources.add(frame.source)
            searches[id(frame)] = aside.submit(_search_quietly, frame)

    with ThreadPoolExecutor(1, thread_name_prefix="search") as aside:
        try:
            from psfd.estimator import raw

            frames = [frame for path in paths for frame in raw.load_frames(path, channel, built)]
        except BaseException:
            aside.shutdown(cancel_futures=True)  # the error is raised once a running search has ended
            raise
        found = {key: search.result() for key, search in searches.items()}
    return frames, [found.get(id(frame)) for frame in frames]


def _search_quietly(frame):
    """`detect.find_target` on a plane (`_load_searched`): its detection, the error that says why it found
    none (`estimate_frames` raises it, naming the plane, without searching again), or None where it failed
    otherwise (searched again there, to raise the same error in its place)."""
    from psfd.errors import EstimationError
    from psfd.estimator import detect

    try:
        return detect.find_target(frame.data, frame.saturated)
    except EstimationError as exc:
        return exc
    except Exception:
        return None


def _import_aside(module: str) -> threading.Thread:
    """Start importing ``module`` on a second thread, to overlap with the decoding of the frames.

    LibRaw's decoding and numpy's plane conversion release the interpreter
    lock for much of their time, and the import runs meanwhile (0.1-0.3 s
    saved on a 24-megapixel RAW, measured in-process). An error is left for
    the caller's own import statement to raise (a failed import leaves no module behind).
    """

    def run() -> None:
        with contextlib.suppress(Exception):
            importlib.import_module(module)

    thread = threading.Thread(target=run, name=f"import {module}", daemon=True)
    thread.start()
    return thread


def _report(args: argparse.Namespace, estimates: list) -> int:
    from psfd.cli import output

    if args.out is not None:
        files = output.write_estimates(estimates, args.out, force=args.force, inputs=_inputs(args),
                                       drawn=not args.no_figures)
    output.log_warnings(estimates)
    if args.json:
        output.print_json(estimates)
    else:
        output.print_table(estimates)
        if args.out is not None:
            print(f"wrote {len(files)} files to {args.out}")
    return 0


def run_bernoulli(args: argparse.Namespace) -> int:
    settings = _settings(args, BERNOULLI)
    check_solver(args.solver, "--solver")
    tps = None if args.tps is None else options.parse_float(args.tps, "--tps")
    if tps is not None and tps < 0:
        raise BadInputError(f"--tps: the smoothing must be 0 or more, got {args.tps}")
    from psfd.estimator import target

    noise = target.load_noise(args.pattern) if args.pattern else None
    importing = _import_aside("psfd.estimator.bernoulli")
    try:
        frames, detections = _load_searched(args.frames, args.channel)
    finally:  # also on a bad frame: no import left running while the interpreter shuts down
        importing.join()
    from psfd.estimator import bernoulli

    # all planes at once: the target is searched once per file and the windows share the cores
    estimates = bernoulli.estimate_frames(frames, noise=noise, solver=args.solver, tps=tps, detections=detections,
                                          **settings)
    return _report(args, estimates)


def pair_planes(a: list, b: list) -> list[tuple]:
    """Match the planes (`psfd.estimator.raw.Frame`) of two photographs by channel (a lone plane on each
    side pairs as is)."""
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


def run_two_photo(args: argparse.Namespace) -> int:
    settings = _settings(args, TWO_PHOTO)
    pairs = pair_planes(_load_all([args.photo_a], args.channel), _load_all([args.photo_b], args.channel))
    from psfd.estimator import twoscale

    estimates = [psf for a, b in pairs for psf in twoscale.estimate_pair(a, b, clip=args.clip, **settings)]
    return _report(args, estimates)


def run_sharp_edge(args: argparse.Namespace) -> int:
    settings = _settings(args, SHARP_EDGE)
    weight = None if args.weight is None else options.parse_float(args.weight, "--weight")
    radius = None if args.radius is None else options.parse_float(args.radius, "--radius")
    if weight is not None and weight < 0:
        raise BadInputError(f"--weight: expected a number >= 0, got {args.weight}")
    if radius is not None and radius <= 0:
        raise BadInputError(f"--radius: expected a positive number of channel pixels, got {args.radius}")
    frames = _load_all(args.frames, args.channel)
    from psfd.cli import output
    from psfd.estimator import sharpedge

    estimates = []
    for frame in frames:  # seconds per megapixel: a bar on a terminal
        try:
            with output.progress_bar(f"{Path(frame.source).name} {frame.channel}", args.quiet) as progress:
                estimates += sharpedge.estimate_edges(frame, weight=weight, radius=radius, target_form=args.target,
                                                      progress=progress, **settings)
        except EstimationError as exc:  # of several frames, name the one (as the Bernoulli estimator does)
            raise type(exc)(f"{frame.source} ({frame.channel}): {exc}") from None
    return _report(args, estimates)
