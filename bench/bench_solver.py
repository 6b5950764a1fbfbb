"""Solver side of the Bernoulli windows, in process, beside the same steps of another psfd checkout in the same run.

Per window of the 400-PSF frame of bench/bench_frames.py (``large``: 24 MP,
``--channel all --grid 10x10``, windows of ~500-800 observations for 289
unknowns), the CPU milliseconds of the steps after u~_D: the normal equations
(`bernoulli.normal_equations`), the LS and non-negative solve with the noise
floor's L^-1 (`bernoulli.solve`) and the four half fits of the prediction error
(`bernoulli.cross_validated`). All windows are solved on one core
(``workers=1``) by this checkout's estimator and by ``--reference``'s
bernoulli module (the rest of psfd is this checkout's), in turn, ``--rounds``
times each, so the machine's load weighs on both alike; the ratios are this
checkout's over the reference's. The last line says whether the PSFs, noise
floors, residuals and prediction errors of the two are the same bit for bit.

Usage: python bench/bench_solver.py --reference CHECKOUT [--rounds N] [--keep DIR]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_frames  # noqa: E402
import checkout  # noqa: E402

import numpy as np  # noqa: E402

from psfd.estimator import bernoulli, raw  # noqa: E402

STEPS = ("normal_equations", "solve", "cross_validated")


def timed_steps(module) -> dict[str, list[float]]:
    """Wrap the module's solver steps so that each adds its CPU seconds to a counter."""
    spent = {}
    for name in STEPS:
        step, box = getattr(module, name), [0.0]

        def wrapper(*args, _step=step, _box=box, **kwargs):
            start = time.process_time()
            try:
                return _step(*args, **kwargs)
            finally:
                _box[0] += time.process_time() - start

        setattr(module, name, wrapper)
        spent[name] = box
    return spent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", required=True, metavar="CHECKOUT", help="psfd checkout to compare with")
    parser.add_argument("--rounds", type=int, default=2, help="runs of all windows by each, in turn")
    parser.add_argument("--keep", metavar="DIR", help="write (or reuse) the frame here instead of a temporary folder")
    args = parser.parse_args()
    modules = {"this": bernoulli, "reference": checkout.module_of(Path(args.reference).resolve(), "bernoulli")}
    spent = {name: timed_steps(module) for name, module in modules.items()}
    totals = {name: {step: 0.0 for step in (*STEPS, "window")} for name in modules}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(args.keep or tmp).resolve() / "large.dng"
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.exists():
            bench_frames.make_frame(path, bench_frames.FRAMES["large"])
        frames = raw.load_frames(path, "all")
        results, windows = {}, 0
        for round_ in range(args.rounds):
            order = list(modules) if round_ % 2 == 0 else list(modules)[::-1]
            for name in order:
                for box in spent[name].values():
                    box[0] = 0.0
                start = time.process_time()
                results[name] = modules[name].estimate_frames(frames, grid=(10, 10), workers=1)
                totals[name]["window"] += time.process_time() - start
                for step, box in spent[name].items():
                    totals[name][step] += box[0]
                windows = len(results[name])
    count = windows * args.rounds
    print(f"{'step':>18} {'ms/window':>10} {'reference':>10} {'ratio':>6}")
    for step in (*STEPS, "window"):
        ours, theirs = totals["this"][step], totals["reference"][step]
        print(f"{step:>18} {ours / count * 1e3:10.2f} {theirs / count * 1e3:10.2f} {ours / theirs:6.3f}")
    same = all(np.array_equal(a.psf, b.psf) and a.noise_floor == b.noise_floor and a.residual == b.residual
               and a.prediction_error == b.prediction_error for a, b in zip(results["this"], results["reference"]))
    print(f"{windows} windows; results the same bit for bit: {same}")


if __name__ == "__main__":
    main()
