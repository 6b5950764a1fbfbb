"""What the card listing before each capture to the card costs as the card fills (psfd/drivers/gphoto.py).

Before a release with the card as capture target the driver lists the files where a new one can appear,
so that a file an exposure leaves there when the camera is lost is found. On libgphoto2's own virtual
camera (the ``vusb`` port driver of the bundled libgphoto2, VCAMERADIR holding N files in DCF folders of
1000, plus the folder the camera writes its captures to), in a child process per card (python-gphoto2
chooses the port driver at import), each case beside its reference, in turn (A B A B ...), medians:

- whole card: `GPhotoCamera._walk` of every folder (what each step listed before), on a new USB session
  (libgphoto2 reads every object's information: the first step of a run, and after each reconnect) and
  again in the same session (libgphoto2 answers from its filesystem cache: every later step);
- step: `GPhotoCamera._card_files` once the camera has written a frame (its folder and the folders beside
  it), on a new session and again in the same one.

The virtual camera answers from memory; a body over USB answers each object's information in a PTP
transaction of its own, so the ratio, not the seconds, is what carries over. The stand-in bodies of the
tests (tests/fake_gphoto.py) are timed the same way for comparison.

Usage: python bench/bench_card_listing.py [--files 1000 5000 20000] [--runs N]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
from psfd.drivers.gphoto import GPhotoCamera

runs, out = int(sys.argv[1]), sys.argv[2]
camera = GPhotoCamera(quiet_s=0.1, timeout=120)
frame = camera.capture(out)  # the camera writes a frame: the driver knows its folder from then on
folder = camera._writes_to
times = {"whole_fresh": [], "whole_cached": [], "step_fresh": [], "step_cached": []}
counts = {}
for _ in range(runs):
    for case in ("whole", "step"):
        camera.reconnect(reset_usb=False)  # a fresh USB session: libgphoto2 reads the card anew
        for when, label in (("fresh", "new session"), ("cached", "same session")):
            started = time.perf_counter()
            files = camera._walk("/") if case == "whole" else camera._card_files()
            times[f"{case}_{when}"].append(time.perf_counter() - started)
            counts[case] = len(files)
camera.close()
print(json.dumps({"times": times, "counts": counts, "folder": folder}))
"""


def virtual_card(root: Path, files: int) -> dict:
    """A VCAMERADIR with ``files`` JPEGs in DCF folders of 1000 (a copy of one small real JPEG each)."""
    import cv2
    import numpy as np

    store = root / "store"
    store.mkdir(parents=True)
    (root / "home").mkdir()
    rng = np.random.default_rng(3)
    frame = store / "frame.jpg"
    cv2.imwrite(str(frame), (rng.random((48, 64)) * 255).astype(np.uint8))
    data = frame.read_bytes()
    for i in range(files):
        folder = store / "DCIM" / f"{100 + i // 1000}GPHOT"
        folder.mkdir(parents=True, exist_ok=True)
        (folder / f"IMG_{i % 1000:04d}.JPG").write_bytes(data)
    return dict(os.environ, VCAMERADIR=str(store), HOME=str(root / "home"))


def on_virtual_camera(files: int, runs: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="psfd-bench-card-") as tmp:
        env = virtual_card(Path(tmp), files)
        proc = subprocess.run([sys.executable, "-c", CHILD, str(runs), str(Path(tmp) / "out")], env=env,
                              capture_output=True, text=True, timeout=1800, check=True)
        return json.loads(proc.stdout.strip().splitlines()[-1])


def on_stand_in(files: int, runs: int) -> dict:
    """The same cases on a stand-in Canon whose card holds ``files`` in folders of 1000."""
    sys.path.insert(0, str(ROOT / "tests"))
    import fake_gphoto as bodies
    from psfd.drivers import gphoto
    from psfd.drivers.base import CameraSetup

    dcim = "/store_00020001/DCIM"
    card = {f"{dcim}/{100 + k}CANON": [f"IMG_{i:04d}.JPG" for i in range(1000)] for k in range(files // 1000)}
    body = bodies.Body(bodies.canon_eos(lens_af=False), folder=f"{dcim}/{100 + len(card)}CANON", card=card)
    bus = bodies.Bus("Canon EOS 5D Mark III", body)
    gphoto._detect, gphoto._open_camera = bus.detect, bus.open
    camera = gphoto.GPhotoCamera(quiet_s=0.1)
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    with tempfile.TemporaryDirectory() as tmp:
        camera.capture(Path(tmp))
    times: dict[str, list[float]] = {"whole_fresh": [], "step_fresh": []}
    counts = {}
    for _ in range(runs):
        for case in ("whole", "step"):
            started = time.perf_counter()
            found = camera._walk("/") if case == "whole" else camera._card_files()
            times[f"{case}_fresh"].append(time.perf_counter() - started)
            counts[case] = len(found)
    return {"times": times, "counts": counts, "folder": camera._writes_to}


def report(kind: str, files: int, result: dict) -> None:
    med = {k: statistics.median(v) for k, v in result["times"].items()}
    counts = result["counts"]
    print(f"{kind}, {files} files on the card (frames written to {result['folder']}):")
    for when, label in (("fresh", "new session"), ("cached", "same session")):
        whole, step = med.get(f"whole_{when}"), med.get(f"step_{when}")
        if whole is None:
            continue
        print(f"  {label:12s}  whole card {whole * 1e3:9.2f} ms ({counts['whole']} files)   step "
              f"{step * 1e3:7.2f} ms ({counts['step']} files)   ratio whole/step {whole / step:7.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, nargs="+", default=[1000, 5000, 20000])
    parser.add_argument("--runs", type=int, default=5)
    args = parser.parse_args()
    for files in args.files:
        report("virtual camera", files, on_virtual_camera(files, args.runs))
    for files in args.files:
        report("stand-in Canon", files, on_stand_in(files, args.runs))


if __name__ == "__main__":
    main()
