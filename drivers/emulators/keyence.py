"""Keyence DL-RS1A (IL-series amplifiers) emulator on a pty, byte for byte.

Understands ``SR,<id>,037`` (value), ``SR,<id>,054`` (zero-set status), ``M0`` (all values),
``SW,<id>,001,<0|1>`` (zero-set on the 0 -> 1 edge); replies end CR LF; errors are
``ER,<cmd>,<nn>`` with the real codes (00 command, 20 length, 21 parameter count,
22 parameter, 65 ID, 67 R/W). Values come from ``displacement()`` (mm, None = out of range)
minus the zero offset, formatted ``+01.234``; beyond +-99.999 (or None) -> ``+99.999``/``-99.999``.

Device faults for :meth:`~drivers.emulators.base.PtyEmulator.inject`, besides the transport
ones: ``er`` (reply ``ER,<cmd>,<code>``), ``stuck`` (value ``+99.999``), ``amp_error``
(``+EE.EEE``), ``zero_impossible`` (zero-set status 2).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

from drivers.emulators.base import PtyEmulator

Physics = Callable[[], float | None]
MAX_COMMAND = 32


def format_value(value: float | None) -> str:
    """Displacement (mm) -> the DL-RS1A field: ``+01.234``; None/beyond range -> ``+-99.999``."""
    if value is None or not math.isfinite(value):
        return "+99.999"
    if abs(value) >= 99.999:
        return "+99.999" if value > 0 else "-99.999"
    return f"{value:+07.3f}"


class KeyenceEmulator(PtyEmulator):
    """Emulated DL-RS1A with amplifiers ``amp_ids``; ``displacement`` gives the true value (mm).

    ``displacement`` is one callable for every amplifier or a mapping id -> callable.
    ``zero_polls`` is how many ``SR,<id>,054`` polls answer 0 (running) before 1 (done).
    """

    device = "Keyence DL-RS1A"

    def __init__(self, displacement: Physics | Mapping[int, Physics], *,
                 amp_ids: tuple[int, ...] = (0,), zero_polls: int = 1) -> None:
        super().__init__()
        self.amp_ids = tuple(amp_ids)
        self._physics = displacement
        self.zero_polls = zero_polls
        self.offsets = dict.fromkeys(self.amp_ids, 0.0)
        self._sw001 = dict.fromkeys(self.amp_ids, 0)
        self._zero_state = dict.fromkeys(self.amp_ids, 1)
        self._zero_wait = dict.fromkeys(self.amp_ids, 0)

    def true_value(self, amp_id: int) -> float | None:
        physics = self._physics[amp_id] if isinstance(self._physics, Mapping) else self._physics
        return physics()

    def _field(self, amp_id: int, line: str) -> str:
        fault = self.take_fault({"stuck", "amp_error"}, line)
        if fault is not None:
            return "+99.999" if fault.kind == "stuck" else "+EE.EEE"
        value = self.true_value(amp_id)
        return format_value(None if value is None else value - self.offsets[amp_id])

    def _ident(self, text: str) -> int | None:
        return int(text) if len(text) == 2 and text.isdigit() else None

    def handle_line(self, line: str) -> None:
        parts = line.split(",")
        cmd = parts[0]
        if len(line) > MAX_COMMAND:
            return self.reply(line, f"ER,{cmd[:2]},20")
        fault = self.take_fault({"er"}, line)
        if fault is not None:
            return self.reply(line, f"ER,{cmd},{fault.code:02d}")
        if cmd == "M0":
            if len(parts) != 1:
                return self.reply(line, "ER,M0,21")
            return self.reply(line, "M0," + ",".join(self._field(i, line) for i in self.amp_ids))
        if cmd not in ("SR", "SW"):
            return self.reply(line, f"ER,{cmd},00")
        if len(parts) != (3 if cmd == "SR" else 4):
            return self.reply(line, f"ER,{cmd},21")
        ident = self._ident(parts[1])
        if ident is None:
            return self.reply(line, f"ER,{cmd},22")
        if ident not in self.amp_ids:
            return self.reply(line, f"ER,{cmd},65")
        head = f"{cmd},{parts[1]},{parts[2]}"
        if cmd == "SR":
            if parts[2] == "037":
                return self.reply(line, f"{head},{self._field(ident, line)}")
            if parts[2] == "054":
                return self.reply(line, f"{head},{self._zero_status(ident)}")
            return self.reply(line, f"ER,{cmd},22")
        if parts[2] == "037":
            return self.reply(line, "ER,SW,67")
        if parts[2] != "001" or parts[3] not in ("0", "1"):
            return self.reply(line, "ER,SW,22")
        value = int(parts[3])
        if value == 1 and self._sw001[ident] == 0:
            self._start_zero(ident, line)
        self._sw001[ident] = value
        return self.reply(line, head)

    def _start_zero(self, ident: int, line: str) -> None:
        value = self.true_value(ident)
        if self.take_fault({"zero_impossible"}, line) is not None or value is None:
            self._zero_state[ident] = 2
        else:
            self.offsets[ident] = value
            self._zero_state[ident] = 1
        self._zero_wait[ident] = self.zero_polls

    def _zero_status(self, ident: int) -> int:
        if self._zero_wait[ident] > 0:
            self._zero_wait[ident] -= 1
            return 0
        return self._zero_state[ident]
