"""A camera driven through libgphoto2 (python-gphoto2): setup for PSF work, capture, download.

Plain hardware code in the style of python-gphoto2's examples: detect the
camera, read and write configuration widgets, trigger a capture and collect
the files it produces from camera events (a RAW+JPEG capture produces two
``GP_EVENT_FILE_ADDED``, not always close together), download them, delete
them from the camera.

`GPhotoCamera.prepare` sets a camera up for PSF work before the rail moves:
a full-resolution RAW format (refused when there is none), the capture
target, single-frame drive, exposure delay where the body offers it over USB,
and autofocus off. `GPhotoCamera.capture` drains stale events before the
trigger (until the camera reports none), retries a busy camera with backoff (a
release answered busy only once the body answers again and no file came of it: the
release may have been taken), waits as long as the exposure needs, collects every
file of the exposure (a file carrying the number of an earlier exposure that may not
have been whole is discarded, whenever it comes), and reconnects once (with a USB
reset where the device is still there) when the camera was lost: the file a lost
exposure left on the card is collected or deleted, and an exposure of unknown length
is never cut short by a reset. An exposure whose capture failed without its file is
remembered (on disk too, by the body's serial number): the next capture on the body
deletes its file once it is there, and is not released while that exposure may still
be going on without having written it. Before a release to the card, only the folder
the camera writes to is listed (and the folders new or numbered next beside it).

Every libgphoto2 call runs in a worker thread with a deadline: python-gphoto2
releases the GIL during libgphoto2 calls, so a camera unplugged in the middle of
a USB transfer ends in a `CameraError` instead of freezing the service.
"""

from __future__ import annotations

import datetime
import json
import logging
import math
import os
import posixpath
import re
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

import gphoto2 as gp

from psfd.drivers.base import CameraInfo, CameraReady, CameraSetup
from psfd.drivers.recording import free_name
from psfd.errors import CameraError
from psfd.exif import exposure_seconds
from psfd.vocabulary import data_dir, offered_choice

log = logging.getLogger(__name__)

# Our setting names -> the widget names vendors use for them (first found wins).
SETTING_ALIASES = {
    "aperture": ("aperture", "f-number", "fnumber"),
    "shutterspeed": ("shutterspeed", "shutterspeed2", "exposuretime"),
    "iso": ("iso", "isospeed"),
    "imageformat": ("imageformat", "imagequality"),
    "capturetarget": ("capturetarget",),
}

# Widgets `prepare` looks at, in the order tried (names of libgphoto2's ptp2 driver).
DRIVE_WIDGETS = ("drivemode", "capturemode", "stillcapturemode")  # Canon EOS; Nikon and Sony
# ``autofocus`` is the ptp2 driver's own switch for focusing before a capture (Nikon and
# generic PTP bodies); ``continuousaf`` is Canon's continuous AF in live view.
AF_SWITCH_WIDGETS = ("autofocus", "continuousaf")
# What the lens or body reports: Canon ``focusmode`` (One Shot / AI Servo / Manual: the lens
# AF/MF switch), Nikon ``focusmode`` (read-only on many bodies) and ``focusmode2`` (MF (fixed)).
FOCUS_MODE_WIDGETS = ("focusmode", "focusmode2")
# Nikon's exposure delay raises the mirror and waits before the shutter. Canon bodies keep
# mirror lock-up in a custom function (``customfuncex``, a raw list of numbers per model),
# which is not set from here: the settle time still applies to them.
DELAY_WIDGETS = ("exposuredelaymode",)

# What the usual libgphoto2 failures mean for the person at the bench.
_CARD_FULL = "on a capture: the camera's memory card is full; free it, or capture to RAM"
_HINTS = {
    gp.GP_ERROR_IO_USB_CLAIM: "the camera is claimed by another process (a desktop photo importer such as "
    "gvfs-gphoto2-volume-monitor, or another gphoto2): close it and retry",
    gp.GP_ERROR_IO_USB_FIND: "the camera is gone from the USB bus (unplugged or switched off)",
    gp.GP_ERROR_MODEL_NOT_FOUND: "the camera is gone (unplugged or switched off)",
    gp.GP_ERROR_IO: "USB input/output failed: the camera was unplugged, switched off or went to sleep",
    gp.GP_ERROR_IO_READ: "reading from the camera failed: the camera was unplugged or switched off",
    gp.GP_ERROR_IO_WRITE: "writing to the camera failed: the camera was unplugged or switched off",
    gp.GP_ERROR_TIMEOUT: "the camera did not answer in time",
    gp.GP_ERROR_CAMERA_BUSY: "the camera is busy (still writing a previous frame, or in a menu)",
    gp.GP_ERROR_NOT_SUPPORTED: "the camera does not support this operation",
    # libgphoto2's ptp2 driver: a Canon release refused with "Perhaps no more memory on card?"
    gp.GP_ERROR_NO_MEMORY: f"out of memory ({_CARD_FULL})",
    gp.GP_ERROR_NO_SPACE: f"not enough free space ({_CARD_FULL})",
    gp.GP_ERROR_FILE_NOT_FOUND: "the file is no longer on the camera (a frame in the camera's RAM that the body let "
    "go, or one deleted on the body)",
    gp.GP_ERROR_DIRECTORY_NOT_FOUND: "the folder is no longer on the camera (the card was changed or formatted)",
}
# What else a camera that refuses a release means. A Canon EOS whose autofocus cannot lock answers
# the full press with PTP DeviceBusy (-110) after hunting (libgphoto2 issues #304, #655); a Nikon
# answers "Out of Focus" (0xA002), which libgphoto2 reports as an unspecified error (-1).
_AF_REFUSED = ("the autofocus could not lock, so the camera would not release: set the lens (or body) focus "
               "switch to M; with focus = \"off\" or \"manual\" this means the lens or body is still on AF")
# The longest shutter speed a body's own exposure program chooses (30 s on DSLRs and mirrorless bodies):
# how long an exposure of unknown length may go on, twice over with long-exposure noise reduction.
_LONGEST_PROGRAM_S = 30.0
# Failures after which the camera handle is useless: reconnect (a USB reset if the device
# is still on the bus) and retry once. A claim by another process is not one of them.
GONE_CODES = frozenset({gp.GP_ERROR_IO, gp.GP_ERROR_IO_READ, gp.GP_ERROR_IO_WRITE, gp.GP_ERROR_IO_USB_FIND,
                        gp.GP_ERROR_MODEL_NOT_FOUND, gp.GP_ERROR_TIMEOUT})


