"""A line-oriented serial link shared by the serial drivers (pyserial underneath).

One command in flight: :meth:`SerialLink.transact` and any multi-line exchange hold
:attr:`SerialLink.lock` (re-entrant). :meth:`SerialLink.write_now` bypasses the lock for
real-time bytes (e.g. GRBL ``!``) that must reach the device while a command waits.
A vanished port (USB adapter unplugged, emulator gone) raises :class:`PortLost`; the next
call reopens the same port name (a re-plugged adapter, e.g. a ``/dev/serial/by-id`` link), and
:meth:`SerialLink.reconnect` opens it, or another name, explicitly.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections.abc import Callable

from drivers.base import DeviceTimeout, DriverError

#: Granularity of blocking reads (s); bounds how late a deadline or a stop request is seen.
POLL_S = 0.02


class PortLost(DriverError):
    """The serial port disappeared or failed (unplugged cable/adapter); reconnect to continue."""


class SerialLink:
    """An open serial port (8N1) that sends and receives text lines.

    ``eol`` terminates every line sent; received lines end at LF (a trailing CR is stripped).
    ``timeout`` is the default wait for one reply line and ``retries`` the default number of
    re-sends after a timeout or an unusable reply (so ``retries + 1`` attempts in all).
    """

    def __init__(self, port: str, baudrate: int, *, timeout: float = 0.5, retries: int = 2,
                 eol: str = "\r\n", device: str = "device") -> None:
        if not (math.isfinite(timeout) and timeout > 0) or retries < 0:
            raise DriverError(f"{device}: timeout must be a finite number of seconds > 0 and "
                              "retries >= 0")
        self.port = port
        self.baudrate = int(baudrate)
        self.timeout = float(timeout)
        self.retries = int(retries)
        self.eol = eol
        self.device = device
        self.lock = threading.RLock()
        self._buf = bytearray()
        self._ser = None
        self._closed = False
        self._open()

    # -- port life cycle -------------------------------------------------------------------
    def _open(self) -> None:
        import serial  # pyserial

        try:
            self._ser = serial.Serial(self.port, self.baudrate, bytesize=serial.EIGHTBITS,
                                      parity=serial.PARITY_NONE, stopbits=serial.STOPBITS_ONE,
                                      timeout=POLL_S, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise PortLost(f"cannot open {self.device} port {self.port!r}: {_short(exc)}; "
                           "check the cable, the port name and that no other program uses "
                           "it") from exc
        self._buf.clear()
        self._closed = False

    def close(self) -> None:
        """Close the port (idempotent); it stays closed until :meth:`reconnect`."""
        self._closed = True
        self._release()

    def _release(self) -> None:
        ser, self._ser = self._ser, None
        if ser is not None:
            with contextlib.suppress(Exception):  # already gone: nothing left to release
                ser.close()

    def reconnect(self, port: str | None = None) -> None:
        """Close and reopen the port (optionally under a new name, e.g. a re-plugged adapter)."""
        with self.lock:
            self.close()
            if port is not None:
                self.port = port
            self._open()

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    def _lost(self, exc: BaseException) -> PortLost:
        self._release()
        return PortLost(f"{self.device} port {self.port} was lost ({_short(exc)}); the cable or "
                        "adapter was probably unplugged: reconnect it and resume")

    def _port(self):
        """The open port; after a loss (not a :meth:`close`) it is reopened once per call."""
        if self._ser is None:
            if self._closed:
                raise PortLost(f"{self.device} port {self.port} is closed")
            try:
                self._open()
            except PortLost as exc:
                raise PortLost(f"{self.device} port {self.port} is still missing; plug the "
                               "device back in (same port name) and resume") from exc
        return self._ser

    # -- raw I/O ---------------------------------------------------------------------------
    def write(self, data: bytes) -> None:
        """Write bytes (caller holds the lock for a command/reply exchange)."""
        try:
            self._port().write(data)
            self._port().flush()
        except PortLost:
            raise
        except Exception as exc:  # SerialException, OSError, SerialTimeoutException
            raise self._lost(exc) from exc

    def write_now(self, data: bytes) -> None:
        """Write real-time bytes at once, without waiting for the command in flight."""
        self.write(data)

    def send_line(self, line: str) -> None:
        self.write((line + self.eol).encode("ascii", errors="replace"))

    def discard_input(self) -> bytes:
        """Drop and return whatever was received and not yet read (stale or late replies)."""
        with self.lock:
            ser = self._port()
            stale = bytes(self._buf)
            self._buf.clear()
            try:
                n = ser.in_waiting
                if n:
                    stale += ser.read(n)
            except Exception as exc:
                raise self._lost(exc) from exc
            return stale

    def read_line(self, timeout: float | None = None,
                  abort: Callable[[], bool] | None = None) -> str | None:
        """Next received line without its terminator, or None when ``timeout`` s pass first.

        Undecodable bytes become U+FFFD so a garbled line is still returned (and rejected by
        the caller's parser). ``abort`` is polled every :data:`POLL_S`; when it returns True the
        read gives up and returns None.
        """
        deadline = time.monotonic() + (self.timeout if timeout is None else timeout)
        while True:
            nl = self._buf.find(b"\n")
            if nl >= 0:
                raw = bytes(self._buf[:nl])
                del self._buf[:nl + 1]
                return raw.decode("ascii", errors="replace").strip("\r")
            if time.monotonic() >= deadline or (abort is not None and abort()):
                return None
            ser = self._port()
            try:
                chunk = ser.read(max(1, ser.in_waiting))
            except Exception as exc:
                raise self._lost(exc) from exc
            self._buf += chunk

    def transact(self, line: str | bytes, accept: Callable[[str], bool], *,
                 timeout: float | None = None, retries: int | None = None,
                 what: str | None = None) -> str:
        """Send ``line`` (+ :attr:`eol`; bytes are sent as they are), return the first reply
        line for which ``accept`` is true.

        Other lines are skipped. When no accepted line arrives within ``timeout`` the stale
        input is dropped and the line re-sent, at most ``retries`` times; then
        :class:`DeviceTimeout` (nothing at all received) or :class:`DriverError` (only
        unusable lines received) is raised.
        """
        timeout = self.timeout if timeout is None else timeout
        retries = self.retries if retries is None else retries
        what = what or (line if isinstance(line, str) else repr(line.decode("ascii", "replace")))
        seen: list[str] = []
        with self.lock:
            for _attempt in range(retries + 1):
                self.discard_input()
                if isinstance(line, bytes):
                    self.write(line)
                else:
                    self.send_line(line)
                deadline = time.monotonic() + timeout
                while (reply := self.read_line(max(0.0, deadline - time.monotonic()))) is not None:
                    if accept(reply):
                        return reply
                    if reply:
                        seen.append(reply)
            stale = self.discard_input()
            if stale.strip():
                seen.append(stale.decode("ascii", errors="replace"))
        attempts = retries + 1
        if not seen:
            raise DeviceTimeout(f"{self.device} on {self.port} did not answer {what} within "
                                f"{timeout:g} s ({attempts} attempts); check the cable, the "
                                f"baud rate ({self.baudrate}) and that the device is powered")
        raise DriverError(f"{self.device} on {self.port} sent unusable replies to {what} "
                          f"({attempts} attempts, last {seen[-1][:40]!r}); check the baud "
                          f"rate ({self.baudrate}), the cable and electrical noise")


def _short(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0][:160]
