"""Cluttered photographs holding the calibration target, for the detection tests.

Rendered independently of the estimator: the target is drawn from its vector
layout (DESIGN.md, "The published target layout", transcribed here rather
than taken from psfd.estimator.target), supersampled inside every photosite
and box-averaged; no code of psfd.estimator.simulate or resample is used.
Around it, the clutter that defeats a detector ranking saddle points over the
whole frame: dead leaves, checkerboard-like patches, text, a chain-link fence,
foliage against a clipped sky, dark shadows. The whole frame is then blurred
by a lens PSF (a Gaussian core plus a wide halo), exposed with shot and read
noise, quantised and clipped, either as an RGGB mosaic written as a real DNG
(psfd's writer; the tests decode it with rawpy) or as an 8-bit plane.

Coordinates: pixel (row i, column j) covers [j - 0.5, j + 0.5) x [i - 0.5,
i + 0.5); a homography maps pattern cells (x right, y down, 0..320) to pixels
of the rendered grid (photosites of the full sensor for a mosaic).

Also a 24-megapixel RAW without a target (`wall_raw24`): the real wall photo in
every Bayer plane, for the memory bounds of the sharp-edge and compare commands.
"""

from __future__ import annotations

import string
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from psfd.estimator import raw
from psfd.estimator.target import default_noise

# The published layout, in 32-cell blocks (DESIGN.md). Every other ring block is a white square.
SIZE, BLOCK = 320, 32
XCORNER_BLOCKS = ((9, 9), (9, 6), (9, 3), (9, 0), (6, 0), (3, 0), (0, 0), (0, 3), (0, 6), (0, 9), (3, 9), (6, 9))
BLACK_BLOCKS = ((9, 8), (9, 5), (9, 2), (8, 0), (5, 0), (2, 0), (0, 2), (0, 5), (0, 8), (2, 9), (5, 9), (8, 9))
_WHITE, _BLACK, _HOURGLASS, _NOISE = 0, 1, 2, 3
_KIND = np.full((10, 10), _NOISE, dtype=np.int8)
_KIND[[0, 9], :] = _KIND[:, [0, 9]] = _WHITE
for _bx, _by in BLACK_BLOCKS:
    _KIND[_by, _bx] = _BLACK
for _bx, _by in XCORNER_BLOCKS:
    _KIND[_by, _bx] = _HOURGLASS

# RGGB photosite offsets (row, col) of each plane, as psfd.estimator.raw names them.
OFFSETS = {"r": (0, 0), "g1": (0, 1), "g2": (1, 0), "b": (1, 1)}
GAINS = {"r": 0.55, "g1": 1.0, "g2": 1.0, "b": 0.75}  # daylight on a grey target, relative to green
SKY = 3.0  # radiance of the sky band in units of the green white level: clipped in every channel


def xcorners(homography: np.ndarray) -> np.ndarray:
    """(12, 2) image positions of the X-corner saddles, in the published order."""
    pts = np.array([[BLOCK * bx + BLOCK / 2, BLOCK * by + BLOCK / 2] for bx, by in XCORNER_BLOCKS])
    return _apply(homography, pts)


