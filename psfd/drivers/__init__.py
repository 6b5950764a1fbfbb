"""Hardware drivers behind small protocols, and the fakes that replace them in tests."""

from __future__ import annotations

import importlib

from psfd.drivers.base import Camera, CameraInfo, Position, Rail
from psfd.errors import BadInputError

__all__ = ["Camera", "CameraInfo", "Position", "Rail", "RAIL_DRIVERS", "open_camera", "open_rail", "open_rig",
           "rail_driver"]

# The rail drivers a plan's ``[rig] rail = NAME`` may name, each one module with an ``open_rail(config)``
# function taking the [rig] table; another controller is one more module and one more line here.
RAIL_DRIVERS = {"grbl": "psfd.drivers.grbl", "simulated": "psfd.drivers.sim"}

# Keys of a plan's [rig] table: for the simulated rig, and for real hardware.
SIM_KEYS = ("scene", "seed", "sensor", "pitch_um", "focal_mm", "cell_mm", "texture_mm", "s", "support",
            "corner_aberration", "exposure", "limits")
REAL_KEYS = ("camera_port", "timeout", "rail", "rail_port", "rail_limits", "rail_baudrate", "rail_feed",
             "rail_timeout", "x_at_lens", "x_away")


def open_rig(config: dict) -> tuple[Camera, Rail]:
    """Camera and rail described by a plan's ``[rig]`` table.

    Parameters
    ----------
    config : dict
        One of
        ``{"simulate": true, "scene": "bernoulli", "seed": 0, ...}`` (the simulated rig, sharing one state),
        ``{"recording": "DIR"}`` (replay of a recorded session, in its recorded order),
        ``{"camera_port": "usb:001,005" or absent (auto-detect), "rail_port": "/dev/ttyUSB0",
        "rail_limits": {"x": [-1500, 0]} (optional: the controller's travel), "rail_baudrate": 115200,
        "rail_feed": 1000 (optional: rapids at the controller's $110), "timeout": 10}``;
        ``"rail"`` names the rail driver (`RAIL_DRIVERS`: ``grbl``, the default, or ``simulated``).

    Returns
    -------
    (Camera, Rail)
    """
    config = dict(config or {})
    if config.get("recording"):
        from psfd.drivers.recording import open_replay

        return open_replay(config["recording"])
    if config.get("simulate"):
        rig = _sim_rig(config)
        return rig.camera, rig.rail
    rail_driver(config)  # a bad rail is refused before the camera is opened
    camera = open_camera(config)
    try:
        return camera, open_rail(config)
    except BaseException:
        camera.close()
        raise


def open_camera(config: dict) -> Camera:
    """Only the camera of a rig description (see `open_rig`)."""
    config = dict(config or {})
    if config.get("recording"):
        from psfd.drivers.recording import RecordingCamera

        return RecordingCamera(config["recording"])
    if config.get("simulate"):
        return _sim_rig(config).camera
    from psfd.drivers.gphoto import GPhotoCamera  # imported here: gphoto2 is only needed for a real camera

    timeout = float(config.get("timeout", 10.0))
    return GPhotoCamera(port=config.get("camera_port") or None, timeout=timeout)


def open_rail(config: dict) -> Rail:
    """Only the rail of a rig description (see `open_rig`)."""
    config = dict(config or {})
    if config.get("recording"):
        from psfd.drivers.recording import RecordingRail

        return RecordingRail(config["recording"])
    if config.get("simulate"):
        return _sim_rig(config).rail
    module = importlib.import_module(RAIL_DRIVERS[rail_driver(config)])
    return module.open_rail(config)


def rail_driver(config: dict) -> str:
    """The rail driver a real rig's [rig] table names (``rail``, default ``grbl``), checked.

    Raises
    ------
    BadInputError
        An unknown driver, or a GRBL rail without ``rail_port``.
    """
    name = config.get("rail", "grbl")
    if name not in RAIL_DRIVERS:
        raise BadInputError(f"rail = {name!r}: use one of {', '.join(map(repr, RAIL_DRIVERS))}")
    if name == "grbl" and not config.get("rail_port"):
        raise BadInputError("rig needs rail_port (or simulate = true, or recording = DIR)")
    return name


def _sim_rig(config: dict):
    """The simulated rig of a [rig] table; it keeps its state between commands (`psfd.drivers.sim.state_path`)."""
    from psfd.drivers.sim import SimRig, state_path

    options = {k: config[k] for k in SIM_KEYS if k in config}
    options["state_file"] = state_path()
    if "rail_limits" in config and "limits" not in options:
        options["limits"] = config["rail_limits"]
    unknown = set(config) - set(SIM_KEYS) - set(REAL_KEYS) - {"simulate"}
    if config.get("rail", "simulated") != "simulated":
        raise BadInputError(f"rail = {config['rail']!r} does not go with simulate = true (the simulated rig's rail)")
    if unknown:
        raise BadInputError(f"unknown simulated rig option(s): {', '.join(sorted(unknown))}")
    try:
        return SimRig(**options)
    except (TypeError, ValueError) as exc:
        raise BadInputError(f"bad simulated rig option: {exc}") from None
