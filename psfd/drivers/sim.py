"""A simulated rig: a small RAW camera and a rail carrying a target, with a known PSF.

The camera renders real DNG files with `psfd.estimator.simulate` (the one
driver module allowed to use the estimator), so everything above the drivers
runs unchanged on it and can be checked against the true PSF.

Geometry (thin lens, focused on the target):

- rail X is the distance from the lens to the target along the optical axis (mm);
  magnification m = f / (X - f),
- rail Y and Z move the target sideways and up/down (mm): its image moves by m*Y, m*Z
  on the sensor, which is how a plan visits the field,
- one target cell of ``cell_mm`` images to m * cell_mm / channel_pitch channel pixels
  (the channel pitch of a Bayer plane is twice the photosite pitch).

Optics: the PSF of each channel is diffraction of a circular pupil at the set
aperture (wavelengths 0.61 / 0.53 / 0.46 um for r / g / b) on the channel
pixel aperture, plus astigmatism and coma along the radial direction growing
linearly from zero at the image centre to ``corner_aberration`` waves at the
corners. The whole target is rendered with the PSF at its centre (the target
covers a small part of the field); `SimRig.truth` returns that PSF.

State: like a real camera and rail, the rig opened by a command (`psfd.drivers.open_rig`)
remembers its settings, its rail position and its shutter count from one
command to the next, in a small JSON file (`state_path`:
``$XDG_DATA_HOME/psfd/sim-rig.json``); ``psfd rail home --simulate`` removes it
first, so the simulated rig starts afresh (default settings, shutter count 0) at home.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy import fft

from psfd.drivers.base import CameraInfo, CameraReady, CameraSetup, Position, RailInfo, target_distance
from psfd.drivers.recording import free_name
from psfd.errors import BadInputError, CameraError, PsfdError, RailError
from psfd.estimator import simulate
from psfd.exif import exposure_seconds
from psfd.vocabulary import MAX_PIXELS, check_s, check_support, data_dir, offered_choice

APERTURES = ("2.8", "4", "5.6", "8", "11", "16", "22")
SHUTTERSPEEDS = ("1/30", "1/60", "1/125", "1/250", "1/500")
ISOS = ("100", "200", "400", "800")
IMAGEFORMATS = ("RAW", "RAW + JPEG")
CAPTURETARGETS = ("Internal RAM", "Memory card")
CHOICES = {
    "aperture": APERTURES,
    "shutterspeed": SHUTTERSPEEDS,
    "iso": ISOS,
    "imageformat": IMAGEFORMATS,
    "capturetarget": CAPTURETARGETS,
}
DEFAULT_SETTINGS = {"aperture": "5.6", "shutterspeed": "1/125", "iso": "100", "imageformat": "RAW",
                    "capturetarget": "Internal RAM"}
WAVELENGTH_UM = {"r": 0.61, "g1": 0.53, "g2": 0.53, "b": 0.46}
SCENES = ("bernoulli", "texture")
TEXTURE_RASTER = 2048  # raster pixels per side of the textured plane
# What a camera and lens on a lab rail can be (photosites of phones to scientific sensors, fisheye to long
# telephoto, a cell of the printed target or the textured plane from a pocket print to a wall): a value
# outside is a slip, and the renderer would take all memory for it (pitch_um = 1e9: a 8e6-pixel-wide raster).
OPTICS_RANGES = {"pitch_um": (0.5, 50.0, "um"), "focal_mm": (4.0, 2000.0, "mm"), "cell_mm": (0.01, 100.0, "mm"),
                 "texture_mm": (10.0, 100_000.0, "mm")}
# The scene's raster pixels (simulate.RASTER per target cell, TEXTURE_RASTER per textured plane) one channel
# pixel may cover: the scene is low-passed to the channel's band on a raster padded by 8/s of them per side
# (simulate.bandlimit_scene), so this bounds the padding. 160 is a target cell at 1/20 channel pixel, the
# whole target 16 pixels wide, far below the estimator's range (0.175 to 0.5 pixel at s = 4, IJCV 2012 sec. 3).
RASTER_PER_PIXEL_MAX = 160.0


def _number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and bool(np.isfinite(value))


def option_problems(options: dict) -> list[str]:
    """Every problem of the simulated rig's options (`SimRig`'s parameters, a plan's [rig] keys), one
    sentence each, checked before anything is rendered: a bad value would otherwise fail only at the
    first frame, deep in the renderer (a negative seed, s = 0, an even support, an odd sensor side).
    """
    problems = []
    if "scene" in options and options["scene"] not in SCENES:
        problems.append(f"scene must be {' or '.join(map(repr, SCENES))}, got {options['scene']!r}")
    seed = options.get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
        problems.append(f"seed must be a non-negative integer, got {seed!r}")
    sensor = options.get("sensor", (480, 640))
    if not (isinstance(sensor, (list, tuple)) and len(sensor) == 2
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 0 and n % 2 == 0 for n in sensor)):
        problems.append(f"sensor must be [rows, columns], two positive even integers, got {sensor!r}")
    elif sensor[0] * sensor[1] > MAX_PIXELS:  # the size psfd reads at most (`psfd.vocabulary.check_image_size`)
        problems.append(f"sensor must have at most {MAX_PIXELS:,} photosites, got {sensor[0]} x {sensor[1]}")
    problems += [f"{key} must be a number from {lo:g} to {hi:g} {unit}, got {options[key]!r}"
                 for key, (lo, hi, unit) in OPTICS_RANGES.items()
                 if key in options and not (_number(options[key]) and lo <= options[key] <= hi)]
    for check, key in ((check_s, "s"), (check_support, "support")):
        try:
            check(options.get(key, 17 if key == "support" else 4), key)
        except BadInputError as exc:
            problems.append(str(exc))
    aberration = options.get("corner_aberration", 0.0)
    if not (_number(aberration) and aberration >= 0):
        problems.append(f"corner_aberration must be a number of waves, 0 or more, got {aberration!r}")
    exposure = options.get("exposure", 0.75)
    if not (_number(exposure) and 0 < exposure <= 1):
        problems.append(f"exposure must be a fraction of the raw range, above 0 and at most 1, got {exposure!r}")
    return problems + _limit_problems(options.get("limits", {"x": (0.0, 0.0)}))


def _limit_problems(limits: object) -> list[str]:
    if not isinstance(limits, dict) or "x" not in {str(k).lower() for k in limits}:
        return [f"limits must be a table of axes with an X axis, e.g. {{ x = [200, 3000] }}, got {limits!r}"]
    return [f"limits.{axis} must be [low, high] with low <= high, got {pair!r}" for axis, pair in limits.items()
            if not (isinstance(pair, (list, tuple)) and len(pair) == 2 and all(map(_number, pair))
                    and pair[0] <= pair[1])]


@dataclass
class SimRig:
    """A simulated camera and rail sharing one state.

    Parameters
    ----------
    scene : str
        ``bernoulli`` (the published calibration target) or ``texture`` (a
        textured plane for near/far pairs).
    seed : int
        Seed of the image noise (each capture draws from seed + capture number) and of the texture.
    sensor : (int, int)
        Photosites (rows, cols), RGGB.
    pitch_um : float
        Photosite pitch.
    focal_mm : float
        Focal length of the lens.
    cell_mm : float
        Printed size of one target cell (the 320-cell target is 32 mm wide by default).
    texture_mm : float
        Side of the textured plane (it fills the frame from the far distance of `pair_distances`).
    s, support : int
        Grid factor and odd support (s-grid samples) of the rendered PSF.
    corner_aberration : float
        Astigmatism + coma at the image corners, in waves.
    exposure : float
        Fraction of the raw range reached by white (the camera exposes automatically).
    limits : dict
        Rail travel per axis in mm.
    state_file : path or None
        Where settings, rail position and shutter count are kept between processes (None: not kept).
    """

    scene: str = "bernoulli"
    seed: int = 0
    sensor: tuple[int, int] = (480, 640)
    pitch_um: float = 8.0
    focal_mm: float = 50.0
    cell_mm: float = 0.1
    texture_mm: float = 240.0
    s: int = 4
    support: int = 17
    corner_aberration: float = 0.35
    exposure: float = 0.75
    limits: dict = field(default_factory=lambda: {"x": (200.0, 3000.0), "y": (-60.0, 60.0), "z": (-45.0, 45.0)})
    state_file: str | os.PathLike | None = None
    settings: dict = field(init=False)
    pos: Position = field(init=False)
    captures: int = field(init=False, default=0)
    last_truth: dict | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        problems = option_problems({f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.init})
        if problems:
            raise ValueError(problems[0])
        self.sensor = (int(self.sensor[0]), int(self.sensor[1]))
        self.limits = {k.lower(): (float(lo), float(hi)) for k, (lo, hi) in self.limits.items()}
        self.settings = dict(DEFAULT_SETTINGS)
        x = min(max(self.distance_for_scale(0.25), self.limits["x"][0]), self.limits["x"][1])
        self.pos = Position(x=x, y=0.0 if "y" in self.limits else None, z=0.0 if "z" in self.limits else None)
        self._faults: dict[str, list[PsfdError]] = {"camera": [], "rail": []}
        self.camera = SimCamera(self)
        self.rail = SimRail(self)
        self._load_state()

    # ------------------------------------------------------------------ state between processes

    def _load_state(self) -> None:
        """Settings, position and shutter count from `state_file`; whatever is missing, unknown or outside
        this rig's choices and travel keeps its default (a file written by another version or rig)."""
        if self.state_file is None:
            return
        try:
            state = json.loads(Path(self.state_file).read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return
        if not isinstance(state, dict):
            return
        settings = state.get("settings") if isinstance(state.get("settings"), dict) else {}
        for name, value in settings.items():
            if name in CHOICES and value in CHOICES[name]:
                self.settings[name] = value
        pos = state.get("position") if isinstance(state.get("position"), dict) else {}
        axes = {}
        for axis in ("x", "y", "z"):
            value = pos.get(axis)
            if axis in self.limits and isinstance(value, (int, float)):
                lo, hi = self.limits[axis]
                axes[axis] = float(value) if lo <= value <= hi else getattr(self.pos, axis)
        self.pos = dataclasses.replace(self.pos, **axes)
        if isinstance(state.get("captures"), int) and state["captures"] >= 0:
            self.captures = state["captures"]

    def save_state(self) -> None:
        """Write settings, position and shutter count to `state_file` (atomically; nothing when None)."""
        if self.state_file is None:
            return
        path = Path(self.state_file)
        state = {"settings": self.settings, "position": dataclasses.asdict(self.pos), "captures": self.captures}
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=".sim-rig.", suffix=".json", dir=path.parent)
            with os.fdopen(fd, "w", encoding="utf-8") as stream:
                json.dump(state, stream, indent=1)
            os.replace(tmp, path)
        except OSError as exc:
            with contextlib.suppress(NameError, OSError):
                os.unlink(tmp)
            raise CameraError(f"cannot keep the simulated rig's state in {path}: {exc.strerror or exc}") from None

    # ------------------------------------------------------------------ optics

    @property
    def channel_pitch_mm(self) -> float:
        return 2.0 * self.pitch_um / 1000.0

    def magnification(self, distance_mm: float | None = None) -> float:
        """Thin-lens magnification f / (d - f) at target distance d (default: the rail X)."""
        d = self.pos.x if distance_mm is None else float(distance_mm)
        if d <= self.focal_mm:
            raise CameraError(f"target at {d:g} mm is inside the focal length ({self.focal_mm:g} mm)")
        return self.focal_mm / (d - self.focal_mm)

    def pixels_per_cell(self, distance_mm: float | None = None) -> float:
        """Channel pixels covered by one target cell at distance d (1/t of IJCV 2012 sec. 3)."""
        return self.magnification(distance_mm) * self.cell_mm / self.channel_pitch_mm

    def distance_for_scale(self, pixels_per_cell: float = 0.25) -> float:
        """Rail X (mm) at which one target cell images to ``pixels_per_cell`` channel pixels.

        Inverts m * cell / pitch = p with m = f / (d - f): d = f (1 + cell / (p * pitch)).
        With s = 4 the paper's well-conditioned range s/t in [0.7, 2] is p in [0.175, 0.5].
        """
        if pixels_per_cell <= 0:
            raise ValueError("pixels_per_cell must be positive")
        return target_distance(pixels_per_cell, self.focal_mm, self.pitch_um, self.cell_mm)

    def scene_problems(self, distances: list[float], apertures: list[float]) -> list[str]:
        """Why the rig cannot render its scene with the target at these rail distances (mm) and f-numbers,
        one sentence each.

        The target must stand beyond the focal length and image large enough for the renderer
        (`RASTER_PER_PIXEL_MAX`); the photosites must be no finer than the PSF grid renders at the
        smallest aperture (`simulate.finest_pitch_um`, at s and the reddest channel).
        """
        problems = []
        if apertures:
            fnumber = max(apertures)
            finest = simulate.finest_pitch_um(fnumber, max(WAVELENGTH_UM.values()), self.s) / 2  # a channel: 2 sites
            if self.pitch_um < finest:
                problems.append(f"pitch_um = {self.pitch_um:g} is finer than the simulated PSF renders at s = {self.s} "
                                f"and f/{fnumber:g} ({finest:.2g} um at least)")
        inside = sorted({d for d in distances if d <= self.focal_mm})
        if inside:
            problems.append(f"x = {', '.join(f'{d:g}' for d in inside)} inside the focal length "
                            f"(focal_mm = {self.focal_mm:g})")
        small = [d for d in sorted(set(distances)) if d > self.focal_mm
                 and self.raster_per_pixel(d) > RASTER_PER_PIXEL_MAX]
        if small:
            what = ("a target cell (cell_mm)" if self.scene == "bernoulli" else "the textured plane (texture_mm)")
            problems.append(f"at x = {small[0]:g} {what} images to {self._scene_pixels(small[0]):.3g} channel pixels "
                            f"(pitch_um = {self.pitch_um:g}, focal_mm = {self.focal_mm:g}), too small to simulate "
                            f"(at least {self._scene_pixels_min():.3g})")
        return problems

    def raster_per_pixel(self, distance_mm: float | None = None) -> float:
        """Scene raster pixels a channel pixel covers with the target at ``distance_mm`` (default: the rail X)."""
        return (simulate.RASTER if self.scene == "bernoulli" else TEXTURE_RASTER) / self._scene_pixels(distance_mm)

    def _scene_pixels(self, distance_mm: float | None = None) -> float:
        """Channel pixels a target cell (bernoulli) or the textured plane (texture) images to."""
        side = self.cell_mm if self.scene == "bernoulli" else self.texture_mm
        return self.magnification(distance_mm) * side / self.channel_pitch_mm

    def _scene_pixels_min(self) -> float:
        return (simulate.RASTER if self.scene == "bernoulli" else TEXTURE_RASTER) / RASTER_PER_PIXEL_MAX

    def field(self, position: Position | None = None) -> tuple[float, float]:
        """Normalised image (x, y) of the target centre for a rail position (default: the current one)."""
        pos = self.pos if position is None else position
        m = self.magnification(pos.x)
        rows, cols = self.sensor
        width_mm, height_mm = cols * self.pitch_um / 1000.0, rows * self.pitch_um / 1000.0
        return 0.5 + m * (pos.y or 0.0) / width_mm, 0.5 + m * (pos.z or 0.0) / height_mm

    def position_for(self, field_xy: tuple[float, float], pixels_per_cell: float = 0.25) -> Position:
        """Rail position that images the target centre at normalised field point ``field_xy`` at that scale."""
        x = self.distance_for_scale(pixels_per_cell)
        m = self.magnification(x)
        rows, cols = self.sensor
        width_mm, height_mm = cols * self.pitch_um / 1000.0, rows * self.pitch_um / 1000.0
        return Position(x=x, y=(field_xy[0] - 0.5) * width_mm / m, z=(field_xy[1] - 0.5) * height_mm / m)

    def field_offsets(self, n: int, pixels_per_cell: float = 0.25, margin: float = 0.03) -> tuple[list, list]:
        """Rail Y and Z values (mm) putting the target on an n x n grid of field points, all in frame.

        The grid spans the field as far as the whole target (320 cells) stays ``margin``
        (normalised) inside the image; returns (ys, zs), one list per axis.
        """
        rows, cols = self.sensor
        half_x = 160 * pixels_per_cell / (cols / 2)  # half the target, normalised
        half_y = 160 * pixels_per_cell / (rows / 2)
        if n < 1 or half_x + margin >= 0.5 or half_y + margin >= 0.5:
            raise ValueError("the target does not fit in the frame at this scale")
        fx = np.linspace(half_x + margin, 1 - half_x - margin, n) if n > 1 else np.array([0.5])
        fy = np.linspace(half_y + margin, 1 - half_y - margin, n) if n > 1 else np.array([0.5])
        ys = [round(self.position_for((f, 0.5), pixels_per_cell).y, 3) for f in fx]
        zs = [round(self.position_for((0.5, f), pixels_per_cell).z, 3) for f in fy]
        return ys, zs

    def pair_distances(self, ratio: float = 4.0, far: float = 2200.0) -> tuple[float, float]:
        """Rail X of a near/far pair whose magnifications differ by ``ratio``.

        The two-photo method needs the ratio above the super-resolution factor s
        (Delbracio et al., SIAM J. Imaging Sci. 2012, sec. 4; IPOL 2013 suggests 2 to 8);
        4 suits s = 3. Magnification f / (d - f) gives near = f + (far - f) / ratio.
        """
        return self.focal_mm + (far - self.focal_mm) / ratio, float(far)

    def truth(self, aperture: float | str, field_xy: tuple[float, float], channel: str = "g1") -> np.ndarray:
        """The PSF (s-grid, unit sum) of ``channel`` at f-number ``aperture`` and normalised field point: the
        optics band-limited to the s-grid's band (`simulate.diffraction_psf`), so its MTF is the lens's own."""
        if channel not in WAVELENGTH_UM:
            raise ValueError(f"unknown channel {channel!r}")
        rows, cols = self.sensor
        return _psf(float(aperture), round(float(field_xy[0]), 4), round(float(field_xy[1]), 4), cols / rows,
                    WAVELENGTH_UM[channel], 2.0 * self.pitch_um, self.s, self.support,
                    self.corner_aberration).copy()

    # ------------------------------------------------------------------ faults for tests

    def fail_next(self, device: str, error: PsfdError) -> None:
        """Make the next request to ``device`` (``camera`` or ``rail``) raise ``error``."""
        self._faults[device].append(error)

    def _check_fault(self, device: str) -> None:
        if self._faults[device]:
            raise self._faults[device].pop(0)

    # ------------------------------------------------------------------ rendering

    def render(self, path: Path) -> dict:
        """Render the current view to a DNG at ``path``; returns the simulation's ground truth."""
        problems = self.scene_problems([self.pos.x], [float(self.settings["aperture"])])
        if problems:  # a plan is refused before it runs (psfd.daemon.plan); a capture by hand is refused here
            raise CameraError(f"the simulated camera cannot render this view: {problems[0]}")
        aperture = float(self.settings["aperture"])
        fx, fy = self.field()
        psfs = {c: self.truth(aperture, (fx, fy), c) for c in WAVELENGTH_UM}
        seed = self.seed * 100003 + self.captures
        if self.scene == "bernoulli":
            truth = simulate.simulate_target(
                path, psf=psfs, s=self.s, pixels_per_cell=self.pixels_per_cell(), centre=(fx, fy),
                sensor=self.sensor, seed=seed, exposure=self.exposure, exif=self.exif(),
            )
        else:
            truth = simulate.simulate_scene(
                path, scene=_texture(self.seed), sensor_to_scene=self._sensor_to_texture(), psf=psfs,
                s=self.s, sensor=self.sensor, seed=seed, exposure=self.exposure, exif=self.exif(),
            )
        truth.update(aperture=aperture, field=(fx, fy), distance_mm=self.pos.x,
                     pixels_per_cell=self.pixels_per_cell(), scene=self.scene)
        return truth

    def exif(self) -> dict:
        """The EXIF a real camera would write with the current settings (keys of `psfd.exif.FrameMetadata`)."""
        return {
            "make": "psfd", "model": "psfd simulated camera", "serial": f"SIM-{self.seed}",
            "lens": f"simulated {self.focal_mm:g} mm", "lens_serial": f"SIM-LENS-{self.seed}",
            "focal_length_mm": self.focal_mm, "f_number": float(self.settings["aperture"]),
            "exposure_s": exposure_seconds(self.settings["shutterspeed"]),
            "iso": float(self.settings["iso"]), "pixel_pitch_um": self.pitch_um,
            "focus_distance_m": self.pos.x / 1000.0,  # the simulated lens is focused on the target
        }

    def _sensor_to_texture(self):
        """Photosite (x, y) -> texture raster (X, Y) for the current rail position."""
        rows, cols = self.sensor
        m = self.magnification()
        mm_per_photosite = self.pitch_um / 1000.0 / m  # on the plane
        raster_per_mm = TEXTURE_RASTER / self.texture_mm
        cx, cy = (cols - 1) / 2, (rows - 1) / 2
        centre = (TEXTURE_RASTER - 1) / 2
        y_off, z_off = self.pos.y or 0.0, self.pos.z or 0.0

        def to_scene(x, y):
            px = (np.asarray(x, np.float64) - cx) * mm_per_photosite - y_off
            py = (np.asarray(y, np.float64) - cy) * mm_per_photosite - z_off
            return centre + px * raster_per_mm, centre + py * raster_per_mm

        return to_scene


