"""Run ``psfd ARGS...`` and SIGKILL its whole process group the Nth time the run reaches a phase.

Usage: ``python tests/kill_at.py PHASE:N ARGS...`` (the caller starts it in a new session, so the
kill takes the estimation workers too, like a power cut). Phases, in the order a step meets them:

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


def kill() -> None:
    if os.getpgrp() == os.getpid():  # our own session: take the workers with us
        os.killpg(os.getpgrp(), signal.SIGKILL)
    os.kill(os.getpid(), signal.SIGKILL)


def arm(phase: str, nth: int) -> None:
    from psfd import catalogue
    from psfd.daemon import runner

    count = {"n": 0}

    def reached() -> bool:
        count["n"] += 1
        return count["n"] == nth

    if phase in ("capture", "pending", "store"):
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
        commit_ready = runner.Runner._commit_ready

        def patched_ready(self, *args):
            if reached():
                kill()
            return commit_ready(self, *args)

        runner.Runner._commit_ready = patched_ready
    elif phase == "commit":
        insert = catalogue.Catalogue._insert

        def patched_insert(self, *args, **kwargs):
            ids = insert(self, *args, **kwargs)
            if reached():
                kill()
            return ids

        catalogue.Catalogue._insert = patched_insert
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
    where, n = sys.argv[1].split(":")
    arm(where, int(n))
    from psfd.cli import main

    sys.exit(main(sys.argv[2:]))
