"""`psfd capture / run / status / demo` on the simulated rig, locally and through the service."""

from __future__ import annotations

import json
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import pytest

from psfd.catalogue import Catalogue
from psfd.cli import main
from psfd.cli.options import parse_axes, parse_channels
from psfd.daemon import client
from psfd.daemon.plan import parse_plan
from psfd.drivers.base import CameraInfo
from psfd.errors import BadInputError

from plans import one_channel_plan
from test_service import served  # noqa: F401 - fixture


def test_capture_locally_adds_the_psfs_to_the_catalogue(tmp_path, capsys):
    db, out = tmp_path / "cat.sqlite", tmp_path / "shots"
    code = main(["capture", "--aperture", "5.6", "--simulate", "--channels", "g1,b", "--out", str(out),
                 "--catalogue", str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "done: 1 step, 1 frame, 2 PSFs" in printed and "bernoulli" in printed
    with Catalogue(db) as cat:
        rows = cat.query().rows
        assert sorted(r["channel"] for r in rows) == ["b", "g1"]
        assert all(r["aperture"] == 5.6 and r["method"] == "bernoulli" for r in rows)
        (frame,) = cat.psf_frames(rows[0]["id"])
    assert frame["path"].startswith(str(out)) and frame["path"].endswith(f"{frame['sha256']}.dng")


def test_two_catalogues_sharing_a_frame_folder_keep_each_others_frames(tmp_path, capsys):
    """A frame the catalogue does not hold is not a crash's leftover unless the catalogue journalled it: the
    first catalogue's frame was deleted by the second's capture, its rows pointing at nothing."""
    shots = tmp_path / "shots"
    for name, aperture in (("a", "5.6"), ("b", "8")):
        assert main(["capture", "--aperture", aperture, "--simulate", "--channels", "g1", "--out", str(shots),
                     "--catalogue", str(tmp_path / f"{name}.sqlite"), "--socket", str(tmp_path / "none.sock"),
                     "--workers", "1"]) == 0
    capsys.readouterr()
    for name in ("a", "b"):
        with Catalogue(tmp_path / f"{name}.sqlite", readonly=True) as cat:
            (row,) = cat.query().rows
            (frame,) = cat.psf_frames(row["id"])
        assert Path(frame["path"]).is_file(), name


def test_a_catalogue_with_an_interrupted_run_keeps_the_frames_another_stored_since(tmp_path, capsys):
    """The frames a crash may have left are the ones its own catalogue journalled as being stored, not every
    unknown file newer than the run: catalogue a's run was killed, b then captured into the same folder, and a's
    next capture deleted b's frame (stored after a's run began), its row pointing at nothing."""
    shots = tmp_path / "shots"
    plan = parse_plan(one_channel_plan("simulate = true"), "killed.toml")
    with Catalogue(tmp_path / "a.sqlite") as cat:  # a run killed before its first frame: interrupted
        rig = cat.add_rig(CameraInfo("psfd simulated camera", "SIM-0", "simulated 50 mm", 50.0))
        cat.start_run(plan.path, plan.text, rig, [(step.key, step.payload()) for step in plan.steps()])
    for name, aperture in (("b", "8"), ("a", "5.6")):
        assert main(["capture", "--aperture", aperture, "--simulate", "--channels", "g1", "--out", str(shots),
                     "--catalogue", str(tmp_path / f"{name}.sqlite"), "--socket", str(tmp_path / "none.sock"),
                     "--workers", "1"]) == 0
    capsys.readouterr()
    with Catalogue(tmp_path / "b.sqlite", readonly=True) as cat:
        (row,) = cat.query().rows
        (frame,) = cat.psf_frames(row["id"])
    assert Path(frame["path"]).is_file()


def test_capture_prints_its_psfs_as_query_shows_them(tmp_path, capsys):
    """The table capture prints is `psfd query`'s for the same PSFs, with MTF50 in lp/mm from the frame's pitch:
    it left the lp/mm column out, as if the pitch were unknown."""
    argv = ["--catalogue", str(tmp_path / "c.sqlite"), "--socket", str(tmp_path / "none.sock")]
    assert main(["capture", "--aperture", "5.6", "--simulate", "--channels", "g1", "--workers", "1", *argv]) == 0
    captured = capsys.readouterr().out.splitlines()[1:]  # after "run 1 done: ..."
    assert main(["query", *argv[:2]]) == 0
    queried = capsys.readouterr().out.splitlines()
    assert "lp/mm x/y" in queried[0] and captured == queried


def test_quiet_capture_prints_no_progress(tmp_path, capsys):
    argv = ["capture", "--aperture", "5.6", "--simulate", "--channels", "g1", "--catalogue", str(tmp_path / "c.sqlite"),
            "--socket", str(tmp_path / "none.sock"), "--workers", "1"]
    assert main(argv) == 0
    assert "1/1 steps" in capsys.readouterr().err  # the progress line, on stderr
    assert main(["-q", *argv]) == 0
    assert capsys.readouterr().err == ""  # `psfd -q`: only errors


def test_capture_near_far_pair(tmp_path, capsys):
    db = tmp_path / "cat.sqlite"
    assert main(["capture", "--aperture", "8", "--target", "pair", "--simulate", "--channels", "g1",
                 "--catalogue", str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1"]) == 0
    assert "1 step, 2 frames, 1 PSF in" in capsys.readouterr().out
    with Catalogue(db) as cat:
        (row,) = cat.query().rows
        assert row["method"] == "two-photo" and row["step"].startswith("a8/x587.5-2200")
        assert len(cat.psf_frames(row["id"])) == 2  # the PSF is tied to both photographs


def test_capture_goes_through_the_service_when_it_is_up(served, tmp_path):  # noqa: F811
    """The service stores into its own catalogue: another --catalogue or --frames is refused, not ignored (the
    user would look for the PSFs there); the service's own, or none, goes through it."""
    proc, sock, db, notes = served
    capture = [sys.executable, "-m", "psfd", "capture", "--aperture", "8", "--simulate", "--rail", "Y=0",
               "--channels", "g1", "--socket", str(sock)]
    plan = tmp_path / "plan.toml"
    assert psfd("plan", "init", "--simulate", plan).returncode == 0
    for argv in (capture + ["--catalogue", tmp_path / "mine.sqlite"], capture + ["--frames", tmp_path / "mine"],
                 [sys.executable, "-m", "psfd", "run", plan, "--socket", sock, "--catalogue", tmp_path / "mine.sqlite"]):
        refused = subprocess.run(list(map(str, argv)), capture_output=True, text=True, timeout=300)
        assert refused.returncode == 2 and refused.stderr.count("\n") == 1, refused.stderr
        assert f"the service at {sock} stores into {tmp_path}/cat" in refused.stderr, refused.stderr
    assert not list(tmp_path.glob("mine*")) and client.request(sock, {"cmd": "status"})["last"] is None
    cli = subprocess.run(list(map(str, capture + ["--catalogue", db])), capture_output=True, text=True, timeout=300)
    assert cli.returncode == 0, cli.stderr
    assert "done: 1 step," in cli.stdout
    assert "lp/mm x/y" in cli.stdout  # the pitch of the service's frames, as psfd query shows them
    with Catalogue(db) as cat:
        assert [r["aperture"] for r in cat.query().rows] == [8.0]
    assert client.request(sock, {"cmd": "status"})["last"]["state"] == "done"


def psfd(*argv) -> subprocess.CompletedProcess:
    """The whole ``psfd ARGV...`` process (on the simulated rig of this test's data folder)."""
    return subprocess.run([sys.executable, "-m", "psfd", *map(str, argv)], capture_output=True, text=True, timeout=300)


SIM_OFFERED = "(offered: 2.8, 4, 5.6, 8, 11, 16, 22)"


def test_apertures_the_camera_does_not_offer_are_refused_before_the_run(tmp_path, private_data_home):
    """Refused at once (exit 2, one line naming what the camera offers), not at the first such step of
    a run that pauses overnight and can never finish: no run is opened, the rig neither moves nor is set."""
    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan("simulate = true", "5.6, 7.1, 3.3"))
    db = tmp_path / "no" / "cat.sqlite"
    for argv, message in ((["run", plan], f"{plan}: apertures f/7.1, f/3.3 are not offered by the camera"),
                          (["capture", "--aperture", "7.1", "--simulate"],
                           "capture: aperture f/7.1 is not offered by the camera")):
        proc = psfd(*argv, "--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
        assert proc.returncode == 2, proc.stderr
        assert proc.stderr.splitlines() == [f"psfd: error: {message} {SIM_OFFERED}"]
        assert not db.parent.exists()  # no catalogue, no folder for it, no frame store
    assert not (private_data_home / "psfd" / "sim-rig.json").exists()  # nothing moved, set or shot


def test_plan_check_refuses_the_apertures_the_run_refuses(tmp_path, private_data_home):
    """`psfd plan check` said "ok" for a simulated plan that `psfd run` then refused at once (the camera does not
    offer f/7.1): it asks the simulated camera as the run does, one line per problem, exit 2, nothing set or made."""
    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan("simulate = true", "5.6, 7.1, 3.3"))
    check = psfd("plan", "check", plan)
    assert check.returncode == 2 and check.stdout == ""
    assert check.stderr.splitlines() == [f"{plan}: apertures f/7.1, f/3.3 are not offered by the camera {SIM_OFFERED}",
                                         f"psfd: error: {plan}: 1 problem found on the rig"]
    plan.write_text(one_channel_plan("simulate = true", "5.6, 8"))
    assert psfd("plan", "check", plan).returncode == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]
    assert not (private_data_home / "psfd" / "sim-rig.json").exists()



def test_camera_settings_the_camera_does_not_offer_are_refused_before_the_run(tmp_path, private_data_home):
    """A setting no choice of the camera matches (ISO 150, shutter 0.008 where it offers "1/125") was refused only
    once the run had opened: the run paused at its start, and a corrected plan is another plan, so the catalogue
    kept a run that could never go on. Now `psfd run` and `psfd plan check` refuse it at once, as apertures."""
    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan('simulate = true\nsettings = { iso = 150, shutterspeed = "1/125" }'))
    db = tmp_path / "no" / "cat.sqlite"
    message = f"{plan}: camera setting iso 150 is not offered by the camera (offered: 100, 200, 400, 800)"
    proc = psfd("run", plan, "--catalogue", db, "--socket", tmp_path / "none.sock", "--workers", "1")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [f"psfd: error: {message}"]
    assert not db.parent.exists()  # no catalogue, no folder for it, no frame store
    check = psfd("plan", "check", plan)
    assert check.returncode == 2 and check.stderr.splitlines()[0] == message
    assert not (private_data_home / "psfd" / "sim-rig.json").exists()  # nothing moved, set or shot

def test_frame_settings_are_stored_as_the_metadata_describes_them(tmp_path, capsys):
    """frames.settings keeps the plan's settings as the camera spells them ("1/250"); its description said
    "shutter speed in s", which a reader of the catalogue (Datasette) would take for a number of seconds."""
    from psfd.catalogue import datasette_metadata

    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan('simulate = true\nsettings = { iso = "200", shutterspeed = "1/250" }'))
    db = tmp_path / "cat.sqlite"
    started = datetime.now(timezone.utc).replace(microsecond=0)
    assert main(["run", str(plan), "--catalogue", str(db), "--socket", str(tmp_path / "none.sock"),
                 "--workers", "1"]) == 0, capsys.readouterr().err
    with Catalogue(db, readonly=True) as cat:
        ((settings, exposure, taken),) = cat.db.execute("SELECT settings, exif_exposure_s, taken_at FROM frames")
    assert json.loads(settings) == {"aperture": 8.0, "iso": "200", "shutterspeed": "1/250"} and exposure == 1 / 250
    assert started <= datetime.fromisoformat(taken) <= datetime.now(timezone.utc)  # a moment, not a duration
    columns = datasette_metadata("cat")["databases"]["cat"]["tables"]["frames"]["columns"]
    assert "in s," not in columns["settings"] and '"1/250"' in columns["settings"]
    assert "exif_exposure_s" in columns["settings"] and "exif_exposure_s" in columns["taken_at"]
    assert not columns["taken_at"].startswith("exposure time")  # the name of exif_exposure_s's quantity


