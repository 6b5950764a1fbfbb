"""The two protocols the daemon and the CLI depend on.

Everything above the drivers talks to a `Camera` and a `Rail`, never to
gphoto2 or pyserial, so that the simulated rig and the recordings can stand in.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable


@dataclass(frozen=True)
class CameraInfo:
    """What a camera says about itself (fields it does not report are empty)."""

    model: str
    serial: str = ""
    lens: str = ""
    focal_length_mm: float | None = None
    port: str = ""


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
    """

    controller: str
    axes: tuple[str, ...]
    travel: dict[str, tuple[float, float]]
    units: str = "mm"
    homing: bool = False
    state: str = ""


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
