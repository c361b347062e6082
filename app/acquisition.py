"""The acquisition runner: move, settle, measure, validate, store, for every planned pose.

For each pose of the session's grid without a stored sample: move the robot (and check the
pose read back against the target), wait ``settle_s``, take ``samples_per_pose`` sensor and
camera readings and average them. A measurement with an invalid reading (sensor out-of-range
or invalid, no spot, spot quality too low) is re-read up to ``max_retries`` times, then stored
as *skipped* with the reason. Every sample is committed to the session at once.

Control (thread-safe, from any thread): :meth:`Runner.pause` (after the pose in flight),
:meth:`Runner.resume`, :meth:`Runner.abort` (the pose in flight is dropped, never half-stored).
A :class:`~drivers.base.DriverError` is retried ``driver_retries`` times on the same pose (not
one marked ``retryable = False``, e.g. a GRBL alarm), then pauses the run with the message
(logged in the session's ``events``); after :meth:`resume` the pose is tried again.
``max_skips_in_a_row`` skipped poses in a row (a sensor stuck out of range, a camera that
sees nothing) also pause the run; the last of them is not stored, so it is
measured again after :meth:`resume` (0: never pause for skips). With ``return_on_pause``
:meth:`Runner.run` returns when paused (so the thread that owns the drivers is free, e.g. to
reconnect them with :meth:`Runner.set_devices`); calling :meth:`Runner.run` again continues.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from app.session import Sample, Session
from calib_core.grid import PoseGrid
from drivers.base import (
    DisplacementSensor,
    DriverError,
    FlangePose,
    MotionRefused,
    Robot,
    SoftLimits,
    SpotCamera,
)


@dataclass(frozen=True)
class RunnerConfig:
    """Acquisition settings (seconds, mm, degrees)."""

    samples_per_pose: int = 3
    settle_s: float = 0.0
    max_retries: int = 2
    retry_delay_s: float = 0.0
    driver_retries: int = 1
    driver_retry_delay_s: float = 0.2
    pose_tolerance_mm: float = 0.1
    pose_tolerance_deg: float = 0.1
    min_quality: float = 0.0
    retry_skipped: bool = False
    return_on_pause: bool = False
    max_skips_in_a_row: int = 3

    def __post_init__(self) -> None:
        from calib_core.errors import InputError

        if self.samples_per_pose < 1:
            raise InputError(f"samples per pose must be >= 1, got {self.samples_per_pose}")
        for name in ("settle_s", "retry_delay_s", "driver_retry_delay_s", "max_retries",
                     "driver_retries", "pose_tolerance_mm", "pose_tolerance_deg",
                     "max_skips_in_a_row"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")


@dataclass(frozen=True)
class Progress:
    """Where a run stands: ``done`` of ``total`` poses stored (``skipped`` of them skipped),
    ``eta_s`` (None until a pose was measured in this run), the ``last`` stored sample,
    ``state`` (idle, running, paused, aborted, finished) and an operator ``message``."""

    done: int
    total: int
    eta_s: float | None
    last: Sample | None
    state: str
    message: str = ""
    skipped: int = 0
    current: int | None = None

    @property
    def fraction(self) -> float:
        return self.done / self.total if self.total else 1.0


ProgressCallback = Callable[[Progress], None]


class _Invalid(Exception):
    """A measurement that failed validation (reason in the message); retried, then skipped."""


class _Aborted(Exception):
    pass


class _SkipStreak(Exception):
    """Too many poses in a row could not be measured: a device is probably at fault."""


def describe_device(device: object) -> str:
    """``module.Class`` of a driver plus its ``describe()`` text when it has one."""
    name = f"{type(device).__module__}.{type(device).__qualname__}"
    describe = getattr(device, "describe", None)
    if callable(describe):
        try:
            return f"{name} ({describe()})"
        except Exception as exc:  # a description must never stop a session
            return f"{name} (describe failed: {exc})"
    return name


def check_grid_limits(grid: PoseGrid, limits: SoftLimits,
                      indices: Iterable[int] | None = None) -> None:
    """Raise :class:`MotionRefused` naming the first grid pose outside ``limits``."""
    for index in range(len(grid)) if indices is None else indices:
        try:
            limits.check(FlangePose(*grid.pose(index)))
        except MotionRefused as exc:
            raise MotionRefused(f"grid pose {index}: {exc}; fix the grid or the limits "
                                "(no pose was measured)") from None


class Runner:
    """Runs the pending poses of ``session`` with the given devices (see the module doc)."""

    def __init__(self, session: Session, robot: Robot, sensor: DisplacementSensor,
                 camera: SpotCamera, config: RunnerConfig | None = None,
                 on_progress: ProgressCallback | None = None) -> None:
        self.session = session
        self.config = config or RunnerConfig()
        self.on_progress = on_progress
        self.robot, self.sensor, self.camera = robot, sensor, camera
        self._go = threading.Event()
        self._go.set()
        self._abort = threading.Event()
        self._running = threading.Lock()
        self._state = "idle"
        self._message = ""
        self._last: Sample | None = None
        self._grid = session.grid
        self._total = len(self._grid)
        self._pose_times: list[float] = []
        self._skips_in_a_row = 0

    # ---- control (any thread) ------------------------------------------------------------
    @property
    def state(self) -> str:
        return self._state

    def pause(self, message: str = "paused by the operator") -> None:
        """Pause after the pose in flight."""
        self._message = message
        self._go.clear()

    def resume(self) -> None:
        self._message = ""
        self._go.set()

    def abort(self, stop_motion: bool = False) -> None:
        """End the run; the pose in flight is dropped. ``stop_motion`` also stops the robot."""
        self._abort.set()
        self._go.set()
        if stop_motion:
            with contextlib.suppress(DriverError):
                self.robot.stop()

    def set_devices(self, robot: Robot | None = None, sensor: DisplacementSensor | None = None,
                    camera: SpotCamera | None = None) -> None:
        """Replace devices (e.g. reconnected after a fault) while the run is paused or idle."""
        self.robot = robot or self.robot
        self.sensor = sensor or self.sensor
        self.camera = camera or self.camera

    def progress(self, current: int | None = None) -> Progress:
        stored = self.session.stored_indices()
        skipped = len(stored - self.session.stored_indices("ok"))
        remaining = self._total - len(stored)
        eta = None
        if self._pose_times:
            eta = float(np.mean(self._pose_times[-20:])) * remaining
        return Progress(len(stored), self._total, eta, self._last, self._state, self._message,
                        skipped, current)

    # ---- the run -------------------------------------------------------------------------
    def run(self) -> Progress:
        """Measure every pending pose; returns the final progress (state finished, aborted,
        or paused with ``return_on_pause``). Not re-entrant."""
        if not self._running.acquire(blocking=False):
            raise RuntimeError("this runner is already running")
        try:
            self._abort.clear()
            pending = self.session.pending_indices(retry_skipped=self.config.retry_skipped)
            self._check_limits(pending)
            self._set_state("running")
            k = 0
            while k < len(pending):
                if self._abort.is_set():
                    return self._finish("aborted", "aborted by the operator")
                if not self._go.is_set():
                    self._set_state("paused")
                    if self.config.return_on_pause:
                        return self.progress()
                    while not self._go.wait(0.1):
                        pass
                    if self._abort.is_set():
                        continue
                    self.session.log_event("resume", "run resumed")
                    self._set_state("running")
                index = pending[k]
                try:
                    self._measure_pose(index)
                except _Aborted:
                    continue
                except _SkipStreak as exc:
                    message = f"pose {index}: {exc}"
                    self.session.log_event("skip-streak", message)
                    self.pause(f"{message}; fix the device, then resume")
                    continue
                except DriverError as exc:
                    message = f"pose {index}: {exc}"
                    self.session.log_event("driver-error", message)
                    if self._go.is_set():  # else the operator's pause message stands
                        self.pause(f"{message}; fix the device, then resume")
                    continue
                k += 1
            return self._finish("finished", "")
        except BaseException as exc:
            self._message = f"run failed: {exc}"
            self._state = "failed"
            self._emit()
            raise
        finally:
            self._running.release()

    def _check_limits(self, pending: list[int]) -> None:
        limits = getattr(self.robot, "limits", None)
        if limits is not None:
            check_grid_limits(self._grid, limits, pending)

    def _finish(self, state: str, message: str) -> Progress:
        self._message = message
        self._set_state(state)
        return self.progress()

    def _set_state(self, state: str, current: int | None = None) -> None:
        self._state = state
        if state != "running" and self._message:
            self.session.log_event(state, self._message)
        self._emit(current)

    def _emit(self, current: int | None = None) -> None:
        if self.on_progress is not None:
            self.on_progress(self.progress(current))

    def _wait(self, seconds: float) -> None:
        if seconds > 0 and self._abort.wait(seconds):
            raise _Aborted
        if self._abort.is_set():
            raise _Aborted

    def _measure_pose(self, index: int) -> None:
        """Move, settle, read, validate and store pose ``index`` (DriverError after retries)."""
        cfg = self.config
        x, y, z, theta = self._grid.pose(index)
        target = FlangePose(x, y, z, theta)
        started = time.monotonic()
        for attempt in range(cfg.driver_retries + 1):
            try:
                readback = self._move(target)
                sample = self._read_valid(index, target, readback)
                break
            except DriverError as exc:
                if (attempt == cfg.driver_retries or not self._go.is_set()
                        or self._abort.is_set() or not exc.retryable):
                    raise  # never move again after a STOP; an alarm is reported at once
                self._wait(cfg.driver_retry_delay_s)
        self._wait(0.0)  # an abort during the reading drops the sample
        if sample.ok:
            self._skips_in_a_row = 0
        else:
            self._skips_in_a_row += 1
            if 0 < cfg.max_skips_in_a_row <= self._skips_in_a_row:
                self._skips_in_a_row = 0
                raise _SkipStreak(f"{cfg.max_skips_in_a_row} poses in a row could not be "
                                  f"measured (last: {sample.reason}); the pose is not stored "
                                  "and will be measured again")
        self.session.add_sample(sample)
        self._last = sample
        self._pose_times.append(time.monotonic() - started)
        self._emit(index)

    def _move(self, target: FlangePose) -> FlangePose:
        self._wait(0.0)
        readback = self.robot.move_to(target)
        cfg = self.config
        dx = max(abs(readback.x - target.x), abs(readback.y - target.y),
                 abs(readback.z - target.z))
        dt = abs(readback.theta_deg - target.theta_deg)
        if dx > cfg.pose_tolerance_mm or dt > cfg.pose_tolerance_deg:
            raise DriverError(
                f"robot reports ({readback.x:.4f}, {readback.y:.4f}, {readback.z:.4f}, "
                f"{readback.theta_deg:.4f} deg) after a move to ({target.x:.4f}, "
                f"{target.y:.4f}, {target.z:.4f}, {target.theta_deg:.4f} deg): "
                f"not at the target (tolerance {cfg.pose_tolerance_mm:g} mm, "
                f"{cfg.pose_tolerance_deg:g} deg)")
        self._wait(cfg.settle_s)
        return readback

    def _read_valid(self, index: int, target: FlangePose, readback: FlangePose) -> Sample:
        cfg = self.config
        reason = ""
        for attempt in range(1, cfg.max_retries + 2):
            try:
                return self._read(index, target, readback, attempt)
            except _Invalid as exc:
                reason = str(exc)
                if attempt <= cfg.max_retries:
                    self._wait(cfg.retry_delay_s)
        return Sample(index, _pose4(target), _pose4(readback), None, None, None,
                      status="skipped", reason=f"{reason} ({cfg.max_retries + 1} attempt(s))",
                      attempts=cfg.max_retries + 1)

    def _read(self, index: int, target: FlangePose, readback: FlangePose,
              attempt: int) -> Sample:
        n = self.config.samples_per_pose
        values = np.empty((n, 4))
        for k in range(n):
            self._wait(0.0)
            reading = self.sensor.read()
            if not reading.ok or reading.value is None:
                raise _Invalid(f"sensor {reading.status.value}"
                               + (f" ({reading.raw})" if reading.raw else ""))
            spot = self.camera.measure_spot()
            if not spot.ok:
                raise _Invalid(f"camera: {spot.reason or 'no spot'}")
            if not (np.isfinite(spot.x) and np.isfinite(spot.y)):
                raise _Invalid("camera: spot position is not finite")
            if spot.quality < self.config.min_quality:
                raise _Invalid(f"camera: spot quality {spot.quality:.2f} below "
                               f"{self.config.min_quality:.2f}")
            values[k] = (reading.value, spot.x, spot.y, spot.quality)
        mean = values.mean(axis=0)
        std = values.std(axis=0, ddof=1) if n > 1 else np.full(4, np.nan)
        return Sample(index, _pose4(target), _pose4(readback), float(mean[0]), float(mean[1]),
                      float(mean[2]), float(mean[3]), d_std=float(std[0]),
                      x_p_std=float(std[1]), y_p_std=float(std[2]), n_readings=n,
                      attempts=attempt)


def _pose4(pose: FlangePose) -> tuple[float, float, float, float]:
    return float(pose.x), float(pose.y), float(pose.z), float(pose.theta_deg)
