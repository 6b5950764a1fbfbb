"""Time per frame of the Bernoulli-target estimator, end to end (load + detect + estimate).

Frames of the sizes the published C implementation was timed on (IPOL 2012
demo: 328x292, 701x401 and 1953x1301 single-channel PGMs, 0.65 s, 0.9 s and
4.2 s) are simulated with a known PSF, written as 16-bit PGMs like
`dcraw -4 -D` output, and estimated with s = 4 and a 17 x 17 support.
Prints the time per frame and its ratio to the published figure (goal <= 1/3),
with the split between detection and the rest.

BLAS runs single-threaded here (set before numpy loads): the reference C code is
single-threaded, and on a shared 2-core machine OpenBLAS worker threads that
lose their core stall small factorisations (a 289 x 289 Cholesky) by 100x,
which would measure the machine's load instead of the code.

Usage: python bench/bench_bernoulli.py [--repeat N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from psfd.estimator import bernoulli, detect, raw, simulate  # noqa: E402

# (cols, rows) of the channel plane, published seconds per frame
CASES = (((328, 292), 0.65), ((701, 401), 0.9), ((1953, 1301), 4.2))


def make_frame(folder: Path, cols: int, rows: int) -> Path:
    """Simulate a target photo (f/5.6 diffraction) and save its g1 plane as a 16-bit PGM."""
    dng = folder / f"target_{cols}x{rows}.dng"
    simulate.simulate_target(
        dng,
        psf=simulate.diffraction_psf(5.6, s=4, support=17),
        pixels_per_cell=0.37,  # as the published example photo
        rotation_deg=3.0,
        sensor=(2 * rows, 2 * cols),
        centre=(0.5, 0.5),
        seed=1,
    )
    plane = raw.load_frame(dng, "g1")
    pgm = folder / f"target_{cols}x{rows}.pgm"
    cv2.imwrite(str(pgm), np.clip(plane.data + 512, 0, 65535).astype(np.uint16))
    dng.unlink()
    return pgm


def run(path: Path) -> tuple[float, float]:
    """Seconds for load + detect + estimate, and for the detection alone."""
    start = time.perf_counter()
    frame = raw.load_frame(path, "g1")
    estimates = bernoulli.estimate_target(frame, s=4, support=17)
    total = time.perf_counter() - start
    assert len(estimates) == 1
    start = time.perf_counter()
    detect.find_target(frame.data, frame.saturated)
    return total, time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs per frame; the best is kept")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        frames = [(make_frame(Path(tmp), *size), size, ref) for size, ref in CASES]
        run(frames[0][0])  # warm-up: imports, BLAS thread pool
        print(f"{'frame':>11} {'total s':>8} {'detect s':>9} {'C ref s':>8} {'ratio':>6}")
        for path, (cols, rows), ref in frames:
            best = min((run(path) for _ in range(args.repeat)), key=lambda t: t[0])
            print(f"{cols:>5}x{rows:<5} {best[0]:8.3f} {best[1]:9.3f} {ref:8.2f} {best[0] / ref:6.2f}")


if __name__ == "__main__":
    main()
