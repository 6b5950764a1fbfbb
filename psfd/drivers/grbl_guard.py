"""Stops a GRBL carriage when the process driving it dies without closing the rail (SIGKILL, the OOM killer).

`psfd.drivers.grbl.GrblRail` starts it before the first line that can move the carriage, in an interpreter
without site-packages (``python -I -S``), importing this module from its folder (so its bytecode is cached)
and nothing of psfd, so that it starts in a few tens of milliseconds (its imports: ~4 ms);
``python -I -S grbl_guard.py PORT_FD OWNER_PIDFD TIMEOUT STOP [NOTES_FD]`` does the same.

``PORT_FD`` is the owner's serial port (the same open file description: the owner's flock stays on it while
this process lives), ``OWNER_PIDFD`` a pidfd of the owner (``os.pidfd_open``), readable once the owner has
exited, whoever else still holds its pipes or descriptors (the forked estimation workers do), ``TIMEOUT``
the seconds one exchange may take and ``STOP`` the longest deceleration (from ``$110``/``$120``; 30 s when
the owner has not read them yet), ``NOTES_FD`` the read end of a pipe on which the owner writes `HOMING` before
``$H`` and `HOMING_DONE` once the cycle has ended (read as it comes, so that it never fills). This process
runs in its own session and ignores SIGINT, SIGTERM, SIGHUP, SIGQUIT and SIGABRT: a terminal's Ctrl-C,
``systemctl stop`` and the service watchdog are for the owner, which stops the carriage itself (or dies, and
this process does it).

While the owner lives this process never reads or writes the port (the owner's replies are the owner's), so a
clean close of the rail simply kills it (SIGKILL).

When the owner has died with the rail open it does what the owner's own stop does (GRBL 1.1, gnea/grbl
doc/markdown/commands.md and interface.md), and nothing more when the carriage stands:

- ``?``: one status report (Idle: a few more over 0.15 s, as a move line the owner sent just before it died
  may not have started yet). Idle, Alarm, Sleep, Check, Door:1-3 (the door holds it): nothing more is sent.
- Run or Jog: ``!`` (a feed hold: a controlled deceleration; a jog is cancelled by it), then ``?`` until
  ``Hold:0`` or Idle, then Ctrl-X (0x18) so that the rest of the move is dropped; after a completed hold the
  reset keeps the position, while a reset in motion or in ``Hold:1`` would throw ALARM:3 and lose it.
- ``Hold:1``/``Hold:0``/``Door:0`` (the owner died in its own stop, or a move waits to be resumed): the same
  wait, then the reset, so that no cycle start resumes the move unattended.
- The owner died in a homing cycle (its last note `HOMING`): Ctrl-X at once, nothing else. GRBL answers no ``?``
  during the cycle (a ``?`` asked in it is answered once it ends) and drops a feed hold sent in it: only a reset
  stops it (ALARM:6), as the owner's interrupted ``$H`` does. A cycle that has just ended keeps its position
  through the reset (Idle).
- Home reported (a controller homing that the owner did not note, or a firmware that reports during the
  cycle): the same reset.
- No answer (GRBL answers no ``?`` during a homing cycle or after a critical alarm): the feed hold anyway,
  then the reset once the longest deceleration is over.
"""

import _signal  # the C module under `signal`, whose enum wrapping would add ~15 ms to the start (measured)
import os
import select
import sys
import termios
import time

# No `re` either (~15 ms of imports): status reports and banners are simple enough to split by hand.
SOFT_RESET = b"\x18"
FEED_HOLD = b"!"
STATUS = b"?"
BANNERS = ("Grbl ", "GrblHAL ", "grblHAL ")
STANDING = ("Idle", "Alarm", "Sleep", "Check")
IDLE_WATCH = 0.15  # s an Idle controller is watched for a move line the owner sent as it died
HOMING = b"H"  # the owner's notes: a homing cycle runs,
HOMING_DONE = b"-"  # and has ended


class Port:
    """Lines from a GRBL controller on a raw serial descriptor shared with the (dead) owner."""

    def __init__(self, fd: int) -> None:
        self.fd = fd
        self.buffer = b""
        self.poll = select.poll()
        self.poll.register(fd, select.POLLIN)

    def write(self, data: bytes) -> None:
        os.write(self.fd, data)

    def line(self, deadline: float) -> str | None:
        """The next non-empty line, or None at the deadline."""
        while b"\n" not in self.buffer:
            left = deadline - time.monotonic()
            if left <= 0 or not self.poll.poll(int(left * 1000) + 1):
                return None
            try:
                chunk = os.read(self.fd, 4096)
            except BlockingIOError:
                continue
            if not chunk:
                raise OSError("the port is gone")
            self.buffer += chunk
        raw, self.buffer = self.buffer.split(b"\n", 1)
        return raw.decode("ascii", "replace").strip() or self.line(deadline)

    def status(self, seconds: float) -> tuple[str, str] | None:
        """``?`` and its report: (state name such as ``Hold:0``, the report), or None without an answer."""
        self.write(STATUS)
        deadline = time.monotonic() + seconds
        while (line := self.line(deadline)) is not None:
            if line.startswith("<"):  # <Hold:0|MPos:..> (GRBL 1.1), <Idle,MPos:..> (0.9)
                return line[1:].split("|")[0].split(",")[0].rstrip(">"), line
        return None

    def reset(self, seconds: float) -> bool:
        """Ctrl-X and the banner (twice: a reset can be lost in the delay that follows an alarm message)."""
        for _ in range(2):
            self.write(SOFT_RESET)
            deadline = time.monotonic() + seconds
            while (line := self.line(deadline)) is not None:
                if line.startswith(BANNERS) and "help]" in line:
                    return True
        return False


