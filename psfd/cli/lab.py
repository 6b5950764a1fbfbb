"""Lab commands: capture, run, status, plan check, serve, demo.

Thin: parse, call the daemon, print. A command that drives the rig goes
through the service when its control socket answers (the service owns the
rig), and runs in this process otherwise.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
from pathlib import Path

from psfd.daemon import plan as plans
from psfd.daemon import service
from psfd.daemon.runner import Control, Runner, RunResult, frames_dir_for, shown_state
from psfd.errors import BadInputError, ServiceError
from psfd.estimator.raw import CHANNELS


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "capture", help="shoot and estimate one target frame or near/far pair now",
        description="Shoot one frame of the Bernoulli noise target (or a near/far pair of a textured plane) "
                    "at one aperture and rail position, estimate its PSFs and add them to the catalogue.")
    p.add_argument("--aperture", required=True, help="f-number, e.g. 5.6")
    p.add_argument("--rail", action="append", default=[], metavar="AXIS=MM",
                   help="rail position, e.g. X=1200 or X=1200,Y=-40 (repeatable); "
                        "default with --simulate: X at the simulated rig's working distance")
    p.add_argument("--target", choices=plans.KINDS, default="bernoulli",
                   help="bernoulli: one frame of the noise target (default); pair: near and far frames "
                        "of a textured plane")
    p.add_argument("--near", help="pair: near distance in mm (default with --simulate: 587.5)")
    p.add_argument("--far", help="pair: far distance in mm (default with --simulate: 2200)")
    p.add_argument("--channels", default="all", help=f"all, or a comma list of {','.join(CHANNELS)}")
    p.add_argument("--out", metavar="DIR", help="store the RAW frames here (default: beside the catalogue)")
    _rig_options(p)
    _common(p)
    p.set_defaults(func=run_capture)

    p = subparsers.add_parser("run", help="run a measurement plan (TOML) on the rig")
    p.add_argument("plan", metavar="PLAN")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--resume", action="store_true", help="continue the unfinished run of this plan")
    how.add_argument("--new", action="store_true",
                     help="start a fresh run even though this plan has an unfinished one")
    p.add_argument("--local", action="store_true", help="run in this process even when the service is up")
    _common(p)
    p.set_defaults(func=run_plan)

    p = subparsers.add_parser("status", help="what the service is doing, or the latest runs in the catalogue")
    p.add_argument("--json", action="store_true", help="print the status as JSON")
    _common(p)
    p.set_defaults(func=run_status)

    p = subparsers.add_parser("plan", help="work with measurement plans")
    sub = p.add_subparsers(dest="plan_command", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("check", help="list every problem of a plan, one per line")
    c.add_argument("plan", metavar="PLAN")
    c.set_defaults(func=run_plan_check)

    p = subparsers.add_parser("serve", help="run the service: control socket, job queue, systemd notify")
    _common(p)
    p.set_defaults(func=run_serve)

    p = subparsers.add_parser("demo", help="a complete plan on the simulated rig, then the query table and report")
    p.add_argument("--workdir", default="psfd-demo", metavar="DIR", help="working folder (default ./psfd-demo)")
    _runner_options(p)
    p.add_argument("--catalogue", metavar="PATH", help="catalogue file (default: DIR/catalogue.sqlite)")
    p.set_defaults(func=run_demo)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--catalogue", default=None, metavar="PATH",
                   help="catalogue file (default $XDG_DATA_HOME/psfd/catalogue.sqlite)")
    p.add_argument("--socket", default=None, metavar="PATH",
                   help=f"service control socket (default {service.default_socket_path()})")
    p.add_argument("--frames", default=None, metavar="DIR", help="frame store (default: beside the catalogue)")
    _runner_options(p)


def _rig_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--simulate", action="store_true", help="use the simulated rig")
    p.add_argument("--camera-port", help="gphoto2 port, e.g. usb:001,004 (default: the first camera)")
    p.add_argument("--rail-port", help="serial port of the rail, e.g. /dev/ttyUSB0")


def _runner_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", help="estimation processes (default: cores - 1, at least 1)")
    p.add_argument("--backlog", help="frames that may wait for estimation before the rig waits (default 4 per worker)")


def _runner(args: argparse.Namespace) -> dict[str, int]:
    """The Runner's ``workers`` and ``backlog`` given on the command line (the others keep its defaults)."""
    from psfd.cli.output import parse_int

    return {name: parse_int(getattr(args, name), f"--{name}", minimum=1)
            for name in ("workers", "backlog") if getattr(args, name) is not None}