def test_plan_check_refuses_a_recording_that_is_not_there(tmp_path):
    """A plan replaying ``recording = "DIR"`` with a mistyped folder checked ok (a note only, as for a rail
    unplugged for now) and then `psfd run` refused it: it is one of the plan's problems, exit 2."""
    plan = tmp_path / "plan.toml"
    plan.write_text(one_channel_plan(f'recording = "{tmp_path / "sesion"}"'))
    check = psfd("plan", "check", plan)
    assert check.returncode == 2 and check.stdout == "", check.stderr
    problem, summary = check.stderr.splitlines()
    assert problem.startswith(f"{plan}: [rig] recording: {tmp_path / 'sesion'}") and "not a readable recording" in problem
    assert summary == f"psfd: error: {plan}: 1 problem found on the rig"
    run = psfd("run", plan, "--catalogue", tmp_path / "cat.sqlite", "--socket", tmp_path / "none.sock")
    assert run.returncode == 2 and "not a readable recording" in run.stderr  # what the check now says first


def test_capture_through_the_service_refuses_an_aperture_not_offered(served, tmp_path, private_data_home):  # noqa: F811
    proc, sock, db, notes = served
    cli = psfd("capture", "--aperture", "7.1", "--simulate", "--channels", "g1", "--socket", sock)
    assert cli.returncode == 2, cli.stderr
    assert cli.stderr.splitlines() == [f"psfd: error: capture: aperture f/7.1 is not offered by the camera "
                                       f"{SIM_OFFERED}"]
    with Catalogue(db) as cat:
        assert cat.runs() == []
    assert not (tmp_path / "cat-frames").exists()  # the service's frame store is made by its first run
    assert not (private_data_home / "psfd" / "sim-rig.json").exists()
    assert proc.poll() is None and client.request(sock, {"cmd": "status"})["state"] == "idle"


