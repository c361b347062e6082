"""Setup tab: simulated or hardware cell, connect, sensor zero, camera chessboard calibration."""

from __future__ import annotations

from typing import Any

from app.panels.state import AppState
from drivers.base import DriverError


def zero_sensor(app: AppState) -> float | None:
    """Zero the sensor at the current reading (worker thread); returns the reading after."""
    app.require_devices()
    app.sensor.zero()
    reading = app.sensor.read()
    app.publish(app.robot.read_pose(), reading)
    return reading.value if reading.ok else None


def calibrate_camera(app: AppState, pattern: tuple[int, int] | None = None,
                     square_mm: float = 1.0, origin: tuple[float, float] | None = None) -> str:
    """Chessboard calibration of the pixel -> plate mapping (worker thread).

    The board lies on the plate with inner corners ``pattern`` (columns, rows), squares of
    ``square_mm``, corner (0, 0) at ``origin`` (fixed frame mm; default: centred on the field of
    view) and its edges along x and y.
    """
    from drivers.sim.render import Chessboard

    app.require_devices()
    cam = app.camera
    if not hasattr(cam, "calibrate"):
        if app.sim:
            return "the direct simulated camera needs no calibration (choose 'rendered')"
        raise DriverError("this camera driver has no chessboard calibration")
    if pattern is None or origin is None:
        if not hasattr(cam, "default_board"):
            raise DriverError("give the chessboard pattern, square size and origin")
        board = cam.default_board()
    else:
        board = Chessboard((int(pattern[0]), int(pattern[1])), float(square_mm),
                           (float(origin[0]), float(origin[1])))
    if hasattr(cam, "default_board"):       # simulated: renders the board itself
        mapping = cam.calibrate(board)
    else:
        mapping = cam.calibrate(board.pattern, board.corners_mm())
        app.camera_mapping = mapping        # kept for the next hardware connect
    return (f"camera calibrated from {mapping.n_corners or board.pattern[0] * board.pattern[1]} "
            f"corners: reprojection rms {mapping.rms_px:.3g} px ({mapping.rms_mm * 1000:.3g} µm)")


def build(gui: Any, app: AppState) -> None:
    mode = gui.add_dropdown("Cell", ("simulated", "hardware"),
                            initial_value="simulated" if app.sim else "hardware")
    sim_cam = gui.add_dropdown("Simulated camera", ("direct", "rendered"),
                               initial_value=app.sim_camera,
                               hint="direct: fast; rendered: images through the OpenCV detector")
    robot_port = gui.add_text("Robot port (GRBL)", "/dev/ttyUSB0")
    sensor_port = gui.add_text("Sensor port (Keyence)", "/dev/ttyUSB1")
    camera = gui.add_text("Camera (index or URL)", "0")
    camera_calib = gui.add_text("Camera calibration JSON", "",
                                hint="pixel -> plate mapping (camera_matrix, dist_coeffs, "
                                     "homography); empty: the last chessboard calibration")
    connect = gui.add_button("Connect", icon="plug-connected")
    status = gui.add_markdown("")
    zero = gui.add_button("Sensor zero")
    with gui.add_folder("Camera chessboard", expand_by_default=False):
        pattern = gui.add_vector2("Inner corners (cols, rows)", (16, 12), step=1)
        square = gui.add_number("Square (mm)", 1.0, min=0.01, step=0.01)
        origin = gui.add_vector2("Corner (0,0) at x y (mm)", (-13.5, 64.5), step=0.01)
        use_default = gui.add_checkbox("Simulated default board", initial_value=True)
        chess = gui.add_button("Camera chessboard calibration")

    def refresh() -> None:
        if app.connected:
            kind = "simulated cell" if app.sim else "hardware"
            status.content = f"**Connected** ({kind}): {type(app.robot).__name__}, " \
                             f"{type(app.sensor).__name__}, {type(app.camera).__name__}"
        else:
            status.content = "**Not connected**"
    refresh()
    app.on_change("devices", refresh)

    @connect.on_click
    def _(event: Any) -> None:
        if not app.has_control(event.client_id, "connect"):
            return
        if mode.value == "simulated":
            app.sim_camera = sim_cam.value
            app.worker.submit("connect", app.connect_sim)
        else:
            app.worker.submit("connect", lambda: app.connect_hardware(
                robot_port.value, sensor_port.value, camera.value, camera_calib.value))

    @zero.on_click
    def _(_: Any) -> None:
        def cmd() -> None:
            value = zero_sensor(app)
            app.notify("sensor zero", f"sensor zeroed; reading now {value}", "success")
        app.worker.submit("sensor zero", cmd)

    @chess.on_click
    def _(_: Any) -> None:
        args = {} if use_default.value else {"pattern": tuple(pattern.value),
                                              "square_mm": float(square.value),
                                              "origin": tuple(origin.value)}
        app.worker.submit("camera calibration",
                          lambda: app.notify("camera", calibrate_camera(app, **args), "success"))
