"""GPhotoCamera on libgphoto2's own virtual camera, and on scripted stand-ins for what it cannot play.

Virtual camera (the ``vusb`` port driver, libgphoto2 2.5.34 as bundled by
python-gphoto2 2.6.4). python-gphoto2 selects the port driver at import time
when VCAMERADIR is set, and the choice holds for the whole process, so the
camera session runs in a child process with VCAMERADIR pointing at a folder
holding a real JPEG (and HOME at a scratch folder: the ptp2 driver keeps its
own settings, capture target and autofocus among them, in ~/.gphoto/settings).
It identifies as "GP VC" (serial 0.1; libgphoto2 matches its USB ids to the
driver model "Nikon DSC D750"), captures by copying the first JPEG of its
folder, announces each capture as FILE_ADDED at +100 ms and CAPTURE_COMPLETE at
+120 ms, floods GP_EVENT_UNKNOWN property-change events (every property read
schedules another one), and accepts PTP opcode 0x9999 through the ``opcode``
widget to announce an extra file after a delay. Its configuration tree::

    actions/    bulb (toggle: fails with GP_ERROR_IO), controlmode, opcode (text)
    settings/   datetime, thumbsize, fastfs, capturetarget (Internal RAM | Memory card),
                autofocus (On | Off)
    status/     serialnumber 0.1, manufacturer GP, cameramodel VC, deviceversion,
                vendorextension, batterylevel
    imgsettings/ imagesize (read-only: 640x480 | 1024x768 | 2048x1536)
    capturesettings/ exposurecompensation, f-number (f/2.8 ... f/22),
                shutterspeed (1.0000s ... 0.0001s)
    other/      5001 5003 5007 5010 500d 5011 (the same PTP properties by code)

No image format setting and JPEG as its only capture format: it shows RAW
refused before any motion. It also shows the capture target and the
autofocus switch set by `prepare`, the capture deadline following the
shutter speed, a second file announced 2.5 s after the trigger collected with
the first, a late file from an earlier exposure discarded instead of counted,
a hung call ending at its deadline, reconnecting, and the card listing of each step following the
folder it writes to (``DCIM/nnnGPHOT``, the next one every 100 file numbers, from GPH_0099.JPG on).

Stand-ins (`tests/fake_gphoto.py`, real gphoto2 error codes in the order a body produces them) show what the
virtual camera cannot: RAW chosen on Canon and Nikon widget trees (sRAW/mRAW refused), single-frame drive,
exposure delay, autofocus reported by the lens, busy (-110) then ready, busy for good, busy answered to
reading the configuration and to deleting, an autofocus that cannot lock (Canon: busy after the hunt; Nikon:
-1), a full card (-3), a RAW+JPEG pair 1.5 s apart, the JPEG of an earlier pair written by a slow card after
the next release, a stale file queued behind a flood of property changes, a cable pulled mid-capture
(reconnect, prepare again, retry once; the file the lost exposure left on the card collected, or deleted when
it may not be all of it; found in the folder the body opened for it), each step listing only the folder the
body writes to on a card of thousands of photographs, a release of unknown exposure time that outlasts its
call's deadline (reported, not reset or released again; its file deleted by the next capture, of this camera
or of a resumed run's), a capture that gets no file before its deadline (the next one not released until that
file comes, then discarded), bulb, a capture that never announces its file, a file the camera no longer holds
(-108), and on a fake clock a Nikon busy through a 30 s exposure (libgphoto2 giving up on it after 5, 20 or
1000 s) or hung after it.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

SESSION = r"""
import json, logging, os, sys, time
from pathlib import Path
import gphoto2 as gp
from psfd.drivers.base import Camera, CameraSetup
from psfd.drivers.gphoto import GPhotoCamera, camera_error, reset_usb_device
from psfd.errors import CameraError

out = Path(sys.argv[1])
report = {}

def attempt(key, fn):
    try:
        report[key] = {"ok": fn()}
    except CameraError as exc:
        report[key] = {"error": str(exc)}

def names(widget, prefix=""):
    found = []
    for i in range(widget.count_children()):
        child = widget.get_child(i)
        found.append(prefix + child.get_name())
        found += names(child, prefix + child.get_name() + "/")
    return found

def files_in(folder):
    return sorted(p.name for p in folder.iterdir()) if folder.exists() else []

try:
    GPhotoCamera(port="usb:009,009")
except CameraError as exc:
    report["wrong_port"] = str(exc)

camera = GPhotoCamera(quiet_s=0.1, timeout=5.0)
report["protocol"] = isinstance(camera, Camera)
report["tree"] = names(camera._config())
info = camera.info()
report["info"] = [info.model, info.serial, info.port]

# -- setup for PSF work
attempt("raw_refused", lambda: camera.prepare(CameraSetup()))
report["files_after_refusal"] = files_in(out)
report["ready"] = camera.prepare(CameraSetup(raw=False, focus="manual")).as_dict()
report["autofocus_after"] = camera.get("autofocus")
report["target_after"] = camera.get("capturetarget")
camera.prepare(CameraSetup(raw=False, capture_target="card"))
report["target_card"] = camera.get("capturetarget")
camera.set("autofocus", "On")
report["ready_any"] = camera.prepare(CameraSetup(raw=False, focus="any", capture_target="ram")).as_dict()
report["autofocus_any"] = camera.get("autofocus")
camera.set("shutterspeed", "1.0000s")
report["deadline_1s"] = camera._capture_deadline()[0]
camera.set("shutterspeed", "0.0050s")
report["deadline_short"] = camera._capture_deadline()[0]

