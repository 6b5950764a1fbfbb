"""Time of one PSF figure as `estimate --out` draws it, in-process, beside the whole figure drawn alone.

`psfd.figures.PSFFigures` draws the axes, ticks and labels of a layout once and
each estimate's own artists over them; this prints the CPU time per figure of
that (the first figure of the layout left out) and of `psfd.figures.save_psf`,
which draws every figure whole, measured in the same run, and their ratio.
The kernels are 17 x 17 samples at s = 4 (a window of the 400-PSF frame of
bench_frames.py): noisy Gaussians of a few widths, each with its noise floor.
CPU time, so that other processes on the machine weigh less than on a clock.

To compare two checkouts, run it from each: PYTHONPATH=CHECKOUT python bench/bench_figures.py

Usage: python bench/bench_figures.py [--figures N]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from psfd import figures
from psfd.estimator.kernels import PSF


def kernels(n: int, seed: int = 0) -> list[PSF]:
    """``n`` unit-sum noisy Gaussians, 17 x 17 at s = 4, as a grid of windows would give."""
    rng = np.random.default_rng(seed)
    r = (np.arange(17) - 8) / 4
    x, y = np.meshgrid(r, r)
    out = []
    for i in range(n):
        sx, sy = rng.uniform(0.4, 1.0, size=2)
        k = np.exp(-0.5 * (x / sx) ** 2 - 0.5 * (y / sy) ** 2)
        k = k / k.sum() + rng.normal(0.0, 2e-4, size=k.shape)
        out.append(PSF(k / k.sum(), 4, "bernoulli", "g1", ["/data/large.dng"], ((i % 10 + 0.5) / 10, 0.5),
                       (100, 50, 200, 150), noise_floor=float(rng.uniform(1e-3, 5e-3))))
    return out


def per_figure(draw, estimates: list[PSF], folder: Path) -> float:
    """Median CPU seconds of ``draw(est, path)`` over ``estimates``."""
    times = []
    for n, est in enumerate(estimates):
        start = time.process_time()
        draw(est, folder / f"{n}.png")
        times.append(time.process_time() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--figures", type=int, default=60)
    args = parser.parse_args()
    estimates = kernels(args.figures + 1)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        drawer = figures.PSFFigures()
        drawer.save(estimates[0], folder / "first.png")  # the layout's axes, once per worker, and the imports
        reused = per_figure(drawer.save, estimates[1:], folder)
        whole = per_figure(figures.save_psf, estimates[1:11], folder)
    print(f"PSF figure, median CPU per figure: {reused * 1e3:.1f} ms drawn over its layout (PSFFigures), "
          f"{whole * 1e3:.1f} ms drawn whole (save_psf): {whole / reused:.1f}x")


if __name__ == "__main__":
    main()
