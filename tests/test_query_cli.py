"""`psfd query`, `psfd export`, `psfd report` on a real catalogue file."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import cv2
import numpy as np
import pytest
import tifffile

from psfd import figures
from psfd.catalogue import Catalogue, FrameRecord
from psfd.cli import main
from psfd.cli import query as query_cli
from psfd.drivers.base import CameraInfo
from psfd.estimator.kernels import PSF

from test_run_lifecycle import small_disk  # noqa: F401 - fixture

# a catalogue and the WAL files its writer keeps for readers without write access
CATALOGUE_FILES = ["cat.sqlite", "cat.sqlite-shm", "cat.sqlite-wal"]
GRID = [(x, y) for y in (1 / 6, 0.5, 5 / 6) for x in (1 / 6, 0.5, 5 / 6)]


def gaussian(sigma: float, support: int = 17) -> np.ndarray:
    r = np.arange(support) - support // 2
    k = np.exp(-(r[:, None] ** 2 + r[None, :] ** 2) / (2 * sigma**2))
    return k / k.sum()


def sigma_at(field, aperture) -> float:
    """Synthetic lens: wider at small apertures' diffraction limit and towards the corners."""
    r2 = (field[0] - 0.5) ** 2 + (field[1] - 0.5) ** 2
    return aperture / 4 * (1 + 2 * r2)


@pytest.fixture
def catalogue(tmp_path):
    """A catalogue with g1 and r PSFs on a 3x3 field grid at f/5.6 and f/8."""
    path = tmp_path / "cat.sqlite"
    with Catalogue(path) as cat:
        rig = cat.add_rig(CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0))
        run = cat.start_run("plan.toml", "plan", rig, [("f5.6", {}), ("f8", {})])
        for key, aperture in (("f5.6", 5.6), ("f8", 8.0)):
            psfs = [
                (PSF(gaussian(sigma_at(f, aperture)), 4, "bernoulli", ch, ["x.dng"], f, (0, 0, 64, 64)),
                 {"aperture": aperture})
                for f in GRID
                for ch in ("r", "g1")
            ]
            cat.commit_step(run, key, [], psfs)
    return str(path)


def run_cli(capsys, *argv):
    code = main(list(argv))
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code, err, expected_code, text):
    assert code == expected_code
    assert err.startswith("psfd: error:") and err.count("\n") == 1 and text in err


def measured_at_centre(cat: Catalogue, info: CameraInfo, plan: tuple[str, str], steps: list[str], sigma: float,
                       source: str, aperture: float) -> int:
    """A run of ``plan`` (path, text) by the rig ``info``, its first step done: one g1 PSF at the field centre."""
    run = cat.start_run(*plan, cat.add_rig(info), [(key, {}) for key in steps])
    cat.commit_step(run, steps[0], [], [(PSF(gaussian(sigma), 4, "bernoulli", "g1", [source], (0.5, 0.5),
                                             (0, 0, 64, 64)), {"aperture": aperture})])
    return run


def test_the_table_names_the_body_when_two_bodies_of_one_model_answer(capsys, catalogue):
    with Catalogue(catalogue) as cat:  # a second body of the same model and lens, measured at the centre
        measured_at_centre(cat, CameraInfo("Canon EOS 400D", "0777", "EF 50mm f/1.8", 50.0),
                           ("other.toml", "other plan"), ["f5.6"], 3.0, "y.dng", 5.6)
    code, out, _ = run_cli(capsys, "query", "--catalogue", catalogue, "--aperture", "5.6", "--channel", "g1",
                           "--near", "0.5,0.5")
    header, *rows, _ = out.splitlines()
    assert code == 0 and header.split()[:3] == ["id", "camera", "serial"]
    assert sorted(row.split()[4] for row in rows) == ["0420", "0777"]  # after "Canon EOS 400D"
    code, out, _ = run_cli(capsys, "query", "--catalogue", catalogue, "--camera", "0420", "--limit", "1")
    assert code == 0 and "serial" not in out.splitlines()[0]  # one body: no column for it


def test_the_table_names_the_lens_copy_when_two_copies_of_one_model_answer(capsys, catalogue):
    with Catalogue(catalogue) as cat:  # two copies of the fixture's lens on its body, told apart by their EXIF
        rig = cat.add_rig(CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0))
        run = cat.start_run("copies.toml", "copies plan", rig, [("A", {}), ("B", {})])
        for n, copy in enumerate(("A", "B")):
            shot = FrameRecord(f"/raw/{copy}.dng", f"{n:064x}", {"aperture": "5.6"}, {}, "t",
                               exif={"lens": "EF 50mm f/1.8", "lens_serial": f"LENS-{copy}"})
            cat.commit_step(run, copy, [shot], [(PSF(gaussian(1.0 + n), 4, "bernoulli", "b", [shot.path],
                                                     (0.5, 0.5), (0, 0, 64, 64)), {"aperture": 5.6})])
    code, out, _ = run_cli(capsys, "query", "--catalogue", catalogue, "--channel", "b", "--near", "0.5,0.5")
    header, *rows, _ = out.splitlines()
    assert code == 0 and header.split()[:4] == ["id", "camera", "lens", "lens"]  # "lens #"
    assert sorted(row.split("  ")[2:4] for row in rows) == [["EF 50mm f/1.8", "LENS-A"], ["EF 50mm f/1.8", "LENS-B"]]


