"""The estimate of a target photo on the scipy-free path equals the one on the scipy path it replaced.

The Bernoulli estimate runs without scipy (0.5-1 s of start-up): the DCTs and
convolutions on OpenCV's DFT (`fourier`), medians and percentiles without
numpy.ma (`quantiles`), the Cholesky solves on OpenCV and numpy, the
neighbour search of the detection on a grid of cells, the F-quantile of the
map's test from its continued fraction. Here the same estimates are run on
the earlier path (scipy.fft, scipy.signal.fftconvolve, scipy.linalg's LAPACK,
numpy's median and percentile, scipy.spatial.cKDTree, scipy.special.fdtri),
kept as the reference, and the PSFs must agree within 1e-3 of their noise
floor: the changes are float rounding (float32 transforms: ~1e-7 of the
pattern), three orders of magnitude below what the estimate can resolve.

The blind sharp-edge estimate (Joshi et al., CVPR 2008) likewise: its
Gaussian filters, bilinear reads and dilation (scipy.ndimage's, bit for bit),
the nearest edge point (OpenCV's exact k-d tree against scipy.spatial.cKDTree),
its smoothness term written densely and the non-negative solve on the normal
equations (`nnls`), against the former scipy.sparse operator and
scipy.optimize.nnls on the Cholesky factor of the same matrix.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.fft
import scipy.signal
from scipy import linalg, ndimage, optimize, sparse, special
from scipy.spatial import cKDTree

from psfd.estimator import bernoulli, detect, fourier, geometry, nnls, quantiles, radiometry, raw, sharpedge, simulate

DATA = Path(__file__).parent / "data"


class _TreeNeighbours:
    def __init__(self, points: np.ndarray) -> None:
        self.tree = cKDTree(points)

    def pairs(self, r: float) -> np.ndarray:
        return self.tree.query_pairs(r, output_type="ndarray").reshape(-1, 2)

    def nearest(self, xy: np.ndarray, k: int, bound: float):
        return self.tree.query(xy, k=k, distance_upper_bound=bound)


def _scipy_cholesky_solve(q, c, idx=None):
    if idx is not None:
        q, c = q.take(idx, axis=0).take(idx, axis=1), c[idx]
    factor, info = linalg.lapack.dpotrf(q, lower=True, clean=False)
    if info != 0:
        raise np.linalg.LinAlgError("not positive definite")
    return linalg.lapack.dpotrs(factor, c, lower=True)[0]


def _scipy_gram(a):
    upper = linalg.blas.ssyrk(1.0, a.T, trans=0, lower=0)
    return upper + np.triu(upper, 1).T


REFERENCE = [
    (fourier, "dct", lambda x, keep=None, axis=-1: np.take(
        scipy.fft.dct(x, type=2, norm="ortho", axis=axis), np.arange(x.shape[axis] if keep is None else keep), axis)),
    (fourier, "idct", lambda c, n=None, axis=-1: scipy.fft.idct(c, type=2, norm="ortho", n=n, axis=axis)),
    (fourier, "idst", lambda c, n=None, axis=-1: scipy.fft.idst(c, type=2, norm="ortho", n=n, axis=axis)),
    (fourier, "convolve_same", lambda a, b: scipy.signal.fftconvolve(a, b, mode="same")),
    (quantiles, "median", np.median),
    (quantiles, "percentile", np.percentile),
    (bernoulli, "_gram", _scipy_gram),
    (bernoulli, "_cholesky_solve", _scipy_cholesky_solve),
    (nnls, "_cholesky_solve", _scipy_cholesky_solve),  # the exchanges of `nnls_normal`
    (bernoulli, "_triangular_inverse", lambda lower: linalg.lapack.dtrtri(lower, lower=1)[0]),
    (detect, "_Neighbours", _TreeNeighbours),
    (geometry, "f_quantile", lambda q, d1, d2: special.fdtri(d1, d2, 1.0 - q)),
]


def _estimates(frames, monkeypatch, reference: bool, **kwargs):
    with monkeypatch.context() as patch:
        if reference:
            for module, name, function in REFERENCE:
                patch.setattr(module, name, function)
        radiometry._tail_raster.cache_clear()  # computed with the transforms in force
        try:
            return bernoulli.estimate_frames(frames, **kwargs)
        finally:
            radiometry._tail_raster.cache_clear()


def _assert_same(new, old):
    assert len(new) == len(old)
    for a, b in zip(new, old):
        floor = b.noise_floor
        assert np.abs(a.psf - b.psf).max() <= 1e-3 * floor
        assert a.noise_floor == pytest.approx(floor, rel=1e-4)
        assert a.window == b.window
        assert a.params["geometry"] == b.params["geometry"]
        for key in ("mass", "crf_alpha", "light_tail"):
            assert a.params[key] == pytest.approx(b.params[key], rel=1e-5, abs=1e-9)
        assert a.prediction_error == pytest.approx(b.prediction_error, rel=1e-4)


@pytest.mark.parametrize("kwargs", [{}, {"grid": (2, 2)}, {"solver": "ls", "support": 25}])
def test_the_example_photo_gives_the_scipy_path_psfs(kwargs, monkeypatch):
    frames = [raw.load_frame(DATA / "img_example.pgm")]
    _assert_same(_estimates(frames, monkeypatch, False, **kwargs), _estimates(frames, monkeypatch, True, **kwargs))


def test_a_raw_file_gives_the_scipy_path_psfs(tmp_path, monkeypatch):
    """Four Bayer planes of a simulated RAW: the detection once and refined per plane, one pattern band."""
    dng = tmp_path / "target.dng"
    simulate.simulate_target(dng, psf=simulate.diffraction_psf(5.6, s=4, support=17), pixels_per_cell=0.37,
                             rotation_deg=3.0, sensor=(500, 600), centre=(0.5, 0.5), seed=1)
    frames = raw.load_frames(dng, "all")
    _assert_same(_estimates(frames, monkeypatch, False, workers=1),
                 _estimates(frames, monkeypatch, True, workers=1))


def _normal_matrix(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    a = np.random.default_rng(seed).standard_normal((4 * n + 3, n))
    return a.T @ a, a.T @ np.random.default_rng(seed + 1).standard_normal(4 * n + 3)


@pytest.mark.parametrize("n", [1, 2, 3, 4, 17, 289])
def test_the_cholesky_solve_is_scipys(n):
    q, c = _normal_matrix(n, n)
    expected = linalg.cho_solve(linalg.cho_factor(q), c)
    # condition numbers of these normal matrices are ~10-100: a few hundred ulps
    np.testing.assert_allclose(bernoulli._cholesky_solve(q, c), expected, rtol=1e-10, atol=1e-12)
    idx = np.flatnonzero(np.arange(n) % 3 != 1)
    block = q[np.ix_(idx, idx)]
    np.testing.assert_allclose(bernoulli._cholesky_solve(q, c, idx), linalg.cho_solve(linalg.cho_factor(block), c[idx]),
                               rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("q", [np.array([[1.0, 2.0], [2.0, 1.0]]), np.diag([1.0, 1.0, -1.0]), np.diag([1.0, 0.0, 1.0, 1.0]),
                               np.diag([2.0, 1.0, 1.0, 1.0, -1e-3])])
def test_a_matrix_that_is_not_positive_definite_is_refused(q):
    with pytest.raises(np.linalg.LinAlgError):
        linalg.cho_factor(q)
    with pytest.raises(np.linalg.LinAlgError):
        bernoulli._cholesky_solve(q, np.ones(len(q)))


@pytest.mark.parametrize("n", [1, 5, 32, 33, 100, 289, 625])
def test_the_triangular_inverse_is_lapacks(n):
    lower = np.linalg.cholesky(_normal_matrix(n, n)[0])
    expected = linalg.lapack.dtrtri(lower, lower=1)[0]
    ours = bernoulli._triangular_inverse(lower)
    assert np.array_equal(np.tril(ours), ours)
    np.testing.assert_allclose(ours, expected, rtol=0, atol=1e-12 * np.abs(expected).max())


def test_the_gram_matrix_is_the_symmetric_rank_update():
    a = np.random.default_rng(5).standard_normal((20000, 289)).astype(np.float32)
    ours = bernoulli._gram(a)
    assert ours.dtype == np.float32 and np.array_equal(ours, ours.T)
    # float32 sums of 20000 products of unit-variance terms: rounding ~1e-7 relative of ~2e4 on the diagonal
    np.testing.assert_allclose(ours, _scipy_gram(a), rtol=0, atol=5e-3)


# ---------------------------------------------------------------- the sharp-edge path without scipy


class _KDTreePoints:
    """`sharpedge._NearestPoints` by scipy.spatial.cKDTree, as the blind prediction queried it before."""

    def __init__(self, x, y):
        self.tree = cKDTree(np.column_stack([x, y]))

    def query(self, x, y, bound):
        distance, index = self.tree.query(np.column_stack([x, y]), distance_upper_bound=bound)
        return np.isfinite(distance), index


SHARP_EDGE_REFERENCE = [
    ("_gaussian_filter", lambda image, sd: ndimage.gaussian_filter(image, sd)),
    ("_bilinear", lambda image, y, x, nearest=False: ndimage.map_coordinates(
        image, [y, x], order=1, mode="nearest" if nearest else "constant")),
    ("_dilate", lambda mask, iterations: ndimage.binary_dilation(mask, iterations=iterations)),
    ("_NearestPoints", _KDTreePoints),
]


@pytest.mark.parametrize("shape", [(40, 50), (7, 9), (3, 200), (301, 280)])
def test_the_sharp_edge_filters_are_scipys_bit_for_bit(shape):
    from psfd.estimator import sharpedge

    rng = np.random.default_rng(shape[0])
    image = rng.normal(size=shape) * 100
    for dtype in (np.float64, np.float32):
        for sd in (0.7, 1.0, 1.6, 4.0):  # kernels wider than the small images: reflected more than once
            expected = ndimage.gaussian_filter(image.astype(dtype), sd)
            got = sharpedge._gaussian_filter(image.astype(dtype), sd)
            assert got.dtype == expected.dtype
            np.testing.assert_array_equal(got, expected)
    # inside, on the last row and column, just outside and far outside
    y = np.r_[rng.uniform(-2, shape[0] + 1, 4000), np.arange(shape[0]), -1e-9, shape[0] - 1 + 1e-9]
    x = np.r_[rng.uniform(-2, shape[1] + 1, 4000), np.full(shape[0], shape[1] - 1.0), 0.0, 0.0]
    for mode in ("constant", "nearest"):
        np.testing.assert_array_equal(sharpedge._bilinear(image, y, x, nearest=mode == "nearest"),
                                      ndimage.map_coordinates(image, [y, x], order=1, mode=mode))
    mask = rng.random(shape) > 0.97
    for iterations in (1, 2, 5):
        np.testing.assert_array_equal(sharpedge._dilate(mask, iterations),
                                      ndimage.binary_dilation(mask, iterations=iterations))


def test_the_nearest_edge_points_are_the_k_d_trees():
    """Around the edge points of the real photograph, at every s-grid sample of a crop: the same point found
    (or none within the bound) as by the k-d tree, wherever the nearest is not an exact tie."""
    from psfd.estimator import sharpedge

    frame = raw.load_frame(DATA / "IMG_0608_v1.pgm", "mono")
    crop = frame.data[300:600, 700:1100] / frame.white
    edges = sharpedge.detect_edges(crop, noise=sharpedge.noise_sigma(crop))
    assert len(edges) > 1000
    y, x = np.mgrid[0:300:0.25, 0:400:0.25]
    y, x = y.ravel(), x.ravel()
    tree = cKDTree(np.column_stack([edges.x, edges.y]))
    for bound in (2.0, 6.7):
        found, index = sharpedge._NearestPoints(edges.x, edges.y).query(x, y, bound)
        distance, expected = tree.query(np.column_stack([x, y]), k=2, distance_upper_bound=bound)
        np.testing.assert_array_equal(found, np.isfinite(distance[:, 0]))
        untied = found & (distance[:, 0] < distance[:, 1])
        assert untied.sum() > 0.99 * found.sum() > 10_000
        np.testing.assert_array_equal(index[untied], expected[untied, 0])


@pytest.mark.parametrize("photo, target_form", [("IMG_0608_v1.pgm", False), ("img_example.pgm", True)])
def test_the_sharp_edge_estimate_is_the_scipy_paths(photo, target_form, monkeypatch):
    """The whole sharp-edge estimate of a real photograph without scipy's filters and k-d tree: within 1e-3 of
    its noise floor of the scipy path's (the target form takes every tied nearest edge point, `_TiedPoints`,
    on both paths: the same bits)."""
    from psfd.estimator import sharpedge

    frame = raw.load_frame(DATA / photo, "mono")
    with bernoulli._one_blas_thread():
        [new] = sharpedge.estimate_edges(frame, target_form=target_form)
        with monkeypatch.context() as patch:
            for name, function in SHARP_EDGE_REFERENCE:
                patch.setattr(sharpedge, name, function)
            [old] = sharpedge.estimate_edges(frame, target_form=target_form)
    assert np.abs(new.psf - old.psf).max() <= 1e-3 * old.noise_floor / old.support  # of the floor per sample
    assert new.noise_floor == pytest.approx(old.noise_floor, rel=1e-6)
    if target_form:
        np.testing.assert_array_equal(new.psf, old.psf)


# --------------------------------------------------------------------------- sharp-edge PSF solve


def _former_gradient_operator(support):
    """The forward differences of eq. (5) as `sharpedge` built them: a scipy.sparse CSR matrix."""
    d = sparse.diags([-np.ones(support - 1), np.ones(support - 1)], [0, 1], shape=(support - 1, support))
    eye = sparse.identity(support)
    return sparse.vstack([sparse.kron(eye, d), sparse.kron(d, eye)]).tocsr()


def _former_solve_kernel(ata, atb, sigma, support, weight=sharpedge.LAMBDA):
    """`sharpedge.solve_kernel` as it was: Lawson-Hanson (scipy.optimize.nnls) on Q's Cholesky factor."""
    g = _former_gradient_operator(support)
    q = ata / sigma**2 + weight * support**2 * (g.T @ g).toarray()
    c = atb / sigma**2
    q[np.diag_indices_from(q)] += 1e-12 * np.trace(q) / q.shape[0]
    chol = linalg.cholesky(q, lower=True)
    k, _ = optimize.nnls(chol.T, linalg.solve_triangular(chol, c, lower=True), maxiter=50 * q.shape[0])
    return k.reshape(support, support), q


