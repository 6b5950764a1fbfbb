"""Frame metadata read back from real files with exifread, and requested-vs-actual checks.

The files are the DNGs psfd writes (`raw.write_dng`, the simulated camera),
TIFF/DNG files written with tifffile carrying only some tags (APEX values,
inch focal-plane units), a DNG without any exposure tag, and a real
photograph without EXIF (the shipped PGM).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import tifffile

from psfd import exif
from psfd.errors import BadInputError, CameraError, SettingsMismatch
from psfd.estimator import raw

MOSAIC = np.full((64, 96), 1000, dtype=np.uint16)
CAMERA = dict(make="psfd", model="psfd simulated camera", serial="SIM-3", lens="simulated 50 mm",
              lens_serial="0000c1234", focal_length_mm=50.0, f_number=5.6, exposure_s=1 / 125, iso=200, pixel_pitch_um=4.3,
              focus_distance_m=1.25)


def _dng(path, **tags):
    raw.write_dng(path, MOSAIC, black=512, white=4095, exif=tags or None)
    return path


def test_psfd_dng_carries_its_exposure_metadata(tmp_path):
    meta = exif.read_metadata(_dng(tmp_path / "a.dng", **CAMERA))
    assert meta == exif.FrameMetadata(
        make="psfd", model="psfd simulated camera", serial="SIM-3", lens="simulated 50 mm", lens_serial="0000c1234",
        focal_length_mm=50.0,
        f_number=5.6, exposure_s=pytest.approx(1 / 125), iso=200.0, focus_distance_m=1.25, width=96, height=64,
        pixel_pitch_um=pytest.approx(4.3, rel=1e-6))
    assert raw.load_frame(tmp_path / "a.dng").data.shape == (32, 48)  # still a DNG LibRaw decodes
    assert exif.check_settings(meta, aperture="f/5.6", shutterspeed="1/125", iso="200", focal_length_mm=50) == []


def test_the_simulated_camera_writes_what_it_was_set_to(tmp_path):
    from psfd.drivers.sim import SimRig

    rig = SimRig(sensor=(120, 160), seed=7)
    rig.camera.set("aperture", "11")
    rig.camera.set("shutterspeed", "1/250")
    meta = exif.read_metadata(rig.camera.capture(tmp_path)[0])
    assert (meta.f_number, meta.exposure_s, meta.iso, meta.serial) == (11.0, 1 / 250, 100.0, "SIM-7")
    assert meta.pixel_pitch_um == pytest.approx(rig.pitch_um) and meta.focal_length_mm == rig.focal_mm
    assert meta.focus_distance_m == pytest.approx(rig.pos.x / 1000.0)
    assert exif.check_settings(meta, aperture=11, shutterspeed="1/250", iso=100, focal_length_mm=50) == []
    with pytest.raises(SettingsMismatch, match=r"the camera used f/11 instead of f/5.6"):
        exif.check_settings(meta, aperture=5.6)


def test_a_camera_at_another_aperture_fails_the_step(tmp_path):
    meta = exif.read_metadata(_dng(tmp_path / "f8.dng", **dict(CAMERA, f_number=8.0, iso=400)))
    with pytest.raises(SettingsMismatch) as caught:
        exif.check_settings(meta, aperture=5.6, shutterspeed="1/125", iso=200, frame="step x=800 f/5.6")
    message = str(caught.value)
    assert message.startswith("step x=800 f/5.6: the camera used f/8 instead of f/5.6, ISO 400 instead of ISO 200")
    assert "\n" not in message and isinstance(caught.value, CameraError)  # fails the step as a camera fault


@pytest.mark.parametrize("reported, asked, ok", [
    (5.657, 5.6, True),    # exact 2^(5/2) against its nominal value
    (5.6, 5.66, True),
    (6.3, 5.6, False),     # the next 1/3 stop
    (7.1, 7.127, True),    # 2^(17/6) = 7.127 written as 7.1
    (6.7, 6.73, True),     # half stops (Nikon f/6.7)
    (22.0, 22.6, True),
    (20.0, 22.0, False),
])
def test_f_numbers_pass_their_rounding_and_not_the_next_third(reported, asked, ok):
    meta = exif.FrameMetadata(f_number=reported)
    if ok:
        assert exif.check_settings(meta, aperture=asked) == []
    else:
        with pytest.raises(SettingsMismatch):
            exif.check_settings(meta, aperture=asked)


def test_exposure_rounding_and_mismatch():
    assert exif.check_settings(exif.FrameMetadata(exposure_s=1 / 128), shutterspeed="1/125") == []
    assert exif.check_settings(exif.FrameMetadata(exposure_s=0.3), shutterspeed='0"3') == []
    with pytest.raises(SettingsMismatch, match=r"exposure 1/100 s instead of 1/125 s"):
        exif.check_settings(exif.FrameMetadata(exposure_s=0.01), shutterspeed="1/125")
    # bulb and "auto" are not compared
    assert exif.check_settings(exif.FrameMetadata(exposure_s=12.0), shutterspeed="bulb", iso="Auto") == []


def test_missing_tags_are_reported_unverified_not_invented(tmp_path):
    meta = exif.read_metadata(_dng(tmp_path / "bare.dng"))
    assert (meta.width, meta.height) == (96, 64)
    assert all(getattr(meta, f) is None for f in ("make", "serial", "lens", "f_number", "exposure_s", "iso",
                                                  "focal_length_mm", "focus_distance_m", "pixel_pitch_um"))
    assert exif.check_settings(meta, aperture=5.6, shutterspeed="1/125", iso=100, focal_length_mm=50) == \
        ["aperture", "shutterspeed", "iso", "focal_length_mm"]


def test_apex_values_and_inch_focal_plane_units(tmp_path):
    # A TIFF/EP file giving only the APEX values and the focal-plane resolution in pixels per inch.
    av, tv = 2 * math.log2(8.0), math.log2(60.0)
    tags = [(37378, "2I", 1, (round(av * 1000), 1000), True),  # ApertureValue
            (37377, "2i", 1, (round(tv * 1000), 1000), True),  # ShutterSpeedValue
            (41486, "2I", 1, (5080, 1), True), (41488, "H", 1, 2, True)]  # 5080 px/inch, unit inch
    path = tmp_path / "apex.tif"
    tifffile.imwrite(path, MOSAIC, photometric=32803, extratags=tags)
    meta = exif.read_metadata(path)
    assert meta.f_number == pytest.approx(8.0, rel=1e-3)
    assert meta.exposure_s == pytest.approx(1 / 60, rel=1e-3)
    assert meta.pixel_pitch_um == pytest.approx(5.0)  # 25400 um / 5080
    assert exif.check_settings(meta, aperture=8, shutterspeed="1/60") == []


def test_a_photograph_without_exif_and_a_missing_file(data_dir, tmp_path):
    meta = exif.read_metadata(data_dir / "img_example.pgm")
    assert meta == exif.FrameMetadata()
    with pytest.raises(BadInputError, match=r"nope.dng: cannot read the frame's metadata"):
        exif.read_metadata(tmp_path / "nope.dng")


@pytest.mark.parametrize("text, seconds", [
    ("1/125", 1 / 125), ("0.0050s", 0.005), ("30", 30.0), ('30"', 30.0), ('1"3', 1.3), ("15/10", 1.5),
    ("2.5", 2.5), ("Bulb", math.inf), ("auto", None), ("", None), (None, None), (0.5, 0.5),
])
def test_exposure_seconds(text, seconds):
    assert exif.exposure_seconds(text) == (pytest.approx(seconds) if seconds else seconds)
