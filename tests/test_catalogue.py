"""The SQLite catalogue: schema and migrations, atomic idempotent steps, queries, concurrency.

Every test uses a real SQLite file in tmp_path.
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import sqlite3
import subprocess
import sys
import threading

import numpy as np
import pytest
import sqlite_utils

from psfd import catalogue as catalogue_module
from psfd.catalogue import MIGRATIONS, SCHEMA_VERSION, Catalogue, FrameRecord, default_path
from psfd.drivers.base import CameraInfo
from psfd.errors import BadInputError, CatalogueError
from psfd.estimator.kernels import PSF

CANON = CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0)
NIKON = CameraInfo("Nikon D850", "77", "AF-S 24-70mm", 35.0)


def gaussian(sigma: float, support: int = 17) -> np.ndarray:
    """Unit-sum isotropic Gaussian kernel on the s-times grid (a synthetic PSF)."""
    r = np.arange(support) - support // 2
    k = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    return k / k.sum()


def make_psf(field=(0.5, 0.5), channel="g1", sigma=2.0, method="bernoulli") -> PSF:
    return PSF(gaussian(sigma), 4, method, channel, ["frame.dng"], field, (0, 0, 64, 64), noise_floor=1e-4)


def frame(n: int, aperture="5.6") -> FrameRecord:
    return FrameRecord(f"/raw/{n}.dng", f"{n:064x}", {"aperture": aperture, "iso": "100"}, {"x": 10.0 * n}, "t")


def new_run(cat: Catalogue, keys=("a", "b", "c"), rig=CANON) -> int:
    return cat.start_run("plan.toml", "[rig]\nsimulate = true\n", cat.add_rig(rig), [(k, {"k": k}) for k in keys])


def count(path, table: str) -> int:
    """Rows in a table, read through a fresh connection (what another process would see)."""
    conn = sqlite3.connect(path)
    try:
        return conn.execute(f"SELECT count(*) FROM {table}").fetchone()[0]
    finally:
        conn.close()


# -- schema ---------------------------------------------------------------------


def test_new_catalogue_has_schema_wal_and_foreign_keys(tmp_path):
    path = tmp_path / "sub" / "cat.sqlite"
    with Catalogue(path) as cat:
        assert cat.schema_version() == SCHEMA_VERSION == len(MIGRATIONS)
        assert {"rigs", "runs", "steps", "frames", "psfs", "psf_frames"} <= set(cat.db.table_names())
        assert cat.db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert cat.db.execute("PRAGMA foreign_keys").fetchone()[0] == 1
        assert cat.db.execute("PRAGMA busy_timeout").fetchone()[0] == 30000
        assert any(ix.columns == ["aperture", "channel", "method"] for ix in cat.db["psfs"].indexes)
        assert cat.integrity_check() == []


def test_migration_from_version_1_keeps_data_and_adds_indexes(tmp_path):
    path = tmp_path / "old.sqlite"
    db = sqlite_utils.Database(path)
    MIGRATIONS[0](db)
    db.execute("PRAGMA user_version = 1")
    db["rigs"].insert({"model": "Old", "serial": "1", "lens": "L"})
    assert db["psfs"].indexes == []
    db.close()

    with Catalogue(path) as cat:
        assert cat.schema_version() == SCHEMA_VERSION
        assert any(ix.columns == ["aperture", "channel", "method"] for ix in cat.db["psfs"].indexes)
        assert cat.add_rig(CameraInfo("Old", "1", "L")) == 1  # the old row is still there


def _catalogue_before(path, migration) -> tuple[sqlite_utils.Database, int]:
    """A catalogue that every migration before ``migration`` has run on, and its schema version."""
    db = sqlite_utils.Database(path)
    before = MIGRATIONS.index(migration)
    for migrate in MIGRATIONS[:before]:
        migrate(db)
    db.execute(f"PRAGMA user_version = {before}")
    return db, before


def test_prediction_error_migration_adds_it_beside_the_noise_floor(tmp_path):
    """A catalogue from before the prediction error (every earlier migration run) opens, its PSFs read
    with no prediction error, and new ones store it."""
    path = tmp_path / "old.sqlite"
    db, before = _catalogue_before(path, catalogue_module._v5_prediction_error)
    db["psfs"].insert({"method": "bernoulli", "channel": "g1", "field_x": 0.5, "field_y": 0.5, "s": 4,
                       "support": 17, "psf": b"", "noise_floor": 2e-3})
    db.close()

    with Catalogue(path) as cat:
        assert cat.schema_version() == SCHEMA_VERSION > before
        (old,) = cat.query().rows
        assert old["noise_floor"] == 2e-3 and old["prediction_error"] is None
        run = new_run(cat, keys=("a",))
        estimate = make_psf()
        estimate.prediction_error = 1.07
        cat.commit_step(run, "a", [frame(1)], [(estimate, {"aperture": 5.6})])
        new = next(row for row in cat.query().rows if row["id"] != old["id"])
        assert new["prediction_error"] == 1.07 and new["noise_floor"] == 1e-4
    # the migration checks for its column: running it again (whatever the order of landing) is harmless
    db = sqlite_utils.Database(path)
    catalogue_module._v5_prediction_error(db)
    assert list(db["psfs"].columns_dict).count("prediction_error") == 1


def test_noise_floors_of_older_catalogues_are_brought_to_one_unit(tmp_path):
    """Version 6: a sharp-edge floor stored as the RMS per sample becomes the norm over its k x k samples (x k),
    a Bernoulli floor of the kernel before its division by the mass becomes the unit-sum kernel's (/ mass);
    two-photo floors, floors without a mass and absent floors stay as they were."""
    path = tmp_path / "old.sqlite"
    db, before = _catalogue_before(path, catalogue_module._v6_noise_floor_as_norm)
    stored = [("sharp-edge", 17, 2.5e-3, None), ("bernoulli", 17, 8e-3, '{"mass": 0.8, "solver": "nnls"}'),
              ("bernoulli", 25, 8e-3, "{}"), ("two-photo", 25, 2e-2, "{}"), ("sharp-edge", 9, None, "{}")]
    for method, support, floor, params in stored:
        db["psfs"].insert({"method": method, "channel": "g1", "field_x": 0.5, "field_y": 0.5, "s": 4,
                           "support": support, "psf": b"", "noise_floor": floor, "params": params})
    db.close()

    with Catalogue(path) as cat:
        assert cat.schema_version() == SCHEMA_VERSION > before
        floors = [row["noise_floor"] for row in cat.db.query("SELECT noise_floor FROM psfs ORDER BY id")]
    assert floors == [pytest.approx(2.5e-3 * 17), pytest.approx(1e-2), 8e-3, 2e-2, None]


def test_psf_sources_of_older_catalogues_become_relative_to_its_folder(tmp_path):
    """Version 7: a PSF's absolute sources inside the catalogue's folder become relative to it, as frame paths
    did (version 4); sources elsewhere, ones already relative and absent ones stay; it runs again unchanged."""
    path = tmp_path / "lab" / "old.sqlite"
    path.parent.mkdir()
    db, before = _catalogue_before(path, catalogue_module._v7_relative_psf_sources)
    near, far = (str(path.parent / "old-frames" / "aa" / f"{n}.dng") for n in ("near", "far"))
    for sources in (json.dumps([near, far]), json.dumps(["/mnt/raw/y.dng"]), json.dumps(["old-frames/bb/z.dng"]),
                    None):
        db["psfs"].insert({"method": "two-photo", "channel": "g1", "field_x": 0.5, "field_y": 0.5, "s": 4,
                           "support": 17, "psf": b"", "sources": sources})
    db.close()
    expected = [json.dumps(["old-frames/aa/near.dng", "old-frames/aa/far.dng"]), json.dumps(["/mnt/raw/y.dng"]),
                json.dumps(["old-frames/bb/z.dng"]), None]

    with Catalogue(path) as cat:
        assert cat.schema_version() == SCHEMA_VERSION > before
        assert [r[0] for r in cat.db.execute("SELECT sources FROM psfs ORDER BY id").fetchall()] == expected
    moved = tmp_path / "moved"
    path.parent.rename(moved)
    with Catalogue(moved / "old.sqlite", readonly=True) as cat:
        assert [row["sources"] for row in cat.query().rows] == [
            [str(moved / "old-frames" / "aa" / "near.dng"), str(moved / "old-frames" / "aa" / "far.dng")],
            ["/mnt/raw/y.dng"], [str(moved / "old-frames" / "bb" / "z.dng")], []]
    db = sqlite_utils.Database(moved / "old.sqlite")
    catalogue_module._v7_relative_psf_sources(db)
    assert [r[0] for r in db.execute("SELECT sources FROM psfs ORDER BY id").fetchall()] == expected
    db.close()


def test_failed_migration_is_rolled_back(tmp_path, monkeypatch):
    path = tmp_path / "cat.sqlite"
    Catalogue(path).close()

    def broken(db):
        db["extra"].create({"id": int}, pk="id")
        raise RuntimeError("migration failed half way")

    monkeypatch.setattr(catalogue_module, "MIGRATIONS", MIGRATIONS + [broken])
    monkeypatch.setattr(catalogue_module, "SCHEMA_VERSION", SCHEMA_VERSION + 1)
    with pytest.raises(RuntimeError):
        Catalogue(path)
    db = sqlite_utils.Database(path)
    assert db.execute("PRAGMA user_version").fetchone()[0] == SCHEMA_VERSION
    assert "extra" not in db.table_names()


def test_newer_foreign_and_garbage_files_are_refused(tmp_path):
    newer = tmp_path / "newer.sqlite"
    Catalogue(newer).close()
    with sqlite3.connect(newer) as conn:
        conn.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    with pytest.raises(CatalogueError, match="newer"):
        Catalogue(newer)

    foreign = tmp_path / "other.sqlite"
    with sqlite3.connect(foreign) as conn:
        conn.execute("CREATE TABLE t (x)")
    with pytest.raises(CatalogueError, match="not a psfd catalogue"):
        Catalogue(foreign)

    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(b"this is not sqlite at all" * 100)
    with pytest.raises(CatalogueError, match="not a psfd catalogue"):
        Catalogue(garbage)

    with pytest.raises(CatalogueError, match="no catalogue"):
        Catalogue(tmp_path / "missing.sqlite", create=False)
    assert not (tmp_path / "missing.sqlite").exists()


def test_unopenable_locations_are_catalogue_errors(tmp_path):
    # /proc refuses new files even to root (a chmod-000 folder would not); under a file, no folder can be made.
    (tmp_path / "file.txt").write_text("")
    for path in ("/proc/psfd.sqlite", tmp_path / "file.txt" / "c.sqlite"):
        with pytest.raises(CatalogueError, match="cannot (open|create) catalogue "):
            Catalogue(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file.txt"]


def test_default_path_follows_xdg(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path))
    assert default_path() == tmp_path / "psfd" / "catalogue.sqlite"
    monkeypatch.setenv("XDG_DATA_HOME", "relative/dir")  # ignored: the spec wants an absolute path
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_path() == tmp_path / "home" / ".local" / "share" / "psfd" / "catalogue.sqlite"


# -- rigs, runs, steps ------------------------------------------------------------


def test_unfinished_run_is_the_newest_running_or_paused_run_of_that_plan(tmp_path):
    """The one rule the runner, the service and the demo use: cancelled and failed runs are closed."""
    text = "[rig]\nsimulate = true\n"
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        paused, cancelled = new_run(cat), new_run(cat)
        cat.finish_run(paused, "paused")
        cat.finish_run(cancelled, "cancelled")
        assert [r["id"] for r in cat.plan_runs(text)] == [cancelled, paused]  # newest first
        assert cat.unfinished_run(text) == paused  # a newer closed run does not hide it
        cat.finish_run(paused, "failed")
        assert cat.unfinished_run(text) is None
        running = new_run(cat)  # journalled running: alive or killed, it is unfinished either way
        assert cat.unfinished_run(text) == running
        assert cat.unfinished_run(text.replace("true", "false")) is None and cat.plan_runs("other plan") == []


def test_a_plan_is_its_content_not_its_text(tmp_path):
    """Comments, layout, key order and the spelling of a number leave a plan the same: its unfinished run is
    found under any of them (and its runs listed), under no other value; a text that is no TOML is only itself."""
    text = '[rig]\nsimulate = true\n\n[capture]\napertures = [5.6, 11]\ny = [-44.16, 0]\n'
    same = ['# note: lens cap removed\n' + text, text + "\n\n", text.replace(" = ", "=").replace(", ", ","),
            '[capture]\ny = [-44.16, 0.0]  # mm\napertures = [5.60, 11.0]\n[rig]\n"simulate" = true\n']
    other = [text.replace("11", "16"), text.replace("[5.6, 11]", "[11, 5.6]"), text.replace("true", "false"),
             text + "z = [0]\n", text.replace("simulate = true", 'simulate = "true"')]
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        run = cat.start_run("plan.toml", text, cat.add_rig(CANON), [("a", {"k": "a"})])
        for edited in same:
            assert cat.unfinished_run(edited) == run, edited
            assert [r["id"] for r in cat.plan_runs(edited)] == [run]
        for changed in other:
            assert cat.unfinished_run(changed) is None and cat.plan_runs(changed) == [], changed
        assert cat.run(run)["plan_text"] == text  # the run keeps the text it was started with
        broken = cat.start_run("broken.toml", "not = [toml", cat.add_rig(CANON), [("a", {"k": "a"})])
        assert cat.unfinished_run("not = [toml") == broken and cat.unfinished_run("not = [toml ") is None


def test_rigs_runs_and_steps_lifecycle(tmp_path):
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        rig = cat.add_rig(CANON)
        assert cat.add_rig(CANON) == rig and cat.add_rig(NIKON) != rig
        run = new_run(cat)
        assert [s["key"] for s in cat.steps(run)] == ["a", "b", "c"]
        assert cat.steps(run)[1]["payload"] == {"k": "b"}
        assert cat.unfinished_run("[rig]\nsimulate = true\n") == run
        assert cat.unfinished_run("other plan") is None

        cat.set_step_state(run, "a", "running")
        cat.set_step_state(run, "a", "failed", reason="camera busy")
        cat.set_step_state(run, "a", "running")
        step = cat.steps(run, states=("running",))[0]
        assert (step["key"], step["attempts"], step["reason"]) == ("a", 2, None)
        assert [s["key"] for s in cat.steps(run, states=("pending",))] == ["b", "c"]

        cat.finish_run(run, "paused")
        summary = cat.run_summary(run)
        assert (summary["state"], summary["running"], summary["pending"], summary["total"]) == ("paused", 1, 2, 3)
        assert cat.unfinished_run("[rig]\nsimulate = true\n") == run  # paused runs resume
        cat.finish_run(run, "done")
        assert cat.unfinished_run("[rig]\nsimulate = true\n") is None
        assert cat.runs()[0]["state"] == "done" and cat.runs()[0]["camera"] == CANON.model

        with pytest.raises(BadInputError):
            cat.set_step_state(run, "a", "sleeping")
        with pytest.raises(CatalogueError):
            cat.set_step_state(run, "zz", "done")
        with pytest.raises(BadInputError, match="duplicate"):
            cat.start_run("p", "t", rig, [("x", {}), ("x", {})])


# -- commit_step: atomic and idempotent -------------------------------------------


def test_commit_step_is_idempotent(tmp_path):
    path = tmp_path / "cat.sqlite"
    with Catalogue(path) as cat:
        run = new_run(cat)
        psfs = [(make_psf(channel=c), {"aperture": 5.6, "focal_length_mm": 50, "frame_indices": [0]}) for c in "rb"]
        ids = cat.commit_step(run, "a", [frame(1), frame(2)], psfs)
        assert len(ids) == 2
        assert cat.commit_step(run, "a", [frame(1), frame(2)], psfs) == ids  # replay after a crash
        assert count(path, "psfs") == 2 and count(path, "frames") == 2 and count(path, "psf_frames") == 2
        assert cat.run_summary(run)["done"] == 1 and cat.run_summary(run)["psfs"] == 2
        # The same file used by another step is one frame, not two.
        cat.commit_step(run, "b", [frame(2), frame(3, aperture="implicit auto")], [(make_psf(), {"aperture": 5.6})])
        assert [f["aperture"] for f in cat.psf_frames(ids[0] + 2)] == [5.6, None]
        assert count(path, "frames") == 3 and cat.frame_hashes() == {frame(n).sha256 for n in (1, 2, 3)}
        assert [f["path"] for f in cat.psf_frames(ids[0])] == ["/raw/1.dng"]
        assert cat.integrity_check() == []


def test_failure_mid_commit_leaves_nothing(tmp_path, monkeypatch):
    path = tmp_path / "cat.sqlite"
    with Catalogue(path) as cat:
        run = new_run(cat)
        good = (make_psf(), {"aperture": 5.6})
        bad = (PSF(np.full((4, 4), np.nan), 4, "bernoulli", "g1", ["f"]), {"aperture": 5.6})
        with pytest.raises(BadInputError):
            cat.commit_step(run, "a", [frame(1)], [good, bad])  # second PSF fails after the first is inserted

        real = Catalogue._psf_record
        calls = []

        def fail_second(*args):
            calls.append(1)
            if len(calls) == 2:
                raise OSError("disk full")
            return real(*args)

        monkeypatch.setattr(Catalogue, "_psf_record", staticmethod(fail_second))
        with pytest.raises(OSError):
            cat.commit_step(run, "a", [frame(1)], [good, good])
        assert len(calls) == 2
        for table in ("frames", "psfs", "psf_frames"):
            assert count(path, table) == 0
        assert cat.steps(run)[0]["state"] == "pending"
        monkeypatch.undo()
        assert len(cat.commit_step(run, "a", [frame(1)], [good, good])) == 2
        assert cat.integrity_check() == []


CRASH_SCRIPT = """
import os, sys
import numpy as np
from psfd.catalogue import Catalogue, FrameRecord
from psfd.estimator.kernels import PSF
real = Catalogue._psf_record
calls = []
def die_on_third(*args):
    calls.append(1)
    if len(calls) == 3:
        os._exit(9)  # the daemon killed mid-transaction: no rollback, no cleanup
    return real(*args)
