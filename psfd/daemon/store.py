"""The frame store: RAW files named by their content, beside the catalogue.

A captured file is written to a temporary name in the store, fsynced, and
renamed to its sha256 (``frames/ab/ab12...ef.dng``): a file with that name is
complete, and the same exposure stored twice is one file. One run at a time
holds the store (`store_lock`, an flock a killed process never leaves
behind), so a run journalled ``running`` whose store nobody holds was killed
(`shown_state`: ``interrupted``). `sweep_frames` removes what a crash left:
temporary folders and the frames its catalogue journalled and never committed.

One writer at a time holds a catalogue too (`catalogue_lock`): a run decides
from what the catalogue says (a step done is skipped, a run ``running`` whose
store nobody holds was killed, the frames journalled and not committed are a
crash's leftovers) and then writes; a second run or capture into the same
catalogue with another frame store would decide from a state the first is
changing (resume the run it is shooting, forget its journal of frames).

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
import json
import os
import re
import shutil
import threading
from pathlib import Path
from typing import Callable, Iterator

from psfd.catalogue import check_owner
from psfd.errors import (STORAGE_ERRNOS, BadInputError, CatalogueError, PsfdError, ServiceError, StorageError,
                         path_reason)

__all__ = ["INCOMING", "catalogue_busy", "catalogue_lock", "catalogue_lock_path", "check_catalogue_free", "check_room",
           "frames_dir_for", "kept_queue", "queue_path", "shown_state", "storage_error", "store_busy", "store_frame",
           "store_lock", "sweep_frames", "write_durably"]

FRAME_NAME = re.compile(r"^[0-9a-f]{64}\.[A-Za-z0-9]+$")
INCOMING = ".incoming-"  # prefix of the temporary folders a capture downloads into


def frames_dir_for(catalogue_path: str | os.PathLike) -> Path:
    """Default frame store beside a catalogue file: ``catalogue.db`` -> ``catalogue-frames/``."""
    path = Path(catalogue_path)
    return path.with_name(path.stem + "-frames")


def store_frame(src: Path, frames_dir: Path, journal: Callable[[str], None] | None = None) -> tuple[Path, str]:
    """Move a captured file into the store under its sha256; returns (path, sha256).

    The data is fsynced before the rename and the folder after it (and the
    store folder when the subfolder is new), so the name is only ever seen on
    a complete file, and survives a power cut once the step commits. An identical file already
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
    if not folder.is_dir():
        folder.mkdir(parents=True, exist_ok=True)
        _fsync_dir(frames_dir)  # the new subfolder's entry: a power cut must not lose it with the frame in it
    dest = folder / f"{sha}{src.suffix.lower()}"
    if dest.exists():
        src.unlink()
    else:
        if journal is not None:
            journal(sha)
        os.replace(src, dest)
        _fsync_dir(folder)
    return dest.resolve(), sha


