"""`psfd camera ...`, `psfd rail ...`, `psfd record ...`: the rig by hand, and recordings of it.

Every command here takes the rig options of `psfd.cli.options.add_rig_options`.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import dataclass, field
from pathlib import Path

from psfd.cli import options, summary
from psfd.errors import BadInputError, CameraError, PsfdError

SETTINGS = ("aperture", "shutterspeed", "iso", "imageformat", "capturetarget")


def register(subparsers: argparse._SubParsersAction) -> None:
    camera = subparsers.add_parser("camera", help=summary("camera"))
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

    rail = subparsers.add_parser("rail", help=summary("rail"))
    rail_sub = rail.add_subparsers(dest="rail_command", metavar="ACTION", required=True)
    p = rail_sub.add_parser("home", help="run the homing cycle (--simulate: also start the simulated rig afresh)")
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
        help=summary("record"),
        description="Every request made to the rig is written to DIR/manifest.json in order, with the "
        "frames it produced (sha256) in DIR/frames. With --plan the rig, camera settings and setup, positions "
        "and apertures are the plan's, and `psfd run` of that plan with `recording = \"DIR\"` in its [rig] "
        "table replays it. A session that fails after the rig moved keeps what it recorded up to the failure.",
    )
    p.add_argument("--out", required=True, metavar="DIR", help="new (or empty) recording folder")
    what = p.add_mutually_exclusive_group(required=True)
    what.add_argument("--plan", metavar="PLAN", help="record the captures of this plan, on its rig")
    what.add_argument("--at", action="append", metavar="X=MM[,Y=MM,Z=MM]",
                      help="a rail position to capture at (repeat for several)")
    p.add_argument("--aperture", action="append", metavar="F[,F...]",
                   help="apertures to capture at each position (repeat or comma-separate; default: as set)")
    p.add_argument("--home", action="store_true", help="home the rail first")
    p.add_argument("--scene", choices=("bernoulli", "texture"), default=None,
                   help="simulated scene (--simulate; default bernoulli)")
    p.add_argument("--seed", default=None, help="simulated rig seed (--simulate; default 0)")
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
    if args.simulate:  # the simulated rig starts afresh: default settings, shutter count 0, then home
        from psfd.drivers.sim import state_path

        state_path().unlink(missing_ok=True)
    return _with_rail(args, lambda rail: rail.home())


def rail_move(args: argparse.Namespace) -> int:
    position = options.parse_axes(args.axes, "move")
    return _with_rail(args, lambda rail: rail.move(**position))


def rail_position(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.position())


def rail_unlock(args: argparse.Namespace) -> int:
    return _with_rail(args, lambda rail: rail.unlock())


def record(args: argparse.Namespace) -> int:
    """Capture at every shot of the session, recording every request; DIR appears only when the rig acted."""
    from psfd.cli.output import check_out_dir, publish, staging_dir
    from psfd.drivers import open_rig
    from psfd.drivers.recording import Recorder

    session = _record_plan(args) if args.plan else _record_options(args)
    out = check_out_dir(args.out)
    work = staging_dir(out)
    frames, failure = 0, None
    try:
        camera, rail = open_rig(session.rig)
        recorder = Recorder(work / "recording", camera, rail, rig=session.rig)
        try:
            frames = _record_session(recorder, session, work / "downloads")
        except BaseException as exc:  # a failure, or Ctrl-C: what the rig did up to it is worth keeping
            failure = exc
        finally:
            recorder.close()
        if failure is not None and not recorder.acted:
            raise failure  # refused before the rig did anything: nothing to keep
        publish(work / "recording", out)  # with the umask's permissions, as any new folder
    finally:
        shutil.rmtree(work, ignore_errors=True)
    if failure is not None:
        print(f"psfd: kept the {len(recorder.requests)} requests recorded up to the failure in {out}", file=sys.stderr)
        raise failure
    print(f"recorded {len(recorder.requests)} requests and {frames} frames into {out}")
    return 0


@dataclass
class Session:
    """What `psfd record` does: the rig, settings and setup applied first, then the shots in order.

    Each shot is (aperture or None: as set, [rail positions]); the rail moves only when the position changes.
    """

    rig: dict
    settings: dict = field(default_factory=dict)
    setup: dict = field(default_factory=dict)
    home: bool = False
    shots: list[tuple[str | None, list[dict]]] = field(default_factory=list)


def _record_options(args: argparse.Namespace) -> Session:
    positions = [options.parse_axes([at], "--at") for at in args.at]
    apertures = options.parse_fnumbers(args.aperture)
    config = options.rig_config(args)
    if not args.simulate and (args.scene or args.seed is not None):
        raise BadInputError("--scene and --seed apply to the simulated rig: add --simulate")
    if args.simulate:
        config.update({"scene": args.scene} if args.scene else {})
        config.update({"seed": options.parse_int(args.seed, "--seed", minimum=0)} if args.seed is not None else {})
    shots = [(aperture, [position]) for position in positions for aperture in apertures or [None]]
    return Session(config, home=args.home, shots=shots)


def _record_plan(args: argparse.Namespace) -> Session:
    """The plan's rig and steps, in the order `psfd run` takes them."""
    from psfd.daemon.plan import fmt, load_plan

    if args.aperture or args.scene or args.seed is not None or args.simulate:
        raise BadInputError("--plan gives the rig and apertures: drop --aperture, --scene, --seed and --simulate")
    plan = load_plan(args.plan)
    shots = []
    for step in plan.steps():
        distances = step.x if isinstance(step.x, tuple) else (step.x,)
        shots.append((fmt(step.aperture), [{"x": x, "y": step.y, "z": step.z} for x in distances]))
    return Session(plan.rig_config(), settings=dict(plan.rig.get("settings", {})),
                   setup=dict(plan.rig.get("camera", {})), home=args.home, shots=shots)


def _record_session(recorder, session: Session, downloads: Path) -> int:
    """The camera and the rail described (so a replay can answer `plan check`), set up, then the shots."""
    from psfd.drivers.base import CameraSetup
    from psfd.vocabulary import offered_choice, setting_text

    camera, rail = recorder.camera, recorder.rail
    camera.info()
    rail.info()
    offered = camera.choices("aperture")
    for aperture, _ in session.shots:  # refused before any motion; the camera's own spelling is recorded
        if aperture is not None and offered_choice(aperture, offered) is None:
            raise CameraError(f"aperture {aperture} is not offered by the camera (offered: {', '.join(offered)})")
    for name, value in session.settings.items():
        camera.set(name, setting_text(value))
    camera.prepare(CameraSetup.from_mapping(session.setup))
    if session.home:
        rail.home()
    frames, at = 0, None
    for aperture, positions in session.shots:
        if aperture is not None:
            camera.set("aperture", offered_choice(aperture, offered))  # offered: checked before any motion
        for position in positions:
            if position != at:
                rail.move(**position)
                at = position
            frames += len(camera.capture(downloads))
    return frames