def stop_carriage(port: "Port", stop: float, timeout: float) -> str | None:
    """What the owner's `GrblRail._halt` does, for a controller the owner left; None when it stood."""
    termios.tcflush(port.fd, termios.TCIFLUSH)  # replies to the owner's last requests: stale now
    found = port.status(timeout)
    # The owner may have died just after writing a move line: its bytes came before our '?', but GRBL may
    # report before it parses the line (the report is a realtime flag, served first). It starts the move
    # within milliseconds: a few more reports over IDLE_WATCH seconds tell.
    watch_until = time.monotonic() + IDLE_WATCH
    while found is not None and found[0] == "Idle" and time.monotonic() < watch_until:
        time.sleep(0.03)
        found = port.status(timeout) or found
    name = found[0] if found else None
    state = name.split(":")[0] if name else None
    if state in STANDING or name in ("Door:1", "Door:2", "Door:3"):
        return None
    if state == "Home":
        return stop_homing(port, timeout)
    if state != "Hold" and name != "Door:0":
        port.write(FEED_HOLD)
    started = time.monotonic()
    while True:
        status = port.status(min(timeout, 0.5))
        if status is not None and (status[0].split(":")[0] in ("Idle", "Alarm") or status[0] in ("Hold:0", "Door:0",
                                                                                                   "Door:1")):
            break
        waited = time.monotonic() - started
        # Silent: reset once the longest deceleration is over. Answering but still decelerating (slower than
        # its settings say): wait on, a reset now would lose the position.
        if waited > stop + timeout and (status is None or waited > 4 * stop + 3 * timeout):
            break
        if status is not None:
            time.sleep(0.05)
    before = f"{name} at {_where(found)}" if found else "no answer to '?'"
    if status is not None and status[0].startswith("Alarm"):
        return f"{before}: feed hold; the controller stopped in ALARM at {_where(status)}"
    reset = port.reset(timeout)
    after = port.status(timeout) if reset else None
    where = f"stopped at {_where(after)}" if after else "reset sent, no answer after it: position unknown"
    return f"{before}: feed hold, reset once standing ({status[0] if status else 'silent'}); {where}"


def stop_homing(port: "Port", timeout: float) -> str:
    """The owner died in a homing cycle: reset (ALARM:6); the cycle would ignore a feed hold."""
    termios.tcflush(port.fd, termios.TCIFLUSH)
    if not port.reset(timeout):
        return "homing cycle: reset sent, no banner after it"
    after = port.status(timeout)
    return f"homing cycle stopped by a reset: {after[0] if after else 'no answer after it'}"


def _where(found: tuple[str, str] | None) -> str:
    for field in found[1].strip("<>").replace(",MPos", "|MPos").replace(",WPos", "|WPos").split("|") if found else ():
        if field.startswith(("MPos:", "WPos:")):
            return field
    return "an unknown position"


def watch(port_fd: int, owner: int, timeout: float, stop: float, notes: int | None = None) -> int:
    """Wait for the owner's exit, then stop the carriage if it moves."""
    pid = os.getppid()  # the owner started this process
    homing = _wait_for(owner, notes) == HOMING
    try:
        port = Port(port_fd)
        done = stop_homing(port, timeout) if homing else stop_carriage(port, stop, timeout)
    except (OSError, termios.error) as exc:  # the cable was pulled, or the port closed under us (tcflush: EIO)
        done = f"the port failed ({exc}): the carriage may still be moving"
    if done:
        sys.stderr.write(f"psfd: the process driving the rail (pid {pid}) died with the rail open; {done}\n")
    return 0


def _wait_for(owner: int, notes: int | None) -> bytes:
    """Wait for the owner's exit, reading its notes meanwhile; its last note."""
    poll = select.poll()
    poll.register(owner, select.POLLIN)
    if notes is not None:
        os.set_blocking(notes, False)
        poll.register(notes, select.POLLIN)
    last = b""
    while True:
        ready = [fd for fd, _ in poll.poll()]
        if notes is not None:  # what the owner wrote before it died is read too
            last, still_open = _read_notes(notes, last)
            if not still_open:
                poll.unregister(notes)
                notes = None
        if owner in ready:
            return last


def _read_notes(notes: int, last: bytes) -> tuple[bytes, bool]:
    """The last note among those waiting (or ``last``), and whether a writer still holds the pipe."""
    while True:
        try:
            chunk = os.read(notes, 4096)
        except BlockingIOError:
            return last, True
        if not chunk:
            return last, False
        last = chunk[-1:]


def main(argv: list[str]) -> int:
    # A terminal's Ctrl-C, `systemctl stop` (SIGTERM to every process of the unit) and the service watchdog
    # (SIGABRT) are meant for the owner: it stops the carriage itself, or dies and leaves it to this process.
    for sig in (_signal.SIGINT, _signal.SIGTERM, _signal.SIGHUP, _signal.SIGQUIT, _signal.SIGABRT):
        _signal.signal(sig, _signal.SIG_IGN)
    notes = int(argv[5]) if len(argv) > 5 else None
    return watch(int(argv[1]), int(argv[2]), float(argv[3]), float(argv[4]), notes)


if __name__ == "__main__":
    sys.exit(main(sys.argv))
