"""A motorised rail on a GRBL controller (grbl 1.1, grblHAL, FluidNC) over a serial port, safe by construction.

What the driver relies on is GRBL 1.1's documented interface (gnea/grbl doc/markdown/interface.md,
commands.md and the firmware source it describes):

- Realtime bytes act at once, never queued: ``?`` asks for one status report
  ``<Idle|MPos:x,y,z|FS:f,s|WCO:..>``, ``!`` is a feed hold (a controlled deceleration to ``Hold:0``),
  0x18 (Ctrl-X) a soft reset. A reset while the carriage moves, or while a hold is still decelerating
  (``Hold:1``), throws ALARM:3 and loses the position; after ``Hold:0`` it keeps the position and empties
  the planner. So every stop here is a feed hold first and a reset only once the carriage stands.
- A line (``$$``, ``$H``, ``$X``, G-code) gets ``ok`` or ``error:N``. ``ALARM:N`` is pushed when the machine
  stops by itself. After ALARM:1 (hard limit) and ALARM:2 (soft limit) the firmware prints
  ``[MSG:Reset to continue]`` after a 500 ms delay and then answers nothing but Ctrl-X (a reset sent during
  that delay is forgotten); homing failures (ALARM:6-9) and a reset in motion (ALARM:3, also from the controller's
  own reset button) are followed by the reset itself, its banner after the same delay.
- With homing enabled (``$22=1``) the controller starts locked in Alarm; ``$H`` homes it (a ``?`` during the
  cycle is answered only once it ends, as ``Home``; ``!`` and ``~`` are dropped: only a reset stops it, ALARM:6),
  ``$X`` unlocks it without homing. Homing goes to the + end unless ``$23`` says otherwise and leaves the
  machine position at -``$27``: machine space is [-``$130``, 0].
- ``$$`` gives the settings, always in mm: ``$100..`` steps/mm, ``$110..`` max rate (mm/min), ``$120..``
  acceleration (mm/s^2), ``$130..`` max travel, ``$10`` (bit 0: MPos or WPos in reports), ``$13`` (reports in
  inches), ``$20/$21/$22`` soft limits, hard limits, homing, ``$24..$27`` homing feed, seek, debounce, pull-off.

From those the driver derives, per controller: units, travel,
move deadlines (a trapezoidal profile at the axis-limited rate and acceleration, plus a margin), the
arrival tolerance (half a step plus the report resolution) and the homing deadline (a 1.5 x travel search
at ``$25`` plus the locate phases at ``$24``). psfd positions are GRBL work coordinates (``WPos = MPos - WCO``);
the travel a move is checked against before anything is sent is the machine travel shifted by the WCO,
narrowed by the ``limits`` the rig configures.

Ctrl-C, SIGTERM (which the CLI raises as an exception), a deadline, an error or a lost answer during a move
end in `_halt`: feed hold, wait for the carriage to stand, reset, and the error says where it stopped.
A banner no reset of ours asked for is a controller that restarted: in a move, or reading another machine
position than before (a power blip counts again from 0 where the carriage stands), the position is lost and
the move is refused; its reset button pressed while the carriage stands changes nothing.
A process killed outright (SIGKILL, the OOM killer) runs nothing: before the first line that can move the
carriage the driver starts a guard process (`psfd.drivers.grbl_guard`, standard library only, in its own
session, SIGINT/SIGTERM/SIGHUP/SIGQUIT/SIGABRT ignored) holding the same port. It watches this process through
a pidfd, never touches the port while it lives and is killed by `close`; when this process dies with the rail
open, it sends ``?`` and, if the carriage moves, what `_halt` sends (``!``, ``?`` until ``Hold:0``, 0x18), or
0x18 alone when this process died in a homing cycle (`_tell_guard`), then exits. A whole control group killed
at once, or a power cut of the PC, takes the guard too: the next open stops the carriage.
The port is opened exclusively (flock, pyserial ``exclusive``) behind a UUCP-style lock file naming the
holder's pid, and without a reset: DTR is left up and HUPCL cleared so that an Arduino's auto-reset
circuit sees no edge on the next open either (the README has the hardware fix).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import math
import os
import re
import signal
import subprocess
import sys
import termios
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, NoReturn

import serial

from psfd.drivers.base import Position, RailInfo
# GRBL's realtime bytes and its standing states, one definition for the driver and its guard (which imports nothing
# of psfd)
from psfd.drivers.grbl_guard import FEED_HOLD, HOMING, HOMING_DONE, SOFT_RESET, STANDING, STATUS
from psfd.errors import RailAlarm, RailError

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")
MM_PER_INCH = 25.4
BANNER = re.compile(r"^(Grbl|GrblHAL|grblHAL)\s+\S+.*\[.*help\]")

# Settings psfd falls back on when a controller's `$$` leaves one out (FluidNC answers a subset): grbl's
# own defaults (defaults.h, DEFAULTS_GENERIC).
GRBL_DEFAULTS = {10: 1, 13: 0, 20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0,
                 100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
                 120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0}
# grbl's default homing cycles (config.h HOMING_CYCLE_0/1): Z first, then X and Y together.
HOMING_CYCLES = ((2,), (0, 1))
HOMING_SEARCH_SCALAR = 1.5  # limits.c: search over 1.5 x max travel
HOMING_LOCATE_SCALAR = 5.0  # and locate over 5 x pull-off
DEADLINE_FACTOR = 1.25  # margin on a computed motion time (host latency, polling, 32-bit float rounding)
BOOT_WAIT = 2.5  # s an Arduino bootloader may hold the port after an auto-reset
READ_SLICE = 0.02  # s a read waits for a byte (fixed: changing pyserial's timeout reconfigures the tty)
# The guard process: grbl_guard imported from its folder (its bytecode cached, unlike a script run by path, which
# is compiled at every start), in an interpreter without site-packages; it needs the standard library only.
GUARD_CODE = "import sys; sys.path.insert(0, sys.argv[1]); import grbl_guard; sys.exit(grbl_guard.main(sys.argv[1:]))"
GUARD_DIR = str(Path(__file__).parent)
GUARD_WAIT = 20.0  # s an open waits for a dead process's guard to stop its carriage (a second or two, usually)

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
    1: "hard limit triggered",
    2: "soft limit: motion target exceeds machine travel",
    3: "reset while in motion",
    4: "probe not in the expected initial state",
    5: "probe did not contact within the programmed travel",
    6: "homing failed: reset during the homing cycle",
    7: "homing failed: safety door opened during homing",
    8: "homing failed: could not clear the limit switch when pulling off",
    9: "homing failed: limit switch not found within the search distance",
    10: "homing failed: the second switch of a dual-motor axis not found (self-squaring)",
}
# What a failed homing cycle asks of the user (the alarm table's own advice, and limits.c's search distances).
HOMING_FAILED = {
    7: "close the safety door",
    8: "the pull-off did not release the switch: raise $27 or check the switch and its wiring",
    9: "the search covers 1.5 x $130 (5 x $27 when locating): check the switch and its wiring, $23 (the end it "
       "homes to) and $130",
    10: "check the second switch of the dual-motor axis and its wiring",
}
# Codes above 9 are each firmware's own (grblHAL core alarms.h, FluidNC Protocol.cpp).
ALARMS_BY_FIRMWARE = {
    "grblHAL": {10: "emergency stop asserted", 11: "homing required", 12: "limit switch engaged",
                13: "probe protection triggered", 14: "spindle at speed timeout", 17: "motor fault"},
    "FluidNC": {10: "spindle control", 11: "control pin initially on", 12: "ambiguous limit switch",
                13: "hard stop", 14: "unhomed", 15: "init"},
}
# Alarms after which the position is kept (the documentation says so); every other one needs homing.
POSITION_KEPT = {2, 4, 5}
CRITICAL = {1, 2}  # the firmware answers nothing but Ctrl-X after these
# Raised with a reset (mc_reset): the system abort follows the alarm's 500 ms delay and clears a '?' asked during it
# (protocol.c, main.c), so the banner is what tells the controller is back.
RESETTING = {3, 6, 7, 8, 9}  # and grbl's own ALARM:10 (`_homing_failed`)


class PortGone(RailError):
    """The serial port vanished (cable pulled): nothing more can be sent."""


# ---------------------------------------------------------------------------------------------- parsing


@dataclass(frozen=True)
class GrblStatus:
    """One status report: state, work and machine position (mm), sub-state, current feed (mm/min)."""

    state: str
    position: tuple[float, ...]
    machine: tuple[float, ...] = ()
    sub: int | None = None
    feed: float | None = None
    pins: str = ""

    @property
    def name(self) -> str:
        """``Hold:0``, ``Door:1``, ``Idle``..."""
        return self.state if self.sub is None else f"{self.state}:{self.sub}"


_STATE = re.compile(r"<([A-Za-z]+)(?::(\d+))?")
_FIELD = re.compile(r"(MPos|WPos|WCO|FS|F|Pn):([^|,>]*(?:,[^|,>]*)*)")


def parse_status(line: str, wco: tuple[float, ...] | None = None,
                 scale: float = 1.0) -> tuple[GrblStatus, tuple[float, ...] | None]:
    """Parse a ``<...>`` status report of GRBL 1.1 (grblHAL, FluidNC) or 0.9.

    Parameters
    ----------
    line : str
        The report, e.g. ``<Run|MPos:10.000,0.000,0.000|FS:500,0>`` or ``<Idle,MPos:..,WPos:..>``.
    wco : tuple of float, optional
        Work coordinate offset last reported, mm (GRBL 1.1 sends WCO only now and then).
    scale : float
        mm per reported unit: 25.4 when the controller reports inches (``$13=1``).

    Returns
    -------
    (GrblStatus, wco) with positions in mm and the WCO now in force.

    Raises
    ------
    RailError
        The line is not a status report.
    """
    state = _STATE.match(line)
    fields: dict[str, tuple[float, ...]] = {}
    pins = ""
    for name, values in _FIELD.findall(line.replace(",MPos", "|MPos").replace(",WPos", "|WPos")):
        if name == "Pn":
            pins = values
            continue
        try:
            fields[name] = tuple(float(v) for v in values.split(",") if v != "")
        except ValueError:
            raise RailError(f"unreadable GRBL status report {line!r}") from None
    if state is None or ("MPos" not in fields and "WPos" not in fields):
        raise RailError(f"unreadable GRBL status report {line!r}")
    mm = {name: tuple(v * scale for v in values) for name, values in fields.items() if name in ("MPos", "WPos", "WCO")}
    if "WCO" in mm:
        wco = mm["WCO"]
    if "MPos" in mm and "WPos" in mm:
        machine, work = mm["MPos"], mm["WPos"]
    elif "MPos" in mm:
        machine = mm["MPos"]
        work = tuple(m - o for m, o in zip(machine, wco or (0.0,) * len(machine)))
    else:
        work = mm["WPos"]
        machine = tuple(w + o for w, o in zip(work, wco or (0.0,) * len(work)))
    rate = fields.get("FS", fields.get("F"))
    feed = rate[0] * scale if rate else None
    sub = int(state.group(2)) if state.group(2) else None
    return GrblStatus(state.group(1), work, machine, sub, feed, pins), wco


# ---------------------------------------------------------------------------------------------- timing


def move_time(delta: list[float], max_rate: list[float], accel: list[float], feed: float | None = None) -> float:
    """Seconds GRBL takes for one straight move from rest to rest.

    The planner (gnea/grbl planner.c) limits the move's rate and acceleration so that no axis exceeds its
    own (``$110..``, ``$120..``): rate = min over moving axes of max_rate_i / |u_i| for the unit vector u,
    likewise the acceleration; the programmed feed is clamped to that rate. The profile is a trapezoid
    (a triangle when the move is too short to reach the rate).

    Parameters
    ----------
    delta : list of float
        Displacement per axis, mm.
    max_rate : list of float
        ``$110..`` per axis, mm/min.
    accel : list of float
        ``$120..`` per axis, mm/s^2.
    feed : float, optional
        Programmed feed, mm/min (None: a rapid, G0).
    """
    length = math.sqrt(sum(d * d for d in delta))
    if length == 0.0:
        return 0.0
    unit = [d / length for d in delta]
    rate = min(abs(m / u) for m, u in zip(max_rate, unit) if u) / 60.0
    if feed:
        rate = min(rate, feed / 60.0)
    a = min(abs(m / u) for m, u in zip(accel, unit) if u)
    if length >= rate * rate / a:
        return length / rate + rate / a
    return 2.0 * math.sqrt(length / a)


def homing_time(settings: dict[int, float], cycles: tuple[tuple[int, ...], ...] = HOMING_CYCLES) -> float:
    """Worst-case seconds of ``$H``: per cycle a search over 1.5 x ``$13x`` at ``$25``, two pull-offs of ``$27``
    at ``$25``, a locate over 5 x ``$27`` at ``$24``, each from rest, and four debounce delays (``$26``).

    The firmware alarms (ALARM:9) when the search runs out, so this bounds a cycle that can still succeed.
    The planner caps a homing motion like any other (planner.c): no axis of the cycle faster than its ``$11x``
    nor accelerating harder than its ``$12x``, whatever ``$25`` and ``$24`` ask.
    """
    pull = settings[27]
    total = 0.0
    for axes in cycles:
        accel = min(settings[120 + i] for i in axes)
        cap = min(settings[110 + i] for i in axes)
        seek, slow = min(settings[25], cap), min(settings[24], cap)
        search = HOMING_SEARCH_SCALAR * max(settings[130 + i] for i in axes)

        def leg(distance: float, rate: float) -> float:
            return move_time([distance], [rate], [accel])
        total += leg(search, seek) + 2 * leg(pull, seek) + leg(HOMING_LOCATE_SCALAR * pull, slow)
        total += 4 * settings[26] / 1000.0
    return total


# ---------------------------------------------------------------------------------------------- locking


def lock_dir() -> Path | None:
    """Where port lock files live: ``$PSFD_LOCK_DIR``, else /run/lock (FHS; minicom and cu look there too).

    None when it cannot be written (a sandboxed service without ``ReadWritePaths=/run/lock``, a distribution
    keeping it for group lock): the device's own flock still keeps a second psfd process out.
    """
    configured = os.environ.get("PSFD_LOCK_DIR")
    for candidate in ([configured] if configured else ["/run/lock", "/var/lock"]):
        if os.path.isdir(candidate) and os.access(candidate, os.W_OK):
            return Path(candidate)
    return None


class PortLock:
    """``LCK..<device>`` lock file for a serial device: flock'ed while held, holding the holder's pid.

    The UUCP naming and pid format (ten characters and a newline) let programs such as minicom see it; a
    file left by a dead process, or naming a live process that does not hold the device, is taken over.
    """

    def __init__(self, port: str) -> None:
        self.port = port
        self.device = os.path.realpath(port)
        name = self.device[len("/dev/"):] if self.device.startswith("/dev/") else self.device.lstrip("/")
        folder = lock_dir()
        self.path = folder / ("LCK.." + name.replace("/", "_")) if folder else None
        self._fd: int | None = None
        self._owned = False

    def acquire(self) -> None:
        for _ in range(5):
            fd, writable = self._open()
            if fd is None:
                log.debug("no lock file for %s: relying on the device's own lock", self.port)
                return
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                pid = _read_pid(fd) or _flock_holder(str(self.path))
                os.close(fd)
                raise RailError(f"rail {self.port} in use by {_describe_pid(pid)}") from None
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:  # the previous holder removed the file between our open and flock
                os.close(fd)
                continue
            other = _read_pid(fd)
            if other and other != os.getpid() and _holds_device(other, self.device):
                os.close(fd)  # a UUCP lock of a program that does not flock (minicom, cu)
                raise RailError(f"rail {self.port} in use by {_describe_pid(other)}")
            if writable:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{os.getpid():10d}\n".encode(), 0)
            self._fd, self._owned = fd, writable
            return
        raise RailError(f"cannot lock rail port {self.port} ({self.path} keeps changing)")

    def release(self) -> None:
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            if self._owned and os.fstat(fd).st_ino == os.stat(self.path).st_ino:
                os.unlink(self.path)
        except OSError:
            pass
        finally:
            os.close(fd)

    def _open(self) -> tuple[int | None, bool]:
        """The lock file, created if need be; read-only when another user's file is in the way."""
        if self.path is None:
            return None, False
        try:
            return os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644), True
        except OSError:
            pass
        try:
            return os.open(self.path, os.O_RDONLY), False
        except OSError:
            return None, False


