"""A camera driven through libgphoto2 (python-gphoto2): settings, capture, download.

Plain hardware code in the style of python-gphoto2's examples: detect the
camera, read and write configuration widgets, trigger a capture and collect
the files it produces from camera events (a RAW+JPEG capture produces two
``GP_EVENT_FILE_ADDED``), download them, optionally delete them from the card.

Every libgphoto2 call runs in a worker thread with a deadline: python-gphoto2
releases the GIL during libgphoto2 calls, so a camera unplugged in the middle of
a USB transfer ends in a `CameraError` instead of freezing the service.
"""

from __future__ import annotations

import os
import re
import threading
import time
from pathlib import Path
from typing import Any, Callable

import gphoto2 as gp

from psfd.drivers.base import CameraInfo
from psfd.drivers.recording import free_name
from psfd.errors import CameraError

# Our setting names -> the widget names vendors use for them (first found wins).
SETTING_ALIASES = {
    "aperture": ("aperture", "f-number", "fnumber"),
    "shutterspeed": ("shutterspeed", "shutterspeed2", "exposuretime"),
    "iso": ("iso", "isospeed"),
    "imageformat": ("imageformat", "imagequality"),
    "capturetarget": ("capturetarget",),
}

# What the usual libgphoto2 failures mean for the person at the bench.
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
}


