"""Every method's noise floor is one quantity: the expected L2 norm of the noise error of its unit-sum kernel.

Delbracio et al., IJCV 2012, sec. 3.1: the least-squares estimate's error
has E||h_e - h||^2 = sigma_n^2 trace((A^T A)^-1); the floor a PSF carries is
the square root, for the kernel as stored (unit sum). The sharp-edge
estimate's posterior (Joshi et al., CVPR 2008, eq. (5)) and the two-photo
fit's least squares give the same norm for theirs. The catalogue, the CSV,
the table and the figures read one unit whatever the method (the sharp-edge
floor was once the RMS per sample, 1/k of the norm, so it read 17x smaller
than a Bernoulli floor of the same noise).

Measured here against what the floor predicts: photographs of one scene that
differ only in their sensor noise. The spread of their PSFs (the RMS over
the shots of ||h_i - mean h||, with n - 1) is the noise error's norm. The
floor bounds it from above: the non-negative and regularised solutions are
projections that can only come closer than the least-squares one (the
posterior covariance of the regularised fit is larger than its sampling
covariance): the floors are 1.4x the spread on the Bernoulli target, 1.4x
(blind) and 4.6x (target form, whose noise is read on the print alone, where
its edges raise the median of `sharpedge.noise_sigma`) on the sharp edges and
2.4x on the pair in these renders. The spread of 4 shots over a 17 x 17 kernel is
known to about 10 % (hundreds of samples add up in it), so the bounds are
0.8 and 5 times the spread: a floor in another unit (the RMS per sample, 17x
smaller) fails them by far.
"""

from __future__ import annotations

import numpy as np
import pytest
import render

from psfd.estimator import bernoulli, sharpedge, simulate, twoscale

S = 4
SUPPORT = 17
SHOTS = 4


def _spread(psfs: list[np.ndarray]) -> float:
    """RMS over the shots of the L2 distance to their mean (n - 1): the norm of the noise error."""
    stack = np.array(psfs)
    return float(np.sqrt(((stack - stack.mean(axis=0)) ** 2).sum() / (len(psfs) - 1)))


def _check(method: str, estimates: list) -> None:
    spread = _spread([e.psf for e in estimates])
    floor = float(np.mean([e.noise_floor for e in estimates]))
    print(f"\n{method}: floor {floor:.4f}, spread of {len(estimates)} shots {spread:.4f} (ratio {floor / spread:.2f})")
    assert 0.8 * spread <= floor <= 5 * spread


def test_the_bernoulli_floor_is_the_norm_of_the_noise_error():
    shot = render.render(render.KINDS["defocus"], render.View(0.3, rotation_deg=10.0, tilt=(0.04, -0.03)), seed=1)
    photo = render.Exposure(electrons=5000.0)  # the noise of the published photograph
    _check("bernoulli", [bernoulli.estimate_target(shot.exposed(photo, seed=k).frame, support=SUPPORT)[0]
                         for k in range(SHOTS)])


@pytest.fixture(scope="module")
def edge_shots() -> list:
    """Photographs of the edge target that differ only in their noise (one render, its light exposed again)."""
    light = render.edge_target_light(render.KINDS["defocus"], rotation_deg=15.0)
    return [render.expose(light, render.Exposure(), k, "edge target")[0] for k in range(SHOTS)]


@pytest.mark.parametrize("target_form", [False, True], ids=["blind", "target form"])
def test_the_sharp_edge_floor_is_the_norm_of_the_noise_error(edge_shots, target_form):
    _check("sharp-edge", [sharpedge.estimate_edges(f, s=S, support=SUPPORT, target_form=target_form)[0]
                          for f in edge_shots])


def test_the_two_photo_floor_is_the_norm_of_the_noise_error():
    psf = simulate.gaussian_psf(0.45, 0.55, s=S, support=SUPPORT)
    scene = simulate.texture_scene((2 * 5 * 128 + 32,) * 2, seed=1)  # simulate_pair's own size at lam = 5
    pairs = [simulate.simulate_pair(psf=psf, s=S, lam=5.0, scene=scene, seed=k) for k in range(SHOTS)]
    _check("two-photo", [twoscale.estimate_pair(p["near"], p["far"], s=S)[0] for p in pairs])
