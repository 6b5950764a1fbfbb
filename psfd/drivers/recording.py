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

`RecordingCamera` and `RecordingRail` behave as the recorded rig did (frames
byte for byte), so tests and benchmarks run the daemon against real hardware
sessions without hardware. The replay follows what the rig *did*, not the
exact sequence of calls, so that a recording made with ``psfd record`` at a
plan's positions and apertures replays under ``psfd run`` of that plan:

- queries (camera ``info``, ``get``, ``choices``; rail ``info``, ``position``)
  are answered from the recording and never consume it;
- the actions between two captures (``set``, ``move``, ``home``, ``unlock``,
  ``prepare``) may come in any order, and an action that changes nothing (a
  move to where the rail already is, a setting already in effect) is answered
  without being recorded;
- each capture must find the rig where the recording's capture found it (rail
  position and every setting the replay set): its frames are then the recorded ones;
- a recorded failure is raised again when the replay makes the request that failed.
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
from psfd.drivers.base import Camera, CameraInfo, CameraReady, CameraSetup, Position, Rail, RailInfo
from psfd.errors import HardwareError, PsfdError
from psfd.vocabulary import same_setting

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

    @property
    def acted(self) -> bool:
        """Whether the rig did anything yet (moved, homed, unlocked, captured): the recording is then worth keeping."""
        return any(r["call"] in ("move", "home", "unlock", "capture") for r in self.requests)

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

    def prepare(self, setup: CameraSetup) -> CameraReady:
        return self._rec.call("camera", "prepare", dataclasses.asdict(setup), lambda: self._camera.prepare(setup))

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

    def info(self) -> RailInfo:
        return self._rec.call("rail", "info", {}, self._rail.info, wrapped=self._rail)

    def unlock(self) -> Position:
        return self._rec.call("rail", "unlock", {}, self._rail.unlock, wrapped=self._rail)

    def close(self) -> None:
        self._rail.close()


# ---------------------------------------------------------------------- replay

QUERIES = {("camera", "info"), ("camera", "get"), ("camera", "choices"), ("rail", "info"), ("rail", "position")}
AXIS_TOLERANCE = 1e-6  # mm: the same requested coordinate, as a float read back from JSON


def _same_request(entry: dict, device: str, call: str, args: dict) -> bool:
    if (entry["device"], entry["call"]) != (device, call) or set(entry["args"]) != set(args):
        return False
    if call == "set":
        return entry["args"]["name"] == args["name"] and same_setting(entry["args"]["value"], args["value"])
    if call == "move":
        return all((a is None and b is None) or (a is not None and b is not None and abs(a - b) <= AXIS_TOLERANCE)
                   for a, b in ((entry["args"][k], args[k]) for k in args))
    return entry["args"] == args


class _RigState:
    """Where the rail was sent and what the camera was set to, as a sequence of actions leaves them."""

    def __init__(self) -> None:
        self.target: dict[str, float] | None = None
        self.settings: dict[str, str] = {}
        self.setup: dict | None = None

    def apply(self, call: str, args: dict, result: Any) -> None:
        if call == "move":
            self.target = {**(self.target or {}), **{k: v for k, v in args.items() if v is not None}}
        elif call in ("home", "unlock") and isinstance(result, dict):
            self.target = {k: v for k, v in result.items() if v is not None}
        elif call == "set":
            self.settings[args["name"]] = args["value"]
        elif call == "prepare":
            self.setup = args

    def changes_nothing(self, call: str, args: dict) -> bool:
        if call == "move":
            given = {k: v for k, v in args.items() if v is not None}
            return self.target is not None and all(
                k in self.target and abs(self.target[k] - v) <= AXIS_TOLERANCE for k, v in given.items())
        if call == "set":
            return args["name"] in self.settings and same_setting(self.settings[args["name"]], args["value"])
        return call == "prepare" and self.setup == args


