"""`psfd camera`, `psfd rail`, `psfd record` on the simulated rig and on the fake GRBL."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from fake_grbl import FakeGrbl
from psfd.cli import main
from psfd.drivers import open_rig


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def test_camera_info_and_set(capsys):
    code, out, _ = run(capsys, "camera", "info", "--simulate")
    assert code == 0 and out.startswith("model    psfd simulated camera")
    assert "aperture       5.6          (offered: 2.8, 4, 5.6, 8, 11, 16, 22)" in out
    code, out, _ = run(capsys, "camera", "info", "--simulate", "--json")
    info = json.loads(out)
    assert info["focal_length_mm"] == 50.0 and info["settings"]["iso"]["choices"][0] == "100"
    assert run(capsys, "camera", "set", "aperture", "8", "--simulate")[:2] == (0, "aperture = 8\n")


def test_camera_value_not_offered_is_one_line_and_exit_4(capsys):
    code, out, err = run(capsys, "camera", "set", "aperture", "3.3", "--simulate")
    assert code == 4 and out == ""
    assert err == "psfd: error: aperture 3.3 is not offered by the camera (offered: 2.8, 4, 5.6, 8, 11, 16, 22)\n"


def test_rail_commands_simulated(capsys):
    assert run(capsys, "rail", "home", "--simulate")[:2] == (0, "X=200 Y=0 Z=0\n")
    assert run(capsys, "rail", "move", "X=1300", "Y=-5", "--simulate")[:2] == (0, "X=1300 Y=-5 Z=0\n")
    code, _, err = run(capsys, "rail", "move", "X=9000", "--simulate")
    assert code == 4 and "outside the soft limits" in err
    code, _, err = run(capsys, "rail", "move", "W=3", "--simulate")
    assert code == 2 and "expected AXIS=MM" in err
    code, _, err = run(capsys, "rail", "home")
    assert code == 2 and err == "psfd: error: rig needs rail_port (or simulate = true, or recording = DIR)\n"


def test_rail_commands_on_grbl(capsys):
    # homing enabled, fast seek; GRBL homes to the + end and backs off 1 mm: machine coordinates are negative
    firmware = FakeGrbl({22: 1, 24: 600, 25: 3000, 26: 10, 110: 6000, 111: 6000, 120: 200, 121: 200},
                        homing_cycles=((0,),), start=(-5.0, -5.0, -50.0))
    try:
        assert run(capsys, "rail", "home", "--rail-port", firmware.port)[:2] == (0, "X=-1\n")
        code, out, _ = run(capsys, "rail", "move", "X=-120", "Y=-4", "--rail-port", firmware.port,
                           "--rail-limits", "X=-200:0,Y=-10:10")
        assert (code, out) == (0, "X=-120 Y=-4\n")
        assert firmware.machine_position()[:2] == [-120.0, -4.0]
        code, _, err = run(capsys, "rail", "move", "X=-120", "Y=-40", "--rail-port", firmware.port,
                           "--rail-limits", "X=-200:0,Y=-10:10")
        assert code == 4 and "Y=-40 mm is outside the rail's travel [-10, 0]" in err
        code, _, err = run(capsys, "rail", "home", "--rail-port", firmware.port, "--rail-limits", "X=5:1")
        assert code == 2 and "minimum is above its maximum" in err
    finally:
        firmware.close()


def test_record_then_replay(capsys, tmp_path):
    out_dir = tmp_path / "rec"
    code, out, err = run(capsys, "record", "--simulate", "--out", str(out_dir), "--home",
                         "--at", "X=1300", "--at", "X=900,Y=5", "--aperture", "4,8", "--seed", "3")
    assert code == 0, err
    assert out == f"recorded 15 requests and 4 frames into {out_dir}\n"
    manifest = json.loads((out_dir / "manifest.json").read_text())
    assert manifest["rig"] == {"simulate": True, "seed": 3}
    captures = [r for r in manifest["requests"] if r["call"] == "capture"]
    assert len(captures) == 4
    assert [p.name for p in tmp_path.iterdir()] == ["rec"]  # no work folder left behind
    # the recording replays: same requests, the recorded frames byte for byte
    camera, rail = open_rig({"recording": str(out_dir)})
    camera.info(), rail.home()
    replayed = []
    for target in ({"x": 1300.0}, {"x": 900.0, "y": 5.0}):
        rail.move(**target)
        for aperture in ("4", "8"):
            camera.set("aperture", aperture)
            replayed += camera.capture(tmp_path / "replay")
    stored = [out_dir / f["file"] for c in captures for f in c["result"]["files"]]
    assert [p.read_bytes() for p in replayed] == [p.read_bytes() for p in stored]


def test_record_failures_leave_nothing(capsys, tmp_path):
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "x").write_text("")
    code, _, err = run(capsys, "record", "--simulate", "--out", str(busy), "--at", "X=1300")
    assert code == 2 and "exists and is not an empty folder" in err
    code, _, err = run(capsys, "record", "--simulate", "--out", str(tmp_path / "new"), "--at", "X=1300",
                       "--aperture", "3.3")
    assert code == 4 and "aperture 3.3 is not offered" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]
    code, _, err = run(capsys, "record", "--simulate", "--out", str(tmp_path / "new"), "--at", "X=abc")
    assert code == 2 and "expected a number" in err


def test_non_positive_fnumbers_are_bad_input(capsys, tmp_path):
    for argv in (["camera", "set", "aperture", "-2", "--simulate"], ["camera", "set", "aperture", "f/0", "--simulate"],
                 ["record", "--simulate", "--out", str(tmp_path / "r"), "--at", "X=1300", "--aperture", "-3"]):
        code, out, err = run(capsys, *argv)
        assert code == 2 and out == "" and err.count("\n") == 1 and "positive f-number" in err
    assert list(tmp_path.iterdir()) == []


def test_record_into_unwritable_place_is_one_line(capsys):
    # /proc refuses new folders even to root, where a chmod-000 folder would not
    code, _, err = run(capsys, "record", "--simulate", "--out", "/proc/psfd-rec", "--at", "X=1300")
    assert code == 2 and err.startswith("psfd: error:") and err.count("\n") == 1


def test_rail_limits_help_names_both_defaults(capsys):
    """The default on a real rail is the controller's own travel, X only (`grbl._check_limits`, the README), not
    the X=0:500 the help said: a user would have thought README's X=-1200 out of range."""
    for command in (["rail", "home"], ["capture"], ["record"], ["camera", "info"]):
        with pytest.raises(SystemExit):
            main([*command, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "0:500" not in text and "X only, over the controller's whole travel" in text, command
        assert "the simulated rig's own travel with --simulate" in text, command


def test_console_entry_point(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "psfd", "rail", "move", "X=1300", "--simulate"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and proc.stdout == "X=1300 Y=0 Z=0\n"


def test_the_simulated_rig_remembers_between_commands(capsys, private_data_home):
    """Like a real camera and rail: what one command set, the next one finds; `rail home` starts afresh."""
    assert run(capsys, "camera", "set", "aperture", "8", "--simulate")[0] == 0
    code, out, _ = run(capsys, "camera", "info", "--simulate")
    assert code == 0 and "aperture       8 " in out
    assert run(capsys, "rail", "move", "X=1200", "Y=-40", "--simulate")[0] == 0
    assert run(capsys, "rail", "position", "--simulate")[:2] == (0, "X=1200 Y=-40 Z=0\n")
    state = json.loads((private_data_home / "psfd" / "sim-rig.json").read_text())
    assert state["settings"]["aperture"] == "8" and state["position"] == {"x": 1200.0, "y": -40.0, "z": 0.0}
    assert run(capsys, "rail", "home", "--simulate")[:2] == (0, "X=200 Y=0 Z=0\n")
    assert "aperture       5.6 " in run(capsys, "camera", "info", "--simulate")[1]
    # a damaged or foreign state file is ignored, never an error
    (private_data_home / "psfd" / "sim-rig.json").write_text('{"settings": {"aperture": "1.0"}, "position": 5}')
    code, out, _ = run(capsys, "camera", "info", "--simulate")
    assert code == 0 and "aperture       5.6 " in out


def test_record_refuses_simulated_rig_options_without_the_simulated_rig(capsys, tmp_path):
    """--scene and --seed shape the simulated rig only: on real hardware they were dropped without a word."""
    out = tmp_path / "rec"
    code, _, err = run(capsys, "record", "--out", str(out), "--at", "X=-100", "--seed", "3",
                       "--rail-port", str(tmp_path / "ttyUSB9"))
    assert code == 2 and err == "psfd: error: --scene and --seed apply to the simulated rig: add --simulate\n"
    assert not out.exists()
