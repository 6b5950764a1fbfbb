"""`psfd camera ...`, `psfd rail ...`, `psfd record ...`: the rig by hand, and recordings of it."""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

from psfd.catalogue import parse_fnumber
from psfd.cli.output import parse_float, parse_int, staging_dir
from psfd.drivers import open_camera, open_rail
from psfd.drivers.base import Position
from psfd.errors import BadInputError, PsfdError

SETTINGS = ("aperture", "shutterspeed", "iso", "imageformat", "capturetarget")


def register(subparsers: argparse._SubParsersAction) -> None:
    camera = subparsers.add_parser("camera", help="camera information and settings")
    camera_sub = camera.add_subparsers(dest="camera_command", metavar="ACTION", required=True)
    p = camera_sub.add_parser("info", help="model, serial, lens and the settings with their offered values")
    p.add_argument("--json", action="store_true", help="print JSON")
    _rig_options(p)
    p.set_defaults(func=camera_info)
    p = camera_sub.add_parser("set", help="set a setting, e.g. `psfd camera set aperture 5.6`")
    p.add_argument("name", help=f"{', '.join(SETTINGS)}, or a gphoto2 widget name")
    p.add_argument("value")
    _rig_options(p)
    p.set_defaults(func=camera_set)

    rail = subparsers.add_parser("rail", help="home, move or read the rail")
    rail_sub = rail.add_subparsers(dest="rail_command", metavar="ACTION", required=True)
    p = rail_sub.add_parser("home", help="run the homing cycle")
    _rig_options(p)
    p.set_defaults(func=rail_home)
    p = rail_sub.add_parser("move", help="absolute move in mm, e.g. `psfd rail move X=120 Y=-5`")
    p.add_argument("axes", nargs="+", metavar="AXIS=MM")
    _rig_options(p)
    p.set_defaults(func=rail_move)
    p = rail_sub.add_parser("position", help="print the current position")
    _rig_options(p)
    p.set_defaults(func=rail_position)
    p = rail_sub.add_parser("unlock", help="clear an alarm lock without homing ($X on GRBL)",
                            description="Clears the controller's alarm lock without homing, e.g. on a rail without "
                                        "homing switches or after a soft-limit alarm; positions are then what the "
                                        "controller believes. Prefer `psfd rail home` when it has switches.")
    _rig_options(p)
    p.set_defaults(func=rail_unlock)

    p = subparsers.add_parser(
        "record",
        help="capture at rail positions and apertures, writing a replayable recording",
        description="Every request made to the rig is written to DIR/manifest.json in order, with the "
        "frames it produced (sha256) in DIR/frames; `open_rig({'recording': DIR})` replays it.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="new (or empty) recording folder")
    p.add_argument("--at", action="append", required=True, metavar="X=MM[,Y=MM,Z=MM]",
                   help="a rail position to capture at (repeat for several)")
    p.add_argument("--aperture", action="append", metavar="F[,F...]",
                   help="apertures to capture at each position (repeat or comma-separate; default: as set)")
    p.add_argument("--home", action="store_true", help="home the rail first")
    p.add_argument("--scene", choices=("bernoulli", "texture"), default=None, help="simulated scene (--simulate)")
    p.add_argument("--seed", default=None, help="simulated rig seed (--simulate)")
    _rig_options(p)
    p.set_defaults(func=record)


def _rig_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--simulate", action="store_true", help="use the simulated rig")
    p.add_argument("--camera-port", help="gphoto2 port, e.g. usb:001,004 (default: the only camera)")
    p.add_argument("--rail-port", help="serial port of the rail, e.g. /dev/ttyUSB0")
    p.add_argument("--rail-limits", metavar="X=MIN:MAX[,Y=MIN:MAX]",
                   help="soft limits in mm (default: X=0:500 on a real rail, the simulated rig's own travel "
                        "with --simulate)")


# ---------------------------------------------------------------- argument values


def rig_config(args: argparse.Namespace) -> dict:
    """The rig description (`psfd.drivers.open_rig`) the options name."""
    config: dict = {"simulate": True} if args.simulate else {}
    if not args.simulate:
        if args.camera_port:
            config["camera_port"] = args.camera_port
        if args.rail_port:
            config["rail_port"] = args.rail_port
    if args.rail_limits:
        config["rail_limits"] = parse_limits(args.rail_limits)
    if args.simulate and getattr(args, "scene", None):
        config["scene"] = args.scene
    if args.simulate and getattr(args, "seed", None) is not None:
        config["seed"] = parse_int(args.seed, "--seed", minimum=0)
    return config


def parse_axes(words: list[str], option: str) -> dict[str, float]:
    """``["X=120", "Y=-5"]`` or ``["X=120,Y=-5"]`` -> ``{"x": 120.0, "y": -5.0}``."""
    axes: dict[str, float] = {}
    for word in (w for item in words for w in item.split(",") if w.strip()):
        name, sep, value = word.strip().partition("=")
        axis = name.strip().lower()
        if not sep or axis not in ("x", "y", "z"):
            raise BadInputError(f"{option}: expected AXIS=MM with AXIS one of X, Y, Z, got {word!r}")
        if axis in axes:
            raise BadInputError(f"{option}: axis {axis.upper()} given twice")
        axes[axis] = parse_float(value, f"{option} {axis.upper()}")
    if not axes:
        raise BadInputError(f"{option}: give at least one AXIS=MM")
    return axes


def parse_limits(text: str) -> dict[str, list[float]]:
    """``X=0:500,Y=-50:50`` -> ``{"x": [0, 500], "y": [-50, 50]}``."""
    limits = {}
    for word in text.split(","):
        name, sep, span = word.strip().partition("=")
        lo, colon, hi = span.partition(":")
        if not sep or not colon or name.strip().lower() not in ("x", "y", "z"):
            raise BadInputError(f"--rail-limits: expected AXIS=MIN:MAX, got {word.strip()!r}")
        bounds = [parse_float(lo, "--rail-limits"), parse_float(hi, "--rail-limits")]
        if bounds[0] > bounds[1]:
            raise BadInputError(f"--rail-limits: {name.strip().upper()} minimum is above its maximum")
        limits[name.strip().lower()] = bounds
    return limits


def check_fnumber(text: str, option: str) -> str:
    """``text`` unchanged if it is a positive f-number (``5.6``, ``f/5.6``); else bad input, not a camera fault."""
    try:
        parse_fnumber(text)
    except BadInputError:
        raise BadInputError(f"{option}: expected a positive f-number such as 5.6, got {text!r}") from None
    return text


def _apertures(values: list[str] | None) -> list[str]:
    return [check_fnumber(v.strip(), "--aperture") for item in values or [] for v in item.split(",") if v.strip()]


def _position_text(pos: Position) -> str:
    return " ".join(f"{a}={v:g}" for a, v in (("X", pos.x), ("Y", pos.y), ("Z", pos.z)) if v is not None)


# ---------------------------------------------------------------- commands


def camera_info(args: argparse.Namespace) -> int:
    camera = open_camera(rig_config(args))
    try:
        info = camera.info()
        settings = {}
        for name in SETTINGS:
            try:
                settings[name] = {"value": camera.get(name), "choices": camera.choices(name)}
            except PsfdError:
                continue  # a setting this camera does not have
    finally:
        camera.close()
    if args.json:
        print(json.dumps({"model": info.model, "serial": info.serial, "lens": info.lens,
                          "focal_length_mm": info.focal_length_mm, "port": info.port, "settings": settings}, indent=1))
        return 0
    print(f"model    {info.model}")
    for label, value in (("serial", info.serial), ("lens", info.lens), ("port", info.port)):
        if value:
            print(f"{label:<8} {value}")
    if info.focal_length_mm:
        print(f"focal    {info.focal_length_mm:g} mm")
    for name, item in settings.items():
        offered = ", ".join(item["choices"]) if item["choices"] else "any"
        print(f"{name:<14} {item['value']:<12} (offered: {offered})")
    return 0


def camera_set(args: argparse.Namespace) -> int:
    # A number must be a positive f-number; named choices ("implicit auto") are the camera's to judge.
    if args.name == "aperture" and any(c.isdigit() for c in args.value):
        check_fnumber(args.value, "aperture")
    camera = open_camera(rig_config(args))
    try:
        camera.set(args.name, args.value)
        print(f"{args.name} = {camera.get(args.name)}")
    finally:
        camera.close()
    return 0


def _with_rail(args: argparse.Namespace, action) -> int:
    rail = open_rail(rig_config(args))
    try:
        print(_position_text(action(rail)))
    finally:
        rail.close()
    return 0


def rail_home(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.home())


def rail_move(args: argparse.Namespace) -> int:
    target = parse_axes(args.axes, "move")
    return _with_rail(args, lambda rail: rail.move(**target))


def rail_position(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.position())


def rail_unlock(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.unlock())


def record(args: argparse.Namespace) -> int:
    """Capture at every --at position and --aperture, recording every request; DIR appears only when complete."""
    from psfd.drivers import open_rig
    from psfd.drivers.recording import Recorder

    positions = [parse_axes([at], "--at") for at in args.at]
    apertures = _apertures(args.aperture)
    out = Path(args.out).absolute()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise BadInputError(f"{out}: exists and is not an empty folder")
    if not out.parent.is_dir() or not os.access(out.parent, os.W_OK):
        raise BadInputError(f"{out.parent}: not a writable folder")
    config = rig_config(args)
    work = staging_dir(out)
    frames = 0
    try:
        camera, rail = open_rig(config)
        recorder = Recorder(work / "recording", camera, rail, rig=config)
        try:
            frames = _record_session(recorder, positions, apertures, args.home, work / "downloads")
        finally:
            recorder.close()
        shutil.rmtree(work / "downloads", ignore_errors=True)
        if out.exists():
            out.rmdir()
        os.replace(work / "recording", out)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"recorded {len(recorder.requests)} requests and {frames} frames into {out}")
    return 0


def _record_session(recorder, positions: list[dict], apertures: list[str], home: bool, downloads: Path) -> int:
    camera, rail = recorder.camera, recorder.rail
    camera.info()
    if home:
        rail.home()
    frames = 0
    for target in positions:
        rail.move(**target)
        for aperture in apertures or [None]:
            if aperture is not None:
                camera.set("aperture", aperture)
            frames += len(camera.capture(downloads))
    return frames
