"""A plan's run on a rig set up for PSF work: the camera prepared before the rail moves, a settle time
after each move, and each frame's own EXIF checked against the request and stored in the catalogue.

The simulated rig writes real DNG files whose EXIF (psfd's DNG writer) is read back with exifread; the
virtual camera of libgphoto2 and the fake GRBL firmware on a pseudo-terminal show RAW refused before
any motion through the whole ``psfd run`` process.
"""

from __future__ import annotations

import os
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import sqlite_utils

from fake_grbl import FakeGrbl
from plans import one_channel_plan
from psfd import catalogue as catalogue_module
from psfd.catalogue import Catalogue
from psfd.daemon.plan import parse_plan
from psfd.daemon.runner import Runner
from psfd.drivers.sim import SimRig

def plan_text(rig: str = "", apertures: str = "8") -> str:
    return one_channel_plan(f"simulate = true\n{rig}", apertures)


def run(tmp_path: Path, text: str, rig: SimRig | None = None, camera=None, rail=None):
    rig = rig or SimRig()
    plan = parse_plan(text)
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        result = Runner(cat, tmp_path / "frames", workers=1, progress=None).run(
            plan, camera or rig.camera, rail or rig.rail)
        steps = cat.steps(result.run_id)
        frames = [cat.psf_frames(i)[0] for i in result.psf_ids]
        psfs = [cat.psf(i)[1] for i in result.psf_ids]
    return result, steps, frames, psfs


def test_frame_exif_is_stored_beside_the_requested_settings(tmp_path):
    rig = SimRig(seed=5)
    result, _, frames, psfs = run(tmp_path, plan_text('settings = { iso = "200", shutterspeed = "1/125" }'), rig)
    assert result.state == "done", result.reason
    frame = frames[0]
    assert frame["settings"] == {"aperture": 8.0, "iso": "200", "shutterspeed": "1/125"}  # what was asked
    assert frame["exif_f_number"] == pytest.approx(8.0) and frame["exif_iso"] == 200  # what the RAW says
    assert frame["exif_exposure_s"] == pytest.approx(1 / 125)
    assert frame["exif_focal_length_mm"] == pytest.approx(50.0)
    assert frame["exif_lens"] == "simulated 50 mm" and frame["exif_serial"] == "SIM-5"
    assert frame["exif_lens_serial"] == "SIM-LENS-5"
    # the simulated lens reports its focus distance (it is focused on the target)
    assert psfs[0]["focus_distance_m"] == pytest.approx(rig.distance_for_scale() / 1000, abs=1e-3)


def test_focus_distance_is_what_the_lens_reports_or_absent(tmp_path):
    rig = SimRig()
    rig.exif = lambda: {**SimRig.exif(rig), "focus_distance_m": 0.75}  # not the rail's distance
    *_, psfs = run(tmp_path / "a", plan_text(), rig)
    assert psfs[0]["focus_distance_m"] == pytest.approx(0.75)
    rig = SimRig()
    # a lens without a distance encoder: no focus distance, not rail / 1000
    rig.exif = lambda: {k: v for k, v in SimRig.exif(rig).items() if k != "focus_distance_m"}
    result, _, frames, psfs = run(tmp_path / "b", plan_text(), rig)
    assert result.state == "done" and psfs[0]["focus_distance_m"] is None
    assert frames[0]["exif_focus_distance_m"] is None


def test_a_frame_shot_at_other_settings_fails_its_step(tmp_path):
    rig = SimRig()
    rig.exif = lambda: {**SimRig.exif(rig), "f_number": 8.0}  # the lens stayed at f/8 (mode dial in Av)
    result, steps, _, _ = run(tmp_path, plan_text(apertures="8, 5.6"), rig)
    assert result.state == "paused" and result.error is not None and result.error.exit_code == 4
    assert [s["state"] for s in steps] == ["done", "failed"]
    assert "the camera used f/8 instead of f/5.6 (read from the RAW's EXIF)" in steps[1]["reason"]
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        assert len(cat.frame_hashes()) == 1 and cat.integrity_check() == []
    assert len(list((tmp_path / "frames").glob("??/*"))) == 1  # the refused frame is not kept


def test_a_focal_length_other_than_the_plans_fails_the_step(tmp_path):
    result, steps, _, _ = run(tmp_path, plan_text("focal_mm = 50"), SimRig(focal_mm=35.0))
    assert result.state == "paused"
    assert "focal length 35 mm instead of 50 mm" in steps[0]["reason"]


