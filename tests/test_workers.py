"""psfd.workers: independent calls on threads, in order, the first error raised once all have ended; forked
workers that a killed worker, a failure or an interrupt ends instead of hanging."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from psfd import workers
from psfd.errors import PairError


def test_concurrently_keeps_the_order_and_raises_the_first_error(monkeypatch):
    import threading
    import time

    seen = []

    def slow(value):
        time.sleep(0.05)
        seen.append(threading.get_ident())
        return value

    assert workers.concurrently(lambda: slow(1), lambda: slow(2), lambda: 3) == [1, 2, 3]
    monkeypatch.setattr(workers, "usable_cores", lambda: 2)
    finished = []

    def fails(message):
        time.sleep(0.02)
        finished.append(message)
        raise PairError(message)

    with pytest.raises(PairError, match="first"):
        workers.concurrently(lambda: fails("first"), lambda: fails("second"), lambda: finished.append("ok"))
    assert sorted(finished) == ["first", "ok", "second"]  # all ended before the error was raised
    monkeypatch.setattr(workers, "usable_cores", lambda: 1)
    seen.clear()
    assert workers.concurrently(lambda: slow("a"), lambda: slow("b")) == ["a", "b"]
    assert set(seen) == {threading.get_ident()}  # one core: all on this thread


def python(code: str, *args: str) -> subprocess.Popen:
    """``code`` in a new interpreter with ``args`` (a hang must fail a test, never the suite: callers wait with a
    timeout), Ctrl-C at its default: a suite started in the background runs with SIGINT ignored, and Python
    keeps it ignored."""
    return subprocess.Popen([sys.executable, "-c", textwrap.dedent(code), *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def test_a_worker_killed_under_its_task_fails_the_work_instead_of_hanging_it():
    """SIGKILL or the OOM killer on a forked worker: multiprocessing.Pool, which psfd used before, waited for
    the dead worker's task for ever, and `psfd estimate --grid` or `psfd compare` hung."""
    proc = python("""
        import os, signal, time
        from psfd import workers
        from psfd.cli import compare
        from psfd.errors import EstimationError

        def task(i):
            if i == 1:
                os.kill(os.getpid(), signal.SIGKILL)
            time.sleep(0.1)
            return i

        for name, run in (("windows", lambda: workers.forked_map(task, 6, 2)),
                          ("beside", lambda: compare._Beside(lambda: task(1)).result())):
            try:
                run()
            except EstimationError as exc:
                print(name, exc.exit_code, exc)
        """)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert out.splitlines() == [f"{name} 3 a worker process ended abruptly (killed, or out of memory?)"
                                for name in ("windows", "beside")]


def test_a_failed_task_or_an_interrupt_ends_the_other_workers_at_once(tmp_path):
    """The work queued behind a failure, or a Ctrl-C, is not done: the workers end at once, none is left."""
    program = """
        import os, pathlib, sys, time
        from psfd import workers

        def task(i):
            (pathlib.Path(sys.argv[1]) / str(os.getpid())).touch()  # this worker started
            if i == 1 and sys.argv[2] == "fail":  # while task 0 sleeps in the other worker
                raise ValueError("task 1 failed")
            time.sleep(60)

        started = time.monotonic()
        try:
            workers.forked_map(task, 4, 2)
        except ValueError as exc:
            print(exc, round(time.monotonic() - started))
        """
    for case in ("fail", "interrupt"):
        started = tmp_path / case
        started.mkdir()
        proc = python(program, str(started), case)
        if case == "interrupt":
            deadline = time.monotonic() + 30
            while len(list(started.iterdir())) < 2 and time.monotonic() < deadline:  # both workers at work
                time.sleep(0.05)
            proc.send_signal(signal.SIGINT)  # Ctrl-C: the workers ignore it, their parent ends them
        out, err = proc.communicate(timeout=30)
        if case == "fail":
            assert out.split() == ["task", "1", "failed", "0"], err  # at once, not after task 0's 60 s
        else:
            assert "KeyboardInterrupt" in err
        assert len(list(started.iterdir())) == 2
        for pid in (int(p.name) for p in started.iterdir()):
            with pytest.raises(ProcessLookupError):  # no worker left running its 60 s
                os.kill(pid, 0)
