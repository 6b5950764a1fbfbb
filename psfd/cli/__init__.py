"""`psfd` command line: parse, call, print.

Each command group lives in its own module with a ``register(subparsers)``
function; this module only assembles them and turns typed errors into a
one-line message and an exit code. Building the parser imports the command
modules and `psfd.cli.options` only, which load nothing heavier than the
standard library: every handler imports the numerics, drivers, catalogue or
daemon it needs when it runs.

Start-up is part of every command a user times: `main` registers only the
module of the command word it was given (`COMMANDS`); the top-level help,
``--version`` and a word it does not know list the command words only.
"""

from __future__ import annotations

import argparse
import atexit
import gc
import os
import select
import signal
import sys
import threading

# The estimators solve many small systems (a few hundred unknowns): BLAS threads
# gain nothing there and, on a loaded 2-core machine, stall them for up to a
# second. Must be set before numpy loads OpenBLAS; a user's own setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
# OpenCV logs its own warnings on stderr (e.g. for an unreadable image) before psfd
# reports the error in one line; must be set before cv2 is imported.
os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
# OpenCV's own check of an image's size before it allocates, for the formats whose header psfd
# does not read itself (psfd.estimator.raw.check_image reads PNG, PNM and TIFF headers).
from psfd.vocabulary import MAX_PIXELS  # noqa: E402 - standard library only

os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(MAX_PIXELS))

import importlib  # noqa: E402

from psfd import __version__  # noqa: E402 - after the environment above
from psfd.cli import logs  # noqa: E402
from psfd.errors import BadInputError, PsfdError, path_reason  # noqa: E402

# Command word -> the module of psfd.cli whose register() adds it, and the word's line in `psfd --help`, in the
# help's order. The lines live here so that the top-level help lists the commands without importing and building
# them (their modules and parsers: 50 ms of a 0.1 s start-up).
COMMANDS = {
    "target": ("target", "write the calibration target as a print-ready PDF or a PNG"),
    "estimate": ("estimate", "estimate PSFs from photographs on disk"),
    "compare": ("compare", "run every applicable method on the same photographs and compare their MTFs"),
    "camera": ("hardware", "camera information and settings"),
    "rail": ("hardware", "home, move or read the rail"),
    "record": ("hardware", "capture at rail positions and apertures, writing a replayable recording"),
    "query": ("query", "list catalogued PSFs (a table, or JSON lines with the arrays)"),
    "export": ("query", "write catalogued PSFs to a new folder, one file each plus index.json"),
    "report": ("query", "draw the field report: per aperture, every channel's PSFs over the sensor, the sagittal "
                        "and meridional MTF50 at each measured point, and MTF50 against image height"),
    "metadata": ("query", "write the Datasette metadata of the catalogue: every table and column described, "
                          "with units"),
    "capture": ("lab", "shoot and estimate one target frame or near/far pair now"),
    "run": ("lab", "run a measurement plan (TOML) on the rig"),
    "status": ("lab", "what the service is doing, or the latest runs in the catalogue"),
    "pause": ("lab", "pause the service's run after its current frame (resumable) and hold its queue"),
    "resume": ("lab", "continue the service's newest paused run, then its queue"),
    "cancel": ("lab", "stop the service's run after its current frame and close it as cancelled (or its paused run)"),
    "plan": ("lab", "work with measurement plans"),
    "serve": ("lab", "run the service: control socket, job queue, systemd notify"),
    "demo": ("lab", "a complete plan on the simulated rig, then the query table and report"),
}
COMMAND_MODULES = tuple(dict.fromkeys(module for module, _ in COMMANDS.values()))


def summary(word: str) -> str:
    """The line of command ``word`` in `psfd --help` (its sub-parser's ``help``)."""
    return COMMANDS[word][1]


