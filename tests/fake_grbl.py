"""A fake GRBL 1.1h controller behind a pseudo-terminal, written from the firmware's documentation and
source (gnea/grbl: doc/markdown/interface.md, commands.md, settings.md, the alarm and error code tables;
grbl/protocol.c, system.c, report.c, limits.c, motion_control.c, serial.c, main.c, defaults.h, config.h),
not from what psfd's driver expects. The driver under test opens the slave side with real pyserial.

What it does as the firmware does:

- Power-up: machine position zeroed wherever the carriage stands; with homing enabled (``$22=1``,
  HOMING_INIT_LOCK) it starts in Alarm and prints ``[MSG:'$H'|'$X' to unlock]`` after the banner.
- The serial ISR picks realtime bytes out of the stream at once (``?``, ``!``, ``~``, 0x18, 0x84 safety
  door, 0x85 jog cancel, the 0x90.. overrides); other bytes go to the RX ring (128 bytes, RX_BUFFER_SIZE)
  and are dropped when it is full; a line waiting in mc_line() for room in the planner (15 blocks, the
  running one included) has been read out of the ring. Lines are filtered as protocol.c does (spaces,
  comments, case, 80 characters at most: error:11).
- The main loop runs realtime flags at its check points: several ``?`` before a report give one report;
  no report in the critical-alarm loop, nor during the homing cycle (a '?' asked in it is answered once, as
  ``Home``, when the cycle completes; a ``!`` or ``~`` asked in it is dropped); lines wait while a hold, a
  door or the sleep (``$SLP``, answered first) suspends the main program, and while the 15-block planner is
  full. A cycle start flagged together with a hold is dropped.
- ``ok`` comes when a motion line is planned, not run; ``G4 P<s>`` is answered once the planner has run empty
  and the dwell has passed (mc_dwell), and a reset during it still answers it before the banner.
- Motion runs in (scaled) real time: one trapezoidal profile per planner block, rate and acceleration
  limited per axis by ``$110..`` and ``$120..`` (planner.c's limit_value_by_axis_maximum), targets
  rounded to whole steps (``$100..``), positions reported from the step count.
- ``!`` decelerates to Hold:1 then Hold:0; ``~`` resumes; 0x18 in motion, in Hold:1 or during homing
  throws ALARM:3 (ALARM:6 when homing), after a completed hold it keeps the position (mc_reset).
- Hard limits (``$21``) are a pin-change interrupt: a switch closing or opening, in motion or standing (not in
  Alarm, not while homing), stops everything dead: ALARM:1. Soft limits (``$20``) check every G-code target
  against the machine travel [-$130, 0]: ALARM:2 (a feed hold first when in motion). Both are critical:
  ``[MSG:Reset to continue]``, then nothing but Ctrl-X is answered, not even ``?``. A reset swallowed by
  the 500 ms delay that follows an ALARM message is cleared before that loop starts (protocol.c), so the
  host must reset after the message.
- ``$H``: cycle 0 (Z) then cycle 1 (X, Y), each a search at ``$25`` over 1.5 x ``$13x``, a pull-off, a
  locate at ``$24`` over 5 x ``$27`` and a final pull-off, each phase counting the cycle's axes from machine
  position 0; homes to the + end unless ``$23`` says otherwise; machine position then -``$27`` (all machine
  space negative), and the startup lines run before its ``ok``. ALARM:8/9 on failure, ALARM:6 on a reset,
  ALARM:7 on the door, then the ``ok`` of ``$H`` and a self reset.
- Status reports in the 1.1 format: ``<State|MPos:..|Bf:..|FS:..|Pn:..|WCO:..|Ov:..>``, MPos or WPos and Bf
  per ``$10``, WCO in the first report after a reset and then every 10 (idle) or 30 (busy) reports, Ov on the
  next but one; ``$13=1`` reports inches (4 decimals) and in/min.
- ``$$`` ``$#`` ``$G`` ``$I`` ``$X`` ``$H`` ``$C`` ``$J=`` ``$SLP`` ``$N=value``, G0/G1/G4/G10 L2/L20/G17/G20/G21/
  G53/G54-59/G90/G91/G92/G92.1/G94, M0/M2/M30/M3/M5/M8/M9, F/N/P/L/S/T, with their error codes.

A physical rail stands behind it: per axis, a switch at each end of a span a little longer than ``$13x``
(the + switch at physical 0) and a mechanical stop 5 mm beyond each switch where the motor stalls and loses
steps (counted in ``crashes``).

Configurable: ``settings`` (e.g. ``{22: 1}`` homing, ``{13: 1}`` inches, ``{100: 25}``, ``{110: 60, 120: 1}`` a
slow rail), ``flavour`` ("grbl", "grblhal", "fluidnc": their banners, boot alarms and ``$$``/``$I`` answers),
``auto_reset`` (an Arduino whose DTR line resets it when the port is opened, unless HUPCL was cleared so DTR
stayed up; a close and reopen within one millisecond tick go unnoticed), ``boot_time`` (its bootloader
delay), ``wake_on_line`` (a board that says nothing, not even to ``?``, until it has received a whole line),
``time_scale`` (simulated seconds per wall second).

Simplifications: each planner block starts and ends at rest (no junction speeds: slower than the
firmware, never faster); bytes arrive as fast as the pty delivers them, not at 115200 baud, so a burst of
more than 128 bytes loses characters even where the firmware would have drained it into an empty planner
(harsher, never more forgiving); arcs, probing, G28/G30, inverse time, parking and spindle/coolant outputs
are not modelled (error:20).
"""

from __future__ import annotations

import math
import os
import re
import select
import termios
import threading
import time
import tty
from dataclasses import dataclass, field

# defaults.h, DEFAULTS_GENERIC (what a freshly flashed grbl 1.1h reports).
DEFAULTS: dict[int, float] = {
    0: 10, 1: 25, 2: 0, 3: 0, 4: 0, 5: 0, 6: 0, 10: 1, 11: 0.010, 12: 0.002, 13: 0,
    20: 0, 21: 0, 22: 0, 23: 0, 24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 30: 1000, 31: 0, 32: 0,
    100: 250.0, 101: 250.0, 102: 250.0, 110: 500.0, 111: 500.0, 112: 500.0,
    120: 10.0, 121: 10.0, 122: 10.0, 130: 200.0, 131: 200.0, 132: 200.0,
}
INT_SETTINGS = {0, 1, 2, 3, 4, 5, 6, 10, 13, 20, 21, 22, 23, 26, 32}
RPM_SETTINGS = {30, 31}
# FluidNC's `$$` answers only this legacy subset, in this order (its machine lives in a YAML file).
FLUIDNC_SETTINGS = (22, 21, 20, 102, 101, 100, 112, 111, 110, 122, 121, 120, 132, 131, 130, 10, 30)

