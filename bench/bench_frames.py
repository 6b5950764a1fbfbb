"""Whole-process time of `psfd estimate target` on simulated 24-megapixel RAW frames.

Two RGGB DNGs of 6000 x 4000 photosites (written into a temporary folder,
f/5.6 diffraction, 3 degrees of rotation, a little perspective and lens
distortion):

- ``advised``: the target at the advised imaging scale (0.3 channel pixel per
  cell, s/t = 1.2 at s = 4), ``--channel all``; goal <= 2.5 s;
- ``large``: the target at 1.05 pixel per cell (a 3200 x 3200 pattern raster,
  the frame of issue 11's 74 s figure), ``--channel all --grid 10x10`` (400
  PSFs); goal <= 5 s on 2 cores. At the default s = 4 that is s/t = 4.2, far
  outside the paper's [0.7, 2.0] (every window warns), so the same command is
  also timed at ``-s 2`` (s/t = 2.1, at the range's edge). Which s is more
  accurate there depends on the lens: on renders of this scale by
  tests/render.py (10 x 10 windows, medians of the RMS MTF error up to 0.5
  and up to 1 cycle per channel pixel, s = 4 against s = 2):

      diffraction f/5.6   0.0137 / 0.0148  against  0.0172 / 0.0331
      diffraction f/11    0.0215 / 0.0227  against  0.0192 / 0.0376
      Gaussian 0.45 px    0.0100 / 0.0096  against  0.0062 / 0.0091

  s = 2 holds a sharp lens's MTF less well near 1 cycle per pixel, its
  grid's Nyquist; below that it is about as good (f/5.6: median MTF50 0.753
  against 0.745 at s = 4, truth 0.778). At s = 1 the error below Nyquist is
  0.038 (f/5.6).

Each command is started as a subprocess (what a user waits for: start-up,
imports, decoding, estimation, teardown), several times; the median is
printed beside the median of a reference command run in the same session,
interleaved with it, so the machine's load weighs on both alike:
``--reference DIR`` times the same command on another checkout of psfd
(e.g. the previous commit), and without it the reference is the C program's
figure on extracted planes, 2.1 s per 1953 x 1301 plane (issue 11), times
the four Bayer planes: a figure from the issue's machine, not measured in
this run (machines of this kind differ by up to 2.6x: `whole.machine`).

The ``--out`` cases time the same commands writing their results (every PSF's
files and figure and the grid's ``grid.png``, or ``--no-figures``), as a user keeps them.

The peak resident memory of each command (median over the runs, MB) is
printed beside its time.

With ``--first-release``, the reference checkout is psfd's first release
(git 41ed5a2), whose ``large`` command issue 11 timed at 74 s on its machine,
and only the cases with a goal run. The first release's time here says how
much slower that machine was on this numerical work (it is nearly all
numerics: the pattern's band-limiting, once per window), and our times
scaled by that factor estimate them on the machine the goals were set on.

Usage: python bench/bench_frames.py [--repeat N] [--reference CHECKOUT [--first-release]] [--keep DIR]
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import whole  # noqa: E402

C_PLANE_SECONDS = 2.1  # published C program, whole process, one 1953x1301 plane on this kind of machine
FIRST_RELEASE_LARGE_SECONDS = 74.0  # the first release's `large` command on issue 11's machine
SENSOR = (4000, 6000)
FRAMES = {"advised": 0.3, "large": 1.05}  # name: channel pixels per cell
OUT = ["--out", "results", "--force"]  # in the frames' folder, replaced by each run
CASES = [  # (case, frame, extra arguments, goal in seconds or None)
    ("advised", "advised", ["--channel", "all"], 2.5),
    ("large", "large", ["--channel", "all", "--grid", "10x10"], 5.0),
    ("large -s 2", "large", ["--channel", "all", "--grid", "10x10", "-s", "2"], 5.0),
    # the same with the results written, as a user keeps them: a figure per PSF, or none
    ("advised --out", "advised", ["--channel", "all", *OUT], None),
    ("large --out", "large", ["--channel", "all", "--grid", "10x10", *OUT], None),
    ("large --no-figures", "large", ["--channel", "all", "--grid", "10x10", *OUT, "--no-figures"], None),
]


def make_frame(path: Path, pixels_per_cell: float) -> None:
    """Render a 24-megapixel target photograph with psfd's simulator (in a subprocess: its memory is freed)."""
    code = (
        "import sys; from psfd.estimator import simulate; "
        "simulate.simulate_target(sys.argv[1], psf=simulate.diffraction_psf(5.6, s=4, support=17), s=4, "
        f"pixels_per_cell={pixels_per_cell}, rotation_deg=3.0, sensor={SENSOR}, seed=1, tilt=(0.02, -0.01), "
        "distortion=0.01)"
    )
    subprocess.run([sys.executable, "-c", code, str(path)], check=True)


