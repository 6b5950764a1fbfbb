"""The resumable runner: a plan's steps, journalled in the catalogue, shot and estimated.

Durability rules, in the order a step goes through them:

1. the step is marked ``running`` in the catalogue before the rig moves;
2. each RAW file goes into the content-addressed frame store (`psfd.daemon.store`);
3. PSFs are estimated in worker processes while the rig goes on to the next
   step, so the rig only waits when every worker is busy;
4. the parent commits frames, PSFs and the step's ``done`` state in one
   catalogue transaction.

A crash between any two of these leaves a step ``running`` (redone on resume)
and perhaps a frame file the catalogue does not know. Each file is journalled
in the catalogue before it enters the store (`Catalogue.pend_frame`), so
`sweep_frames` removes exactly those at the start of every run: no file is
orphaned, none is counted twice, and a frame store shared with another
catalogue keeps that one's frames.
A failed step (camera gone, rail alarm, no target in the frame) is marked
``failed`` with its reason, the estimates already under way are committed,
the rig is released, and the run is ``paused``: ``--resume`` retries it. A worker
that dies (killed, out of memory) fails the step it was estimating so; the other
steps handed to the workers are estimated again in new ones. Signals are the
parent's alone (`work.init_worker`): Ctrl-C or SIGTERM sent to the whole process
or control group stops the run exactly as when sent to psfd only.

A run's journal says ``running`` only while its process holds the frame-store
lock (`store.store_busy`) and the catalogue's (`store.catalogue_lock`: one writing
run per catalogue, whatever its frame store, so that what a run reads before it
writes, a step done or a frame journalled, is not changed under it): a ``running``
run whose store and catalogue are free was killed, and is resumable like a paused
one (`interrupted`). Starting a plan that has an
unfinished run (`Catalogue.unfinished_run`) is refused unless the caller
resumes it or asks for a new run, so that no position is measured twice by accident.
A run is closed whenever it has no step left: a resumed run with nothing to do, and
at the start of every run, any run killed between its last commit and its close
(`Catalogue.close_finished_runs`), a `psfd capture` included.

A frame or a commit the storage refuses (disk full, read-only file system) is a
`StorageError`: the step is not committed, the run pauses (or, when even that
cannot be written, is left interrupted) and ``--resume`` continues once there is room.

`run_plan` is the one way to run a plan: check what would refuse it before
anything is created (`preflight`), open the plan's rig and ask it what it cannot
do (`check_rig`), take the frame store, open the catalogue, run, and fetch the
stored rows; the command line and the service both call it.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import logging
import multiprocessing
import os
import shutil
import signal
import stat
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from datetime import datetime, timezone
from multiprocessing import resource_tracker
from pathlib import Path
from typing import IO, Any, Callable

from psfd.catalogue import UNFINISHED_STATES, Catalogue, FrameRecord, catalogue_exists, check_owner, discard_unused
from psfd.daemon import work
from psfd.daemon.plan import Plan, Step, check_rail, plan_changes, plan_key, recording_problems
from psfd.daemon.store import (INCOMING, catalogue_lock, catalogue_lock_path, check_catalogue_free, check_room,
                               shown_state, storage_error, store_frame, store_lock, sweep_frames)
from psfd.drivers import open_rig
from psfd.drivers.base import Camera, CameraReady, CameraSetup, Rail, settle
from psfd.errors import (BadInputError, CameraError, EstimationError, HardwareError, Interrupted, PsfdError, RailError,
                         StorageError)
from psfd.estimator.raw import RAW_SUFFIXES
from psfd.exif import check_settings, read_metadata
from psfd.vocabulary import BACKLOG_MAX, WORKERS_MAX, check_count, offered_choice

# Below this much free space, a failed download is put down to the storage: no RAW file is smaller.
FRAME_BYTES_MIN = 1 << 20

__all__ = ["Control", "RunResult", "Runner", "StoppedBeforeStart", "default_workers", "preflight", "release_rig",
           "run_plan", "start_check", "unfinished_runs"]

log = logging.getLogger(__name__)


class Control:
    """Requests from outside a running plan (control socket, signals), read between frames."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._request: str | None = None

    def request(self, what: str) -> None:
        """Ask the runner to stop after the current frame: ``pause`` or ``cancel``."""
        if what not in ("pause", "cancel"):
            raise ValueError(what)
        with self._lock:
            # a cancel is never downgraded to a pause
            if self._request != "cancel":
                self._request = what
        log.info("%s requested: stopping after the current frame", what)

    @property
    def requested(self) -> str | None:
        with self._lock:
            return self._request


class StoppedBeforeStart(Interrupted):
    """A stop asked before the run was journalled, for a `Runner` made with ``stop_before_journal``: no run
    was started or reopened, nothing was stored."""


@dataclass
class RunResult:
    """How a run ended and what it took."""

    run_id: int
    state: str  # done, paused, cancelled, failed (a one-shot run that did not finish)
    reason: str | None = None
    error: PsfdError | None = None
    steps_done: int = 0
    frames: int = 0
    psfs: int = 0
    elapsed_s: float = 0.0
    capture_s: float = 0.0
    rig_wait_s: float = 0.0
    psf_ids: list[int] = field(default_factory=list)
    rows: list[dict] | None = None  # the stored PSF rows, when `run_plan` was asked for them

    def to_dict(self) -> dict:
        """JSON-ready fields: what the service answers and the command line prints."""
        out = {
            "run_id": self.run_id, "state": self.state, "reason": self.reason,
            "exit_code": self.error.exit_code if self.error else 0,
            "steps_done": self.steps_done, "frames": self.frames, "psfs": self.psfs,
            "psf_ids": self.psf_ids, "elapsed_s": round(self.elapsed_s, 3),
        }
        if self.rows is not None:
            out["rows"] = self.rows
        return out


