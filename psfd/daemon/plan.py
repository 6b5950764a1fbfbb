"""Measurement plans: a TOML file that says what to shoot, where, and how to estimate it.

A plan has four tables::

    [rig]                       # simulate = true, or the ports of real hardware
    simulate = true             # any other key of psfd.drivers.open_rig may follow
    # scene = "texture"         # simulated rig: the textured plane a two-photo target needs
    # camera_port = "usb:001,004"
    # rail_port = "/dev/ttyUSB0"
    # rail_limits = { x = [0, 2000], y = [-150, 150], z = [-100, 100] }
    # settings = { iso = "100", shutterspeed = "1/60" }

    [target]
    kind = "bernoulli"          # or "two-photo" (once "pair"), with near = ... and far = ... in mm

    [capture]                   # positions that frame the target on the simulated rig
    apertures = [5.6, 8, 11]
    x = [1300]                  # rail distances in mm (bernoulli only)
    y = [-44.16, 0, 44.16]      # lateral positions (mm) walking the target over the field
    z = [-29.12, 0, 29.12]
    channels = ["r", "g1", "g2", "b"]
    repeats = 1

    [estimator]
    s = 4
    support = 17                # odd; default 4 s + 1
    solver = "nnls"             # bernoulli only: "nnls" (default), "ls", "ls-threshold" (psfd.vocabulary)
    grid = [1, 1]

Rail positions are checked against ``rail_limits`` (on the simulated rig, its
default travel when none are given), and a pair's far/near ratio against ``s``;
``s``, ``support`` and ``grid`` against their bounds (`psfd.vocabulary.check_sizes`), and the
number of steps, counted before the plan is expanded, against `psfd.vocabulary.PLAN_STEPS_MAX`.
`check_text` returns every problem found, one sentence each, so that
``psfd plan check`` can list them all at once; `load_plan` raises one
BadInputError naming the first and counting the rest.

Optics (a bernoulli target only): ``[capture] scale = [0.25]`` (Bayer-channel pixels per target
cell) instead of ``x`` puts the rail where one cell images to that many pixels, from ``focal_mm``
and ``pitch_um`` in [rig] and the cell in [target] (``cell_mm``, or ``printed = "target.pdf"``);
``x_at_lens`` and ``x_away`` map the lens-to-target distance to rail X (`scale_distances`).
``[rig] rail`` names the rail driver (`psfd.drivers.RAIL_DRIVERS`). ``[rig.camera]`` holds the
camera's setup for PSF work (`psfd.drivers.base.CameraSetup`: ``focus``, ``settle_s``, ``capture_target``...).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from psfd.drivers import RAIL_DRIVERS, REAL_KEYS, SIM_KEYS
from psfd.drivers.base import CameraSetup, RailInfo, cell_pixels, target_distance
from psfd.errors import BadInputError, PsfdError
from psfd.vocabulary import (AXES, BERNOULLI, CAPTURE_KINDS, CHANNELS, DEFAULT_S, DEFAULT_SOLVER, PLAN_BYTES_MAX,
                             SOLVERS, TARGET_MIN_PX_PER_CELL, TWO_PHOTO, canonical, check_grid, check_s, check_solver,
                             check_steps, check_support, default_support, plan_content, same_setting, setting_text)

# [rig] holds what psfd.drivers.open_rig reads (its simulated-rig and hardware keys), our
# camera settings, applied once before the first step, and the camera's setup for PSF work
# ([rig.camera], `psfd.drivers.base.CameraSetup`), applied after them and before any motion.
RUNNER_KEYS = ("settings", "camera")
RIG_KEYS = {"simulate", "recording", *RUNNER_KEYS, *SIM_KEYS, *REAL_KEYS}
# How the rig is reached and driven, not what it shoots: a camera plugged back in on another USB port, or a
# longer timeout, leaves the plan what it was (`plan_meaning`); the runner checks that a resumed run has the
# camera and lens it began with.
LINK_KEYS = ("camera_port", "rail_port", "timeout", "rail_timeout", "rail_baudrate", "rail_feed")
# The hardware keys of [rig] that are positive numbers (`psfd.drivers.open_rig` reads them without checking).
HARDWARE_NUMBERS = {"timeout": "a positive number of seconds", "rail_timeout": "a positive number of seconds",
                    "rail_feed": "a positive speed in mm/min"}
TABLES = {
    "rig": RIG_KEYS,
    "target": {"kind", "near", "far", "cell_mm", "printed"},
    "capture": {"apertures", "x", "scale", "y", "z", "channels", "repeats"},
    "estimator": {"s", "support", "solver", "grid"},
}


@dataclass(frozen=True)
class Step:
    """One exposure position: aperture, rail position(s), repeat index.

    For a two-photo plan ``x`` is ``(near, far)``: the step shoots both frames.
    """

    aperture: float
    x: float | tuple[float, float]
    y: float | None
    z: float | None
    repeat: int

    @property
    def key(self) -> str:
        """Deterministic key, e.g. ``a5.6/x1200/y-40/z10/r0`` (pair: ``x800-1600``)."""
        x = f"{fmt(self.x[0])}-{fmt(self.x[1])}" if isinstance(self.x, tuple) else fmt(self.x)
        parts = [f"a{fmt(self.aperture)}", f"x{x}"]
        parts += [f"{axis}{fmt(v)}" for axis, v in (("y", self.y), ("z", self.z)) if v is not None]
        return "/".join(parts + [f"r{self.repeat}"])

    def payload(self) -> dict[str, Any]:
        """JSON-ready description stored with the step in the catalogue."""
        out: dict[str, Any] = {"aperture": self.aperture, "y": self.y, "z": self.z, "repeat": self.repeat}
        if isinstance(self.x, tuple):
            out.update(near=self.x[0], far=self.x[1])
        else:
            out["x"] = self.x
        return out

    @classmethod
    def from_payload(cls, payload: dict[str, Any]) -> "Step":
        x = (payload["near"], payload["far"]) if "near" in payload else payload["x"]
        return cls(payload["aperture"], x, payload.get("y"), payload.get("z"), payload["repeat"])


@dataclass
class Plan:
    """A validated plan; ``text`` is kept verbatim with its runs (`plan_key` says which plan it is)."""

    text: str
    path: str
    rig: dict[str, Any]
    kind: str  # bernoulli or two-photo (`kind_name`)
    apertures: list[float]
    x: list[float]
    y: list[float] | None
    z: list[float] | None
    channels: list[str]
    repeats: int = 1
    near: float | None = None
    far: float | None = None
    estimator: dict[str, Any] = field(default_factory=dict)

    @property
    def camera_settings(self) -> dict[str, str]:
        """[rig] settings as the text each is sent to the camera (`setting_text`)."""
        return {name: setting_text(value) for name, value in self.rig.get("settings", {}).items()}

    def steps(self) -> list[Step]:
        """Steps in execution order: rail distance, then a serpentine walk of the field grid
        (the shortest lateral moves), then apertures and repeats at each position."""
        xs: list[Any] = [(self.near, self.far)] if self.kind == TWO_PHOTO else list(self.x)
        ys: list[Any] = self.y if self.y is not None else [None]
        zs: list[Any] = self.z if self.z is not None else [None]
        out = []
        for x in xs:
            for row, y in enumerate(ys):
                for z in zs if row % 2 == 0 else zs[::-1]:
                    for aperture, repeat in itertools.product(self.apertures, range(self.repeats)):
                        out.append(Step(aperture, x, y, z, repeat))
        return out

    def rig_config(self) -> dict[str, Any]:
        """The [rig] table as `psfd.drivers.open_rig` takes it (camera settings and setup are the runner's)."""
        return {k: v for k, v in self.rig.items() if k not in RUNNER_KEYS}

    def estimator_options(self) -> dict[str, Any]:
        """Keyword arguments for the estimator of this plan's target kind."""
        opts = dict(self.estimator)
        if "grid" in opts:
            opts["grid"] = tuple(opts["grid"])
        return opts


def kind_name(kind: Any) -> Any:
    """A plan's target kind by its one name: ``pair`` (psfd 0.1, still in stored plans) is ``two-photo``."""
    return TWO_PHOTO if kind == "pair" else kind


def plan_text(tables: dict[str, dict[str, Any]]) -> str:
    """The TOML text of a plan given as its tables (the value types plans use: booleans,
    numbers, strings, lists of them, and tables of lists such as ``rail_limits``)."""
    lines: list[str] = []
    for name, table in tables.items():
        lines += [f"[{name}]", *(f"{key} = {_toml(value)}" for key, value in table.items()), ""]
    return "\n".join(lines)


def plan_meaning(plan: Plan) -> dict[str, dict[str, Any]]:
    """What a plan does: every value that changes a frame or an estimate, its defaults filled in.

    Two plans of one meaning shoot the same steps with the same settings and estimate them alike,
    whatever their comments, key order or defaults written out (``repeats = 1``; ``channels = "all"``
    or the four listed, in any order). Rail X is where the steps go: a ``scale`` made into distances
    (`scale_distances`), so ``x_at_lens``, ``x_away`` and the cell size count through it; the order
    of a list of positions or apertures counts, as it orders the steps.
    """
    s = plan.estimator.get("s", DEFAULT_S[plan.kind])
    estimator = {"s": s, "support": plan.estimator.get("support", default_support(s)),
                 "grid": plan.estimator.get("grid", [1, 1])}
    if plan.kind == BERNOULLI:
        estimator["solver"] = plan.estimator.get("solver", DEFAULT_SOLVER)
    capture = {"apertures": plan.apertures, "x": plan.x, "y": plan.y, "z": plan.z, "repeats": plan.repeats,
               "channels": [c for c in CHANNELS if c in plan.channels]}
    target = {"kind": plan.kind, "near": plan.near, "far": plan.far}
    return canonical({"rig": _rig_meaning(plan.rig), "target": target, "capture": capture, "estimator": estimator})


def _rig_meaning(rig: dict[str, Any]) -> dict[str, Any]:
    """[rig] with the defaults of the rig it opens (`psfd.drivers.open_rig`, `CameraSetup`) written out, its camera
    settings as the text the camera is sent (`setting_text`), without how it is reached (`LINK_KEYS`) and where
    the lens sits (x_at_lens and x_away count through rail X)."""
    simulate = rig.get("simulate", False) is True
    defaults: dict[str, Any] = {"simulate": False, "rail": "simulated" if simulate else "grbl", "settings": {}}
    if simulate:
        from psfd.drivers.sim import SimRig

        fields = SimRig.__dataclass_fields__
        defaults.update({k: fields[k].default_factory() if k == "limits" else fields[k].default  # type: ignore[misc]
                         for k in SIM_KEYS})
    meaning = {**defaults, **{k: v for k, v in rig.items() if k not in ("x_at_lens", "x_away", *LINK_KEYS)}}
    meaning["settings"] = {name: setting_text(v) for name, v in rig.get("settings", {}).items()}
    meaning["camera"] = dataclasses.asdict(CameraSetup.from_mapping(rig.get("camera")))
    return meaning


def plan_key(text: str) -> str:
    """Which plan a text is, as one string: two texts are one plan when theirs are equal (`plan_meaning`).

    A text that is no valid plan (a catalogue may hold one an older psfd took) is only its content
    (`psfd.vocabulary.plan_content`), which the key of no valid plan is.
    """
    try:
        meaning = plan_meaning(parse_plan(text))
    except PsfdError:
        return plan_content(text)
    return json.dumps(["plan", meaning], sort_keys=True)


def plan_changes(old: str, new: str) -> list[str]:
    """What two plans do differently (`plan_meaning`), one ``[table] key old -> new`` each, e.g.
    ``[capture] repeats 1 -> 2``; texts that are no valid plan are compared by their content (`plan_content`)."""
    try:
        before, after = plan_meaning(parse_plan(old)), plan_meaning(parse_plan(new))
    except PsfdError:
        before, after = _tables(old), _tables(new)
    changes = []
    for name in dict.fromkeys([*before, *after]):
        one, two = before.get(name), after.get(name)
        if not (isinstance(one, dict) and isinstance(two, dict)):
            changes += [f"[{name}]"] if _json(one) != _json(two) else []
            continue
        changes += [f"[{name}] {key} {_shown(one.get(key))} -> {_shown(two.get(key))}"
                    for key in dict.fromkeys([*one, *two]) if _json(one.get(key)) != _json(two.get(key))]
    return changes


def _tables(text: str) -> dict[str, Any]:
    content = json.loads(plan_content(text))
    return content if isinstance(content, dict) else {}


def _json(value: Any) -> str:
    """A value's canonical text: compared as text, true is not 1 (as Python's == would have it)."""
    return json.dumps(value, sort_keys=True)


def _shown(value: Any, width: int = 40) -> str:
    """A value as a change names it, on one short line: ``unset`` for a key not given."""
    text = "unset" if value is None else json.dumps(value, sort_keys=True)
    return text if len(text) <= width else text[:width - 3] + "..."


def _toml(value: Any) -> str:
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{key} = {_toml(v)}" for key, v in value.items()) + " }"
    return json.dumps(value)  # JSON's booleans, numbers, strings and arrays are TOML's too