# -- settings
report["aperture_before"] = camera.get("aperture")
report["aperture_choices"] = camera.choices("aperture")
camera.set("aperture", "5.6")
report["aperture_after"] = camera.get("aperture")
camera.set("aperture", "f/8")  # the vendor's own spelling is accepted too
report["aperture_vendor_spelling"] = camera.get("aperture")
attempt("aperture_refused", lambda: camera.set("aperture", "1.2"))
report["aperture_kept"] = camera.get("aperture")
attempt("unknown_setting", lambda: camera.get("iso"))
report["shutterspeed"] = camera.get("shutterspeed")

# -- capture
report["captures"] = [[p.name for p in camera.capture(out)] for _ in range(2)]
# one exposure of two files, the second announced 2.5 s after the trigger
camera.files_per_exposure = 2
camera.set("opcode", "0x9999,0x0,0x9c4")  # vusb: announce one more file in 2500 ms
started = time.monotonic()
report["late_pair"] = [p.name for p in camera.capture(out / "late")]
report["late_pair_s"] = time.monotonic() - started
# count unknown: the late file arrives after the capture was collected, and the next
# capture (after the rail has moved and settled) does not count it
camera.files_per_exposure = None
camera.set("opcode", "0x9999,0x0,0x9c4")
report["quiet_first"] = [p.name for p in camera.capture(out / "quiet1")]
time.sleep(3.0)
report["quiet_second"] = [p.name for p in camera.capture(out / "quiet2")]
report["strays"] = [s.rsplit("/", 1)[-1] for s in camera.strays]