Catalogue._psf_record = staticmethod(die_on_third)
cat = Catalogue(sys.argv[1])
k = np.ones((5, 5)) / 25
psfs = [(PSF(k, 4, "bernoulli", c, ["f"]), {"aperture": 8}) for c in ("r", "g1", "g2", "b")]
cat.commit_step(1, "a", [FrameRecord("/raw/x.dng", "ab" * 32, {}, {}, "t")], psfs)
"""


def test_process_killed_mid_commit_loses_nothing_and_stores_nothing_twice(tmp_path):
    path = tmp_path / "cat.sqlite"
    with Catalogue(path) as cat:
        run = new_run(cat)
        assert run == 1
    proc = subprocess.run([sys.executable, "-c", CRASH_SCRIPT, str(path)], capture_output=True, text=True)
    assert proc.returncode == 9, proc.stderr
    with Catalogue(path) as cat:
        assert count(path, "psfs") == 0 and count(path, "frames") == 0
        assert cat.steps(run)[0]["state"] == "pending" and cat.integrity_check() == []
        # The resumed daemon redoes the step, twice for good measure: four PSFs in all.
        psfs = [(make_psf(channel=c), {"aperture": 8}) for c in ("r", "g1", "g2", "b")]
        cat.commit_step(run, "a", [frame(1)], psfs)
        cat.commit_step(run, "a", [frame(1)], psfs)
        assert count(path, "psfs") == 4


def test_second_writer_waits_then_gets_a_typed_error(tmp_path):
    path = tmp_path / "cat.sqlite"
    with Catalogue(path) as first, Catalogue(path, timeout=0.05) as second:
        run = new_run(first)
        first.db.execute("BEGIN IMMEDIATE")  # another writer holds the lock
        with pytest.raises(CatalogueError, match="cannot write"):
            second.set_step_state(run, "a", "running")
        assert second.steps(run)[0]["state"] == "pending"  # reading is still fine (WAL)
        first.db.rollback()
        second.set_step_state(run, "a", "running")
        assert first.steps(run)[0]["attempts"] == 1


def test_integrity_check_reports_psfs_of_unfinished_steps(tmp_path):
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        run = new_run(cat)
        cat.commit_step(run, "a", [], [(make_psf(), {})])
        cat.db.execute("UPDATE steps SET state = 'pending' WHERE key = 'a'")
        problems = cat.integrity_check()
        assert len(problems) == 1 and "'a'" in problems[0]


# -- queries ------------------------------------------------------------------------

GRID = [(x, y) for y in (1 / 6, 0.5, 5 / 6) for x in (1 / 6, 0.5, 5 / 6)]


def fill(cat: Catalogue) -> None:
    """Canon at f/5.6 and f/8 (r, g1 on a 3x3 field grid), Nikon at f/4 (g1 centre only)."""
    run = new_run(cat, keys=("f5.6", "f8"))
    for key, aperture in (("f5.6", 5.6), ("f8", 8.0)):
        psfs = [
            (make_psf(field, channel, sigma=aperture / 4), {"aperture": aperture, "focal_length_mm": 50})
            for field in GRID
            for channel in ("r", "g1")
        ]
        cat.commit_step(run, key, [frame(int(aperture * 10))], psfs)
    nikon = new_run(cat, keys=("n",), rig=NIKON)
    cat.commit_step(nikon, "n", [], [(make_psf(channel="g1", method="two-photo"), {"aperture": 4})])


def test_two_copies_of_one_lens_model_are_told_apart_by_the_serial_their_frames_record(tmp_path):
    """A lab measuring several copies of one lens model mounts each on the same body: one rig (model, body
    serial, lens name). The lens serial number each RAW records (EXIF LensSerialNumber) tells their PSFs
    apart: --lens takes it exactly, as --camera takes the body's serial; the name still matches both."""
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        run = new_run(cat, keys=("copy A", "copy B"))
        for key, n, serial in (("copy A", 1, "0000c1234"), ("copy B", 2, "0000c5678")):
            shot = dataclasses.replace(frame(n), exif={"lens": CANON.lens, "lens_serial": serial})
            cat.commit_step(run, key, [shot], [(make_psf(channel=c, sigma=n), {"aperture": 5.6}) for c in ("r", "g1")])
        for serial, sigma in (("0000c1234", 1), ("0000c5678", 2)):
            rows = cat.query(lens=serial).rows
            assert len(rows) == 2 and all(np.array_equal(cat.psf(r["id"])[0], gaussian(sigma)) for r in rows)
        assert len(cat.query(lens="50mm")) == 4 and len(cat.query(lens="0000c")) == 0  # a serial is exact
        assert cat.why_empty(lens="0000c9999").startswith("no PSF of lens '0000c9999'")


