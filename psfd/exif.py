"""What a RAW file says about the exposure that made it, read with exifread.

The settings a plan asks for are not always what the camera used: a lens
without electronic contacts, a mode dial left in Av, a body that rounds
1/3-stop values. The RAW's own EXIF is the record of what happened, so the
runner stores it beside the requested values and `check_settings` refuses a
frame whose f-number, exposure time or ISO is not the one asked for.

Tags are looked up in the EXIF IFD first and then in IFD0: TIFF/EP and DNG
allow the exposure tags in IFD0 (psfd's own DNG writer puts them there), and
camera files (CR2, NEF, ARW, Adobe DNG) keep them in the EXIF IFD. Formats
exifread does not parse (Canon CR3, Fujifilm RAF) give empty metadata: every
field is None and nothing can be checked, which `check_settings` reports.

This module imports nothing from psfd but the errors, so the daemon, the
drivers and the estimate commands can all use it.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path
from typing import Any

from psfd.errors import BadInputError, SettingsMismatch

log = logging.getLogger(__name__)

# Half of a 1/3 stop: cameras round f-numbers and exposure times to a nominal
# series (f/5.6 is 2^(5/2) = 5.657, 1/125 s is 2^-7 = 1/128), which is at most
# a few hundredths of a stop away, while the next setting is 1/3 stop away.
STOP_TOLERANCE = 1.0 / 6.0
FOCAL_TOLERANCE = 0.02  # relative: zoom lenses report focal lengths in coarse steps

# EXIF FocalPlaneResolutionUnit -> micrometres per unit (EXIF 2.3: 2 inch, 3 cm; 4 mm and
# 5 um are written by some bodies although only TIFF/EP defines them).
_UNIT_UM = {2: 25400.0, 3: 10000.0, 4: 1000.0, 5: 1.0}


@dataclass(frozen=True)
class FrameMetadata:
    """Exposure metadata of one frame (None where the file does not say)."""

    make: str | None = None
    model: str | None = None
    serial: str | None = None
    lens: str | None = None
    lens_serial: str | None = None
    focal_length_mm: float | None = None
    f_number: float | None = None
    exposure_s: float | None = None
    iso: float | None = None
    focus_distance_m: float | None = None
    width: int | None = None
    height: int | None = None
    pixel_pitch_um: float | None = None

    def as_dict(self) -> dict[str, Any]:
        """Plain dict, for the catalogue."""
        return dataclasses.asdict(self)


def read_metadata(path: str | Path) -> FrameMetadata:
    """Exposure metadata of a RAW (or TIFF/JPEG) file from its EXIF.

    Parameters
    ----------
    path : path-like
        The frame.

    Returns
    -------
    FrameMetadata
        Missing tags are None; a format exifread cannot parse gives all None.

    Raises
    ------
    BadInputError
        The file cannot be opened.
    """
    import exifread  # imported here: only needed when a frame is read

    path = Path(path)
    try:
        with open(path, "rb") as fh:
            tags = exifread.process_file(fh, details=True, extract_thumbnail=False)
    except OSError as exc:
        raise BadInputError(f"{path}: cannot read the frame's metadata ({exc.strerror or exc})") from None
    except Exception as exc:  # noqa: BLE001 - a malformed maker note must not lose the frame
        log.warning("%s: EXIF unreadable (%s: %s)", path, type(exc).__name__, exc)
        tags = {}
    if not tags:
        log.warning("%s: no EXIF metadata that exifread can read; settings cannot be checked", path)
    return _metadata(tags)


def _metadata(tags: dict) -> FrameMetadata:
    f_number = _number(tags, "FNumber")
    if f_number is None or f_number <= 0:
        av = _number(tags, "ApertureValue")  # APEX: Av = 2 log2(N)
        f_number = 2.0 ** (av / 2.0) if av is not None else None
    exposure = _number(tags, "ExposureTime")
    if exposure is None or exposure <= 0:
        tv = _number(tags, "ShutterSpeedValue")  # APEX: Tv = -log2(t)
        exposure = 2.0 ** (-tv) if tv is not None else None
    iso = _number(tags, "ISOSpeedRatings") or _number(tags, "PhotographicSensitivity")
    focal = _number(tags, "FocalLength")
    distance = _number(tags, "SubjectDistance")  # metres; 0 unknown, 0xFFFFFFFF infinity: both left out
    return FrameMetadata(
        make=_text(tags, "Make"),
        model=_text(tags, "Model"),
        serial=_text(tags, "BodySerialNumber") or _text(tags, "SerialNumber", ("MakerNote",))
        or _text(tags, "Tag 0xC62F", ("Image",)),  # DNG CameraSerialNumber, unknown to exifread
        lens=_text(tags, "LensModel") or _text(tags, "LensModel", ("MakerNote",)),
        lens_serial=_text(tags, "LensSerialNumber"),  # EXIF 2.3: tells two copies of one lens model apart
        focal_length_mm=focal if focal else None,
        f_number=f_number if f_number else None,
        exposure_s=exposure if exposure else None,
        iso=iso if iso else None,
        focus_distance_m=distance if distance and distance < 4e9 else None,
        width=_int(tags, "ImageWidth", ("Image",)) or _int(tags, "ExifImageWidth"),
        height=_int(tags, "ImageLength", ("Image",)) or _int(tags, "ExifImageLength"),
        pixel_pitch_um=_pitch(tags),
    )


def _pitch(tags: dict) -> float | None:
    """Photosite pitch from FocalPlaneXResolution (pixels per unit of FocalPlaneResolutionUnit).

    The tag gives the sampling of the image plane directly, so no table of
    sensor sizes per model is needed; a camera that omits it gives None (the
    plan's ``pitch_um`` then stands).
    """
    resolution = _number(tags, "FocalPlaneXResolution")
    unit = _int(tags, "FocalPlaneResolutionUnit")
    if not resolution or unit not in _UNIT_UM:
        return None
    return _UNIT_UM[unit] / resolution


def _find(tags: dict, name: str, ifds: tuple[str, ...] = ("EXIF", "Image")) -> Any:
    for ifd in ifds:
        tag = tags.get(f"{ifd} {name}")
        if tag is not None:
            return tag
    return None


def _number(tags: dict, name: str) -> float | None:
    tag = _find(tags, name)
    values = getattr(tag, "values", None)
    if not values or isinstance(values, (str, bytes)):
        return None
    value = values[0]
    try:
        if hasattr(value, "den") and value.den == 0:
            return None
        return float(Fraction(value.num, value.den)) if hasattr(value, "den") else float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None


def _int(tags: dict, name: str, ifds: tuple[str, ...] = ("EXIF", "Image")) -> int | None:
    tag = _find(tags, name, ifds)
    values = getattr(tag, "values", None)
    if not values or isinstance(values, (str, bytes)):
        return None
    try:
        return int(values[0])
    except (TypeError, ValueError):
        return None


def _text(tags: dict, name: str, ifds: tuple[str, ...] = ("EXIF", "Image")) -> str | None:
    tag = _find(tags, name, ifds)
    if tag is None:
        return None
    text = str(tag.printable if hasattr(tag, "printable") else tag).strip().strip("\x00").strip()
    return text or None


# ---------------------------------------------------------------------- requested vs actual


def exposure_seconds(text: str | float | None) -> float | None:
    """Seconds of an exposure time as cameras and plans write it.

    ``1/125``, ``0.0050s`` (libgphoto2's generic PTP), ``30``, ``30"`` and
    ``1"3`` (1.3 s, Sony), ``15/10`` (Nikon), ``2.5``. Returns ``math.inf`` for
    bulb or time exposures (the length is set by whoever holds the shutter) and
    None for text that is no exposure time (``auto``).
    """
    if text is None:
        return None
    if isinstance(text, (int, float)):
        return float(text) if text > 0 else None
    value = str(text).strip().lower()
    if value in ("bulb", "b", "time", "t", "bulb/time"):
        return math.inf
    value = re.sub(r'^(\d+)"(\d+)$', r"\1.\2", value)  # Sony 1"3 = 1.3 s
    value = value.rstrip('s"').strip()
    match = re.fullmatch(r"(\d+(?:\.\d+)?)\s*/\s*(\d+(?:\.\d+)?)", value)
    try:
        seconds = float(match.group(1)) / float(match.group(2)) if match else float(value)
    except (ValueError, ZeroDivisionError):
        return None
    return seconds if seconds > 0 and math.isfinite(seconds) else None


def _stops(actual: float, requested: float) -> float:
    """Distance in stops between two f-numbers or two exposure factors of the same kind."""
    return abs(math.log2(actual / requested))


def check_settings(
    meta: FrameMetadata,
    *,
    aperture: float | str | None = None,
    shutterspeed: float | str | None = None,
    iso: float | str | None = None,
    focal_length_mm: float | None = None,
    frame: str = "frame",
) -> list[str]:
    """Compare what was asked with what the RAW says the camera did.

    Parameters
    ----------
    meta : FrameMetadata
        From `read_metadata`.
    aperture : f-number asked (``5.6``, ``"f/5.6"``), or None to skip.
    shutterspeed : exposure time asked (``"1/125"``, seconds), or None; bulb is not checked.
    iso : ISO asked, or None (``auto`` is not checked).
    focal_length_mm : focal length the plan assumes, or None.
    frame : name of the frame for the message.

    Returns
    -------
    list of str
        Settings that were asked but the file does not record (not verified).

    Raises
    ------
    SettingsMismatch
        One line naming every setting that differs: an f-number or exposure
        time more than 1/6 stop away (rounding to the camera's nominal values
        passes, the next 1/3-stop setting does not), another ISO (same rule),
        or a focal length more than 2 % away.
    """
    problems: list[str] = []
    unverified: list[str] = []
    if aperture is not None:
        wanted = float(str(aperture).lower().removeprefix("f/").removeprefix("f"))
        if meta.f_number is None:
            unverified.append("aperture")
        elif _stops(meta.f_number, wanted) * 2.0 > STOP_TOLERANCE:  # f-number: 1 stop = factor sqrt(2)
            problems.append(f"f/{_g(meta.f_number)} instead of f/{_g(wanted)}")
    wanted_t = exposure_seconds(shutterspeed)
    if wanted_t is not None and math.isfinite(wanted_t):
        if meta.exposure_s is None:
            unverified.append("shutterspeed")
        elif _stops(meta.exposure_s, wanted_t) > STOP_TOLERANCE:
            problems.append(f"exposure {_exposure_text(meta.exposure_s)} instead of {_exposure_text(wanted_t)}")
    wanted_iso = _float_or_none(iso)
    if wanted_iso is not None:
        if meta.iso is None:
            unverified.append("iso")
        elif _stops(meta.iso, wanted_iso) > STOP_TOLERANCE:
            problems.append(f"ISO {_g(meta.iso)} instead of ISO {_g(wanted_iso)}")
    if focal_length_mm is not None:
        if meta.focal_length_mm is None:
            unverified.append("focal_length_mm")
        elif abs(meta.focal_length_mm / float(focal_length_mm) - 1.0) > FOCAL_TOLERANCE:
            problems.append(f"focal length {_g(meta.focal_length_mm)} mm instead of {_g(focal_length_mm)} mm")
    if problems:
        raise SettingsMismatch(
            f"{frame}: the camera used {', '.join(problems)} (read from the RAW's EXIF); "
            "check the mode dial (M), the lens and the plan's settings")
    return unverified


def _float_or_none(value: float | str | None) -> float | None:
    try:
        return float(value) if value is not None else None
    except ValueError:
        return None  # "auto" and the like: nothing to compare


def _g(value: float) -> str:
    return f"{value:.3g}"


def _exposure_text(seconds: float) -> str:
    if seconds < 1.0:
        return f"1/{1.0 / seconds:.4g} s"
    return f"{seconds:.4g} s"
