"""`psfd camera ...`, `psfd rail ...`, `psfd record ...`: the rig by hand, and recordings of it.

Every command here takes the rig options of `psfd.cli.options.add_rig_options`.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
from pathlib import Path

from psfd.cli import options
from psfd.errors import PsfdError

SETTINGS = ("aperture", "shutterspeed", "iso", "imageformat", "capturetarget")


def register(subparsers: argparse._SubParsersAction) -> None:
    camera = subparsers.add_parser("camera", help="camera information and settings")
    camera_sub = camera.add_subparsers(dest="camera_command", metavar="ACTION", required=True)
    p = camera_sub.add_parser("info", help="model, serial, lens and the settings with their offered values")
    p.add_argument("--json", action="store_true", help="print JSON")
    options.add_rig_options(p)
    p.set_defaults(func=camera_info)
    p = camera_sub.add_parser("set", help="set a setting, e.g. `psfd camera set aperture 5.6`")
    p.add_argument("name", help=f"{', '.join(SETTINGS)}, or a gphoto2 widget name")
    p.add_argument("value")
    options.add_rig_options(p)
    p.set_defaults(func=camera_set)

    rail = subparsers.add_parser("rail", help="home, move or read the rail")
    rail_sub = rail.add_subparsers(dest="rail_command", metavar="ACTION", required=True)
    p = rail_sub.add_parser("home", help="run the homing cycle")
    options.add_rig_options(p)
    p.set_defaults(func=rail_home)
    p = rail_sub.add_parser("move", help="absolute move in mm, e.g. `psfd rail move X=120 Y=-5`")
    p.add_argument("axes", nargs="+", metavar="AXIS=MM")
    options.add_rig_options(p)
    p.set_defaults(func=rail_move)
    p = rail_sub.add_parser("position", help="print the current position")
    options.add_rig_options(p)
    p.set_defaults(func=rail_position)
    p = rail_sub.add_parser("unlock", help="clear an alarm lock without homing ($X on GRBL)",
                            description="Clears the controller's alarm lock without homing, e.g. on a rail without "
                                        "homing switches or after a soft-limit alarm; positions are then what the "
                                        "controller believes. Prefer `psfd rail home` when it has switches.")
    options.add_rig_options(p)
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
    options.add_rig_options(p)
    p.set_defaults(func=record)


def _position_text(pos) -> str:
    return " ".join(f"{a}={v:g}" for a, v in (("X", pos.x), ("Y", pos.y), ("Z", pos.z)) if v is not None)


# ---------------------------------------------------------------- commands


def camera_info(args: argparse.Namespace) -> int:
    from psfd.drivers import open_camera

    camera = open_camera(options.rig_config(args))
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
        options.parse_fnumber(args.value, "aperture")
    from psfd.drivers import open_camera

    camera = open_camera(options.rig_config(args))
    try:
        camera.set(args.name, args.value)
        print(f"{args.name} = {camera.get(args.name)}")
    finally:
        camera.close()
    return 0


def _with_rail(args: argparse.Namespace, action) -> int:
    from psfd.drivers import open_rail

    rail = open_rail(options.rig_config(args))
    try:
        print(_position_text(action(rail)))
    finally:
        rail.close()
    return 0


def rail_home(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.home())


def rail_move(args: argparse.Namespace) -> int:
    position = options.parse_axes(args.axes, "move")
    return _with_rail(args, lambda rail: rail.move(**position))


def rail_position(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.position())


def rail_unlock(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.unlock())


def record(args: argparse.Namespace) -> int:
    """Capture at every --at position and --aperture, recording every request; DIR appears only when complete."""
    from psfd.cli.output import check_out_dir, staging_dir
    from psfd.drivers import open_rig
    from psfd.drivers.recording import Recorder

    positions = [options.parse_axes([at], "--at") for at in args.at]
    apertures = options.parse_fnumbers(args.aperture)
    out = check_out_dir(args.out)
    config = options.rig_config(args)
    if args.simulate:
        config.update({"scene": args.scene} if args.scene else {})
        config.update({"seed": options.parse_int(args.seed, "--seed", minimum=0)} if args.seed is not None else {})
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
    for position in positions:
        rail.move(**position)
        for aperture in apertures or [None]:
            if aperture is not None:
                camera.set("aperture", aperture)
            frames += len(camera.capture(downloads))
    return frames