class GPhotoCamera:
    """`Camera` on a USB camera through libgphoto2.

    Parameters
    ----------
    port : str, optional
        libgphoto2 port such as ``usb:001,005``; None auto-detects the single camera connected.
    timeout : float
        Seconds allowed for one call (settings, one event wait, one download).
    capture_timeout : float
        Seconds allowed from the trigger to the last file of a capture on top of the
        exposure itself: writing and announcing a RAW file. The exposure time (twice
        it, for the dark frame of long-exposure noise reduction) and the exposure
        delay are added from the camera's settings at each capture.
    quiet_s : float
        When the number of files per exposure is unknown (no `prepare`, or a format
        that does not tell), a capture is complete after this long without a new file.
    busy_s : float
        How long a busy camera (gphoto2 -110) is retried, with backoff from 0.1 s to 2 s. After a
        release, a body busy exposing or writing is waited for until the capture's deadline instead.
    drain_s : float
        Longest time spent discarding stale events before a trigger; a camera that still reports
        events then is not released (a file of an earlier exposure may be among them).
    reconnect_s : float
        How long a lost camera is waited for (re-enumeration after a USB reset or a replug).
    delete_after_download : bool
        Delete each file from the camera once downloaded (keeps the card from filling overnight).
    state_dir : path, optional
        Where an exposure whose capture failed without its file is remembered for the body (by model and
        serial number) until its file is found, so that a later camera on that body finds it too
        (default ``$XDG_DATA_HOME/psfd/cameras``).
    """

    def __init__(
        self,
        port: str | None = None,
        timeout: float = 10.0,
        capture_timeout: float = 30.0,
        quiet_s: float = 1.0,
        busy_s: float = 10.0,
        drain_s: float = 10.0,
        reconnect_s: float = 20.0,
        delete_after_download: bool = True,
        state_dir: str | Path | None = None,
    ) -> None:
        self.timeout = float(timeout)
        self.capture_timeout = float(capture_timeout)
        self.quiet_s = float(quiet_s)
        self.busy_s = float(busy_s)
        self.drain_s = float(drain_s)
        self.reconnect_s = float(reconnect_s)
        self.delete_after_download = delete_after_download
        self.state_dir = Path(state_dir) if state_dir is not None else data_dir() / "cameras"
        self.files_per_exposure: int | None = None  # set by prepare from the image format
        self.strays: list[str] = []  # files announced outside any capture, discarded
        self._setup: CameraSetup | None = None
        self._delay_s = 0.0
        # of the capture under way: whether the shutter was released, the files on the card before it
        self._released = False
        self._card_before: set[tuple[str, str]] | None = None
        self._exposure_unknown = False
        self._released_at = 0.0  # wall-clock time of the release (a lost exposure outlives the process)
        self._serial, self._deadline_s = "", 0.0
        # an exposure whose capture failed without its file, which may still write one (`_note_lost`)
        self._lost: dict[str, Any] | None = None
        self._discarded: set[tuple[str, str]] = set()  # files discarded as strays (one may be announced later)
        # (folder, DCF stem) of exposures filed or discarded whose files may still come: how many (None: unknown)
        self._open: dict[tuple[str, str], int | None] = {}
        # the card folder the camera wrote its last frame to, and the folders a listing of the whole card found
        self._writes_to: str | None = None
        self._folders_seen: set[str] = set()
        self._camera: Any = None
        self._model = ""
        self.port = ""
        self._connect(port)

    # ------------------------------------------------------------------ connection

    def _connect(self, port: str | None, model: str | None = None) -> None:
        """Find the camera (by port, by driver model, or the only one) and initialise it."""
        found = self._call("detecting cameras", _detect)
        if port is not None:
            matches = [c for c in found if c[1] == port]
        elif model is not None:
            matches = [c for c in found if c[0] == model]
        else:
            matches = found
        listing = ", ".join(f"{name} on {addr}" for name, addr in found) or "none"
        if not matches:
            where = f" on {port}" if port else ""
            raise CameraError(f"no camera found{where} (detected: {listing}); check the cable and that it is on")
        if len(matches) > 1:
            raise CameraError(f"several cameras found ({listing}); give the port of the one to use")
        self._model, self.port = matches[0]
        self._camera = self._call(f"connecting to {self._model}", _open_camera, self._model, self.port)

    def reconnect(self, reset_usb: bool = True, wait_s: float = 0.0) -> None:
        """Release the camera, reset its USB device if possible, and connect again.

        After a USB reset or a replug the device comes back at another address,
        so the camera is found again by its driver model, for up to ``wait_s``
        seconds. A camera prepared before is prepared again (Canon bodies forget
        the capture target with the USB session).
        """
        self.close()
        if reset_usb and self.port.startswith("usb:"):
            if reset_usb_device(self.port):
                time.sleep(2.0)  # the camera re-enumerates after a bus reset
        deadline = time.monotonic() + wait_s
        while True:
            try:
                self._connect(None, model=self._model)
                break
            except CameraError:
                if time.monotonic() >= deadline:
                    raise
                time.sleep(1.0)
        if self._setup is not None:
            self.prepare(self._setup)

    def close(self) -> None:
        """Release the camera (idempotent)."""
        camera, self._camera = self._camera, None
        if camera is not None:
            try:
                self._run(camera.exit, (), self.timeout)
            except (gp.GPhoto2Error, TimeoutError):
                pass  # releasing a camera that is already gone is not an error

    def __enter__(self) -> "GPhotoCamera":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ Camera protocol

    def info(self) -> CameraInfo:
        """Model, serial and lens from the status widgets the camera reports."""
        config = self._config()
        values = {name: _widget_value(config, name) for name in (
            "manufacturer", "cameramodel", "serialnumber", "eosserialnumber", "lensname", "focallength")}
        manufacturer, model = values["manufacturer"] or "", values["cameramodel"] or self._model
        if manufacturer and not model.lower().startswith(manufacturer.lower()):
            model = f"{manufacturer} {model}"
        return CameraInfo(
            model=model,
            serial=_serial(config),
            lens=values["lensname"] or "",
            focal_length_mm=_leading_number(values["focallength"]),
            port=self.port,
        )

    def get(self, name: str) -> str:
        """Current value of a setting (``aperture`` is given without an ``f/`` prefix)."""
        widget, _ = self._find(self._config(), name)
        return _normalise(name, str(self._call(f"reading {name}", widget.get_value)))

    def choices(self, name: str) -> list[str]:
        """Values offered for a setting (empty for a free-form setting)."""
        widget, _ = self._find(self._config(), name)
        return [_normalise(name, c) for c in _widget_choices(widget)]

    def set(self, name: str, value: str) -> None:
        """Set a setting; a value not offered raises CameraError listing the offered ones."""
        config = self._config()
        widget, vendor = self._find(config, name)
        if widget.get_readonly():
            raise CameraError(f"{name} ({vendor}) is read-only on this camera (mode dial or lens may fix it)")
        offered = _widget_choices(widget)
        if offered:
            raw = offered_choice(str(value), offered)
            if raw is None:
                listing = ", ".join(_normalise(name, c) for c in offered)
                raise CameraError(f"{name} {value} is not offered by the camera (offered: {listing})")
        else:
            raw = str(value)
        self._call(f"setting {name}", widget.set_value, raw)
        self._call(f"setting {name}", self._cam().set_config, config)

    def prepare(self, setup: CameraSetup) -> CameraReady:
        """Set the camera up for PSF work before the rail moves; see `CameraSetup`.

        In order: a full-resolution RAW format (raw-only preferred, RAW+JPEG
        accepted, reduced sRAW/mRAW never: they are not the sensor's mosaic), the
        capture target, single-frame drive (a self-timer or burst changes what one
        trigger does), the exposure delay, and autofocus off.

        Raises
        ------
        CameraError
            The camera offers no RAW format, autofocus stays on (the lens or body
            switch is on AF), ``focus = "manual"`` and nothing reports the focus
            mode, or a setting did not take.
        """
        notes: list[str] = []
        image_format, files = self._prepare_format(setup)
        target = self._prepare_one(
            "capture target", ("capturetarget",), lambda c: _target_choice(c, setup.capture_target), notes)
        drive = self._prepare_one("drive mode", DRIVE_WIDGETS, _single_choice, notes)
        delay = self._prepare_delay(setup, notes)
        focus, detail = self._prepare_focus(setup, notes)
        self._setup, self.files_per_exposure = setup, files
        # Nikon's plain "On" waits about a second (up to 3 s on recent bodies)
        self._delay_s = _leading_number(delay) or (3.0 if delay and delay.lower() == "on" else 0.0)
        for note in notes:
            log.warning("camera %s: %s", self._model, note)
        return CameraReady(
            image_format=image_format, files_per_exposure=files, capture_target=target,
            focus=focus, focus_detail=detail, exposure_delay=delay, drive_mode=drive,
            settle_s=float(setup.settle_s), notes=tuple(notes),
        )

    def capture(self, dest: Path) -> list[Path]:
        """One exposure, every file it produced (RAW, RAW+JPEG) downloaded into ``dest``.

        A camera lost on the way (unplugged, switched off, hung in a transfer) is
        reconnected, prepared again, and the capture retried once. A file that an exposure
        released before the loss left on the card is this capture's frame when it is the whole
        of one exposure (`_left_on_card`), and deleted otherwise. When the exposure time is not
        known (no shutter speed setting, or ``auto``), a camera that stops answering after the
        release may still be exposing: it is neither reset nor released again, the capture fails,
        and the file that exposure writes is deleted by a later capture (`_settle_lost`).
        """
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        try:
            return self._capture_once(dest)
        except CameraError as exc:
            if not getattr(exc, "gone", False):
                raise
            if self._released and self._exposure_unknown:
                self._note_lost()
                raise CameraError(f"{exc}; the exposure time is unknown (no shutter speed set to a time), so the "
                                  "camera may still be exposing: not reset or released again") from None
            log.warning("camera %s lost during a capture (%s): reconnecting and retrying once", self._model, exc)
            released, before = self._released, self._card_before
            try:
                self.reconnect(reset_usb=True, wait_s=self.reconnect_s)
            except CameraError as again:
                raise CameraError(f"{exc}; reconnecting failed: {again}") from None
            left = self._left_on_card(before) if released and before is not None else []
            return self._fetch(left, dest) if left else self._capture_once(dest)

    # ------------------------------------------------------------------ preparation steps

    def _prepare_format(self, setup: CameraSetup) -> tuple[str | None, int | None]:
        """Set a RAW image format; returns the camera's value and the files one exposure gives."""
        widget, name = self._first(SETTING_ALIASES["imageformat"])
        if widget is None:
            if setup.raw:
                raise CameraError(f"camera {self._model} has no image format setting, so RAW cannot be set "
                                  "or verified over USB; refusing before any motion")
            return None, None
        current, offered = str(widget.get_value()), _widget_choices(widget)
        if not setup.raw:
            return current, _files_of(current)
        best = raw_choice(current, offered)
        if best is None:
            raise CameraError(f"camera {self._model} cannot shoot full-resolution RAW ({name} offers: "
                              f"{', '.join(offered) or 'nothing'}); refusing before any motion")
        if best != current:
            if widget.get_readonly():
                raise CameraError(f"camera {self._model} is set to {current} and {name} is read-only (an automatic "
                                  "mode on the dial?): set it to RAW on the body; refusing before any motion")
            self._apply(name, best)
        return best, _files_of(best)

    def _prepare_one(self, what: str, names: tuple[str, ...], pick: Callable[[list[str]], str | None],
                     notes: list[str]) -> str | None:
        """Set the first of ``names`` the camera has to the choice ``pick`` makes; returns the value."""
        widget, name = self._first(names)
        if widget is None:
            notes.append(f"no {what} setting: the camera's own default applies")
            return None
        current, offered = str(widget.get_value()), _widget_choices(widget)
        wanted = pick(offered)
        if wanted is None or wanted == current:
            if wanted is None:
                notes.append(f"{what} left at {current} (none of {', '.join(offered)} fits)")
            return current
        if widget.get_readonly():
            notes.append(f"{what} is {current} and read-only here (wanted {wanted})")
            return current
        self._apply(name, wanted)
        return wanted

    def _prepare_delay(self, setup: CameraSetup, notes: list[str]) -> str | None:
        widget, name = self._first(DELAY_WIDGETS)
        if widget is None:
            if setup.exposure_delay:
                notes.append("no exposure delay or mirror lock-up setting over USB: only the settle time "
                             "damps vibrations (set mirror lock-up on the body if it has one)")
            return None
        current = str(widget.get_value())
        if not setup.exposure_delay or widget.get_readonly():
            return current
        wanted = _delay_choice(_widget_choices(widget))
        if wanted is not None and wanted != current:
            self._apply(name, wanted)
            return wanted
        return current

    def _prepare_focus(self, setup: CameraSetup, notes: list[str]) -> tuple[str, str]:
        """Turn autofocus off where a widget allows it; returns (state, what the camera reports)."""
        if setup.focus == "any":
            reports = self._focus_reports()
            return ("manual" if any(_is_manual(v) for v in reports.values()) else
                    "af" if reports else "unknown"), _describe(reports)
        switched = []
        for name in AF_SWITCH_WIDGETS:
            widget, _ = self._first((name,))
            if widget is None or widget.get_readonly():
                continue
            off = _off_choice(_widget_choices(widget))
            if off is not None:
                if str(widget.get_value()) != off:
                    self._apply(name, off)
                switched.append(f"{name} = {off}")
        for name in FOCUS_MODE_WIDGETS:
            widget, _ = self._first((name,))
            if widget is None or widget.get_readonly() or _is_manual(str(widget.get_value())):
                continue
            manual = next((c for c in _widget_choices(widget) if _is_manual(c)), None)
            if manual is not None:
                self._apply(name, manual)
        reports = self._focus_reports()
        detail = _describe(reports, switched)
        if any(_is_manual(v) for v in reports.values()):
            return "manual", detail
        if reports:
            raise CameraError(f"camera {self._model} reports autofocus ({detail}) and it cannot be turned off "
                              "over USB: set the lens (or body) focus switch to M; refusing before any motion")
        if switched:
            return "af-off", detail
        if setup.focus == "manual":
            raise CameraError(f"camera {self._model} reports no focus mode, so manual focus cannot be confirmed "
                              "(focus = \"manual\"): check the lens switch and use focus = \"off\" to go on")
        notes.append("the camera reports no focus mode: make sure the lens is on manual focus")
        return "unknown", detail

    def _focus_reports(self) -> dict[str, str]:
        config = self._config()
        return {n: v for n in FOCUS_MODE_WIDGETS if (v := _widget_value(config, n)) is not None}

    # ------------------------------------------------------------------ capture steps

    def _capture_once(self, dest: Path) -> list[Path]:
        self._released, self._card_before = False, None
        config = self._config()
        timeout, bulb_s = self._capture_deadline(config)
        self._serial, self._deadline_s = _serial(config), timeout
        if self._lost is None:  # a camera on this body before may have lost an exposure
            self._lost = self._read_lost()
        self._drain()
        if self._on_card():
            self._card_before = self._card_files()
        self._settle_lost(self._card_before)
        files = self._trigger_and_collect(timeout, bulb_s)
        self._still_open(files)
        return self._fetch(files, dest)

    def _fetch(self, paths: list[tuple[str, str]], dest: Path) -> list[Path]:
        """Download the files of one exposure into ``dest`` (and delete them from the camera)."""
        saved = []
        if paths:
            self._wrote_in(paths[-1][0])
        for folder, name in paths:
            saved.append(self._download(folder, name, dest))
            if self.delete_after_download:
                self._delete(folder, name)
        return saved

    def _still_open(self, files: list[tuple[str, str]]) -> None:
        """Remember an exposure of ``files`` that may not be whole, so that a file of it coming later is no frame.

        A body names the files of one exposure with one file number (DCF: ``IMG_0002.CR2``, ``IMG_0002.JPG``)
        and libgphoto2 passes that name on; a file of this exposure written after its capture gave up (a slow
        card) comes with the next exposure's, as the first file the body writes after the next release.
        """
        expected = self.files_per_exposure
        for folder, stem in {(f, Path(n).stem) for f, n in files}:
            owed = None if expected is None else expected - sum(Path(n).stem == stem for _, n in files)
            if owed is None or owed > 0:
                self._open[(folder, stem)] = owed
        while len(self._open) > 16:  # exposures of unknown count: only the latest can still be writing
            del self._open[next(iter(self._open))]

    def _earlier(self, folder: str, name: str) -> bool:
        """Whether a file announced now belongs to an exposure filed or discarded before (`_still_open`);
        if so it is discarded as a stray."""
        if (folder, name) in self._discarded:
            log.debug("camera %s: %s/%s, discarded before, was announced now", self._model, folder, name)
            return True
        key = (folder, Path(name).stem)
        if key not in self._open:
            return False
        owed = self._open.pop(key)
        if owed is None or owed > 1:
            self._open[key] = None if owed is None else owed - 1
        self._stray(folder, name, "belongs to an earlier exposure (it carries that exposure's file number)")
        return True

    def _stray(self, folder: str, name: str, why: str) -> None:
        """Discard a file that is no frame of this capture: noted, and deleted from the camera."""
        self.strays.append(f"{folder}/{name}")
        self._discarded.add((folder, name))
        log.warning("camera %s: %s/%s %s; not counted", self._model, folder, name, why)
        if self.delete_after_download:
            self._delete(folder, name)

    def _on_card(self) -> bool:
        """Whether captures go to the card (so that they outlive a lost USB session); unprepared: may be."""
        return self._setup is None or self._setup.capture_target == "card"

    def _card_files(self) -> set[tuple[str, str]]:
        """(folder, name) of the files on the card wherever a new file can appear.

        Listing a folder makes libgphoto2 read the information of every object in it: on a card that holds
        months of photographs that grows with the card, each step. So once the camera has written a frame in
        this session, only the folder it writes to is listed, with the folders beside it that are new or
        numbered next (a body moves on to the next DCF folder when one is full, libgphoto2's virtual camera
        every 100 file numbers, whether that folder is there already or not); before that, the whole card.
        """
        if self._writes_to is None:
            return self._walk("/")
        found = self._files_in(self._writes_to)
        number = _folder_number(self._writes_to)
        for folder in self._subfolders(posixpath.dirname(self._writes_to)):
            following = number is not None and _folder_number(folder) == number + 1
            if folder != self._writes_to and (following or folder not in self._folders_seen):
                found |= self._walk(folder)
        return found

    def _walk(self, folder: str) -> set[tuple[str, str]]:
        """(folder, name) of every file below ``folder``; the folders found are remembered as seen."""
        self._folders_seen.add(folder)
        found = self._files_in(folder)
        for sub in self._subfolders(folder):
            found |= self._walk(sub)
        return found

    def _files_in(self, folder: str) -> set[tuple[str, str]]:
        files = self._call("listing the camera's files", self._cam().folder_list_files, folder)
        return {(folder, files.get_name(i)) for i in range(files.count())}

    def _subfolders(self, folder: str) -> list[str]:
        folders = self._call("listing the camera's folders", self._cam().folder_list_folders, folder)
        return [posixpath.join(folder, folders.get_name(i)) for i in range(folders.count())]

    def _wrote_in(self, folder: str) -> None:
        """The camera wrote a frame in ``folder``: listings look there (`_card_files`)."""
        folder = folder.rstrip("/") or "/"
        if self._writes_to is not None and folder != self._writes_to:
            self._folders_seen.add(self._writes_to)
        self._writes_to = folder

    def _left_on_card(self, before: set[tuple[str, str]]) -> list[tuple[str, str]]:
        """The files an exposure released before the camera was lost wrote to the card, if they are one exposure.

        Files new since ``before`` (the listing just before the release) are the whole of that exposure
        when they are as many as one exposure gives and share one name (a RAW and its JPEG); otherwise
        (the RAW of a pair without its JPEG, or a count not known) they are deleted, as files of no
        capture, and the exposure is taken again.
        """
        new = sorted(self._card_files() - before)
        if len(new) == self.files_per_exposure and len({Path(name).stem for _, name in new}) == 1:
            log.warning("camera %s: %s, written before the camera was lost, is this capture's", self._model,
                        ", ".join(name for _, name in new))
            return new
        for folder, name in new:
            self._stray(folder, name, "was written before the camera was lost and is not known to be a whole exposure")
        return []

    # ------------------------------------------------------------------ an exposure whose capture failed

    def _note_lost(self) -> None:
        """Remember the exposure released in this capture, which failed without its file: it may still write one.

        Until that file is found (`_settle_lost`), or the exposure cannot be going on any longer, no capture on
        this body is released: the file would come with that capture's. With a serial number the note is kept
        on disk too, for the next camera on the body (a failed step pauses the run, which lets the camera go).
        """
        longest = 2.0 * _LONGEST_PROGRAM_S if self._exposure_unknown else 0.0
        before = self._card_before
        self._lost = {
            "model": self._model, "serial": self._serial, "released": self._released_at,
            "until": self._released_at + 2.0 * self._deadline_s + longest,
            # the folders listed before the release, and their files: the file is looked for there
            "folders": None if before is None else [self._writes_to] if self._writes_to else sorted(self._folders_seen),
            "before": None if before is None else sorted([folder, name] for folder, name in before),
        }
        path = self._lost_path()
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
            try:
                with os.fdopen(fd, "w") as stream:
                    json.dump(self._lost, stream)
                os.replace(tmp, path)
            finally:
                Path(tmp).unlink(missing_ok=True)
        except OSError as exc:  # the capture's own error is the one to report; this camera still remembers
            log.warning("camera %s: the exposure whose capture failed is not remembered in %s (%s)",
                        self._model, path, exc)

    def _settle_lost(self, listing: set[tuple[str, str]] | None) -> None:
        """Before a release: delete the file of an exposure whose capture failed (`_note_lost`) once it is on the
        card, and refuse the release while that exposure may still be going on without having written it.

        Its file is the lowest-numbered new one in the folders listed before its release (the body numbers on,
        so files written later by the body carry higher numbers), with the files of the same number. Found
        only after that exposure could have ended (a run resumed later), it may as well be a photograph taken
        with the body meanwhile, when the exposure wrote none: it is named and left on the card.
        """
        lost = self._lost
        if lost is None:
            return
        if listing is not None and lost["before"] is not None:
            found = _first_exposure(listing, lost["folders"], {tuple(f) for f in lost["before"]},
                                    self.files_per_exposure)
            if found and time.time() >= lost["until"]:
                log.warning("camera %s: %s, new on the card since the exposure released at %s whose capture failed, "
                            "is left on the card: it is that exposure's file or a photograph taken since",
                            self._model, ", ".join(f"{folder}/{name}" for folder, name in found),
                            _clock(lost["released"]))
            elif found:
                for folder, name in found:
                    self._stray(folder, name, "was written by an exposure whose capture failed")
                self._still_open(found)  # the JPEG of a RAW found may come later
            if found:
                self._forget_lost()
                return
        if time.time() < lost["until"]:
            raise CameraError(
                f"an earlier exposure (released at {_clock(lost['released'])}, its capture failed) may still be under "
                f"way and has written no file yet: not released until it has, or until {_clock(lost['until'])}, "
                "so that its file is not taken for this one")
        log.warning("camera %s: no file came of the exposure released at %s whose capture failed; not looked for any "
                    "more", self._model, _clock(lost["released"]))
        self._forget_lost()

    def _lost_path(self) -> Path | None:
        """The note of this body's lost exposure; None without a serial number (bodies could not be told apart)."""
        if not self._serial:
            return None
        return self.state_dir / re.sub(r"[^A-Za-z0-9.-]+", "_", f"lost-{self._model}-{self._serial}.json")

    def _read_lost(self) -> dict[str, Any] | None:
        path = self._lost_path()
        if path is None or not path.exists():
            return None
        try:
            lost = json.loads(path.read_text())
            if {"released", "until", "folders", "before"} <= set(lost):
                return lost
        except (OSError, ValueError):
            pass
        log.warning("camera %s: %s is not a note of a lost exposure; ignored", self._model, path)
        return None

    def _forget_lost(self) -> None:
        self._lost = None
        path = self._lost_path()
        if path is not None:
            path.unlink(missing_ok=True)

    def _capture_deadline(self, config: Any = None) -> tuple[float, float | None]:
        """Seconds allowed from the trigger to the last file, and the bulb time if the camera is on bulb."""
        config = self._config() if config is None else config
        shutter = next((v for n in SETTING_ALIASES["shutterspeed"] if (v := _widget_value(config, n))), None)
        seconds = exposure_seconds(shutter)
        self._exposure_unknown = seconds is None  # the capture's deadline cannot follow the exposure
        seconds = seconds or 0.0
        bulb_s = None
        if math.isinf(seconds):
            bulb_s = self._setup.bulb_s if self._setup is not None else None
            if bulb_s is None:
                raise CameraError(f"shutterspeed is {shutter}: give the exposure time (bulb_s) or set a timed "
                                  "shutter speed")
            seconds = bulb_s
        # long-exposure noise reduction takes a dark frame as long as the exposure
        return self.capture_timeout + 2.0 * seconds + self._delay_s, bulb_s

    def _drain(self) -> None:
        """Discard events queued before the trigger, up to the camera's first GP_EVENT_TIMEOUT.

        A file among them belongs to no capture of ours. libgphoto2 hands events over in the order
        the body reported them and answers GP_EVENT_TIMEOUT only once nothing is queued and nothing
        came for the whole wait, so no file announced before the timeout can come after the release.
        A body may report property changes faster than they are read, a stale file queued behind
        them: a drain stopped by a clock would let that file through as the next exposure's.
        """
        deadline = time.monotonic() + self.drain_s
        while True:
            event, data = self._call("draining camera events", self._cam().wait_for_event, 10,
                                     timeout=self.timeout)
            if event == gp.GP_EVENT_TIMEOUT:
                return
            if event == gp.GP_EVENT_FILE_ADDED and not self._earlier(data.folder, data.name):
                self._stray(data.folder, data.name, "was announced after its capture had been collected"
                            if self._lost is None else "was written by an exposure whose capture failed")
                self._still_open([(data.folder, data.name)])
                if self._lost is not None:  # the first file the body wrote since is the lost exposure's
                    self._forget_lost()
            if time.monotonic() > deadline:
                raise CameraError(f"camera {self._model} kept reporting events for {self.drain_s:g} s before the "
                                  "release (live view on, or a menu open?): not released, since a file of an "
                                  "earlier exposure may be queued behind them")

    def _trigger_and_collect(self, timeout: float, bulb_s: float | None) -> list[tuple[str, str]]:
        """Trigger one exposure and gather the (folder, name) of each file it adds."""
        if bulb_s is None:
            return self._collect(*self._release_once(timeout), timeout)
        start = time.monotonic()
        self._released, self._released_at = True, time.time()
        self._bulb(bulb_s)
        return self._collect([], start, timeout)

    def _release_once(self, timeout: float) -> tuple[list[tuple[str, str]], float]:
        """Release the shutter for one exposure; returns the files already announced and when it was released.

        libgphoto2 answers busy (-110) both for a release the body refused (still writing a frame, an
        autofocus hunting) and for one it took: its Nikon path waits for the body while it exposes and
        gives up with -110 after a limit (5 s in 2.5.23, 20 s after libgphoto2 issue #465) while the
        exposure goes on. So a busy release is tried again only once the body answers again and has
        announced no file (`_after_busy_release`): a second release would take a second exposure.
        """
        pause, refused_s = 0.1, 0.0
        while True:
            start = time.monotonic()
            try:
                return self._release(timeout), start
            except CameraError as exc:
                code = getattr(exc, "code", None)
                if code == gp.GP_ERROR:
                    raise CameraError(f"camera {self._model} refused the release and libgphoto2 gives no reason; "
                                      f"most often {_AF_REFUSED} [gphoto2 {gp.GP_ERROR}]") from None
                if code != gp.GP_ERROR_CAMERA_BUSY:
                    raise
            files, busy_s = self._after_busy_release(pause, start, timeout)
            if files:
                return files, start
            refused_s += time.monotonic() - start - busy_s
            pause = min(2.0 * pause, 2.0)
            if refused_s + pause > self.busy_s:
                raise _stayed_busy(self.busy_s, "triggering a capture", _AF_REFUSED)
            log.info("camera %s refused the release as busy: releasing again", self._model)

    def _release(self, timeout: float) -> list[tuple[str, str]]:
        """One release; returns the file a blocking capture names (cameras without trigger_capture)."""
        self._released, self._released_at = True, time.time()  # from here on, an exposure may have been taken
        try:
            # a release may take the autofocus's hunt (some 10 s on a Canon) before it answers
            self._once("triggering a capture", self._cam().trigger_capture, timeout=timeout)
            return []
        except CameraError as exc:
            if getattr(exc, "code", None) != gp.GP_ERROR_NOT_SUPPORTED:
                raise
        # any further file of the same exposure still arrives as an event
        path = self._once("capturing", self._cam().capture, gp.GP_CAPTURE_IMAGE, timeout=timeout)
        return [(path.folder, path.name)]

    def _after_busy_release(self, window: float, start: float, timeout: float) -> tuple[list[tuple[str, str]], float]:
        """The file of a release answered busy, or none once the body answers and stays quiet for ``window``.

        A body that answers the event wait busy too is exposing or writing (a Nikon is busy to every
        request until the file is written): it is waited for up to the capture's deadline, which
        follows the exposure time, then given ``quiet_s`` to announce the file. Returns the files and
        the seconds the body answered busy.
        """
        entered, poll = time.monotonic(), 0.1
        busy_s, quiet_since = 0.0, entered
        while True:
            try:
                event, data = self._once("waiting for the capture", self._cam().wait_for_event, 100,
                                         timeout=0.1 + self.timeout)
            except CameraError as exc:
                if getattr(exc, "code", None) != gp.GP_ERROR_CAMERA_BUSY:
                    raise
                if time.monotonic() - start > timeout:
                    self._note_lost()
                    raise _busy_error(f"camera {self._model} stayed busy for {timeout:g} s after the release "
                                      "(exposure, delay and writing included): it may be hung; switch it off "
                                      "and on") from None
                time.sleep(poll)
                poll = min(2.0 * poll, 2.0)
                quiet_since = time.monotonic()
                busy_s, window = quiet_since - entered, max(window, self.quiet_s)
                continue
            if event == gp.GP_EVENT_FILE_ADDED and not self._earlier(data.folder, data.name):
                return [(data.folder, data.name)], busy_s
            if time.monotonic() - quiet_since >= window:
                return [], busy_s
            if event == gp.GP_EVENT_TIMEOUT:
                time.sleep(0.02)  # some drivers answer a wait at once: do not spin

    def _collect(self, files: list[tuple[str, str]], start: float, timeout: float) -> list[tuple[str, str]]:
        """Gather the files of the exposure released at ``start`` (``files``: those already announced)."""
        expected = self.files_per_exposure
        last_new = time.monotonic()
        while True:
            now = time.monotonic()
            if expected is not None and len(files) >= expected:
                return files
            if expected is None and files and now - last_new >= self.quiet_s:
                return files
            if now - start > timeout:
                if files:
                    log.warning("camera %s: %d of %d files of the exposure arrived within %g s",
                                self._model, len(files), expected or len(files), timeout)
                    return files
                self._note_lost()
                raise CameraError(f"capture produced no file within {timeout:g} s (exposure, delay and "
                                  "writing included)")
            wait_ms = 200 if expected is not None else int(1000 * min(self.quiet_s, self.timeout))
            # a body still exposing or writing may answer busy until the capture's deadline
            event, data = self._call("waiting for the capture", self._cam().wait_for_event, wait_ms,
                                     timeout=wait_ms / 1000 + self.timeout,
                                     busy_s=max(self.busy_s, start + timeout - now))
            if (event == gp.GP_EVENT_FILE_ADDED and (data.folder, data.name) not in files
                    and not self._earlier(data.folder, data.name)):
                files.append((data.folder, data.name))
                last_new = time.monotonic()
            elif event == gp.GP_EVENT_TIMEOUT and time.monotonic() - now < 0.01:
                time.sleep(0.02)  # some drivers answer a wait at once: do not spin

    def _bulb(self, seconds: float) -> None:
        """A bulb exposure of ``seconds``: the shutter is always closed again, whatever happens."""
        self._apply("bulb", 1, verify=False)
        try:
            time.sleep(seconds)
        finally:
            self._apply("bulb", 0, verify=False)

    def _download(self, folder: str, name: str, dest: Path) -> Path:
        """Copy one file from the camera into ``dest`` under a name not already used there."""
        camera_file = self._call(
            f"downloading {name}", self._cam().file_get, folder, name, gp.GP_FILE_TYPE_NORMAL
        )
        target = free_name(dest, name)
        tmp = target.with_name(f".{target.name}.part")
        try:
            self._call(f"saving {name}", camera_file.save, str(tmp))
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)
        return target

    def _delete(self, folder: str, name: str) -> None:
        try:
            self._call(f"deleting {name}", self._cam().file_delete, folder, name)
        except CameraError as exc:
            if getattr(exc, "gone", False):
                raise
            if getattr(exc, "code", None) in (gp.GP_ERROR_FILE_NOT_FOUND, gp.GP_ERROR_DIRECTORY_NOT_FOUND):
                log.debug("camera %s: %s is already gone from the camera", self._model, name)
                return
            # a read-only card, or a RAM capture the camera dropped itself: nothing is lost; but a
            # file left on the card (a body that stayed busy) fills it over a night
            log.log(logging.WARNING if self._on_card() else logging.DEBUG, "camera %s: %s stays on the camera (%s)",
                    self._model, name, exc)

    # ------------------------------------------------------------------ plumbing

    def _config(self) -> Any:
        return self._call("reading the configuration", self._cam().get_config)

    def _first(self, names: tuple[str, ...]) -> tuple[Any, str]:
        """The first widget of ``names`` the camera has, and its name (None, "" if none)."""
        config = self._config()
        for name in names:
            try:
                return config.get_child_by_name(name), name
            except gp.GPhoto2Error:
                continue
        return None, ""

    def _apply(self, name: str, value: Any, verify: bool = True) -> None:
        """Set vendor widget ``name`` to ``value`` and check that the camera kept it."""
        config = self._config()
        widget = config.get_child_by_name(name)
        self._call(f"setting {name}", widget.set_value, value)
        self._call(f"setting {name}", self._cam().set_config, config)
        if verify:
            now = _widget_value(self._config(), name)
            if now != str(value):
                raise CameraError(f"camera {self._model} kept {name} = {now} when set to {value} "
                                  "(the mode dial, a lens switch or a menu may fix it)")

    def _find(self, config: Any, name: str) -> tuple[Any, str]:
        """The widget behind one of our setting names (or a vendor widget name given as is)."""
        for vendor in SETTING_ALIASES.get(name, (name,)):
            try:
                return config.get_child_by_name(vendor), vendor
            except gp.GPhoto2Error:
                continue
        known = ", ".join(SETTING_ALIASES)
        raise CameraError(f"camera has no setting {name!r} (portable names: {known}; or a gphoto2 widget name)")

    def _cam(self) -> Any:
        if self._camera is None:
            error = CameraError("camera is not connected (closed, or lost after an earlier failure); reconnect it")
            error.gone = True  # type: ignore[attr-defined]
            raise error
        return self._camera

    def _call(self, what: str, fn: Callable, *args: Any, timeout: float | None = None,
              busy_s: float | None = None) -> Any:
        """`_once`, retried with backoff while the camera answers busy (gphoto2 -110), for ``busy_s``
        (default: the camera's ``busy_s``).

        PTP's DeviceBusy (0x2019, which libgphoto2 reports as -110) may answer any
        operation while the body writes a frame, not only the next release: reading
        the configuration, downloading and deleting are retried as the trigger is.
        """
        pause, started = 0.1, time.monotonic()
        allowed = self.busy_s if busy_s is None else busy_s
        while True:
            try:
                return self._once(what, fn, *args, timeout=timeout)
            except CameraError as exc:
                if getattr(exc, "code", None) != gp.GP_ERROR_CAMERA_BUSY:
                    raise
                if time.monotonic() - started + pause > allowed:
                    raise _stayed_busy(allowed, what) from None
                log.info("camera busy while %s: retrying in %.1f s", what, pause)
                time.sleep(pause)
                pause = min(2.0 * pause, 2.0)

    def _once(self, what: str, fn: Callable, *args: Any, timeout: float | None = None) -> Any:
        """Run one libgphoto2 call with a deadline, turning failures into CameraError."""
        seconds = self.timeout if timeout is None else timeout
        try:
            return self._run(fn, args, seconds)
        except TimeoutError:
            # libgphoto2 is stuck inside the call: abandon this handle, a reconnect makes a new one.
            self._camera = None
            error = CameraError(
                f"camera did not answer while {what} within {seconds:g} s (unplugged or hung); reconnect it")
            error.gone = True  # type: ignore[attr-defined]
            raise error from None
        except gp.GPhoto2Error as exc:
            raise camera_error(what, exc, self.port) from None

    @staticmethod
    def _run(fn: Callable, args: tuple, seconds: float) -> Any:
        result: dict[str, Any] = {}

        def work() -> None:
            try:
                result["value"] = fn(*args)
            except BaseException as exc:  # handed to the caller's thread
                result["error"] = exc

        worker = threading.Thread(target=work, name="gphoto2-call", daemon=True)
        worker.start()
        worker.join(seconds)
        if worker.is_alive():
            raise TimeoutError
        if "error" in result:
            raise result["error"]
        return result.get("value")


