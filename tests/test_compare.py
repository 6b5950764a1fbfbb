"""Method comparison: the thesis's finding on simulated frames, and `psfd compare`.

Delbracio et al., IJCV 2012, sec. 5.1 / Fig. 8 and Delbracio PhD thesis 2013,
Fig. 1.3: with the edge pattern the estimate depends on the gradient-penalty
weight and a strong penalty under-estimates the high frequencies; the
Bernoulli pattern needs no penalty and recovers them.
"""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from psfd.cli import main
from psfd.errors import PsfdError
from psfd import figures
from psfd.cli.compare import Estimate, print_table
from psfd.estimator import gamma, mtf, sharpedge, simulate
from psfd.estimator.kernels import PSF
from psfd.estimator.mtf import HIGH, LOW, band_errors

from conftest import DATA

S = 4
SUPPORT = 17
WINDOW = 80  # observed pixels per side, the thesis's gamma window
SIGMA = 0.02  # noise of the thesis's simulation (IJCV 2012, sec. 5.1)


@pytest.fixture(scope="module")
def sharp_truth():
    # Aliased at the channel sampling, as in the thesis's simulation: MTF 0.6 at Nyquist, 0.1 at 1 cycle/pixel.
    return simulate.gaussian_psf(0.4, 0.3, theta=0.5, s=S, support=SUPPORT)


def signed_high(psf, truth):
    """Mean of MTF(estimate) - MTF(truth) above Nyquist, x and y profiles: < 0 means lost high frequencies."""
    f, mx, my = mtf.profiles(psf, S)
    _, tx, ty = mtf.profiles(truth, S)
    hi = f > 0.5
    return float(np.mean(np.concatenate([(mx - tx)[hi], (my - ty)[hi]])))


def ideal_estimate(view, truth, weight, seed):
    """Non-blind estimate with the view known exactly: v = S_s(u * h) + n, eq. (5) with the given weight."""
    u = view[: S * (WINDOW - 1) + SUPPORT, : S * (WINDOW - 1) + SUPPORT]
    a = gamma.view_matrix(u, S, SUPPORT)
    v = a @ truth.ravel() + np.random.default_rng(seed).normal(0.0, SIGMA, a.shape[0])
    k, _ = sharpedge.solve_kernel(a.T @ a, a.T @ v, SIGMA, SUPPORT, weight)
    return k / k.sum()


def test_edge_pattern_depends_on_the_weight_and_loses_high_frequencies(sharp_truth):
    """The thesis's Fig. 8 setting: same solver (eq. (5), k >= 0), same noise, the two patterns, several weights."""
    bern_view, edge_view = gamma.bernoulli_view(S), gamma.edge_view(S, WINDOW)
    weights = (0.0, 2.0, 200.0, 2e4)
    rows = {}
    for name, view, ws in (("bernoulli", bern_view, (0.0, 2.0)), ("edges", edge_view, weights)):
        for w in ws:
            runs = [ideal_estimate(view, sharp_truth, w, seed) for seed in range(2)]
            errs = [band_errors(k, S, sharp_truth, S) for k in runs]
            rows[name, w] = (np.mean([e[LOW] for e in errs]), np.mean([e[HIGH] for e in errs]),
                             np.mean([signed_high(k, sharp_truth) for k in runs]))
    print("\npattern    weight   MTF err <=Nyq  >Nyq   mean signed >Nyq")
    for (name, w), (lo, hi, sg) in rows.items():
        print(f"{name:<10} {w:>7g}   {lo:.4f}        {hi:.4f}  {sg:+.4f}")
    bern_high = rows["bernoulli", 0.0][1]
    edge_high = [rows["edges", w][1] for w in weights]
    # the noise target needs no penalty and is the most accurate above Nyquist ...
    assert bern_high < min(edge_high)
    # ... and a small penalty does not change it (same estimate to 10 % of its error)
    assert abs(rows["bernoulli", 2.0][1] - bern_high) < 0.1 * bern_high
    # the edge estimate depends on the weight: its high-frequency error spans a factor > 3 over the weights
    assert max(edge_high) > 3 * min(edge_high)
    # a strong penalty under-estimates the high frequencies (mean MTF deficit above Nyquist)
    assert rows["edges", 2e4][2] < -0.04
    # without a penalty the edge estimate is noisier above Nyquist than the noise target's, by the
    # conditioning gap (gamma ratio ~70, i.e. ~8x in RMS for plain least squares; k >= 0 narrows it)
    assert rows["edges", 0.0][1] > 2 * bern_high


