"""The client side of the service's control socket: where it is, and one request at a time.

Standard library only, so that any command can ask whether the service is up
without loading the service itself (see `psfd.daemon.service` for the protocol).

No socket file means no service: the command works without it. A socket that
exists but refuses the caller is an error, never a reason to run locally behind
the service's back: permission denied is reported at once; a refused connect (a
service restarting) and a full connection queue (a burst of clients) are retried
for `CONNECT_PATIENCE` seconds first.

Except a socket that its service left when it was killed (SIGKILL, out of memory,
the machine's power lost): the service holds an advisory lock on `lock_path` from
before it binds its socket until it has ended, and the kernel releases it however
the process ends. A refused socket whose lock is free has no service behind it: the
client says so in one line, removes it when this user may (holding the lock, so no
service can be starting meanwhile) and goes on as with no socket. Without a lock
file to ask (a socket psfd did not make, or one this user may not read), nothing
says the service ended: refused as before.
"""

from __future__ import annotations

import errno
import fcntl
import grp
import json
import logging
import os
import socket
import stat
import time
from pathlib import Path

from psfd.errors import ServiceError, by_name
from psfd.vocabulary import REQUEST_BYTES_MAX

__all__ = ["CONNECT_PATIENCE", "MAX_REQUEST", "connect", "default_socket_path", "lock_path", "request", "service_up",
           "submit"]

MAX_REQUEST = REQUEST_BYTES_MAX  # a plan is a few kB; refuse anything absurd instead of buffering it
CONNECT_PATIENCE = 5.0  # seconds a refused or busy connect is retried before it is an error
RETRY = (errno.ECONNREFUSED, errno.EAGAIN, errno.ETIMEDOUT)
log = logging.getLogger(__name__)


def default_socket_path() -> Path:
    """$PSFD_SOCKET, else the systemd RuntimeDirectory, else a per-user runtime folder."""
    if os.environ.get("PSFD_SOCKET"):
        return Path(os.environ["PSFD_SOCKET"])
    if os.environ.get("RUNTIME_DIRECTORY"):
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0]) / "control.sock"
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "psfd" / "control.sock"
    return Path(f"/tmp/psfd-{os.getuid()}") / "control.sock"


def lock_path(socket_path: str | os.PathLike) -> Path:
    """The file beside a control socket that its service holds locked (flock) while it runs: ``control.sock.lock``."""
    path = Path(socket_path)
    return path.with_name(path.name + ".lock")


def connect(path: str | os.PathLike, timeout: float | None = 10.0,
            patience: float = CONNECT_PATIENCE) -> socket.socket | None:
    """A socket connected to the service; None when there is no socket file, or only the one a service that
    ended left (no service).

    Raises
    ------
    ServiceError
        The path is not a socket, the socket refuses this user, or it stayed refused or
        busy for ``patience`` seconds.
    """
    path = Path(path)
    try:
        mode = path.stat().st_mode
    except (FileNotFoundError, NotADirectoryError):
        return None
    except OSError as exc:
        raise ServiceError(f"cannot reach the service at {path}: {exc.strerror}") from None
    if not stat.S_ISSOCK(mode):
        raise ServiceError(f"{path} is not a control socket (it is a file or a folder)")
    deadline, pause = time.monotonic() + patience, 0.01
    while True:
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        sock.settimeout(timeout)
        try:
            sock.connect(str(path))
            return sock
        except FileNotFoundError:  # removed meanwhile: a service that stopped
            sock.close()
            return None
        except OSError as exc:
            sock.close()
            code = errno.ETIMEDOUT if isinstance(exc, TimeoutError) else exc.errno
            behind = _behind(path) if code == errno.ECONNREFUSED else "unknown"
            if behind == "ended":
                return None
            if code not in RETRY or time.monotonic() + pause > deadline:
                raise ServiceError(_refusal(path, code, exc, patience, behind == "running")) from None
        time.sleep(pause)
        pause = min(2 * pause, 0.25)