def _serial(config: Any) -> str:
    """The body's serial number as its status widgets report it (Nikon and generic PTP, Canon EOS)."""
    return _widget_value(config, "serialnumber") or _widget_value(config, "eosserialnumber") or ""


def _clock(seconds: float) -> str:
    return datetime.datetime.fromtimestamp(seconds).strftime("%H:%M:%S")


def _first_exposure(listing: set[tuple[str, str]], folders: list[str], before: set[tuple[str, str]],
                    files: int | None) -> list[tuple[str, str]]:
    """The files of the lowest-numbered exposure new in ``folders`` since ``before`` (at most ``files`` of them)."""
    new = [f for f in listing if f[0] in folders and f not in before]
    if not new:
        return []
    stem = Path(min(new, key=lambda f: _file_number(f[1]))[1]).stem
    same = sorted(f for f in new if Path(f[1]).stem == stem)
    return same[:files] if files else same


def _folder_number(folder: str) -> int | None:
    """The number of a DCF folder (``/store_00010001/DCIM/101CANON``: 101), None for another folder."""
    match = re.match(r"([1-9]\d\d)[0-9A-Z_]{5}$", posixpath.basename(folder), re.I)
    return int(match.group(1)) if match else None


def _file_number(name: str) -> tuple[int, str]:
    """Sort key of a DCF file name by its number (``IMG_0042.CR2``: 42), then its name."""
    digits = re.search(r"(\d+)$", Path(name).stem)
    return (int(digits.group(1)) if digits else -1), name


