"""Scripted stand-ins for camera bodies the virtual camera cannot play, at the python-gphoto2 API.

A `Body` answers the calls `GPhotoCamera` makes on a ``gphoto2.Camera``
(get_config / set_config, trigger_capture, wait_for_event, file_get,
file_delete, exit) and fails them with real ``gphoto2.GPhoto2Error`` codes
in the order libgphoto2 reports them:

- a body still writing the previous frame answers PTP operations with
  DeviceBusy 0x2019 (any operation: configuration, download and delete as well
  as the next trigger), which the ptp2 driver's ``translate_ptp_result`` turns
  into GP_ERROR_CAMERA_BUSY (-110, "I/O in progress"), until it is done
  (scripted per method);
- a Nikon answers every operation with DeviceBusy from the release until the
  exposure (the shutter speed it is set to) has been taken and its file written,
  then announces the file. libgphoto2's ptp2 Nikon path repeats a release the
  body refuses as busy, then waits for the body (``nikon_wait_busy``) and
  answers -110 when it is still busy after a limit, while the exposure goes on:
  5 s in 2.5.23 (libgphoto2 issue #420), 20 s after the fix of #465, 1000 s
  since 2021 ("D780 can do 900 second exposures"); here both waits end at it;
- an autofocus that cannot lock refuses the release: a Canon EOS answers the
  full press with DeviceBusy (-110) after hunting for a while (libgphoto2
  issues #304, #655: "Canon EOS Full-Press failed (0x2019: PTP Device Busy)"
  some 10 s after the half press), a Nikon with 0xA002 "Out of Focus", which
  libgphoto2 reports as GP_ERROR (-1);
- a full card with the card as capture target: GP_ERROR_NO_MEMORY (-3), as the
  ptp2 driver reports a Canon release result 7 ("Perhaps no more memory on card?");
- a body reporting property changes (PTP DevicePropChanged: exposure metering, battery,
  live view) faster than they are read: libgphoto2 hands each over as a GP_EVENT_UNKNOWN, one
  per ``wait_for_event``, in the order the body reported them (its event queue is first in,
  first out), reading the changed value over USB; a file announced behind them comes only once
  they are read, and GP_EVENT_TIMEOUT only when nothing is queued and nothing new came for the
  whole wait;
- a RAW+JPEG exposure is announced as two GP_EVENT_FILE_ADDED, the JPEG
  after the RAW (Canon writes the RAW first; on a slow card the second comes
  seconds later);
- file names as the body writes them on its card (DCF): the files of one exposure share
  its number (``IMG_0002.CR2`` and ``IMG_0002.JPG``), numbered on from one exposure to the next,
  and libgphoto2 passes the body's own name on (the ptp2 driver copies ``oi.Filename`` into the
  event's path); a body writes its buffer to the card in order and announces each file once
  written, so a file of an earlier exposure that a slow card writes late (``late``) comes after the
  next release but before that exposure's own files;
- a file the camera no longer holds: ``file_get`` and ``file_delete`` fail
  with GP_ERROR_FILE_NOT_FOUND (-108), as the virtual camera of libgphoto2
  2.5.34 answers;
- a cable pulled during a capture: the pending event wait fails with
  GP_ERROR_IO (-7, the PTP layer's translation of the USB error), every later
  call on that handle fails the same way, the body is missing from
  autodetection until it re-enumerates, then comes back at a new address
  with a fresh USB session (driver-side settings such as the capture target
  back at their defaults, events not yet handed over lost); the files on its
  card are still there, listed by ``folder_list_folders`` and
  ``folder_list_files`` as python-gphoto2 returns them (a ``CameraList`` of
  names; a folder not on the card fails with GP_ERROR_DIRECTORY_NOT_FOUND, -107),
  and the body numbers its files on from where it was, in the folder it writes to
  (the next DCF folder once it opens one) beside the folders of earlier photographs.

Widget trees are modelled on libgphoto2's ptp2 driver (widget names, types,
choices and read-only flags as ``gphoto2 --list-config`` shows them for a Canon
EOS body and for a Nikon D5300), with the same ``get_child_by_name`` failure
(GP_ERROR_BAD_PARAMETERS) for a widget a body does not have.
"""

