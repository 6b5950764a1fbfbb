"""Plans for real rigs: the rail driver named in [rig], `plan check` asking the controller (the fake GRBL
on a pseudo-terminal) or the recording for its axes and travel, and rail distances from a wanted scale."""

from __future__ import annotations

import numpy as np
import pytest

from fake_grbl import FakeGrbl
from psfd.cli import main
from psfd.daemon.plan import check_text, parse_plan
from psfd.drivers import open_rail
from psfd.drivers.sim import SimRail, SimRig
from psfd.errors import BadInputError
from psfd.printing import write_target

PLAN = """[rig]
{rig}

[target]
kind = "bernoulli"
{target}

[capture]
apertures = [8]
{capture}
"""


def plan_text(rig: str, capture: str = "x = [-40]", target: str = "") -> str:
    return PLAN.format(rig=rig, capture=capture, target=target)


def check(capsys, tmp_path, text: str) -> tuple[int, str, str]:
    path = tmp_path / "plan.toml"
    path.write_text(text)
    code = main(["plan", "check", str(path)])
    out, err = capsys.readouterr()
    return code, out, err


def test_plan_check_asks_the_controller_for_its_travel(capsys, tmp_path):
    # grbl's machine travel is [-$130, 0]: a plan written for a rail counted from 0 up is refused
    firmware = FakeGrbl({110: 6000, 120: 200, 130: 300}, homing_cycles=((0,),), start=(-100.0, -50.0, -50.0))
    try:
        rig = f'rail = "grbl"\nrail_port = "{firmware.port}"'
        code, out, err = check(capsys, tmp_path, plan_text(rig, "x = [-40, 120]\ny = [5]"))
        assert code == 2 and out == ""
        assert "x = 120 outside the travel of the rail (Grbl 1.1h" in err and "x: [-300, 0]" in err
        assert "y = 5: the rail (Grbl 1.1h.20190825) has no Y axis (axes: X)" in err  # a one-axis rig
        code, out, err = check(capsys, tmp_path, plan_text(rig, "x = [-40, -120]"))
        assert code == 0, err
        assert "ok, 2 steps" in out and "rail Grbl 1.1h" in out and "X [-300, 0]" in out
    finally:
        firmware.close()
    assert not [line for line in firmware.lines if line.startswith(("G0", "G1", "$H", "$J"))]  # asked, never moved


def test_plan_check_notes_a_rail_it_cannot_ask(capsys, tmp_path):
    code, out, err = check(capsys, tmp_path, plan_text(f'rail_port = "{tmp_path / "ttyUSB9"}"'))
    assert code == 0 and "ok, 1 step" in out
    assert "note: rail not asked for its travel" in err


def test_plan_check_asks_the_recording(capsys, tmp_path):
    recording = tmp_path / "rec"
    assert main(["record", "--simulate", "--rail-limits", "X=200:3000", "--out", str(recording),
                 "--at", "X=1300", "--aperture", "8"]) == 0  # the plan's capture: it replays
    capsys.readouterr()
    code, _, err = check(capsys, tmp_path, plan_text(f'recording = "{recording}"', "x = [1300]\ny = [0, 10]"))
    assert code == 2 and "y = 0, 10: the rail (psfd simulated rail) has no Y axis (axes: X)" in err
    code, out, _ = check(capsys, tmp_path, plan_text(f'recording = "{recording}"', "x = [1300]"))
    assert code == 0 and "rail psfd simulated rail: X [200, 3000]" in out


def test_the_rail_driver_is_named_in_the_rig_table():
    assert isinstance(open_rail({"rail": "simulated", "rail_limits": {"x": [0, 100]}}), SimRail)
    with pytest.raises(BadInputError, match="rail = 'stepper': use one of 'grbl', 'simulated'"):
        open_rail({"rail": "stepper"})
    assert "[rig] rail must be one of 'grbl', 'simulated', got 'stepper'" in check_text(
        plan_text('rail = "stepper"'))
    assert any("does not go with simulate = true" in p for p in check_text(
        plan_text('simulate = true\nrail = "grbl"', "x = [1300]")))
    # a real camera with the simulated rail needs no port
    assert check_text(plan_text('rail = "simulated"', "x = [1300]")) == []


