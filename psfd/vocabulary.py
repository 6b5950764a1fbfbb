"""The words and sizes every part of psfd shares: methods, solvers, channels, f-numbers, s, support, grid.

The command line, the plan checker, the catalogue and the estimators all take
their names, defaults and bounds from here, so that one method has one name
and one size has one check with one message. Standard library only: the
command line builds its parser from this module without loading numpy.

Methods (one name each, also the ``method`` of every stored PSF):

- ``bernoulli``: one photograph of the Bernoulli noise target (Delbracio et al., IJCV 2012);
- ``two-photo``: two photographs of a textured plane at different distances
  (Delbracio et al., SIAM J. Imaging Sciences 2012);
- ``sharp-edge``: the sharp-edge prediction baseline (Joshi et al., CVPR 2008).

Older names stay readable (`ALIASES`): the command words ``target``, ``pair``,
``edges`` and the plan kind ``pair`` (plan texts are stored and hashed in
catalogues, so an old plan must still parse and resume).
"""

from __future__ import annotations

import math
import os
import numbers
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from psfd.errors import BadInputError

BERNOULLI = "bernoulli"
TWO_PHOTO = "two-photo"
SHARP_EDGE = "sharp-edge"
METHODS = (BERNOULLI, TWO_PHOTO, SHARP_EDGE)
# Names of psfd 0.1 (command words and the plan kind "pair"), still accepted everywhere a method is named.
ALIASES = {"target": BERNOULLI, "pair": TWO_PHOTO, "edges": SHARP_EDGE}
# What the rig shoots: a plan's [target] kind and `psfd capture --target`.
CAPTURE_KINDS = (BERNOULLI, TWO_PHOTO)

# Solvers of the Bernoulli method's normal equations (psfd.estimator.bernoulli.solve).
SOLVERS = ("ls", "ls-threshold", "nnls")
DEFAULT_SOLVER = "nnls"  # unbiased: psfd.estimator.bernoulli.solve says why, with the numbers

# Default super-resolution factor per method: 4 for the target methods (IJCV 2012 sec. 5);
# 3 for two photographs, whose distance ratio must exceed s (SIAM J. Imaging Sci. 2012, Remark 2)
# and is 2 to 8 in practice (IPOL 2013, App. 7).
DEFAULT_S = {BERNOULLI: 4, TWO_PHOTO: 3, SHARP_EDGE: 4}

# Bounds of the sizes a user gives, checked before anything is allocated.
# s: the papers use 1 to 4; 8 is already far beyond what a printed target resolves.
S_MAX = 8
# support: the normal equations hold support^4 float64 values (143 MB at 65, 1.3 GB at 113);
# 65 samples span 16 channel pixels at s = 4, far wider than any in-focus PSF.
SUPPORT_MAX = 65
# grid: windows per side. 32 x 32 windows of a 6000 x 4000 RAW's Bayer plane are still
# 94 x 62 pixels, about the smallest that holds enough noise samples for a 17 x 17 kernel.
GRID_MAX = 32
# image size, checked on the file's header before it is decoded: a 151-megapixel medium-format
# sensor (14204 x 10652) fits; each pixel costs about 40 bytes on its way through the estimators.
MAX_PIXELS = 160_000_000
# estimation processes: each holds numpy, OpenCV and a frame (~0.2-1 GB); more than cores gains nothing.
WORKERS_MAX = 64
# frames captured but not yet estimated, per run (each is a file in the store and a queued job)
BACKLOG_MAX = 1024
# steps of one plan: 100,000 steps are more than a day of shooting even at one step a second;
# the journal holds one row per step, written when the run starts.
PLAN_STEPS_MAX = 100_000
PLAN_BYTES_MAX = 1 << 20  # a plan file: a few kB of TOML
# control-socket requests: a plan is a few kB; a request is an object holding strings and flags.
REQUEST_BYTES_MAX = 1 << 20
REQUEST_DEPTH_MAX = 32

AXES = ("x", "y", "z")  # rail axes, in millimetres
CHANNELS = ("r", "g1", "g2", "b")  # Bayer planes, named after the sensor's own CFA pattern
MONO = "mono"  # a single-channel image is its own plane