def test_the_nearest_psf_is_kept_per_lens_copy_and_rows_name_the_copy(tmp_path):
    """Two copies of one lens model measured at the same field location on one body: --near keeps the nearest
    PSF of each copy (before, the newest copy's hid the other's), and every row names the copy it measured."""
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        run = new_run(cat, keys=("copy A", "copy B", "no serial"))
        for key, n, serial in (("copy A", 1, "0000c1234"), ("copy B", 2, "0000c5678"), ("no serial", 3, None)):
            shot = dataclasses.replace(frame(n), exif={"lens": CANON.lens, "lens_serial": serial})
            cat.commit_step(run, key, [shot], [(make_psf(channel="g1", sigma=n), {"aperture": 5.6})])
        rows = cat.query(near=(0.5, 0.5)).rows
        sigma = {"0000c1234": 1, "0000c5678": 2, None: 3}
        assert sorted(r["lens_serial"] or "" for r in rows) == ["", "0000c1234", "0000c5678"]
        assert all(np.array_equal(cat.psf(r["id"])[0], gaussian(sigma[r["lens_serial"]])) for r in rows)
        assert [r["lens_serial"] for r in cat.query(lens="0000c1234", near=(0.5, 0.5))] == ["0000c1234"]


def test_query_filters_and_array_round_trip(tmp_path):
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        fill(cat)
        assert len(cat.query()) == 37
        exact = cat.query(camera="Canon", aperture=5.6, channel="g1")
        assert exact.note is None and len(exact) == 9
        assert {r["aperture"] for r in exact} == {5.6} and {r["channel"] for r in exact} == {"g1"}
        assert len(cat.query(camera="canon")) == 36 and len(cat.query(camera="0420")) == 36
        assert len(cat.query(lens="24-70")) == 1 and len(cat.query(method="two-photo")) == 1
        assert len(cat.query(camera="canon", method="two-photo")) == 0
        assert len(cat.query(limit=5)) == 5

        row = exact.rows[0]
        array, meta = cat.psf(row["id"])
        np.testing.assert_array_equal(array, gaussian(5.6 / 4))  # the .npy blob is lossless float64
        assert array.dtype == np.float64 and meta["window"] == [0, 0, 64, 64]
        assert meta["camera"] == CANON.model and meta["step"] == "f5.6" and meta["psfd_version"]
        assert math.isclose(meta["mtf50_x"], make_psf(sigma=1.4).metrics()["mtf50_x"])
        with pytest.raises(CatalogueError):
            cat.psf(10_000)