# -- failures
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
    """A VCAMERADIR holding one real JPEG, and a scratch HOME; returns the environment and the JPEG's sha256."""
    folder.mkdir()
    (folder.parent / "home").mkdir()
    jpeg = folder / "frame.jpg"
    rng = np.random.default_rng(3)
    assert cv2.imwrite(str(jpeg), (rng.random((48, 64)) * 255).astype(np.uint8))
    env = dict(os.environ, VCAMERADIR=str(folder), HOME=str(folder.parent / "home"))
    return env, hashlib.sha256(jpeg.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    root = tmp_path_factory.mktemp("vcamera")
    env, digest = _virtual_camera(root / "store")
    out = root / "downloads"
    proc = subprocess.run(
        [sys.executable, "-c", SESSION, str(out)], env=env, capture_output=True, text=True, timeout=180
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


def test_the_virtual_camera_is_what_the_docstring_says(session):
    tree = set(session[0]["tree"])
    for name in ("actions/bulb", "actions/opcode", "settings/capturetarget", "settings/autofocus",
                 "capturesettings/f-number", "capturesettings/shutterspeed", "imgsettings/imagesize"):
        assert name in tree
    assert not [n for n in tree if n.endswith(("imageformat", "imagequality", "focusmode", "drivemode"))]


def test_raw_is_refused_before_any_motion(session):
    report, _, _ = session
    message = report["raw_refused"]["error"]
    assert "has no image format setting, so RAW cannot be set" in message
    assert message.endswith("refusing before any motion")
    assert report["files_after_refusal"] == []  # nothing was shot


def test_prepare_sets_capture_target_and_turns_autofocus_off(session):
    report, _, _ = session
    ready = report["ready"]
    assert ready["capture_target"] == "Internal RAM" and report["target_after"] == "Internal RAM"
    assert ready["focus"] == "af-off" and ready["focus_detail"] == "autofocus = Off"
    assert report["autofocus_after"] == "Off"
    assert ready["settle_s"] == 2.0 and ready["image_format"] is None
    assert any("no exposure delay" in note for note in ready["notes"])
    assert report["target_card"] == "Memory card"
    # focus = "any" leaves the lens alone and records what the camera reports (here: nothing)
    assert report["autofocus_any"] == "On" and report["ready_any"]["focus"] == "unknown"


def test_capture_deadline_follows_the_shutter_speed(session):
    report, _, _ = session
    assert report["deadline_1s"] == pytest.approx(30.0 + 2 * 1.0)  # writing + exposure + its dark frame
    assert report["deadline_short"] == pytest.approx(30.0 + 2 * 0.005)


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
    assert not [p for p in out.rglob("*.part")]


def test_a_file_announced_seconds_later_belongs_to_its_exposure(session):
    report, out, digest = session
    pair = report["late_pair"]
    assert len(pair) == 2 and report["late_pair_s"] > 2.0  # waited for the second file, 2.5 s on
    assert all(hashlib.sha256((out / "late" / n).read_bytes()).hexdigest() == digest for n in pair)


def test_a_late_file_is_not_counted_in_the_next_capture(session):
    report, _, _ = session
    assert len(report["quiet_first"]) == 1 and len(report["quiet_second"]) == 1
    assert len(report["strays"]) == 1
    assert report["strays"][0] not in report["quiet_first"] + report["quiet_second"]


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


LISTING = r"""
import json, sys
from psfd.drivers.base import CameraSetup
from psfd.drivers.gphoto import GPhotoCamera

class Listed:
    # the libgphoto2 camera, its folder listings noted
    def __init__(self, camera):
        self.camera, self.folders = camera, []
    def __getattr__(self, name):
        return getattr(self.camera, name)
    def folder_list_files(self, folder):
        self.folders.append(folder)
        return self.camera.folder_list_files(folder)

camera = GPhotoCamera(quiet_s=0.1, timeout=5.0)
camera.prepare(CameraSetup(raw=False, capture_target="card"))
camera._camera = listed = Listed(camera._camera)
steps = []
for step in range(3):
    files = camera.capture(sys.argv[1])
    steps.append({"files": [f.name for f in files], "listed": listed.folders[:]})
    listed.folders.clear()
print(json.dumps(steps))
"""


def test_on_the_virtual_camera_each_step_lists_the_folder_it_writes_to(tmp_path):
    # earlier photographs in the card's first DCF folder; the virtual camera writes its first capture there, and
    # the next ones in a folder it opens (101GPHOT: it moves on every 100 file numbers, starting at 99)
    env, _ = _virtual_camera(tmp_path / "store")
    earlier = tmp_path / "store" / "DCIM" / "100GPHOT"
    earlier.mkdir(parents=True)
    for i in range(50):
        (earlier / f"IMG_{i:04d}.JPG").write_bytes((tmp_path / "store" / "frame.jpg").read_bytes())
    proc = subprocess.run([sys.executable, "-c", LISTING, str(tmp_path / "out")], env=env, capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    steps = json.loads(proc.stdout.strip().splitlines()[-1])
    dcim = "/store_00010001/DCIM"
    assert [step["files"] for step in steps] == [["GPH_0099.JPG"], ["GPH_0101.JPG"], ["GPH_0103.JPG"]]
    assert steps[0]["listed"] == ["/", "/store_00010001", dcim, f"{dcim}/100GPHOT"]  # where it writes: not known yet
    assert steps[1]["listed"] == [f"{dcim}/100GPHOT"]  # where the first capture was written
    assert steps[2]["listed"] == [f"{dcim}/101GPHOT"]  # the folder it opened for the second: not 100GPHOT again


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


# ---------------------------------------------------------------------- stand-ins


@pytest.fixture
def bodies():
    """The stand-in bodies (importing gphoto2 here is harmless: no VCAMERADIR, no USB access)."""
    import fake_gphoto

    return fake_gphoto


@pytest.fixture
def fake(monkeypatch, bodies):
    """Build a GPhotoCamera on scripted bodies: ``fake(bus, clock=None, **camera_options)``."""
    from psfd.drivers.gphoto import GPhotoCamera

    def make(bus, clock=None, **options):
        bodies.install(monkeypatch, bus, clock)
        options.setdefault("timeout", 5.0)
        return GPhotoCamera(**options)

    return make


def _value(config, name):
    return config.get_child_by_name(name).get_value()


def test_an_f_number_however_psfd_reads_it_sets_the_bodys_own_choice(fake, bodies, monkeypatch):
    """A Nikon lists f/8, a Canon 8 (libgphoto2's ptp2 widgets ``f-number`` and ``aperture``): every spelling psfd
    reads as f/8 (`psfd.vocabulary.parse_fnumber`, as `psfd capture --aperture` and a recording read it) sets it.
    Before, the driver had its own matching and refused F8, which the rest of psfd takes."""
    from psfd.drivers.gphoto import GPhotoCamera

    for model, tree, widget, choice in (("Nikon DSC D5300", bodies.nikon_d5300(), "f-number", "f/8"),
                                        ("Canon EOS 5D Mark III", bodies.canon_eos(), "aperture", "8")):
        for spelling in ("8", "8.0", "f/8", "F8", "F/8"):
            body = bodies.Body(tree)
            bodies.install(monkeypatch, bodies.Bus(model, body))
            GPhotoCamera(timeout=5.0).set("aperture", spelling)
            assert _value(body.config, widget) == choice, (model, spelling)


def test_canon_prepare_picks_raw_ram_single_and_refuses_an_af_lens(fake, bodies):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    body = bodies.Body(bodies.canon_eos(lens_af=True))
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body))
    with pytest.raises(CameraError, match=r"reports autofocus \(focusmode = One Shot\).*set the lens \(or body\) "
                                          r"focus switch to M; refusing before any motion"):
        camera.prepare(CameraSetup())
    assert body.shots == 0 and "trigger_capture" not in body.calls
    # RAW alone (not sRAW/mRAW, not RAW+JPEG), RAM, single frame were set on the way
    assert _value(body.config, "imageformat") == "RAW"
    assert _value(body.config, "capturetarget") == "Internal RAM"
    assert _value(body.config, "drivemode") == "Single"

    body = bodies.Body(bodies.canon_eos(lens_af=False, image_format="RAW + Large Fine JPEG"))
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body))
    ready = camera.prepare(CameraSetup(focus="manual"))
    assert (ready.image_format, ready.files_per_exposure, ready.focus) == ("RAW", 1, "manual")
    assert ready.exposure_delay is None and any("mirror lock-up" in n for n in ready.notes)