def _paths(args: argparse.Namespace) -> tuple[Path, Path, Path]:
    from psfd.catalogue import default_path

    catalogue = Path(args.catalogue) if args.catalogue else default_path()
    frames = Path(args.frames) if getattr(args, "frames", None) else frames_dir_for(catalogue)
    sock = Path(args.socket) if args.socket else service.default_socket_path()
    return catalogue, frames, sock


# -- run and capture -----------------------------------------------------------------------------


def execute(plan: plans.Plan, catalogue_path: Path, frames_dir: Path, resume: bool = False,
            runner_options: dict[str, int] | None = None, new: bool = False, oneshot: bool = False) -> RunResult:
    """Run a plan in this process on the rig its [rig] table names (see `Runner.run` for the flags)."""
    from psfd.catalogue import Catalogue
    from psfd.drivers import open_rig

    control = Control()

    def stop(signum, frame):  # first Ctrl-C or SIGTERM: finish the current frame and pause
        signal.signal(signum, signal.default_int_handler)
        print("\npsfd: stopping after the current frame (again to abort)", file=sys.stderr)
        control.request("pause")

    previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        with Catalogue(catalogue_path) as catalogue:
            camera, rail = open_rig(plan.rig_config())
            runner = Runner(catalogue, frames_dir, control=control, **(runner_options or {}))
            return runner.run(plan, camera, rail, resume=resume, new=new, oneshot=oneshot)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def plural(n: int, word: str) -> str:
    """``1 step``, ``2 steps``."""
    return f"{n} {word}{'s' * (n != 1)}"


def _report(result: RunResult | dict, resume_hint: str | None) -> int:
    """Print how a run ended; the exit code of the error that stopped it, else 0.

    ``resume_hint`` is the command line that continues a paused run (None: a one-shot run).
    """
    r = result if isinstance(result, dict) else service.result_dict(result)
    if r.get("run_id") is None or r["state"] == "failed":  # not started (camera not found...) or one-shot failed
        print(f"psfd: error: {r.get('reason')}", file=sys.stderr)
        return int(r.get("exit_code") or ServiceError.exit_code)
    print(f"run {r['run_id']} {r['state']}: {plural(r['steps_done'], 'step')}, {plural(r['frames'], 'frame')}, "
          f"{plural(r['psfs'], 'PSF')} in {r['elapsed_s']:.1f} s")
    if r["state"] == "paused":
        hint = f"; continue with: {resume_hint}" if resume_hint else ""
        print(f"run {r['run_id']} paused ({r['reason']}){hint}", file=sys.stderr)
        return int(r["exit_code"])
    return 0


def _again(args: argparse.Namespace, *command: str) -> str:
    """The command line ``psfd COMMAND...`` with this one's catalogue, socket and frame store (those given)."""
    import shlex

    words = ["psfd", *command]
    for name in ("catalogue", "socket", "frames"):
        if getattr(args, name, None):
            words += [f"--{name}", getattr(args, name)]
    return shlex.join(words)


def run_plan(args: argparse.Namespace) -> int:
    catalogue, frames, sock = _paths(args)
    plan = plans.load_plan(args.plan)
    if not args.local and service.service_up(sock):
        answer = service.request(sock, {"cmd": "submit", "plan": plan.text, "path": str(Path(args.plan).resolve()),
                                        "resume": args.resume, "new": args.new})
        follow = "psfd status" + (f" --socket {args.socket}" if args.socket else "")
        print(f"submitted {args.plan} to the service at {sock} ({answer['queued']} queued); "
              f"follow it with: {follow}")
        return 0
    options = _runner(args)
    if args.resume and not catalogue.exists():
        raise BadInputError(f"no unfinished run of plan {args.plan} to resume (no catalogue at {catalogue})")
    result = execute(plan, catalogue, frames, args.resume, options, new=args.new)
    return _report(result, _again(args, "run", args.plan, "--resume"))


