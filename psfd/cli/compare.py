"""`psfd compare`: every method that applies to the photographs, side by side.

Which methods apply is read from the frames: a frame of the Bernoulli
target gives the Bernoulli estimate and the sharp-edge estimate from the
step edges of its marks; a frame of the edge target gives the sharp-edge target estimate;
two frames without a target are a near/far pair (two-photo) and each frame
also gives a blind sharp-edge estimate. The MTF profiles of all estimates
are overlaid in one figure (`psfd.figures.comparison_figure`), and a table
gives the MTF error of each against the truth (``--truth``) or against each
other (`psfd.estimator.mtf.error_table`).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any, Callable, Iterable, NamedTuple

from psfd.cli import options, summary
from psfd.errors import BadInputError, EstimationError, PsfdError
from psfd.vocabulary import BERNOULLI, CHANNELS, DEFAULT_S, MONO, SHARP_EDGE, TWO_PHOTO
from psfd.workers import ForkedWorkers, can_fork, concurrently, usable_cores


class Estimate(NamedTuple):
    """One line of the comparison: a method's PSF (`psfd.estimator.kernels.PSF`), or why it could not run.

    A named tuple rather than a dataclass: `dataclasses` would add its import time to every `psfd --help`.
    """

    label: str
    psf: Any
    reason: str = ""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "compare",
        help=summary("compare"),
        description=(
            "Bernoulli-target frames give the Bernoulli and the sharp-edge (from its marks) estimates, "
            "edge-target frames the sharp-edge target estimate, two frames of a textured plane the two-photo "
            "estimate (and sharp-edge on each). Prints a table of MTF errors against --truth (or between the methods) and, with --out, "
            "writes the overlaid MTF figure compare.png, compare.json and every estimate."
        ),
    )
    parser.add_argument("frames", nargs="+", metavar="FRAME", help="RAW file or single-channel image")
    parser.add_argument("--truth", metavar="PSF.npy",
                        help=f"true PSF (.npy) on the -s grid (without -s: s {DEFAULT_S[BERNOULLI]}, whatever "
                             "each method's own s)")
    parser.add_argument("--out", metavar="DIR", help="write compare.png, compare.json and the estimates here")
    parser.add_argument("--force", action="store_true", help="replace --out if it holds an earlier comparison")
    parser.add_argument("--pattern", metavar="PGM",
                        help="noise of the printed target, as `psfd target` saved it (default: the published one)")
    parser.add_argument("--channel", help="Bayer plane of RAW files: r, g1, g2 or b (default g1; a single-channel "
                                          "image is its own plane, mono)")
    options.add_size_options(parser, grid=False)
    parser.add_argument("--weights", default="2",
                        help="comma-separated sharp-edge regularisation weights (default 2, the paper's)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # -s given: every method and the truth on that grid; else each method's default, the truth on s = 4
    sizes = {method: options.sizes(args, method) for method in (BERNOULLI, TWO_PHOTO, SHARP_EDGE)}
    weights = [options.parse_float(w, "--weights") for w in str(args.weights).split(",") if w.strip()]
    if not weights or any(w < 0 for w in weights):
        raise BadInputError("--weights: expected non-negative numbers separated by commas")
    if args.channel is not None:  # None: each file's default plane (`psfd.estimator.raw.load_frame`)
        args.channel = options.parse_channel(args.channel, allowed=(*CHANNELS, MONO))  # G1 is g1
    inputs = [*args.frames, *(path for path in (args.truth, args.pattern) if path)]  # never deleted by --force
    if args.out is not None:
        from psfd.cli import output

        output.check_out_dir(args.out, args.force, inputs)
    from psfd.estimator import mtf, raw, target

    truth_s = sizes[BERNOULLI]["s"]
    truth = load_truth(args.truth, truth_s) if args.truth else None
    noise = target.load_noise(args.pattern) if args.pattern else None
    frames = [raw.load_frame(path, args.channel) for path in args.frames]
    estimates = run_methods(frames, sizes, weights, quiet=args.quiet, noise=noise)
    done = [e for e in estimates if e.psf is not None]
    if not done:
        reasons = "; ".join(f"{e.label}: {e.reason}" for e in estimates)
        raise EstimationError(f"no method could estimate a PSF ({reasons})")
    table = mtf.error_table({e.label: (e.psf.psf, e.psf.s) for e in done},
                            None if truth is None else (truth, truth_s))
    if args.out is not None:  # written before anything is printed: a write that fails leaves one error line only
        write_outputs(Path(args.out), done, table, truth, truth_s, force=args.force, inputs=inputs)
    print_table(estimates, table, truth is not None, truth_s=truth_s)
    if args.out is not None:
        print(f"wrote the comparison to {args.out}")
    return 0


def load_truth(path: str, s: int):
    """A true PSF from .npy: real, 2-D, odd-sized, finite, with positive mass."""
    import numpy as np

    from psfd.vocabulary import check_image_size

    if Path(path).is_dir():
        raise BadInputError(f"{path}: is a folder, not a .npy array")
    if not Path(path).is_file():  # the wording of every other file psfd reads
        raise BadInputError(f"{path}: no such file")
    try:  # mapped, not read: the header's shape is checked before anything is allocated
        psf = np.load(path, allow_pickle=False, mmap_mode="r")
    except (OSError, ValueError) as exc:
        raise BadInputError(f"{path}: not a readable .npy array ({type(exc).__name__})") from None
    shape = "a real, finite 2-D array of odd size"
    # integers or floats only: a cast from complex drops the imaginary part (with a ComplexWarning), one
    # from text parses it, from booleans gives 0 and 1
    if psf.dtype.kind not in "iuf":
        raise BadInputError(f"{path}: a PSF must be {shape} on the {s}-times grid, not of {psf.dtype} values")
    if psf.ndim == 2:
        check_image_size(psf.shape[1], psf.shape[0], path)
    psf = np.array(psf, dtype=np.float64)
    if psf.ndim != 2 or psf.shape[0] % 2 == 0 or psf.shape[1] % 2 == 0 or not np.all(np.isfinite(psf)):
        raise BadInputError(f"{path}: a PSF must be {shape} on the {s}-times grid")
    if psf.sum() <= 0:
        raise BadInputError(f"{path}: the PSF has no positive mass")
    return psf / psf.sum()


# ---------------------------------------------------------------- which methods apply


def _attempt(label: str, call: Callable[[], list]) -> list[Estimate]:
    """Run one method; a failure the photographs cause becomes a table line, not an abort."""
    try:
        return [Estimate(label, psf) for psf in call()]
    except PsfdError as exc:
        return [Estimate(label, None, str(exc))]


def _bernoulli_target(frame):
    """The Bernoulli target's detection in a frame (`psfd.estimator.detect.find_target`), or None."""
    from psfd.estimator import detect

    try:
        return detect.find_target(frame.data, frame.saturated)
    except PsfdError:
        return None