def test_readers_say_when_a_run_is_not_done(capsys, catalogue, tmp_path):
    """A run stopped part-way (killed, paused, cancelled): query, export and report say that its other
    PSFs are missing, on stderr, in index.json and under the report's title; a whole run says nothing."""
    with Catalogue(catalogue) as cat:
        run = measured_at_centre(cat, CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0),
                                 ("part.toml", "part"), ["f11", "f16", "f22"], 3.0, "y.dng", 11.0)
        cat.finish_run(run, "paused")
    note = f"run {run} is not done (paused, 1 of 3 steps): the PSFs of its other steps are missing"
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--channel", "g1")
    assert code == 0 and err == f"psfd: note: {note}\n"
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--aperture", "5.6")
    assert code == 0 and err == ""  # the rows of the whole run only
    code, _, err = run_cli(capsys, "export", "--catalogue", catalogue, "--aperture", "11", "--out",
                           str(tmp_path / "ex"))
    assert code == 0 and note in err
    assert json.loads((tmp_path / "ex" / "index.json").read_text())["note"] == note
    code, _, err = run_cli(capsys, "report", "--catalogue", catalogue, "--out", str(tmp_path / "r.png"))
    assert code == 0 and note in err
    with Catalogue(catalogue, readonly=True) as cat:
        rows = cat.query().rows
        arrays = {row["id"]: cat.psf(row["id"])[0] for row in rows}
    title = figures.report_figure(rows, arrays, "g1", note=note)._suptitle.get_text()
    assert f"Note: {note}." in title.replace("\n", " ")


def test_readers_call_a_killed_run_interrupted_as_status_does(capsys, catalogue):
    """A run whose process was killed stays journalled ``running``: the readers' note said "running", as if
    it were still shooting, where `psfd status` says "interrupted" (nobody holds its frame store)."""
    with Catalogue(catalogue) as cat:
        run = measured_at_centre(cat, CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0),
                                 ("killed.toml", "killed"), ["f11", "f16"], 3.0, "y.dng", 11.0)
    code, out, err = run_cli(capsys, "status", "--catalogue", catalogue, "--json")
    assert code == 0 and json.loads(out)["runs"][0]["state"] == "interrupted"
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--aperture", "11")
    assert code == 0
    assert err == f"psfd: note: run {run} is not done (interrupted, 1 of 2 steps): the PSFs of its other steps " \
                  "are missing\n"


def test_metadata_describes_a_catalogue_and_refuses_what_is_not_one(capsys, catalogue, tmp_path):
    code, out, err = run_cli(capsys, "metadata", "--catalogue", catalogue)
    assert code == 0 and "cat" in json.loads(out)["databases"]
    garbage = tmp_path / "notes.sqlite"
    garbage.write_text("not a database")
    for path in (tmp_path / "mistyped.sqlite", garbage):
        code, out, err = run_cli(capsys, "metadata", "--catalogue", str(path), "--out", str(tmp_path / "m.json"))
        assert_one_line_error(code, err, 5, path.name)
        assert out == "" and not (tmp_path / "m.json").exists()


def test_query_table_and_note(capsys, catalogue):
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--aperture", "5.6", "--channel", "g1")
    lines = out.splitlines()
    assert code == 0 and err == ""
    assert lines[0].split()[:4] == ["id", "camera", "lens", "f/"] and len(lines) == 1 + 9 + 1
    assert all(" 5.6 " in line and " g1 " in line for line in lines[1:-1])
    assert lines[-1].startswith("units: ") and "mtf50 in cycles per channel pixel" in lines[-1]
    assert "lp/mm" not in lines[0]  # no pixel pitch known for these PSFs: no lp/mm column
    assert "lp/mm" not in lines[-1] and "dist" not in lines[-1]  # nor units of columns not shown
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--channel", "g1", "--near", "0.5,0.5")
    assert code == 0 and out.splitlines()[0].split()[-1] == "dist" and "dist: field distance" in out.splitlines()[-1]

    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--aperture", "f/6.3")
    assert code == 0 and err.strip() == "psfd: note: f/6.3 not measured; nearest is f/5.6"
    assert len(out.splitlines()) == 1 + 18 + 1


def test_query_aperture_answers_for_every_lens_and_names_those_not_measured_at_it(capsys, catalogue):
    """`--aperture 11` in a catalogue of a lens measured at f/5.6 and f/8 and one measured at f/11: each lens
    answers with its own nearest f-number, shown in the f/ column, and the note on stderr names the lens
    that has no f/11 (before, the first lens was left out without a word)."""
    with Catalogue(catalogue) as cat:
        measured_at_centre(cat, CameraInfo("Nikon D850", "77", "AF-S 85mm f/1.8G", 85.0), ("other.toml", "other"),
                           ["f11"], 2.0, "y.nef", 11.0)
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--aperture", "11", "--channel", "g1",
                             "--near", "0.5,0.5")
    rows = [line.split() for line in out.splitlines()[1:-1]]
    assert code == 0 and [(row[1], row[-9]) for row in rows] == [("Canon", "8"), ("Nikon", "11")]
    assert err == "psfd: note: f/11 not measured with Canon EOS 400D #0420 / EF 50mm f/1.8 (nearest: f/8)\n"