class Log:
    """Camera and rail proxies that log each request with the time it returned."""

    def __init__(self, rig: SimRig, settle_s: float) -> None:
        self.calls: list[tuple[str, float]] = []
        log, rig_camera = self, rig.camera

        class Camera:
            def __getattr__(self, name):
                return log.wrap(f"camera.{name}", getattr(rig_camera, name))

            def prepare(self, setup):
                log.calls.append(("camera.prepare", time.monotonic()))
                ready = rig_camera.prepare(setup)
                log.setup = setup
                return type(ready)(**{**ready.as_dict(), "settle_s": settle_s})

        class Rail:
            def __getattr__(self, name):
                return log.wrap(f"rail.{name}", getattr(rig.rail, name))

        self.camera, self.rail = Camera(), Rail()

    def wrap(self, name, fn):
        def call(*args, **kwargs):
            try:
                return fn(*args, **kwargs)
            finally:
                self.calls.append((name, time.monotonic()))
        return call


def test_camera_prepared_before_the_first_move_and_each_frame_waits_for_the_rail_to_settle(tmp_path):
    log = Log(SimRig(), settle_s=0.4)
    text = plan_text('[rig.camera]\nfocus = "manual"\ncapture_target = "card"', apertures="8, 11")
    result, *_ = run(tmp_path, text, camera=log.camera, rail=log.rail)
    assert result.state == "done", result.reason
    names = [name for name, _ in log.calls]
    assert names.index("camera.prepare") < names.index("rail.move")
    assert log.setup.focus == "manual" and log.setup.capture_target == "card"
    moved = [t for name, t in log.calls if name == "rail.move"]
    shot_start = [t for name, t in log.calls if name == "camera.capture"]
    assert len(moved) == 2
    # the capture returned at least the settle time after the move (rendering a frame takes longer still)
    for t_move, t_capture in zip(moved, shot_start):
        assert t_capture - t_move >= 0.4


def test_a_bad_camera_table_is_refused_by_the_plan():
    from psfd.daemon.plan import check_text

    problems = check_text(plan_text('[rig.camera]\nfocus = "auto"\nsettle = 2'))
    assert any("unknown camera setup key(s) settle" in p for p in problems), problems
    assert not check_text(plan_text('[rig.camera]\nfocus = "any"\nsettle_s = 0'))


# ---------------------------------------------------------------------- schema


def test_frame_exif_migration_adds_only_the_missing_columns(tmp_path):
    path = tmp_path / "old.sqlite"
    db = sqlite_utils.Database(sqlite3.connect(path))
    catalogue_module._v1_tables(db)
    catalogue_module._v2_query_indexes(db)
    db["frames"].add_column("exif_lens", str)  # as if another version's migration had added one already
    db.execute("PRAGMA user_version = 2")
    db.conn.commit()
    db.close()
    with Catalogue(path) as cat:
        assert cat.schema_version() == catalogue_module.SCHEMA_VERSION
        columns = set(cat.db["frames"].columns_dict)
    assert set(catalogue_module.FRAME_EXIF) <= columns


def test_lens_serial_migration_adds_the_column_to_a_version_8_catalogue(tmp_path):
    path = tmp_path / "v8.sqlite"
    Catalogue(path).close()
    db = sqlite_utils.Database(sqlite3.connect(path))
    db.execute("ALTER TABLE frames DROP COLUMN exif_lens_serial")
    db.execute("PRAGMA user_version = 8")
    db.conn.commit()
    db.close()
    with Catalogue(path) as cat:
        assert cat.schema_version() == catalogue_module.SCHEMA_VERSION
        assert "exif_lens_serial" in cat.db["frames"].columns_dict


# ---------------------------------------------------------------------- real libraries


def test_psfd_run_refuses_a_camera_without_raw_before_the_rail_moves(tmp_path):
    """libgphoto2's virtual camera shoots JPEG only: the run stops at the camera setup, the rail never moves."""
    firmware = FakeGrbl({110: 6000, 120: 200}, homing_cycles=((0,),), start=(-100.0, -50.0, -50.0))
    try:
        proc = _run_on_virtual_camera(tmp_path, f'rail_port = "{firmware.port}"\nrail_limits = {{ x = [-150, -10] }}',
                                      "x = [-40, -60]")
        lines = list(firmware.lines)
        position = firmware.machine_position()
    finally:
        firmware.close()
    assert proc.returncode != 0, proc.stdout
    assert "camera setup:" in proc.stderr and "RAW cannot be set" in proc.stderr, proc.stderr
    assert not [line for line in lines if line.startswith(("G0", "G1", "G90", "$J"))], lines
    assert position[0] == pytest.approx(0.0)  # the machine position the controller booted with
    with Catalogue(tmp_path / "c.sqlite") as cat:
        assert cat.frame_hashes() == set()


