"""GrblRail through real pyserial on a pseudo-terminal, with a fake GRBL firmware on the other end.

Every scenario ends in a completed move or a typed error within a short timeout, never a hang.
"""

from __future__ import annotations

import time

import pytest

from fake_grbl import FakeGrbl
from psfd.drivers.base import Position, Rail
from psfd.drivers.grbl import GrblRail, parse_status
from psfd.errors import RailAlarm, RailError

LIMITS = {"x": (0, 500), "y": (-50, 50)}


@pytest.fixture
def fake():
    firmware = FakeGrbl(speed=500.0)
    yield firmware
    firmware.close()


@pytest.fixture
def rail(fake):
    driver = GrblRail(fake.port, timeout=0.5, limits=LIMITS, feed=30000, poll=0.01)
    yield driver
    driver.close()


def test_banner_home_move_and_status(fake, rail):
    assert isinstance(rail, Rail)
    assert rail.banner.startswith("Grbl 1.1")
    assert rail.home() == Position(0.0, 0.0, None)
    assert fake.lines[-1] == "$H"
    pos = rail.move(x=120.0, y=-12.5)
    assert pos == Position(120.0, -12.5, None)
    assert fake.lines[-1] == "G90 G21 G1 X120.000 Y-12.500 F30000"
    assert fake.position()[:2] == [120.0, -12.5]
    assert rail.position() == Position(120.0, -12.5, None)
    # only X: Y stays where it was
    assert rail.move(x=80) == Position(80.0, -12.5, None)


def test_move_waits_for_motion_to_finish(fake, rail):
    fake.speed = 100.0  # 50 mm takes 0.5 s
    rail.move(x=50)
    # the fake interpolates its position in time: at the target means the motion had ended
    assert fake.position()[0] == 50.0 and fake.state == "Idle"


def test_parse_status_both_versions():
    status, wco = parse_status("<Run|MPos:12.000,3.500,0.000|FS:500,0|WCO:2.000,0.500,0.000>")
    assert status.state == "Run" and status.position == (10.0, 3.0, 0.0) and wco == (2.0, 0.5, 0.0)
    status, _ = parse_status("<Idle|MPos:12.000,3.500,0.000|FS:0,0>", wco)  # WCO is remembered
    assert status.position == (10.0, 3.0, 0.0)
    status, _ = parse_status("<Idle,MPos:5.529,0.560,7.000,WPos:1.529,-5.440,-0.000>")
    assert status.state == "Idle" and status.position == (1.529, -5.44, 0.0)
    with pytest.raises(RailError, match="unreadable"):
        parse_status("<garbage>")


def test_soft_limits_refuse_before_sending(fake, rail):
    sent = len(fake.lines)
    with pytest.raises(RailError, match=r"X=600 mm is outside the soft limits \[0, 500\]"):
        rail.move(x=600)
    with pytest.raises(RailError, match="no Z axis"):
        rail.move(x=10, z=5)
    assert len(fake.lines) == sent


def test_error_code_has_its_meaning(fake, rail):
    fake.errors["G90"] = 22
    with pytest.raises(RailError, match=r"error:22 \(feed rate not set\)"):
        rail.move(x=10)


def test_homing_disabled_error(fake, rail):
    fake.homing_enabled = False
    with pytest.raises(RailError, match=r"error:5 \(homing cycle not enabled"):
        rail.home()


def test_alarm_during_move(fake, rail):
    fake.speed = 100.0
    fake.alarm_after = (0.1, 1)
    with pytest.raises(RailAlarm, match=r"ALARM:1 \(hard limit triggered"):
        rail.move(x=100)
    # the controller is now locked: a new move is refused with error:9, also an alarm
    with pytest.raises(RailAlarm, match="error:9"):
        rail.move(x=10)
    rail.home()
    assert rail.move(x=10).x == 10.0


def test_garbage_bytes_are_skipped(fake, rail):
    fake.garbage = True
    assert rail.move(x=42).x == 42.0
    assert rail.home().x == 0.0


def test_silence_times_out(fake, rail):
    fake.silent = True
    start = time.monotonic()
    with pytest.raises(RailError, match=r"no status report to '\?' from rail on .* within 0.5 s \(nothing received\)"):
        rail.move(x=10)
    assert time.monotonic() - start < 3.0


def test_missing_ok_times_out(fake, rail):
    fake.mute_lines = True  # status reports still come, the line is never acknowledged
    with pytest.raises(RailError, match=r"no 'ok' to 'G90 G21 G1 X10.000 F30000' from rail on .* within 0.5 s"):
        rail.move(x=10)


def test_no_banner_is_an_error():
    firmware = FakeGrbl()
    firmware.silent = True
    try:
        with pytest.raises(RailError, match="no GRBL banner after a reset from rail on .* within 0.3 s"):
            GrblRail(firmware.port, timeout=0.3)
    finally:
        firmware.close()


def test_port_vanishing_mid_move(fake, rail):
    fake.speed = 100.0
    fake.vanish_after = 0.1
    with pytest.raises(RailError, match="is gone|no status report"):
        rail.move(x=100)
    rail.close()
    rail.close()  # idempotent


def test_missing_port_is_an_error(tmp_path):
    with pytest.raises(RailError, match="cannot open rail port"):
        GrblRail(str(tmp_path / "ttyNONE"), timeout=0.2)


def test_bad_limits_are_refused(fake):
    with pytest.raises(RailError, match="min 5 is above max 1"):
        GrblRail(fake.port, limits={"x": (5, 1)})
    with pytest.raises(RailError, match="unknown rail axis"):
        GrblRail(fake.port, limits={"x": (0, 1), "w": (0, 1)})
