"""Time of the target detection on cluttered frames, against the previous detector in the same run.

Frames (tests/scenes.py): a 24-megapixel RGGB DNG of a cluttered outdoor
scene (foliage against a clipped sky, a chain-link fence, checkerboards,
text) with the target at 0.4 px/cell, whose g1 plane (3000 x 2000) is what
`find_target` sees for one channel of such a RAW; an 8-bit 1953 x 1301
plane of the same kind; the real 328 x 292 example photo; and a 3000 x 2000
indoor plane with the target shot close up at 5 px/cell (beyond the
previous detector's pyramid); and a cluttered plane without a target (the
time to refuse it).

Reference: the previous detector (commit PREVIOUS: per-tile candidates
judged by their ring, every candidate through the ring tests, four pyramid
levels), read from the git history and timed on the same frames in the
same run, interleaved with this one. Also timed: refining a detection on
the other three planes of the RAW (`refine_target`), which is what a frame
costs per extra channel when it is detected once.

Prints, per frame, the median (and minimum) wall time over interleaved
repeats, the median CPU time of the process (steadier than wall time on a
shared machine: it leaves out the time spent waiting for a core), and the
ratios new / previous of both. The goal is at most 0.5 s for the
3000 x 2000 plane.

Usage: python bench/bench_detect.py [--repeat N]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from psfd.errors import PsfdError  # noqa: E402
from psfd.estimator import detect, raw  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import scenes  # noqa: E402

PREVIOUS = "c948fc3"  # last commit with the previous detector


def previous_detector(folder: Path):
    """The detector of commit PREVIOUS as a module, or None without git history."""
    try:
        source = subprocess.run(["git", "-C", str(ROOT), "show", f"{PREVIOUS}:psfd/estimator/detect.py"],
                                check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    path = folder / "detect_previous.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("detect_previous", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["detect_previous"] = module
    spec.loader.exec_module(module)
    return module


def timed(function, *args) -> tuple[float, float, str]:
    """(wall seconds, CPU seconds of the process, outcome) of one call."""
    start, cpu = time.perf_counter(), time.process_time()
    try:
        function(*args)
        outcome = "found"
    except PsfdError as exc:
        outcome = type(exc).__name__
    return time.perf_counter() - start, time.process_time() - cpu, outcome


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=7)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        old = previous_detector(folder)
        dng = folder / "cluttered.dng"
        scenes.raw_scene(dng, seed=2, scale=0.4, angle=200.0)
        planes = {p.channel: p for p in raw.load_frames(dng)}
        plane = scenes.plane_scene(seed=5, scale=0.36, angle=75.0)
        close = scenes.plane_scene(seed=100, shape=(2000, 3000), scale=5.0, angle=268.0, fill=True)
        empty = scenes.plane_scene(seed=7, targets=0)
        photo = cv2.imread(str(ROOT / "tests" / "data" / "img_example.pgm"), cv2.IMREAD_UNCHANGED).astype(np.float64)
        frames = {
            "3000x2000 g1 plane of a cluttered 24 MP RAW": (planes["g1"].data, planes["g1"].saturated),
            "1953x1301 cluttered 8-bit plane": (plane.image.astype(np.float64), plane.image >= 255),
            "328x292 real example photo": (photo, None),
            "3000x2000 plane, target close up at 5 px/cell": (close.image.astype(np.float64), close.image >= 255),
            "1953x1301 cluttered plane without a target": (empty.image.astype(np.float64), empty.image >= 255),
        }
        found = detect.find_target(*frames["3000x2000 g1 plane of a cluttered 24 MP RAW"])
        others = [(planes[c].data, found, planes[c].saturated, detect.plane_shift(planes["g1"].offset, planes[c].offset))
                  for c in ("r", "g2", "b")]
        detectors = {"new": detect.find_target} | ({"previous": old.find_target} if old else {})
        times = {(name, key): [] for name in frames for key in detectors}
        cpu = {(name, key): [] for name in frames for key in detectors}
        outcome: dict[tuple[str, str], str] = {}
        refine_times = []
        for _ in range(args.repeat):  # interleaved, so that both see the same machine load
            for name, frame in frames.items():
                for key, function in detectors.items():
                    seconds, process, outcome[name, key] = timed(function, *frame)
                    times[name, key].append(seconds)
                    cpu[name, key].append(process)
            start = time.perf_counter()
            for args_ in others:
                detect.refine_target(*args_)
            refine_times.append((time.perf_counter() - start) / len(others))
    print(f"target detection, wall median (min) and CPU median of {args.repeat} interleaved runs")
    for name in frames:
        new, new_cpu = np.array(times[name, "new"]), np.median(cpu[name, "new"])
        line = f"  {name:46s} new {np.median(new):6.3f} s ({new.min():.3f}) cpu {new_cpu:.3f} {outcome[name, 'new']}"
        if old:
            prev, prev_cpu = np.array(times[name, "previous"]), np.median(cpu[name, "previous"])
            line += (f" | previous {np.median(prev):6.3f} s ({prev.min():.3f}) cpu {prev_cpu:.3f}"
                     f" {outcome[name, 'previous']} | new/previous wall {np.median(new) / np.median(prev):.2f}"
                     f" cpu {new_cpu / prev_cpu:.2f}")
        print(line)
    if not old:
        print(f"  (previous detector not timed: no git history with commit {PREVIOUS})")
    g1 = np.median(times["3000x2000 g1 plane of a cluttered 24 MP RAW", "new"])
    print(f"  refine_target on another plane of the RAW: {np.median(refine_times) * 1000:.1f} ms "
          f"({np.median(refine_times) / g1:.3f} of a detection); goal for the 3000x2000 plane <= 0.5 s")


if __name__ == "__main__":
    main()
