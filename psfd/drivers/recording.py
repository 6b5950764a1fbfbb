"""Recordings of a rig session and the fakes that replay them.

A recording is a folder::

    manifest.json      {"version": 1, "rig": {...}, "requests": [...]}
    frames/0003-IMG_0001.DNG ...

``requests`` lists every request made to the rig in order, e.g.
``{"device": "camera", "call": "set", "args": {"name": "aperture", "value": "5.6"}, "result": null}``;
a capture's result names the files it produced, copied into ``frames/`` with
their sha256; a rail request's result is the position it reported (with the
serial lines exchanged, ``serial``, when the rail keeps them); a request
that failed keeps ``{"error": {"type": "RailAlarm", "message": ...}}`` instead.

`RecordingCamera` and `RecordingRail` answer the same requests in the same
order with the recorded results (frames byte for byte), so tests and
benchmarks run the daemon against real hardware sessions without hardware.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any, Callable

from psfd import errors
from psfd.drivers.base import Camera, CameraInfo, Position, Rail
from psfd.errors import HardwareError, PsfdError

MANIFEST = "manifest.json"
FRAMES = "frames"
VERSION = 1


class ReplayError(HardwareError):
    """A replayed request differs from the recording, or the recording is damaged."""


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _plain(value: Any) -> Any:
    """JSON form of a request's arguments or result (what the manifest stores and compares)."""
    if dataclasses.is_dataclass(value):
        value = dataclasses.asdict(value)
    return json.loads(json.dumps(value))


def _describe(device: str, call: str, args: dict) -> str:
    inner = ", ".join(f"{k}={v!r}" for k, v in args.items() if v is not None)
    return f"{device}.{call}({inner})"


def free_name(folder: Path, name: str) -> Path:
    """``folder/name``, or ``stem-1.ext``, ``stem-2.ext``... if taken (camera file counters wrap)."""
    path, n = folder / name, 1
    while path.exists():
        path = folder / f"{Path(name).stem}-{n}{Path(name).suffix}"
        n += 1
    return path


# ---------------------------------------------------------------------- recording


class Recorder:
    """Record every request made to a camera and a rail into ``folder``.

    Use ``recorder.camera`` and ``recorder.rail`` in place of the real devices;
    the manifest is rewritten (atomically) after every request, so a session
    that dies half-way still leaves a readable recording of what happened.

    Parameters
    ----------
    folder : path-like
        New or empty folder.
    camera, rail : Camera, Rail, optional
        The devices to wrap.
    rig : dict, optional
        Description of the rig stored in the manifest (ports, simulation options).
    """

    def __init__(self, folder: str | os.PathLike, camera: Camera | None = None, rail: Rail | None = None,
                 rig: dict | None = None) -> None:
        self.folder = Path(folder)
        if self.folder.exists() and any(self.folder.iterdir()):
            raise errors.BadInputError(f"{self.folder}: recording folder exists and is not empty")
        (self.folder / FRAMES).mkdir(parents=True, exist_ok=True)
        self.requests: list[dict] = []
        self.rig = _plain(rig or {})
        self.camera = _RecordedCamera(self, camera) if camera is not None else None
        self.rail = _RecordedRail(self, rail) if rail is not None else None
        self._write()

    def call(self, device: str, call: str, args: dict, fn: Callable[[], Any],
             encode: Callable[[Any], Any] = _plain, wrapped: Any = None) -> Any:
        """Run one request on the real device and append it, with its result or error, to the manifest.

        A device keeping a transcript of its latest request in ``exchange`` (the GRBL
        rail's serial lines) has it stored with the entry, for reading, not for replay.
        """
        entry: dict[str, Any] = {"device": device, "call": call, "args": _plain(args)}
        try:
            result = fn()
        except PsfdError as exc:
            entry["error"] = {"type": type(exc).__name__, "message": str(exc)}
            self._append(entry, wrapped)
            raise
        entry["result"] = encode(result)
        self._append(entry, wrapped)
        return result

    def keep_frames(self, paths: list[Path]) -> dict:
        """Copy captured files into the recording; the manifest entry of a capture."""
        files = []
        for path in paths:
            stored = Path(FRAMES) / f"{len(self.requests):04d}-{path.name}"
            shutil.copyfile(path, self.folder / stored)
            files.append({"name": path.name, "file": stored.as_posix(), "sha256": sha256(self.folder / stored)})
        return {"files": files}

    def close(self) -> None:
        """Release the wrapped devices."""
        for device in (self.camera, self.rail):
            if device is not None:
                device.close()

    def _append(self, entry: dict, wrapped: Any = None) -> None:
        if getattr(wrapped, "exchange", None):
            entry["serial"] = list(wrapped.exchange)
        self.requests.append(entry)
        self._write()

    def _write(self) -> None:
        manifest = {"version": VERSION, "rig": self.rig, "requests": self.requests}
        tmp = self.folder / f".{MANIFEST}.part"
        tmp.write_text(json.dumps(manifest, indent=1) + "\n")
        os.replace(tmp, self.folder / MANIFEST)