def method_name(name: str) -> str:
    """The one name of a method given by its name or an older alias (``pair`` -> ``two-photo``).

    Raises
    ------
    BadInputError
        Not a method.
    """
    if name in METHODS:
        return name
    if name in ALIASES:
        return ALIASES[name]
    raise BadInputError(f"unknown method {name!r} (one of {', '.join(METHODS)})")


def default_support(s: int) -> int:
    """Default kernel side on the s-grid: 4 s + 1, i.e. 4 channel pixels (IJCV 2012 sec. 5.2, Fig. 18)."""
    return 4 * int(s) + 1


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def check_s(s: Any, name: str = "s") -> int:
    """The super-resolution factor, an integer from 1 to `S_MAX`; else the one BadInputError for it."""
    if not _is_int(s) or not 1 <= s <= S_MAX:
        raise BadInputError(f"{name} must be a positive integer up to {S_MAX}, got {s!r}")
    return int(s)


def check_support(support: Any, name: str = "support") -> int:
    """The kernel side on the s-grid, an odd integer from 3 to `SUPPORT_MAX`; else the one BadInputError for it."""
    if not _is_int(support) or not 3 <= support <= SUPPORT_MAX or support % 2 == 0:
        raise BadInputError(f"{name} must be an odd integer from 3 to {SUPPORT_MAX}, got {support!r}")
    return int(support)


def check_grid(grid: Any, name: str = "grid") -> tuple[int, int]:
    """Windows (across, down), each an integer from 1 to `GRID_MAX`; else the one BadInputError for it."""
    if (not isinstance(grid, (tuple, list)) or len(grid) != 2
            or not all(_is_int(g) and 1 <= g <= GRID_MAX for g in grid)):
        raise BadInputError(f"{name} must be [nx, ny] with integers from 1 to {GRID_MAX}, got {grid!r}")
    return int(grid[0]), int(grid[1])


def check_sizes(
    s: Any, support: Any = None, grid: Any = (1, 1), names: Mapping[str, str] | None = None
) -> tuple[int, int, tuple[int, int]]:
    """``s``, ``support`` (`default_support` when None) and ``grid`` checked, before anything is allocated.

    ``names`` says how the caller names them in messages (default ``s``,
    ``support``, ``grid``; e.g. ``-s``, ``--support``, ``--grid`` on the
    command line). Returns them as Python ints; raises the BadInputError of
    the first one out of bounds (`check_s`, `check_support`, `check_grid`).
    """
    names = names or {}
    s = check_s(s, names.get("s", "s"))
    support = default_support(s) if support is None else check_support(support, names.get("support", "support"))
    return s, support, check_grid(grid, names.get("grid", "grid"))


def check_count(value: Any, name: str, maximum: int) -> int:
    """A count a user gives (``workers``, ``backlog``), an integer from 1 to ``maximum``; else a BadInputError."""
    if not _is_int(value) or not 1 <= value <= maximum:
        raise BadInputError(f"{name}: must be an integer from 1 to {maximum}, got {value!r}")
    return int(value)


def check_image_size(width: int, height: int, name: str) -> None:
    """Refuse an image whose header announces more than `MAX_PIXELS` (or no pixels), before it is decoded."""
    if width <= 0 or height <= 0 or width * height > MAX_PIXELS:
        raise BadInputError(f"{name}: a {width}x{height} image is {width * height:,} pixels; psfd reads frames "
                            f"of at most {MAX_PIXELS:,} pixels")


def check_steps(count: int, name: str = "plan") -> None:
    """Refuse a plan of more than `PLAN_STEPS_MAX` steps (its count, computed before it is expanded)."""
    if count > PLAN_STEPS_MAX:
        raise BadInputError(f"{name} expands to {count:,} steps, more than {PLAN_STEPS_MAX:,}: split it into "
                            "several plans")


def check_solver(solver: Any, name: str = "solver") -> str:
    """``solver`` if it is one of `SOLVERS`; else the one BadInputError for it."""
    if solver not in SOLVERS:
        raise BadInputError(f"{name} must be one of {', '.join(SOLVERS)}, got {solver!r}")
    return solver