def test_a_scale_becomes_rail_distances_on_a_real_rig(tmp_path):
    target, _ = write_target(tmp_path / "target.pdf", np.random.default_rng(0).integers(0, 2, (256, 256)),
                             size_mm=640.0)  # 640 mm for 320 cells: 2 mm cells
    rig = f'rail_port = "/dev/ttyUSB0"\nfocal_mm = 100\npitch_um = 4\nx_at_lens = -50\nx_away = -1'
    plan = parse_plan(plan_text(rig, "scale = [0.25, 0.5]", f'printed = "{target}"'))
    # d = f (1 + cell / (p * 2 pitch)): 100 (1 + 2 / (0.25 * 0.008)) = 100100 mm; rail X = -50 - d
    assert plan.x == pytest.approx([-50 - 100100.0, -50 - 50100.0])
    plan = parse_plan(plan_text('rail_port = "/dev/ttyUSB0"\nfocal_mm = 50\npitch_um = 4', "scale = [0.2]",
                                "cell_mm = 0.1"))
    assert plan.x == pytest.approx([50 * (1 + 0.1 / (0.2 * 0.008))])
    # the simulated rig's own optics by default: the scale the demo and the tests use
    assert parse_plan(plan_text("simulate = true", "scale = [0.25]")).x == pytest.approx(
        [SimRig().distance_for_scale(0.25)], abs=0.01)


def test_scale_problems_are_listed():
    problems = check_text(plan_text('rail_port = "/dev/ttyUSB0"\nfocal_mm = 50', "scale = [0.25]"))
    assert problems == ["[capture] a scale needs pitch_um, cell_mm (focal_mm and pitch_um in [rig], cell_mm or "
                        'printed = "TARGET.pdf" in [target])']
    problems = check_text(plan_text('rail_port = "/dev/ttyUSB0"', "scale = [0.25]\nx = [100]"))
    assert any("not both" in p for p in problems)
    problems = check_text(plan_text("simulate = true", "scale = [0.01]"))  # 31 m away: off the simulated rail
    assert any(p.startswith("x = 31300 outside the simulated rail's limits.x") for p in problems), problems
    problems = check_text(plan_text('rail_port = "/dev/ttyUSB0"\nfocal_mm = 50\npitch_um = 4', "scale = [0.2]",
                                    f'printed = "/nonexistent.pdf"'))
    assert any("cannot read the printed target" in p for p in problems), problems


def test_the_hardware_keys_of_the_rig_table_are_checked_by_plan_check(capsys, tmp_path):
    """Timeouts, feed and baud rate of a real rig: plan check ended in a traceback for a baud rate that is not
    a number or a negative rail timeout (pyserial's ValueError), passed a feed of -5 mm/min and a camera timeout
    of "abc", which psfd run then met as a traceback."""
    rig = (f'rail_port = "{tmp_path / "ttyUSB9"}"\nrail_baudrate = "fast"\nrail_timeout = -1\nrail_feed = -5\n'
           'timeout = "abc"')
    code, out, err = check(capsys, tmp_path, plan_text(rig))
    assert code == 2 and out == "", err
    assert "[rig] rail_baudrate must be a positive integer (bits per second), got 'fast'" in err
    assert "[rig] rail_timeout must be a positive number of seconds, got -1" in err
    assert "[rig] rail_feed must be a positive speed in mm/min, got -5" in err
    assert "[rig] timeout must be a positive number of seconds, got 'abc'" in err
    assert "Traceback" not in err and err.count("\n") == 5
    plan = tmp_path / "plan.toml"
    code = main(["run", str(plan), "--local", "--catalogue", str(tmp_path / "c" / "cat.sqlite")])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"psfd: error: plan {plan}: [rig] ") and err.count("\n") == 1, err
    assert not (tmp_path / "c").exists()


def test_plan_check_asks_the_simulated_rail_the_plan_describes(capsys, tmp_path):
    """A simulated rig whose rail_limits name X only has no Y axis: psfd run refused y = [10] (exit 2) after
    plan check had said ok, as plan check asked a default simulated rig for its apertures only."""
    sim = 'simulate = true\nrail_limits = { x = [200, 3000] }'
    code, out, err = check(capsys, tmp_path, plan_text(sim, "x = [1300]\ny = [10]"))
    assert code == 2 and out == ""
    assert "y = 10: the rail (psfd simulated rail) has no Y axis (axes: X)" in err
    code, out, err = check(capsys, tmp_path, plan_text(sim, "x = [1300]"))
    assert code == 0 and "ok, 1 step" in out and "rail psfd simulated rail: X [200, 3000]" in out, err