BANNERS = {
    "grbl": "Grbl 1.1h ['$' for help]",
    "grblhal": "GrblHAL 1.1f ['$' or '$HELP' for help]",
    "fluidnc": "Grbl 3.7 [FluidNC v3.7.8 (noradio) '$' for help]",
}
BUILD_INFO = {
    "grbl": ["[VER:1.1h.20190825:]", "[OPT:V,15,128]"],
    "grblhal": ["[VER:1.1f.20240125:]", "[OPT:VNMSL,35,1024,3,0]", "[AXS:3:XYZ]", "[FIRMWARE:grblHAL]"],
    "fluidnc": ["[VER:3.7 FluidNC v3.7.8:]", "[OPT:PHS]", "[MSG: Machine: psfd rail]"],
}

N_AXIS = 3
PLANNER_BLOCKS = 15  # BLOCK_BUFFER_SIZE 16, one kept free; the running block is one of them
LINE_BUFFER = 80
MM_PER_INCH = 25.4
HOMING_SEARCH_SCALAR = 1.5
HOMING_LOCATE_SCALAR = 5.0
ALARM_DELAY = 0.5  # report_alarm_message: delay_ms(500)
STOP_MARGIN = 5.0  # mm of mechanical travel beyond each switch

_WORD = re.compile(r"[A-Z]")
_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)")
_NUMBER_SETTING = re.compile(r"(\d+)=([-+]?(?:\d+\.?\d*|\.\d+))$")


def _lround(x: float) -> int:
    """C's lround: halves away from zero (Python's round() is to even)."""
    return int(math.copysign(math.floor(abs(x) + 0.5), x))


@dataclass
class Block:
    """One planner block: a straight line in machine mm (between whole-step end points)."""

    start: list[float]
    target: list[float]
    length: float
    unit: list[float]
    rate: float  # mm/s
    accel: float  # mm/s^2
    homing: tuple | None = None  # (axes, approach) for the homing cycle's own motions
    s: float = 0.0

    def point(self) -> list[float]:
        return [a + self.s * u for a, u in zip(self.start, self.unit)]


@dataclass
class ParserState:
    """The g-code parser's modal state (gcode.c gc_state)."""

    motion: int = 0
    units_inch: bool = False
    incremental: bool = False
    coord_select: int = 0
    feed: float = 0.0  # mm/min, 0 = undefined
    g92: list[float] = field(default_factory=lambda: [0.0] * N_AXIS)
    position: list[float] = field(default_factory=lambda: [0.0] * N_AXIS)  # machine mm


def advance(s: float, v: float, length: float, vmax: float, a: float, dt: float, hold: bool) -> tuple[float, float]:
    """Advance a rest-to-rest trapezoidal motion along ``length`` by ``dt`` seconds, exactly, phase by phase.

    ``hold`` decelerates to rest at ``a`` (a feed hold). Returns the new distance and speed.
    """
    for _ in range(6):  # accelerate, cruise, brake: a few phases at most
        remaining = length - s
        if remaining <= 1e-12:
            return length, 0.0
        if dt <= 0.0:
            break
        if hold:
            t = min(dt, v / a)
            s += v * t - 0.5 * a * t * t
            v = max(0.0, v - a * t)
            return (length, 0.0) if s >= length else (s, v)
        brake = v * v / (2.0 * a)
        if remaining <= brake + 1e-12:  # on the final ramp: stop exactly at the end
            decel = v * v / (2.0 * remaining)
            if dt >= v / decel:
                return length, 0.0
            return s + v * dt - 0.5 * decel * dt * dt, v - decel * dt
        if v < vmax:
            peak = math.sqrt((2.0 * a * remaining + v * v) / 2.0)  # where acceleration meets braking
            top = min(vmax, peak)
            t = (top - v) / a
            if dt < t:
                return s + v * dt + 0.5 * a * dt * dt, v + a * dt
            s, v, dt = s + v * t + 0.5 * a * t * t, top, dt - t
            if top == peak:
                s = length - v * v / (2.0 * a)
            continue
        t = (remaining - brake) / v
        if dt < t:
            return s + v * dt, v
        s, dt = length - brake, dt - t
    return s, v


