"""The frame store: RAW files named by their content, beside the catalogue.

A captured file is written to a temporary name in the store, fsynced, and
renamed to its sha256 (``frames/ab/ab12...ef.dng``): a file with that name is
complete, and the same exposure stored twice is one file. One run at a time
holds the store (`store_lock`, an flock a killed process never leaves
behind), so a run journalled ``running`` whose store nobody holds was killed
(`shown_state`: ``interrupted``). `sweep_frames` removes what a crash left:
temporary folders and the frames its catalogue journalled and never committed.

Only the store's owner writes to it: another user's files and folders in it (a root
``psfd capture`` in the service's store) would be ones the service cannot use.
A write the file system refuses for lack of room (disk full, quota, read-only)
is a `StorageError`: the run pauses and resumes once there is room.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import os
import re
import shutil
import threading
from pathlib import Path
from typing import Callable, Iterator

from psfd.catalogue import check_owner
from psfd.errors import STORAGE_ERRNOS, BadInputError, ServiceError, StorageError, path_reason

__all__ = ["INCOMING", "check_room", "frames_dir_for", "shown_state", "storage_error", "store_busy", "store_frame",
           "store_lock", "sweep_frames"]

FRAME_NAME = re.compile(r"^[0-9a-f]{64}\.[A-Za-z0-9]+$")
INCOMING = ".incoming-"  # prefix of the temporary folders a capture downloads into


def frames_dir_for(catalogue_path: str | os.PathLike) -> Path:
    """Default frame store beside a catalogue file: ``catalogue.db`` -> ``catalogue-frames/``."""
    path = Path(catalogue_path)
    return path.with_name(path.stem + "-frames")


def store_frame(src: Path, frames_dir: Path, journal: Callable[[str], None] | None = None) -> tuple[Path, str]:
    """Move a captured file into the store under its sha256; returns (path, sha256).

    The data is fsynced before the rename and the folder after it, so the
    name is only ever seen on a complete file. An identical file already
    stored is re-used. ``journal(sha256)`` is called before a new file is put
    into the store (not for one re-used, which is someone else's): the
    catalogue's `pend_frame`, which lets `sweep_frames` tell a crash's leftover
    from another catalogue's frame.
    """
    digest = hashlib.sha256()
    with open(src, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
        os.fsync(fh.fileno())
    sha = digest.hexdigest()
    folder = frames_dir / sha[:2]
    folder.mkdir(parents=True, exist_ok=True)
    dest = folder / f"{sha}{src.suffix.lower()}"
    if dest.exists():
        src.unlink()
    else:
        if journal is not None:
            journal(sha)
        os.replace(src, dest)
        _fsync_dir(folder)
    return dest.resolve(), sha


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def check_room(frames_dir: Path, needed: int) -> None:
    """Refuse (StorageError) to store a frame where the file system is read-only or has fewer than ``needed``
    bytes free: said before the camera writes, or after a write failed for that reason whatever error the
    driver made of it (libgphoto2 reports a full disk as its own I/O error, numpy as a short write)."""
    try:
        fs = os.statvfs(frames_dir)
    except OSError:
        return  # the write itself will say what is wrong
    if fs.f_flag & os.ST_RDONLY:
        raise StorageError(f"cannot store frames in {frames_dir}: {os.strerror(errno.EROFS)}")
    free = fs.f_bavail * fs.f_frsize
    if free < needed:
        raise StorageError(f"cannot store a frame in {frames_dir}: {os.strerror(errno.ENOSPC)} ({free / 1e6:.1f} MB "
                           f"free, a frame takes {needed / 1e6:.1f} MB)")


def storage_error(exc: OSError, what: str) -> StorageError | None:
    """The StorageError of a write the file system refused for lack of room (disk full, read-only, quota),
    naming ``what`` was being written; None for another failure."""
    if exc.errno not in STORAGE_ERRNOS:
        return None
    where = f" ({exc.filename})" if exc.filename else ""
    return StorageError(f"{what}: {exc.strerror}{where}")


_held: dict[Path, int] = {}  # stores this process holds, and how many times (store_lock is re-entrant)
_held_lock = threading.Lock()


@contextlib.contextmanager
def store_lock(frames_dir: Path) -> Iterator[None]:
    """Hold the frame store for one run at a time.

    Another run's sweep would take this run's stored-but-not-yet-committed
    frames for orphans. The lock is an flock, so a killed run never leaves it
    behind. Re-entrant within a process: `run_plan` takes the store before it
    creates a catalogue, and the runner takes it again.
    """
    key = Path(os.path.abspath(frames_dir))
    with _held_lock:
        if key in _held:
            _held[key] += 1
            held = True
        else:
            held = False
    if held:
        try:
            yield
        finally:
            with _held_lock:
                _held[key] -= 1
        return
    check_owner(frames_dir, "the frame store")
    try:
        frames_dir.mkdir(parents=True, exist_ok=True)
        fh = open(frames_dir / ".lock", "a")
    except OSError as exc:
        error = storage_error(exc, f"cannot use {frames_dir} as the frame store")
        raise error or BadInputError(f"cannot use {frames_dir} as the frame store: "
                                     f"{path_reason(frames_dir, exc)}") from None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ServiceError(f"the frame store {frames_dir} is in use by another run") from None
        with _held_lock:
            _held[key] = 1
        try:
            yield
        finally:
            with _held_lock:
                del _held[key]
            fcntl.flock(fh, fcntl.LOCK_UN)


def store_busy(frames_dir: str | os.PathLike) -> bool:
    """True while some process holds the frame store's lock, i.e. runs a plan on it."""
    lock = Path(frames_dir) / ".lock"
    try:
        fh = open(lock, "rb")
    except OSError:
        return False  # no lock file (or unreadable): no run has ever held it
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fh, fcntl.LOCK_UN)
        return False


def shown_state(state: str, frames_dir: str | os.PathLike) -> str:
    """A run's state as a user should read it: ``running`` with nobody holding the store is ``interrupted``."""
    return "interrupted" if state == "running" and not store_busy(frames_dir) else state


def sweep_frames(frames_dir: Path, known: set[str], pending: set[str]) -> list[Path]:
    """Remove what a crash left in the store: temporary folders, and the frames a run journalled as being
    stored (``pending``, `Catalogue.pending_frames`) that its catalogue does not hold (``known``). Any other
    file is kept: a folder may be shared with other catalogues, whose frames this one does not know.
    Returns the removed paths.
    """
    removed: list[Path] = []
    if not frames_dir.is_dir():
        return removed
    for incoming in frames_dir.glob(INCOMING + "*"):
        shutil.rmtree(incoming, ignore_errors=True)
        removed.append(incoming)
    for sha in sorted(pending - known):
        for path in (frames_dir / sha[:2]).glob(sha + ".*"):
            if FRAME_NAME.match(path.name):
                path.unlink()
                removed.append(path)
    return removed