def edge_scene_dng(path, psf, *, px_per_square=20.0, angle=8.0, sensor=(440, 440), seed=0):
    """A real DNG of the edge target (four Bayer planes rendered with ``psf``) via simulate_scene."""
    pps = 32
    scene = sharpedge.edge_target(px_per_square=pps)
    a, k = np.deg2rad(angle), pps / (2 * px_per_square)  # raster pixels per sensor photosite
    cy, cx = (sensor[0] - 1) / 2, (sensor[1] - 1) / 2

    def to_scene(x, y):
        x, y = np.asarray(x) - cx, np.asarray(y) - cy
        return (k * (np.cos(a) * x - np.sin(a) * y) + scene.shape[1] / 2 - 0.5,
                k * (np.sin(a) * x + np.cos(a) * y) + scene.shape[0] / 2 - 0.5)

    return simulate.simulate_scene(path, scene=scene, sensor_to_scene=to_scene, psf=psf, s=S, sensor=sensor,
                                   seed=seed, background=1.0)


@pytest.fixture(scope="module")
def edge_target_errors(tmp_path_factory, sharp_truth):
    """Sharp-edge target-form estimates of a real DNG of the edge target at the paper's and a strong weight."""
    from psfd.estimator import raw

    path = tmp_path_factory.mktemp("edges") / "edges.dng"
    edge_scene_dng(path, sharp_truth)
    frame = raw.load_frame(path, "g1")
    edge = {w: sharpedge.estimate_edges(frame, s=S, weight=w, target_form=True)[0].psf for w in (2.0, 2e6)}
    return {w: (band_errors(k, S, sharp_truth, S)[HIGH], signed_high(k, sharp_truth)) for w, k in edge.items()}


def test_pipeline_sharp_edge_depends_on_the_weight(edge_target_errors):
    """The same finding through the whole sharp-edge estimator (target form) on a real DNG."""
    err = edge_target_errors
    print(f"\nsharp-edge target: MTF err >Nyq {err[2.0][0]:.4f} (w=2), {err[2e6][0]:.4f} "
          f"(w=2e6, mean signed {err[2e6][1]:+.4f})")
    assert err[2e6][0] > 2 * err[2.0][0]
    assert err[2e6][1] < -0.05


def test_pipeline_bernoulli_beats_sharp_edge(tmp_path, sharp_truth, edge_target_errors):
    """Bernoulli estimate of a DNG of the noise target against the sharp-edge estimates of the edge target."""
    pytest.importorskip("psfd.estimator.radiometry", reason="the Bernoulli pipeline is not complete yet")
    from psfd.estimator import bernoulli, raw

    simulate.simulate_target(tmp_path / "bern.dng", psf=sharp_truth, s=S, pixels_per_cell=0.25, rotation_deg=5,
                             sensor=(480, 640), seed=2)
    bern = bernoulli.estimate_target(raw.load_frame(tmp_path / "bern.dng", "g1"), s=S)[0].psf
    bern_err = band_errors(bern, S, sharp_truth, S)[HIGH]
    edge = {w: e for w, (e, _) in edge_target_errors.items()}
    print(f"\nbernoulli: MTF err >Nyq {bern_err:.4f}; sharp-edge target {edge[2.0]:.4f} (w=2), {edge[2e6]:.4f} (w=2e6)")
    assert bern_err < min(edge.values())


# ---------------------------------------------------------------- psfd compare


@pytest.fixture(scope="module")
def edge_dng(tmp_path_factory, sharp_truth):
    folder = tmp_path_factory.mktemp("cmp")
    edge_scene_dng(folder / "edges.dng", sharp_truth)
    np.save(folder / "truth.npy", sharp_truth)
    return folder


