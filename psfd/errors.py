"""Typed errors a user can cause, each with a one-line message and a CLI exit code.

The CLI prints ``str(error)`` on one line of stderr and exits with ``error.exit_code``,
the one table of the README: 0 done, 1 nothing matched, 2 bad input, 3 the
photographs cannot support an estimate, 4 camera or rail, 5 catalogue or service
(a full or read-only disk included), 130 interrupted by Ctrl-C, 143 stopped by SIGTERM
(128 + the signal, as a shell reports a process the signal ended). The service sends an error's
type name with its answer (`by_name`), so the same refusal exits with the same code
whether a command ran here or through the service.
"""

from __future__ import annotations

import errno
import os
import pwd
import signal
from pathlib import Path


class PsfdError(Exception):
    """Base class: a failure with a message meant for the user."""

    exit_code = 1


class NoMatchError(PsfdError):
    """A query matched nothing (``query``, ``export`` and ``report`` alike)."""

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


class StorageError(CatalogueError):
    """The catalogue or the frame store cannot be written: disk full, read-only file system, quota."""


class ServiceError(PsfdError):
    """The service or its control socket refused or failed a request."""

    exit_code = 5


class Interrupted(PsfdError):
    """Stopped by Ctrl-C (exit 130), SIGTERM (143) or a hang-up (129); a run stopped so is paused and resumable."""

    exit_code = 128 + signal.SIGINT

    def __init__(self, message: str, signum: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.exit_code = 128 + int(signum)


# errno values that mean "this storage cannot take more writes now", not a fault of the device or input
STORAGE_ERRNOS = {errno.ENOSPC, errno.EROFS, errno.EDQUOT, errno.EFBIG}


def by_name(name: str, message: str, default: type[PsfdError] = ServiceError) -> PsfdError:
    """The error of type ``name`` (a class of this module) with ``message``; ``default`` when there is none."""
    kind = globals().get(name)
    if not (isinstance(kind, type) and issubclass(kind, PsfdError)):
        kind = default
    return kind(message)


def path_reason(path: str | os.PathLike, exc: OSError) -> str:
    """Why a path could not be used, in words: a component that is a file is named (``notes is a file,
    not a folder``) instead of the system's "File exists" or "Not a directory"."""
    if exc.errno in (errno.EEXIST, errno.ENOTDIR):
        for parent in [Path(path), *Path(path).parents]:
            if parent.exists() or parent.is_symlink():
                if not parent.is_dir():
                    return f"{parent} is a file, not a folder"
                break
    return exc.strerror or str(exc)


def user_name(uid: int) -> str:
    """A user's login name, for messages about who owns what (``uid N`` when it has none)."""
    try:
        return pwd.getpwuid(uid).pw_name
    except KeyError:
        return f"uid {uid}"
