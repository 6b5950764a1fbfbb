"""Forked worker processes, as the estimators and `psfd compare` start them: how many cores this
process may use, and the signal set-up every worker shares."""

from __future__ import annotations

import os
import signal
import sys


def usable_cores() -> int:
    """The processors this process may run on (its affinity, where the system has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def in_worker() -> bool:
    """True in a worker process that multiprocessing started (a forked pool's, the daemon's).

    Read without importing multiprocessing (13 ms of a one-photo estimate's start-up): a process that
    multiprocessing started has it loaded, and one that never loaded it was not started by it.
    """
    module = sys.modules.get("multiprocessing")
    return module is not None and module.parent_process() is not None


def worker_signals() -> None:
    """A worker's initializer: it leaves interrupts to its parent (which ends it) and ends quietly when terminated."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