class Progress:
    """How far a run is, on a stream: a tqdm bar on a terminal, one plain line per step otherwise.

    On a terminal the bar fits the terminal's width (and follows it when resized) and shows the
    steps done, the elapsed and the remaining time; written to a file or a pipe (a log, CI,
    journald), each step is one line with the same counts and times, and nothing is redrawn.
    None as the stream: silent (the service reports through its status instead).
    """

    def __init__(self, run_id: int, total: int, done: int, stream: IO[str] | None) -> None:
        self.run_id, self.total, self.done, self.stream = run_id, total, done, stream
        self.tty = bool(stream and hasattr(stream, "isatty") and stream.isatty())
        self.first, self.started = done, time.monotonic()
        self.bar = None
        if self.tty:
            from tqdm import tqdm  # only a terminal needs it

            self.bar = tqdm(total=total, initial=done, desc=f"run {run_id}", unit="step", file=stream,
                            dynamic_ncols=True, leave=True, smoothing=0.1)

    def step(self, key: str, note: str = "") -> None:
        """One more step done (``key``), with an optional note."""
        self.done += 1
        if self.bar is not None:
            self.bar.update(1)
        self.show(key, note)

    def show(self, key: str, note: str = "") -> None:
        """Show the step under way (or ending) without counting it."""
        if self.stream is None:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(f"{key} {note}".strip(), refresh=True)
            return
        self.stream.write(f"run {self.run_id}: {self.done}/{self.total} steps {key} {note}".rstrip()
                          + self._times() + "\n")
        self.stream.flush()

    def _times(self) -> str:
        """``, 12 s elapsed, about 30 s left`` (the rate of this session's steps; nothing before the first)."""
        elapsed = time.monotonic() - self.started
        made = self.done - self.first
        if made <= 0:
            return ""
        left = elapsed / made * (self.total - self.done)
        return f", {_duration(elapsed)} elapsed" + (f", about {_duration(left)} left" if self.done < self.total else "")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _duration(seconds: float) -> str:
    """``42 s``, ``3 min 05 s``, ``2 h 07 min``."""
    seconds = int(round(seconds))
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


def default_workers() -> int:
    """One estimation process per core but one (at least 1, at most 4).

    The capture loop keeps a core: downloading and hashing RAW files, and on the
    simulated rig rendering them, is CPU work too. On 2 cores one worker ran
    the bench 1.8x faster than two (bench/bench_throughput.py).
    """
    return max(1, min(4, (os.cpu_count() or 2) - 1))


_STDERR = object()  # the default progress stream: sys.stderr when the Runner is made


class Estimators:
    """A run's estimation processes: a pool of spawned workers, started afresh when one of them died.

    Parameters
    ----------
    count : int
        Worker processes.
    estimate : callable
        Module-level function run in the workers, signature of `work.estimate_step`.
    kind, channels, options
        Its arguments other than the frames: `Plan.kind`, `Plan.channels`, `Plan.estimator_options`.
    """

    def __init__(self, count: int, estimate: Callable[..., list], kind: str, channels: list[str],
                 options: dict) -> None:
        self.count, self.estimate = count, estimate
        self.kind, self.channels, self.options = kind, channels, options
        self.pool = self._start()

    def _start(self) -> cf.ProcessPoolExecutor:
        ctx = multiprocessing.get_context("spawn")  # no fork of a threaded service
        _start_resource_tracker()
        pool = cf.ProcessPoolExecutor(self.count, mp_context=ctx, initializer=work.init_worker,
                                      initargs=(os.getpid(),))
        for _ in range(self.count):  # start every worker now, not on the first estimate
            pool.submit(work.warm_up)
        return pool

    def submit(self, records: list[FrameRecord]) -> cf.Future:
        """Hand the estimate of a step's frames to the workers.

        Raises
        ------
        concurrent.futures.BrokenExecutor
            A worker died since the pool was started (BrokenProcessPool): `restart` it.
        """
        return self.pool.submit(self.estimate, self.kind, [r.path for r in records], self.channels, self.options)

    def restart(self) -> None:
        """A new pool in place of a broken one (a worker that dies breaks its whole pool)."""
        self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = self._start()

    def close(self) -> None:
        """Let the workers finish and end."""
        self.pool.shutdown()