def _detect() -> list[tuple[str, str]]:
    """(driver model, port) of every camera libgphoto2 finds."""
    cameras = gp.Camera.autodetect()
    return [(cameras.get_name(i), cameras.get_value(i)) for i in range(cameras.count())]


def _open_camera(model: str, port: str) -> Any:
    """Initialise the camera of driver ``model`` at ``port`` (python-gphoto2's choose-camera example)."""
    camera = gp.Camera()
    port_list = gp.PortInfoList()
    port_list.load()
    camera.set_port_info(port_list[port_list.lookup_path(port)])
    abilities = gp.CameraAbilitiesList()
    abilities.load()
    camera.set_abilities(abilities[abilities.lookup_model(model)])
    camera.init()
    return camera


def _busy_error(message: str) -> CameraError:
    """A camera that answered busy (gphoto2 -110) for too long: a one-line error, not a lost camera."""
    error = CameraError(f"{message} [gphoto2 {gp.GP_ERROR_CAMERA_BUSY}]")
    error.code, error.gone = gp.GP_ERROR_CAMERA_BUSY, False  # type: ignore[attr-defined]
    return error


def _stayed_busy(seconds: float, what: str, also: str = "") -> CameraError:
    """`_busy_error` of a call answered busy for ``seconds``; ``also``: what else that means for this call."""
    return _busy_error(f"camera stayed busy for {seconds:g} s while {what} (still writing a frame, or a menu is "
                       f"open{'; or ' + also if also else ''})")