def test_psfd_run_refuses_a_plan_outside_the_rails_travel_before_anything(tmp_path):
    """The controller's own travel ($130: X in [-300, 0] after + end homing) is asked before the run opens:
    a plan reaching past it is refused at once (exit 2), not at the step that cannot be reached."""
    firmware = FakeGrbl({110: 6000, 120: 200, 130: 300}, homing_cycles=((0,),), start=(-100.0, -50.0, -50.0))
    try:
        proc = _run_on_virtual_camera(tmp_path, f'rail_port = "{firmware.port}"', "x = [-40, -400]")
        lines = list(firmware.lines)
    finally:
        firmware.close()
    assert proc.returncode == 2, proc.stderr
    assert "x = -400 outside the travel of the rail" in proc.stderr and "x: [-300, 0]" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not [line for line in lines if line.startswith(("G0", "G1", "G90", "$J", "$H"))], lines
    assert not (tmp_path / "c.sqlite").exists() and not (tmp_path / "c-frames").exists()


def test_psfd_run_refuses_apertures_the_camera_does_not_offer_before_anything(tmp_path):
    """The virtual camera offers f/2.8 to f/22 in third stops: a plan at f/1.4 and f/6.7 is refused at once
    (exit 2), naming what the camera offers, before a run is opened and before the rail moves."""
    firmware = FakeGrbl({110: 6000, 120: 200}, homing_cycles=((0,),), start=(-100.0, -50.0, -50.0))
    try:
        proc = _run_on_virtual_camera(tmp_path, f'rail_port = "{firmware.port}"', "x = [-40]", "5.6, 1.4, 6.7")
        lines = list(firmware.lines)
    finally:
        firmware.close()
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [
        f"psfd: error: {tmp_path / 'plan.toml'}: apertures f/1.4, f/6.7 are not offered by the camera "
        "(offered: 2.8, 3.5, 4, 4.5, 5, 5.6, 6.3, 7.1, 8, 9, 10, 11, 13, 14, 16, 18, 20, 22)"]
    assert not [line for line in lines if line.startswith(("G0", "G1", "G90", "$J", "$H"))], lines
    assert not (tmp_path / "c.sqlite").exists() and not (tmp_path / "c-frames").exists()


def test_a_rig_that_cannot_be_opened_leaves_no_catalogue_or_frame_store(tmp_path):
    """The camera opens, the rail's port does not exist: one line, exit 4, and neither `psfd run` nor
    `psfd capture` leaves the catalogue, its folders or the frame store (``--out`` too) it would have made."""
    plan = _write_plan(tmp_path, 'rail_port = "/dev/psfd-no-such-port"', "x = [-40]")
    kept = tmp_path / "kept"
    kept.mkdir()  # a folder that was there before stays, and stays as it was
    capture = ["capture", "--aperture", "5.6", "--rail", "X=-40", "--rail-port", "/dev/psfd-no-such-port",
               "--socket", tmp_path / "none.sock"]
    for argv in (["run", plan, "--local"], capture, [*capture, "--out", tmp_path / "new" / "frames"]):
        for catalogue in (tmp_path / "new" / "deeper" / "c.sqlite", kept / "c.sqlite"):
            proc = _psfd_on_virtual_camera(tmp_path, *argv, "--catalogue", catalogue)
            assert proc.returncode == 4, proc.stderr
            (line,) = proc.stderr.strip().splitlines()
            assert line.startswith("psfd: error: ") and "/dev/psfd-no-such-port" in line, line
            assert not (tmp_path / "new").exists() and list(kept.iterdir()) == []


def _write_plan(tmp_path: Path, rig: str, capture: str, apertures: str = "5.6") -> Path:
    """``plan.toml`` in tmp_path: the ``rig`` table, the Bernoulli target, ``apertures`` and the ``capture`` lines."""
    plan = tmp_path / "plan.toml"
    plan.write_text(f'[rig]\n{rig}\n\n[target]\nkind = "bernoulli"\n\n[capture]\napertures = [{apertures}]\n'
                    f'{capture}\n')
    return plan


def _psfd_on_virtual_camera(tmp_path: Path, *argv) -> subprocess.CompletedProcess:
    """The whole ``psfd ARGV...`` process with libgphoto2's virtual camera (one JPEG in its store) attached."""
    store = tmp_path / "vcamera"
    if not store.exists():
        store.mkdir()
        (tmp_path / "home").mkdir()
        assert cv2.imwrite(str(store / "frame.jpg"),
                           (np.random.default_rng(1).random((48, 64)) * 255).astype(np.uint8))
    env = dict(os.environ, VCAMERADIR=str(store), HOME=str(tmp_path / "home"), XDG_DATA_HOME=str(tmp_path / "data"))
    return subprocess.run([sys.executable, "-m", "psfd", *map(str, argv), "--workers", "1"],
                          env=env, capture_output=True, text=True, timeout=180)


def _run_on_virtual_camera(tmp_path: Path, rig: str, capture: str, apertures: str = "5.6"
                           ) -> subprocess.CompletedProcess:
    """The whole `psfd run` process on libgphoto2's virtual camera and the ``rig`` table, into ``c.sqlite``."""
    plan = _write_plan(tmp_path, rig, capture, apertures)
    return _psfd_on_virtual_camera(tmp_path, "run", plan, "--local", "--catalogue", tmp_path / "c.sqlite")