def test_compare_cli_with_truth(edge_dng, capsys):
    out = edge_dng / "out"
    code = main(["compare", str(edge_dng / "edges.dng"), "--truth", str(edge_dng / "truth.npy"),
                 "--weights", "2,2e6", "--out", str(out)])
    text = capsys.readouterr().out
    print(text)
    assert code == 0
    assert "sharp-edge target w=2 edges.dng" in text and "sharp-edge target w=2e+06 edges.dng" in text
    summary = json.loads((out / "compare.json").read_text())
    errors = summary["errors"]
    assert summary["against"] == "truth"
    # the grid the truth was read on is said: without -s, the Bernoulli s (4), whatever each method's own s
    assert summary["truth_s"] == 4 and "truth: read on the s = 4 grid" in text
    # the strong penalty's high-frequency error is the larger one (see the test above)
    assert errors["sharp-edge target w=2e+06 edges.dng"][HIGH] > errors["sharp-edge target w=2 edges.dng"][HIGH]
    figure = cv2.imread(str(out / "compare.png"))
    assert figure is not None and figure.shape[2] == 3
    assert len(list(out.glob("*.npy"))) == 2


def test_compare_cli_without_truth_compares_the_methods(edge_dng, capsys):
    code = main(["compare", str(edge_dng / "edges.dng"), "--weights", "2,2e6"])
    text = capsys.readouterr().out
    assert code == 0
    assert text.count("vs sharp-edge target") == 2


def test_compare_cli_bad_inputs(edge_dng, tmp_path, capsys):
    out = tmp_path / "never"
    frame = str(edge_dng / "edges.dng")
    (tmp_path / "bad.npy").write_text("not an array")
    np.save(tmp_path / "even.npy", np.ones((4, 4)))
    cases = [
        (["--truth", str(tmp_path / "missing.npy")], 2),
        (["--truth", str(tmp_path / "bad.npy")], 2),
        (["--truth", str(tmp_path / "even.npy")], 2),
        (["--weights", "2,-1"], 2),
        (["-s", "zero"], 2),
    ]
    for extra, exit_code in cases:
        assert main(["compare", frame, "--out", str(out), *extra]) == exit_code
        err = capsys.readouterr().err
        assert err.startswith("psfd: error:") and err.count("\n") == 1
        assert not out.exists()
    flat = np.full((120, 120), 30000, np.uint16)
    flat = (flat + np.random.default_rng(0).normal(0, 200, flat.shape)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "flat.png"), flat)
    assert main(["compare", str(tmp_path / "flat.png"), "--out", str(out)]) == 3
    assert "no method could estimate a PSF" in capsys.readouterr().err
    assert not out.exists()


def test_error_footnote_only_with_an_error_column(capsys):
    kernel = np.zeros((9, 9))
    kernel[4, 4] = 1.0
    one = Estimate("bernoulli x.dng", PSF(kernel, 2, "bernoulli", "g1", ["x.dng"], (0.5, 0.5), (0, 0, 8, 8),
                                          noise_floor=0.048))
    skipped = Estimate("sharp-edge x.dng", None, "no edges")
    print_table([one, skipped], {one.label: {}}, with_truth=False)
    text = capsys.readouterr().out
    assert "MTF50" in text and "skipped: no edges" in text and "MTF error" not in text
    # each estimate's floor relative to its kernel (a unit kernel here: the floor itself)
    assert "noise 4.8%" in text and "noise: each estimate's noise floor over its kernel's L2 norm" in text
    print_table([one], {one.label: {LOW: 0.01, HIGH: 0.02}}, with_truth=True)
    text = capsys.readouterr().out
    assert "MTF error: RMS difference" in text and text.splitlines()[1].split()[-1] == "4.8%"


def test_a_failed_comparison_figure_leaves_no_output_folder(tmp_path, monkeypatch):
    """compare.png is written inside the same staging folder as the estimates: all or nothing."""
    from psfd.cli import compare
    from psfd.errors import BadInputError

    kernel = simulate.gaussian_psf(0.5, s=4, support=17)
    estimates = [Estimate("bernoulli", PSF(kernel, 4, "bernoulli", "g1", ["a.dng"]))]
    def disk_full(curves, against_truth=False):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(figures, "comparison_figure", disk_full)  # the last files fail, after the estimates
    out = tmp_path / "cmp"
    with pytest.raises(BadInputError, match="No space left on device"):
        compare.write_outputs(out, estimates, {}, None, 4)
    assert list(tmp_path.iterdir()) == []


