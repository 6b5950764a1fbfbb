"""Detection of the Bernoulli target: X-corners, orientation, scale, and the failures."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from psfd.errors import BadInputError, MultipleTargetsError, TargetNotFoundError
from psfd.estimator import detect, target

SUPER = 4  # rendering grid per image pixel (area-averaged down)


def render_target(
    shape: tuple[int, int],
    scale: float,
    angle: float = 0.0,
    centre: tuple[float, float] | None = None,
    tilt: float = 0.0,
    blur: float = 0.6,
    noise: float = 0.005,
    background: float = 1.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Photograph of the published target: (image, homography pattern cells -> image px).

    The target raster (target.cells) is warped by a homography onto a SUPER
    times finer grid, blurred by a Gaussian PSF of ``blur`` image pixels,
    area-averaged to the image grid, mapped to [0.1, 0.9] and given Gaussian
    noise of standard deviation ``noise``. ``tilt`` is a perspective term per
    cell (0.0003 shrinks one side of the target by about 10 %).
    """
    rows, cols = shape
    cx, cy = centre if centre is not None else ((cols - 1) / 2, (rows - 1) / 2)
    a = np.deg2rad(angle)
    to_centre = np.array([[1, 0, -target.SIZE / 2], [0, 1, -target.SIZE / 2], [0, 0, 1.0]])
    perspective = np.array([[1, 0, 0], [0, 1, 0], [tilt, 0.3 * tilt, 1.0]])
    similarity = np.array([[scale * np.cos(a), -scale * np.sin(a), cx], [scale * np.sin(a), scale * np.cos(a), cy], [0, 0, 1]])
    homography = similarity @ perspective @ to_centre
    n = max(2, int(np.ceil(1.5 * SUPER * scale)))  # raster pixels per cell, finer than the render grid
    raster = target.cells(None, n).astype(np.float32)
    from_raster = np.array([[1 / n, 0, 0.5 / n], [0, 1 / n, 0.5 / n], [0, 0, 1]])  # raster pixel centre -> cells
    to_super = np.array([[SUPER, 0, (SUPER - 1) / 2], [0, SUPER, (SUPER - 1) / 2], [0, 0, 1]])  # image -> render grid
    big = cv2.warpPerspective(
        raster, to_super @ homography @ from_raster, (cols * SUPER, rows * SUPER),
        flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0,
    )
    big[big < 0] = background
    if blur > 0:
        big = cv2.GaussianBlur(big, (0, 0), blur * SUPER)
    image = cv2.resize(big, (cols, rows), interpolation=cv2.INTER_AREA).astype(np.float64)
    rng = np.random.default_rng(seed)
    return 0.1 + 0.8 * image + rng.normal(0.0, noise, image.shape), homography