def test_query_json_near(capsys, catalogue):
    code, out, _ = run_cli(capsys, "query", "--catalogue", catalogue, "--near", "0.8,0.1", "--json")
    rows = [json.loads(line) for line in out.splitlines()]
    assert code == 0 and len(rows) == 4  # one per (aperture, channel)
    with Catalogue(catalogue, create=False) as cat:
        for row in rows:
            assert (row["field_x"], row["field_y"]) == pytest.approx((5 / 6, 1 / 6))
            np.testing.assert_array_equal(np.array(row["psf"]), cat.psf(row["id"])[0])


@pytest.mark.parametrize("fmt", ["npy", "tiff", "json", "tif", "TIFF"])  # tif: as the files are named
def test_export_formats(capsys, catalogue, tmp_path, fmt):
    out_dir = tmp_path / "export"
    code, _, _ = run_cli(capsys, "export", "--catalogue", catalogue, "--channel", "g1", "--aperture", "8",
                         "--format", fmt, "--out", str(out_dir))
    assert code == 0
    index = json.loads((out_dir / "index.json").read_text())
    assert len(index["psfs"]) == 9 and len(list(out_dir.iterdir())) == 9 + 2  # and index.json, metrics.csv
    with Catalogue(catalogue, create=False) as cat:
        for entry in index["psfs"]:
            expected = cat.psf(entry["id"])[0]
            path = out_dir / entry["file"]
            if fmt == "npy":
                np.testing.assert_array_equal(np.load(path), expected)
            elif fmt.lower() in ("tiff", "tif"):
                with tifffile.TiffFile(path) as tif:
                    assert tif.pages[0].dtype == np.float32
                    assert json.loads(tif.pages[0].description)["id"] == entry["id"]
                    # float32 rounding: relative error below 2^-24 of the largest value
                    np.testing.assert_allclose(tif.asarray(), expected, rtol=0, atol=expected.max() * 2**-23)
            else:
                np.testing.assert_array_equal(np.array(json.loads(path.read_text())["psf"]), expected)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_export_failure_leaves_nothing(capsys, catalogue, tmp_path, monkeypatch):
    real, calls = query_cli._write_psf, []

    def fail_third(*args):
        calls.append(1)
        if len(calls) == 3:
            raise OSError("disk full")
        return real(*args)

    monkeypatch.setattr(query_cli, "_write_psf", fail_third)
    code, _, err = run_cli(capsys, "export", "--catalogue", catalogue, "--out", str(tmp_path / "export"))
    assert_one_line_error(code, err, 2, "disk full")
    assert len(calls) == 3
    assert sorted(p.name for p in tmp_path.iterdir()) == CATALOGUE_FILES


def test_export_force_replaces_an_earlier_export_and_nothing_else(catalogue, tmp_path):
    def export(*argv: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "psfd", "export", "--catalogue", catalogue, "--channel", "g1",
                               "--aperture", "8", *argv], capture_output=True, text=True, timeout=120)

    out = tmp_path / "export"
    for fmt, suffix in (("npy", ".npy"), ("tiff", ".tif"), ("json", ".json"), ("npy", ".npy")):
        done = export("--format", fmt, "--out", str(out), "--force")
        assert done.returncode == 0, done.stderr
        psfs = [p.suffix for p in out.iterdir() if p.name.startswith("psf")]
        assert psfs == [suffix] * 9 and len(list(out.iterdir())) == 9 + 2  # and index.json, metrics.csv
    (out / "keep.txt").write_text("mine")
    before = sorted(p.name for p in out.iterdir())
    done = export("--out", str(out), "--force")
    assert_one_line_error(done.returncode, done.stderr, 2, "keep.txt")
    assert sorted(p.name for p in out.iterdir()) == before and (out / "keep.txt").read_text() == "mine"


def test_report_as_png_and_vector(capsys, catalogue, tmp_path):
    """`psfd report` writes the field report (its content: tests/test_figures.py) by the file's suffix."""
    (tmp_path / "figs").mkdir()
    for name, magic in (("report.png", b"\x89PNG"), ("report.pdf", b"%PDF"), ("report.svg", b"<?xml")):
        out = tmp_path / "figs" / name
        code, stdout, _ = run_cli(capsys, "report", "--catalogue", catalogue, "--out", str(out))
        assert code == 0 and stdout == f"report written to {out}\n"
        assert out.read_bytes().startswith(magic)
    image = cv2.imread(str(tmp_path / "figs" / "report.png"))
    assert image.shape[1] > 1200 and image.std() > 20  # two channels and two MTF50 maps per row
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == ["report.pdf", "report.png", "report.svg"]
    # --channel picks the channel of the MTF50 maps; every channel's PSFs are drawn
    code, _, _ = run_cli(capsys, "report", "--catalogue", catalogue, "--channel", "r", "--out", str(tmp_path / "r.png"))
    assert code == 0
    code, _, err = run_cli(capsys, "report", "--catalogue", catalogue, "--channel", "b", "--out", str(tmp_path / "b.png"))
    assert code == 1 and "no PSF" in err and not (tmp_path / "b.png").exists()  # nothing matched


