"""Reading frames: RAW files split into Bayer planes, or single-channel images.

Every estimator works on one channel plane at a time, never demosaiced
(Delbracio et al., IJCV 2012, sec. 5: "each of the four CFA channels is
processed separately"). A plane keeps its black level subtracted, its white
level, and a mask of saturated photosites, because clipping breaks the linear
model v = S_s(u_D * h) + n that every method relies on.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
import struct
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from psfd.errors import BadInputError
from psfd.vocabulary import CHANNELS, MONO, check_image_size

__all__ = ["CHANNELS", "MONO", "RAW_SUFFIXES", "Frame", "check_image", "image_size", "load_frame", "load_frames",
           "read_image", "write_dng"]

RAW_SUFFIXES = {".dng", ".cr2", ".cr3", ".nef", ".arw", ".orf", ".rw2", ".raf", ".pef", ".srw", ".raw"}
IMAGE_SUFFIXES = {".pgm", ".pnm", ".png", ".tif", ".tiff"}


@dataclass
class Frame:
    """One channel plane of a photograph.

    Attributes
    ----------
    data : ndarray of float64
        Linear values, black level subtracted.
    channel : str
        ``r``, ``g1``, ``g2``, ``b`` for a RAW plane, ``mono`` for a single-channel image.
    white : float
        Saturation level in the units of ``data``.
    saturated : ndarray of bool
        Photosites at or above the white level.
    source : str
        Path of the file the plane came from.
    offset : tuple of int
        (row, col) of the plane's first photosite on the full sensor.
    sensor_shape : tuple of int
        Shape of the full sensor (for a single-channel image, its own shape).
    from_mosaic : bool
        True for a plane split from a RAW Bayer mosaic, False for a single-channel image.
    """

    data: np.ndarray
    channel: str
    white: float
    saturated: np.ndarray
    source: str
    offset: tuple[int, int] = (0, 0)
    sensor_shape: tuple[int, int] = field(default=(0, 0))
    from_mosaic: bool = False

    @property
    def shape(self) -> tuple[int, int]:
        return self.data.shape  # type: ignore[return-value]


def load_frames(path: str | os.PathLike, channel: str = "all",
                built: Callable[[Frame], None] | None = None) -> list[Frame]:
    """Load the requested channel planes of a RAW file or single-channel image.

    Parameters
    ----------
    path : path-like
        A RAW file that LibRaw reads (DNG, CR2, NEF, ARW, ...) or an 8/16-bit
        single-channel PGM, PNG or TIFF.
    channel : str
        ``all``, or one of ``r``, ``g1``, ``g2``, ``b`` of a RAW file, or ``mono``, the one
        plane of a single-channel image (which ``all`` gives too).
    built : callable, optional
        Called with each requested plane as soon as it is built, ``g1`` first (the plane a target is
        searched on), before its size is checked: work on it can start on another thread while the
        file's other planes are built. It must not modify the plane.

    Returns
    -------
    list of Frame

    Raises
    ------
    BadInputError
        Missing, unreadable, truncated or colour (non-RAW) files, an unknown channel, or a
        channel the file does not have (a Bayer channel of a single-channel image).
    """
    path = Path(path)
    if channel != "all" and channel not in CHANNELS and channel != MONO:
        raise BadInputError(f"unknown channel {channel!r}: use r, g1, g2, b or all")
    if path.is_dir():
        raise BadInputError(f"{path}: is a folder, not a frame")
    if not path.is_file():
        raise BadInputError(f"{path}: no such file")
    if path.suffix.lower() in IMAGE_SUFFIXES:
        # never relabelled: a Bayer name would make its pitch twice the photosite's (mtf.channel_pitch_mm)
        if channel not in ("all", MONO):
            raise BadInputError(f"{path}: has no {channel} channel (a single-channel image: its one plane is mono)")
        frame = _load_single_channel(path)
        if built is not None:
            built(frame)
        return _large_enough(path, [frame])
    planes = _load_raw(path, None if channel == "all" else channel, built)
    if channel == "all":
        return _large_enough(path, [planes[c] for c in CHANNELS if c in planes])
    if channel not in planes:
        raise BadInputError(f"{path}: has no {channel} channel (has {', '.join(planes)})")
    return _large_enough(path, [planes[channel]])


# channel pixels a plane needs on each side for any estimate (the target detector's smallest image)
MIN_SIDE = 16


def _large_enough(path: Path, frames: list[Frame]) -> list[Frame]:
    """``frames``, or the one bad-input error of a file too small for any method, naming it."""
    for frame in frames:
        rows, cols = frame.shape
        if min(rows, cols) < MIN_SIDE:
            plane = "" if frame.channel == MONO else f" ({frame.channel} plane)"
            raise BadInputError(f"{path}: {cols}x{rows} pixels{plane}, too small for any estimate (at least "
                                f"{MIN_SIDE}x{MIN_SIDE})")
    return frames


def load_frame(path: str | os.PathLike, channel: str | None = None) -> Frame:
    """Load one channel plane; see `load_frames`. ``channel`` None: a RAW file's ``g1``, a single-channel
    image's own plane (``mono``)."""
    if channel is None:
        channel = MONO if Path(path).suffix.lower() in IMAGE_SUFFIXES else "g1"
    return load_frames(path, channel)[0]


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence file descriptor 2 while LibRaw reads: it prints its own complaint about a
    damaged file ("Unexpected end of file") before raising, and errors must stay one line."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _load_raw(path: Path, wanted: str | None = None,
              built: Callable[[Frame], None] | None = None) -> dict[str, Frame]:
    """The Bayer planes of a RAW file, or only the ``wanted`` one (the others are named, not built); ``built``
    as `load_frames` says."""
    import rawpy  # imported here: LibRaw is only needed for RAW input

    with rawpy.RawPy() as raw:
        try:
            with _quiet_stderr():
                raw.open_file(str(path))  # reads the header only: the size is checked before the data is unpacked
                check_image_size(raw.sizes.raw_width, raw.sizes.raw_height, str(path))
                _check_camera_raw(path)
                raw.unpack()
                if raw.raw_type != rawpy.RawType.Flat:  # read once unpacked (rawpy would unpack to tell)
                    raise BadInputError(f"{path}: a linear (demosaiced) RAW file, {raw.num_colors} colours per "
                                        "pixel: psfd reads the photosites of a Bayer mosaic, not demosaiced images")
                # the photosites as decoded (uint16), LibRaw's own buffer, not copied: the requested planes
                # are converted from it before it is freed, and only the 2 x 2 colour pattern is read
                # (raw_colors_visible would build a second full-size array)
                mosaic = raw.raw_image_visible
                pattern = raw.raw_pattern
                top, left = raw.sizes.top_margin, raw.sizes.left_margin
                colors = np.array([[raw.raw_color(top + dy, left + dx) for dx in (0, 1)] for dy in (0, 1)])
                desc = raw.color_desc.decode("ascii", "replace")
                blacks = list(raw.black_level_per_channel)
                white = float(raw.white_level)
        except (rawpy.LibRawError, OSError, ValueError) as exc:
            if path.suffix.lower() not in RAW_SUFFIXES:
                raise BadInputError(f"{path}: not an image psfd reads (a camera RAW file, PGM, PNG or TIFF)") from None
            raise BadInputError(f"{path}: not a readable RAW file ({_libraw_reason(exc)})") from None
        if mosaic.ndim != 2 or min(mosaic.shape) < 4:
            raise BadInputError(f"{path}: not a Bayer mosaic")
        if pattern is None or pattern.shape != (2, 2):
            # a 6 x 6 X-Trans sensor (Fujifilm): its 2 x 2 sub-grids each mix red, green and blue photosites,
            # so the planes would not be colour channels at all
            shape = "no" if pattern is None else "x".join(str(n) for n in pattern.shape)
            raise BadInputError(f"{path}: a {shape} colour filter pattern, not a 2 x 2 Bayer mosaic (psfd reads "
                                "Bayer sensors only)")
        return _bayer_planes(path, mosaic, colors, desc, blacks, white, wanted, built)