def test_query_nearest_aperture_with_note(tmp_path):
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        fill(cat)
        result = cat.query(camera="Canon", aperture=6.3, channel="g1")
        assert result.note == "f/6.3 not measured; nearest is f/5.6"
        assert {r["aperture"] for r in result} == {5.6} and len(result) == 9
        # 7.1 is 1/3 stop from f/8 and 2/3 stop from f/5.6.
        assert cat.query(camera="Canon", aperture=7.1).note == "f/7.1 not measured; nearest is f/8"
        # Only the Nikon (camera filter applied first) has f/4.
        assert {r["aperture"] for r in cat.query(camera="Nikon", aperture=11)} == {4.0}
        assert cat.query(camera="Canon", aperture=5.65).note is None  # within the 1 % tolerance of f/5.6


def test_query_takes_the_nearest_aperture_of_each_body_and_lens(tmp_path):
    """A lens measured only at f/4 and f/8 vanished from the answer to f/11 when another lens had f/11, with no
    note: the nearest f-number was taken over the whole catalogue. Each body, lens copy and focal length has its
    own nearest f-number (in stops), and the note names those without the one asked."""
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        fill(cat)  # Canon at f/5.6 and f/8, Nikon at f/4
        sony = new_run(cat, keys=("a", "b"), rig=CameraInfo("Sony A7", "9", "FE 50mm", 50.0))
        for key, serial, aperture in (("a", "L1", 11.0), ("b", "L2", 4.0)):  # two copies of one lens
            shot = dataclasses.replace(frame(100 + len(key) + ord(key)), exif={"lens_serial": serial})
            cat.commit_step(sony, key, [shot], [(make_psf(channel="g1"), {"aperture": aperture})])
        zoom = new_run(cat, keys=("70",), rig=NIKON)  # the Nikon's zoom at another focal length, at f/11
        cat.commit_step(zoom, "70", [], [(make_psf(channel="g1"), {"aperture": 11.0, "focal_length_mm": 70.0})])
        result = cat.query(aperture=11, channel="g1")
        got = sorted((r["camera"], r["lens_serial"] or "", r["focal_length_mm"] or 0, r["aperture"]) for r in result)
        assert got == [*[(CANON.model, "", 50, 8.0)] * 9,  # f/8 is 1 stop from f/11, f/5.6 2 stops
                       (NIKON.model, "", 0, 4.0), (NIKON.model, "", 70, 11.0),
                       ("Sony A7", "L1", 0, 11.0), ("Sony A7", "L2", 0, 4.0)]
        assert result.note == ("f/11 not measured with Canon EOS 400D #0420 / EF 50mm f/1.8 (nearest: f/8), "
                               "Nikon D850 #77 / AF-S 24-70mm at an unknown focal length (nearest: f/4), "
                               "Sony A7 #9 / FE 50mm #L2 (nearest: f/4)")
        one = cat.query(camera="Canon", aperture=11)  # one body and lens: the note as it was
        assert one.note == "f/11 not measured; nearest is f/8" and {r["aperture"] for r in one} == {8.0}
        assert cat.query(camera="Sony", aperture=11.05).note == "f/11.05 not measured with Sony A7 #9 / FE 50mm #L2 " \
            "(nearest: f/4)"  # within 1 % of f/11: L1 has it


