"""The frame store: RAW files named by their content, beside the catalogue.

A captured file is written to a temporary name in the store, fsynced, and
renamed to its sha256 (``frames/ab/ab12...ef.dng``): a file with that name is
complete, and the same exposure stored twice is one file. One run at a time
holds the store (`store_lock`, an flock a killed process never leaves
behind), so a run journalled ``running`` whose store nobody holds was killed
(`shown_state`: ``interrupted``). `sweep_frames` removes what a crash left:
temporary folders and frames the catalogue does not know.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import re
import shutil
from pathlib import Path
from typing import Iterator

from psfd.errors import BadInputError, ServiceError

__all__ = ["INCOMING", "frames_dir_for", "shown_state", "store_busy", "store_frame", "store_lock", "sweep_frames"]

FRAME_NAME = re.compile(r"^[0-9a-f]{64}\.[A-Za-z0-9]+$")
INCOMING = ".incoming-"  # prefix of the temporary folders a capture downloads into


def frames_dir_for(catalogue_path: str | os.PathLike) -> Path:
    """Default frame store beside a catalogue file: ``catalogue.db`` -> ``catalogue-frames/``."""
    path = Path(catalogue_path)
    return path.with_name(path.stem + "-frames")


def store_frame(src: Path, frames_dir: Path) -> tuple[Path, str]:
    """Move a captured file into the store under its sha256; returns (path, sha256).

    The data is fsynced before the rename and the folder after it, so the
    name is only ever seen on a complete file. An identical file already
    stored is re-used.
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
        os.replace(src, dest)
        _fsync_dir(folder)
    return dest.resolve(), sha


def _fsync_dir(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def store_lock(frames_dir: Path) -> Iterator[None]:
    """Hold the frame store for one run at a time.

    Another run's sweep would take this run's stored-but-not-yet-committed
    frames for orphans. The lock is an flock, so a killed run never leaves it behind.
    """
    try:
        frames_dir.mkdir(parents=True, exist_ok=True)
        fh = open(frames_dir / ".lock", "a")
    except OSError as exc:
        raise BadInputError(f"cannot use {frames_dir} as the frame store: {exc.strerror or exc}") from None
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise ServiceError(f"the frame store {frames_dir} is in use by another run") from None
        try:
            yield
        finally:
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


def sweep_frames(frames_dir: Path, known: set[str]) -> list[Path]:
    """Remove what a crash left in the store: temporary folders and frames the catalogue does not hold.

    Only files named like stored frames (sha256 + suffix) are touched; ``known``
    holds the catalogued hashes. Returns the removed paths.
    """
    removed: list[Path] = []
    if not frames_dir.is_dir():
        return removed
    for incoming in frames_dir.glob(INCOMING + "*"):
        shutil.rmtree(incoming, ignore_errors=True)
        removed.append(incoming)
    for path in frames_dir.glob("??/*"):
        if FRAME_NAME.match(path.name) and path.name.split(".")[0] not in known:
            path.unlink()
            removed.append(path)
    return removed