def camera_error(what: str, exc: gp.GPhoto2Error, port: str = "") -> CameraError:
    """A one-line CameraError for a libgphoto2 failure, with what it usually means.

    The error carries the gphoto2 ``code`` and ``gone`` (True when the camera
    handle is lost and a reconnect is the way on).
    """
    where = f" on {port}" if port else ""
    hint = _HINTS.get(exc.code, exc.string)
    error = CameraError(f"camera{where}: {what} failed: {hint} [gphoto2 {exc.code}]")
    error.code = exc.code  # type: ignore[attr-defined]
    error.gone = exc.code in GONE_CODES  # type: ignore[attr-defined]
    return error


def reset_usb_device(port: str) -> bool:
    """Reset the USB still-image device at libgphoto2 port ``usb:BBB,DDD`` with pyusb.

    Only a device exposing a still-image interface (USB class 6, PTP) is reset,
    never a hub or another device that happens to sit at that address.

    Returns
    -------
    bool
        True if a reset was sent (False without permission, backend or device).
    """
    match = re.fullmatch(r"usb:(\d+),(\d+)", port)
    if match is None:
        return False
    import usb.core  # pyusb: only needed for this recovery step

    bus, address = int(match.group(1)), int(match.group(2))
    try:
        device = usb.core.find(custom_match=lambda d: d.bus == bus and d.address == address)
        if device is None or not any(i.bInterfaceClass == 6 for cfg in device for i in cfg):
            return False
        device.reset()
        return True
    except (usb.core.USBError, usb.core.NoBackendError, NotImplementedError, ValueError):
        return False