def test_nikon_prepare_sets_exposure_delay_and_driver_af_off(fake, bodies):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    body = bodies.Body(bodies.nikon_d5300(focus="Manual"))
    camera = fake(bodies.Bus("Nikon DSC D5300", body))
    ready = camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    assert ready.image_format == "NEF (Raw)" and ready.files_per_exposure == 1
    assert ready.capture_target == "Memory card" and ready.drive_mode == "Single Shot"
    assert ready.exposure_delay == "On" and _value(body.config, "exposuredelaymode") == "On"
    assert ready.focus == "manual" and _value(body.config, "autofocus") == "Off"
    # 0.5 s exposure: 30 s writing + twice the exposure + up to 3 s of exposure delay
    assert camera._capture_deadline() == (pytest.approx(30.0 + 1.0 + 3.0), None)

    body = bodies.Body(bodies.nikon_d5300(focus="AF-S"))
    camera = fake(bodies.Bus("Nikon DSC D5300", body))
    with pytest.raises(CameraError, match="focusmode = AF-S"):
        camera.prepare(CameraSetup())
    assert camera.prepare(CameraSetup(focus="any")).focus == "af"


def test_a_jpeg_only_camera_is_refused(fake, bodies):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    camera = fake(bodies.Bus("Compact", bodies.Body(bodies.jpeg_compact())))
    with pytest.raises(CameraError, match=r"cannot shoot full-resolution RAW \(imageformat offers: Large Fine JPEG"):
        camera.prepare(CameraSetup())


def test_raw_choice_and_files_per_exposure():
    from psfd.drivers.gphoto import _files_of, raw_choice

    canon = ["Large Fine JPEG", "RAW + Large Fine JPEG", "RAW", "mRAW", "sRAW"]
    assert raw_choice("Large Fine JPEG", canon) == "RAW"
    assert raw_choice("sRAW", ["sRAW", "mRAW", "S-RAW", "RAW (M)"]) is None  # reduced RAW is not the mosaic
    assert raw_choice("JPEG", ["RAW+JPEG", "JPEG"]) == "RAW+JPEG"  # no RAW alone: RAW with a JPEG
    assert raw_choice("C-RAW", ["cRAW", "RAW"]) == "RAW"  # lossy compressed RAW only when nothing better
    assert raw_choice("Standard", ["Standard", "Fine", "cRAW"]) == "cRAW"
    assert raw_choice("C-RAW", ["JPEG", "C-RAW", "C-RAW+JPEG"]) == "C-RAW"
    formats = ("NEF (Raw)", "NEF+Fine", "RAW + Large Fine JPEG", "RAW", "JPEG Fine", "C-RAW", "RAW & JPEG")
    assert [_files_of(f) for f in formats] == [1, 2, 2, 1, 1, 1, 2]


def test_busy_then_ready_is_retried_with_backoff(fake, bodies, tmp_path):
    import gphoto2 as gp

    busy = gp.GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY)
    body = bodies.Body(bodies.canon_eos(), script={"trigger_capture": [busy, busy, None]})
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), quiet_s=0.1)
    started = time.monotonic()
    files = camera.capture(tmp_path)
    assert [f.name for f in files] == ["IMG_0001.CR2"] and body.shots == 1
    assert body.calls.count("trigger_capture") == 3
    assert time.monotonic() - started >= 0.3  # 0.1 s then 0.2 s of backoff


def test_a_camera_busy_for_good_is_a_clear_error(fake, bodies, tmp_path):
    import gphoto2 as gp
    from psfd.errors import CameraError

    busy = gp.GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY)
    body = bodies.Body(bodies.canon_eos(), script={"trigger_capture": [busy] * 50})
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), busy_s=0.6)
    with pytest.raises(CameraError, match=r"stayed busy for 0.6 s while triggering a capture .* \[gphoto2 -110\]"):
        camera.capture(tmp_path)
    assert body.shots == 0


def test_a_body_still_writing_is_waited_for_by_every_call(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup

    import gphoto2 as gp

    # PTP DeviceBusy answers any operation while the body writes, not only the next trigger
    busy = gp.GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY)
    body = bodies.Body(bodies.canon_eos(lens_af=False))
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body))
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    body.script = {"get_config": [busy, None, None, busy], "file_delete": [busy, busy]}
    assert [f.name for f in camera.capture(tmp_path)] == ["IMG_0001.CR2"]
    assert body.store == {}  # deleted once the body answered: the card does not fill overnight
    camera.set("aperture", "8")  # the runner's next step, while the body may still be writing
    assert _value(body.config, "aperture") == "8"
    # a release refused while the body writes, the event wait answered busy too: released again once the
    # body answers and no file came of the refused release
    body.script = {"trigger_capture": [busy], "wait_for_event": [None, busy, busy]}
    assert [f.name for f in camera.capture(tmp_path / "again")] == ["IMG_0002.CR2"]
    assert body.shots == 2 and body.calls.count("trigger_capture") == 3


def _long_nikon(bodies, **body_options):
    """A Nikon D5300 set to NEF and 30 s, writing 2 s, on a fake clock; returns the body and the clock."""
    clock = bodies.Clock()
    config = bodies.nikon_d5300(quality="NEF (Raw)", shutter="30.0000s")
    return bodies.Body(config, files=(("DSC_0001.NEF", 2.0),), clock=clock, **body_options), clock