from __future__ import annotations

import copy
import math
import re
import threading
import time
from types import SimpleNamespace

import gphoto2 as gp


class Clock:
    """A monotonic clock whose ``sleep`` moves it on at once: long exposures and waits take no time.

    `install` puts it in place of the ``time`` module of `psfd.drivers.gphoto`; bodies given the
    same clock keep their exposures and busy spells on it.
    """

    def __init__(self, start: float = 1000.0) -> None:
        self.now = start
        self._lock = threading.Lock()

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        """Wall-clock time on this clock (seconds since the epoch)."""
        return 1.8e9 + self.now

    def sleep(self, seconds: float) -> None:
        with self._lock:
            self.now += max(0.0, seconds)

    def run(self, fn, args: tuple, seconds: float):
        """`GPhotoCamera._run` on this clock: a call still inside libgphoto2 after ``seconds`` is abandoned
        (TimeoutError) while the body goes on with what it was doing."""
        started = self.now
        try:
            value = fn(*args)
        except Exception:
            if self.now - started > seconds:
                raise TimeoutError from None
            raise
        if self.now - started > seconds:
            raise TimeoutError
        return value


class Widget:
    """The part of ``gphoto2.CameraWidget`` the driver uses."""

    def __init__(self, name: str, kind: int, value=None, choices=(), readonly=False, children=()) -> None:
        self.name, self.kind, self.value = name, kind, value
        self.choices, self.readonly = list(choices), readonly
        self.children = list(children)

    def get_name(self) -> str:
        return self.name

    def get_type(self) -> int:
        return self.kind

    def get_value(self):
        return self.value

    def set_value(self, value) -> None:
        self.value = value  # libgphoto2 checks nothing here: the body decides at set_config

    def get_readonly(self) -> int:
        return int(self.readonly)

    def count_choices(self) -> int:
        return len(self.choices)

    def get_choice(self, i: int) -> str:
        return self.choices[i]

    def get_child_by_name(self, name: str) -> "Widget":
        for child in self.children:
            if child.name == name:
                return child
            try:
                return child.get_child_by_name(name)
            except gp.GPhoto2Error:
                continue
        raise gp.GPhoto2Error(gp.GP_ERROR_BAD_PARAMETERS)

    def walk(self):
        yield self
        for child in self.children:
            yield from child.walk()


def radio(name, value, choices, readonly=False) -> Widget:
    return Widget(name, gp.GP_WIDGET_RADIO, value, choices, readonly)


def text(name, value) -> Widget:
    return Widget(name, gp.GP_WIDGET_TEXT, value, readonly=True)


def toggle(name, value=0) -> Widget:
    return Widget(name, gp.GP_WIDGET_TOGGLE, value)


def tree(*widgets: Widget) -> Widget:
    return Widget("main", gp.GP_WIDGET_WINDOW, children=[Widget("settings", gp.GP_WIDGET_SECTION,
                                                                  children=list(widgets))])


CANON_FORMATS = ["Large Fine JPEG", "Large Normal JPEG", "Medium Fine JPEG", "Small Fine JPEG",
                 "RAW + Large Fine JPEG", "RAW", "mRAW + Large Fine JPEG", "mRAW", "sRAW + Large Fine JPEG",
                 "sRAW"]
CANON_SHUTTER = ["bulb", "30", "15", "8", "4", "2", "1", "0.5", "1/4", "1/15", "1/60", "1/125", "1/250",
                 "1/1000", "1/4000"]


