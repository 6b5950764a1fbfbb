"""The PSF catalogue: one SQLite file holding rigs, runs, steps, frames and PSFs.

The catalogue owns all SQL of psfd. It is opened in WAL mode so that readers
(``psfd query``, a deblurring program) never block the daemon writing; readers open
it read-only and need no write access (see `Catalogue`); every
write is one transaction, so a reader never sees half of a step: either all the
frames and PSFs of a step and its ``done`` state, or none of them. That is what
lets the daemon resume after a crash with no PSF lost and none stored twice.

The schema is versioned with ``PRAGMA user_version``: ``MIGRATIONS[i]`` takes a
catalogue from version ``i`` to ``i + 1`` inside one transaction.

Frame paths inside the catalogue's folder (the frame store beside it) are
stored relative to that folder, so a catalogue and its frames can be moved or
copied together; a frame elsewhere keeps its absolute path, and so do the
absolute paths of older catalogues outside the folder (`psf_frames` returns
absolute paths either way). A PSF's ``sources`` are stored the same way and
read back absolute, under the catalogue's current folder. `datasette_metadata`
describes every table and column, with units, in the metadata format Datasette
reads.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import logging
import math
import os
import sqlite3
import stat
import threading
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
import sqlite_utils

from psfd import __version__
from psfd.drivers.base import CameraInfo
from psfd.errors import BadInputError, CatalogueError, StorageError, path_reason, user_name
from psfd.estimator.kernels import PSF
from psfd.vocabulary import (BERNOULLI, SHARP_EDGE, camera_fnumber, data_dir, method_name, parse_fnumber,
                             plan_content)

log = logging.getLogger(__name__)

STEP_STATES = ("pending", "running", "done", "failed")
RUN_STATES = ("running", "done", "paused", "cancelled", "failed")
# A run in one of these states may be resumed; done, cancelled and failed runs are closed.
UNFINISHED_STATES = ("running", "paused")
# Two f-numbers within 1 % are the same aperture (cameras report 5.6 for f/5.66).
APERTURE_TOLERANCE = 0.01


@dataclass
class FrameRecord:
    """A RAW file a step captured: where it is, its hash, how it was taken."""

    path: str
    sha256: str
    settings: dict
    rail: dict
    taken_at: str
    exif: dict | None = None  # what the RAW says the camera did (`psfd.exif.FrameMetadata.as_dict`)


@dataclass
class QueryResult:
    """PSF rows (metadata, no arrays) and a note when the asked aperture was replaced."""

    rows: list[dict] = field(default_factory=list)
    note: str | None = None

    def __len__(self) -> int:
        return len(self.rows)

    def __iter__(self) -> Iterator[dict]:
        return iter(self.rows)


def default_path() -> Path:
    """The user's catalogue: ``$XDG_DATA_HOME/psfd/catalogue.sqlite``, else ``~/.local/share/psfd/...``.

    A relative or empty ``XDG_DATA_HOME`` is ignored, as the XDG base directory
    specification requires.
    """
    return data_dir() / "catalogue.sqlite"


# ---------------------------------------------------------------------------
# Schema and migrations


def _v1_tables(db: sqlite_utils.Database) -> None:
    """Version 1: the six tables and the uniqueness the writers rely on."""
    db["rigs"].create(
        {"id": int, "model": str, "serial": str, "lens": str, "focal_length_mm": float, "created": str},
        pk="id",
        not_null={"model", "serial", "lens"},
    )
    db["rigs"].create_index(["model", "serial", "lens"], unique=True)
    db["runs"].create(
        {
            "id": int, "rig_id": int, "plan_path": str, "plan_text": str, "plan_hash": str,
            "started": str, "finished": str, "state": str,
        },
        pk="id",
        foreign_keys=[("rig_id", "rigs", "id")],
        not_null={"plan_text", "plan_hash", "state"},
    )
    db["steps"].create(
        {
            "id": int, "run_id": int, "key": str, "position": int, "state": str, "payload": str,
            "reason": str, "attempts": int, "updated": str,
        },
        pk="id",
        foreign_keys=[("run_id", "runs", "id")],
        not_null={"run_id", "key", "position", "state", "attempts"},
        defaults={"attempts": 0},
    )
    db["steps"].create_index(["run_id", "key"], unique=True)
    db["frames"].create(
        {
            "id": int, "path": str, "sha256": str, "settings": str, "aperture": float, "rail": str,
            "taken_at": str,
        },
        pk="id",
        not_null={"path", "sha256"},
    )
    db["frames"].create_index(["sha256"], unique=True)
    db["psfs"].create(
        {
            "id": int, "rig_id": int, "run_id": int, "step_id": int,
            "method": str, "channel": str, "aperture": float, "focal_length_mm": float,
            "focus_distance_m": float, "field_x": float, "field_y": float,
            "window_x0": int, "window_y0": int, "window_x1": int, "window_y1": int,
            "s": int, "support": int, "psf": bytes,
            "mtf50_x": float, "mtf50_y": float, "fwhm_x": float, "fwhm_y": float,
            "noise_floor": float, "residual": float, "params": str, "psfd_version": str,
            "warnings": str, "sources": str, "created": str,
        },
        pk="id",
        foreign_keys=[("rig_id", "rigs", "id"), ("run_id", "runs", "id"), ("step_id", "steps", "id")],
        not_null={"method", "channel", "field_x", "field_y", "s", "support", "psf"},
    )
    db["psf_frames"].create(
        {"psf_id": int, "frame_id": int},
        pk=("psf_id", "frame_id"),
        foreign_keys=[("psf_id", "psfs", "id"), ("frame_id", "frames", "id")],
    )


def _v2_query_indexes(db: sqlite_utils.Database) -> None:
    """Version 2: indexes for the queries (by aperture/channel/method, per run, per step, per frame)."""
    db["psfs"].create_index(["aperture", "channel", "method"])
    db["psfs"].create_index(["rig_id"])
    db["psfs"].create_index(["run_id"])
    db["psfs"].create_index(["step_id"])
    db["psf_frames"].create_index(["frame_id"])
    db["steps"].create_index(["run_id", "state"])
    db["runs"].create_index(["plan_hash"])


def _database_folder(db: sqlite_utils.Database) -> Path | None:
    """The folder of the catalogue file a connection has open (None for an in-memory database)."""
    for _, name, file in db.execute("PRAGMA database_list").fetchall():
        if name == "main" and file:
            return Path(file).resolve().parent
    return None


def _v4_relative_frame_paths(db: sqlite_utils.Database) -> None:
    """Version 4: frame paths inside the catalogue's folder become relative to it (others stay absolute).

    Paths already relative are left alone, so running it again, or after any other migration, changes nothing.
    """
    folder = _database_folder(db)
    if folder is None:
        return
    for frame_id, path in db.execute("SELECT id, path FROM frames").fetchall():
        if not os.path.isabs(path):
            continue
        stored = stored_frame_path(path, folder)
        if stored != path:
            db.execute("UPDATE frames SET path = ? WHERE id = ?", [stored, frame_id])


def stored_frame_path(path: str | os.PathLike, folder: Path) -> str:
    """How a frame path is stored: relative to the catalogue's ``folder`` when inside it, else absolute."""
    absolute = Path(os.path.abspath(path))
    try:
        return absolute.relative_to(folder).as_posix()
    except ValueError:
        try:  # the same file through a symbolic link in either path
            return absolute.resolve().relative_to(folder.resolve()).as_posix()
        except (ValueError, OSError):
            return str(absolute)


# A frame's own EXIF beside the requested ``settings``: column -> FrameMetadata field.
FRAME_EXIF = {
    "exif_focal_length_mm": "focal_length_mm", "exif_f_number": "f_number", "exif_exposure_s": "exposure_s",
    "exif_iso": "iso", "exif_lens": "lens", "exif_serial": "serial", "exif_focus_distance_m": "focus_distance_m",
    "exif_lens_serial": "lens_serial",
}
FRAME_EXIF_TEXT = ("exif_lens", "exif_serial", "exif_lens_serial")


def _v3_frame_exif(db: sqlite_utils.Database) -> None:
    """Version 3: what each frame's RAW says the camera used (NULL for older frames).

    Adds only the columns that are missing, so it holds whichever other migrations ran before it.
    """
    have = set(db["frames"].columns_dict)
    for column in FRAME_EXIF:
        if column not in have:
            db["frames"].add_column(column, str if column in FRAME_EXIF_TEXT else float)


def _v5_prediction_error(db: sqlite_utils.Database) -> None:
    """Version 5: the cross-validated prediction error beside the noise floor (NULL for older PSFs).

    Adds the column only when it is missing, whatever other migrations already ran.
    """
    if "prediction_error" not in db["psfs"].columns_dict:
        db["psfs"].add_column("prediction_error", float)