# how long libgphoto2 waits for a busy Nikon after a release: 2.5.23, after the fix of #465, since 2021
@pytest.mark.parametrize("library_wait_s", [5.0, 20.0, 1000.0])
def test_a_long_nikon_exposure_is_one_frame(fake, bodies, tmp_path, library_wait_s):
    from psfd.drivers.base import CameraSetup

    # the body answers busy for the 30 s and the writing; libgphoto2 may give up on it before
    body, clock = _long_nikon(bodies, library_wait_s=library_wait_s)
    camera = fake(bodies.Bus("Nikon DSC D5300", body), clock=clock)
    camera.prepare(CameraSetup(focus="manual"))
    frames = [camera.capture(tmp_path / str(i)) for i in (1, 2)]
    assert [[f.name for f in files] for files in frames] == [["DSC_0001.NEF"], ["DSC_0002.NEF"]]
    assert frames[0][0].read_bytes() == b"DSC_0001.NEF of shot 1"
    assert body.shots == 2 and camera.strays == [] and body.store == {}  # no second release, nothing left


def test_a_nikon_that_stays_busy_after_the_release_is_reported_not_released_again(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    body, clock = _long_nikon(bodies, library_wait_s=20.0, hangs=True)
    bus = bodies.Bus("Nikon DSC D5300", body)
    camera = fake(bus, clock=clock)
    camera.prepare(CameraSetup(focus="manual"))  # exposure delay On: up to 3 s
    # waited as long as the exposure needs: 30 s writing + 30 s + its dark frame + the delay
    with pytest.raises(CameraError, match=r"Nikon DSC D5300 stayed busy for 93 s after the release \(exposure, "
                                          r"delay and writing included\).*hung.*\[gphoto2 -110\]"):
        camera.capture(tmp_path)
    assert body.shots == 1 and list(tmp_path.iterdir()) == [] and bus.opened == ["usb:001,004"]


def test_a_release_of_unknown_exposure_time_is_not_cut_short_and_taken_again(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    # shutter speed auto: the body's program exposes 40 s, libgphoto2 waits for it inside the release
    # (up to 1000 s), longer than the capture's deadline for an unknown exposure (30 s + 3 s of delay)
    clock = bodies.Clock()
    config = bodies.nikon_d5300(quality="NEF (Raw)", shutter="auto")
    body = bodies.Body(config, files=(("DSC_0001.NEF", 2.0),), clock=clock, auto_exposure_s=40.0)
    again = bodies.Body(config, files=(("DSC_0001.NEF", 2.0),), clock=clock, auto_exposure_s=40.0)
    bus = bodies.Bus("Nikon DSC D5300", body, again)
    camera = fake(bus, clock=clock)
    camera.prepare(CameraSetup(focus="manual"))
    with pytest.raises(CameraError, match=r"triggering a capture within 33 s .*exposure time is unknown.*not "
                                          r"reset or released again$"):
        camera.capture(tmp_path)
    assert body.shots + again.shots == 1 and bus.resets == [] and bus.opened == ["usb:001,004"]


def _lost_auto_exposure(fake, bodies, tmp_path, clock, card):
    """A D5300 on auto exposing 40 s to its card, its release outliving the capture's deadline (then set to 1 s
    on its dial); returns the camera, the body's settings and its bus."""
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    config = bodies.nikon_d5300(quality="NEF (Raw)", shutter="auto")
    body = bodies.Body(config, files=(("DSC_0001.NEF", 2.0),), clock=clock, auto_exposure_s=40.0, store=card)
    bus = bodies.Bus("Nikon DSC D5300", body)
    camera = fake(bus, clock=clock)
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    with pytest.raises(CameraError, match=r"exposure time is unknown"):
        camera.capture(tmp_path / "1")
    assert list(card) == ["DSC_0001.NEF"] and list((tmp_path / "1").iterdir()) == []
    config.get_child_by_name("shutterspeed").value = "1.0000s"
    return camera, config, bus


# the same camera captures again (reconnecting), or the failed step paused the run, which let the camera go, and
# the resumed run's camera captures (a new camera, a new session)
@pytest.mark.parametrize("resumed", [False, True])
def test_the_file_of_a_lost_exposure_is_deleted_by_the_next_capture(fake, bodies, tmp_path, resumed):
    from psfd.drivers.base import CameraSetup

    clock, card = bodies.Clock(), {}
    camera, config, bus = _lost_auto_exposure(fake, bodies, tmp_path, clock, card)
    note = "lost-Nikon_DSC_D5300-00000000000000000000000006909849.json"  # the body's model and serial number
    assert [p.name for p in camera.state_dir.iterdir()] == [note]
    again = bodies.Body(config, files=(("DSC_0001.NEF", 2.0),), clock=clock, store=card, shots=1)
    if resumed:
        camera.close()
        camera = fake(bodies.Bus("Nikon DSC D5300", again), clock=clock)
        camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    else:
        bus.bodies.append(again)
    files = camera.capture(tmp_path / "2")
    assert [f.read_bytes() for f in files] == [b"DSC_0002.NEF of shot 2"]
    assert camera.strays == [f"{again.FOLDER}/DSC_0001.NEF"] and card == {}  # nothing left to fill the card
    assert list(camera.state_dir.iterdir()) == []  # the body's note of the lost exposure is gone with it
    assert [f.name for f in camera.capture(tmp_path / "3")] == ["DSC_0003.NEF"] and again.shots == 3



def test_a_file_found_after_the_lost_exposure_could_have_ended_is_left_on_the_card(fake, bodies, tmp_path, caplog):
    """The run resumed the next morning: the new file on the card may be the lost exposure's, or a photograph
    someone took with the body meanwhile (when that exposure wrote none). Nothing is deleted that may be a
    user's photograph; the file is named, never taken as a frame, and the note is forgotten."""
    from psfd.drivers.base import CameraSetup

    clock, card = bodies.Clock(), {}
    camera, config, bus = _lost_auto_exposure(fake, bodies, tmp_path, clock, card)
    camera.close()
    clock.sleep(8 * 3600.0)
    again = bodies.Body(config, files=(("DSC_0001.NEF", 2.0),), clock=clock, store=card, shots=1)
    camera = fake(bodies.Bus("Nikon DSC D5300", again), clock=clock)
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    with caplog.at_level("WARNING", logger="psfd.drivers.gphoto"):
        files = camera.capture(tmp_path / "2")
    assert [f.read_bytes() for f in files] == [b"DSC_0002.NEF of shot 2"]
    assert list(card) == ["DSC_0001.NEF"] and camera.strays == []
    assert any("DSC_0001.NEF" in r.getMessage() and "left on the card" in r.getMessage() for r in caplog.records)
    assert list(camera.state_dir.iterdir()) == []

def test_a_late_file_of_a_capture_that_got_none_is_not_a_later_frame(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    # a Canon on auto exposing 40 s into its RAM: no file within the capture's deadline (30 s + nothing known)
    clock = bodies.Clock()
    config = bodies.canon_eos(lens_af=False, shutter="auto")
    body = bodies.Body(config, clock=clock, auto_exposure_s=40.0)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), clock=clock)
    camera.prepare(CameraSetup(focus="manual"))
    with pytest.raises(CameraError, match=r"capture produced no file within 30 s"):
        camera.capture(tmp_path / "1")
    camera.set("shutterspeed", "1/125")
    # the next step comes while that exposure may still be under way: not released, said in one line
    with pytest.raises(CameraError, match=r"^an earlier exposure .* may still be under way.*not released"):
        camera.capture(tmp_path / "2")
    assert body.shots == 1
    clock.sleep(15.0)  # its file comes: discarded, and the step is taken
    files = camera.capture(tmp_path / "3")
    assert [f.read_bytes() for f in files] == [b"IMG_0002.CR2 of shot 2"]
    assert camera.strays == [f"{body.FOLDER}/IMG_0001.CR2"] and body.store == {}


def test_a_file_the_camera_no_longer_holds(fake, bodies, tmp_path, caplog):
    from psfd.errors import CameraError

    # a late file of an earlier exposure that the body let go: nothing is left on the camera, nothing to say
    body = bodies.Body(bodies.canon_eos(), queued=["IMG_0000.JPG"], dropped=["IMG_0000.JPG", "IMG_0002.CR2"])
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), quiet_s=0.1)
    with caplog.at_level("DEBUG", logger="psfd.drivers.gphoto"):
        assert [f.name for f in camera.capture(tmp_path / "1")] == ["IMG_0001.CR2"]
    assert camera.strays == [f"{body.FOLDER}/IMG_0000.JPG"]
    assert not [r for r in caplog.records if "stays on the camera" in r.getMessage()]
    # the file of this exposure is gone before its download: the frame fails, said in one line
    with pytest.raises(CameraError, match=r"downloading IMG_0002.CR2 failed: the file is no longer on the camera.*"
                                          r"\[gphoto2 -108\]$"):
        camera.capture(tmp_path / "2")
    assert list((tmp_path / "2").iterdir()) == []
    assert [f.name for f in camera.capture(tmp_path / "3")] == ["IMG_0003.CR2"] and body.shots == 3