def apply_homography(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    p = np.column_stack([points, np.ones(len(points))]) @ h.T
    return p[:, :2] / p[:, 2:]


def frame_for(scale: float) -> tuple[int, int]:
    """An image large enough for the target at any rotation, with a margin."""
    side = int(470 * scale) + 40
    return side, side + 40


# Tolerance 0.1 px: a tenth of a camera pixel is 0.4 of a sample of the s = 4
# grid the PSF is estimated on; the thesis's refinement (App. A.1) on
# symmetric X-corners is unbiased, so what is left is the noise (here 0.5 %
# of the range, a raw frame's shot noise at mid-grey) over the window
# of +-8 cells: measured 0.01-0.03 px without noise, 0.03-0.06 px with it.
TOLERANCE = 0.1


@pytest.mark.parametrize(
    ("angle", "scale", "tilt"),
    [(0, 0.37, 0.0), (17, 0.25, 0.0003), (45, 0.8, 0.0004), (90, 0.3, 0.0), (133, 1.5, 0.0003), (200, 0.5, 0.0002),
     (271, 2.0, 0.0), (329, 0.37, 0.0004)],
)
def test_corners_and_orientation_at_any_rotation_and_scale(angle, scale, tilt):
    image, h = render_target(frame_for(scale), scale, angle=angle, tilt=tilt, seed=int(angle))
    truth = apply_homography(h, target.xcorner_points())
    found = detect.find_target(image)
    # Orientation: corner k is XCORNER_BLOCKS[k]; a wrong quarter turn would be off by a block or more.
    errors = np.linalg.norm(found.corners - truth, axis=1)
    assert errors.max() < TOLERANCE, errors
    np.testing.assert_array_equal(found.pattern_points, target.xcorner_points())
    assert found.scale == pytest.approx(scale, rel=0.1)


def test_smallest_scale_is_found_and_oriented():
    # At 0.2 px/cell the mark's sectors span 3 pixels; the window of +-8 cells
    # is 1.6 px, so the noise weighs more: 0.2 px, still under a camera pixel.
    image, h = render_target(frame_for(0.2), 0.2, angle=63, seed=5)
    found = detect.find_target(image)
    errors = np.linalg.norm(found.corners - apply_homography(h, target.xcorner_points()), axis=1)
    assert errors.max() < 0.2, errors


@pytest.mark.parametrize(("angle", "seed"), [(63, 5), (200, 2)])
def test_lower_end_of_the_papers_scale_range_is_found(angle, seed):
    # IJCV 2012 sec. 3.3 takes s/t down to 0.7: 0.175 px/cell at s = 4, where the marks' saddles are
    # centred on the image smoothed half as much (`_search`). The corners come as close as at 0.2 px/cell
    # (measured 0.17-0.23 px over six turns); the bound is a quarter pixel, one sample of the PSF's s = 4 grid.
    image, h = render_target(frame_for(0.175), 0.175, angle=angle, seed=seed)
    found = detect.find_target(image)
    errors = np.linalg.norm(found.corners - apply_homography(h, target.xcorner_points()), axis=1)
    assert errors.max() < 0.25, errors
    np.testing.assert_array_equal(found.pattern_points, target.xcorner_points())


def test_small_target_in_a_large_frame():
    image, h = render_target((1301, 1953), 0.3, angle=33, tilt=0.0003, centre=(1500.0, 300.0), noise=0.01)
    found = detect.find_target(image)
    errors = np.linalg.norm(found.corners - apply_homography(h, target.xcorner_points()), axis=1)
    assert errors.max() < TOLERANCE, errors


def test_real_photograph_in_a_large_real_frame(data_dir):
    # The example photo pasted, turned by 37 degrees, into the 1953 x 1301
    # textured wall of the two-photo data: clutter everywhere, target ~5 %.
    wall = cv2.imread(str(data_dir / "IMG_0608_v1.pgm"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    photo = cv2.imread(str(data_dir / "img_example.pgm"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    reference = detect.find_target(photo).corners
    turn = cv2.getRotationMatrix2D((164.0, 146.0), 37.0, 1.0)
    turned = cv2.warpAffine(photo, turn, photo.shape[::-1], flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    wall[900:1192, 1500:1828] = turned
    found = detect.find_target(wall)
    expected = np.column_stack([reference, np.ones(12)]) @ turn.T + [1500.0, 900.0]
    # Bicubic rotation of an 8-bit photo of a target at 0.36 px/cell.
    assert np.linalg.norm(found.corners - expected, axis=1).max() < TOLERANCE


def test_blur_does_not_shift_the_corners():
    # A symmetric PSF keeps the X-corners in place (IJCV 2012, sec. 4.1).
    image, h = render_target(frame_for(0.5), 0.5, angle=21, blur=1.2, noise=0.0)
    found = detect.find_target(image)
    errors = np.linalg.norm(found.corners - apply_homography(h, target.xcorner_points()), axis=1)
    assert errors.max() < 0.05, errors


def test_real_photograph(data_dir):
    image = cv2.imread(str(data_dir / "img_example.pgm"), cv2.IMREAD_UNCHANGED).astype(np.float64)
    found = detect.find_target(image)
    # The published example images the target at about 0.37 px/cell (DESIGN.md).
    assert 0.3 < found.scale < 0.45
    assert np.all((found.corners > 0) & (found.corners < [image.shape[1], image.shape[0]]))
    h, _ = cv2.findHomography(found.pattern_points, found.corners)
    # Orientation: the two blocks next to corner (9, 9) are black, the ones
    # beside corners (9, 0) and (0, 9) on the ring's other side are white.
    def level(block):
        x, y = apply_homography(h, np.array([target.block_centre(block)]))[0]
        return float(image[int(round(y)) - 2 : int(round(y)) + 3, int(round(x)) - 2 : int(round(x)) + 3].mean())

    dark = [level((8, 9)), level((9, 8))]
    light = [level((9, 1)), level((1, 9)), level((1, 0)), level((0, 1))]
    assert max(dark) < 0.3 * min(light), (dark, light)
    # The homography explains the 12 refined corners to a fraction of a pixel
    # (what is left is lens distortion and the noise of the refinement).
    residual = np.linalg.norm(apply_homography(h, found.pattern_points) - found.corners, axis=1)
    assert residual.max() < 0.5


@pytest.mark.parametrize(("scale", "gap"), [(0.37, 4), (0.22, 2), (1.0, 3)])
def test_target_in_shade_beside_a_bright_area(scale, gap):
    # A target in shade a few pixels from a clipped window or sky: the
    # contrast around its outer marks is the window's, three times theirs.
    image, h = render_target(frame_for(scale), scale, noise=0.002, blur=0.7)
    image *= 0.3
    outline = apply_homography(h, np.array([[0, 0], [320, 0], [0, 320], [320, 320.0]]))
    image[:, int(outline[:, 0].max()) + gap :] = 1.0
    found = detect.find_target(image, saturated=image >= 1.0)
    errors = np.linalg.norm(found.corners - apply_homography(h, target.xcorner_points()), axis=1)
    # Below 0.3 px/cell the refinement window is under 2.4 px: 0.2 px as at the smallest scale.
    assert errors.max() < (TOLERANCE if scale >= 0.3 else 0.2), errors


def test_saturated_mask_is_accepted():
    image, h = render_target(frame_for(0.37), 0.37, angle=10)
    clipped = np.minimum(image, 0.8)
    found = detect.find_target(clipped, saturated=clipped >= 0.8)
    errors = np.linalg.norm(found.corners - apply_homography(h, target.xcorner_points()), axis=1)
    assert errors.max() < TOLERANCE, errors


@pytest.mark.parametrize("kind", ["texture", "blank", "near photo"])
def test_no_target(kind, data_dir):
    rng = np.random.default_rng(7)
    if kind == "texture":
        image = cv2.GaussianBlur(rng.random((400, 500)), (0, 0), 1.5)
    elif kind == "blank":
        image = np.full((300, 400), 1234.0)
    else:
        image = cv2.imread(str(data_dir / "IMG_0602_v1_CUT.pgm"), cv2.IMREAD_UNCHANGED)
    with pytest.raises(TargetNotFoundError, match="no calibration target found"):
        detect.find_target(image)


def test_a_lone_noise_patch_is_not_a_target():
    # The noise without its ring of marks.
    noise = np.kron(target.default_noise(), np.ones((2, 2)))
    image = np.pad(noise, 40, constant_values=0.5)
    with pytest.raises(TargetNotFoundError):
        detect.find_target(image)


def test_two_targets():
    left, _ = render_target((300, 300), 0.5, angle=10)
    right, _ = render_target((300, 300), 0.45, angle=-70, seed=3)
    with pytest.raises(MultipleTargetsError):
        detect.find_target(np.hstack([left, right]))


def test_too_blurred_to_locate():
    # A PSF of 8 cells (sigma) on a 32-cell mark: the hourglass is gone.
    image, _ = render_target(frame_for(0.25), 0.25, angle=30, blur=2.0)
    with pytest.raises(TargetNotFoundError):
        detect.find_target(image)


def test_bad_input():
    with pytest.raises(BadInputError):
        detect.find_target(np.zeros((10, 10, 3)))


def test_simulated_raw_frames(tmp_path):
    """The detector on Bayer planes of DNG files written by the simulator."""
    from psfd.estimator import raw, simulate

    psf = simulate.gaussian_psf(0.6, s=4)
    cases = [
        dict(pixels_per_cell=0.25, rotation_deg=0.0, centre=(0.5, 0.5)),
        dict(pixels_per_cell=0.37, rotation_deg=150.0, tilt=(0.1, 0.05), distortion=0.02, centre=(0.6, 0.4)),
    ]
    for k, case in enumerate(cases):
        path = tmp_path / f"target{k}.dng"
        truth = simulate.simulate_target(path, psf=psf, seed=k, **case)
        for channel in ("g1", "r"):
            frame = raw.load_frame(path, channel)
            found = detect.find_target(frame.data, frame.saturated)
            errors = np.linalg.norm(found.corners - truth["corners"][channel], axis=1)
            assert errors.max() < TOLERANCE, (case, channel, errors)
            assert found.scale == pytest.approx(case["pixels_per_cell"], rel=0.05)


# --------------------------------------------------------------------------- cluttered frames
#
# Frames of tests/scenes.py: the target drawn from its vector layout into a
# busy outdoor scene (foliage against a clipped sky, a chain-link fence,
# checkerboards, text, dead leaves, shadows), blurred, noisy, quantised. The
# previous detector, which ranked saddles over the whole frame, found the
# target in 2 of 20 such frames.

import scenes  # noqa: E402

from psfd.estimator import bernoulli, raw  # noqa: E402

# Corners against the truth, in pixels: the refinement is the one above, but
# on 8-bit planes (quantisation 0.4 % of the range, noise 0.5 %) of scenes
# rendered with 8 x 8 samples per pixel, whose box average of the hourglass
# diagonals is itself exact only to about 1/64 of a pixel's area: measured
# 0.03-0.15 px over 30 scenes at 0.3-0.5 px/cell, 0.02-0.06 px on 14-bit planes.
SCENE_TOLERANCE = 0.2
# The same PSF from the whole frame as from a crop around the target (issue
# 10): the refinement reads only the marks' surroundings, so both give the
# same corners and the same kernel; 0.01 is the bound asked for, measured 1e-4.
MTF_TOLERANCE = 0.01


def _same_psf(full: raw.Frame, box: tuple[int, int, int, int]) -> float:
    """Largest MTF difference between the estimates from ``full`` and from its crop ``box``."""
    whole = bernoulli.estimate_target(full)[0]
    part = bernoulli.estimate_target(scenes.crop_frame(full, box))[0]
    # the whole 2-D MTF, not only its axes: both kernels are on the same s-grid
    def mtf_2d(psf: np.ndarray) -> np.ndarray:
        return np.abs(np.fft.fft2(psf)) / psf.sum()

    return float(np.abs(mtf_2d(whole.psf) - mtf_2d(part.psf)).max())


def _check_plane_scene(scene: scenes.Scene, psf: bool) -> None:
    frame = scenes.plane_frame(scene)
    found = detect.find_target(frame.data, frame.saturated)
    errors = np.linalg.norm(found.corners - scene.corners(), axis=1)
    assert errors.max() < SCENE_TOLERANCE, (scene.params, errors)
    assert found.scale == pytest.approx(scene.scale, rel=0.1)
    # Detection in the whole frame and in a crop around the target agree.
    box = scene.box(margin=30)
    in_crop = detect.find_target(frame.data[box[1] : box[3], box[0] : box[2]])
    np.testing.assert_allclose(in_crop.corners + box[:2], found.corners, atol=1e-3)
    if psf:
        assert _same_psf(frame, box) < MTF_TOLERANCE


@pytest.mark.parametrize("seed", [0, 4])
def test_target_in_a_cluttered_8bit_plane(seed):
    # 1953 x 1301, the size of the real frames, target at 0.3-0.5 px/cell, any rotation.
    _check_plane_scene(scenes.plane_scene(seed), psf=seed == 0)


# From the smallest scale of the cluttered frames to a target shot close up:
# the estimator accepts any scale and advises s/t in [0.7, 2] (IJCV 2012
# sec. 3.3), 0.09-2 px/cell for s = 8 .. 1, and a lab user at the bench may
# fill the frame (5 px/cell is a 1600-pixel target in a 3000 x 2000 plane).
@pytest.mark.parametrize(
    ("scale", "angle", "shape"),
    [(0.3, 305.0, (1301, 1953)), (1.0, 20.0, (1301, 1953)), (3.0, 135.0, (2000, 3000)), (5.0, 268.0, (2000, 3000))],
)
def test_target_at_any_scale_in_a_cluttered_plane(scale, angle, shape):
    # The small one outdoors under a clipped sky, the others shot close up indoors.
    scene = scenes.plane_scene(int(10 * scale) + 50, shape=shape, scale=scale, angle=angle, fill=scale > 0.5)
    _check_plane_scene(scene, psf=False)


@pytest.fixture(scope="module")
def cluttered_raw(tmp_path_factory):
    """A 24-megapixel RGGB DNG of a cluttered scene, written by psfd's DNG writer."""
    path = tmp_path_factory.mktemp("scene") / "cluttered.dng"
    return scenes.raw_scene(path, seed=101)


def test_target_in_every_plane_of_a_cluttered_24mp_raw(cluttered_raw):
    planes = raw.load_frames(cluttered_raw.path)  # decoded by rawpy
    assert [p.channel for p in planes] == ["r", "g1", "g2", "b"] and planes[0].shape == (2000, 3000)
    g1 = next(p for p in planes if p.channel == "g1")
    once = detect.find_target(g1.data, g1.saturated)
    for plane in planes:
        truth = cluttered_raw.corners(plane.channel)
        found = detect.find_target(plane.data, plane.saturated)
        assert np.linalg.norm(found.corners - truth, axis=1).max() < SCENE_TOLERANCE, plane.channel
        # Detected once on g1, refined here: the same corners as a search of this plane.
        shift = detect.plane_shift(g1.offset, plane.offset)
        refined = detect.refine_target(plane.data, once, plane.saturated, shift)
        np.testing.assert_allclose(refined.corners, found.corners, atol=1e-3)


def test_same_psf_from_the_raw_frame_as_from_a_crop(cluttered_raw):
    g1 = raw.load_frame(cluttered_raw.path, "g1")
    assert _same_psf(g1, cluttered_raw.box("g1", margin=30)) < MTF_TOLERANCE


def test_no_target_in_a_cluttered_frame():
    scene = scenes.plane_scene(7, targets=0)
    with pytest.raises(TargetNotFoundError, match="no calibration target found in the 1953x1301 image"):
        detect.find_target(scene.image)


def test_two_targets_in_a_cluttered_frame():
    scene = scenes.plane_scene(8, targets=2)
    with pytest.raises(MultipleTargetsError, match="2 calibration targets found in the image; frame exactly one"):
        detect.find_target(scene.image)


def test_plane_shift_follows_the_bayer_offsets():
    # RGGB: r at photosite (0, 0), b at (1, 1): a point of the r plane lies
    # half a pixel up and left on the b plane.
    assert detect.plane_shift((0, 0), (1, 1)) == (-0.5, -0.5)
    assert detect.plane_shift((0, 1), (1, 0)) == (0.5, -0.5)
    assert detect.plane_shift((0, 0), (0, 0)) == (0.0, 0.0)


def test_refining_from_a_start_a_pixel_away_gives_the_same_corners():
    # The planes of a frame differ by the Bayer half-pixel offsets and the
    # lens's lateral colour (up to about a pixel).
    image, _ = render_target(frame_for(0.3), 0.3, angle=140, tilt=0.0003)
    found = detect.find_target(image)
    refined = detect.refine_target(image, found, shift=(1.0, -0.8))
    np.testing.assert_allclose(refined.corners, found.corners, atol=1e-3)
    assert refined.scale == pytest.approx(found.scale)


def test_refining_where_there_is_no_target_is_refused():
    image, _ = render_target(frame_for(0.4), 0.4, angle=20)
    found = detect.find_target(image)
    with pytest.raises(TargetNotFoundError):
        detect.refine_target(np.full_like(image, 0.5), found)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(30))
def test_sweep_cluttered_8bit_planes(seed):
    _check_plane_scene(scenes.plane_scene(seed), psf=seed % 5 == 0)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4))
def test_sweep_larger_targets(seed):
    # 0.6-1.1 px/cell: the target covers 1.5-5 % of the frame's area.
    scale = 0.6 + 0.15 * seed
    _check_plane_scene(scenes.plane_scene(200 + seed, scale=scale), psf=False)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(100, 106))
def test_sweep_cluttered_24mp_raws(seed, tmp_path):
    scene = scenes.raw_scene(tmp_path / "scene.dng", seed=seed)
    for plane in raw.load_frames(scene.path):
        found = detect.find_target(plane.data, plane.saturated)
        errors = np.linalg.norm(found.corners - scene.corners(plane.channel), axis=1)
        assert errors.max() < SCENE_TOLERANCE, (seed, plane.channel, errors)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(300, 306))
def test_sweep_frames_without_or_with_two_targets(seed):
    with pytest.raises(TargetNotFoundError):
        detect.find_target(scenes.plane_scene(seed, targets=0).image)
    with pytest.raises(MultipleTargetsError):
        detect.find_target(scenes.plane_scene(seed, targets=2).image)


@pytest.mark.parametrize("seed, n, spread", [(0, 0, 100.0), (1, 1, 100.0), (2, 50, 30.0), (3, 2000, 400.0),
                                             (4, 3000, 2000.0)])
def test_the_neighbour_search_is_ckdtrees(seed, n, spread):
    """detect._Neighbours (which spares scipy.spatial's start-up) finds what scipy.spatial.cKDTree finds."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    points = rng.random((n, 2)) * spread
    points[: n // 10] = np.round(points[: n // 10])  # some on cell borders
    ours, tree = detect._Neighbours(points), cKDTree(points)
    for r in (1.0, 7.5, 40.0):
        expected = tree.query_pairs(r, output_type="ndarray").reshape(-1, 2)
        np.testing.assert_array_equal(ours.pairs(r), expected[np.lexsort((expected[:, 1], expected[:, 0]))])
    queries = np.vstack([rng.random((300, 2)) * spread * 1.2 - 0.1 * spread, [[-1e9, -1e9], [1e308, 5.0]]])
    for bound in (2.0, 25.0):
        dist, idx = ours.nearest(queries, 6, bound)
        expected_dist, expected_idx = tree.query(queries, k=6, distance_upper_bound=bound)
        np.testing.assert_array_equal(idx, expected_idx)
        np.testing.assert_allclose(dist, expected_dist, rtol=1e-15, atol=0)
