"""Whole `psfd ...` processes, as a user times them, beside a reference measured in the same run.

Each case starts the command as a subprocess (median of --runs, after one
uncounted round), alternating with its reference, and prints both medians,
their peak memory and the median of the pairwise ratios (bench/whole.py).

The reference of a case, first that applies:
  --before DIR       the same command run from another psfd source tree
                     (e.g. `git worktree add /tmp/before main`): before/after;
  --reference K=CMD  a reference program for cases of kind K (target, pair,
                     edges), e.g. a build of the published C implementation:
                     CMD is split like a shell line, with {frame}, {near},
                     {far}, {pattern} and {out} replaced;
  otherwise          a baseline process: Python reading the same file with
                     OpenCV and taking one numpy FFT of it, the least any
                     Python tool does on that input (for the start-up cases,
                     the bare interpreter).

Also printed: the published C implementations' whole-process times on this
kind of machine (2 cores; issue figures: 0.71 s for 328x292, 1.07 s for
701x401, 2.1 s for 1953x1301, 3.7 s for the pair), and our time over them.
Those were not measured in this run, and machines of this kind differ by up
to 2.6x. With --first-release, --before DIR is psfd's first release (git
41ed5a2), which those figures timed beside C on their machine (psfd over C:
2.0-2.7, 2.0, 1.1, 0.8): this run's ratio to it times that one estimates the
ratio to C on this machine ("/C est."), the speeds of both programs assumed
to scale alike from one machine to another. That over-states it where the
first release's start-up (half its time, imports) was slower there than its
numerics: `bench_frames.py --first-release` times the first release's
74-second 24 MP command here, whose ratio F (1.27 on a quiet 2-core Xeon)
is how much slower the issue's machine was on numerical work, which is
nearly all of a C program's time; --machine-factor F prints our time times
F over the published figure ("F/pub"): our ratio to C on that machine.

Frames: the real example photo (328 x 292) and the real wall pair
(tests/data), the 701 x 401 and 1953 x 1301 target planes simulated with a
known PSF and written as 16-bit PGMs like `dcraw -4 -D` output, and with
--raw24 a simulated 24-megapixel RGGB DNG of the target (`--channel all`) and one of
the real wall photo in every Bayer plane (sharp edges and compare: time and peak memory).

Compile the trees timed first (`python -m compileall psfd`): an installed
package has its bytecode, and without it every run would compile the
modules it loads; a tree with missing or stale bytecode is named on stderr.

Usage: python bench/bench_commands.py [--runs N] [--warmup N] [--cases a,b] [--before DIR [--first-release]]
       [--machine-factor F] [--reference K=CMD] [--raw24]
"""

from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import whole  # noqa: E402

TREE = Path(__file__).resolve().parent.parent
DATA = TREE / "tests" / "data"
EXAMPLE = DATA / "img_example.pgm"
NEAR, FAR = DATA / "IMG_0608_v1.pgm", DATA / "IMG_0602_v1_CUT.pgm"
PSFD = [sys.executable, "-m", "psfd"]
# psfd's first release over the published C program, whole processes timed on one machine (issue figures;
# the 328x292 photo: 2.1-3.1 s against 0.71-1.2 s, the middle of their 2.0-2.7)
FIRST_OVER_C = {"target 328x292 (real)": 2.35, "target 701x401 (sim.)": 2.0, "target 1953x1301 (sim.)": 1.1,
                "pair s=3 (real)": 0.8}
# a Python process that reads the input and takes one FFT of it: the floor of any Python tool
BASELINE = ("import sys, numpy, cv2\n"
            "for p in sys.argv[1:]:\n"
            "    a = cv2.imread(p, cv2.IMREAD_UNCHANGED).astype(numpy.float64)\n"
            "    numpy.fft.rfft2(a)\n")
BASELINE_RAW = ("import sys, numpy, rawpy\n"
                "with rawpy.imread(sys.argv[1]) as r:\n"
                "    mosaic = r.raw_image_visible.astype(numpy.float64)\n"
                "for dy in (0, 1):\n"
                "    for dx in (0, 1):\n"
                "        numpy.fft.rfft2(mosaic[dy::2, dx::2])\n")


def simulated_plane(folder: Path, cols: int, rows: int) -> Path:
    """A target photo (f/5.6 diffraction, 0.37 px per cell as the example photo), its g1 plane as a 16-bit PGM."""
    import cv2
    import numpy as np

    from psfd.estimator import raw, simulate

    dng = folder / f"target_{cols}x{rows}.dng"
    simulate.simulate_target(dng, psf=simulate.diffraction_psf(5.6, s=4, support=17), pixels_per_cell=0.37,
                             rotation_deg=3.0, sensor=(2 * rows, 2 * cols), centre=(0.5, 0.5), seed=1)
    plane = raw.load_frame(dng, "g1")
    pgm = folder / f"target_{cols}x{rows}.pgm"
    cv2.imwrite(str(pgm), np.clip(plane.data + 512, 0, 65535).astype(np.uint16))
    dng.unlink()
    return pgm