# ---------------------------------------------------------------------- choosing values

# A RAW format's own names; ``nef (raw)`` and ``raw + large fine jpeg`` both contain one.
_RAW_WORD = re.compile(r"\b(c-?raw|raw|nef|cr2|cr3|arw|raf|orf|rw2|pef|dng|srw|3fr|iiq)\b", re.I)
# Reduced RAW (Canon sRAW/mRAW, Sony/Nikon RAW M and S): demosaiced or binned, not the sensor mosaic.
_REDUCED_RAW = re.compile(r"\b[ms]-?raw\b|\braw\s*\(?\s*[ms]\s*\)?(?![a-z])|\b(small|medium)\s+raw\b", re.I)


def raw_choice(current: str, offered: list[str]) -> str | None:
    """The image format to shoot PSFs in, or None when no full-resolution RAW is offered.

    Preference: RAW alone, then compressed RAW alone (Canon C-RAW is lossy),
    then RAW with a JPEG (two files per exposure); the current value is kept when
    it is as good as the best offered.
    """
    def rank(choice: str) -> int | None:
        if not _RAW_WORD.search(choice) or _REDUCED_RAW.search(choice):
            return None
        lossy = bool(re.search(r"\bc-?raw\b", choice, re.I))
        return (0 if _files_of(choice) == 1 else 2) + (1 if lossy else 0)

    ranked = [(r, c) for c in offered if (r := rank(c)) is not None]
    if not ranked:
        return None
    best = min(r for r, _ in ranked)
    if current in offered and rank(current) == best:
        return current
    return next(c for r, c in ranked if r == best)