def _edge_target(frame):
    """The edge target located in a frame (`psfd.estimator.sharpedge.edge_target_in`), or None."""
    import cv2

    from psfd.estimator import sharpedge

    # the sector-based search's k-d tree draws from OpenCV's per-thread generator: each frame's search starts
    # from the state a fresh thread starts with (seed 0 stands for it), as it did when every search had a
    # fresh process or thread, so what a frame shows does not depend on the thread or process searching it
    cv2.setRNGSeed(0)
    try:
        return sharpedge.edge_target_in(frame)
    except PsfdError:
        return None


BERNOULLI_FRAME, EDGE_TARGET_FRAME, PLAIN_FRAME = "bernoulli", "edge target", "plain"
# frames searched for their targets at once while their planes together hold no more pixels than one plane of
# a 24-megapixel RAW: the Bernoulli search of such a plane alone takes 240 MB at its peak
SEARCH_TOGETHER_PIXELS = 6_000_000


class _Found(NamedTuple):
    """What a frame shows (`_search`), and where: the Bernoulli target's detection or the edge target's located
    pattern, which the frame's methods take rather than search again."""

    kind: str
    target: Any = None


def _search(frame) -> _Found:
    """What a frame shows: the Bernoulli target, the edge target, or neither (a textured plane)."""
    detection = _bernoulli_target(frame)
    if detection is not None:
        return _Found(BERNOULLI_FRAME, detection)
    pattern = _edge_target(frame)
    return _Found(PLAIN_FRAME) if pattern is None else _Found(EDGE_TARGET_FRAME, pattern)


