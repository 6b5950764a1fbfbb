"""The two-photo estimate on the real wall pair: the whole `psfd estimate pair` process, and its steps in-process.

The pair shipped with the tests (IMG_0608_v1.pgm, 1953x1301, and
IMG_0602_v1_CUT.pgm, 251x221: one green channel of a Canon EOS 400D) is the
IPOL 2013 demo pair. What a user waits for is the whole process
(`psfd estimate pair FAR NEAR -s 3`): it is started as a subprocess (median of
--runs, bench/whole.py) beside a reference measured in the same run, the same
command from another psfd source tree (--before DIR) or else the bare
interpreter, and set against the published C implementation's whole-process
time on this kind of machine (3.7 s; the goal is 0.3 of it).

For the daemon, which imports once and then estimates pair after pair, the
steps are also timed in-process after a warm-up (best of --runs): reading,
registration (SIFT + homography), the near photo on the s-grid, least
squares for k, and k -> h, with BLAS on one thread as the command line sets it.

Usage: python bench/bench_twoscale.py [--runs N] [--before DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

# as `psfd` itself sets it before numpy loads (psfd.cli): small products gain nothing from BLAS threads
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

sys.path.insert(0, str(Path(__file__).resolve().parent))
import whole  # noqa: E402

TREE = Path(__file__).resolve().parent.parent
DATA = TREE / "tests" / "data"
FAR, NEAR = DATA / "IMG_0602_v1_CUT.pgm", DATA / "IMG_0608_v1.pgm"
PUBLISHED_S = 3.7  # the published C implementation, whole process, s = 3, on this kind of machine
GOAL = 0.3  # of the published time


def whole_process(runs: int, before: str | None) -> None:
    argv = [sys.executable, "-m", "psfd", "estimate", "pair", str(FAR), str(NEAR), "-s", "3"]
    env_a = dict(os.environ, PYTHONPATH=str(TREE))
    if before:
        ref, env_b, label = argv, dict(os.environ, PYTHONPATH=str(Path(before).resolve())), "before"
    else:
        ref, env_b, label = [sys.executable, "-c", "pass"], None, "python"
    with tempfile.TemporaryDirectory() as cwd:  # not the tree: `-m psfd` must find the PYTHONPATH one
        result = whole.paired(argv, ref, runs=runs, env_a=env_a, env_b=env_b, cwd=cwd)
    ours = result.median("a", "wall")
    print(f"whole process, psfd estimate pair -s 3: {ours:.3f} s, peak {result.median('a', 'peak_mib'):.0f} MiB"
          f"{'  exit codes ' + str(result.failed()) if result.failed() else ''}")
    print(f"  {label}: {result.median('b', 'wall'):.3f} s; ratio (pairwise median) {result.ratio():.2f}")
    print(f"  over the published C time ({PUBLISHED_S} s): {ours / PUBLISHED_S:.2f} (goal {GOAL})")


def steps(runs: int) -> None:
    from psfd.estimator import pair_register, raw, twoscale

    timed = [
        (pair_register, "register", "registration (SIFT + homography)"),
        (twoscale, "resample_near", "near photo on the s-grid"),
        (twoscale, "solve_kernel", "least squares for k"),
        (twoscale, "psf_from_kernel", "k -> h"),
    ]
    spent: dict[str, float] = {}
    for module, name, label in timed:
        def wrapper(*args, _f=getattr(module, name), _label=label, **kwargs):
            t0 = time.perf_counter()
            try:
                return _f(*args, **kwargs)
            finally:
                spent[_label] = spent.get(_label, 0.0) + time.perf_counter() - t0

        setattr(module, name, wrapper)

    def once() -> dict[str, float]:
        spent.clear()
        t0 = time.perf_counter()
        a, b = raw.load_frame(FAR, "mono"), raw.load_frame(NEAR, "mono")
        t1 = time.perf_counter()
        twoscale.estimate_pair(a, b, s=3)
        t2 = time.perf_counter()
        return {"reading": t1 - t0, **spent, "other (checks, window)": t2 - t1 - sum(spent.values()),
                "total": t2 - t0}

    once()  # warm-up: imports, OpenCV's thread pool
    best = [once() for _ in range(runs)]
    print(f"in-process, after a warm-up (best of {runs}):")
    for label in best[0]:
        print(f"  {label:<34} {min(r[label] for r in best):6.3f} s")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5, help="timed runs of each (default 5)")
    parser.add_argument("--before", metavar="DIR", help="psfd source tree whose command is the reference")
    args = parser.parse_args()
    whole_process(args.runs, args.before)
    steps(args.runs)


if __name__ == "__main__":
    main()
