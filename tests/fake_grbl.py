"""A small fake GRBL 1.1 firmware on the master side of a pseudo-terminal.

The driver under test opens the slave side with real pyserial. The fake
answers the part of the protocol the driver uses (soft reset and banner,
``$H``, ``$X``, ``G90 G21 G1 ... F..``, the ``?`` real-time status report)
and simulates motion at a fixed speed. Faults are switched on by attributes:
``errors`` (line prefix -> error code), ``alarm_after`` (seconds into a move,
then ALARM:N), ``garbage`` (noise before every reply), ``silent`` (no replies), ``mute_lines``
(status reports only: command lines get no ``ok``),
``vanish_after`` (seconds into a move, then the port disappears).
"""

from __future__ import annotations

import os
import re
import select
import threading
import time

BANNER = b"\r\nGrbl 1.1h ['$' for help]\r\n"


class FakeGrbl:
    def __init__(self, speed: float = 500.0, homing_time: float = 0.05) -> None:
        self.master, self._slave = os.openpty()
        self.port = os.ttyname(self._slave)
        self.speed = speed  # mm/s
        self.homing_time = homing_time
        self.homing_enabled = True
        self.errors: dict[str, int] = {}
        self.alarm_after: tuple[float, int] | None = None
        self.vanish_after: float | None = None
        self.garbage = False
        self.silent = False
        self.mute_lines = False
        self.lines: list[str] = []  # every line received, for assertions
        self.state = "Idle"
        self._pos = [0.0, 0.0, 0.0]
        self._move: tuple[list[float], list[float], float, float] | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self.vanished = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ control

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._close_fds()

    def _close_fds(self) -> None:
        # Closing the master is what a USB adapter being pulled looks like to the driver.
        for name in ("master", "_slave"):
            fd = getattr(self, name)
            if fd >= 0:
                setattr(self, name, -1)
                try:
                    os.close(fd)
                except OSError:
                    pass

    def position(self) -> list[float]:
        with self._lock:
            return self._current()

    # ------------------------------------------------------------------ firmware loop

    def _run(self) -> None:
        buffer = b""
        while not self._stop.is_set() and not self.vanished:
            self._tick()
            try:
                ready, _, _ = select.select([self.master], [], [], 0.01)
                data = os.read(self.master, 1024) if ready else b""
            except (OSError, ValueError):
                return
            if not ready:
                continue
            for byte in data:
                if byte == 0x3F:  # '?' real-time status
                    self._send(self._status())
                elif byte == 0x18:  # Ctrl-X soft reset
                    with self._lock:
                        if self._move is not None:
                            self._pos, self._move, self.state = self._current(), None, "Alarm"
                    buffer = b""
                    self._send(BANNER.decode())
                elif byte in (0x0A, 0x0D):
                    if buffer:
                        self._line(buffer.decode("ascii", "replace").strip())
                    buffer = b""
                else:
                    buffer += bytes([byte])

    def _tick(self) -> None:
        """Advance the simulated machine: finish moves, fire scheduled faults."""
        with self._lock:
            if self._move is None:
                return
            elapsed = time.monotonic() - self._move[2]
            if self.vanish_after is not None and elapsed >= self.vanish_after:
                self.vanished = True
                self._close_fds()
                return
            if self.alarm_after is not None and elapsed >= self.alarm_after[0]:
                self._pos, self._move, self.state = self._current(), None, "Alarm"
                code = self.alarm_after[1]
                self.alarm_after = None
                self._send(f"ALARM:{code}\r\n")
                return
            if elapsed >= self._move[3]:
                self._pos, self._move, self.state = list(self._move[1]), None, "Idle"

    def _line(self, line: str) -> None:
        self.lines.append(line)
        if self.mute_lines:
            return
        for prefix, code in self.errors.items():
            if line.startswith(prefix):
                self._send(f"error:{code}\r\n")
                return
        if line == "$H":
            if not self.homing_enabled:
                self._send("error:5\r\n")
                return
            self.state = "Home"
            time.sleep(self.homing_time)
            with self._lock:
                self._pos, self.state = [0.0, 0.0, 0.0], "Idle"
            self._send("ok\r\n")
        elif line == "$X":
            self.state = "Idle"
            self._send("ok\r\n")
        elif line.startswith("G"):
            if self.state == "Alarm":
                self._send("error:9\r\n")
                return
            words = dict(re.findall(r"([XYZF])(-?[\d.]+)", line))
            with self._lock:
                start = self._current()
                end = list(start)
                for i, axis in enumerate("XYZ"):
                    if axis in words:
                        end[i] = float(words[axis])
                distance = max(abs(a - b) for a, b in zip(start, end))
                self._move = (start, end, time.monotonic(), distance / self.speed)
                self.state = "Run"
            self._send("ok\r\n")
        else:
            self._send("error:20\r\n")

    def _current(self) -> list[float]:
        if self._move is None:
            return list(self._pos)
        start, end, t0, duration = self._move
        f = min(1.0, (time.monotonic() - t0) / duration) if duration > 0 else 1.0
        return [a + f * (b - a) for a, b in zip(start, end)]

    def _status(self) -> str:
        with self._lock:
            x, y, z = self._current()
            state = self.state if self._move is None else "Run"
        return f"<{state}|MPos:{x:.3f},{y:.3f},{z:.3f}|FS:0,0>\r\n"

    def _send(self, text: str) -> None:
        if self.silent or self.vanished:
            return
        data = text.encode()
        if self.garbage:
            data = b"\xff\xfe\x00#~\x07noise\r\n" + data
        try:
            os.write(self.master, data)
        except OSError:
            pass
