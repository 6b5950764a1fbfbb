"""Accuracy of each Bernoulli solver against the independent renderer (tests/render.py), per render kind.

For every kind (Gaussian, rotated anisotropic Gaussian, diffraction at f/5.6,
f/11 and f/22 for a 2 x 4.3 um Bayer plane at 0.55 um, a defocus disc, each
with the photosite box) at supports 17 and 25, scales 0.30-0.50 pixel per
cell, rotations 0-180 degrees and a little perspective, the photograph goes
through the whole pipeline (`estimate_target`) with each solver, and, to
separate the solver from the light model, through `estimate_plane` with the
true map and the true light field. Printed per kind and solver (means over
the seeds): the max MTF error along the two axes up to s/2 cycles per pixel
and over the whole 2-D band, the mean signed MTF error where the true MTF
exceeds 0.05 (negative: too wide), the RMS width over the truth's (and that of
the core, render.core_width, blind to the outermost samples), all against
the truth on the support (render.support_truth), and the max error against
the continuous |ĥ| (what the support cannot hold added), with the noise floor,
the cross-validated prediction error and the time of each solver relative to
``ls`` in the same run.

Usage: python bench/bench_accuracy.py [--seeds 1 2 3] [--electrons 5000] [--solvers nnls]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as bench_bernoulli: time the code, not the machine's load

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import render  # noqa: E402

from psfd.estimator import bernoulli  # noqa: E402
from psfd.vocabulary import SOLVERS  # noqa: E402

S = 4
# (kind, support, pixels per cell, rotation in degrees)
CASES = [
    ("gaussian", 17, 0.30, 0.0),
    ("gaussian", 25, 0.45, 60.0),
    ("anisotropic", 17, 0.40, 35.0),
    ("anisotropic", 25, 0.33, 120.0),
    ("airy-f5.6", 17, 0.37, 100.0),
    ("airy-f5.6", 25, 0.50, 20.0),
    ("airy-f11", 17, 0.30, 45.0),
    ("airy-f11", 25, 0.45, 160.0),
    ("airy-f22", 17, 0.35, 170.0),
    ("airy-f22", 25, 0.50, 75.0),
    ("defocus", 17, 0.40, 90.0),
    ("defocus", 25, 0.33, 140.0),
]


def measure(case, seed: int, electrons: float, solvers) -> dict:
    kind, support, pixels_per_cell, rotation = case
    kernel = render.KINDS[kind]
    view = render.View(pixels_per_cell, rotation_deg=rotation, tilt=(0.04, -0.03))
    shot = render.render(kernel, view, seed=seed, exposure=render.Exposure(electrons=electrons))
    out = {}
    for solver in solvers:
        start = time.perf_counter()
        (est,) = bernoulli.estimate_target(shot.frame, solver=solver, support=support)
        seconds = time.perf_counter() - start
        (plane,) = bernoulli.estimate_plane(shot.normalised(), shot.to_pattern, s=S, support=support, solver=solver)
        out[solver] = (render.compare(est.psf, kernel, S), render.compare(plane["psf"], kernel, S), est, seconds)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--solvers", nargs="+", default=list(SOLVERS), choices=SOLVERS,
                        help="the time column is relative to ls: include it to read that column")
    parser.add_argument("--electrons", type=float, default=render.Exposure().electrons,
                        help="photoelectrons at reflectance 1 (5000: the noise of the published photograph)")
    args = parser.parse_args()
    print(f"s = {S}, {args.electrons:g} e- at reflectance 1, seeds {args.seeds}; errors against the truth on the "
          "support; 'cont.': against the continuous MTF; 'true light': true map and light field")
    head = (f"{'kind':<12}{'k':>3}{'px/cell':>8}{'rot':>5} {'solver':<13}{'max':>7}{'2-D':>7}{'signed':>8}"
            f"{'width':>7}{'core':>6}{'cont.':>7} | {'true light: max':>15}{'signed':>8}{'width':>7}{'core':>6} |"
            f"{'floor':>7}{'pred.':>6}{'time':>6}")
    print(head)
    for case in CASES:
        runs = [measure(case, seed, args.electrons, args.solvers) for seed in args.seeds]
        kind, support, ppc, rotation = case
        outside = render.KINDS[kind].outside(S, support)
        for solver in args.solvers:
            whole = [r[solver][0] for r in runs]
            true = [r[solver][1] for r in runs]
            ests = [r[solver][2] for r in runs]
            ratio = np.median([r[solver][3] / r["ls"][3] for r in runs]) if "ls" in args.solvers else np.nan

            def mean(items, name):
                return float(np.mean([getattr(e, name) for e in items]))

            print(f"{kind:<12}{support:>3}{ppc:>8.2f}{rotation:>5.0f} {solver:<13}"
                  f"{mean(whole, 'max_mtf'):>7.4f}{mean(whole, 'max_mtf_2d'):>7.4f}{mean(whole, 'mean_signed'):>+8.4f}"
                  f"{mean(whole, 'width_ratio'):>7.3f}{mean(whole, 'core_width_ratio'):>6.3f}"
                  f"{mean(whole, 'max_continuous'):>7.4f} | "
                  f"{mean(true, 'max_mtf'):>15.4f}{mean(true, 'mean_signed'):>+8.4f}{mean(true, 'width_ratio'):>7.3f}"
                  f"{mean(true, 'core_width_ratio'):>6.3f} |"
                  f"{mean(ests, 'noise_floor'):>7.4f}{mean(ests, 'prediction_error'):>6.2f}{ratio:>6.2f}")
        print(f"{'':<28}(mass beyond the support {outside:.3f}, aliasing of the point samples "
              f"{render.KINDS[kind].aliasing(S):.4f})")


if __name__ == "__main__":
    main()