def simulated_raw24(folder: Path) -> Path:
    """A 6000 x 4000 RGGB DNG of the target at the advised scale."""
    from psfd.estimator import simulate

    dng = folder / "target_24mp.dng"
    simulate.simulate_target(dng, psf=simulate.diffraction_psf(5.6, s=4, support=17), pixels_per_cell=0.25,
                             rotation_deg=3.0, sensor=(4000, 6000), centre=(0.5, 0.5), seed=2)
    return dng


def wall_raw24(folder: Path) -> Path:
    """A 6000 x 4000 RGGB DNG whose four planes are the real wall photo (`scenes.wall_raw24` of tests/, the
    frame of the slow memory test): the sharp-edge cases' 24-megapixel frame."""
    sys.path.insert(0, str(TREE / "tests"))
    import scenes

    return scenes.wall_raw24(folder / "wall_24mp.dng")


def make(function: str, folder: Path, *args: int) -> Path:
    """Run one of the frame makers above in a child process and return the file it wrote.

    The parent stays small: a child's peak memory as the kernel reports it
    cannot read below the size of the process it was started from.
    """
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).resolve().parent)!r}); import bench_commands; "
            f"from pathlib import Path; print(bench_commands.{function}(Path({str(folder)!r}), *{args!r}))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return Path(done.stdout.strip().splitlines()[-1])


def cases(folder: Path, raw24: bool) -> list[tuple[str, str, list[str], dict[str, str], float | None]]:
    """(name, kind, psfd arguments, placeholders, published C seconds)."""
    out = [
        ("psfd --version", "start", ["--version"], {}, None),
        ("psfd --help", "start", ["--help"], {}, None),
        ("target 328x292 (real)", "target", ["estimate", "target", str(EXAMPLE)], {"frame": str(EXAMPLE)}, 0.71),
    ]
    for (cols, rows), published in (((701, 401), 1.07), ((1953, 1301), 2.1)):
        pgm = make("simulated_plane", folder, cols, rows)
        out.append((f"target {cols}x{rows} (sim.)", "target", ["estimate", "target", str(pgm)], {"frame": str(pgm)},
                    published))
    pair = {"near": str(NEAR), "far": str(FAR), "frame": str(NEAR)}
    out += [
        ("pair s=3 (real)", "pair", ["estimate", "pair", str(FAR), str(NEAR), "-s", "3"], pair, 3.7),
        ("edges 1953x1301 (real)", "edges", ["estimate", "edges", str(NEAR)], {"frame": str(NEAR)}, None),
        ("compare pair (real)", "compare", ["compare", str(FAR), str(NEAR)], pair, None),
    ]
    if raw24:
        dng = make("simulated_raw24", folder)
        out.append(("target 24 MP RAW, all", "raw", ["estimate", "target", str(dng), "--channel", "all"],
                    {"frame": str(dng)}, None))
        wall = make("wall_raw24", folder)
        out += [
            ("edges 24 MP RAW, g1", "raw", ["estimate", "edges", str(wall), "--channel", "g1"], {"frame": str(wall)},
             None),
            ("edges 24 MP RAW, all", "raw", ["estimate", "edges", str(wall)], {"frame": str(wall)}, None),
            ("compare 24 MP RAW", "raw", ["compare", str(wall)], {"frame": str(wall)}, None),
        ]
    return out


def reference(kind: str, args: list[str], fields: dict[str, str], options, out_dir: Path
              ) -> tuple[list[str], dict[str, str] | None, str]:
    """The reference command of a case, its environment and its label."""
    if options.before:
        env = dict(os.environ, PYTHONPATH=str(Path(options.before).resolve()))
        return PSFD + args, env, "before"
    if kind in options.reference:
        line = options.reference[kind].format(out=str(out_dir / "ref"), pattern=options.pattern, **fields)
        return shlex.split(line), None, "reference"
    if kind == "start":
        return [sys.executable, "-c", "pass"], None, "python"
    if kind == "raw":
        return [sys.executable, "-c", BASELINE_RAW, fields["frame"]], None, "baseline"
    files = [fields["near"], fields["far"]] if "near" in fields else [fields["frame"]]
    return [sys.executable, "-c", BASELINE] + files, None, "baseline"


