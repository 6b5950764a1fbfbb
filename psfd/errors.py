"""Typed errors a user can cause, each with a one-line message and a CLI exit code.

The CLI prints ``str(error)`` on one line of stderr and exits with ``error.exit_code``.
Codes are grouped so that scripts can tell a bad input (2) from a measurement that
the photographs cannot support (3), a hardware fault (4) and a catalogue or service
problem (5).
"""

from __future__ import annotations


class PsfdError(Exception):
    """Base class: a failure with a message meant for the user."""

    exit_code = 1


class BadInputError(PsfdError):
    """A file, argument or plan that cannot be used as given."""

    exit_code = 2


class EstimationError(PsfdError):
    """The photographs do not support a PSF estimate."""

    exit_code = 3


class TargetNotFoundError(EstimationError):
    """No calibration target was found in the frame."""


class MultipleTargetsError(EstimationError):
    """More than one calibration target was found in the frame."""


class SaturatedError(EstimationError):
    """Saturated pixels fall where the estimate needs linear data."""


class PairError(EstimationError):
    """A near/far pair violates a condition of the two-photo method."""


class HardwareError(PsfdError):
    """Camera or rail failure."""

    exit_code = 4


class CameraError(HardwareError):
    """The camera is missing, busy, gone, or refused a request."""


class SettingsMismatch(CameraError):
    """The RAW file says the camera used other settings than the ones asked for."""


class RailError(HardwareError):
    """The rail controller reported an error or stopped answering."""


class RailAlarm(RailError):
    """The rail controller is in ALARM state and must be homed or unlocked."""


class CatalogueError(PsfdError):
    """The catalogue cannot be opened or does not hold what was asked."""

    exit_code = 5


class ServiceError(PsfdError):
    """The service or its control socket refused or failed a request."""

    exit_code = 5