def _v6_noise_floor_as_norm(db: sqlite_utils.Database) -> None:
    """Version 6: every noise floor in one unit, the L2 norm of the unit-sum kernel's error (`PSF.noise_floor`).

    Sharp-edge floors were the RMS per sample (times the support: the norm over its k x k samples); Bernoulli
    floors were those of the kernel before it was divided by its mass (over the mass, kept in its params).
    """
    rows = list(db.query("SELECT id, method, support, noise_floor, params FROM psfs WHERE noise_floor IS NOT NULL "
                         "AND method IN (?, ?)", [SHARP_EDGE, BERNOULLI]))  # read whole before any row changes
    for row in rows:
        if row["method"] == SHARP_EDGE:
            floor = row["noise_floor"] * row["support"]
        else:
            mass = json.loads(row["params"] or "{}").get("mass")
            if not isinstance(mass, (int, float)) or not mass > 0:
                continue
            floor = row["noise_floor"] / mass
        db.execute("UPDATE psfs SET noise_floor = ? WHERE id = ?", [floor, row["id"]])


def _v7_relative_psf_sources(db: sqlite_utils.Database) -> None:
    """Version 7: a PSF's sources inside the catalogue's folder become relative to it, as frame paths did in
    version 4 (others stay absolute).

    Sources already relative are left alone, so running it again, or after any other migration, changes nothing.
    """
    folder = _database_folder(db)
    if folder is None:
        return
    rows = db.execute("SELECT id, sources FROM psfs WHERE sources IS NOT NULL").fetchall()  # read whole first
    for psf_id, text in rows:
        sources = json.loads(text)
        stored = [stored_frame_path(s, folder) if os.path.isabs(s) else s for s in sources]
        if stored != sources:
            db.execute("UPDATE psfs SET sources = ? WHERE id = ?", [json.dumps(stored), psf_id])


def _v8_pending_frames(db: sqlite_utils.Database) -> None:
    """Version 8: the frames a run has put into its frame store and not yet committed (`Catalogue.pend_frame`).

    A crash between storing a frame and committing its step leaves a file no row holds; this journal names the
    files a run of this catalogue made, so that the next run removes those and nothing else (a frame store may
    be shared with other catalogues, whose frames this one does not know).
    """
    if "pending_frames" not in db.table_names():
        db["pending_frames"].create({"sha256": str, "stored": str}, pk="sha256")


def _v9_lens_serial(db: sqlite_utils.Database) -> None:
    """Version 9: the lens serial number each frame's RAW records (NULL for older frames), so that two copies
    of one lens model, which share a rig, can be told apart (`psfd query --lens SERIAL`)."""
    _v3_frame_exif(db)  # adds the one column it lacks


def _v10_pending_store(db: sqlite_utils.Database) -> None:
    """Version 10: the frame store each pending frame was put into (NULL for older rows: any store).

    A catalogue may have runs on several frame stores (`psfd capture --out DIR`); a run sweeps its own store
    only, and must forget only that store's pending frames, or a killed run's leftovers in another store
    would never be removed.
    """
    if "store" not in db["pending_frames"].columns_dict:
        db["pending_frames"].add_column("store", str)


# In the order they landed: a catalogue's user_version counts the migrations it ran. Each later one
# checks its columns before adding them, so a catalogue is the same whichever of them ran first.
MIGRATIONS: list[Callable[[sqlite_utils.Database], None]] = [
    _v1_tables, _v2_query_indexes, _v3_frame_exif, _v4_relative_frame_paths, _v5_prediction_error,
    _v6_noise_floor_as_norm, _v7_relative_psf_sources, _v8_pending_frames, _v9_lens_serial,
    _v10_pending_store]
SCHEMA_VERSION = len(MIGRATIONS)


# ---------------------------------------------------------------------------
# Helpers


def catalogue_exists(path: str | os.PathLike) -> bool:
    """Whether a catalogue is at ``path``: False when the file is missing, and also when it is a database no
    psfd ever wrote to (no table, `PRAGMA user_version` 0): SQLite makes the file as soon as it is opened, so a
    run killed (or a power cut) before the schema's first commit leaves such a file. It holds no run: readers
    treat it as no catalogue, and the next writer makes the catalogue in it (`Catalogue._check_is_catalogue`)."""
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            return False
    except OSError:
        return False
    try:
        conn = sqlite3.connect(f"{path.absolute().as_uri()}?mode=ro", uri=True)
    except sqlite3.Error:
        return True  # let the catalogue's own opening say what is wrong
    try:
        return bool(conn.execute("PRAGMA user_version").fetchone()[0]
                    or conn.execute("SELECT count(*) FROM sqlite_master").fetchone()[0])
    except sqlite3.Error:
        return True
    finally:
        conn.close()


def discard_unused(path: str | os.PathLike) -> bool:
    """Remove the catalogue at ``path`` (and its ``-wal`` and ``-shm``) when it holds no run: the one a run
    created and was stopped, or refused, before it journalled anything. Only for a caller that made it and
    holds it (`psfd.daemon.store.catalogue_lock`). Returns whether it was removed."""
    path = Path(path)
    if catalogue_exists(path):
        try:
            conn = sqlite3.connect(f"{path.absolute().as_uri()}?mode=ro", uri=True)
            try:
                if conn.execute("SELECT count(*) FROM runs").fetchone()[0]:
                    return False
            finally:
                conn.close()
        except sqlite3.Error:  # not a catalogue this process made: leave it as it is
            return False
    for suffix in ("", "-wal", "-shm"):
        with contextlib.suppress(FileNotFoundError):
            path.with_name(path.name + suffix).unlink()
    return True


def check_owner(path: Path, what: str) -> None:
    """Refuse to write into ``path`` (a catalogue, a frame store), when it exists, unless this process's user
    owns it: files this user made there would be theirs, and the owner (e.g. the service's user) could then
    not write, move or remove them."""
    try:
        owner = path.stat().st_uid
    except OSError:  # missing, or not reachable: the write itself says what is wrong
        return
    if owner != os.geteuid():
        me, them = user_name(os.geteuid()), user_name(owner)
        raise StorageError(f"{what} {path} belongs to {them}: writing to it as {me} would leave files {them} "
                           f"cannot use; submit to the service, or run as {them}")


def _check_sqlite_utils() -> None:
    """Refuse to write with a sqlite-utils whose table methods commit the caller's transaction.

    Every write is one transaction (`Catalogue._write`); before 4.0 (no ``Database.atomic``) each
    ``create`` or ``insert`` ended it with ``with conn:``, so that a migration, or a step's frames and PSFs,
    were committed piece by piece: a kill in between left tables under schema version 0 (a file no psfd
    would open) or a step half stored.
    """
    if not hasattr(sqlite_utils.Database, "atomic"):
        from importlib.metadata import version

        raise CatalogueError(f"psfd needs sqlite-utils 4.0 or newer to write a catalogue (this is "
                             f"{version('sqlite-utils')}): pip install 'sqlite-utils>=4.0'")


def _storage_error(exc: sqlite3.Error, what: str) -> StorageError | None:
    """The StorageError of an SQLite failure to write the storage: disk full (SQLITE_FULL), a read-only
    file or file system (SQLITE_READONLY*), a failed write (SQLITE_IOERR*: EROFS after a remount)."""
    if getattr(exc, "sqlite_errorname", "").startswith(("SQLITE_FULL", "SQLITE_READONLY", "SQLITE_IOERR")):
        return StorageError(f"{what}: {exc}")
    return None


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _real(value: Any) -> float | None:
    """A float for a REAL column; NaN (e.g. MTF50 of a kernel that never falls to 0.5) becomes NULL."""
    if value is None:
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array, dtype=np.float64), allow_pickle=False)
    return buffer.getvalue()


def _from_npy(blob: bytes) -> np.ndarray:
    return np.load(io.BytesIO(blob), allow_pickle=False)


def _stops(a: float, b: float) -> float:
    """Distance between two f-numbers in stops (f-numbers form a geometric scale)."""
    return abs(2.0 * math.log2(a / b))


# The serial number of the lens copy that took a PSF's frames, as their EXIF records it.
_LENS_SERIAL = """(SELECT group_concat(DISTINCT f.exif_lens_serial) FROM psf_frames pf
                   JOIN frames f ON f.id = pf.frame_id WHERE pf.psf_id = p.id)"""