class Runner:
    """Runs plans against one catalogue and one frame store.

    Parameters
    ----------
    catalogue : psfd.catalogue.Catalogue
        Journal of runs and steps, and home of frames and PSFs.
    frames_dir : path
        Frame store (content-addressed RAW files).
    workers : int, optional
        Estimation processes (default: `default_workers`).
    control : Control, optional
        Pause/cancel requests, checked after each frame.
    progress : stream or None
        Where the progress bar goes (stderr by default, None for silence).
    on_step : callable, optional
        Called with (key, state, reason) whenever a step changes state (service status).
    estimate : callable
        Module-level function run in the workers, signature of `work.estimate_step`.
    backlog : int, optional
        Frames captured but not yet estimated before the rig waits (default 4 per
        worker). A queue deeper than the workers lets the rig keep moving while
        estimation catches up; the steps in it are journalled "running", so a
        crash only redoes them.
    stop_before_journal : bool
        What a stop asked before the run is journalled (started, or reopened to resume) does. True: the
        run ends unstarted, `StoppedBeforeStart` and nothing journalled (the command line: its plan file is
        there to run again). False (default): the run is journalled and pauses at once, so that the
        service's submitted plan stays resumable from the catalogue.
    """

    def __init__(
        self,
        catalogue: Any,
        frames_dir: str | os.PathLike,
        *,
        workers: int | None = None,
        control: Control | None = None,
        progress: IO[str] | None | object = _STDERR,
        on_step: Callable[[str, str, str | None], None] | None = None,
        estimate: Callable[..., list] = work.estimate_step,
        backlog: int | None = None,
        stop_before_journal: bool = False,
    ) -> None:
        self.catalogue = catalogue
        self.stop_before_journal = stop_before_journal
        self.frames_dir = Path(frames_dir)
        self.workers = default_workers() if workers is None else check_count(workers, "workers", WORKERS_MAX)
        self.control = control or Control()
        # sys.stderr as it is when the runner is made, not when this module was imported: a caller
        # that redirected it (a test, a service writing to a log) gets the bar where it expects
        self.progress_stream = sys.stderr if progress is _STDERR else progress
        self.on_step = on_step or (lambda key, state, reason: None)
        self.estimate = estimate
        self.backlog = 4 * self.workers if backlog is None else check_count(backlog, "backlog", BACKLOG_MAX)
        self._frame_bytes = 0  # the largest frame this run stored: the room the store needs for the next
        self.ready: CameraReady | None = None  # what `Camera.prepare` did for the current run
        self._estimators: Estimators | None = None  # the current run's workers
        self._put: set[str] = set()  # frames this runner put into the store (others were there already)

    # -- public -------------------------------------------------------------------------------

    def run(self, plan: Plan, camera: Camera, rail: Rail, resume: bool = False, new: bool = False,
            oneshot: bool = False) -> RunResult:
        """Run (or resume) a plan on an open rig; the rig is released when the run ends.

        With ``resume`` the latest unfinished (paused or interrupted) run of this
        plan (`Catalogue.unfinished_run` by `plan_key`: the same steps and settings, whatever its
        comments, layout or defaults written out) goes on with its own stored steps (pending, failed and
        interrupted). Without it a new run starts, unless the plan has an unfinished run and ``new`` is
        false: that is refused, so that no PSF is stored twice by accident.
        A ``oneshot`` run (`psfd capture`) is never left resumable: where it
        would pause it is closed as ``failed``.

        Returns
        -------
        RunResult
            ``done``, ``paused`` (a step failed or a pause/stop was asked: resumable),
            ``cancelled``, or ``failed`` (oneshot). Work committed before a failure stays committed.

        Raises
        ------
        BadInputError
            ``resume`` with no unfinished run, or an unfinished run and neither ``resume`` nor ``new``;
            a position the rail says it cannot reach or an aperture the camera does not offer (`check_rig`).
        """
        try:
            check_rig(plan, camera, rail)  # refused before the run is opened and before any motion, not at the step
            with store_lock(self.frames_dir), catalogue_lock(self.catalogue.path):
                run_id = self._open_run(plan, camera, rail, resume, new)
                try:
                    result = self._execute(plan, run_id, camera, rail)
                except BaseException:  # second Ctrl-C, or a bug: leave the run resumable, not "running"
                    with contextlib.suppress(Exception):
                        self.catalogue.finish_run(run_id, "failed" if oneshot else "paused")
                    raise
                if oneshot and result.state == "paused":
                    result.state = "failed"
                    self.catalogue.finish_run(run_id, "failed")
                # INFO: the failed step that ended a run was already a warning, with its reason
                log.info("run %d %s: %d steps, %d PSFs in %.1f s%s", run_id, result.state, result.steps_done,
                         result.psfs, result.elapsed_s, f" ({result.reason})" if result.reason else "")
                return result
        finally:
            release_rig(camera, rail)

    # -- steps --------------------------------------------------------------------------------

    def _open_run(self, plan: Plan, camera: Camera, rail: Rail, resume: bool, new: bool) -> int:
        pending = self.catalogue.pending_frames(self.frames_dir)  # another store's are swept by its own runs
        sweep_frames(self.frames_dir, self.catalogue.frame_hashes(), pending)
        self.catalogue.forget_pending(pending)
        # we hold the store lock, so a run journalled "running" here was killed: it is interrupted,
        # and done if it was killed between its last commit and its close (the one resumed here too:
        # it is reopened below and closed by _execute, so that its resume reports it done)
        unfinished = start_check(self.catalogue, plan, resume, new)
        self.catalogue.close_finished_runs()
        if unfinished is not None:
            check_same_rig(self.catalogue, unfinished, plan, camera)
            lost = position_lost(rail, self.catalogue, unfinished)
            if lost:  # refused before the run reopens: it stays resumable once the rail is put right
                raise RailError(lost)
            check_not_stopped(self.control, self.stop_before_journal)
            self.catalogue.finish_run(unfinished, "running")
            return unfinished
        check_not_stopped(self.control, self.stop_before_journal)
        rig_id = self.catalogue.add_rig(camera.info())
        steps = [(step.key, step.payload()) for step in plan.steps()]
        return self.catalogue.start_run(plan.path, plan.text, rig_id, steps)

    def _execute(self, plan: Plan, run_id: int, camera: Camera, rail: Rail) -> RunResult:
        result = RunResult(run_id, "done")
        started = time.monotonic()
        todo = self.catalogue.steps(run_id, ("pending", "running", "failed"))
        if not todo:  # killed after its last commit: only the close was missing
            self.catalogue.finish_run(run_id, "done")
            return RunResult(run_id, "done", reason="every step was already done")
        total = len(self.catalogue.steps(run_id))
        log.info("run %d of %s: %d of %d steps to do, %d worker(s)", run_id, plan.path, len(todo), total,
                 self.workers)
        bar = Progress(run_id, total, total - len(todo), self.progress_stream)
        bar.show("resuming" if bar.done else "starting")
        options = plan.estimator_options()
        focal = camera.info().focal_length_mm
        inflight: list[tuple[Step, list, cf.Future]] = []
        self._estimators = Estimators(self.workers, self.estimate, plan.kind, plan.channels, options)
        with contextlib.closing(self._estimators):
            try:
                try:
                    self._apply_settings(camera, plan.camera_settings)
                except PsfdError as exc:
                    result.error, result.reason = exc, f"camera settings: {exc}"
                    todo = []
                if result.error is None:
                    try:
                        self.ready = prepare_camera(camera, plan)
                    except PsfdError as exc:  # no RAW, autofocus on: refused before the rail moves
                        result.error, result.reason = exc, f"camera setup: {exc}"
                        todo = []
                for row in todo:
                    if self.control.requested:
                        break
                    step = Step.from_payload(row["payload"])
                    t0 = time.monotonic()
                    try:
                        if not self._set_state(run_id, step.key, "running"):
                            continue  # committed meanwhile by another process on this catalogue: never twice
                        records = self._capture(plan, step, camera, rail)
                    except (PsfdError, OSError) as exc:  # camera gone, rail alarm, disk full
                        self._fail(result, run_id, step.key, _step_error(exc))
                        break
                    result.capture_s += time.monotonic() - t0
                    self._hand_over(run_id, focal, step, records, inflight, result, bar)
                    # The rig waits only when the backlog of unestimated frames is full.
                    t0 = time.monotonic()
                    while len(inflight) > self.backlog:
                        self._commit_first(run_id, focal, inflight, result, bar)
                    result.rig_wait_s += time.monotonic() - t0
                    self._commit_ready(run_id, focal, inflight, result, bar)
                    if result.error is not None:
                        break
            finally:
                release_rig(camera, rail)
                while inflight:
                    self._commit_first(run_id, focal, inflight, result, bar)
        bar.close()
        result.elapsed_s = time.monotonic() - started
        # a stop that came after the last commit has nothing left to pause or cancel: the run is done
        finished = result.error is None and not self.catalogue.steps(run_id, ("pending", "running", "failed"))
        requested = None if finished else self.control.requested
        if requested == "cancel" or (requested and result.error is None):
            result.state, result.reason = ("cancelled" if requested == "cancel" else "paused"), f"{requested} requested"
        elif result.error is not None:
            result.state = "paused"
        try:
            self.catalogue.finish_run(run_id, result.state)
        except StorageError as exc:  # the journal keeps "running": the run shows as interrupted, resumable
            if result.error is None:
                result.state, result.error, result.reason = "paused", exc, f"closing the run: {exc}"
        return result

    def _set_state(self, run_id: int, key: str, state: str, reason: str | None = None) -> bool:
        """False, and nothing changed, when the step is done (`Catalogue.set_step_state`)."""
        if not self.catalogue.set_step_state(run_id, key, state, reason):
            return False
        self.on_step(key, state, reason)
        return True

    def _fail(self, result: RunResult, run_id: int, key: str, exc: PsfdError) -> None:
        log.warning("run %d step %s failed: %s", run_id, key, exc)
        if result.error is None:
            result.error, result.reason = exc, f"step {key}: {exc}"
        try:
            self._set_state(run_id, key, "failed", str(exc))
        except StorageError:  # a full disk refuses this too: the step stays "running", redone on resume
            pass

    @staticmethod
    def _apply_settings(camera: Camera, settings: dict[str, str]) -> None:
        for name, value in settings.items():
            camera.set(name, value)

    def _capture(self, plan: Plan, step: Step, camera: Camera, rail: Rail) -> list[FrameRecord]:
        """Move, set the aperture, expose; returns the FrameRecords of the stored RAW files."""
        camera.set("aperture", _aperture_choice(camera, step.aperture))
        distances = step.x if isinstance(step.x, tuple) else (step.x,)
        settings = {"aperture": step.aperture, **plan.camera_settings}
        records: list[FrameRecord] = []
        try:
            for x in distances:
                at = rail.move(x=x, y=step.y, z=step.z)
                settle(self.ready.settle_s, since=time.monotonic())  # the rig's vibrations die out
                path, sha = self._expose(camera)
                records.append(FrameRecord(
                    path=str(path), sha256=sha, settings=settings, rail={"x": at.x, "y": at.y, "z": at.z},
                    taken_at=datetime.now(timezone.utc).isoformat(timespec="seconds"),
                ))  # listed first, so that a frame refused for its settings is discarded with the step
                records[-1].exif = frame_exif(path, settings, plan.rig.get("focal_mm"), step.key)
        except BaseException:
            self._discard(records)  # the near frame of a pair whose far frame failed
            raise
        return records

    def _expose(self, camera: Camera) -> tuple[Path, str]:
        """One exposure downloaded into a temporary folder of the store, its RAW file stored by hash.

        The store must have room for a frame as large as the largest of this run before the camera
        writes (`check_room`); a download that fails on a file system that is full or read-only
        afterwards is the storage's failure, whatever error the camera driver made of it.
        """
        check_room(self.frames_dir, self._frame_bytes)
        incoming = Path(tempfile.mkdtemp(prefix=INCOMING, dir=self.frames_dir))
        try:
            try:
                files = [p for p in camera.capture(incoming) if p.suffix.lower() in RAW_SUFFIXES]
                if not files:
                    raise CameraError("the camera produced no RAW file: set imageformat to RAW")
                path, sha = store_frame(files[0], self.frames_dir, self._journal)
            except (PsfdError, OSError):
                check_room(self.frames_dir, max(self._frame_bytes, FRAME_BYTES_MIN))
                raise
            self._frame_bytes = max(self._frame_bytes, path.stat().st_size)
            return path, sha
        finally:
            shutil.rmtree(incoming, ignore_errors=True)

    def _journal(self, sha: str) -> None:
        """`store_frame`'s journal: the frame is this catalogue's to remove until its step commits."""
        self.catalogue.pend_frame(sha, self.frames_dir)
        self._put.add(sha)

    def _discard(self, records: list) -> None:
        """Remove the frames of a failed step (the retry shoots new ones) that this runner put into the store
        and no step holds: a file that was there already (the same bytes: a replayed recording, the simulated
        rig) is another catalogue's frame in a shared store."""
        known = self.catalogue.frame_hashes()
        for record in records:
            if record.sha256 in self._put and record.sha256 not in known:
                Path(record.path).unlink(missing_ok=True)
            self._put.discard(record.sha256)
        self.catalogue.forget_pending(record.sha256 for record in records)

    def _hand_over(self, run_id: int, focal: float | None, step: Step, records: list, inflight: list,
                   result: RunResult, bar: Progress) -> None:
        """Give a step's estimate to the workers; a pool that broke since the last one first settles the
        steps it held (`_commit_first` fails the one a dead worker ran and restarts it)."""
        while True:
            try:
                inflight.append((step, records, self._estimators.submit(records)))
                return
            except cf.BrokenExecutor:  # BrokenProcessPool
                if not inflight:  # a worker died idle: no estimate went with it
                    self._estimators.restart()
                else:  # commits what was estimated before the break, then restarts the pool (`_commit_first`)
                    self._commit_first(run_id, focal, inflight, result, bar)

    def _commit_ready(self, run_id, focal, inflight, result, bar) -> None:
        while inflight and inflight[0][2].done():
            self._commit_first(run_id, focal, inflight, result, bar)

    def _commit_first(self, run_id: int, focal: float | None, inflight: list, result: RunResult,
                      bar: Progress) -> None:
        """Wait for the oldest estimate and commit its step (steps commit in capture order)."""
        step, records, future = inflight.pop(0)
        try:
            estimates = future.result()
        except cf.BrokenExecutor:  # BrokenProcessPool
            # A worker died (SIGKILL, the OOM killer) and its pool failed every estimate in it. The oldest
            # is the one a worker was running (exactly so with one worker): its step fails; the others
            # are redone in a new pool, their frames are stored.
            error = EstimationError("the estimation process ended abruptly (killed, or out of memory?)")
            self._estimators.restart()
            inflight[:] = [(s, r, self._estimators.submit(r)) for s, r, _ in inflight]
            self._fail_step(result, run_id, step, records, bar, error)
            return
        except Exception as exc:  # noqa: BLE001 - any failure of one step pauses the run, it never aborts it
            error = exc if isinstance(exc, PsfdError) else EstimationError(
                f"estimation failed ({type(exc).__name__}: {exc})")
            self._fail_step(result, run_id, step, records, bar, error)
            return
        exif = records[-1].exif or {}  # a pair's PSF is the far frame's (its focus and focal length)
        meta = {
            "aperture": step.aperture,
            "focal_length_mm": exif.get("focal_length_mm") or focal,
            "focus_distance_m": exif.get("focus_distance_m"),  # what the lens reports, else unknown
            "frame_indices": list(range(len(records))),
        }
        try:
            ids = self.catalogue.commit_step(run_id, step.key, records, [(psf, dict(meta)) for psf in estimates])
        except StorageError as exc:  # rolled back whole: the step is redone on resume, its frames are not kept
            self._fail_step(result, run_id, step, records, bar, exc)
            return
        self.on_step(step.key, "done", None)
        result.steps_done += 1
        result.frames += len(records)
        result.psfs += len(ids)
        result.psf_ids += list(ids)
        bar.step(step.key)

    def _fail_step(self, result: RunResult, run_id: int, step: Step, records: list, bar: Progress,
                   error: PsfdError) -> None:
        """Fail a captured step that was not committed; its frames go (the retry shoots new ones)."""
        self._fail(result, run_id, step.key, error)
        self._discard(records)
        bar.show(step.key, f"failed: {error}")


