"""Rendering the calibration targets for print: a vector PDF and a raster PNG.

The Bernoulli target keeps the published layout (`psfd.estimator.target`);
only the noise realisation changes. The printed cells must be large enough
that ink does not soak across cell borders (Delbracio PhD thesis 2013, ch. 2
discussion: the authors printed "some 70 cm"), hence the 700 mm default. The
sharp-edge target is `psfd.estimator.sharpedge.edge_target`.

The PDF is written by hand: none of the project's dependencies (numpy, scipy,
OpenCV, rawpy, tifffile, ...) writes PDF, and the files need only what PDF 1.4
has had since the start: filled rectangles (``re``), filled paths
(``m``/``l``/``c``/``h``) and one line of text in a standard font.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import cv2
import numpy as np

from psfd.errors import BadInputError
from psfd.estimator import sharpedge, target

MM_PER_POINT = 25.4 / 72.0
# White border around the target, in blocks: one block, as on the published print, keeps the
# outer marks apart from whatever is behind the board; a 700 mm target then fits A0 (841 mm).
MARGIN_BLOCKS = 1
MIN_SIZE_MM = 50.0
# PDF viewers and printers limit a page side to 14400 points (200 inches) unless UserUnit is used.
MAX_PAGE_MM = 14400 * MM_PER_POINT


def _check_size(size_mm: float, page_per_size: float) -> None:
    """The target side must fit a PDF page once the white border (page / target side) is added."""
    largest = MAX_PAGE_MM / page_per_size
    if not MIN_SIZE_MM <= size_mm <= largest:
        raise BadInputError(f"target size must be between {MIN_SIZE_MM:g} and {largest:.0f} mm, got {size_mm:g}")


def _check_px(px: int) -> None:
    if not 1 <= px <= 64:
        raise BadInputError(f"pixels per cell must be between 1 and 64, got {px}")


def run_raster(noise: np.ndarray) -> np.ndarray:
    """Cell-level black mask of everything drawn as rectangles (noise and black squares).

    The X-corner blocks are left white here: their hourglasses are drawn as triangles.
    """
    black = target.cells(noise, supersample=1) < 0.5
    for bx, by in target.XCORNER_BLOCKS:
        black[by * target.BLOCK : (by + 1) * target.BLOCK, bx * target.BLOCK : (bx + 1) * target.BLOCK] = False
    return black


def black_runs(black: np.ndarray) -> list[tuple[int, int, int]]:
    """Runs of black cells along each row, as (row, first column, length)."""
    runs = []
    padded = np.zeros((black.shape[0], black.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = black
    for row, line in enumerate(padded):
        edges = np.flatnonzero(np.diff(line))  # starts and stops alternate
        runs.extend((row, int(a), int(b - a)) for a, b in zip(edges[0::2], edges[1::2]))
    return runs


def hourglass_triangles() -> list[tuple[tuple[int, int], ...]]:
    """The X-corner marks as triangles (three (x, y) cell corners each).

    Each hourglass is two black triangles with bases on the block's top and
    bottom edges and apexes at the block centre, the saddle point.
    """
    triangles = []
    for bx, by in target.XCORNER_BLOCKS:
        x0, y0 = bx * target.BLOCK, by * target.BLOCK
        x1, y1 = x0 + target.BLOCK, y0 + target.BLOCK
        centre = (x0 + target.BLOCK // 2, y0 + target.BLOCK // 2)
        triangles.append(((x0, y0), (x1, y0), centre))
        triangles.append(((x0, y1), (x1, y1), centre))
    return triangles


def _num(value: float) -> str:
    text = f"{value:.4f}".rstrip("0").rstrip(".")
    return text if text not in ("", "-0") else "0"


def _pdf_string(text: str) -> str:
    return "(" + text.replace("\\", "\\\\").replace("(", "\\(").replace(")", "\\)") + ")"


def pdf_bytes(noise: np.ndarray, size_mm: float = 700.0, caption: str = "") -> bytes:
    """The target as a one-page vector PDF.

    Parameters
    ----------
    noise : ndarray (256, 256)
        Noise values in {0, 1} (0 black).
    size_mm : float
        Side of the whole 320-cell target on paper.
    caption : str
        Text printed in the bottom margin.

    Returns
    -------
    bytes
        The PDF file. The page is the target plus a white margin of
        MARGIN_BLOCKS blocks on every side; the drawing is in cell units
        through one ``cm`` transform, so every coordinate is an integer.
    """
    _check_size(size_mm, 1 + 2 * MARGIN_BLOCKS / target.BLOCKS)
    cell = size_mm / target.SIZE / MM_PER_POINT  # points per cell
    margin = MARGIN_BLOCKS * target.BLOCK * cell
    page = target.SIZE * cell + 2 * margin
    # y down in cell units: PDF user space has y up from the bottom-left corner.
    ops = ["q", f"{cell:.6f} 0 0 {-cell:.6f} {_num(margin)} {_num(page - margin)} cm", "0 g"]
    ops += [f"{x} {y} {n} 1 re" for y, x, n in black_runs(run_raster(noise))]
    ops += [f"{a[0]} {a[1]} m {b[0]} {b[1]} l {c[0]} {c[1]} l h" for a, b, c in hourglass_triangles()]
    # One path, one nonzero fill: abutting pieces merge, so no hairline seams between runs.
    ops += ["f", "Q"]
    return pdf_document(ops, (page, page), caption, margin)


def printed_cell_mm(path: str | os.PathLike) -> float:
    """Side of one cell (mm) of a Bernoulli target PDF written by `pdf_bytes`, from its page size.

    The page is the 320-cell target plus MARGIN_BLOCKS blocks of white on each side, so the cell is the
    page width over 320 + 2 * 32 * MARGIN_BLOCKS cells. That is the cell as drawn: a print scaled to fit
    the paper is smaller, so measure the print and give ``cell_mm`` when it was scaled.
    """
    import re

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise BadInputError(f"{path}: cannot read the printed target ({exc.strerror or exc})") from None
    match = re.search(rb"/MediaBox \[0 0 ([0-9.]+) [0-9.]+\]", data)
    if not data.startswith(b"%PDF") or match is None:
        raise BadInputError(f"{path}: not a target PDF written by psfd target (no page size)")
    return float(match.group(1)) * MM_PER_POINT / (target.SIZE + 2 * MARGIN_BLOCKS * target.BLOCK)


def pdf_document(ops: list[str], page: tuple[float, float], caption: str = "", margin: float = 0.0) -> bytes:
    """A one-page PDF 1.4 file around a content stream.

    Parameters
    ----------
    ops : list of str
        Content-stream operators (the drawing).
    page : (float, float)
        Page width and height in points (the MediaBox).
    caption : str
        One line of Helvetica in the bottom margin of ``margin`` points, if given.

    Returns
    -------
    bytes
        The file: objects, a cross-reference table with their byte offsets, trailer.
    """
    ops = list(ops)
    if caption:
        font = min(9.0, 0.4 * margin, (page[0] - 2 * margin) / (0.55 * len(caption)))
        ops.append(f"BT /F1 {_num(font)} Tf {_num(margin)} {_num(0.35 * margin)} Td {_pdf_string(caption)} Tj ET")
    content = zlib.compress("\n".join(ops).encode("latin-1"), 9)
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        (
            f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {_num(page[0])} {_num(page[1])}] "
            "/Resources << /Font << /F1 5 0 R >> >> /Contents 4 0 R >>"
        ).encode(),
        f"<< /Length {len(content)} /Filter /FlateDecode >>\nstream\n".encode() + content + b"\nendstream",
        b"<< /Type /Font /Subtype /Type1 /BaseFont /Helvetica /Encoding /WinAnsiEncoding >>",
        b"<< /Producer (psfd) >>",
    ]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for number, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f"{number} 0 obj\n".encode() + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n".encode()
    out += b"0000000000 65535 f \n" + b"".join(f"{o:010d} 00000 n \n".encode() for o in offsets)
    out += f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R /Info 6 0 R >>\nstartxref\n{xref}\n%%EOF\n".encode()
    return bytes(out)


def png_bytes(noise: np.ndarray, px_per_cell: int = 8, margin_cells: int = MARGIN_BLOCKS * target.BLOCK) -> bytes:
    """The target as an 8-bit grey PNG, ``px_per_cell`` pixels per cell, with a white border.

    Noise cell (row r, column c) covers pixel rows [(m + 32 + r) p, (m + 33 + r) p)
    and the same columns for c, with m = margin_cells and p = px_per_cell.
    """
    _check_px(px_per_cell)
    raster = np.round(target.cells(noise, supersample=px_per_cell) * 255).astype(np.uint8)
    pad = margin_cells * px_per_cell
    raster = np.pad(raster, pad, constant_values=255)
    return _png(raster)


def _png(raster: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", raster)
    if not ok:  # OpenCV encodes any grey uint8 image; this guards a broken build
        raise BadInputError("cannot encode the target as PNG")
    return encoded.tobytes()


def noise_path(out: Path, origin: str) -> Path:
    """Where the noise realisation of a rendered target is kept, named after where the noise came from:
    ``x.pdf`` with ``seed7`` -> ``x.seed7.noise.pgm`` (``published`` for the published noise), so that
    targets of different noise written to one folder never share a noise file."""
    return out.with_name(f"{out.stem}.{origin}.noise.pgm")


def _refuse_overwrite(path: Path, data: bytes | None, force: bool, what: str) -> None:
    """Refuse to replace a file that holds something else (the same bytes again are harmless)."""
    if not path.exists() or force:
        return
    if data is not None and path.is_file() and path.read_bytes() == data:
        return
    raise BadInputError(f"{path}: exists and holds {what}; choose another --out or add --force to replace it")


def output_format(out: str | os.PathLike) -> tuple[Path, str]:
    """Check a target output path before rendering: (path, ".pdf" or ".png")."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".pdf", ".png"):
        raise BadInputError(f"{out}: unknown target format {out.suffix or '(none)'!r}; use .pdf or .png")
    if not out.parent.is_dir():
        raise BadInputError(f"{out.parent}: {'not a folder' if out.parent.exists() else 'no such folder'}")
    if not os.access(out.parent, os.W_OK):
        raise BadInputError(f"{out.parent}: not a writable folder")
    return out, suffix