# Metadata columns of a PSF row; the array is read only by Catalogue.psf().
_ROW_SQL = f"""
SELECT p.id, p.method, p.channel, p.aperture, p.focal_length_mm, p.focus_distance_m,
       p.field_x, p.field_y, p.window_x0, p.window_y0, p.window_x1, p.window_y1, p.s, p.support,
       p.mtf50_x, p.mtf50_y, p.fwhm_x, p.fwhm_y, p.noise_floor, p.prediction_error, p.residual, p.params,
       p.psfd_version, p.warnings, p.sources, p.created, p.rig_id, p.run_id,
       st.key AS step, r.model AS camera, r.serial, r.lens, {_LENS_SERIAL} AS lens_serial
FROM psfs p LEFT JOIN rigs r ON r.id = p.rig_id LEFT JOIN steps st ON st.id = p.step_id
"""


def _row(raw: dict, folder: Path) -> dict:
    """A PSF row as readers see it: JSON columns decoded, ``sources`` absolute under the catalogue's ``folder``."""
    row = dict(raw)
    row["window"] = [row.pop(k) for k in ("window_x0", "window_y0", "window_x1", "window_y1")]
    for key in ("params", "warnings", "sources"):
        row[key] = json.loads(row[key]) if row[key] else ({} if key == "params" else [])
    row["sources"] = [str(folder / source) for source in row["sources"]]  # an absolute path stays as it is
    return row