def parse_rail(values: list[str]) -> dict[str, float]:
    """``["X=1200,Y=-40", "z=5"]`` -> {"x": 1200.0, "y": -40.0, "z": 5.0}."""
    out: dict[str, float] = {}
    for item in ",".join(values).split(","):
        if not item.strip():
            continue
        axis, sep, value = item.partition("=")
        axis = axis.strip().lower()
        if not sep or axis not in plans.AXES:
            raise BadInputError(f"--rail: expected AXIS=MM with AXIS one of X, Y, Z, got {item!r}")
        try:
            out[axis] = float(value)
        except ValueError:
            raise BadInputError(f"--rail: {axis.upper()} must be a number of mm, got {value!r}") from None
    return out


def capture_plan(args: argparse.Namespace) -> str:
    """The one-step plan text of a `psfd capture` command line (its options checked here, named as options)."""
    rail = parse_rail(args.rail)
    try:
        aperture = float(str(args.aperture).lower().removeprefix("f/"))
    except ValueError:
        raise BadInputError(f"--aperture: expected an f-number such as 5.6, got {args.aperture!r}") from None
    if not (aperture > 0 and aperture < float("inf")):
        raise BadInputError(f"--aperture: expected a positive f-number such as 5.6, got {args.aperture!r}")
    channels = _capture_channels(args.channels)
    if args.target == "bernoulli" and (args.near is not None or args.far is not None):
        raise BadInputError("--near and --far apply to --target pair; give the distance as --rail X=MM")
    lines = ["[rig]"]
    if args.simulate:
        lines.append("simulate = true")
        if args.target == "pair":
            lines.append('scene = "texture"')
    for key in ("camera_port", "rail_port"):
        if getattr(args, key):
            lines.append(f"{key} = {json.dumps(getattr(args, key))}")
    lines += ["", "[target]", f'kind = "{args.target}"']
    if args.target == "pair":
        if "x" in rail:
            raise BadInputError("--rail X does not apply to a pair: give --near MM and --far MM")
        near, far = _pair_distances(args)
        lines += [f"near = {near}", f"far = {far}"]
    lines += ["", "[capture]", f"apertures = [{aperture}]"]
    if args.target == "bernoulli":
        lines.append(f"x = [{rail['x'] if 'x' in rail else _default_distance(args)}]")
    lines += [f"{axis} = [{rail[axis]}]" for axis in ("y", "z") if axis in rail]
    lines.append(f"channels = {json.dumps(channels)}")
    return "\n".join(lines) + "\n"


def _capture_channels(text: str) -> str | list[str]:
    if text.strip() == "all":
        return "all"
    channels = [c.strip() for c in text.split(",")]
    bad = [c for c in channels if c not in CHANNELS]
    if bad or len(set(channels)) != len(channels):
        raise BadInputError(f"--channels: expected all, or a comma list of distinct {', '.join(CHANNELS)}, "
                            f"got {text!r}")
    return channels