def _check_camera_raw(path: Path) -> None:
    """Refuse a plain TIFF image under a RAW file's name (a grey photograph saved as ``.dng``).

    LibRaw reads such a file as the mosaic of an unknown camera with a colour pattern it guesses, so its
    planes would be no colour channels. A camera's TIFF-based RAW file names its maker (TIFF/EP: Make) and a
    DNG carries DNGVersion (DNG 1.4, sec. "DNGVersion": required); a file that has neither is not one.
    """
    with open(path, "rb") as fh:
        if fh.read(4) not in TIFF_MAGIC:
            return  # not TIFF-based (CR3, RAF, ...): LibRaw knows the camera from the format itself
    page = _first_tiff_page(path)
    make, dng_version = 271, 50706
    if page is not None and not {make, dng_version} & page[2]:
        raise BadInputError(f"{path}: a TIFF image without a camera's make or DNG tags, not a camera RAW file "
                            "(a single-channel image is read as such when named .tif)")


def _bayer_planes(path: Path, mosaic: np.ndarray, colors: np.ndarray, desc: str, blacks: list, white: float,
                  wanted: str | None, built: Callable[[Frame], None] | None = None) -> dict[str, Frame]:
    """The named planes of a mosaic (``colors``: the 2 x 2 indices into ``desc``), only ``wanted`` built,
    ``g1`` first and each passed to ``built`` (`load_frames`) once made; the names in raster order.

    The greens are named as LibRaw numbers them: index 1 (``g1``) is the green on the rows of red, index 3
    (``g2``) the one on the rows of blue, whatever the pattern's phase, so ``g1`` is the same photosites of
    every Bayer sensor and of every crop of one. A file whose two greens share one index has them in raster
    order.
    """
    names = _plane_names(path, colors, desc)
    planes: dict[str, Frame] = dict.fromkeys(name for name, *_ in names)  # type: ignore[arg-type]  # raster order
    for name, dy, dx, index in sorted(names, key=lambda plane: plane[0] != "g1"):
        if wanted is not None and name != wanted:
            continue
        plane = mosaic[dy::2, dx::2]  # a view: the two arrays below are the plane's only copies
        black = float(blacks[index]) if index < len(blacks) else 0.0
        planes[name] = Frame(
            data=plane - black,
            channel=name,
            white=white - black,
            saturated=plane >= white,
            source=str(path),
            offset=(dy, dx),
            sensor_shape=mosaic.shape,
            from_mosaic=True,
        )
        if built is not None:
            built(planes[name])
    return planes


