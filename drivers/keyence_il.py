"""Keyence IL-series displacement sensor through a DL-RS1A RS-232C unit.

Protocol (ASCII, commands and replies end CR LF, one command in flight):

- read ``SR,<id>,037`` -> ``SR,<id>,037,+01.234``; or ``M0`` -> ``M0,+01.234,+00.512,...``
  (one value per amplifier, in ID order);
- ``+99.999`` / ``-99.999`` beyond the range, ``+EE.EEE`` amplifier error, anything
  non-numeric invalid;
- zero-set: ``SW,<id>,001,0`` then ``SW,<id>,001,1`` (each echoed ``SW,<id>,001``), then poll
  ``SR,<id>,054`` -> ``...,0`` running, ``1`` done, ``2`` impossible;
- errors ``ER,<cmd>,<nn>`` (see :data:`ER_CODES`).
"""

from __future__ import annotations

import math
import re
import threading
import time

from drivers.base import DriverError, ReadingStatus, SensorReading
from drivers.serial_port import SerialLink

#: Meaning of the DL-RS1A error codes in ``ER,<cmd>,<nn>`` replies.
ER_CODES: dict[int, str] = {
    0: "invalid command",
    20: "command length error",
    21: "wrong number of parameters",
    22: "parameter out of range (also returned while the amplifier is starting up: wait and "
        "retry)",
    29: "communication error",
    65: "no amplifier with this ID",
    67: "read/write switch error (the item cannot be written)",
}
#: Error codes worth re-sending the same command for (within the retry budget).
RETRYABLE_ER = frozenset({29})
OUT_OF_RANGE_FIELDS = frozenset({"+99.999", "-99.999", "+FFFFFFF", "-FFFFFFF"})
AMPLIFIER_ERROR_FIELD = "+EE.EEE"
_NUMBER = re.compile(r"[+-]?\d{1,4}(\.\d{1,6})?")


class KeyenceError(DriverError):
    """The DL-RS1A answered ``ER,<cmd>,<nn>`` or refused an operation."""


def parse_value(field: str) -> SensorReading:
    """One measured-value field of an ``SR``/``M0`` reply -> :class:`SensorReading` (mm).

    ``+99.999``/``-99.999`` -> OUT_OF_RANGE; ``+EE.EEE`` and any non-numeric field -> INVALID
    (value None, the field kept in ``raw``). Never raises.
    """
    text = field.strip()
    if text in OUT_OF_RANGE_FIELDS:
        return SensorReading(ReadingStatus.OUT_OF_RANGE, None, text)
    if _NUMBER.fullmatch(text):
        return SensorReading(ReadingStatus.OK, float(text), text)
    return SensorReading(ReadingStatus.INVALID, None, text)


def describe_invalid(reading: SensorReading) -> str:
    """Operator text for an INVALID reading."""
    if reading.raw == AMPLIFIER_ERROR_FIELD:
        return "amplifier error (+EE.EEE): check the sensor head cable and the amplifier"
    return f"non-numeric value {reading.raw!r}"


def parse_error(line: str) -> tuple[str, int] | None:
    """``ER,<cmd>,<nn>`` -> (cmd, nn); None for any other line."""
    parts = line.strip().split(",")
    if len(parts) == 3 and parts[0] == "ER" and parts[2].isdigit():
        return parts[1], int(parts[2])
    return None


def error_message(cmd: str, code: int, port: str) -> str:
    meaning = ER_CODES.get(code, "unknown error code")
    return f"Keyence DL-RS1A on {port} refused {cmd}: ER {code:02d} {meaning}"