def _write_atomic(out: Path, data: bytes, noise: np.ndarray | None = None, origin: str = "",
                  force: bool = False) -> None:
    """Write ``data`` to ``out`` (and ``noise`` beside it, `noise_path` of ``origin``) under temporary
    names, then rename.

    A failure leaves neither file behind, and never a target without its noise. A file that exists
    with other content is not replaced unless ``force``: a printed target's noise is never lost.
    """
    pgm = noise_path(out, origin)
    pgm_data = None if noise is None else target.noise_bytes(noise)
    _refuse_overwrite(out, data, force, "another target")
    if pgm_data is not None:
        _refuse_overwrite(pgm, pgm_data, force, "another noise pattern, the record of a printed target")
    tmp_target = out.with_name(f".{out.name}.part")
    tmp_noise = pgm.with_name(f".{pgm.stem}.part.pgm")
    existed = out.exists()
    try:
        tmp_target.write_bytes(data)
        if pgm_data is not None:
            tmp_noise.write_bytes(pgm_data)
        os.replace(tmp_target, out)
        if noise is not None:
            try:
                os.replace(tmp_noise, pgm)
            except OSError:
                if not existed:
                    out.unlink(missing_ok=True)
                raise
    except OSError as exc:
        raise BadInputError(f"{out}: cannot write ({exc.strerror or exc})") from None
    finally:
        tmp_target.unlink(missing_ok=True)
        tmp_noise.unlink(missing_ok=True)