def _plane_names(path: Path, colors: np.ndarray, desc: str) -> list[tuple[str, int, int, int]]:
    """(name, row, column, index into ``desc``) of the four positions of the 2 x 2 pattern, in raster order."""
    names = []
    greens = 0
    by_index = sorted(int(i) for i in colors.ravel() if int(i) < len(desc) and desc[int(i)].lower() == "g") == [1, 3]
    for dy in (0, 1):
        for dx in (0, 1):
            index = int(colors[dy, dx])
            letter = desc[index].lower() if index < len(desc) else "?"
            if letter == "g":
                greens += 1
                name = ("g1" if index == 1 else "g2") if by_index else f"g{greens}"
            elif letter in ("r", "b"):
                name = letter
            else:
                raise BadInputError(f"{path}: unsupported colour filter {desc!r}")
            names.append((name, dy, dx, index))
    return names


def _libraw_reason(exc: Exception) -> str:
    """LibRaw's error class in words."""
    name = type(exc).__name__
    if "Unsupported" in name:
        return "a format LibRaw does not know"
    if "IOError" in name or "DataError" in name:
        return "truncated or damaged"
    return "LibRaw could not decode it"


def image_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(width, height) an image file's header announces, read without decoding it.

    PNG (the IHDR chunk), PNM/PGM (the text header) and TIFF (its first IFD, through
    tifffile); None for another format or a header that does not parse, which the
    decoder then judges (OpenCV applies OPENCV_IO_MAX_IMAGE_PIXELS, set by the command line).
    """
    with open(path, "rb") as fh:
        head = fh.read(512)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":  # PNG spec, sec. 11.2.2
        return struct.unpack(">II", head[16:24])
    if re.match(rb"P[1-6]\s", head):  # Netpbm: magic, width, height (and maxval), comments start with #
        fields = re.sub(rb"#[^\n]*", b" ", head).split()
        if len(fields) >= 3 and fields[1].isdigit() and fields[2].isdigit():
            return int(fields[1]), int(fields[2])
        return None
    if head[:4] in TIFF_MAGIC:
        page = _first_tiff_page(path)
        return None if page is None else (page[0], page[1])
    return None


TIFF_MAGIC = (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+")  # classic and BigTIFF, both byte orders


def _first_tiff_page(path: str | os.PathLike) -> tuple[int, int, set[int]] | None:
    """(width, height, tag codes) of a TIFF file's first image, or None when tifffile cannot parse it."""
    import logging

    import tifffile

    log = logging.getLogger("tifffile")
    level = log.level
    log.setLevel(logging.CRITICAL)  # its complaints ("contains no pages") would add lines to the one-line error
    try:
        with tifffile.TiffFile(path) as tif:
            page = tif.pages[0]
            return int(page.imagewidth), int(page.imagelength), set(page.tags.keys())
    except Exception:  # noqa: BLE001 - a TIFF tifffile cannot parse: the decoder says why
        return None
    finally:
        log.setLevel(level)