def fmt(value: float) -> str:
    """Shortest text of a number for keys: 1200.0 -> ``1200``, 5.6 -> ``5.6``."""
    value = float(value)
    return str(int(value)) if value.is_integer() else f"{value:g}"


def load_plan(path: str | Path) -> Plan:
    """Read and validate a plan file.

    Raises
    ------
    BadInputError
        The file cannot be read or the plan has problems (the first is named,
        ``psfd plan check`` lists them all).
    """
    return parse_plan(read_plan_text(path), str(path))


def read_plan_text(path: str | Path) -> str:
    """The text of a plan file, refused (BadInputError) when unreadable or longer than `PLAN_BYTES_MAX`."""
    path = Path(path)
    try:
        if path.stat().st_size > PLAN_BYTES_MAX:
            raise BadInputError(f"plan {path} is {path.stat().st_size:,} bytes, more than a plan needs "
                                f"({PLAN_BYTES_MAX:,} at most)")
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInputError(f"cannot read plan {path}: {exc}") from None


def parse_plan(text: str, path: str = "<plan>") -> Plan:
    """Validate plan text and build the Plan; raises BadInputError on the first problem."""
    problems = check_text(text)
    if problems:
        more = f" ({len(problems) - 1} more; run 'psfd plan check {path}')" if len(problems) > 1 else ""
        raise BadInputError(f"plan {path}: {problems[0]}{more}")
    data = tomllib.loads(text)
    target = data["target"]
    rig = simulated_rig(data.get("rig", {}), target)
    capture, estimator = data["capture"], data.get("estimator", {})
    channels = capture.get("channels", ["g1"])
    return Plan(
        text=text,
        path=path,
        rig=rig,
        kind=kind_name(target["kind"]),
        apertures=[float(a) for a in capture["apertures"]],
        x=([float(v) for v in capture["x"]] if "x" in capture
           else scale_distances(rig, target, capture["scale"]) if "scale" in capture else []),  # a pair: none
        y=[float(v) for v in capture["y"]] if "y" in capture else None,
        z=[float(v) for v in capture["z"]] if "z" in capture else None,
        channels=list(CHANNELS) if channels == "all" else list(channels),
        repeats=int(capture.get("repeats", 1)),
        near=float(target["near"]) if "near" in target else None,
        far=float(target["far"]) if "far" in target else None,
        estimator=dict(estimator),
    )