class Replay:
    """The recorded rig, replayed (see the module's docstring for the rules).

    Shared by a `RecordingCamera` and a `RecordingRail` it replays the whole rig;
    given a ``device`` it follows that device's requests only.
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
        self.start = 0  # the first entry after the last replayed capture
        self.used: set[int] = set()
        self.state = _RigState()  # what the replay asked for

    def answer(self, device: str, call: str, args: dict) -> Any:
        """The recorded result of a request (recorded errors are raised); `ReplayError` when the recording
        cannot answer it."""
        args = _plain(args)
        if (device, call) in QUERIES:
            return self._query(device, call, args)
        asked = _describe(device, call, args)
        end = next((i for i in range(self.start, len(self.requests)) if self.requests[i]["call"] == "capture"),
                   len(self.requests))
        if call == "capture":
            if end == len(self.requests):
                raise ReplayError(f"{self.folder}: {asked} is past the end of the recording "
                                  f"({len(self.requests)} requests)")
            self._check_state(end)
            self.start = end + 1
            return self._result(self.requests[end])
        index = next((i for i in range(self.start, end) if i not in self.used
                      and _same_request(self.requests[i], device, call, args)), None)
        if index is None:
            if self.state.changes_nothing(call, args):
                return dataclasses.asdict(Position(**self._position())) if call == "move" else None
            pending = next((i for i in range(self.start, end) if i not in self.used
                            and (self.requests[i]["device"], self.requests[i]["call"]) not in QUERIES), end)
            if pending == len(self.requests):
                raise ReplayError(f"{self.folder}: {asked} is past the end of the recording "
                                  f"({len(self.requests)} requests)")
            entry = self.requests[pending]
            raise ReplayError(f"{self.folder}: request {pending + 1} is {asked} but the recording has "
                              f"{_describe(entry['device'], entry['call'], entry['args'])}")
        self.used.add(index)
        result = self._result(self.requests[index])  # a recorded failure changed nothing
        self.state.apply(call, args, result)
        return result

    def _query(self, device: str, call: str, args: dict) -> Any:
        """A query's recorded answer: the one nearest after the last capture, else the latest before it."""
        if call == "position" and self.state.target is not None:
            return self._position()
        asked = (device, call, args)
        matches = [i for i, r in enumerate(self.requests) if (r["device"], r["call"], r["args"]) == asked]
        if call == "get" and args["name"] in self.state.settings:
            matches = [i for i in matches if i >= self.start and "result" in self.requests[i]]
            if not matches:  # the value the replay set, as the camera would read it back
                return self.state.settings[args["name"]]
        if not matches:
            raise ReplayError(f"{self.folder}: the recording never asked {_describe(device, call, args)}")
        after = [i for i in matches if i >= self.start]
        return self._result(self.requests[after[0] if after else matches[-1]])

    def _position(self) -> dict:
        target = self.state.target or {}
        return {axis: target.get(axis) for axis in ("x", "y", "z")}

    def shots(self) -> list[tuple[dict[str, str], dict[str, float]]]:
        """Where the recorded rig stood at each capture, in order: the camera settings set before it (name to
        value, the camera's spelling) and the rail position it was sent to (axis to mm; empty: never moved).
        A replayed capture must find the rig so (`_check_state`)."""
        state, shots = _RigState(), []
        for entry in self.requests:
            if entry["call"] == "capture":
                shots.append((dict(state.settings), dict(state.target or {})))
            elif "result" in entry:
                state.apply(entry["call"], entry["args"], entry["result"])
        return shots

    def _check_state(self, capture: int) -> None:
        """The replayed rig must stand where the recorded one stood for this capture."""
        recorded = _RigState()
        for entry in self.requests[:capture]:
            if "result" in entry:
                recorded.apply(entry["call"], entry["args"], entry["result"])
        differences = [f"{name} {value} (recorded: {recorded.settings[name]})"
                       for name, value in self.state.settings.items()
                       if name in recorded.settings and not same_setting(value, recorded.settings[name])]
        if recorded.target is not None and not self.state.changes_nothing("move", recorded.target):
            differences.append(f"rail at {self._position()} (recorded: {recorded.target})")
        if differences:
            raise ReplayError(f"{self.folder}: capture {capture + 1} was recorded with the rig set otherwise: "
                              + ", ".join(differences))

    @staticmethod
    def _result(entry: dict) -> Any:
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

    def prepare(self, setup: CameraSetup) -> CameraReady:
        """The recorded preparation; no settle time (a replayed rail does not shake)."""
        ready = dict(self._replay.answer("camera", "prepare", dataclasses.asdict(setup)))
        return CameraReady(**{**ready, "notes": tuple(ready.get("notes", ())), "settle_s": 0.0})

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

    def info(self) -> RailInfo:
        info = dict(self._replay.answer("rail", "info", {}))
        return RailInfo(**{**info, "axes": tuple(info["axes"]),
                           "travel": {axis: tuple(span) for axis, span in info["travel"].items()}})

    def unlock(self) -> Position:
        return Position(**self._replay.answer("rail", "unlock", {}))

    def close(self) -> None:
        pass


def open_replay(folder: str | os.PathLike) -> tuple[RecordingCamera, RecordingRail]:
    """Camera and rail sharing one replay: the whole rig's session, captures in their recorded order."""
    replay = Replay(folder)
    return RecordingCamera(replay), RecordingRail(replay)
