"""`psfd target`: the printed target (PDF, PNG) and the noise saved beside it."""

from __future__ import annotations

import re
import shutil
import subprocess
import zlib

import cv2
import numpy as np
import pytest

from psfd import printing
from psfd.cli import main
from psfd.estimator import target

PX = 8  # pixels per cell of the rasters compared below


def parse_pdf(data: bytes) -> dict:
    """Read back a PDF through its cross-reference table, as a viewer does.

    Returns the objects by number and the decompressed page content.
    """
    assert data.startswith(b"%PDF-1.")
    startxref = int(re.search(rb"startxref\s+(\d+)\s+%%EOF\s*$", data)[1])
    head = re.match(rb"xref\s+0 (\d+)\s+", data[startxref:])
    assert head, "startxref does not point at the xref table"
    count = int(head[1])
    table = data[startxref + head.end() : startxref + head.end() + 20 * count]
    assert table[:20] == b"0000000000 65535 f \n"  # entries are exactly 20 bytes
    objects = {}
    for number in range(1, count):
        entry = table[20 * number : 20 * (number + 1)]
        offset = int(entry[:10])
        assert entry[10:] == b" 00000 n \n"
        assert data[offset:].startswith(f"{number} 0 obj".encode()), f"xref offset of object {number} is wrong"
        end = data.index(b"endobj", offset)
        objects[number] = data[offset:end]
    trailer = data[data.index(b"trailer", startxref) :]
    root = int(re.search(rb"/Root (\d+) 0 R", trailer)[1])
    assert b"/Type /Catalog" in objects[root]
    page = next(o for o in objects.values() if b"/Type /Page " in o)
    contents = int(re.search(rb"/Contents (\d+) 0 R", page)[1])
    stream_obj = objects[contents]
    length = int(re.search(rb"/Length (\d+)", stream_obj)[1])
    start = stream_obj.index(b"stream\n") + len(b"stream\n")
    assert stream_obj[start + length :].startswith(b"\nendstream")  # /Length is exact
    content = zlib.decompress(stream_obj[start : start + length]).decode("latin-1")
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]+)\]", page)[1].split()]
    return {"objects": objects, "content": content, "mediabox": box}


def rasterise_content(content: str, px: int) -> np.ndarray:
    """Fill the content's rectangles and triangles (cell units) on a px-per-cell grid, 1 white 0 black.

    A pixel is black when its centre lies strictly inside a shape, the rule
    `target.cells` uses, so the two must agree pixel for pixel.
    """
    side = target.SIZE * px
    out = np.ones((side, side))
    centres = (np.arange(side) + 0.5) / px
    for x, y, w, h in re.findall(r"^(\d+) (\d+) (\d+) (\d+) re$", content, re.M):
        x, y, w, h = (int(v) for v in (x, y, w, h))
        out[y * px : (y + h) * px, x * px : (x + w) * px] = 0
    for tri in re.findall(r"^(\d+) (\d+) m (\d+) (\d+) l (\d+) (\d+) l h$", content, re.M):
        (ax, ay, bx, by, cx, cy) = (int(v) for v in tri)
        x0, x1, y0, y1 = min(ax, bx, cx), max(ax, bx, cx), min(ay, by, cy), max(ay, by, cy)
        yy, xx = np.meshgrid(centres[y0 * px : y1 * px], centres[x0 * px : x1 * px], indexing="ij")
        inside = np.ones_like(yy, dtype=bool)
        sign = np.sign((bx - ax) * (cy - ay) - (by - ay) * (cx - ax))
        for p, q in (((ax, ay), (bx, by)), ((bx, by), (cx, cy)), ((cx, cy), (ax, ay))):
            inside &= sign * ((q[0] - p[0]) * (yy - p[1]) - (q[1] - p[1]) * (xx - p[0])) > 0
        out[y0 * px : y1 * px, x0 * px : x1 * px][inside] = 0
    return out


