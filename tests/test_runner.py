"""The resumable runner on the simulated rig, with a real catalogue and real estimators."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from fake_grbl import FakeGrbl

from psfd.catalogue import Catalogue
from psfd.daemon.plan import parse_plan
from psfd.daemon.runner import Control, Runner, start_check
from psfd.daemon.store import frames_dir_for, shown_state, store_busy, store_frame, store_lock, sweep_frames
from psfd.drivers import open_rig
from psfd.drivers.base import CameraInfo
from psfd.drivers.grbl import GrblRail
from psfd.drivers.sim import SimRig
from psfd.errors import BadInputError, CameraError, EstimationError, RailAlarm, RailError

# 2 apertures x 2 field positions x 1 channel: small enough for the default suite.
PLAN = """
[rig]
simulate = true

[target]
kind = "bernoulli"

[capture]
apertures = [4, 11]
x = [{x}]
y = [{y0}, {y1}]
channels = ["g1"]
"""


def small_plan(extra: str = "") -> str:
    from psfd.drivers.sim import SimRig

    rig = SimRig()
    y0, y1 = (float(v) for v in rig.field_offsets(2)[0])
    return PLAN.format(x=rig.distance_for_scale(), y0=y0, y1=y1) + extra


def stored_files(frames: Path) -> set[str]:
    return {p.name.split(".")[0] for p in frames.glob("??/*")}


def check_complete(catalogue_path: Path, frames: Path, plan) -> None:
    """Integrity ok, every step done once with its PSF, and the frame store equals the catalogue's frames."""
    with Catalogue(catalogue_path) as cat:
        assert cat.integrity_check() == []
        rows = cat.query().rows
        hashes = cat.frame_hashes()
    keys = sorted(r["step"] for r in rows)
    assert keys == sorted(s.key for s in plan.steps())  # every expected PSF exactly once
    assert stored_files(frames) == hashes  # no orphan, none missing
    assert not list(frames.glob(".incoming-*"))


class FailingCamera:
    """The simulated camera, unplugged after ``after`` captures."""

    def __init__(self, camera, after: int) -> None:
        self.camera, self.left = camera, after

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def capture(self, dest):
        if self.left == 0:
            raise CameraError("camera not found on usb:001,004 (unplugged?)")
        self.left -= 1
        return self.camera.capture(dest)


def test_a_frame_that_makes_a_new_subfolder_syncs_the_store_folder_too(tmp_path, monkeypatch):
    """A frame is fsynced, renamed into its sha256[:2] subfolder, and that subfolder synced; a new subfolder's
    own entry lives in the store folder, which a power cut could otherwise lose with the committed frame."""
    from psfd.daemon import store

    synced = []
    monkeypatch.setattr(store, "_fsync_dir", lambda folder: synced.append(Path(folder)))
    frames = tmp_path / "frames"
    frames.mkdir()
    (tmp_path / "a.dng").write_bytes(b"first")
    path, sha = store_frame(tmp_path / "a.dng", frames)
    assert synced == [frames, frames / sha[:2]]
    synced.clear()
    same_folder = next(data for data in (b"second %d" % i for i in range(100_000))
                       if hashlib.sha256(data).hexdigest()[:2] == sha[:2])
    (tmp_path / "b.dng").write_bytes(same_folder)
    store_frame(tmp_path / "b.dng", frames)
    assert synced == [frames / sha[:2]]  # an existing subfolder: its own entry is already on disk


