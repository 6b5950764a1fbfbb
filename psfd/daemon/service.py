"""`psfd serve`: the long-running service, its control socket and its systemd handshake.

Control socket: a Unix stream socket (mode 0660, no network listener) that
speaks JSON lines. Each request is one JSON object on one line and gets one
JSON object back::

    {"cmd": "submit", "plan": "<TOML text>", "path": "plan.toml", "resume": false, "new": false}
    {"cmd": "status"}
    {"cmd": "pause"}            # stop after the current frame; the run stays resumable, the queue waits
    {"cmd": "resume"}           # resume the catalogue's newest paused or interrupted run, then the queue
    {"cmd": "cancel"}           # stop after the current frame and close the run as cancelled; with no run
                                # in progress, close the newest paused run as cancelled; the queue goes on
    {"cmd": "cancel", "queued": true}  # drop the plans queued and not started; the run in progress goes on
    {"cmd": "submit", ..., "wait": true}   # answer only when the job has ended (used by `psfd capture`)
    {"cmd": "submit", ..., "oneshot": true}  # never left resumable: closed as failed where it would pause

`psfd.daemon.client` is the other end (any command can use it without loading
this module). ``resume`` and ``new`` mean what they mean to `Runner.run`; a submit that the
catalogue refuses (nothing to resume, or an unfinished run without ``new``)
is answered with the error at once instead of queued.

The ``resume`` request reads what to continue from the catalogue, not from the service's memory,
so that it works after a restart (`systemctl stop` pauses the run, `systemctl start` brings
a service that never saw it): the newest paused or interrupted run (`runner.unfinished_runs`,
never one another process is shooting), with the plan text stored with it. Its answer names the
run (``run_id``, ``plan``) and, when other runs are unfinished, says so in ``note``. ``status``
says ``paused`` whenever no job runs and ``resume`` has such a run, ``paused_plan`` its plan.

A ``pause`` holds the queue (``held`` in ``status``, ``held_by`` ``"pause"``): the operator who asked for it
may be at the rig, and the next plan would move the rail at once. The queue goes on with the next
``resume``, whose run is continued first, the next submit (the operator is back), or a ``cancel``, which
closes the paused run as cancelled when the operator gives it up; a run that pauses on its own (a failed
step) or is cancelled while it runs does not hold it.

The plans queued and not started are kept beside the catalogue (`store.queue_path`, written before a submit is
answered and again when the runner takes one), so that a service stopped or killed with plans queued (an
overnight list, `systemctl restart`, a power cut) queues them again when it starts: held (``held_by``
``"restart"``) until a ``resume``, which continues the run the stop paused or the kill interrupted first,
a submit or a ``cancel``, as after a pause: nothing moves the rail before an operator says so; a
``cancel`` with ``queued`` drops them (and any other queued plan). A plan taken by the runner is no
longer kept, so it is never measured twice (one the catalogue refuses by then fails when taken, as a
submit would, and says why). A ``capture`` (its client waits) and a one-shot job are not kept: their
client is answered "not started".

Answers carry ``"ok": true`` or ``"ok": false`` with ``"error"``, ``"error_type"`` and
``"exit_code"`` (the `psfd.errors` type, so the client raises the same error and the
command exits with the same code as a local run) and ``"problems"`` for a bad plan. A
bad request never stops the service, and every request gets an answer: lines longer
than `REQUEST_BYTES_MAX` or nested deeper than `REQUEST_DEPTH_MAX` are refused before
they are parsed. The listen queue is the system's largest (SOMAXCONN), and the client
retries a full one briefly, so a burst of clients all get answers.

The service's socket folder must belong to the service's user and not be writable by
everyone: anyone who can write the folder could put their own socket in its place.
From before it binds its socket until it has ended, the service holds an exclusive
flock on ``control.sock.lock`` beside it (`client.lock_path`, mode 0640, never removed:
a lock file removed and made again could be held by two services). The kernel releases
it however the process ends, so a socket that refuses connections while its lock is
free is one a killed service left (SIGKILL, out of memory, power lost): clients then
go on without the service, and a service started again replaces it. A second service
on the same socket is refused while the first holds the lock, starting as well as
listening.

systemd: READY=1, STATUS=... and WATCHDOG=1 datagrams go to $NOTIFY_SOCKET
through the standard library's socket module (the protocol is one datagram of
``KEY=value`` lines, so no extra dependency is worth it). SIGTERM lets the
current frame finish, commits the estimates under way, pauses the run and exits 0; so does a hang-up
(SIGHUP, unless ignored: ``nohup``), after which output to the terminal goes to /dev/null.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import queue
import re
import signal
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from psfd.catalogue import Catalogue
from psfd.daemon.client import MAX_REQUEST, lock_path
from psfd.daemon.plan import Plan, check_text, parse_plan, plan_key
from psfd.daemon.runner import Control, leave_terminal, preflight, run_plan, unfinished_runs
from psfd.daemon.store import catalogue_lock, kept_queue, queue_path, write_durably
from psfd.errors import BadInputError, PsfdError, ServiceError, path_reason, user_name
from psfd.vocabulary import REQUEST_DEPTH_MAX

SOCKET_MODE = 0o660
LOCK_MODE = 0o640  # the socket's group reads it, to ask whether the service is still there
LOCK_PATIENCE = 2.0  # seconds a lock held by clients asking about a refused socket (a moment each) is waited for
log = logging.getLogger(__name__)


def notify(message: str) -> bool:
    """Send one sd_notify datagram (``READY=1``, ``STATUS=...``, ``WATCHDOG=1``); False outside systemd."""
    address = os.environ.get("NOTIFY_SOCKET")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]  # abstract namespace
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.setblocking(False)  # a receiver that stopped reading must never stall the service
            sock.sendto(message.encode(), address)
        return True
    except OSError:
        return False


def watchdog_interval() -> float | None:
    """Half the watchdog period systemd asked for (seconds), or None when there is none for us."""
    usec = os.environ.get("WATCHDOG_USEC")
    pid = os.environ.get("WATCHDOG_PID")
    if not usec or (pid and pid != str(os.getpid())):
        return None
    return int(usec) / 2e6


# -- service -------------------------------------------------------------------------------------


@dataclass
class Job:
    plan: Plan
    resume: bool = False
    wait: bool = False  # somebody waits for the answer: add the PSF rows to it
    new: bool = False
    oneshot: bool = False
    first: bool = False  # ahead of the queue: the resume that ends a pause's hold
    taken: bool = False  # by the runner: its run is the catalogue's from now on, no longer the kept queue's
    dropped: bool = False  # by a `cancel` of the queue before the runner took it: answered, to be skipped
    done: threading.Event = field(default_factory=threading.Event)
    result: dict | None = None

    @property
    def kept(self) -> bool:
        """Kept for a service started again until taken (`Service._save_queue`): nobody waits for it."""
        return not (self.wait or self.oneshot)


class JobQueue(queue.Queue):
    """First in, first out, except a `Job` marked ``first``: it goes ahead of the others."""

    def _put(self, item: Job | None) -> None:
        if item is not None and item.first:
            self.queue.appendleft(item)
        else:
            self.queue.append(item)


class Service:
    """The service: one control socket, one job queue, one runner thread.

    Parameters
    ----------
    catalogue_path, frames_dir : path
        Catalogue file and frame store every run writes to.
    socket_path : path
        Control socket to create.
    runner_options : dict, optional
        ``workers`` and ``backlog`` for each run's `Runner` (absent: its defaults).
    """

    def __init__(self, catalogue_path: str | os.PathLike, frames_dir: str | os.PathLike,
                 socket_path: str | os.PathLike, runner_options: dict[str, int] | None = None) -> None:
        # absolute: clients in other folders read these paths from `status`
        self.catalogue_path = Path(os.path.abspath(catalogue_path))
        self.frames_dir = Path(os.path.abspath(frames_dir))
        self.socket_path = Path(socket_path)
        self.runner_options = runner_options or {}
        self.jobs: JobQueue = JobQueue()
        self.control = Control()
        self.stopping = threading.Event()
        self.lock = threading.Lock()
        self.current: dict[str, Any] | None = None
        self.last: dict[str, Any] | None = None
        self.queued = 0
        self.held = False  # a pause holds the queue until a resume or a submit
        self.held_by: str | None = None  # "pause", or "restart": a queue kept by the service before this one
        self.queue_file = queue_path(self.catalogue_path)
        self.released = threading.Event()
        self.released.set()
        self.waiting: list[Job] = []  # submitted, not ended: another plain submit of one of their plans is refused
        self.lock_fd: int | None = None  # the service's lock (`hold_lock`), held while it runs

    # -- lifecycle ---------------------------------------------------------------------------

    def serve(self) -> int:
        """Listen until SIGTERM/SIGINT; returns the exit status."""
        listener = self._listen()
        try:
            self._open_catalogue()
        except BaseException:
            listener.close()
            self.socket_path.unlink(missing_ok=True)
            self._release()
            raise
        self._restore_queue()
        signal.signal(signal.SIGTERM, self._on_signal)
        signal.signal(signal.SIGINT, self._on_signal)
        if signal.getsignal(signal.SIGHUP) == signal.SIG_DFL:  # not under nohup, which asked to ignore it
            signal.signal(signal.SIGHUP, self._on_signal)
        runner = threading.Thread(target=self._run_jobs, name="runner")
        runner.start()
        interval = watchdog_interval()
        listener.settimeout(min(1.0, interval) if interval else 1.0)
        log.info("psfd service listening on %s: catalogue %s, frames %s", self.socket_path, self.catalogue_path,
                 self.frames_dir)
        notify(f"READY=1\nSTATUS=idle, listening on {self.socket_path}\nMAINPID={os.getpid()}")
        next_ping = 0.0
        try:
            while not self.stopping.is_set():
                if interval and time.monotonic() >= next_ping:
                    notify("WATCHDOG=1")
                    next_ping = time.monotonic() + interval
                try:
                    conn, _ = listener.accept()
                except TimeoutError:
                    continue
                except InterruptedError:
                    continue
                threading.Thread(target=self._serve_client, args=(conn,), daemon=True).start()
        finally:
            notify("STOPPING=1\nSTATUS=stopping: finishing the current frame")
            with self.lock:
                kept = self._kept()
            if kept:
                log.info("%d queued plans not started (%s): queued again when the service starts", len(kept),
                         ", ".join(job.plan.path for job in kept))
            self.released.set()  # the jobs a pause held are answered "not started"
            listener.close()
            self.socket_path.unlink(missing_ok=True)
            self.control.request("pause")
            self.jobs.put(None)
            while runner.is_alive():
                runner.join(timeout=interval or 1.0)
                if interval:
                    notify("WATCHDOG=1")
            log.info("psfd service stopped")
            self._release()  # after the socket is gone and the run paused: the service has ended
        return 0

    def _release(self) -> None:
        if self.lock_fd is not None:
            os.close(self.lock_fd)
            self.lock_fd = None

    def _open_catalogue(self) -> None:
        """Create or migrate the catalogue now, as the service's user: readers then find it at the current
        schema, with the files SQLite needs to read it without write access (`psfd.catalogue`)."""
        Catalogue(self.catalogue_path).close()

    def _listen(self) -> socket.socket:
        path = self.socket_path
        try:
            path.parent.mkdir(parents=True, exist_ok=True, mode=0o750)
        except OSError as exc:
            reason = path_reason(path.parent, exc)
            raise ServiceError(f"cannot create the socket folder {path.parent}: {reason}") from None
        _check_socket_folder(path.parent)
        self.lock_fd = hold_lock(path)
        try:
            return self._bind(path)
        except BaseException:
            self._release()
            raise

    def _bind(self, path: Path) -> socket.socket:
        """The listening socket at ``path``; under the service's lock, so that a socket there is a dead service's."""
        if path.exists() or path.is_symlink():
            if _answers(path):  # a service of a psfd that took no lock
                raise ServiceError(f"a service is already listening on {path}")
            path.unlink()  # stale socket of a service that died
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o117)  # the socket is born 0660: no window where others could connect
        try:
            sock.bind(str(path))
        except OSError as exc:
            sock.close()
            raise ServiceError(f"cannot create the control socket {path}: {exc.strerror}") from None
        finally:
            os.umask(old)
        os.chmod(path, SOCKET_MODE)
        sock.listen(socket.SOMAXCONN)  # a burst of clients waits in the queue (the client retries a full one)
        return sock

    def _on_signal(self, signum: int, frame: Any) -> None:
        # finish the current frame, commit what is being estimated, pause the run, exit
        if signum == signal.SIGHUP:  # the terminal or ssh session that started the service is gone
            leave_terminal()
        log.info("%s: stopping the service after the current frame", signal.Signals(signum).name)
        self.control.request("pause")
        self.stopping.set()

    # -- runner thread -----------------------------------------------------------------------

    def _run_jobs(self) -> None:
        while True:
            self.released.wait()
            job = self.jobs.get()
            if job is None:
                return
            if self._held_back(job):
                continue
            done = self._done_before(job)
            with self.lock:
                if job.dropped:  # by a `cancel` of the queue: already answered
                    continue
                if self.stopping.is_set():
                    job.result = {"state": "not started", "reason": "the service is stopping"}
                    self.waiting.remove(job)
                    job.done.set()
                    continue
                job.taken = True
                if job.kept:
                    self._save_queue()  # before the run starts: a kill from here on leaves it the catalogue's
                self.queued -= 1
                self.control = Control()
                self.current = {"plan": job.plan.path, "step": None, "done": done,
                                "total": len(job.plan.steps())}
            log.info("starting %s%s", job.plan.path, " (resuming)" if job.resume else "")
            try:
                result = run_plan(job.plan, self.catalogue_path, self.frames_dir, resume=job.resume, new=job.new,
                                  oneshot=job.oneshot, rows=job.wait, control=self.control, progress=None,
                                  on_step=self._on_step, **self.runner_options)
                job.result = result.to_dict()
            except PsfdError as exc:
                job.result = {"state": "failed", "reason": str(exc), "exit_code": exc.exit_code}
                log.error("%s failed: %s", job.plan.path, exc)
            except Exception as exc:  # noqa: BLE001 - the service outlives a broken job and says why
                job.result = {"state": "failed", "reason": f"{type(exc).__name__}: {exc}", "exit_code": 1}
                log.exception("%s failed", job.plan.path)
            with self.lock:
                last = {k: v for k, v in job.result.items() if k not in ("rows", "psf_ids")}
                self.last, self.current = {"plan": job.plan.path, **last}, None
            notify(f"STATUS=idle; last run {job.result.get('run_id', '-')}: {job.result['state']}")
            with self.lock:
                self.waiting.remove(job)
            job.done.set()

    def _held_back(self, job: Job) -> bool:
        """Put ``job`` back at the head of the queue when a pause came while it was being taken."""
        with self.lock:
            if not self.held or self.stopping.is_set():
                return False
            job.first = True
            self.jobs.put(job)
            return True

    def _hold(self, held: bool, by: str = "pause") -> None:
        """Hold the queue (a pause, or the queue of a service before this one) or let it go on; under
        ``self.lock``."""
        self.held, self.held_by = held, by if held else None
        if held:
            self.released.clear()
        else:
            self.released.set()

    def _done_before(self, job: Job) -> int:
        """The steps a resumed job's run has done already, so that `status` counts them as `psfd run --resume`
        does (``3/12 steps``, not ``0/12`` as if the run started again); 0 for a new run."""
        if not job.resume:
            return 0
        try:
            with Catalogue(self.catalogue_path, readonly=True) as catalogue:
                run_id = catalogue.unfinished_run(job.plan.text, plan_key)
                return 0 if run_id is None else int(catalogue.run_summary(run_id)["done"])
        except PsfdError:  # the run itself says why the catalogue cannot be used
            return 0

    def _on_step(self, key: str, state: str, reason: str | None) -> None:
        with self.lock:
            if self.current is None:
                return
            self.current["step"] = key
            if state == "done":
                self.current["done"] += 1
            if reason:
                self.current["reason"] = reason
            status = f"running {self.current['plan']}: {self.current['done']}/{self.current['total']} {key}"
        notify(f"STATUS={status}")

    # -- control socket ----------------------------------------------------------------------

    def _serve_client(self, conn: socket.socket) -> None:
        with conn:
            conn.settimeout(30.0)
            try:
                reader = conn.makefile("rb")
                while True:
                    line = reader.readline(MAX_REQUEST + 1)
                    if not line:
                        return
                    answer = self.handle_line(line)
                    conn.sendall(json.dumps(answer).encode() + b"\n")
                    if len(line) > MAX_REQUEST:
                        return  # the rest of that line is not a request
            except OSError:
                return

    def handle_line(self, line: bytes) -> dict:
        """Answer one request line; never raises (a bad request gets ``ok: false``)."""
        try:
            return self._answer(line)
        except Exception as exc:  # noqa: BLE001 - a bug must not drop the client without an answer
            log.exception("request failed: %s: %s", type(exc).__name__, exc)
            return {"ok": False, "error": f"internal error ({type(exc).__name__}: {exc})", "error_type": "ServiceError",
                    "exit_code": ServiceError.exit_code}

    def _answer(self, line: bytes) -> dict:
        if len(line) > MAX_REQUEST:
            return _refused(BadInputError(f"request longer than {MAX_REQUEST} bytes"))
        if nesting(line) > REQUEST_DEPTH_MAX:  # json.loads recurses once per level
            return _refused(BadInputError(f"request nested deeper than {REQUEST_DEPTH_MAX} levels"))
        try:
            req = json.loads(line)
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            return _refused(BadInputError(f"request is not JSON: {exc}"))
        if not isinstance(req, dict) or not isinstance(req.get("cmd"), str):
            return _refused(BadInputError('request must be a JSON object with "cmd"'))
        handler = getattr(self, f"_cmd_{req['cmd']}", None)
        if handler is None:
            return _refused(BadInputError(f"unknown command {req['cmd']!r} "
                                          "(expected submit, status, pause, resume, cancel)"))
        try:
            return {"ok": True, **handler(req)}
        except PsfdError as exc:
            log.warning("%s refused: %s", req["cmd"], exc)
            return _refused(exc)

    def _enqueue(self, plan: Plan, resume: bool, wait: bool, new: bool = False, oneshot: bool = False) -> dict:
        if self.stopping.is_set():
            raise ServiceError("the service is stopping")
        preflight(plan, self.catalogue_path, self.frames_dir, resume, new)  # refuse now what the runner would later
        job = Job(plan, resume, wait, new=new, oneshot=oneshot)
        with self.lock:
            # preflight cannot see a queued plan (its run is not journalled yet): the second would measure it again
            if not (new or resume or oneshot) and any(same_plan(j.plan.text, plan.text) for j in self.waiting):
                raise BadInputError(f"plan {plan.path} is already submitted and its run not ended: `psfd status` "
                                    "follows it; add --new to measure it again")
            self.waiting.append(job)
            if job.kept:
                self._save_queue()
            self.queued += 1
            queued = self.queued  # as submitted: the runner thread may take the job at once
            held, job.first = self.held, self.held and resume  # a resume ends a hold first, then the queue
            self.jobs.put(job)  # queued before the hold ends: the runner takes it in its place
            self._hold(False)
        if held:
            log.info("the held queue goes on")
        log.info("plan %s submitted%s, %d queued", plan.path,
                 " to resume" if resume else " as a new run" if new else "", queued)
        if not wait:
            return {"queued": queued, "plan": plan.path}
        while not job.done.wait(1.0):
            pass
        return {"result": job.result}

    def _kept(self) -> list[Job]:
        """The jobs a service started again queues again: submitted, not taken, nobody waiting; under
        ``self.lock``."""
        return [job for job in self.waiting if job.kept and not job.taken]  # a dropped job is no longer waiting

    def _save_queue(self) -> None:
        """Write the kept jobs to `store.queue_path` (none: no file); under ``self.lock``."""
        entries = [{"plan": job.plan.text, "path": job.plan.path, "resume": job.resume, "new": job.new}
                   for job in self._kept()]
        try:
            if entries:
                write_durably(self.queue_file, json.dumps(entries, indent=1) + "\n")
            else:
                self.queue_file.unlink(missing_ok=True)
        except OSError as exc:
            # the queue goes on in memory; an older file must not outlive it, or a plan taken since would be
            # queued again by the next service and measured twice (if the file cannot go either, the
            # catalogue's folder cannot be written, nor can that plan's run)
            with contextlib.suppress(OSError):
                self.queue_file.unlink(missing_ok=True)
            log.warning("cannot keep the queue in %s (%s): a service started again will not queue these plans",
                        self.queue_file, path_reason(self.queue_file, exc))

    def _restore_queue(self) -> None:
        """Queue again, held, the plans the service before this one kept (`store.kept_queue`)."""
        try:
            entries = kept_queue(self.catalogue_path)
        except (OSError, ValueError) as exc:  # a damaged file must not keep the service down: set aside, said
            aside = self.queue_file.with_name(self.queue_file.name + ".unreadable")
            with contextlib.suppress(OSError):
                os.replace(self.queue_file, aside)
            log.warning("the queue kept in %s cannot be read (%s): its plans are not queued again; set aside as %s",
                        self.queue_file, exc, aside)
            return
        restored = []
        for entry in entries:
            path = str(entry.get("path", "<queued plan>"))
            try:  # parsed only: what the catalogue refuses (a run made since) the runner refuses when it takes it
                plan = submitted_plan(str(entry.get("plan", "")), path)
            except PsfdError as exc:
                log.warning("plan %s, queued before the service stopped, is not queued again: %s", path, exc)
                continue
            restored.append(Job(plan, bool(entry.get("resume")), new=bool(entry.get("new"))))
        with self.lock:
            for job in restored:
                self.waiting.append(job)
                self.queued += 1
                self.jobs.put(job)
            if restored:
                self._hold(True, "restart")
            self._save_queue()  # without the plans refused
        if restored:
            log.info("%d plans queued before the service stopped are queued again (%s), held until `psfd resume`",
                     len(restored), ", ".join(job.plan.path for job in restored))

    def _cmd_submit(self, req: dict) -> dict:
        text, path = req.get("plan"), req.get("path", "<submitted plan>")
        if not isinstance(text, str):
            raise BadInputError('submit needs "plan": the text of a plan')
        return self._enqueue(submitted_plan(text, str(path)), bool(req.get("resume")), bool(req.get("wait")),
                             new=bool(req.get("new")), oneshot=bool(req.get("oneshot")))

    def _resumable(self) -> list[dict]:
        """The catalogue's paused and interrupted runs, newest first (`unfinished_runs`): what ``resume``
        continues. A ``running`` one is being shot, by this service or another process, and is left alone."""
        return [r for r in unfinished_runs(self.catalogue_path, self.frames_dir) if r["state"] != "running"]

    def _cmd_status(self, req: dict) -> dict:
        unfinished = self._resumable()  # read first: the catalogue is not read under the lock
        with self.lock:
            # "paused" from the catalogue, not from memory: a restarted service has the runs the last one paused
            state = "running" if self.current else ("paused" if unfinished else "idle")
            answer = {"state": state, "current": self.current, "last": self.last, "queued": self.queued,
                      "held": self.held, "held_by": self.held_by,
                      "paused_plan": unfinished[0]["plan_path"] if unfinished else None,
                      "catalogue": str(self.catalogue_path), "frames": str(self.frames_dir)}
        answer["unfinished"] = unfinished
        return answer

    def _cmd_pause(self, req: dict) -> dict:
        with self.lock:
            if self.current is None and not self.queued:
                raise ServiceError("no run is in progress")
            log.info("pause asked on the control socket%s", f": {self.queued} queued held until `resume`"
                     if self.queued else "")
            self._hold(True)
            self.control.request("pause")
        return {"requested": "pause"}

    def _cmd_cancel(self, req: dict) -> dict:
        """Cancel the run in progress after its current frame; with none, close the newest paused run (the
        one `resume` would continue) as cancelled and let a queue its pause held go on; with ``queued``, drop
        the queued plans instead."""
        if req.get("queued"):
            return self._drop_queue()
        with self.lock:
            if self.current is not None:
                self.control.request("cancel")
                log.info("cancel asked on the control socket")
                return {"requested": "cancel"}
        unfinished = self._resumable()  # read first, as status does
        if not unfinished:
            raise ServiceError("no run is in progress or paused")
        run = unfinished[0]
        if run["state"] != "paused":  # its frame store may hold frames it stored and did not commit
            raise ServiceError(f"run {run['id']} of {run['plan_path']} was interrupted, not paused: `psfd resume` "
                               "continues it; cancel it once it runs")
        # the runner starts no job meanwhile (it takes one under self.lock), nor does another process write
        with self.lock, catalogue_lock(self.catalogue_path), Catalogue(self.catalogue_path) as catalogue:
            stored = catalogue.run(run["id"])
            if self.current is not None or stored["state"] != "paused":
                raise ServiceError(f"run {run['id']} started again meanwhile: cancel again to cancel it")
            if any(job.resume and same_plan(job.plan.text, stored["plan_text"]) for job in self.waiting):
                raise ServiceError(f"run {run['id']} is queued to resume: cancel it once it runs")
            catalogue.finish_run(run["id"], "cancelled")
            held = self.held
            self._hold(False)
        log.info("cancel asked on the control socket: run %d of %s (%s) closed as cancelled%s", run["id"],
                 run["plan_path"], _progress(run), "; the held queue goes on" if held else "")
        return {"requested": "cancel", "run_id": run["id"], "plan": run["plan_path"], "progress": _progress(run),
                "held": held}

    def _drop_queue(self) -> dict:
        """Drop every plan queued and not started (kept ones too: a stop no longer forgets them, this does);
        their waiting clients are answered "not started". The run in progress, or a paused one, stays."""
        with self.lock:
            dropped = [job for job in self.waiting if not job.taken]
            if not dropped:
                raise ServiceError("no plan is queued")
            for job in dropped:
                job.dropped = True
                job.result = {"state": "not started", "reason": "its queued plan was cancelled"}
                self.waiting.remove(job)
                job.done.set()
            self.queued -= len(dropped)
            self._save_queue()
            self._hold(False)  # nothing is left to hold
        paths = [job.plan.path for job in dropped]
        log.info("cancel asked on the control socket: %d queued plans dropped (%s)", len(paths), ", ".join(paths))
        return {"requested": "cancel", "dropped": paths}

    def _cmd_resume(self, req: dict) -> dict:
        if self.current is not None:
            raise ServiceError("a run is in progress")
        unfinished = self._resumable()
        if not unfinished:
            with self.lock:
                if not self.held:
                    raise ServiceError("no paused run to resume")
                self._hold(False)
            log.info("resume asked on the control socket: no paused run; the held queue goes on")
            return {"queued": self.queued, "note": "no paused run: the queued plans go on"}
        run, others = unfinished[0], unfinished[1:]
        with Catalogue(self.catalogue_path, readonly=True) as catalogue:
            text = catalogue.run(run["id"])["plan_text"]
        # parsed as a submitted plan: a stored text this psfd no longer reads is refused with its problems
        plan = submitted_plan(text, run["plan_path"] or f"<plan of run {run['id']}>")
        note = None
        if others:
            note = (f"run {run['id']} is the newest of {len(unfinished)} unfinished runs; the others: "
                    + "; ".join(f"run {r['id']} of {r['plan_path']} ({_progress(r)})" for r in others)
                    + "; `resume` again once this one has ended continues the next")
        log.info("resume asked on the control socket: run %d of %s (%s)%s", run["id"], plan.path, _progress(run),
                 f"; {note}" if note else "")
        answer = {"run_id": run["id"], "plan": plan.path, **self._enqueue(plan, True, bool(req.get("wait")))}
        if note:
            answer["note"] = note
        return answer


def submitted_plan(text: str, path: str) -> Plan:
    """A plan text received (a submit) or stored with a run (a resume): every problem named, or the Plan.

    Raises
    ------
    BadInputError
        With ``problems``, every problem of the text (`check_text`).
    """
    problems = check_text(text)
    if problems:
        error = BadInputError(f"plan {path}: " + "; ".join(problems))
        error.problems = problems  # type: ignore[attr-defined]
        raise error
    return parse_plan(text, path)


def _progress(run: dict) -> str:
    """``paused, 1/4 steps done``: an unfinished run (`unfinished_runs`) as the log and the answers say it."""
    return f"{run['state']}, {run['done']}/{run['total']} steps done"


def same_plan(a: str, b: str) -> bool:
    """Whether two plan texts are one plan (`plan_key`: comments, layout and defaults written out do not count)."""
    return a == b or plan_key(a) == plan_key(b)


def _refused(exc: PsfdError) -> dict:
    """The answer to a refused request: the message, and the error's type and exit code for the client."""
    out = {"ok": False, "error": str(exc), "error_type": type(exc).__name__, "exit_code": exc.exit_code}
    if getattr(exc, "problems", None):
        out["problems"] = exc.problems
    return out


