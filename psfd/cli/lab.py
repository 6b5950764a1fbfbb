"""Lab commands: capture, run, status, plan check, serve, demo.

Thin: parse, call the daemon, print. A command that drives the rig goes
through the service when its control socket answers (the service owns the
rig), and runs in this process otherwise.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path

from psfd.daemon import plan as plans
from psfd.daemon import service
from psfd.daemon.runner import Control, Runner, RunResult, frames_dir_for
from psfd.errors import BadInputError, ServiceError
from psfd.estimator.raw import CHANNELS


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("capture", help="shoot and estimate one target frame or near/far pair now")
    p.add_argument("--aperture", required=True, help="f-number, e.g. 5.6")
    p.add_argument("--rail", action="append", default=[], metavar="AXIS=MM",
                   help="rail position, e.g. X=1200 or X=1200,Y=-40 (repeatable)")
    p.add_argument("--target", choices=plans.KINDS, default="bernoulli")
    p.add_argument("--near", help="pair: near distance in mm")
    p.add_argument("--far", help="pair: far distance in mm")
    p.add_argument("--channels", default="all", help=f"all, or a comma list of {','.join(CHANNELS)}")
    p.add_argument("--out", metavar="DIR", help="store the RAW frames here (default: beside the catalogue)")
    _rig_options(p)
    _common(p)
    p.set_defaults(func=run_capture)

    p = subparsers.add_parser("run", help="run a measurement plan (TOML) on the rig")
    p.add_argument("plan", metavar="PLAN")
    p.add_argument("--resume", action="store_true", help="continue the unfinished run of this plan")
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
    _common(c)
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
            runner_options: dict[str, int] | None = None) -> RunResult:
    """Run a plan in this process on the rig its [rig] table names."""
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
            return runner.run(plan, camera, rail, resume=resume)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _report(result: RunResult | dict, plan_path: str | None) -> int:
    """Print how a run ended; the exit code of the error that paused it, else 0."""
    r = result if isinstance(result, dict) else service.result_dict(result)
    if r.get("run_id") is None:  # the service could not start the job (camera not found, ...)
        print(f"psfd: error: {r.get('reason')}", file=sys.stderr)
        return int(r.get("exit_code", ServiceError.exit_code))
    print(f"run {r['run_id']} {r['state']}: {r['steps_done']} steps, {r['frames']} frames, "
          f"{r['psfs']} PSFs in {r['elapsed_s']:.1f} s")
    if r["state"] == "paused":
        hint = f"; continue with: psfd run {plan_path} --resume" if plan_path else ""
        print(f"run {r['run_id']} paused ({r['reason']}){hint}", file=sys.stderr)
        return int(r["exit_code"])
    return 0


def run_plan(args: argparse.Namespace) -> int:
    catalogue, frames, sock = _paths(args)
    plan = plans.load_plan(args.plan)
    if not args.local and service.service_up(sock):
        answer = service.request(sock, {"cmd": "submit", "plan": plan.text, "path": str(Path(args.plan).resolve()),
                                        "resume": args.resume})
        print(f"submitted {args.plan} to the service at {sock} ({answer['queued']} queued); "
              "follow it with: psfd status")
        return 0
    return _report(execute(plan, catalogue, frames, args.resume, _runner(args)), args.plan)


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
    """The one-step plan text of a `psfd capture` command line."""
    rail = parse_rail(args.rail)
    try:
        aperture = float(str(args.aperture).lower().removeprefix("f/"))
    except ValueError:
        raise BadInputError(f"--aperture: expected an f-number such as 5.6, got {args.aperture!r}") from None
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
    channels = "all" if args.channels == "all" else [c.strip() for c in args.channels.split(",")]
    lines.append(f"channels = {json.dumps(channels)}")
    return "\n".join(lines) + "\n"


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
    plan = plans.parse_plan(text, "capture")
    if service.service_up(sock):
        if args.out:
            raise BadInputError("--out cannot be used through the service (it writes to its own frame store)")
        answer = service.request(sock, {"cmd": "submit", "plan": text, "path": "capture", "wait": True},
                                 timeout=None)
        result = answer["result"]
    else:
        run = execute(plan, catalogue, frames, runner_options=_runner(args))
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
    if args.json:
        print(json.dumps({"service": None, "runs": summaries}))
        return 0
    print(f"no service at {sock}; latest runs in {catalogue}:")
    print(f"{'run':>5} {'state':<10} {'done':>9} {'failed':>6} {'psfs':>6}  plan")
    for s in summaries:
        print(f"{s['id']:>5} {s['state']:<10} {s['done']:>4}/{s['total']:<4} {s['failed']:>6} {s['psfs']:>6}  "
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
    print(f"{path}: ok, {steps} steps, {steps * (2 if plan.kind == 'pair' else 1)} frames, "
          f"{steps * len(plan.channels) * nx * ny} PSFs")
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
        '[estimator]\ns = 4\nsolver = "ls-threshold"\n'
    )


def run_demo(args: argparse.Namespace) -> int:
    workdir = Path(args.workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    plan_path = workdir / "demo.toml"
    if not plan_path.exists():
        plan_path.write_text(demo_plan(), encoding="utf-8")
    catalogue = Path(args.catalogue) if args.catalogue else workdir / "catalogue.sqlite"
    plan = plans.load_plan(plan_path)
    print(f"demo: {len(plan.steps())} steps on the simulated rig into {catalogue}")
    result = execute(plan, catalogue, frames_dir_for(catalogue), resume=True, runner_options=_runner(args))
    code = _report(result, str(plan_path))
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