def check_text(text: str) -> list[str]:
    """Every problem of a plan, one sentence each (empty when the plan is usable)."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        return [f"not valid TOML: {exc}"]
    problems: list[str] = []
    for name in data:
        if name not in TABLES:
            problems.append(f"unknown table [{name}] (expected {', '.join(f'[{t}]' for t in TABLES)})")
        elif not isinstance(data[name], dict):
            problems.append(f"{name} must be a table [{name}]")
    for name, keys in TABLES.items():
        table = data.get(name)
        if isinstance(table, dict):
            problems += [f"[{name}] unknown key '{k}' (expected one of: {', '.join(sorted(keys))})"
                         for k in table if k not in keys]
    tables = {name: data.get(name) if isinstance(data.get(name), dict) else {} for name in TABLES}
    for name in ("target", "capture"):
        if name not in data:
            problems.append(f"missing table [{name}]")
    problems += _check_rig(tables["rig"])
    kind = kind_name(tables["target"].get("kind"))
    problems += _check_target(tables["target"], kind, "target" in data)
    if tables["rig"].get("simulate") is True:
        scene = tables["rig"].get("scene", "bernoulli")
        if kind == TWO_PHOTO and scene != "texture":
            problems.append('[rig] a simulated pair needs scene = "texture" (a textured plane)')
        if kind == BERNOULLI and scene != "bernoulli":
            problems.append('[rig] a simulated bernoulli target needs scene = "bernoulli" (the default)')
    problems += _check_capture(tables["capture"], kind, "capture" in data)
    problems += _check_count(tables["capture"], kind)
    problems += _check_optics(tables["rig"], tables["target"], tables["capture"])
    problems += _check_limits(tables["rig"], tables["target"], tables["capture"], kind)
    problems += _check_simulated(tables["rig"], tables["target"], tables["capture"], kind)
    problems += _check_detectable(tables["rig"], tables["target"], tables["capture"], kind)
    problems += _check_estimator(tables["estimator"], kind)
    problems += _check_ratio(tables["target"], tables["estimator"], kind)
    return problems


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _number_list(table: dict, key: str, where: str, positive: bool = False) -> list[str]:
    value = table[key]
    if not isinstance(value, list) or not value:
        return [f"{where} {key} must be a non-empty list of numbers"]
    bad = [v for v in value if not _is_number(v) or (positive and v <= 0)]
    if bad:
        kind = "positive numbers" if positive else "numbers"
        return [f"{where} {key} must hold {kind}, got {', '.join(repr(v) for v in bad)}"]
    return _twice(value, f"{where} {key}")


def _twice(values: list, where: str) -> list[str]:
    """Values that make one step key (`fmt`: 6 significant digits): exact repeats, and values that print alike
    (``x = [1300.001, 1300.004]`` is step ``x1300`` twice, which the run would refuse)."""
    keys: dict[str, list] = {}
    for v in values:
        keys.setdefault(fmt(v), []).append(v)
    problems = []
    for text, same in keys.items():
        if len(same) > 1 and len(set(same)) == 1:
            problems.append(f"{where} lists {text} twice")
        elif len(same) > 1:
            problems.append(f"{where} lists {' and '.join(map(str, same))}, one value ({text}) to the 6 significant "
                            "digits that key the steps")
    return problems


def _check_rig(rig: dict) -> list[str]:
    problems = []
    simulate = rig.get("simulate", False)
    if not isinstance(simulate, bool):
        problems.append("[rig] simulate must be true or false")
    for key in ("camera_port", "rail_port"):
        if key in rig and not isinstance(rig[key], str):
            problems.append(f"[rig] {key} must be a string")
    rail = rig.get("rail", "simulated" if simulate is True else "grbl")
    if rail not in RAIL_DRIVERS:
        problems.append(f"[rig] rail must be one of {', '.join(map(repr, RAIL_DRIVERS))}, got {rail!r}")
    elif simulate is True and rail != "simulated":
        problems.append(f"[rig] rail = {rail!r} does not go with simulate = true (the simulated rig's rail)")
    elif rail == "grbl" and "rail_port" not in rig and "recording" not in rig:
        problems.append("[rig] needs rail_port (or simulate = true, or recording = DIR)")
    problems += [f"[rig] {key} must be {what}, got {rig[key]!r}" for key, what in HARDWARE_NUMBERS.items()
                 if key in rig and not (_is_number(rig[key]) and rig[key] > 0)]
    baudrate = rig.get("rail_baudrate", 115200)
    if not (isinstance(baudrate, int) and not isinstance(baudrate, bool) and baudrate > 0):
        problems.append(f"[rig] rail_baudrate must be a positive integer (bits per second), got {baudrate!r}")
    if "x_at_lens" in rig and not _is_number(rig["x_at_lens"]):
        problems.append("[rig] x_at_lens must be a number (the rail X, in mm, of a target at the lens)")
    if rig.get("x_away", 1) not in (1, -1) or isinstance(rig.get("x_away"), bool):
        problems.append("[rig] x_away must be 1 (the target goes away from the lens as X grows) or -1")
    from psfd.drivers.sim import option_problems  # the simulated rig's keys, as it checks them itself

    problems += [f"[rig] {problem}" for problem in option_problems({k: rig[k] for k in SIM_KEYS if k in rig})]
    settings = rig.get("settings", {})
    if isinstance(settings, dict):
        problems += _check_settings(settings)
    else:
        problems.append("[rig] settings must be a table of camera setting names to values")
    camera = rig.get("camera", {})
    if not isinstance(camera, dict):
        problems.append("[rig] camera must be a table [rig.camera] (keys of the camera setup)")
    else:
        try:
            CameraSetup.from_mapping(camera)
        except BadInputError as exc:
            problems.append(f"[rig.camera] {exc}")
    limits = rig.get("rail_limits", {})
    if not isinstance(limits, dict):
        return problems + ["[rig] rail_limits must be a table such as { x = [0, 2000] }"]
    for axis, pair in limits.items():
        if axis not in AXES:
            problems.append(f"[rig] rail_limits has unknown axis '{axis}' (expected x, y, z)")
        elif not (isinstance(pair, list) and len(pair) == 2 and all(map(_is_number, pair)) and pair[0] < pair[1]):
            problems.append(f"[rig] rail_limits.{axis} must be [low, high] with low < high, got {pair!r}")
    return problems


def _check_settings(settings: dict) -> list[str]:
    """Values no camera widget takes, and an aperture, which each step sets from [capture] apertures.

    gphoto2 widgets take text: a string is sent as written, a finite number as its text (`setting_text`);
    nan, inf, a boolean (not the "On" or "1" a camera lists), a list, a table or a date is none of them.
    """
    bad = [f"{name} = {_written(v)}" for name, v in settings.items() if not (isinstance(v, str) or _is_number(v))]
    problems = [f"[rig] settings {', '.join(bad)}: a camera setting takes its value as the camera lists it "
                '("100", "1/125", "On") or a finite number'] if bad else []
    if "aperture" in settings:
        problems.append("[rig] settings aperture: each step sets the aperture from [capture] apertures "
                        "(remove it from settings)")
    return problems


def _written(value: Any) -> str:
    """A TOML value as a plan writes it: ``true``, ``nan``, ``-inf``, ``[100]``, ``1979-05-27``."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # Python spells nan, inf and -inf as TOML does
    if hasattr(value, "isoformat"):
        return value.isoformat()
    return _toml(value)