def _size(frame) -> int:
    """Pixels of a frame's plane: the sharp-edge work, the longest of a comparison, follows them."""
    rows, cols = frame.data.shape
    return rows * cols


def run_methods(frames: list, sizes: dict[str, dict], weights: list[float], quiet: int = 1,
                noise: Any = None) -> list[Estimate]:
    """Every method that applies to the frames (see the module docstring), in a stable order.

    ``sizes`` holds each method's ``s`` and ``support`` (`psfd.cli.options.sizes`), ``noise`` the printed
    target's noise cells (`psfd.estimator.target.load_noise`; None: the published ones). What each frame
    shows (`_search`) decides its methods. The largest frame is searched and its methods run in this
    process, with a progress bar on a terminal unless ``quiet``; the other frames are searched and
    their methods and the pair's run beside it in a forked worker (`_Beside`), without one: each
    frame's methods start as soon as its own search ends (the largest frame's sharp-edge estimate,
    the longest of a comparison, no longer waits for the other frames' searches).
    """
    main = max(range(len(frames)), key=lambda i: _size(frames[i]))
    others = [i for i in range(len(frames)) if i != main]
    if not others:
        found = _search(frames[main])
        return _in_order({main: found.kind},
                         {main: _frame_methods(frames[main], found, sizes, weights, quiet, noise)})
    # the frames are searched for the targets at once, unless the searches' temporaries together would pass
    # the memory bound (some 40 bytes per pixel each): then the others wait for this frame's search
    together = sum(_size(frame) for frame in frames) <= SEARCH_TOGETHER_PIXELS
    # the searches' and the methods' modules, loaded once before the fork rather than in both processes
    from psfd.cli import output  # noqa: F401
    from psfd.estimator import detect, sharpedge, twoscale  # noqa: F401

    told = _Message(_forks())  # this frame's kind, for the worker: the pair needs it
    # the worker draws no bar: two processes redrawing one terminal line would garble it
    beside = _Beside(lambda: _beside_main(frames, main, told.receive, together, sizes, weights, noise))
    try:
        found = _search(frames[main])
        told.send(found.kind)
        kinds = {main: found.kind}
        results = {main: _frame_methods(frames[main], found, sizes, weights, quiet, noise)}
    except BaseException:
        beside.cancel()
        raise
    other_kinds, other_results = beside.result()
    kinds.update(other_kinds)
    results.update(other_results)
    return _in_order(kinds, results)


def _beside_main(frames: list, main: int, main_kind: Callable[[], str], together: bool,
                 sizes: dict[str, dict], weights: list[float], noise: Any = None
                 ) -> tuple[dict[int, str], dict[int, list]]:
    """The work beside the largest frame's (``main``): the other frames' kinds and methods, then the pair's.

    ``main_kind`` returns the largest frame's kind, waiting for it if need be. Returns the other
    frames' kinds and results by frame index; the pair's results under the index ``len(frames)``.
    """
    others = [i for i in range(len(frames)) if i != main]
    if not together:
        main_kind()  # this frame's search has ended: the memory of its temporaries is free
    searches = [lambda f=frames[i]: _search(f) for i in others]
    found = dict(zip(others, concurrently(*searches) if together else [search() for search in searches]))
    results = {i: _frame_methods(frames[i], found[i], sizes, weights, 1, noise) for i in others}
    kinds = {i: f.kind for i, f in found.items()}
    every = {**kinds, main: main_kind()}
    plain = [frames[i] for i in range(len(frames)) if every[i] == PLAIN_FRAME]
    if len(plain) == 2:
        results[len(frames)] = _pair(*plain, sizes)
    return kinds, results


def _in_order(kinds: dict[int, str], results: dict[int, list]) -> list[Estimate]:
    """The estimates in the table's order: the targets' frames' by frame, the pair's, the plain frames'."""
    frames = sorted(kinds)
    targets = [e for i in frames if kinds[i] != PLAIN_FRAME for e in results[i]]
    blind = [e for i in frames if kinds[i] == PLAIN_FRAME for e in results[i]]
    return targets + results.get(len(frames), []) + blind