def _files_of(image_format: str) -> int | None:
    """Files one exposure produces in ``image_format``: 1 for RAW or JPEG alone, 2 for RAW plus another."""
    if not _RAW_WORD.search(image_format):
        return 1 if image_format else None
    rest = _RAW_WORD.sub("", image_format)
    return 1 if not re.search(r"[a-z0-9]", rest, re.I) else 2


def _target_choice(offered: list[str], target: str) -> str | None:
    pattern = r"\bram\b|sdram" if target == "ram" else r"card"
    return next((c for c in offered if re.search(pattern, c, re.I)), None)


def _single_choice(offered: list[str]) -> str | None:
    singles = [c for c in offered if c.lower().startswith("single")]
    return min(singles, key=len) if singles else None


def _off_choice(offered: list[str]) -> str | None:
    return next((c for c in offered if c.strip().lower() == "off"), None)


def _delay_choice(offered: list[str]) -> str | None:
    """``On``, or the shortest delay of at least 1 s (mirror vibrations of a DSLR last about that long)."""
    on = next((c for c in offered if c.strip().lower() == "on"), None)
    if on is not None:
        return on
    delays = [(n, c) for c in offered if (n := _leading_number(c))]
    long_enough = [d for d in delays if d[0] >= 1.0]
    if long_enough:
        return min(long_enough)[1]
    return max(delays)[1] if delays else None