def write_durably(path: Path, text: str) -> None:
    """Replace ``path`` by ``text`` whole: written to a temporary name, fsynced, renamed, the folder fsynced
    (a power cut leaves the old file or the new one)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)


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


_held: dict[Path, int] = {}  # lock files this process holds, and how many times (the locks are re-entrant)
_held_lock = threading.Lock()


@contextlib.contextmanager
def store_lock(frames_dir: Path) -> Iterator[None]:
    """Hold the frame store for one run at a time.

    Another run's sweep would take this run's stored-but-not-yet-committed
    frames for orphans. The lock is an flock, so a killed run never leaves it
    behind. Re-entrant within a process: `run_plan` takes the store before it
    creates a catalogue, and the runner takes it again.
    """
    def failed(exc: OSError) -> PsfdError:
        what = f"cannot use {frames_dir} as the frame store"
        return storage_error(exc, what) or BadInputError(f"{what}: {path_reason(frames_dir, exc)}")

    def opening() -> None:
        check_owner(frames_dir, "the frame store")
        try:
            frames_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise failed(exc) from None

    with _exclusive(frames_dir / ".lock", opening, failed,
                    lambda: ServiceError(f"the frame store {frames_dir} is in use by another run")):
        yield


@contextlib.contextmanager
def catalogue_lock(catalogue_path: str | os.PathLike) -> Iterator[None]:
    """Hold a catalogue for one writing run (`psfd run`, `capture`, a service's job) at a time.

    An flock on `catalogue_lock_path`, so that a killed run never leaves it behind; it names the holder's
    pid for the refusal. Re-entrant within a process, as `store_lock`: `run_plan` takes it before it creates
    the catalogue, and the runner takes it again.

    Raises
    ------
    ServiceError
        Another process holds the catalogue.
    """
    lock = catalogue_lock_path(catalogue_path)

    def failed(exc: OSError) -> PsfdError:
        what = f"cannot lock the catalogue {catalogue_path}"
        return storage_error(exc, what) or CatalogueError(f"{what}: {path_reason(lock.parent, exc)}")

    def opening() -> None:  # the catalogue's folder, as `Catalogue` makes it for a new catalogue
        try:
            lock.parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise failed(exc) from None

    with _exclusive(lock, opening, failed,
                    lambda: ServiceError(_in_use(catalogue_path)), pid=True):
        yield


@contextlib.contextmanager
def _exclusive(lock: Path, opening: Callable[[], None], failed: Callable[[OSError], PsfdError],
               busy: Callable[[], PsfdError], pid: bool = False) -> Iterator[None]:
    """An exclusive, re-entrant flock on the file ``lock``; ``opening()`` runs before the first open,
    ``failed(exc)`` is the error when the file cannot be opened, ``busy()`` when another process holds it,
    ``pid``: write this process's pid into the file.

    A lock file may be removed by its holder (a run that made a catalogue and journalled nothing,
    `psfd.daemon.runner.run_plan`): one found replaced or gone once locked is opened again, so that two
    processes never hold two files of one name.
    """
    key = Path(os.path.abspath(lock))
    with _held_lock:
        held = key in _held
        if held:
            _held[key] += 1
    if held:
        try:
            yield
        finally:
            with _held_lock:
                _held[key] -= 1
        return
    opening()
    while True:
        try:
            fh = open(lock, "a+")
        except OSError as exc:
            raise failed(exc) from None
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.close()
            raise busy() from None
        try:
            same = os.stat(lock).st_ino == os.fstat(fh.fileno()).st_ino
        except OSError:
            same = False
        if same:
            break
        fh.close()  # removed by the process that held it: lock the file now there
    with fh:
        if pid:
            with contextlib.suppress(OSError):  # for the refusal's message only: a full disk may refuse it
                fh.truncate(0)
                fh.write(f"{os.getpid()}\n")
                fh.flush()
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
    return _held_by_other(Path(frames_dir) / ".lock")


def _held_by_other(lock: Path) -> bool:
    """Whether some process holds an flock on ``lock`` (False when the file is missing or unreadable)."""
    try:
        fh = open(lock, "rb")
    except OSError:
        return False  # no lock file (or unreadable): nobody has ever held it
    with fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return True
        fcntl.flock(fh, fcntl.LOCK_UN)
        return False


def catalogue_lock_path(catalogue_path: str | os.PathLike) -> Path:
    """The lock file of a catalogue: ``catalogue.sqlite-run.lock`` beside the file it names, through any
    symbolic link (two paths of one catalogue share its lock)."""
    return _beside_catalogue(catalogue_path, "-run.lock")


def queue_path(catalogue_path: str | os.PathLike) -> Path:
    """The file where the service keeps the plans queued and not started (`psfd.daemon.service`):
    ``catalogue.sqlite-queue.json`` beside the catalogue, through any symbolic link, as its lock."""
    return _beside_catalogue(catalogue_path, "-queue.json")


def _beside_catalogue(catalogue_path: str | os.PathLike, suffix: str) -> Path:
    """The catalogue's file name plus ``suffix``, in the folder of the file the path names (links followed)."""
    real = Path(os.path.realpath(catalogue_path))
    return real.with_name(real.name + suffix)


def kept_queue(catalogue_path: str | os.PathLike) -> list[dict]:
    """The plans a service kept for a catalogue (`queue_path`), each ``{"plan", "path", "resume", "new"}``;
    [] when it kept none.

    Raises
    ------
    OSError, ValueError
        The file cannot be read, or is not such a list.
    """
    try:
        entries = json.loads(queue_path(catalogue_path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        return []
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise ValueError("not a list of plans")
    return entries


def catalogue_busy(catalogue_path: str | os.PathLike) -> bool:
    """Whether another process writes the catalogue (`catalogue_lock`); this one may (the service checks a
    submitted plan while it runs another)."""
    lock = catalogue_lock_path(catalogue_path)
    with _held_lock:
        if Path(os.path.abspath(lock)) in _held:
            return False
    return _held_by_other(lock)


def check_catalogue_free(catalogue_path: str | os.PathLike) -> None:
    """Refuse (ServiceError) a catalogue another run writes (`catalogue_lock`), before anything is opened."""
    if catalogue_busy(catalogue_path):
        raise ServiceError(_in_use(catalogue_path))


def _in_use(catalogue_path: str | os.PathLike) -> str:
    try:  # the holder's pid, unless it has not written it yet (or could not: a full disk)
        holder = f"psfd process {int(catalogue_lock_path(catalogue_path).read_text())}"
    except (OSError, ValueError):
        holder = "another psfd process"
    return (f"the catalogue {catalogue_path} is in use by {holder} (one process writes a catalogue at a time): "
            "wait for it to end, or stop it (Ctrl-C or SIGTERM pauses a run)")


def shown_state(state: str, frames_dir: str | os.PathLike, catalogue_path: str | os.PathLike | None = None) -> str:
    """A run's state as a user should read it: ``running`` with nobody holding its store nor its catalogue
    (``catalogue_path``, when given) is ``interrupted``."""
    if state != "running" or store_busy(frames_dir):
        return state
    return "running" if catalogue_path is not None and catalogue_busy(catalogue_path) else "interrupted"


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