def test_store_frame_is_content_addressed_and_sweep_removes_orphans(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("a.dng", "b.dng"):
        (tmp_path / name).write_bytes(b"same bytes")
    journal = []
    first, sha = store_frame(tmp_path / "a.dng", frames, journal.append)
    second, sha2 = store_frame(tmp_path / "b.dng", frames, journal.append)
    assert first == second and sha == sha2 and first.name == f"{sha}.dng"
    assert not (tmp_path / "b.dng").exists()  # the duplicate was dropped, not stored twice
    assert journal == [sha]  # journalled before it entered the store, once: the second was already there
    (frames / ".incoming-x").mkdir()
    orphan = frames / "ff" / ("f" * 64 + ".dng")
    orphan.parent.mkdir()
    orphan.write_bytes(b"left by a crash")
    unknown = frames / "ee" / ("e" * 64 + ".dng")  # another catalogue's frame: never journalled here
    unknown.parent.mkdir()
    unknown.write_bytes(b"another catalogue's")
    keep = frames / "ff" / "notes.txt"
    keep.write_text("not a frame")
    removed = sweep_frames(frames, {sha}, {sha, "f" * 64, "d" * 64})
    assert set(removed) == {frames / ".incoming-x", orphan}
    assert first.exists() and keep.exists() and unknown.exists()


def test_a_plain_run_meeting_a_live_run_is_told_to_follow_or_stop_it(tmp_path):
    """--resume and --new would both meet the frame store in use: the refusal says what to do instead."""
    plan = parse_plan(small_plan(), "small.toml")
    db, frames = tmp_path / "cat.sqlite", tmp_path / "frames"
    with Catalogue(db) as cat:
        rig = cat.add_rig(CameraInfo("psfd simulated camera", "SIM-0", "simulated 50 mm", 50.0))
        run = cat.start_run(plan.path, plan.text, rig, [(step.key, step.payload()) for step in plan.steps()])
        with store_lock(frames):  # the run's process, alive
            with pytest.raises(BadInputError, match=f"run {run} of plan small.toml is running .* in another psfd "
                                                    "process: follow it with `psfd status`, or stop it"):
                start_check(cat, plan, False, False, frames)
        with pytest.raises(BadInputError, match="is interrupted .*: add --resume to continue it, or --new"):
            start_check(cat, plan, False, False, frames)  # killed: nobody holds its store


def test_run_failure_pauses_keeps_work_and_resume_completes(tmp_path):
    plan = parse_plan(small_plan(), "small.toml")
    db, frames = tmp_path / "cat.sqlite", tmp_path / "frames"
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(db) as cat:
        result = Runner(cat, frames, workers=1, progress=None).run(plan, FailingCamera(camera, 2), rail)
        assert result.state == "paused" and isinstance(result.error, CameraError)
        assert "unplugged" in result.reason
        summary = cat.run_summary(result.run_id)
        assert (summary["done"], summary["failed"], summary["pending"]) == (2, 1, 1)
        assert cat.runs()[0]["state"] == "paused"
        # resume: only the failed and pending steps run again
        camera, rail = open_rig(plan.rig_config())
        again = Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert again.run_id == result.run_id and again.state == "done" and again.steps_done == 2
        assert cat.run_summary(result.run_id)["done"] == 4
    check_complete(db, frames, plan)


def test_missing_target_pauses_the_run(tmp_path):
    """Y at the end of travel puts the target half out of the frame: no target, the run pauses."""
    plan = parse_plan(small_plan().replace("apertures = [4, 11]", "apertures = [4]")
                      .replace("y = [", "y = [60, "), "edge.toml")
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        # backlog 1: exactly one more step is shot while the failing one is estimated
        result = Runner(cat, tmp_path / "frames", workers=1, backlog=1, progress=None).run(plan, camera, rail)
        assert result.state == "paused" and isinstance(result.error, EstimationError)
        (failed,) = cat.steps(result.run_id, ("failed",))
        assert failed["key"].startswith("a4/x1300/y60") and failed["reason"] == str(result.error)
        # the failed step's frame is not kept (the retry shoots a new one), the others are catalogued
        assert stored_files(tmp_path / "frames") == cat.frame_hashes()
        # the step shot while the failed one was being estimated is kept: work done is never thrown away
        summary = cat.run_summary(result.run_id)
        assert (summary["failed"], summary["done"], summary["pending"]) == (1, 1, 1)


def test_rail_alarm_pauses_the_run(tmp_path):
    plan = parse_plan(small_plan(), "small.toml")

    class AlarmRail:
        def __init__(self, rail):
            self.rail = rail

        def __getattr__(self, name):
            return getattr(self.rail, name)

        def move(self, x=None, y=None, z=None):
            raise RailAlarm("rail in ALARM (hard limit): home it before moving")

    camera, rail = open_rig(plan.rig_config())
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        result = Runner(cat, tmp_path / "frames", workers=1, progress=None).run(plan, camera, AlarmRail(rail))
        assert result.state == "paused" and "ALARM" in result.reason
        assert cat.run_summary(result.run_id)["failed"] == 1


@pytest.mark.parametrize("homing", [0, 1])
def test_a_rail_that_restarted_while_the_run_was_stopped_is_refused_until_put_right(tmp_path, homing):
    """A USB-powered controller that boots again (cable pulled and put back, power cut) counts from machine
    position 0 wherever the carriage stands (grbl main.c); with homing off ($22=0) it comes up Idle, and a
    resume would shoot every step left 60 mm off (the carriage at -60 reads 0). The resume is refused
    before any motion, the run stays resumable, and goes on once the rail is put right as the error says:
    homed, or moved by hand to where 0 was, reset, and moved back to the run's last position."""
    firmware = FakeGrbl({22: homing, 24: 600, 25: 3000, 26: 10, 110: 6000, 120: 200}, homing_cycles=((0,),),
                        start=(-10.0, -50.0, -50.0), boot_time=0.2)
    plan = parse_plan(PLAN.replace("simulate = true", f'rail_port = "{firmware.port}"')
                      .format(x="-40, -60, -80", y0=0, y1=0).replace("apertures = [4, 11]", "apertures = [8]")
                      .replace("y = [0, 0]\n", ""), "grbl.toml")
    rig = SimRig()  # its camera; the rail is the controller on the pseudo-terminal
    db, frames = tmp_path / "cat.sqlite", tmp_path / "frames"
    try:
        rail = GrblRail(firmware.port, poll=0.02)
        if homing:
            rail.home()  # machine 0 is the + switch's trigger point
        with Catalogue(db) as cat:
            first = Runner(cat, frames, workers=1, progress=None).run(plan, FailingCamera(rig.camera, 1), rail)
            assert first.state == "paused" and [s["state"] for s in cat.steps(first.run_id)] == [
                "done", "failed", "pending"]
            offset = firmware.physical_position()[0] - firmware.machine_position()[0]
            firmware.power_cycle()
            time.sleep(0.4)
            sent = len(firmware.lines)
            with pytest.raises(RailError) as refused:
                Runner(cat, frames, workers=1, progress=None).run(plan, rig.camera, GrblRail(firmware.port, poll=0.02),
                                                                   resume=True)
            assert not [ln for ln in firmware.lines[sent:] if ln.startswith(("G0", "G1", "$J", "$H"))]
            message = str(refused.value)
            assert "reads X=0 mm" in message and f"run {first.run_id} left it at X=-60 to -40 mm" in message, message
            assert cat.steps(first.run_id, ("done",)) and cat.runs()[0]["state"] == "paused"  # still resumable
            # put right as the message says
            if homing:
                assert "`psfd rail home`" in message
                rail = GrblRail(firmware.port, poll=0.02)
                rail.home()
            else:
                assert "`psfd rail move X=-40`" in message
                firmware.push(0, offset - firmware.physical_position()[0])  # by hand to where 0 was
                firmware.power_cycle()
                time.sleep(0.4)
                rail = GrblRail(firmware.port, poll=0.02)
                rail.move(x=-40)
            again = Runner(cat, frames, workers=1, progress=None).run(plan, rig.camera, rail, resume=True)
            assert again.state == "done" and again.steps_done == 2
            shot = [cat.psf_frames(i)[0]["rail"]["x"] for i in first.psf_ids + again.psf_ids]
        assert shot == [-40.0, -60.0, -80.0]
        # the last step stood where the plan meant: the controller's coordinates agree with the carriage again
        assert firmware.physical_position()[0] - firmware.machine_position()[0] == pytest.approx(offset, abs=0.01)
    finally:
        firmware.close()
    check_complete(db, frames, plan)


def test_pause_request_stops_after_the_current_frame(tmp_path):
    plan = parse_plan(small_plan(), "small.toml")
    control = Control()
    seen = []

    def on_step(key, state, reason):
        seen.append((key, state))
        if state == "running":
            control.request("pause")

    camera, rail = open_rig(plan.rig_config())
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        result = Runner(cat, tmp_path / "frames", workers=1, control=control, progress=None,
                        on_step=on_step).run(plan, camera, rail)
        assert result.state == "paused" and result.steps_done == 1
        assert seen == [(plan.steps()[0].key, "running"), (plan.steps()[0].key, "done")]
        assert cat.run_summary(result.run_id)["pending"] == 3


def _run_cli(args: list[str], env: dict) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "psfd", *args], env=env, start_new_session=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _done_steps(db: Path) -> int:
    if not db.exists():
        return 0
    with Catalogue(db) as cat:
        runs = cat.runs()
        return cat.run_summary(runs[0]["id"])["done"] if runs else 0