def _start_resource_tracker() -> None:
    """Start multiprocessing's resource tracker (the spawned pool's semaphores are registered with it) with
    SIGHUP blocked, as Python starts it with SIGINT and SIGTERM blocked: it is in the terminal's process
    group, and a hang-up killed it, so that the next semaphore started a new tracker, which logged a
    traceback for each semaphore released after. The tracker unblocks only its own two signals."""
    blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGHUP})
    try:
        resource_tracker.ensure_running()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, blocked)


def leave_terminal() -> None:
    """After a hang-up (an ssh session dropped, a terminal closed): point standard output and error at /dev/null
    where they were the terminal, or a pipe whose reader went with it. Every write there fails (EIO, EPIPE),
    and a run must still pause cleanly and a service remove its socket; a log file or the journal (a regular
    file or a socket) keeps the lines that follow. The run's own record, and `psfd status`, say how it ended."""
    null = os.open(os.devnull, os.O_WRONLY)
    for fd in (1, 2):
        with contextlib.suppress(OSError):
            mode = os.fstat(fd).st_mode  # a hung-up terminal no longer says it is one (isatty: EIO)
            if not (stat.S_ISREG(mode) or stat.S_ISSOCK(mode)):
                os.dup2(null, fd)
    os.close(null)


def check_not_stopped(control: Control | None, stop_before_journal: bool) -> None:
    """Raise `StoppedBeforeStart` when ``stop_before_journal`` and a stop was asked (`Runner`'s parameter)."""
    if stop_before_journal and control is not None and control.requested:
        raise StoppedBeforeStart(f"{control.requested} requested before the run started")


