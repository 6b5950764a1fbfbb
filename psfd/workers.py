"""Forked worker processes, as the estimators and `psfd compare` start them: how many cores this
process may use, and the signal set-up every worker shares."""

from __future__ import annotations

import os
import signal


def usable_cores() -> int:
    """The processors this process may run on (its affinity, where the system has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def worker_signals() -> None:
    """A worker's initializer: it leaves interrupts to its parent (which ends it) and ends quietly when terminated."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