class KeyenceIL:
    """:class:`drivers.base.DisplacementSensor` for an IL sensor head on a DL-RS1A.

    ``amp_id`` is the amplifier ID (0 = the one next to the DL-RS1A); ``command`` is ``"SR"``
    (read one amplifier) or ``"M0"`` (read all, take this ID's field). ``timeout`` (s) is the
    wait per attempt (the unit answers within 500 ms), ``retries`` the re-sends after a
    timeout/garbled reply before :class:`~drivers.base.DeviceTimeout`/``DriverError``.
    """

    def __init__(self, port: str, *, baudrate: int = 9600, amp_id: int = 0,
                 timeout: float = 0.5, retries: int = 2, command: str = "SR",
                 zero_timeout: float = 5.0) -> None:
        if command not in ("SR", "M0"):
            raise DriverError(f"Keyence read command must be SR or M0, not {command!r}")
        if not (math.isfinite(zero_timeout) and zero_timeout > 0):
            raise DriverError("Keyence zero_timeout must be a finite number of seconds > 0")
        if not 0 <= amp_id <= 99:
            raise DriverError(f"Keyence amplifier ID must be 0..99, not {amp_id}")
        self.amp_id = amp_id
        self.command = command
        self.zero_timeout = zero_timeout
        self._link = SerialLink(port, baudrate, timeout=timeout, retries=retries,
                                eol="\r\n", device="Keyence DL-RS1A")
        self._lock = threading.Lock()

    @property
    def port(self) -> str:
        return self._link.port

    # -- protocol --------------------------------------------------------------------------
    def _query(self, cmd: str, prefix: str) -> str:
        """Send ``cmd``; return the reply starting with ``prefix`` (ER -> KeyenceError)."""
        name = cmd.split(",")[0]

        def accept(line: str) -> bool:
            return line.startswith(prefix) or parse_error(line) is not None

        for _attempt in range(self._link.retries + 1):
            reply = self._link.transact(cmd, accept, what=cmd)
            err = parse_error(reply)
            if err is None:
                return reply
            if err[1] not in RETRYABLE_ER:
                raise KeyenceError(error_message(name, err[1], self.port))
        raise KeyenceError(error_message(name, err[1], self.port) + " (persisting after "
                           f"{self._link.retries + 1} attempts)")

    def read(self) -> SensorReading:
        """One reading in mm, or an OUT_OF_RANGE / INVALID reading (never a made-up value)."""
        with self._lock:
            if self.command == "SR":
                head = f"SR,{self.amp_id:02d},037"
                reply = self._query(head, head + ",")
                return parse_value(reply[len(head) + 1:])
            reply = self._query("M0", "M0,")
            fields = reply.split(",")[1:]
            if self.amp_id >= len(fields):
                raise KeyenceError(f"Keyence DL-RS1A on {self.port}: M0 returned {len(fields)} "
                                   f"value(s), none for amplifier ID {self.amp_id:02d}")
            return parse_value(fields[self.amp_id])

    def zero(self) -> None:
        """Zero-set: ``SW,<id>,001,0``, ``SW,<id>,001,1``, then poll ``SR,<id>,054`` until 1."""
        ident = f"{self.amp_id:02d}"
        with self._lock:
            for value in (0, 1):
                self._query(f"SW,{ident},001,{value}", f"SW,{ident},001")
            head = f"SR,{ident},054"
            deadline = time.monotonic() + self.zero_timeout
            while True:
                state = self._query(head, head + ",")[len(head) + 1:].strip()
                if state == "1":
                    return
                if state == "2":
                    raise KeyenceError(f"Keyence amplifier {ident} on {self.port}: zero-set "
                                       "impossible (target out of range or amplifier busy); "
                                       "bring the target into range and retry")
                if state != "0":
                    raise KeyenceError(f"Keyence amplifier {ident} on {self.port}: unexpected "
                                       f"zero-set status {state!r}")
                if time.monotonic() > deadline:
                    raise KeyenceError(f"Keyence amplifier {ident} on {self.port}: zero-set "
                                       f"still running after {self.zero_timeout:g} s")
                time.sleep(0.02)

    def describe(self) -> str:
        """Connection summary stored with a session."""
        return (f"Keyence DL-RS1A on {self.port} {self._link.baudrate} 8N1, amplifier "
                f"{self.amp_id:02d}, read {self.command}")

    def reconnect(self, port: str | None = None) -> None:
        """Reopen the serial port (after :class:`~drivers.serial_port.PortLost`)."""
        with self._lock:
            self._link.reconnect(port)

    def close(self) -> None:
        self._link.close()

    def __enter__(self) -> KeyenceIL:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
