"""`psfd compare`: every method that applies to the photographs, side by side.

Which methods apply is read from the frames: a frame of the Bernoulli
target gives the Bernoulli estimate and the sharp-edge estimate from the
step edges of its marks; a frame of the edge target gives the sharp-edge target estimate;
two frames without a target are a near/far pair (two-photo) and each frame
also gives a blind sharp-edge estimate. The MTF profiles of all estimates
are overlaid in one figure, and a table gives the MTF error of each against
the truth (``--truth``) or against each other.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from psfd.cli import output
from psfd.errors import BadInputError, EstimationError, PsfdError
from psfd.estimator import mtf, raw
from psfd.estimator.psf import PSF

LOW, HIGH = "low", "high"  # frequency bands of the error: up to and above the channel Nyquist (0.5)
COLOURS = ((200, 90, 0), (0, 0, 210), (0, 150, 0), (160, 0, 160), (0, 140, 220), (120, 80, 40), (90, 90, 90))


@dataclass
class Estimate:
    """One line of the comparison: a method's PSF, or why it could not run."""

    label: str
    psf: PSF | None
    reason: str = ""


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "compare",
        help="run every applicable method on the same photographs and compare their MTFs",
        description=(
            "Bernoulli-target frames give the Bernoulli and the sharp-edge (from its marks) estimates, "
            "edge-target frames the sharp-edge target estimate, two frames of a textured plane the two-photo "
            "estimate (and sharp-edge on each). Prints a table of MTF errors against --truth (or between the methods) and, with --out, "
            "writes the overlaid MTF figure compare.png, compare.json and every estimate."
        ),
    )
    parser.add_argument("frames", nargs="+", metavar="FRAME", help="RAW file or single-channel image")
    parser.add_argument("--truth", metavar="PSF.npy", help="true PSF on the same s-times grid")
    parser.add_argument("--out", metavar="DIR", help="write compare.png, compare.json and the estimates here")
    parser.add_argument("-s", default="4", help="super-resolution factor of every estimate (default 4)")
    parser.add_argument("--channel", default="g1", help="Bayer plane of RAW files: r, g1, g2 or b (default g1)")
    parser.add_argument("--support", help="odd kernel side on the s-times grid (default 4s+1)")
    parser.add_argument("--weights", default="2",
                        help="comma-separated sharp-edge regularisation weights (default 2, the paper's)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    s = output.parse_int(args.s, "-s", minimum=1)
    support = output.parse_support(args.support)
    weights = [output.parse_float(w, "--weights") for w in str(args.weights).split(",") if w.strip()]
    if not weights or any(w < 0 for w in weights):
        raise BadInputError("--weights: expected non-negative numbers separated by commas")
    if args.channel not in raw.CHANNELS:
        raise BadInputError(f"--channel: use r, g1, g2 or b, got {args.channel!r}")
    if args.out is not None:
        output.check_out_dir(args.out)
    truth = load_truth(args.truth, s) if args.truth else None
    frames = [raw.load_frame(path, args.channel) for path in args.frames]
    estimates = run_methods(frames, s, support, weights)
    done = [e for e in estimates if e.psf is not None]
    if not done:
        reasons = "; ".join(f"{e.label}: {e.reason}" for e in estimates)
        raise EstimationError(f"no method could estimate a PSF ({reasons})")
    table = error_table(done, truth, s)
    print_table(estimates, table, truth is not None)
    if args.out is not None:
        write_outputs(Path(args.out), done, table, truth, s)
        print(f"wrote the comparison to {args.out}")
    return 0


def load_truth(path: str, s: int) -> np.ndarray:
    """A true PSF from .npy: 2-D, odd-sized, finite, with positive mass."""
    try:
        psf = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise BadInputError(f"{path}: not a readable .npy array ({type(exc).__name__})") from None
    if psf.ndim != 2 or psf.shape[0] % 2 == 0 or psf.shape[1] % 2 == 0 or not np.all(np.isfinite(psf)):
        raise BadInputError(f"{path}: a PSF must be a finite 2-D array of odd size on the {s}-times grid")
    if psf.sum() <= 0:
        raise BadInputError(f"{path}: the PSF has no positive mass")
    return psf / psf.sum()


# ---------------------------------------------------------------- which methods apply


def _attempt(label: str, call: Callable[[], list[PSF]]) -> list[Estimate]:
    """Run one method; a failure the photographs cause becomes a table line, not an abort."""
    try:
        return [Estimate(label, psf) for psf in call()]
    except PsfdError as exc:
        return [Estimate(label, None, str(exc))]


def _has_bernoulli(frame: raw.Frame) -> bool:
    from psfd.estimator import detect

    try:
        detect.find_target(frame.data, frame.saturated)
    except PsfdError:
        return False
    return True


def _has_edge_target(frame: raw.Frame) -> bool:
    from psfd.estimator import sharpedge

    try:
        sharpedge.locate_target(frame.data / frame.white)
    except PsfdError:
        return False
    return True


def run_methods(frames: list[raw.Frame], s: int, support: int | None, weights: list[float]) -> list[Estimate]:
    """Every method that applies to the frames (see the module docstring), in a stable order."""
    from psfd.estimator import sharpedge

    def edges(frame: raw.Frame, target: bool) -> list[Estimate]:
        kind = "sharp-edge target" if target else "sharp-edge"
        return [
            e
            for w in weights
            for e in _attempt(
                f"{kind} w={w:g} {Path(frame.source).name}",
                lambda w=w: sharpedge.estimate_edges(frame, s=s, support=support, weight=w, target=target),
            )
        ]

    out: list[Estimate] = []
    plain: list[raw.Frame] = []
    for frame in frames:
        if _has_bernoulli(frame):
            from psfd.estimator import bernoulli

            out += _attempt(f"bernoulli {Path(frame.source).name}",
                            lambda f=frame: bernoulli.estimate_target(f, s=s, support=support))
            out += edges(frame, target=True)  # its marks: the noise cells are no isolated step edges
        elif _has_edge_target(frame):
            out += edges(frame, target=True)
        else:
            plain.append(frame)
    if len(plain) == 2:
        from psfd.estimator import twoscale

        a, b = plain
        out += _attempt(f"two-photo {Path(a.source).name}+{Path(b.source).name}",
                        lambda: twoscale.estimate_pair(a, b, s=s, support=support))
    for frame in plain:
        out += edges(frame, target=False)
    return out


# ---------------------------------------------------------------- MTF errors


def mtf_errors(psf: np.ndarray, s: int, reference: np.ndarray, s_ref: int) -> dict[str, float]:
    """RMS difference of the x and y MTF profiles of two kernels, below and above the channel Nyquist.

    The bands are [0, 0.5] and (0.5, s/2] cycles per channel pixel (the
    second only exists for a sub-pixel kernel; it is the part the thesis
    shows a gradient penalty removes, Delbracio PhD thesis 2013, Fig. 1.3).
    """
    f, mx, my = mtf.profiles(psf, s)
    fr, rx, ry = mtf.profiles(reference, s_ref)
    top = min(f[-1], fr[-1])
    grid = f[f <= top]
    diff = np.concatenate([np.interp(grid, f, mx) - np.interp(grid, fr, rx),
                           np.interp(grid, f, my) - np.interp(grid, fr, ry)])
    band = np.concatenate([grid, grid])
    low = band <= 0.5
    high = ~low
    rms = lambda d: float(np.sqrt(np.mean(d * d))) if d.size else float("nan")  # noqa: E731
    return {LOW: rms(diff[low]), HIGH: rms(diff[high])}


def error_table(estimates: list[Estimate], truth: np.ndarray | None, s: int) -> dict:
    """Errors against the truth ({label: {low, high}}) or between every pair ({label: {label: {low, high}}})."""
    if truth is not None:
        return {e.label: mtf_errors(e.psf.psf, e.psf.s, truth, s) for e in estimates}
    return {
        a.label: {b.label: mtf_errors(a.psf.psf, a.psf.s, b.psf.psf, b.psf.s) for b in estimates if b is not a}
        for a in estimates
    }


def _fmt(v: float) -> str:
    return "-" if not math.isfinite(v) else f"{v:.4f}"


def print_table(estimates: list[Estimate], table: dict, with_truth: bool, stream=None) -> None:
    stream = sys.stdout if stream is None else stream
    width = max(len(e.label) for e in estimates) + 2
    shown = False  # whether any MTF error was printed, to explain it
    if with_truth:
        head = f"{'MTF err <=Nyq':>14} {'MTF err >Nyq':>13} {'MTF50 x':>8} {'MTF50 y':>8}"
        print(f"{'method':<{width}} {head}", file=stream)
    for e in estimates:
        if e.psf is None:
            print(f"{e.label:<{width}} skipped: {e.reason}", file=stream)
            continue
        m = e.psf.metrics()
        if with_truth:
            err = table[e.label]
            print(f"{e.label:<{width}} {_fmt(err[LOW]):>14} {_fmt(err[HIGH]):>13} "
                  f"{_fmt(m['mtf50_x']):>8} {_fmt(m['mtf50_y']):>8}", file=stream)
            shown = True
        else:
            print(f"{e.label}: MTF50 x {_fmt(m['mtf50_x'])} y {_fmt(m['mtf50_y'])}", file=stream)
            for other, err in table[e.label].items():
                print(f"    vs {other:<{width}} MTF err <=Nyq {_fmt(err[LOW])}  >Nyq {_fmt(err[HIGH])}", file=stream)
                shown = True
        for w in e.psf.warnings:
            print(f"    warning: {w}", file=stream)
    if shown:
        print("MTF error: RMS difference of the x and y MTF profiles, cycles per channel pixel (Nyquist 0.5).",
              file=stream)


# ---------------------------------------------------------------- figure and files

W, H = 760, 460
LEFT, TOP, RIGHT, BOTTOM = 56, 16, 250, 44


def mtf_figure(curves: list[tuple[str, np.ndarray, int]]) -> np.ndarray:
    """Overlaid MTF profiles (x solid, y dotted), one colour per curve, legend on the right (BGR uint8)."""
    img = np.full((H, W, 3), 255, np.uint8)
    x0, y0, x1, y1 = LEFT, TOP, W - RIGHT, H - BOTTOM
    fmax = max(s for _, _, s in curves) / 2.0

    def px(f, m):
        return x0 + np.asarray(f) / fmax * (x1 - x0), y1 - np.clip(m, 0, 1.05) / 1.05 * (y1 - y0)

    nx, _ = px(0.5, 0)
    cv2.line(img, (int(nx), y0), (int(nx), y1), (170, 170, 170), 1)
    cv2.putText(img, "Nyquist", (int(nx) + 4, y0 + 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (90, 90, 90), 1, cv2.LINE_AA)
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
        cv2.putText(img, label[:40], (x1 + 38, ly), cv2.FONT_HERSHEY_SIMPLEX, 0.33, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, (x0, y0), (x1, y1), (0, 0, 0), 1)
    for f in np.arange(0, fmax + 1e-9, 0.5):
        xx, _ = px(f, 0)
        cv2.putText(img, f"{f:g}", (int(xx) - 8, y1 + 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    for m in (0.0, 0.5, 1.0):
        _, yy = px(0, m)
        cv2.putText(img, f"{m:.1f}", (x0 - 34, int(yy) + 5), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "cycles / channel pixel   (x solid, y dotted)", (x0 + 60, H - 8),
                cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def _plain(value):
    """JSON-ready copy: numpy values to Python, NaN to null."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    return None if isinstance(value, float) and not math.isfinite(value) else value


def write_outputs(out: Path, estimates: list[Estimate], table: dict, truth: np.ndarray | None, s: int) -> None:
    """The estimates (output.write_estimates) with compare.png and compare.json, all in one atomic folder."""
    curves = [(e.label, e.psf.psf, e.psf.s) for e in estimates]
    if truth is not None:
        curves.insert(0, ("truth", truth, s))
    summary = {
        "errors": table,
        "against": "truth" if truth is not None else "each other",
        "methods": {e.label: {"method": e.psf.method, "params": e.psf.params, "warnings": e.psf.warnings,
                              **e.psf.metrics()} for e in estimates},
    }

    def figure(path: Path) -> None:
        if not cv2.imwrite(str(path), mtf_figure(curves)):
            raise OSError(f"cannot encode {path.name}")

    output.write_estimates(
        [e.psf for e in estimates],
        out,
        extra={"compare.png": figure,
               "compare.json": lambda path: path.write_text(json.dumps(_plain(summary), indent=1))},
    )