def state_path() -> Path:
    """Where the simulated rig opened by commands keeps its state: ``$XDG_DATA_HOME/psfd/sim-rig.json``."""
    return data_dir() / "sim-rig.json"


@functools.lru_cache(maxsize=256)
def _psf(fnumber: float, fx: float, fy: float, aspect: float, wavelength: float, channel_pitch: float, s: int,
         support: int, corner: float) -> np.ndarray:
    # Radial aberration vector along the field point's radius on the sensor (``aspect``: columns / rows; the
    # normalised field's diagonal is not the sensor's), zero on axis, |a| = corner at the corners.
    ax, ay = (2 * fx - 1) * aspect, 2 * fy - 1
    ax, ay = ax * corner / np.hypot(aspect, 1.0), ay * corner / np.hypot(aspect, 1.0)
    psf = simulate.diffraction_psf(fnumber, wavelength_um=wavelength, pitch_um=channel_pitch, s=s,
                                   support=support, aberration=(ax, ay))
    psf.flags.writeable = False  # shared by the cache
    return psf


@functools.lru_cache(maxsize=4)
def _texture(seed: int) -> np.ndarray:
    """A textured plane with a natural-image-like 1/f amplitude spectrum, reflectance in [0.05, 0.95].

    Scale-free texture keeps detail at every distance, which a near/far pair needs
    (Delbracio et al., IPOL 2013: the scene must hold enough texture at both scales).
    """
    rng = np.random.default_rng(10_000 + seed)
    n = TEXTURE_RASTER
    fy = fft.fftfreq(n)[:, None]
    fx = fft.rfftfreq(n)[None, :]
    radius = np.hypot(fx, fy)
    radius[0, 0] = 1.0
    spectrum = (rng.normal(size=radius.shape) + 1j * rng.normal(size=radius.shape)) / radius
    spectrum[0, 0] = 0.0
    texture = fft.irfft2(spectrum, s=(n, n), workers=-1)
    texture = (texture - texture.mean()) / (4.0 * texture.std())
    texture = np.clip(0.5 + texture, 0.05, 0.95).astype(np.float32)
    texture.flags.writeable = False  # shared by the cache
    return texture