def _has_run(db: Path) -> bool:
    if not db.exists():
        return False
    with Catalogue(db) as cat:
        return bool(cat.runs())


def test_sigkill_at_random_steps_then_resume(tmp_path):
    """Kill the whole process group (like a power cut) at random points several times, then resume."""
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(small_plan())
    plan = parse_plan(plan_path.read_text(), str(plan_path))
    total = len(plan.steps())
    db = tmp_path / "cat.sqlite"
    frames = frames_dir_for(db)
    env = {**os.environ, "PSFD_SOCKET": str(tmp_path / "none.sock")}
    # backlog 1: commits follow captures closely, so kills land between commits
    args = ["run", str(plan_path), "--catalogue", str(db), "--workers", "1", "--backlog", "1"]
    rng = random.Random(7)
    done_at_kill = []
    for _ in range(3):
        proc = _run_cli(args + ["--resume"] * _has_run(db), env)
        # wait for a random number of committed steps (not the last ones), then a random part of
        # a step more: the kill lands during a capture, a frame store, an estimate or a commit
        done = _done_steps(db)
        goal = rng.randint(done, max(done, total - 2))
        deadline = time.monotonic() + 120
        while proc.poll() is None and _done_steps(db) < goal and time.monotonic() < deadline:
            time.sleep(0.05)
        time.sleep(rng.uniform(0.0, 0.25))  # a part of a step (about 0.5 s): the kill falls before the run ends
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        done_at_kill.append(_done_steps(db))
    assert any(0 < n < total for n in done_at_kill), done_at_kill  # at least one kill fell mid-run
    # the killed run is shown as interrupted (nobody holds its frame store), not "running" forever
    status = subprocess.run([sys.executable, "-m", "psfd", "status", "--catalogue", str(db)], env=env,
                            capture_output=True, text=True, timeout=60)
    assert " interrupted " in status.stdout and " running " not in status.stdout, status.stdout
    # starting the plan again without --resume is refused: no position is measured twice
    again = subprocess.run([sys.executable, "-m", "psfd", *args], env=env, capture_output=True, text=True,
                           timeout=60)
    assert again.returncode == 2 and again.stderr.count("\n") == 1, again.stderr
    assert "is interrupted" in again.stderr and "add --resume" in again.stderr and "--new" in again.stderr
    proc = _run_cli(args + ["--resume"], env)
    out, err = proc.communicate(timeout=300)
    assert proc.returncode == 0, err
    assert "done" in out
    with Catalogue(db) as cat:
        assert len(cat.runs()) == 1  # every attempt resumed the same run
    check_complete(db, frames, plan)


