"""Run ``psfd ARGS...`` with its estimates held in the worker, so that a test acts while one is in flight.

Usage: ``PSFD_HOLD=FOLDER python tests/held_estimate.py ARGS...``. While ``FOLDER/hold`` exists, an
estimate that starts in a worker writes the worker's pid to ``FOLDER/estimating`` and waits there until
``hold`` is removed, then estimates as usual. A test creates ``hold``, waits for ``estimating``, acts
(a signal to the whole process group, a kill of the worker alone) and removes ``hold``: whatever it
did lands while the estimate is under way in the worker, on every run, not at a random moment.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from psfd.daemon import work

estimate_step = work.estimate_step  # the real one: in the workers this module is imported, not run


def held_estimate(kind: str, paths: list[str], channels: list[str], options: dict) -> list:
    folder = Path(os.environ["PSFD_HOLD"])
    if (folder / "hold").exists():
        (folder / "estimating.tmp").write_text(str(os.getpid()))
        (folder / "estimating.tmp").replace(folder / "estimating")  # whole, never half-written
        deadline = time.monotonic() + 120
        while (folder / "hold").exists() and time.monotonic() < deadline:
            time.sleep(0.01)
    return estimate_step(kind, paths, channels, options)


if __name__ == "__main__":
    work.estimate_step = held_estimate  # before the runner is imported: its default estimate
    from psfd.cli import main

    sys.exit(main(sys.argv[1:]))