def test_query_near_keeps_nearest_per_aperture_channel_method(tmp_path):
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        fill(cat)
        near = (0.8, 0.1)
        result = cat.query(camera="Canon", near=near)
        expected = min(GRID, key=lambda p: math.hypot(p[0] - near[0], p[1] - near[1]))
        assert len(result) == 4  # (5.6, 8) x (r, g1)
        assert {(r["aperture"], r["channel"]) for r in result} == {(5.6, "r"), (5.6, "g1"), (8.0, "r"), (8.0, "g1")}
        for row in result:
            assert (row["field_x"], row["field_y"]) == pytest.approx(expected)
            assert row["distance"] == pytest.approx(math.hypot(expected[0] - 0.8, expected[1] - 0.1))
        one = cat.query(aperture=8, channel="r", near=(0.1, 0.9))
        assert len(one) == 1 and (one.rows[0]["field_x"], one.rows[0]["field_y"]) == pytest.approx((1 / 6, 5 / 6))


def test_an_empty_answer_names_the_first_filter_that_leaves_no_psf_and_what_there_is(tmp_path):
    """Filters applied one at a time (camera, lens, method, channel, then aperture, whose nearest measured
    value is taken among the others' PSFs): the first that leaves none is named, with the values there are."""
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        assert cat.why_empty() == "the catalogue holds no PSF"
        fill(cat)
        sony = new_run(cat, keys=("s",), rig=CameraInfo("Sony A7", "9", "FE 50mm", 50.0))
        cat.commit_step(sony, "s", [], [(make_psf(channel="g1"), {})])  # no f-number recorded
        assert cat.why_empty(camera="canon", channel="g1") is None  # it matches
        assert cat.why_empty(camera="EOS 5D") == ("no PSF of camera 'EOS 5D' (the catalogue has Canon EOS 400D, "
                                                  "Nikon D850, Sony A7)")
        assert cat.why_empty(lens="85mm", channel="g1") == ("no PSF of lens '85mm' (the catalogue has AF-S 24-70mm, "
                                                            "EF 50mm f/1.8, FE 50mm)")
        assert cat.why_empty(camera="canon", method="two-photo", channel="b") == (
            "no PSF of method two-photo with camera 'canon' (these have bernoulli)")
        assert cat.why_empty(camera="nikon", channel="r", aperture=4) == (
            "no PSF of channel r with camera 'nikon' (these have g1)")
        assert cat.why_empty(camera="sony", aperture=4) == "no PSF at f/4 with camera 'sony' (these have no f-number)"
        assert cat.why_empty(channel="b") == "no PSF of channel b (the catalogue has g1, r)"
        assert len(cat.query(camera="sony", aperture=4)) == 0 and len(cat.query(camera="sony")) == 1