_JSON_STRING = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"')


def nesting(line: bytes) -> int:
    """How deep the arrays and objects of a JSON text nest (brackets inside strings are text).

    Counted without parsing, so that a hostile line is refused before `json.loads`
    recurses into it; the count stops one level past `REQUEST_DEPTH_MAX`.
    """
    depth = deepest = 0
    for byte in _JSON_STRING.sub(b"", line):
        if byte in b"[{":
            depth += 1
            deepest = max(deepest, depth)
            if deepest > REQUEST_DEPTH_MAX:
                break
        elif byte in b"]}":
            depth -= 1
    return deepest


def hold_lock(socket_path: Path) -> int:
    """Take the lock a service holds from before it binds ``socket_path`` until it has ended (`client.lock_path`);
    returns its file descriptor: closing it, or the process ending however it ends, releases the lock.

    Raises
    ------
    ServiceError
        Another service holds it (listening, starting or stopping), or the lock file cannot be made.
    """
    path = lock_path(socket_path)
    try:  # O_RDWR refuses a folder, and a FIFO does not block it; never through a link someone put there
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, LOCK_MODE)
    except OSError as exc:
        raise ServiceError(f"cannot make the service's lock file {path}: {path_reason(path, exc)}") from None
    try:
        os.fchmod(fd, LOCK_MODE)  # whatever the umask, as the socket: its group may ask whether we run
        deadline = time.monotonic() + LOCK_PATIENCE
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return fd
            except BlockingIOError:
                if time.monotonic() > deadline:
                    if _answers(Path(socket_path)):
                        raise ServiceError(f"a service is already listening on {socket_path}") from None
                    raise ServiceError(f"another psfd serve holds {socket_path} (its lock {path}): it is starting "
                                       "or stopping") from None
            time.sleep(0.02)
    except OSError as exc:
        os.close(fd)
        raise ServiceError(f"cannot use the service's lock file {path}: {exc.strerror}") from None
    except BaseException:
        os.close(fd)
        raise


def _answers(path: Path) -> bool:
    """True when something accepts connections on ``path`` (one try: a refused one is a stale socket)."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(2.0)
        try:
            sock.connect(str(path))
        except OSError:
            return False
    return True


def _check_socket_folder(folder: Path) -> None:
    """Refuse a socket folder that another user owns or everyone may write: either could swap the socket."""
    info = folder.stat()
    if info.st_uid != os.geteuid():
        raise ServiceError(f"the socket folder {folder} belongs to {user_name(info.st_uid)}, not to "
                           f"{user_name(os.geteuid())}: its owner could replace the socket; use a folder of your own")
    if info.st_mode & 0o002:
        raise ServiceError(f"the socket folder {folder} is writable by everyone: anyone could replace the socket "
                           "(chmod o-w, or use another folder)")
