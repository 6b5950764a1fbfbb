"""GrblRail through real pyserial on a pseudo-terminal, against a fake GRBL 1.1h firmware that follows the
firmware's documented behaviour (tests/fake_grbl.py).

Every scenario ends in a completed move or a typed error, and never with the carriage still moving.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import serial

from fake_grbl import FakeGrbl, advance
from psfd.cli import main
from psfd.drivers import open_rail
from psfd.drivers.base import Position, Rail, RailInfo
from psfd.drivers.grbl import GrblRail, PortLock, homing_time, move_time, parse_status
from psfd.drivers.grbl_guard import watch
from psfd.errors import RailAlarm, RailError

# A bench rail that moves quickly (100 mm/s, 200 mm/s^2) and homes in about a second; homing off, as grbl ships.
BENCH = {110: 6000, 111: 6000, 112: 6000, 120: 200, 121: 200, 122: 200, 24: 600, 25: 3000, 26: 10}
HOMING = {**BENCH, 22: 1}
SLOW = {**BENCH, 110: 1200}  # 20 mm/s: a 150 mm move lasts 7.5 s, time enough to interrupt it
FEED_HOLD = ord("!")


@pytest.fixture
def make_fake():
    fakes = []

    def make(settings: dict | None = None, **options) -> FakeGrbl:
        options.setdefault("homing_cycles", ((0,),))  # a one-axis rail's firmware homes X only
        fakes.append(FakeGrbl({**BENCH, **(settings or {})}, **options))
        return fakes[-1]

    yield make
    for fake in fakes:
        fake.close()


@pytest.fixture
def connect():
    rails = []

    def open_(fake: FakeGrbl, **options) -> GrblRail:
        options = {"poll": 0.02, **options}  # the default 2 s exchange timeout: tests run on loaded machines
        rails.append(GrblRail(fake.port, **options))
        return rails[-1]

    yield open_
    for rail in rails:
        rail.close()


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def psfd_process(*argv: str) -> subprocess.Popen:
    """psfd as started from a terminal: Ctrl-C at its default, even where the tests run as a background job
    (a non-interactive shell starts those with SIGINT ignored, and Python then keeps it ignored)."""
    def terminal_defaults() -> None:
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.signal(signal.SIGHUP, signal.SIG_DFL)  # ignored under nohup, and kept so by the child
    return subprocess.Popen([sys.executable, "-m", "psfd", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=terminal_defaults)


def settled(fake: FakeGrbl) -> bool:
    """The carriage stands and stays standing."""
    first = fake.physical_position()
    time.sleep(0.2)
    return not fake.moving and fake.physical_position() == first


# ---------------------------------------------------------------------------------------------- parsing, timing


def test_parse_status_formats():
    status, wco = parse_status("<Run|MPos:12.000,3.500,0.000|FS:500,0|WCO:2.000,0.500,0.000>")
    assert status.state == "Run" and status.position == (10.0, 3.0, 0.0) and wco == (2.0, 0.5, 0.0)
    assert status.machine == (12.0, 3.5, 0.0) and status.feed == 500.0
    status, _ = parse_status("<Hold:0|MPos:12.000,3.500,0.000|FS:0,0>", wco)  # WCO is remembered
    assert status.name == "Hold:0" and status.state == "Hold" and status.position == (10.0, 3.0, 0.0)
    status, _ = parse_status("<Idle|WPos:-1.000,0.000,0.000|FS:0,0|Pn:XD>", (2.0, 0.0, 0.0))  # $10=0
    assert status.machine == (1.0, 0.0, 0.0) and status.pins == "XD"
    status, _ = parse_status("<Idle|MPos:-3.9370,0.0000,0.0000|FS:0.0,0>", scale=25.4)  # $13=1: inches
    assert status.position[0] == pytest.approx(-100.0, abs=0.003)
    status, _ = parse_status("<Idle,MPos:5.529,0.560,7.000,WPos:1.529,-5.440,-0.000>")  # GRBL 0.9
    assert status.state == "Idle" and status.position == (1.529, -5.44, 0.0)
    with pytest.raises(RailError, match="unreadable"):
        parse_status("<garbage>")


@pytest.mark.parametrize("distance, rate, accel", [(100.0, 500.0, 10.0), (2.0, 60.0, 1.0), (0.5, 6000.0, 200.0)])
def test_move_time_matches_the_firmware_profile(distance, rate, accel):
    # The driver's closed form against the fake's step-by-step profile (two independent readings of planner.c).
    s = v = t = 0.0
    while s < distance:
        s, v = advance(s, v, distance, rate / 60.0, accel, 0.001, hold=False)
        t += 0.001
    assert move_time([distance], [rate], [accel]) == pytest.approx(t, abs=0.002)
    # a diagonal is held to the slowest axis' share of its rate and acceleration
    diagonal = move_time([30.0, 40.0], [600.0, 60000.0], [5.0, 500.0])
    assert diagonal == pytest.approx(move_time([50.0], [1000.0], [25 / 3]))


def test_homing_deadline_follows_seek_rate_and_travel():
    settings = {24: 25.0, 25: 500.0, 26: 250, 27: 1.0, 110: 500.0, 111: 500.0, 112: 500.0, 120: 10.0, 121: 10.0,
                122: 10.0, 130: 2000.0, 131: 200.0, 132: 200.0}
    # a 2 m rail at the default seek rate: the search alone may last 1.5 x 2000 mm / (500 mm/min) = 360 s
    assert homing_time(settings) > 360.0 > 240.0  # the first driver allowed a fixed 120 s


def test_homing_deadline_bounds_a_cycle_whose_seek_rate_the_max_rate_caps(make_fake):
    """The planner caps a homing motion at the axis' $110 like any other (planner.c): with $25 above it the
    search runs at $110, and the deadline follows. The driver's closed form against the fake's simulated cycle
    from the far end of the rail (the longest that succeeds), on the fake's own clock."""
    fake = make_fake({**HOMING, 25: 6000, 110: 600, 130: 20}, start=(-22.0, -50.0, -50.0), time_scale=4.0)
    link, say = serial_link(fake)
    started = fake.now()
    link.write(b"$H\n")
    assert fake.wait_for(lambda f: f.written.endswith(b"ok\r\n"), timeout=10) and fake.crashes == 0
    took = fake.now() - started  # simulated seconds, a few ms of polling included
    assert took < homing_time(fake.settings, cycles=((0,),)) < 2 * took
    link.close()


# ---------------------------------------------------------------------------------------------- the fake itself