def _check_target(target: dict, kind: Any, present: bool) -> list[str]:
    if not present:
        return []
    if kind not in CAPTURE_KINDS:
        expected = ", ".join(repr(k) for k in CAPTURE_KINDS)
        return [f"[target] kind must be one of {expected}, got {target.get('kind')!r}"]
    if kind == BERNOULLI:
        return [f"[target] {k} applies to kind = \"{TWO_PHOTO}\" only" for k in ("near", "far") if k in target]
    problems = []
    for key in ("near", "far"):
        if key not in target:
            problems.append(f"[target] kind = \"{TWO_PHOTO}\" needs {key} (distance in mm)")
        elif not _is_number(target[key]) or target[key] <= 0:
            problems.append(f"[target] {key} must be a positive distance in mm, got {target[key]!r}")
    if not problems and target["near"] >= target["far"]:
        problems.append(f"[target] near ({target['near']}) must be closer than far ({target['far']})")
    return problems


def _check_capture(capture: dict, kind: Any, present: bool) -> list[str]:
    if not present:
        return []
    problems = []
    if "apertures" not in capture:
        problems.append("[capture] needs apertures, e.g. apertures = [5.6, 8]")
    else:
        problems += _number_list(capture, "apertures", "[capture]", positive=True)
    if kind == BERNOULLI and ("x" in capture) == ("scale" in capture):
        problems.append("[capture] needs x (rail distances in mm) or scale (channel pixels per target cell) "
                        "for a bernoulli target, not both")
    for key in ("x", "scale"):
        if kind == TWO_PHOTO and key in capture:
            problems.append(f"[capture] {key} does not apply to a pair target: set near and far in [target]")
    if "scale" in capture:
        problems += _number_list(capture, "scale", "[capture]", positive=True)
    for axis in AXES:
        if axis in capture:
            problems += _number_list(capture, axis, "[capture]")
    channels = capture.get("channels", ["g1"])
    if channels != "all":
        if not isinstance(channels, list) or not channels:
            problems.append(f"[capture] channels must be \"all\" or a list of {', '.join(CHANNELS)}")
        else:
            bad = [c for c in channels if c not in CHANNELS]
            if bad:
                problems.append(f"[capture] unknown channel(s) {', '.join(map(repr, bad))} "
                                f"(expected {', '.join(CHANNELS)})")
            elif len(set(channels)) != len(channels):
                problems.append("[capture] channels lists a channel twice")
    repeats = capture.get("repeats", 1)
    if not isinstance(repeats, int) or isinstance(repeats, bool) or repeats < 1:
        problems.append(f"[capture] repeats must be a positive integer, got {repeats!r}")
    return problems


