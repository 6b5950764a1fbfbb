"""The sharp-edge PSF solve (eq. (5) of Joshi et al., CVPR 2008), in process, beside another psfd checkout's.

The normal equations are those `estimate_edges` builds on the real wall photo
(tests/data/IMG_0608_v1.pgm, blind: the whole plane and a 3 x 2 grid at
17 x 17, the whole plane at 9 x 9); each is solved for the weights 0, 2 (the
paper's) and 2e6 by this checkout's `sharpedge.solve_kernel` and by
``--reference``'s, in turn, ``--rounds`` times, so the machine's load weighs
on both alike. Printed: the median milliseconds per solve of each and the
median of the paired ratios (this checkout's over the reference's), and the
largest difference of the kernels relative to their peak.

Usage: python bench/bench_edge_solve.py --reference CHECKOUT [--rounds N]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import checkout  # noqa: E402

import numpy as np  # noqa: E402

from psfd.estimator import raw, sharpedge  # noqa: E402

PHOTO = Path(__file__).resolve().parent.parent / "tests" / "data" / "IMG_0608_v1.pgm"
RUNS = (("17 x 17", {"support": 17}), ("17 x 17, 3 x 2 grid", {"support": 17, "grid": (3, 2)}),
        ("9 x 9", {"support": 9}))
WEIGHTS = (0.0, 2.0, 2e6)


def systems(frame, kwargs) -> list[tuple]:
    """The (ata, atb, sigma, support) that `estimate_edges` hands to `solve_kernel`, one per window."""
    found, solve = [], sharpedge.solve_kernel

    def recorded(ata, atb, sigma, support, weight=sharpedge.LAMBDA):
        found.append((ata, atb, sigma, support))
        return solve(ata, atb, sigma, support, weight)

    sharpedge.solve_kernel = recorded
    try:
        sharpedge.estimate_edges(frame, **kwargs)
    finally:
        sharpedge.solve_kernel = solve
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", required=True, metavar="CHECKOUT", help="psfd checkout to compare with")
    parser.add_argument("--rounds", type=int, default=7, help="solves of each system by each, in turn")
    args = parser.parse_args()
    reference = checkout.module_of(Path(args.reference), "sharpedge")
    solvers = {"this": sharpedge.solve_kernel, "reference": reference.solve_kernel}
    frame = raw.load_frame(PHOTO, "mono")
    print(f"{'windows':>20} {'weight':>7} {'ms/solve':>9} {'reference':>10} {'ratio':>6} {'max diff':>9}")
    for label, kwargs in RUNS:
        found = systems(frame, kwargs)
        for weight in WEIGHTS:
            spent = {name: [] for name in solvers}
            diff = 0.0
            for round_ in range(args.rounds):
                order = list(solvers) if round_ % 2 == 0 else list(solvers)[::-1]
                kernels = {}
                for name in order:
                    start = time.perf_counter()
                    kernels[name] = [solvers[name](*system, weight)[0] for system in found]
                    spent[name].append((time.perf_counter() - start) / len(found))
                diff = max(diff, max(float(np.abs(a - b).max() / np.abs(b).max())
                                     for a, b in zip(kernels["this"], kernels["reference"])))
            ours, theirs = np.median(spent["this"]), np.median(spent["reference"])
            ratio = np.median(np.array(spent["this"]) / np.array(spent["reference"]))
            print(f"{label:>20} {weight:7g} {ours * 1e3:9.2f} {theirs * 1e3:10.2f} {ratio:6.3f} {diff:9.1e}")


if __name__ == "__main__":
    main()