def test_an_autofocus_that_cannot_lock_is_named(fake, bodies, tmp_path):
    from psfd.errors import CameraError

    # Canon: the full press hunts, then answers DeviceBusy; each attempt takes longer than a plain call
    body = bodies.Body(bodies.canon_eos(lens_af=True), af_locks=False, af_hunt_s=0.4)
    bus = bodies.Bus("Canon EOS 5D Mark III", body)
    camera = fake(bus, timeout=0.3, busy_s=0.6, reconnect_s=0.2)
    with pytest.raises(CameraError, match=r"autofocus.*set the lens .* to M.*\[gphoto2 -110\]"):
        camera.capture(tmp_path)
    assert body.shots == 0 and bus.opened == ["usb:001,004"]  # refused, not taken for a lost camera
    # Nikon: 0xA002 Out of Focus, reported by libgphoto2 as an unspecified error
    body = bodies.Body(bodies.nikon_d5300(focus="AF-S"), af_locks=False)
    camera = fake(bodies.Bus("Nikon DSC D5300", body))
    with pytest.raises(CameraError, match=r"refused the release.*autofocus.*\[gphoto2 -1\]"):
        camera.capture(tmp_path)
    assert body.calls.count("trigger_capture") == 1  # an unspecified error is not retried


def test_a_full_card_is_named(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    body = bodies.Body(bodies.canon_eos(lens_af=False), card_shots=1)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), delete_after_download=False)
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    camera.capture(tmp_path / "1")
    with pytest.raises(CameraError, match=r"memory card is full.*\[gphoto2 -3\]"):
        camera.capture(tmp_path / "2")


