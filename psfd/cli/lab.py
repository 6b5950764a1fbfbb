"""Lab commands: capture, run, status, pause, resume, cancel, plan check, serve, demo.

Thin: parse, call the daemon, print. A command that drives the rig goes
through the service when its control socket answers (the service owns the
rig), and runs the plan in this process otherwise (`psfd.daemon.runner.run_plan`).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
from pathlib import Path

from psfd.cli import options, summary
from psfd.daemon import client
from psfd.errors import BadInputError, Interrupted, ServiceError, path_reason
from psfd.vocabulary import BERNOULLI, CAPTURE_KINDS, CHANNELS, DEFAULT_S, DEFAULT_SOLVER, TWO_PHOTO


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "capture", help=summary("capture"),
        description="Shoot one frame of the Bernoulli noise target (or a near/far pair of a textured plane) "
                    "at one aperture and rail position, estimate its PSFs and add them to the catalogue.")
    p.add_argument("--aperture", required=True, help="f-number, e.g. 5.6")
    p.add_argument("--rail", action="append", default=[], metavar="AXIS=MM",
                   help="rail position, e.g. X=1200 or X=1200,Y=-40 (repeatable); "
                        "default with --simulate: X at the simulated rig's working distance")
    p.add_argument("--target", default=BERNOULLI, metavar="|".join(CAPTURE_KINDS),
                   help=f"{BERNOULLI}: one frame of the noise target (default); {TWO_PHOTO} (once pair): near "
                        "and far frames of a textured plane")
    p.add_argument("--near", help=f"{TWO_PHOTO}: near distance in mm (default with --simulate: 587.5)")
    p.add_argument("--far", help=f"{TWO_PHOTO}: far distance in mm (default with --simulate: 2200)")
    p.add_argument("--channels", default="all", help=f"all (the default), or a comma list of {','.join(CHANNELS)}")
    p.add_argument("--out", metavar="DIR", help="store the RAW frames here (default: beside the catalogue)")
    options.add_rig_options(p)
    _service_options(p)
    p.set_defaults(func=run_capture)

    p = subparsers.add_parser("run", help=summary("run"))
    p.add_argument("plan", metavar="PLAN", help="the plan file (TOML; `psfd plan init` writes one)")
    how = p.add_mutually_exclusive_group()
    how.add_argument("--resume", action="store_true", help="continue the unfinished run of this plan")
    how.add_argument("--new", action="store_true",
                     help="start a fresh run even though this plan has an unfinished one")
    p.add_argument("--local", action="store_true", help="run in this process even when the service is up")
    _service_options(p)
    p.set_defaults(func=run_plan_file)

    p = subparsers.add_parser("status", help=summary("status"))
    p.add_argument("--json", action="store_true", help="print the status as JSON")
    options.add_service_options(p)
    p.set_defaults(func=run_status)

    for word in CONTROLS:
        p = subparsers.add_parser(word, help=summary(word), description=f"{summary(word).capitalize()}.")
        options.add_socket_option(p)
        if word == "cancel":
            p.add_argument("--queued", action="store_true",
                           help="drop the plans queued and not started instead (the run in progress goes on)")
        p.set_defaults(func=run_control, request=word, queued=False)

    p = subparsers.add_parser("plan", help=summary("plan"))
    sub = p.add_subparsers(dest="plan_command", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("check", help="list every problem of a plan, one per line")
    c.add_argument("plan", metavar="PLAN")
    c.set_defaults(func=run_plan_check)
    c = sub.add_parser("init", help="write a plan with every key, commented (edit it, then plan check and run)")
    c.add_argument("plan", metavar="PLAN", help="file to write, e.g. plan.toml")
    c.add_argument("--simulate", action="store_true", help="a small plan for the simulated rig, ready to run")
    c.add_argument("--force", action="store_true", help="replace PLAN if it exists")
    c.set_defaults(func=run_plan_init)

    p = subparsers.add_parser("serve", help=summary("serve"))
    _service_options(p)
    p.set_defaults(func=run_serve)

    p = subparsers.add_parser("demo", help=summary("demo"))
    p.add_argument("--workdir", default="psfd-demo", metavar="DIR", help="working folder (default ./psfd-demo)")
    options.add_runner_options(p)
    options.add_catalogue_option(p, default="DIR/catalogue.sqlite")
    p.set_defaults(func=run_demo)


def _service_options(p: argparse.ArgumentParser) -> None:
    options.add_service_options(p)
    options.add_runner_options(p)


# -- running a plan here -------------------------------------------------------------------------


def unstarted_note(resume: bool, again: str | None = None) -> str:
    """What a Ctrl-C or SIGTERM before the run was journalled left: nothing stored, or the run to resume as it
    was (``again``: the command line that continues it)."""
    if not resume:
        return "before the run started: nothing was stored"
    return "before the run went on: it is as it was" + (f"; continue with: {again}" if again else "")


@contextlib.contextmanager
def unstarted(note: str):
    """A Ctrl-C or SIGTERM raised inside (`psfd.cli.Terminated`), before the run is journalled, ends the
    command with ``note`` after its one line (``psfd: terminated (NOTE)``), exit 130 or 143."""
    try:
        yield
    except KeyboardInterrupt as exc:
        exc.add_note(note)
        raise


def run_here(plan, catalogue: Path, frames: Path, quiet: int = 0, again: str | None = None, **flags):
    """`run_plan` in this process; the first Ctrl-C, SIGTERM or hang-up (SIGHUP: the terminal or ssh session
    is gone, and so is the output) pauses after the current frame. ``quiet`` (`psfd -q`): no progress lines.

    A Ctrl-C or SIGTERM before the run is journalled (the run's modules loading, the rig opening) ends the
    command with nothing journalled and nothing created once the rig answered, and says so
    (`unstarted_note`; ``again``: the command line that resumes a run); from the moment the run is journalled
    it pauses the run, and ``again`` is the hint of `_report`.
    """
    note = unstarted_note(bool(flags.get("resume")), again)
    stopped: list[int] = []

    def stop(signum, frame):  # first Ctrl-C, SIGTERM or hang-up: finish the current frame and pause
        signal.signal(signum, previous[signum])  # the second one stops the command where it is
        if signum == signal.SIGHUP:
            leave_terminal()
        print("\npsfd: stopping after the current frame (again to abort)", file=sys.stderr)
        stopped.append(signum)
        control.request("pause")

    if quiet:
        flags["progress"] = None
    with unstarted(note):  # main's SIGTERM handler and Python's SIGINT one, until ours
        from psfd.cli import Terminated
        from psfd.daemon.runner import Control, StoppedBeforeStart, leave_terminal, run_plan

        control = Control()
        # a hang-up only where it would end the process: `nohup psfd run` asked to go on without a terminal
        hang_up = (signal.SIGHUP,) if signal.getsignal(signal.SIGHUP) == signal.SIG_DFL else ()
        previous = {sig: signal.signal(sig, stop) for sig in (signal.SIGINT, signal.SIGTERM, *hang_up)}
    try:
        result = run_plan(plan, catalogue, frames, control=control, stop_before_journal=True, **flags)
    except StoppedBeforeStart:  # the first stop came before the run was journalled: end as main ends a stop
        stop_exc = KeyboardInterrupt() if stopped[0] == signal.SIGINT else Terminated()
        stop_exc.add_note(note)
        raise stop_exc from None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if stopped and result.error is None and result.state != "done":  # stopped by the user: exit 130 or 143
        result.reason = f"interrupted by {signal.Signals(stopped[0]).name}"
        result.error = Interrupted(result.reason, stopped[0])
    return result


def plural(n: int, word: str) -> str:
    """``1 step``, ``2 steps``."""
    return f"{n} {word}{'s' * (n != 1)}"


def _report(r: dict, resume_hint: str | None) -> int:
    """Print how a run ended (`RunResult.to_dict`); the exit code of the error that stopped it, else 0.

    ``resume_hint`` is the command line that continues a paused run (None: a one-shot run).
    """
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


def writable_folder(path: Path, option: str, create: bool = True) -> Path:
    """Create ``path`` as a folder (parents too) or say in one line why it cannot be one.

    With ``create`` false a missing ``path`` is only checked: a command the rig may still refuse makes it
    later, so that a refusal leaves no empty folder behind.
    """
    if path.exists() and not path.is_dir():
        raise BadInputError(f"{option} {path}: exists and is not a folder")
    if not create and not path.exists():
        parent = next(p for p in path.absolute().parents if p.exists())  # the one it would be made in
        if not parent.is_dir():
            raise BadInputError(f"{option} {path}: cannot create the folder ({parent} is a file, not a folder)")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise BadInputError(f"{option} {path}: cannot create the folder ({parent} is not writable)")
        return path
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BadInputError(f"{option} {path}: cannot create the folder ({path_reason(path, exc)})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise BadInputError(f"{option} {path}: not a writable folder")
    return path


# -- run and capture -----------------------------------------------------------------------------


def run_plan_file(args: argparse.Namespace) -> int:
    again = _again(args, "run", args.plan, "--resume")
    with unstarted(unstarted_note(args.resume, again)):  # nothing is written before run_here journals the run
        from psfd.daemon import plan as plans

        catalogue, frames, sock = options.paths(args)
        plan = plans.load_plan(args.plan)
        served = not args.local and client.service_up(sock)
        runner = None if served else options.runner_options(args)  # the service runs with its own
    if served:
        check_service_paths(args, sock, "or add --local to run in this process")
        answer = client.submit(sock, plan.text, str(Path(args.plan).resolve()), resume=args.resume, new=args.new)
        follow = "psfd status" + (f" --socket {args.socket}" if args.socket else "")
        print(f"submitted {args.plan} to the service at {sock} ({answer['queued']} queued); "
              f"follow it with: {follow}")
        return 0
    result = run_here(plan, catalogue, frames, args.quiet, again, resume=args.resume, new=args.new, **runner)
    return _report(result.to_dict(), again)


def check_service_paths(args: argparse.Namespace, sock: Path, otherwise: str) -> dict:
    """Refuse a --catalogue or --frames other than the service's own: a run through the service stores there
    only, and the user would look for the PSFs in the other place. Returns the service's status answer."""
    answer = client.request(sock, {"cmd": "status"})
    for option, given, key in (("--catalogue", args.catalogue, "catalogue"), ("--frames", args.frames, "frames")):
        theirs = answer.get(key)
        if given and theirs and os.path.abspath(given) != theirs:
            raise BadInputError(f"{option} {given}: the service at {sock} stores into {theirs}; leave {option} out, "
                                f"{otherwise}")
    return answer


def capture_plan(args: argparse.Namespace) -> str:
    """The one-step plan text of a `psfd capture` command line (its options checked here, named as options)."""
    from psfd.daemon import plan as plans

    kind = plans.kind_name(args.target)
    if kind not in CAPTURE_KINDS:
        raise BadInputError(f"--target: use {' or '.join(CAPTURE_KINDS)}, got {args.target!r}")
    rail = options.parse_axes(args.rail, "--rail") if args.rail else {}
    aperture = options.parse_fnumber(args.aperture)
    channels = options.parse_channels(args.channels)
    rig = options.rig_config(args)
    target: dict = {"kind": kind}
    capture: dict = {"apertures": [aperture]}
    if kind == BERNOULLI:
        if args.near is not None or args.far is not None:
            raise BadInputError(f"--near and --far apply to --target {TWO_PHOTO}; give the distance as --rail X=MM")
        capture["x"] = [rail["x"] if "x" in rail else _default_distance(args)]
    else:
        if "x" in rail:
            raise BadInputError("--rail X does not apply to a pair: give --near MM and --far MM")
        target["near"], target["far"] = _pair_distances(args)
        if args.simulate:
            rig["scene"] = "texture"
    capture.update({axis: [rail[axis]] for axis in ("y", "z") if axis in rail})
    capture["channels"] = channels
    return plans.plan_text({"rig": rig, "target": target, "capture": capture})


def _default_distance(args: argparse.Namespace) -> float:
    if not args.simulate:
        raise BadInputError("--rail X=MM is needed: the distance of the target on the rail")
    from psfd.drivers import sim

    return float(sim.SimRig().distance_for_scale())


def _pair_distances(args: argparse.Namespace) -> tuple[float, float]:
    if args.near is None or args.far is None:
        if not args.simulate:
            raise BadInputError("--near MM and --far MM are needed for a pair")
        from psfd.drivers import sim

        near, far = sim.SimRig(scene="texture").pair_distances()
    near = options.parse_float(args.near, "--near") if args.near is not None else near
    far = options.parse_float(args.far, "--far") if args.far is not None else far
    return near, far


def run_capture(args: argparse.Namespace) -> int:
    from psfd.cli import output
    from psfd.daemon import plan as plans

    catalogue, frames, sock = options.paths(args)
    if args.out:
        frames = Path(args.out)
    text = capture_plan(args)
    problems = plans.check_text(text)  # what is left after capture_plan: positions off the rail, lambda <= s
    if problems:
        option = "--near/--far" if plans.kind_name(args.target) == TWO_PHOTO else "--rail"
        raise BadInputError(f"{option}: {problems[0].removeprefix('[target] ')}")
    plan = plans.parse_plan(text, "capture")
    runner = options.runner_options(args)
    if client.service_up(sock):
        if args.out:
            raise BadInputError("--out cannot be used through the service (it writes to its own frame store)")
        catalogue = Path(check_service_paths(args, sock, "or stop the service").get("catalogue") or catalogue)
        result = client.submit(sock, text, "capture", new=True, wait=True, oneshot=True)["result"]
    else:
        if args.out:
            writable_folder(frames, "--out", create=False)  # made by the run, once the rig has answered
        result = run_here(plan, catalogue, frames, args.quiet, new=True, oneshot=True, rows=True, **runner).to_dict()
    code = _report(result, None)
    if result.get("rows"):
        rows = _with_units(catalogue, result["rows"])
        print(output.format_rows(rows))
        print(output.units_line(rows))
    return code


def _with_units(catalogue: Path, rows: list[dict]) -> list[dict]:
    """The stored rows with MTF50 in lp/mm where the frames or the plan tell the pitch, as `psfd query` shows
    the same PSFs (`psfd.cli.query.with_units`); as they are when the catalogue cannot be read here."""
    from psfd.catalogue import Catalogue
    from psfd.cli.query import with_units
    from psfd.errors import PsfdError

    try:
        with Catalogue(catalogue, readonly=True) as cat:
            return with_units(cat, rows)
    except (PsfdError, OSError):  # a service's catalogue this user may not read: the rows without lp/mm
        return rows


# -- status, plan check, serve -------------------------------------------------------------------


STATUS_KEYS = ("service", "catalogue", "runs")  # `psfd status --json`, with or without the service (docs/formats.md)
SERVICE_KEYS = ("socket", "state", "queued", "held", "held_by", "current", "last", "paused_plan", "unfinished")


def status(args: argparse.Namespace) -> dict:
    """What `psfd status` shows, in one shape whether or not the service runs (`STATUS_KEYS`):
    ``service`` (None when no service answers, else `SERVICE_KEYS`), the ``catalogue`` whose latest runs
    are listed (the service's own when it says which) and those ``runs`` (newest first, at most 10)."""
    from psfd.catalogue import Catalogue, catalogue_exists
    from psfd.daemon.store import frames_dir_for, shown_state
    from psfd.errors import CatalogueError

    catalogue, frames, sock = options.paths(args)
    service = None
    if client.service_up(sock):
        answer = client.request(sock, {"cmd": "status"})
        service = {"socket": str(sock), **{key: answer.get(key) for key in SERVICE_KEYS[1:]}}
        if answer.get("catalogue") and not args.catalogue:
            catalogue = Path(answer["catalogue"])
            frames = frames_dir_for(catalogue)
    runs: list[dict] = []
    exists = catalogue_exists(catalogue)  # not an empty file a run killed while creating it left
    if exists:
        try:
            with Catalogue(catalogue, readonly=True) as cat:
                runs = [cat.run_summary(r["id"]) for r in cat.runs()[:10]]
        except CatalogueError:
            if service is None:
                raise
    for run in runs:  # a run its process no longer holds was killed: say so, it is resumable
        run["state"] = shown_state(run["state"], frames, catalogue)
    return {"service": service, "catalogue": str(catalogue) if exists else None, "runs": runs}


def run_status(args: argparse.Namespace) -> int:
    info = status(args)
    if args.json:
        print(json.dumps(info))
        return 0
    service = info["service"]
    if service is not None:
        by = "the service's restart" if service["held_by"] == "restart" else "a pause"
        held = f", held by {by} until `resume`" if service["held"] else ""
        print(f"service at {service['socket']}: {service['state']}, {service['queued']} queued{held}")
        if service["current"]:
            c = service["current"]
            print(f"  running {c['plan']}: {c['done']}/{c['total']} steps, at {c['step']}")
        if service["last"]:
            last = service["last"]
            print(f"  last: {last['plan']} run {last.get('run_id', '-')} {last['state']}"
                  + (f" ({last['reason']})" if last.get("reason") else ""))
        for run in service["unfinished"] or []:  # paused and interrupted runs: what --resume continues
            print(f"  run {run['id']} of {run['plan_path']} is {run['state']} ({run['done']}/{run['total']} steps "
                  f"done); continue with: {_again(args, 'run', run['plan_path'], '--resume')}")
        return 0
    catalogue, _, sock = options.paths(args)
    if info["catalogue"] is None:
        print(f"no service at {sock}; no catalogue at {catalogue}")
        return 0
    print(f"no service at {sock}; latest runs in {info['catalogue']}:")
    print(f"{'run':>5} {'state':<11} {'done':>9} {'failed':>6} {'psfs':>6}  plan")
    for s in info["runs"]:
        print(f"{s['id']:>5} {s['state']:<11} {s['done']:>4}/{s['total']:<4} {s['failed']:>6} {s['psfs']:>6}  "
              f"{s['plan_path']}")
    _print_kept(Path(info["catalogue"]))
    return 0


def _print_kept(catalogue: Path) -> None:
    """The plans a stopped service kept for ``catalogue`` (`store.kept_queue`), which the next one queues again."""
    from psfd.daemon.store import kept_queue, queue_path

    try:
        kept = kept_queue(catalogue)
    except (OSError, ValueError) as exc:
        print(f"the service's kept queue {queue_path(catalogue)} cannot be read ({exc})")
        return
    if kept:
        print(f"{len(kept)} plans queued when the service ended ({', '.join(str(e.get('path')) for e in kept)}): "
              "`psfd serve` queues them again, held until `psfd resume`")


# the service's control requests a command sends as they are, and what does it when no service is up
CONTROLS = {
    "pause": "a run in a terminal pauses after its current frame with Ctrl-C",
    "resume": "continue a paused run with `psfd run PLAN --resume`",
    "cancel": "a run in a terminal stops after its current frame with Ctrl-C (then start it afresh with --new)",
}


def run_control(args: argparse.Namespace) -> int:
    """`psfd pause`, `resume`, `cancel`: the request of that name to the service (`psfd.daemon.service`)."""
    sock = options.socket_path(args)
    if not client.service_up(sock):
        raise ServiceError(f"no service at {sock}: {CONTROLS[args.request]}")
    answer = client.request(sock, {"cmd": args.request, **({"queued": True} if args.queued else {})})
    if "dropped" in answer:
        print(f"dropped {len(answer['dropped'])} queued plans: {', '.join(answer['dropped'])}")
    elif args.request == "pause":
        print(f"pause asked: the service at {sock} pauses its run after the current frame and holds its queue; "
              "continue with: psfd resume" + (f" --socket {args.socket}" if args.socket else ""))
    elif "progress" in answer:  # a cancel with no run in progress: the paused run was closed
        print(f"cancelled run {answer['run_id']} of {answer['plan']} ({answer['progress']})"
              + ("; the held queue goes on" if answer["held"] else ""))
    elif args.request == "cancel":
        print(f"cancel asked: the service at {sock} closes its run as cancelled after the current frame")
    elif "run_id" in answer:
        print(f"resuming run {answer['run_id']} of {answer['plan']} ({answer['queued']} queued)")
    if answer.get("note"):
        print(answer["note"])
    return 0


def run_plan_check(args: argparse.Namespace) -> int:
    from psfd.daemon import plan as plans

    path = Path(args.plan)
    text = plans.read_plan_text(path)
    problems = plans.check_text(text)
    for problem in problems:
        print(f"{path}: {problem}", file=sys.stderr)
    if problems:
        raise BadInputError(f"{path}: {len(problems)} problem{'s' * (len(problems) > 1)} found")
    plan = plans.parse_plan(text, str(path))
    problems, rail = _ask_rail(plan)
    for problem in problems:
        print(f"{path}: {problem}", file=sys.stderr)
    if problems:
        raise BadInputError(f"{path}: {len(problems)} problem{'s' * (len(problems) > 1)} found on the rig")
    steps = len(plan.steps())
    nx, ny = plan.estimator_options().get("grid", (1, 1))
    print(f"{path}: ok, {plural(steps, 'step')}, {plural(steps * (2 if plan.kind == TWO_PHOTO else 1), 'frame')}, "
          f"{plural(steps * len(plan.channels) * nx * ny, 'PSF')}" + (f"; {rail}" if rail else ""))
    return 0


def run_plan_init(args: argparse.Namespace) -> int:
    from psfd.cli import output
    from psfd.daemon import plan as plans

    path = Path(args.plan)
    if path.exists() and not args.force:
        raise BadInputError(f"{path}: exists; choose another name or add --force to replace it")
    if path.is_dir():
        raise BadInputError(f"{path}: is a folder")
    text = plans.plan_template(simulate=args.simulate)
    output.write_file(path, lambda staging: staging.write_text(text, encoding="utf-8"))
    print(f"wrote {path}: check it with `psfd plan check {path}`, run it with `psfd run {path}`")
    return 0


def _ask_rail(plan) -> tuple[list[str], str | None]:
    """The plan against the axes and travel its rail (the controller, or the recording) reports.

    Returns the problems and what was asked; a rail that cannot be asked now (unplugged, in use by a
    run) is noted on stderr and the plan is judged on its own limits, but a recording that cannot be read
    (a mistyped folder) is a problem, as `psfd run` refuses it. The simulated rig is the one the plan
    describes (its rail_limits name its axes); its camera's apertures and settings are asked as `psfd run`
    asks them (`runner.camera_problems`), so that a plan check passes only what the run accepts; a recording's
    captures are held to the plan's (`plan.recording_problems`), as `psfd run` holds them.
    """
    from psfd.daemon.plan import check_rail, recording_problems
    from psfd.drivers import open_camera, open_rail
    from psfd.errors import PsfdError

    problems: list[str] = []
    if plan.rig.get("simulate") is True:
        from psfd.daemon.runner import camera_problems

        problems = camera_problems(plan, open_camera(plan.rig_config()))
    try:
        rail = open_rail(plan.rig_config())
    except PsfdError as exc:
        if plan.rig.get("recording") is not None:  # a folder on disk, not a device unplugged for now: run refuses it
            return [f"[rig] recording: {exc}"], None
        print(f"psfd: note: rail not asked for its travel ({exc})", file=sys.stderr)
        return problems, None
    problems += recording_problems(plan)
    try:
        info = rail.info()
    except PsfdError as exc:  # an older recording that never asked: each move is checked when it is replayed
        print(f"psfd: note: rail not asked for its travel ({exc})", file=sys.stderr)
        return problems, None
    finally:
        rail.close()
    travel = ", ".join(f"{axis.upper()} [{lo:g}, {hi:g}]" for axis, (lo, hi) in info.travel.items())
    return problems + check_rail(plan, info), f"rail {info.controller}: {travel}"


def run_serve(args: argparse.Namespace) -> int:
    from psfd.daemon import service

    catalogue, frames, sock = options.paths(args)
    return service.Service(catalogue, frames, sock, runner_options=options.runner_options(args)).serve()


# -- demo ----------------------------------------------------------------------------------------


def demo_plan() -> str:
    """A complete plan on the simulated rig: 3 apertures x a 3x3 field grid x 4 channels."""
    from psfd.daemon import plan as plans
    from psfd.drivers import sim

    rig = sim.SimRig()
    distance = float(rig.distance_for_scale())
    y, z = rig.field_offsets(3)
    return (
        "# psfd demo: the simulated rig walks the target over a 3x3 field grid at three apertures\n"
        "[rig]\nsimulate = true\n\n"
        f'[target]\nkind = "{BERNOULLI}"\n\n'
        f"[capture]\napertures = [4, 8, 16]\nx = [{plans.fmt(distance)}]\n"
        f"y = {json.dumps([float(v) for v in y])}\nz = {json.dumps([float(v) for v in z])}\n"
        'channels = "all"\nrepeats = 1\n\n'
        f'[estimator]\ns = {DEFAULT_S[BERNOULLI]}\nsolver = "{DEFAULT_SOLVER}"\n'
    )


def run_demo(args: argparse.Namespace) -> int:
    import contextlib

    from psfd.catalogue import Catalogue
    from psfd.daemon import plan as plans
    from psfd.daemon.store import frames_dir_for

    runner = options.runner_options(args)  # every option is checked before anything is written or printed
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
            runs, unfinished = cat.plan_runs(text, key=plans.plan_key), cat.unfinished_run(text, plans.plan_key)
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
        resume = unfinished is not None
        print(f"demo: {plural(len(plan.steps()), 'step')} on the simulated rig into {catalogue}"
              + (f" (resuming run {unfinished})" if resume else ""))
        again = _again(args, "demo", "--workdir", str(workdir))
        result = run_here(plan, catalogue, frames_dir_for(catalogue), args.quiet, again, resume=resume,
                          new=not resume, **runner)
        code = _report(result.to_dict(), again)
    _demo_outputs(catalogue, workdir)
    return code


def _demo_outputs(catalogue: Path, workdir: Path) -> None:
    """The query tables (centre and corner of the field) and the report figure, as `psfd query` and `psfd report`
    print and draw them, with the note `psfd query` gives (the corner lies outside the measured windows)."""
    from psfd.catalogue import Catalogue
    from psfd.cli import output
    from psfd.cli.query import with_units

    with Catalogue(catalogue, readonly=True) as cat:
        for name, near in (("centre", (0.5, 0.5)), ("corner", (0.0, 0.0))):
            print(f"\n$ psfd query --catalogue {catalogue} --channel g1 --near {near[0]:g},{near[1]:g}   # {name}")
            result = cat.query(channel="g1", near=near)
            if result.note:
                sys.stdout.flush()  # the note after its command line, as the command prints it
                print(f"psfd: note: {result.note}", file=sys.stderr)
            rows = with_units(cat, result.rows)
            print(output.format_rows(rows))
        print(output.units_line(rows))
        report = workdir / "report.png"
        output.write_report(cat, cat.query().rows, "g1", report)
    print(f"\nreport figure: {report}  (all PSFs: psfd query --catalogue {catalogue})")