def test_query_near_notes_a_nearest_psf_outside_the_grid_of_stored_locations(tmp_path):
    """The nearest PSF of a group is an extrapolation when the location asked is more than half the grid step
    of the group's stored locations from it along x or y: outside every measured window. The note says so."""
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        fill(cat)  # Canon: a whole 3x3 grid (step 1/3); Nikon: one location, the centre
        for near in ((0.8, 0.1), (0.0, 0.0), (1.0, 1.0), (0.5, 0.5), (0.9, 0.9)):
            # inside the whole grid, its corners too: the windows tile the field; one location covers it all
            assert cat.query(near=near).note is None
        sony = new_run(cat, keys=("s",), rig=CameraInfo("Sony A7", "9", "FE 50mm", 50.0))
        holed = [f for f in GRID if f != (5 / 6, 5 / 6)]  # the bottom-right window failed
        cat.commit_step(sony, "s", [], [(make_psf(field, "g1"), {"aperture": 8}) for field in holed])
        result = cat.query(camera="sony", near=(0.9, 0.9))
        (row,) = result.rows
        assert row["distance"] == pytest.approx(math.hypot(0.9 - 5 / 6, 0.4))
        assert result.note == ("no PSF measured near 0.9,0.9: the nearest stored location (0.500,0.833) is 0.406 "
                               "away, more than half the grid step (0.333 across, 0.333 down)")
        assert cat.query(camera="sony", near=(0.5, 0.5)).note is None
        assert cat.query(near=(0.9, 0.9)).note == (  # Canon r, g1 at f/5.6, f/8; Nikon; Sony
            "no PSF measured near 0.9,0.9 for 1 of 6 PSFs: the nearest stored location (0.500,0.833) is 0.406 "
            "away, more than half the grid step (0.333 across, 0.333 down)")
        away = new_run(cat, keys=("o",), rig=CameraInfo("Olympus E-M1", "3", "12-40mm", 12.0))
        cat.commit_step(away, "o", [], [(make_psf((0.2, 0.5), "g1"), {"aperture": 8})])  # one window, left
        assert cat.query(camera="olympus", near=(0.6, 0.5)).note is None  # 0.4: within the half field
        assert cat.query(camera="olympus", near=(0.8, 0.5)).note == (
            "no PSF measured near 0.8,0.5: the nearest stored location (0.200,0.500) is 0.600 away, more than half "
            "the grid step (1.000 across, 1.000 down)")