def _step_error(exc: PsfdError | OSError) -> PsfdError:
    """A step's failure as a typed error: an OSError is storage (disk full, read-only) or, else, the rig's."""
    if isinstance(exc, PsfdError):
        return exc
    return storage_error(exc, "storing the frame") or HardwareError(f"storing the frame: {exc}")


# mm: a restarted controller reads its power-up position exactly; GRBL reports three decimals
_SAME_MM = 1e-3


def position_lost(rail: Rail, catalogue: Catalogue, run_id: int) -> str | None:
    """Why the rail cannot resume run ``run_id`` where the run left it, or None.

    A controller that restarted while the run was stopped (a USB cable pulled and put back, a power cut)
    counts its position again from wherever the carriage stands: GRBL from machine position 0 (grbl
    main.c), locked in alarm until homed only when homing is enabled. Its reports look like any others,
    so the restart shows only in where the rail reads: at its power-up position (`RailInfo.power_up`)
    although the run cannot have left it there, outside the span from its latest stored frame to the
    targets of its interrupted steps (a move cut short stops in between). Resuming would shoot every
    step left at the wrong place, or drive the carriage into an end stop. None when the rail cannot say
    or the run has no stored frame yet.
    """
    left = catalogue.steps(run_id, ("pending", "running", "failed"))
    last = catalogue.last_rail_position(run_id)
    if not left or not last:
        return None
    try:
        info, at = rail.info(), rail.position()
    except PsfdError as exc:
        log.debug("rail not asked where it restarts: %s", exc)
        return None
    start = {axis: v for axis, v in (info.power_up or {}).items() if last.get(axis) is not None}
    if not start or any(getattr(at, axis) is None or abs(getattr(at, axis) - v) > _SAME_MM
                        for axis, v in start.items()):
        return None
    spans = {axis: [float(last[axis])] for axis in start}
    for row in left:
        if row["state"] != "pending":  # interrupted or failed: the carriage may be on its way there
            step = Step.from_payload(row["payload"])
            for axis, value in (("x", step.x), ("y", step.y), ("z", step.z)):
                for v in value if isinstance(value, tuple) else (value,):
                    if v is not None and axis in spans:
                        spans[axis].append(float(v))
    if all(min(s) - _SAME_MM <= start[axis] <= max(s) + _SAME_MM for axis, s in spans.items()):
        return None
    reads = ", ".join(f"{axis.upper()}={getattr(at, axis):g}" for axis in start)
    left_at = ", ".join(f"{axis.upper()}={min(s):g}" + (f" to {max(s):g}" if max(s) > min(s) else "")
                        for axis, s in spans.items())
    back = " ".join(f"{axis.upper()}={last[axis]:g}" for axis in start)
    fix = ("home it (`psfd rail home`) and resume" if info.homing else
           f"move the carriage by hand to the + end, power-cycle the controller, `psfd rail move {back}` and resume")
    return (f"the rail reads {reads} mm, where its controller starts after power-up, but run {run_id} left it at "
            f"{left_at} mm: the controller restarted (USB cable or power) and its position is lost; {fix}")