def canon_eos(lens_af: bool = True, image_format: str = "Large Fine JPEG", shutter: str = "1/125") -> Widget:
    """A Canon EOS DSLR as libgphoto2 shows it: focusmode follows the lens AF/MF switch."""
    focus = ("One Shot", ["One Shot", "AI Focus", "AI Servo"]) if lens_af else ("Manual", ["Manual"])
    return tree(
        text("manufacturer", "Canon Inc."), text("cameramodel", "Canon EOS 5D Mark III"),
        text("eosserialnumber", "012345678901"), text("lensname", "EF50mm f/1.8 STM"),
        radio("imageformat", image_format, CANON_FORMATS),
        radio("capturetarget", "Memory card", ["Internal RAM", "Memory card"]),
        radio("drivemode", "Continuous high speed", ["Single", "Continuous high speed", "Continuous low speed",
                                                     "Single silent", "Timer 10 sec", "Timer 2 sec"]),
        radio("focusmode", focus[0], focus[1]),
        radio("aperture", "5.6", ["1.8", "2.8", "4", "5.6", "8", "11", "16", "22"]),
        radio("shutterspeed", shutter, CANON_SHUTTER),
        radio("iso", "100", ["Auto", "100", "200", "400", "800"]),
        toggle("bulb"),
    )


def nikon_d5300(focus: str = "Manual", quality: str = "JPEG Fine", shutter: str = "0.5000s") -> Widget:
    """Nikon D5300 (values from a real ``--list-config``): driver AF switch, exposure delay, SDRAM target."""
    return tree(
        text("manufacturer", "Nikon Corporation"), text("cameramodel", "D5300"),
        text("serialnumber", "00000000000000000000000006909849"),
        radio("capturetarget", "Internal RAM", ["Internal RAM", "Memory card"]),
        radio("autofocus", "On", ["On", "Off"]),
        radio("imagequality", quality, ["JPEG Basic", "JPEG Normal", "JPEG Fine", "NEF (Raw)", "NEF+Basic",
                                        "NEF+Normal", "NEF+Fine"]),
        radio("focusmode", focus, ["Manual", "AF-S", "AF-C", "AF-A"], readonly=True),
        radio("capturemode", "Burst", ["Single Shot", "Burst", "Continuous Low Speed", "Timer",
                                       "Quick Response Remote", "Delayed Remote", "Quiet Release"]),
        radio("exposuredelaymode", "Off", ["On", "Off"]),
        radio("f-number", "f/5.6", ["f/2.8", "f/4", "f/5.6", "f/8", "f/11"]),
        radio("shutterspeed", shutter, ["0.0010s", "0.0080s", "0.5000s", "1.0000s", "30.0000s"], readonly=True),
        toggle("bulb"),
    )


def jpeg_compact() -> Widget:
    """A compact that only shoots JPEG."""
    return tree(radio("imageformat", "Large Fine JPEG", ["Large Fine JPEG", "Medium Fine JPEG", "Small JPEG"]),
                radio("capturetarget", "Memory card", ["Internal RAM", "Memory card"]))