# -- concurrency ----------------------------------------------------------------------

STEPS, PER_STEP = 60, 4


def _reader(path, ready, done, out):
    """Query in a loop while the writer commits; report what was seen."""
    try:
        out.put(_read_until_done(path, ready, done))
    except BaseException as exc:  # report instead of leaving the test waiting on the queue
        out.put(([], [repr(exc)]))


def _read_until_done(path, ready, done):
    cat = Catalogue(path, create=False)
    seen, torn = set(), []
    ready.set()
    while True:
        finished = done.is_set()
        rows = cat.query().rows
        per_step: dict = {}
        for row in rows:
            per_step[row["step"]] = per_step.get(row["step"], 0) + 1
        torn += [(k, n) for k, n in per_step.items() if n != PER_STEP]
        torn += cat.integrity_check()
        if rows:
            array, _ = cat.psf(rows[-1]["id"])
            if not math.isclose(array.sum(), 1.0):
                torn.append(("array", rows[-1]["id"]))
        seen.add(len(rows))
        if finished:
            break
    cat.close()
    return sorted(seen), torn


def test_reader_never_sees_half_a_step_and_never_blocks_the_writer(tmp_path):
    path = tmp_path / "cat.sqlite"
    writer = Catalogue(path, timeout=0.0)  # no busy wait: any lock held by the reader would raise
    run = new_run(writer, keys=[f"s{i}" for i in range(STEPS)])
    ctx = multiprocessing.get_context("fork")
    ready, done, out = ctx.Event(), ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_reader, args=(str(path), ready, done, out))
    proc.start()
    try:
        assert ready.wait(30)
        for i in range(STEPS):
            psfs = [(make_psf((0.1 * j, 0.5), ch), {"aperture": 5.6}) for j, ch in enumerate("r g1 g2 b".split())]
            writer.commit_step(run, f"s{i}", [frame(i)], psfs)
        done.set()
        seen, torn = out.get(timeout=60)
    finally:
        proc.join(30)
        writer.close()
    assert torn == []
    assert seen[-1] == STEPS * PER_STEP
    assert all(n % PER_STEP == 0 for n in seen)
    assert len(seen) > 2  # the reader really overlapped the writer (it saw intermediate states)