def stale_bytecode(tree: Path) -> list[str]:
    """The modules of ``tree``/psfd whose bytecode is missing or older than their source.

    Python recompiles those in every run it cannot write the cache of, and
    otherwise in the first (warm-up) run only: 0.1-0.5 s a run, which a
    timing of start-up must not include. Timestamp-based .pyc files record
    the source's modification time and size (PEP 552).
    """
    import importlib.util

    stale = []
    for source in sorted((tree / "psfd").rglob("*.py")):
        cached = Path(importlib.util.cache_from_source(str(source)))
        try:
            header = cached.read_bytes()[:16]
        except OSError:
            stale.append(f"{source.relative_to(tree)} (no bytecode)")
            continue
        flags = int.from_bytes(header[4:8], "little")
        info = source.stat()
        if flags == 0 and (int.from_bytes(header[8:12], "little") != int(info.st_mtime) & 0xFFFFFFFF
                           or int.from_bytes(header[12:16], "little") != info.st_size & 0xFFFFFFFF):
            stale.append(f"{source.relative_to(tree)} (bytecode older than the source)")
    return stale


def warn_stale(tree: Path) -> None:
    stale = stale_bytecode(tree)
    if stale:
        shown = ", ".join(stale[:5]) + (f" and {len(stale) - 5} more" if len(stale) > 5 else "")
        print(f"warning: {tree}: {len(stale)} modules would be compiled while timed: {shown}; "
              f"run `{Path(sys.executable).name} -m compileall -q {tree / 'psfd'}` first", file=sys.stderr, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="timed runs of each command (default 5)")
    parser.add_argument("--warmup", type=int, default=1, help="uncounted rounds first (default 1)")
    parser.add_argument("--cases", help="comma-separated substrings of the case names to run")
    parser.add_argument("--before", metavar="DIR", help="psfd source tree whose commands are the reference")
    parser.add_argument("--reference", action="append", default=[], metavar="KIND=CMD",
                        help="reference program for target, pair or edges cases")
    parser.add_argument("--pattern", default="", help="noise pattern file for a reference's {pattern}")
    parser.add_argument("--first-release", action="store_true",
                        help="--before DIR is the first release (41ed5a2): estimate the ratio to C on this machine")
    parser.add_argument("--machine-factor", type=float, metavar="F",
                        help="the issue's machine over this one on numerics (bench_frames.py --first-release)")
    parser.add_argument("--raw24", action="store_true", help="also a simulated 24-megapixel RAW (slow to make)")
    options = parser.parse_args()
    options.reference = dict(item.split("=", 1) for item in options.reference)
    if options.first_release and not options.before:
        parser.error("--first-release names the --before tree: give --before DIR")
    print(whole.machine())
    for tree in [TREE] + ([Path(options.before).resolve()] if options.before else []):
        warn_stale(tree)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        print(f"{'case':<24} {'psfd s':>7} {'MiB':>6} {'ref s':>7} {'MiB':>6} {'ratio':>6}  {'reference':<9}"
              f" {'C pub. s':>8} {'/pub':>5}" + (f" {'/C est.':>7}" if options.first_release else "")
              + (f" {'F/pub':>5}" if options.machine_factor else ""))
        for name, kind, args, fields, published in cases(folder, options.raw24):
            if options.cases and not any(c in name for c in options.cases.split(",")):
                continue
            ref, env, label = reference(kind, args, fields, options, folder)
            out_dir = folder / "ref"
            # run outside any source tree, each side's psfd named by PYTHONPATH: `python -m psfd` looks in
            # the working folder first, and an editable install would otherwise win over --before
            result = whole.paired(PSFD + args, ref, runs=options.runs, warmup=options.warmup,
                                  env_a=dict(os.environ, PYTHONPATH=str(TREE)), env_b=env, cwd=str(folder),
                                  prepare=lambda: shutil.rmtree(out_dir, ignore_errors=True))
            pub = f"{published:8.2f} {result.median('a', 'wall') / published:5.2f}" if published else ""
            if options.first_release and name in FIRST_OVER_C:
                pub += f" {result.ratio() * FIRST_OVER_C[name]:7.2f}"
            if options.machine_factor and published:
                pub += f" {result.median('a', 'wall') * options.machine_factor / published:5.2f}"
            note = f"  exit codes {result.failed()}" if result.failed() else ""
            print(f"{name:<24} {result.median('a', 'wall'):7.3f} {result.median('a', 'peak_mib'):6.0f} "
                  f"{result.median('b', 'wall'):7.3f} {result.median('b', 'peak_mib'):6.0f} {result.ratio():6.2f}  "
                  f"{label:<9} {pub}{note}", flush=True)


if __name__ == "__main__":
    main()
