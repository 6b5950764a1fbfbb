"""The client side of the service's control socket: where it is, and one request at a time.

Standard library only, so that any command can ask whether the service is up
without loading the service itself (see `psfd.daemon.service` for the protocol).
"""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

from psfd.errors import ServiceError

__all__ = ["MAX_REQUEST", "default_socket_path", "request", "service_up", "submit"]

MAX_REQUEST = 1 << 20  # a plan is a few kB; refuse anything absurd instead of buffering it


def default_socket_path() -> Path:
    """$PSFD_SOCKET, else the systemd RuntimeDirectory, else a per-user runtime folder."""
    if os.environ.get("PSFD_SOCKET"):
        return Path(os.environ["PSFD_SOCKET"])
    if os.environ.get("RUNTIME_DIRECTORY"):
        return Path(os.environ["RUNTIME_DIRECTORY"].split(":")[0]) / "control.sock"
    if os.environ.get("XDG_RUNTIME_DIR"):
        return Path(os.environ["XDG_RUNTIME_DIR"]) / "psfd" / "control.sock"
    return Path(f"/tmp/psfd-{os.getuid()}") / "control.sock"


def request(path: str | os.PathLike, payload: dict, timeout: float | None = 10.0) -> dict:
    """Send one request to the service and return its answer.

    Raises
    ------
    ServiceError
        The socket cannot be reached or the service refused the request.
    """
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(timeout)
            sock.connect(str(path))
            sock.sendall(json.dumps(payload).encode() + b"\n")
            with sock.makefile("rb") as reader:
                line = reader.readline(MAX_REQUEST)
    except OSError as exc:
        raise ServiceError(f"cannot reach the service at {path}: {exc.strerror or exc}") from None
    if not line:
        raise ServiceError(f"the service at {path} closed the connection without answering")
    answer = json.loads(line)
    if not answer.get("ok"):
        raise ServiceError(answer.get("error", "request refused"))
    return answer


def service_up(path: str | os.PathLike) -> bool:
    """True when something accepts connections on the control socket."""
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(2.0)
            sock.connect(str(path))
        return True
    except OSError:
        return False


def submit(path: str | os.PathLike, plan_text: str, plan_path: str, *, resume: bool = False, new: bool = False,
           wait: bool = False, oneshot: bool = False) -> dict:
    """Submit a plan to the service (flags as in `psfd.daemon.runner.Runner.run`).

    Returns the service's answer: ``queued`` at once, or with ``wait`` the ``result``
    of the run (`RunResult.to_dict`, with its PSF rows) when it has ended.
    """
    payload = {"cmd": "submit", "plan": plan_text, "path": plan_path, "resume": resume, "new": new,
               "wait": wait, "oneshot": oneshot}
    return request(path, payload, timeout=None if wait else 10.0)