def test_compare_that_cannot_write_prints_one_error_line_and_no_table(tmp_path, monkeypatch, capsys):
    """As `estimate`: the results are written before the table is printed, so a full disk gives the one error
    line, not a table of results that were never written followed by the error."""
    def disk_full(curves, against_truth=False):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(figures, "comparison_figure", disk_full)
    example = Path(__file__).parent / "data" / "img_example.pgm"
    code = main(["compare", str(example), "--out", str(tmp_path / "cmp")])
    out, err = capsys.readouterr()
    assert code == 2 and out == "" and err.count("\n") == 1 and "No space left on device" in err
    assert list(tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def real_pair_alone():
    """The real pair's frames and each method run alone in this process: the two-photo estimate, then the
    sharp-edge estimate of each photo (its PSFs, or why it could not run)."""
    from psfd.estimator import raw, twoscale
    from psfd.vocabulary import DEFAULT_S, SHARP_EDGE, TWO_PHOTO

    far = raw.load_frame(DATA / "IMG_0602_v1_CUT.pgm", "mono")
    near = raw.load_frame(DATA / "IMG_0608_v1.pgm", "mono")
    [pair] = twoscale.estimate_pair(far, near, s=DEFAULT_S[TWO_PHOTO])
    alone = [("two-photo IMG_0602_v1_CUT.pgm+IMG_0608_v1.pgm", pair)]
    for frame in (far, near):
        label = f"sharp-edge w=2 {Path(frame.source).name}"
        try:
            alone += [(label, psf) for psf in sharpedge.estimate_edges(frame, s=DEFAULT_S[SHARP_EDGE])]
        except PsfdError as exc:
            alone.append((label, str(exc)))
    return far, near, alone


@pytest.mark.parametrize("schedule", ["forked", "forked, one search at a time", "one core"])
def test_compare_of_the_real_pair_is_each_method_run_alone(real_pair_alone, monkeypatch, schedule):
    """The largest frame searched and its methods run here, the other frame searched and its methods and the
    pair's run in the forked worker (which waits for this frame's kind before the pair, and before its own
    search when the searches' memory would not fit together); or, on one core, all in this process: the
    estimates, and their order, of each method run alone in this process, bit for bit; the frame done here
    shows its progress, up to the end."""
    import contextlib

    from psfd.cli import compare, output
    from psfd.vocabulary import BERNOULLI, DEFAULT_S, SHARP_EDGE, TWO_PHOTO

    far, near, alone = real_pair_alone
    sizes = {m: {"s": DEFAULT_S[m], "support": None, "grid": (1, 1)} for m in (BERNOULLI, TWO_PHOTO, SHARP_EDGE)}
    bars = {}

    @contextlib.contextmanager
    def recorded(label, quiet=0, stream=None):
        bars[label] = []
        yield None if quiet else bars[label].append

    monkeypatch.setattr(output, "progress_bar", recorded)
    if schedule == "forked, one search at a time":
        monkeypatch.setattr(compare, "SEARCH_TOGETHER_PIXELS", 0)
    if schedule == "one core":
        monkeypatch.setattr(compare, "usable_cores", lambda: 1)
    found = compare.run_methods([far, near], sizes, [2.0], quiet=0)
    assert [e.label for e in found] == [label for label, _ in alone]
    for estimate, (_, expected) in zip(found, alone):
        if isinstance(expected, str):
            assert estimate.psf is None and estimate.reason == expected
        else:
            np.testing.assert_array_equal(estimate.psf.psf, expected.psf)
            assert estimate.psf.params == expected.params
    near_bar = bars["sharp-edge w=2 IMG_0608_v1.pgm"]  # the largest frame: done in this process, with its bar
    assert near_bar and near_bar[-1] == pytest.approx(1.0) and near_bar == sorted(near_bar)


def test_a_frames_kind_does_not_depend_on_what_its_thread_drew_before(monkeypatch):
    """The board search's k-d tree draws from OpenCV's per-thread generator, and from some states it labels
    this board's corners otherwise (another of the board's symmetries) or misses it: the kind's search starts
    from the state of a fresh thread whatever the thread drew before, so either process may search a frame."""
    import threading

    from psfd.cli import compare
    from test_sharpedge import S as EDGE_S, SUPPORT as EDGE_SUPPORT, edge_frame

    frame = edge_frame(simulate.gaussian_psf(0.6, 0.5, theta=0.4, s=EDGE_S, support=EDGE_SUPPORT), px_per_square=14,
                       angle=20, seed=1, distortion=0.02)
    views = []
    locate = sharpedge.locate_target
    monkeypatch.setattr(sharpedge, "locate_target", lambda image: views.append(locate(image)) or views[-1])
    fresh = threading.Thread(target=compare._edge_target, args=(frame,))
    fresh.start()
    fresh.join()
    cv2.setRNGSeed(1)  # a search straight from this state labels the corners otherwise
    assert compare._edge_target(frame) is not None
    assert len(views) == 2
    np.testing.assert_array_equal(views[1].homography, views[0].homography)
    cv2.setRNGSeed(1)
    assert not np.array_equal(locate(frame.data / frame.white).homography, views[0].homography)



@pytest.mark.parametrize("scene", ["bernoulli", "edge target"])
def test_compare_searches_each_frame_once(tmp_path, sharp_truth, monkeypatch, scene):
    """A frame's target is searched once, for its kind: its methods take what that search found (the Bernoulli
    detection, the edge target's located corners) rather than search again (three more searches of a Bernoulli
    frame, two of them for a board it does not show; a second board search from another generator state), and
    give what each method gives alone on the target so located, bit for bit."""
    from psfd.cli import compare
    from psfd.estimator import bernoulli, detect, raw

    path = tmp_path / "frame.dng"
    if scene == "bernoulli":
        simulate.simulate_target(path, psf=sharp_truth, s=S, pixels_per_cell=0.25, rotation_deg=5,
                                 sensor=(480, 640), seed=2)
    else:
        edge_scene_dng(path, sharp_truth)
    frame = raw.load_frame(path, "g1")
    searches = {"find_target": 0, "locate_target": 0}
    for module, name in ((detect, "find_target"), (sharpedge, "locate_target")):
        def counted(*args, name=name, search=getattr(module, name), **kwargs):
            searches[name] += 1
            return search(*args, **kwargs)

        monkeypatch.setattr(module, name, counted)
    sizes = {method: {"s": S, "support": None} for method in ("bernoulli", "two-photo", "sharp-edge")}
    found = compare.run_methods([frame], sizes, [2.0])
    monkeypatch.undo()
    if scene == "bernoulli":
        assert searches == {"find_target": 1, "locate_target": 0}
        alone = bernoulli.estimate_target(frame, s=S) + sharpedge.estimate_edges(frame, s=S, target_form=True)
        assert [e.label for e in found] == ["bernoulli frame.dng", "sharp-edge target w=2 frame.dng"]
    else:
        assert searches == {"find_target": 1, "locate_target": 1}  # the Bernoulli target first, then the board
        cv2.setRNGSeed(0)  # the state the kind's search starts from
        alone = sharpedge.estimate_edges(frame, s=S, pattern=sharpedge.edge_target_in(frame))
        assert [e.label for e in found] == ["sharp-edge target w=2 frame.dng"]
    for estimate, expected in zip(found, alone, strict=True):
        np.testing.assert_array_equal(estimate.psf.psf, expected.psf)
        assert estimate.psf.params == expected.params

def test_the_worker_waiting_for_a_message_ends_when_the_parent_sends_none():
    """`_Message` in a forked worker: the value sent, or EOFError once the sender's end is closed unsent
    (the worker closed its own copy of it), rather than a worker waiting for ever."""
    import multiprocessing

    from psfd.cli import compare

    for send in (True, False):
        message = compare._Message(True)
        compare._BESIDE = message.receive
        try:
            with multiprocessing.get_context("fork").Pool(1) as pool:
                pending = pool.apply_async(compare._run_beside)
                if send:
                    message.send("plain")
                    assert pending.get(timeout=30) == "plain"
                else:
                    message.pipe[1].close()
                    with pytest.raises(EOFError):
                        pending.get(timeout=30)
        finally:
            compare._BESIDE = None


def psfd_cli(*argv) -> subprocess.CompletedProcess:
    """The whole `python -m psfd` process, as a user runs it."""
    return subprocess.run([sys.executable, "-m", "psfd", *map(str, argv)], capture_output=True, text=True)


def test_compare_of_a_single_channel_image_is_mono(tmp_path):
    """A PGM is its own plane, mono, in the file names, each estimate's JSON and metrics.csv (a Bayer label
    would halve its lp/mm); asked for a Bayer channel it is refused in one line, nothing written."""
    out = tmp_path / "cmp"
    done = psfd_cli("compare", DATA / "img_example.pgm", "--out", out)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in out.glob("*.npy")) == ["img_example_bernoulli_mono_w00.npy",
                                                         "img_example_sharp-edge_mono_w00.npy"]
    assert [json.loads(p.read_text())["channel"] for p in sorted(out.glob("img_example_*.json"))] == ["mono"] * 2
    with open(out / "metrics.csv", newline="") as fh:
        assert [row["channel"] for row in csv.DictReader(fh)] == ["mono"] * 2
    never = tmp_path / "never"
    done = psfd_cli("compare", DATA / "img_example.pgm", "--channel", "g1", "--out", never)
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert done.stderr.startswith(f"psfd: error: {DATA / 'img_example.pgm'}: ") and "mono" in done.stderr
    assert not never.exists()


