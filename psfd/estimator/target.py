"""The published Bernoulli calibration target: layout and cell values.

Layout in pattern-cell units (one cell = one noise value; cell (i, j) covers
[i, i+1) x [j, j+1), x to the right, y down). A 10 x 10 grid of 32-cell blocks;
the central 8 x 8 blocks hold the 256 x 256 Bernoulli(0.5) noise and the ring
of 36 border blocks holds 12 X-corners, 12 black and 12 white flat squares
(Delbracio et al., IJCV 2012, sec. 3.3, Fig. 5; Delbracio PhD thesis 2013, App. A.1).
"""

from __future__ import annotations

import os
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from psfd.errors import BadInputError
from psfd.estimator.raw import read_image

if TYPE_CHECKING:  # annotations only: numpy.typing is not imported at run time
    import numpy.typing as npt

__all__ = [
    "BLACK_BLOCKS", "BLOCK", "BLOCKS", "NOISE", "NOISE_START", "NOISE_STOP", "ORIENTATION_CORNER", "SIZE",
    "WHITE_BLOCKS", "XCORNER_BLOCKS", "block_centre", "cells", "default_noise", "load_noise", "noise_bytes",
    "save_noise", "seeded_noise", "xcorner_points"
]

BLOCK = 32  # cells per block side
BLOCKS = 10  # blocks per target side
SIZE = BLOCK * BLOCKS  # 320 cells
NOISE = 256  # noise cells per side
NOISE_START = BLOCK  # first noise cell (32)
NOISE_STOP = NOISE_START + NOISE  # one past the last noise cell (288)

# Block indices (bx, by). The order of XCORNER_BLOCKS is the order of detected corners.
XCORNER_BLOCKS = ((9, 9), (9, 6), (9, 3), (9, 0), (6, 0), (3, 0), (0, 0), (0, 3), (0, 6), (0, 9), (3, 9), (6, 9))
BLACK_BLOCKS = ((9, 8), (9, 5), (9, 2), (8, 0), (5, 0), (2, 0), (0, 2), (0, 5), (0, 8), (2, 9), (5, 9), (8, 9))
WHITE_BLOCKS = ((9, 7), (9, 4), (9, 1), (7, 0), (4, 0), (1, 0), (0, 1), (0, 4), (0, 7), (1, 9), (4, 9), (7, 9))
# (9, 9) is the only X-corner flanked by two black squares: it fixes the orientation.
ORIENTATION_CORNER = (9, 9)


def block_centre(block: tuple[int, int]) -> tuple[float, float]:
    """Centre (x, y) of a block in cell coordinates."""
    bx, by = block
    return (BLOCK * bx + BLOCK / 2, BLOCK * by + BLOCK / 2)


def xcorner_points() -> np.ndarray:
    """(12, 2) array of the X-corner saddle points (x, y) in cell coordinates."""
    return np.array([block_centre(b) for b in XCORNER_BLOCKS], dtype=np.float64)


def default_noise() -> np.ndarray:
    """The published 256 x 256 noise (0 black, 1 white), shipped as ``pattern_noise.pgm``."""
    with resources.as_file(resources.files("psfd") / "data" / "pattern_noise.pgm") as path:
        return load_noise(path)


def load_noise(path: str | os.PathLike) -> np.ndarray:
    """Read a 256 x 256 noise realisation from an image (dark = 0, light = 1).

    An image of one value is refused: it holds no noise, and neither a target printed from it nor a
    photograph estimated with it could give a PSF.
    """
    if Path(path).is_dir():
        raise BadInputError(f"{path}: is a folder, not a noise pattern image")
    if not Path(path).is_file():  # otherwise imread's None reads as a bad image
        raise BadInputError(f"{path}: no such file")
    image = read_image(path)  # its header's size checked before it is decoded
    if image is None or image.ndim != 2:
        raise BadInputError(f"{path}: not a single-channel noise pattern image")
    if image.shape != (NOISE, NOISE):
        raise BadInputError(f"{path}: noise pattern must be {NOISE}x{NOISE} cells, got {image.shape[1]}x{image.shape[0]}")
    if image.min() == image.max():
        colour = "black" if image.max() == 0 else "white" if image.max() == np.iinfo(image.dtype).max else "one grey"
        raise BadInputError(f"{path}: no noise pattern, every cell is {colour}")
    return (image.astype(np.float64) > image.max() / 2).astype(np.float64)


def seeded_noise(seed: int) -> np.ndarray:
    """A new 256 x 256 Bernoulli(0.5) realisation, reproducible from ``seed``."""
    rng = np.random.default_rng(seed)
    return rng.integers(0, 2, size=(NOISE, NOISE)).astype(np.float64)


def noise_bytes(noise: np.ndarray) -> bytes:
    """A noise realisation as an 8-bit binary PGM (0 black, 255 white), the published format."""
    ok, encoded = cv2.imencode(".pgm", (np.asarray(noise) > 0.5).astype(np.uint8) * 255)
    if not ok:  # OpenCV encodes any grey uint8 image; this guards a broken build
        raise BadInputError("cannot encode the noise pattern as PGM")
    return encoded.tobytes()


def save_noise(noise: np.ndarray, path: str | Path) -> None:
    """Write a noise realisation as `noise_bytes`; a failed write is the OSError that says why (a full disk)."""
    Path(path).write_bytes(noise_bytes(noise))


def cells(noise: np.ndarray | None = None, supersample: int = 1, dtype: npt.DTypeLike = np.float64) -> np.ndarray:
    """Reflectance of the whole target on a grid of ``supersample`` pixels per cell.

    Parameters
    ----------
    noise : ndarray (256, 256), optional
        Noise values in {0, 1}; the published realisation by default.
    supersample : int
        Pixels per cell side. The hourglass X-corner marks are exact only at
        the cell level when supersample is 1 (their edges are diagonal), so
        renderers use 8 or more.
    dtype : numpy dtype
        Of the result: float32 for a caller that works in float32 (the values,
        0 and 1, are the same in either), without a float64 raster and its copy.

    Returns
    -------
    ndarray of ``dtype``, (320 * supersample, 320 * supersample), 0 black and 1 white.
    """
    noise = default_noise() if noise is None else np.asarray(noise, dtype=np.float64)
    n = int(supersample)
    out = np.ones((SIZE * n, SIZE * n), dtype=dtype)
    # each cell n x n times (np.kron(noise, ones((n, n))) without its products)
    out[NOISE_START * n : NOISE_STOP * n, NOISE_START * n : NOISE_STOP * n] = noise.repeat(n, axis=0).repeat(n, axis=1)
    for bx, by in BLACK_BLOCKS:
        out[by * BLOCK * n : (by + 1) * BLOCK * n, bx * BLOCK * n : (bx + 1) * BLOCK * n] = 0.0
    # Hourglass: black triangles on the top and bottom edges, apexes at the block centre.
    side = BLOCK * n
    v, u = (np.mgrid[0:side, 0:side] + 0.5) / side - 0.5  # block-local, centre at 0
    hourglass = np.abs(u) < np.abs(v)
    for bx, by in XCORNER_BLOCKS:
        block = out[by * side : (by + 1) * side, bx * side : (bx + 1) * side]
        block[hourglass] = 0.0
    return out
