"""A motorised rail driven by a GRBL controller over a serial port (pyserial).

The protocol kept here is the small part of GRBL 1.1 a measuring rail needs:

- the ``Grbl x.y`` banner after a soft reset (Ctrl-X) tells that the controller is alive,
- ``$H`` runs the homing cycle and answers ``ok`` when it is finished,
- ``G90 G21 G1 X.. Y.. Z.. F..`` queues an absolute move in millimetres and answers ``ok`` at once,
- ``?`` (a real-time byte, no newline) asks for a status report ``<Idle|MPos:x,y,z|...>``
  (GRBL 0.9 writes ``<Idle,MPos:x,y,z,WPos:...>``); motion is finished when the
  state is ``Idle`` at the target,
- ``error:N`` answers a refused line, ``ALARM:N`` is pushed when the machine stops.

Every exchange has a deadline, so a silent, babbling or unplugged controller
ends in a `RailError`, never a hang. Another controller (Marlin, a Thorlabs
stage...) fits in one module by implementing the same four `Rail` methods.
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass

import serial

from psfd.drivers.base import Position
from psfd.errors import RailAlarm, RailError

AXES = ("x", "y", "z")
DEFAULT_LIMITS = {"x": (0.0, 500.0)}
SOFT_RESET = b"\x18"
POSITION_TOLERANCE_MM = 0.01  # GRBL reports 3 decimals; a finished move lands within a step of the target

# GRBL 1.1 error codes (grbl/doc/csv/error_codes_en_US.csv), short meanings.
ERRORS = {
    1: "G-code word without a letter",
    2: "bad or missing numeric value",
    3: "'$' system command not recognised",
    4: "negative value where a positive one is expected",
    5: "homing cycle not enabled in settings ($22=1)",
    6: "step pulse time must be greater than 3 us",
    7: "EEPROM read failed, settings restored to defaults",
    8: "'$' command only valid when Idle",
    9: "G-code locked out during alarm or jog state",
    10: "soft limits need homing enabled",
    11: "line too long, not executed",
    12: "setting exceeds the maximum step rate",
    13: "safety door opened",
    14: "build info or startup line too long for EEPROM",
    15: "jog target exceeds machine travel",
    16: "invalid jog command",
    17: "laser mode requires PWM output",
    20: "unsupported or invalid G-code command",
    21: "more than one command of the same modal group in the block",
    22: "feed rate not set",
    23: "command requires an integer value",
    24: "two commands in the block need the axis words",
    25: "G-code word repeated in the block",
    26: "command needs axis words and none were given",
    27: "line number out of range",
    28: "command is missing a P or L value",
    29: "unsupported work coordinate system",
    30: "G53 needs G0 or G1 motion mode",
    31: "unused axis words with G80 active",
    32: "arc without axis words in the selected plane",
    33: "motion target is invalid",
    34: "arc radius definition cannot be computed",
    35: "arc offset definition missing IJK words",
    36: "unused, leftover G-code words in the block",
    37: "dynamic tool length offset on a non-configured axis",
    38: "tool number greater than the maximum supported",
}

# GRBL 1.1 alarm codes (grbl/doc/csv/alarm_codes_en_US.csv), short meanings.
ALARMS = {
    1: "hard limit triggered; position is likely lost, re-home",
    2: "soft limit: motion target exceeds machine travel; position retained",
    3: "reset while in motion; position is likely lost, re-home",
    4: "probe not in the expected initial state",
    5: "probe did not contact within the programmed travel",
    6: "homing failed: reset during the homing cycle",
    7: "homing failed: safety door opened during homing",
    8: "homing failed: could not clear the limit switch when pulling off",
    9: "homing failed: limit switch not found within the search distance",
}

_STATE = re.compile(r"<([A-Za-z]+)")
_FIELDS = {name: re.compile(name + r":(-?[\d.]+),(-?[\d.]+)(?:,(-?[\d.]+))?") for name in ("MPos", "WPos", "WCO")}


@dataclass(frozen=True)
class GrblStatus:
    """One parsed status report: machine state and work position (mm)."""

    state: str
    position: tuple[float, ...]


def parse_status(line: str, wco: tuple[float, ...] | None = None) -> tuple[GrblStatus, tuple[float, ...] | None]:
    """Parse a ``<...>`` status report of GRBL 1.1 or 0.9.

    Parameters
    ----------
    line : str
        The report, e.g. ``<Run|MPos:10.000,0.000,0.000|FS:500,0>``.
    wco : tuple of float, optional
        Work coordinate offset last reported (GRBL 1.1 sends WCO only now and then).

    Returns
    -------
    (GrblStatus, wco) with the work position (WPos, or MPos - WCO) and the WCO now in force.

    Raises
    ------
    RailError
        The line is not a status report.
    """
    state = _STATE.match(line)
    found = {name: rx.search(line) for name, rx in _FIELDS.items()}
    if state is None or (found["MPos"] is None and found["WPos"] is None):
        raise RailError(f"unreadable GRBL status report {line!r}")

    def values(match: re.Match) -> tuple[float, ...]:
        return tuple(float(v) for v in match.groups() if v is not None)

    if found["WCO"] is not None:
        wco = values(found["WCO"])
    if found["WPos"] is not None:
        position = values(found["WPos"])
    else:
        mpos = values(found["MPos"])
        offset = wco or (0.0,) * len(mpos)
        position = tuple(m - o for m, o in zip(mpos, offset))
    return GrblStatus(state.group(1), position), wco


class GrblRail:
    """`Rail` on a GRBL controller.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``/dev/ttyUSB0``.
    baudrate : int
        115200 for GRBL 1.1 (9600 for 0.8).
    timeout : float
        Seconds allowed for one exchange (a line and its ``ok``, a status report, the banner).
    limits : dict
        Soft limits per axis in mm, e.g. ``{"x": (0, 500), "y": (-50, 50)}``; the axes listed are
        the axes the rail has. Moves outside are refused before anything is sent.
    feed : float
        Feed rate of moves, mm/min.
    homing_timeout : float
        Seconds allowed for the homing cycle.
    poll : float
        Seconds between status reports while waiting for motion (GRBL recommends at most 5-10 Hz).
    """

    def __init__(
        self,
        port: str,
        baudrate: int = 115200,
        timeout: float = 2.0,
        limits: dict[str, tuple[float, float]] | None = None,
        feed: float = 1000.0,
        homing_timeout: float = 120.0,
        poll: float = 0.1,
    ) -> None:
        self.port = port
        self.timeout = float(timeout)
        self.limits = _check_limits(DEFAULT_LIMITS if limits is None else limits)
        self.feed = float(feed)
        self.homing_timeout = float(homing_timeout)
        self.poll = float(poll)
        self._wco: tuple[float, ...] | None = None
        self._buffer = b""
        # Transcript of the latest request ("> sent", "< received"), kept by recordings.
        self.exchange: list[str] = []
        try:
            # A short read timeout: the deadlines below are kept by our own loops.
            self._serial = serial.Serial(port, baudrate=baudrate, timeout=0.05, write_timeout=self.timeout)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise RailError(f"cannot open rail port {port}: {_reason(exc)}") from None
        try:
            self.banner = self._reset()
        except RailError:
            self.close()
            raise

    # ------------------------------------------------------------------ Rail protocol

    def home(self) -> Position:
        """Run the homing cycle (``$H``); returns the position after it."""
        self.exchange = []
        self._command("$H", self.homing_timeout)
        return self._position(self._status())

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None) -> Position:
        """Absolute move in mm on the axes given; returns once GRBL reports Idle at the target."""
        self.exchange = []
        target = {axis: float(v) for axis, v in zip(AXES, (x, y, z)) if v is not None}
        if not target:
            raise RailError("move needs at least one axis position")
        for axis, value in target.items():
            if axis not in self.limits:
                raise RailError(f"rail has no {axis.upper()} axis (configured axes: {self._axes_text()})")
            lo, hi = self.limits[axis]
            if not lo <= value <= hi:
                raise RailError(f"{axis.upper()}={value:g} mm is outside the soft limits [{lo:g}, {hi:g}] mm")
        start = self._status()
        words = " ".join(f"{axis.upper()}{value:.3f}" for axis, value in target.items())
        self._command(f"G90 G21 G1 {words} F{self.feed:g}", self.timeout)
        distance = max(abs(value - _axis(start.position, axis)) for axis, value in target.items())
        # Allowed time: the move at the programmed feed, twice over for acceleration, plus one exchange.
        deadline = time.monotonic() + 2.0 * 60.0 * distance / self.feed + self.timeout
        return self._wait_until_at(target, deadline)

    def position(self) -> Position:
        """Current work position."""
        self.exchange = []
        return self._position(self._status())

    def close(self) -> None:
        """Release the serial port (idempotent)."""
        port = getattr(self, "_serial", None)
        if port is not None and port.is_open:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass

    def __enter__(self) -> "GrblRail":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ exchanges

    def _reset(self) -> str:
        """Soft-reset the controller and wait for its ``Grbl x.y`` banner."""
        self._serial.reset_input_buffer()
        self._write(SOFT_RESET)
        deadline = time.monotonic() + self.timeout
        while True:
            line = self._readline(deadline, "GRBL banner after a reset")
            if line.startswith("Grbl "):
                return line

    def _command(self, line: str, seconds: float) -> list[str]:
        """Send one line and read until its ``ok``; returns the lines received before it."""
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + seconds
        received = []
        while True:
            reply = self._readline(deadline, f"'ok' to {line!r}")
            if reply == "ok":
                return received
            if reply.startswith("error:"):
                code = _code(reply)
                meaning = ERRORS.get(code, "unknown error")
                cls = RailAlarm if code == 9 else RailError
                hint = "; home the rail ($H) to clear the alarm" if code == 9 else ""
                raise cls(f"GRBL refused {line!r}: error:{code} ({meaning}){hint}")
            if reply.startswith("<"):
                self._wco = parse_status(reply, self._wco)[1]
            received.append(reply)

    def _status(self) -> GrblStatus:
        """Ask for one status report (``?``)."""
        self._write(b"?")
        deadline = time.monotonic() + self.timeout
        while True:
            reply = self._readline(deadline, "status report to '?'")
            if reply.startswith("<"):
                status, self._wco = parse_status(reply, self._wco)
                return status

    def _wait_until_at(self, target: dict[str, float], deadline: float) -> Position:
        """Poll status reports until GRBL is Idle at the target."""
        while True:
            status = self._status()
            if status.state == "Alarm":
                raise RailAlarm(f"rail stopped in ALARM state at {self._describe(status)}; home it ($H)")
            if status.state == "Door":
                raise RailError(f"rail stopped: safety door open at {self._describe(status)}")
            at_target = all(abs(_axis(status.position, a) - v) <= POSITION_TOLERANCE_MM for a, v in target.items())
            if status.state == "Idle" and at_target:
                return self._position(status)
            if time.monotonic() > deadline:
                want = ", ".join(f"{a.upper()}={v:g}" for a, v in target.items())
                raise RailError(
                    f"rail did not reach {want} mm in time: {status.state} at {self._describe(status)}"
                )
            time.sleep(self.poll)

    def _write(self, data: bytes) -> None:
        self._note("> " + ("^X" if data == SOFT_RESET else data.decode("ascii", "replace").strip()))
        try:
            self._serial.write(data)
            self._serial.flush()
        except serial.SerialTimeoutException:
            raise RailError(f"rail port {self.port}: write timed out (controller not reading)") from None
        except (serial.SerialException, OSError) as exc:
            raise RailError(f"rail port {self.port} is gone ({_reason(exc)})") from None

    def _readline(self, deadline: float, waiting_for: str) -> str:
        """Next non-empty line, ALARM pushes raised as RailAlarm; RailError at the deadline."""
        while True:
            while b"\n" not in self._buffer:
                if time.monotonic() > deadline:
                    tail = self._buffer.decode("ascii", "replace").strip()
                    seen = f" (received {tail[-60:]!r})" if tail else " (nothing received)"
                    raise RailError(f"no {waiting_for} from rail on {self.port} within {self.timeout:g} s{seen}")
                try:
                    chunk = self._serial.read(max(1, self._serial.in_waiting))
                except (serial.SerialException, OSError) as exc:
                    raise RailError(f"rail port {self.port} is gone ({_reason(exc)})") from None
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\n", 1)
            # Line noise decodes to replacement characters and is then skipped as an unknown line.
            line = raw.decode("ascii", "replace").strip()
            if line:
                self._note("< " + line)
            if line.startswith("ALARM:"):
                code = _code(line)
                raise RailAlarm(f"rail ALARM:{code} ({ALARMS.get(code, 'unknown alarm')})")
            if line:
                return line

    # ------------------------------------------------------------------ helpers

    def _note(self, text: str) -> None:
        self.exchange.append(text)
        del self.exchange[:-200]  # a long move polls many status reports: keep the latest

    def _position(self, status: GrblStatus) -> Position:
        values = {axis: (_axis(status.position, axis) if axis in self.limits else None) for axis in AXES}
        return Position(x=values["x"] if values["x"] is not None else 0.0, y=values["y"], z=values["z"])

    def _describe(self, status: GrblStatus) -> str:
        return ", ".join(f"{a.upper()}={_axis(status.position, a):g}" for a in AXES if a in self.limits)

    def _axes_text(self) -> str:
        return ", ".join(a.upper() for a in self.limits)


def _check_limits(limits: dict) -> dict[str, tuple[float, float]]:
    checked = {}
    for axis, bounds in limits.items():
        name = str(axis).lower()
        if name not in AXES:
            raise RailError(f"unknown rail axis {axis!r} in limits (use x, y, z)")
        try:
            lo, hi = (float(v) for v in bounds)
        except (TypeError, ValueError):
            raise RailError(f"limits for {name.upper()} must be two numbers (min, max), got {bounds!r}") from None
        if lo > hi:
            raise RailError(f"limits for {name.upper()}: min {lo:g} is above max {hi:g}")
        checked[name] = (lo, hi)
    if "x" not in checked:
        raise RailError("rail limits must include the X axis")
    return checked


def _axis(position: tuple[float, ...], axis: str) -> float:
    index = AXES.index(axis)
    return position[index] if index < len(position) else 0.0


def _code(line: str) -> int:
    try:
        return int(line.split(":", 1)[1])
    except ValueError:
        return -1


def _reason(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