class Body:
    """One USB session with a camera body.

    Parameters
    ----------
    config : Widget
        The body's widget tree (its settings persist across sessions as on a real body,
        except ``capturetarget``, which libgphoto2 sets per session).
    files : list of (name, delay_s)
        Files each exposure announces, with their delay after the trigger.
    script : dict
        Per method, the errors to raise on successive calls (None: answer normally),
        e.g. ``{"trigger_capture": [busy, busy]}``.
    queued : list of str or (str, float)
        Files announced before the first trigger (a late file of an earlier exposure), at the
        session's start or the given seconds after it.
    unplug_after_trigger : bool
        The cable is pulled right after the next trigger.
    af_locks : bool
        False: the autofocus finds nothing to lock on. With autofocus in use (a ``focusmode``
        that is not manual, or a driver ``autofocus`` switch at On) the release is refused
        after ``af_hunt_s`` of hunting, as the vendor does (see the module docstring).
    af_hunt_s : float
        How long a trigger hunts before the refusal.
    card_shots : int, optional
        Frames the card has room for; with ``capturetarget`` on the card a trigger beyond
        them fails with GP_ERROR_NO_MEMORY.
    library_wait_s : float
        A Nikon: how long libgphoto2 waits for the busy body around a release before it
        answers -110 (see the module docstring).
    hangs : bool
        A Nikon that stays busy for good after its next release.
    dropped : list of str
        File names the body announces but no longer holds (a frame in RAM it let go).
    clock : Clock, optional
        The clock of the body's exposures and waits (default: the real one).
    folder : str, optional
        The folder the body writes its files to (default `FOLDER`).
    card : dict, optional
        Other folders on the card and the files they hold (earlier photographs, listed only).
    late : dict, optional
        Seconds a named file (``IMG_0001.JPG``: the file of that shot) is written later than the
        others of its exposure (a slow card).
    store : dict, optional
        The files the body holds, by name. Files on the card outlive the USB session: give the
        sessions of one body the same dict (and the later one the ``shots`` taken before it).
    shots : int
        Exposures the body numbered before this session.
    auto_exposure_s : float
        How long the body exposes when its shutter speed is no time (``auto``: the body's exposure
        program chooses).
    flood_s : float
        For this long from the session's start the body reports a property change every
        ``flood_every_s``; libgphoto2 spends ``event_read_s`` reading each one it hands over.

    Each file of an exposure is announced its delay after the exposure ends (the shutter
    speed it is set to; a bulb exposure has ended when the bulb is released).
    """

    def __init__(self, config: Widget, files=(("IMG_0001.CR2", 0.05),), script=None, queued=(),
                 unplug_after_trigger=False, af_locks=True, af_hunt_s=0.0,
                 card_shots=None, library_wait_s=1000.0, hangs=False, dropped=(), clock=None,
                 flood_s=0.0, flood_every_s=0.005, event_read_s=0.01, store=None, shots=0, auto_exposure_s=0.0,
                 late=None, folder=None, card=None) -> None:
        self.config, self.files = config, list(files)
        self.script = {k: list(v) for k, v in (script or {}).items()}
        self.calls: list[str] = []
        self.clock = clock or time
        started = self.clock.monotonic()
        queued = [(q, 0.0) if isinstance(q, str) else q for q in queued]
        self.pending: list[tuple[float, str]] = [(started + at, name) for name, at in queued]
        self.store: dict[str, bytes] = {} if store is None else store
        self.store.update({name: b"stale" for name, _ in queued if name not in dropped})
        self.next_change, self.flood_until = started, started + flood_s
        self.flood_every_s, self.event_read_s = flood_every_s, event_read_s
        self.unplugged = False
        self.unplug_after_trigger = unplug_after_trigger
        self.shots, self.auto_exposure_s = shots, auto_exposure_s
        self.late = dict(late or {})
        if folder is not None:
            self.FOLDER = folder
        self.card = {f: list(names) for f, names in (card or {}).items()}
        self.listed: list[tuple[str, str]] = []  # (listing call, folder) in the order made
        self.bulb_log: list[tuple[int, float]] = []
        self.af_locks, self.af_hunt_s = af_locks, af_hunt_s
        self.card_shots = card_shots
        self.library_wait_s, self.hangs, self.dropped = library_wait_s, hangs, set(dropped)
        self.busy_until = -math.inf  # a Nikon answers DeviceBusy until then

    FOLDER = "/store_00020001/DCIM/100CANON"  # where the body writes, unless given ``folder``

    def _enter(self, method: str) -> None:
        self.calls.append(method)
        if self.unplugged:
            raise gp.GPhoto2Error(gp.GP_ERROR_IO)
        errors = self.script.get(method)
        if errors:
            error = errors.pop(0)
            if error is not None:
                raise error
        if method not in ("trigger_capture", "exit") and self._busy():
            raise gp.GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY)

    def _busy(self) -> bool:
        return self.clock.monotonic() < self.busy_until

    def _nikon(self) -> bool:
        return self._value("manufacturer") == "Nikon Corporation"

    def _value(self, name: str):
        try:
            return self.config.get_child_by_name(name).get_value()
        except gp.GPhoto2Error:
            return None

    def _autofocus(self) -> bool:
        """Whether a release focuses first: the lens or body mode, and Nikon's driver switch."""
        mode = self._value("focusmode")
        return (mode is not None and not str(mode).lower().startswith("manual")) or self._value("autofocus") == "On"

    def get_config(self):
        self._enter("get_config")
        return copy.deepcopy(self.config)

    def set_config(self, config: Widget) -> None:
        self._enter("set_config")
        mine = {w.name: w for w in self.config.walk()}
        for widget in config.walk():
            target = mine.get(widget.name)
            if target is None or widget.value == target.value:
                continue
            if target.readonly:
                raise gp.GPhoto2Error(gp.GP_ERROR_NOT_SUPPORTED)
            if target.choices and widget.value not in target.choices:
                raise gp.GPhoto2Error(gp.GP_ERROR_BAD_PARAMETERS)
            target.value = widget.value
            if target.name == "bulb":
                self.bulb_log.append((int(widget.value), self.clock.monotonic()))
                if int(widget.value) == 0:
                    self._expose(0.0)

    def trigger_capture(self) -> None:
        self._enter("trigger_capture")
        nikon = self._nikon()
        if nikon:  # libgphoto2 repeats the release while the body refuses it as busy
            self._library_waits()
        if not self.af_locks and self._autofocus():
            self.clock.sleep(self.af_hunt_s)
            raise gp.GPhoto2Error(gp.GP_ERROR if nikon else gp.GP_ERROR_CAMERA_BUSY)
        on_card = self._value("capturetarget") == "Memory card"
        if on_card and self.card_shots is not None and self.shots >= self.card_shots:
            raise gp.GPhoto2Error(gp.GP_ERROR_NO_MEMORY)
        self._expose(_seconds(self._value("shutterspeed")) or self.auto_exposure_s)
        if self.unplug_after_trigger:
            self.unplugged = True
        if nikon:  # then waits for the body (nikon_wait_busy)
            self._library_waits()

    def _library_waits(self) -> None:
        """libgphoto2 waiting for a busy Nikon: -110 when the body is still busy after its limit."""
        if self._busy():
            self.clock.sleep(min(self.busy_until - self.clock.monotonic(), self.library_wait_s))
        if self._busy():
            raise gp.GPhoto2Error(gp.GP_ERROR_CAMERA_BUSY)

    def _expose(self, seconds: float) -> None:
        self.shots += 1
        ends = self.clock.monotonic() + seconds
        for name, delay in self.files:
            shot_name = name.replace("0001", f"{self.shots:04d}")
            if shot_name not in self.dropped:
                self.store[shot_name] = f"{shot_name} of shot {self.shots}".encode()
            written = ends + delay + self.late.get(shot_name, 0.0)
            # the card is written in order: a file waits for those buffered before it
            self.pending.append((max([written] + [t for t, _ in self.pending]), shot_name))
        if self._nikon():  # busy until the last file is written
            self.busy_until = math.inf if self.hangs else max(t for t, _ in self.pending)

    def wait_for_event(self, timeout_ms: int):
        self._enter("wait_for_event")
        end = self.clock.monotonic() + timeout_ms / 1000.0
        while True:
            due = sorted(p for p in self.pending if p[0] <= self.clock.monotonic())
            change = self.next_change if self.next_change < self.flood_until else math.inf
            if change <= min([self.clock.monotonic()] + [t for t, _ in due]):  # reported before any due file
                self.next_change += self.flood_every_s
                self.clock.sleep(self.event_read_s)
                return gp.GP_EVENT_UNKNOWN, "PTP Property d1d7 changed"
            if due:
                self.pending.remove(due[0])
                return gp.GP_EVENT_FILE_ADDED, SimpleNamespace(folder=self.FOLDER, name=due[0][1])
            if self.clock.monotonic() >= end:
                return gp.GP_EVENT_TIMEOUT, None
            self.clock.sleep(0.005)

    def file_get(self, folder: str, name: str, kind: int):
        self._enter("file_get")
        if name not in self.store:
            raise gp.GPhoto2Error(gp.GP_ERROR_FILE_NOT_FOUND)
        camera_file = gp.CameraFile()
        camera_file.set_data_and_size(self.store[name])
        return camera_file

    def file_delete(self, folder: str, name: str) -> None:
        self._enter("file_delete")
        if self.store.pop(name, None) is None:
            raise gp.GPhoto2Error(gp.GP_ERROR_FILE_NOT_FOUND)

    def _folders(self) -> set[str]:
        return {self.FOLDER, *self.card}

    def _known(self, folder: str) -> bool:
        """Whether ``folder`` is on the card (a folder that holds files, or one above such a folder)."""
        top = folder.rstrip("/")
        return any(path == top or path.startswith(top + "/") for path in self._folders())

    def folder_list_folders(self, folder: str) -> "CameraList":
        self._enter("folder_list_folders")
        self.listed.append(("folders", folder))
        if not self._known(folder):
            raise gp.GPhoto2Error(gp.GP_ERROR_DIRECTORY_NOT_FOUND)
        top = folder.rstrip("/") + "/"
        return CameraList(sorted({p[len(top):].split("/")[0] for p in self._folders() if p.startswith(top)}))

    def folder_list_files(self, folder: str) -> "CameraList":
        self._enter("folder_list_files")
        self.listed.append(("files", folder))
        if not self._known(folder):
            raise gp.GPhoto2Error(gp.GP_ERROR_DIRECTORY_NOT_FOUND)
        return CameraList(sorted(self.store) if folder == self.FOLDER else self.card.get(folder, []))

    def exit(self) -> None:
        self._enter("exit")


