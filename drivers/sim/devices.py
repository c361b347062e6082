"""Simulated twins of the three devices, backed by one :class:`SimWorld`."""

from __future__ import annotations

import threading
import time

import numpy as np

from drivers.base import (
    DriverError,
    FlangePose,
    SensorReading,
    SoftLimits,
    SpotMeasurement,
)
from drivers.sim.world import SimWorld


class SimRobot:
    """A robot that checks its soft limits, takes ``move_time_s`` per move and can be stopped.

    ``move_to`` returns the reported pose (true pose + repeatability error, see SimWorld).
    A :meth:`stop` during a move leaves the flange part-way (linear interpolation in time) and
    raises :class:`DriverError`.
    """

    def __init__(self, world: SimWorld, limits: SoftLimits | None = None,
                 move_time_s: float | None = None) -> None:
        self.world = world
        self.limits = world.workcell.limits if limits is None else limits
        self.move_time_s = (world.workcell.timing.move_time_s if move_time_s is None
                            else float(move_time_s))
        self._stop = threading.Event()
        self._closed = False

    def _check_open(self) -> None:
        if self._closed:
            raise DriverError("simulated robot is closed")

    def move_to(self, target: FlangePose) -> FlangePose:
        """Check limits against the current pose, move (taking ``move_time_s``), report."""
        self._check_open()
        current = self.world.true_pose
        self.limits.check(target, current)
        self._stop.clear()
        if self.move_time_s > 0:
            start = time.monotonic()
            if self._stop.wait(self.move_time_s):
                f = min(1.0, (time.monotonic() - start) / self.move_time_s)
                a, b = current.as_array(), target.as_array()
                x, y, z, th = a + f * (b - a)
                self.world.move(FlangePose(x, y, z, th, target.quaternion if f >= 0.5
                                           else current.quaternion))
                raise DriverError("motion stopped before reaching the target")
        self.world.move(target)
        return self.world.reported_pose()

    def read_pose(self) -> FlangePose:
        self._check_open()
        return self.world.reported_pose()

    def stop(self) -> None:
        """Feed hold: ends a move in progress at once (thread-safe)."""
        self._stop.set()

    def close(self) -> None:
        self._stop.set()
        self._closed = True


class SimSensor:
    """A displacement sensor reading the world's beam: out-of-range beyond ``+-range``."""

    def __init__(self, world: SimWorld) -> None:
        self.world = world
        self._closed = False

    def read(self) -> SensorReading:
        if self._closed:
            raise DriverError("simulated sensor is closed")
        return self.world.read_sensor()

    def zero(self) -> None:
        """Zero at the current reading; :class:`DriverError` when no surface is in range."""
        if self._closed:
            raise DriverError("simulated sensor is closed")
        if not self.world.zero_sensor():
            raise DriverError("zero-set impossible: no surface within the sensor range")

    def close(self) -> None:
        self._closed = True


class SimCameraDirect:
    """A camera that returns the world's noisy spot without rendering (fast path for tests).

    ``grab`` returns a blank frame; use :class:`drivers.sim.devices.SimCamera` for rendered
    frames that go through the OpenCV detector.
    """

    def __init__(self, world: SimWorld) -> None:
        self.world = world

    def grab(self) -> np.ndarray:
        w, h = self.world.workcell.camera.resolution
        return np.zeros((h, w), np.uint8)

    def measure_spot(self) -> SpotMeasurement:
        xy = self.world.camera_spot()
        if xy is None:
            return SpotMeasurement(False, reason="no spot in the camera's view")
        return SpotMeasurement(True, float(xy[0]), float(xy[1]), quality=1.0)

    def close(self) -> None:
        pass