def test_band_errors_are_exact_and_one_value_per_pair_across_grids():
    """Kernels on grids of different s are compared on one frequency grid, each MTF evaluated there exactly:
    a kernel against its own samples on a twice finer grid (zeros between them: the same samples at the same
    positions, so the same MTF) differs by nothing, and the error does not depend on which kernel comes first."""
    coarse = simulate.gaussian_psf(0.5, 0.35, theta=0.3, s=2, support=9)
    fine = np.zeros((17, 17))
    fine[::2, ::2] = coarse
    for first, second in (((coarse, 2), (fine, 4)), ((fine, 4), (coarse, 2))):
        errors = band_errors(*first, *second)
        assert errors[LOW] < 1e-12 and errors[HIGH] < 1e-12, errors
    pair = simulate.gaussian_psf(0.55, s=3, support=13)
    edges = simulate.gaussian_psf(0.4, 0.6, theta=0.2, s=4, support=17)
    assert band_errors(pair, 3, edges, 4) == band_errors(edges, 4, pair, 3)


def test_compare_errors_between_methods_are_one_value_per_pair(tmp_path):
    """The real pair: the two-photo estimate (s 3) and the sharp-edge one (s 4) have one MTF error whichever
    comes first, in the table and in compare.json; the footnote gives the band limit's unit, not the error's."""
    out = tmp_path / "cmp"
    done = psfd_cli("compare", DATA / "IMG_0608_v1.pgm", DATA / "IMG_0602_v1_CUT.pgm", "--out", out)
    assert done.returncode == 0, done.stderr
    errors = json.loads((out / "compare.json").read_text())["errors"]
    pairs = [(a, b) for a in errors for b in errors[a]]
    assert len(pairs) == 2
    for a, b in pairs:
        assert errors[a][b] == errors[b][a]
    shown = [line.split("MTF err")[1] for line in done.stdout.splitlines() if line.lstrip().startswith("vs ")]
    assert len(shown) == 2 and shown[0] == shown[1]
    assert "cycles per channel pixel (Nyquist 0.5)." not in done.stdout
    assert "MTF error: RMS difference of the x and y MTF profiles (unitless)" in done.stdout