class CameraList:
    """The part of ``gphoto2.CameraList`` a listing uses: names by index."""

    def __init__(self, names) -> None:
        self.names = list(names)

    def count(self) -> int:
        return len(self.names)

    def get_name(self, i: int) -> str:
        return self.names[i]


class Bus:
    """The USB bus as autodetection sees it: bodies come and go, each at its own port."""

    def __init__(self, model: str, *bodies: Body, absent_scans: int = 0) -> None:
        self.model, self.bodies = model, list(bodies)
        self.absent_scans = absent_scans  # scans that miss an unplugged body before it re-enumerates
        self.opened: list[str] = []
        self.resets: list[str] = []

    def detect(self) -> list[tuple[str, str]]:
        if not self.bodies:
            return []
        if self.opened and self.absent_scans > 0:
            self.absent_scans -= 1
            return []
        return [(self.model, f"usb:001,{len(self.opened) + 4:03d}")]

    def open(self, model: str, port: str) -> Body:
        self.opened.append(port)
        body = self.bodies.pop(0)
        for widget in body.config.walk():  # a new USB session: libgphoto2's per-session default
            if widget.name == "capturetarget":
                widget.value = "Memory card"
        return body

    def reset(self, port: str) -> bool:
        self.resets.append(port)
        return False  # the device is no longer on the bus: nothing to reset


def _seconds(shutter) -> float:
    """Exposure seconds of a shutter speed as the widgets write it (``30.0000s``, ``1/125``); bulb: 0."""
    match = re.fullmatch(r"(\d+(?:\.\d+)?)(?:/(\d+))?s?", str(shutter or "").strip())
    if match is None:
        return 0.0
    return float(match.group(1)) / float(match.group(2) or 1)


def install(monkeypatch, bus: Bus, clock: Clock | None = None) -> None:
    """Make `psfd.drivers.gphoto` find and open bodies on ``bus`` instead of USB (and keep time, call
    deadlines included, by ``clock``)."""
    from psfd.drivers import gphoto

    monkeypatch.setattr(gphoto, "_detect", bus.detect)
    monkeypatch.setattr(gphoto, "_open_camera", bus.open)
    monkeypatch.setattr(gphoto, "reset_usb_device", bus.reset)
    if clock is not None:
        monkeypatch.setattr(gphoto, "time", clock)
        monkeypatch.setattr(gphoto.GPhotoCamera, "_run", staticmethod(clock.run))