def writable_folder(path: Path, option: str) -> Path:
    """Create ``path`` as a folder (parents too) or say in one line why it cannot be one."""
    if path.exists() and not path.is_dir():
        raise BadInputError(f"{option} {path}: exists and is not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInputError(f"{option} {path}: cannot create the folder ({exc.strerror or exc})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise BadInputError(f"{option} {path}: not a writable folder")
    return path


def _default_distance(args: argparse.Namespace) -> float:
    if not args.simulate:
        raise BadInputError("--rail X=MM is needed: the distance of the target on the rail")
    from psfd.drivers import sim

    return float(sim.SimRig().distance_for_scale())


def _pair_distances(args: argparse.Namespace) -> tuple[float, float]:
    from psfd.cli.output import parse_float

    if args.near is None or args.far is None:
        if not args.simulate:
            raise BadInputError("--near MM and --far MM are needed for a pair")
        from psfd.drivers import sim

        near, far = sim.SimRig(scene="texture").pair_distances()
    near = parse_float(args.near, "--near") if args.near is not None else near
    far = parse_float(args.far, "--far") if args.far is not None else far
    return near, far


def run_capture(args: argparse.Namespace) -> int:
    catalogue, frames, sock = _paths(args)
    if args.out:
        frames = Path(args.out)
    text = capture_plan(args)
    problems = plans.check_text(text)  # what is left after capture_plan: positions off the rail, lambda <= s
    if problems:
        option = "--near/--far" if args.target == "pair" else "--rail"
        raise BadInputError(f"{option}: {problems[0].removeprefix('[target] ')}")
    plan = plans.parse_plan(text, "capture")
    options = _runner(args)
    if service.service_up(sock):
        if args.out:
            raise BadInputError("--out cannot be used through the service (it writes to its own frame store)")
        answer = service.request(sock, {"cmd": "submit", "plan": text, "path": "capture", "wait": True,
                                        "new": True, "oneshot": True}, timeout=None)
        result = answer["result"]
    else:
        if args.out:
            writable_folder(frames, "--out")
        run = execute(plan, catalogue, frames, runner_options=options, new=True, oneshot=True)
        result = service.result_dict(run)
        if run.psf_ids:
            from psfd.catalogue import Catalogue

            with Catalogue(catalogue, create=False) as cat:
                result["rows"] = [cat.psf(i)[1] for i in run.psf_ids]
    code = _report(result, None)
    if result.get("rows"):
        from psfd.cli.query import format_table

        print(format_table(result["rows"]))
    return code


# -- status, plan check, serve -------------------------------------------------------------------


def run_status(args: argparse.Namespace) -> int:
    catalogue, _, sock = _paths(args)
    if service.service_up(sock):
        answer = service.request(sock, {"cmd": "status"})
        answer.pop("ok", None)
        if args.json:
            print(json.dumps(answer))
            return 0
        print(f"service at {sock}: {answer['state']}, {answer['queued']} queued")
        if answer["current"]:
            c = answer["current"]
            print(f"  running {c['plan']}: {c['done']}/{c['total']} steps, at {c['step']}")
        if answer["last"]:
            last = answer["last"]
            print(f"  last: {last['plan']} run {last.get('run_id', '-')} {last['state']}"
                  + (f" ({last['reason']})" if last.get("reason") else ""))
        return 0
    from psfd.catalogue import Catalogue

    if not catalogue.exists():
        print(f"no service at {sock}; no catalogue at {catalogue}")
        return 0
    with Catalogue(catalogue, create=False) as cat:
        summaries = [cat.run_summary(r["id"]) for r in cat.runs()[:10]]
    frames = Path(args.frames) if args.frames else frames_dir_for(catalogue)
    for s in summaries:  # a run its process no longer holds was killed: say so, it is resumable
        s["state"] = shown_state(s["state"], frames)
    if args.json:
        print(json.dumps({"service": None, "runs": summaries}))
        return 0
    print(f"no service at {sock}; latest runs in {catalogue}:")
    print(f"{'run':>5} {'state':<11} {'done':>9} {'failed':>6} {'psfs':>6}  plan")
    for s in summaries:
        print(f"{s['id']:>5} {s['state']:<11} {s['done']:>4}/{s['total']:<4} {s['failed']:>6} {s['psfs']:>6}  "
              f"{s['plan_path']}")
    return 0


def run_plan_check(args: argparse.Namespace) -> int:
    path = Path(args.plan)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInputError(f"cannot read plan {path}: {exc}") from None
    problems = plans.check_text(text)
    for problem in problems:
        print(f"{path}: {problem}", file=sys.stderr)
    if problems:
        raise BadInputError(f"{path}: {len(problems)} problem{'s' * (len(problems) > 1)} found")
    plan = plans.parse_plan(text, str(path))
    steps = len(plan.steps())
    nx, ny = plan.estimator_options().get("grid", (1, 1))
    print(f"{path}: ok, {plural(steps, 'step')}, {plural(steps * (2 if plan.kind == 'pair' else 1), 'frame')}, "
          f"{plural(steps * len(plan.channels) * nx * ny, 'PSF')}")
    return 0


def run_serve(args: argparse.Namespace) -> int:
    catalogue, frames, sock = _paths(args)
    return service.Service(catalogue, frames, sock, runner_options=_runner(args)).serve()


# -- demo ----------------------------------------------------------------------------------------


def demo_plan() -> str:
    """A complete plan on the simulated rig: 3 apertures x a 3x3 field grid x 4 channels."""
    from psfd.drivers import sim

    rig = sim.SimRig()
    distance = float(rig.distance_for_scale())
    y, z = rig.field_offsets(3)
    return (
        "# psfd demo: the simulated rig walks the target over a 3x3 field grid at three apertures\n"
        "[rig]\nsimulate = true\n\n"
        '[target]\nkind = "bernoulli"\n\n'
        f"[capture]\napertures = [4, 8, 16]\nx = [{plans.fmt(distance)}]\n"
        f"y = {json.dumps([float(v) for v in y])}\nz = {json.dumps([float(v) for v in z])}\n"
        'channels = "all"\nrepeats = 1\n\n'
        '[estimator]\ns = 4\n'
    )


def run_demo(args: argparse.Namespace) -> int:
    import contextlib
    import hashlib

    from psfd.catalogue import Catalogue

    options = _runner(args)  # every option is checked before anything is written or printed
    workdir = Path(args.workdir)
    catalogue = Path(args.catalogue) if args.catalogue else workdir / "catalogue.sqlite"
    if catalogue.is_dir():
        raise BadInputError(f"--catalogue {catalogue}: is a folder, expected a catalogue file")
    created = not workdir.exists()
    writable_folder(workdir, "--workdir")
    plan_path = workdir / "demo.toml"
    try:
        text = plan_path.read_text(encoding="utf-8") if plan_path.exists() else demo_plan()
        plan = plans.parse_plan(text, str(plan_path))
        with Catalogue(catalogue) as cat:
            runs = [r for r in cat.runs() if r["plan_hash"] == hashlib.sha256(text.encode()).hexdigest()]
    except BaseException:
        if created:  # leave no empty working folder behind a refused demo
            with contextlib.suppress(OSError):
                workdir.rmdir()
        raise
    if not plan_path.exists():
        staging = workdir / ".demo.toml.partial"
        staging.write_text(text, encoding="utf-8")
        staging.replace(plan_path)
    code = 0
    if runs and runs[0]["state"] == "done":  # a second demo in the same folder shows the first one's results
        print(f"demo: already measured in {catalogue} (run {runs[0]['id']}, {plural(runs[0]['psfs'], 'PSF')}); "
              f"delete {catalogue} to measure again")
    else:
        resume = bool(runs) and runs[0]["state"] in ("paused", "running")
        print(f"demo: {plural(len(plan.steps()), 'step')} on the simulated rig into {catalogue}"
              + (f" (resuming run {runs[0]['id']})" if resume else ""))
        result = execute(plan, catalogue, frames_dir_for(catalogue), resume=resume, runner_options=options,
                         new=not resume)
        code = _report(result, _again(args, "demo", "--workdir", str(workdir)))
    _demo_outputs(catalogue, workdir)
    return code


def _demo_outputs(catalogue: Path, workdir: Path) -> None:
    """The query tables (centre and corner of the field) and the report figure, drawn by `psfd.cli.query`."""
    import cv2

    from psfd.catalogue import Catalogue
    from psfd.cli import query

    with Catalogue(catalogue, create=False) as cat:
        for name, near in (("centre", (0.5, 0.5)), ("corner", (0.0, 0.0))):
            print(f"\n$ psfd query --catalogue {catalogue} --channel g1 --near {near[0]:g},{near[1]:g}   # {name}")
            print(query.format_table(cat.query(channel="g1", near=near).rows))
        image = query.draw_report(cat, cat.query().rows, "g1")
    report = workdir / "report.png"
    staging = workdir / ".report.partial.png"
    if not cv2.imwrite(str(staging), image):
        raise BadInputError(f"could not write {report}")
    staging.replace(report)
    print(f"\nreport figure: {report}  (all PSFs: psfd query --catalogue {catalogue})")