def check_rig(plan: Plan, camera: Camera, rail: Rail) -> None:
    """Refuse a plan the open rig says it cannot do: positions off the rail, apertures the camera lacks,
    captures its recording does not hold.

    Raises
    ------
    BadInputError
        The problems of `rail_problems`, `camera_problems` and `recording_problems`, on one line.
    """
    problems = rail_problems(plan, rail) + camera_problems(plan, camera) + recording_problems(plan)
    if problems:
        raise BadInputError(f"{plan.path}: {'; '.join(problems)}")


def rail_problems(plan: Plan, rail: Rail) -> list[str]:
    """Positions of the plan that the rail says it cannot reach (`plan.check_rail`); none when it cannot say.

    A rail that does not answer ``info`` (an older recording) is left to refuse each move itself.
    """
    try:
        info = rail.info()
    except PsfdError as exc:
        log.debug("rail not asked for its travel: %s", exc)
        return []
    return check_rail(plan, info)


def camera_problems(plan: Plan, camera: Camera) -> list[str]:
    """The plan's apertures and camera settings that the camera does not offer (`aperture_problems`,
    `setting_problems`)."""
    return aperture_problems(plan, camera) + setting_problems(plan, camera)


def setting_problems(plan: Plan, camera: Camera) -> list[str]:
    """The plan's camera settings whose value no choice of the camera matches, one problem each.

    Asked before the run opens, as `aperture_problems`: the settings are applied as the run starts, and a
    corrected plan is another plan, so the run refused then could never go on. A setting the camera cannot
    list (free-form, unknown to it, a recording that never asked) is left to refuse itself when applied.
    """
    problems = []
    for name, text in plan.camera_settings.items():
        try:
            choices = camera.choices(name)
        except PsfdError as exc:
            log.debug("camera not asked for its %s choices: %s", name, exc)
            continue
        if choices and offered_choice(text, choices) is None:
            problems.append(f"camera setting {name} {text} is not offered by the camera (offered: {', '.join(choices)})")
    return problems


def aperture_problems(plan: Plan, camera: Camera) -> list[str]:
    """The plan's apertures that the camera does not offer, as one problem naming the offered ones.

    Asked before the run opens: otherwise the run would pause at the first such step (overnight, perhaps)
    and no resume could finish it. A camera that cannot list its apertures (an error, a recording that never
    asked, a free-form setting) is left to refuse each step itself, as `_aperture_choice` does.
    """
    try:
        choices = camera.choices("aperture")
    except PsfdError as exc:
        log.debug("camera not asked for its apertures: %s", exc)
        return []
    missing = [a for a in plan.apertures if offered_choice(str(a), choices) is None]
    if not choices or not missing:
        return []
    named = ", ".join(f"f/{a:g}" for a in missing)
    verb = "are" if len(missing) > 1 else "is"
    return [f"aperture{'s' * (len(missing) > 1)} {named} {verb} not offered by the camera "
            f"(offered: {', '.join(choices)})"]


def prepare_camera(camera: Camera, plan: Plan) -> CameraReady:
    """Set the camera up for PSF work as the plan's ``[rig.camera]`` table asks (`CameraSetup`), before any motion."""
    return camera.prepare(CameraSetup.from_mapping(plan.rig.get("camera", {})))


