"""`psfd record` then `psfd run` on the recording: a plan replays what was recorded at its positions and
apertures, a failed session keeps what it recorded, and a plan that asks the rig for something else is told
where it parts from the recording."""

from __future__ import annotations

import json
from pathlib import Path

from plans import one_channel_plan
from psfd.catalogue import Catalogue
from psfd.cli import main
from psfd.drivers.recording import open_replay
from psfd.drivers.sim import SimRig

X = SimRig().distance_for_scale()


def run(capfd, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    out, err = capfd.readouterr()
    return code, out, err


def write_plan(path: Path, rig: str, apertures: str = "4, 8") -> Path:
    path.write_text(one_channel_plan(rig, apertures))
    return path


def replay_run(capfd, tmp_path: Path, recording: Path, apertures: str = "4, 8"):
    plan = write_plan(tmp_path / "replay.toml", f'recording = "{recording}"', apertures)
    catalogue = tmp_path / "replay.sqlite"
    code, out, err = run(capfd, "run", str(plan), "--local", "--catalogue", str(catalogue), "--workers", "1")
    return code, out, err, catalogue


def test_a_plan_replays_the_recording_psfd_record_made_of_it(capfd, tmp_path):
    plan = write_plan(tmp_path / "plan.toml", 'simulate = true\nseed = 2\nsettings = { iso = "200" }\n'
                                              '[rig.camera]\nfocus = "manual"')
    code, out, err = run(capfd, "record", "--plan", str(plan), "--out", str(tmp_path / "rec"))
    assert code == 0, err
    manifest = json.loads((tmp_path / "rec" / "manifest.json").read_text())
    calls = [(r["device"], r["call"]) for r in manifest["requests"]]
    assert calls[:6] == [("camera", "info"), ("rail", "info"), ("camera", "choices"), ("camera", "set"),
                         ("camera", "prepare"), ("camera", "set")]
    assert manifest["requests"][4]["args"]["focus"] == "manual"
    assert calls.count(("camera", "capture")) == 2 and calls.count(("rail", "move")) == 1

    # the same plan, its [rig] naming the recording; the runner's own order of requests differs from
    # record's (it sets the aperture before moving, moves at every step, asks for info twice)
    plan = tmp_path / "replay.toml"
    plan.write_text((tmp_path / "plan.toml").read_text().replace("simulate = true\n",
                                                                   f'recording = "{tmp_path / "rec"}"\n'))
    code, out, err = run(capfd, "run", str(plan), "--local", "--catalogue", str(tmp_path / "c.sqlite"),
                         "--workers", "1")
    assert code == 0, err
    assert "2 steps, 2 frames, 2 PSFs" in out
    with Catalogue(tmp_path / "c.sqlite") as cat:
        frames = [cat.psf_frames(row["id"])[0] for row in cat.query().rows]
    assert sorted(f["exif_f_number"] for f in frames) == [4.0, 8.0] and {f["exif_iso"] for f in frames} == {200}
    recorded = {f["sha256"] for r in manifest["requests"] if r["call"] == "capture" for f in r["result"]["files"]
                if f["name"].endswith(".DNG")}
    assert {f["sha256"] for f in frames} == recorded  # the recorded frames, byte for byte


def test_a_plan_replays_a_recording_made_at_its_positions(capfd, tmp_path):
    """The case of the issue: `psfd record --at ... --aperture ...`, then a plan with those positions."""
    recording = tmp_path / "rec"
    code, _, err = run(capfd, "record", "--simulate", "--out", str(recording), "--at", f"X={X}",
                       "--aperture", "4,8")
    assert code == 0, err
    code, out, err, _ = replay_run(capfd, tmp_path, recording)
    assert code == 0, err
    assert "2 steps, 2 frames, 2 PSFs" in out


def test_a_plan_that_departs_from_the_recording_is_told_where_before_its_run_opens(capfd, tmp_path):
    """Apertures in another order, another position, more steps than recorded, another scene: `psfd plan check`
    lists it and `psfd run` refuses it in one line (exit 2) before a catalogue is made, where the run opened and
    paused at the first capture that differs (exit 4)."""
    recording = tmp_path / "rec"
    code, _, err = run(capfd, "record", "--simulate", "--out", str(recording), "--at", f"X={X},Y=0",
                       "--aperture", "4,8")
    assert code == 0, err
    rig = f'recording = "{recording}"'

    def at_y(text: str, y: str = "0") -> str:
        return text.replace("channels", f"y = [{y}]\nchannels")

    departing = {
        "aperture": (at_y(one_channel_plan(rig, "8, 4")),
                     f"capture 1 (step a8/x{X:g}/y0/r0) was recorded with aperture 4 (the plan: 8); 1 more capture(s) "
                     "differ"),
        "position": (at_y(one_channel_plan(rig, "4, 8"), "10"),
                     f"capture 1 (step a4/x{X:g}/y10/r0) was recorded with rail y 0 (the plan: 10); 1 more"),
        "steps": (at_y(one_channel_plan(rig, "4, 8, 11")), "holds 2 capture(s), the plan takes 3"),
        "an axis left alone": (one_channel_plan(rig, "4, 8"),
                               f"capture 1 (step a4/x{X:g}/r0) was recorded with rail y 0 (the plan: unset); 1 more"),
        "scene": (at_y(one_channel_plan(rig, "4, 8")).replace('"bernoulli"', '"two-photo"\nnear = 400\nfar = 2000')
                  .replace(f"x = [{X}]\n", ""), 'shows the simulated scene "bernoulli": a two-photo target needs '
                                              '"texture"'),
    }
    for name, (text, problem) in departing.items():
        plan = tmp_path / f"{name}.toml"
        plan.write_text(text)
        code, out, err = run(capfd, "plan", "check", str(plan))
        assert code == 2 and f"{plan}: [rig] recording {recording}" in err and problem in err, (name, err)
        catalogue = tmp_path / f"{name}.sqlite"
        code, out, err = run(capfd, "run", str(plan), "--local", "--catalogue", str(catalogue), "--workers", "1")
        assert code == 2 and len(err.strip().splitlines()) == 1 and problem in err, (name, err)
        assert not catalogue.exists() and not (tmp_path / f"{name}-frames").exists()
    plan = tmp_path / "same.toml"
    plan.write_text(at_y(one_channel_plan(rig, "4, 8")))
    code, out, err = run(capfd, "plan", "check", str(plan))
    assert code == 0 and out.startswith(f"{plan}: ok, 2 steps"), err


def test_record_keeps_what_it_recorded_before_a_failure(capfd, tmp_path):
    recording = tmp_path / "rec"
    code, out, err = run(capfd, "record", "--simulate", "--out", str(recording), "--at", f"X={X}",
                         "--at", "X=9000", "--aperture", "4")
    assert code == 4 and out == ""
    assert f"kept the 9 requests recorded up to the failure in {recording}" in err
    assert "X=9000 mm is outside the soft limits" in err
    manifest = json.loads((recording / "manifest.json").read_text())
    assert [r["call"] for r in manifest["requests"]][-3:] == ["capture", "set", "move"]
    assert manifest["requests"][-1]["error"]["type"] == "RailError"
    assert [p.name for p in tmp_path.iterdir()] == ["rec"]  # no work folder left behind
    # the recording replays up to the failure, and the failure again
    camera, rail = open_replay(recording)
    rail.move(x=X)
    camera.set("aperture", "4")
    assert [p.suffix for p in camera.capture(tmp_path / "replayed")] == [".DNG"]
    try:
        rail.move(x=9000)
    except Exception as exc:  # noqa: BLE001 - the recorded error, raised again with its type
        assert type(exc).__name__ == "RailError" and "outside the soft limits" in str(exc)
    else:
        raise AssertionError("the recorded failure was not raised")


def test_record_refused_before_the_rig_acts_leaves_nothing(capfd, tmp_path):
    code, _, err = run(capfd, "record", "--simulate", "--out", str(tmp_path / "rec"), "--at", "X=1300",
                       "--aperture", "3.3")
    assert code == 4 and "aperture 3.3 is not offered" in err and "kept" not in err
    assert list(tmp_path.iterdir()) == []
    plan = write_plan(tmp_path / "plan.toml", "simulate = true")
    code, _, err = run(capfd, "record", "--plan", str(plan), "--aperture", "4", "--out", str(tmp_path / "rec"))
    assert code == 2 and "--plan gives the rig and apertures" in err
    assert [p.name for p in tmp_path.iterdir()] == ["plan.toml"]
