"""The three device interfaces every driver implements (hardware and simulated twin alike).

Units: mm and degrees. A driver raises :class:`DriverError` (or a subclass) with a one-line
operator message; it never returns a made-up number.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol, runtime_checkable

import numpy as np

from calib_core.errors import LasercalError

#: Interval (s) at which a moving robot reports its pose to an ``on_motion`` callback.
MOTION_REPORT_S = 1.0 / 30.0


class DriverError(LasercalError):
    """A device failed or answered with an error; the message says which and what to do.

    ``retryable`` False: repeating the same operation cannot help (an alarm lock, a refused
    target), so callers report it at once instead of retrying and masking the cause.
    """

    retryable: bool = True


class DeviceTimeout(DriverError):
    """A device did not answer in time (after the bounded retries)."""


class MotionRefused(DriverError):
    """A motion target was refused before anything was sent (soft limits, step limit, disarmed)."""

    retryable = False


@dataclass(frozen=True)
class FlangePose:
    """Flange pose in the fixed frame: position mm, rotation about z in degrees.

    ``quaternion`` (w, x, y, z) is set for a 6-dof flange; then it defines the orientation and
    ``theta_deg`` is its rotation about z for display only.
    """

    x: float
    y: float
    z: float
    theta_deg: float = 0.0
    quaternion: tuple[float, float, float, float] | None = None

    def as_array(self) -> np.ndarray:
        return np.array([self.x, self.y, self.z, self.theta_deg])


MotionCallback = Callable[[FlangePose], None]


@dataclass(frozen=True)
class SoftLimits:
    """Axis-aligned box of allowed flange positions plus a theta range and a maximum jog step."""

    x: tuple[float, float]
    y: tuple[float, float]
    z: tuple[float, float]
    theta_deg: tuple[float, float]
    max_step: float = float("inf")

    def check(self, target: FlangePose, current: FlangePose | None = None) -> None:
        """Raise :class:`MotionRefused` if ``target`` is outside the limits (or too far a step)."""
        for name, value, (lo, hi) in (
            ("x", target.x, self.x), ("y", target.y, self.y), ("z", target.z, self.z),
            ("theta", target.theta_deg, self.theta_deg),
        ):
            if not np.isfinite(value) or not lo <= value <= hi:
                raise MotionRefused(f"target {name}={value:g} is outside the soft limits "
                                    f"[{lo:g}, {hi:g}]; nothing was sent to the robot")
        if current is not None:
            step = float(np.linalg.norm(np.array([target.x - current.x, target.y - current.y,
                                                  target.z - current.z])))
            if step > self.max_step:
                raise MotionRefused(f"step of {step:.3f} mm exceeds the maximum step "
                                    f"{self.max_step:g} mm; nothing was sent to the robot")


class ReadingStatus(StrEnum):
    OK = "ok"
    OUT_OF_RANGE = "out-of-range"
    INVALID = "invalid"


@dataclass(frozen=True)
class SensorReading:
    """One displacement reading: ``value`` in mm when ``status`` is OK, else None."""

    status: ReadingStatus
    value: float | None = None
    raw: str = ""

    @property
    def ok(self) -> bool:
        return self.status is ReadingStatus.OK


@dataclass(frozen=True)
class SpotMeasurement:
    """A detected laser spot: fixed-frame ``x, y`` in mm, pixel ``u, v``, quality in [0, 1].

    ``ok`` is False (with ``reason``) for an empty, saturated or ambiguous frame; then the
    coordinates are NaN and must not be used.
    """

    ok: bool
    x: float = float("nan")
    y: float = float("nan")
    u: float = float("nan")
    v: float = float("nan")
    quality: float = 0.0
    reason: str = ""
    extra: dict[str, float] = field(default_factory=dict)


@runtime_checkable
class Robot(Protocol):
    """A robot carrying the sensor: absolute moves that return once the motion has ended."""

    limits: SoftLimits

    def move_to(self, target: FlangePose, on_motion: MotionCallback | None = None
                ) -> FlangePose:
        """Check the soft limits, move, wait for the end of motion, return the pose read back.

        ``on_motion`` (optional) is called, in the caller's thread, with the poses the robot
        passes through while it moves (about every :data:`MOTION_REPORT_S`), for a live view.
        """
        ...

    def read_pose(self) -> FlangePose: ...

    def stop(self) -> None:
        """Stop any motion at once (feed hold); safe to call from another thread."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class DisplacementSensor(Protocol):
    """A triangulation displacement sensor (reading along the beam, mm)."""

    def read(self) -> SensorReading: ...

    def zero(self) -> None:
        """Set the current reading as zero; raise :class:`DriverError` if impossible."""
        ...

    def close(self) -> None: ...


@runtime_checkable
class SpotCamera(Protocol):
    """A calibrated camera that locates the laser spot in the fixed frame (mm)."""

    def grab(self) -> np.ndarray:
        """One frame, grey levels (H, W) uint8 or uint16."""
        ...

    def measure_spot(self) -> SpotMeasurement: ...

    def close(self) -> None: ...