def _check_count(capture: dict, kind: Any) -> list[str]:
    """The number of steps `Plan.steps` would make, counted before anything is expanded (`check_steps`)."""
    def length(key: str) -> int:
        value = capture.get(key)
        return len(value) if isinstance(value, list) and value else 1

    repeats = capture.get("repeats", 1)
    repeats = repeats if isinstance(repeats, int) and repeats > 0 else 1
    distances = length("x") * length("scale")  # a plan gives one of them (the other counts 1)
    count = length("apertures") * (1 if kind == TWO_PHOTO else distances) * length("y") * length("z") * repeats
    try:
        check_steps(count, "[capture]")
    except BadInputError as exc:
        return [str(exc)]
    return []


def _rail_limits(rig: dict) -> Any:
    """The travel limits a run will meet: the plan's own, else the simulated rig's defaults."""
    limits = rig.get("rail_limits", rig.get("limits"))
    if limits is None and rig.get("simulate") is True:
        from psfd.drivers.sim import SimRig

        return {axis: list(pair) for axis, pair in SimRig.__dataclass_fields__["limits"].default_factory().items()}
    return limits


def _check_limits(rig: dict, target: dict, capture: dict, kind: Any) -> list[str]:
    limits = _rail_limits(rig)
    if not isinstance(limits, dict):
        return []
    values: dict[str, list] = {axis: capture.get(axis) for axis in AXES}
    if kind == BERNOULLI and "scale" in capture:
        try:
            values["x"] = scale_distances(rig, target, capture["scale"])
        except (BadInputError, TypeError, ValueError):
            values["x"] = []  # the scale's own problem is reported by _check_optics
    if kind == TWO_PHOTO:
        values["x"] = [target.get("near"), target.get("far")]
    problems = []
    for axis, pair in limits.items():
        if not (isinstance(pair, list) and len(pair) == 2 and all(map(_is_number, pair)) and pair[0] <= pair[1]):
            continue  # _check_rig names a malformed pair
        outside = [v for v in values.get(axis) or [] if _is_number(v) and not pair[0] <= v <= pair[1]]
        if outside:
            where = next((key for key in ("rail_limits", "limits") if key in rig), "the simulated rail's limits")
            problems.append(f"{axis} = {', '.join(fmt(v) for v in outside)} outside {where}.{axis} "
                            f"[{fmt(pair[0])}, {fmt(pair[1])}]")
    return problems


def _check_simulated(rig: dict, target: dict, capture: dict, kind: Any) -> list[str]:
    """The simulated rig against the plan: one printed cell (`simulated_rig`), and a view it can render at
    every rail distance of the plan (`psfd.drivers.sim.SimRig.scene_problems`)."""
    if rig.get("simulate") is not True:
        return []
    from psfd.drivers.sim import SimRig, option_problems

    try:
        cell = target_cell(target)
    except BadInputError as exc:
        return [] if "scale" in capture else [f"[target] {exc}"]  # a scale's own problem is _check_optics'
    if "cell_mm" in rig and _is_number(cell) and _is_number(rig["cell_mm"]) and cell != rig["cell_mm"]:
        return [f"[target] cell_mm = {fmt(cell)} and [rig] cell_mm = {fmt(rig['cell_mm'])} disagree: the simulated "
                "rig prints its target with [target]'s cell when [rig] gives none (give it once)"]
    options = {k: v for k, v in simulated_rig(rig, target).items() if k in SIM_KEYS and k != "limits"}
    problems = option_problems(options)
    if problems:  # [rig]'s own are _check_rig's; a cell of [target] is named here (a non-positive one, _check_optics)
        return [f"[target] {p}" for p in problems if p.startswith("cell_mm") and "cell_mm" not in rig
                and _is_number(cell) and cell > 0]
    if kind == TWO_PHOTO:
        distances = [target.get("near"), target.get("far")]
    else:
        try:
            distances = scale_distances(rig, target, capture["scale"]) if "scale" in capture else capture.get("x")
        except (BadInputError, TypeError, ValueError):
            distances = []  # the scale's own problem is reported by _check_optics
    distances = [float(d) for d in distances or [] if _is_number(d)]
    apertures = [float(a) for a in capture.get("apertures", []) if _is_number(a) and a > 0] \
        if isinstance(capture.get("apertures"), list) else []
    return [f"[rig] {p}" for p in SimRig(**options).scene_problems(distances, apertures)]