def check_image(path: str | os.PathLike) -> None:
    """Refuse an image whose header announces more pixels than psfd reads (`vocabulary.MAX_PIXELS`)."""
    size = image_size(path)
    if size is not None:
        check_image_size(size[0], size[1], str(path))


def read_image(path: str | os.PathLike) -> np.ndarray | None:
    """``cv2.imread(path, IMREAD_UNCHANGED)`` after `check_image`; None when OpenCV cannot decode it."""
    check_image(path)
    try:
        with _quiet_stderr():  # libpng prints "libpng error: Read Error" on a truncated PNG before failing
            return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    except cv2.error:  # OpenCV's own size limit on a header `image_size` does not parse
        raise BadInputError(f"{path}: the image is larger than psfd reads") from None


def _load_single_channel(path: Path) -> Frame:
    image = read_image(path)
    if image is None:
        raise BadInputError(f"{path}: not a readable image")
    if image.ndim != 2:
        raise BadInputError(f"{path}: has {image.shape[2]} colour channels; give one channel or a RAW file")
    if image.dtype not in (np.uint8, np.uint16):
        raise BadInputError(f"{path}: unsupported sample type {image.dtype}; use 8 or 16 bit")
    # a PGM's maxval is its white, 8-bit (up to 255) or 16-bit (4095 or 16383 for a camera's 12 or 14 bits)
    white = float(_pnm_maxval(path) or np.iinfo(image.dtype).max)
    data = image.astype(np.float64)
    return Frame(
        data=data,
        channel=MONO,
        white=white,
        saturated=data >= white,
        source=str(path),
        offset=(0, 0),
        sensor_shape=data.shape,
    )


def _pnm_maxval(path: Path) -> int | None:
    """The declared maximum of a PGM/PNM header (16-bit files often use 4095 or 16383)."""
    if path.suffix.lower() not in (".pgm", ".pnm"):
        return None
    with open(path, "rb") as fh:
        head = fh.read(256)
    tokens: list[bytes] = []
    for line in head.split(b"\n"):
        tokens.extend(line.split(b"#", 1)[0].split())
        if len(tokens) >= 4:
            break
    try:
        return int(tokens[3])
    except (IndexError, ValueError):
        return None


