"""Where psfd's log goes: the standard library's `logging`, set up once by the command line.

Every module logs to its own logger (``logging.getLogger(__name__)``); this
module decides what reaches stderr and how it looks:

- level: warnings and errors by default, ``-v`` adds information (``-vv``
  debugging), ``-q`` keeps errors only; the service (``psfd serve``) logs
  information by default, since its log is all it says;
- on a terminal or in a file: ``psfd: warning: ...`` lines, the same form as
  the one-line errors (the service adds a timestamp);
- under systemd, when stderr is the journal (``$JOURNAL_STREAM`` names it):
  the sd-daemon priority prefixes (``<4>`` warning, ``<6>`` information...) and
  no timestamp, which journald adds itself; ``journalctl -p warning`` then
  filters by level.

Warnings go to stderr, never into the tables and JSON lines on stdout.
Standard library only, like the rest of the parser.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import TextIO

# sd-daemon(3) priorities: the syslog levels journald understands as line prefixes.
PRIORITY = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, logging.INFO: 6, logging.DEBUG: 7}


def add_options(parser: argparse.ArgumentParser, suppress: bool = False) -> None:
    """``-v``/``--verbose`` and ``-q``/``--quiet`` (counted). ``suppress``: for subcommands, so that
    an option given before the subcommand is not reset by the subcommand's default."""
    default = argparse.SUPPRESS if suppress else 0
    group = parser.add_argument_group("log")
    group.add_argument("-v", "--verbose", action="count", default=default,
                       help="say more on stderr (-v information, -vv debugging)")
    group.add_argument("-q", "--quiet", action="count", default=default, help="errors only on stderr")


def level(verbose: int, quiet: int, service: bool = False) -> int:
    """The logging level of a command line: WARNING (INFO for the service), one step per -v or -q."""
    base = logging.INFO if service else logging.WARNING
    return min(logging.CRITICAL, max(logging.DEBUG, base - 10 * verbose + 10 * quiet))


def journal_stream(stream: TextIO) -> bool:
    """Whether ``stream`` is the journal: ``$JOURNAL_STREAM`` holds the device and inode of the
    stream systemd connected (systemd.exec(5)), so compare it with the stream's own."""
    value = os.environ.get("JOURNAL_STREAM", "")
    device, _, inode = value.partition(":")
    try:
        info = os.fstat(stream.fileno())
        return bool(device and inode) and (info.st_dev, info.st_ino) == (int(device), int(inode))
    except (OSError, ValueError, AttributeError):
        return False


class JournalFormatter(logging.Formatter):
    """``<N>message``: the priority prefix of sd-daemon(3), no timestamp (journald adds its own)."""

    def format(self, record: logging.LogRecord) -> str:
        priority = PRIORITY.get(record.levelno, 6 if record.levelno < logging.WARNING else 3)
        text = super().format(record)
        return "\n".join(f"<{priority}>{line}" for line in text.splitlines() or [""])


class PlainFormatter(logging.Formatter):
    """``psfd: warning: message`` (with a timestamp first for the service)."""

    def __init__(self, timestamps: bool) -> None:
        super().__init__("%(asctime)s %(message)s" if timestamps else "%(message)s", "%Y-%m-%d %H:%M:%S")

    def format(self, record: logging.LogRecord) -> str:
        record = logging.makeLogRecord(record.__dict__)
        record.msg = f"psfd: {record.levelname.lower()}: {record.getMessage()}"
        record.args = None
        return super().format(record)


class Handler(logging.StreamHandler):
    """A stream handler that lifts a progress bar out of the way (tqdm, when one is drawn) to write a line."""

    def __init__(self, stream: TextIO) -> None:
        super().__init__(stream)
        self.pid = os.getpid()  # the process whose bars it lifts

    def emit(self, record: logging.LogRecord) -> None:
        tqdm = sys.modules.get("tqdm")
        # A forked worker writes its line as it is: the bars are its parent's, and tqdm's lock is one for every
        # forked process, so a worker killed while holding it (Ctrl-C, a failed task) left the parent's log stuck.
        if tqdm is None or os.getpid() != self.pid:
            super().emit(record)
            return
        with tqdm.tqdm.external_write_mode(file=self.stream):
            super().emit(record)


def setup(verbose: int = 0, quiet: int = 0, service: bool = False, stream: TextIO | None = None) -> logging.Handler:
    """Send psfd's log to ``stream`` (stderr) at the level the options ask for; returns the handler.

    Replaces the handler of an earlier call, so tests and embedding programs can call it again.
    """
    stream = sys.stderr if stream is None else stream
    handler = Handler(stream)
    handler.set_name("psfd")
    journal = journal_stream(stream)
    handler.setFormatter(JournalFormatter("%(message)s") if journal else PlainFormatter(timestamps=service))
    logger = logging.getLogger("psfd")
    for old in [h for h in logger.handlers if h.get_name() == "psfd"]:
        logger.removeHandler(old)
    logger.addHandler(handler)
    logger.setLevel(level(verbose, quiet, service))
    logger.propagate = False  # one line per record, whatever the embedding program's root logger does
    # exifread says "File format not recognized." on its own logger for files psfd reports itself
    logging.getLogger("exifread").setLevel(logging.ERROR)
    return handler