def test_resume_refusals_and_new(tmp_path):
    """--resume needs an unfinished run; an unfinished run blocks a plain start; new=True starts anyway."""
    plan = parse_plan(small_plan(), "small.toml")
    frames = tmp_path / "frames"
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        camera, rail = open_rig(plan.rig_config())
        with pytest.raises(BadInputError, match="no unfinished run of plan small.toml to resume"):
            Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert cat.runs() == []
        control = Control()
        control.request("pause")  # pauses before the first step: an unfinished run
        camera, rail = open_rig(plan.rig_config())
        first = Runner(cat, frames, workers=1, control=control, progress=None).run(plan, camera, rail)
        assert first.state == "paused"
        camera, rail = open_rig(plan.rig_config())
        with pytest.raises(BadInputError, match=r"run 1 of plan small.toml is paused \(0/4 steps done\): add --resume"):
            Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail)
        camera, rail = open_rig(plan.rig_config())
        control = Control()
        control.request("pause")
        second = Runner(cat, frames, workers=1, control=control, progress=None).run(plan, camera, rail, new=True)
        assert second.run_id == 2 and [r["id"] for r in cat.runs()] == [2, 1]


def test_oneshot_run_that_fails_is_closed_not_resumable(tmp_path):
    plan = parse_plan(small_plan(), "capture")
    camera, rail = open_rig(plan.rig_config())
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        result = Runner(cat, tmp_path / "frames", workers=1, progress=None).run(
            plan, FailingCamera(camera, 0), rail, oneshot=True)
        assert result.state == "failed" and "unplugged" in result.reason
        assert cat.runs()[0]["state"] == "failed"
        camera, rail = open_rig(plan.rig_config())
        with pytest.raises(BadInputError, match="no unfinished run"):
            Runner(cat, tmp_path / "frames", workers=1, progress=None).run(plan, camera, rail, resume=True)


