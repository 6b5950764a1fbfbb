"""`psfd capture / run / status / demo` on the simulated rig, locally and through the service."""

from __future__ import annotations

import subprocess
import sys

import pytest

from psfd.catalogue import Catalogue
from psfd.cli import main
from psfd.cli.lab import parse_rail
from psfd.daemon import service
from psfd.errors import BadInputError

from test_service import served  # noqa: F401 - fixture


def test_capture_locally_adds_the_psfs_to_the_catalogue(tmp_path, capsys):
    db, out = tmp_path / "cat.sqlite", tmp_path / "shots"
    code = main(["capture", "--aperture", "5.6", "--simulate", "--channels", "g1,b", "--out", str(out),
                 "--catalogue", str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "done: 1 steps, 1 frames, 2 PSFs" in printed and "bernoulli" in printed
    with Catalogue(db) as cat:
        rows = cat.query().rows
        assert sorted(r["channel"] for r in rows) == ["b", "g1"]
        assert all(r["aperture"] == 5.6 and r["method"] == "bernoulli" for r in rows)
        (frame,) = cat.psf_frames(rows[0]["id"])
    assert frame["path"].startswith(str(out)) and frame["path"].endswith(f"{frame['sha256']}.dng")


def test_capture_near_far_pair(tmp_path, capsys):
    db = tmp_path / "cat.sqlite"
    assert main(["capture", "--aperture", "8", "--target", "pair", "--simulate", "--channels", "g1",
                 "--catalogue", str(db), "--socket", str(tmp_path / "none.sock"), "--workers", "1"]) == 0
    assert "1 steps, 2 frames, 1 PSFs" in capsys.readouterr().out
    with Catalogue(db) as cat:
        (row,) = cat.query().rows
        assert row["method"] == "two-photo" and row["step"].startswith("a8/x587.5-2200")
        assert len(cat.psf_frames(row["id"])) == 2  # the PSF is tied to both photographs


def test_capture_goes_through_the_service_when_it_is_up(served, tmp_path):  # noqa: F811
    proc, sock, db, notes = served
    cli = subprocess.run([sys.executable, "-m", "psfd", "capture", "--aperture", "8", "--simulate",
                          "--rail", "Y=0", "--channels", "g1", "--socket", str(sock),
                          "--catalogue", str(tmp_path / "ignored.sqlite")],
                         capture_output=True, text=True, timeout=300)
    assert cli.returncode == 0, cli.stderr
    assert "done: 1 steps" in cli.stdout
    with Catalogue(db) as cat:  # stored in the service's catalogue, not the one on the command line
        assert [r["aperture"] for r in cat.query().rows] == [8.0]
    assert not (tmp_path / "ignored.sqlite").exists()
    assert service.request(sock, {"cmd": "status"})["last"]["state"] == "done"


@pytest.mark.parametrize("argv, message", [
    (["capture", "--aperture", "f/abc", "--simulate"], "--aperture: expected an f-number"),
    (["capture", "--aperture", "5.6", "--rail", "W=3", "--simulate"], "--rail: expected AXIS=MM"),
    (["capture", "--aperture", "5.6"], "--rail X=MM is needed"),
    (["capture", "--aperture", "5.6", "--target", "pair", "--rail", "X=900", "--simulate"], "give --near MM"),
    (["capture", "--aperture", "5.6", "--target", "pair", "--near", "close", "--simulate"], "--near: expected a number"),
    (["capture", "--aperture", "5.6", "--simulate", "--workers", "0"], "--workers: must be at least 1"),
])
def test_bad_capture_arguments(argv, message, tmp_path, capsys):
    db = tmp_path / "cat.sqlite"
    assert main(argv + ["--catalogue", str(db), "--socket", str(tmp_path / "none.sock")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0]
    assert not db.exists()  # nothing half-written


def test_bad_plan_run_leaves_no_catalogue(tmp_path, capsys):
    plan = tmp_path / "bad.toml"
    plan.write_text("[target]\nkind = 'bernoulli'\n[capture]\napertures = []\n")
    db = tmp_path / "cat.sqlite"
    assert main(["run", str(plan), "--catalogue", str(db), "--socket", str(tmp_path / "none.sock")]) == 2
    err = capsys.readouterr().err
    assert "psfd plan check" in err and len(err.strip().splitlines()) == 1
    assert not db.exists()


def test_parse_rail():
    assert parse_rail(["X=1200,y=-40", "Z=5"]) == {"x": 1200.0, "y": -40.0, "z": 5.0}
    with pytest.raises(BadInputError, match="Y must be a number"):
        parse_rail(["Y=left"])


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
    # physical sanity of what was stored: at every field point f/16 (diffraction) is softer than f/4
    mtf = {(r["aperture"], r["channel"], r["step"].split("/", 1)[1]): r["mtf50_x"] for r in rows}
    softer = [mtf[(16.0, c, where)] < mtf[(4.0, c, where)] for (a, c, where) in mtf if a == 4.0]
    assert len(softer) == 36 and all(softer)