def run(capsys, *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_pdf_is_well_formed_and_draws_the_layout(tmp_path, capsys):
    out = tmp_path / "t.pdf"
    code, stdout, _ = run(capsys, "target", "--out", str(out), "--seed", "7", "--size-mm", "700")
    assert code == 0 and "seed 7" in stdout
    pdf = parse_pdf(out.read_bytes())
    # Page = target + one block of margin each side: 700 mm * 12/10 = 840 mm = 2381.1 pt.
    side_pt = 840 / 25.4 * 72
    assert pdf["mediabox"] == pytest.approx([0, 0, side_pt, side_pt], abs=1e-3)
    noise = target.seeded_noise(7)
    content = pdf["content"]
    # one rectangle per run of black cells in a row, two triangles per X-corner
    expected_runs = len(printing.black_runs(printing.run_raster(noise)))
    assert content.count(" re\n") == expected_runs
    assert len(re.findall(r" l h$", content, re.M)) == 2 * len(target.XCORNER_BLOCKS)
    cell = float(re.search(r"^([\d.]+) 0 0 -[\d.]+ [\d.]+ [\d.]+ cm$", content, re.M)[1])
    assert cell * 25.4 / 72 == pytest.approx(700 / 320, rel=1e-6)
    assert "seed 7" in content and "cell 2.1875 mm" in content and "print at 100 %" in content
    # the drawing is exactly the layout: same pixels as target.cells at 8 px per cell
    np.testing.assert_array_equal(rasterise_content(content, PX), target.cells(noise, PX))
    # small: a 256x256 noise target in well under 100 kB (one rectangle per row run, compressed)
    assert out.stat().st_size < 100_000
    saved = target.load_noise(tmp_path / "t.seed7.noise.pgm")
    np.testing.assert_array_equal(saved, noise)


def test_png_matches_the_layout_and_its_noise(tmp_path, capsys):
    out = tmp_path / "t.png"
    code, _, _ = run(capsys, "target", "--out", str(out), "--seed", "11")
    assert code == 0
    image = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    margin = printing.MARGIN_BLOCKS * target.BLOCK * PX
    assert image.dtype == np.uint8 and image.shape == ((target.SIZE * PX + 2 * margin),) * 2
    assert (image[:margin] == 255).all() and (image[:, -margin:] == 255).all()
    saved = target.load_noise(tmp_path / "t.seed11.noise.pgm")
    np.testing.assert_array_equal(saved, target.seeded_noise(11))
    # noise region: every pixel of cell (r, c) equals the saved noise value
    start = margin + target.NOISE_START * PX
    region = image[start : start + target.NOISE * PX, start : start + target.NOISE * PX]
    cells = region.reshape(target.NOISE, PX, target.NOISE, PX).transpose(0, 2, 1, 3)
    assert (cells == (saved * 255).astype(np.uint8)[:, :, None, None]).all()
    inner = image[margin:-margin, margin:-margin]
    np.testing.assert_array_equal(inner, np.round(target.cells(saved, PX) * 255).astype(np.uint8))


def test_seed_is_reproducible_and_default_is_published(tmp_path, capsys):
    a, b, c, d = (tmp_path / f"{n}.pdf" for n in "abcd")
    for path, extra in ((a, ["--seed", "5"]), (b, ["--seed", "5"]), (c, ["--seed", "6"]), (d, [])):
        assert run(capsys, "target", "--out", str(path), *extra)[0] == 0
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes() != c.read_bytes()
    np.testing.assert_array_equal(target.load_noise(tmp_path / "d.published.noise.pgm"), target.default_noise())


def test_own_noise_round_trips(tmp_path, capsys):
    noise = target.seeded_noise(99)
    target.save_noise(noise, tmp_path / "lab.pgm")
    out = tmp_path / "lab_target.png"
    assert run(capsys, "target", "--out", str(out), "--noise", str(tmp_path / "lab.pgm"))[0] == 0
    np.testing.assert_array_equal(target.load_noise(tmp_path / "lab_target.lab.noise.pgm"), noise)


@pytest.mark.skipif(shutil.which("pdftoppm") is None, reason="no PDF rasteriser (pdftoppm) on this machine")
def test_pdf_rasterised_by_poppler_matches_png(tmp_path, capsys):
    # 8 points per cell, rendered at 72 dpi: 8 pixels per cell, as the PNG
    size_mm = target.SIZE * 8 * 25.4 / 72
    assert run(capsys, "target", "--out", str(tmp_path / "t.pdf"), "--seed", "3", "--size-mm", str(size_mm))[0] == 0
    assert run(capsys, "target", "--out", str(tmp_path / "t.png"), "--seed", "3")[0] == 0
    subprocess.run(["pdftoppm", "-r", "72", "-gray", "-png", str(tmp_path / "t.pdf"), str(tmp_path / "r")], check=True)
    rendered = cv2.imread(str(next(tmp_path.glob("r*.png"))), cv2.IMREAD_GRAYSCALE)
    png = cv2.imread(str(tmp_path / "t.png"), cv2.IMREAD_GRAYSCALE)
    assert rendered.shape == png.shape
    margin = printing.MARGIN_BLOCKS * target.BLOCK * PX  # the bottom margin holds the caption
    diff = np.abs(rendered.astype(int) - png.astype(int))[: png.shape[0] - margin]
    # anti-aliasing only touches the hourglass diagonals: under 0.1 % of pixels differ by more than half
    assert np.mean(diff > 128) < 1e-3
    # every cell centre agrees, except those on the hourglass diagonals (which run through them)
    centres = np.arange(PX // 2, png.shape[0] - margin, PX)
    off = diff[np.ix_(centres, centres)] >= 64
    diagonal_cells = 12 * 2 * 2 * (target.BLOCK // 2)
    assert off.sum() <= diagonal_cells


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--out", "{tmp}/t.jpg"], "unknown target format"),
        (["--out", "{tmp}/missing/t.pdf"], "missing: no such folder"),
        (["--out", "{tmp}/file.txt/t.pdf"], "file.txt: not a folder"),
        (["--out", "{tmp}/t.pdf", "--seed", "abc"], "--seed"),
        (["--out", "{tmp}/t.pdf", "--seed", "-3"], "--seed"),
        (["--out", "{tmp}/t.pdf", "--seed", "1", "--noise", "{tmp}/file.txt"], "not both"),
        (["--out", "{tmp}/t.pdf", "--noise", "{tmp}/file.txt"], "noise pattern"),
        (["--out", "{tmp}/t.pdf", "--size-mm", "5"], "target size"),
        (["--out", "{tmp}/t.png", "--size-mm", "-5"], "--size-mm: must be a positive"),
        (["--out", "{tmp}/t.png", "--size-mm", "0"], "--size-mm: must be a positive"),
        (["--out", "{tmp}/t.png", "--kind", "edges", "--size-mm", "-5"], "--size-mm: must be a positive"),
        (["--out", "{tmp}/t.png", "--noise", "{tmp}/missing.pgm"], "missing.pgm: no such file"),
        (["--out", "{tmp}/t.pdf", "--size-mm", "nan"], "--size-mm"),
        (["--out", "{tmp}/t.png", "--px-per-cell", "0"], "--px-per-cell"),
        # a pattern with no noise in it would print a target no photograph of which can be estimated
        (["--out", "{tmp}/t.pdf", "--noise", "{tmp}/black.pgm"], "black.pgm: no noise pattern, every cell is black"),
        (["--out", "{tmp}/t.pdf", "--noise", "{tmp}/folder"], "folder: is a folder"),
    ],
)
def test_bad_input_one_line_nothing_written(tmp_path, capsys, argv, message):
    (tmp_path / "file.txt").write_text("not an image\n")
    cv2.imwrite(str(tmp_path / "black.pgm"), np.zeros((target.NOISE, target.NOISE), np.uint8))
    (tmp_path / "folder").mkdir()
    code, stdout, stderr = run(capsys, "target", *(a.format(tmp=tmp_path) for a in argv))
    assert code == 2
    assert stderr.startswith("psfd: error: ") and stderr.count("\n") == 1 and message in stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["black.pgm", "file.txt", "folder"]


def test_a_noise_file_that_cannot_be_written_says_why(tmp_path):
    # the kernel's file size limit (RLIMIT_FSIZE) stops the noise file past 60 kB, after the 49 kB PDF: EFBIG
    # as a full disk gives ENOSPC, in a process of its own (Python ignores SIGXFSZ, so write() fails instead)
    import resource
    import sys

    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (60_000, 60_000))

    done = subprocess.run([sys.executable, "-m", "psfd", "target", "--out", str(tmp_path / "t.pdf"), "--seed", "3"],
                          capture_output=True, text=True, timeout=120, preexec_fn=limit)
    assert done.returncode == 2
    assert done.stderr == f"psfd: error: {tmp_path / 't.pdf'}: cannot write (File too large)\n"
    assert list(tmp_path.iterdir()) == []


