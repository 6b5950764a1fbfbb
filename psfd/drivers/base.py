"""The two protocols the daemon and the CLI depend on.

Everything above the drivers talks to a `Camera` and a `Rail`, never to
gphoto2 or pyserial, so that the simulated rig and the recordings can stand in.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

from psfd.errors import BadInputError


@dataclass(frozen=True)
class CameraInfo:
    """What a camera says about itself (fields it does not report are empty)."""

    model: str
    serial: str = ""
    lens: str = ""
    focal_length_mm: float | None = None
    port: str = ""


FOCUS_RULES = ("off", "manual", "any")
CAPTURE_TARGETS = ("ram", "card")


@dataclass(frozen=True)
class CameraSetup:
    """How a camera must be set up for PSF work; `Camera.prepare` applies it before the rail moves.

    Parameters
    ----------
    raw : bool
        Shoot RAW: refuse (before any motion) a camera that cannot be set to a
        full-resolution RAW format. False only for demonstrations.
    focus : str
        ``off``: turn autofocus off where the body allows it and refuse when the
        lens or body still reports autofocus; ``manual``: as ``off``, and also
        refuse when the camera reports no focus mode at all (nothing confirms
        manual focus); ``any``: leave focus alone (a person at the bench).
    capture_target : str
        ``ram`` (default): frames go to the camera's RAM and only exist on this
        computer once downloaded; ``card``: they are written to the memory card
        first (kept on the card if the download fails).
    exposure_delay : bool
        Use the body's exposure delay (mirror up, pause, then shutter) where it
        offers one over USB.
    settle_s : float
        Seconds between the rail stopping and the shutter, for the rig's
        vibrations to die out (plan setting, default 2 s); see `settle`.
    bulb_s : float, optional
        Exposure time when the camera's shutter speed is bulb (bulb is refused without it).
    """

    raw: bool = True
    focus: str = "off"
    capture_target: str = "ram"
    exposure_delay: bool = True
    settle_s: float = 2.0
    bulb_s: float | None = None

    def __post_init__(self) -> None:
        if self.focus not in FOCUS_RULES:
            raise BadInputError(f"focus = {self.focus!r}: use one of {', '.join(FOCUS_RULES)}")
        if self.capture_target not in CAPTURE_TARGETS:
            raise BadInputError(f"capture_target = {self.capture_target!r}: use ram or card")
        if not 0.0 <= float(self.settle_s) <= 600.0:
            raise BadInputError(f"settle_s = {self.settle_s}: give seconds between 0 and 600")
        if self.bulb_s is not None and not float(self.bulb_s) > 0.0:
            raise BadInputError(f"bulb_s = {self.bulb_s}: give a positive exposure time in seconds")

    @classmethod
    def from_mapping(cls, table: Mapping[str, Any] | None) -> "CameraSetup":
        """A setup from a plan table whose keys are the field names; unknown keys are refused."""
        table = dict(table or {})
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(table) - fields)
        if unknown:
            known = ", ".join(sorted(fields))
            raise BadInputError(f"unknown camera setup key(s) {', '.join(unknown)} (known: {known})")
        try:
            return cls(**table)
        except (TypeError, ValueError) as exc:
            raise BadInputError(f"bad camera setup: {exc}") from None


@dataclass(frozen=True)
class CameraReady:
    """What `Camera.prepare` did and found: store it with the run, log the notes.

    ``image_format``, ``capture_target``, ``drive_mode`` and ``exposure_delay``
    are the camera's own values after preparation (None: the body has no such
    setting). ``focus`` is ``manual`` (the lens or body reports manual focus),
    ``af-off`` (autofocus turned off through the driver, nothing reports AF),
    ``af`` (autofocus on: only with ``focus = "any"``) or ``unknown``.
    ``files_per_exposure`` is how many files one exposure produces (2 for
    RAW+JPEG; None when the format does not tell). ``settle_s`` is the wait the
    runner applies after each move (0 for a simulated rail, which does not shake).
    """

    image_format: str | None
    files_per_exposure: int | None
    capture_target: str | None
    focus: str
    focus_detail: str
    exposure_delay: str | None
    drive_mode: str | None
    settle_s: float
    notes: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """Plain dict, for the catalogue."""
        return dataclasses.asdict(self)


def settle(seconds: float, since: float | None = None, *, sleep: Callable[[float], None] = time.sleep,
           clock: Callable[[], float] = time.monotonic) -> float:
    """Wait until ``seconds`` have passed since the rail stopped; returns the seconds waited.

    ``since`` is the `time.monotonic` reading taken when the move returned
    (default: now), so time already spent (saving the previous frame) counts.
    """
    start = clock() if since is None else float(since)
    remaining = start + float(seconds) - clock()
    if remaining > 0:
        sleep(remaining)
        return remaining
    return 0.0


def target_distance(pixels_per_cell: float, focal_mm: float, pitch_um: float, cell_mm: float) -> float:
    """Lens-to-target distance (mm) at which one printed cell images to ``pixels_per_cell`` Bayer-channel pixels.

    Thin lens: magnification m = f / (d - f), and a cell of ``cell_mm`` covers m * cell / (2 pitch) channel
    pixels (a channel samples every other photosite), so d = f (1 + cell / (p * 2 pitch)).
    """
    if not pixels_per_cell > 0:
        raise BadInputError(f"scale {pixels_per_cell}: pixels per cell must be positive")
    return focal_mm * (1.0 + cell_mm / (pixels_per_cell * 2.0 * pitch_um / 1000.0))


def cell_pixels(distance_mm: float, focal_mm: float, pitch_um: float, cell_mm: float) -> float:
    """Bayer-channel pixels one printed cell images to at lens-to-target distance ``distance_mm`` (beyond the
    focal length): the inverse of `target_distance`, m * cell / (2 pitch) with m = f / (d - f)."""
    return focal_mm / (distance_mm - focal_mm) * cell_mm / (2.0 * pitch_um / 1000.0)


@dataclass(frozen=True)
class Position:
    """Rail position in millimetres (None for an axis the rail does not have)."""

    x: float
    y: float | None = None
    z: float | None = None


@dataclass(frozen=True)
class RailInfo:
    """What a rail controller says about itself.

    ``travel`` is the reachable span per axis in mm, in the coordinates `Rail.move` takes (for a GRBL
    controller: its machine travel [-$130, 0] shifted by the work offset, narrowed by the rig's limits).
    Positions are always mm; ``units`` is what the controller itself reports in ("mm" or "inch").
    ``power_up`` is where each axis reads after the controller restarts, in the same coordinates (GRBL
    counts from machine position 0 wherever the carriage stands); None for a rail that keeps its position.
    """

    controller: str
    axes: tuple[str, ...]
    travel: dict[str, tuple[float, float]]
    units: str = "mm"
    homing: bool = False
    state: str = ""
    power_up: dict[str, float] | None = None


@runtime_checkable
class Camera(Protocol):
    """A camera that captures RAW frames to files."""

    def info(self) -> CameraInfo:
        """Model, serial number, lens and port."""
        ...

    def get(self, name: str) -> str:
        """Current value of a setting (``aperture``, ``shutterspeed``, ``iso``, ``imageformat``, ...)."""
        ...

    def choices(self, name: str) -> list[str]:
        """Values the camera offers for a setting."""
        ...

    def set(self, name: str, value: str) -> None:
        """Set a setting; a value not offered raises CameraError listing the offered ones."""
        ...

    def prepare(self, setup: CameraSetup) -> CameraReady:
        """Set the camera up for PSF work (RAW, capture target, focus, exposure delay) before any motion.

        Raises CameraError, naming what to change, when the camera cannot be set
        up as asked (no RAW, autofocus that cannot be turned off).
        """
        ...

    def capture(self, dest: Path) -> list[Path]:
        """Capture one exposure and download every file it produced into folder ``dest``."""
        ...

    def close(self) -> None:
        """Release the camera."""
        ...


@runtime_checkable
class Rail(Protocol):
    """A motorised stage with an X axis and optional Y and Z axes, in millimetres."""

    def home(self) -> Position:
        """Run the homing cycle and return the position after it."""
        ...

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None) -> Position:
        """Absolute move; returns once motion has finished."""
        ...

    def position(self) -> Position:
        """Current position."""
        ...

    def info(self) -> RailInfo:
        """Controller, axes, travel per axis, units, whether it homes, current state."""
        ...

    def unlock(self) -> Position:
        """Clear an alarm lock without homing (the position is what the controller believes)."""
        ...

    def close(self) -> None:
        """Release the port (a rail is never left moving: moves return only once motion has stopped)."""
        ...