class _RecordedCamera:
    def __init__(self, recorder: Recorder, camera: Camera) -> None:
        self._rec, self._camera = recorder, camera

    def info(self) -> CameraInfo:
        return self._rec.call("camera", "info", {}, self._camera.info)

    def get(self, name: str) -> str:
        return self._rec.call("camera", "get", {"name": name}, lambda: self._camera.get(name))

    def choices(self, name: str) -> list[str]:
        return self._rec.call("camera", "choices", {"name": name}, lambda: self._camera.choices(name))

    def set(self, name: str, value: str) -> None:
        args = {"name": name, "value": str(value)}
        self._rec.call("camera", "set", args, lambda: self._camera.set(name, str(value)))

    def capture(self, dest: Path) -> list[Path]:
        return self._rec.call("camera", "capture", {}, lambda: self._camera.capture(Path(dest)),
                              encode=self._rec.keep_frames)

    def close(self) -> None:
        self._camera.close()


class _RecordedRail:
    def __init__(self, recorder: Recorder, rail: Rail) -> None:
        self._rec, self._rail = recorder, rail

    def home(self) -> Position:
        return self._rec.call("rail", "home", {}, self._rail.home, wrapped=self._rail)

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None) -> Position:
        return self._rec.call("rail", "move", {"x": x, "y": y, "z": z}, lambda: self._rail.move(x=x, y=y, z=z),
                              wrapped=self._rail)

    def position(self) -> Position:
        return self._rec.call("rail", "position", {}, self._rail.position, wrapped=self._rail)

    def close(self) -> None:
        self._rail.close()


# ---------------------------------------------------------------------- replay


class Replay:
    """A cursor over a recording's requests.

    Shared by a `RecordingCamera` and a `RecordingRail` it checks the order of
    all requests; given a ``device`` it follows that device's requests only.
    """

    def __init__(self, folder: str | os.PathLike, device: str | None = None) -> None:
        self.folder = Path(folder)
        path = self.folder / MANIFEST
        try:
            manifest = json.loads(path.read_text())
            requests = manifest["requests"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise errors.BadInputError(f"{path}: not a readable recording ({type(exc).__name__})") from None
        if manifest.get("version") != VERSION:
            raise errors.BadInputError(f"{path}: unsupported recording version {manifest.get('version')!r}")
        self.rig = manifest.get("rig", {})
        self.requests = [r for r in requests if device is None or r["device"] == device]
        self.cursor = 0

    def answer(self, device: str, call: str, args: dict) -> Any:
        """The recorded result of the next request, which must be this one; recorded errors are raised."""
        asked = _describe(device, call, _plain(args))
        if self.cursor >= len(self.requests):
            raise ReplayError(
                f"{self.folder}: request {self.cursor + 1} {asked} is past the end of the recording "
                f"({len(self.requests)} requests)"
            )
        entry = self.requests[self.cursor]
        expected = _describe(entry["device"], entry["call"], entry["args"])
        if (entry["device"], entry["call"], entry["args"]) != (device, call, _plain(args)):
            raise ReplayError(
                f"{self.folder}: request {self.cursor + 1} is {asked} but the recording has {expected}"
            )
        self.cursor += 1
        if "error" in entry:
            cls = getattr(errors, entry["error"]["type"], None)
            if not (isinstance(cls, type) and issubclass(cls, PsfdError)):
                cls = HardwareError
            raise cls(entry["error"]["message"])
        return entry["result"]

    def copy_frames(self, result: dict, dest: Path) -> list[Path]:
        """Copy a recorded capture's files to ``dest`` after checking them against their sha256."""
        dest.mkdir(parents=True, exist_ok=True)
        out = []
        for item in result["files"]:
            source = self.folder / item["file"]
            if not source.is_file() or sha256(source) != item["sha256"]:
                raise ReplayError(f"{self.folder}: recorded frame {item['file']} is missing or altered")
            target = free_name(dest, item["name"])
            tmp = target.with_name(f".{target.name}.part")
            shutil.copyfile(source, tmp)
            os.replace(tmp, target)
            out.append(target)
        return out


def _replay(source: str | os.PathLike | Replay, device: str) -> Replay:
    return source if isinstance(source, Replay) else Replay(source, device)


class RecordingCamera:
    """`Camera` answering from a recording (a folder, or a `Replay` shared with a rail)."""

    def __init__(self, source: str | os.PathLike | Replay) -> None:
        self._replay = _replay(source, "camera")

    def info(self) -> CameraInfo:
        return CameraInfo(**self._replay.answer("camera", "info", {}))

    def get(self, name: str) -> str:
        return self._replay.answer("camera", "get", {"name": name})

    def choices(self, name: str) -> list[str]:
        return list(self._replay.answer("camera", "choices", {"name": name}))

    def set(self, name: str, value: str) -> None:
        self._replay.answer("camera", "set", {"name": name, "value": str(value)})

    def capture(self, dest: Path) -> list[Path]:
        return self._replay.copy_frames(self._replay.answer("camera", "capture", {}), Path(dest))

    def close(self) -> None:
        pass


class RecordingRail:
    """`Rail` answering from a recording (a folder, or a `Replay` shared with a camera)."""

    def __init__(self, source: str | os.PathLike | Replay) -> None:
        self._replay = _replay(source, "rail")

    def home(self) -> Position:
        return Position(**self._replay.answer("rail", "home", {}))

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None) -> Position:
        return Position(**self._replay.answer("rail", "move", {"x": x, "y": y, "z": z}))

    def position(self) -> Position:
        return Position(**self._replay.answer("rail", "position", {}))

    def close(self) -> None:
        pass


def open_replay(folder: str | os.PathLike) -> tuple[RecordingCamera, RecordingRail]:
    """Camera and rail sharing one cursor: the whole session must be replayed in its recorded order."""
    replay = Replay(folder)
    return RecordingCamera(replay), RecordingRail(replay)
