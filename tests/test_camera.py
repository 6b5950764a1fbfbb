"""GPhotoCamera through libgphoto2's own virtual camera (the ``vusb`` port driver).

python-gphoto2 selects the virtual USB port driver at import time when
VCAMERADIR is set, and the choice holds for the whole process. So the camera
session runs in a child process with VCAMERADIR pointing at a folder holding a
real JPEG; this test process never imports gphoto2, and other tests that do are
unaffected. The child reports what it saw as JSON; the assertions are here.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

SESSION = r"""
import json, os, sys
from pathlib import Path
import gphoto2 as gp
from psfd.drivers.base import Camera
import time
from psfd.drivers.gphoto import GPhotoCamera, camera_error, reset_usb_device
from psfd.errors import CameraError

out = Path(sys.argv[1])
report = {}

def attempt(key, fn):
    try:
        report[key] = {"ok": fn()}
    except CameraError as exc:
        report[key] = {"error": str(exc)}

try:
    GPhotoCamera(port="usb:009,009")
except CameraError as exc:
    report["wrong_port"] = str(exc)

camera = GPhotoCamera(settle=0.1, timeout=5.0)
report["protocol"] = isinstance(camera, Camera)
info = camera.info()
report["info"] = [info.model, info.serial, info.port]
report["aperture_before"] = camera.get("aperture")
report["aperture_choices"] = camera.choices("aperture")
camera.set("aperture", "5.6")
report["aperture_after"] = camera.get("aperture")
camera.set("aperture", "f/8")  # the vendor's own spelling is accepted too
report["aperture_vendor_spelling"] = camera.get("aperture")
attempt("aperture_refused", lambda: camera.set("aperture", "1.2"))
report["aperture_kept"] = camera.get("aperture")
attempt("unknown_setting", lambda: camera.get("iso"))
camera.set("shutterspeed", "0.0050s")
report["shutterspeed"] = camera.get("shutterspeed")
report["captures"] = [[p.name for p in camera.capture(out)] for _ in range(2)]
os.remove(os.path.join(os.environ["VCAMERADIR"], "frame.jpg"))  # the camera's storage goes away
attempt("capture_gone", lambda: camera.capture(out))
camera.reconnect()
report["after_reconnect"] = camera.info().model
# a call that never returns (a camera hung in a USB transfer) ends at its deadline
started = time.monotonic()
attempt("hung", lambda: camera._call("waiting for the capture", time.sleep, 5.0, timeout=0.2))
report["hung_seconds"] = time.monotonic() - started
attempt("after_hung", lambda: camera.get("aperture"))
camera.reconnect(reset_usb=False)
report["after_second_reconnect"] = camera.get("aperture")
report["usb_reset_elsewhere"] = reset_usb_device("usb:999,999")
camera.close()
camera.close()
attempt("after_close", lambda: camera.get("aperture"))
report["claimed"] = str(camera_error("connecting", gp.GPhoto2Error(gp.GP_ERROR_IO_USB_CLAIM), "usb:001,004"))
print(json.dumps(report))
"""


def _virtual_camera(folder: Path) -> tuple[dict, str]:
    """A VCAMERADIR holding one real JPEG; returns the environment and the JPEG's sha256."""
    folder.mkdir()
    jpeg = folder / "frame.jpg"
    rng = np.random.default_rng(3)
    assert cv2.imwrite(str(jpeg), (rng.random((48, 64)) * 255).astype(np.uint8))
    return dict(os.environ, VCAMERADIR=str(folder)), hashlib.sha256(jpeg.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("vcamera")
    env, digest = _virtual_camera(root / "store")
    out = root / "downloads"
    proc = subprocess.run(
        [sys.executable, "-c", SESSION, str(out)], env=env, capture_output=True, text=True, timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout.strip().splitlines()[-1]), out, digest


def test_connect_and_info(session):
    report, _, _ = session
    assert report["protocol"] is True
    model, serial, port = report["info"]
    assert model == "GP VC" and serial == "0.1" and port.startswith("usb:")
    assert "no camera found on usb:009,009" in report["wrong_port"]
    assert "detected: " in report["wrong_port"] and port in report["wrong_port"]


def test_aperture_maps_to_f_number(session):
    report, _, _ = session
    # the virtual camera's widget is `f-number` with values `f/2.8`...; we speak `aperture` and `5.6`
    assert report["aperture_before"] == "2.8"
    assert report["aperture_choices"][:3] == ["2.8", "3.5", "4"] and "22" in report["aperture_choices"]
    assert report["aperture_after"] == "5.6"
    assert report["aperture_vendor_spelling"] == "8"
    assert report["shutterspeed"] == "0.0050s"


def test_value_not_offered_lists_the_offer(session):
    report, _, _ = session
    message = report["aperture_refused"]["error"]
    assert message.startswith("aperture 1.2 is not offered by the camera (offered: 2.8, 3.5, 4,")
    assert report["aperture_kept"] == "8"
    assert "camera has no setting 'iso'" in report["unknown_setting"]["error"]


def test_capture_downloads_the_file(session):
    report, out, digest = session
    first, second = report["captures"]
    assert len(first) == 1 and len(second) == 1 and first != second
    for name in first + second:
        assert hashlib.sha256((out / name).read_bytes()).hexdigest() == digest
    assert not [p for p in out.iterdir() if p.name.endswith(".part")]


def test_failures_are_camera_errors(session):
    report, _, _ = session
    assert "failed" in report["capture_gone"]["error"]
    assert report["after_reconnect"] == "GP VC"
    assert "camera is not connected" in report["after_close"]["error"]
    assert "claimed by another process" in report["claimed"]


def test_a_hung_call_ends_at_its_deadline(session):
    report, _, _ = session
    assert report["hung"]["error"] == (
        "camera did not answer while waiting for the capture within 0.2 s (unplugged or hung); reconnect it"
    )
    assert report["hung_seconds"] < 2.0  # returned long before the 5 s call would have
    assert "camera is not connected" in report["after_hung"]["error"]
    assert report["after_second_reconnect"] == "2.8"  # the virtual camera starts afresh on each connection
    assert report["usb_reset_elsewhere"] is False  # nothing is reset without a still-image device there


def test_cli_on_the_virtual_camera(tmp_path):
    env, _ = _virtual_camera(tmp_path / "store")

    def psfd(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "psfd", *argv], env=env, capture_output=True, text=True,
                              timeout=120)

    info = psfd("camera", "info")
    assert info.returncode == 0 and info.stdout.startswith("model    GP VC\n")
    assert "aperture       2.8          (offered: 2.8, 3.5, 4," in info.stdout
    assert psfd("camera", "set", "aperture", "5.6").stdout == "aperture = 5.6\n"
    refused = psfd("camera", "set", "aperture", "1.2")
    assert refused.returncode == 4 and refused.stderr.startswith("psfd: error: aperture 1.2 is not offered")
    missing = psfd("camera", "info", "--camera-port", "usb:009,009")
    assert missing.returncode == 4 and "no camera found on usb:009,009" in missing.stderr