def open_rail(config: dict) -> "SimRail":
    """A simulated rail alone (``rail = "simulated"`` beside a real camera): instant moves within ``rail_limits``."""
    limits = config.get("rail_limits")
    return SimRig(**({"limits": limits} if limits else {})).rail


class SimCamera:
    """`Camera` of a `SimRig`: offers the usual settings and captures rendered DNGs."""

    def __init__(self, rig: SimRig) -> None:
        self.rig = rig

    def info(self) -> CameraInfo:
        self.rig._check_fault("camera")
        return CameraInfo(model="psfd simulated camera", serial=f"SIM-{self.rig.seed}",
                          lens=f"simulated {self.rig.focal_mm:g} mm", focal_length_mm=self.rig.focal_mm, port="sim")

    def get(self, name: str) -> str:
        self.rig._check_fault("camera")
        return self.rig.settings[self._known(name)]

    def choices(self, name: str) -> list[str]:
        self.rig._check_fault("camera")
        return list(CHOICES[self._known(name)])

    def set(self, name: str, value: str) -> None:
        self.rig._check_fault("camera")
        offered = CHOICES[self._known(name)]
        choice = offered_choice(str(value), list(offered))
        if choice is None:
            raise CameraError(f"{name} {value} is not offered by the camera (offered: {', '.join(offered)})")
        self.rig.settings[name] = choice
        self.rig.save_state()

    def prepare(self, setup: CameraSetup) -> CameraReady:
        """RAW format and capture target as asked; the simulated lens has a fixed focus and no mirror."""
        self.rig._check_fault("camera")
        if setup.raw and "RAW" not in self.rig.settings["imageformat"]:
            self.rig.settings["imageformat"] = "RAW"
        self.rig.settings["capturetarget"] = CAPTURETARGETS[0 if setup.capture_target == "ram" else 1]
        self.rig.save_state()
        image_format = self.rig.settings["imageformat"]
        return CameraReady(
            image_format=image_format, files_per_exposure=2 if "JPEG" in image_format else 1,
            capture_target=self.rig.settings["capturetarget"], focus="manual",
            focus_detail="simulated lens: fixed focus", exposure_delay=None, drive_mode=None,
            settle_s=0.0,  # a simulated rail does not shake
        )

    def capture(self, dest: Path) -> list[Path]:
        """Render one exposure into ``dest``: a DNG, plus a JPEG preview in RAW + JPEG mode."""
        self.rig._check_fault("camera")
        dest = Path(dest)
        dest.mkdir(parents=True, exist_ok=True)
        self.rig.captures += 1
        self.rig.save_state()
        stem = f"SIM_{self.rig.captures:04d}"
        dng = free_name(dest, f"{stem}.DNG")
        truth = self.rig.render(dng)
        self.rig.last_truth = truth
        files = [dng]
        if self.rig.settings["imageformat"] == "RAW + JPEG":
            files.append(_write_preview(dng, free_name(dest, f"{stem}.JPG")))
        return files

    def close(self) -> None:
        pass

    @staticmethod
    def _known(name: str) -> str:
        if name not in CHOICES:
            raise CameraError(f"camera has no setting {name!r} (has: {', '.join(CHOICES)})")
        return name


