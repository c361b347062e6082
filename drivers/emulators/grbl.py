"""GRBL 1.1 emulator (axes X Y Z and A in degrees) on a pty, byte for byte.

Lines end LF (CR accepted); replies ``ok`` / ``error:N``; ``ALARM:N`` pushed on an alarm.
Real-time bytes act at once, even mid-line: ``?`` status report
``<Idle|MPos:x,y,z,a|FS:f,0|WCO:x,y,z,a>`` (``WPos`` instead with ``report="wpos"``; ``WCO`` on
the first report and every 10th), ``!`` feed hold (``Hold:0``), ``~`` resume, ``0x18`` soft reset
(banner; alarm 3 if reset while running). G-code: ``G0 G1 G4 G21 G90 G91``, words
``X Y Z A F P``; ``G4 P0``'s ``ok`` is sent when the motion queue is empty; ``$X`` unlocks.

Motion: the machine position (``position`` in work coordinates, ``machine_position``)
moves linearly to each target in ``move_time(distance)`` seconds (0 = instantly).

Device faults, besides the transport ones: ``error`` (reply ``error:<code>``), ``alarm``
(``ALARM:<code>``, motion stopped, G-code locked until ``$X``/reset), ``early_idle`` (the next
motion reports ``Idle`` and its ``G4 P0`` ``ok`` at once although the axes take ``seconds``
more to arrive; with ``stall=True`` they stop half-way and never arrive).
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from dataclasses import dataclass

from drivers.emulators.base import PtyEmulator

Vec = tuple[float, float, float, float]
AXES = "XYZA"
BANNER = "\r\nGrbl 1.1h ['$' for help]"
_WORD = re.compile(r"([A-Z])([-+]?(?:\d+\.?\d*|\.\d+))")


@dataclass
class _Segment:
    start: Vec
    end: Vec
    t0: float
    duration: float
    held_at: float | None = None  # elapsed time when held

    def at(self, now: float) -> Vec:
        elapsed = self.held_at if self.held_at is not None else now - self.t0
        frac = 1.0 if self.duration <= 0 else min(1.0, max(0.0, elapsed / self.duration))
        return tuple(s + frac * (e - s) for s, e in zip(self.start, self.end, strict=True))

    def done(self, now: float) -> bool:
        return self.held_at is None and now - self.t0 >= self.duration


class GrblEmulator(PtyEmulator):
    """Emulated GRBL 1.1 controller; ``move_time`` is seconds per move (float) or f(distance).

    ``on_arrive(work_position)`` is called (emulator thread, lock held) at the end of each move.
    """

    device = "GRBL"
    eol = b"\r\n"
    realtime = b"?!~\x18"

    def __init__(self, *, move_time: float | Callable[[float], float] = 0.0,
                 start: Vec = (0.0, 0.0, 0.0, 0.0), wco: Vec = (0.0, 0.0, 0.0, 0.0),
                 report: str = "mpos",
                 on_arrive: Callable[[Vec], None] | None = None) -> None:
        super().__init__()
        self.on_arrive = on_arrive
        if report not in ("mpos", "wpos"):
            raise ValueError("report must be 'mpos' or 'wpos'")
        self.move_time = move_time
        self.wco = tuple(float(v) for v in wco)
        self.report = report
        self._mpos: Vec = tuple(float(v) + o for v, o in zip(start, self.wco, strict=True))
        self._queue: list[Vec] = []
        self._segment: _Segment | None = None
        self._dwells: list[str] = []
        self.state = "Idle"
        self._absolute = True
        self._motion = 0
        self._feed_rate: float | None = None
        self._reports = 0
        self._fake_idle = False
        self.send(BANNER.encode() + self.eol)

    # -- positions -------------------------------------------------------------------------
    def _now_mpos(self, now: float | None = None) -> Vec:
        if self._segment is None:
            return self._mpos
        return self._segment.at(time.monotonic() if now is None else now)

    @property
    def machine_position(self) -> Vec:
        with self.lock:
            return self._now_mpos()

    @property
    def position(self) -> Vec:
        """Current work position (x, y, z mm, a deg) = machine position - WCO."""
        with self.lock:
            return tuple(m - o for m, o in zip(self._now_mpos(), self.wco, strict=True))

    def _duration(self, start: Vec, end: Vec) -> float:
        if callable(self.move_time):
            return float(self.move_time(math.dist(start, end)))
        return float(self.move_time)

    # -- real-time commands ----------------------------------------------------------------
    def handle_realtime(self, byte: int) -> None:
        now = time.monotonic()
        if byte == ord("?"):
            self.reply("?", self._status(now))
        elif byte == ord("!"):
            if self.state == "Run" and self._segment is not None:
                self._segment.held_at = now - self._segment.t0
                self.state = "Hold:0"
        elif byte == ord("~"):
            if self.state.startswith("Hold") and self._segment is not None:
                self._segment.t0 = now - (self._segment.held_at or 0.0)
                self._segment.held_at = None
                self.state = "Run"
        elif byte == 0x18:
            self._reset(now)

    def _reset(self, now: float) -> None:
        running = self.state == "Run" and not self._fake_idle
        self._mpos = self._now_mpos(now)
        self._segment, self._queue, self._dwells = None, [], []
        self._partial.clear()
        self._fake_idle = False
        self._reports = 0
        self.send(BANNER.encode() + self.eol)
        if running or self.state == "Alarm":
            if running:
                self.send(b"ALARM:3" + self.eol)
            self.state = "Alarm"
            self.send(b"[MSG:'$H'|'$X' to unlock]" + self.eol)
        else:
            self.state = "Idle"

    def _status(self, now: float) -> str:
        mpos = self._now_mpos(now)
        if self.report == "wpos":
            axes = "WPos:" + ",".join(f"{m - o:.3f}" for m, o in zip(mpos, self.wco, strict=True))
        else:
            axes = "MPos:" + ",".join(f"{m:.3f}" for m in mpos)
        state = "Idle" if self._fake_idle and self.state == "Run" else self.state
        text = f"<{state}|{axes}|FS:{self._feed_rate or 0:.0f},0"
        if self._reports % 10 == 0:
            text += "|WCO:" + ",".join(f"{o:.3f}" for o in self.wco)
        self._reports += 1
        return text + ">"

    # -- motion ----------------------------------------------------------------------------
    def tick(self, now: float) -> None:
        seg = self._segment
        if seg is not None and seg.done(now):
            self._mpos = seg.end
            self._segment = None
            if self.on_arrive is not None:
                self.on_arrive(tuple(m - o for m, o in zip(seg.end, self.wco, strict=True)))
        if self._segment is None and self._queue and self.state != "Alarm":
            end = self._queue.pop(0)
            self._segment = _Segment(self._mpos, end, now, self._duration(self._mpos, end))
            self.state = "Run"
            self.tick(now)
            return
        if self._segment is None and not self._queue and self.state == "Run":
            self.state = "Idle"
            self._fake_idle = False
        if self.state == "Idle" and self._dwells:
            dwells, self._dwells = self._dwells, []
            for line in dwells:
                self.reply(line, "ok")

    def _alarm(self, code: int, now: float) -> None:
        self._mpos = self._now_mpos(now)
        self._segment, self._queue, self._dwells = None, [], []
        self._fake_idle = False
        self.state = "Alarm"
        self.send(f"ALARM:{code}".encode() + self.eol)

    # -- lines -----------------------------------------------------------------------------
    def handle_line(self, line: str) -> None:
        now = time.monotonic()
        text = line.strip().upper().replace(" ", "")
        fault = self.take_fault({"error", "alarm"}, line)
        if fault is not None and fault.kind == "alarm":
            return self._alarm(fault.code, now)
        if fault is not None:
            return self.reply(line, f"error:{fault.code}")
        if not text:
            return self.reply(line, "ok")
        if text.startswith("$"):
            if text == "$X":
                if self.state == "Alarm":
                    self.state = "Idle"
                    self.send(b"[MSG:Caution: Unlocked]" + self.eol)
                return self.reply(line, "ok")
            if text in ("$$", "$#", "$G", "$I"):
                return self.reply(line, "ok")
            return self.reply(line, "error:3")
        if self.state == "Alarm":
            return self.reply(line, "error:9")
        words = _WORD.findall(text)
        if "".join(a + b for a, b in words) != text:
            return self.reply(line, "error:2" if text[:1].isalpha() else "error:1")
        self._gcode(line, words, now)

    def _gcode(self, line: str, words: list[tuple[str, str]], now: float) -> None:
        seen: set[str] = set()
        target: dict[str, float] = {}
        dwell = False
        pause: float | None = None
        motion = self._motion
        for letter, number in words:
            value = float(number)
            if letter == "G":
                if value in (0, 1):
                    motion = int(value)
                elif value == 4:
                    dwell = True
                elif value in (90, 91):
                    self._absolute = value == 90
                elif value != 21:
                    return self.reply(line, "error:20")
                continue
            if letter in seen:
                return self.reply(line, "error:25")
            seen.add(letter)
            if letter in AXES:
                target[letter] = value
            elif letter == "F":
                if value <= 0:
                    return self.reply(line, "error:4")
                self._feed_rate = value
            elif letter == "P":
                pause = value
            else:
                return self.reply(line, "error:20")
        if dwell:
            if pause is None:
                return self.reply(line, "error:28")
            if (self._segment is None and not self._queue) or self._fake_idle:
                return self.reply(line, "ok")
            self._dwells.append(line)
            return None
        if pause is not None:
            return self.reply(line, "error:36")
        self._motion = motion
        if not target:
            return self.reply(line, "ok")
        if motion == 1 and self._feed_rate is None:
            return self.reply(line, "error:22")
        last = self._queue[-1] if self._queue else (
            self._segment.end if self._segment else self._mpos)
        end = tuple(
            (target[a] + o if self._absolute else last[i] + target[a]) if a in target else last[i]
            for i, (a, o) in enumerate(zip(AXES, self.wco, strict=True)))
        early = self.take_fault({"early_idle"}, line)
        if early is not None:
            start = self._now_mpos(now)
            if early.stall:  # the axes stop half-way and never arrive
                end = tuple((s + e) / 2 for s, e in zip(start, end, strict=True))
            self._queue = []
            self._segment = _Segment(start, end, now, early.seconds or 0.3)
            self.state = "Run"
            self._fake_idle = True
            return self.reply(line, "ok")
        self._queue.append(end)
        self.reply(line, "ok")
        self.tick(now)