def test_store_busy_only_while_a_run_holds_the_store(tmp_path):
    frames = tmp_path / "frames"
    assert not store_busy(frames)
    with store_lock(frames):
        assert store_busy(frames) and shown_state("running", frames) == "running"
    assert not store_busy(frames) and shown_state("running", frames) == "interrupted"
    assert shown_state("paused", frames) == "paused"


def test_progress_goes_to_the_stderr_of_the_moment(tmp_path, capsys):
    # the bar goes to sys.stderr as it is when the runner is made (pytest's capture here), not to the
    # stream that was sys.stderr when psfd.daemon.runner was first imported
    with Catalogue(tmp_path / "c.sqlite") as cat:
        assert Runner(cat, tmp_path / "frames").progress_stream is sys.stderr
        assert Runner(cat, tmp_path / "frames", progress=None).progress_stream is None


def test_a_failed_step_keeps_the_same_frame_another_catalogue_stored_in_a_shared_store(tmp_path):
    """Two catalogues may share a frame store (`psfd capture --out DIR`), where a frame is one file per
    content. A replayed recording, or the simulated rig started afresh, gives the same bytes again: a pair
    step of the second catalogue whose far frame failed removed its near frame, which was the first
    catalogue's committed frame. A failed step removes only the files it put into the store."""
    near, far = SimRig(scene="texture").pair_distances()
    plan = parse_plan(f'[rig]\nsimulate = true\nscene = "texture"\n\n[target]\nkind = "two-photo"\nnear = {near}\n'
                      f'far = {far}\n\n[capture]\napertures = [8]\nchannels = ["g1"]\n', "pair.toml")
    shared = tmp_path / "frames"
    rig = SimRig(scene="texture")
    with Catalogue(tmp_path / "a.sqlite") as cat:
        assert Runner(cat, shared, workers=1, progress=None).run(plan, rig.camera, rig.rail).state == "done"
    rig = SimRig(scene="texture")  # afresh: its near frame is the first catalogue's, byte for byte
    with Catalogue(tmp_path / "b.sqlite") as cat:
        first = Runner(cat, shared, workers=1, progress=None).run(plan, FailingCamera(rig.camera, 1), rig.rail)
        assert first.state == "paused" and "camera not found" in first.reason
        check_complete(tmp_path / "a.sqlite", shared, plan)  # both its frames are still there
        again = Runner(cat, shared, workers=1, progress=None).run(plan, rig.camera, rig.rail, resume=True)
        assert again.state == "done"
    with Catalogue(tmp_path / "a.sqlite", readonly=True) as a, Catalogue(tmp_path / "b.sqlite", readonly=True) as b:
        assert stored_files(shared) == a.frame_hashes() | b.frame_hashes()  # no orphan, none missing