def write_target(
    out: str | os.PathLike,
    noise: np.ndarray,
    *,
    origin: str = "published",
    size_mm: float = 700.0,
    caption: str = "",
    px_per_cell: int = 8,
    force: bool = False,
) -> tuple[Path, Path]:
    """Render the Bernoulli target to ``out`` (.pdf or .png) and save its noise beside it.

    ``origin`` names the noise (``seed7``, ``published``...) in the noise file's name (`noise_path`).
    Files that exist with other content are refused unless ``force``.

    Returns
    -------
    (target path, noise path)
    """
    out, suffix = output_format(out)
    data = pdf_bytes(noise, size_mm, caption) if suffix == ".pdf" else png_bytes(noise, px_per_cell)
    _write_atomic(out, data, noise, origin, force)
    return out, noise_path(out, origin)


# ---------------------------------------------------------------- the sharp-edge target

EDGE_CELLS_PER_SQUARE = 16  # PNG pixels per square = 16 x px_per_cell


def edge_pdf_bytes(size_mm: float, caption: str = "") -> bytes:
    """The sharp-edge target as a vector PDF: black squares, disks as four 90-degree Bezier arcs.

    ``size_mm`` is the side of the board; the page adds the white border of
    sharpedge.BORDER squares. Drawn in square units (y down) through one ``cm`` transform.
    """
    nx, ny = sharpedge.SQUARES
    _check_size(size_mm, 1 + 2 * sharpedge.BORDER / nx)
    square = size_mm / nx / MM_PER_POINT  # points per square
    margin = sharpedge.BORDER * square
    width, height = nx * square + 2 * margin, ny * square + 2 * margin
    r = sharpedge.DISK
    k = 0.5522847498 * r  # control-point distance of a cubic Bezier quarter circle

    def disk(cx: float, cy: float) -> str:
        pts = [(cx + r, cy), (cx + r, cy + k), (cx + k, cy + r), (cx, cy + r), (cx - k, cy + r), (cx - r, cy + k),
               (cx - r, cy), (cx - r, cy - k), (cx - k, cy - r), (cx, cy - r), (cx + k, cy - r), (cx + r, cy - k),
               (cx + r, cy)]
        path = [f"{_num(pts[0][0])} {_num(pts[0][1])} m"]
        path += [" ".join(f"{_num(x)} {_num(y)}" for x, y in pts[i : i + 3]) + " c" for i in range(1, 13, 3)]
        return " ".join(path) + " h"

    black = [(i, j) for j in range(ny) for i in range(nx) if (i + j) % 2 == 0]
    white = [(i, j) for j in range(ny) for i in range(nx) if (i + j) % 2 == 1]
    ops = ["q", f"{square:.6f} 0 0 {-square:.6f} {_num(margin)} {_num(height - margin)} cm", "0 g"]
    ops += [f"{i} {j} 1 1 re" for i, j in black] + [disk(i + 0.5, j + 0.5) for i, j in white] + ["f", "1 g"]
    ops += [disk(i + 0.5, j + 0.5) for i, j in black] + ["f", "Q"]
    return pdf_document(ops, (width, height), caption, margin)


def write_edge_target(out: str | os.PathLike, *, size_mm: float = 700.0, caption: str = "",
                      px_per_cell: int = 8, force: bool = False) -> Path:
    """Render the sharp-edge target to ``out`` (.pdf, or .png at 16 px_per_cell pixels per square);
    a file that exists with other content is refused unless ``force``."""
    out, suffix = output_format(out)
    if suffix == ".pdf":
        data = edge_pdf_bytes(size_mm, caption)
    else:
        _check_px(px_per_cell)
        data = _png((sharpedge.edge_target(px_per_square=EDGE_CELLS_PER_SQUARE * px_per_cell) * 255).astype(np.uint8))
    _write_atomic(out, data, force=force)
    return out
