"""`psfd estimate ...` and its writers: files, figures, JSON lines, bad input."""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import os
import stat
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import tifffile
from scipy.special import ndtr

from psfd import figures
from psfd.cli import main, output
from psfd.errors import BadInputError
from psfd.estimator import raw
from psfd.estimator.kernels import PSF

DATA = Path(__file__).parent / "data"


def gaussian(sigma_x: float, sigma_y: float, s: int = 4, support: int = 17) -> np.ndarray:
    """A unit-sum Gaussian kernel on the s-times grid (sigmas in channel pixels)."""
    r = (np.arange(support) - support // 2) / s
    k = np.exp(-0.5 * (r[None, :] / sigma_x) ** 2 - 0.5 * (r[:, None] / sigma_y) ** 2)
    return k / k.sum()


def synthetic(window: int = 0, **extra) -> PSF:
    return PSF(
        psf=gaussian(0.6, 0.9),
        s=4,
        method="bernoulli",
        channel="g1",
        sources=["/data/IMG_0001.dng"],
        field=(0.25 + 0.5 * window, 0.5),
        window=(320 * window, 0, 320 * (window + 1), 480),
        noise_floor=1.5e-3,
        residual=0.01,
        params={"solver": "ls-threshold", "grid": (2, 1)},
        **extra,
    )


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# ---------------------------------------------------------------- writers


def test_plain_converts_arrays_at_once_as_it_does_item_by_item():
    """Arrays of numbers take one tolist(); with NaN or inf each value is looked at, and those become null."""
    arrays = [np.arange(6, dtype=np.int16).reshape(2, 3), np.linspace(0, 1, 6, dtype=np.float32).reshape(3, 2),
              np.array([[0.5, np.nan], [-np.inf, 2.0]]), np.array([True, False])]
    for array in arrays:
        fast = output.plain(array)
        assert fast == output.plain(array.tolist())  # the item-by-item path, through the nested lists
        assert all(type(v) in (int, float, bool, type(None)) for v in np.ravel(np.array(fast, dtype=object)))
        json.dumps(fast, allow_nan=False)
    assert output.plain(arrays[2]) == [[0.5, None], [None, 2.0]]


def test_estimate_tiffs_carry_the_sample_pitch_the_raw_gives(tmp_path):
    """As `export --format tif`: the kernel is sampled at the channel pixel pitch / s, 2 x 4.3 um / 4 = 2.15 um
    on a Bayer plane (4651.2 samples per cm); a source without a pitch gives no resolution, as before."""
    mosaic = np.full((64, 96), 1000, dtype=np.uint16)
    raw.write_dng(tmp_path / "IMG_0001.dng", mosaic, black=512, white=4095, exif={"pixel_pitch_um": 4.3})
    pitched = dataclasses.replace(synthetic(0), sources=[str(tmp_path / "IMG_0001.dng")])
    bare = dataclasses.replace(synthetic(0), sources=[str(tmp_path / "IMG_0002.pgm")])
    output.write_estimates([pitched, bare], tmp_path / "out", drawn=False)
    with tifffile.TiffFile(tmp_path / "out" / "IMG_0001_bernoulli_g1_w00.tif") as tif:
        tags = tif.pages[0].tags
        x, y = tags["XResolution"].value, tags["YResolution"].value
        assert x[0] / x[1] == pytest.approx(1e4 / 2.15, rel=1e-5) and y == x
        assert tags["ResolutionUnit"].value == tifffile.RESUNIT.CENTIMETER
    with tifffile.TiffFile(tmp_path / "out" / "IMG_0002_bernoulli_g1_w00.tif") as tif:
        assert tif.pages[0].tags["ResolutionUnit"].value == tifffile.RESUNIT.NONE


def test_estimates_carry_the_settings_the_raw_records(tmp_path):
    """The f-number, focal length and focus distance of a RAW file's EXIF go with its PSFs into NAME.json,
    metrics.csv and --json, as `psfd query` gives them for catalogued ones; an image without EXIF has none."""
    mosaic = np.full((64, 96), 1000, dtype=np.uint16)
    raw.write_dng(tmp_path / "IMG_0001.dng", mosaic, black=512, white=4095,
                  exif={"f_number": 8.0, "focal_length_mm": 50.0, "focus_distance_m": 1.3})
    shot = dataclasses.replace(synthetic(0), sources=[str(tmp_path / "IMG_0001.dng")])
    bare = dataclasses.replace(synthetic(0), sources=[str(tmp_path / "IMG_0002.pgm")])
    output.write_estimates([shot, bare], tmp_path / "out", drawn=False)
    record = json.loads((tmp_path / "out" / "IMG_0001_bernoulli_g1_w00.json").read_text())
    assert (record["aperture"], record["focal_length_mm"], record["focus_distance_m"]) == (8.0, 50.0, 1.3)
    record = json.loads((tmp_path / "out" / "IMG_0002_bernoulli_g1_w00.json").read_text())
    assert (record["aperture"], record["focal_length_mm"], record["focus_distance_m"]) == (None, None, None)
    with open(tmp_path / "out" / "metrics.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert [(r["aperture [f-number]"], r["focal_length [mm]"], r["focus_distance [m]"]) for r in rows] == [
        ("8", "50", "1.3"), ("", "", "")]
    lines = io.StringIO()
    output.print_json([shot], lines)
    assert json.loads(lines.getvalue())["aperture"] == 8.0


def test_write_estimates_files_round_trip(tmp_path):
    kernel = np.arange(25.0).reshape(5, 5) - 12  # signed, as an inter-image kernel can be
    residual = np.random.default_rng(0).normal(size=(40, 60))
    estimates = [synthetic(0, figures={"kernel": kernel, "residual": residual}), synthetic(1)]
    files = output.write_estimates(estimates, tmp_path / "out")
    names = sorted(p.name for p in (tmp_path / "out").iterdir())
    assert names == sorted(p.name for p in files)
    assert names == sorted(
        [f"IMG_0001_bernoulli_g1_w0{i}.{ext}" for i in (0, 1) for ext in ("npy", "tif", "png", "json")]
        + [f"IMG_0001_bernoulli_g1_w00.{k}.{ext}" for k in ("kernel", "residual") for ext in ("npy", "png")]
        + ["metrics.csv", "grid.png"]  # two windows of one channel: a grid, drawn where they were measured
    )
    base = tmp_path / "out" / "IMG_0001_bernoulli_g1_w00"
    np.testing.assert_array_equal(np.load(f"{base}.npy"), estimates[0].psf)
    tif = tifffile.imread(f"{base}.tif")
    assert tif.dtype == np.float32
    np.testing.assert_array_equal(tif, estimates[0].psf.astype(np.float32))
    assert json.loads(Path(f"{base}.json").read_text())["window"] == [0, 0, 320, 480]
    np.testing.assert_array_equal(np.load(f"{base}.kernel.npy"), kernel)
    np.testing.assert_array_equal(np.load(f"{base}.residual.npy"), residual)
    for name in (f"{base}.png", f"{base}.kernel.png", f"{base}.residual.png", f"{tmp_path}/out/grid.png"):
        image = cv2.imread(name, cv2.IMREAD_COLOR)  # figures, not bare arrays
        assert image is not None and min(image.shape[:2]) > 400 and image.std() > 10
    # one CSV row per estimate, units in the header, the metrics the JSON has
    import csv

    with open(tmp_path / "out" / "metrics.csv", newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert [r["file"] for r in rows] == ["IMG_0001_bernoulli_g1_w00.npy", "IMG_0001_bernoulli_g1_w01.npy"]
    metrics = estimates[1].metrics()
    assert float(rows[1]["mtf50_x [cycles/px]"]) == pytest.approx(metrics["mtf50_x"], rel=1e-5)
    assert float(rows[1]["fwhm_y [channel px]"]) == pytest.approx(metrics["fwhm_y"], rel=1e-5)
    predicted = estimates[1].prediction_error  # None here: empty, as every unknown
    assert rows[1]["prediction_error [cross-validated residual / noise level]"] == (
        "" if predicted is None else format(predicted, ".6g"))
    assert rows[1]["window x0 y0 x1 y1 [channel px]"] == "320 0 640 480"
    assert rows[0]["mtf50_x [lp/mm]"] == ""  # no pitch known for this source: empty, never a guess
    # no temporary folder left beside the output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    output.write_estimates(estimates, tmp_path / "bare", drawn=False)  # --no-figures: grid.png neither
    assert not list((tmp_path / "bare").glob("*.png")) and (tmp_path / "bare" / "metrics.csv").exists()


def test_figures_drawn_by_forked_workers_are_each_estimates_own(tmp_path):
    """Six estimates: two forked workers draw three figures each, every one the figure of its own estimate
    (checked on the last of each worker's, drawn over the others)."""
    estimates = [dataclasses.replace(synthetic(0), psf=gaussian(0.4 + 0.1 * n, 0.9)) for n in range(6)]
    output.write_estimates(estimates, tmp_path / "out")
    assert len(list((tmp_path / "out").glob("*.png"))) == 6
    for n in (2, 5):
        figures.save_psf(estimates[n], tmp_path / "whole.png")
        drawn = cv2.imread(str(tmp_path / "out" / f"IMG_0001_bernoulli_g1_w{n:02d}.png"))
        assert np.array_equal(drawn, cv2.imread(str(tmp_path / "whole.png"))), n


@pytest.mark.parametrize("count", [2, 6])  # six: the figures are drawn by forked workers, which fail there
def test_write_estimates_is_atomic(tmp_path, monkeypatch, count):
    calls = {"n": 0}
    real = figures.PSFFigures.save

    def failing(self, est, path, pitch_um=None):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(28, "No space left on device")
        return real(self, est, path, pitch_um)

    monkeypatch.setattr(figures.PSFFigures, "save", failing)
    with pytest.raises(BadInputError, match="cannot write results"):
        output.write_estimates([synthetic(n % 2) for n in range(count)], tmp_path / "new")
    assert list(tmp_path.iterdir()) == []  # neither the folder nor a temporary one
    existing = tmp_path / "old"
    existing.mkdir()
    (existing / "keep.txt").write_text("x")
    calls["n"] = 0
    with pytest.raises(BadInputError):
        output.write_estimates([synthetic(n % 2) for n in range(count)], existing)
    assert [p.name for p in existing.iterdir()] == ["keep.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["old"]


def test_write_estimates_refuses_unwritable(tmp_path):
    (tmp_path / "file").write_text("x")
    for bad in (tmp_path / "missing" / "out", tmp_path / "file", tmp_path / "file" / "out"):
        with pytest.raises(BadInputError):
            output.write_estimates([synthetic(0)], bad)
    assert [p.name for p in tmp_path.iterdir()] == ["file"]


def test_print_json_lines():
    flat = PSF(psf=np.full((5, 5), 1 / 25), s=1, method="two-photo", channel="mono", sources=["a.pgm", "b.pgm"])
    stream = io.StringIO()
    output.print_json([synthetic(0), synthetic(1), flat], stream)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 3
    records = [json.loads(line) for line in lines]  # strict JSON: NaN would not parse in other readers
    for record in records:
        for key in ("method", "source", "channel", "s", "support", "field_x", "field_y", "psf", "mtf50_x", "mtf50_y"):
            assert key in record
    first = records[0]
    assert first["method"] == "bernoulli" and first["source"] == "/data/IMG_0001.dng" and first["channel"] == "g1"
    assert first["s"] == 4 and first["support"] == 17 and first["field_x"] == 0.25 and first["field_y"] == 0.5
    np.testing.assert_allclose(first["psf"], synthetic(0).psf, rtol=1e-15)
    # A Gaussian of sigma 0.6 px has MTF exp(-2 pi^2 sigma^2 f^2) = 0.5 at f = sqrt(ln 2 / 2) / (pi sigma) = 0.312;
    # sampled on 17 taps at s = 4 the truncation changes it by far less than 1 %.
    assert first["mtf50_x"] == pytest.approx(math.sqrt(math.log(2) / 2) / (math.pi * 0.6), rel=0.01)
    assert first["params"]["grid"] == [2, 1]
    assert records[2]["source"] == [os.path.abspath("a.pgm"), os.path.abspath("b.pgm")]  # results outlive the cwd


def test_print_json_nan_is_null():
    delta = np.zeros((3, 3))
    delta[1, 1] = 1.0  # a perfect kernel: MTF is 1 everywhere, MTF50 undefined
    stream = io.StringIO()
    output.print_json([PSF(psf=delta, s=1, method="bernoulli", channel="r", sources=["x.dng"])], stream)
    record = json.loads(stream.getvalue())
    assert record["mtf50_x"] is None and record["mtf50_y"] is None


def test_print_table_and_warnings_on_stderr(capsys):
    from psfd.cli import logs

    est = synthetic(0, warnings=["pixels per cell 0.9 outside 0.35..0.5"])
    output.print_table([est])
    logs.setup()
    output.log_warnings([est])
    captured = capsys.readouterr()
    assert "IMG_0001 " in captured.out and " g1 " in captured.out and "0.25,0.50" in captured.out
    assert "warning" not in captured.out  # the table stays a table
    assert captured.err == "psfd: warning: IMG_0001.dng g1 at (0.25, 0.50): pixels per cell 0.9 outside 0.35..0.5\n"


# ---------------------------------------------------------------- bad input on the command line


@pytest.fixture
def bad_files(tmp_path: Path) -> Path:
    folder = tmp_path / "in"
    folder.mkdir()
    (folder / "notes.pgm").write_text("this is not an image\n")
    (folder / "colour.png").write_bytes(cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))[1].tobytes())
    mosaic = np.random.default_rng(1).integers(600, 4000, size=(96, 128)).astype(np.uint16)
    raw.write_dng(folder / "whole.dng", mosaic, black=512, white=16383)
    data = (folder / "whole.dng").read_bytes()
    (folder / "cut.dng").write_bytes(data[: len(data) // 2])
    pgm = cv2.imencode(".pgm", np.zeros((64, 64), np.uint8))[1].tobytes()
    (folder / "trunc.pgm").write_bytes(pgm[: len(pgm) // 2])  # OpenCV would log its own error line
    photo = cv2.imread(str(DATA / "img_example.pgm"), cv2.IMREAD_UNCHANGED)
    png = cv2.imencode(".png", photo)[1].tobytes()
    (folder / "trunc.png").write_bytes(png[: len(png) // 2])  # libpng would print its own "Read Error" line
    (folder / "empty.tif").write_bytes(b"II*\0" + bytes(100))  # tifffile would log "contains no pages"
    # a grey photograph saved as TIFF but named .dng: LibRaw reads it as a Bayer mosaic of a camera it guesses
    tifffile.imwrite(folder / "grey.dng", photo.astype(np.uint16) * 257)
    # a linear DNG, demosaiced (three samples per pixel, PhotometricInterpretation LinearRaw): no photosites
    rgb = np.stack([mosaic] * 3, axis=-1)
    tifffile.imwrite(folder / "linear.dng", rgb, photometric=34892, subfiletype=0,
                     extratags=[(50706, "B", 4, (1, 4, 0, 0), True), (50708, "s", 0, "linear", True)])
    return folder


BAD = [
    (["target", "{in}/notes.pgm"], "not a readable image"),
    (["target", "{in}/colour.png"], "colour channels"),
    (["target", "{in}/cut.dng"], "not a readable RAW file"),
    (["target", "{in}/trunc.png"], "trunc.png: not a readable image"),
    (["target", "{in}/empty.tif"], "empty.tif: not a readable image"),
    (["target", "{in}/grey.dng"], "grey.dng: a TIFF image without a camera's make or DNG tags"),
    (["target", "{in}/linear.dng"], "linear.dng: a linear (demosaiced) RAW file"),
    (["target", "{in}/missing.dng"], "no such file"),
    (["target", "{in}/whole.dng", "--grid", "3"], "--grid"),
    (["target", "{in}/whole.dng", "--grid", "0x2"], "--grid"),
    (["target", "{in}/whole.dng", "--support", "16"], "odd"),
    (["target", "{in}/whole.dng", "--support", "1"], "--support"),
    (["target", "{in}/whole.dng", "-s", "0"], "-s"),
    (["target", "{in}/whole.dng", "-s", "four"], "-s"),
    (["target", "{in}/whole.dng", "--channel", "green"], "unknown channel"),
    (["target", "{in}/whole.dng", "--solver", "cg"], "--solver"),
    (["target", "{in}/whole.dng", "--pattern", "{in}/notes.pgm"], "noise pattern"),
    (["target", "{in}/whole.dng", "--pattern", "{in}/missing.pgm"], "missing.pgm: no such file"),
    (["target", "{in}/whole.dng", "--out", "{in}"], "exists and is not an empty folder"),
    (["target", "{in}/whole.dng", "--out", "{in}/whole.dng/out"], "whole.dng: not a folder"),
    (["target", "{in}/whole.dng", "--out", "{in}/missing/out"], "missing: no such folder"),
    (["pair", "{in}/whole.dng", "{in}/cut.dng"], "not a readable RAW file"),
    (["pair", "{in}/whole.dng", "{in}/missing.pgm"], "no such file"),
    (["edges", "{in}/notes.pgm", "--weight", "x"], "--weight"),
    (["edges", "{in}/whole.dng", "--grid", "2x"], "--grid"),
    # bounds named as the command line spells the option (not the plan's [nx, ny], not a bare "weight")
    (["target", "{in}/whole.dng", "--grid", "33x1"], "--grid: N and M from 1 to 32, got 33x1"),
    (["edges", "{in}/whole.dng", "--weight", "-1"], "--weight: expected a number >= 0"),
    (["edges", "{in}/whole.dng", "--radius", "0"], "--radius: expected a positive number"),
]


@pytest.mark.parametrize("argv, message", BAD)
def test_bad_input_one_line_nothing_written(bad_files, capfd, argv, message):
    # capfd, not capsys: LibRaw writes to file descriptor 2 itself, and that must not show
    before = sorted(p.name for p in bad_files.parent.rglob("*"))
    out = bad_files.parent / "results"
    argv = [a.format(**{"in": bad_files}) for a in argv]
    if "--out" not in argv:
        argv += ["--out", str(out)]
    code, stdout, stderr = run(capfd, "estimate", *argv)
    assert code == 2
    assert stderr.startswith("psfd: error: ") and stderr.count("\n") == 1 and message in stderr
    assert stdout == ""
    assert sorted(p.name for p in bad_files.parent.rglob("*")) == before  # no results folder, no temporary


@pytest.mark.parametrize("name", ["trunc.pgm", "trunc.png", "empty.tif"])
def test_no_decoder_log_lines(bad_files, name):
    # In a fresh process, as a user runs it: OpenCV reads its log level when first imported, libpng writes
    # to file descriptor 2, tifffile logs through `logging`, which psfd sends to stderr.
    proc = subprocess.run([sys.executable, "-m", "psfd", "estimate", "target", str(bad_files / name)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr == f"psfd: error: {bad_files / name}: not a readable image\n"


def test_unwritable_out_is_one_line_error():
    # /proc refuses new folders even to root, where a chmod-000 folder would not
    with pytest.raises(BadInputError) as info:
        output.write_estimates([synthetic(0)], "/proc/psfd-nope")
    assert "\n" not in str(info.value) and "/proc" in str(info.value)


def test_pair_help_cites_both_papers(capsys):
    with pytest.raises(SystemExit):
        main(["estimate", "pair", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "SIAM J. Imaging Sciences 2012" in text and "IPOL 2013" in text


def test_pair_channels_must_match(bad_files, capsys, data_dir):
    code, _, stderr = run(capsys, "estimate", "pair", bad_files / "whole.dng", data_dir / "img_example.pgm")
    assert code == 2 and "same channels" in stderr and stderr.count("\n") == 1


@pytest.mark.parametrize("suffix, channel", [(".pgm", c) for c in raw.CHANNELS] + [(".png", "g1"), (".tif", "b")])
def test_a_single_channel_image_has_no_bayer_channel(tmp_path, data_dir, suffix, channel):
    """A one-plane image is its own plane, mono: asked for a Bayer channel it is refused in one line naming
    the file and what it has, not relabelled (a Bayer label would halve its lp/mm, `mtf.channel_pitch_mm`)."""
    image = tmp_path / f"target{suffix}"
    cv2.imwrite(str(image), cv2.imread(str(data_dir / "img_example.pgm"), cv2.IMREAD_UNCHANGED))
    out = tmp_path / "never"
    done = subprocess.run([sys.executable, "-m", "psfd", "estimate", "bernoulli", str(image), "--channel", channel,
                           "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 2
    assert done.stderr.startswith(f"psfd: error: {image}: ") and done.stderr.count("\n") == 1
    assert f"no {channel} channel" in done.stderr and "mono" in done.stderr
    assert done.stdout == "" and not out.exists()


# ---------------------------------------------------------------- end to end


def test_pair_end_to_end_on_real_photos(tmp_path, capsys, data_dir):
    near, far = data_dir / "IMG_0602_v1_CUT.pgm", data_dir / "IMG_0608_v1.pgm"
    code, stdout, stderr = run(capsys, "estimate", "pair", far, near, "--json", "--out", tmp_path / "out")
    assert code == 0, stderr
    (record,) = [json.loads(line) for line in stdout.splitlines()]
    assert record["method"] == "two-photo" and record["channel"] == "mono"
    assert sorted(record["source"]) == sorted([str(near), str(far)])
    assert record["s"] == 3 and record["support"] == 13  # defaults: s = 3, support 4s + 1
    psf = np.array(record["psf"])
    assert psf.shape == (13, 13) and psf.sum() == pytest.approx(1.0, abs=1e-9)
    files = sorted(p.name for p in (tmp_path / "out").iterdir())
    base = "IMG_0608_v1+IMG_0602_v1_CUT_two-photo_mono_w00"
    assert files == sorted([f"{base}{tail}" for tail in (
        ".npy", ".tif", ".png", ".json", ".kernel.npy", ".kernel.png", ".residual.npy", ".residual.png")]
        + ["metrics.csv"])
    np.testing.assert_array_equal(np.load(tmp_path / "out" / f"{base}.npy"), psf)
    # Which photo is near is detected: the other order gives the same estimate up to the
    # registration, which is fitted the other way round; the change stays below the noise floor
    # (expected RMS error of the kernel values, IJCV 2012 sec. 2) of the estimate itself.
    code, stdout, _ = run(capsys, "estimate", "pair", near, far, "--json")
    assert code == 0
    swapped = json.loads(stdout)
    assert sorted(swapped["source"]) == sorted(record["source"])
    assert np.abs(np.array(swapped["psf"]) - psf).max() < record["noise_floor"]


# Relative L2 errors ||h_e - h|| / ||h|| accepted end to end. The expected error from sensor noise is
# PSF.noise_floor / ||h|| (IJCV 2012 sec. 2). On the simulated DNG it is 3.5 % and 2-9 % is measured
# (the rest is discretisation bias of u~_D): 0.15 still rejects the same Gaussian 20 % wider (23 % away).
# The small round-trip photo has a floor of 7-11 % and 6-19 % is measured, so its bound is a multiple
# of the floor the estimator reports for that very photo.
DNG_TOLERANCE = 0.15
ROUND_TRIP_FLOORS = 2.5


def relative_error(estimate: np.ndarray, truth: np.ndarray) -> float:
    """||h_e - h|| / ||h||, the error measure of IJCV 2012 sec. 5."""
    return float(np.linalg.norm(estimate - truth) / np.linalg.norm(truth))


def test_target_end_to_end_on_real_photo(capsys, data_dir):
    code, stdout, stderr = run(capsys, "estimate", "target", data_dir / "img_example.pgm", "--json")
    assert code == 0, stderr
    (record,) = [json.loads(line) for line in stdout.splitlines()]
    assert record["method"] == "bernoulli" and record["channel"] == "mono"
    assert record["source"] == str(data_dir / "img_example.pgm")
    assert record["s"] == 4 and record["support"] == 17 and record["params"]["solver"] == "nnls"
    psf = np.array(record["psf"])
    # physical sanity: non-negative (nnls), unit sum, centred within a channel pixel
    assert psf.min() >= 0 and psf.sum() == pytest.approx(1.0, abs=1e-9)
    cx, cy = (float(np.sum(np.arange(17) * psf.sum(axis=a))) - 8 for a in (0, 1))
    assert abs(cx) < 4 and abs(cy) < 4
    assert 0 < record["mtf50_x"] < 2 and 0 < record["mtf50_y"] < 2
    # reported with the noise floor: the cross-validated prediction error (1.22 on this photo)
    assert record["noise_floor"] > 0 and 1.0 < record["prediction_error"] < 1.5
    # the table shows it too
    code, stdout, stderr = run(capsys, "estimate", "target", data_dir / "img_example.pgm")
    assert code == 0, stderr
    header, row = stdout.splitlines()[:2]
    assert header.split()[-2:] == ["noise", "pred."]
    assert row.split()[-1] == f"{record['prediction_error']:.2f}"
    assert row.split()[-2] == f"{record['noise_floor'] / np.linalg.norm(record['psf']):.1%}"  # relative to the kernel



def test_results_name_their_photograph_by_a_path_that_outlives_the_working_folder(tmp_path, monkeypatch, capsys,
                                                                                    data_dir):
    """A photograph given by a relative path: the JSON, NAME.json and metrics.csv name it by its absolute path
    (a relative one is relative to a folder the results do not record)."""
    monkeypatch.chdir(data_dir.parent)
    relative = Path(data_dir.name) / "img_example.pgm"
    code, stdout, stderr = run(capsys, "estimate", "target", relative, "--json", "--out", tmp_path / "out",
                               "--no-figures")
    assert code == 0, stderr
    where = str(data_dir / "img_example.pgm")
    assert json.loads(stdout)["source"] == where
    (written,) = (tmp_path / "out").glob("*.json")
    assert json.loads(written.read_text())["source"] == where
    with open(tmp_path / "out" / "metrics.csv", encoding="utf-8") as stream:
        assert [row["source"] for row in csv.DictReader(stream)] == [where]

def test_thesis_spline_geometry_is_selectable_and_agrees_on_the_real_photo(capsys, data_dir):
    records = {}
    for extra in ([], ["--tps", "10"]):
        code, stdout, stderr = run(capsys, "estimate", "target", data_dir / "img_example.pgm", "--json", *extra)
        assert code == 0, stderr
        record = json.loads(stdout)
        records[record["params"]["geometry"]] = record
    assert set(records) == {"homography+radial", "homography+tps(10)"}
    # the two geometries differ by a few hundredths of a pixel on this near-frontal view: MTF50 agrees
    # within 0.03 cycles/pixel, the spread the paper reports between repeated shots (IJCV 2012, sec. 5.6)
    default, thesis = records["homography+radial"], records["homography+tps(10)"]
    for key in ("mtf50_x", "mtf50_y"):
        assert default[key] == pytest.approx(thesis[key], abs=0.03)
    code, _, stderr = run(capsys, "estimate", "target", data_dir / "img_example.pgm", "--tps", "-1")
    assert code == 2 and stderr.startswith("psfd: error: --tps")


def test_target_end_to_end_on_simulated_dng(tmp_path, capsys):
    from psfd.estimator import simulate

    truth = simulate.gaussian_psf(0.55, 0.75, s=4, support=17)
    dng = tmp_path / "sim.dng"
    simulate.simulate_target(dng, psf=truth, s=4, pixels_per_cell=0.35, rotation_deg=8.0, seed=3)
    out = tmp_path / "out"
    code, stdout, stderr = run(capsys, "estimate", "target", dng, "--out", out)
    assert code == 0, stderr
    assert "MTF50" in stdout and all(f" {c} " in stdout for c in raw.CHANNELS)
    files = sorted(p.name for p in out.iterdir())
    extensions = ("npy", "tif", "png", "json")
    assert files == sorted([f"sim_bernoulli_{c}_w00.{ext}" for c in raw.CHANNELS for ext in extensions]
                           + ["metrics.csv"])
    for channel in raw.CHANNELS:
        estimate = np.load(out / f"sim_bernoulli_{channel}_w00.npy")
        assert relative_error(estimate, truth) < DNG_TOLERANCE, channel


def test_no_figures_writes_the_psf_files_and_metrics_only(tmp_path, capsys, data_dir):
    out = tmp_path / "out"
    code, stdout, stderr = run(capsys, "estimate", "bernoulli", data_dir / "img_example.pgm", "--out", out,
                               "--no-figures")
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"img_example_bernoulli_mono_w00.{ext}" for ext in ("npy", "tif", "json")] + ["metrics.csv"])
    assert "wrote 4 files" in stdout
    # without --out there is nothing to leave figures out of: one line, before any work
    code, stdout, stderr = run(capsys, "estimate", "bernoulli", data_dir / "img_example.pgm", "--no-figures")
    assert code == 2 and stdout == "" and stderr == "psfd: error: --no-figures leaves figures out of --out: " \
        "give --out DIR too\n"


def box_gaussian(sigma: float, s: int = 4, support: int = 17) -> np.ndarray:
    """Gaussian (sigma channel pixels) integrated over a square pixel, sampled on the s-times grid."""
    x = (np.arange(support) - support // 2) / s
    g = ndtr((x + 0.5) / sigma) - ndtr((x - 0.5) / sigma)
    h = np.outer(g, g)
    return h / h.sum()


def photograph_png(png: np.ndarray, sigma: float, rng: np.random.Generator, pixels_per_cell: float = 0.4,
                   factor: int = 10, shape: tuple[int, int] = (200, 220)) -> np.ndarray:
    """A 16-bit "photograph" of a rendered target: perspective warp, Gaussian blur, pixel integration, noise.

    The target is warped (cv2.warpPerspective) onto a grid ``factor`` times
    finer than the camera's, blurred there by a Gaussian of ``sigma`` camera
    pixels and area-averaged by ``factor``: the camera PSF is exactly that
    Gaussian convolved with the square pixel (`box_gaussian`).
    """
    side = png.shape[0]
    px_per_cell = side / (320 + 2 * 32)  # the PNG has a one-block margin
    k = pixels_per_cell * factor / px_per_cell
    a = np.deg2rad(12.0)
    rows, cols = shape
    centre = np.array([[1, 0, -side / 2], [0, 1, -side / 2], [0, 0, 1]])
    perspective = np.array([[1, 0, 0], [0, 1, 0], [1.5e-5, -1e-5, 1]])
    similarity = np.array([[k * np.cos(a), -k * np.sin(a), 0], [k * np.sin(a), k * np.cos(a), 0], [0, 0, 1]])
    place = np.array([[1, 0, cols * factor / 2], [0, 1, rows * factor / 2], [0, 0, 1]])
    fine = cv2.warpPerspective(png.astype(np.float32) / 255, place @ similarity @ perspective @ centre,
                               (cols * factor, rows * factor), flags=cv2.INTER_LINEAR, borderValue=0.8)
    fine = cv2.GaussianBlur(fine, (0, 0), sigma * factor)
    ideal = cv2.resize(fine, (cols, rows), interpolation=cv2.INTER_AREA)  # exact box average by `factor`
    values = 2000 + 40000 * ideal.astype(np.float64)
    values += rng.normal(size=values.shape) * np.sqrt(values / 2.5 + 4)  # shot and read noise
    return np.clip(np.round(values), 0, 65535).astype(np.uint16)


def test_rendered_target_round_trip(tmp_path, capsys):
    assert run(capsys, "target", "--out", tmp_path / "lab.png", "--seed", "21", "--px-per-cell", "4")[0] == 0
    png = cv2.imread(str(tmp_path / "lab.png"), cv2.IMREAD_GRAYSCALE)
    sigma = 0.5
    photo = photograph_png(png, sigma, np.random.default_rng(5))
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    code, stdout, stderr = run(
        capsys, "estimate", "target", tmp_path / "photo.png", "--pattern", tmp_path / "lab.seed21.noise.pgm", "--json"
    )
    assert code == 0, stderr
    record = json.loads(stdout)
    truth = box_gaussian(sigma)
    floor = record["noise_floor"] / np.linalg.norm(truth)
    assert floor < 0.15  # the photo is informative enough for the comparison to mean something
    assert relative_error(np.array(record["psf"]), truth) < ROUND_TRIP_FLOORS * floor
    # without --pattern the published noise is assumed: the model does not fit, which is refused,
    # so the saved noise is what made the estimate work
    code, stdout, stderr = run(capsys, "estimate", "target", tmp_path / "photo.png", "--json")
    assert code == 3 and stdout == "" and "does not follow the target's pattern" in stderr
    # psfd compare reads the printed noise the same way: its Bernoulli line is that estimate, not skipped
    code, stdout, stderr = run(capsys, "compare", tmp_path / "photo.png", "--pattern",
                               tmp_path / "lab.seed21.noise.pgm")
    assert code == 0, stderr
    line = next(text for text in stdout.splitlines() if text.startswith("bernoulli photo.png"))
    assert f"MTF50 x {record['mtf50_x']:.4f} y {record['mtf50_y']:.4f}" in line


def test_channel_names_ignore_case_as_everywhere(tmp_path, capsys):
    # `--channel G1` as `psfd query` and `psfd compare` take it: the channel as a datasheet prints it
    mosaic = np.random.default_rng(3).integers(600, 4000, size=(96, 128)).astype(np.uint16)
    raw.write_dng(tmp_path / "frame.dng", mosaic, black=512, white=16383)
    code, stdout, stderr = run(capsys, "estimate", "bernoulli", tmp_path / "frame.dng", "--channel", "G1")
    assert code == 3 and "(g1): no calibration target found" in stderr  # read as g1: no target in the noise
    code, stdout, stderr = run(capsys, "estimate", "bernoulli", DATA / "img_example.pgm", "--channel", "MONO",
                               "--json")
    assert code == 0 and json.loads(stdout)["channel"] == "mono"


@pytest.mark.parametrize("flip", [1, 0], ids=["left-right", "upside-down"])
def test_a_mirrored_target_is_said_to_be_mirrored(tmp_path, capsys, flip):
    # the real photograph as a mirror (or the back of a backlit transparency) shows it: no turn of the
    # published layout matches it, and "no calibration target found" would send the user looking for a
    # target that is in the frame
    photo = cv2.imread(str(DATA / "img_example.pgm"), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(tmp_path / "mirror.pgm"), cv2.flip(photo, flip))
    code, stdout, stderr = run(capsys, "estimate", "bernoulli", tmp_path / "mirror.pgm")
    assert code == 3 and stdout == ""
    assert stderr.count("\n") == 1
    assert stderr.startswith(f"psfd: error: {tmp_path / 'mirror.pgm'} (mono): the target is seen mirrored")


def test_sharp_edge_errors_name_the_frame(capsys):
    # of several frames, the one line says which one holds no target (the wall of the real pair)
    code, stdout, stderr = run(capsys, "estimate", "sharp-edge", DATA / "img_example.pgm",
                               DATA / "IMG_0602_v1_CUT.pgm", "--target")
    assert code == 3 and stdout == ""
    assert stderr == f"psfd: error: {DATA / 'IMG_0602_v1_CUT.pgm'} (mono): no edge target and no Bernoulli target " \
                     "found in the frame\n"


def test_edges_end_to_end_passes_its_options(tmp_path, capsys):
    from psfd.estimator import sharpedge

    # the edge target, slightly rotated, blurred and integrated over 10x10 fine pixels per channel pixel
    fine = cv2.warpAffine(sharpedge.edge_target(px_per_square=120.0).astype(np.float32),
                          np.float32([[np.cos(0.1), -np.sin(0.1), 60], [np.sin(0.1), np.cos(0.1), 40]]),
                          (1400, 1400), borderValue=1.0)
    image = cv2.resize(cv2.GaussianBlur(fine, (0, 0), 5.0), (140, 140), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(tmp_path / "edges.png"), np.round(2000 + 40000 * image.astype(np.float64)).astype(np.uint16))
    records = []
    for mode in (["--target"], []):
        code, stdout, stderr = run(capsys, "estimate", "edges", tmp_path / "edges.png", *mode, "--weight", "3",
                                   "--radius", "2.5", "-s", "3", "--support", "11", "--json")
        assert code == 0, stderr
        records.append(json.loads(stdout))
    for record in records:
        assert record["method"] == "sharp-edge" and record["s"] == 3 and record["support"] == 11
        assert record["params"]["weight"] == 3 and record["params"]["radius"] == 2.5
        assert np.sum(record["psf"]) == pytest.approx(1.0, abs=1e-9)
    # --target reaches the estimator: the sharp image predicted from the target's geometry differs
    assert not np.allclose(records[0]["psf"], records[1]["psf"])


def test_no_target_is_an_estimation_error(tmp_path, capfd):
    rng = np.random.default_rng(2)
    cv2.imwrite(str(tmp_path / "wall.png"), cv2.GaussianBlur(rng.integers(0, 255, (240, 320), np.uint8), (0, 0), 3))
    code, stdout, stderr = run(capfd, "estimate", "target", tmp_path / "wall.png", "--out", tmp_path / "out")
    assert code == 3  # EstimationError: the photograph does not support an estimate
    assert stderr.startswith("psfd: error: ") and stderr.count("\n") == 1 and stdout == ""
    assert [p.name for p in tmp_path.iterdir()] == ["wall.png"]


def test_output_folders_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        output.write_estimates([synthetic(0)], tmp_path / "shared")
        os.umask(0o077)
        output.write_estimates([synthetic(0)], tmp_path / "private")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "shared").stat().st_mode) == 0o755  # not mkdtemp's 0700
    assert stat.S_IMODE((tmp_path / "private").stat().st_mode) == 0o700
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o644 for p in (tmp_path / "shared").iterdir())


def test_force_replaces_an_output_folder_whole_and_nothing_else(tmp_path, capsys):
    out = tmp_path / "out"
    output.write_estimates([synthetic(0, figures={"kernel": np.eye(3)}), synthetic(1)], out)  # NAME.kernel.* too
    with pytest.raises(BadInputError, match="add --force"):
        output.write_estimates([synthetic(0)], out)
    output.write_estimates([synthetic(0)], out, force=True)
    assert sorted(p.name for p in out.iterdir()) == sorted(  # the earlier w01 files are gone, not mixed in
        [f"IMG_0001_bernoulli_g1_w00.{ext}" for ext in ("npy", "tif", "png", "json")] + ["metrics.csv"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging or old folder left
    home = tmp_path / "home"
    (home / "Documents").mkdir(parents=True)
    with pytest.raises(BadInputError, match="holds the folder Documents"):
        output.write_estimates([synthetic(0)], home, force=True)
    assert [p.name for p in home.iterdir()] == ["Documents"]
    (tmp_path / "file").write_text("mine")
    with pytest.raises(BadInputError, match="not a folder"):
        output.write_estimates([synthetic(0)], tmp_path / "file", force=True)


def psfd(cwd: Path, *argv: str) -> subprocess.CompletedProcess:
    """`python -m psfd ARGV` run as a user runs it, in ``cwd``."""
    return subprocess.run([sys.executable, "-m", "psfd", *map(str, argv)], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


def contents(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (hidden ones too) with its bytes."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_force_never_deletes_a_folder_of_the_users_files(tmp_path, data_dir):
    """The audit's case: `--out . --force` in a folder of photographs refuses before writing, deleting nothing."""
    shoot = tmp_path / "shoot"
    shoot.mkdir()
    for name in ("IMG_0001.pgm", "IMG_0002.pgm"):
        (shoot / name).write_bytes((data_dir / "img_example.pgm").read_bytes())
    (shoot / "notes.txt").write_text("notes\n")
    notes = tmp_path / "nonempty"
    notes.mkdir()
    (notes / "notes.txt").write_text("notes\n")
    before = contents(tmp_path)
    for out, named in ((".", "IMG_0001.pgm"), ("../nonempty", "notes.txt")):
        done = psfd(shoot, "estimate", "bernoulli", "IMG_0001.pgm", "--out", out, "--force")
        assert done.returncode == 2 and done.stdout == ""
        assert done.stderr.startswith("psfd: error: ") and done.stderr.count("\n") == 1
        assert named in done.stderr and "new or empty folder" in done.stderr
        assert contents(tmp_path) == before  # every file kept, with its content; no results, no staging


def test_force_never_deletes_an_input_named_like_a_result(tmp_path, data_dir):
    """A frame inside the folder to replace, though named as psfd names a figure, is kept."""
    out = tmp_path / "out"
    out.mkdir()
    frame = out / "IMG_0001_bernoulli_mono_w00.png"
    cv2.imwrite(str(frame), cv2.imread(str(data_dir / "img_example.pgm"), cv2.IMREAD_UNCHANGED))
    (out / "metrics.csv").write_text("id\n")
    before = contents(tmp_path)
    done = psfd(tmp_path, "estimate", "bernoulli", frame, "--out", out, "--force")
    assert done.returncode == 2 and done.stderr.startswith("psfd: error: ") and done.stderr.count("\n") == 1
    assert frame.name in done.stderr and "input" in done.stderr
    assert contents(tmp_path) == before


def test_force_replaces_earlier_results_of_the_same_command(tmp_path, data_dir):
    first = psfd(tmp_path, "estimate", "bernoulli", data_dir / "img_example.pgm", "--out", "psfs")
    assert first.returncode == 0, first.stderr
    names = sorted(contents(tmp_path / "psfs"))
    assert "metrics.csv" in names and "img_example_bernoulli_mono_w00.npy" in names
    again = psfd(tmp_path, "estimate", "bernoulli", data_dir / "img_example.pgm", "--out", "psfs")
    assert again.returncode == 2 and "--force" in again.stderr
    (tmp_path / "psfs" / "metrics.csv").write_text("stale\n")
    replaced = psfd(tmp_path, "estimate", "bernoulli", data_dir / "img_example.pgm", "--out", "psfs", "--force")
    assert replaced.returncode == 0, replaced.stderr
    assert sorted(contents(tmp_path / "psfs")) == names and (tmp_path / "psfs" / "metrics.csv").read_text() != "stale\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["psfs"]  # no staging or old folder left


def test_force_replaces_an_earlier_comparison(tmp_path, data_dir):
    """compare's own files (compare.png, compare.json) are results too; its --truth is never deleted."""
    frame = data_dir / "img_example.pgm"
    assert psfd(tmp_path, "compare", frame, "--out", "cmp").returncode == 0
    names = sorted(contents(tmp_path / "cmp"))
    assert {"compare.png", "compare.json", "metrics.csv"} <= set(names)
    replaced = psfd(tmp_path, "compare", frame, "--out", "cmp", "--force")
    assert replaced.returncode == 0, replaced.stderr
    assert sorted(contents(tmp_path / "cmp")) == names
    truth = next((tmp_path / "cmp").glob("*_bernoulli_*.npy"))
    before = contents(tmp_path)
    refused = psfd(tmp_path, "compare", frame, "--truth", truth, "--out", "cmp", "--force")
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and truth.name in refused.stderr
    assert contents(tmp_path) == before


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_only_on_a_terminal_and_not_with_quiet():
    """As `psfd run` shows its steps: a bar on a terminal; nothing in a pipe, a file or with -q."""
    for stream, quiet in ((io.StringIO(), 0), (_Terminal(), 1)):
        with output.progress_bar("work", quiet, stream) as progress:
            assert progress is None
        assert stream.getvalue() == ""
    terminal = _Terminal()
    with output.progress_bar("frame g1", 0, terminal) as progress:
        for fraction in (0.0, 0.25, 0.5, 1.0, 1.2):
            progress(fraction)
    drawn = terminal.getvalue()
    assert "frame g1:" in drawn and "100%" in drawn and "120%" not in drawn


def test_edges_show_progress_on_a_terminal(tmp_path):
    """`psfd estimate edges` on a terminal draws a bar on stderr that reaches 100 %; stdout keeps the table only."""
    import fcntl
    import pty
    import struct
    import termios

    from psfd.estimator import sharpedge

    image = cv2.GaussianBlur(sharpedge.edge_target(px_per_square=20.0).astype(np.float32), (0, 0), 1.0)
    cv2.imwrite(str(tmp_path / "edges.png"), np.round(2000 + 40000 * image.astype(np.float64)).astype(np.uint16))
    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))  # a terminal 100 columns wide
    try:
        done = subprocess.run([sys.executable, "-m", "psfd", "estimate", "edges", str(tmp_path / "edges.png"),
                               "-s", "2"], stdout=subprocess.PIPE, stderr=follower, text=True, timeout=120)
        os.close(follower)
        follower = -1
        drawn = b""
        while True:
            try:
                chunk = os.read(leader, 65536)
            except OSError:  # the terminal's other end is closed: all was read
                break
            if not chunk:
                break
            drawn += chunk
    finally:
        os.close(leader)
        if follower >= 0:
            os.close(follower)
    assert done.returncode == 0
    assert "edges.png mono:" in drawn.decode() and "100%" in drawn.decode()
    assert "%" not in done.stdout.split("\n", 1)[0]  # the table's header, no bar


def test_an_empty_read_only_out_folder_is_refused_not_replaced(tmp_path):
    """An empty folder is replaced by the one psfd writes beside it; one the user made read-only must stay so
    (its mode, owner and ACLs would be lost), so it is refused like any folder psfd cannot write."""
    out = tmp_path / "ro"
    out.mkdir()
    out.chmod(0o555)
    command = [sys.executable, "-m", "psfd", "estimate", "bernoulli", str(Path(__file__).parent / "data" /
                                                                          "img_example.pgm"), "--out", str(out)]
    if os.geteuid() == 0:  # root writes anywhere: drop that capability, which a user's process does not have
        import shutil

        if shutil.which("setpriv") is None:
            pytest.skip("running as root without setpriv")
        command = ["setpriv", "--bounding-set=-dac_override,-dac_read_search",
                   "--inh-caps=-dac_override,-dac_read_search", *command]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr == f"psfd: error: {out}: not a writable folder\n", done.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o555 and not any(out.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ro"]  # no staging folder left beside it


@pytest.mark.parametrize("method", ["bernoulli", "sharp-edge", "two-photo"])
def test_an_image_too_small_for_any_estimate_is_one_bad_input_line_naming_it(tmp_path, method):
    """Every method refuses it alike, before any work: exit 2, the file named (it was exit 2 without the file
    from one method and exit 3, "0 usable pixels", from another)."""
    tiny = tmp_path / "tiny.pgm"
    assert cv2.imwrite(str(tiny), np.full((8, 12), 128, np.uint8))
    frames = [tiny, tiny] if method == "two-photo" else [tiny]
    done = subprocess.run([sys.executable, "-m", "psfd", "estimate", method, *map(str, frames)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr == f"psfd: error: {tiny}: 12x8 pixels, too small for any estimate (at least 16x16)\n"


def test_estimate_out_makes_the_folder_but_no_missing_parent(tmp_path, data_dir):
    """As export and report --out: the folder named is made where its parent exists; a missing parent (a typo,
    media not mounted) is a one-line bad input naming it, before any work, and nothing is created."""
    frame = data_dir / "img_example.pgm"
    missing = psfd(tmp_path, "estimate", "bernoulli", frame, "--out", "missing/psfs", "--no-figures")
    assert (missing.returncode, missing.stdout) == (2, "")
    assert missing.stderr == f"psfd: error: {tmp_path / 'missing'}: no such folder\n"
    assert list(tmp_path.iterdir()) == []
    made = psfd(tmp_path, "estimate", "bernoulli", frame, "--out", "psfs", "--no-figures")
    assert made.returncode == 0 and (tmp_path / "psfs" / "metrics.csv").is_file(), made.stderr


def test_targets_searched_while_the_planes_are_decoded_are_the_estimators_own(tmp_path, capsys, monkeypatch):
    """`psfd estimate target` searches each file's first plane (g1) on a second thread while the other planes
    and files are decoded, and hands the detections to `estimate_frames`: they are the ones it finds itself,
    and the PSFs bit for bit its own, for several files, a file named twice (searched once, as the estimator
    does) and a single channel."""
    from psfd.cli import estimate
    from psfd.estimator import bernoulli, simulate

    monkeypatch.setattr("psfd.workers.usable_cores", lambda: 2)  # the search aside even on one core
    truth = simulate.gaussian_psf(0.55, 0.75, s=4, support=17)
    a, b = tmp_path / "a.dng", tmp_path / "b.dng"
    simulate.simulate_target(a, psf=truth, s=4, pixels_per_cell=0.35, rotation_deg=8.0, seed=3)
    simulate.simulate_target(b, psf=truth, s=4, pixels_per_cell=0.4, rotation_deg=-5.0, seed=4)
    for files, channel in (([a, b, a], "all"), ([b], "r")):  # r, g1, g2, b of a, of b, of a again; r of b
        frames, searched = estimate._load_searched([str(f) for f in files], channel)
        wanted = "g1" if channel == "all" else channel  # the plane of a file the estimator searches
        firsts = [i for i, f in enumerate(frames) if f.channel == wanted
                  and f.source not in {g.source for g in frames[:i] if g.channel == wanted}]
        assert [i for i, d in enumerate(searched) if d is not None] == firsts == ([1, 5] if channel == "all" else [0])
        own = [d for _, d in bernoulli._detections(frames)]
        for i in firsts:
            np.testing.assert_array_equal(searched[i].corners, own[i].corners)
        code, stdout, stderr = run(capsys, "estimate", "target", *files, "--channel", channel, "--json")
        assert code == 0, stderr
        got = [np.array(json.loads(line)["psf"]) for line in stdout.splitlines()]
        want = bernoulli.estimate_frames([f for path in files for f in raw.load_frames(path, channel)])
        assert len(got) == len(want) == len(frames)
        assert all(np.array_equal(g, w.psf) for g, w in zip(got, want))
