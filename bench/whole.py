"""Timing of whole processes, as a user waits for them: standard library only.

A command is started as a subprocess and reaped with `os.wait4`, which gives
the operating system's own accounting of that child: its user and system
seconds and its peak resident memory (Linux: kilobytes). Wall time is the
monotonic clock read around start and reap, so start-up, imports and
interpreter teardown are all in it.

A command and its reference run in turn (A B A B ...) and the ratio is taken
pair by pair, then the median: on a shared machine whose speed drifts, a ratio
of two figures measured minutes apart means little.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import tempfile
from dataclasses import dataclass


@dataclass
class Run:
    wall: float  # seconds
    cpu: float  # user + system seconds
    peak_mib: float  # peak resident memory of the process
    code: int  # exit status
    error: str = ""  # the end of what a failed run wrote on stderr


def run(argv: list[str], env: dict[str, str] | None = None, cwd: str | None = None) -> Run:
    """Start ``argv``, wait for it, and return its wall and CPU time and peak memory."""
    with tempfile.TemporaryFile("w+") as err:  # kept aside: a warning on a terminal is no part of the time
        start = _now()
        proc = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err, env=env,
                                cwd=cwd, text=True)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = _now() - start
        proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here: tell Popen
        error = ""
        if proc.returncode:
            err.seek(0)
            error = err.read()[-2000:]
    return Run(wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0, proc.returncode, error)


def machine() -> str:
    """The processor and the cores this process may use, for the first line of a benchmark's output.

    Machines of one kind differ: the same psfd commit took 8.6 s on one 2-core machine and 3.3 s on another
    for the same 400-PSF command, so a time means little without the machine it was measured on, and a
    figure remembered from another machine (the published C programs' in issue 11) is no reference.
    """
    model = "unknown processor"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as info:
            model = next((line.split(":", 1)[1].strip() for line in info if line.startswith("model name")), model)
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return f"machine: {model}, {cores} usable cores"


def _now() -> float:
    import time

    return time.monotonic()


@dataclass
class Paired:
    a: list[Run]
    b: list[Run]

    @staticmethod
    def _median(runs: list[Run], field: str) -> float:
        return statistics.median(getattr(r, field) for r in runs)

    def median(self, which: str, field: str) -> float:
        return self._median(self.a if which == "a" else self.b, field)

    def ratio(self) -> float:
        """Median over pairs of wall(A) / wall(B)."""
        return statistics.median(x.wall / y.wall for x, y in zip(self.a, self.b))

    def failed(self) -> list[int]:
        return sorted({r.code for r in self.a + self.b if r.code != 0})


def paired(a: list[str], b: list[str], runs: int = 5, warmup: int = 1, env_a: dict[str, str] | None = None,
           env_b: dict[str, str] | None = None, prepare=None, cwd: str | None = None) -> Paired:
    """Run ``a`` and ``b`` in turn ``runs`` times after ``warmup`` uncounted rounds, both in ``cwd``.

    ``prepare`` is called before every run (e.g. to empty an output folder) and is not timed.
    """
    out = Paired([], [])
    for i in range(warmup + runs):
        for argv, env, into in ((a, env_a, out.a), (b, env_b, out.b)):
            if prepare is not None:
                prepare()
            r = run(argv, env, cwd)
            if i >= warmup:
                into.append(r)
    return out