def test_fake_follows_the_documented_alarm_behaviour(make_fake):
    """Boot lock, error:9, $X, the critical soft-limit alarm that only Ctrl-X ends: as interface.md says."""
    fake = make_fake({22: 1, 20: 1}, time_scale=0.5)  # the firmware's 500 ms alarm delay lasts 1 s here
    link = serial.Serial(fake.port, 115200, timeout=0.3)

    def say(data: bytes, wait: float = 0.15) -> list[str]:
        link.write(data)
        time.sleep(wait)
        return [ln for ln in link.read(4096).decode().split("\r\n") if ln]

    assert say(b"?")[0].startswith("<Alarm|MPos:0.000,0.000,0.000|FS:0,0|WCO:")
    assert say(b"G0 X-1\n") == ["error:9"]
    assert say(b"$X\n") == ["[MSG:Caution: Unlocked]", "ok"]
    link.write(b"G1 X10 F100\n")
    assert fake.wait_for(lambda f: 2 in f.alarms())
    assert say(b"\x18", 1.3) == ["ALARM:2", "[MSG:Reset to continue]"]  # a reset during the delay is forgotten
    assert say(b"?") == [] and say(b"$$\n") == []  # deaf: not even a status report
    assert say(b"\x18", 0.3) == ["ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    link.close()


def test_fake_feed_hold_and_reset_in_motion_as_the_firmware(make_fake):
    """commands.md: `!` decelerates to a stop (Hold:1, then Hold:0); a reset in motion throws ALARM:3, and a
    reset in a completed hold keeps the position (protocol.c clears STEP_CONTROL_EXECUTE_HOLD at the cycle
    stop that completes the hold; mc_reset kills the steppers only in a cycle, a jog or an executing hold)."""
    fake = make_fake({**SLOW, 120: 20})  # 20 mm/s braked at 20 mm/s^2: a hold decelerates for 1 s
    link = serial.Serial(fake.port, 115200, timeout=0.3)
    link.write(b"G0 X-150\n")
    assert fake.wait_for(lambda f: f.machine_position()[0] < -10.0)
    link.write(b"!")
    assert fake.wait_for(lambda f: f.status() == "Hold:1", timeout=1)
    assert fake.wait_for(lambda f: f.status() == "Hold:0", timeout=2)
    held = fake.machine_position()[0]
    link.write(b"\x18")
    assert fake.wait_for(lambda f: f.status() == "Idle") and settled(fake)
    assert fake.resets() == ["Hold:0"] and fake.alarms() == [] and fake.machine_position()[0] == held
    link.write(b"G0 X-150\n")  # the rest of the first move was dropped: this one starts from where it stood
    assert fake.wait_for(lambda f: f.machine_position()[0] < held - 10.0)
    link.write(b"!")
    assert fake.wait_for(lambda f: f.status() == "Hold:1", timeout=1)
    link.write(b"\x18")  # while still decelerating
    assert fake.wait_for(lambda f: f.alarms() == [3])
    assert fake.resets()[-1] == "Hold:1" and not fake.moving
    link.close()


def test_fake_dwell_homing_and_sleep_as_the_firmware(make_fake):
    """G4 answers once the buffered motion has run and the dwell has passed (motion_control.c mc_dwell:
    protocol_buffer_synchronize, then delay_sec); a completed $H runs the startup lines before its 'ok'
    (system.c); $SLP is answered, then the sleep holds the main program until a reset, which ends in Alarm
    (protocol.c)."""
    fake = make_fake(time_scale=2.0)
    fake.startup_lines[0] = "G21G90"
    link = serial.Serial(fake.port, 115200, timeout=0.3)

    def say(data: bytes, wait: float = 0.15) -> list[str]:
        link.write(data)
        time.sleep(wait)
        return [ln for ln in link.read(4096).decode().split("\r\n") if ln]

    arrived = []
    fake.when(lambda f: not f.moving and f.machine_position()[0] == -50.0,
              lambda f: arrived.append((f.now(), f.written.count(b"ok"))))
    assert say(b"G0 X-50\nG4 P1\n", 0.05) == ["ok"]  # the motion line is buffered at once, the dwell waits
    assert fake.wait_for(lambda f: f.written.count(b"ok") == 2)
    done = fake.now()
    assert arrived[0][1] == 1 and done - arrived[0][0] >= 1.0  # answered after the move and then one second
    assert say(b"G4 P-1\n") == ["ok", "error:4"]  # the dwell's 'ok'; P, like F, N, S and T, is never negative

    fake.settings[22] = 1
    assert say(b"$H\n", 1.5) == [">G21G90:ok", "ok"]
    assert say(b"$SLP\n") == ["ok", "[MSG:Sleeping]"]
    assert say(b"G0 X-20\n") == [] and not fake.moving  # held with the main program
    assert say(b"?")[0].startswith("<Sleep|")
    assert say(b"\x18") == ["Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert say(b"?")[0].startswith("<Alarm|MPos:-1.000,") and fake.lines[-1] == "$SLP"  # the G0 was dropped
    link.close()


def serial_link(fake: FakeGrbl):
    """A raw serial link to the fake and ``say(bytes, wait)``: what came back within ``wait`` seconds, by line."""
    link = serial.Serial(fake.port, 115200, timeout=0.3)

    def say(data: bytes, wait: float = 0.15) -> list[str]:
        link.write(data)
        time.sleep(wait)
        return [ln for ln in link.read(4096).decode().split("\r\n") if ln]
    return link, say


def test_fake_homing_answers_realtime_bytes_as_the_firmware(make_fake):
    """limits.c runs no realtime check point during the cycle: a '?' is flagged, not answered, and served once
    by mc_homing_cycle's protocol_execute_realtime() after the last cycle, still in the Home state and at the
    homed position, before system.c sets Idle, runs the startup lines and answers 'ok' (gnea/grbl#1061). A
    feed hold or cycle start flagged meanwhile finds no motion to hold or start there and is dropped: the
    controller ends Idle, not in a hold."""
    fake = make_fake({**HOMING, 25: 600}, start=(-20.0, -50.0, -50.0), time_scale=2.0)  # a 2 s search
    fake.startup_lines[0] = "G21"
    link, say = serial_link(fake)
    link.write(b"$H\n")
    assert fake.wait_for(lambda f: f.status() == "Home" and f.moving)
    assert say(b"??!~", 0.3) == []  # the search goes on, in silence
    assert fake.moving and fake.status() == "Home"
    assert fake.wait_for(lambda f: f.written.endswith(b"ok\r\n"), timeout=10)
    answer = say(b"", 0.1)
    assert len(answer) == 3 and answer[0].startswith("<Home|MPos:-1.000,") and answer[1:] == [">G21:ok", "ok"]
    assert say(b"?")[0].startswith("<Idle|MPos:-1.000,") and fake.status() == "Idle"
    assert say(b"G0 X-5\n") == ["ok"] and fake.wait_for(lambda f: f.machine_position()[0] == -5.0)
    link.close()


def test_fake_homing_reset_and_failure_as_the_firmware(make_fake):
    """A reset during the cycle: mc_reset() kills the steppers at once (ALARM:6); limits.c zeroes the machine
    position of the cycle's axes at the start of every phase, so the controller then reads the distance of the
    interrupted phase. A '?' flagged in the cycle is cleared by the abort. After the alarm's 500 ms delay
    system.c still answers the '$H' ('ok'), then main() re-initialises: banner, lock message. A switch not found
    within 1.5 x $130 is ALARM:9 with the same sequel."""
    fake = make_fake({**HOMING, 25: 600}, start=(-40.0, -50.0, -50.0), time_scale=2.0)
    link, say = serial_link(fake)
    assert say(b"$X\nG0 X-5\n") == ["[MSG:Caution: Unlocked]", "ok", "ok"]
    assert fake.wait_for(lambda f: f.status() == "Idle" and f.machine_position()[0] == -5.0)
    link.write(b"$H\n")
    assert fake.wait_for(lambda f: f.status() == "Home" and f.physical_position()[0] > -30.0)
    assert say(b"?", 0.1) == []
    lines = say(b"\x18", 0.6)
    searched = fake.physical_position()[0] + 45.0  # what the search covered before the reset
    assert lines == ["ALARM:6", "ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert not fake.moving and fake.alarms() == [6] and fake.resets() == ["Home"]
    assert fake.machine_position()[0] == pytest.approx(searched, abs=0.01) and 10.0 < searched < 40.0
    assert say(b"?")[0].startswith("<Alarm|")
    link.close()

    fake = make_fake({**HOMING, 130: 20}, span=(500.0, 500.0, 500.0), start=(-100.0, -50.0, -50.0))
    link, say = serial_link(fake)
    link.write(b"$H\n")
    assert fake.wait_for(lambda f: f.alarms() == [9])
    assert say(b"", 0.7) == ["ALARM:9", "ok", "Grbl 1.1h ['$' for help]", "[MSG:'$H'|'$X' to unlock]"]
    assert say(b"?")[0].startswith("<Alarm|MPos:30.000,")  # the whole search, 1.5 x $130, counted from 0
    link.close()


def test_fake_planner_and_serial_buffer_as_the_firmware(make_fake):
    """planner.c: 16 blocks, one kept free, the running block among them: 15 motion lines are acknowledged and
    the 16th waits in mc_line(), already read out of the 128-byte RX ring (protocol.c reads it character by
    character), so the ring has room for the 128 bytes after it; what comes beyond is lost (serial.c)."""
    fake = make_fake({10: 3, 110: 60})  # 1 mm/s: nothing completes meanwhile
    link = serial.Serial(fake.port, 115200, timeout=0.3)
    for n in range(1, 16):
        link.write(b"G1X-%dF60\n" % (5 * n))
        assert fake.wait_for(lambda f: len(f.lines) == n)
    link.write(b"G1X-80F60\n")  # the 16th
    time.sleep(0.2)
    assert link.read(4096).decode().split() == ["ok"] * 15
    link.write(b"G1X-2F60\n" * 15)  # 135 bytes behind the waiting line: the last 7 are lost
    time.sleep(0.2)
    link.write(b"?")
    time.sleep(0.2)
    assert re.search(r"\|Bf:0,0\|", link.read(4096).decode())
    link.close()


def test_fake_drops_a_cycle_start_flagged_with_a_hold(make_fake):
    """protocol.c: a cycle start set in the same pass as a feed hold is dropped ("auto-cycle-start doesn't
    resume a hold without an explicit user-input"): a '!' meeting the auto cycle start of a line just taken
    leaves the move queued in Hold:0 until '~'."""
    fake = make_fake()
    fake.when(lambda f: "cycle_start" in f._flags and f._planner, lambda f: f._flags.add("feed_hold"))
    link = serial.Serial(fake.port, 115200, timeout=0.3)
    link.write(b"G0 X-50\n")
    assert fake.wait_for(lambda f: f.status() == "Hold:0") and settled(fake)
    assert fake.machine_position()[0] == 0.0
    link.write(b"~")
    assert fake.wait_for(lambda f: f.status() == "Idle" and f.machine_position()[0] == -50.0)
    link.close()


# ---------------------------------------------------------------------------------------------- connecting


def test_a_startup_line_that_moves_the_carriage_is_refused_at_open(make_fake, connect):
    """GRBL runs its startup lines after every reset that ends Idle (protocol.c), and psfd resets after every
    stop: a line that moves the carriage (or shifts its coordinates) would run unattended after each one."""
    fake = make_fake()
    fake.startup_lines[1] = "G0X-20"
    with pytest.raises(RailError, match=r"startup line \$N1=G0X-20 runs after every reset.*send `\$N1=`"):
        connect(fake)
    assert fake.machine_position()[0] == 0.0 and fake.resets() == []  # refused before anything moved it
    fake.startup_lines[1] = "G21G90"  # modes only: harmless, and run after the resets psfd sends
    rail = connect(fake)
    assert rail.move(x=-5).x == -5.0


def send_lines(fake: FakeGrbl, *lines: str) -> None:
    """G-code a person sent from a terminal before psfd opened the port, each answered 'ok'."""
    link = serial.Serial(fake.port, 115200, timeout=2.0)
    for line in lines:
        link.write(line.encode() + b"\n")
        assert link.readline().strip() == b"ok", line
    link.close()


@pytest.mark.parametrize("lines, refused", [
    (["G92 X-10"], r"a G92 offset is active \(X=10"),
    (["G10 L2 P2 X-30", "G55"],
     r"work coordinates G55 are active, but a reset.* selects G54 \(X=0 mm against X=-30 mm\)"),
])
def test_a_work_origin_that_a_reset_would_change_is_refused_at_open(make_fake, connect, lines, refused):
    """GRBL clears G92 offsets and selects G54 (or its startup line's system) at every reset (gc_init), and
    psfd resets after every stop: from then on a plan's positions would lie elsewhere on the rail than those
    before it, under the same names in the catalogue. The G54-G59 offsets themselves are kept in EEPROM."""
    fake = make_fake()
    send_lines(fake, *lines)
    with pytest.raises(RailError, match=refused):
        connect(fake)
    assert fake.machine_position()[0] == 0.0 and fake.resets() == []


def test_a_work_origin_kept_across_resets_is_accepted(make_fake, connect):
    """A G54 zero set with G10 L20 (EEPROM), or G55 selected by a startup line as well: the same after a reset."""
    fake = make_fake()
    send_lines(fake, "G10 L20 P1 X10", "G10 L2 P2 X-40", "G55", "$N0=G55")
    rail = connect(fake)
    assert rail.move(x=5).x == 5.0 and fake.machine_position()[0] == pytest.approx(-35.0)


@pytest.mark.parametrize("mode, state, after", [("$C", "Check", "Idle"), ("$SLP", "Sleep", "Alarm")])
def test_a_controller_left_in_check_mode_or_asleep_is_reset_at_once(make_fake, connect, mode, state, after):
    """Check mode ($C) and sleep ($SLP) ignore a feed hold (protocol.c: no hold in STATE_CHECK_MODE; SLEEP is
    kept from changing to HOLD) and nothing moves in them: the open resets at the first report after its feed
    hold instead of waiting for a Hold:0 that never comes. Sleep comes back as Alarm (protocol_main_loop)."""
    fake = make_fake()
    link = serial.Serial(fake.port, 115200, timeout=0.2)
    link.write(mode.encode() + b"\n")
    assert fake.wait_for(lambda f: f.status() == state)
    link.close()
    rail = connect(fake)
    sent = [byte for _, byte in fake.realtime]
    hold, reset = sent.index(FEED_HOLD), sent.index(0x18)
    assert sent[hold + 1:reset] == [ord("?")]  # one report after the feed hold, then the reset
    assert fake.resets() == [state] and fake.alarms() == []
    assert rail.info().state == after


def test_info_gives_where_a_restarted_controller_reads_in_work_coordinates(make_fake, connect):
    """GRBL counts from machine position 0 at power-up (main.c) and keeps the G54 offset in EEPROM: in the
    work coordinates psfd moves in, a restarted controller reads minus the work offset."""
    fake = make_fake()
    with fake._lock:
        fake._coords[0][0] = -200.0  # G10 L2 P1 X-200, stored once: distances from the - end, positive
    rail = connect(fake)
    info = rail.info()
    assert info.travel == {"x": (0.0, 200.0)} and info.power_up == {"x": 200.0}
    assert rail.position().x == 200.0  # this controller has just booted


def test_open_reads_the_controller_and_does_not_reset_it(make_fake, connect):
    fake = make_fake()
    rail = connect(fake)
    assert isinstance(rail, Rail)
    assert fake.resets() == [] and "$$" in fake.lines  # the first driver reset GRBL at every open
    info = rail.info()
    assert info == RailInfo(controller="Grbl 1.1h.20190825", axes=("x",), travel={"x": (-200.0, 0.0)}, units="mm",
                            homing=False, state="Idle", power_up={"x": 0.0})
    assert rail.position() == Position(0.0, None, None)


def test_home_to_the_plus_end_gives_negative_coordinates(make_fake, connect):
    fake = make_fake({22: 1}, start=(-30.0, -50.0, -50.0))
    rail = connect(fake, limits={"x": (-200, 0), "y": (-50, 50)})
    assert rail.info().travel == {"x": (-200.0, 0.0), "y": (-50.0, 0.0)}  # the config narrows, never widens
    assert rail.home() == Position(-1.0, 0.0, None)  # GRBL homes to + and backs off $27
    assert fake.physical_position()[0] == pytest.approx(-1.0)  # 1 mm inside the switch
    assert rail.move(x=-150.0) == Position(-150.0, 0.0, None)
    sent = len(fake.lines)
    with pytest.raises(RailError, match=r"X=10 mm is outside the rail's travel \[-200, 0\] mm"):
        rail.move(x=10)
    with pytest.raises(RailError, match=r"rail has no Z axis"):
        rail.move(x=-10, z=5)
    assert len(fake.lines) == sent  # refused before anything was sent


def test_configured_limits_outside_the_controller_travel_are_refused(make_fake):
    fake = make_fake()
    with pytest.raises(RailError, match=r"rail_limits X=\[0, 500\] mm lie outside the controller's travel \[-200, 0\]"):
        GrblRail(fake.port, limits={"x": (0, 500)})
    with pytest.raises(RailError, match="min 5 is above max 1"):
        GrblRail(fake.port, limits={"x": (5, 1)})
    with pytest.raises(RailError, match="unknown rail axis"):
        GrblRail(fake.port, limits={"x": (0, 1), "w": (0, 1)})


def test_open_rail_config_keys_still_work(make_fake):
    fake = make_fake()
    rail = open_rail({"rail_port": fake.port, "rail_limits": {"x": [-100, 0]}, "rail_baudrate": 115200,
                      "rail_feed": 3000, "rail_timeout": 0.5})
    try:
        assert rail.info().travel == {"x": (-100.0, 0.0)}
        assert rail.move(x=-5).x == -5.0 and fake.lines[-1] == "G90 G21 G1 X-5.0000 F3000"
    finally:
        rail.close()


def test_second_opener_is_refused_with_the_holder_pid(make_fake, connect):
    fake = make_fake()
    rail = connect(fake)
    with pytest.raises(RailError, match=rf"rail {fake.port} in use by pid {os.getpid()} "):
        GrblRail(fake.port, timeout=0.5)
    lock = PortLock(fake.port).path
    assert lock.read_text().strip() == str(os.getpid())
    rail.close()
    assert not lock.exists()
    connect(fake).close()  # free again


def test_without_a_lock_directory_the_device_lock_still_refuses(make_fake, connect, monkeypatch, tmp_path):
    monkeypatch.setenv("PSFD_LOCK_DIR", str(tmp_path / "absent"))  # e.g. a sandbox without /run/lock
    fake = make_fake()
    rail = connect(fake)
    with pytest.raises(RailError, match=rf"rail {fake.port} in use by pid {os.getpid()} "):
        GrblRail(fake.port, timeout=0.5)  # pyserial's exclusive flock, holder read from /proc/locks
    rail.close()
    connect(fake).close()


def test_grblhal_banner_and_boot_alarm(make_fake, connect):
    fake = make_fake({22: 1}, flavour="grblhal", auto_reset=True, boot_time=0.3, start=(-5.0, -50.0, -50.0))
    rail = connect(fake)
    assert rail.banner == "GrblHAL 1.1f ['$' or '$HELP' for help]" and rail.info().controller.startswith("GrblHAL")
    with pytest.raises(RailAlarm, match="homing needed"):
        rail.move(x=-10)
    assert rail.home().x == -1.0 and rail.move(x=-10).x == -10.0


def test_fluidnc_subset_of_settings(make_fake, connect):
    fake = make_fake({130: 800}, flavour="fluidnc")
    rail = connect(fake)
    assert rail.info().controller.startswith("FluidNC") and rail.info().travel == {"x": (-800.0, 0.0)}
    assert rail.move(x=-20).x == -20.0


def test_silent_controller_is_probed_not_reset(make_fake, connect):
    fake = make_fake(wake_on_line=True)  # answers nothing, not even '?', until it receives a whole line
    rail = connect(fake)
    assert "$I" in fake.lines and fake.resets() == []
    assert rail.move(x=-3).x == -3.0


def test_arduino_auto_reset_happens_only_at_the_first_open(make_fake, connect):
    fake = make_fake(auto_reset=True, boot_time=0.3)
    rail = connect(fake)
    assert rail.rebooted and rail.move(x=-20).x == -20.0
    rail.close()
    assert fake.wait_for(lambda f: not f.peer_open)  # the next command is another process, later
    rail = connect(fake)  # HUPCL cleared at the first open: DTR stayed up, no edge, no reboot
    assert not rail.rebooted and rail.position().x == -20.0
    assert [e for e in fake.events if e[0] == "boot"] == [("boot",)]


# ---------------------------------------------------------------------------------------------- settings-derived


def test_inch_reports_are_converted(make_fake, connect):
    fake = make_fake({13: 1})
    rail = connect(fake)
    assert rail.units == "inch" and rail.info().travel == {"x": (-200.0, 0.0)}  # settings stay in mm
    assert rail.move(x=-100.0).x == pytest.approx(-100.0, abs=0.003)
    assert fake.machine_position()[0] == -100.0


def test_slow_rail_completes_within_its_own_deadline(make_fake, connect):
    fake = make_fake({110: 60, 120: 1})  # 1 mm/s and 1 mm/s^2: 2 mm take 3 s
    rail = connect(fake)
    start = time.monotonic()
    assert rail.move(x=-2.0).x == -2.0
    assert time.monotonic() - start >= 2.9


def test_arrival_tolerance_follows_steps_per_mm(make_fake, connect):
    fake = make_fake({100: 25})  # 0.04 mm steps: GRBL lands on the nearest step
    rail = connect(fake)
    reached = rail.move(x=-10.02).x
    assert reached == fake.machine_position()[0] and abs(reached + 10.02) <= 0.5 / 25 + 0.001


# ---------------------------------------------------------------------------------------------- stopping


@pytest.mark.parametrize("sig, code, word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_signal_mid_move_stops_the_carriage_and_frees_the_port(make_fake, connect, sig, code, word):
    fake = make_fake(SLOW)
    proc = psfd_process("rail", "move", "X=-150", "--rail-port", fake.port)
    try:
        assert fake.wait_for(lambda f: f.machine_position()[0] < -20.0, timeout=30)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert proc.returncode == code and err.startswith(f"psfd: {word} (rail stopped at X=-")
    assert settled(fake) and fake.physical_position()[0] > -100.0
    assert fake.resets() == ["Hold:0"] and fake.alarms() == []  # held first, reset once standing: position kept
    assert not fake.peer_open and not PortLock(fake.port).path.exists()
    assert connect(fake).position().x == fake.machine_position()[0]


def test_timeout_is_reported_once_the_carriage_stands(make_fake, connect):
    # A rail slower than its own settings (a feed override, a stalling motor): the fake runs at 1/4 speed.
    fake = make_fake(time_scale=0.25)
    rail = connect(fake)
    with pytest.raises(RailError, match=r"did not reach X=-150 mm within .* s .*; rail stopped at X=-") as caught:
        rail.move(x=-150)
    assert not fake.moving and fake.status() == "Idle"
    assert fake.resets() == ["Hold:0"] and fake.alarms() == []
    assert rail.position().x == fake.machine_position()[0] > -150, caught.value


def test_second_process_is_refused_and_the_move_goes_on(make_fake, capsys):
    fake = make_fake(SLOW)
    proc = psfd_process("rail", "move", "X=-60", "--rail-port", fake.port)
    try:
        assert fake.wait_for(lambda f: f.moving, timeout=30)
        code, _, err = run(capsys, "rail", "position", "--rail-port", fake.port)
        assert code == 4 and err.startswith(f"psfd: error: rail {fake.port} in use by pid {proc.pid} (")
        out, err = proc.communicate(timeout=30)
    finally:
        proc.kill()
    assert proc.returncode == 0 and out == "X=-60\n", err
    assert fake.resets() == [] and fake.alarms() == []


def children(pid: int) -> list[int]:
    """Pids of the children of process ``pid`` (/proc/PID/task/TID/children)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(c) for c in (task / "children").read_text().split()]
    return found


def killed_mid_move(fake, guard_too: bool = False) -> subprocess.Popen:
    """`psfd rail move X=-150` killed with SIGKILL once the carriage is past -20 mm, and reaped; ``guard_too``:
    its guard killed first (a SIGKILL of the whole control group, systemd-oomd)."""
    proc = psfd_process("rail", "move", "X=-150", "--rail-port", fake.port)
    try:
        assert fake.wait_for(lambda f: f.machine_position()[0] < -20.0, timeout=30)
        for pid in children(proc.pid) if guard_too else ():
            os.kill(pid, signal.SIGKILL)
    finally:
        proc.kill()  # SIGKILL: no chance to stop anything
        proc.wait()
    return proc


def test_sigkill_mid_move_is_stopped_by_the_guard(make_fake, connect):
    """kill -9 (the OOM killer, systemd's last SIGKILL of the main pid) mid-move: nothing in the process runs,
    its guard process stops the carriage as a Ctrl-C would (feed hold, Hold:0, reset) without any other
    psfd command opening the port, and then frees the port."""
    fake = make_fake(SLOW)
    proc = killed_mid_move(fake)
    killed_at = fake.machine_position()[0]
    assert fake.wait_for(lambda f: not f.peer_open, timeout=15)  # the guard's copy of the port closed too
    assert settled(fake)
    # 20 mm/s brakes over 1 mm at 200 mm/s^2: the carriage stands within the guard's reaction (tens of ms)
    assert killed_at - 5.0 < fake.machine_position()[0] < -20.0 and fake.physical_position()[0] > -100.0
    assert FEED_HOLD in [byte for _, byte in fake.realtime]
    assert fake.resets() == ["Hold:0"] and fake.alarms() == []  # held, reset standing: no ALARM:3
    assert fake.physical_position()[0] - fake.machine_position()[0] == pytest.approx(-50.0, abs=0.01)  # kept
    assert PortLock(fake.port).path.read_text().strip() == str(proc.pid)  # left behind by the killed process,
    assert connect(fake).position().x == fake.machine_position()[0]  # taken over: its pid is dead


def test_open_right_after_a_sigkill_waits_for_the_guard(make_fake, connect):
    """`psfd run --resume` at once: the dead process's guard still holds the port while it stops the carriage;
    the open waits for it rather than report the port in use by a dead pid."""
    fake = make_fake(SLOW)
    killed_mid_move(fake)
    rail = connect(fake)
    assert fake.resets() == ["Hold:0"] and fake.alarms() == []  # the guard's stop; the open found it standing
    assert settled(fake) and rail.position().x == fake.machine_position()[0] > -100.0


def test_guard_of_a_closed_rail_sends_nothing(make_fake, connect):
    fake = make_fake()
    rail = connect(fake)
    assert rail.position().x == 0.0 and rail._guard is None  # the carriage stands until the first move
    rail.move(x=-10)
    guard = rail._guard
    assert guard.poll() is None  # watching while the rail is open
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGABRT):  # Ctrl-C, `systemctl stop`, watchdog
        os.kill(guard.pid, sig)
    time.sleep(0.2)
    assert guard.poll() is None and os.getsid(guard.pid) == guard.pid  # its own session, signals ignored
    realtime, lines = list(fake.realtime), list(fake.lines)
    rail.close()
    assert guard.returncode == -signal.SIGKILL  # ended, and reaped
    assert fake.realtime == realtime and fake.lines == lines and fake.resets() == []
    assert fake.wait_for(lambda f: not f.peer_open, timeout=2)


def _owner(tmp_path, fake, *lines: str) -> subprocess.Popen:
    """A process that opens the fake's rail as psfd does (its guard and all) and runs ``lines``; stdout piped."""
    script = tmp_path / "owner.py"
    script.write_text("import os, signal, sys, time\nfrom psfd.drivers.grbl import GrblRail\n"
                      "rail = GrblRail(sys.argv[1])\n" + "".join(line + "\n" for line in lines))
    return subprocess.Popen([sys.executable, str(script), fake.port], stdout=subprocess.PIPE, text=True)


def test_guard_of_a_process_killed_standing_only_asks(make_fake, connect, tmp_path):
    """A process killed while the carriage stands: its guard asks for one status report and sends nothing
    else (no feed hold, no reset)."""
    fake = make_fake()
    proc = _owner(tmp_path, fake, "print(rail.move(x=-10).x, flush=True)", "time.sleep(60)")
    try:
        assert proc.stdout.readline() == "-10.0\n"
        realtime, lines = len(fake.realtime), list(fake.lines)
        proc.kill()
        proc.wait()
        assert fake.wait_for(lambda f: not f.peer_open, timeout=10)
    finally:
        proc.kill()
        proc.stdout.close()
    asked = [byte for _, byte in fake.realtime[realtime:]]
    assert asked and set(asked) == {ord("?")}
    assert fake.lines == lines and fake.resets() == [] and fake.alarms() == []
    assert fake.machine_position()[0] == -10.0 and connect(fake).position().x == -10.0


def test_sigkill_during_the_stop_of_a_ctrl_c_is_finished_by_the_guard(make_fake, connect):
    """Ctrl-C, then kill -9 while psfd waits for the hold to complete: the guard finds Hold:1, waits for
    Hold:0 and resets, so that no cycle start can resume the move unattended."""
    fake = make_fake({**SLOW, 120: 10})  # 20 mm/s braked at 10 mm/s^2: a hold decelerates for 2 s
    proc = psfd_process("rail", "move", "X=-150", "--rail-port", fake.port)
    try:
        assert fake.wait_for(lambda f: f.machine_position()[0] < -30.0, timeout=30)
        proc.send_signal(signal.SIGINT)
        assert fake.wait_for(lambda f: f.status() == "Hold:1", timeout=5)
        proc.kill()
        proc.wait()
        assert fake.status() == "Hold:1"  # still decelerating: a reset now would be ALARM:3
        assert fake.wait_for(lambda f: not f.peer_open, timeout=15)
    finally:
        proc.kill()
    assert [byte for _, byte in fake.realtime].count(FEED_HOLD) == 1  # psfd's: the guard found the hold on
    assert fake.resets() == ["Hold:0"] and fake.alarms() == [] and fake.status() == "Idle"
    assert connect(fake).position().x == fake.machine_position()[0]


def test_sigkill_just_after_the_move_line_is_stopped_by_the_guard(make_fake, connect, tmp_path):
    """Killed the moment the move line is written: the guard may meet GRBL still Idle, before the line runs;
    it asks again before deciding the carriage stands."""
    fake = make_fake(SLOW)
    proc = _owner(tmp_path, fake, "rail._ensure_guard()",
                  "time.sleep(0.5)  # the guard is up and waiting: it reacts within a millisecond",
                  "rail._serial.write(b'G90 G21 G0 X-150.0000\\n')", "os.kill(os.getpid(), signal.SIGKILL)")
    assert proc.wait(timeout=60) == -signal.SIGKILL
    proc.stdout.close()
    assert fake.wait_for(lambda f: not f.peer_open, timeout=15)
    assert settled(fake) and -5.0 < fake.machine_position()[0] <= 0.0
    assert fake.resets() == ["Hold:0"] and fake.alarms() == []
    assert connect(fake).position().x == fake.machine_position()[0]


@pytest.mark.parametrize("signum, exit_code", [(signal.SIGINT, 130), (signal.SIGTERM, 143),
                                               (signal.SIGHUP, -signal.SIGHUP), (signal.SIGKILL, -signal.SIGKILL)])
def test_psfd_stopped_during_homing_stops_the_carriage(make_fake, signum, exit_code):
    """GRBL answers no '?' during a homing cycle and drops the feed holds sent in it: only a reset stops it
    (ALARM:6). Ctrl-C and SIGTERM: psfd resets at once and says so. A hang-up (its default action: the
    process ends) or kill -9: the guard, told by psfd that a homing cycle runs, resets at once too, rather
    than asking, holding and waiting out the longest deceleration first, while the search goes on."""
    fake = make_fake({**HOMING, 25: 600}, start=(-150.0, -50.0, -50.0))  # a 10 mm/s search, 15 s to the switch
    proc = psfd_process("rail", "home", "--rail-port", fake.port)
    try:
        assert fake.wait_for(lambda f: f.status() == "Home" and f.moving, timeout=30)
        time.sleep(0.5)
        before = len(fake.realtime)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=30)
        assert fake.wait_for(lambda f: not f.peer_open, timeout=20)
    finally:
        proc.kill()
    assert settled(fake) and fake.alarms() == [6] and fake.resets() == ["Home"]
    assert fake.physical_position()[0] < -60.0  # far from the switch it was searching for
    sent = [byte for _, byte in fake.realtime]
    assert sent[before:before + 1] == [0x18] and FEED_HOLD not in sent
    assert proc.returncode == exit_code
    if exit_code > 0:
        assert "homing stopped by a reset (Alarm): the position is lost" in err, err


def test_guard_of_a_process_killed_moving_after_homing_holds_first(make_fake, tmp_path):
    """The note that a homing cycle runs ends with the cycle: killed in a move after `home`, the guard stops the
    carriage as after any move (feed hold, Hold:0, reset: the position kept), not with the reset at once that
    a homing cycle needs."""
    fake = make_fake({**SLOW, 22: 1}, start=(-30.0, -50.0, -50.0))
    proc = _owner(tmp_path, fake, "print(rail.home().x, flush=True)", "rail.move(x=-150)")
    try:
        assert proc.stdout.readline() == "-1.0\n"
        assert fake.wait_for(lambda f: f.machine_position()[0] < -20.0, timeout=30)
        proc.kill()
        proc.wait()
        assert fake.wait_for(lambda f: not f.peer_open, timeout=15)
    finally:
        proc.kill()
        proc.stdout.close()
    assert settled(fake) and fake.resets() == ["Hold:0"] and fake.alarms() == []
    assert FEED_HOLD in [byte for _, byte in fake.realtime]


def test_guard_meeting_a_vanished_port_says_so_in_one_line(capsys):
    """The owner dies and the USB cable is out (the pty's other side gone): the guard's first tty call fails with
    termios.error, which is no OSError; it ends with its one-line message, not a traceback."""
    master, slave = os.openpty()
    os.close(master)
    child = subprocess.Popen([sys.executable, "-c", ""])
    owner = os.pidfd_open(child.pid)
    child.wait()
    try:
        assert watch(slave, owner, 0.2, 0.5) == 0
    finally:
        os.close(slave)
        os.close(owner)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "the port failed" in err and "the carriage may still be moving" in err


def test_reopen_does_not_reset_a_moving_controller(make_fake, connect):
    """The process and its guard both killed (systemd-oomd, a SIGKILL of the whole control group): the
    controller goes on with the move; the next open stops it."""
    fake = make_fake(SLOW)
    killed_mid_move(fake, guard_too=True)  # the controller goes on with the move
    assert fake.wait_for(lambda f: not f.peer_open, timeout=5)
    assert fake.moving
    rail = connect(fake)  # what `psfd run --resume` does next
    assert fake.alarms() == [] and fake.resets() == ["Hold:0"]  # held, then reset standing: no ALARM:3
    assert settled(fake) and rail.position().x == fake.machine_position()[0]


def test_reopen_stops_a_homing_cycle_left_running(make_fake, connect):
    """A homing cycle whose process and guard were both killed: grbl answers neither '?' nor '$I' in it, so
    the next open resets it, which ends the cycle (ALARM:6), and goes on from the Alarm it leaves."""
    fake = make_fake({**HOMING, 25: 600}, start=(-150.0, -50.0, -50.0))
    link, _ = serial_link(fake)
    link.write(b"$H\n")
    assert fake.wait_for(lambda f: f.status() == "Home" and f.moving)
    link.close()
    rail = connect(fake)
    assert settled(fake) and fake.resets() == ["Home"] and fake.alarms() == [6]
    assert rail.info().state == "Alarm" and fake.physical_position()[0] < -60.0


def test_silence_mid_move_stops_the_carriage(make_fake, connect):
    fake = make_fake(SLOW)
    fake.when(lambda f: f.machine_position()[0] < -20.0, FakeGrbl.go_silent)
    rail = connect(fake, timeout=1.0)
    with pytest.raises(RailError, match=r"stopped answering.*feed hold and reset sent, position unknown"):
        rail.move(x=-150)
    assert settled(fake) and fake.physical_position()[0] > -100.0
    assert fake.resets() == ["Hold:0"]  # the reset waited for the deceleration: nothing lost


def test_operator_feed_hold_is_reported_at_once(make_fake, connect):
    fake = make_fake(SLOW)
    held = []
    fake.when(lambda f: f.machine_position()[0] < -20.0, lambda f: (held.append(time.monotonic()), f.press_feed_hold()))
    rail = connect(fake)
    with pytest.raises(RailError, match=r"feed hold \(Hold:\d\) at X=-2\d.* the move is cancelled; rail stopped at X="):
        rail.move(x=-150)
    assert time.monotonic() - held[0] < 4.0  # not waited out: the move had more than 6 s to go, its deadline 12 s
    assert settled(fake) and fake.status() == "Idle" and fake.alarms() == []
    assert rail.position().x == fake.machine_position()[0]


@pytest.mark.parametrize("homing", [1, 0])
def test_reset_button_mid_move_is_reported_as_its_alarm(make_fake, connect, capsys, homing):
    """The controller's own reset (abort) button mid-move: ALARM:3, then the 500 ms delay that follows an alarm
    message, then the system abort (protocol.c), whose re-initialisation clears a '?' asked during the delay
    (main.c clears sys_rt_exec_state). The alarm, not a lost status report, is what the operator is told, and
    what to do: home, or without homing ($22=0, where `psfd rail home` is refused) unlock, or start again
    from the + end at power-up (main.c zeroes the position at power-up only; a reset keeps the count)."""
    fake = make_fake({**SLOW, 22: homing})
    rail = connect(fake)
    if homing:
        rail.unlock()
    fake.when(lambda f: f.machine_position()[0] < -20.0, FakeGrbl.press_reset)
    advice = (r"homing needed: `psfd rail home`" if homing else
              r"`psfd rail unlock` \(homing is disabled, \$22=0\).*the \+ end and power-cycle the controller")
    with pytest.raises(RailAlarm, match=r"ALARM:3 \(reset while in motion\) at X=-2\d.*; " + advice) as alarm:
        rail.move(x=-150)
    assert settled(fake) and fake.alarms() == [3]
    assert rail.info().state == "Alarm"  # the state the alarm set survives the abort (main.c prior_state)
    assert ("rail home" in str(alarm.value)) == bool(homing)
    rail.close()
    code, _, err = run(capsys, "rail", "move", "X=-10", "--rail-port", fake.port)  # the next command says it too
    assert code == 4 and re.search(r"locked in ALARM at X=-2\d.*: " + advice, err)
    assert ("rail home" in err) == bool(homing)


@pytest.mark.parametrize("homing", [0, 1])
def test_a_controller_restarted_between_moves_is_refused_not_followed(make_fake, connect, homing):
    """A power blip of the controller between two moves (a brown-out as the motors start, a loose supply): it
    boots again, prints its banner unasked and counts from machine 0 where the carriage stands (main.c), in
    Alarm only when homing is enabled (HOMING_INIT_LOCK). The next move is refused, not sent 30 mm off."""
    fake = make_fake({22: homing}, boot_time=0.3)
    rail = connect(fake)
    if homing:
        rail.unlock()
    assert rail.move(x=-30).x == -30.0
    fake.power_cycle()
    assert fake.wait_for(lambda f: f.written.count(b"Grbl 1.1h") == 2)  # booted again
    sent = len(fake.lines)
    lost = r"controller on .* restarted \(.*reads X=0, .*\(was at X=-30\); the position is lost"
    with pytest.raises(RailError, match=lost):
        rail.move(x=-60)
    assert fake.lines[sent:] == [] and fake.machine_position()[0] == 0.0


def test_a_controller_restarted_mid_move_says_so(make_fake, connect):
    """The same blip mid-move: the carriage stops dead with the motors; the '?' asked while it booted is lost
    with the restart. The error says what happened, not that the controller stopped answering."""
    fake = make_fake(SLOW, boot_time=0.3)
    fake.when(lambda f: f.machine_position()[0] < -20.0, FakeGrbl.power_cycle)
    rail = connect(fake)
    with pytest.raises(RailError, match=r"controller on .* restarted during the move .*reads X=0.*position is lost"):
        rail.move(x=-150)
    assert settled(fake) and fake.machine_position()[0] == 0.0 and fake.resets() == []


def test_the_reset_button_pressed_while_standing_keeps_the_position(make_fake, connect):
    """A reset while nothing moves keeps the position (mc_reset kills nothing then): no false restart."""
    fake = make_fake()
    rail = connect(fake)
    assert rail.move(x=-30).x == -30.0
    fake.press_reset()
    assert fake.wait_for(lambda f: f.written.count(b"Grbl 1.1h") == 2)
    assert rail.move(x=-40).x == -40.0 and fake.alarms() == [] and fake.resets() == ["Idle"]


def test_safety_door_is_reported_at_once(make_fake, connect):
    fake = make_fake(SLOW)
    fake.when(lambda f: f.machine_position()[0] < -20.0, FakeGrbl.open_door)
    rail = connect(fake)
    with pytest.raises(RailError, match=r"safety door opened during the move to X=-150 mm"):
        rail.move(x=-150)
    assert settled(fake) and fake.alarms() == []
    with pytest.raises(RailError, match="safety door is open"):
        rail.move(x=-10)
    fake.close_door()
    fake.open_door()  # a door pin change while idle
    fake.close_door()


# ---------------------------------------------------------------------------------------------- alarms


def test_boot_alarm_then_unlock(make_fake, capsys):
    fake = make_fake({22: 1})
    code, _, err = run(capsys, "rail", "move", "X=-10", "--rail-port", fake.port)
    assert code == 4 and "locked in ALARM" in err and "homing needed" in err
    assert run(capsys, "rail", "unlock", "--rail-port", fake.port)[:2] == (0, "X=0\n")
    assert run(capsys, "rail", "move", "X=-10", "--rail-port", fake.port)[:2] == (0, "X=-10\n")
    assert "$X" in fake.lines and "$H" not in fake.lines


def test_soft_limit_alarm_then_recovery(make_fake, connect):
    fake = make_fake({20: 1, 22: 1})
    # Another program drove the controller past its travel and left it deaf (only Ctrl-X is heard).
    link = serial.Serial(fake.port, 115200, timeout=0.2)
    link.write(b"$X\nG1 X-20 F3000\n")
    assert fake.wait_for(lambda f: f.machine_position()[0] == -20.0)
    link.write(b"G1 X5 F3000\n")
    assert fake.wait_for(lambda f: 2 in f.alarms() and "Reset to continue" in f.written.decode())
    link.close()
    rail = connect(fake, boot_wait=1.0)
    with pytest.raises(RailAlarm, match="homing needed"):
        rail.move(x=-10)
    assert rail.unlock() == Position(-20.0, None, None)  # ALARM:2 keeps the position
    assert rail.move(x=-10).x == -10.0


def test_hard_limit_mid_move_is_reset_and_homing_needed(make_fake, connect):
    fake = make_fake({21: 1, 22: 1}, start=(-60.0, -50.0, -50.0))
    rail = connect(fake)
    rail.unlock()  # unlocked where it stands: the controller believes X=0, the carriage is 60 mm from the + switch
    with pytest.raises(RailAlarm, match=r"ALARM:1 \(hard limit triggered\) .*homing needed.*switch X still pressed"):
        rail.move(x=-150)
    assert fake.resets()[-1] == "Alarm"  # reset after [MSG:Reset to continue]: no longer deaf
    assert rail.info().state == "Alarm"
    fake.push(0, 170.0)  # the operator pushes the carriage off the far switch (both switches share one pin)
    assert rail.home().x == -1.0 and rail.move(x=-50).x == -50.0
    assert fake.crashes == 0


def test_a_switch_closed_while_the_rail_stands_is_reported_at_the_next_move(make_fake, connect):
    """Hard limits are a pin-change interrupt (limits.c): any change of a limit pin outside Alarm, the carriage
    standing too, kills everything and throws the critical ALARM:1; here the carriage is pushed by hand onto
    the + switch between two moves. The next move reports the alarm and the switch and sends no motion."""
    fake = make_fake({21: 1, 22: 1}, start=(-20.0, -50.0, -50.0))
    rail = connect(fake)
    assert rail.home().x == -1.0 and rail.move(x=-30).x == -30.0
    fake.push(0, 30.5)  # physically 0.5 mm past the + switch's trigger point
    assert fake.wait_for(lambda f: f.alarms() == [1])
    sent = len(fake.lines)
    with pytest.raises(RailAlarm, match=r"ALARM:1 \(hard limit triggered\).*homing needed.*switch X still pressed"):
        rail.move(x=-50)
    assert not [line for line in fake.lines[sent:] if line.startswith("G")] and fake.resets() == ["Alarm"]
    fake.push(0, -10.0)  # freed: in Alarm the pin change is ignored
    assert fake.alarms() == [1] and rail.home().x == -1.0


def test_travel_keeps_off_the_homing_switch_when_hard_limits_are_on(make_fake, connect):
    """Homing leaves machine 0 where the + switch closed and the carriage at -$27 (grbl limits.c); a move
    back to 0 closes the switch again, which with hard limits on is ALARM:1 and a lost position. The
    travel ends at -$27 then, and a plan reaching 0 is refused before anything is sent."""
    fake = make_fake({20: 1, 21: 1, 22: 1, 27: 1.0})
    rail = connect(fake)
    assert rail.home().x == -1.0
    assert rail.info().travel == {"x": (-200.0, -1.0)}
    sent = len(fake.lines)
    with pytest.raises(RailError, match=r"X=0 mm is outside the rail's travel \[-200, -1\]"):
        rail.move(x=0)
    assert fake.lines[sent:] == [] and rail.move(x=-1.0).x == -1.0 and fake.alarms() == []
    # without hard limits the switch is only read while homing: the whole span stays open
    assert connect(make_fake({20: 1, 22: 1})).info().travel == {"x": (-200.0, 0.0)}


def test_homing_without_a_switch_fails_cleanly(make_fake, connect):
    fake = make_fake({22: 1, 130: 20}, span=(500.0, 500.0, 500.0), start=(-100.0, -50.0, -50.0))
    rail = connect(fake)
    with pytest.raises(RailAlarm, match=r"ALARM:9 \(homing failed: limit switch not found.*\) after '\$H', the "
                                         r"position is lost; the search covers 1\.5 x \$130 .*check the switch and its "
                                         r"wiring, \$23 .*, then `psfd rail home` again"):
        rail.home()
    assert rail.info().state == "Alarm"  # the firmware reset itself; the driver is in step with it again
    with pytest.raises(RailError, match="homing cycle not enabled"):
        connect(make_fake()).home()


# ---------------------------------------------------------------------------------------------- faults


def test_error_code_has_its_meaning(make_fake, connect):
    fake = make_fake()
    rail = connect(fake)
    fake.errors["G90"] = 22
    with pytest.raises(RailError, match=r"error:22 \(feed rate not set\)"):
        rail.move(x=-10)
    assert fake.resets() == []  # a refused line queued nothing: no stop sequence


def test_line_noise_is_skipped(make_fake, connect):
    fake = make_fake()
    fake.noise = True
    rail = connect(fake)
    assert rail.move(x=-42).x == -42.0


def test_port_vanishing_mid_move(make_fake, connect):
    fake = make_fake(SLOW)
    fake.when(lambda f: f.machine_position()[0] < -10.0, FakeGrbl.unplug)
    rail = connect(fake)
    with pytest.raises(RailError, match="is gone") as gone:
        rail.move(x=-100)
    # the reason once, then what to do: the port takes no feed hold any more
    assert str(gone.value).count("is gone") == 1 and "the next psfd command that opens the port stops it" in str(
        gone.value), gone.value
    rail.close()
    rail.close()  # idempotent


def test_missing_port_is_an_error(tmp_path):
    with pytest.raises(RailError, match="cannot open rail port"):
        GrblRail(str(tmp_path / "ttyNONE"), timeout=0.2)


def test_unanswering_port_is_an_error(make_fake):
    fake = make_fake()
    fake.go_silent()
    start = time.monotonic()
    with pytest.raises(RailError, match="no banner from the controller .* after a reset"):
        GrblRail(fake.port, timeout=0.3, boot_wait=0.5)
    assert time.monotonic() - start < 3.0


def test_udev_rule_and_readme_cover_the_usual_controller_chips():
    root = Path(__file__).resolve().parents[1]
    text = (root / "systemd" / "99-psfd.rules").read_text()
    rules = [ln for ln in text.splitlines() if ln.startswith('SUBSYSTEM=="tty"')]
    ids = set()
    for rule in rules:
        assert 'GROUP="psfd"' in rule and 'ENV{ID_MM_DEVICE_IGNORE}="1"' in rule and 'SYMLINK+="psfd-rail"' in rule
        vendors = re.search(r'ATTRS\{idVendor\}=="([^"]+)"', rule).group(1).split("|")
        products = re.search(r'ATTRS\{idProduct\}=="([^"]+)"', rule).group(1).split("|")
        ids |= {f"{v}:{p}" for v in vendors for p in products}
    readme = (root / "README.md").read_text()
    # CH340, FTDI FT232R, CP210x, STM32 CDC (grblHAL), Arduino Uno: in the rule and in the README's table
    for pair in ("1a86:7523", "0403:6001", "10c4:ea60", "0483:5740", "2341:0043"):
        assert pair in ids and pair in readme

