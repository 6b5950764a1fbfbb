"""Recording a rig session and replaying it: same answers, byte-identical frames, clear mismatches."""

from __future__ import annotations

import json
import shutil

import pytest

from fake_grbl import FakeGrbl
from psfd.drivers import open_rig
from psfd.drivers.grbl import GrblRail
from psfd.drivers.base import Position
from psfd.drivers.recording import Recorder, RecordingCamera, RecordingRail, ReplayError, open_replay
from psfd.drivers.sim import SimRig
from psfd.errors import BadInputError, CameraError, RailAlarm, RailError


def _session(camera, rail, dest):
    """The requests a short measurement makes; returns what the devices answered."""
    answers = [camera.info(), rail.home(), camera.choices("aperture")]
    frames = []
    for x, aperture in [(1300.0, "5.6"), (900.0, "11")]:
        answers.append(rail.move(x=x, y=5.0))
        camera.set("aperture", aperture)
        answers.append(camera.get("aperture"))
        frames += camera.capture(dest)
    with pytest.raises(CameraError, match="not offered") as refused:
        camera.set("aperture", "1.4")
    answers.append(str(refused.value))
    answers.append(rail.position())
    return answers, frames


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    root = tmp_path_factory.mktemp("recording")
    rig = SimRig(seed=4)
    rig.camera.set("imageformat", "RAW + JPEG")
    folder = root / "rec"
    recorder = Recorder(folder, rig.camera, rig.rail, rig={"simulate": True, "seed": 4})
    answers, frames = _session(recorder.camera, recorder.rail, root / "live")
    recorder.close()
    return folder, answers, frames


def test_manifest_lists_every_request(recording):
    folder, _, frames = recording
    manifest = json.loads((folder / "manifest.json").read_text())
    calls = [(r["device"], r["call"]) for r in manifest["requests"]]
    assert calls == [
        ("camera", "info"), ("rail", "home"), ("camera", "choices"),
        ("rail", "move"), ("camera", "set"), ("camera", "get"), ("camera", "capture"),
        ("rail", "move"), ("camera", "set"), ("camera", "get"), ("camera", "capture"),
        ("camera", "set"), ("rail", "position"),
    ]
    assert manifest["rig"] == {"simulate": True, "seed": 4}
    capture = manifest["requests"][6]["result"]["files"]
    assert [f["name"] for f in capture] == ["SIM_0001.DNG", "SIM_0001.JPG"]
    assert len(capture[0]["sha256"]) == 64 and (folder / capture[0]["file"]).is_file()
    assert manifest["requests"][11]["error"]["type"] == "CameraError"
    assert len(frames) == 4


def test_replay_gives_the_same_answers_and_identical_frames(recording, tmp_path):
    folder, answers, frames = recording
    camera, rail = open_rig({"recording": str(folder)})
    replayed, replayed_frames = _session(camera, rail, tmp_path / "replayed")
    assert replayed == answers
    assert [p.name for p in replayed_frames] == [p.name for p in frames]
    for live, again in zip(frames, replayed_frames):
        assert again.read_bytes() == live.read_bytes()


def test_a_request_off_the_recording_is_an_error(recording, tmp_path):
    folder, _, _ = recording
    camera, rail = open_replay(folder)
    camera.info()
    with pytest.raises(ReplayError, match=r"request 2 is rail\.move\(x=10\) but the recording has rail\.home\(\)"):
        rail.move(x=10)
    camera, rail = open_replay(folder)
    camera.info(), rail.home(), camera.choices("aperture"), rail.move(x=1300.0, y=5.0)
    with pytest.raises(ReplayError, match=r"camera\.set\(name='aperture', value='8'\) but the recording has "
                                          r"camera\.set\(name='aperture', value='5.6'\)"):
        camera.set("aperture", "8")


def test_replay_end_damage_and_device_only(recording, tmp_path):
    folder = tmp_path / "copy"
    shutil.copytree(recording[0], folder)  # this test damages a frame
    # a camera alone follows the camera's requests only
    camera = RecordingCamera(folder)
    camera.info(), camera.choices("aperture"), camera.set("aperture", "5.6"), camera.get("aperture")
    (frame, preview) = camera.capture(tmp_path / "a")
    assert frame.name == "SIM_0001.DNG"
    # a recorded failure is raised again, with its type and message
    camera, rail = open_replay(folder)
    for step in (camera.info, rail.home, lambda: camera.choices("aperture"), lambda: rail.move(x=1300.0, y=5.0)):
        step()
    manifest = json.loads((folder / "manifest.json").read_text())
    stored = folder / manifest["requests"][6]["result"]["files"][0]["file"]
    stored.write_bytes(stored.read_bytes()[:-10])
    camera.set("aperture", "5.6"), camera.get("aperture")
    with pytest.raises(ReplayError, match="is missing or altered"):
        camera.capture(tmp_path / "b")


def test_recorded_errors_replay_and_end_of_recording(tmp_path):
    rig = SimRig()
    rig.fail_next("rail", RailAlarm("rail ALARM:9 (homing failed: limit switch not found within the search distance)"))
    recorder = Recorder(tmp_path / "rec", rig.camera, rig.rail)
    with pytest.raises(RailAlarm):
        recorder.rail.home()
    assert recorder.rail.home() == Position(200.0, 0.0, 0.0)
    _, rail = open_replay(tmp_path / "rec")
    with pytest.raises(RailAlarm, match="ALARM:9"):
        rail.home()
    assert rail.home() == Position(200.0, 0.0, 0.0)
    assert rail.position() == Position(200.0, 0.0, 0.0)  # a query: answered from where the replay stands
    assert rail.move(x=200.0) == Position(200.0, 0.0, 0.0)  # a move that changes nothing needs no recording
    with pytest.raises(ReplayError, match=r"rail\.move\(x=300\) is past the end of the recording \(2 requests"):
        rail.move(x=300)


def test_bad_recording_folders(tmp_path):
    with pytest.raises(BadInputError, match="not a readable recording"):
        open_replay(tmp_path)
    (tmp_path / "x").write_text("")
    with pytest.raises(BadInputError, match="exists and is not empty"):
        Recorder(tmp_path)


def test_grbl_session_keeps_its_serial_exchange(tmp_path):
    firmware = FakeGrbl({22: 1, 24: 600, 25: 3000, 26: 10, 110: 30000, 120: 3000}, homing_cycles=((0,),),
                        start=(-5.0, -50.0, -50.0))
    try:
        rail = GrblRail(firmware.port, timeout=0.5, limits={"x": (-200, 0)}, feed=30000, poll=0.01)
        recorder = Recorder(tmp_path / "rec", rail=rail, rig={"rail_port": firmware.port})
        live = [recorder.rail.home(), recorder.rail.move(x=-150.0)]
        firmware.errors["G90"] = 33
        with pytest.raises(RailError, match="error:33"):
            recorder.rail.move(x=-10.0)
        recorder.close()
    finally:
        firmware.close()
    manifest = json.loads((tmp_path / "rec" / "manifest.json").read_text())
    home, move, refused = manifest["requests"]
    assert "> $H" in home["serial"] and "< ok" in home["serial"]
    assert "> G90 G21 G1 X-150.0000 F30000" in move["serial"] and move["serial"][-1].startswith("< <Idle|MPos:-150.000")
    assert refused["serial"][-1] == "< error:33"
    replayed = RecordingRail(tmp_path / "rec")
    assert [replayed.home(), replayed.move(x=-150.0)] == live
    with pytest.raises(RailError, match=r"error:33 \(motion target is invalid\)"):
        replayed.move(x=-10.0)