# ---------------------------------------------------------------------- optics and the rail


def optics(rig: dict, target: dict) -> dict[str, float]:
    """Focal length, photosite pitch and printed cell size (mm, um, mm) that turn a scale into distances.

    ``focal_mm`` and ``pitch_um`` come from [rig], the cell from [target] (``cell_mm``, or the page size
    of the ``printed`` target PDF); on the simulated rig each defaults to the simulated camera's own.

    Raises
    ------
    BadInputError
        One of the three is missing or not a positive number.
    """
    values: dict[str, Any] = {"focal_mm": rig.get("focal_mm"), "pitch_um": rig.get("pitch_um")}
    values["cell_mm"] = target_cell(target)
    if rig.get("simulate") is True:
        from psfd.drivers.sim import SimRig

        defaults = SimRig.__dataclass_fields__
        values = {k: v if v is not None else rig.get(k, defaults[k].default) for k, v in values.items()}
    missing = [k for k, v in values.items() if v is None]
    if missing:
        raise BadInputError(f"a scale needs {', '.join(missing)} (focal_mm and pitch_um in [rig], cell_mm or "
                            "printed = \"TARGET.pdf\" in [target])")
    bad = [k for k, v in values.items() if not (_is_number(v) and v > 0)]
    if bad:
        raise BadInputError(f"{', '.join(bad)} must be positive numbers")
    return {k: float(v) for k, v in values.items()}


def target_cell(target: dict) -> Any:
    """The printed cell (mm) [target] gives: ``cell_mm``, else the page of its ``printed`` PDF; None without either.

    Raises
    ------
    BadInputError
        The printed PDF cannot be read.
    """
    if target.get("cell_mm") is None and isinstance(target.get("printed"), str):
        from psfd.printing import printed_cell_mm

        return printed_cell_mm(target["printed"])
    return target.get("cell_mm")


def simulated_rig(rig: dict, target: dict) -> dict:
    """[rig] of a simulated rig with the printed cell of [target] (`target_cell`) when [rig] gives none: the
    simulated target is then the one the plan's ``scale`` puts the rail for (else its own 0.1 mm cell)."""
    cell = target_cell(target) if rig.get("simulate") is True and "cell_mm" not in rig else None
    return rig if cell is None else {**rig, "cell_mm": cell}


def scale_distances(rig: dict, target: dict, scales: list[float]) -> list[float]:
    """Rail X (mm) of each wanted scale (channel pixels per target cell), from the plan's optics.

    The lens-to-target distance (`psfd.drivers.base.target_distance`) becomes a rail coordinate through
    ``x_at_lens`` (the rail X of a target at the lens, default 0) and ``x_away`` (1: the target goes away
    as X grows, the default; -1: it comes closer, as on a rail homed at the far end), to 0.01 mm.
    """
    o = optics(rig, target)
    x0, sign = float(rig.get("x_at_lens", 0.0)), int(rig.get("x_away", 1))
    return [round(x0 + sign * target_distance(float(p), o["focal_mm"], o["pitch_um"], o["cell_mm"]), 2)
            for p in scales]


def _check_optics(rig: dict, target: dict, capture: dict) -> list[str]:
    problems = [f"[target] {k} must be a positive size in mm, got {target[k]!r}"
                for k in ("cell_mm",) if k in target and not (_is_number(target[k]) and target[k] > 0)]
    if "printed" in target and not isinstance(target["printed"], str):
        problems.append("[target] printed must be the path of the target PDF (psfd target)")
    rig_bad = any(k in rig and not (_is_number(rig[k]) and rig[k] > 0) for k in ("focal_mm", "pitch_um"))
    if "scale" in capture and not problems and not rig_bad:  # a bad focal_mm or pitch_um is _check_rig's
        try:
            optics(rig, target)
        except BadInputError as exc:
            problems.append(f"[capture] {exc}")
    return problems


def _check_detectable(rig: dict, target: dict, capture: dict, kind: Any) -> list[str]:
    """Scales, or rail X with the plan's optics, at which a target cell images smaller than the target is found
    from (`TARGET_MIN_PX_PER_CELL`): every frame there would fail with "no calibration target found"."""
    if kind != BERNOULLI:
        return []
    try:
        o = optics(rig, target)
        x0, sign = float(rig.get("x_at_lens", 0.0)), int(rig.get("x_away", 1))
    except (BadInputError, TypeError, ValueError):
        return []  # no optics (a real rig's plan of rail X), or their own problem (_check_optics, _check_rig)
    if "scale" in capture:
        key, sizes = "scale", {v: v for v in capture["scale"] if _is_number(v)}
    else:
        key, sizes = "x", {x: cell_pixels(d, o["focal_mm"], o["pitch_um"], o["cell_mm"])
                           for x in capture.get("x") or [] if _is_number(x)
                           and (d := sign * (float(x) - x0)) > o["focal_mm"]}
    return [f"[capture] {key} = {fmt(value)}: a target cell images to {size:.2g} channel pixel, smaller than the "
            f"{TARGET_MIN_PX_PER_CELL:g} the target is found from (bring it closer: scale "
            f"{TARGET_MIN_PX_PER_CELL:g} or more)"
            for value, size in sizes.items() if 0 < size < TARGET_MIN_PX_PER_CELL]


def check_rail(plan: Plan, info: RailInfo) -> list[str]:
    """Every position of the plan the rail cannot reach: an axis it does not have, or outside its travel.

    ``info`` is what the rail (a controller, or a recording of one) says of itself (`Rail.info`).
    """
    values: dict[str, list[float]] = {"x": [plan.near, plan.far] if plan.kind == TWO_PHOTO else plan.x,
                                      "y": plan.y or [], "z": plan.z or []}
    problems = []
    for axis, wanted in values.items():
        wanted = [v for v in wanted if v is not None]
        if not wanted:
            continue
        if axis not in info.axes or axis not in info.travel:
            problems.append(f"{axis} = {', '.join(fmt(v) for v in wanted)}: the rail ({info.controller}) has no "
                            f"{axis.upper()} axis (axes: {', '.join(a.upper() for a in info.axes) or 'none'})")
            continue
        lo, hi = info.travel[axis]
        outside = [v for v in wanted if not lo <= v <= hi]
        if outside:
            problems.append(f"{axis} = {', '.join(fmt(v) for v in outside)} outside the travel of the rail "
                            f"({info.controller}) {axis}: [{fmt(lo)}, {fmt(hi)}]")
    return problems