def reflectance(X: np.ndarray, Y: np.ndarray, noise: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Reflectance (0 black, 1 white) of the printed target at pattern points; NaN off the paper.

    ``margin`` cells of white paper surround the 320-cell layout.
    """
    Xc, Yc = np.clip(X, 0, SIZE - 1e-3), np.clip(Y, 0, SIZE - 1e-3)
    bx, by = (Xc // BLOCK).astype(np.int32), (Yc // BLOCK).astype(np.int32)
    kind = _KIND[by, bx]
    out = (kind != _BLACK).astype(np.float32)
    # Hourglass: black triangles on the block's top and bottom edges, apexes at its centre.
    hourglass = kind == _HOURGLASS
    u, v = Xc[hourglass] % BLOCK - BLOCK / 2, Yc[hourglass] % BLOCK - BLOCK / 2
    out[hourglass] = np.abs(u) >= np.abs(v)
    cells = kind == _NOISE
    out[cells] = noise[Yc[cells].astype(np.int32) - BLOCK, Xc[cells].astype(np.int32) - BLOCK]
    out[(X < 0) | (X >= SIZE) | (Y < 0) | (Y >= SIZE)] = 1.0
    out[(X < -margin) | (X >= SIZE + margin) | (Y < -margin) | (Y >= SIZE + margin)] = np.nan
    return out


def draw_target(
    canvas: np.ndarray,
    homography: np.ndarray,
    *,
    black: float = 0.04,
    white: float = 0.8,
    gradient: float = 0.1,
    margin: float = 0.0,
    supersample: int = 8,
    noise: np.ndarray | None = None,
) -> None:
    """Draw the target into ``canvas`` (radiance, modified in place), box-averaged over each pixel.

    Each pixel is sampled at ``supersample`` x ``supersample`` points; points
    on the paper take the ink or paper radiance (``black`` .. ``white``, lit
    with a linear ``gradient`` across the target), the others keep the
    canvas value. Blur comes later, on the whole frame. This is the one place
    that draws the target: a physically finer renderer can replace it.
    """
    noise = default_noise() if noise is None else noise
    inv = np.linalg.inv(homography)
    rim = np.array([[-margin, -margin], [SIZE + margin, -margin], [SIZE + margin, SIZE + margin], [-margin, SIZE + margin]])
    box = _apply(homography, rim)
    x0, y0 = np.maximum(np.floor(box.min(axis=0)).astype(int) - 1, 0)
    x1, y1 = np.minimum(np.ceil(box.max(axis=0)).astype(int) + 2, [canvas.shape[1], canvas.shape[0]])
    n = int(supersample)
    offsets = ((np.arange(n) + 0.5) / n - 0.5).astype(np.float32)
    step = max(1, 2_000_000 // ((x1 - x0) * n * n))  # rows per chunk: bounded memory
    # Local pixel coordinates keep float32 exact to well under a subsample.
    local = (inv @ np.array([[1.0, 0, x0], [0, 1, y0], [0, 0, 1]])).astype(np.float32)
    xs = (np.arange(x1 - x0, dtype=np.float32)[:, None] + offsets).reshape(-1)
    for r0 in range(y0, y1, step):
        r1 = min(r0 + step, y1)
        ys = (np.arange(r0 - y0, r1 - y0, dtype=np.float32)[:, None] + offsets).reshape(-1)
        X, Y = _apply_xy(local, xs[None, :], ys[:, None])
        value = reflectance(X, Y, noise, margin)
        value = (black + (white - black) * value) * (1.0 + gradient * (X + 0.5 * Y - 0.75 * SIZE) / SIZE)
        # Off the paper the pixel keeps the scene behind, in proportion.
        paper = ~np.isnan(value)
        shape = (r1 - r0, n, x1 - x0, n)
        inked = np.where(paper, value, 0.0).reshape(shape).sum(axis=(1, 3))
        covered = paper.reshape(shape).sum(axis=(1, 3))
        canvas[r0:r1, x0:x1] = (inked + canvas[r0:r1, x0:x1] * (n * n - covered)) / (n * n)


def target_homography(
    centre: tuple[float, float], scale: float, angle: float, tilt: tuple[float, float] = (0.0, 0.0)
) -> np.ndarray:
    """Pattern cells -> pixels: ``scale`` px per cell at the centre, turned by ``angle`` degrees.

    ``tilt`` = (px, py) magnifies the right (bottom) edge by about 1 + p and
    shrinks the left (top) one alike: a target seen slightly from the side.
    """
    half = SIZE / 2
    to_centre = np.array([[1.0, 0, -half], [0, 1, -half], [0, 0, 1]])
    persp = np.array([[1.0, 0, 0], [0, 1, 0], [-tilt[0] / half, -tilt[1] / half, 1]])
    a = np.deg2rad(angle)
    sim = np.array([[scale * np.cos(a), -scale * np.sin(a), centre[0]], [scale * np.sin(a), scale * np.cos(a), centre[1]],
                    [0, 0, 1]])
    return sim @ persp @ to_centre


# --------------------------------------------------------------------------- clutter


def clutter(
    shape: tuple[int, int], rng: np.random.Generator, unit: float = 1.0, outdoor: bool = True
) -> tuple[np.ndarray, int]:
    """A busy scene (radiance, 1 = white level of green) and the row where the sky band ends.

    ``unit`` is the size of a channel pixel in canvas pixels (2 on a sensor
    mosaic), so that the clutter has the same size in every channel plane.
    Indoors (``outdoor`` False) there is no sky band and no foliage against it (row 0).
    """
    rows, cols = shape
    canvas = np.full(shape, 0.3, dtype=np.float32)
    _dead_leaves(canvas, rng, unit)
    _shadows(canvas, rng)
    for _ in range(int(rng.integers(3, 7))):
        _checkerboard(canvas, rng, unit)
    _fence(canvas, rng, unit)
    _text(canvas, rng, unit)
    if not outdoor:
        return canvas, 0
    horizon = int(rows * rng.uniform(0.15, 0.3))
    canvas[:horizon] = SKY
    _foliage(canvas, rng, unit, horizon)
    return canvas, horizon


def _dead_leaves(canvas: np.ndarray, rng: np.random.Generator, unit: float) -> None:
    """Occluding discs, radii with density r^-3 (a scale-invariant texture, as natural images)."""
    rows, cols = canvas.shape
    lo, hi = 2.0 * unit, 150.0 * unit
    mean_area = np.pi * 2 * lo**2 * np.log(hi / lo)
    count = int(2.0 * rows * cols / mean_area)
    u = rng.random(count)
    radii = lo / np.sqrt(1 - u * (1 - (lo / hi) ** 2))  # inverse CDF of r^-3 on [lo, hi]
    xs, ys = rng.uniform(0, cols, count), rng.uniform(0, rows, count)
    levels = rng.uniform(0.03, 0.7, count)
    for x, y, r, v in zip(xs.astype(int), ys.astype(int), np.rint(radii).astype(int), levels):
        cv2.circle(canvas, (int(x), int(y)), int(r), float(v), -1)


def _shadows(canvas: np.ndarray, rng: np.random.Generator) -> None:
    rows, cols = canvas.shape
    for _ in range(int(rng.integers(1, 4))):
        w, h = int(cols * rng.uniform(0.1, 0.3)), int(rows * rng.uniform(0.1, 0.3))
        x, y = int(rng.integers(0, cols - w)), int(rng.integers(0, rows - h))
        canvas[y : y + h, x : x + w] *= rng.uniform(0.03, 0.1)


def _checkerboard(canvas: np.ndarray, rng: np.random.Generator, unit: float) -> None:
    """A sheared, turned board of dark squares on a light ground: true X-corners in the wrong layout."""
    rows, cols = canvas.shape
    n, m = int(rng.integers(3, 10)), int(rng.integers(3, 10))
    side = rng.uniform(4.0, 20.0) * unit
    a, shear = rng.uniform(0, np.pi), rng.uniform(-0.3, 0.3)
    basis = side * np.array([[np.cos(a), -np.sin(a) + shear * np.cos(a)], [np.sin(a), np.cos(a) + shear * np.sin(a)]])
    origin = np.array([rng.uniform(0, cols), rng.uniform(0, rows)])
    dark, light = rng.uniform(0.02, 0.15), rng.uniform(0.4, 0.9)
    ground = np.array([[0, 0], [n, 0], [n, m], [0, m]], dtype=np.float64)
    cv2.fillConvexPoly(canvas, np.rint(ground @ basis.T + origin).astype(np.int32), float(light))
    for i in range(n):
        for j in range(m):
            if (i + j) % 2 == 0:
                square = np.array([[i, j], [i + 1, j], [i + 1, j + 1], [i, j + 1]], dtype=np.float64)
                cv2.fillConvexPoly(canvas, np.rint(square @ basis.T + origin).astype(np.int32), float(dark))


def _fence(canvas: np.ndarray, rng: np.random.Generator, unit: float) -> None:
    """A chain-link fence: thin diagonal wires crossing at every mesh node."""
    rows, cols = canvas.shape
    w, h = int(cols * rng.uniform(0.15, 0.35)), int(rows * rng.uniform(0.1, 0.25))
    x, y = int(rng.integers(0, cols - w)), int(rng.integers(0, rows - h))
    patch = np.ascontiguousarray(canvas[y : y + h, x : x + w])
    mesh = rng.uniform(5.0, 12.0) * unit
    wire = max(1, int(round(unit)))
    level = float(rng.uniform(0.05, 0.2))
    for k in np.arange(-h, w + h, mesh):
        cv2.line(patch, (int(k), 0), (int(k + h), h), level, wire)
        cv2.line(patch, (int(k), 0), (int(k - h), h), level, wire)
    canvas[y : y + h, x : x + w] = patch


def _text(canvas: np.ndarray, rng: np.random.Generator, unit: float) -> None:
    """Signs: lines of dark letters on light boards and light letters on dark ones."""
    rows, cols = canvas.shape
    letters = string.ascii_uppercase + string.digits + "XX++"
    for _ in range(int(rng.integers(10, 30))):
        words = "".join(rng.choice(list(letters), int(rng.integers(4, 14))))
        size = rng.uniform(0.3, 1.6) * unit
        thick = max(1, int(round(rng.uniform(1, 3) * unit)))
        (tw, th), _ = cv2.getTextSize(words, cv2.FONT_HERSHEY_SIMPLEX, size, thick)
        x, y = int(rng.integers(4, max(5, cols - tw - 6))), int(rng.integers(th + 4, rows - 8))
        ink, board = (0.05, 0.75) if rng.random() < 0.6 else (0.8, 0.08)
        cv2.rectangle(canvas, (x - 4, y - th - 4), (x + tw + 4, y + 6), board, -1)
        mask = np.zeros((th + 12, tw + 10), dtype=np.uint8)  # putText draws on 8-bit images only
        cv2.putText(mask, words, (4, th + 4), cv2.FONT_HERSHEY_SIMPLEX, size, 255, thick)
        region = canvas[y - th - 4 : y + 8, x - 4 : x + tw + 6]
        region[mask[: region.shape[0], : region.shape[1]] > 127] = ink


def _foliage(canvas: np.ndarray, rng: np.random.Generator, unit: float, horizon: int) -> None:
    """Tree crowns on the sky line: dark leaves and twigs with clipped sky showing through."""
    rows, cols = canvas.shape
    for _ in range(int(rng.integers(6, 14))):
        radius = rng.uniform(40.0, 160.0) * unit
        cx, cy = rng.uniform(0, cols), horizon + rng.uniform(-1.0, 0.3) * radius
        trunk = (int(cx), int(cy + 1.8 * radius))
        cv2.line(canvas, (int(cx), int(cy)), trunk, 0.05, max(1, int(radius / 12)))
        # Twigs, then leaves: dense enough to cover about half of the crown.
        for _ in range(int(radius / unit)):
            a, r = rng.uniform(0, 2 * np.pi), radius * np.sqrt(rng.random())
            end = (int(cx + r * np.cos(a)), int(cy + r * np.sin(a)))
            cv2.line(canvas, trunk if rng.random() < 0.3 else (int(cx), int(cy)), end, 0.06, max(1, int(unit)))
        count = int(0.8 * radius**2 / (2.5 * unit) ** 2)
        a, r = rng.uniform(0, 2 * np.pi, count), radius * np.sqrt(rng.random(count))
        xs, ys = cx + r * np.cos(a), cy + r * np.sin(a)
        axes = rng.uniform(0.8, 3.5, (count, 2)) * unit
        turns = rng.uniform(0, 180, count)
        levels = rng.uniform(0.02, 0.25, count)
        for x, y, (p, q), t, v in zip(xs, ys, axes, turns, levels):
            cv2.ellipse(canvas, (int(x), int(y)), (int(round(p)), int(round(q))), float(t), 0, 360, float(v), -1)


def _lens_blur(canvas: np.ndarray, core: float, halo: float = 0.1) -> np.ndarray:
    """Lens PSF: a Gaussian core of ``core`` pixels (sigma) and a halo 6 times wider carrying ``halo`` of the energy.

    The halo is smooth, so it is computed on a 4 times smaller copy.
    """
    sharp = cv2.GaussianBlur(canvas, (0, 0), core)
    rows, cols = canvas.shape
    small = cv2.resize(canvas, (cols // 4, rows // 4), interpolation=cv2.INTER_AREA)
    wide = cv2.resize(cv2.GaussianBlur(small, (0, 0), 1.5 * core), (cols, rows), interpolation=cv2.INTER_LINEAR)
    return cv2.addWeighted(sharp, 1.0 - halo, wide, halo, 0.0)


# --------------------------------------------------------------------------- frames


@dataclass
class Scene:
    """A rendered frame and where its targets are.

    Attributes
    ----------
    homographies : list of ndarray
        Pattern cells -> rendered grid (sensor photosites for a mosaic) per target.
    image : ndarray or None
        The 8-bit plane (uint8), for plane scenes.
    path : Path or None
        The DNG, for mosaic scenes.
    """

    homographies: list[np.ndarray]
    scale: float  # channel pixels per cell at the target centre
    angle: float
    image: np.ndarray | None = None
    path: Path | None = None
    params: dict = field(default_factory=dict)

    def corners(self, channel: str | None = None, which: int = 0) -> np.ndarray:
        """True X-corners of target ``which`` in channel-plane pixels (``channel`` of a mosaic)."""
        return _to_plane(xcorners(self.homographies[which]), channel)

    def box(self, channel: str | None = None, which: int = 0, margin: int = 20) -> tuple[int, int, int, int]:
        """(x0, y0, x1, y1) of a crop around target ``which`` in plane pixels."""
        rim = np.array([[0, 0], [SIZE, 0], [SIZE, SIZE], [0, SIZE]], dtype=np.float64)
        pts = _to_plane(_apply(self.homographies[which], rim), channel)
        x0, y0 = np.floor(pts.min(axis=0)).astype(int) - margin
        x1, y1 = np.ceil(pts.max(axis=0)).astype(int) + margin
        return max(int(x0), 0), max(int(y0), 0), int(x1), int(y1)


def _to_plane(points: np.ndarray, channel: str | None) -> np.ndarray:
    """Sensor photosite coordinates to those of a Bayer plane (unchanged for a single plane)."""
    if channel is None:
        return points
    dy, dx = OFFSETS[channel]
    return (points - [dx, dy]) / 2.0


def _place(
    rng: np.random.Generator, shape: tuple[int, int], horizon: int, extent: float, taken: list[np.ndarray]
) -> tuple[float, float]:
    """A target centre below the sky band, inside the frame, away from other targets."""
    rows, cols = shape
    reach = extent * 0.75  # half-diagonal of the target plus its margin, with perspective
    for _ in range(1000):
        c = np.array([rng.uniform(reach, cols - reach), rng.uniform(horizon + reach, rows - reach)])
        if all(np.linalg.norm(c - t) > 2.2 * reach for t in taken):
            return float(c[0]), float(c[1])
    raise ValueError("frame too small for the targets")


def _fill_place(rng: np.random.Generator, shape: tuple[int, int], homography: np.ndarray, margin: float) -> tuple[float, float]:
    """A centre, anywhere, where the whole target (``homography``, centred at 0) fits in the frame."""
    rim = np.array([[-margin, -margin], [SIZE + margin, -margin], [SIZE + margin, SIZE + margin], [-margin, SIZE + margin]])
    outline = _apply(homography, rim)
    lo, hi = -outline.min(axis=0) + 4, np.array([shape[1], shape[0]]) - outline.max(axis=0) - 4
    if np.any(hi < lo):
        raise ValueError("frame too small for the target")
    return float(rng.uniform(lo[0], hi[0])), float(rng.uniform(lo[1], hi[1]))


def _layout_scene(
    shape: tuple[int, int], unit: float, seed: int, targets: int, scale: float | None, angle: float | None,
    fill: bool = False,
) -> tuple[np.ndarray, Scene]:
    """The radiance canvas with ``targets`` targets drawn in, before blur and exposure.

    ``fill``: one target placed anywhere its outline fits, with no paper
    margin, as a target shot close up at the bench that fills much of the
    frame (an indoor scene: no sky); otherwise targets sit below the sky
    band with room to spare.
    """
    rng = np.random.default_rng(seed)
    canvas, horizon = clutter(shape, rng, unit, outdoor=not fill)
    scale = float(rng.uniform(0.3, 0.5)) if scale is None else float(scale)
    angle = float(rng.uniform(0, 360)) if angle is None else float(angle)
    margin = float(rng.choice([0.0, 8.0, 40.0]))
    if fill:
        if targets != 1:
            raise ValueError("a frame-filling scene holds one target")
        margin = 0.0
    # Samples per pixel side: 8 up to a canvas pixel per cell; beyond, at
    # least 8 per cell side (a target of several pixels per cell fills
    # millions of pixels, and the refinement then averages many edge pixels).
    supersample = int(np.clip(np.ceil(8.0 / (scale * unit)), 2, 8))
    homographies, centres = [], []
    for k in range(targets):
        tilt = tuple(rng.uniform(-0.08, 0.08, 2))
        if fill:  # one target, turned by ``angle``
            centre = _fill_place(rng, shape, target_homography((0.0, 0.0), scale * unit, angle, tilt), margin)
        else:
            extent = (SIZE + 2 * margin) * scale * unit * 1.5
            centre = _place(rng, shape, horizon, extent, centres)
        centres.append(np.array(centre))
        turn = angle if k == 0 else float(rng.uniform(0, 360))
        h = target_homography(centre, scale * unit, turn, tilt)
        black, white = float(rng.uniform(0.02, 0.06)), float(rng.uniform(0.55, 0.85))  # ink and paper
        draw_target(canvas, h, black=black, white=white, gradient=float(rng.uniform(-0.15, 0.15)), margin=margin,
                    supersample=supersample)
        homographies.append(h)
    scene = Scene(homographies=homographies, scale=scale, angle=angle,
                  params={"seed": seed, "margin": margin, "horizon": horizon})
    return canvas, scene


def plane_scene(
    seed: int,
    shape: tuple[int, int] = (1301, 1953),
    scale: float | None = None,
    angle: float | None = None,
    targets: int = 1,
    blur: float | None = None,
    fill: bool = False,
) -> Scene:
    """An 8-bit single-channel plane (like one Bayer plane of a DSLR saved as PGM).

    ``scale`` (px per cell, 0.3-0.5 by default), ``angle`` (degrees, any by
    default) and the PSF core ``blur`` (sigma in px, 0.45-0.8 by default)
    are drawn from ``seed`` when not given; ``targets`` may be 0, 1 or 2.
    ``fill`` places one target wherever it fits, as a close-up at the bench
    that fills much of an indoor frame (see `_layout_scene`).
    """
    canvas, scene = _layout_scene(shape, 1.0, seed, targets, scale, angle, fill)
    rng = np.random.default_rng(seed + 1_000_003)
    blur = float(rng.uniform(0.45, 0.8)) if blur is None else blur
    light = _lens_blur(canvas, blur)
    # Shot plus read noise at 8 bits: 1.3 DN RMS at mid grey.
    dn = 255.0 * light
    dn += rng.standard_normal(dn.shape, dtype=np.float32) * np.sqrt(0.015 * np.maximum(dn, 0) + 0.3)
    scene.image = np.clip(np.rint(dn), 0, 255).astype(np.uint8)
    scene.params["blur"] = blur
    return scene


def raw_scene(
    path: str | Path,
    seed: int,
    sensor: tuple[int, int] = (4000, 6000),
    scale: float | None = None,
    angle: float | None = None,
    targets: int = 1,
    blur: float | None = None,
) -> Scene:
    """A 24-megapixel RGGB frame written as a DNG: 14-bit values, black level 512.

    ``scale`` is in channel-plane pixels per cell (a plane has half the
    sensor's resolution); ``blur`` is the PSF core in plane pixels.
    Each channel sees the radiance through its own gain and a slowly varying
    colour of the scene (the target itself is grey).
    """
    canvas, scene = _layout_scene(sensor, 2.0, seed, targets, scale, angle)
    rng = np.random.default_rng(seed + 1_000_003)
    blur = float(rng.uniform(0.35, 0.6)) if blur is None else blur
    light = _lens_blur(canvas, 2.0 * blur)
    black, white, electrons_per_dn, read = 512, 16383, 1.5, 3.0
    mosaic = np.empty(sensor, dtype=np.uint16)
    for name, (dy, dx) in OFFSETS.items():
        plane = light[dy::2, dx::2]
        tint = cv2.resize(rng.uniform(0.7, 1.3, (6, 9)).astype(np.float32), (plane.shape[1], plane.shape[0]),
                          interpolation=cv2.INTER_LINEAR)
        for k in range(len(scene.homographies)):  # the grey target keeps the light's colour only
            x0, y0, x1, y1 = scene.box(name, which=k, margin=40)
            tint[y0:y1, x0:x1] = 1.0
        signal = plane * tint * GAINS[name] * (white - black)
        noisy = signal + rng.standard_normal(signal.shape, dtype=np.float32) * np.sqrt(
            np.maximum(signal, 0) / electrons_per_dn + read**2)
        mosaic[dy::2, dx::2] = np.clip(np.rint(noisy + black), 0, white).astype(np.uint16)
    raw.write_dng(path, mosaic, pattern="RGGB", black=black, white=white)
    scene.path = Path(path)
    scene.params["blur"] = blur
    return scene


def plane_frame(scene: Scene, box: tuple[int, int, int, int] | None = None) -> raw.Frame:
    """The 8-bit plane (or a crop of it) as a psfd Frame."""
    data = scene.image.astype(np.float64)
    if box is not None:
        x0, y0, x1, y1 = box
        data = data[y0:y1, x0:x1]
    return raw.Frame(data=data, channel="mono", white=255.0, saturated=data >= 255, source="scene",
                     sensor_shape=data.shape)


def crop_frame(frame: raw.Frame, box: tuple[int, int, int, int]) -> raw.Frame:
    """A crop of a plane as a Frame of its own."""
    x0, y0, x1, y1 = box
    return raw.Frame(data=frame.data[y0:y1, x0:x1].copy(), channel=frame.channel, white=frame.white,
                     saturated=frame.saturated[y0:y1, x0:x1].copy(), source=frame.source,
                     offset=frame.offset, sensor_shape=frame.sensor_shape, from_mosaic=frame.from_mosaic)


def wall_raw24(path: Path) -> Path:
    """A 6000 x 4000 RGGB DNG at ``path`` whose four planes are the real wall photo (tests/data/IMG_0608_v1.pgm),
    mirrored into 3000 x 2000, 14 bits: real edges at the real photo's density."""
    near = Path(__file__).parent / "data" / "IMG_0608_v1.pgm"
    wall = cv2.imread(str(near), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 64
    row = np.hstack([wall, wall[:, ::-1]])[:, :3000]
    plane = np.vstack([row, row[::-1]])[:2000]
    mosaic = np.empty((4000, 6000), np.uint16)
    for dy in (0, 1):
        for dx in (0, 1):
            mosaic[dy::2, dx::2] = plane
    raw.write_dng(path, mosaic, white=16383)
    return path


def _apply(h: np.ndarray, points: np.ndarray) -> np.ndarray:
    x, y = _apply_xy(h, points[:, 0], points[:, 1])
    return np.column_stack([x, y])


def _apply_xy(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / w, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / w
