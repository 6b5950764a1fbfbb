"""Where psfd's log and progress go: -v/-q, stderr, journald's priorities, a width-aware bar or plain lines."""

from __future__ import annotations

import fcntl
import io
import logging
import os
import pty
import re
import select
import struct
import tempfile
import termios
import time

from psfd.cli import logs
from psfd.daemon.runner import Progress


def emit(stream, *records: tuple[int, str], **options) -> str:
    logs.setup(stream=stream, **options)
    log = logging.getLogger("psfd.test")
    for level, message in records:
        log.log(level, message)
    stream.flush()
    return stream.getvalue() if hasattr(stream, "getvalue") else ""


def test_levels_follow_verbose_and_quiet():
    records = [(logging.DEBUG, "d"), (logging.INFO, "i"), (logging.WARNING, "w"), (logging.ERROR, "e")]
    assert emit(io.StringIO(), *records) == "psfd: warning: w\npsfd: error: e\n"
    assert emit(io.StringIO(), *records, verbose=1) == "psfd: info: i\npsfd: warning: w\npsfd: error: e\n"
    assert emit(io.StringIO(), *records, verbose=2).startswith("psfd: debug: d\n")
    assert emit(io.StringIO(), *records, quiet=1) == "psfd: error: e\n"
    assert emit(io.StringIO(), *records, service=True).count("psfd: info: i") == 1  # the service says more


def test_journald_gets_priority_prefixes_and_no_timestamp(monkeypatch):
    """systemd sets JOURNAL_STREAM to the device:inode of the stream it connected; that stream gets <N> prefixes."""
    with tempfile.TemporaryFile("w+") as stream:
        info = os.fstat(stream.fileno())
        monkeypatch.setenv("JOURNAL_STREAM", f"{info.st_dev}:{info.st_ino}")
        assert logs.journal_stream(stream)
        emit(stream, (logging.INFO, "listening"), (logging.WARNING, "step a5.6 failed: camera gone"),
             (logging.ERROR, "two\nlines"), service=True)
        stream.seek(0)
        assert stream.read() == "<6>listening\n<4>step a5.6 failed: camera gone\n<3>two\n<3>lines\n"
        monkeypatch.setenv("JOURNAL_STREAM", "1:2")  # another stream's: plain lines, with timestamps
        assert not logs.journal_stream(stream)
    out = emit(io.StringIO(), (logging.INFO, "listening"), service=True)
    assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d psfd: info: listening\n", out)


def test_v_and_q_work_before_and_after_the_command():
    from psfd.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(["-v", "status"]).verbose == 1
    assert parser.parse_args(["status", "-vv"]).verbose == 2
    assert parser.parse_args(["-q", "rail", "home", "--simulate"]).quiet == 1
    assert parser.parse_args(["estimate", "bernoulli", "x.dng", "-q"]).quiet == 1
    assert parser.parse_args(["status"]).verbose == 0


def terminal(columns: int):
    """A real pseudo-terminal of ``columns`` columns: (stream to write, function reading what it shows)."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    stream = os.fdopen(slave, "w")

    def shown() -> str:
        stream.flush()
        chunks = []
        while select.select([master], [], [], 0.2)[0]:
            chunks.append(os.read(master, 65536))
        return b"".join(chunks).decode()

    return stream, shown


def test_progress_on_a_terminal_fits_its_width_and_tells_the_time():
    stream, shown = terminal(60)
    bar = Progress(3, total=40, done=10, stream=stream)
    bar.show("starting")
    for _ in range(3):
        bar.step("a5.6/x1300/y-44.16/z-29.12/r0")
        time.sleep(0.05)
    bar.close()
    frames = [f for f in re.split(r"[\r\n]", shown()) if f.strip()]
    visible = [re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", f) for f in frames]
    assert visible and all(len(f) <= 60 for f in visible)  # never wraps: redrawn in place
    last = visible[-1]
    assert last.startswith("run 3:") and "13/40" in last and re.search(r"\d\d:\d\d<\d\d:\d\d", last)  # elapsed<left
    stream.close()


def test_progress_elsewhere_is_one_plain_line_per_step():
    stream = io.StringIO()
    bar = Progress(2, total=3, done=0, stream=stream)
    bar.show("starting")
    bar.step("a4/x1300/r0")
    bar.step("a8/x1300/r0", "failed: camera gone")
    bar.close()
    lines = stream.getvalue().splitlines()
    assert lines[0] == "run 2: 0/3 steps starting"
    assert re.fullmatch(r"run 2: 1/3 steps a4/x1300/r0, \d+ s elapsed, about \d+ s left", lines[1])
    assert lines[2].startswith("run 2: 2/3 steps a8/x1300/r0 failed: camera gone, ")
    assert "\r" not in stream.getvalue() and len(lines) == 3
    silent = Progress(2, total=3, done=0, stream=None)
    silent.step("x")
    silent.close()


def test_a_warning_during_a_bar_lands_on_its_own_line():
    stream, shown = terminal(80)
    logs.setup(stream=stream)
    bar = Progress(1, total=2, done=0, stream=stream)
    bar.step("a4/x1300/r0")
    logging.getLogger("psfd.daemon.runner").warning("run 1 step a8 failed: camera gone")
    bar.close()
    lines = [re.sub(r"\x1b\[[0-9;]*[A-Za-z]", "", line).strip() for line in re.split(r"[\r\n]", shown())]
    assert "psfd: warning: run 1 step a8 failed: camera gone" in lines  # a line of its own, not inside the bar
    stream.close()


FORKED_WORKER_KILLED_WHILE_LOGGING = r"""
import logging, os, signal, sys, time
from psfd.cli import logs
import tqdm  # loaded as when a bar is drawn (`estimate edges`, `compare`, `run` on a terminal)

log = logging.getLogger("psfd.test")
stuck_r, stuck_w = os.pipe()  # a stream nobody reads, full: a write to it blocks
os.set_blocking(stuck_w, False)
try:
    while True:
        os.write(stuck_w, b"x" * 65536)
except BlockingIOError:
    os.set_blocking(stuck_w, True)
logs.setup(stream=sys.stderr)
log.warning("before the workers")  # the first line sets up what every later one takes
pid = os.fork()
if pid == 0:  # a forked worker: its line blocks half-written, then the worker is killed (Ctrl-C, a task failed)
    sys.stderr = os.fdopen(stuck_w, "w")
    logging.getLogger("psfd").handlers[0].setStream(sys.stderr)
    log.warning("from the worker")
    os._exit(0)
time.sleep(0.5)
os.kill(pid, signal.SIGKILL)
os.waitpid(pid, 0)
log.warning("the parent goes on")
print("done")
"""


def test_a_worker_killed_while_it_logs_leaves_the_parents_log_working():
    """A forked worker's log line took the progress bar's lock (tqdm's, shared by every forked process); a worker
    killed while writing it (its stderr slow or full, then ended by Ctrl-C or a failed task) left it held, and the
    parent's next log line waited for it for ever. A worker has no bar of its own to lift out of the way."""
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", FORKED_WORKER_KILLED_WHILE_LOGGING], capture_output=True, text=True,
                          timeout=60)
    assert done.stdout == "done\n", done.stderr
    assert done.stderr.splitlines() == ["psfd: warning: before the workers", "psfd: warning: the parent goes on"]