class SimRail:
    """`Rail` of a `SimRig`: instant moves within the rig's travel limits."""

    def __init__(self, rig: SimRig) -> None:
        self.rig = rig

    def home(self) -> Position:
        """Go home: X at its low limit, Y and Z at 0."""
        self.rig._check_fault("rail")
        self.rig.pos = Position(x=self.rig.limits["x"][0], y=self._zero("y"), z=self._zero("z"))
        self.rig.save_state()
        return self.rig.pos

    def move(self, x: float | None = None, y: float | None = None, z: float | None = None) -> Position:
        self.rig._check_fault("rail")
        target = {"x": x, "y": y, "z": z}
        if all(v is None for v in target.values()):
            raise RailError("move needs at least one axis position")
        current = dataclasses.asdict(self.rig.pos)
        for axis, value in target.items():
            if value is None:
                continue
            if axis not in self.rig.limits:
                raise RailError(f"rail has no {axis.upper()} axis")
            lo, hi = self.rig.limits[axis]
            if not lo <= float(value) <= hi:
                raise RailError(f"{axis.upper()}={float(value):g} mm is outside the soft limits [{lo:g}, {hi:g}] mm")
            current[axis] = float(value)
        self.rig.pos = Position(**current)
        self.rig.save_state()
        return self.rig.pos

    def position(self) -> Position:
        self.rig._check_fault("rail")
        return self.rig.pos

    def info(self) -> RailInfo:
        self.rig._check_fault("rail")
        return RailInfo(controller="psfd simulated rail", axes=tuple(self.rig.limits), travel=dict(self.rig.limits),
                        units="mm", homing=True, state="Idle")

    def unlock(self) -> Position:
        self.rig._check_fault("rail")
        return self.rig.pos  # never locked

    def close(self) -> None:
        pass

    def _zero(self, axis: str) -> float | None:
        return 0.0 if axis in self.rig.limits else None



def _write_preview(dng: Path, path: Path) -> Path:
    """A small 8-bit JPEG of the green plane, as a camera's RAW + JPEG mode adds."""
    from psfd.estimator import raw

    green = raw.load_frame(dng, "g1")
    image = np.clip(255.0 * np.sqrt(np.clip(green.data / green.white, 0, 1)), 0, 255).astype(np.uint8)
    tmp = path.with_name(f".{path.name}.part.jpg")
    try:
        if not cv2.imwrite(str(tmp), image):
            raise CameraError(f"{path}: cannot write JPEG preview")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
