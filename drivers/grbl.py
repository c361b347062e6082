"""Robot behind a GRBL 1.1-compatible controller (axes X Y Z mm, A = theta in degrees).

A move is ``G90 G1 X.. Y.. Z.. A.. F..`` (``ok``), then ``G4 P0`` whose ``ok`` marks the end of
motion, then ``?`` -> ``<Idle|MPos:x,y,z,a|...>`` (or ``WPos``; ``WCO`` converts MPos to work
coordinates, which are the ones commanded and returned). ``error:N`` / ``ALARM:N`` become
:class:`GrblError` / :class:`GrblAlarm` with GRBL's meaning. :meth:`GrblRobot.stop` writes the
real-time feed hold ``!`` at once, even while a move waits. Soft limits are checked before
anything is sent.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

from drivers.base import (
    MOTION_REPORT_S,
    DeviceTimeout,
    DriverError,
    FlangePose,
    MotionCallback,
    MotionRefused,
    SoftLimits,
)
from drivers.serial_port import SerialLink

#: GRBL 1.1 ``error:N`` meanings (the common ones).
GRBL_ERRORS: dict[int, str] = {
    1: "G-code word without a letter",
    2: "numeric value missing or badly formatted",
    3: "'$' system command not recognised",
    4: "negative value for a positive-only parameter",
    5: "homing cycle not enabled in the settings",
    8: "'$' command only valid when Idle",
    9: "G-code locked out during alarm or jog state (clear the alarm: $X or home with $H)",
    11: "line too long",
    15: "jog target exceeds machine travel",
    20: "unsupported or invalid G-code command",
    21: "more than one G-code command of the same modal group",
    22: "feed rate not set",
    23: "G-code command requires an integer value",
    24: "two G-code commands that both need axis words",
    25: "G-code word repeated in the block",
    26: "G-code command needs axis words, none given",
    28: "G-code command is missing a required P or L value",
    33: "motion target invalid",
    36: "unused G-code words left in the block",
}
#: GRBL 1.1 ``ALARM:N`` meanings.
GRBL_ALARMS: dict[int, str] = {
    1: "hard limit triggered; machine position is likely lost, re-homing is recommended",
    2: "motion target exceeds machine travel (soft limit); position retained, unlock with $X",
    3: "reset while in motion; position may be lost, re-homing is recommended",
    4: "probe fail: probe not in the expected initial state",
    5: "probe fail: probe did not contact the workpiece",
    6: "homing fail: reset during the homing cycle",
    7: "homing fail: safety door opened during homing",
    8: "homing fail: pull-off did not clear the limit switch",
    9: "homing fail: limit switch not found within the search distance",
}
STATES = ("Idle", "Run", "Hold", "Jog", "Alarm", "Door", "Check", "Home", "Sleep")


class GrblError(DriverError):
    """The controller answered ``error:N`` (command rejected)."""


class GrblAlarm(DriverError):
    """The controller raised ``ALARM:N`` or is in the Alarm state (motion locked)."""

    retryable = False  # locked until the operator unlocks: a retry only hides the cause


class MotionStopped(DriverError):
    """A move was interrupted by :meth:`GrblRobot.stop` (feed hold)."""


def error_text(code: int) -> str:
    return f"error:{code} {GRBL_ERRORS.get(code, 'unknown GRBL error code')}"


def alarm_text(code: int) -> str:
    return f"ALARM:{code} {GRBL_ALARMS.get(code, 'unknown GRBL alarm code')}"


def _code(line: str, prefix: str) -> int:
    tail = line[len(prefix):].strip()
    return int(tail) if tail.isdigit() else -1


@dataclass(frozen=True)
class GrblStatus:
    """A parsed ``<...>`` status report; positions are (x, y, z, a) or None if absent."""

    state: str
    mpos: tuple[float, ...] | None = None
    wpos: tuple[float, ...] | None = None
    wco: tuple[float, ...] | None = None

    @property
    def base_state(self) -> str:
        return self.state.split(":")[0]


def parse_status(line: str) -> GrblStatus:
    """``<State|MPos:x,y,z,a|FS:..|WCO:..>`` -> :class:`GrblStatus`; DriverError if malformed.

    Needs four axes (X Y Z A) in MPos or WPos.
    """
    text = line.strip()
    if not (text.startswith("<") and text.endswith(">")):
        raise DriverError(f"malformed GRBL status report {text[:60]!r}")
    fields = text[1:-1].split("|")
    state = fields[0]
    if state.split(":")[0] not in STATES:
        raise DriverError(f"unknown GRBL state {state[:20]!r} in status report")
    found: dict[str, tuple[float, ...]] = {}
    for field in fields[1:]:
        key, _, values = field.partition(":")
        if key in ("MPos", "WPos", "WCO"):
            try:
                numbers = tuple(float(v) for v in values.split(","))
            except ValueError:
                raise DriverError(f"malformed {key} in GRBL status report {text[:60]!r}") from None
            if len(numbers) < 4 or not all(math.isfinite(v) for v in numbers):
                raise DriverError(f"GRBL status report {key} has {len(numbers)} axes; the robot "
                                  "needs X Y Z A (4 axes)")
            found[key] = numbers[:4]
    if "MPos" not in found and "WPos" not in found:
        raise DriverError(f"GRBL status report without MPos/WPos {text[:60]!r}")
    return GrblStatus(state, found.get("MPos"), found.get("WPos"), found.get("WCO"))


class GrblRobot:
    """:class:`drivers.base.Robot` on a GRBL 1.1 controller (work coordinates, mm and deg).

    ``feed`` mm/min; ``timeout`` s per reply (re-sent ``retries`` times); ``move_timeout`` s for
    the end of a move (None: 10 s + 3x the nominal duration); ``settle_timeout`` s to see Idle
    at the target within ``tolerance`` (mm, deg) after the ``G4 P0`` ``ok``.

    ``MPos`` reports are converted with the last ``WCO`` seen (zero until one arrives); with
    non-zero work offsets set GRBL's ``$10=0`` so that it reports ``WPos``.
    """

    def __init__(self, port: str, limits: SoftLimits, *, baudrate: int = 115200,
                 timeout: float = 1.0, retries: int = 2, feed: float = 1000.0,
                 move_timeout: float | None = None, settle_timeout: float = 2.0,
                 tolerance: float = 0.02) -> None:
        if not (math.isfinite(feed) and feed > 0):
            raise DriverError("GRBL feed rate must be a finite number > 0 mm/min")
        for name, value in (("move_timeout", move_timeout), ("settle_timeout", settle_timeout),
                            ("tolerance", tolerance)):
            if value is not None and not (math.isfinite(value) and value > 0):
                raise DriverError(f"GRBL {name} must be a finite number > 0")
        self.limits = limits
        self.feed = float(feed)
        self.move_timeout = move_timeout
        self.settle_timeout = settle_timeout
        self.tolerance = tolerance
        self._wco: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
        self._stop = threading.Event()
        self._held = False
        self._link = SerialLink(port, baudrate, timeout=timeout, retries=retries, eol="\n",
                                device="GRBL controller")

    @property
    def port(self) -> str:
        return self._link.port

    # -- protocol --------------------------------------------------------------------------
    def _command(self, line: str, *, timeout: float | None = None,
                 retries: int | None = None) -> None:
        """Send a G-code line and wait for its ``ok``; error/alarm replies raise."""

        def accept(reply: str) -> bool:
            return reply == "ok" or reply.startswith(("error:", "ALARM:"))

        reply = self._link.transact(line, accept, timeout=timeout, retries=retries)
        if reply.startswith("error:"):
            raise GrblError(f"GRBL on {self.port} rejected {line!r}: "
                            f"{error_text(_code(reply, 'error:'))}")
        if reply.startswith("ALARM:"):
            raise GrblAlarm(f"GRBL on {self.port}: {alarm_text(_code(reply, 'ALARM:'))}")

    def status(self) -> GrblStatus:
        """Query ``?`` and parse the report (alarms pushed meanwhile raise)."""

        def accept(reply: str) -> bool:
            if reply.startswith("ALARM:"):
                return True
            if not reply.startswith("<"):
                return False
            try:
                parse_status(reply)
            except DriverError:
                return False
            return True

        reply = self._link.transact(b"?", accept, what="'?'")
        if reply.startswith("ALARM:"):
            raise GrblAlarm(f"GRBL on {self.port}: {alarm_text(_code(reply, 'ALARM:'))}")
        status = parse_status(reply)
        if status.wco is not None:
            self._wco = status.wco
        return status

    def _pose(self, status: GrblStatus) -> FlangePose:
        if status.wpos is not None:
            work = status.wpos
        else:
            work = tuple(m - o for m, o in zip(status.mpos or (), self._wco, strict=True))
        return FlangePose(*work[:4])

    def read_pose(self) -> FlangePose:
        """Current pose in work coordinates (x, y, z mm, theta = A deg)."""
        with self._link.lock:
            pose = self._pose(self.status())
        return pose

    def _clear_hold(self) -> None:
        """After a stop: wait for the hold to complete, then soft-reset to flush the queue."""
        deadline = time.monotonic() + self.settle_timeout
        while self.status().state == "Hold:1" and time.monotonic() < deadline:
            time.sleep(0.02)
        self._link.discard_input()
        self._link.write(b"\x18")
        end = time.monotonic() + max(2.0, self._link.timeout)
        while (line := self._link.read_line(max(0.0, end - time.monotonic()))) is not None:
            if line.startswith("Grbl"):
                break
        else:
            raise DeviceTimeout(f"GRBL on {self.port} did not restart after the soft reset")
        self._held = False

    def _check(self, target: FlangePose) -> FlangePose:
        """The 4-axis target (theta from a z-only quaternion), checked against the limits."""
        if target.quaternion is not None:
            qw, qx, qy, qz = target.quaternion
            norm = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
            if not (math.isfinite(norm) and norm > 0) or max(abs(qx), abs(qy)) > 1e-9 * norm:
                raise MotionRefused("the GRBL robot only rotates about z (axis A); a tilted "
                                    "orientation was requested; nothing was sent to the robot")
            theta = math.degrees(2.0 * math.atan2(qz, qw))
            target = FlangePose(target.x, target.y, target.z, (theta + 180.0) % 360.0 - 180.0)
        self.limits.check(target)
        return target

    def move_to(self, target: FlangePose, on_motion: MotionCallback | None = None
                ) -> FlangePose:
        """Check limits, move, wait for the end of motion, return the pose read back.

        A quaternion target must be a rotation about z; theta = 2 atan2(qz, qw). With
        ``on_motion`` the controller is asked for its status (``?``) every
        :data:`MOTION_REPORT_S` during the move and each reported pose goes to the callback.
        """
        target = self._check(target)
        x, y, z, a = target.x, target.y, target.z, target.theta_deg
        with self._link.lock:
            self._stop.clear()
            if self._held:
                self._clear_hold()
            start = self.status()
            if start.base_state == "Alarm":
                raise GrblAlarm(f"GRBL on {self.port} is in the Alarm state; check the machine, "
                                "then unlock ($X, `lasercal robot unlock`) or home it")
            begin = self._pose(start)
            self._command(f"G90 G1 X{x:.3f} Y{y:.3f} Z{z:.3f} A{a:.3f} F{self.feed:g}")
            dist = math.dist(begin.as_array(), target.as_array())
            wait = self.move_timeout or 10.0 + 3.0 * dist / self.feed * 60.0
            self._wait_motion(target, wait, on_motion)
            pose = self._settle(target)
        return pose

    def _wait_motion(self, target: FlangePose, wait: float,
                     on_motion: MotionCallback | None = None) -> None:
        """Send ``G4 P0`` and wait ``wait`` s at most for its ``ok`` (end of motion).

        Whenever no line arrives for one reply timeout (for :data:`MOTION_REPORT_S` with
        ``on_motion``), ``?`` probes the controller: a report of Idle at the target means the
        ``ok`` was lost and the motion is over; any other report goes to ``on_motion``.
        """
        link = self._link
        link.discard_input()
        link.send_line("G4 P0")
        deadline = time.monotonic() + wait
        poll = link.timeout if on_motion is None else min(link.timeout, MOTION_REPORT_S)
        while True:
            remaining = deadline - time.monotonic()
            line = link.read_line(max(0.0, min(poll, remaining)), self._stop.is_set)
            if self._stop.is_set():
                raise MotionStopped(f"move stopped by operator (feed hold sent to {self.port}); "
                                    "the next move clears the controller's queue")
            if line is None:
                if remaining <= 0:
                    raise DeviceTimeout(f"GRBL on {self.port}: no end of motion (G4 P0 ok) "
                                        f"within {wait:g} s")
                link.write(b"?")
            elif line == "ok":
                return
            elif line.startswith("error:"):
                raise GrblError(f"GRBL on {self.port} rejected 'G4 P0': "
                                f"{error_text(_code(line, 'error:'))}")
            elif line.startswith("ALARM:"):
                raise GrblAlarm(f"GRBL on {self.port}: {alarm_text(_code(line, 'ALARM:'))}")
            elif line.startswith("<"):
                try:
                    status = parse_status(line)
                except DriverError:
                    continue
                if status.wco is not None:
                    self._wco = status.wco
                pose = self._pose(status)
                if status.base_state == "Alarm":
                    raise GrblAlarm(f"GRBL on {self.port} went into Alarm during the move")
                if (status.base_state == "Idle" and
                        float(abs(pose.as_array() - target.as_array()).max()) <= self.tolerance):
                    return  # the ok was lost; the motion is over
                if on_motion is not None:
                    on_motion(pose)

    def jog(self, dx: float = 0.0, dy: float = 0.0, dz: float = 0.0,
            dtheta: float = 0.0) -> FlangePose:
        """Relative move from the pose read back; refused beyond ``limits.max_step``."""
        current = self.read_pose()
        target = FlangePose(current.x + dx, current.y + dy, current.z + dz,
                            current.theta_deg + dtheta)
        self.limits.check(target, current)
        return self.move_to(target)

    def _settle(self, target: FlangePose) -> FlangePose:
        """Poll ``?`` until Idle at ``target``; Idle elsewhere past the deadline is an error."""
        deadline = time.monotonic() + self.settle_timeout
        while True:
            status = self.status()
            pose = self._pose(status)
            err = float(abs(pose.as_array() - target.as_array()).max())
            if status.base_state == "Idle" and err <= self.tolerance:
                return pose
            if status.base_state == "Alarm":
                raise GrblAlarm(f"GRBL on {self.port} went into Alarm during the move")
            if self._stop.is_set():
                raise MotionStopped(f"move stopped by operator (feed hold sent to {self.port})")
            if time.monotonic() > deadline:
                where = f"x={pose.x:.3f} y={pose.y:.3f} z={pose.z:.3f} theta={pose.theta_deg:.3f}"
                if status.base_state == "Idle":
                    raise DriverError(f"GRBL on {self.port} reports Idle at {where}, {err:.3f} "
                                      "from the target: the pose was not reached (lost steps, "
                                      "stalled axis or wrong controller setting)")
                raise DeviceTimeout(f"GRBL on {self.port} still {status.state} at {where} "
                                    f"{self.settle_timeout:g} s after the end of motion")
            time.sleep(0.02)

    def describe(self) -> str:
        """Connection summary stored with a session."""
        return (f"GRBL 1.1 on {self.port} {self._link.baudrate} 8N1, feed {self.feed:g} mm/min, "
                f"tolerance {self.tolerance:g}")

    def stop(self) -> None:
        """Feed hold ``!`` written at once (safe from any thread, even during a move)."""
        self._stop.set()
        self._held = True
        self._link.write_now(b"!")

    def unlock(self) -> None:
        """Clear an alarm lock (``$X``); the operator must have checked the machine first."""
        with self._link.lock:
            self._command("$X")

    def reconnect(self, port: str | None = None) -> None:
        """Reopen the serial port (after :class:`~drivers.serial_port.PortLost`)."""
        self._link.reconnect(port)

    def close(self) -> None:
        self._link.close()

    def __enter__(self) -> GrblRobot:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