def write_dng(
    path: str | os.PathLike,
    mosaic: np.ndarray,
    *,
    pattern: str = "RGGB",
    black: int = 0,
    white: int = 65535,
    model: str = "psfd simulated camera",
    exif: dict | None = None,
) -> None:
    """Write a Bayer mosaic as a minimal uncompressed DNG that LibRaw decodes.

    Parameters
    ----------
    path : path-like
        Output file; written to a temporary name and renamed, so a reader never
        sees a partial file.
    mosaic : ndarray of uint16
        The raw photosite values, black level included.
    pattern : str
        The CFA pattern in raster order, e.g. ``RGGB``: 4 letters for a 2x2 Bayer pattern, n^2 for n x n
        (36 for a 6x6 X-Trans sensor).
    black, white : int
        Black and white levels of the raw values.
    model : str
        UniqueCameraModel tag.
    exif : dict, optional
        Exposure metadata written as TIFF/EP tags in IFD0 (where DNG allows them),
        keys as `psfd.exif.FrameMetadata`: ``make``, ``model``, ``serial``, ``lens``,
        ``focal_length_mm``, ``f_number``, ``exposure_s``, ``iso``, ``focus_distance_m``,
        ``pixel_pitch_um``; None values and absent keys are left out.
    """
    import tifffile

    mosaic = np.ascontiguousarray(mosaic, dtype=np.uint16)
    cfa_codes = {"R": 0, "G": 1, "B": 2}
    side = math.isqrt(len(pattern))
    if side < 2 or side * side != len(pattern):
        raise ValueError(f"CFA pattern {pattern!r}: n x n letters, n >= 2")
    identity = [v for i in range(9) for v in ((1, 1) if i % 4 == 0 else (0, 1))]
    tags = [
        (50706, "B", 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, "B", 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, "s", 0, model, True),  # UniqueCameraModel
        (33421, "H", 2, (side, side), True),  # CFARepeatPatternDim
        (33422, "B", side * side, tuple(cfa_codes[c] for c in pattern.upper()), True),  # CFAPattern
        (50714, "H", 1, int(black), True),  # BlackLevel
        (50717, "H", 1, int(white), True),  # WhiteLevel
        (50721, "2i", 9, identity, True),  # ColorMatrix1 (identity: values stay raw)
    ] + _exif_tags(exif or {})
    path = Path(path)
    tmp = path.with_name(f".{path.name}.part")
    try:
        tifffile.imwrite(tmp, mosaic, photometric=32803, compression=None, extratags=tags, subfiletype=0)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _exif_tags(exif: dict) -> list[tuple]:
    """tifffile extratags for the exposure metadata of `write_dng` (tag numbers of EXIF 2.3 / DNG 1.4)."""

    def rational(value: float) -> tuple[int, int]:
        f = Fraction(float(value)).limit_denominator(100_000)
        return f.numerator, f.denominator

    tags: list[tuple] = []
    # Make, Model, BodySerialNumber, LensModel, LensSerialNumber
    text = {"make": 271, "model": 272, "serial": 42033, "lens": 42036, "lens_serial": 42037}
    for key, code in text.items():
        if exif.get(key):
            tags.append((code, "s", 0, str(exif[key]), True))
    if exif.get("serial"):
        tags.append((50735, "s", 0, str(exif["serial"]), True))  # DNG CameraSerialNumber
    rationals = {"exposure_s": 33434, "f_number": 33437, "focus_distance_m": 37382, "focal_length_mm": 37386}
    for key, code in rationals.items():
        if exif.get(key):  # ExposureTime, FNumber, SubjectDistance, FocalLength
            tags.append((code, "2I", 1, rational(exif[key]), True))
    if exif.get("iso"):
        tags.append((34855, "H", 1, int(round(float(exif["iso"]))), True))  # ISOSpeedRatings
    if exif.get("pixel_pitch_um"):
        per_cm = rational(10_000.0 / float(exif["pixel_pitch_um"]))  # photosites per centimetre
        tags += [(41486, "2I", 1, per_cm, True), (41487, "2I", 1, per_cm, True),  # FocalPlaneX/YResolution
                 (41488, "H", 1, 3, True)]  # FocalPlaneResolutionUnit: centimetre
    return tags
