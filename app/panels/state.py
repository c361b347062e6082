"""Shared state of the dashboard: devices, session, grid, calibration, live view.

The devices are only touched on the worker thread (:class:`app.worker.Worker`); GUI callbacks
read the plain attributes here and enqueue commands. Listeners (``on_change``) let the panels
refresh their handles when the state changes (any thread; viser handles are thread-safe).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from app.worker import Worker
from calib_core.errors import InputError
from calib_core.grid import PoseGrid, paper_grid
from drivers.base import DriverError, FlangePose, MotionRefused, SensorReading

#: Simulated move duration when the workcell TOML says 0 (makes the motion visible).
SIM_MOVE_TIME_S = 0.05
#: Live view: at most this many scene updates per second.
LIVE_MAX_HZ = 30.0
#: Live view on hardware: the robot's pose is polled at most this often (status queries).
HARDWARE_POSE_POLL_S = 0.2
_LEVEL_COLOR = {"info": "blue", "warning": "yellow", "error": "red", "success": "green"}


def pose_rotation(pose: FlangePose) -> np.ndarray:
    """Flange rotation matrix: from the quaternion when set, else ``Rz(theta)``."""
    from calib_core.model import rotation_about_z, rotation_from_quaternion

    if pose.quaternion is not None:
        return rotation_from_quaternion(np.asarray([pose.quaternion]))[0]
    return rotation_about_z(np.array([pose.theta_deg]))[0]


@dataclass(frozen=True)
class LiveSample:
    """Latest pose and reading seen (from the live view or the acquisition)."""

    pose: FlangePose
    reading: SensorReading | None
    t: float


class TapRobot:
    """A robot wrapper that reports every pose to the live view (same interface)."""

    def __init__(self, robot: Any, app: AppState) -> None:
        self._robot, self._app = robot, app
        self.limits = robot.limits

    def move_to(self, target: FlangePose, on_motion: Any = None) -> FlangePose:
        pose = self._robot.move_to(target, on_motion=self._app.motion_update)
        self._app.publish(pose, None)
        return pose

    def read_pose(self) -> FlangePose:
        return self._robot.read_pose()

    def stop(self) -> None:
        self._robot.stop()

    def close(self) -> None:
        self._robot.close()


class TapSensor:
    """A sensor wrapper that reports every reading to the live view."""

    def __init__(self, sensor: Any, app: AppState) -> None:
        self._sensor, self._app = sensor, app

    def read(self) -> SensorReading:
        reading = self._sensor.read()
        self._app.publish(None, reading)
        return reading

    def zero(self) -> None:
        self._sensor.zero()

    def close(self) -> None:
        self._sensor.close()


class AppState:
    """Everything the panels share. ``server`` is a :class:`viser.ViserServer`."""

    def __init__(self, server: Any, workcell: Any, *, sim: bool = True,
                 session_path: Path | None = None, seed: int | None = 0,
                 sim_move_time_s: float | None = None) -> None:
        from app.scene import WorkcellScene

        self.server = server
        self.workcell = workcell
        self.sim = sim
        self.seed = seed
        self.sim_move_time_s = sim_move_time_s
        self.sim_camera = "direct"
        self.controller: int | None = None
        self.session_path = session_path
        self.session: Any = None
        self.grid: PoseGrid = paper_grid()
        self.runner: Any = None
        self.progress: Any = None
        self.armed = False
        self.live = True
        self.robot: Any = None
        self.sensor: Any = None
        self.camera: Any = None
        self.world: Any = None
        self.calibration: Any = None
        self.solve_view: Any = None
        self.data_frame: Any = None          # an uploaded calibration data CSV (Solve tab)
        self.data_source: str | None = None
        self.measure_calibration: Any = None  # an uploaded calibration JSON (Measure tab)
        self.measurements: dict[str, dict[str, Any]] = {}   # latest result per Measure kind
        self.camera_mapping: Any = None      # pixel -> plate of the hardware camera
        self.excluded: set[int] = set()
        self.flagged: set[int] = set()
        self.messages: deque[tuple[float, str, str, str]] = deque(maxlen=200)
        self.latest: LiveSample | None = None
        self.last_solve_s: float | None = None
        self.solve_count = 0
        self._listeners: dict[str, list[Callable[[], None]]] = {}
        self._last_push = 0.0
        self._flush_pending = False
        self._last_pose_poll = 0.0
        self._publish_lock = threading.Lock()
        self.scene = WorkcellScene(server, workcell) if server is not None else None
        self.worker = Worker(self.notify, idle=self._idle, idle_period_s=1.0 / LIVE_MAX_HZ)

    # ---- events ------------------------------------------------------------------------------
    def on_change(self, topic: str, fn: Callable[[], None]) -> None:
        """Call ``fn()`` whenever ``topic`` changes ('devices', 'progress', 'solve', 'grid',
        'session', 'arm')."""
        self._listeners.setdefault(topic, []).append(fn)

    def changed(self, topic: str) -> None:
        for fn in self._listeners.get(topic, []):
            try:
                fn()
            except Exception as exc:  # a display refresh must not break a command
                self.notify("display", f"refresh of {topic} failed: {exc}", "warning")

    def notify(self, title: str, body: str, level: str = "info") -> None:
        """Show a notification in every connected browser tab (and keep it in ``messages``)."""
        self.messages.append((time.time(), level, title, body))
        if self.server is None:
            return
        for client in list(self.server.get_clients().values()):
            with contextlib.suppress(Exception):
                client.add_notification(title, body, color=_LEVEL_COLOR.get(level),
                                        auto_close_seconds=None if level == "error" else 6.0)

    # ---- devices (worker thread) -------------------------------------------------------------
    @property
    def connected(self) -> bool:
        return self.robot is not None and self.sensor is not None and self.camera is not None

    def connect_sim(self) -> None:
        """Connect the simulated robot, sensor and camera (worker thread)."""
        from drivers.sim.devices import SimCamera, SimCameraDirect, SimRobot, SimSensor
        from drivers.sim.world import SimWorld

        self.disconnect()
        world = SimWorld(self.workcell, seed=self.seed)
        move = self.sim_move_time_s
        if move is None:
            move = self.workcell.timing.move_time_s or SIM_MOVE_TIME_S
        self.world, self.robot = world, SimRobot(world, move_time_s=move)
        self.sensor = SimSensor(world)
        self.camera = SimCamera(world, seed=self.seed) if self.sim_camera == "rendered" \
            else SimCameraDirect(world)
        self.sim = True
        self.publish(self.robot.read_pose(), self.sensor.read())
        self.changed("devices")

    def connect_hardware(self, robot_port: str, sensor_port: str, camera: str,
                         camera_calib: str = "") -> None:
        """Connect the GRBL robot, Keyence sensor and OpenCV camera (worker thread).

        ``camera`` is a device index ("0" -> 0) or a URL; ``camera_calib`` a camera calibration
        JSON (``PixelToPlate``); empty: the last chessboard result, else uncalibrated.
        """
        from app.panels.upload import read_json_file

        try:
            from drivers.camera_cv import OpenCVCamera, PixelToPlate
            from drivers.grbl import GrblRobot
            from drivers.keyence_il import KeyenceIL
        except ImportError as exc:
            raise DriverError(f"hardware driver not available in this installation ({exc})"
                              ) from None
        mapping = self.camera_mapping
        if camera_calib.strip():
            mapping = PixelToPlate.from_json_dict(read_json_file(camera_calib.strip()))
        source = camera.strip()
        if not source:
            raise InputError("give the camera index (e.g. 0) or URL")
        self.disconnect()
        opened: list[Any] = []
        try:
            opened.append(GrblRobot(robot_port.strip(), self.workcell.limits))
            opened.append(KeyenceIL(sensor_port.strip()))
            opened.append(OpenCVCamera(int(source) if source.isdigit() else source,
                                       mapping=mapping))
        except BaseException:
            for dev in opened:
                with contextlib.suppress(Exception):
                    dev.close()
            raise
        self.camera_mapping = mapping
        self.attach(*opened)
        if mapping is None:
            self.notify("camera", "camera not calibrated: run the chessboard calibration or "
                        "give a camera calibration JSON", "warning")

    def attach(self, robot: Any, sensor: Any, camera: Any, world: Any = None) -> None:
        """Use already opened devices (worker thread); ``world`` set for a simulated cell."""
        self.disconnect()
        self.robot, self.sensor, self.camera, self.world = robot, sensor, camera, world
        self.sim = world is not None
        self.publish(robot.read_pose(), sensor.read())
        self.changed("devices")

    def disconnect(self) -> None:
        for dev in (self.robot, self.sensor, self.camera):
            if dev is not None:
                with contextlib.suppress(Exception):
                    dev.close()
        self.robot = self.sensor = self.camera = self.world = None
        self.changed("devices")

    def require_devices(self) -> None:
        if not self.connected:
            raise DriverError("no devices connected: use Setup > Connect first")

    def check_control(self, client_id: int | None) -> None:
        """Only the tab holding control may command devices; the first to ask gets it.

        ``client_id`` None is a local caller (tests, the CLI). STOP needs no control.
        """
        if client_id is None:
            return
        if self.controller is None:
            self.controller = client_id
            self.changed("control")
        elif self.controller != client_id:
            raise MotionRefused(f"tab #{self.controller} holds control of the cell; use "
                                "'Take control' to hand it over")

    def has_control(self, client_id: int | None, title: str) -> bool:
        """:meth:`check_control` for a GUI callback: a refusal becomes a warning notification."""
        try:
            self.check_control(client_id)
        except MotionRefused as exc:
            self.notify(title, str(exc), "warning")
            return False
        return True

    def take_control(self, client_id: int) -> None:
        """Explicit hand-over: ``client_id`` becomes the controlling tab."""
        previous, self.controller = self.controller, client_id
        self.changed("control")
        if previous is not None and previous != client_id:
            self.notify("control", f"control handed over from tab #{previous} to tab "
                        f"#{client_id}", "warning")

    def release_control(self, client_id: int) -> None:
        """A closed tab gives control back."""
        if self.controller == client_id:
            self.controller = None
            self.changed("control")

    def require_motion(self, client_id: int | None = None) -> None:
        """Refuse motion unless armed, connected, in control and no acquisition is running."""
        self.check_control(client_id)
        if not self.armed:
            raise MotionRefused("motion is disarmed: switch on 'Arm motion' first")
        self.require_devices()
        if self.runner is not None and self.runner.state == "running":
            raise MotionRefused("an acquisition is running: pause or abort it first")

    def move_to(self, target: FlangePose) -> FlangePose:
        """Checked move (worker thread): armed, soft limits, max step; publishes the pose."""
        self.require_motion()
        current = self.robot.read_pose()
        self.robot.limits.check(target, current)
        pose = self.robot.move_to(target, on_motion=self.motion_update)
        self.publish(pose, self.sensor.read())
        return pose

    def stop_motion(self) -> None:
        """STOP (any thread): feed hold now, pause a running acquisition, disarm motion."""
        self.armed = False
        if self.runner is not None and self.runner.state == "running":
            self.runner.pause("STOP pressed by the operator")
        robot = self.robot
        if robot is not None:
            robot.stop()
        self.changed("arm")

    # ---- live view -----------------------------------------------------------------------------
    def _idle(self) -> None:
        """Worker idle hook: one live reading while the live view is on."""
        if not (self.live and self.connected):
            return
        if self.runner is not None and self.runner.state == "running":
            return
        now = time.monotonic()
        pose = None
        if self.sim or now - self._last_pose_poll >= HARDWARE_POSE_POLL_S or self.latest is None:
            pose, self._last_pose_poll = self.robot.read_pose(), now
        self.publish(pose, self.sensor.read())

    def motion_update(self, pose: FlangePose) -> None:
        """A pose the robot passes through while it moves (worker thread, inside ``move_to``).

        On the simulated cell the sensor is read there too, so the live spot follows the
        motion; a hardware sensor is left to the acquisition (no extra traffic on its line).
        """
        reading = None
        if self.sim and self.sensor is not None:
            with contextlib.suppress(DriverError):
                reading = self.sensor.read()
        self.publish(pose, reading)

    def publish(self, pose: FlangePose | None, reading: SensorReading | None) -> None:
        """Record the latest pose/reading and redraw flange, beam and live spot.

        At most :data:`LIVE_MAX_HZ` redraws per second; a sample that arrives sooner is drawn
        by a deferred flush, so the newest pose and reading always reach the clients (no
        reading is silently dropped during a burst, e.g. the samples after each move of an
        acquisition).
        """
        with self._publish_lock:
            prev = self.latest
            if pose is None:
                if prev is None:
                    return
                pose = prev.pose
            now = time.monotonic()
            self.latest = LiveSample(pose, reading, now)
            if self.scene is None:
                return
            wait = self._last_push + 1.0 / LIVE_MAX_HZ - now
            if wait > 0:
                if not self._flush_pending:
                    self._flush_pending = True
                    timer = threading.Timer(wait, self._flush)
                    timer.daemon = True
                    timer.start()
                return
            self._last_push = now
            sample = self.latest
        self._draw(sample)

    def _flush(self) -> None:
        with self._publish_lock:
            self._flush_pending = False
            self._last_push = time.monotonic()
            sample = self.latest
        if sample is not None:
            self._draw(sample)

    def _draw(self, sample: LiveSample) -> None:
        reading = sample.reading
        d = reading.value if reading is not None and reading.ok else None
        pose = sample.pose
        self.scene.set_pose(np.array([pose.x, pose.y, pose.z]), pose_rotation(pose), d,
                            reading_known=reading is not None)
        self.changed("live")

    # ---- session ------------------------------------------------------------------------------
    def open_session(self, path: Path) -> None:
        """Open an existing session file for review or to continue it."""
        from app.session import Session

        self.close_session()
        try:
            session = Session.open(path)
        except InputError:
            raise
        self.session, self.session_path = session, Path(path)
        self.data_frame = self.data_source = None
        self.grid = session.grid
        self.changed("grid")
        self.changed("session")

    def new_session_path(self) -> Path:
        stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
        base = Path.cwd() / f"lasercal-session-{stamp}.db"
        k = 2
        while base.exists():
            base = Path.cwd() / f"lasercal-session-{stamp}-{k}.db"
            k += 1
        return base

    def ensure_session(self) -> Any:
        """The session to acquire into: the open one while poses are pending, else a new file."""
        from app.session import Session

        if self.session is not None and self.session.pending_indices():
            return self.session
        if self.session is None and self.session_path is not None and self.session_path.exists():
            self.open_session(self.session_path)
            if self.session.pending_indices():
                return self.session
        path = self.session_path
        if path is None or path.exists():
            path = self.new_session_path()
            if self.session_path is not None:
                self.notify("session", f"{self.session_path.name} is complete; new samples go "
                            f"to {path}", "info")
        self.close_session()
        toml = ""
        with contextlib.suppress(Exception):
            toml = Path(self.workcell.source).read_text() if Path(
                self.workcell.source).is_file() else ""
        self.session = Session.create(path, self.grid, workcell_toml=toml,
                                      drivers={"robot": type(self.robot).__name__,
                                               "sensor": type(self.sensor).__name__,
                                               "camera": type(self.camera).__name__})
        self.session_path = path
        self.data_frame = self.data_source = None
        self.excluded, self.flagged = set(), set()
        self.calibration = self.solve_view = None
        self.changed("session")
        return self.session

    def close_session(self) -> None:
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        self.session = None