def _frame_methods(frame, found: _Found, sizes: dict[str, dict], weights: list[float],
                   quiet: int, noise: Any = None) -> list[Estimate]:
    """The estimates of one frame as `_search` ``found`` it: its target's methods (the Bernoulli one with the
    printed ``noise``), or the blind sharp-edge."""
    if found.kind == BERNOULLI_FRAME:
        from psfd.estimator import bernoulli, sharpedge

        estimates = _attempt(f"bernoulli {Path(frame.source).name}",
                             lambda: bernoulli.estimate_target(frame, detection=found.target, noise=noise,
                                                               **_method_size(sizes, BERNOULLI)))
        # its marks: the noise cells are no isolated step edges
        return estimates + _edges(frame, sharpedge.bernoulli_pattern(found.target), sizes, weights, quiet)
    return _edges(frame, found.target, sizes, weights, quiet)


def _method_size(sizes: dict[str, dict], method: str) -> dict:
    return {key: sizes[method][key] for key in ("s", "support")}


def _edges(frame, pattern, sizes: dict[str, dict], weights: list[float], quiet: int) -> list[Estimate]:
    """The sharp-edge estimates of a frame, one per weight, each with its progress bar: of the target form
    when the frame shows a located ``pattern`` (`psfd.estimator.sharpedge.KnownPattern`), else blind."""
    from psfd.cli.output import progress_bar
    from psfd.estimator import sharpedge

    kind = "sharp-edge target" if pattern is not None else "sharp-edge"
    estimates = []
    for w in weights:
        label = f"{kind} w={w:g} {Path(frame.source).name}"
        with progress_bar(label, quiet) as progress:
            estimates += _attempt(label, lambda: sharpedge.estimate_edges(frame, weight=w, pattern=pattern,
                                                                          progress=progress,
                                                                          **_method_size(sizes, SHARP_EDGE)))
    return estimates


def _pair(a, b, sizes: dict[str, dict]) -> list[Estimate]:
    """The two-photo estimate of two frames without a target."""
    from psfd.estimator import twoscale

    return _attempt(f"two-photo {Path(a.source).name}+{Path(b.source).name}",
                    lambda: twoscale.estimate_pair(a, b, **_method_size(sizes, TWO_PHOTO)))


# the call of the `_Beside` being started: set in the parent, read in the forked worker
_BESIDE: Callable[[], Any] | None = None


def _run_beside() -> Any:
    return _BESIDE()


def _forks() -> bool:
    """Whether a `_Beside` call runs in a forked worker: with two cores or more, where fork exists."""
    return usable_cores() >= 2 and can_fork()


class _Beside:
    """A call run in a forked worker while this process goes on with other work.

    The frames of a comparison are independent, and so is the two-photo estimate
    of a pair (SIFT, resampling): on two cores they overlap. With one core, or
    no fork, the call runs here when its result is asked for. The worker receives
    nothing pickled (it inherits the frames by the fork) and sends back what the
    call returns, as `psfd.estimator.bernoulli` does for its windows. The call
    catches the failures the photographs cause (`_attempt`); anything else is raised here.
    """

    def __init__(self, call: Callable[[], Any]) -> None:
        global _BESIDE
        self.pool = self.pending = None
        if not _forks():
            self.call = call
            return
        _BESIDE = call
        try:
            self.pool = ForkedWorkers(1)
            self.pending = self.pool.submit(_run_beside)  # forks here
        finally:
            _BESIDE = None

    def result(self) -> Any:
        """What the call returned, waiting for the worker if it still runs (`ForkedWorkers.result`)."""
        if self.pool is None:
            return self.call()
        with self.pool:
            return self.pool.result(self.pending)

    def cancel(self) -> None:
        if self.pool is not None:
            self.pool.end()


_UNSENT = object()  # what a `_Message` holds until its value arrives


class _Message:
    """One value sent once from this process to a `_Beside` call, which may wait for it.

    In a forked worker, a pipe made before the fork: the worker closes its copy of the sending
    end before it waits, so that it ends (EOFError) rather than waits for ever if this process
    dies before it sends. Without a worker the call runs after the value was sent.
    """

    def __init__(self, forked: bool) -> None:
        self.pipe = None
        self.value: Any = _UNSENT
        if forked:
            import multiprocessing

            self.pipe = multiprocessing.get_context("fork").Pipe(duplex=False)  # (receiving, sending)

    def send(self, value: Any) -> None:
        if self.pipe is None:
            self.value = value
        else:
            self.pipe[1].send(value)
            self.pipe[1].close()

    def receive(self) -> Any:
        """The value sent, waiting for it; in the worker, the same value on every call."""
        if self.value is _UNSENT:  # only in the worker: without one the value was sent first
            if not self.pipe[1].closed:
                self.pipe[1].close()
            self.value = self.pipe[0].recv()
        return self.value