@pytest.mark.parametrize("argv, message", [
    (["capture", "--aperture", "f/abc", "--simulate"], "--aperture: expected an f-number"),
    (["capture", "--aperture", "5.6", "--rail", "W=3", "--simulate"], "--rail: expected AXIS=MM"),
    (["capture", "--aperture", "5.6"], "--rail X=MM is needed"),
    (["capture", "--aperture", "5.6", "--target", "pair", "--rail", "X=900", "--simulate"], "give --near MM"),
    (["capture", "--aperture", "5.6", "--target", "pair", "--near", "close", "--simulate"], "--near: expected a number"),
    (["capture", "--aperture", "5.6", "--simulate", "--workers", "0"], "--workers: must be at least 1"),
    (["capture", "--aperture", "-2", "--simulate"], "--aperture: expected a positive f-number"),
    (["capture", "--aperture", "5.6", "--channels", "g3", "--simulate"], "--channels: expected all, or a comma"),
    (["capture", "--aperture", "5.6", "--near", "800", "--simulate"], "--near and --far apply to --target two-photo"),
])
def test_bad_capture_arguments(argv, message, tmp_path, capsys):
    db = tmp_path / "cat.sqlite"
    assert main(argv + ["--catalogue", str(db), "--socket", str(tmp_path / "none.sock")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not db.exists()  # nothing half-written


def test_capture_out_must_be_a_writable_folder(tmp_path, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("mine")
    for out, message in ((notes, "exists and is not a folder"), (notes / "sub", "cannot create the folder")):
        code = main(["capture", "--aperture", "5.6", "--simulate", "--out", str(out), "--catalogue",
                     str(tmp_path / "cat.sqlite"), "--socket", str(tmp_path / "none.sock")])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith(f"psfd: error: --out {out}: {message}")
    assert notes.read_text() == "mine"


def test_failed_capture_is_an_error_and_not_resumable(tmp_path, capsys):
    db, none = tmp_path / "cat.sqlite", str(tmp_path / "none.sock")
    # Y at the end of the travel puts the target half out of the frame: the step fails, not the command line
    code = main(["capture", "--simulate", "--aperture", "5.6", "--rail", "X=1300,Y=60", "--channels", "g1",
                 "--catalogue", str(db), "--socket", none, "--workers", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and err[-1].startswith("psfd: error: step a5.6/x1300/y60/r0: ")
    assert err[-1].endswith("no calibration target found in the 320x240 image")
    assert not any("paused" in line for line in err)
    with Catalogue(db) as cat:
        assert [r["state"] for r in cat.runs()] == ["failed"]  # closed: `psfd status` shows nothing to resume
    # a position off the rail is refused before the rig moves, named as the option that gave it
    assert main(["capture", "--simulate", "--aperture", "5.6", "--rail", "X=-5", "--catalogue", str(db),
                 "--socket", none]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["psfd: error: --rail: x = -5 outside the simulated rail's limits.x [200, 3000]"]
    assert main(["capture", "--simulate", "--aperture", "5.6", "--target", "pair", "--near", "800", "--far", "900",
                 "--catalogue", str(db), "--socket", none]) == 2
    assert "--near/--far: far / near = 1.12 must exceed s = 3" in capsys.readouterr().err


def test_paused_run_hint_repeats_the_options_and_restart_is_refused(tmp_path, capsys):
    """A step the rig refuses pauses the run; the hint is a command that works as printed."""
    plan = tmp_path / "small.toml"
    plan.write_text("[rig]\nsimulate = true\n[target]\nkind = 'bernoulli'\n[capture]\napertures = [5.6]\n"
                    "x = [1300]\ny = [60]\nchannels = ['g1']\n")  # the target half out of the frame
    db, sock = tmp_path / "my run.sqlite", tmp_path / "none.sock"
    common = ["--catalogue", str(db), "--socket", str(sock), "--workers", "1"]
    assert main(["run", str(plan), *common]) == 3
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert err.endswith(f"continue with: psfd run {plan} --resume --catalogue '{db}' --socket {sock}")
    # a plain restart would measure the same positions again: refused, naming the run
    assert main(["run", str(plan), *common]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "run 1 of plan" in err[0] and "is paused (0/1 steps done)" in err[0]
    assert "add --resume" in err[0] and "--new" in err[0]
    assert main(["run", str(plan), "--new", *common]) == 3  # deliberately a second run
    capsys.readouterr()
    with Catalogue(db) as cat:
        assert len(cat.runs()) == 2
    # --resume where nothing is unfinished is an error, and creates no catalogue
    other = tmp_path / "other.sqlite"
    assert main(["run", str(plan), "--resume", "--catalogue", str(other), "--socket", str(sock)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no unfinished run of plan" in err[0] and not other.exists()


def test_capture_help_states_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["capture", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert "Shoot one frame" in out and "noise target (default)" in out
    assert "(default with --simulate: 587.5)" in out and "(default with --simulate: 2200)" in out


@pytest.mark.parametrize("argv, message", [
    (["--workdir", "notes.txt"], "--workdir notes.txt: exists and is not a folder"),
    (["--workdir", "notes.txt/demo"], "--workdir notes.txt/demo: cannot create the folder"),
    (["--workers", "0"], "--workers: must be at least 1"),
    (["--catalogue", "afolder"], "--catalogue afolder: is a folder"),
])
def test_bad_demo_arguments_write_and_print_nothing(argv, message, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "afolder").mkdir()
    assert main(["demo", *argv]) == 2
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert out == "" and len(lines) == 1 and lines[0].startswith(f"psfd: error: {message}")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afolder", "notes.txt"]


def test_bad_plan_run_leaves_no_catalogue(tmp_path, capsys):
    plan = tmp_path / "bad.toml"
    plan.write_text("[target]\nkind = 'bernoulli'\n[capture]\napertures = []\n")
    db = tmp_path / "cat.sqlite"
    assert main(["run", str(plan), "--catalogue", str(db), "--socket", str(tmp_path / "none.sock")]) == 2
    err = capsys.readouterr().err
    assert "psfd plan check" in err and len(err.strip().splitlines()) == 1
    assert not db.exists()


def test_parse_rail():
    assert parse_axes(["X=1200,y=-40", "Z=5"], "--rail") == {"x": 1200.0, "y": -40.0, "z": 5.0}
    with pytest.raises(BadInputError, match="Y must be a number"):
        parse_axes(["Y=left"], "--rail")


def test_parse_channels_in_any_case():
    """--channels G1,B is g1,b as --channel G1 is g1 (the stored names are lower case); ALL is all."""
    assert parse_channels("G1, B") == ["g1", "b"] and parse_channels("ALL") == "all"
    with pytest.raises(BadInputError, match="distinct"):
        parse_channels("g1,G1")
    with pytest.raises(BadInputError, match="got 'g3'"):
        parse_channels("g3")


def test_status_without_service_lists_runs(tmp_path, capsys):
    db = tmp_path / "cat.sqlite"
    none = str(tmp_path / "none.sock")
    assert main(["status", "--catalogue", str(db), "--socket", none]) == 0
    assert "no catalogue" in capsys.readouterr().out
    assert main(["capture", "--aperture", "4", "--simulate", "--channels", "g1", "--catalogue", str(db),
                 "--socket", none, "--workers", "1"]) == 0
    capsys.readouterr()
    assert main(["status", "--catalogue", str(db), "--socket", none]) == 0
    out = capsys.readouterr().out
    assert "latest runs" in out and "1/1" in out and "capture" in out


def test_demo(tmp_path):
    """The whole demo once: 3 apertures x 3x3 field x 4 channels, then the table and the report."""
    workdir = tmp_path / "demo"
    cli = subprocess.run([sys.executable, "-m", "psfd", "demo", "--workdir", str(workdir)],
                         capture_output=True, text=True, timeout=900)
    assert cli.returncode == 0, cli.stderr
    with Catalogue(workdir / "catalogue.sqlite") as cat:
        rows = cat.query().rows
        assert cat.integrity_check() == []
    assert len(rows) == 3 * 9 * 4
    assert {r["aperture"] for r in rows} == {4.0, 8.0, 16.0}
    assert {r["channel"] for r in rows} == {"r", "g1", "g2", "b"}
    assert "done: 27 steps" in cli.stdout
    assert "$ psfd query" in cli.stdout and (workdir / "report.png").stat().st_size > 0
    # a second demo in the same folder measures nothing again: it says so and shows the results
    again = subprocess.run([sys.executable, "-m", "psfd", "demo", "--workdir", str(workdir)],
                           capture_output=True, text=True, timeout=300)
    assert again.returncode == 0, again.stderr
    assert "demo: already measured" in again.stdout and "(run 1, 108 PSFs)" in again.stdout
    assert "steps" not in again.stdout.splitlines()[0] and "$ psfd query" in again.stdout
    # the corner's table comes with the note psfd query gives there: no PSF was measured at 0,0
    corner = psfd("query", "--catalogue", workdir / "catalogue.sqlite", "--channel", "g1", "--near", "0,0")
    assert corner.returncode == 0 and corner.stderr.startswith("psfd: note: no PSF measured near 0,0")
    assert again.stderr == corner.stderr
    # physical sanity of what was stored: at every field point f/16 (diffraction) is softer than f/4
    mtf = {(r["aperture"], r["channel"], r["step"].split("/", 1)[1]): r["mtf50_x"] for r in rows}
    softer = [mtf[(16.0, c, where)] < mtf[(4.0, c, where)] for (a, c, where) in mtf if a == 4.0]
    assert len(softer) == 36 and all(softer)


def test_plan_init_writes_every_key_and_passes_plan_check(tmp_path, capsys):
    from psfd.daemon.plan import TABLES

    for simulate in (True, False):
        path = tmp_path / f"plan-{simulate}.toml"
        assert main(["plan", "init", str(path)] + ["--simulate"] * simulate) == 0
        text = path.read_text()
        for table, keys in TABLES.items():
            section = text.split(f"[{table}]", 1)[1].split("\n[", 1)[0]
            named = {line.lstrip("# ").split(" =", 1)[0] for line in section.splitlines() if " = " in line}
            assert keys <= named, f"[{table}] lacks {keys - named}"
        assert main(["plan", "check", str(path)]) == 0
    assert "ok, 2 steps" in capsys.readouterr().out  # the simulated one is small enough to try at once
    code = main(["plan", "init", str(tmp_path / "plan-True.toml")])
    assert code == 2 and "exists" in capsys.readouterr().err
    # a two-photo plan as the template's comments say (the kind, near and far, no x, the simulated rig's
    # textured plane): no Bernoulli-only key or default is left active to refuse it
    text = (tmp_path / "plan-True.toml").read_text().replace('kind = "bernoulli"', 'kind = "two-photo"')
    text = text.replace("# near = ", "near = ").replace("# far = ", "far = ").replace('# scene = "bernoulli"',
                                                                                    'scene = "texture"')
    pair = tmp_path / "pair.toml"
    pair.write_text("\n".join(line for line in text.splitlines() if not line.startswith("x = ")) + "\n")
    assert main(["plan", "check", str(pair)]) == 0, capsys.readouterr().err


def test_status_json_has_one_shape(tmp_path, capsys):
    db, none = tmp_path / "cat.sqlite", str(tmp_path / "none.sock")
    assert main(["status", "--json", "--catalogue", str(db), "--socket", none]) == 0
    assert json.loads(capsys.readouterr().out) == {"service": None, "catalogue": None, "runs": []}
    assert main(["capture", "--aperture", "4", "--simulate", "--channels", "g1", "--catalogue", str(db),
                 "--socket", none, "--workers", "1"]) == 0
    capsys.readouterr()
    assert main(["status", "--json", "--catalogue", str(db), "--socket", none]) == 0
    status = json.loads(capsys.readouterr().out)
    assert status["service"] is None and status["catalogue"] == str(db)
    assert set(status["runs"][0]) == {"id", "state", "plan_path", "started", "finished", "pending", "running",
                                      "done", "failed", "total", "psfs", "frames"}


def test_every_command_help_says_what_the_command_does(capsys):
    """`psfd CMD --help` of a command that has no description of its own opens with its line in the listing
    (run, status, serve, demo, plan check, rail home... printed their usage and options only)."""
    from psfd.cli import _commands, build_parser

    for command in _commands(build_parser()):
        with pytest.raises(SystemExit):
            main([*command.prog.split()[1:], "--help"])
        usage, _, rest = capsys.readouterr().out.partition("\n\n")
        assert not rest.startswith(("positional arguments:", "options:")), f"{command.prog}: no description"
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    assert "PLAN the plan file (TOML; `psfd plan init` writes one)" in " ".join(capsys.readouterr().out.split())


def test_status_takes_no_runner_options(capsys):
    """--workers and --backlog size a run's estimation; psfd status listed them and ignored them."""
    with pytest.raises(SystemExit):
        main(["status", "--workers", "2"])
    assert "unrecognized arguments: --workers" in capsys.readouterr().err


@pytest.mark.parametrize("argv, default", [
    (["capture"], "--channels CHANNELS all (the default), or a comma list of r,g1,g2,b"),
    (["query"], "--limit N at most this many PSFs (default: all)"),
    (["export"], "--limit N at most this many PSFs (default: all)"),
    (["record"], "--scene {bernoulli,texture} simulated scene (--simulate; default bernoulli)"),
    (["record"], "--seed SEED simulated rig seed (--simulate; default 0)"),
])
def test_help_states_the_defaults_of_options_with_one(argv, default, capsys):
    with pytest.raises(SystemExit):
        main([*argv, "--help"])
    assert default in " ".join(capsys.readouterr().out.split())