def timed(command: list[str], env: dict, cwd: Path, reference: bool = False) -> tuple[float, float]:
    """Wall seconds and peak resident memory (MB, the largest of the process and the workers it waited for).

    A reference checkout that fails (an older one without the case's option) gives NaN; ours stops the run.
    """
    done = whole.run(command, env, str(cwd))
    if done.code and reference:
        return math.nan, math.nan
    if done.code:
        sys.exit(f"{' '.join(command)} failed:\n{done.error}")
    return done.wall, done.peak_mib


def checkout_env(checkout: Path) -> dict:
    """The environment that makes ``python -m psfd`` run the psfd of ``checkout``.

    The commands run in the frames' folder: ``-m`` puts the working directory
    first on the module path, which from a checkout's root would shadow the
    PYTHONPATH (both commands would time the same code).
    """
    return {**os.environ, "PYTHONPATH": str(checkout.resolve())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3, help="runs of each command (median kept)")
    parser.add_argument("--reference", metavar="CHECKOUT", help="a psfd checkout to time the same commands with")
    parser.add_argument("--keep", metavar="DIR", help="write (or reuse) the frames here instead of a temporary folder")
    parser.add_argument("--first-release", action="store_true",
                        help="--reference is the first release (41ed5a2): estimate the times on issue 11's machine")
    args = parser.parse_args()
    if args.first_release and not args.reference:
        parser.error("--first-release names the --reference checkout: give --reference CHECKOUT")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep or tmp).resolve()
        folder.mkdir(parents=True, exist_ok=True)
        our_env = checkout_env(Path(__file__).resolve().parents[1])
        reference_env = checkout_env(Path(args.reference)) if args.reference else None
        print(whole.machine())
        print(f"{'case':>18} {'psfd s':>7} {'ref s':>7} {'ratio':>6} {'goal s':>7} {'psfd MB':>8} {'ref MB':>7}   reference")
        times = {}
        for name, frame_name, extra, goal in CASES:
            if args.first_release and goal is None:
                continue
            frame = folder / f"{frame_name}.dng"
            if not frame.exists():
                make_frame(frame, FRAMES[frame_name])
            command = [sys.executable, "-m", "psfd", "estimate", "target", str(frame), *extra]
            ours, theirs = [], []
            for _ in range(args.repeat):  # interleaved: both see the same load
                ours.append(timed(command, our_env, folder))
                if reference_env is not None:
                    theirs.append(timed(command, reference_env, folder, reference=True))
            mine, mine_mb = (statistics.median(run[j] for run in ours) for j in (0, 1))
            if reference_env is not None:
                ref, ref_mb = (statistics.median(run[j] for run in theirs) for j in (0, 1))
                label = f"psfd at {args.reference}"
            else:
                ref, ref_mb, label = 4 * C_PLANE_SECONDS, float("nan"), "C program, 4 planes (issue 11)"
            goal_text = "-" if goal is None else f"{goal:.1f}"
            print(f"{name:>18} {mine:7.2f} {ref:7.2f} {mine / ref:6.2f} {goal_text:>7} {mine_mb:8.0f} {ref_mb:7.0f}   "
                  f"{label}")
            times[name] = (mine, ref, goal)
        if args.first_release:
            print_first_release(times)


def print_first_release(times: dict[str, tuple[float, float, float]]) -> None:
    """Our times scaled to issue 11's machine by the first release's `large` command, timed on both."""
    factor = FIRST_RELEASE_LARGE_SECONDS / times["large"][1]
    print(f"first release, large: {times['large'][1]:.1f} s here, {FIRST_RELEASE_LARGE_SECONDS:.0f} s on issue 11's "
          f"machine: that machine {factor:.2f}x this one's time")
    for name, (mine, _, goal) in times.items():
        print(f"{name:>18} there (est.) {mine * factor:6.2f} s   goal {goal:.1f} s")


if __name__ == "__main__":
    main()
