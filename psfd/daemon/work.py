"""Estimation jobs that run in worker processes beside the capture loop.

Kept apart from the runner and free of heavy imports at module level: a
spawned worker imports this module first, so `init_worker` can pin the
numerical libraries to one thread each before numpy, scipy and OpenCV load
(the workers already share the cores; nested thread pools only oversubscribe).
"""

from __future__ import annotations

import os
import signal
import threading

from psfd.vocabulary import BERNOULLI

THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def init_worker(parent_pid: int) -> None:
    """Pin libraries to one thread, leave signals to the parent, and exit when the parent process is gone.

    Ctrl-C reaches the terminal's whole process group and `systemctl stop` the whole control group: a
    worker that died of either would take the estimate in flight with it, while the parent, which
    finishes the current frame and commits what is being estimated, needs it. So SIGINT (and SIGHUP, a
    terminal's hang-up) is ignored and SIGTERM is held for the watch thread, which ends the worker only when
    the parent sent it: the pool terminates its workers so when one of them died. A parent killed with
    SIGKILL cannot shut its pool down; without the watch the workers would wait on their queue forever.
    """
    for name in THREAD_VARIABLES:
        os.environ[name] = "1"
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGHUP, signal.SIG_IGN)  # a hang-up reaches the terminal's group too: the parent pauses
    # blocked before any thread starts, so that every thread inherits it and only the watch takes it
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGTERM})

    def watch() -> None:
        while os.getppid() == parent_pid:
            sent = signal.sigtimedwait({signal.SIGTERM}, 0.5)
            if sent is not None and sent.si_pid == parent_pid:
                break
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def warm_up() -> None:
    """Import the estimators (a second or two per process) while the rig shoots the first frame."""
    import psfd.estimator.bernoulli  # noqa: F401
    import psfd.estimator.twoscale  # noqa: F401


def estimate_step(kind: str, paths: list[str], channels: list[str], options: dict) -> list:
    """Estimate the PSFs of one step's frames.

    Parameters
    ----------
    kind : str
        ``bernoulli`` (one frame of the noise target) or ``two-photo`` (near frame, far frame): `Plan.kind`.
    paths : list of str
        The stored RAW frames of the step, in capture order.
    channels : list of str
        Bayer channels to estimate.
    options : dict
        Keyword arguments of the estimator (s, support, solver, grid).

    Returns
    -------
    list of psfd.estimator.kernels.PSF
        All windows of every channel, channel by channel.
    """
    import cv2

    cv2.setNumThreads(1)
    out = []
    if kind == BERNOULLI:
        from psfd.estimator.bernoulli import estimate_frames

        planes = _planes(paths[0], channels)
        # one search for the target per frame; the steps already run in parallel processes
        out += estimate_frames([planes[channel] for channel in channels], workers=1, **options)
    else:
        from psfd.estimator.twoscale import estimate_pair

        near, far = _planes(paths[0], channels), _planes(paths[1], channels)
        for channel in channels:
            out += estimate_pair(near[channel], far[channel], **options)
    return out


def _planes(path: str, channels: list[str]) -> dict:
    """The planes of a stored frame by channel: only the one asked for when there is one (a plan's default,
    g1), whose decoding costs half as long and a quarter of the memory of all four (24 MP: 0.10 against
    0.18 s, 48 against 190 MB); all of them otherwise."""
    from psfd.estimator import raw

    return {f.channel: f for f in raw.load_frames(path, channels[0] if len(channels) == 1 else "all")}