def test_raw_and_jpeg_seconds_apart_are_one_exposure(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup

    files = (("IMG_0001.CR2", 0.1), ("IMG_0001.JPG", 1.6))  # the JPEG 1.5 s after the RAW
    body = bodies.Body(bodies.canon_eos(lens_af=False, image_format="RAW + Large Fine JPEG"), files=files)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body))
    camera.prepare(CameraSetup(focus="manual", raw=False))  # keeps RAW + JPEG: two files per exposure
    assert camera.files_per_exposure == 2
    first = camera.capture(tmp_path / "1")
    second = camera.capture(tmp_path / "2")
    assert [f.name for f in first] == ["IMG_0001.CR2", "IMG_0001.JPG"]
    assert [f.name for f in second] == ["IMG_0002.CR2", "IMG_0002.JPG"]
    assert (tmp_path / "1" / "IMG_0001.JPG").read_bytes() == b"IMG_0001.JPG of shot 1"
    assert body.store == {}  # every file deleted from the camera once downloaded


def test_a_late_file_of_an_earlier_exposure_is_not_this_exposures(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup

    # RAW+JPEG on a slow card: the first exposure's JPEG is written 30 s late, after its capture gave up with
    # the RAW alone and after the next capture's drain; the card writes it before the next exposure's files
    clock = bodies.Clock()
    config = bodies.canon_eos(lens_af=False, image_format="RAW + Large Fine JPEG")
    body = bodies.Body(config, files=(("IMG_0001.CR2", 0.5), ("IMG_0001.JPG", 1.0)), late={"IMG_0001.JPG": 30.5},
                       clock=clock)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), clock=clock)
    camera.prepare(CameraSetup(focus="manual", raw=False))
    assert [f.name for f in camera.capture(tmp_path / "1")] == ["IMG_0001.CR2"]  # 1 of 2 files, said in the log
    second = camera.capture(tmp_path / "2")
    assert [f.read_bytes() for f in second] == [b"IMG_0002.CR2 of shot 2", b"IMG_0002.JPG of shot 2"]
    assert camera.strays == [f"{body.FOLDER}/IMG_0001.JPG"] and body.store == {}
    assert [f.name for f in camera.capture(tmp_path / "3")] == ["IMG_0003.CR2", "IMG_0003.JPG"]


def test_a_file_queued_before_the_trigger_is_not_counted(fake, bodies, tmp_path):
    body = bodies.Body(bodies.canon_eos(), queued=["IMG_0000.JPG"])
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), quiet_s=0.2)
    assert [f.name for f in camera.capture(tmp_path)] == ["IMG_0001.CR2"]
    assert camera.strays == [f"{body.FOLDER}/IMG_0000.JPG"] and "IMG_0000.JPG" not in body.store


def test_a_file_queued_behind_a_flood_of_property_changes_is_not_this_exposure(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    # a frame the body wrote after an earlier capture gave up, reported 0.3 s into a second of property
    # changes that come every 5 ms and take 10 ms each to read: it is handed over some 0.6 s on
    clock = bodies.Clock()
    body = bodies.Body(bodies.canon_eos(lens_af=False), queued=[("IMG_0000.CR2", 0.3)], flood_s=1.0, clock=clock)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), clock=clock)
    camera.prepare(CameraSetup(focus="manual"))
    files = camera.capture(tmp_path / "1")
    assert [f.read_bytes() for f in files] == [b"IMG_0001.CR2 of shot 1"]
    assert camera.strays == [f"{body.FOLDER}/IMG_0000.CR2"] and body.store == {}
    # a body that never stops reporting changes (live view on): not released, said in one line
    body = bodies.Body(bodies.canon_eos(lens_af=False), flood_s=3600.0, clock=clock)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), clock=clock)
    with pytest.raises(CameraError, match=r"kept reporting events for 10 s before the release"):
        camera.capture(tmp_path / "2")
    assert body.shots == 0


def test_a_cable_pulled_mid_capture_reconnects_and_retries_once(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup

    config = bodies.canon_eos(lens_af=False)
    first = bodies.Body(config, unplug_after_trigger=True)
    again = bodies.Body(config)  # the same body after it re-enumerated, a new USB session
    bus = bodies.Bus("Canon EOS 5D Mark III", first, again, absent_scans=1)
    camera = fake(bus, quiet_s=0.1, reconnect_s=5.0)
    camera.prepare(CameraSetup())
    assert _value(config, "capturetarget") == "Internal RAM"
    files = camera.capture(tmp_path)
    assert [f.name for f in files] == ["IMG_0001.CR2"]
    assert files[0].read_bytes() == b"IMG_0001.CR2 of shot 1"  # shot again by the new session
    assert first.calls[-2:] == ["wait_for_event", "exit"]  # GP_ERROR_IO on the wait, then released
    assert bus.opened == ["usb:001,004", "usb:001,005"] and bus.resets == ["usb:001,004"]
    assert camera.port == "usb:001,005"
    assert _value(config, "capturetarget") == "Internal RAM"  # prepared again after the new session


def test_a_file_the_lost_exposure_left_on_the_card_is_collected_or_deleted(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup

    # the body wrote the exposure to its card, then the cable went before the file was announced
    config, card = bodies.canon_eos(lens_af=False), {}
    first = bodies.Body(config, unplug_after_trigger=True, store=card)
    again = bodies.Body(config, store=card, shots=1)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", first, again), quiet_s=0.1)
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))  # RAW: one file per exposure
    files = camera.capture(tmp_path / "1")
    assert [f.read_bytes() for f in files] == [b"IMG_0001.CR2 of shot 1"]
    assert again.shots == 1 and card == {}  # not shot again; nothing left on the card
    # files per exposure unknown: whether the file is the whole exposure is not known; deleted, shot again
    config, card = bodies.canon_eos(lens_af=False), {}
    first = bodies.Body(config, unplug_after_trigger=True, store=card)
    again = bodies.Body(config, store=card, shots=1)
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", first, again), quiet_s=0.1)
    files = camera.capture(tmp_path / "2")
    assert [f.read_bytes() for f in files] == [b"IMG_0002.CR2 of shot 2"]
    assert camera.strays == [f"{first.FOLDER}/IMG_0001.CR2"] and card == {}


