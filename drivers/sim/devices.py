"""Simulated twins of the three devices, backed by one :class:`SimWorld`."""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Iterable

import numpy as np

from drivers.base import (
    MOTION_REPORT_S,
    DriverError,
    FlangePose,
    MotionCallback,
    SensorReading,
    SoftLimits,
    SpotMeasurement,
)
from drivers.camera_cv import (
    DetectorConfig,
    FrozenFrameCheck,
    PixelToPlate,
    SpotDetection,
    calibrate_chessboard,
    measure_average,
)
from drivers.sim.render import Chessboard, FrameRenderer, Spot
from drivers.sim.world import SimWorld, pose_rotation

#: Faults a :class:`SimCamera` can inject into its frames.
CAMERA_FAULTS = frozenset({"no_spot", "saturate", "second_reflection", "freeze"})


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

    def move_to(self, target: FlangePose, on_motion: MotionCallback | None = None
                ) -> FlangePose:
        """Check limits against the current pose, move (taking ``move_time_s``), report.

        With ``on_motion`` the flange passes through the straight-line poses of the move
        (every :data:`MOTION_REPORT_S`), each reported to the callback.
        """
        self._check_open()
        current = self.world.true_pose
        self.limits.check(target, current)
        self._stop.clear()
        a, b = current.as_array(), target.as_array()

        def between(f: float) -> FlangePose:
            x, y, z, th = a + f * (b - a)
            return FlangePose(x, y, z, th, target.quaternion if f >= 0.5 else current.quaternion)
        if self.move_time_s > 0:
            start = time.monotonic()
            step = MOTION_REPORT_S if on_motion is not None else self.move_time_s
            while (left := start + self.move_time_s - time.monotonic()) > 0:
                if self._stop.wait(min(step, left)):
                    self.world.move(between(min(1.0, (time.monotonic() - start)
                                                / self.move_time_s)))
                    raise DriverError("motion stopped before reaching the target")
                if on_motion is not None and time.monotonic() - start < self.move_time_s:
                    self.world.move(between((time.monotonic() - start) / self.move_time_s))
                    on_motion(self.world.reported_pose())
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


class SimCamera:
    """The simulated bottom camera: renders frames and measures them with the OpenCV detector.

    Each frame shows the spot where the world's camera measurement puts it (true spot plus the
    ``[noise] camera`` error, projected through the lens model), with speckle and read noise;
    :func:`drivers.camera_cv.detect_spot` finds it against a laser-off background frame and
    ``mapping`` turns pixels into plate mm. ``mapping`` starts as the exact inverse of the
    camera model; :meth:`calibrate` replaces it by a chessboard fit, as on the hardware.
    ``faults`` (a subset of :data:`CAMERA_FAULTS`) injects an empty frame, a saturated spot,
    a second reflection, or a frozen stream (``freeze``: the previous frame again).
    """

    def __init__(self, world: SimWorld, seed: int | None = 0,
                 config: DetectorConfig | None = None, average: int = 1,
                 faults: Iterable[str] = ()) -> None:
        self.world = world
        self.spec = world.workcell.camera
        self.renderer = FrameRenderer(self.spec, seed)
        self.config = config or DetectorConfig(max_aspect=max(1.3, 1.25 * self.spec.spot_aspect))
        self.average = max(1, int(average))
        self.faults: set[str] = set()
        self.set_faults(faults)
        self.background = self.renderer.render()
        self.mapping = PixelToPlate(self.spec.camera_matrix(), self.spec.dist_coeffs(),
                                    np.linalg.inv(self.spec.homography()))
        self.last_truth_px: np.ndarray | None = None
        self._last_frame: np.ndarray | None = None
        self._frozen = FrozenFrameCheck()
        self._closed = False

    def set_faults(self, faults: Iterable[str]) -> None:
        faults = set(faults)
        unknown = faults - CAMERA_FAULTS
        if unknown:
            raise ValueError(f"unknown camera fault(s) {sorted(unknown)}; "
                             f"expected {sorted(CAMERA_FAULTS)}")
        self.faults = faults

    def default_board(self) -> Chessboard:
        """A 16 x 12 (inner corners) chessboard of 1 mm squares centred on the field of view."""
        pattern, square = (16, 12), 1.0
        c = np.asarray(self.spec.fov_centre)
        origin = c - square * np.array([(pattern[0] - 1) / 2, (pattern[1] - 1) / 2])
        return Chessboard(pattern, square, (float(origin[0]), float(origin[1])))

    def calibrate(self, board: Chessboard | None = None) -> PixelToPlate:
        """Chessboard step: render the board on the plate, fit ``mapping`` (lens intrinsics
        known from the camera model, homography from the board's corners)."""
        board = board or self.default_board()
        image = self.renderer.render_chessboard(board)
        self.mapping = calibrate_chessboard(image, board.pattern, board.corners_mm(),
                                            self.spec.camera_matrix(), self.spec.dist_coeffs())
        return self.mapping

    def _spot_angle(self) -> float:
        """Image angle of the spot's major axis: the beam's tilt direction on the plate."""
        wc = self.world.workcell
        direction = pose_rotation(self.world.true_pose) @ wc.beam.u_prime
        return math.degrees(math.atan2(direction[1], direction[0])) + self.spec.rotation_deg

    def grab(self) -> np.ndarray:
        if self._closed:
            raise DriverError("simulated camera is closed")
        if "freeze" in self.faults and self._last_frame is not None:
            return self._last_frame.copy()
        self._last_frame = self._render()
        return self._last_frame

    def _render(self) -> np.ndarray:
        xy = self.world.camera_spot()
        self.last_truth_px = None
        if xy is None or "no_spot" in self.faults:
            return self.renderer.render()
        uv = self.spec.project(xy)[0]
        self.last_truth_px = uv
        peak = self.spec.spot_peak * (4.0 if "saturate" in self.faults else 1.0)
        spots = [self.renderer.spot_for(float(uv[0]), float(uv[1]), peak, self._spot_angle())]
        if "second_reflection" in self.faults:
            spots.append(Spot(float(uv[0]) + 40.0, float(uv[1]) + 25.0, 0.6 * peak,
                              self.spec.spot_sigma_px * 1.3))
        return self.renderer.render(spots)

    def detect(self) -> SpotDetection:
        """Grab and detect; a frame identical to the previous one is refused (frozen)."""
        return self._frozen.detect(self.grab(), self.background, self.config)

    def measure_spot(self) -> SpotMeasurement:
        return measure_average(self.detect, self.mapping, self.average)

    def close(self) -> None:
        self._closed = True
