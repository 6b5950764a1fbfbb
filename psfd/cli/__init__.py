"""`psfd` command line: parse, call, print.

Each command group lives in its own module with a ``register(subparsers)``
function; this module only assembles them and turns typed errors into a
one-line message and an exit code.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# The estimators solve many small systems (a few hundred unknowns): BLAS threads
# gain nothing there and, on a loaded 2-core machine, stall them for up to a
# second. Must be set before numpy loads OpenBLAS; a user's own setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from psfd import __version__
from psfd.errors import PsfdError

# Modules that add commands. A module listed here but not present yet is skipped.
COMMAND_MODULES = (
    "psfd.cli.target",
    "psfd.cli.estimate",
    "psfd.cli.compare",
    "psfd.cli.hardware",
    "psfd.cli.query",
    "psfd.cli.lab",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="psfd", description="Sub-pixel camera PSF measurement.")
    parser.add_argument("--version", action="version", version=f"psfd {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for name in COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue
            raise
        module.register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except PsfdError as exc:
        print(f"psfd: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("psfd: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