def test_query_csv_and_units(capsys, catalogue):
    import csv
    import io

    code, out, _ = run_cli(capsys, "query", "--catalogue", catalogue, "--channel", "g1", "--csv")
    rows = list(csv.DictReader(io.StringIO(out)))
    assert code == 0 and len(rows) == 18
    header = out.splitlines()[0].split(",")
    assert "mtf50_x [cycles/px]" in header and "mtf50_x [lp/mm]" in header and "fwhm_x [channel px]" in header
    with Catalogue(catalogue, create=False) as cat:
        for row in rows:
            stored = cat.psf(int(row["id"]))[1]
            assert float(row["mtf50_x [cycles/px]"]) == pytest.approx(stored["mtf50_x"], rel=1e-5)
            # every number the table and JSON give, the prediction error too
            predicted = row["prediction_error [cross-validated residual / noise level]"]
            assert (predicted == "" if stored["prediction_error"] is None else
                    float(predicted) == pytest.approx(stored["prediction_error"], rel=1e-5))
            assert row["aperture [f-number]"] == format(stored["aperture"], ".6g") and row["camera"] == "Canon EOS 400D"
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--channel", "b", "--csv")
    assert code == 1 and len(out.splitlines()) == 1 and "no PSF matches" in err  # the header alone


def test_the_formats_page_lists_every_csv_header_and_the_pixel_of_each_px(capsys, catalogue):
    """docs/formats.md promises that a column is never renamed; a CSV column's name is its whole header, as
    programs read it (`row["mtf50_x [cycles/px]"]` above: `mtf50_x [lp/mm]` shares the part before the
    bracket). `mtf50_x [cycles/px]` counts channel pixels and `image_height [px]` photosites: read with the
    photosite pitch, the first gave lp/mm twice too high. The page lists every header as written, in order,
    and says which pixel each px is."""
    import csv
    import io
    import re
    from pathlib import Path

    text = (Path(__file__).parents[1] / "docs" / "formats.md").read_text(encoding="utf-8")
    section = text.split("\n## CSV", 1)[1].split("\n## ", 1)[0]
    table = [re.match(r"\| `(.+?)` \| (.+) \|$", line) for line in section.splitlines() if line.startswith("| `")]
    code, out, _ = run_cli(capsys, "query", "--catalogue", catalogue, "--csv")
    assert code == 0 and [m.group(1) for m in table] == next(csv.reader(io.StringIO(out)))
    units = {m.group(1): m.group(2) for m in table}
    for header in ("mtf50_x [cycles/px]", "mtf50_y [cycles/px]"):
        assert "cycles per channel pixel" in units[header]
    assert "photosites" in units["image_height [px]"]
    assert all("channel pixel" in unit for header, unit in units.items() if "[channel px]" in header)
    assert "two photosites across" in " ".join(section.split())  # what a channel pixel is


def test_bad_inputs_give_one_line_errors(capsys, catalogue, tmp_path):
    cases = [
        (["query", "--near", "0.8;0.1"], 2, "--near"),
        (["query", "--near", "1.5,0.1"], 2, "--near"),
        (["query", "--aperture", "wide"], 2, "f-number"),
        (["query", "--channel", "green"], 2, "channel"),
        (["query", "--limit", "0"], 2, "--limit"),
        (["export", "--format", "bmp", "--out", str(tmp_path / "x")], 2, "format"),
        (["query", "--method", "foo"], 2, "unknown method 'foo'"),
        (["export", "--method", "two-photo", "--out", str(tmp_path / "empty")], 1, "no PSF matches"),
        (["report", "--method", "two-photo", "--out", str(tmp_path / "r.png")], 1, "no PSF matches"),
        (["report", "--out", str(tmp_path / "r.xyz")], 2, "cannot write a figure"),
    ]
    for argv, expected, text in cases:
        code, _, err = run_cli(capsys, *argv, "--catalogue", catalogue)
        assert_one_line_error(code, err, expected, text)
    assert sorted(p.name for p in tmp_path.iterdir()) == CATALOGUE_FILES

    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("mine")
    code, _, err = run_cli(capsys, "export", "--catalogue", catalogue, "--out", str(tmp_path / "full"))
    assert_one_line_error(code, err, 2, "not an empty folder")
    assert [p.name for p in (tmp_path / "full").iterdir()] == ["keep.txt"]

    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(os.urandom(4096))
    code, _, err = run_cli(capsys, "query", "--catalogue", str(garbage))
    assert_one_line_error(code, err, 5, "not a psfd catalogue")
    empty = tmp_path / "empty.sqlite"
    empty.touch()
    code, _, err = run_cli(capsys, "query", "--catalogue", str(empty))
    assert_one_line_error(code, err, 5, "no catalogue")  # as `status` says: a writer makes a catalogue in it
    assert empty.stat().st_size == 0
    code, _, err = run_cli(capsys, "query", "--catalogue", str(tmp_path / "missing.sqlite"))
    assert_one_line_error(code, err, 5, "no catalogue")
    assert not (tmp_path / "missing.sqlite").exists()


