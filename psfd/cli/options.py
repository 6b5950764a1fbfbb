"""Option values and the option groups several commands share.

Every number, f-number, rail position and size a user types is parsed here,
so that each command refuses it with the same one-line `BadInputError` (not
argparse's usage dump). Option groups (`add_rig_options`, `add_service_options`,
`add_runner_options`) give every command that drives the rig, or the
service, the same options with the same meaning.

Standard library only: the parser is built before any command runs, so this
module must not load numpy, OpenCV or the estimators.
"""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

from psfd import vocabulary
from psfd.errors import BadInputError
from psfd.vocabulary import AXES

CLI_NAMES = {"s": "-s", "support": "--support", "grid": "--grid"}  # how `vocabulary.check_sizes` names them here


# ---------------------------------------------------------------- values


def parse_int(text: str | int, name: str, minimum: int | None = None) -> int:
    """An integer option value, or a one-line BadInputError."""
    try:
        value = int(str(text).strip())
    except ValueError:
        raise BadInputError(f"{name}: expected an integer, got {text!r}") from None
    if minimum is not None and value < minimum:
        raise BadInputError(f"{name}: must be at least {minimum}, got {value}")
    return value


def parse_float(text: str | float, name: str) -> float:
    """A finite number option value, or a one-line BadInputError."""
    try:
        value = float(str(text).strip())
    except ValueError:
        raise BadInputError(f"{name}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise BadInputError(f"{name}: expected a finite number, got {text!r}")
    return value


def parse_fnumber(text: str, name: str = "--aperture") -> float:
    """A positive f-number (``5.6``, ``f/5.6``); bad input, never a camera fault."""
    value = vocabulary.parse_fnumber(text, name)
    if value is None:
        raise BadInputError(f"{name}: expected an f-number such as 5.6, got {text!r}")
    return value


def parse_fnumbers(values: list[str] | None, name: str = "--aperture") -> list[str]:
    """Repeated or comma-separated f-numbers, each checked, kept as typed (the camera's own spelling)."""
    words = [v.strip() for item in values or [] for v in item.split(",") if v.strip()]
    for word in words:
        parse_fnumber(word, name)
    return words


def parse_axes(words: list[str], name: str) -> dict[str, float]:
    """Rail positions ``["X=120", "Y=-5"]`` or ``["X=120,Y=-5"]`` -> ``{"x": 120.0, "y": -5.0}``."""
    axes: dict[str, float] = {}
    for word in (w.strip() for item in words for w in item.split(",") if w.strip()):
        label, sep, value = word.partition("=")
        axis = label.strip().lower()
        if not sep or axis not in AXES:
            raise BadInputError(f"{name}: expected AXIS=MM with AXIS one of X, Y, Z, got {word!r}")
        if axis in axes:
            raise BadInputError(f"{name}: axis {axis.upper()} given twice")
        try:
            axes[axis] = parse_float(value, name)
        except BadInputError:
            raise BadInputError(f"{name}: {axis.upper()} must be a number of mm; expected a number, "
                                f"got {value.strip()!r}") from None
    if not axes:
        raise BadInputError(f"{name}: give at least one AXIS=MM")
    return axes


def parse_limits(text: str, name: str = "--rail-limits") -> dict[str, list[float]]:
    """Rail travel ``X=0:500,Y=-50:50`` -> ``{"x": [0, 500], "y": [-50, 50]}``."""
    limits = {}
    for word in text.split(","):
        label, sep, span = word.strip().partition("=")
        lo, colon, hi = span.partition(":")
        axis = label.strip().lower()
        if not sep or not colon or axis not in AXES:
            raise BadInputError(f"{name}: expected AXIS=MIN:MAX, got {word.strip()!r}")
        bounds = [parse_float(lo, name), parse_float(hi, name)]
        if bounds[0] > bounds[1]:
            raise BadInputError(f"{name}: {axis.upper()} minimum is above its maximum")
        limits[axis] = bounds
    return limits


def parse_grid(text: str) -> tuple[int, int]:
    """``--grid NxM``: N windows across and M down (their bounds: `vocabulary.check_sizes`)."""
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", str(text))
    if not match:
        raise BadInputError(f"--grid: expected NxM, N windows across and M down (e.g. 3x2), got {text!r}")
    grid = int(match[1]), int(match[2])
    if not all(1 <= n <= vocabulary.GRID_MAX for n in grid):
        raise BadInputError(f"--grid: N and M from 1 to {vocabulary.GRID_MAX}, got {text.strip()}")
    return grid


def sizes(args: argparse.Namespace, method: str) -> dict:
    """``s``, ``support`` and ``grid`` of a command line, checked (`vocabulary.check_sizes`) before any work.

    An ``-s`` not given is the method's default (`vocabulary.DEFAULT_S`).
    """
    s = vocabulary.DEFAULT_S[method] if args.s is None else parse_int(args.s, "-s")
    support = None if args.support is None else parse_int(args.support, "--support")
    grid = parse_grid(args.grid) if getattr(args, "grid", None) is not None else (1, 1)
    s, support, grid = vocabulary.check_sizes(s, support, grid, CLI_NAMES)
    return {"s": s, "support": support, "grid": grid}


def parse_channel(text: str, name: str = "--channel", allowed: tuple[str, ...] = vocabulary.CHANNELS) -> str:
    """One channel among ``allowed``, in any case (``G1`` is ``g1``), as stored: lower case.

    The catalogue stores the names of `psfd.vocabulary.CHANNELS` and ``mono``, all lower case, and
    ``--camera`` ignores case: a channel typed as printed on a datasheet (``G1``) is the same channel.
    """
    channel = text.strip().lower()
    if channel not in allowed:
        raise BadInputError(f"{name}: unknown channel {text!r} (one of {', '.join(allowed)})")
    return channel


def parse_method(text: str, name: str = "--method") -> str:
    """A method's one name (`psfd.vocabulary.method_name`: an older alias too), in any case, as a filter
    ignores case: ``Bernoulli`` is ``bernoulli``, ``Two-Photo`` is ``two-photo``."""
    try:
        return vocabulary.method_name(text.strip().lower())
    except BadInputError:
        raise BadInputError(f"{name}: unknown method {text!r} (one of {', '.join(vocabulary.METHODS)})") from None


def parse_near(text: str, name: str = "--near") -> tuple[float, float]:
    """A normalised field location ``"0.8,0.1"`` -> (0.8, 0.1), both in [0, 1]."""
    try:
        x, y = (float(p) for p in text.split(","))
    except ValueError:
        raise BadInputError(f"{name} wants X,Y (two numbers in [0, 1]), got {text!r}") from None
    if not (0.0 <= x <= 1.0 and 0.0 <= y <= 1.0):
        raise BadInputError(f"{name} {text}: field coordinates are normalised to [0, 1]")
    return x, y


def parse_channels(text: str, name: str = "--channels") -> list[str] | str:
    """``all`` or a comma list of distinct Bayer channels, in any case (as `parse_channel`)."""
    if text.strip().lower() == "all":
        return "all"
    channels = [c.strip().lower() for c in text.split(",")]
    bad = [c for c in channels if c not in vocabulary.CHANNELS]
    if bad or len(set(channels)) != len(channels):
        raise BadInputError(f"{name}: expected all, or a comma list of distinct {', '.join(vocabulary.CHANNELS)}, "
                            f"got {text!r}")
    return channels


# ---------------------------------------------------------------- option groups


def add_size_options(p: argparse.ArgumentParser, method: str | None = None, grid: bool = True) -> None:
    """``-s``, ``--support`` and (``grid``) ``--grid``; ``method`` names the default s (None: each method's)."""
    default = (f"default {vocabulary.DEFAULT_S[method]}" if method
               else "default: each method's, " + ", ".join(f"{m} {s}" for m, s in vocabulary.DEFAULT_S.items()))
    p.add_argument("-s", help=f"super-resolution factor, 1 to {vocabulary.S_MAX} ({default})")
    p.add_argument("--support", help=f"odd kernel side on the s-times grid, 3 to {vocabulary.SUPPORT_MAX} "
                                     "(default 4s+1)")
    if grid:
        p.add_argument("--grid", default="1x1", help=f"NxM local windows, N across and M down, each 1 to "
                                                     f"{vocabulary.GRID_MAX} (default 1x1)")


def add_rig_options(p: argparse.ArgumentParser) -> None:
    """The options of every command that drives the rig (see `rig_config`)."""
    group = p.add_argument_group("rig")
    group.add_argument("--simulate", action="store_true", help="use the simulated rig")
    group.add_argument("--camera-port", help="gphoto2 port, e.g. usb:001,004 (default: the only camera)")
    group.add_argument("--rail-port", help="serial port of the rail, e.g. /dev/ttyUSB0")
    group.add_argument("--rail-limits", metavar="X=MIN:MAX[,Y=MIN:MAX]",
                       help="narrower soft limits in mm, and the rail's axes (default: X only, over the "
                            "controller's whole travel as it reports it; the simulated rig's own travel with "
                            "--simulate)")


def rig_config(args: argparse.Namespace) -> dict:
    """The rig description the rig options name: the ``[rig]`` table of a plan, `psfd.drivers.open_rig`'s argument."""
    config: dict = {"simulate": True} if args.simulate else {}
    if not args.simulate:
        config.update({key: getattr(args, key) for key in ("camera_port", "rail_port") if getattr(args, key)})
    if args.rail_limits:
        config["rail_limits"] = parse_limits(args.rail_limits)
    return config


def add_catalogue_option(p: argparse.ArgumentParser, default: str = "$XDG_DATA_HOME/psfd/catalogue.sqlite") -> None:
    p.add_argument("--catalogue", metavar="PATH", help=f"catalogue file (default {default})")


def add_service_options(p: argparse.ArgumentParser) -> None:
    """``--catalogue``, ``--socket`` and ``--frames``: where a command finds the service or works without it."""
    add_catalogue_option(p)
    add_socket_option(p)
    p.add_argument("--frames", metavar="DIR", help="frame store (default: beside the catalogue)")


def add_socket_option(p: argparse.ArgumentParser) -> None:
    """``--socket``: where a command finds the service."""
    from psfd.daemon.client import default_socket_path  # standard library only

    p.add_argument("--socket", metavar="PATH", help=f"service control socket (default {default_socket_path()})")


def add_runner_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", help=f"estimation processes, 1 to {vocabulary.WORKERS_MAX} (default: cores - 1, "
                                     "at least 1)")
    p.add_argument("--backlog", help=f"frames that may wait for estimation before the rig waits, 1 to "
                                     f"{vocabulary.BACKLOG_MAX} (default 4 per worker)")


def runner_options(args: argparse.Namespace) -> dict[str, int]:
    """The Runner's ``workers`` and ``backlog`` given on the command line (the others keep its defaults),
    each within its bound (`vocabulary.WORKERS_MAX`, `vocabulary.BACKLOG_MAX`)."""
    bounds = {"workers": vocabulary.WORKERS_MAX, "backlog": vocabulary.BACKLOG_MAX}
    return {name: vocabulary.check_count(parse_int(getattr(args, name), f"--{name}", minimum=1), f"--{name}", bound)
            for name, bound in bounds.items() if getattr(args, name) is not None}


def paths(args: argparse.Namespace) -> tuple[Path, Path, Path]:
    """Catalogue file, frame store and control socket the service options name (their defaults otherwise)."""
    from psfd.catalogue import default_path
    from psfd.daemon import store

    catalogue = Path(args.catalogue) if args.catalogue else default_path()
    frames = Path(args.frames) if getattr(args, "frames", None) else store.frames_dir_for(catalogue)
    return catalogue, frames, socket_path(args)


def socket_path(args: argparse.Namespace) -> Path:
    """The control socket ``--socket`` names, else the default one."""
    from psfd.daemon import client

    return Path(args.socket) if getattr(args, "socket", None) else client.default_socket_path()