class GPhotoCamera:
    """`Camera` on a USB camera through libgphoto2.

    Parameters
    ----------
    port : str, optional
        libgphoto2 port such as ``usb:001,005``; None auto-detects the single camera connected.
    timeout : float
        Seconds allowed for one call (settings, one event wait, one download).
    capture_timeout : float
        Seconds allowed from the trigger to the first file of a capture (long exposures need more).
    settle : float
        Quiet time after the last new file before a capture is considered complete
        (a RAW+JPEG capture announces its two files one after the other).
    delete_after_download : bool
        Delete each file from the camera once downloaded (keeps the card from filling overnight).
    """

    def __init__(
        self,
        port: str | None = None,
        timeout: float = 10.0,
        capture_timeout: float = 30.0,
        settle: float = 1.0,
        delete_after_download: bool = True,
    ) -> None:
        self.timeout = float(timeout)
        self.capture_timeout = float(capture_timeout)
        self.settle = float(settle)
        self.delete_after_download = delete_after_download
        self._camera: Any = None
        self._model = ""
        self.port = ""
        self._connect(port)

    # ------------------------------------------------------------------ connection

    def _connect(self, port: str | None, model: str | None = None) -> None:
        """Find the camera (by port, by driver model, or the only one) and initialise it."""
        cameras = self._call("detecting cameras", gp.Camera.autodetect)
        found = [(cameras.get_name(i), cameras.get_value(i)) for i in range(cameras.count())]
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

    def reconnect(self, reset_usb: bool = True) -> None:
        """Release the camera, reset its USB device if possible, and connect again.

        After a USB reset the device may come back at another address, so the
        camera is found again by its driver model rather than by its old port.
        """
        self.close()
        if reset_usb and self.port.startswith("usb:"):
            if reset_usb_device(self.port):
                time.sleep(2.0)  # the camera re-enumerates after a bus reset
        self._connect(None, model=self._model)

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
        config = self._call("reading the configuration", self._cam().get_config)
        values = {name: _widget_value(config, name) for name in (
            "manufacturer", "cameramodel", "serialnumber", "eosserialnumber", "lensname", "focallength")}
        manufacturer, model = values["manufacturer"] or "", values["cameramodel"] or self._model
        if manufacturer and not model.lower().startswith(manufacturer.lower()):
            model = f"{manufacturer} {model}"
        return CameraInfo(
            model=model,
            serial=values["serialnumber"] or values["eosserialnumber"] or "",
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
            raw = _match_choice(name, str(value), offered)
            if raw is None:
                listing = ", ".join(_normalise(name, c) for c in offered)
                raise CameraError(f"{name} {value} is not offered by the camera (offered: {listing})")
        else:
            raw = str(value)
        self._call(f"setting {name}", widget.set_value, raw)
        self._call(f"setting {name}", self._cam().set_config, config)

    def capture(self, dest: Path) -> list[Path]:
        """Trigger one exposure and download every file it produced (RAW, RAW+JPEG) into ``dest``."""
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        paths = self._trigger_and_collect()
        saved = []
        for folder, name in paths:
            saved.append(self._download(folder, name, dest))
            if self.delete_after_download:
                try:
                    self._call(f"deleting {name}", self._cam().file_delete, folder, name)
                except CameraError:
                    pass  # a read-only card: the frame is downloaded, which is what matters
        return saved

    # ------------------------------------------------------------------ capture steps

    def _trigger_and_collect(self) -> list[tuple[str, str]]:
        """Trigger a capture and gather the (folder, name) of each file added."""
        files: list[tuple[str, str]] = []
        try:
            self._call("triggering a capture", self._cam().trigger_capture)
        except CameraError as exc:
            if getattr(exc, "code", None) != gp.GP_ERROR_NOT_SUPPORTED:
                raise
            # Cameras without trigger_capture: a blocking capture returns the first file;
            # any further file of the same exposure still arrives as an event below.
            path = self._call("capturing", self._cam().capture, gp.GP_CAPTURE_IMAGE, timeout=self.capture_timeout)
            files.append((path.folder, path.name))
        start = last_new = time.monotonic()
        while True:
            now = time.monotonic()
            if files and now - last_new >= self.settle:
                return files
            if not files and now - start > self.capture_timeout:
                raise CameraError(f"capture produced no file within {self.capture_timeout:g} s")
            wait_ms = int(1000 * min(self.settle, self.timeout))
            event, data = self._call(
                "waiting for the capture", self._cam().wait_for_event, wait_ms, timeout=wait_ms / 1000 + self.timeout
            )
            if event == gp.GP_EVENT_FILE_ADDED and (data.folder, data.name) not in files:
                files.append((data.folder, data.name))
                last_new = time.monotonic()
            elif event == gp.GP_EVENT_TIMEOUT and time.monotonic() - now < 0.01:
                time.sleep(0.02)  # some drivers answer a wait at once: do not spin

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

    # ------------------------------------------------------------------ plumbing

    def _config(self) -> Any:
        return self._call("reading the configuration", self._cam().get_config)

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
            raise CameraError("camera is not connected (closed, or lost after an earlier failure); reconnect it")
        return self._camera

    def _call(self, what: str, fn: Callable, *args: Any, timeout: float | None = None) -> Any:
        """Run one libgphoto2 call with a deadline, turning failures into CameraError."""
        seconds = self.timeout if timeout is None else timeout
        try:
            return self._run(fn, args, seconds)
        except TimeoutError:
            # libgphoto2 is stuck inside the call: abandon this handle, a reconnect makes a new one.
            self._camera = None
            raise CameraError(
                f"camera did not answer while {what} within {seconds:g} s (unplugged or hung); reconnect it"
            ) from None
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


def camera_error(what: str, exc: gp.GPhoto2Error, port: str = "") -> CameraError:
    """A one-line CameraError for a libgphoto2 failure, with what it usually means."""
    where = f" on {port}" if port else ""
    hint = _HINTS.get(exc.code, exc.string)
    error = CameraError(f"camera{where}: {what} failed: {hint} [gphoto2 {exc.code}]")
    error.code = exc.code  # type: ignore[attr-defined]
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


def _match_choice(name: str, value: str, offered: list[str]) -> str | None:
    """The offered raw value equal to ``value`` as written, after normalising, or numerically."""
    if value in offered:
        return value
    wanted = _normalise(name, value)
    for raw in offered:
        if _normalise(name, raw) == wanted:
            return raw
    try:
        number = float(wanted)
    except ValueError:
        return None
    for raw in offered:
        try:
            if abs(float(_normalise(name, raw)) - number) < 1e-9:
                return raw
        except ValueError:
            continue
    return None


def _leading_number(text: str | None) -> float | None:
    match = re.match(r"\s*(\d+(?:\.\d+)?)", text or "")
    return float(match.group(1)) if match else None