def _behind(path: Path) -> str:
    """What is behind the refusing socket ``path``, told by the lock its service holds while it runs (`lock_path`):
    ``running`` (held: a service starting or stopping), ``ended`` (free: the socket of a service that ended
    without removing it, now removed if this user may, and a warning line says so) or ``unknown`` (no lock
    file this user may read).
    """
    real = Path(os.path.realpath(path))  # the lock is beside the socket itself, not beside a link to it
    try:  # read-only, never created: only the service makes it; O_NONBLOCK: a FIFO in its place must not hang us
        fd = os.open(lock_path(real), os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK)
    except OSError:
        return "unknown"
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return "unknown"
        try:  # shared: clients asking at once do not hold each other up; a service takes it exclusive
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return "running"
        except OSError:  # a file system without locks
            return "unknown"
        # while we hold the lock no service can be binding a new socket here: the one at `real` is the old one
        try:
            real.unlink()
            done = "removed"
        except FileNotFoundError:
            done = "removed meanwhile"
        except OSError as exc:
            done = f"not removed ({exc.strerror})"
    finally:
        os.close(fd)
    log.warning("%s: the socket of a psfd serve that ended without removing it; %s, going on without the service",
                path, done)
    return "ended"


def _refusal(path: Path, code: int | None, exc: OSError, patience: float, running: bool = False) -> str:
    """Why a socket that exists would not take this connection, and what to do about it (``running``: its
    service holds its lock)."""
    if code in (errno.EACCES, errno.EPERM):
        try:
            group = grp.getgrgid(path.stat().st_gid).gr_name
        except (OSError, KeyError):
            group = "its group"
        return f"the control socket {path} refuses you: Permission denied (members of group {group} may use it)"
    if code == errno.ECONNREFUSED and running:
        return (f"the control socket {path} exists but its connection was refused for {patience:g} s while its service "
                f"holds {lock_path(path)}: it is starting or stopping; try again")
    if code == errno.ECONNREFUSED:
        return (f"the control socket {path} exists but its connection was refused for {patience:g} s: the service "
                f"stopped or is restarting; start it, or remove {path} to work without it")
    if code in (errno.EAGAIN, errno.ETIMEDOUT):
        return f"the service at {path} is busy: its connection queue stayed full for {patience:g} s; try again"
    return f"cannot reach the service at {path}: {exc.strerror or exc}"


def request(path: str | os.PathLike, payload: dict, timeout: float | None = 10.0) -> dict:
    """Send one request to the service and return its answer.

    Raises
    ------
    PsfdError
        The service's refusal as the error type it named (a bad plan is a BadInputError here as
        in a local run, with its exit code), ServiceError when it named none.
    ServiceError
        No service, or the socket refused the connection (`connect`).
    """
    sock = connect(path, timeout)
    if sock is None:
        raise ServiceError(f"cannot reach the service at {path}: no such socket")
    try:
        with sock:
            sock.sendall(json.dumps(payload).encode() + b"\n")
            with sock.makefile("rb") as reader:
                line = reader.readline(MAX_REQUEST)
    except OSError as exc:
        raise ServiceError(f"cannot reach the service at {path}: {exc.strerror or exc}") from None
    if not line:
        raise ServiceError(f"the service at {path} closed the connection without answering")
    answer = json.loads(line)
    if not answer.get("ok"):
        raise by_name(answer.get("error_type", ""), answer.get("error", "request refused"))
    return answer


def service_up(path: str | os.PathLike) -> bool:
    """True when the service answers on the control socket, False when there is no socket.

    Raises ServiceError when the socket exists but refuses (`connect`): that is never "no service".
    """
    sock = connect(path, timeout=2.0)
    if sock is None:
        return False
    sock.close()
    return True


def submit(path: str | os.PathLike, plan_text: str, plan_path: str, *, resume: bool = False, new: bool = False,
           wait: bool = False, oneshot: bool = False) -> dict:
    """Submit a plan to the service (flags as in `psfd.daemon.runner.Runner.run`).

    Returns the service's answer: ``queued`` at once, or with ``wait`` the ``result``
    of the run (`RunResult.to_dict`, with its PSF rows) when it has ended.
    """
    payload = {"cmd": "submit", "plan": plan_text, "path": plan_path, "resume": resume, "new": new,
               "wait": wait, "oneshot": oneshot}
    return request(path, payload, timeout=None if wait else 10.0)
