"""Run throughput on the simulated rig, against a serial reference measured in the same run.

Prints frames/min and PSFs/min of the runner (capture in the parent, estimation in
worker processes), the share of the run the rig spent waiting on estimation, and
the speed-up over doing the same steps one after the other (capture, estimate,
capture, ...) in one process.

    python bench/bench_throughput.py [--steps 12] [--workers N] [--channels g1,r]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

# Same conditions for the serial reference as for the workers: one BLAS thread (set before numpy loads).
for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_name] = "1"

from psfd.catalogue import Catalogue
from psfd.daemon import work
from psfd.daemon.plan import parse_plan
from psfd.daemon.runner import Runner, default_workers
from psfd.drivers import open_rig
from psfd.drivers import sim
from psfd.drivers.sim import SimRig


def bench_plan(steps: int, channels: list[str]) -> str:
    rig = SimRig()
    y, z = rig.field_offsets(steps)
    return (
        '[rig]\nsimulate = true\n[target]\nkind = "bernoulli"\n'
        f"[capture]\napertures = [5.6]\nx = [{rig.distance_for_scale()}]\n"
        f"y = {[float(v) for v in y]}\nchannels = {channels}\n".replace("'", '"')
    )


def serial_reference(plan, folder: Path) -> float:
    """Seconds to capture and estimate every step one after the other, in this process."""
    camera, rail = open_rig(plan.rig_config())
    options = plan.estimator_options()
    t0 = time.perf_counter()
    for i, step in enumerate(plan.steps()):
        camera.set("aperture", f"{step.aperture:g}")
        rail.move(x=step.x, y=step.y, z=step.z)
        dest = folder / f"serial{i}"
        dest.mkdir()
        paths = [str(p) for p in camera.capture(dest)]
        work.estimate_step(plan.kind, paths, plan.channels, options)
    elapsed = time.perf_counter() - t0
    camera.close()
    rail.close()
    return elapsed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=12)
    parser.add_argument("--workers", type=int, default=default_workers())
    parser.add_argument("--channels", default="g1,r")
    args = parser.parse_args()
    plan = parse_plan(bench_plan(args.steps, args.channels.split(",")), "bench")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        serial = serial_reference(plan, folder)
        sim._psf.cache_clear()
        camera, rail = open_rig(plan.rig_config())
        with Catalogue(folder / "cat.sqlite") as cat:
            result = Runner(cat, folder / "frames", workers=args.workers, progress=None).run(plan, camera, rail)
    minutes = result.elapsed_s / 60
    load = ", ".join(f"{v:.1f}" for v in os.getloadavg())
    print(f"steps {result.steps_done}, channels {args.channels}, workers {args.workers}, "
          f"{os.cpu_count()} cores, load average {load} (the simulated camera renders on the CPU too)")
    print(f"runner: {result.elapsed_s:.1f} s, {result.frames / minutes:.1f} frames/min, {result.psfs / minutes:.1f} PSFs/min")
    print(f"rig busy (move + capture + store): {result.capture_s:.1f} s = {result.capture_s / result.elapsed_s:.0%} of the run")
    print(f"rig waiting on estimation: {result.rig_wait_s:.1f} s = {result.rig_wait_s / result.elapsed_s:.0%} of the run")
    print(f"serial reference (capture, estimate, capture, ...): {serial:.1f} s; "
          f"runner speed-up {serial / result.elapsed_s:.2f}x")


if __name__ == "__main__":
    main()