def test_unwritable_outputs_are_one_line_errors(capsys, catalogue, tmp_path):
    # /proc refuses new files and folders even to root, where a chmod-000 folder would not.
    code, _, err = run_cli(capsys, "export", "--catalogue", catalogue, "--out", "/proc/psfd-export")
    assert_one_line_error(code, err, 2, "cannot write in /proc")
    code, _, err = run_cli(capsys, "report", "--catalogue", catalogue, "--out", "/proc/psfd-report.png")
    assert_one_line_error(code, err, 2, "could not write /proc/psfd-report.png")
    (tmp_path / "file.txt").write_text("")
    code, _, err = run_cli(capsys, "report", "--catalogue", catalogue, "--out", str(tmp_path / "file.txt" / "r.png"))
    assert_one_line_error(code, err, 2, "file.txt: not a folder")
    code, _, err = run_cli(capsys, "query", "--catalogue", "/proc/psfd.sqlite")
    assert_one_line_error(code, err, 5, "no catalogue")


def test_json_query_without_match_says_so_on_stderr(capsys, catalogue):
    code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, "--camera", "EOS 5D", "--json")
    assert (code, out, err) == (1, "", "psfd: error: no PSF matches: no PSF of camera 'EOS 5D' (the catalogue has "
                                       "Canon EOS 400D)\n")  # exit 1, as grep