def test_each_step_lists_only_the_folder_the_camera_writes_to(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup

    # a card used for months: three full DCF folders of earlier photographs beside the one the body writes to
    dcim = "/store_00020001/DCIM"
    earlier = {f"{dcim}/{100 + k}CANON": [f"IMG_{i:04d}.JPG" for i in range(2000)] for k in range(3)}
    config = bodies.canon_eos(lens_af=False)
    body = bodies.Body(config, folder=f"{dcim}/103CANON", card=earlier)
    bus = bodies.Bus("Canon EOS 5D Mark III", body)
    camera = fake(bus, quiet_s=0.1)
    camera.prepare(CameraSetup(focus="manual", capture_target="card"))
    camera.capture(tmp_path / "1")  # where the body writes is not known before its first frame: the whole card
    assert {folder for _, folder in body.listed} >= set(earlier)
    body.listed.clear()
    for step in (2, 3):
        camera.capture(tmp_path / str(step))
    assert body.listed == [("files", f"{dcim}/103CANON"), ("folders", dcim)] * 2
    # the cable goes after the next release, and the body opened the next folder for that frame: found there
    body.unplug_after_trigger = True
    again = bodies.Body(config, folder=f"{dcim}/104CANON", card={**earlier, f"{dcim}/103CANON": []},
                        store=body.store, shots=3)
    bus.bodies.append(again)
    files = camera.capture(tmp_path / "4")
    assert [f.read_bytes() for f in files] == [b"IMG_0004.CR2 of shot 4"]
    assert again.shots == 3 and body.store == {}  # not shot again, nothing left


def test_a_second_loss_fails_the_capture(fake, bodies, tmp_path):
    from psfd.errors import CameraError

    config = bodies.canon_eos()
    bus = bodies.Bus("Canon EOS 5D Mark III", bodies.Body(config, unplug_after_trigger=True),
                     bodies.Body(config, unplug_after_trigger=True))
    camera = fake(bus, quiet_s=0.1)
    with pytest.raises(CameraError, match=r"waiting for the capture failed: USB input/output failed.*\[gphoto2 -7\]"):
        camera.capture(tmp_path)
    assert len(bus.opened) == 2 and list(tmp_path.iterdir()) == []


def test_a_camera_that_stays_away_is_reported(fake, bodies, tmp_path):
    from psfd.errors import CameraError

    bus = bodies.Bus("Canon EOS 5D Mark III", bodies.Body(bodies.canon_eos(), unplug_after_trigger=True))
    camera = fake(bus, reconnect_s=0.5)
    with pytest.raises(CameraError, match=r"\[gphoto2 -7\]; reconnecting failed: no camera found"):
        camera.capture(tmp_path)


def test_bulb_needs_a_time_and_always_closes_the_shutter(fake, bodies, tmp_path):
    from psfd.drivers.base import CameraSetup
    from psfd.errors import CameraError

    body = bodies.Body(bodies.canon_eos(lens_af=False, shutter="bulb"))
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body))
    camera.prepare(CameraSetup())
    with pytest.raises(CameraError, match=r"shutterspeed is bulb: give the exposure time \(bulb_s\)"):
        camera.capture(tmp_path)
    assert body.shots == 0
    camera.prepare(CameraSetup(bulb_s=0.3))
    assert camera._capture_deadline() == (pytest.approx(30.0 + 0.6), 0.3)
    assert [f.name for f in camera.capture(tmp_path)] == ["IMG_0001.CR2"]
    (on, t_on), (off, t_off) = body.bulb_log
    assert (on, off) == (1, 0) and t_off - t_on >= 0.3


def test_no_file_within_the_deadline(fake, bodies, tmp_path):
    from psfd.errors import CameraError

    body = bodies.Body(bodies.canon_eos(), files=())
    camera = fake(bodies.Bus("Canon EOS 5D Mark III", body), capture_timeout=0.4)
    with pytest.raises(CameraError, match=r"capture produced no file within 0.4\d* s"):
        camera.capture(tmp_path)


def test_camera_setup_from_a_plan_table():
    from psfd.drivers.base import CameraSetup, settle
    from psfd.errors import BadInputError

    setup = CameraSetup.from_mapping({"focus": "manual", "settle_s": 3})
    assert setup.focus == "manual" and setup.settle_s == 3 and setup.raw and setup.capture_target == "ram"
    with pytest.raises(BadInputError, match="unknown camera setup key"):
        CameraSetup.from_mapping({"focuss": "manual"})
    with pytest.raises(BadInputError, match="focus = 'auto': use one of off, manual, any"):
        CameraSetup(focus="auto")
    waits = []
    clock = iter([10.5, 10.5]).__next__
    assert settle(2.0, since=10.0, sleep=waits.append, clock=clock) == pytest.approx(1.5) and waits == [1.5]
    assert settle(2.0, since=0.0, sleep=waits.append, clock=lambda: 10.0) == 0.0 and waits == [1.5]
