"""What the rail's guard process (psfd/drivers/grbl_guard.py) costs: a port open with a move, a whole command.

Against the fake GRBL controller of the tests (tests/fake_grbl.py) behind a pseudo-terminal, each case beside
its reference in the same run, in turn (A B A B ...), medians and the median of the pairwise ratios:

- move: ``GrblRail(port)``, one 0.5 mm move (the guard starts before it), ``close()``, in this process,
  against the same class with `_ensure_guard` made a no-op;
- command: ``psfd rail position --rail-port PTY`` as a whole process, this tree against --before DIR (a
  tree without the guard, e.g. ``git archive`` of an older commit, compiled); skipped without --before. It
  moves nothing, so it starts no guard: this shows the open itself costs nothing more.

The guard's own start-up (``python -I -S`` and its imports) runs beside the move; a clean close kills it, so
a short command does not wait for it.

Usage: python bench/bench_rail_guard.py [--runs N] [--before DIR]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
import whole  # noqa: E402
from fake_grbl import FakeGrbl  # noqa: E402

from psfd.drivers.grbl import GrblRail  # noqa: E402


class Unguarded(GrblRail):
    def _ensure_guard(self) -> None:
        pass


def open_move_close(cls, fake: FakeGrbl) -> None:
    rail = cls(fake.port)
    rail.move(x=-0.5 if rail.position().x == 0.0 else 0.0)
    rail.close()


def timed(make) -> float:
    start = time.perf_counter()
    make()
    return time.perf_counter() - start


def alternate(a, b, runs: int) -> tuple[list[float], list[float]]:
    ta, tb = [], []
    for i in range(runs + 1):
        x, y = timed(a), timed(b)
        if i:  # the first round warms the caches up
            ta.append(x)
            tb.append(y)
    return ta, tb


def report(name: str, ta: list[float], tb: list[float], against: str) -> None:
    ratio = statistics.median(x / y for x, y in zip(ta, tb))
    print(f"{name:8s} {statistics.median(ta) * 1000:8.1f} ms   {against}: {statistics.median(tb) * 1000:8.1f} ms   "
          f"ratio {ratio:.3f}   difference {(statistics.median(ta) - statistics.median(tb)) * 1000:+.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=15)
    parser.add_argument("--before", type=Path, help="a psfd tree without the guard, for the whole command")
    args = parser.parse_args()
    fake = FakeGrbl({110: 6000, 120: 200})
    try:
        report("move", *alternate(lambda: open_move_close(GrblRail, fake), lambda: open_move_close(Unguarded, fake),
                                  args.runs), "without the guard")
        if args.before:
            command = [sys.executable, "-m", "psfd", "rail", "position", "--rail-port", fake.port]
            pair = whole.paired(command, command, runs=args.runs, env_a={**os.environ, "PYTHONPATH": str(ROOT)},
                                env_b={**os.environ, "PYTHONPATH": str(args.before)}, cwd="/")
            if pair.failed():
                sys.exit(f"exit codes {pair.failed()}: {pair.a[-1].error or pair.b[-1].error}")
            report("command", [r.wall for r in pair.a], [r.wall for r in pair.b], f"--before {args.before}")
            print(f"{'':8s} cpu (the guard's included): {pair.median('a', 'cpu') * 1000:.1f} ms against "
                  f"{pair.median('b', 'cpu') * 1000:.1f} ms")
    finally:
        fake.close()


if __name__ == "__main__":
    main()