def _read_pid(fd: int) -> int | None:
    try:
        return int(os.pread(fd, 64, 0).split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _holds_device(pid: int, device: str) -> bool:
    """Whether process ``pid`` has ``device`` open (assume so when /proc will not tell)."""
    try:
        fds = os.listdir(f"/proc/{pid}/fd")
    except FileNotFoundError:
        return False
    except OSError:
        return True
    for fd in fds:
        try:
            if os.readlink(f"/proc/{pid}/fd/{fd}") == device:
                return True
        except OSError:
            continue
    return False


def _flock_holder(device: str) -> int | None:
    """pid holding a flock on ``device``, from /proc/locks (``... FLOCK ... <pid> MAJ:MIN:INODE ...``)."""
    try:
        st = os.stat(device)
        with open("/proc/locks") as locks:
            for line in locks:
                parts = line.split()
                if len(parts) >= 6 and parts[1] == "FLOCK":
                    major, minor, inode = parts[5].split(":")
                    if (int(inode) == st.st_ino and int(major, 16) == os.major(st.st_dev)
                            and int(minor, 16) == os.minor(st.st_dev)):
                        return int(parts[4])
    except (OSError, ValueError):
        pass
    return None


def _describe_pid(pid: int | None) -> str:
    if pid is None:
        return "another process"
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            command = f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        command = ""
    return f"pid {pid} ({command[:80]})" if command else f"pid {pid}"


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Hold SIGINT and SIGTERM back while a stop sequence runs: a second Ctrl-C must not cut it short."""
    held = {signal.SIGINT, signal.SIGTERM}
    try:
        previous = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    except (AttributeError, OSError, ValueError):
        previous = None
    try:
        yield
    finally:
        if previous is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, previous)


# ---------------------------------------------------------------------------------------------- the driver


class GrblRail:
    """`Rail` on a GRBL controller.

    Parameters
    ----------
    port : str
        Serial device, e.g. ``/dev/ttyUSB0`` or ``/dev/psfd-rail``.
    baudrate : int
        115200 for GRBL 1.1 (grblHAL and FluidNC on native USB ignore it).
    timeout : float
        Seconds allowed for one exchange (a line and its ``ok``, a status report, the banner after a reset).
    limits : dict, optional
        ``{"x": (lo, hi), ...}`` in mm: the axes the rail has (default: X only) and, optionally, a narrower
        range than the controller's travel. Moves outside either are refused before anything is sent.
    feed : float, optional
        Feed of moves, mm/min; default: rapids at the controller's max rates (``$110..``).
    homing_timeout : float, optional
        Seconds allowed for ``$H``; default: derived from ``$25``, ``$24``, ``$27`` and ``$130..``.
    poll : float
        Seconds between status reports while waiting for motion (GRBL recommends at most 5-10 Hz).
    boot_wait : float
        Seconds a controller may take to answer after the port opens (an Arduino bootloader after an
        auto-reset).
    """

    def __init__(self, port: str, baudrate: int = 115200, timeout: float = 2.0,
                 limits: dict[str, tuple[float, float]] | None = None, feed: float | None = None,
                 homing_timeout: float | None = None, poll: float = 0.1, boot_wait: float = BOOT_WAIT) -> None:
        self.port = port
        self.timeout = float(timeout)
        self.feed = float(feed) if feed else None
        self.poll = float(poll)
        self.boot_wait = float(boot_wait)
        self._configured = _check_limits(limits)
        self._homing_timeout = homing_timeout
        self.exchange: list[str] = []  # the latest request's serial lines ("> sent", "< received"), for recordings
        self.banner = ""
        self.version = ""
        self.firmware = ""
        self.options = ""
        self.settings: dict[int, float] = {}
        self.rebooted = False
        self._wco: tuple[float, ...] | None = None
        self._buffer = b""
        self._moving = False
        self._alarmed = False
        self._restarted = False  # a banner came that no reset of ours asked for
        self._last: GrblStatus | None = None  # the latest status report
        self._serial: serial.Serial | None = None
        self._guard: subprocess.Popen | None = None
        self._guard_owner = os.getpid()
        self._guard_notes: int | None = None  # the write end of the pipe that tells the guard what we are doing
        self._lock = PortLock(port)
        self._lock.acquire()
        try:
            self._serial = _open_port(port, baudrate, self.timeout)
            self._connect()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ Rail protocol

    @property
    def axes(self) -> tuple[str, ...]:
        """Axes the rail moves."""
        return tuple(self.travel)

    @property
    def units(self) -> str:
        """Units the controller reports in (``$13``); positions psfd returns are always mm."""
        return "inch" if self._scale != 1.0 else "mm"

    def info(self) -> RailInfo:
        """Controller, axes, travel (mm, in the coordinates `move` takes), units, homing, state, and the
        power-up position: machine position 0 (grbl main.c clears sys_position at boot), less the work offset."""
        self.exchange = []
        status = self._status()
        wco = self._wco or ()
        power_up = {axis: 0.0 - wco[AXES.index(axis)] if AXES.index(axis) < len(wco) else 0.0 for axis in self.travel}
        return RailInfo(controller=self.banner or self.firmware, axes=self.axes, travel=dict(self.travel),
                        units=self.units, homing=self._homing_enabled, state=status.name, power_up=power_up)

    def home(self) -> Position:
        """Run the homing cycle (``$H``); returns the position after it (GRBL: -``$27`` in machine coordinates)."""
        self.exchange = []
        if not self._homing_enabled:
            raise RailError(f"homing cycle not enabled in the controller's settings ($22=0): "
                            f"{self._known_position()}, or fit homing switches and set $22=1")
        self._make_ready("home", allow_alarm=True)
        self._ensure_guard()
        seconds = self._homing_timeout or homing_time(self._settings_full) * DEADLINE_FACTOR + self.timeout + 1.0
        self._moving = True
        self._tell_guard(HOMING)
        try:
            self._command("$H", seconds, what=f"'ok' to '$H' (the homing cycle; {seconds:.0f} s allowed from "
                                              f"$130, $25, $24, $27 and $110)")
        except BaseException as exc:
            if self._moving:
                self._moving = False
                # A homing cycle ignores feed holds: only a reset stops it (ALARM:6, position lost).
                stopped = self._reset_in_motion()
                if isinstance(exc, RailError):
                    raise type(exc)(f"{exc}; homing stopped by a reset ({stopped}): the position is lost, "
                                    f"homing needed") from None
                exc.add_note(f"homing stopped by a reset ({stopped}): the position is lost")
            raise
        finally:
            self._tell_guard(HOMING_DONE)
        self._moving = False
        return self._position(self._status())

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None) -> Position:
        """Absolute move in mm; returns once GRBL reports Idle at the target, within one step.

        Raises
        ------
        RailError
            Axis missing or target outside the travel (nothing sent); the controller locked, held, its
            door open, a deadline passed, no answer: the carriage has been stopped and the message says where.
        RailAlarm
            The controller threw an alarm during the move.
        """
        self.exchange = []
        target = self._target({"x": x, "y": y, "z": z})
        status = self._make_ready("move")
        start = {axis: self._axis(status.position, axis) for axis in target}
        delta = [target.get(axis, start.get(axis, 0.0)) - start.get(axis, 0.0) for axis in AXES]
        expected = move_time(delta, self._axis_settings(110), self._axis_settings(120), self.feed)
        allowed = expected * DEADLINE_FACTOR + 1.0 + self.timeout + 2 * self.poll
        words = " ".join(f"{axis.upper()}{value:.4f}" for axis, value in target.items())
        line = f"G90 G21 G1 {words} F{self.feed:g}" if self.feed else f"G90 G21 G0 {words}"
        self._ensure_guard()
        self._moving = True
        try:
            self._command(line, self.timeout)
            status = self._wait_arrival(target, allowed, expected)
        except BaseException as exc:
            if not self._moving:
                raise
            # a port that is gone takes no feed hold: the board goes on with what it was sent
            stopped = ("the carriage may still be moving: the next psfd command that opens the port stops it"
                       if isinstance(exc, PortGone) else self._halt())
            if isinstance(exc, RailError):
                raise type(exc)(f"{exc}; {stopped}") from None
            exc.add_note(stopped)
            raise
        self._moving = False
        return self._position(status)

    def position(self) -> Position:
        """Current work position."""
        self.exchange = []
        return self._position(self._status())

    def unlock(self) -> Position:
        """Clear an alarm lock without homing (``$X``); the position is what the controller believes."""
        self.exchange = []
        status = self._status()
        if status.state != "Alarm":
            return self._position(status)
        self._command("$X", self.timeout)
        log.warning("rail %s unlocked without homing: positions are where the controller believes it is", self.port)
        return self._position(self._status())

    def close(self) -> None:
        """Release the serial port and the lock (idempotent); the guard leaves without touching the port."""
        self._stop_guard()
        port, self._serial = self._serial, None
        if port is not None:
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass
        self._lock.release()

    def __enter__(self) -> "GrblRail":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ the guard process

    def _ensure_guard(self) -> None:
        """Before a line that can move the carriage: start the process that stops it if this one dies with the
        port open (`grbl_guard`), or keep the one running.

        Nothing in a process killed by SIGKILL runs, and the controller goes on with its move: a separate
        process holding the same port watches this one through a pidfd (a pipe would stay open in the forked
        estimation workers) and, on its death, sends the feed hold and the reset `_halt` would have sent, or the
        reset alone when a pipe from this process last said a homing cycle runs (`_tell_guard`): the cycle answers
        no ``?`` and ignores the feed hold, which would only delay the reset by the worst-case deceleration.
        fork+exec (subprocess) is safe with the service's threads; its own session keeps a terminal's Ctrl-C
        away from it, and it ignores SIGTERM, so `systemctl stop` leaves the stop to this process. Started at
        the first motion rather than at the open: the carriage stands until then, and commands that only read
        the rail (`psfd rail position`) do not pay for a second interpreter (~20 ms of a 2-core machine).
        """
        guard = self._guard
        if guard is not None and self._guard_owner == os.getpid():
            if guard.poll() is None:
                return
            log.warning("rail %s: the guard process (pid %d) ended (%s): starting another", self.port, guard.pid,
                        guard.returncode)
        self._guard = None
        self._close_guard_notes()
        if self._serial is None or not sys.executable:
            return
        try:
            owner = os.pidfd_open(os.getpid())
        except (AttributeError, OSError) as exc:  # Linux before 5.3
            log.warning("rail %s: no guard process (%s): a process killed mid-move leaves the carriage running "
                        "until the next psfd command opens the port", self.port, _reason(exc))
            return
        notes = None
        try:
            fd = self._serial.fileno()
            notes, self._guard_notes = os.pipe()
            self._guard = subprocess.Popen(
                [sys.executable, "-I", "-S", "-c", GUARD_CODE, GUARD_DIR, str(fd), str(owner), f"{self.timeout:g}",
                 f"{self._stop_time():.3f}", str(notes)],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, pass_fds=(fd, owner, notes),
                start_new_session=True)
            self._guard_owner = os.getpid()
        except OSError as exc:
            log.warning("rail %s: cannot start the guard process (%s)", self.port, _reason(exc))
            self._close_guard_notes()
        finally:
            os.close(owner)
            if notes is not None:
                os.close(notes)

    def _tell_guard(self, doing: bytes) -> None:
        """Tell the guard what this process does now (`grbl_guard.HOMING`, `grbl_guard.HOMING_DONE`); it reads the
        pipe as it comes, so the pipe never fills."""
        if self._guard_notes is None or self._guard_owner != os.getpid():
            return
        try:
            os.write(self._guard_notes, doing)
        except OSError:  # the guard has gone: `_ensure_guard` starts another before the next motion
            pass

    def _close_guard_notes(self) -> None:
        notes, self._guard_notes = self._guard_notes, None
        if notes is not None and self._guard_owner == os.getpid():
            os.close(notes)

    def _stop_guard(self) -> None:
        """End the guard of a rail being closed, and reap it (not from a forked child: it is its parent's).

        SIGKILL, not a message it would read once started: the guard never touches the port while this process
        lives, so it has nothing to finish, and a short command does not wait for its start-up (~30 ms). Our
        own child, not yet reaped: its pid cannot have been reused.
        """
        guard, self._guard = self._guard, None
        if guard is None or self._guard_owner != os.getpid():
            return
        guard.kill()
        guard.wait()
        self._close_guard_notes()

    # ------------------------------------------------------------------ connecting

    def _connect(self) -> None:
        """Find the controller's state without resetting it, read ``$$``, ``$I`` and the WCO, settle the travel."""
        status = self._probe()
        if status.state in ("Run", "Jog"):
            log.warning("rail %s was moving when opened (a process stopped mid-move): stopping it", self.port)
            self._halt()
        elif status.state == "Hold" or status.name == "Door:0" or status.state in ("Sleep", "Check"):
            self._halt()  # Hold:0 with moves queued, or a mode only a reset leaves: no motion, position kept
        elif status.state == "Home":
            raise RailError(f"rail {self.port} is running a homing cycle started elsewhere: wait for it to end")
        elif status.state == "Door":
            raise RailError(f"rail {self.port}: safety door open ({status.name}); close it and try again")
        lines = self._command("$$", self.timeout)
        self.settings = {int(m.group(1)): float(m.group(2)) for m in map(_SETTING.match, lines) if m}
        self._settings_full = {**GRBL_DEFAULTS, **self.settings}
        missing = sorted(n for n in (13, 22, 110, 120, 130) if n not in self.settings)
        if missing:
            log.info("rail %s: `$$` has no %s; using grbl's defaults", self.port, ", ".join(f"${n}" for n in missing))
        self._scale = MM_PER_INCH if self._settings_full[13] else 1.0
        info = self._command("$I", self.timeout)
        self._check_work_origin(self._check_startup_lines())
        self.version = next((ln[5:-1].split(":")[0] for ln in info if ln.startswith("[VER:")), "")
        self.options = next((ln[5:-1] for ln in info if ln.startswith("[OPT:")), "")
        if "[FIRMWARE:grblHAL]" in info:
            self.firmware = f"grblHAL {self.version}"
        elif "FluidNC" in self.version:
            self.firmware = self.version[self.version.index("FluidNC"):]
        else:
            self.firmware = f"Grbl {self.version}".strip()
        status = self._status_with_wco()
        self.travel = self._travel(len(status.machine))

    def _check_startup_lines(self) -> list[str]:
        """Refuse a controller whose startup lines (``$N0``, ``$N1``) move the carriage or shift its coordinates;
        returns the lines.

        GRBL runs them after every reset that ends Idle (protocol.c, system_execute_startup) and after every
        completed ``$H`` (system.c), and psfd resets the controller after every stop: a line with an axis word
        (G0 X10, G92 X0, G10 L20 X0) or a move to a stored position (G28, G30) would move the carriage
        unattended, or shift every position after it.
        """
        try:
            lines = self._command("$N", self.timeout)
        except RailError as exc:  # a firmware without startup lines (FluidNC keeps its own in a file)
            log.debug("rail %s: no startup lines (%s)", self.port, exc)
            return []
        startup = []
        for number, text in (m.groups() for m in map(_STARTUP_LINE.match, lines) if m):
            code = re.sub(r"\(.*?\)|;.*", "", text.upper())
            if _MOVES.search(code):
                raise RailError(f"rail {self.port}: the controller's startup line $N{number}={text} runs after every "
                                f"reset, which psfd sends after every stop, and would move the carriage or shift its "
                                f"coordinates: clear it (send `$N{number}=` from a terminal)")
            startup.append(code)
        return startup

    def _check_work_origin(self, startup: list[str]) -> None:
        """Refuse work coordinates that the resets psfd sends after every stop would move.

        A reset clears the G92 offsets and selects G54, then the startup lines run (grbl gc_init, protocol.c):
        a G92 offset, or another coordinate system selected by hand, would put every position after the
        first stop elsewhere on the rail than the same position before it, under the same name in the
        catalogue. The offsets of G54-G59 themselves are kept in EEPROM (G10 L2 / L20) across resets.
        """
        try:
            modes = " ".join(self._command("$G", self.timeout))
            offsets = {m.group(1): [float(v) * self._scale for v in m.group(2).split(",")]
                       for m in map(_OFFSET.match, self._command("$#", self.timeout)) if m}
        except RailError as exc:  # a firmware that does not report them: nothing to compare
            log.debug("rail %s: no work coordinate report (%s)", self.port, exc)
            return
        axes = [AXES.index(axis) for axis in self._configured]

        def shown(values: list[float]) -> str:
            return ", ".join(f"{AXES[i].upper()}={values[i]:g}" for i in axes if i < len(values))

        g92 = offsets.get("G92", [])
        if any(abs(g92[i]) > 1e-6 for i in axes if i < len(g92)):
            raise RailError(f"rail {self.port}: a G92 offset is active ({shown(g92)} mm): GRBL clears it at every "
                            "reset, which psfd sends after every stop, and the positions after one would lie "
                            "elsewhere: clear it (send `G92.1`) and set the work zero with `G10 L20 P1` instead "
                            "(kept across resets)")
        active = next(iter(_SYSTEM.findall(modes)), "G54")
        restored = ([code for line in startup for code in _SYSTEM.findall(line)] or ["G54"])[-1]
        now, then = offsets.get(active, []), offsets.get(restored, [])
        if any(abs(now[i] - then[i]) > 1e-6 for i in axes if i < min(len(now), len(then))):
            raise RailError(f"rail {self.port}: work coordinates {active} are active, but a reset, which psfd sends "
                            f"after every stop, selects {restored} ({shown(then)} mm against {shown(now)} mm): send "
                            f"`{restored}`, or make {active} the startup system (`$N0={active}`)")

    def _probe(self) -> GrblStatus:
        """A status report, asking with ``?`` (and ``$I`` for boards that wait for a line); reset only if deaf."""
        started = time.monotonic()
        deadline = started + max(self.boot_wait, self.timeout)
        next_ask = 0.0
        line_sent = answer_due = False
        status = None
        while time.monotonic() < deadline and (status is None or answer_due):
            now = time.monotonic()
            if now >= next_ask and status is None:
                self._write(STATUS)
                next_ask = now + 0.25
            if not line_sent and now - started > 0.75:
                self._write(b"$I\n")  # some boards stay silent until they have received a whole line
                line_sent = answer_due = True
            line = self._read_line(min(next_ask, deadline) if status is None else deadline)
            if line is None:
                continue
            if BANNER.match(line):
                self.banner = line
                self.rebooted = True
                answer_due = False  # a reset empties the input buffer: the $I, if sent, is gone
                deadline = max(deadline, time.monotonic() + self.timeout)
                log.warning("rail %s rebooted when its port was opened (Arduino auto-reset): its position restarted "
                            "at 0; see the README for the capacitor that prevents it", self.port)
            elif line.startswith("<"):
                status, self._wco = parse_status(line, self._wco, self._scale)
            elif line == "ok" or line.startswith("error:"):
                answer_due = False
        if status is not None:
            return status
        # Nothing at all: deaf after a critical alarm (only Ctrl-X is heard), or hung. Resetting a controller
        # that says nothing is the one way left to find out.
        log.warning("rail %s answers neither '?' nor '$I': resetting it", self.port)
        self._reset()
        return self._status()

    def _status_with_wco(self) -> GrblStatus:
        """Status reports until one carries the WCO (GRBL 1.1 sends it every 10 to 30 reports)."""
        self._wco = None
        for _ in range(32):
            status = self._status()
            if self._wco is not None:
                return status
        log.info("rail %s reports no WCO: work coordinates taken as machine coordinates", self.port)
        self._wco = (0.0,) * len(status.machine)
        return self._status()

    def _travel(self, n_axes: int) -> dict[str, tuple[float, float]]:
        """Per rail axis, the reachable span in work coordinates: machine travel - WCO, narrowed by the config."""
        force_origin = "Z" in self.options.split(",")[0]  # HOMING_FORCE_SET_ORIGIN compiled in
        travel = {}
        for axis, (lo_cfg, hi_cfg) in self._configured.items():
            index = AXES.index(axis)
            if index >= n_axes:
                raise RailError(f"rail_limits name axis {axis.upper()} but the controller on {self.port} has "
                                f"{n_axes} axes")
            length = self._settings_full[130 + index]
            homes_to_minus = bool(int(self._settings_full[23]) & (1 << index))
            if force_origin and homes_to_minus:
                lo, hi = 0.0, length
            else:
                lo, hi = -length, 0.0  # GRBL's machine space is negative, whichever end it homes to
                if self._homing_enabled and self._settings_full[21]:
                    # the homed end is where its switch closed (grbl limits.c sets the position to -$27 after
                    # the pull-off, $27 - $130 homing to the - end): a move back to it closes the switch, ALARM:1
                    pulloff = self._settings_full[27]
                    lo, hi = (lo + pulloff, hi) if homes_to_minus else (lo, hi - pulloff)
            offset = self._wco[index] if self._wco and index < len(self._wco) else 0.0
            lo, hi = lo - offset, hi - offset
            if lo_cfg is not None:
                if min(hi, hi_cfg) <= max(lo, lo_cfg):  # no room left to move in
                    raise RailError(
                        f"rail_limits {axis.upper()}=[{lo_cfg:g}, {hi_cfg:g}] mm lie outside the controller's travel "
                        f"[{lo:g}, {hi:g}] mm (${130 + index}={length:g}, work offset {offset:g}; GRBL's machine "
                        f"coordinates are negative after homing to the + end)")
                lo, hi = max(lo, lo_cfg), min(hi, hi_cfg)
            travel[axis] = (lo, hi)
        return travel

    # ------------------------------------------------------------------ motion

    def _target(self, wanted: dict[str, float | None]) -> dict[str, float]:
        target = {axis: float(v) for axis, v in wanted.items() if v is not None}
        if not target:
            raise RailError("move needs at least one axis position")
        for axis, value in target.items():
            if axis not in self.travel:
                axes = ", ".join(a.upper() for a in self.axes)
                raise RailError(f"rail has no {axis.upper()} axis (its axes: {axes})")
            lo, hi = self.travel[axis]
            if not math.isfinite(value) or not lo <= value <= hi:
                raise RailError(f"{axis.upper()}={value:g} mm is outside the rail's travel [{lo:g}, {hi:g}] mm")
        return target

    def _make_ready(self, doing: str, allow_alarm: bool = False) -> GrblStatus:
        """The controller's state, checked before any line that moves it is sent."""
        status = self._status()
        if status.state == "Alarm" and not allow_alarm:
            raise RailAlarm(f"rail is locked in ALARM at {self._where(status)}: {self._alarm_advice(None)}")
        if status.state == "Door":
            raise RailError(f"cannot {doing}: the safety door is open ({status.name}) at {self._where(status)}")
        if status.state in ("Hold", "Sleep", "Check"):
            log.warning("rail %s found in %s before %s: clearing it", self.port, status.name, doing)
            self._halt()
            status = self._status()
        if status.state not in ("Idle", "Alarm"):
            raise RailError(f"cannot {doing}: the rail is busy ({status.name}) at {self._where(status)}")
        return status

    def _wait_arrival(self, target: dict[str, float], allowed: float, expected: float) -> GrblStatus:
        """Status reports until Idle at the target; a hold, a door, an alarm or the deadline end it at once."""
        deadline = time.monotonic() + allowed
        idle_elsewhere = 0
        want = ", ".join(f"{a.upper()}={v:g}" for a, v in target.items())
        while True:
            status = self._status()
            if status.state == "Idle":
                if all(abs(self._axis(status.position, a) - v) <= self._tolerance(a) for a, v in target.items()):
                    self._moving = False
                    return status
                idle_elsewhere += 1  # the report may come before the cycle starts; three in a row is a stop
                if idle_elsewhere >= 3:
                    self._moving = False
                    raise RailError(f"rail stopped at {self._where(status)} short of {want} mm")
            elif status.state == "Hold":
                raise RailError(f"rail feed hold ({status.name}) at {self._where(status)} during the move to "
                                f"{want} mm: the move is cancelled")
            elif status.state == "Door":
                raise RailError(f"safety door opened during the move to {want} mm ({status.name})")
            elif status.state == "Alarm":
                self._moving = False
                self._on_alarm(None, f"during the move to {want} mm")
            elif status.state not in ("Run", "Jog"):
                raise RailError(f"rail in unexpected state {status.name} during the move to {want} mm")
            if time.monotonic() > deadline:
                raise RailError(f"rail did not reach {want} mm within {allowed:.1f} s (the move takes "
                                f"{expected:.1f} s at the controller's $110/$120): {status.name} at "
                                f"{self._where(status)}")
            time.sleep(self.poll)

    def _halt(self) -> str:
        """Feed hold, wait for the carriage to stand, then reset to empty the planner; where it stopped."""
        self._moving = False
        self._ensure_guard()  # a move found at the open: this process may die while it stops it
        with _signals_deferred():
            try:
                self._write(FEED_HOLD)
            except PortGone as exc:
                return f"the carriage may still be moving ({exc})"
            started = time.monotonic()
            stop = self._stop_time()
            status: GrblStatus | None = None
            heard = False
            while True:
                try:
                    status = self._status(min(self.timeout, 0.5))
                    heard = True
                except PortGone as exc:
                    return f"the carriage may still be moving ({exc})"
                except RailAlarm as alarm:
                    return f"the controller stopped it: {alarm}"
                except RailError:
                    status = None
                # standing: check mode and sleep ignore the feed hold (protocol.c) and move nothing
                if status is not None and (status.state in STANDING or status.name in ("Hold:0", "Door:0", "Door:1")):
                    break
                waited = time.monotonic() - started
                # Silent: once the worst-case deceleration has run out, reset blind. Answering but still
                # decelerating (slower than its settings say): keep waiting, a reset now would lose the position.
                if waited > stop + self.timeout and (status is None or waited > 4 * stop + 3 * self.timeout):
                    break
                if status is not None:
                    time.sleep(min(self.poll, 0.05))
            if status is not None and status.state == "Alarm":
                return f"rail stopped in ALARM at {self._where(status)}"
            try:
                self._reset(attempts=1)
                after = self._status()
            except RailError:
                if heard and status is not None:
                    return f"rail stopped at {self._where(status)}, then stopped answering"
                return ("the controller stopped answering: feed hold and reset sent, position unknown "
                        f"({self._known_position()})")
            return f"rail stopped at {self._where(after)}"

    def _reset_in_motion(self) -> str:
        """Reset now (homing ignores feed holds); returns the state afterwards (the position a homing cycle
        leaves is the count of its interrupted phase, limits.c: not shown)."""
        with _signals_deferred():
            try:
                self._reset()
                status = self._status()
            except RailError as exc:
                return f"no answer after the reset: {exc}"
            return status.name

    def _stop_time(self) -> float:
        """Worst case to decelerate from the fastest rate at the lowest acceleration of the rail's axes."""
        if not self.settings:
            return 30.0  # not read yet (a move left running by another process): wait while it decelerates
        indices = [AXES.index(a) for a in self.travel] or [0]
        rate = max(self._settings_full[110 + i] for i in indices) / 60.0
        if self.feed:
            rate = min(rate, self.feed / 60.0)
        return rate / min(self._settings_full[120 + i] for i in indices) + 0.5

    # ------------------------------------------------------------------ alarms

    def _on_alarm(self, code: int | None, during: str) -> NoReturn:
        """The controller threw an alarm: bring it back to talking (a reset if it went deaf), then raise."""
        self._alarmed = True  # alarm lines that follow (a firmware's own boot alarm) are part of this one
        try:
            status = self._recover(code)
        finally:
            self._alarmed = False
        meaning = self._alarm_meaning(code) if code is not None else "locked"
        text = f"ALARM:{code} ({meaning})" if code is not None else "ALARM"
        # a failed homing cycle leaves the count of its interrupted phase (limits.c): no position to show
        where = ", the position is lost" if self._homing_failed(code) else f" at {self._where(status)}"
        advice = self._alarm_advice(code)
        switches = "".join(c for c in status.pins if c in "XYZABC")
        if switches:
            advice += f"; limit switch {switches} still pressed: free the carriage first"
        raise RailAlarm(f"rail {' '.join(filter(None, (text, during)))}{where}; {advice}")

    def _alarm_advice(self, code: int | None) -> str:
        """What to do after alarm ``code`` (None: found locked in Alarm)."""
        if self._homing_failed(code) and code in HOMING_FAILED:
            return f"{HOMING_FAILED[code]}, then `psfd rail home` again"
        kept = "the position was kept: `psfd rail unlock` is enough"
        if code in POSITION_KEPT:
            return f"{self._known_position()} ({kept})" if self._homing_enabled else kept
        if self._homing_enabled:
            return self._known_position() + (
                ", or `psfd rail unlock` if the position is known to be right" if code is None else "")
        # `psfd rail home` would only be refused: the position the controller counts, or the + end at power-up
        return ("`psfd rail unlock` (homing is disabled, $22=0) goes on from the position the controller counted, "
                f"which may be off by lost steps; to start from a known one, {self._known_position()}")

    def _homing_failed(self, code: int | None) -> bool:
        """ALARM:6-9, and 10 on grbl itself (grblHAL and FluidNC number their own alarms from 10 on)."""
        return code is not None and (6 <= code <= 9 or (code == 10 and self._alarm_firmware() == ""))

    def _known_position(self) -> str:
        """How to get a known position back: home, or without homing the + end at power-up (main.c clears the
        machine position at power-up only: a reset, its button or Ctrl-X, keeps the count)."""
        if self._homing_enabled:
            return "homing needed: `psfd rail home`"
        return "move the carriage by hand to the + end and power-cycle the controller"

    def _recover(self, code: int | None) -> GrblStatus:
        if code in CRITICAL:
            # The firmware prints [MSG:Reset to continue] 500 ms after the alarm and forgets a reset sent
            # before it; only then does Ctrl-X bring it back.
            self._wait_for(lambda ln: "Reset to continue" in ln, self.timeout)
            self._reset()
        elif code in RESETTING or self._homing_failed(code):
            self._wait_for(lambda ln: bool(BANNER.match(ln)), self.timeout)
            self._drain(0.2, watch=False)
        else:
            self._drain(0.2, watch=False)
        return self._status()

    def _alarm_meaning(self, code: int) -> str:
        return ALARMS_BY_FIRMWARE.get(self._alarm_firmware(), {}).get(code) or ALARMS.get(code, "unknown alarm")

    def _alarm_firmware(self) -> str:
        """"grblHAL", "FluidNC" (whose alarms above 9 are their own), or "" for grbl itself."""
        name = f"{self.banner} {self.firmware}"
        return "grblHAL" if "grblhal" in name.lower() else "FluidNC" if "FluidNC" in name else ""

    # ------------------------------------------------------------------ exchanges

    def _command(self, line: str, seconds: float, what: str | None = None) -> list[str]:
        """Send one line and read until its ``ok``; returns the lines received before it."""
        self._drain(0.0)
        self._write(line.encode("ascii") + b"\n")
        deadline = time.monotonic() + seconds
        received = []
        while True:
            reply = self._read_line(deadline)
            if reply is None:
                what = what or f"'ok' to {line!r}"
                raise RailError(f"no {what} from rail on {self.port} within {seconds:g} s")
            if reply == "ok":
                return received
            if reply.startswith("error:"):
                self._moving = False  # a refused line queued nothing
                code = _code(reply)
                cls = RailAlarm if code == 9 else RailError
                hint = "; the controller is locked: `psfd rail home` or `psfd rail unlock`" if code == 9 else ""
                raise cls(f"GRBL refused {line!r}: error:{code} ({ERRORS.get(code, 'unknown error')}){hint}")
            if reply.startswith("ALARM:"):
                self._moving = False
                self._on_alarm(_code(reply), f"after {line!r}")
            if BANNER.match(reply):
                raise RailError(f"the controller on {self.port} reset itself while answering {line!r}")
            if reply.startswith("<"):
                self._wco = parse_status(reply, self._wco, self._scale)[1]
                continue
            received.append(reply)

    def _status(self, seconds: float | None = None) -> GrblStatus:
        """Ask for one status report (``?``)."""
        seconds = self.timeout if seconds is None else seconds
        self._write(STATUS)
        deadline = time.monotonic() + seconds
        while True:
            reply = self._read_line(deadline)
            if reply is None:
                raise RailError(f"no status report to '?' from rail on {self.port} within {seconds:g} s"
                                + (" (the controller stopped answering)" if self._moving else ""))
            if reply.startswith("<"):
                status, self._wco = parse_status(reply, self._wco, self._scale)
                if self._restarted:
                    self._check_restart(status)
                self._last = status
                return status
            if reply.startswith("ALARM:") and not self._alarmed:
                self._moving = False
                self._on_alarm(_code(reply), "")
            if BANNER.match(reply):
                self.banner, self._restarted = reply, True
                self._write(STATUS)  # the '?' asked before went with the restart (main.c clears the realtime flags)
                deadline = time.monotonic() + seconds

    def _check_restart(self, status: GrblStatus) -> None:
        """After a banner no reset of ours asked for: refuse to go on where the position is lost.

        A controller that restarts by itself (a power blip, a brown-out as the motors start) counts again from
        machine position 0 wherever the carriage stands (main.c), in Alarm only with homing enabled. Its reset
        button while nothing moves keeps the position (mc_reset kills nothing then; in motion it throws
        ALARM:3, handled as an alarm): the machine position it reads then is the one it read before.
        """
        self._restarted = False
        before, moving = self._last, self._moving
        if not moving and (before is None or all(abs(a - b) <= 1e-3 for a, b in zip(status.machine, before.machine))):
            log.warning("rail %s: the controller was reset while standing; its position is unchanged", self.port)
            return
        self._moving = False
        advice = self._known_position()
        was = f" (was at {self._where(before)})" if before is not None else ""
        raise RailError(f"the controller on {self.port} restarted{' during the move' if moving else ''} (its banner "
                        f"came unasked: a power blip, a brown-out): it reads {self._where(status)}, its power-up "
                        f"position{was}; the position is lost: {advice}")

    def _reset(self, attempts: int = 2) -> None:
        """Ctrl-X and wait for the banner (twice by default: a reset can be lost in an alarm's delay)."""
        for _ in range(attempts):
            self._write(SOFT_RESET)
            if self._wait_for(lambda ln: bool(BANNER.match(ln)), self.timeout):
                self._drain(0.1, watch=False)  # the [MSG:..] lines (and a boot ALARM) that follow the banner
                return
        raise RailError(f"no banner from the controller on {self.port} after a reset (Ctrl-X)")

    def _wait_for(self, predicate, seconds: float) -> bool:
        deadline = time.monotonic() + seconds
        while True:
            line = self._read_line(deadline)
            if line is None:
                return False
            if BANNER.match(line):
                self.banner = line
            if predicate(line):
                return True

    def _drain(self, quiet: float, watch: bool = True) -> None:
        """Read what is pending until ``quiet`` seconds pass without a line (0: only what has arrived);
        an alarm among it is handled (``watch``)."""
        while True:
            line = self._read_line(time.monotonic() + quiet)
            if line is None:
                return
            if BANNER.match(line):
                self.banner = line
                self._restarted = self._restarted or watch  # unasked: the next status report tells what it cost
            elif watch and line.startswith("ALARM:"):
                self._moving = False
                self._on_alarm(_code(line), "")

    def _write(self, data: bytes) -> None:
        shown = {SOFT_RESET: "^X", FEED_HOLD: "!", STATUS: "?"}.get(data) or data.decode("ascii", "replace").strip()
        self._note("> " + shown)
        if self._serial is None:
            raise RailError(f"rail port {self.port} is closed")
        try:
            self._serial.write(data)
            self._serial.flush()
        except serial.SerialTimeoutException:
            raise RailError(f"rail port {self.port}: write timed out (controller not reading)") from None
        except (serial.SerialException, OSError) as exc:
            raise PortGone(f"rail port {self.port} is gone ({_reason(exc)})") from None

    def _read_line(self, deadline: float) -> str | None:
        """Next non-empty line, or None at the deadline; RailError if the port is gone."""
        while True:
            while b"\n" not in self._buffer:
                if self._serial is None:
                    raise RailError(f"rail port {self.port} is closed")
                try:
                    waiting = self._serial.in_waiting
                    if not waiting and time.monotonic() >= deadline:
                        return None
                    chunk = self._serial.read(max(1, waiting))  # at most READ_SLICE s when nothing comes
                except (serial.SerialException, OSError) as exc:
                    raise PortGone(f"rail port {self.port} is gone ({_reason(exc)})") from None
                self._buffer += chunk
            raw, self._buffer = self._buffer.split(b"\n", 1)
            # Line noise decodes to replacement characters and is then skipped as an unknown line.
            line = raw.decode("ascii", "replace").strip()
            if line:
                self._note("< " + line)
                return line

    # ------------------------------------------------------------------ helpers

    @property
    def _homing_enabled(self) -> bool:
        return bool(self._settings_full[22])

    def _axis_settings(self, base: int) -> list[float]:
        return [self._settings_full[base + i] for i in range(len(AXES))]

    def _tolerance(self, axis: str) -> float:
        """Half a step (GRBL rounds targets to whole steps) plus the report's last digit, mm."""
        index = AXES.index(axis)
        resolution = 0.0001 * MM_PER_INCH if self._scale != 1.0 else 0.001
        return 0.5 / self._settings_full[100 + index] + resolution + 1e-6

    def _note(self, text: str) -> None:
        self.exchange.append(text)
        del self.exchange[:-200]  # a long move polls many status reports: keep the latest

    def _position(self, status: GrblStatus) -> Position:
        values = {axis: (round(self._axis(status.position, axis), 4) if axis in self.travel else None) for axis in AXES}
        return Position(x=values["x"] if values["x"] is not None else 0.0, y=values["y"], z=values["z"])

    def _where(self, status: GrblStatus) -> str:
        return ", ".join(f"{a.upper()}={self._axis(status.position, a):g}" for a in (self.travel or {"x": 0}))

    @staticmethod
    def _axis(position: tuple[float, ...], axis: str) -> float:
        index = AXES.index(axis)
        return position[index] if index < len(position) else 0.0

    _scale = 1.0
    _settings_full: dict[int, float] = GRBL_DEFAULTS
    travel: dict[str, tuple[float, float]] = {}


_STARTUP_LINE = re.compile(r"^\$N(\d)=(.*)$")
# in a startup line: an axis word (a move, G92 or G10 offsets), or G28 / G30, the moves to stored positions
_MOVES = re.compile(r"[XYZABC]|G0*(28|30)(?!\.1)")
_SETTING = re.compile(r"^\$(\d+)=([-+]?\d*\.?\d+)")
_OFFSET = re.compile(r"^\[(G5[4-9]|G92):([-+0-9.,]+)\]$")  # a line of `$#`
_SYSTEM = re.compile(r"G5[4-9](?![.0-9])")  # a coordinate system selection (G54-G59), in `$G` or a line


def open_rail(config: dict) -> GrblRail:
    """The GRBL rail of a plan's [rig] table (``rail = "grbl"``, the default; see `psfd.drivers.open_rig`)."""
    return GrblRail(
        config["rail_port"],
        baudrate=int(config.get("rail_baudrate", 115200)),
        timeout=float(config.get("rail_timeout", 2.0)),
        limits=config.get("rail_limits"),
        feed=float(config["rail_feed"]) if config.get("rail_feed") else None,  # default: the controller's rapids
    )


def _open_port(port: str, baudrate: int, timeout: float) -> serial.Serial:
    """Open without resetting the controller, exclusively (flock), and keep DTR up after close."""
    link = serial.Serial()
    link.port = port
    link.baudrate = baudrate
    link.timeout = READ_SLICE
    link.write_timeout = timeout
    link.dsrdtr = False  # no hardware handshake: pyserial then sets DTR/RTS itself, to the states below
    link.rtscts = False
    link.dtr = True  # the kernel raised DTR on open already: asserting it again is no edge, so no reset
    link.rts = True
    link.exclusive = True
    device = os.path.realpath(port)
    for attempt in range(2):
        try:
            link.open()
            break
        except (serial.SerialException, OSError, ValueError) as exc:
            busy = getattr(exc, "errno", None) in (errno.EAGAIN, errno.EWOULDBLOCK) or "exclusively lock" in str(exc)
            if not busy:
                raise RailError(f"cannot open rail port {port}: {_reason(exc)}") from None
            holder = _flock_holder(device)
            # a flock whose process is dead is held by that process's guard, stopping the carriage: wait for it
            if attempt or holder is None or os.path.exists(f"/proc/{holder}") or not _guard_done(port, device, holder):
                raise RailError(f"rail {port} in use by {_describe_pid(holder)}") from None
    with contextlib.suppress(termios.error, OSError, AttributeError):
        # Without HUPCL the kernel keeps DTR up when the port closes, so the next open makes no DTR edge
        # either: an Arduino with the auto-reset capacitor is then reset once, at the first open after boot.
        attrs = termios.tcgetattr(link.fd)
        attrs[2] &= ~termios.HUPCL
        termios.tcsetattr(link.fd, termios.TCSANOW, attrs)
    return link


def _guard_done(port: str, device: str, dead: int) -> bool:
    """Wait while the guard of process ``dead`` stops the carriage it left (the flock of a dead process is its
    guard's: they share the port's open file description); True once the port is free."""
    log.warning("rail %s: pid %d died with the rail open; waiting while its guard stops the carriage", port, dead)
    deadline = time.monotonic() + GUARD_WAIT
    while time.monotonic() < deadline:
        if _flock_holder(device) != dead:
            return True
        time.sleep(0.05)
    return False


def _check_limits(limits: dict | None) -> dict[str, tuple[float | None, float | None]]:
    """``{"x": (lo, hi)}`` checked; no limits: the X axis over the controller's whole travel."""
    if not limits:
        return {"x": (None, None)}
    checked: dict[str, tuple[float | None, float | None]] = {}
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


def _code(line: str) -> int:
    try:
        return int(line.split(":", 1)[1].split()[0])
    except (ValueError, IndexError):
        return -1


def _reason(exc: BaseException) -> str:
    return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