def test_edge_target_pdf_is_well_formed(tmp_path, capsys):
    from psfd.estimator import sharpedge

    code, _, _ = run(capsys, "target", "--kind", "edges", "--out", str(tmp_path / "e.pdf"), "--size-mm", "400")
    assert code == 0
    pdf = parse_pdf((tmp_path / "e.pdf").read_bytes())
    nx, ny = sharpedge.SQUARES
    side_pt = 400 * (1 + 2 * sharpedge.BORDER / nx) / 25.4 * 72  # board plus its white border
    assert pdf["mediabox"] == pytest.approx([0, 0, side_pt, side_pt], abs=1e-3)
    assert pdf["content"].count(" re\n") == nx * ny // 2  # the black squares
    assert pdf["content"].count(" c ") == 4 * nx * ny  # one disk of four Bezier arcs per square
    assert sorted(p.name for p in tmp_path.iterdir()) == ["e.pdf"]  # no noise file for this target


def test_no_noise_pattern_is_overwritten_silently(tmp_path, capsys):
    """A target printed from seed 7 keeps its noise when another target is written to the same name."""
    out = tmp_path / "target.pdf"
    assert run(capsys, "target", "--out", str(out), "--seed", "7")[0] == 0
    assert run(capsys, "target", "--out", str(tmp_path / "target.png"))[0] == 0  # the published noise
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "target.pdf", "target.png", "target.published.noise.pgm", "target.seed7.noise.pgm"]
    np.testing.assert_array_equal(target.load_noise(tmp_path / "target.seed7.noise.pgm"), target.seeded_noise(7))
    pdf = out.read_bytes()
    assert run(capsys, "target", "--out", str(out), "--seed", "7")[0] == 0  # the same target again: harmless
    code, _, err = run(capsys, "target", "--out", str(out), "--seed", "8")  # another target under that name
    assert code == 2 and "exists" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert out.read_bytes() == pdf and not (tmp_path / "target.seed8.noise.pgm").exists()
    assert run(capsys, "target", "--out", str(out), "--seed", "8", "--force")[0] == 0
    assert out.read_bytes() != pdf and (tmp_path / "target.seed7.noise.pgm").exists()