def test_query_subprocess_uses_the_default_catalogue(catalogue, tmp_path):
    data_home = tmp_path / "xdg"
    (data_home / "psfd").mkdir(parents=True)
    os.replace(catalogue, data_home / "psfd" / "catalogue.sqlite")
    env = {**os.environ, "XDG_DATA_HOME": str(data_home)}
    proc = subprocess.run(
        [sys.executable, "-m", "psfd", "query", "--channel", "r", "--aperture", "8", "--near", "0.5,0.5", "--json"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    (row,) = [json.loads(line) for line in proc.stdout.splitlines()]
    assert (row["channel"], row["aperture"], row["field_x"], row["field_y"]) == ("r", 8.0, 0.5, 0.5)
    assert np.array(row["psf"]) == pytest.approx(gaussian(sigma_at((0.5, 0.5), 8.0)))


def _capture(catalogue, *argv) -> None:
    """One simulated-rig capture into ``catalogue`` by the whole ``psfd`` process (its frames beside it)."""
    proc = subprocess.run(
        [sys.executable, "-m", "psfd", "capture", "--aperture", "5.6", "--simulate", "--channels", "g1",
         "--catalogue", str(catalogue), "--socket", str(catalogue.parent / "none.sock"), "--workers", "1", *argv],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr


def _query_json(catalogue) -> list[dict]:
    proc = subprocess.run([sys.executable, "-m", "psfd", "query", "--catalogue", str(catalogue), "--json"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return [json.loads(line) for line in proc.stdout.splitlines()]


def test_moved_catalogue_and_frame_store_show_the_frames_where_they_now_are(tmp_path):
    """The audit: a catalogue copied with its frame store, the old folder gone, shows the sources under the
    new folder (JSON and CSV), files that exist."""
    import csv

    _capture(tmp_path / "k1" / "cat.sqlite")
    moved = tmp_path / "moved"
    moved.mkdir()
    subprocess.run(["cp", "-a", str(tmp_path / "k1" / "cat.sqlite"), str(tmp_path / "k1" / "cat-frames"),
                    str(moved)], check=True)
    os.rename(tmp_path / "k1", tmp_path / "k1.away")
    (row,) = _query_json(moved / "cat.sqlite")
    (source,) = row["sources"]
    assert source.startswith(str(moved / "cat-frames") + os.sep) and os.path.isfile(source)
    table = subprocess.run([sys.executable, "-m", "psfd", "query", "--catalogue", str(moved / "cat.sqlite"), "--csv"],
                           capture_output=True, text=True, timeout=120)
    assert table.returncode == 0, table.stderr
    (record,) = csv.DictReader(table.stdout.splitlines())
    assert record["source"] == source


def test_sources_outside_the_catalogue_folder_stay_absolute(tmp_path):
    shots = tmp_path / "elsewhere" / "shots"
    _capture(tmp_path / "k1" / "cat.sqlite", "--out", str(shots))
    with Catalogue(tmp_path / "k1" / "cat.sqlite", readonly=True) as cat:
        (stored,) = json.loads(cat.db.execute("SELECT sources FROM psfs").fetchone()[0])
    assert os.path.isabs(stored) and stored.startswith(str(shots) + os.sep)
    os.rename(tmp_path / "k1", tmp_path / "moved")
    (row,) = _query_json(tmp_path / "moved" / "cat.sqlite")
    assert row["sources"] == [stored] and os.path.isfile(stored)


def _psfd(*argv: str, **kwargs) -> subprocess.CompletedProcess:
    """The whole ``python -m psfd`` process, as a user runs it."""
    return subprocess.run([sys.executable, "-m", "psfd", *argv], capture_output=True, text=True, timeout=120,
                          **kwargs)


def test_channel_names_are_read_in_any_case_as_camera_names_are(catalogue, tmp_path):
    """--channel G1 is --channel g1 (the stored names are lower case); an unknown one is still refused."""
    lower = _psfd("query", "--catalogue", catalogue, "--channel", "g1", "--csv")
    assert lower.returncode == 0, lower.stderr
    upper = _psfd("query", "--catalogue", catalogue, "--channel", "G1", "--csv")
    assert upper.returncode == 0 and upper.stdout == lower.stdout, upper.stderr
    red = _psfd("query", "--catalogue", catalogue, "--channel", "R", "--csv")
    rows = red.stdout.splitlines()[1:]
    assert red.returncode == 0 and len(rows) == 18 and all(",r," in row for row in rows), red.stderr
    mono = _psfd("query", "--catalogue", catalogue, "--channel", "Mono")
    assert mono.returncode == 1 and "no PSF matches" in mono.stderr  # known, none stored: no match, not bad input
    export = _psfd("export", "--catalogue", catalogue, "--channel", "G1", "--aperture", "8", "--out",
                   str(tmp_path / "ex"))
    assert export.returncode == 0 and len(json.loads((tmp_path / "ex" / "index.json").read_text())["psfs"]) == 9
    bad = _psfd("query", "--catalogue", catalogue, "--channel", "G3")
    assert bad.returncode == 2 and bad.stderr == ("psfd: error: --channel: unknown channel 'G3' "
                                                  "(one of r, g1, g2, b, mono)\n")


def test_method_names_are_read_in_any_case_as_channel_names_are(catalogue):
    """--method Bernoulli is --method bernoulli (the README: the filters ignore case); it was an unknown method."""
    lower = _psfd("query", "--catalogue", catalogue, "--method", "bernoulli", "--csv")
    assert lower.returncode == 0 and len(lower.stdout.splitlines()) == 1 + 36, lower.stderr
    for name in ("Bernoulli", "BERNOULLI", "Target"):  # target: psfd 0.1's word for it
        upper = _psfd("query", "--catalogue", catalogue, "--method", name, "--csv")
        assert upper.returncode == 0 and upper.stdout == lower.stdout, upper.stderr
    pair = _psfd("query", "--catalogue", catalogue, "--method", "Two-Photo")
    assert pair.returncode == 1 and "no PSF of method two-photo" in pair.stderr  # known, none stored
    bad = _psfd("query", "--catalogue", catalogue, "--method", "Bernouli")
    assert bad.returncode == 2 and bad.stderr == ("psfd: error: --method: unknown method 'Bernouli' "
                                                  "(one of bernoulli, two-photo, sharp-edge)\n")


def test_no_match_says_which_filter_left_no_psf_and_what_the_catalogue_has(catalogue, tmp_path):
    """One line, exit 1 as before: the first filter that leaves no PSF, and the values there are."""
    cases = [
        (["query", "--channel", "b"], "no PSF matches: no PSF of channel b (the catalogue has g1, r)"),
        (["query", "--camera", "canon", "--method", "two-photo", "--aperture", "4"],
         "no PSF matches: no PSF of method two-photo with camera 'canon' (these have bernoulli)"),
        (["export", "--camera", "nikon", "--out", str(tmp_path / "ex")],
         "no PSF matches: no PSF of camera 'nikon' (the catalogue has Canon EOS 400D); nothing exported"),
        (["report", "--channel", "B", "--out", str(tmp_path / "r.png")],
         "no PSF matches: no PSF of channel b (the catalogue has g1, r); nothing to report"),
    ]
    for argv, message in cases:
        done = _psfd(*argv, "--catalogue", catalogue)
        assert (done.returncode, done.stdout, done.stderr) == (1, "", f"psfd: error: {message}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == CATALOGUE_FILES


def test_near_notes_on_stderr_when_no_psf_was_measured_there(catalogue):
    """The table is as before (the nearest PSF, its dist); one note line on stderr when that PSF's location is
    more than half the grid step of the stored locations away along x or y, none inside the grid."""
    with Catalogue(catalogue) as cat:
        rig = cat.add_rig(CameraInfo("Sony A7", "9", "FE 50mm", 50.0))
        run = cat.start_run("sony.toml", "sony plan", rig, [("f8", {})])
        cat.commit_step(run, "f8", [], [(PSF(gaussian(2.0), 4, "bernoulli", "g1", ["s.dng"], f, (0, 0, 64, 64)),
                                         {"aperture": 8.0}) for f in GRID if f != (5 / 6, 5 / 6)])
    inside = _psfd("query", "--catalogue", catalogue, "--near", "0.95,0.05")
    assert inside.returncode == 0 and inside.stderr == "" and len(inside.stdout.splitlines()) == 1 + 5 + 1
    far = _psfd("query", "--catalogue", catalogue, "--camera", "sony", "--near", "0.9,0.9")
    assert far.returncode == 0 and far.stderr == (
        "psfd: note: no PSF measured near 0.9,0.9: the nearest stored location (0.500,0.833) is 0.406 away, more "
        "than half the grid step (0.333 across, 0.333 down)\n")
    (row,) = far.stdout.splitlines()[1:-1]
    assert row.split()[-1] == "0.406" and "field distance to --near, normalised" in far.stdout.splitlines()[-1]


def test_tiff_exports_carry_the_sample_pitch_as_resolution_in_centimetres(tmp_path):
    """A PSF is sampled at the channel pixel pitch / s (a Bayer plane's pixel is two photosites, a mono plane's
    one): its TIFF says so in XResolution, YResolution (samples per cm) and ResolutionUnit (centimetre); one of
    unknown pitch keeps no unit, as before."""
    from psfd.catalogue import FrameRecord

    path = tmp_path / "cat.sqlite"
    with Catalogue(path) as cat:
        rig = cat.add_rig(CameraInfo("Canon EOS 400D", "0420", "EF 50mm f/1.8", 50.0))
        for n, (plan, channel, s) in enumerate((("[rig]\npitch_um = 5.7\n", "g1", 4), ("[rig]\npitch_um = 4.3\n",
                                                                                       "mono", 3), ("plan", "r", 4))):
            run = cat.start_run(f"p{n}.toml", plan, rig, [("f8", {})])
            frame = FrameRecord(str(tmp_path / f"frame{n}.pgm"), f"{n:064x}", {"aperture": "8"}, {}, "t")
            cat.commit_step(run, "f8", [frame], [(PSF(gaussian(2.0, 4 * s + 1), s, "bernoulli", channel,
                                                      [frame.path], (0.5, 0.5), (0, 0, 64, 64)), {"aperture": 8.0})])
    out = tmp_path / "ex"
    done = _psfd("export", "--catalogue", str(path), "--format", "tif", "--out", str(out))
    assert done.returncode == 0, done.stderr
    expected = {"g1": 10 * 4 / (2 * 5.7e-3), "mono": 10 * 3 / 4.3e-3}  # samples per cm: 7017.5 and 6976.7
    seen = set()
    for entry in json.loads((out / "index.json").read_text())["psfs"]:
        with tifffile.TiffFile(out / entry["file"]) as tif:
            tags = tif.pages[0].tags
            unit = tags["ResolutionUnit"].value
            if entry["channel"] in expected:
                assert unit == tifffile.RESUNIT.CENTIMETER
                for name in ("XResolution", "YResolution"):
                    numerator, denominator = tags[name].value
                    assert numerator / denominator == pytest.approx(expected[entry["channel"]], rel=1e-9)
            else:  # no pitch known: no unit, no claim
                assert unit == tifffile.RESUNIT.NONE
            seen.add(entry["channel"])
    assert seen == {"g1", "mono", "r"}


def _as_user_without_write_access(command: list[str]) -> list[str]:
    """``command`` run so that file modes restrict it: as it is for a user, without root's override for root."""
    if os.geteuid() != 0:
        return command
    import shutil

    if shutil.which("setpriv") is None:
        pytest.skip("running as root without setpriv: chmod does not restrict root")
    return ["setpriv", "--bounding-set=-dac_override,-dac_read_search", "--inh-caps=-dac_override,-dac_read_search",
            *command]


def test_a_catalogue_copied_alone_to_read_only_media_is_read_as_immutable(catalogue, tmp_path):
    """No -wal or -shm beside it and no right to create them (a DVD, a read-only share, chmod 0555): the read-only
    open fails, so the file is read with SQLite's immutable=1, said in one log line. A non-empty -wal without its
    -shm holds commits the file lacks: that copy is still refused, not read incomplete."""
    import shutil

    normal = _psfd("query", "--catalogue", catalogue, "--csv")
    assert normal.returncode == 0, normal.stderr
    media, partial = tmp_path / "media", tmp_path / "partial"
    media.mkdir()
    shutil.copy(catalogue, media / "cat.sqlite")
    partial.mkdir()
    with Catalogue(catalogue) as writer:  # a commit still in the -wal alone, copied without its -shm
        writer.db.execute("PRAGMA wal_autocheckpoint = 0")
        writer.add_rig(CameraInfo("Sony A7", "9", "FE 50mm", 50.0))
        for suffix in ("", "-wal"):
            shutil.copy(catalogue + suffix, partial / f"cat.sqlite{suffix}")
    assert (partial / "cat.sqlite-wal").stat().st_size > 0
    for folder in (media, partial):
        for path in folder.iterdir():
            path.chmod(0o444)
        folder.chmod(0o555)
    try:
        command = [sys.executable, "-m", "psfd", "query", "--csv", "--catalogue"]
        done = subprocess.run(_as_user_without_write_access([*command, str(media / "cat.sqlite")]),
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and done.stdout == normal.stdout, done.stderr
        assert done.stderr == (f"psfd: warning: {media / 'cat.sqlite'}: read as immutable (SQLite immutable=1): its "
                               f"-wal and -shm files are missing and {media} is read-only\n")
        assert sorted(p.name for p in media.iterdir()) == ["cat.sqlite"]
        refused = subprocess.run(_as_user_without_write_access([*command, str(partial / "cat.sqlite")]),
                                 capture_output=True, text=True, timeout=120)
        assert_one_line_error(refused.returncode, refused.stderr, 5, "without write access")
        assert sorted(p.name for p in partial.iterdir()) == ["cat.sqlite", "cat.sqlite-wal"]
    finally:
        for folder in (media, partial):
            folder.chmod(0o755)


def test_report_and_metadata_out_make_the_file_but_no_missing_folder(catalogue, tmp_path):
    """As estimate and export --out: the file named is made in a folder that exists; a missing folder (a typo,
    media not mounted) is a one-line bad input naming it, and nothing is created."""
    (tmp_path / "notes.txt").write_text("mine")
    for command, name in (("report", "r.png"), ("metadata", "m.json")):
        missing = _psfd(command, "--catalogue", catalogue, "--out", str(tmp_path / "missing" / name))
        assert (missing.returncode, missing.stdout) == (2, "")
        assert missing.stderr == f"psfd: error: {tmp_path / 'missing'}: no such folder\n"
        under_a_file = _psfd(command, "--catalogue", catalogue, "--out", str(tmp_path / "notes.txt" / name))
        assert_one_line_error(under_a_file.returncode, under_a_file.stderr, 2, "notes.txt: not a folder")
        made = _psfd(command, "--catalogue", catalogue, "--out", str(tmp_path / name))
        assert made.returncode == 0 and (tmp_path / name).stat().st_size > 0, made.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([*CATALOGUE_FILES, "m.json", "notes.txt", "r.png"])


def test_report_and_metadata_on_a_read_only_disk_name_the_file_asked_for(small_disk, catalogue):
    """The one-line error names the --out file and the reason, not the hidden staging file: removing that
    missing file failed too on a read-only file system (EROFS) and replaced the error."""
    subprocess.run(["mount", "-o", "remount,ro", str(small_disk)], check=True)
    try:
        for command, name in (("report", "r.png"), ("metadata", "m.json")):
            refused = _psfd(command, "--catalogue", catalogue, "--out", str(small_disk / name))
            assert (refused.returncode, refused.stdout) == (2, "")
            assert refused.stderr == f"psfd: error: could not write {small_disk / name}: Read-only file system\n"
    finally:
        subprocess.run(["mount", "-o", "remount,rw", str(small_disk)], check=True)
    assert list(small_disk.iterdir()) == []


def test_export_out_makes_the_folder_but_no_missing_parent(catalogue, tmp_path):
    missing = _psfd("export", "--catalogue", catalogue, "--out", str(tmp_path / "missing" / "ex"))
    assert (missing.returncode, missing.stderr) == (2, f"psfd: error: {tmp_path / 'missing'}: no such folder\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == CATALOGUE_FILES
    made = _psfd("export", "--catalogue", catalogue, "--channel", "g1", "--aperture", "8", "--out", str(tmp_path / "ex"))
    assert made.returncode == 0 and len(list((tmp_path / "ex").iterdir())) == 9 + 2, made.stderr


def test_metadata_out_never_replaces_the_catalogue(catalogue, tmp_path):
    """`psfd metadata --catalogue C --out C` (a slip of the shell history) replaced every measurement with
    the JSON; it, the -wal beside it and a link to it are refused with a one-line bad input, untouched."""
    os.symlink(catalogue, tmp_path / "link.sqlite")
    before = {name: (tmp_path / name).read_bytes() for name in CATALOGUE_FILES}
    for out in (catalogue, catalogue + "-wal", str(tmp_path / "link.sqlite")):
        refused = _psfd("metadata", "--catalogue", catalogue, "--out", out)
        assert_one_line_error(refused.returncode, refused.stderr, 2, "the catalogue's own file")
        assert refused.stdout == ""
    assert {name: (tmp_path / name).read_bytes() for name in CATALOGUE_FILES} == before
    assert _psfd("query", "--catalogue", catalogue, "--limit", "1").returncode == 0


def test_serial_numbers_are_matched_in_any_case_as_names_are(capsys, catalogue):
    """The README: the filters ignore case; --camera and --lens take the exact serial of the body or the lens
    copy. A serial with letters (SIM-0, a Nikon's or a lens's) typed in another case matched nothing."""
    with Catalogue(catalogue) as cat:
        rig = cat.add_rig(CameraInfo("Nikon Z 6", "ZB-1234", "NIKKOR Z 50mm f/1.8 S", 50.0))
        run = cat.start_run("z6.toml", "z6 plan", rig, [("A", {})])
        shot = FrameRecord("/raw/z.nef", f"{7:064x}", {"aperture": "5.6"}, {}, "t",
                           exif={"lens": "NIKKOR Z 50mm f/1.8 S", "lens_serial": "LX-77"})
        cat.commit_step(run, "A", [shot], [(PSF(gaussian(1.0), 4, "bernoulli", "b", [shot.path], (0.5, 0.5),
                                                (0, 0, 64, 64)), {"aperture": 5.6})])
    for option, serial in (("--camera", "ZB-1234"), ("--camera", "zb-1234"), ("--lens", "LX-77"), ("--lens", "lx-77")):
        code, out, err = run_cli(capsys, "query", "--catalogue", catalogue, option, serial, "--csv")
        rows = out.splitlines()[1:]
        assert code == 0 and len(rows) == 1 and ",Nikon Z 6,ZB-1234," in rows[0], (option, serial, err)
    code, _, err = run_cli(capsys, "query", "--catalogue", catalogue, "--camera", "zb-123")
    assert code == 1 and "no PSF of camera 'zb-123'" in err  # a serial is matched whole, not in part