def frame_exif(path: Path, settings: dict, focal_mm: float | None, key: str) -> dict:
    """What the RAW at ``path`` says the camera did; a setting other than the one asked fails the step.

    Raises
    ------
    SettingsMismatch
        The f-number, exposure time, ISO or focal length (the plan's ``focal_mm``) differs (`check_settings`).
    """
    meta = read_metadata(path)
    check_settings(meta, aperture=settings.get("aperture"), shutterspeed=settings.get("shutterspeed"),
                   iso=settings.get("iso"), focal_length_mm=focal_mm, frame=f"step {key}")
    return meta.as_dict()


def start_check(catalogue: Catalogue, plan: Plan, resume: bool, new: bool,
                frames_dir: str | os.PathLike | None = None) -> int | None:
    """The run to resume (None: start a new one), or why this plan may not start.

    ``frames_dir``: the frame store, to tell a live run from an interrupted one
    (None: the caller holds the store, so a ``running`` run is interrupted).

    Raises
    ------
    BadInputError
        ``resume`` and the plan has no unfinished run (`Catalogue.unfinished_run` by `plan_key`: none
        of the same plan), saying what changed when one was started from this file; or it has one
        and neither ``resume`` nor ``new`` was asked.
    """
    unfinished = catalogue.unfinished_run(plan.text, plan_key)
    if resume:
        if unfinished is None:
            raise BadInputError(f"no unfinished run of plan {plan.path} to resume"
                                + _changed_since(catalogue, plan, frames_dir))
        return unfinished
    if unfinished is not None and not new:
        summary = catalogue.run_summary(unfinished)
        progress = _progress(summary, frames_dir, catalogue.path)
        # a run another process is shooting: --resume and --new would both meet its frame store in use
        advice = ("in another psfd process: follow it with `psfd status`, or stop it (Ctrl-C or SIGTERM there "
                  "pauses it) and add --resume" if progress.startswith("running") else
                  "add --resume to continue it, or --new to start a fresh run")
        raise BadInputError(f"run {unfinished} of plan {plan.path} is {progress}: {advice}"
                            + _reworded(catalogue.run(unfinished), plan))
    return None


def check_same_rig(catalogue: Catalogue, run_id: int, plan: Plan, camera: Camera) -> None:
    """Refuse to resume a run with another camera body or lens than it began with: the catalogue files a run's
    PSFs under the rig it began with (a camera swapped while the run was paused would be misfiled)."""
    began = catalogue.run_rig(run_id)
    info = camera.info()
    now = {"model": info.model, "serial": info.serial or "", "lens": info.lens or ""}
    if now != began:
        raise BadInputError(f"run {run_id} of plan {plan.path} began with {_rig_name(began)}, the camera now is "
                            f"{_rig_name(now)}: put that camera and lens back to resume it, or run the plan with "
                            "--new instead of --resume to start afresh")


def _rig_name(rig: dict) -> str:
    serial = f" (serial {rig['serial']})" if rig["serial"] else ""
    return f"{rig['model']}{serial} with {rig['lens'] or 'an unnamed lens'}"


def _progress(summary: dict, frames_dir: str | os.PathLike | None, catalogue_path: Path) -> str:
    """``interrupted (3/6 steps done)``: a run's state as a user reads it (`start_check`'s ``frames_dir``)."""
    state = summary["state"]
    state = (shown_state(state, frames_dir, catalogue_path) if frames_dir is not None
             else state.replace("running", "interrupted"))
    return f"{state} ({summary['done']}/{summary['total']} steps done)"


def _reworded(run: dict, plan: Plan) -> str:
    """Why a run is of this plan although the file was moved or edited since: a plan is what it does (`plan_key`)."""
    notes = []
    if not _same_file(run["plan_path"], plan.path):
        notes.append(f"started from {run['plan_path']}")
    if run["plan_text"] != plan.text:
        notes.append("the same plan: the texts differ in comments, layout or defaults written out, "
                     "or the rig's link, only")
    return f" ({'; '.join(notes)})" if notes else ""


def _changed_since(catalogue: Catalogue, plan: Plan, frames_dir: str | os.PathLike | None) -> str:
    """Why ``--resume`` finds no run of a plan file that has one: what the plan changed since (`plan_changes`).

    Empty when no unfinished run was started from this file.
    """
    for run in catalogue.runs():  # newest first
        if run["state"] in UNFINISHED_STATES and _same_file(run["plan_path"], plan.path):
            changes = plan_changes(catalogue.run(run["id"])["plan_text"], plan.text)
            if changes:
                progress = _progress(catalogue.run_summary(run["id"]), frames_dir, catalogue.path)
                return (f": run {run['id']} of it is {progress}, but the plan changed since ({'; '.join(changes)}); "
                        "put its values back to resume it, or run it with --new instead of --resume to start "
                        "afresh")
    return ""


def _same_file(stored: str | None, path: str) -> bool:
    """Whether a run's stored plan path names the plan file ``path`` (either relative to the current folder)."""
    return stored is not None and os.path.abspath(stored) == os.path.abspath(path)


def preflight(plan: Plan, catalogue_path: str | os.PathLike, frames_dir: str | os.PathLike, resume: bool,
              new: bool) -> None:
    """Refuse what the run would refuse, reading only, before anything is created or changed.

    The catalogue (when it exists) is opened read-only: one this psfd cannot use (a newer
    schema, not a catalogue) is refused untouched, and so is a plan `start_check` refuses;
    a catalogue or frame store of another user is refused (`check_owner`), and so is a
    path where a file stands in place of a folder; ``resume`` without a catalogue has
    nothing to resume.
    """
    catalogue_path, frames_dir = Path(catalogue_path), Path(frames_dir)
    _check_folder(catalogue_path.parent, "the catalogue's folder")
    _check_folder(frames_dir, "the frame store")
    check_catalogue_free(catalogue_path)
    if catalogue_exists(catalogue_path):  # an empty file a killed run left is made a catalogue by this one
        with Catalogue(catalogue_path, readonly=True) as catalogue:
            check_owner(catalogue_path, "the catalogue")
            start_check(catalogue, plan, resume, new, frames_dir)
    elif resume:
        raise BadInputError(f"no unfinished run of plan {plan.path} to resume (no catalogue at {catalogue_path})")
    check_owner(frames_dir, "the frame store")


