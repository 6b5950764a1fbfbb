"""Work on several cores, as the estimators and `psfd compare` spread it: how many cores this process may
use, independent calls on threads or forked processes, and the signal set-up every forked worker shares."""

from __future__ import annotations

import os
import signal
import sys
import threading
from typing import Any, Callable


def usable_cores() -> int:
    """The processors this process may run on (its affinity, where the system has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def can_fork() -> bool:
    """Whether this system forks processes (`ForkedWorkers`): not on Windows, where work stays on one core."""
    import multiprocessing  # here, not at the top: 13 ms of the start-up of a one-window estimate

    return "fork" in multiprocessing.get_all_start_methods()


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


_TASK: Callable[[int], Any] | None = None  # what `forked_map`'s workers run: it reaches them by the fork


def forked_map(task: Callable[[int], Any], count: int, workers: int) -> list[Any]:
    """``[task(0), ..., task(count - 1)]`` on ``workers`` forked processes (here when one, or without fork).

    The task and everything it reads reach the workers by the fork, never pickled: only the indices go
    out and the results come back. The workers leave interrupts to this process (`worker_signals`), which
    ends them; the first exception raised by a task is raised here, and a worker's death as `ForkedWorkers`
    says.
    """
    global _TASK
    workers = max(1, min(int(workers), count))
    if workers > 1 and not can_fork():
        workers = 1
    if workers == 1:
        return [task(i) for i in range(count)]
    _TASK = task
    try:
        with ForkedWorkers(workers) as pool:
            futures = [pool.submit(_run_task, i) for i in range(count)]  # the first one forks the workers
            return pool.results(futures)
    finally:
        _TASK = None


class ForkedWorkers:
    """Processes forked from this one at the first `submit`, for work they inherit by the fork.

    concurrent.futures, not multiprocessing.Pool: a Pool replaces a worker that was killed (SIGKILL, the
    OOM killer) and waits for ever for the task it held, so the command hangs; here the death fails the
    work, and `result` raises `EstimationError` (exit code 3). Used as a context manager, the workers
    end at once when the block is left by an exception (an interrupt, a task's failure), their queued
    work cancelled, and are waited for otherwise.
    """

    def __init__(self, workers: int) -> None:
        import concurrent.futures
        import multiprocessing

        self.pool = concurrent.futures.ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"),
                                                           initializer=worker_signals)

    def submit(self, call: Callable[..., Any], *args: Any) -> Any:
        """`concurrent.futures.Executor.submit`: ``call`` and ``args`` are pickled, so a module-level function."""
        return self.pool.submit(call, *args)

    @staticmethod
    def result(future: Any) -> Any:
        """What a submitted call returned, or the exception it raised; `EstimationError` if its worker died."""
        from concurrent.futures.process import BrokenProcessPool

        from psfd.errors import EstimationError

        try:
            return future.result()
        except BrokenProcessPool:
            raise EstimationError("a worker process ended abruptly (killed, or out of memory?)") from None

    def results(self, futures: list[Any]) -> list[Any]:
        """`result` of each future, in order; the first failure raised as soon as it happens, not after the
        futures before it."""
        import concurrent.futures

        concurrent.futures.wait(futures, return_when=concurrent.futures.FIRST_EXCEPTION)
        for future in futures:
            if future.done() and future.exception() is not None:
                self.result(future)  # raises what the task raised
        return [self.result(future) for future in futures]

    def close(self) -> None:
        """Wait for the submitted work, then let the workers end."""
        self.pool.shutdown()

    def end(self) -> None:
        """End the workers now, their queued work cancelled."""
        terminate = getattr(self.pool, "terminate_workers", None)  # Python 3.14
        if terminate is not None:
            terminate()
        else:  # before 3.14 the executor's processes are only in this attribute, which shutdown clears
            processes = list((self.pool._processes or {}).values())
            self.pool.shutdown(wait=False, cancel_futures=True)
            for process in processes:
                process.terminate()
        self.pool.shutdown()  # reaps them

    def __enter__(self) -> "ForkedWorkers":
        return self

    def __exit__(self, kind: type | None, *_: Any) -> None:
        if kind is None:
            self.close()
        else:
            self.end()


def _run_task(index: int) -> Any:
    assert _TASK is not None
    return _TASK(index)


def concurrently(*calls: Callable[[], Any]) -> list[Any]:
    """The results of independent calls, in order, run on threads beside this one when there are cores for it.

    OpenCV (SIFT, resizing) and numpy's element-wise work release the GIL, so
    two such calls overlap on two cores. Each call does the same arithmetic as
    when run alone, so the results do not depend on it. The first exception
    raised, in the order of the calls, is raised once all have finished.
    """
    if len(calls) < 2 or usable_cores() < 2:
        return [call() for call in calls]
    results: list[Any] = [None] * len(calls)
    errors: list[BaseException | None] = [None] * len(calls)

    def run(index: int) -> None:
        try:
            results[index] = calls[index]()
        except BaseException as exc:  # re-raised in the caller's thread below
            errors[index] = exc

    threads = [threading.Thread(target=run, args=(i,), daemon=True) for i in range(1, len(calls))]
    for thread in threads:
        thread.start()
    run(0)
    for thread in threads:
        thread.join()
    for error in errors:
        if error is not None:
            raise error
    return results