class Catalogue:
    """The SQLite catalogue of rigs, runs, steps, frames and PSFs.

    Parameters
    ----------
    path : str or Path
        The SQLite file. Created (with its folder) when missing, unless ``create`` is False.
    create : bool
        False: a missing file raises CatalogueError instead of creating an empty catalogue.
    timeout : float
        Seconds a writer waits for another writer's lock (SQLite busy timeout).
    readonly : bool
        A reader's connection (SQLite ``mode=ro``): it creates and changes nothing, so it
        needs no write access to the file or its folder. (A catalogue of an older schema is
        first migrated by a writer's connection when this process may write it.)

    The connection may be shared between threads; calls are serialised by a lock.

    Readers without write access. A WAL database can be read by a process that may not
    write it or its folder only while its ``-wal`` and ``-shm`` files exist (SQLite, "Read-Only
    Databases" in its WAL documentation, since 3.22); SQLite deletes them when the last
    connection closes unless SQLITE_FCNTL_PERSIST_WAL is set, which Python's sqlite3 module
    cannot set. A writer's `close` therefore puts them back, empty, with the catalogue's own
    mode and owner: an empty WAL and an uninitialised index are states SQLite reads from
    (the read-only index is then rebuilt in the reader's memory). ``immutable=1`` is used only
    when they are missing and cannot be made, and the ``-wal`` held nothing (a catalogue copied
    alone to read-only media, `_on_read_only_media`): it is only safe for a file nobody changes,
    and the service changes the catalogue it serves, whose -wal and -shm then exist.

    Ownership. A writer must own an existing catalogue (`check_owner`): files another user
    made beside it (SQLite's ``-wal`` of a root process) could not be written by its owner.
    """

    def __init__(self, path: str | os.PathLike, *, create: bool = True, timeout: float = 30.0,
                 readonly: bool = False) -> None:
        self.path = Path(path)
        self.readonly = readonly
        self.folder = Path(os.path.abspath(self.path)).parent  # frame paths are stored relative to it
        if not readonly:
            _check_sqlite_utils()
        if not self.path.exists():
            if readonly or not create:
                raise CatalogueError(f"no catalogue at {self.path}")
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise CatalogueError(f"cannot create catalogue {self.path}: {path_reason(self.path.parent, exc)}"
                                     ) from None
        elif self.path.is_dir():
            raise CatalogueError(f"{self.path} is a folder, not a catalogue file")
        elif readonly and not catalogue_exists(self.path):  # a file a writer killed before its first commit left
            raise CatalogueError(f"no catalogue at {self.path}")
        elif not readonly:
            check_owner(self.path, "the catalogue")
        self._lock = threading.RLock()
        try:
            self._open(create, timeout, immutable=False)
        except sqlite3.OperationalError as exc:  # read-only file or folder, locked, ...
            if not self._on_read_only_media():
                raise self._open_error(exc) from None
            log.warning("%s: read as immutable (SQLite immutable=1): its -wal and -shm files are missing and %s is "
                        "read-only", self.path, self.path.parent)
            try:
                self._open(create, timeout, immutable=True)
            except sqlite3.OperationalError as again:
                raise CatalogueError(f"cannot open catalogue {self.path}: {again}") from None

    def _open(self, create: bool, timeout: float, immutable: bool) -> None:
        """Connect and check the file (`_check_is_catalogue`, then the schema: checked, or migrated by a
        writer); an SQLite OperationalError is raised as it is, for the caller to tell why."""
        try:
            if self.readonly:
                uri = f"{self.path.absolute().as_uri()}?mode=ro" + ("&immutable=1" if immutable else "")
                conn = sqlite3.connect(uri, uri=True, timeout=timeout, check_same_thread=False)
            else:
                conn = sqlite3.connect(str(self.path), timeout=timeout, check_same_thread=False)
        except sqlite3.Error as exc:  # e.g. "unable to open database file" in a read-only folder
            raise CatalogueError(f"cannot open catalogue {self.path}: {exc}") from None
        self.db = sqlite_utils.Database(conn)
        try:
            self.db.execute(f"PRAGMA busy_timeout = {int(timeout * 1000)}")
            self.db.execute("PRAGMA foreign_keys = ON")
            self._check_is_catalogue(create and not self.readonly)
            if self.readonly:
                self._check_readable_version()
            else:  # the version was checked first: a catalogue this psfd refuses is left as it was
                self.db.enable_wal()
                self._migrate()
        except sqlite3.OperationalError:
            self.db.close()
            raise
        except sqlite3.DatabaseError as exc:
            self.db.close()
            raise CatalogueError(f"{self.path} is not a psfd catalogue ({exc})") from None
        except BaseException:
            self.db.close()
            raise

    def _on_read_only_media(self) -> bool:
        """Whether a reader's failed open is that of a catalogue on read-only media, which SQLite reads with
        ``immutable=1``: its ``-shm`` missing and not to be created (the folder is read-only, see the class
        notes), and its ``-wal`` missing or empty, so the file alone holds every commit.

        Then no psfd writes it either: a writer (the service) creates both files when it opens the
        catalogue and keeps them after (`_keep_wal_files`). A non-empty ``-wal`` holds commits the file
        lacks, which an immutable read would not see: that stays an error (`_open_error`).
        """
        if not self.readonly or os.access(self.path.parent, os.W_OK):
            return False
        wal = self.path.with_name(self.path.name + "-wal")
        try:
            empty_wal = wal.stat().st_size == 0
        except OSError:
            empty_wal = not wal.exists()
        return empty_wal and not self.path.with_name(self.path.name + "-shm").exists()

    def _open_error(self, exc: sqlite3.OperationalError) -> CatalogueError:
        side = self.path.with_name(self.path.name + "-shm")
        if self.readonly and not side.exists() and not os.access(self.path.parent, os.W_OK):
            return CatalogueError(
                f"cannot read {self.path} without write access to {self.path.parent}: its {side.name} file is "
                "missing and its -wal holds commits not in the file (psfd keeps both files; they come back when "
                "its owner, e.g. the service, opens it)")
        return _storage_error(exc, f"cannot open catalogue {self.path}") or CatalogueError(
            f"cannot open catalogue {self.path}: {exc}")

    # -- connection and transactions ---------------------------------------

    def close(self) -> None:
        """Close the connection; a writer then keeps the WAL files readers without write access need."""
        with self._lock:
            self._checkpoint()
            self.db.close()
            if not self.readonly:
                self._keep_wal_files()

    def _checkpoint(self) -> None:
        """Copy the WAL's committed pages into the catalogue file, without waiting for readers (PASSIVE).

        SQLite does it at close only when no other connection is open: with a reader open (a query,
        Datasette), or in the service that keeps the catalogue open, the rows written would stay in the
        -wal alone, and a copy of the catalogue file would lack them.
        """
        if not self.readonly:
            with contextlib.suppress(sqlite3.Error):
                self.db.execute("PRAGMA wal_checkpoint(PASSIVE)")

    def _keep_wal_files(self) -> None:
        """Re-create the ``-wal`` and ``-shm`` files SQLite deleted at the last close (see the class notes),
        empty, with the catalogue's mode and (for root) its owner, as SQLite itself creates them."""
        try:
            info = self.path.stat()
        except OSError:
            return
        for suffix in ("-wal", "-shm"):
            try:  # O_EXCL: a file another connection made (and uses) is never touched
                fd = os.open(self.path.with_name(self.path.name + suffix),
                             os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
            except OSError:
                continue
            try:
                os.fchmod(fd, stat.S_IMODE(info.st_mode) & 0o666)
                if os.geteuid() == 0:
                    os.fchown(fd, info.st_uid, info.st_gid)
            finally:
                os.close(fd)

    def __enter__(self) -> Catalogue:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @contextlib.contextmanager
    def _write(self) -> Iterator[sqlite_utils.Database]:
        """One write transaction. IMMEDIATE takes the write lock up front, so two writers
        queue on the busy timeout instead of failing on a read-to-write upgrade.

        A transaction that cannot be written (disk full, read-only file system) is rolled
        back whole and raised as a StorageError; another SQLite failure as a CatalogueError.
        """
        with self._lock:
            if self.readonly:
                raise CatalogueError(f"{self.path} is open for reading only")
            if self.db.conn.in_transaction:
                raise CatalogueError("nested catalogue transaction")
            try:
                self.db.execute("BEGIN IMMEDIATE")
            except sqlite3.OperationalError as exc:  # busy timeout ran out, read-only file, ...
                raise (_storage_error(exc, f"cannot write to {self.path}")
                       or CatalogueError(f"cannot write to {self.path}: {exc}")) from None
            try:
                yield self.db
                self.db.execute("COMMIT")
            except sqlite3.OperationalError as exc:
                self._rollback()
                raise (_storage_error(exc, f"cannot write to {self.path}")
                       or CatalogueError(f"cannot write to {self.path}: {exc}")) from None
            except BaseException:
                self._rollback()
                raise

    def _rollback(self) -> None:
        if self.db.conn.in_transaction:  # SQLite may have rolled back on its own (SQLITE_FULL)
            with contextlib.suppress(sqlite3.Error):
                self.db.execute("ROLLBACK")

    @contextlib.contextmanager
    def _read(self) -> Iterator[sqlite_utils.Database]:
        """A read transaction: every SELECT inside sees the same snapshot."""
        with self._lock:
            if self.db.conn.in_transaction:
                yield self.db
                return
            self.db.execute("BEGIN")
            try:
                yield self.db
            finally:
                self.db.rollback()

    def _check_is_catalogue(self, create: bool) -> None:
        """Refuse, before writing anything to it, a file that is not (and may not become) a catalogue,
        or one of a newer psfd (whose files this one must not change, not even to WAL mode).

        The version and the tables are read in one snapshot: another process making the catalogue meanwhile
        commits both at once, and read apart they looked like tables under version 0, a file no psfd made.
        """
        with self._read():
            version = self.schema_version()
            tables = version == 0 and self.db.table_names()
        if version > SCHEMA_VERSION:
            raise CatalogueError(self._newer(version))
        if version > 0:
            return
        if tables:
            raise CatalogueError(f"{self.path} is a SQLite file but not a psfd catalogue")
        if not create:
            raise CatalogueError(f"{self.path} is empty, not a psfd catalogue")

    def _check_readable_version(self) -> None:
        """A reader's check of the schema: a newer one is refused; an older one is migrated by a writer's
        connection when this process may write the catalogue, and refused with what to do otherwise."""
        version = self.schema_version()
        if version > SCHEMA_VERSION:
            raise CatalogueError(self._newer(version))
        if version < SCHEMA_VERSION:
            if os.access(self.path, os.W_OK) and os.access(self.path.parent, os.W_OK | os.X_OK):
                Catalogue(self.path, create=False).close()
            else:
                raise CatalogueError(
                    f"{self.path} has schema version {version}, older than this psfd's ({SCHEMA_VERSION}); "
                    "it is upgraded when its owner (e.g. the service) opens it")

    def _newer(self, version: int) -> str:
        return f"{self.path} has schema version {version}, newer than this psfd ({SCHEMA_VERSION}); upgrade psfd"

    def _migrate(self) -> None:
        version = self.schema_version()
        if version > SCHEMA_VERSION:
            raise CatalogueError(self._newer(version))
        while version < SCHEMA_VERSION:
            with self._write() as db:
                # Re-read inside the lock: another process may have migrated meanwhile.
                version = self.schema_version()
                if version < SCHEMA_VERSION:
                    MIGRATIONS[version](db)
                    version += 1
                    db.execute(f"PRAGMA user_version = {version}")

    def schema_version(self) -> int:
        """The catalogue's ``PRAGMA user_version``."""
        return int(self.db.execute("PRAGMA user_version").fetchone()[0])

    def integrity_check(self) -> list[str]:
        """Problems found (empty when sound): SQLite's own check, foreign keys, and PSFs of unfinished steps.

        A PSF whose step is not ``done`` would mean a step was half committed.
        """
        with self._read() as db:
            problems = [r[0] for r in db.execute("PRAGMA integrity_check").fetchall() if r[0] != "ok"]
            problems += [
                f"foreign key: {table} row {rowid} -> {parent}"
                for table, rowid, parent, _ in db.execute("PRAGMA foreign_key_check").fetchall()
            ]
            problems += [
                f"psf {r['id']} belongs to step {r['key']!r} in state {r['state']}"
                for r in db.query(
                    "SELECT p.id, s.key, s.state FROM psfs p JOIN steps s ON s.id = p.step_id "
                    "WHERE s.state != 'done'"
                )
            ]
        return problems

    # -- rigs and runs ------------------------------------------------------

    def add_rig(self, info: CameraInfo) -> int:
        """Id of the rig (camera model and serial, lens); inserted the first time it is seen."""
        key = {"model": info.model, "serial": info.serial or "", "lens": info.lens or ""}
        with self._write() as db:
            row = next(
                db.query("SELECT id FROM rigs WHERE model = :model AND serial = :serial AND lens = :lens", key),
                None,
            )
            if row is not None:
                return int(row["id"])
            return int(
                db["rigs"].insert({**key, "focal_length_mm": _real(info.focal_length_mm), "created": _now()}).last_pk
            )

    def start_run(self, plan_path: str, plan_text: str, rig_id: int, steps: list[tuple[str, dict]]) -> int:
        """Record a new run of a plan with all its steps ``pending``, in execution order.

        Raises
        ------
        BadInputError
            When two steps share a key.
        """
        keys = [key for key, _ in steps]
        if len(set(keys)) != len(keys):
            dupes = sorted({k for k in keys if keys.count(k) > 1})
            raise BadInputError(f"plan has duplicate step keys: {', '.join(dupes)}")
        now = _now()
        with self._write() as db:
            run_id = int(
                db["runs"].insert(
                    {
                        "rig_id": rig_id, "plan_path": str(plan_path), "plan_text": plan_text,
                        "plan_hash": hashlib.sha256(plan_text.encode()).hexdigest(),
                        "started": now, "finished": None, "state": "running",
                    }
                ).last_pk
            )
            db["steps"].insert_all(
                {
                    "run_id": run_id, "key": key, "position": i, "state": "pending",
                    "payload": json.dumps(payload, sort_keys=True), "reason": None, "attempts": 0,
                    "updated": now,
                }
                for i, (key, payload) in enumerate(steps)
            )
        return run_id

    def plan_runs(self, plan_text: str, states: tuple[str, ...] | None = None,
                  key: Callable[[str], str] = plan_content) -> list[dict]:
        """The runs of this plan, newest first: id, state, started, finished, psfs; ``states``: only those in them.

        A run is of this plan when ``key`` gives its stored text and ``plan_text`` one string: by default
        when the texts say the same (`plan_content`); the daemon's `psfd.daemon.plan.plan_key` also takes
        defaults written out for the plan they stand for. So a plan edited after a stop without changing
        what it does is still the plan of its runs, and no position is measured twice.
        """
        sql = ("SELECT u.id, u.state, u.started, u.finished, u.plan_text, "
               "(SELECT count(*) FROM psfs p WHERE p.run_id = u.id) AS psfs FROM runs u")
        params: list[Any] = []
        if states:
            sql += f" WHERE u.state IN ({', '.join('?' * len(states))})"
            params += list(states)
        with self._read() as db:
            rows = list(db.query(sql + " ORDER BY u.id DESC", params))
        content, same = key(plan_text), {}  # each stored text is parsed once
        for row in rows:
            if row["plan_text"] not in same:
                same[row["plan_text"]] = key(row["plan_text"]) == content
        return [{k: v for k, v in row.items() if k != "plan_text"} for row in rows if same[row["plan_text"]]]

    def unfinished_run(self, plan_text: str, key: Callable[[str], str] = plan_content) -> int | None:
        """The run of this plan (`plan_runs` by ``key``) to resume: the newest that is ``running`` or ``paused``
        (`UNFINISHED_STATES`), or None. Done, cancelled and failed runs are closed.

        Whether a ``running`` run is still alive or was killed is the frame store's to say
        (`psfd.daemon.store.shown_state`); either way it is unfinished.
        """
        return next((int(r["id"]) for r in self.plan_runs(plan_text, UNFINISHED_STATES, key)), None)

    def finish_run(self, run_id: int, state: str) -> None:
        """Set a run's state (``done``, ``paused``, ``cancelled``, ``failed``; ``running`` to resume it)."""
        if state not in RUN_STATES:
            raise BadInputError(f"unknown run state {state!r} (one of {', '.join(RUN_STATES)})")
        with self._write() as db:
            cursor = db.execute(
                "UPDATE runs SET state = ?, finished = ? WHERE id = ?",
                [state, None if state == "running" else _now(), run_id],
            )
            if cursor.rowcount == 0:
                raise CatalogueError(f"no run {run_id}")
        if state != "running":  # a run that stops leaves the catalogue file whole, whoever keeps it open
            with self._lock:
                self._checkpoint()

    def close_finished_runs(self) -> list[int]:
        """Close as ``done`` every run journalled ``running`` that has no step left: a process killed between
        its last commit and its close. Only for a caller that holds the runs' frame store (`store_lock`), so
        that none of them is alive. Returns their ids."""
        with self._write() as db:
            ids = [r[0] for r in db.execute(
                "SELECT id FROM runs u WHERE u.state = 'running' AND NOT EXISTS "
                "(SELECT 1 FROM steps s WHERE s.run_id = u.id AND s.state != 'done')").fetchall()]
            if ids:
                db.execute(f"UPDATE runs SET state = 'done', finished = ? WHERE id IN ({', '.join('?' * len(ids))})",
                           [_now(), *ids])
        return ids

    def runs(self) -> list[dict]:
        """All runs, newest first: id, plan_path, plan_hash, state, started, finished, rig and PSF count."""
        with self._read() as db:
            return list(
                db.query(
                    "SELECT u.id, u.plan_path, u.plan_hash, u.state, u.started, u.finished, u.rig_id, "
                    "r.model AS camera, r.lens, (SELECT count(*) FROM psfs p WHERE p.run_id = u.id) AS psfs "
                    "FROM runs u LEFT JOIN rigs r ON r.id = u.rig_id ORDER BY u.id DESC"
                )
            )

    def run(self, run_id: int) -> dict:
        """One run with its plan text."""
        with self._read() as db:
            row = next(db.query("SELECT * FROM runs WHERE id = ?", [run_id]), None)
        if row is None:
            raise CatalogueError(f"no run {run_id}")
        return row

    def run_rig(self, run_id: int) -> dict:
        """The rig a run began with: its camera ``model``, body ``serial`` and ``lens`` (as `add_rig` keys it)."""
        with self._read() as db:
            row = next(db.query("SELECT r.model, r.serial, r.lens FROM runs u JOIN rigs r ON r.id = u.rig_id "
                                "WHERE u.id = ?", [run_id]), None)
        if row is None:
            raise CatalogueError(f"no run {run_id}")
        return row

    def run_summary(self, run_id: int) -> dict:
        """A run's state and counts: steps per state (``pending``, ``running``, ``done``, ``failed``),
        ``total`` steps, ``psfs`` stored and the ``frames`` they came from."""
        with self._read() as db:
            run = self.run(run_id)
            counts = dict.fromkeys(STEP_STATES, 0)
            for row in db.query("SELECT state, count(*) AS n FROM steps WHERE run_id = ? GROUP BY state", [run_id]):
                counts[row["state"]] = row["n"]
            psfs = db.execute("SELECT count(*) FROM psfs WHERE run_id = ?", [run_id]).fetchone()[0]
            frames = db.execute(
                "SELECT count(DISTINCT pf.frame_id) FROM psf_frames pf JOIN psfs p ON p.id = pf.psf_id "
                "WHERE p.run_id = ?",
                [run_id],
            ).fetchone()[0]
        return {
            "id": run_id, "state": run["state"], "plan_path": run["plan_path"],
            "started": run["started"], "finished": run["finished"],
            **counts, "total": sum(counts.values()), "psfs": psfs, "frames": frames,
        }

    # -- steps ----------------------------------------------------------------

    def steps(self, run_id: int, states: tuple[str, ...] | None = None) -> list[dict]:
        """Steps of a run in execution order: key, state, payload (dict), reason, attempts, position, updated."""
        sql = "SELECT key, state, payload, reason, attempts, position, updated FROM steps WHERE run_id = ?"
        params: list[Any] = [run_id]
        if states:
            sql += f" AND state IN ({', '.join('?' * len(states))})"
            params += list(states)
        with self._read() as db:
            rows = list(db.query(sql + " ORDER BY position", params))
        for row in rows:
            row["payload"] = json.loads(row["payload"]) if row["payload"] else {}
        return rows

    def last_rail_position(self, run_id: int) -> dict | None:
        """The rail position ({x, y, z} in mm) of the run's latest stored frame; None before its first."""
        sql = ("SELECT f.rail FROM frames f JOIN psf_frames pf ON pf.frame_id = f.id JOIN psfs p ON p.id = pf.psf_id "
               "WHERE p.run_id = ? ORDER BY f.id DESC LIMIT 1")
        with self._read() as db:
            row = db.execute(sql, [run_id]).fetchone()
        return json.loads(row[0]) if row and row[0] else None

    def _step(self, db: sqlite_utils.Database, run_id: int, key: str) -> dict:
        row = next(db.query("SELECT id, state FROM steps WHERE run_id = ? AND key = ?", [run_id, key]), None)
        if row is None:
            raise CatalogueError(f"run {run_id} has no step {key!r}")
        return row

    def set_step_state(self, run_id: int, key: str, state: str, reason: str | None = None) -> bool:
        """Move a step to ``state`` with an optional reason; entering ``running`` counts an attempt.

        A ``done`` step stays done (returns False): its PSFs are committed, and another process on this
        catalogue (one with another frame store, which the store's lock does not hold back) may have
        committed it since the caller read its steps; shooting it again would store its PSFs twice.
        """
        if state not in STEP_STATES:
            raise BadInputError(f"unknown step state {state!r} (one of {', '.join(STEP_STATES)})")
        with self._write() as db:
            step = self._step(db, run_id, key)
            if step["state"] == "done":
                return False
            db.execute(
                "UPDATE steps SET state = ?, reason = ?, updated = ?, attempts = attempts + ? WHERE id = ?",
                [state, reason, _now(), int(state == "running"), step["id"]],
            )
        return True

    def commit_step(
        self, run_id: int, key: str, frames: list[FrameRecord], psfs: list[tuple[PSF, dict]]
    ) -> list[int]:
        """Store a step's frames and PSFs and mark it ``done``, all in one transaction.

        Parameters
        ----------
        frames : list of FrameRecord
            The RAW files the step captured (a file already catalogued, by hash, is reused).
        psfs : list of (PSF, dict)
            Each PSF with ``aperture``, ``focal_length_mm``, ``focus_distance_m`` and
            ``frame_indices`` (indices into ``frames``; missing means all of them).

        Returns
        -------
        list of int
            Ids of the step's PSFs. A step already ``done`` inserts nothing and returns the
            ids stored when it was committed: replaying a step after a crash is harmless.
        """
        with self._write() as db:
            step = self._step(db, run_id, key)
            if step["state"] == "done":
                return [r["id"] for r in db.query("SELECT id FROM psfs WHERE step_id = ? ORDER BY id", [step["id"]])]
            rig_id = db.execute("SELECT rig_id FROM runs WHERE id = ?", [run_id]).fetchone()[0]
            ids = self._insert(db, frames, psfs, rig_id=rig_id, run_id=run_id, step_id=step["id"])
            db.execute(
                "UPDATE steps SET state = 'done', reason = NULL, updated = ? WHERE id = ?", [_now(), step["id"]]
            )
        return ids

    def _insert(
        self,
        db: sqlite_utils.Database,
        frames: list[FrameRecord],
        psfs: list[tuple[PSF, dict]],
        *,
        rig_id: int | None,
        run_id: int | None,
        step_id: int | None,
    ) -> list[int]:
        frame_ids = [self._insert_frame(db, f, self.folder) for f in frames]
        db.conn.executemany("DELETE FROM pending_frames WHERE sha256 = ?", [(f.sha256,) for f in frames])
        ids = []
        for estimate, meta in psfs:
            indices = meta.get("frame_indices")
            indices = range(len(frame_ids)) if indices is None else indices
            if any(not 0 <= i < len(frame_ids) for i in indices):
                raise BadInputError(f"frame index out of range in {list(indices)} ({len(frame_ids)} frames)")
            record = self._psf_record(estimate, meta, rig_id, run_id, step_id, self.folder)
            psf_id = int(db["psfs"].insert(record).last_pk)
            db["psf_frames"].insert_all(
                ({"psf_id": psf_id, "frame_id": frame_ids[i]} for i in sorted(set(indices))),
            )
            ids.append(psf_id)
        return ids

    @staticmethod
    def _insert_frame(db: sqlite_utils.Database, frame: FrameRecord, folder: Path) -> int:
        db["frames"].insert(
            {
                "path": stored_frame_path(frame.path, folder), "sha256": frame.sha256,
                "settings": json.dumps(frame.settings, sort_keys=True),
                "aperture": camera_fnumber(frame.settings.get("aperture")),
                "rail": json.dumps(frame.rail, sort_keys=True), "taken_at": frame.taken_at,
                **{column: (frame.exif or {}).get(name) for column, name in FRAME_EXIF.items()},
            },
            ignore=True,  # the same file (same hash) is one frame, whoever uses it
        )
        return int(db.execute("SELECT id FROM frames WHERE sha256 = ?", [frame.sha256]).fetchone()[0])

    @staticmethod
    def _psf_record(estimate: PSF, meta: dict, rig_id: int | None, run_id: int | None, step_id: int | None,
                    folder: Path) -> dict:
        array = np.asarray(estimate.psf, dtype=np.float64)
        if array.ndim != 2 or array.shape[0] % 2 == 0 or array.shape[1] % 2 == 0 or not np.all(np.isfinite(array)):
            raise BadInputError(f"PSF array must be 2-D, odd-sized and finite (got shape {array.shape})")
        metrics = estimate.metrics()
        x0, y0, x1, y1 = (int(v) for v in estimate.window)
        return {
            "rig_id": rig_id, "run_id": run_id, "step_id": step_id,
            "method": estimate.method, "channel": estimate.channel,
            "aperture": parse_fnumber(meta.get("aperture")),
            "focal_length_mm": _real(meta.get("focal_length_mm")),
            "focus_distance_m": _real(meta.get("focus_distance_m")),
            "field_x": float(estimate.field[0]), "field_y": float(estimate.field[1]),
            "window_x0": x0, "window_y0": y0, "window_x1": x1, "window_y1": y1,
            "s": int(estimate.s), "support": int(array.shape[0]), "psf": _npy(array),
            **{k: _real(v) for k, v in metrics.items()},
            "noise_floor": _real(estimate.noise_floor), "prediction_error": _real(estimate.prediction_error),
            "residual": _real(estimate.residual),
            "params": json.dumps(estimate.params, sort_keys=True, default=str),
            "psfd_version": __version__,
            "warnings": json.dumps(list(estimate.warnings)),
            # as frame paths: relative to the catalogue's folder when inside it, so the two can move together
            "sources": json.dumps([stored_frame_path(s, folder) for s in estimate.sources]),
            "created": _now(),
        }

    # -- queries --------------------------------------------------------------

    def query(
        self,
        camera: str | None = None,
        lens: str | None = None,
        aperture: float | None = None,
        channel: str | None = None,
        method: str | None = None,
        near: tuple[float, float] | None = None,
        limit: int | None = None,
    ) -> QueryResult:
        """PSFs matching the filters (metadata rows; arrays via :meth:`psf`).

        Parameters
        ----------
        camera, lens : str, optional
            Case-insensitive substring of the camera model / the lens, or the exact serial of the body / of the
            lens copy (in any case).
        aperture : float, optional
            f-number. Each camera body, lens copy and focal length (`_optics`) that was not measured at it
            gives its PSFs at its nearest measured aperture (in stops) among the other filters, and
            ``note`` names them.
        channel, method : str, optional
            Exact channel (r, g1, g2, b, mono), and method (`psfd.vocabulary.METHODS`, or an older alias).
        near : (x, y), optional
            Normalised field location: keeps, per (rig, lens copy, focal length, aperture, channel, method),
            the PSF whose field position is nearest, and orders rows by that distance.
        limit : int, optional
            At most this many rows.
        """
        where, params = [], []
        for _, _, clause, values in _filters(camera, lens, method, channel):
            where.append(clause)
            params += values
        note, nearest = None, {}
        with self._read() as db:
            if aperture is not None:
                nearest, note = self._nearest_apertures(db, where, params, float(aperture))
                # the f-numbers kept, whatever the optics; each row is then checked against its own below
                where.append("(" + (" OR ".join(["p.aperture BETWEEN ? AND ?"] * len(nearest)) or "0") + ")")
                params += [bound for a in nearest.values() for bound in _aperture_range(a)]
            sql = _ROW_SQL + (f" WHERE {' AND '.join(where)}" if where else "")
            sql += " ORDER BY r.model, r.lens, p.aperture, p.channel, p.method, p.field_y, p.field_x, p.id"
            rows = [_row(r, self.folder) for r in db.query(sql, params)]
        if aperture is not None:
            rows = [r for r in rows if _same_aperture(r["aperture"], nearest.get(_optics(r)))]
        if near is not None:
            rows, far = _nearest_per_group(rows, near)
            note = "; ".join(n for n in (note, far) if n) or None
        if limit is not None:
            rows = rows[: max(int(limit), 0)]
        return QueryResult(rows, note)

    def why_empty(
        self,
        camera: str | None = None,
        lens: str | None = None,
        aperture: float | None = None,
        channel: str | None = None,
        method: str | None = None,
    ) -> str | None:
        """Why `query` with these filters finds no PSF, in a phrase; None when it finds some.

        The filters are applied one at a time, in the order camera, lens, method, channel, aperture,
        and the first that leaves no PSF is named with the values the PSFs before it have, e.g.
        ``"no PSF of channel b with camera 'canon' (these have g1, r)"``. The aperture comes last
        because `query` takes the measured f-number nearest the one asked among the PSFs of the
        other filters: it leaves none only when none of them has an f-number.
        """
        where: list[str] = []
        params: list = []
        named: list[str] = []
        with self._read() as db:
            if not self._count(db, where, params):
                return "the catalogue holds no PSF"
            for name, label, clause, values in _filters(camera, lens, method, channel):
                if not self._count(db, [*where, clause], [*params, *values]):
                    column = {"camera": "r.model", "lens": "r.lens", "method": "p.method", "channel": "p.channel"}
                    there = [str(v) if v else "(none)" for v in self._distinct(db, column[name], where, params)]
                    return _empty_phrase(f"no PSF of {label}", named, _listed(there))
                where, params, named = [*where, clause], [*params, *values], [*named, label]
            if aperture is not None and not self._apertures(db, where, params):
                return _empty_phrase(f"no PSF at f/{float(aperture):g}", named, "no f-number")
        return None

    @staticmethod
    def _count(db: sqlite_utils.Database, where: list[str], params: list) -> int:
        sql = "SELECT count(*) FROM psfs p LEFT JOIN rigs r ON r.id = p.rig_id"
        return int(db.execute(sql + (f" WHERE {' AND '.join(where)}" if where else ""), params).fetchone()[0])

    @staticmethod
    def _distinct(db: sqlite_utils.Database, column: str, where: list[str], params: list) -> list:
        sql = f"SELECT DISTINCT {column} FROM psfs p LEFT JOIN rigs r ON r.id = p.rig_id"
        sql += (f" WHERE {' AND '.join(where)}" if where else "") + f" ORDER BY {column}"
        return [row[0] for row in db.execute(sql, params).fetchall()]

    @staticmethod
    def _apertures(db: sqlite_utils.Database, where: list[str], params: list) -> list[float]:
        return Catalogue._distinct(db, "p.aperture", [*where, "p.aperture IS NOT NULL"], params)

    @staticmethod
    def _nearest_apertures(db: sqlite_utils.Database, where: list[str], params: list, asked: float
                           ) -> tuple[dict[tuple, float], str | None]:
        """The measured f-number nearest ``asked`` (in stops; the smaller of two as near) of each `_optics`
        among the PSFs of the filters ``where``, and a note naming the optics not measured at ``asked``.

        Per optics, not over the catalogue: a lens measured at f/4 and f/8 answers f/11 with its f/8 PSFs
        whether or not another lens was measured at f/11, and what one lens answers does not change when
        another is added to the catalogue.
        """
        sql = (f"SELECT DISTINCT p.rig_id, {_LENS_SERIAL} AS lens_serial, p.focal_length_mm, p.aperture, "
               "r.model AS camera, r.serial, r.lens FROM psfs p LEFT JOIN rigs r ON r.id = p.rig_id WHERE "
               + " AND ".join([*where, "p.aperture IS NOT NULL"]))
        measured: dict[tuple, list[float]] = {}
        names: dict[tuple, dict] = {}
        for row in db.query(sql, params):
            measured.setdefault(_optics(row), []).append(row["aperture"])
            names[_optics(row)] = row
        nearest = {optics: min(apertures, key=lambda a: (_stops(a, asked), a)) for optics, apertures in measured.items()}
        missing = {optics: a for optics, a in nearest.items() if not _same_aperture(asked, a)}
        if not missing:
            return nearest, None
        if len(nearest) == 1:
            return nearest, f"f/{asked:g} not measured; nearest is f/{next(iter(missing.values())):g}"
        focal_lengths: dict[tuple, int] = {}
        for rig, lens_serial, _ in nearest:
            focal_lengths[rig, lens_serial] = focal_lengths.get((rig, lens_serial), 0) + 1
        named = sorted(f"{_optics_name(names[optics], focal_lengths[optics[:2]] > 1)} (nearest: f/{a:g})"
                       for optics, a in missing.items())
        return nearest, f"f/{asked:g} not measured with {_listed(named)}"

    def psf(self, psf_id: int) -> tuple[np.ndarray, dict]:
        """The PSF array (float64) and its metadata row."""
        with self._read() as db:
            row = next(db.query(_ROW_SQL + " WHERE p.id = ?", [psf_id]), None)
            blob = db.execute("SELECT psf FROM psfs WHERE id = ?", [psf_id]).fetchone()
        if row is None or blob is None:
            raise CatalogueError(f"no PSF {psf_id}")
        return _from_npy(blob[0]), _row(row, self.folder)

    def psf_frames(self, psf_id: int) -> list[dict]:
        """The frames a PSF was estimated from (``path`` absolute, wherever it is stored relative)."""
        with self._read() as db:
            rows = list(
                db.query(
                    "SELECT f.* FROM frames f JOIN psf_frames pf ON pf.frame_id = f.id WHERE pf.psf_id = ? "
                    "ORDER BY f.id",
                    [psf_id],
                )
            )
        for row in rows:
            row["path"] = str(self.folder / row["path"])  # an absolute path stays as it is
            row["settings"] = json.loads(row["settings"] or "{}")
            row["rail"] = json.loads(row["rail"] or "{}")
        return rows

    def pend_frame(self, sha256: str, store: str | os.PathLike | None = None) -> None:
        """Journal a frame about to be put into the frame store ``store``, before its step commits
        (`pending_frames`)."""
        where = stored_frame_path(store, self.folder) if store is not None else None
        with self._write() as db:
            db["pending_frames"].insert({"sha256": sha256, "stored": _now(), "store": where}, replace=True)

    def pending_frames(self, store: str | os.PathLike | None = None) -> set[str]:
        """SHA-256 of the frames journalled by `pend_frame` whose step has not committed them; with ``store``,
        only those put into that frame store (and those of older catalogues, which did not say where)."""
        sql, params = "SELECT sha256 FROM pending_frames", []
        if store is not None:
            sql += " WHERE store IS NULL OR store = ?"
            params = [stored_frame_path(store, self.folder)]
        with self._read() as db:
            return {row[0] for row in db.execute(sql, params).fetchall()}

    def forget_pending(self, hashes: Iterable[str]) -> None:
        """Drop ``hashes`` from the pending frames: swept, discarded or committed."""
        with self._write() as db:
            db.conn.executemany("DELETE FROM pending_frames WHERE sha256 = ?", [(h,) for h in hashes])

    def frame_hashes(self) -> set[str]:
        """SHA-256 of every catalogued frame (the daemon's frame store keeps exactly these files)."""
        with self._read() as db:
            return {row[0] for row in db.execute("SELECT sha256 FROM frames").fetchall()}


def _optics(row: Mapping[str, Any]) -> tuple:
    """What an f-number is measured on: the camera body (rig), the lens copy and the focal length."""
    return row["rig_id"], row["lens_serial"], row["focal_length_mm"]


def _optics_name(row: Mapping[str, Any], focal_length: bool) -> str:
    """``Canon EOS 400D #0420 / EF 50mm f/1.8 #c1234``, and ``at 70 mm`` with ``focal_length``."""
    body = " ".join(part for part in (row["camera"], f"#{row['serial']}" if row["serial"] else "") if part)
    lens = " ".join(part for part in (row["lens"], f"#{row['lens_serial']}" if row["lens_serial"] else "") if part)
    name = f"{body or 'unknown camera'} / {lens or 'unknown lens'}"
    if focal_length:
        focal = row["focal_length_mm"]
        name += f" at {focal:g} mm" if focal is not None else " at an unknown focal length"
    return name


def _aperture_range(aperture: float) -> tuple[float, float]:
    """The f-numbers that are ``aperture`` (`APERTURE_TOLERANCE`)."""
    return aperture / (1 + APERTURE_TOLERANCE), aperture * (1 + APERTURE_TOLERANCE)


def _same_aperture(value: float | None, aperture: float | None) -> bool:
    if value is None or aperture is None:
        return False
    lo, hi = _aperture_range(aperture)
    return lo <= value <= hi


def _filters(camera: str | None, lens: str | None, method: str | None, channel: str | None
             ) -> list[tuple[str, str, str, list]]:
    """The SQL of the filters given: (name, how a message names it, clause, its parameters), in the order
    `Catalogue.why_empty` applies them."""
    filters = []
    if camera:
        filters.append(("camera", f"camera {camera!r}",
                        "(instr(lower(r.model), lower(?)) > 0 OR lower(r.serial) = lower(?))", [camera, camera]))
    if lens:
        # the name, or the exact serial of the lens copy that took one of the PSF's frames
        filters.append(("lens", f"lens {lens!r}", "(instr(lower(r.lens), lower(?)) > 0 OR EXISTS (SELECT 1 FROM "
                        "psf_frames pf JOIN frames f ON f.id = pf.frame_id WHERE pf.psf_id = p.id AND "
                        "lower(f.exif_lens_serial) = lower(?)))", [lens, lens]))
    if method:
        method = method_name(method)
        filters.append(("method", f"method {method}", "p.method = ?", [method]))
    if channel:
        filters.append(("channel", f"channel {channel}", "p.channel = ?", [channel]))
    return filters


def _listed(values: list[str], most: int = 8) -> str:
    """``a, b, c``, or the first ``most`` and how many more (a catalogue of many cameras stays one line)."""
    shown = ", ".join(values[:most])
    return shown + (f" and {len(values) - most} more" if len(values) > most else "")


def _empty_phrase(what: str, before: list[str], there: str) -> str:
    """``no PSF of X (the catalogue has ...)``, or ``no PSF of X with Y, Z (these have ...)`` after other filters."""
    if not before:
        return f"{what} (the catalogue has {there})"
    return f"{what} with {', '.join(before)} (these have {there})"


def _nearest_per_group(rows: list[dict], near: tuple[float, float]) -> tuple[list[dict], str | None]:
    """Keep the PSF nearest ``near`` per (rig, lens copy, focal length, aperture, channel, method), nearest first,
    and a note when one of them lies outside the grid of its group's stored locations (`_far_note`).

    Ties (repeated measurements at one location) go to the newest PSF. ``distance`` is in normalised
    field units, as ``field_x`` and ``field_y`` (a fraction of the width across, of the height down).
    """
    x, y = near
    for row in rows:
        row["distance"] = math.hypot(row["field_x"] - x, row["field_y"] - y)
    best: dict[tuple, dict] = {}
    groups: dict[tuple, list[dict]] = {}
    for row in sorted(rows, key=lambda r: (r["distance"], -r["id"])):
        group = (row["rig_id"], row["lens_serial"], row["focal_length_mm"], row["aperture"], row["channel"],
                 row["method"])
        best.setdefault(group, row)
        groups.setdefault(group, []).append(row)
    kept = sorted(best.values(), key=lambda r: (r["distance"], r["aperture"] or 0.0, r["channel"], r["method"]))
    return kept, _far_note(near, [(best[g], groups[g]) for g in best])


# Two stored field coordinates closer than this are one grid line: window edges are whole channel
# pixels (`psfd.estimator.kernels.split_grid`), so the centres of one grid column in frames of one size
# differ by a pixel or less, 1/1000 of the field on the smallest planes psfd reads.
_SAME_LINE = 1e-3


def _grid_step(values: list[float]) -> float:
    """The grid step of stored field coordinates along one axis: the median gap between distinct ones
    (robust to a missing window and to grids of several frames); 1, the whole field, for a single one."""
    lines: list[float] = []
    for value in sorted(values):
        if not lines or value - lines[-1] > _SAME_LINE:
            lines.append(value)
    gaps = [b - a for a, b in zip(lines, lines[1:])]
    return float(np.median(gaps)) if gaps else 1.0


def _far_note(near: tuple[float, float], groups: list[tuple[dict, list[dict]]]) -> str | None:
    """A note when the nearest PSF of a group is farther from ``near`` than half its grid step along x or y.

    Grid windows tile the measured region, each reaching half a step either side of its centre
    (`psfd.estimator.kernels.split_grid`): a point within half a step of the nearest stored location
    along both axes lies inside that PSF's window, the edges of a whole grid's outer windows included.
    Farther, it lies in no measured window (a failed window, a partial run, outside the target's
    region): the PSF returned was measured elsewhere in the field. A single location along an axis has
    no step; it is taken as covering that axis (step 1, the whole field), so only a location more than
    half the field away is noted. The farthest such PSF is named; how many there are when not all.
    """
    far = []
    for row, members in groups:
        steps = (_grid_step([r["field_x"] for r in members]), _grid_step([r["field_y"] for r in members]))
        offsets = (abs(row["field_x"] - near[0]), abs(row["field_y"] - near[1]))
        if any(offset > step / 2 + 1e-9 for offset, step in zip(offsets, steps)):
            far.append((row["distance"], row, steps))
    if not far:
        return None
    distance, row, (across, down) = max(far, key=lambda item: item[0])
    share = f" for {len(far)} of {len(groups)} PSFs" if len(far) < len(groups) else ""
    return (f"no PSF measured near {near[0]:g},{near[1]:g}{share}: the nearest stored location "
            f"({row['field_x']:.3f},{row['field_y']:.3f}) is {distance:.3f} away, more than half the grid step "
            f"({across:.3f} across, {down:.3f} down)")


# ---------------------------------------------------------------------------
# Description for other tools

# Every column of every table, with its unit: shown by Datasette (`datasette_metadata`) and the docs.
COLUMNS: dict[str, dict[str, str]] = {
    "rigs": {
        "id": "rig id",
        "model": "camera model as the camera reports it",
        "serial": "camera body serial number ('' when unknown)",
        "lens": "lens name ('' when unknown)",
        "focal_length_mm": "focal length when the rig was first seen, mm",
        "created": "when the rig was first seen, ISO 8601 UTC",
    },
    "runs": {
        "id": "run id",
        "rig_id": "the rig (rigs.id)",
        "plan_path": "path of the plan file as given",
        "plan_text": "the plan's TOML text, verbatim (a run is resumed for a text of the same plan: comments, "
                     "layout and defaults written out aside)",
        "plan_hash": "SHA-256 of plan_text",
        "started": "start, ISO 8601 UTC",
        "finished": "end, ISO 8601 UTC (empty while running)",
        "state": "running, done, paused, cancelled or failed",
    },
    "steps": {
        "id": "step id",
        "run_id": "the run (runs.id)",
        "key": "aperture, rail position and repeat, e.g. a5.6/x1200/y-40/z10/r0 (rail positions in mm)",
        "position": "order of the step in its run",
        "state": "pending, running, done or failed",
        "payload": "the step as JSON: aperture (f-number), x or near/far, y, z (mm), repeat",
        "reason": "why the step failed (empty otherwise)",
        "attempts": "how many times the step was started",
        "updated": "last change, ISO 8601 UTC",
    },
    "frames": {
        "id": "frame id",
        "path": "the RAW file: relative to the catalogue's folder when inside it, else absolute",
        "sha256": "SHA-256 of the file's content (its name in the frame store)",
        "settings": "camera settings asked for, JSON: aperture as an f-number (a number), the plan's [rig] settings "
                    "as given, in the camera's own words (e.g. shutterspeed \"1/250\", iso \"200\": strings, not "
                    "seconds; exif_exposure_s has the exposure in s)",
        "aperture": "f-number asked for",
        "rail": "rail position of the exposure, JSON {x, y, z} in mm",
        "taken_at": "when the frame was taken, ISO 8601 UTC (the host's clock once the file is downloaded; how long "
                    "the exposure lasted is exif_exposure_s)",
        "exif_focal_length_mm": "focal length the RAW's EXIF records, mm (NULL when absent)",
        "exif_f_number": "f-number the RAW's EXIF records",
        "exif_exposure_s": "exposure time the RAW's EXIF records, s",
        "exif_iso": "ISO speed the RAW's EXIF records",
        "exif_lens": "lens the RAW's EXIF names",
        "exif_serial": "camera serial number the RAW's EXIF records",
        "exif_lens_serial": "lens serial number the RAW's EXIF records (NULL when the camera does not write it)",
        "exif_focus_distance_m": "focus distance the RAW's EXIF records, m (NULL when the lens does not say)",
    },
    "psfs": {
        "id": "PSF id",
        "rig_id": "the rig (rigs.id)",
        "run_id": "the run (runs.id)",
        "step_id": "the step (steps.id)",
        "method": "bernoulli, two-photo or sharp-edge",
        "channel": "Bayer channel plane: r, g1, g2, b (or mono)",
        "aperture": "f-number",
        "focal_length_mm": "focal length, mm",
        "focus_distance_m": "focus distance, m",
        "field_x": "window centre across the image, normalised: 0 left edge, 1 right edge",
        "field_y": "window centre down the image, normalised: 0 top edge, 1 bottom edge",
        "window_x0": "window left edge on the channel plane, channel pixels",
        "window_y0": "window top edge on the channel plane, channel pixels",
        "window_x1": "window right edge (exclusive), channel pixels",
        "window_y1": "window bottom edge (exclusive), channel pixels",
        "s": "super-resolution factor: kernel samples per channel pixel",
        "support": "kernel side, samples of the s-times grid (odd)",
        "psf": "the kernel: a NumPy .npy file (float64, support x support, unit sum, centred), "
               "numpy.load(io.BytesIO(blob))",
        "mtf50_x": "MTF50 along x (horizontal frequency), cycles per channel pixel (Nyquist 0.5)",
        "mtf50_y": "MTF50 along y (vertical frequency), cycles per channel pixel (Nyquist 0.5)",
        "fwhm_x": "full width at half maximum along x, channel pixels",
        "fwhm_y": "full width at half maximum along y, channel pixels",
        "noise_floor": "expected L2 norm of the unit-sum kernel's error from sensor noise (over all its samples)",
        "prediction_error": "cross-validated prediction error: the kernel fitted on one half of the noise region "
                            "predicts the other half, RMS residual over the noise level (about 1 when the model "
                            "holds; NULL for methods without it and older rows)",
        "residual": "RMS residual of the image model, normalised data units (0 to 1)",
        "params": "estimator parameters, JSON",
        "psfd_version": "psfd version that made the estimate",
        "warnings": "conditions of the method only partly met, JSON list of sentences",
        "sources": "files the estimate came from, JSON list: relative to the catalogue's folder when inside it, "
                   "else absolute",
        "created": "when the estimate was stored, ISO 8601 UTC",
    },
    "psf_frames": {
        "psf_id": "the PSF (psfs.id)",
        "frame_id": "a frame it was estimated from (frames.id)",
    },
    "pending_frames": {
        "sha256": "SHA-256 of a file a run put into its frame store, its step not yet committed",
        "stored": "when it was stored, ISO 8601 UTC",
        "store": "the frame store it was put into: relative to the catalogue's folder when inside it, else "
                 "absolute; NULL in older catalogues (any store)",
    },
}
TABLES = {
    "rigs": "Cameras and lenses, one row per model, serial and lens.",
    "runs": "Runs of measurement plans, with the plan's text.",
    "steps": "The journal of each run: one row per exposure position, with its state.",
    "frames": "RAW frames, stored once by content hash.",
    "psfs": "Sub-pixel PSFs, one per channel, field location and aperture, with their metrics.",
    "psf_frames": "Which frames each PSF was estimated from.",
    "pending_frames": "Frames stored by a run whose step is not committed yet: a crash's leftovers, removed by "
                      "the next run on their frame store.",
}
# Units Datasette shows beside values (names from Pint's registry); the others are in the descriptions.
UNITS = {"rigs": {"focal_length_mm": "mm"}, "psfs": {"focal_length_mm": "mm", "focus_distance_m": "m"}}


def datasette_metadata(database: str = "catalogue") -> dict:
    """Datasette's metadata (``datasette CATALOGUE.sqlite -m metadata.json``) for a catalogue file
    whose name without suffix is ``database``: every table and column described, with units."""
    return {
        "title": "psfd PSF catalogue",
        "description": "Sub-pixel point spread functions measured by psfd: MTF50 in cycles per channel pixel "
                       "(Nyquist 0.5), FWHM in channel pixels, field positions normalised (0,0 top-left).",
        "databases": {
            database: {
                "description": f"psfd catalogue, schema version {SCHEMA_VERSION}",
                "tables": {
                    name: {
                        "description": TABLES[name],
                        "columns": dict(columns),
                        **({"units": UNITS[name]} if name in UNITS else {}),
                        **({"sort_desc": "id"} if name in ("runs", "psfs") else {}),
                    }
                    for name, columns in COLUMNS.items()
                },
            }
        },
    }