def test_a_run_paused_by_an_older_psfd_resumes_under_its_plan_with_defaults_written_out(tmp_path, monkeypatch,
                                                                                         data_dir):
    """tests/data/paused-run-f26fdaf.sqlite: a catalogue psfd f26fdaf wrote (the plan's runs compared by what its
    text says), run 1 of the plan below without channels, paused before its first step. The same plan with its
    defaults written out and a comment resumes that run; one that shoots other steps is refused in one line that
    names the change and says how to start afresh."""
    monkeypatch.chdir(tmp_path)
    shutil.copy(data_dir / "paused-run-f26fdaf.sqlite", "cat.sqlite")
    defaults = small_plan("repeats = 1\n\n[estimator]\ns = 4\nsupport = 17\n") + "# channels: the default, written out"
    other = small_plan("repeats = 2\n")
    with Catalogue("cat.sqlite") as cat:
        stored = cat.run(1)["plan_text"]
        assert 'channels = ["g1"]' not in stored and 'channels = ["g1"]' in defaults
        for text in (defaults, other):  # the same positions as the stored plan
            assert parse_plan(text).steps()[0].payload() == parse_plan(stored).steps()[0].payload()
        camera, rail = open_rig(parse_plan(other).rig_config())
        with pytest.raises(BadInputError) as refused:
            Runner(cat, "frames", workers=1, progress=None).run(parse_plan(other, "paused-plan.toml"), camera, rail,
                                                                resume=True)
        assert str(refused.value) == ("no unfinished run of plan paused-plan.toml to resume: run 1 of it is paused "
                                      "(0/4 steps done), but the plan changed since ([capture] repeats 1 -> 2); put "
                                      "its values back to resume it, or run it with --new instead of --resume to "
                                      "start afresh")
        plan = parse_plan(defaults, "paused-plan.toml")
        camera, rail = open_rig(plan.rig_config())
        result = Runner(cat, "frames", workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert (result.run_id, result.state, result.steps_done) == (1, "done", 4)
        assert [r["id"] for r in cat.runs()] == [1]
    check_complete(tmp_path / "cat.sqlite", tmp_path / "frames", plan)


class SettingSpy:
    """The simulated camera, keeping each (name, value) it is set to."""

    def __init__(self, camera) -> None:
        self.camera, self.sets = camera, []

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def set(self, name: str, value: str) -> None:
        self.sets.append((name, value))
        self.camera.set(name, value)


def test_a_setting_written_as_a_number_or_as_its_text_is_one_plan(tmp_path):
    """iso = 100.0 and iso = "100" set the camera to its one choice "100": a run paused under one resumes
    under the other, and the camera is sent the choice's text, not "100.0" (before, the resume was refused as
    another plan, and a free-form widget would have been set to "100.0")."""
    number, text = (parse_plan(small_plan().replace("simulate = true", f"simulate = true\nsettings = {{ iso = {v} }}"),
                               "small.toml") for v in ("100.0", '"100"'))
    frames = tmp_path / "frames"
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        control = Control()
        control.request("pause")  # after the settings, before the first step
        camera, rail = open_rig(number.rig_config())
        spy = SettingSpy(camera)
        first = Runner(cat, frames, workers=1, control=control, progress=None).run(number, spy, rail)
        assert first.state == "paused" and spy.sets == [("iso", "100")]
        camera, rail = open_rig(text.rig_config())
        again = Runner(cat, frames, workers=1, progress=None).run(text, camera, rail, resume=True)
        assert (again.run_id, again.state, again.steps_done) == (first.run_id, "done", 4)
    check_complete(tmp_path / "cat.sqlite", frames, text)


class OtherBody:
    """The simulated camera, reporting another body's serial or another lens (a camera swapped on the rig)."""

    def __init__(self, camera, **changes) -> None:
        self.camera, self.changes = camera, changes

    def __getattr__(self, name):
        return getattr(self.camera, name)

    def info(self) -> CameraInfo:
        return dataclasses.replace(self.camera.info(), **self.changes)


def test_a_run_resumes_only_with_the_camera_and_lens_it_began_with(tmp_path):
    """The catalogue keeps a run's PSFs under the rig the run began with: resumed with another body or lens
    (a camera swapped while the run was paused), its later PSFs would be filed under the first one. Refused in
    one line that names both; the run stays resumable with the right camera."""
    plan = parse_plan(small_plan(), "small.toml")
    frames = tmp_path / "frames"
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        control = Control()
        control.request("pause")
        camera, rail = open_rig(plan.rig_config())
        first = Runner(cat, frames, workers=1, control=control, progress=None).run(plan, camera, rail)
        assert first.state == "paused"
        for changes, named in (({"serial": "SIM-9"}, "serial SIM-9"), ({"lens": "simulated 35 mm"}, "simulated 35 mm")):
            camera, rail = open_rig(plan.rig_config())
            with pytest.raises(BadInputError) as refused:
                Runner(cat, frames, workers=1, progress=None).run(plan, OtherBody(camera, **changes), rail,
                                                                  resume=True)
            message = str(refused.value)
            assert message.startswith(f"run {first.run_id} of plan small.toml began with psfd simulated camera")
            assert named in message and "\n" not in message
            assert cat.runs()[0]["state"] == "paused" and len(cat.runs()) == 1
        camera, rail = open_rig(plan.rig_config())
        again = Runner(cat, frames, workers=1, progress=None).run(plan, camera, rail, resume=True)
        assert (again.run_id, again.state, again.steps_done) == (first.run_id, "done", 4)
