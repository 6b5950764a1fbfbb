"""Run ``psfd ARGS...`` and SIGKILL its whole process group the Nth time the run reaches a phase.

Usage: ``python tests/kill_at.py PHASE:N[:SIGNAL] ARGS...`` (the caller starts it in a new session, so the
kill takes the estimation workers too, like a power cut). SIGNAL (``TERM``, ``INT``; default ``KILL``)
sends another signal to the group instead, as `systemctl stop` or Ctrl-C do; the process handles it
right after the phase. Phases before the run's first step, in the order a run meets them:

- ``plan``: the plan file is read (the command has not begun to run it);
- ``rig``: the rig is open (nothing is created yet: no catalogue, no frame store);
- ``opening``: the frame store is held and the catalogue open, the run not yet journalled;
- ``journal``: the run is journalled (a new run started, or a paused one reopened to go on).

Phases, in the order a step meets them:

- ``capture``: the frame is downloaded into the store's temporary folder, not yet stored;
- ``pending``: the frame is journalled as being stored (`Catalogue.pend_frame`), not yet in the store;
- ``store``: the frame is stored under its hash, not yet catalogued;
- ``estimate``: the step's estimate was just handed to a worker;
- ``commit``: the step's frames and PSFs are inserted, inside the transaction, before COMMIT;
- ``last-commit``: every step is committed, the run is about to be closed as done;
- ``close-down``: the run is closed as done; the rig and the catalogue are being released.
"""

from __future__ import annotations

import os
import signal
import sys


SIGNAL = signal.SIGKILL


def kill() -> None:
    if os.getpgrp() == os.getpid():  # our own session: take the workers with us
        os.killpg(os.getpgrp(), SIGNAL)
    if SIGNAL == signal.SIGKILL:
        os.kill(os.getpid(), SIGNAL)
    elif os.getpgrp() != os.getpid():
        os.kill(os.getpid(), SIGNAL)


def arm(phase: str, nth: int) -> None:
    from psfd import catalogue
    from psfd.daemon import plan, runner

    count = {"n": 0}

    def reached() -> bool:
        count["n"] += 1
        return count["n"] == nth

    def after(function):  # the phase is reached when `function` returns
        def patched(*args, **kwargs):
            out = function(*args, **kwargs)
            if reached():
                kill()
            return out

        return patched

    def before(function):  # the phase is reached when `function` is called
        def patched(*args, **kwargs):
            if reached():
                kill()
            return function(*args, **kwargs)

        return patched

    if phase == "plan":
        plan.load_plan = after(plan.load_plan)
    elif phase == "rig":
        runner.open_rig = after(runner.open_rig)
    elif phase == "opening":
        runner.sweep_frames = before(runner.sweep_frames)
    elif phase == "journal":
        finish_run = catalogue.Catalogue.finish_run

        def patched_reopen(self, run_id, state):
            finish_run(self, run_id, state)
            if state == "running" and reached():
                kill()

        catalogue.Catalogue.start_run = after(catalogue.Catalogue.start_run)
        catalogue.Catalogue.finish_run = patched_reopen
    elif phase in ("capture", "pending", "store"):
        store_frame = runner.store_frame

        def patched_store(src, frames_dir, journal=None):
            if phase == "capture" and reached():
                kill()

            def journalled(sha: str) -> None:
                journal(sha)
                if phase == "pending" and reached():
                    kill()

            out = store_frame(src, frames_dir, journalled)
            if phase == "store" and reached():
                kill()
            return out

        runner.store_frame = patched_store
    elif phase == "estimate":
        runner.Runner._commit_ready = before(runner.Runner._commit_ready)
    elif phase == "commit":
        catalogue.Catalogue._insert = after(catalogue.Catalogue._insert)
    elif phase in ("last-commit", "close-down"):
        finish_run = catalogue.Catalogue.finish_run
        release_rig = runner.release_rig
        closed = {"done": False}

        def patched_finish(self, run_id, state):
            if state == "done" and phase == "last-commit" and reached():
                kill()
            finish_run(self, run_id, state)
            closed["done"] = closed["done"] or state == "done"

        def patched_release(camera, rail):
            if closed["done"] and reached():
                kill()
            release_rig(camera, rail)

        catalogue.Catalogue.finish_run = patched_finish
        runner.release_rig = patched_release
    else:
        raise SystemExit(f"unknown phase {phase!r}")


if __name__ == "__main__":
    where, n, *name = sys.argv[1].split(":")
    SIGNAL = signal.Signals[f"SIG{name[0]}"] if name else signal.SIGKILL
    arm(where, int(n))
    from psfd.cli import main

    sys.exit(main(sys.argv[2:]))