def parse_fnumber(value: Any, name: str = "aperture") -> float | None:
    """f-number of user input or a camera setting: ``5.6``, ``"f/5.6"``, ``"F5.6"``; None when absent.

    Raises
    ------
    BadInputError
        Not a number (``"expected an f-number such as 5.6"``) or not positive
        (``"expected a positive f-number such as 5.6"``), named ``name``.
    """
    if value is None or value == "":
        return None
    text = str(value).strip().lower().removeprefix("f/").removeprefix("f")
    try:
        number = float(text)
    except ValueError:
        raise BadInputError(f"{name}: expected an f-number such as 5.6, got {value!r}") from None
    if not math.isfinite(number) or number <= 0:
        raise BadInputError(f"{name}: expected a positive f-number such as 5.6, got {value!r}")
    return number


# Channel pixels per target cell from which the Bernoulli target is found in a frame (psfd.estimator.detect,
# measured): smaller, every frame of a step fails with "no calibration target found". It is the smallest
# imaging scale of IJCV 2012 sec. 3.3 at the default s = 4 (s/t = 0.7).
TARGET_MIN_PX_PER_CELL = 0.175


def camera_fnumber(value: Any) -> float | None:
    """f-number of a camera's own setting, None when it is not one (``"implicit auto"``)."""
    try:
        return parse_fnumber(value)
    except BadInputError:
        return None


def same_setting(a: Any, b: Any) -> bool:
    """Two values of a setting mean the same: equal text, the same f-number (``5.6``, ``f/5.6``, ``F5.6``) or
    the same number (an exposure compensation of ``-1`` and ``-1.0``)."""
    if str(a) == str(b):
        return True
    fa, fb = _setting_number(a), _setting_number(b)
    return fa is not None and fb is not None and abs(fa - fb) < 1e-6


def offered_choice(value: str, offered: list[str]) -> str | None:
    """The camera's own choice among ``offered`` that is ``value``: the same text, else the same setting
    (`same_setting`: ``f/8`` for ``8`` or ``F8``); None when it offers none."""
    if value in offered:
        return value
    return next((choice for choice in offered if same_setting(choice, value)), None)


def _setting_number(value: Any) -> float | None:
    """The number a setting's value is: an f-number however spelt (`camera_fnumber`), else its finite number."""
    number = camera_fnumber(value)
    if number is not None:
        return number
    try:
        number = float(str(value))
    except ValueError:
        return None
    return number if math.isfinite(number) else None


def data_dir() -> Path:
    """The user's psfd data folder: ``$XDG_DATA_HOME/psfd``, else ``~/.local/share/psfd``.

    A relative or empty ``XDG_DATA_HOME`` is ignored, as the XDG base directory specification requires.
    """
    base = os.environ.get("XDG_DATA_HOME", "")
    root = Path(base) if base and os.path.isabs(base) else Path.home() / ".local" / "share"
    return root / "psfd"


def plan_content(text: str) -> str:
    """What a plan's text says, as one canonical string: two texts are the same plan when theirs are equal.

    The parsed TOML as JSON with sorted keys, so comments, blank lines, layout, key order, quoting and the
    spelling of a number (5.6 or 5.60, 4 or 4.0) do not count; every key and value, and the order of a
    list, does. A text that is not TOML (a catalogue may hold one) is only itself: a JSON list of it,
    which the content of no TOML text is.
    """
    import json  # here, not at the top: every command imports this module, `psfd --version` included,
    import tomllib  # and these two cost ~18 ms that only the commands comparing plans need

    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return json.dumps([text])
    return json.dumps(canonical(data), sort_keys=True, default=repr)


def canonical(value: Any) -> Any:
    """A parsed TOML value with each whole float as an int: a plan reads 4.0 as it reads 4 (booleans stay)."""
    if isinstance(value, dict):
        return {key: canonical(v) for key, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [canonical(v) for v in value]
    if isinstance(value, float) and value.is_integer():
        return int(value)
    return value


def setting_text(value: str | int | float) -> str:
    """The text a camera setting is set to for a plan's value: gphoto2 widgets take text, so a string is
    sent as written and a number as its text, a whole one as an integer (a plan reads 100.0 as 100):
    ``iso = 100``, ``100.0`` and ``"100"`` all set ``"100"``."""
    return str(canonical(value))