class FakeGrbl:
    """GRBL 1.1h firmware on the master side of a pty; ``port`` is the device pyserial opens."""

    def __init__(self, settings: dict[int, float] | None = None, *, flavour: str = "grbl",
                 time_scale: float = 1.0, start: tuple[float, ...] = (-50.0, -50.0, -50.0),
                 span: tuple[float, ...] | None = None, auto_reset: bool = False, boot_time: float = 1.0,
                 wake_on_line: bool = False, homing_cycles: tuple[tuple[int, ...], ...] = ((2,), (0, 1)),
                 rx_buffer: int = 128) -> None:
        if flavour not in BANNERS:
            raise ValueError(f"unknown flavour {flavour!r}")
        self.settings = dict(DEFAULTS)
        self.settings.update(settings or {})
        self.flavour = flavour
        self.time_scale = float(time_scale)
        self.auto_reset = auto_reset
        self.boot_time = float(boot_time)
        self.wake_on_line = wake_on_line
        self.homing_cycles = homing_cycles
        self.rx_size = rx_buffer
        # The physical rail: the + switch at 0, the - switch at -span, stops STOP_MARGIN beyond each.
        self.span = list(span or [self.settings[130 + i] + 3.0 for i in range(N_AXIS)])
        self._offset = [float(p) for p in start]  # physical position = machine position + offset
        # Test hooks and records.
        self.errors: dict[str, int] = {}  # line prefix -> error code, answered instead of executing the line
        self.lines: list[str] = []  # every line taken from the RX buffer
        self.realtime: list[tuple[float, int]] = []  # (simulated time, byte) of every realtime command
        self.events: list[tuple] = []  # ("alarm", n), ("reset", state), ("boot",), ("open",), ("close",)
        self.crashes = 0  # times the carriage ran into a mechanical stop
        self.tx_enabled = True
        self.noise = False
        self.written = bytearray()  # everything the firmware printed, whether the host got it or not
        self._triggers: list[tuple] = []
        self._lock = threading.RLock()
        self._t0 = time.monotonic()
        self._door_ajar = False
        self._dtr = False
        self._peer_open = False
        self._hupcl = True
        self._woken = not wake_on_line
        self._booting_until: float | None = None
        self._last_tick = 0.0
        self.master, slave = os.openpty()
        self.port = os.ttyname(slave)
        # A USB serial tty: raw, HUPCL set (the kernel drops DTR on the last close).
        tty.setraw(slave)
        attrs = termios.tcgetattr(slave)
        attrs[2] |= termios.HUPCL
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.close(slave)
        self._poll = select.poll()
        self._poll.register(self.master, select.POLLIN | select.POLLHUP)
        self._coords = [[0.0] * N_AXIS for _ in range(6)]  # G54..G59, kept in EEPROM across resets
        self.startup_lines = ["", ""]  # $N0, $N1 in EEPROM: run after every reset that ends Idle (protocol.c)
        self._power_up()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fake-grbl", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ test-side controls

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.unplug()

    def unplug(self) -> None:
        """Pull the USB cable: the port disappears under whoever has it open."""
        with self._lock:
            if self.master >= 0:
                fd, self.master = self.master, -1
                try:
                    os.close(fd)
                except OSError:
                    pass

    def when(self, condition, action) -> None:
        """Run ``action(self)`` once, in the firmware thread, as soon as ``condition(self)`` holds."""
        with self._lock:
            self._triggers.append((condition, action))

    def go_silent(self) -> None:
        """The controller goes on listening and acting, but nothing it sends reaches the host any more."""
        self.tx_enabled = False

    def press_feed_hold(self) -> None:
        """The operator presses the feed-hold button (the same flag as ``!``)."""
        with self._lock:
            self._flags.add("feed_hold")

    def press_reset(self) -> None:
        """The operator presses the controller's reset (abort) button: the pin interrupt calls mc_reset(), as
        Ctrl-X does (system.c, CONTROL_INT_vect)."""
        with self._lock:
            self.events.append(("reset", self._state_name()))
            self._mc_reset()

    def open_door(self) -> None:
        with self._lock:
            self._door_ajar = True
            self._flags.add("door")

    def close_door(self) -> None:
        with self._lock:
            self._door_ajar = False

    def power_cycle(self) -> None:
        """The board loses power and boots again (a USB cable pulled and put back, a power cut): the motors
        stop dead and the position restarts at 0 where the carriage stands (grbl main.c clears
        sys_position at boot); with homing enabled it comes up locked in Alarm."""
        with self._lock:
            self._reboot()

    def push(self, axis: int, mm: float) -> None:
        """Someone moves the carriage by hand (motors idle): the controller counts no steps."""
        with self._lock:
            self._offset[axis] += mm

    def machine_position(self) -> list[float]:
        """MPos in mm, from the step counter."""
        with self._lock:
            return self._reported_mpos()

    def physical_position(self) -> list[float]:
        with self._lock:
            return [m + o for m, o in zip(self._mpos, self._offset)]

    def status(self) -> str:
        """The state as a status report names it, e.g. ``Hold:0``."""
        with self._lock:
            return self._state_name()

    @property
    def moving(self) -> bool:
        with self._lock:
            return self._block is not None and self._v > 0.0

    @property
    def peer_open(self) -> bool:
        return self._peer_open

    def alarms(self) -> list[int]:
        return [e[1] for e in self.events if e[0] == "alarm"]

    def resets(self) -> list[str]:
        """The state the firmware was in at each Ctrl-X it received."""
        return [e[1] for e in self.events if e[0] == "reset"]

    def wait_for(self, predicate, timeout: float = 5.0) -> bool:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if predicate(self):
                return True
            time.sleep(0.005)
        return bool(predicate(self))

    def now(self) -> float:
        """Simulated seconds since the fake was made."""
        return (time.monotonic() - self._t0) * self.time_scale

    # ------------------------------------------------------------------ power-up and reset (main.c)

    def _power_up(self) -> None:
        """Power-up: position zeroed where the carriage stands; HOMING_INIT_LOCK with $22=1."""
        self._mpos = [0.0] * N_AXIS
        self._pins = frozenset(self._switches())  # as the pins read at boot: no change yet
        self.state = "Alarm" if self.settings[22] else "Idle"
        self._boot_alarm = bool(self.settings[22])
        self._reinit()

    def _reinit(self) -> None:
        """main()'s loop after power-up or a system abort: everything cleared but position and alarm."""
        prior = self.state
        self._flags: set[str] = set()
        self._exec_alarm = 0
        self._rx = bytearray()
        self._held = 0  # bytes at the head of _rx already read into the line waiting in mc_line() (not in the ring)
        self._planner: list[Block] = []
        self._block: Block | None = None
        self._v = 0.0
        self._hold = False  # STEP_CONTROL_EXECUTE_HOLD
        self._suspend: set[str] = set()
        self._homing: dict | None = None
        self._deaf = False
        self._soft_limit = False
        self._answer_after_reset = False
        self._dwell: list | None = None  # [seconds, end]: a G4 waiting for the buffer, then for its time
        self._busy_until = 0.0
        self._after_busy = None
        self._wco_counter = 0
        self._ovr_counter = 0
        self._gc = ParserState(position=self._reported_mpos())
        self._write_line("")
        self._write_line(BANNERS[self.flavour])
        alarm = prior in ("Alarm", "Sleep")
        if self.settings[21] and self._switches():  # CHECK_LIMITS_AT_INIT
            alarm = True
            self._write_line("[MSG:Check Limits]")
        if alarm:
            self.state = "Alarm"
            if self._boot_alarm and self.flavour == "grblhal":
                self.events.append(("alarm", 11))
                self._write_line("ALARM:11")
                self._write_line("[MSG:Homing cycle required]")
            elif self._boot_alarm and self.flavour == "fluidnc":
                self.events.append(("alarm", 14))
                self._write_line("[MSG:INFO: ALARM: Unhomed]")
                self._write_line("ALARM:14")
            else:
                self._write_line("[MSG:'$H'|'$X' to unlock]")
        else:
            self.state = "Idle"
            if self._door_ajar:
                self._flags.add("door")
            self._run_startup_lines()
        self._boot_alarm = False

    def _run_startup_lines(self) -> None:
        """system_execute_startup(): $N0 and $N1, each echoed with its answer."""
        for text in filter(None, self.startup_lines):
            code = self._gcode(text)
            self._write_line(f">{text}:" + ("ok" if not code else f"error:{code}"))

    def _reboot(self) -> None:
        """The MCU itself resets (DTR pulse on an Arduino): motors stop dead, position restarts at 0."""
        self.events.append(("boot",))
        self._offset = [m + o for m, o in zip(self._mpos, self._offset)]
        self._mpos = [0.0] * N_AXIS
        self._block, self._v, self._planner, self._homing = None, 0.0, [], None
        self._booting_until = self.now() + self.boot_time

    def _mc_reset(self) -> None:
        """mc_reset(): flags the abort; in motion, in a hold still decelerating or homing, an alarm."""
        if "reset" in self._flags:
            return
        self._flags.add("reset")
        if self.state in ("Run", "Jog") or self._hold or self._homing is not None:
            if self._homing is not None:
                self._exec_alarm = self._exec_alarm or 6
            else:
                self._exec_alarm = 3
            self._block, self._v = None, 0.0  # st_go_idle(): the motors stop dead

    # ------------------------------------------------------------------ the firmware thread

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                if self.master < 0:
                    return
                try:
                    self._serial_io()
                except OSError:
                    return
                now = self.now()
                self._stepper(now)
                for trigger in list(self._triggers):
                    if trigger[0](self):
                        self._triggers.remove(trigger)
                        trigger[1](self)
                self._limit_pin_change()  # a carriage pushed by hand
                if self._booting_until is not None:
                    if now >= self._booting_until:
                        self._booting_until = None
                        self._power_up()
                elif now < self._busy_until:
                    pass  # delay_ms() in the main program; the ISRs still run
                elif self._after_busy is not None:
                    action, self._after_busy = self._after_busy, None
                    action()
                elif self._homing is not None:
                    self._homing_cycle(now)
                else:
                    self._main_loop()
            time.sleep(0.001)

    # ------------------------------------------------------------------ serial port (serial.c, the tty)

    def _serial_io(self) -> None:
        events = self._poll.poll(0)
        if any(ev & select.POLLHUP for _, ev in events):  # nobody has the port open
            if self._peer_open:
                self._peer_open = False
                self.events.append(("close",))
                if self._hupcl:
                    self._dtr = False  # the kernel drops DTR on the last close
            return
        if not self._peer_open:
            self._peer_open = True
            self.events.append(("open",))
            if not self._dtr:  # opening raises DTR; on an Arduino that edge resets the MCU
                self._dtr = True
                if self.auto_reset:
                    self._reboot()
        self._hupcl = bool(termios.tcgetattr(self.master)[2] & termios.HUPCL)
        if any(ev & select.POLLIN for _, ev in events):
            for byte in os.read(self.master, 4096):
                self._isr(byte)

    def _isr(self, byte: int) -> None:
        """The RX interrupt: realtime bytes act at once, the rest goes to the ring buffer."""
        if self._booting_until is not None:
            return  # the bootloader owns the UART
        if byte == 0x0A and not self._woken:
            self._woken = True
        realtime = {0x3F: "status", 0x7E: "cycle_start", 0x21: "feed_hold", 0x84: "door"}
        if byte == 0x18:
            self.realtime.append((self.now(), byte))
            self.events.append(("reset", self._state_name()))
            self._mc_reset()
        elif byte in realtime:
            self.realtime.append((self.now(), byte))
            self._flags.add(realtime[byte])
        elif byte == 0x85:
            self.realtime.append((self.now(), byte))
            if self.state == "Jog":
                self._flags.add("motion_cancel")
        elif byte > 0x7F:
            pass  # overrides are accepted but not modelled; unknown extended bytes are dropped
        elif len(self._rx) - self._held < self.rx_size:
            self._rx.append(byte)

    def _write_line(self, text: str) -> None:
        data = (text + "\r\n").encode("ascii")
        if self.noise:
            data = b"\xff\xfe#~\x07noise\r\n" + data
        self.written += data
        if not (self.tx_enabled and self._peer_open and self._woken) or self._booting_until is not None:
            return  # a closed port, or a board that is not talking yet, drops what it sends
        try:
            os.write(self.master, data)
        except OSError:
            pass

    # ------------------------------------------------------------------ main loop (protocol.c)

    def _main_loop(self) -> None:
        if self._deaf:  # do { } while (bit_isfalse(sys_rt_exec_state, EXEC_RESET));
            if "reset" in self._flags:
                if self._answer_after_reset:
                    self._write_line("ok")  # the line that hit the soft limit still gets its 'ok'
                self._reinit()
            return
        if not self._exec_rt_system():
            return
        if self._suspend or self._soft_limit or self._homing is not None:
            return  # protocol_exec_rt_suspend() holds the main program
        if self._dwell is not None:
            self._dwell_step()  # mc_dwell() holds the main program: no line is read meanwhile
        else:
            self._process_lines()
        if self._homing is None and self._planner and self.state == "Idle":
            self._flags.add("cycle_start")  # protocol_auto_cycle_start()

    def _dwell_step(self) -> None:
        """mc_dwell(): protocol_buffer_synchronize() until the planner is empty and the cycle over, then
        delay_sec(); the G4 line's 'ok' comes after both."""
        if self._planner or self._block is not None or self.state == "Run":
            return
        if self._dwell[1] is None:
            self._dwell[1] = self.now() + self._dwell[0]
        elif self.now() >= self._dwell[1]:
            self._dwell = None
            self._write_line("ok")

    def _exec_rt_system(self) -> bool:
        """protocol_exec_rt_system(); False when the main program must not go on in this pass."""
        if self._exec_alarm:
            code = self._exec_alarm
            self.state = "Alarm"
            self.events.append(("alarm", code))
            self._write_line(f"ALARM:{code}")
            self._busy_until = self.now() + ALARM_DELAY
            if code in (1, 2):
                def critical() -> None:
                    self._write_line("[MSG:Reset to continue]")
                    self._flags.discard("reset")  # a reset that came during the delay is forgotten
                    self._exec_alarm = 0
                    self._deaf = True
                self._after_busy = critical
            else:
                self._exec_alarm = 0
            return False
        flags = self._flags
        if "reset" in flags:
            if self._dwell is not None:
                self._write_line("ok")  # mc_dwell() returns on the abort and gc_execute_line() answers the G4
            self._reinit()
            return False
        if "status" in flags:
            flags.discard("status")
            self._write_line(self._status_report())
        held = bool(flags & {"motion_cancel", "feed_hold", "door"})
        if held:
            if self.state not in ("Alarm", "Check"):
                if self.state in ("Run", "Jog") and not self._suspend & {"jog_cancel"}:
                    self._hold = True
                    if self.state == "Jog":
                        self._suspend.add("jog_cancel")
                if self.state == "Idle":
                    self._suspend = {"hold_complete"}
                if "feed_hold" in flags and self.state not in ("Door", "Jog", "Sleep"):
                    self.state = "Hold"
                if "door" in flags:
                    self._write_line("[MSG:Check Door]")
                    if "jog_cancel" not in self._suspend and self.state != "Sleep":
                        self.state = "Door"
                    self._suspend.add("door_ajar")
            flags -= {"motion_cancel", "feed_hold", "door"}
        if self.state == "Door" and not self._door_ajar and "hold_complete" in self._suspend:
            self._suspend.discard("door_ajar")  # the suspend loop sees the door closed
        if "sleep" in flags:  # only from Idle or Alarm: nothing to decelerate, the sleep starts at once
            flags.discard("sleep")
            self.state = "Sleep"
            self._suspend = {"hold_complete", "sleep"}
            self._write_line("[MSG:Sleeping]")
        if "cycle_start" in flags:
            flags.discard("cycle_start")
            if not held:  # a cycle start flagged together with a hold is dropped: no resume without the user
                self._cycle_start()
        if "cycle_stop" in flags:
            flags.discard("cycle_stop")
            if self.state in ("Hold", "Door") and not self._soft_limit and "jog_cancel" not in self._suspend:
                if self._hold:
                    self._suspend.add("hold_complete")  # Hold:0, ready to resume
                self._hold = False
            else:
                if "jog_cancel" in self._suspend:  # flush the jog and resync the parser
                    self._planner, self._block, self._hold = [], None, False
                    self._gc.position = self._reported_mpos()
                self._suspend = set()
                self.state = "Idle"
        return True

    def _cycle_start(self) -> None:
        if self.state == "Door" and "door_ajar" not in self._suspend and "hold_complete" in self._suspend:
            self.state = "Hold"  # door closed: resume like a completed hold
        if self.state == "Idle" or (self.state == "Hold" and "hold_complete" in self._suspend):
            self._suspend = set()
            if self._planner:
                self.state = "Run"
                self._start_block()
            else:
                self.state = "Idle"

    def _process_lines(self) -> None:
        while True:
            ends = [i for i in (self._rx.find(b"\n"), self._rx.find(b"\r")) if i >= 0]
            if not ends:
                return
            end = min(ends)
            raw = bytes(self._rx[:end])
            line, overflow = self._filter(raw)
            if line and not line.startswith("$") and self._queued() >= PLANNER_BLOCKS:
                self._held = end + 1  # mc_line() waits for room in the planner with the line read out of the ring
                return
            self._held = 0
            del self._rx[: end + 1]
            self.lines.append(raw.decode("ascii", "replace").strip())
            self._answer(line, overflow, raw)
            if (self._exec_alarm or self._after_busy or self._flags & {"reset", "sleep"} or self._homing
                    or self._soft_limit or self._dwell is not None):
                return

    @staticmethod
    def _filter(raw: bytes) -> tuple[str, bool]:
        """protocol_main_loop()'s filter: no blanks, controls or comments, upper case, 80 characters."""
        out: list[str] = []
        comment = None
        overflow = False
        for c in raw.decode("ascii", "replace"):
            if comment == "(":
                comment = None if c == ")" else comment
            elif comment == ";" or c <= " " or c == "/":
                continue
            elif c in "(;":
                comment = c
            elif len(out) >= LINE_BUFFER - 1:
                overflow = True
            else:
                out.append(c.upper())
        return "".join(out), overflow

    def _answer(self, line: str, overflow: bool, raw: bytes) -> None:
        if overflow:
            return self._write_line("error:11")
        text = raw.decode("ascii", "replace").strip()
        for prefix, code in self.errors.items():
            if text.startswith(prefix):
                return self._write_line(f"error:{code}")
        if not line:
            code = 0  # an empty line or a comment: 'ok', for syncing
        elif line.startswith("$"):
            code = self._system_command(line)
        elif self.state in ("Alarm", "Jog"):
            code = 9
        else:
            code = self._gcode(line)
        if code is not None:  # None: answered later ($H at the end of the cycle, a soft limit after the reset)
            self._write_line("ok" if code == 0 else f"error:{code}")

    # ------------------------------------------------------------------ '$' commands (system.c)

    def _system_command(self, line: str) -> int | None:
        rest = line[1:]
        if rest == "":
            self._write_line("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]")
            return 0
        if rest[0] == "J":
            if self.state not in ("Idle", "Jog"):
                return 8
            return self._gcode(rest[2:], jog=True) if rest.startswith("J=") else 3
        if rest[0] in "$GCX":
            if len(rest) != 1:
                return 3
            if rest == "$":
                if self.state in ("Run", "Hold"):
                    return 8  # takes too long to print during a cycle
                self._report_settings()
            elif rest == "G":
                self._write_line(self._gcode_modes())
            elif rest == "C":
                if self.state == "Check":
                    self._mc_reset()
                    self._write_line("[MSG:Disabled]")
                elif self.state != "Idle":
                    return 8
                else:
                    self.state = "Check"
                    self._write_line("[MSG:Enabled]")
            elif self.state == "Alarm":  # $X: otherwise no effect
                if self._door_ajar:
                    return 13
                self._write_line("[MSG:Caution: Unlocked]")
                self.state = "Idle"
            return 0
        if self.state not in ("Idle", "Alarm"):
            return 8
        if rest == "#":
            for i in range(6):
                self._write_line(f"[G{54 + i}:{self._axis_text(self._coords[i])}]")
            for name in ("G28", "G30"):
                self._write_line(f"[{name}:{self._axis_text([0.0] * N_AXIS)}]")
            self._write_line(f"[G92:{self._axis_text(self._gc.g92)}]")
            self._write_line(f"[TLO:{self._coord_text(0.0)}]")
            self._write_line(f"[PRB:{self._axis_text([0.0] * N_AXIS)}:0]")
            return 0
        if rest == "H":
            if not self.settings[22]:
                return 5
            if self._door_ajar:
                return 13
            self.state = "Home"
            self._homing = {"cycles": list(self.homing_cycles), "axes": (), "phase": None, "wait": None}
            return None
        if rest == "I":
            for text in BUILD_INFO[self.flavour]:
                self._write_line(text)
            return 0
        if rest == "N":
            for n, text in enumerate(self.startup_lines):
                self._write_line(f"$N{n}={text}")
            return 0
        if rest[:1] == "N" and rest[1:2] in ("0", "1") and rest[2:3] == "=":
            self.startup_lines[int(rest[1])] = rest[3:]
            return 0
        if rest == "SLP":
            self._flags.add("sleep")  # EXEC_SLEEP: the line is answered first, the sleep follows
            return 0
        match = _NUMBER_SETTING.match(rest)
        if match is None or int(match.group(1)) not in DEFAULTS:
            return 3
        number, value = int(match.group(1)), float(match.group(2))
        if value < 0:
            return 4
        if number == 20 and value and not self.settings[22]:
            return 10
        self.settings[number] = int(value) if number in INT_SETTINGS else value
        return 0

    def _report_settings(self) -> None:
        for n in FLUIDNC_SETTINGS if self.flavour == "fluidnc" else sorted(self.settings):
            value = self.settings[n]
            if n in INT_SETTINGS:
                text = str(int(value))
            elif n in RPM_SETTINGS:
                text = f"{value:.0f}"
            else:
                text = f"{value:.3f}"
            self._write_line(f"${n}={text}")

    def _gcode_modes(self) -> str:
        gc = self._gc
        return (f"[GC:G{gc.motion} G{54 + gc.coord_select} G17 G{20 if gc.units_inch else 21} "
                f"G{91 if gc.incremental else 90} G94 M5 M9 T0 F{self._rate_text(gc.feed)} S0]")

    # ------------------------------------------------------------------ g-code (gcode.c, the subset above)

    def _gcode(self, line: str, jog: bool = False) -> int | None:
        words: list[tuple[str, float]] = []
        pos = 0
        while pos < len(line):
            if not _WORD.match(line[pos]):
                return 1
            number = _NUMBER.match(line, pos + 1)
            if number is None:
                return 2
            words.append((line[pos], float(number.group())))
            pos = number.end()
        gc = self._gc
        motion, non_modal, machine, g92_clear = None, None, False, False
        units_inch, incremental, coord_select = gc.units_inch, gc.incremental, gc.coord_select
        groups: set[str] = set()
        values: dict[str, float] = {}
        for letter, value in words:
            if letter in "GM":
                group = _modal_group(letter, value)
                if group is None:
                    return 20
                if group in groups:
                    return 21
                groups.add(group)
                if jog and group not in ("units", "distance", "g53"):
                    return 16
                if letter == "M":
                    continue
                if value in (0, 1):
                    motion = int(value)
                elif value in (20, 21):
                    units_inch = value == 20
                elif value in (90, 91):
                    incremental = value == 91
                elif group == "coord":
                    coord_select = int(value) - 54
                elif value == 53:
                    machine = True
                elif value in (4, 10, 92):
                    non_modal = int(value)
                elif math.isclose(value, 92.1):
                    g92_clear = True
                continue
            if letter in values:
                return 25
            if letter not in "FNPLSTXYZ":
                return 20
            values[letter] = value
        if jog and "F" not in values:
            return 22
        if any(values.get(letter, 0.0) < 0 for letter in "FNPST"):
            return 4  # checked as the words are read, before anything else (gcode.c)
        if "N" in values and not 1 <= values["N"] <= 9999999:
            return 27
        scale = MM_PER_INCH if units_inch else 1.0
        axes = {i: values[a] * scale for i, a in enumerate("XYZ") if a in values}
        allowed = {"N", "F", "S", "T"} | (set("XYZ") if axes else set())
        if non_modal == 4:
            if "P" not in values:
                return 28
            allowed.add("P")
        if non_modal == 10:
            if "L" not in values or "P" not in values:
                return 28
            if not axes:
                return 26
            allowed |= {"L", "P"}
        if set(values) - allowed:
            return 36
        motion_mode = gc.motion if motion is None else motion
        if machine and motion_mode not in (0, 1):
            return 30
        feed = values["F"] * scale if "F" in values else (0.0 if jog else gc.feed)
        if axes and non_modal not in (10, 92) and motion_mode == 1 and feed <= 0:
            return 22
        if non_modal == 10 and not 0 <= int(values["P"]) <= 6:
            return 29
        # Every check passed: the block executes.
        if not jog:
            gc.units_inch, gc.incremental, gc.coord_select = units_inch, incremental, coord_select
            gc.motion = motion_mode
            gc.feed = feed
        if g92_clear:
            gc.g92 = [0.0] * N_AXIS
            self._wco_counter = 0
        if non_modal == 10:
            index = int(values["P"]) - 1 if values["P"] else coord_select
            for i, v in axes.items():
                self._coords[index][i] = gc.position[i] - v - gc.g92[i] if values["L"] == 20 else v
            self._wco_counter = 0
            return 0
        if non_modal == 92:
            for i, v in axes.items():
                gc.g92[i] = gc.position[i] - self._coords[coord_select][i] - v
            self._wco_counter = 0
            return 0
        if non_modal == 4:
            if self.state == "Check":
                return 0
            self._dwell = [values["P"], None]
            return None  # answered by _dwell_step
        if not axes:
            return 0
        offset = [self._coords[coord_select][i] + gc.g92[i] for i in range(N_AXIS)]
        target = list(gc.position)
        for i, v in axes.items():
            target[i] = v if machine else gc.position[i] + v if incremental else v + offset[i]
        if jog:
            if self.settings[20] and self._outside_travel(target):
                return 15  # jogging checks the travel itself: an error, not an alarm
            self._plan(target, feed, rapid=False)
            gc.position = target
            if self.state == "Idle":
                self.state = "Jog"
                self._start_block()
            return 0
        if self.settings[20] and self._outside_travel(target):
            self._soft_limit_alarm()
            return None
        if self.state != "Check":
            self._plan(target, feed, rapid=motion_mode == 0)
        gc.position = target
        return 0

    def _outside_travel(self, target: list[float]) -> bool:
        # system_check_travel_limits(): machine space is [-max_travel, 0] on every axis
        return any(t > 0 or t < -self.settings[130 + i] for i, t in enumerate(target))

    def _soft_limit_alarm(self) -> None:
        """limits_soft_check(): in motion a feed hold first; then a reset and the critical ALARM:2."""
        self._soft_limit = True
        self._answer_after_reset = True
        if self.state == "Run":
            self._hold = True
            self.state = "Hold"
            self.when(lambda f: f._block is None, lambda f: f._raise_soft_limit())
        else:
            self._raise_soft_limit()

    def _raise_soft_limit(self) -> None:
        self._block, self._v, self._planner, self._hold = None, 0.0, [], False
        self._exec_alarm = 2
        self._exec_rt_system()

    # ------------------------------------------------------------------ planner and stepper

    def _plan(self, target: list[float], feed: float, rapid: bool, homing: tuple | None = None) -> None:
        """plan_buffer_line(): whole-step targets, rate and acceleration limited per axis."""
        start = self._planner[-1].target if self._planner else self._block.target if self._block else self._mpos
        if homing is None:
            steps = [_lround(t * self._spmm(i)) for i, t in enumerate(target)]
            if steps == [_lround(p * self._spmm(i)) for i, p in enumerate(start)]:
                return  # PLAN_EMPTY_BLOCK
            target = [n / self._spmm(i) for i, n in enumerate(steps)]
        delta = [t - p for t, p in zip(target, start)]
        length = math.sqrt(sum(d * d for d in delta))
        if length == 0.0:
            return
        unit = [d / length for d in delta]
        accel = _limit([self.settings[120 + i] for i in range(N_AXIS)], unit)
        rapid_rate = _limit([self.settings[110 + i] for i in range(N_AXIS)], unit)
        rate = rapid_rate if rapid else min(feed, rapid_rate)
        self._planner.append(Block(list(start), list(target), length, unit, rate / 60.0, accel, homing))

    def _queued(self) -> int:
        """Planner blocks in use, the running one included (plan_get_block_buffer_available)."""
        return len(self._planner) + (self._block is not None)

    def _spmm(self, axis: int) -> float:
        return float(self.settings[100 + axis])

    def _start_block(self) -> None:
        if self._block is None and self._planner:
            self._block = self._planner.pop(0)
            self._v = 0.0

    def _stepper(self, now: float) -> None:
        dt, self._last_tick = max(0.0, now - self._last_tick), now
        block = self._block
        if block is None or dt == 0.0 or self._booting_until is not None:
            return
        if self.state in ("Hold", "Door") and not self._hold:
            return
        block.s, self._v = advance(block.s, self._v, block.length, block.rate, block.accel, dt, self._hold)
        self._mpos = block.point()
        if self._physics(block):
            return
        if block.s >= block.length:
            self._mpos = list(block.target)
            self._block, self._v = None, 0.0
            if block.homing is not None:
                return  # the homing sequencer takes over
            if self._planner and not self._hold and self.state in ("Run", "Jog"):
                self._start_block()
            else:
                self._flags.add("cycle_stop")
        elif self._hold and self._v == 0.0:
            # The hold is complete: what is left of the block is planned again, from rest.
            rest = Block(list(self._mpos), block.target, block.length - block.s, block.unit, block.rate,
                         block.accel, block.homing)
            self._planner.insert(0, rest)
            self._block = None
            self._flags.add("cycle_stop")

    def _physics(self, block: Block) -> bool:
        """The rail behind the controller: stalls at the mechanical stops, switches. True: the block ended."""
        for i in range(N_AXIS):
            p = self._mpos[i] + self._offset[i]
            if p > STOP_MARGIN or p < -self.span[i] - STOP_MARGIN:
                stop = STOP_MARGIN if p > 0 else -self.span[i] - STOP_MARGIN
                self._offset[i] += stop - p  # the motor stalls: steps counted, carriage still
                self.crashes += 1
        pressed = self._switches()
        if block.homing is not None:
            axes, approach = block.homing
            hit = [i for i in axes if i in pressed]
            if approach and hit:
                for i in hit:  # the axis is locked out at its switch
                    p = self._mpos[i] + self._offset[i]
                    self._mpos[i] -= p - (0.0 if p > 0 else -self.span[i])
                self._homing["locked"] |= set(hit)
                self._block, self._v = None, 0.0
                return True
            return False
        self._limit_pin_change()
        return self._block is None

    def _limit_pin_change(self) -> None:
        """The limit pin-change interrupt (limits.c): with hard limits on, any change of a switch, closing or
        opening, moving or standing, kills everything and throws ALARM:1; ignored in Alarm and while homing
        (limits_disable() for the cycle)."""
        pins = frozenset(self._switches())
        changed, self._pins = pins != self._pins, pins
        if (changed and self.settings[21] and self.state != "Alarm" and self._homing is None
                and not self._exec_alarm and self._booting_until is None):
            self._mc_reset()
            self._exec_alarm = 1

    def _switches(self) -> dict[int, bool]:
        pressed = {}
        for i in range(N_AXIS):
            p = self._mpos[i] + self._offset[i]
            if p >= 0.0 or p <= -self.span[i]:  # a switch is closed from its trigger point on
                pressed[i] = True
        return pressed

    # ------------------------------------------------------------------ homing (limits.c limits_go_home)

    def _homing_cycle(self, now: float) -> None:
        """Search, pull-off, locate, pull-off for each cycle; only Ctrl-X (or the door) interrupts it."""
        h = self._homing
        if self._flags & {"reset", "door"}:
            self._exec_alarm = self._exec_alarm or (6 if "reset" in self._flags else 7)
            return self._homing_failed()
        if self._block is not None:
            return
        if h["phase"] is not None and h["wait"] is None:  # this phase's motion just ended
            approach = h["phase"] in (0, 2)
            pressed = self._switches()
            if approach and not set(h["axes"]) <= h["locked"]:
                if h["locked"] and h["left"] > 1e-9:  # some axes locked: the others go on
                    return self._homing_move(h["left"], h["rate"], [i for i in h["axes"] if i not in h["locked"]])
                self._exec_alarm = 9  # no switch within the search distance
                return self._homing_failed()
            if not approach and any(i in pressed for i in h["axes"]):
                self._exec_alarm = 8  # the pull-off did not clear the switch
                return self._homing_failed()
            h["wait"] = now + self.settings[26] / 1000.0  # debounce delay
            return
        if h["wait"] is not None:
            if now < h["wait"]:
                return
            h["wait"] = None
            if h["phase"] == 3:
                self._set_home(h["axes"])
                h["phase"] = None
        if h["phase"] is None:
            if not h["cycles"]:
                return self._homing_done()
            h["axes"], h["phase"] = h["cycles"].pop(0), -1
        h["phase"] += 1
        h["locked"] = set()
        for i in h["axes"]:  # every phase counts from machine 0 on the cycle's axes (sys_position[idx] = 0)
            self._offset[i] += self._mpos[i]
            self._mpos[i] = 0.0
        if h["phase"] == 0:
            distance = HOMING_SEARCH_SCALAR * max(self.settings[130 + i] for i in h["axes"])
            rate = self.settings[25]
        elif h["phase"] == 2:
            distance, rate = self.settings[27] * HOMING_LOCATE_SCALAR, self.settings[24]
        else:
            distance, rate = self.settings[27], self.settings[25]
        self._homing_move(distance, rate, list(h["axes"]))

    def _homing_done(self) -> None:
        """mc_homing_cycle()'s realtime check point, still in the Home state: a '?' flagged during the cycle is
        answered now, once; a feed hold or cycle start flagged during it has nothing to hold or start and is
        dropped. Then system.c sets Idle, runs the startup lines and answers the '$H'."""
        self._homing = None
        if "status" in self._flags:
            self._write_line(self._status_report())
        self._flags -= {"status", "feed_hold", "cycle_start"}
        self.state = "Idle"
        self._gc.position = self._reported_mpos()
        self._run_startup_lines()
        self._write_line("ok")

    def _homing_move(self, distance: float, rate: float, axes: list[int]) -> None:
        h = self._homing
        approach = h["phase"] in (0, 2)
        target = list(self._mpos)
        for i in axes:
            toward_minus = bool(int(self.settings[23]) & (1 << i))
            target[i] += (-distance if toward_minus == approach else distance)
        start = list(self._mpos)
        self._plan(target, rate * math.sqrt(len(axes)), rapid=False, homing=(tuple(axes), approach))
        self._start_block()
        h["rate"] = rate
        self.when(lambda f: f._block is None, lambda f: h.__setitem__(
            "left", distance - max(abs(a - b) for a, b in zip(f._mpos, start))))

    def _set_home(self, axes: tuple[int, ...]) -> None:
        """Machine position after the cycle: -pull-off (or pull-off - travel homing to the - end)."""
        for i in axes:
            if int(self.settings[23]) & (1 << i):
                steps = _lround((-self.settings[130 + i] + self.settings[27]) * self._spmm(i))
            else:
                steps = _lround(-self.settings[27] * self._spmm(i))
            physical = self._mpos[i] + self._offset[i]
            self._mpos[i] = steps / self._spmm(i)
            self._offset[i] = physical - self._mpos[i]

    def _homing_failed(self) -> None:
        """The alarm, then system_execute_line() still answers $H, then main() re-initialises."""
        self._block, self._v, self._homing = None, 0.0, None
        code, self._exec_alarm = self._exec_alarm, 0
        self.state = "Alarm"
        self.events.append(("alarm", code))
        self._write_line(f"ALARM:{code}")
        self._busy_until = self.now() + ALARM_DELAY

        def then_reset() -> None:
            self._write_line("ok")
            self._reinit()
        self._after_busy = then_reset

    # ------------------------------------------------------------------ reports (report.c)

    def _state_name(self) -> str:
        if self.state == "Hold":
            if "jog_cancel" in self._suspend:
                return "Jog"
            return "Hold:0" if "hold_complete" in self._suspend else "Hold:1"
        if self.state == "Door":
            if "hold_complete" not in self._suspend and self._hold:
                return "Door:2"
            return "Door:1" if self._door_ajar else "Door:0"
        return self.state

    def _reported_mpos(self) -> list[float]:
        return [_lround(m * self._spmm(i)) / self._spmm(i) for i, m in enumerate(self._mpos)]

    def _status_report(self) -> str:
        mask = int(self.settings[10])
        position = self._reported_mpos()
        wco = [self._coords[self._gc.coord_select][i] + self._gc.g92[i] for i in range(N_AXIS)]
        fields = [self._state_name()]
        if mask & 1:
            fields.append("MPos:" + self._axis_text(position))
        else:
            fields.append("WPos:" + self._axis_text([p - w for p, w in zip(position, wco)]))
        if mask & 2:
            fields.append(f"Bf:{PLANNER_BLOCKS - self._queued()},{self.rx_size - len(self._rx) + self._held}")
        fields.append(f"FS:{self._rate_text(self._v * 60.0)},0")
        pins = "".join(a for i, a in enumerate("XYZ") if i in self._switches()) + ("D" if self._door_ajar else "")
        if pins:
            fields.append("Pn:" + pins)
        busy = self.state in ("Home", "Run", "Hold", "Jog", "Door")
        if self._wco_counter > 0:
            self._wco_counter -= 1
        else:
            self._wco_counter = 29 if busy else 9
            self._ovr_counter = self._ovr_counter or 1
            fields.append("WCO:" + self._axis_text(wco))
        if self._ovr_counter > 0:
            self._ovr_counter -= 1
        else:
            self._ovr_counter = 19 if busy else 9
            fields.append("Ov:100,100,100")
        return "<" + "|".join(fields) + ">"

    def _coord_text(self, mm: float) -> str:
        return f"{mm / MM_PER_INCH:.4f}" if self.settings[13] else f"{mm:.3f}"

    def _axis_text(self, values: list[float]) -> str:
        return ",".join(self._coord_text(v) for v in values)

    def _rate_text(self, mm_per_min: float) -> str:
        return f"{mm_per_min / MM_PER_INCH:.1f}" if self.settings[13] else f"{mm_per_min:.0f}"


def _modal_group(letter: str, value: float) -> str | None:
    """The modal group of a G or M word (None: not supported here)."""
    if letter == "G":
        if 54 <= value <= 59 and value == int(value):
            return "coord"
        if math.isclose(value, 92.1):
            return "nonmodal"
        return {0: "motion", 1: "motion", 4: "nonmodal", 10: "nonmodal", 17: "plane", 20: "units", 21: "units",
                53: "g53", 90: "distance", 91: "distance", 92: "nonmodal", 94: "feedmode"}.get(value)
    if value != int(value):
        return None
    return {0: "stop", 2: "stop", 30: "stop", 3: "spindle", 4: "spindle", 5: "spindle", 8: "coolant",
            9: "coolant"}.get(int(value))


def _limit(maxima: list[float], unit: list[float]) -> float:
    """planner.c limit_value_by_axis_maximum(): the largest vector value no axis exceeds."""
    return min(abs(m / u) for m, u in zip(maxima, unit) if u != 0.0)
