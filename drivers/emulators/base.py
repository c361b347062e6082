"""Pseudo-terminal plumbing and fault injection shared by the protocol emulators.

A :class:`PtyEmulator` owns both ends of ``pty.openpty()`` (raw mode, so CR LF pass
unchanged); a driver opens :attr:`PtyEmulator.path` with pyserial. A background thread reads
the master side, splits lines at CR or LF (bytes in :attr:`PtyEmulator.realtime` are handled
at once, even mid-line), and calls :meth:`PtyEmulator.handle_line`. Replies go through
:meth:`PtyEmulator.reply`, where transport faults apply:

=========== ==============================================================================
``silent``   no reply at all (the driver times out)
``garbage``  the reply is replaced by ``data`` (default: binary junk ending CR LF)
``noise``    ``data`` is sent before the real reply
``truncate`` only the first half of the reply is sent, without terminator
``delay``    the reply is sent ``seconds`` later
``vanish``   the port disappears (both pty fds closed) instead of replying
=========== ==============================================================================

Device faults (``er``, ``stuck``, ``error``, ``alarm`` ...) are documented by each emulator.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import pty
import select
import threading
import time
import traceback
import tty
from dataclasses import dataclass

TRANSPORT_FAULTS = frozenset({"silent", "garbage", "noise", "truncate", "delay", "vanish"})
DEFAULT_GARBAGE = b"\xff\xfe#%&\x00garbage\x7f\r\n"
MAX_LINE = 1024


@dataclass
class Fault:
    """One injected fault: affects the next ``count`` matching events (``count=-1``: forever).

    ``match`` restricts it to received lines starting with that text (``None``: any line);
    the first ``skip`` matching events pass unharmed; ``code``, ``data``, ``seconds`` and
    ``stall`` parametrise the kinds that use them.
    """

    kind: str
    count: int = 1
    match: str | None = None
    code: int = 0
    data: bytes = b""
    seconds: float = 0.0
    stall: bool = False
    skip: int = 0
    hits: int = 0


class PtyEmulator:
    """Base class: serve a line protocol on a pty in a background thread.

    Subclasses implement :meth:`handle_line` (and optionally :meth:`handle_realtime`,
    :meth:`tick`); all three run on the emulator thread with :attr:`lock` held.
    """

    device = "device"
    eol = b"\r\n"
    realtime: bytes = b""
    tick_s = 0.005

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self._faults: list[Fault] = []
        self._log: list[tuple[float, str]] = []
        self._raw = bytearray()
        self.errors: list[str] = []  # tracebacks of handler failures (tests assert it is empty)
        self._scheduled: list[tuple[float, bytes]] = []
        self._partial = bytearray()
        self._stop = threading.Event()
        self._vanish_req = threading.Event()
        self._gone = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = self._slave = -1
        self.path = ""
        self._open_pty()

    # -- life cycle ------------------------------------------------------------------------
    def _open_pty(self) -> None:
        master, slave = pty.openpty()
        tty.setraw(master)
        tty.setraw(slave)
        flags = fcntl.fcntl(master, fcntl.F_GETFL)
        fcntl.fcntl(master, fcntl.F_SETFL, flags | os.O_NONBLOCK)
        self._master, self._slave = master, slave
        self.path = os.ttyname(slave)
        self._partial.clear()
        self._scheduled.clear()
        self._gone.clear()

    def start(self) -> PtyEmulator:
        """Start serving in a daemon thread; returns self."""
        if self._thread is None:
            self._thread = threading.Thread(target=self._serve, name=f"{self.device} emulator",
                                            daemon=True)
            self._thread.start()
        return self

    def close(self) -> None:
        """Stop the thread and close the pty (idempotent)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        with self.lock:
            self._close_fds()

    def __enter__(self) -> PtyEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self._master = self._slave = -1
        self._gone.set()

    def vanish(self, timeout: float = 2.0) -> None:
        """Make the port disappear as if unplugged (the driver's next I/O fails)."""
        if self._thread is None or not self._thread.is_alive():
            with self.lock:
                self._close_fds()
            return
        self._vanish_req.set()
        self._gone.wait(timeout)
        with self.lock:  # the close itself has finished
            pass

    def replug(self) -> str:
        """After :meth:`vanish`: serve again on a new pty (state kept); returns the new path."""
        with self.lock:
            if not self._gone.is_set():
                raise RuntimeError("replug() needs the port to have vanished first")
            self._vanish_req.clear()
            self._open_pty()
            return self.path

    @property
    def gone(self) -> bool:
        """True once the port has vanished (waits for a close in progress to finish)."""
        with self.lock:
            return self._gone.is_set()

    # -- faults and log --------------------------------------------------------------------
    def inject(self, kind: str, count: int = 1, *, match: str | None = None, code: int = 0,
               data: bytes = b"", seconds: float = 0.0, stall: bool = False,
               skip: int = 0) -> Fault:
        """Queue a fault (see the module and emulator docs for the kinds); returns it."""
        fault = Fault(kind, count, match, code, data, seconds, stall, skip)
        with self.lock:
            self._faults.append(fault)
        return fault

    def clear_faults(self) -> None:
        with self.lock:
            self._faults.clear()

    def take_fault(self, kinds: frozenset[str] | set[str], line: str) -> Fault | None:
        """Consume one use of the first active fault of one of ``kinds`` matching ``line``."""
        for fault in self._faults:
            if fault.kind in kinds and (fault.match is None or line.startswith(fault.match)):
                if fault.skip > 0:
                    fault.skip -= 1
                    continue
                fault.hits += 1
                if fault.count > 0:
                    fault.count -= 1
                    if fault.count == 0:
                        self._faults.remove(fault)
                return fault
        return None

    @property
    def received(self) -> list[str]:
        """Every line (without terminator) and real-time byte received, in order."""
        with self.lock:
            return [text for _, text in self._log]

    @property
    def received_bytes(self) -> bytes:
        """Every byte received, exactly as sent by the driver."""
        with self.lock:
            return bytes(self._raw)

    @property
    def log(self) -> list[tuple[float, str]]:
        """``(time.monotonic(), text)`` for every line and real-time byte received."""
        with self.lock:
            return list(self._log)

    # -- output ----------------------------------------------------------------------------
    def send(self, data: bytes) -> None:
        """Write raw bytes to the driver (dropped when the port is gone or full)."""
        if self._master < 0 or not data:
            return
        with contextlib.suppress(OSError):
            os.write(self._master, data)

    def reply(self, line: str, text: str) -> None:
        """Send ``text`` + :attr:`eol` as the reply to ``line``, applying transport faults."""
        payload = text.encode("ascii") + self.eol
        fault = self.take_fault(TRANSPORT_FAULTS, line)
        if fault is None:
            self.send(payload)
        elif fault.kind == "garbage":
            self.send(fault.data or DEFAULT_GARBAGE)
        elif fault.kind == "noise":
            self.send((fault.data or DEFAULT_GARBAGE) + payload)
        elif fault.kind == "truncate":
            self.send(payload[:max(1, len(text) // 2)])
        elif fault.kind == "delay":
            self._scheduled.append((time.monotonic() + fault.seconds, payload))
        elif fault.kind == "vanish":
            self._close_fds()
        # "silent": nothing

    # -- subclass hooks --------------------------------------------------------------------
    def handle_line(self, line: str) -> None:
        raise NotImplementedError

    def handle_realtime(self, byte: int) -> None:
        """A byte of :attr:`realtime` arrived."""

    def tick(self, now: float) -> None:
        """Called every loop turn (at least every :attr:`tick_s`)."""

    # -- thread ----------------------------------------------------------------------------
    def _feed(self, data: bytes) -> None:
        self._raw += data
        for byte in data:
            if byte in self.realtime:
                self._log.append((time.monotonic(), chr(byte)))
                self.handle_realtime(byte)
            elif byte in (10, 13):
                if self._partial:
                    line = self._partial.decode("ascii", errors="replace")
                    self._partial.clear()
                    self._log.append((time.monotonic(), line))
                    self.handle_line(line)
            elif len(self._partial) < MAX_LINE:
                self._partial.append(byte)
            if self._master < 0:  # a fault closed the port
                return

    def _serve(self) -> None:
        while not self._stop.is_set():
            with self.lock:
                if self._vanish_req.is_set() and not self._gone.is_set():
                    self._close_fds()
                fd = self._master
            if fd < 0:
                time.sleep(self.tick_s)
                continue
            try:
                ready, _, _ = select.select([fd], [], [], self.tick_s)
            except (OSError, ValueError):
                continue
            with self.lock:
                if fd != self._master:
                    continue
                if ready:
                    try:
                        data = os.read(fd, 4096)
                    except (BlockingIOError, InterruptedError):
                        data = b""
                    except OSError:
                        data = b""
                    try:
                        self._feed(data)
                    except Exception:  # an emulator bug must not kill the port silently
                        self.errors.append(traceback.format_exc())
                        traceback.print_exc()
                now = time.monotonic()
                due = [p for t, p in self._scheduled if t <= now]
                self._scheduled = [(t, p) for t, p in self._scheduled if t > now]
                for payload in due:
                    self.send(payload)
                if self._master >= 0:
                    self.tick(now)
