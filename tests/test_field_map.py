"""Each window's PSF is the PSF at that window's place on the sensor, through the forked workers as in one process.

Every other grid test renders one PSF over the whole frame. There, a PSF
returned for the wrong window (jobs regrouped for the workers, `_groups`,
and mapped back) would be as right as the true one. Here the left half of a
photograph of the target is rendered through a sharp kernel and the right
half through a wide one (tests/render.py, one geometry and one noise
realisation, the halves joined at the grid's boundary). A second photograph
is the other way round. Both go through one `estimate_frames` call with a
2 x 1 grid, which makes two groups of two jobs, in two workers and in one
process. Each PSF must have the width of its half, within 15 %: RMS widths
0.535 and 1.110 channel pixel for the truths on the 17 x 17 support,
measured 0.555-0.581 and 1.124-1.138 (the windows' wrong halves would be 2x off).
"""

from __future__ import annotations

import numpy as np
import pytest
import render

from psfd.estimator import bernoulli
from psfd.estimator.raw import Frame

S = 4
SHARP, WIDE = render.gaussian(0.35), render.gaussian(0.8)


def _joined(left: render.Render, right: render.Render, column: int, name: str) -> Frame:
    """The photograph ``left`` up to ``column`` and ``right`` from there on."""
    data = np.concatenate([left.frame.data[:, :column], right.frame.data[:, column:]], axis=1)
    saturated = np.concatenate([left.frame.saturated[:, :column], right.frame.saturated[:, column:]], axis=1)
    return Frame(data, left.frame.channel, left.frame.white, saturated, name)


@pytest.fixture(scope="module")
def halves():
    view = render.View(0.3, rotation_deg=10.0, tilt=(0.04, -0.03))
    sharp, wide = (render.render(kernel, view, seed=1) for kernel in (SHARP, WIDE))
    left, _ = bernoulli.estimate_target(sharp.frame, grid=(2, 1))
    column = left.window[2]  # where the grid splits the target
    return _joined(sharp, wide, column, "sharp-left"), _joined(wide, sharp, column, "wide-left")


@pytest.mark.parametrize("workers", [2, 1])
def test_each_window_has_the_psf_of_its_half(halves, workers):
    estimates = bernoulli.estimate_frames(list(halves), grid=(2, 1), workers=workers)
    truth = {kernel: render.rms_width(kernel.sampled(S, 17), S) for kernel in (SHARP, WIDE)}
    expected = {"sharp-left": (SHARP, WIDE), "wide-left": (WIDE, SHARP)}
    assert [e.sources[0] for e in estimates] == ["sharp-left", "sharp-left", "wide-left", "wide-left"]
    for est in estimates:
        kernel = expected[est.sources[0]][0 if est.field[0] < 0.5 else 1]
        width = render.rms_width(est.psf, S)
        print(f"\n{est.sources[0]} at x = {est.field[0]:.2f}: RMS width {width:.3f}, truth {truth[kernel]:.3f}")
        assert width == pytest.approx(truth[kernel], rel=0.15)