@pytest.mark.parametrize("kind, words", [
    ("complex", "real"), ("strings", "real"), ("three-d", "2-D"), ("even", "odd"), ("nan", "finite"),
    ("negative", "positive mass"), ("missing", "no such file"), ("folder", "is a folder"),
])
def test_compare_refuses_a_truth_that_is_no_psf(tmp_path, kind, words):
    """A --truth that is not a real, finite, 2-D, odd-sized array of positive mass is one line (exit 2), no
    warning text (numpy's ComplexWarning on a complex array), nothing written; a missing one is "no such file",
    as every other file psfd reads."""
    truth = tmp_path / f"{kind}.npy"
    arrays = {"complex": np.ones((17, 17)) * (1 + 1j) / 289, "strings": np.full((17, 17), "1"),
              "three-d": np.ones((3, 17, 17)), "even": np.ones((16, 16)), "nan": np.full((17, 17), np.nan),
              "negative": -np.ones((17, 17))}
    if kind in arrays:
        np.save(truth, arrays[kind])
    if kind == "folder":
        truth.mkdir()
    out = tmp_path / "never"
    done = psfd_cli("compare", DATA / "img_example.pgm", "--truth", truth, "--out", out)
    assert done.returncode == 2
    assert done.stderr.startswith(f"psfd: error: {truth}: ") and done.stderr.count("\n") == 1, done.stderr
    assert words in done.stderr and "Warning" not in done.stderr
    assert done.stdout == "" and not out.exists()