def test_one_catalogue_shared_by_threads(tmp_path):
    """The service's control thread reads the catalogue its runner thread writes."""
    with Catalogue(tmp_path / "cat.sqlite") as cat:
        run = new_run(cat, keys=[f"s{i}" for i in range(20)])
        errors, summaries = [], []

        def write():
            for i in range(20):
                cat.commit_step(run, f"s{i}", [frame(i)], [(make_psf(channel=c), {}) for c in ("r", "b")])

        def read():
            try:
                while not summaries or summaries[-1]["done"] < 20:
                    summaries.append(cat.run_summary(run))
            except Exception as exc:  # noqa: BLE001 - reported below
                errors.append(exc)

        threads = [threading.Thread(target=write), threading.Thread(target=read)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert errors == []
        assert all(s["psfs"] == 2 * s["done"] for s in summaries)  # never a step without its PSFs
        assert summaries[-1]["psfs"] == 40 and cat.integrity_check() == []


# -- frame paths and the description for other tools ----------------------------------


def test_frame_paths_are_relative_to_the_catalogue_folder_so_it_can_move(tmp_path):
    folder = tmp_path / "lab"
    store = folder / "cat-frames" / "ab"
    store.mkdir(parents=True)
    inside, outside = store / "1.dng", tmp_path / "elsewhere" / "2.dng"
    with Catalogue(folder / "cat.sqlite") as cat:
        run = new_run(cat, keys=("a",))
        records = [FrameRecord(str(inside), "1" * 64, {}, {}, "t"), FrameRecord(str(outside), "2" * 64, {}, {}, "t")]
        estimate = make_psf()
        estimate.sources = [str(inside), str(outside)]
        (psf_id,) = cat.commit_step(run, "a", records, [(estimate, {"aperture": 5.6})])
        stored = [r[0] for r in cat.db.execute("SELECT path FROM frames ORDER BY id").fetchall()]
        (sources,) = cat.db.execute("SELECT sources FROM psfs").fetchone()
    assert stored == ["cat-frames/ab/1.dng", str(outside)]  # inside: relative; elsewhere: absolute
    assert sources == json.dumps(stored)  # the PSF's sources are stored the same way
    moved = tmp_path / "moved"
    (folder).rename(moved)
    with Catalogue(moved / "cat.sqlite") as cat:
        paths = [f["path"] for f in cat.psf_frames(psf_id)]
        assert cat.psf(psf_id)[1]["sources"] == paths
    assert paths == [str(moved / "cat-frames" / "ab" / "1.dng"), str(outside)]


def test_a_copy_of_the_file_alone_holds_every_ended_run_even_when_a_reader_is_open(tmp_path):
    # A reader open (a query, Datasette) stops SQLite's own checkpoint at close: the rows would stay in the
    # -wal only, and `cp catalogue.sqlite` would copy none of them. The service keeps its catalogue open
    # between runs: a run that ends leaves the file whole too.
    path = tmp_path / "cat.sqlite"
    Catalogue(path).close()
    reader = sqlite3.connect(f"{path.absolute().as_uri()}?mode=ro", uri=True)
    copy = tmp_path / "copy.sqlite"
    try:
        assert reader.execute("SELECT count(*) FROM psfs").fetchone() == (0,)
        with Catalogue(path) as cat:
            for n, key in enumerate(("a", "b")):
                run = new_run(cat, keys=(key,))
                cat.commit_step(run, key, [frame(n + 1)], [(make_psf(), {"aperture": 5.6})])
                if key == "a":
                    cat.finish_run(run, "done")
                    copy.write_bytes(path.read_bytes())  # the file alone, without its -wal
                    assert count(copy, "psfs") == 1 and count(copy, "runs") == 1
        copy.write_bytes(path.read_bytes())  # closed: the run left unfinished too
        assert count(copy, "psfs") == 2 and count(copy, "runs") == 2
    finally:
        reader.close()


def test_migration_to_relative_frame_paths_reads_old_absolute_paths(tmp_path):
    """A catalogue written before relative paths: absolute paths inside its folder become relative, others stay."""
    path = tmp_path / "old.sqlite"
    db = sqlite_utils.Database(path)
    for migrate in MIGRATIONS[:2]:
        migrate(db)
    db.execute("PRAGMA user_version = 2")
    db["frames"].insert_all([{"path": str(tmp_path / "old-frames" / "aa" / "x.dng"), "sha256": "a" * 64},
                             {"path": "/mnt/raw/y.dng", "sha256": "b" * 64}])
    db.close()
    with Catalogue(path) as cat:
        assert cat.schema_version() == SCHEMA_VERSION
        assert [r[0] for r in cat.db.execute("SELECT path FROM frames ORDER BY id").fetchall()] == [
            "old-frames/aa/x.dng", "/mnt/raw/y.dng"]


def test_datasette_metadata_describes_every_table_and_column(tmp_path):
    with Catalogue(tmp_path / "lab.sqlite") as cat:
        schema = {name: [c.name for c in cat.db[name].columns] for name in cat.db.table_names()}
    meta = catalogue_module.datasette_metadata("lab")
    tables = meta["databases"]["lab"]["tables"]
    assert set(tables) == set(schema)
    for name, columns in schema.items():
        assert set(tables[name]["columns"]) == set(columns), name
        assert all(isinstance(text, str) and text for text in tables[name]["columns"].values())
    psfs = tables["psfs"]["columns"]
    assert "cycles per channel pixel" in psfs["mtf50_x"] and "channel pixels" in psfs["fwhm_x"]
    assert "numpy.load" in psfs["psf"]
    assert tables["psfs"]["units"] == {"focal_length_mm": "mm", "focus_distance_m": "m"}


def test_relative_frame_paths_migration_runs_again_without_change(tmp_path, monkeypatch):
    """Other branches' migrations may reach a catalogue in another order: running version 4 again (from any
    working folder) leaves relative paths alone instead of reading them against the working folder."""
    path = tmp_path / "lab" / "cat.sqlite"
    path.parent.mkdir()
    with Catalogue(path) as cat:
        cat.db["frames"].insert_all([{"path": "cat-frames/aa/x.dng", "sha256": "a" * 64},
                                     {"path": "/mnt/raw/y.dng", "sha256": "b" * 64}])
    monkeypatch.chdir(tmp_path)
    db = sqlite_utils.Database(path)
    catalogue_module._v4_relative_frame_paths(db)  # by name: the latest migration is another one
    assert [r[0] for r in db.execute("SELECT path FROM frames ORDER BY id").fetchall()] == [
        "cat-frames/aa/x.dng", "/mnt/raw/y.dng"]
    db.close()


def test_a_sqlite_utils_that_commits_half_way_is_refused_before_any_file(tmp_path, monkeypatch):
    """sqlite-utils before 4.0 (which pyproject allowed) ended the catalogue's transaction in each table
    method: a catalogue killed while being made kept its tables under schema version 0, which every command
    then refused as not a psfd catalogue, and a step's rows were committed one by one. Such a library is
    refused in one line before the catalogue file is made; readers, which write nothing, still read."""
    path = tmp_path / "new" / "cat.sqlite"
    Catalogue(tmp_path / "old.sqlite").close()
    monkeypatch.delattr(sqlite_utils.Database, "atomic")  # what 3.x lacks
    with pytest.raises(CatalogueError, match=r"^psfd needs sqlite-utils 4.0 or newer .*: pip install "):
        Catalogue(path)
    assert not path.parent.exists()
    with Catalogue(tmp_path / "old.sqlite", readonly=True) as cat:
        assert cat.runs() == []


def test_a_catalogue_made_by_another_process_while_it_is_opened_is_a_catalogue(tmp_path, monkeypatch):
    """Opening a file read its schema version and then its tables, apart: when another process made the
    catalogue in between (two runs starting, a run and the service, a query while a run starts; here the file
    a killed creation left, in WAL mode), the opener saw tables under version 0 and refused the file as 'a
    SQLite file but not a psfd catalogue' (psfd run exit 5). Both are read in one snapshot."""
    path = tmp_path / "cat.sqlite"
    conn = sqlite3.connect(path)
    conn.execute("PRAGMA journal_mode = WAL")  # a creation killed after its first statement
    conn.close()
    real = Catalogue.schema_version
    made = []

    def meanwhile(self):
        version = real(self)
        if not made:  # the other process makes the catalogue right after this one read version 0
            made.append(subprocess.run([sys.executable, "-c", "import sys; from psfd.catalogue import Catalogue; "
                                        "Catalogue(sys.argv[1]).close()", str(path)], capture_output=True,
                                       text=True, timeout=120))
        return version

    monkeypatch.setattr(Catalogue, "schema_version", meanwhile)
    with Catalogue(path) as cat:
        assert made[0].returncode == 0, made[0].stderr
        assert cat.schema_version() == SCHEMA_VERSION and cat.runs() == []