def recording_problems(plan: Plan) -> list[str]:
    """How the recording a plan replays (``[rig] recording``) differs from the plan; empty without one.

    A replayed capture must find the rig where the recorded one stood (`psfd.drivers.recording.Replay`),
    so each capture of the plan, in its order, is held to the recorded one: its aperture, rail position
    and camera settings; and a simulated session's scene to the target. Said here, a plan made for another
    recording is refused before its run opens instead of pausing it at the first capture that differs.
    """
    folder = plan.rig.get("recording")
    if folder is None:
        return []
    from psfd.drivers.recording import Replay

    where = f"[rig] recording {folder}"
    try:
        replay = Replay(folder)
    except PsfdError as exc:
        return [f"{where}: {exc}"]
    problems = []
    scene = replay.rig.get("scene", "bernoulli") if replay.rig.get("simulate") is True else None
    wanted = "texture" if plan.kind == TWO_PHOTO else "bernoulli"
    if scene is not None and scene != wanted:
        problems.append(f'{where} shows the simulated scene "{scene}": a {plan.kind} target needs "{wanted}"')
    captures = [(step, x) for step in plan.steps() for x in (step.x if isinstance(step.x, tuple) else (step.x,))]
    shots = replay.shots()
    if len(shots) < len(captures):
        problems.append(f"{where} holds {len(shots)} capture(s), the plan takes {len(captures)}")
    differ = [(n, step, wrong) for n, ((step, x), shot) in enumerate(zip(captures, shots), 1)
              if (wrong := _shot_differences(step, x, plan.camera_settings, shot))]
    if differ:
        n, step, wrong = differ[0]
        more = f"; {len(differ) - 1} more capture(s) differ" if len(differ) > 1 else ""
        problems.append(f"{where}: capture {n} (step {step.key}) was recorded with {', '.join(wrong)}{more}")
    return problems


def _shot_differences(step: Step, x: float, settings: dict[str, str],
                      shot: tuple[dict[str, str], dict[str, float]]) -> list[str]:
    """What differs between a recorded capture and the plan's capture at rail ``x`` of ``step``: ``aperture 8
    (the plan: 5.6)``, ``rail y -40 (the plan: 0)``; compared as the replay compares them."""
    from psfd.drivers.recording import AXIS_TOLERANCE

    recorded, at = shot
    wanted = {"aperture": fmt(step.aperture), **settings}
    wrong = [f"{name} {recorded.get(name, 'unset')} (the plan: {value})" for name, value in wanted.items()
             if not (name in recorded and same_setting(recorded[name], value))]
    planned = {axis: value for axis, value in zip(AXES, (x, step.y, step.z)) if value is not None}
    for axis in (a for a in AXES if a in planned or a in at):  # an axis the plan leaves alone was not moved
        if not (axis in planned and axis in at and abs(at[axis] - planned[axis]) <= AXIS_TOLERANCE):
            shown = [fmt(where[axis]) if axis in where else "unset" for where in (at, planned)]
            wrong.append(f"rail {axis} {shown[0]} (the plan: {shown[1]})")
    return wrong


def _check_ratio(target: dict, est: dict, kind: Any) -> list[str]:
    """A pair's distance ratio lambda ~ far / near must exceed s (SIAM J. Imaging Sci. 2012, Remark 2;
    the estimator measures lambda from the photos and refuses lambda <= s, so say it before the rig moves)."""
    near, far, s = target.get("near"), target.get("far"), est.get("s", DEFAULT_S[TWO_PHOTO])
    if kind != TWO_PHOTO or not all(map(_is_number, (near, far, s))) or near <= 0 or near >= far:
        return []
    if far / near <= s:
        return [f"[target] far / near = {far / near:.3g} must exceed s = {fmt(s)} (move near closer or far away)"]
    return []


def _check_estimator(est: dict, kind: Any) -> list[str]:
    """The sizes and solver, each by the one check of `psfd.vocabulary` (every problem, not only the first)."""
    checks = [(check_s, est.get("s", DEFAULT_S.get(kind, DEFAULT_S[BERNOULLI])), "s")]
    checks += [(check, est[key], key) for check, key in ((check_support, "support"), (check_grid, "grid"))
               if key in est]
    if "solver" in est:
        if kind == TWO_PHOTO:
            return _problems(checks) + ["[estimator] solver applies to a bernoulli target only"]
        checks.append((check_solver, est["solver"], "solver"))
    return _problems(checks)


def _problems(checks: list[tuple[Any, Any, str]]) -> list[str]:
    problems = []
    for check, value, key in checks:
        try:
            check(value, f"[estimator] {key}")
        except BadInputError as exc:
            problems.append(str(exc))
    return problems


