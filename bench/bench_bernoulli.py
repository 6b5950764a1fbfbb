"""Per-window cost of the Bernoulli-target estimator, beside the whole `psfd estimate target` process.

What a user waits for is the whole process (bench/bench_frames.py and
bench/bench_commands.py time it against the published C program); the daemon
keeps psfd loaded and pays, per photograph, the steps below. For each frame
this prints both:

- ``whole s``: `psfd estimate target FRAME ...` started as a subprocess
  (start-up, imports, decoding, estimation, teardown), median of --repeat,
  and ``cpu s``, the CPU seconds of that process and its workers (on a
  machine shared with other work, the steadier of the two);
- in-process, warm (imports and BLAS loaded, one run before): ``load``
  (decoding the planes), ``detect`` (the target found once, refined per
  plane), ``prepare`` (map D, light, masks, windows), ``band`` (the pattern's
  band-limited raster, `PatternBand`), then per window the median and mean
  milliseconds of one window solved on one core (wall and CPU; `estimate_window`: the
  window's band difference, u~_D, the normal equations, the solver and the
  cross-validated prediction error), and ``windows s``: all windows solved
  as `estimate_frames` does (forked workers on every core when worth it).

Frames: the 1953 x 1301 plane the published C program was timed on (IPOL
2012: 2.1 s whole process on this kind of machine, issue 11), simulated with a
known PSF and written as a 16-bit PGM like `dcraw -4 -D` output, one PSF; and
the two 24-megapixel RGGB DNGs of bench/bench_frames.py, ``--channel all``:
the target at the advised scale (one PSF per plane, goal 2.5 s whole process)
and the target at 1.05 pixel per cell with ``--grid 10x10`` (400 PSFs, goal
5 s whole process on 2 cores, ~5 ms per window).

BLAS runs on one thread, as `estimate_frames` sets it (`bernoulli._one_blas_thread`).

Usage: python bench/bench_bernoulli.py [--repeat N] [--keep DIR] [--frames plane,advised,large]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_frames  # noqa: E402
import whole  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from psfd.estimator import bernoulli, raw, simulate, target  # noqa: E402

S, SUPPORT = 4, 17
PLANE = (1953, 1301)  # cols, rows
C_PLANE_SECONDS = bench_frames.C_PLANE_SECONDS


def make_plane(path: Path) -> None:
    """Simulate a target photo (f/5.6 diffraction) and save its g1 plane as a 16-bit PGM."""
    cols, rows = PLANE
    dng = path.with_suffix(".dng")
    simulate.simulate_target(dng, psf=simulate.diffraction_psf(5.6, s=S, support=SUPPORT), s=S,
                             pixels_per_cell=0.37, rotation_deg=3.0, sensor=(2 * rows, 2 * cols), centre=(0.5, 0.5),
                             seed=1)
    plane = raw.load_frame(dng, "g1")
    cv2.imwrite(str(path), np.clip(plane.data + 512, 0, 65535).astype(np.uint16))
    dng.unlink()


def in_process(path: Path, channel: str, grid: tuple[int, int]) -> dict:
    """Seconds of each step of `estimate_frames` on ``path``, and milliseconds per window on one core."""
    out = {}
    with bernoulli._one_blas_thread():
        start = time.perf_counter()
        frames = raw.load_frames(path, channel)
        out["load"] = time.perf_counter() - start
        start = time.perf_counter()
        detections = bernoulli._detections(frames)
        out["detect"] = time.perf_counter() - start
        noise = target.default_noise()
        start = time.perf_counter()
        planes = [bernoulli._prepare(f, d, noise, S, SUPPORT, grid, None) for f, d in detections]
        out["prepare"] = time.perf_counter() - start
        start = time.perf_counter()
        bands = {}
        for factor in sorted({p.factor for p in planes}):
            same = [p for p in planes if p.factor == factor]
            bands[factor] = bernoulli.PatternBand(noise, factor, S, [j for p in same for j in p.jacobians],
                                                  same[0].reference)
        out["band"] = time.perf_counter() - start
        # one core, window by window (the first plane's windows: the others cost the same)
        plane = planes[0]
        ms, cpu = [], []
        for k in range(len(plane.windows)):
            start, start_cpu = time.perf_counter(), time.process_time()
            bernoulli._window_result(plane, k, bands[plane.factor], "nnls")
            ms.append(1000 * (time.perf_counter() - start))
            cpu.append(1000 * (time.process_time() - start_cpu))
        out["window_ms"] = (statistics.median(ms), statistics.fmean(ms), statistics.median(cpu))
        groups = bernoulli._groups([len(p.windows) for p in planes])
        start = time.perf_counter()
        bernoulli._run_windows(planes, bands, groups, "nnls", None)
        out["windows"] = time.perf_counter() - start
        out["count"] = sum(len(group) for group in groups)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs of each whole process (median kept)")
    parser.add_argument("--keep", metavar="DIR", help="write (or reuse) the frames here instead of a temporary folder")
    parser.add_argument("--frames", default="plane,advised,large", help="which frames, comma-separated")
    args = parser.parse_args()
    wanted = args.frames.split(",")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep or tmp).resolve()
        folder.mkdir(parents=True, exist_ok=True)
        cases = []  # name, path, channel, grid, extra arguments, whole-process reference (s, label)
        if "plane" in wanted:
            path = folder / f"target_{PLANE[0]}x{PLANE[1]}.pgm"
            if not path.exists():
                make_plane(path)
            cases.append(("plane", path, "g1", (1, 1), [], (C_PLANE_SECONDS, "C program")))
        for name, frame_name, extra, goal in bench_frames.CASES:
            if name not in wanted:  # a frame's own case (the in-process steps run at the default s)
                continue
            path = folder / f"{frame_name}.dng"
            if not path.exists():
                bench_frames.make_frame(path, bench_frames.FRAMES[frame_name])
            grid = tuple(int(x) for x in extra[extra.index("--grid") + 1].split("x")) if "--grid" in extra else (1, 1)
            cases.append((name, path, "all", grid, extra, (goal, "goal")))
        env = bench_frames.checkout_env(Path(__file__).resolve().parents[1])
        print(f"{'frame':>8} {'whole s':>8} {'cpu s':>6} {'ref s':>6} {'ratio':>6} | {'load':>5} {'detect':>6} "
              f"{'prepare':>7} {'band':>5} {'ms/window':>10} {'mean':>6} {'cpu ms':>7} {'windows s':>9} {'n':>4}")
        for name, path, channel, grid, extra, (ref, label) in cases:
            in_process(path, channel, grid)  # warm-up: imports, BLAS, page cache
            steps = in_process(path, channel, grid)
            command = [sys.executable, "-m", "psfd", "estimate", "target", str(path), *extra]
            runs = [whole.run(command, env, str(folder)) for _ in range(args.repeat)]
            if any(r.code for r in runs):
                sys.exit(f"{' '.join(command)} failed:\n{next(r.error for r in runs if r.code)}")
            wall, cpu = statistics.median(r.wall for r in runs), statistics.median(r.cpu for r in runs)
            median_ms, mean_ms, cpu_ms = steps["window_ms"]
            print(f"{name:>8} {wall:8.2f} {cpu:6.2f} {ref:6.2f} {wall / ref:6.2f} | {steps['load']:5.2f} "
                  f"{steps['detect']:6.2f} {steps['prepare']:7.2f} {steps['band']:5.2f} {median_ms:10.1f} "
                  f"{mean_ms:6.1f} {cpu_ms:7.1f} {steps['windows']:9.2f} {steps['count']:4d}   ({label})")


if __name__ == "__main__":
    main()