@pytest.mark.parametrize("support", [3, 5, 17, 33])
def test_the_smoothness_matrix_is_the_sparse_operators_normal_matrix(support):
    former = _former_gradient_operator(support)
    assert np.array_equal(sharpedge._smoothness_matrix(support), (former.T @ former).toarray())


@pytest.fixture(scope="module")
def edge_systems():
    """What `estimate_edges` hands to `solve_kernel` (its normal equations of eq. (5), sigma, support) on the real
    wall photo, blind, and on a simulated frame of the edge target, target form, at 9 x 9 and 17 x 17; and the
    photo's 17 x 17 PSFs on the current path."""
    from test_sharpedge import S as EDGE_S, SUPPORT as EDGE_SUPPORT, edge_frame

    systems, solve = [], sharpedge.solve_kernel

    def recorded(ata, atb, sigma, support, weight=sharpedge.LAMBDA):
        systems.append((ata, atb, sigma, support))
        return solve(ata, atb, sigma, support, weight)

    wall = raw.load_frame(DATA / "IMG_0608_v1.pgm", "mono")
    target = edge_frame(simulate.gaussian_psf(0.8, 0.5, theta=0.5, s=EDGE_S, support=EDGE_SUPPORT))
    patch = pytest.MonkeyPatch()
    patch.setattr(sharpedge, "solve_kernel", recorded)
    try:
        psfs = sharpedge.estimate_edges(wall, support=17)
        sharpedge.estimate_edges(wall, support=9)
        for support in (9, 17):
            sharpedge.estimate_edges(target, support=support, target_form=True)
    finally:
        patch.undo()
    assert [system[3] for system in systems] == [17, 9, 9, 17]
    return systems, psfs