def plan_template(simulate: bool = False) -> str:
    """A plan with every key (`TABLES`), each explained: in use where a plan needs it, commented out
    where its default stands (``psfd plan init``). It passes `check_text` as written.

    ``simulate``: a small plan the simulated rig runs in seconds (two apertures at the centre of the
    field, the g1 channel); else a plan for a real rig, whose rail positions must be measured first.
    """
    from psfd.drivers.sim import SimRig

    sim = SimRig()
    ys, zs = sim.field_offsets(3)
    travel = ", ".join(f"{axis} = [{fmt(lo)}, {fmt(hi)}]" for axis, (lo, hi) in sim.limits.items())
    hardware = [
        (not simulate, 'rail_port = "/dev/psfd-rail"', "the rail's serial port (see systemd/99-psfd.rules)"),
        (False, 'camera_port = "usb:001,004"', "gphoto2 port of the camera (default: the only one connected)"),
    ]
    rig = ([(True, "simulate = true", "the simulated rig, no hardware: remove this line for a real rig")]
           if simulate else []) + hardware + [
        (False, "simulate = false", "true: the simulated rig instead of hardware")] * (not simulate) + [
        (False, 'recording = "session/"', "replay a recording made by `psfd record` instead of hardware"),
        (False, "timeout = 10", "camera: seconds to wait for an answer"),
        (False, "rail_limits = { x = [-1500, 0], y = [-150, 0] }",
         "narrower soft limits than the controller's travel, mm; also the rail's axes"),
        (False, "rail_baudrate = 115200", "serial speed of the rail controller"),
        (False, "rail_feed = 1000", "rail speed, mm/min"),
        (False, "rail_timeout = 2.0", "rail: seconds to wait for an answer"),
        (False, 'settings = { iso = "100", shutterspeed = "1/125" }',
         "camera settings set before the first step (each step sets the aperture)"),
        (False, 'camera = { focus = "off", settle_s = 1.0, capture_target = "ram" }',
         "[rig.camera]: autofocus off (or manual, any), seconds to settle after a move, frames to ram or card"),
        (False, 'rail = "grbl"', 'the rail driver: "grbl", or "simulated"'),
        (False, "x_at_lens = 0", "rail X, mm, of a target at the lens (for the capture scale key)"),
        (False, "x_away = 1", "1: the target goes away from the lens as X grows; -1: as X falls"),
        (None, "the simulated rig's own keys (with simulate = true):", ""),
        (False, 'scene = "bernoulli"', '"bernoulli" (the noise target) or "texture" (a plane for two-photo)'),
        (False, "seed = 0", "image noise and texture"),
        (False, "sensor = [480, 640]", "photosites, rows and columns"),
        (False, "pitch_um = 8.0", "photosite pitch, um (MTF50 in lp/mm comes from it)"),
        (False, "focal_mm = 50.0", "focal length, mm"),
        (False, "cell_mm = 0.1", "printed size of one target cell, mm"),
        (False, "texture_mm = 240.0", "side of the textured plane, mm"),
        (False, "s = 4", "grid factor of the rendered true PSF"),
        (False, "support = 17", "side of the rendered true PSF, samples"),
        (False, "corner_aberration = 0.35", "astigmatism and coma at the image corners, waves"),
        (False, "exposure = 0.75", "fraction of the raw range that white reaches"),
        (False, f"limits = {{ {travel} }}", "its rail travel, mm"),
    ]
    if simulate:
        positions = [
            (True, f"x = [{fmt(sim.distance_for_scale())}]", "rail distances of the target, mm (a cell images to 1/4 px)"),
            (True, "y = [0]", f"lateral positions, mm; y = {json.dumps(ys)} walks a 3x3 field grid"),
            (True, "z = [0]", f"vertical positions, mm; z = {json.dumps(zs)} with it"),
            (False, "scale = [0.25]", "instead of x: channel pixels per target cell; psfd puts the rail there"),
        ]
    else:
        positions = [
            (True, "x = [-1300]", "rail positions, mm, in GRBL's work coordinates (-travel to 0 after homing, "
                                "see README): where a noise cell images to about 1/4 px"),
            (True, "y = [0]", "lateral positions, mm, that walk the target over the field, e.g. [-40, 0, 40]"),
            (False, "z = [0]", "vertical positions, mm (a rail with a Z axis)"),
            (False, "scale = [0.25]", "instead of x: channel pixels per target cell; psfd puts the rail there"),
        ]
    target = [
        (True, f'kind = "{BERNOULLI}"', f'"{BERNOULLI}" (the printed noise target) or "{TWO_PHOTO}" (two photos '
                                        'of a textured plane: give near and far, no x)'),
        (False, "near = 600", f"{TWO_PHOTO}: near distance, mm (far / near must exceed s)"),
        (False, "far = 2200", f"{TWO_PHOTO}: far distance, mm"),
        (False, "cell_mm = 0.5", f"{BERNOULLI}: printed size of one noise cell, mm (for the capture scale key)"),
        (False, 'printed = "target.pdf"', f"{BERNOULLI}: or the printed PDF, whose cell size psfd reads"),
    ]
    capture = [(True, f"apertures = {'[5.6, 11]' if simulate else '[5.6, 8, 11]'}", "f-numbers, each at every position"),
               *positions,
               (True, "channels = " + ('["g1"]' if simulate else '"all"'), '"all" or a list of ' + ", ".join(CHANNELS)),
               (True, "repeats = 1", "exposures per position and aperture")]
    estimator = [
        (False, f"s = {DEFAULT_S[BERNOULLI]}", f"super-resolution: kernel samples per pixel, 1 to 8 (default "
                                               f"{DEFAULT_S[BERNOULLI]}, {TWO_PHOTO} {DEFAULT_S[TWO_PHOTO]})"),
        (False, f"support = {4 * DEFAULT_S[BERNOULLI] + 1}", "kernel side in samples, odd (default 4 s + 1)"),
        (False, f'solver = "{DEFAULT_SOLVER}"', f"{BERNOULLI} only: {', '.join(SOLVERS)}"),
        (True, "grid = [1, 1]", "windows across and down the target, a PSF each"),
    ]
    lines = [f"# psfd measurement plan ({'simulated rig' if simulate else 'real rig'}): every key and what it means.",
             "# A line starting with # shows a default or an example: remove the # to use it.",
             "# Check it with `psfd plan check PLAN`, run it with `psfd run PLAN` (add --resume after a stop)."]
    for name, entries in (("rig", rig), ("target", target), ("capture", capture), ("estimator", estimator)):
        lines += ["", f"[{name}]"]
        for active, setting, note in entries:
            if active is None:
                lines.append(f"# {setting}")
            else:
                text = setting if active else f"# {setting}"
                lines.append(f"{text:<34}# {note}" if len(text) < 34 else f"{text}  # {note}")
    return "\n".join(lines) + "\n"