# ---------------------------------------------------------------- table, figure and files


def print_table(estimates: list[Estimate], table: dict, with_truth: bool, stream=None,
                truth_s: int | None = None) -> None:
    """The comparison table on ``stream`` (stdout); ``truth_s``: the s grid the truth was read on, said under it."""
    from psfd.cli.output import fmt
    from psfd.estimator.mtf import HIGH, LOW

    stream = sys.stdout if stream is None else stream
    width = max(len(e.label) for e in estimates) + 2
    shown = False  # whether any MTF error was printed, to explain it
    if with_truth:
        head = f"{'MTF err <=Nyq':>14} {'MTF err >Nyq':>13} {'MTF50 x':>8} {'MTF50 y':>8} {'noise':>7}"
        print(f"{'method':<{width}} {head}", file=stream)
    for e in estimates:
        if e.psf is None:
            print(f"{e.label:<{width}} skipped: {e.reason}", file=stream)
            continue
        m = e.psf.metrics()
        if with_truth:
            err = table[e.label]
            print(f"{e.label:<{width}} {fmt(err[LOW], '.4f'):>14} {fmt(err[HIGH], '.4f'):>13} "
                  f"{fmt(m['mtf50_x'], '.4f'):>8} {fmt(m['mtf50_y'], '.4f'):>8} {fmt(e.psf.relative_noise, '.1%'):>7}",
                  file=stream)
            shown = True
        else:
            print(f"{e.label}: MTF50 x {fmt(m['mtf50_x'], '.4f')} y {fmt(m['mtf50_y'], '.4f')}, "
                  f"noise {fmt(e.psf.relative_noise, '.1%')}", file=stream)
            for other, err in table[e.label].items():
                print(f"    vs {other:<{width}} MTF err <=Nyq {fmt(err[LOW], '.4f')}  >Nyq {fmt(err[HIGH], '.4f')}",
                      file=stream)
                shown = True
        for w in e.psf.warnings:  # on the log (stderr), not inside the table
            logging.getLogger("psfd.compare").warning("%s: %s", e.label, w)
    if shown:
        print("MTF error: RMS difference of the x and y MTF profiles (unitless), up to and above the Nyquist "
              "frequency, 0.5 cycles per channel pixel.", file=stream)
    if with_truth and truth_s is not None:  # without -s not every method's own s: a truth on another is misread
        print(f"truth: read on the s = {truth_s} grid (samples 1/{truth_s} channel pixel apart); -s sets it.",
              file=stream)
    if any(e.psf is not None for e in estimates):  # a noise figure was printed
        print("noise: each estimate's noise floor over its kernel's L2 norm (its relative error from sensor noise).",
              file=stream)


def write_outputs(out: Path, estimates: list[Estimate], table: dict, truth, s: int, force: bool = False,
                  inputs: Iterable[str] = ()) -> None:
    """The estimates (output.write_estimates) with compare.png and compare.json, all in one atomic folder
    (``force``, ``inputs``: `psfd.cli.output.check_out_dir`)."""
    from psfd import figures
    from psfd.cli import output

    curves = [(e.label, e.psf.psf, e.psf.s) for e in estimates]
    if truth is not None:
        curves.insert(0, ("truth", truth, s))
    summary = {
        "errors": table,
        "against": "truth" if truth is not None else "each other",
        **({"truth_s": s} if truth is not None else {}),
        "methods": {e.label: {"method": e.psf.method, "params": e.psf.params, "warnings": e.psf.warnings,
                              **e.psf.metrics()} for e in estimates},
    }
    output.write_estimates(
        [e.psf for e in estimates],
        out,
        extra={"compare.png": lambda path: figures.save_comparison(curves, path, truth is not None),
               "compare.json": lambda path: path.write_text(json.dumps(output.plain(summary), indent=1))},
        force=force,
        inputs=inputs,
    )