def command_modules(argv: list[str] | None) -> tuple[str, ...]:
    """The command modules a command line needs: its command word's, all without ``argv``, else none
    (--version, the top-level help, no or an unknown command word: the commands are listed, not built)."""
    if argv is None:
        return COMMAND_MODULES
    word = next((a for a in argv if not a.startswith("-")), None)
    return (COMMANDS[word][0],) if word in COMMANDS else ()


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The ``psfd`` parser with the commands ``argv`` needs (`command_modules`; all without ``argv``)."""
    parser = argparse.ArgumentParser(prog="psfd", description="Sub-pixel camera PSF measurement.")
    parser.add_argument("--version", action="version", version=f"psfd {__version__}")
    logs.add_options(parser)
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    modules = command_modules(argv)
    for name in modules:
        importlib.import_module(f"psfd.cli.{name}").register(subparsers)
    if not modules:  # listed for the help and argparse's own messages; none of them runs
        for word, (_, line) in COMMANDS.items():
            subparsers.add_parser(word, help=line)
        return parser
    for command in _commands(parser):  # -v and -q after the command too: `psfd run plan.toml -v`
        logs.add_options(command, suppress=True)
    _describe(parser)
    return parser


def _describe(parser: argparse.ArgumentParser) -> None:
    """A command without a description of its own says in its --help what its line in the listing says."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for listed in action._choices_actions:
                sub = action.choices[listed.dest]
                sub.description = sub.description or listed.help
                _describe(sub)


def _commands(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    """Every parser below ``parser`` that runs a command (the leaves of the subcommand tree)."""
    found = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in dict.fromkeys(action.choices.values()):  # aliases share their parser
                found += _commands(sub) or [sub]
    return found


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where the process is, so that a moving rail is stopped and its port released."""


def _raise_terminated(signum: int, frame: object) -> None:
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    """Run one command line and return its exit code; without ``argv``, the process's own (the program).

    The exit code is the README's table (`psfd.errors`): 0 done, 1 nothing matched, 2 bad input, 3 the
    photographs cannot support an estimate, 4 camera or rail, 5 catalogue or service, 130 interrupted
    by Ctrl-C, 143 stopped by SIGTERM (outside `psfd serve`).

    The program's exit skips the garbage collector's last passes over everything numpy, scipy and
    OpenCV loaded (`gc.freeze` as the last exit handler: 0.1 s idle, up to 0.7 s on a loaded machine,
    for cycles the operating system frees anyway); the other exit handlers, flushing and closing run as usual.
    """
    if argv is None:
        atexit.register(gc.freeze)  # registered first, so it runs last
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    logs.setup(args.verbose, args.quiet, service=args.command == "serve")
    in_main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _raise_terminated) if in_main_thread else None
    try:
        code = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, while it can still be handled
        return code
    except BrokenPipeError:
        if not _stdout_closed():
            print("psfd: error: broken pipe", file=sys.stderr)
            return BadInputError.exit_code
        # The reader went away (`psfd query | head -1`): not an error. Point stdout at /dev/null so
        # that the interpreter's own flush at exit cannot fail again (Python docs, "Note on SIGPIPE").
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except PsfdError as exc:
        print(f"psfd: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except OSError as exc:
        # A file-system refusal the commands did not foresee (read-only disk, a file where a
        # folder should be, disk full): still the user's environment, still one line.
        where = f"{exc.filename}: " if exc.filename else ""
        reason = path_reason(exc.filename, exc) if exc.filename else (exc.strerror or str(exc))
        print(f"psfd: error: {where}{reason}", file=sys.stderr)
        return BadInputError.exit_code
    except KeyboardInterrupt as exc:
        stopped = "".join(f" ({note})" for note in getattr(exc, "__notes__", ()))
        print(f"psfd: {'terminated' if isinstance(exc, Terminated) else 'interrupted'}{stopped}", file=sys.stderr)
        return 128 + (signal.SIGTERM if isinstance(exc, Terminated) else signal.SIGINT)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _stdout_closed() -> bool:
    """True when standard output is a pipe or socket whose reader has gone (poll reports an error on it)."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (OSError, ValueError):
        return False


if __name__ == "__main__":
    sys.exit(main())