def _is_manual(value: str) -> bool:
    """``Manual``, ``MF``, ``MF (fixed)``, ``Manual Focus``, ``M`` (not ``DMF``: AF first)."""
    return bool(re.match(r"\s*(manual|mf\b|m\s*$)", value, re.I))


def _describe(reports: dict[str, str], switched: list[str] | None = None) -> str:
    parts = [f"{k} = {v}" for k, v in reports.items()] + list(switched or [])
    return ", ".join(parts) or "no focus setting reported"


# ---------------------------------------------------------------------- widget helpers


def _widget_value(config: Any, name: str) -> str | None:
    try:
        value = config.get_child_by_name(name).get_value()
    except gp.GPhoto2Error:
        return None
    return str(value) if value not in (None, "") else None


def _widget_choices(widget: Any) -> list[str]:
    if widget.get_type() not in (gp.GP_WIDGET_RADIO, gp.GP_WIDGET_MENU):
        return []
    return [widget.get_choice(i) for i in range(widget.count_choices())]


def _normalise(name: str, value: str) -> str:
    """Vendors write apertures as ``f/5.6`` (Nikon) or ``5.6`` (Canon): we use ``5.6``."""
    if name == "aperture" and value.lower().startswith("f/"):
        return value[2:]
    return value


def _leading_number(text: str | None) -> float | None:
    match = re.match(r"\s*(\d+(?:\.\d+)?)", text or "")
    return float(match.group(1)) if match else None