@pytest.mark.parametrize("weight", [0.0, 2.0, 2e6])
def test_the_edge_kernel_is_the_scipy_paths_minimiser(edge_systems, weight):
    """The same strictly convex problem: the same Q bit for bit, and the same minimiser to 1e-9 of the kernel's
    peak (measured: 2e-15 to 2e-12), with the constraint active (zeros in the kernels) at every weight."""
    bound = 0
    for ata, atb, sigma, support in edge_systems[0]:
        k, q = sharpedge.solve_kernel(ata, atb, sigma, support, weight)
        k_former, q_former = _former_solve_kernel(ata, atb, sigma, support, weight)
        assert np.array_equal(q, q_former)
        assert np.abs(k - k_former).max() <= 1e-9 * np.abs(k_former).max()
        assert k.min() >= 0.0
        bound += int(np.count_nonzero(k_former == 0))
    assert bound > 0


def test_the_photos_edge_psf_is_the_scipy_paths(edge_systems, monkeypatch):
    psfs = edge_systems[1]
    monkeypatch.setattr(sharpedge, "solve_kernel", _former_solve_kernel)
    former = sharpedge.estimate_edges(raw.load_frame(DATA / "IMG_0608_v1.pgm", "mono"), support=17)
    assert len(psfs) == len(former) == 1
    for a, b in zip(psfs, former):
        assert np.abs(a.psf - b.psf).max() <= 1e-3 * b.noise_floor / b.support  # of the floor per sample
        assert a.noise_floor == pytest.approx(b.noise_floor, rel=1e-9)
        assert a.residual == pytest.approx(b.residual, rel=1e-6)
        ours, theirs = dict(a.params), dict(b.params)
        assert ours.pop("mass") == pytest.approx(theirs.pop("mass"), rel=1e-9)
        assert ours == theirs