def _check_folder(folder: Path, what: str) -> None:
    """Refuse a folder that cannot exist because a file stands where it, or one of its parents, should be."""
    for part in (folder, *folder.parents):
        if part.exists():
            if not part.is_dir():
                raise BadInputError(f"cannot use {folder} as {what}: {part} is a file, not a folder")
            return


def unfinished_runs(catalogue_path: str | os.PathLike, frames_dir: str | os.PathLike) -> list[dict]:
    """The catalogue's runs that are not closed, newest first, as `Catalogue.run_summary` with their state
    as a user reads it (`shown_state`: ``running``, ``paused`` or ``interrupted``); none without a catalogue."""
    if not catalogue_exists(catalogue_path):
        return []
    with Catalogue(catalogue_path, readonly=True) as catalogue:
        runs = [catalogue.run_summary(r["id"]) for r in catalogue.runs() if r["state"] in UNFINISHED_STATES]
    for run in runs:
        run["state"] = shown_state(run["state"], frames_dir, catalogue_path)
    return runs


def run_plan(
    plan: Plan,
    catalogue_path: str | os.PathLike,
    frames_dir: str | os.PathLike,
    *,
    resume: bool = False,
    new: bool = False,
    oneshot: bool = False,
    rows: bool = False,
    **runner_options: Any,
) -> RunResult:
    """Run a plan on the rig its ``[rig]`` table names, into a catalogue and a frame store.

    The one way to run a plan: `preflight`, open the rig and `check_rig`, then take
    the catalogue (`catalogue_lock`: no other process writes it) and the frame store
    (a path that cannot be one is refused before a catalogue is created), open the
    catalogue (created when missing), `Runner.run` (``resume``,
    ``new`` and ``oneshot`` as there), and with ``rows`` put the stored PSF rows
    (metadata, no arrays) into the result. ``runner_options`` go to `Runner`
    (``workers``, ``backlog``, ``control``, ``progress``, ``on_step``).

    A rig that cannot be opened, or refuses the plan, leaves no catalogue, catalogue
    folder or frame store behind: none is made before the rig has answered, and so
    does a stop asked meanwhile with ``stop_before_journal`` (`Runner`). A new catalogue
    that the run leaves without a run journalled (stopped, a full disk, a camera gone
    before the run started) is removed with what was made for it. The rig is
    released on every path.
    """
    preflight(plan, catalogue_path, frames_dir, resume, new)
    camera, rail = open_rig(plan.rig_config())
    try:
        check_rig(plan, camera, rail)  # Runner.run asks again for its other callers: two queries, no motion
        check_not_stopped(runner_options.get("control"), runner_options.get("stop_before_journal", False))
        made = [] if catalogue_exists(catalogue_path) else _absent(Path(catalogue_path), Path(frames_dir))
        with catalogue_lock(catalogue_path):
            try:
                with store_lock(Path(frames_dir)), Catalogue(catalogue_path) as catalogue:
                    result = Runner(catalogue, frames_dir, **runner_options).run(plan, camera, rail, resume=resume,
                                                                                 new=new, oneshot=oneshot)
                    if rows:
                        result.rows = [catalogue.psf(i)[1] for i in result.psf_ids]
            except BaseException:
                if made:  # a stop or a refusal before the run was journalled: the new catalogue holds nothing
                    _discard_new(Path(catalogue_path), Path(frames_dir), made)
                raise
    finally:
        release_rig(camera, rail)  # Runner.run released it already, unless the store or catalogue refused
    return result


def _absent(catalogue_path: Path, frames_dir: Path) -> list[Path]:
    """What a run makes for a new catalogue: the catalogue file, the frame store and the folders of either
    that do not exist yet, the deepest first."""
    paths = [catalogue_path]
    for folder in (frames_dir, catalogue_path.parent):
        for part in (folder, *folder.parents):
            if part.exists():
                break
            paths.append(part)
    return sorted(set(paths), key=lambda p: len(Path(os.path.abspath(p)).parts), reverse=True)


def _discard_new(catalogue_path: Path, frames_dir: Path, made: list[Path]) -> None:
    """Remove a new catalogue that holds no run, its lock, and the frame store and folders made for it
    (`_absent`): a run stopped or refused before it journalled anything leaves nothing behind."""
    if not discard_unused(catalogue_path):
        return
    catalogue_lock_path(catalogue_path).unlink(missing_ok=True)
    if frames_dir in made:
        (frames_dir / ".lock").unlink(missing_ok=True)
    for folder in (path for path in made if path != catalogue_path):  # the deepest first
        with contextlib.suppress(OSError):  # a folder that is not empty keeps what is in it
            folder.rmdir()


def _aperture_choice(camera: Camera, aperture: float) -> str:
    """The camera's own spelling of an f-number (``5.6``, ``f/5.6``, ``F5.6``...)."""
    try:
        choices = camera.choices("aperture")
    except CameraError:
        choices = []
    choice = offered_choice(str(aperture), choices)
    if choice is not None:
        return choice
    offered = ", ".join(choices)
    if choices:
        raise CameraError(f"aperture f/{aperture:g} is not offered by the camera (offered: {offered})")
    return f"{aperture:g}"


def release_rig(camera: Camera, rail: Rail) -> None:
    """Make the rig safe: motion has stopped when a move returns, so release both devices.

    Releasing the ports leaves the rail where it stopped (an alarm is never
    driven through) and frees the camera for a person to inspect.
    """
    for device in (camera, rail):
        try:
            device.close()
        except Exception:  # noqa: BLE001 - a device already gone must not hide the run's own error
            pass
