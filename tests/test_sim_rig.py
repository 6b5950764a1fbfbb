"""The simulated rig: real DNG frames whose geometry and PSF follow the rail and the aperture."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from psfd.drivers import open_rig
from psfd.drivers.base import Camera, Position, Rail
from psfd.drivers.sim import APERTURES, SimRig
from psfd.errors import BadInputError, CameraError, RailAlarm, RailError
from psfd.estimator import raw
from psfd.estimator.kernels import centroid
from psfd.estimator.mtf import directional_profile


def _second_moments(psf: np.ndarray, s: int) -> np.ndarray:
    """Covariance of a PSF in channel pixels^2."""
    c = (np.arange(psf.shape[0]) - psf.shape[0] // 2) / s
    y, x = np.meshgrid(c, c, indexing="ij")
    mx, my = (psf * x).sum(), (psf * y).sum()
    return np.array([[(psf * (x - mx) ** 2).sum(), (psf * (x - mx) * (y - my)).sum()],
                     [(psf * (x - mx) * (y - my)).sum(), (psf * (y - my) ** 2).sum()]])


def _target_box(plane: np.ndarray) -> tuple[float, float, float, float]:
    """Bounding box (x0, x1, y0, y1) of the target: where the local contrast is high."""
    local = cv2.blur(plane, (5, 5))
    contrast = cv2.blur((plane - local) ** 2, (5, 5)) ** 0.5
    ys, xs = np.nonzero(contrast > 0.5 * np.percentile(contrast, 99.5))
    return xs.min(), xs.max(), ys.min(), ys.max()


def test_protocols_and_settings(tmp_path):
    camera, rail = open_rig({"simulate": True})
    assert isinstance(camera, Camera) and isinstance(rail, Rail)
    assert camera.info().focal_length_mm == 50.0
    assert camera.choices("aperture") == ["2.8", "4", "5.6", "8", "11", "16", "22"]
    for spelling in ("f/8", "F8", "8.0"):  # every spelling psfd reads as f/8 (`parse_fnumber`), as the gphoto driver
        camera.set("aperture", "5.6")
        camera.set("aperture", spelling)
        assert camera.get("aperture") == "8", spelling
    with pytest.raises(CameraError, match=r"aperture 3.3 is not offered by the camera \(offered: 2.8, 4, 5.6"):
        camera.set("aperture", "3.3")
    with pytest.raises(CameraError, match="no setting 'zoom'"):
        camera.get("zoom")
    camera.set("imageformat", "RAW + JPEG")
    files = camera.capture(tmp_path)
    assert [f.suffix for f in files] == [".DNG", ".JPG"]
    assert cv2.imread(str(files[1]), cv2.IMREAD_UNCHANGED).shape == (240, 320)


def test_rail_limits_and_home():
    rig = SimRig()
    assert rig.rail.home() == Position(200.0, 0.0, 0.0)
    assert rig.rail.move(x=900, y=10) == Position(900.0, 10.0, 0.0)
    with pytest.raises(RailError, match=r"X=5000 mm is outside the soft limits \[200, 3000\]"):
        rig.rail.move(x=5000)
    rig.fail_next("rail", RailAlarm("rail ALARM:1 (hard limit triggered)"))
    with pytest.raises(RailAlarm):
        rig.rail.move(x=500)
    assert rig.rail.position().x == 900.0
    with pytest.raises(BadInputError, match="unknown simulated rig option"):
        open_rig({"simulate": True, "lens": "x"})


def test_frame_geometry_follows_the_rail(tmp_path):
    """Distance sets the imaging scale, Y/Z the field position; checked on the rendered pixels."""
    rig = SimRig()
    s = 4
    x = rig.distance_for_scale(1 / s)
    assert x == pytest.approx(1300.0)  # 50 mm * (1 + 0.1 mm / (0.25 px * 0.016 mm/px))
    assert rig.pixels_per_cell(x) == pytest.approx(0.25)
    for field in [(0.5, 0.5), (0.3, 0.7)]:
        pos = rig.position_for(field, 1 / s)
        rig.rail.move(x=pos.x, y=pos.y, z=pos.z)
        assert rig.field() == pytest.approx(field)
        (path,) = rig.camera.capture(tmp_path)
        plane = raw.load_frame(path, "g1")
        assert plane.data.shape == (240, 320) and plane.white == 16383 - 512
        x0, x1, y0, y1 = _target_box(plane.data)
        # The 320-cell target (noise and border marks) is 80 channel pixels wide at 0.25 px/cell; its
        # box is found to within the 5-pixel contrast window plus the PSF support (2 px each side).
        assert x1 - x0 + 1 == pytest.approx(80, abs=6) and y1 - y0 + 1 == pytest.approx(80, abs=6)
        assert (x0 + x1) / 2 / 319 == pytest.approx(field[0], abs=0.02)
        assert (y0 + y1) / 2 / 239 == pytest.approx(field[1], abs=0.02)
        assert rig.last_truth["pixels_per_cell"] == pytest.approx(0.25)


def test_field_offsets_keep_the_target_in_frame(tmp_path):
    rig = SimRig()
    ys, zs = rig.field_offsets(3)
    assert len(ys) == 3 and len(zs) == 3 and ys[1] == 0.0 and ys[0] == -ys[2] and zs[0] == -zs[2]
    rig.rail.move(x=rig.distance_for_scale(0.25), y=ys[2], z=zs[0])  # top-right corner of the grid
    (path,) = rig.camera.capture(tmp_path)
    x0, x1, y0, y1 = _target_box(raw.load_frame(path, "g1").data)
    assert x1 < 319 and y0 > 0 and x1 - x0 + 1 == pytest.approx(80, abs=6)  # whole target, at the edge
    assert x1 > 300 and y0 < 20


def test_truth_psf_diffraction_and_field():
    rig = SimRig()
    centre_56 = rig.truth(5.6, (0.5, 0.5), "g1")
    centre_22 = rig.truth(22, (0.5, 0.5), "g1")
    corner_56 = rig.truth(5.6, (0.95, 0.95), "g1")
    for psf in (centre_56, centre_22, corner_56):
        # band-limited to the s-grid's band (simulate.diffraction_psf), it rings at most 4 % of its peak below 0
        assert psf.shape == (17, 17) and psf.sum() == pytest.approx(1.0) and psf.min() >= -0.05 * psf.max()
        assert np.allclose(centroid(psf), (0.0, 0.0), atol=0.05)  # centred to 1/20 of an s-grid sample
    # diffraction: the Airy core at f/22 (2.44 * 0.53 um * 22 = 28 um across) widens the PSF
    assert np.trace(_second_moments(centre_22, 4)) > 1.2 * np.trace(_second_moments(centre_56, 4))
    # on axis the PSF is symmetric; toward the corner astigmatism stretches it along the radius
    def anisotropy(psf):
        ev = np.linalg.eigvalsh(_second_moments(psf, 4))
        return ev[1] / ev[0]

    assert anisotropy(centre_56) == pytest.approx(1.0, abs=0.02)
    assert anisotropy(corner_56) > 1.1
    # red is wider than blue (diffraction scales with wavelength)
    assert np.trace(_second_moments(rig.truth(22, (0.5, 0.5), "r"), 4)) > np.trace(
        _second_moments(rig.truth(22, (0.5, 0.5), "b"), 4))


def test_no_field_point_resolves_better_than_the_aberration_free_lens():
    """Aberrations only lower the MTF of a lens at a given aperture: |OTF| of an aberrated pupil is at most the
    diffraction-limited one at every frequency (Goodman, Introduction to Fourier Optics, sec. 6.4). So every
    true PSF of a plan's field grid (and the corners) has, across and along its radius, at most the MTF of
    the aberration-free centre at that aperture and wavelength.

    Tolerance 0.01: both kernels are cut to 17 x 17 samples, which drops 6 % of the light at the centre and
    up to 12 % in a corner at f/22; that moves their MTFs by up to 0.007 relative to each other (measured,
    at 1 cycle per pixel where the centre's is 0). Point-sampled kernels put the corner up to 0.05 above the
    centre at f/2.8-f/8 (the aliasing of optics that pass up to 12 cycles per pixel into the s = 4 band)."""
    rig = SimRig()
    ys, zs = rig.field_offsets(3)  # the 3 x 3 grid of `psfd plan init --simulate` and the demo
    # one quadrant: the field is symmetric about its centre (a mirrored point has the mirrored PSF)
    grid = [rig.field(Position(rig.pos.x, y, z)) for y, z in ((ys[0], zs[0]), (ys[0], zs[1]), (ys[1], zs[0]))]
    fields = [*grid, (0.05, 0.05)]
    freqs = np.linspace(0.0, rig.s / 2, 65)
    aspect = rig.sensor[1] / rig.sensor[0]
    for aperture in APERTURES:
        for channel in ("r", "b"):  # the longest and the shortest wavelength
            centre = rig.truth(aperture, (0.5, 0.5), channel)
            for fx, fy in fields:
                psf = rig.truth(aperture, (fx, fy), channel)
                radius = np.arctan2(fy - 0.5, (fx - 0.5) * aspect)
                for angle in (radius, radius + np.pi / 2):  # meridional, sagittal
                    excess = directional_profile(psf, rig.s, angle, freqs) - directional_profile(
                        centre, rig.s, angle, freqs)
                    assert excess.max() <= 0.01, (aperture, channel, (fx, fy), angle, freqs[excess.argmax()])


def test_frames_use_the_truth_psf(tmp_path):
    rig = SimRig()
    rig.camera.set("aperture", "11")
    rig.camera.capture(tmp_path)
    truth = rig.last_truth
    assert truth["aperture"] == 11.0 and truth["field"] == (0.5, 0.5)
    for channel in ("r", "g1", "g2", "b"):
        assert np.array_equal(truth["psf"][channel], rig.truth(11, (0.5, 0.5), channel))


def test_texture_pair_is_one_plane_at_two_scales(tmp_path):
    """The far frame is the near frame seen smaller: downscaling the near one by the ratio of
    magnifications predicts the centre of the far one."""
    rig = SimRig(scene="texture", seed=2)
    near_x, far_x = rig.pair_distances(ratio=4.0)
    rig.rail.move(x=near_x)
    (near_path,) = rig.camera.capture(tmp_path)
    m_near = rig.magnification()
    rig.rail.move(x=far_x)
    (far_path,) = rig.camera.capture(tmp_path)
    ratio = m_near / rig.magnification()
    assert ratio == pytest.approx(4.0)
    near = raw.load_frame(near_path, "g1").data
    far = raw.load_frame(far_path, "g1").data
    small = cv2.resize(near, None, fx=1 / ratio, fy=1 / ratio, interpolation=cv2.INTER_AREA)
    h, w = small.shape
    cy, cx = (far.shape[0] - h) // 2, (far.shape[1] - w) // 2
    crop = far[cy : cy + h, cx : cx + w]
    corr = np.corrcoef(small[2:-2, 2:-2].ravel(), crop[2:-2, 2:-2].ravel())[0, 1]
    # half-pixel misalignment of the centred crop and the different PSFs keep it below 1
    assert corr > 0.85
    # and the far frame is not the near one: different content at the same pixels
    assert np.corrcoef(near.ravel(), far.ravel())[0, 1] < 0.5


def test_aberrations_point_along_the_physical_radius_of_a_4_3_sensor():
    """Astigmatism and coma are symmetric about the plane through the optical axis and the field point: the
    PSF's principal axes lie along and across the radius on the sensor, as `figures.sagittal_meridional`
    measures them. On a 640 x 480 sensor the radius to the field point (0.95, 0.95) is at atan(3/4) = 36.9
    degrees, not 45 (the diagonal of the normalised field)."""
    rig = SimRig()
    rows, cols = rig.sensor
    expected = np.degrees(np.arctan2(0.45 * rows, 0.45 * cols))
    for aperture in (4, 8):
        h = rig.truth(aperture, (0.95, 0.95), "g1")  # signed: clipping its lobes would favour the grid's axes
        y, x = np.mgrid[:h.shape[0], :h.shape[1]] - (h.shape[0] - 1) / 2
        x, y = x - (h * x).sum(), y - (h * y).sum()
        sxx, syy, sxy = (h * x * x).sum(), (h * y * y).sum(), (h * x * y).sum()
        axis = 0.5 * np.degrees(np.arctan2(2 * sxy, sxx - syy))  # a principal axis, in (-90, 90]
        off = abs((axis - expected + 45) % 90 - 45)  # from the radius or from across it
        assert off < 2.0, (aperture, axis, expected)  # 0.7-1.0 (the square pixel and band); 8.1 at 45
